"""The shutdown ramp: the output from its set-point to 0 V in equal steps, the one ramp-down of every stop.

The engine's shutdown (:meth:`bench.runtime.engine.Engine._zero_voltage`) calls :func:`ramp_to_zero`, for a run
and for a manual session's end alike (manual control is a mode of the engine, bench/runtime/manual_mode.py); what
the ramp says (events), how it waits and what stops it early are the caller's.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.interfaces import Amplifier


def ramp_to_zero(amp: Amplifier, v0: float, ramp_s: float, pause: Callable[[float], bool],
                 record: Callable[[float], None], steps: int) -> bool:
    """Set-points v0 × (1 − k/steps), k = 1 … steps, the k-th ``ramp_s`` × k/steps after the ramp began.

    ``pause(offset)`` waits until ``offset`` seconds after the start on the caller's clock and returns False on an
    urgent stop (a second stop request, a latched fault), which ends the ramp before the next set-point;
    ``record(sent)`` follows every set-point with the value the amplifier really commanded. Returns whether the
    ramp reached its last set-point (False: cut short). Driver errors propagate; either way the caller then commands
    0 V at once."""
    for k in range(1, steps + 1):
        if not pause(ramp_s * k / steps):
            return False
        record(amp.set_voltage(v0 * (1 - k / steps)))
    return True
