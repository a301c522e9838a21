"""`bench benchmark`: the integrators (main), acquisition through the drivers, hardware-timed rigs (daq), whole runs
(run), the fitter (fit) and the fault matrix (faults: is the output at 0 V when a run returns, whatever failed)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def best_of(fn: Callable[[], object], repeats: int = 3, warm: Callable[[], object] | None = None) -> float:
    """Best wall time of ``repeats`` calls [s], after one call that is not timed (JIT compilation / cache load):
    ``warm`` if given — a small case of the same code (one step, one candidate), which loads it as well at a
    fraction of the cost: with one repeat (``--quick``) a whole untimed call doubled the set's time — else ``fn``."""
    (warm or fn)()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def copy_protocol(source: Path, copy: Path, edit: Callable[[Any], None]) -> Path:
    """A copy of the protocol file ``source`` at ``copy``, changed by ``edit`` (given the parsed TOML document, to
    change in place); its rig path made absolute, since the copy lives in another folder. Returns ``copy``."""
    import tomlkit

    doc = tomlkit.parse(source.read_text(encoding="utf-8"))
    head: Any = doc["protocol"]
    head["rig"] = (source.parent / str(head["rig"])).resolve().as_posix()
    edit(doc)
    copy.write_text(tomlkit.dumps(doc), encoding="utf-8")
    return copy


def noise_free_rig(rig: Path, folder: Path) -> Path:
    """A copy of the rig file ``rig`` in ``folder`` with the twins' datasheet noise and monitor errors off
    (``[simulation] noise = false``), for comparisons that must not read the noise. Returns the copy."""
    import tomlkit

    doc = tomlkit.parse(rig.read_text(encoding="utf-8"))
    sim: Any = doc.setdefault("simulation", tomlkit.table())
    sim["noise"] = False
    copy = folder / f"{rig.stem}-noise-free.toml"
    copy.write_text(tomlkit.dumps(doc), encoding="utf-8")
    return copy
