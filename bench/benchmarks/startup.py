"""Start-up of the command line: ``bench --help``, a command's ``--help`` and a TAB completion, each against
``python -c "import typer, rich"`` (the floor of any typer + rich program) measured in the same run.

Each is a fresh interpreter (``sys.executable -m bench``), best of the repeats after one untimed call that lets
Python cache the bytecode (as an installed package has it), so the ratio compares start-up work, not compilation.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Mapping

from bench.benchmarks.acquisition import Figure

STARTUP_TARGET = 2.0  # issue 24: `bench --help` within 2× `python -c "import typer, rich"`


def _best(argv: list[str], repeats: int, env: Mapping[str, str]) -> float:
    """Best wall time of ``repeats`` runs of ``argv`` [s], after one untimed run; stdout and stderr discarded."""
    subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        best = min(best, time.perf_counter() - t0)
    return best


def run_all(quick: bool = False) -> list[Figure]:
    """``bench --help``, ``bench fit --help`` and a completion against ``import typer, rich`` (quick: 5 repeats)."""
    repeats = 5 if quick else 15
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    python = sys.executable
    floor = _best([python, "-c", "import typer, rich"], repeats, env)
    cases = [("bench --help", [python, "-m", "bench", "--help"], {}),
             ("bench fit --help", [python, "-m", "bench", "fit", "--help"], {}),
             ("TAB: bench protocols show thesis-", [python, "-m", "bench"],
              {"_BENCH_COMPLETE": "complete_bash", "COMP_WORDS": "bench protocols show thesis-", "COMP_CWORD": "3"})]
    out = [Figure('python -c "import typer, rich" (the floor)', floor * 1e3, "ms", f"best of {repeats}")]
    for k, (label, argv, extra) in enumerate(cases):
        wall = _best(argv, repeats, {**env, **extra})
        ratio = wall / floor
        verdict = f"target ≤ {STARTUP_TARGET:g}×: {'ok' if ratio <= STARTUP_TARGET else 'ABOVE TARGET'}" if k == 0 \
            else "no target (typer itself loads pydantic to parse a command's options)" if k == 1 else ""
        out += [Figure(label, wall * 1e3, "ms", f"best of {repeats}"),
                Figure("  over the floor, same run", ratio, "×", verdict)]
    return out
