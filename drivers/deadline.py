"""How long a link waits for a reply: a :class:`ReplyTimer` hands out one :class:`Deadline` per wait.

On hardware (and on twins served in real time) a wait ends after its timeout on the wall clock: :data:`WALL`.
In a virtual-time simulation the wall clock says nothing about the instrument — a host or a twin thread starved
of CPU is late, not silent — so the simulated rig gives each link a timer that asks the twin instead (see
``sim_devices.transport.TwinTimer``): a reply the twin deliberately withheld ends the wait at once (its timeout
passes on the rig clock), and only a twin that does nothing at all is given up on, after a long wall-clock guard.

A link calls :meth:`ReplyTimer.sending` just before each request goes out, then :meth:`ReplyTimer.start` for each
wait on its reply, and blocks at most :meth:`Deadline.left` at a time before asking :meth:`Deadline.expired` again.
"""

from __future__ import annotations

import time
from typing import Protocol


class Deadline(Protocol):
    """The end of one wait for a reply."""

    @property
    def detail(self) -> str:
        """Why it expired, for the timeout's message ("" when simply its timeout passed)."""

    def expired(self) -> bool:
        """Whether to give up on the reply now."""

    def left(self) -> float:
        """Wall seconds a blocking read may last before :meth:`expired` is asked again (≥ 0)."""


class ReplyTimer(Protocol):
    """Source of a link's deadlines."""

    def sending(self) -> None:
        """A request is about to go out: the waits that follow are for its reply."""

    def start(self, timeout: float) -> Deadline:
        """A wait of ``timeout`` [s] for the reply to the request last sent (0: a look, not a wait)."""

    def bound(self, timeout: float) -> float:
        """Wall-clock limit [s] for a blocking call the link cannot cut into slices (a port write, a socket
        connect, a client library's own receive loop) whose nominal timeout is ``timeout``."""


class WallDeadline:
    """Expires ``timeout`` s of wall time after it was made."""

    detail = ""

    def __init__(self, timeout: float) -> None:
        self.end = time.monotonic() + timeout

    def expired(self) -> bool:
        """Whether the wall clock has passed the end."""
        return time.monotonic() >= self.end

    def left(self) -> float:
        """Wall seconds until the end."""
        return max(self.end - time.monotonic(), 0.0)


class WallTimer:
    """Timeouts on the wall clock: the right thing for a real instrument."""

    def sending(self) -> None:
        """Nothing to note."""

    def start(self, timeout: float) -> WallDeadline:
        """``timeout`` s from now."""
        return WallDeadline(timeout)

    def bound(self, timeout: float) -> float:
        """The timeout itself."""
        return timeout


WALL = WallTimer()
