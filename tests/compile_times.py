"""pytest plugin: how long each test process spends compiling numba kernels, and in which tests.

``pytest -p tests.compile_times`` with ``BENCH_COMPILE_TIMES=FILE``: each process (each pytest-xdist worker) appends
to FILE its total wall time inside numba's outermost compilations (nested ones, a kernel compiling the kernels it
calls, are counted once; a kernel loaded from the cache is no compilation) and the tests (with their fixtures'
set-up) that spent the most. A measurement of the suite (issue 24: what compilation costs it), not a test.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from numba.core import event


class _Compiles(event.Listener):
    """Wall time inside outermost ``numba:compile`` events, per thread nesting."""

    def __init__(self) -> None:
        self.local = threading.local()
        self.lock = threading.Lock()
        self.total = 0.0
        self.count = 0

    def on_start(self, ev: Any) -> None:
        depth = getattr(self.local, "depth", 0)
        if depth == 0:
            self.local.t0 = time.perf_counter()
        self.local.depth = depth + 1

    def on_end(self, ev: Any) -> None:
        self.local.depth -= 1
        if self.local.depth == 0:
            with self.lock:
                self.total += time.perf_counter() - self.local.t0
                self.count += 1


_LISTENER = _Compiles()
_PER_TEST: dict[str, float] = {}


def pytest_configure(config: pytest.Config) -> None:
    event.register("numba:compile", _LISTENER)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    before = _LISTENER.total
    yield
    spent = _LISTENER.total - before
    if spent > 0:
        _PER_TEST[item.nodeid] = spent


def pytest_sessionfinish(session: pytest.Session) -> None:
    target = os.environ.get("BENCH_COMPILE_TIMES")
    if not target:
        return
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    top = sorted(_PER_TEST.items(), key=lambda kv: -kv[1])[:15]
    lines = [f"{worker}: {_LISTENER.total:.1f} s compiling in {_LISTENER.count} compilations, "
             f"{len(_PER_TEST)} tests"] + [f"{worker}   {s:6.1f} s  {name}" for name, s in top]
    with Path(target).open("a", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
