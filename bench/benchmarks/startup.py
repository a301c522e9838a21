"""Start-up of the command line: ``bench --help``, a command's ``--help`` and a TAB completion, each against
``python -c "import typer, rich"`` (the floor of any typer + rich program) measured in the same run.

Each is a fresh interpreter (``sys.executable -m bench``), best of the repeats after one untimed round that lets
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


def _once(argv: list[str], env: Mapping[str, str]) -> float:
    """Wall time of one run of ``argv`` [s]; stdout and stderr discarded."""
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def run_all(quick: bool = False) -> list[Figure]:
    """``bench --help``, ``bench fit --help`` and a completion against ``import typer, rich`` (quick: 3 repeats,
    no ``fit --help``). The commands take turns within each repeat, so a change of load touches all alike."""
    repeats = 3 if quick else 15
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    python = sys.executable
    floor = 'python -c "import typer, rich" (the floor)'
    cases = [(floor, [python, "-c", "import typer, rich"], {}),
             ("bench --help", [python, "-m", "bench", "--help"], {}),
             *([] if quick else [("bench fit --help", [python, "-m", "bench", "fit", "--help"], {})]),
             ("TAB: bench protocols show thesis-", [python, "-m", "bench"],
              {"_BENCH_COMPLETE": "complete_bash", "COMP_WORDS": "bench protocols show thesis-", "COMP_CWORD": "3"})]
    best = dict.fromkeys((label for label, _, _ in cases), float("inf"))
    for k in range(repeats + 1):  # the first round is not timed: Python writes the bytecode cache
        for label, argv, extra in cases:
            wall = _once(argv, {**env, **extra})
            if k:
                best[label] = min(best[label], wall)
    out = [Figure(floor, best[floor] * 1e3, "ms", f"best of {repeats}")]
    for label, _, _ in cases[1:]:
        ratio = best[label] / best[floor]
        verdict = f"target ≤ {STARTUP_TARGET:g}×: {'ok' if ratio <= STARTUP_TARGET else 'ABOVE TARGET'}" \
            if label == "bench --help" else "no target (typer itself loads pydantic to parse a command's arguments)"
        out += [Figure(label, best[label] * 1e3, "ms", f"best of {repeats}"),
                Figure("  over the floor, same run", ratio, "×", verdict)]
    return out
