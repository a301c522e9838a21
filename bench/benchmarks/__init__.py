"""`bench benchmark`: the integrators (main), acquisition through the drivers, hardware-timed rigs (daq), whole runs
(run), the fitter (fit) and the fault matrix (faults: is the output at 0 V when a run returns, whatever failed)."""

from __future__ import annotations

import time
from collections.abc import Callable


def best_of(fn: Callable[[], object], repeats: int = 3) -> float:
    """Best wall time of ``repeats`` calls [s], after one call that is not timed (JIT compilation / cache load)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
