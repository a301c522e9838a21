"""The one clock shared by all simulated instruments of a rig (ophyd-async style injectable clock).

``WallClock`` runs in real time (hardware-in-the-loop); ``VirtualClock`` only moves when told to, so a
protocol engine can run the simulated rig as fast as the machine allows with the same bytes on the wire.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
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
    """Time that advances only through :meth:`advance` / :meth:`advance_to` (thread-safe, monotonic).

    A simulated device that acts on its own clock (a DAQ filling stream packets) can :meth:`subscribe` to be told
    the new time after each advance, in the advancing thread: it then acts when its time comes instead of
    finding out at its next poll of the wall clock."""

    virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()
        self._listeners: tuple[Callable[[float], None], ...] = ()

    def subscribe(self, listener: Callable[[float], None]) -> None:
        """Call ``listener(t)`` after every advance (keep it short: it runs in the thread that advanced)."""
        with self._lock:
            self._listeners = (*self._listeners, listener)

    def unsubscribe(self, listener: Callable[[float], None]) -> None:
        """Stop calling ``listener`` (no-op if it is not subscribed)."""
        with self._lock:
            self._listeners = tuple(f for f in self._listeners if f != listener)

    def _told(self, t: float) -> float:
        for listener in self._listeners:
            listener(t)
        return t

    def now(self) -> float:
        """Current virtual time [s]. Read without the lock (the hosts' most frequent call: every wait, poll and driver
        deadline): a float attribute is read whole, so a reader gets the time before or after a concurrent advance,
        as with the lock; only the advances, which read and write it, take the lock."""
        return self._t

    def advance(self, dt: float) -> float:
        """Move time forward by dt ≥ 0 [s]; returns the new time."""
        if dt < 0:
            raise ValueError(f"virtual time cannot go back (dt = {dt})")
        with self._lock:
            self._t += dt
            t = self._t
        return self._told(t)

    def sleep(self, dt: float) -> None:
        """A wait in virtual time: advances the clock instead of blocking."""
        self.advance(max(dt, 0.0))

    def wait_until(self, t: float) -> None:
        """Jump to t."""
        self.advance_to(t)

    def advance_to(self, t: float) -> float:
        """Move time forward to t (no-op if t is in the past); returns the new time."""
        with self._lock:
            self._t = now = max(self._t, float(t))
        return self._told(now)
