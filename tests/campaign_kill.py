"""Test helpers: wait for a condition, and kill a `bench run` process once its log shows a step has started."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path


def wait_for(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    """Poll ``predicate`` every 50 ms; AssertionError naming ``what`` after ``timeout`` s (a guard, not a claim)."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def kill_at_step(proc: subprocess.Popen, folder: Path, step: int, timeout: float) -> None:
    """kill -9 the run ``proc`` once its RUN.log in ``folder`` records step ``step`` starting (no end recorded)."""
    try:
        wait_for(lambda: any(folder.glob("*.log")) and f"step {step} start" in next(folder.glob("*.log")).read_text(),
                 timeout, f"step {step}")
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        proc.kill()
