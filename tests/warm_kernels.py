"""Compile the numba kernels the suite uses into the kernel cache once, before pytest-xdist's workers start.

With an empty cache (a clean clone, as CI has) each worker compiled the kernels it met on its own, the two often
the same kernels at the same time (tests/compile_times.py measures it). ``python -m tests.warm_kernels PART`` runs
small versions of the suite's workloads — short virtual-time runs on every rig kind, a small fit of each model —
so that their kernels are compiled into the cache (bench/models/jit.py: a cache keyed by the kernel sources, which
every process of the same sources loads); conftest.py runs the parts side by side, one process each, before the
workers start. What a part misses is compiled where it is used, as before: this changes how long, not what.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _run(tmp: Path, protocol: str, rig: str | None = None) -> Path:
    from bench.runtime.run import execute, plan_run

    plan = plan_run(ROOT / "protocols" / protocol, ROOT / "rigs" / rig if rig else None)
    result = execute(plan, tmp / f"{Path(protocol).stem}-{rig or 'own'}.h5", virtual=True, operator=lambda _m: True)
    return Path(result.path)


def membrane(tmp: Path) -> None:
    """The membrane's runs on both rig kinds (software- and hardware-timed) and a small fit with its polish."""
    from bench.identify.core import FitSettings, fit
    from bench.identify.problems import MembraneProblem

    daq = _run(tmp, "short/thesis-identification-short.toml")
    _run(tmp, "short/thesis-identification-short.toml", "thesis-sim.toml")
    small = FitSettings(population=5, generations=2, polish_iterations=1)
    fit(MembraneProblem([daq], h=5e-4), small, fine=MembraneProblem([daq], h=1e-4))


def lozenge(tmp: Path) -> None:
    """The LS-DEA's runs (motor and hung-mass rigs) and a small fit with its polish."""
    from bench.identify.core import FitSettings, fit
    from bench.identify.problems import LozengeProblem

    iso = _run(tmp, "short/lsdea-isopotential-short.toml")
    _run(tmp, "short/lsdea-isotonic-short.toml")
    _run(tmp, "short/lsdea-isometric-short.toml", "lsdea-motor-sim.toml")
    fit(LozengeProblem([iso]), FitSettings(population=5, generations=2, polish_iterations=1))


PARTS: dict[str, Callable[[Path], None]] = {"membrane": membrane, "lozenge": lozenge}


def main(part: str) -> int:
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="warm-kernels-") as tmp:
        os.environ["BENCH_STATE_DIR"] = str(Path(tmp) / "state")  # no latch or lock of the user's
        PARTS[part](Path(tmp))
    print(f"warm kernels {part}: {time.perf_counter() - started:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
