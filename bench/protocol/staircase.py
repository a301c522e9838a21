"""What a software-timed rig does to the drive: the set-point staircase against the protocol's waveform.

On a rig without a buffered output (ADAM-4024), the engine sends one set-point every 1/``setpoint_Hz``; between
two ticks the amplifier holds the last value. The dry run reports how far that zero-order hold strays from the
waveform the protocol asks for (hardware-timed rigs play the waveform itself at the DAQ's scan rate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.protocol.program import Program

FINE_HZ = 20_000.0  # evaluation grid of the waveform
MAX_POINTS = 2_000_000  # per step: longer steps are evaluated on their first MAX_POINTS / FINE_HZ seconds


@dataclass(frozen=True)
class Staircase:
    """Largest deviation of the held set-points from the requested waveform, and where."""

    max_error_V: float
    step: str
    setpoint_Hz: float
    per_step: dict[str, float]  # step name → its largest deviation [V]


def staircase_distortion(program: Program) -> Staircase | None:
    """The set-point staircase's worst deviation [V] over all streamed voltage steps (None: hardware-timed rig or
    no streamed voltage waveform)."""
    rig = program.rig
    if rig.amplifier is None or rig.amplifier.drive == "daq":
        return None
    rate = program.protocol.recording.setpoint_Hz
    worst, where = 0.0, ""
    per_step: dict[str, float] = {}
    for seg in program.segments:
        if seg.voltage is None or seg.duration <= 0:
            continue
        n = min(int(seg.duration * FINE_HZ) + 1, MAX_POINTS)
        t = seg.t_start + np.arange(n) / FINE_HZ
        ticks = seg.t_start + np.floor((t - seg.t_start) * rate + 1e-9) / rate
        err = float(np.max(np.abs(seg.voltage(t) - seg.voltage(ticks))))
        per_step[seg.name] = err
        if err > worst:
            worst, where = err, seg.name
    return Staircase(worst, where, rate, per_step) if where else None
