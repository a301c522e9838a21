"""The one clock shared by all simulated instruments of a rig (ophyd-async style injectable clock).

``WallClock`` runs in real time (hardware-in-the-loop); ``VirtualClock`` only moves when told to, so a
protocol engine can run the simulated rig as fast as the machine allows with the same bytes on the wire.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Source of simulated time [s] since the rig started."""

    virtual: bool

    def now(self) -> float:
        """Current time [s]."""

    def sleep(self, dt: float) -> None:
        """Wait dt [s] of this clock's time."""

    def wait_until(self, t: float) -> None:
        """Wait until this clock reads t (no-op if it is past)."""


class WallClock:
    """Monotonic wall-clock time since construction."""

    virtual = False

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        """Seconds since the rig started."""
        return time.monotonic() - self._t0

    def sleep(self, dt: float) -> None:
        """Real sleep."""
        time.sleep(max(dt, 0.0))

    def wait_until(self, t: float) -> None:
        """Sleep until the clock reads t."""
        dt = t - self.now()
        if dt > 0:
            time.sleep(dt)


class VirtualClock:
    """Time that advances only through :meth:`advance` / :meth:`advance_to` (thread-safe, monotonic)."""

    virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Current virtual time [s]."""
        with self._lock:
            return self._t

    def advance(self, dt: float) -> float:
        """Move time forward by dt ≥ 0 [s]; returns the new time."""
        if dt < 0:
            raise ValueError(f"virtual time cannot go back (dt = {dt})")
        with self._lock:
            self._t += dt
            return self._t

    def sleep(self, dt: float) -> None:
        """A wait in virtual time: advances the clock instead of blocking."""
        self.advance(max(dt, 0.0))

    def wait_until(self, t: float) -> None:
        """Jump to t."""
        self.advance_to(t)

    def advance_to(self, t: float) -> float:
        """Move time forward to t (no-op if t is in the past); returns the new time."""
        with self._lock:
            self._t = max(self._t, float(t))
            return self._t
