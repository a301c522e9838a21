"""A segment's set-point ticks as arrays: :func:`bench.protocol.program.ticks` for the dry run, in a few numpy
passes instead of one Python call (and one waveform evaluation) per tick.

The values are :func:`~bench.protocol.program.ticks`' doubles: the same elementwise operations, and Python's
``min``/``max`` written as ``np.where`` (which of two equal values is kept matters for signed zeros).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.protocol.program import HOLD_KEEPALIVE_S, Program, Segment


@dataclass(frozen=True)
class TickArrays:
    """The ticks of one segment: their times (the end tick last), voltage set-points (None: the segment sets
    none) and the go-tos: at ticks ``motor`` (indices), to motor position ``target`` at ``velocity`` and
    ``acceleration``."""

    t: np.ndarray
    voltage: np.ndarray | None
    motor: np.ndarray
    target: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


def _min(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Python's ``min(a, b)`` elementwise: b where b < a, else a."""
    return np.where(np.less(b, a), b, a)


def _max(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Python's ``max(a, b)`` elementwise: b where b > a, else a."""
    return np.where(np.greater(b, a), b, a)


def tick_times(program: Program, seg: Segment) -> np.ndarray:
    """The times of :func:`~bench.protocol.program.ticks` before the end tick."""
    if seg.duration <= 0:
        return np.zeros(0)
    dt = 1.0 / program.protocol.recording.setpoint_Hz
    out = []
    t, k = seg.t_start, 0
    while t < seg.t_end - 1e-12:
        out.append(t)
        k += 1
        t = seg.t_start + k * dt if t < seg.stream_until - 1e-12 else t + max(dt, HOLD_KEEPALIVE_S)
    return np.array(out, dtype=float)


def tick_arrays(program: Program, seg: Segment) -> TickArrays:
    """:func:`~bench.protocol.program.ticks` of ``seg`` (none for a segment without duration)."""
    none = np.zeros(0)
    if seg.duration <= 0:
        return TickArrays(none, None, np.zeros(0, dtype=np.int64), none, none, none)
    dt = 1.0 / program.protocol.recording.setpoint_Hz
    ts = tick_times(program, seg)
    t = np.append(ts, seg.t_end)
    voltage = None if seg.voltage is None else np.asarray(seg.voltage(t), dtype=float)
    m = program.rig.motor
    idx = np.zeros(0, dtype=np.int64)
    target = velocity = acceleration = none
    if m is not None and program.has_motor_axis and (seg.move is not None or seg.position is not None):
        if seg.move is not None:  # one go-to, at the first tick
            idx = np.zeros(min(ts.size, 1), dtype=np.int64)
            x, v, a = (np.full(idx.size, float(q)) for q in seg.move)
        else:  # a go-to per tick towards x(t + 2dt) at the mean speed over those two ticks (motor_command)
            assert seg.position is not None
            idx = np.arange(ts.size)
            ahead = _min(ts + 2 * dt, seg.t_end)
            x_now, x = np.asarray(seg.position(ts), float), np.asarray(seg.position(ahead), float)
            step = np.abs(x - x_now)
            v = _min(m.max_velocity_m_per_s, _max(step / _max(ahead - ts, dt), 1e-4))
            a = np.full(idx.size, float(m.max_acceleration_m_per_s2))
        target = _min(_max(np.asarray(program.motor_position(x), float), m.travel_m[0]), m.travel_m[1])
        velocity, acceleration = np.asarray(v, float), a
    return TickArrays(t, voltage, idx, target, velocity, acceleration)
