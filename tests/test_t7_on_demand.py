"""The T7 twin pumping on demand in virtual time: packets leave when the host waits on the twin (or after a step of
rig time without a host), not at every move of the clock — the same packets, only fewer pumps.
"""

from __future__ import annotations

from bench.core.clock import VirtualClock
from sim_devices.transport import Faults, TwinTimer


def test_a_twin_timer_tells_the_twin_before_each_blocking_read_not_for_a_look_or_a_withheld_reply() -> None:
    """``waiting`` is called each time the driver is about to block (``left`` > 0), never for a look (timeout 0) or
    once the twin has withheld the reply (the wait ends at once)."""
    clock = VirtualClock()
    faults = Faults(clock=clock.now)
    calls: list[float] = []
    timer = TwinTimer(faults, clock, waiting=lambda: calls.append(clock.now()))
    timer.sending()
    wait = timer.start(1.0)
    assert wait.left() > 0 and wait.left() > 0 and len(calls) == 2
    assert timer.start(0.0).left() == 0.0 and len(calls) == 2
    faults.withheld += 1  # the twin swallowed the reply
    assert wait.left() == 0.0 and len(calls) == 2
