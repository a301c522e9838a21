"""Compile a validated protocol for a rig into a timed program of segments, with the static checks.

Each segment has a start time on the run clock, a duration, and what it does to the set-points:
``voltage(t)`` / ``position(t)`` functions of absolute run time (None: hold), a motor go-to, or specimen
changes. Static checks refuse, with one line naming the step and field, anything outside the rig's or
specimen's limits that can be known without the model: voltages, travel, channels the rig lacks,
set-point density of waveforms, and laser storage capacity per storing step. The run lasts at most
``MAX_DURATION_S`` (7 days) and records at most ``MAX_SAMPLES`` samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from bench.core.motion import MotionProfile
from bench.protocol.schema import MAX_DURATION_S, HoldStep, MoveStep, Protocol, RampStep, SetStep, WaveformStep
from bench.rig import RigConfig
from bench.waveforms import Waveform

Signal = Callable[[np.ndarray], np.ndarray]
RELAX_RAMP_S = 0.5  # a relax step brings the voltage to zero over this time (or a tenth of the step)
MOVE_SETTLE_S = 0.05
MAX_SAMPLES = 10**10  # recorded samples over a whole run (all streams): ~ 1 TB uncompressed


class ProtocolLimitError(ValueError):
    """A protocol that the rig or specimen must not run (one line naming file, step and field)."""


@dataclass
class Segment:
    """One step on the run clock."""

    index: int
    label: str
    name: str
    kind: Literal["waveform", "ramp", "hold", "wait", "relax", "move", "set"]
    t_start: float
    duration: float
    voltage: Signal | None = None
    position: Signal | None = None  # LS-DEA aperture x(t) [m]
    move: tuple[float, float, float] | None = None  # (aperture target [m], velocity, acceleration)
    changes: dict[str, float | int] = field(default_factory=dict)
    frequency: float | None = None
    storing: bool = False  # laser data storage runs during this step
    stream_until: float = 0.0  # set-points at the full rate until this run time, then keep-alive only

    @property
    def t_end(self) -> float:
        """End time on the run clock [s]."""
        return self.t_start + self.duration


@dataclass
class Program:
    """A protocol compiled for a rig."""

    protocol: Protocol
    rig: RigConfig
    segments: list[Segment]

    @property
    def duration(self) -> float:
        """Total run time [s]."""
        return self.segments[-1].t_end if self.segments else 0.0

    @property
    def has_motor_axis(self) -> bool:
        """Whether the aperture is driven by the motor (LS-DEA motor configuration)."""
        return self.rig.motor is not None and self.rig.specimen.kind == "lsdea" and \
            self.rig.specimen.lsdea.configuration == "motor"

    def motor_position(self, x: float | np.ndarray) -> float | np.ndarray:
        """Motor position [m] for an aperture x [m]."""
        cfg = self.rig.specimen.lsdea
        return (x - cfg.x_at_motor_zero_m) / cfg.motor_sign

    def aperture(self, motor: float | np.ndarray) -> float | np.ndarray:
        """Aperture x [m] for a motor position [m]."""
        cfg = self.rig.specimen.lsdea
        return cfg.x_at_motor_zero_m + cfg.motor_sign * motor


def _ramp(t0: float, duration: float, a: float, b: float) -> Signal:
    def f(t: np.ndarray) -> np.ndarray:
        s = np.clip((np.asarray(t, dtype=float) - t0) / duration, 0.0, 1.0)
        return a + (b - a) * s

    return f


def _wave(t0: float, w: Waveform) -> Signal:
    def f(t: np.ndarray) -> np.ndarray:
        return w(np.asarray(t, dtype=float) - t0)

    return f


def compile_program(protocol: Protocol, rig: RigConfig) -> Program:
    """Lay the protocol's steps on the run clock and apply the static checks."""
    where = f"protocol file {protocol.path}"
    motor_axis = rig.motor is not None and rig.specimen.kind == "lsdea" and rig.specimen.lsdea.configuration == "motor"
    rec = protocol.recording
    capacity = rig.laser.capacity if rig.laser else 0
    v_limit = rig.limits.max_voltage_V
    if rig.amplifier is not None:
        v_limit = min(v_limit, rig.amplifier.max_voltage_V)
    program = Program(protocol, rig, [])
    t = 0.0
    v_now = 0.0
    x_now = (rig.specimen.lsdea.x_at_motor_zero_m if motor_axis else None)

    def refuse(label: str, what: str) -> ProtocolLimitError:
        return ProtocolLimitError(f"{where}: {label}: {what}")

    def check_voltage(label: str, lo: float, hi: float) -> None:
        if rig.amplifier is None:
            raise refuse(label, f"channel voltage: rig {rig.name} has no amplifier")
        peak = max(abs(lo), abs(hi))
        if peak > v_limit:
            raise refuse(label, f"peak voltage {peak:.0f} V exceeds the rig limit {v_limit:.0f} V")

    def check_aperture(label: str, lo: float, hi: float) -> None:
        if not motor_axis:
            raise refuse(label, f"channel position: rig {rig.name} has no motor driving the LS-DEA")
        m_lo, m_hi = sorted((float(program.motor_position(lo)), float(program.motor_position(hi))))
        tr = rig.motor.travel_m  # type: ignore[union-attr]
        if m_lo < tr[0] - 1e-12 or m_hi > tr[1] + 1e-12:
            raise refuse(label, f"aperture {lo * 1e3:.1f}…{hi * 1e3:.1f} mm needs motor {m_lo * 1e3:.1f}…"
                         f"{m_hi * 1e3:.1f} mm, outside travel [{tr[0] * 1e3:.1f}, {tr[1] * 1e3:.1f}] mm")

    for i, (step, label) in enumerate(zip(protocol.steps, protocol.labels, strict=True)):
        name = step.name or step.type
        seg: Segment
        if isinstance(step, WaveformStep):
            wave = Waveform(step.kind, step.amplitude_si, step.frequency_Hz, step.offset_si)
            lo, hi = (step.offset_si - abs(step.amplitude_si), step.offset_si + abs(step.amplitude_si)) \
                if step.kind == "sine" else sorted((step.offset_si, step.offset_si + step.amplitude_si))
            if step.frequency_Hz * rec.points_per_cycle > rec.setpoint_Hz:
                raise refuse(label, f"frequency_Hz {step.frequency_Hz:g} needs ≥ {rec.points_per_cycle} set-points per "
                             f"cycle, i.e. recording.setpoint_Hz ≥ {step.frequency_Hz * rec.points_per_cycle:g}")
            seg = Segment(i, label, name, "waveform", t, step.duration, frequency=step.frequency_Hz)
            if step.channel == "voltage":
                check_voltage(label, lo, hi)
                seg.voltage = _wave(t, wave)
                v_now = float(wave(np.array([step.duration]))[0])
            else:
                check_aperture(label, lo, hi)
                seg.position = _wave(t, wave)
                x_now = float(wave(np.array([step.duration]))[0])
        elif isinstance(step, RampStep):
            seg = Segment(i, label, name, "ramp", t, step.duration_s)
            if step.channel == "voltage":
                check_voltage(label, v_now, step.to_si)
                seg.voltage = _ramp(t, step.duration_s, v_now, step.to_si)
                v_now = step.to_si
            else:
                check_aperture(label, float(x_now if x_now is not None else 0.0), step.to_si)
                seg.position = _ramp(t, step.duration_s, float(x_now), step.to_si)  # type: ignore[arg-type]
                x_now = step.to_si
        elif isinstance(step, HoldStep):
            seg = Segment(i, label, name, step.type, t, step.duration_s)
            if step.type == "relax" and v_now != 0.0:
                seg.voltage = _ramp(t, min(RELAX_RAMP_S, step.duration_s / 10), v_now, 0.0)
                v_now = 0.0
        elif isinstance(step, MoveStep):
            if x_now is None:
                raise refuse(label, f"a move step needs the motor: rig {rig.name} has no motor driving the LS-DEA")
            check_aperture(label, min(step.position_si, float(x_now)), max(step.position_si, float(x_now)))
            m = rig.motor
            if step.velocity_si > m.max_velocity_m_per_s or step.acceleration_si > m.max_acceleration_m_per_s2:  # type: ignore[union-attr]
                raise refuse(label, f"velocity/acceleration beyond the rig's {m.max_velocity_m_per_s:g} m/s, "  # type: ignore[union-attr]
                             f"{m.max_acceleration_m_per_s2:g} m/s²")  # type: ignore[union-attr]
            prof = MotionProfile.plan(0.0, float(x_now), 0.0, step.position_si, step.velocity_si, step.acceleration_si,
                                      step.acceleration_si)
            seg = Segment(i, label, name, "move", t, prof.t_end + MOVE_SETTLE_S,
                          move=(step.position_si, step.velocity_si, step.acceleration_si))
            x_now = step.position_si
        else:
            assert isinstance(step, SetStep)
            changes = {k: v for k, v in (("temperature_K", step.temperature_K), ("hung_mass_kg", step.hung_mass_kg),
                                         ("prototype", step.prototype)) if v is not None}
            kind = rig.specimen.kind
            if kind == "membrane" and ({"hung_mass_kg", "prototype"} & set(changes)):
                raise refuse(label, "hung_mass_kg and prototype apply to the LS-DEA, the rig holds a membrane")
            if kind == "lsdea" and "temperature_K" in changes:
                raise refuse(label, "temperature_K acts on the membrane model only")
            if "hung_mass_kg" in changes and rig.specimen.lsdea.configuration != "hung":
                raise refuse(label, "hung_mass_kg needs the hung-mass (isotonic) configuration")
            seg = Segment(i, label, name, "set", t, 0.0, changes=changes)
        seg.storing = bool(rig.laser and rec.displacement_Hz > 0 and seg.kind in ("waveform", "ramp", "move"))
        if seg.kind in ("waveform", "ramp"):
            seg.stream_until = seg.t_end
        elif seg.kind == "relax" and seg.voltage is not None:
            seg.stream_until = t + min(RELAX_RAMP_S, seg.duration / 10)
        else:
            seg.stream_until = t
        if seg.storing:
            points = int(np.floor(seg.duration * rec.displacement_Hz)) + 1
            if points > capacity:
                raise refuse(label, f"{points} laser points at recording.displacement_Hz = {rec.displacement_Hz:g} "
                             f"exceed the {rig.laser.model} storage of {capacity} points; "  # type: ignore[union-attr]
                             "lower the rate or split the step")
        program.segments.append(seg)
        t += seg.duration
        if not t <= MAX_DURATION_S:
            raise refuse(label, f"the run reaches {t:.4g} s here, beyond the limit of {MAX_DURATION_S:.0f} s (7 days)")
    from bench.protocol.predict import sample_counts  # predict imports this module

    samples = sum(sample_counts(program).values())
    if samples > MAX_SAMPLES:
        raise ProtocolLimitError(f"{where}: recording: {samples:.3g} samples over the run exceed the limit of "
                                 f"{MAX_SAMPLES:.0e}; lower the recording rates")
    return program


def plays_on(prev: Segment, nxt: Segment) -> bool:
    """Whether a hardware-timed stream plays ``nxt`` straight after ``prev`` (appended, no restart): both last,
    ``nxt`` starts where ``prev`` ends and needs no specimen change (an operator's action stops the stream)."""
    return prev.duration > 0 and nxt.duration > 0 and not nxt.changes and abs(nxt.t_start - prev.t_end) <= 1e-9


def voltage_at(seg: Segment, t: float) -> float | None:
    """Voltage set-point [V] of ``seg`` at run time t (None: keep the present one)."""
    return None if seg.voltage is None else float(seg.voltage(np.array([t]))[0])


def motor_command(program: Program, seg: Segment, t: float, dt: float,
                  first: bool) -> tuple[float, float, float] | None:
    """Motor go-to (motor position [m], velocity [m/s], acceleration [m/s²]) to send at run time t, or None.

    ``move`` steps command their target once; aperture waveforms and ramps stream a go-to per set-point
    tick (LinRS has no streaming mode) towards x(t + 2dt) at the average speed over those two ticks: every
    command is superseded mid-cruise by the next, so the motor moves continuously at the waveform's speed
    instead of stopping at each target (which would alias the damping force c·ẋ at the sampling ticks).
    """
    m = program.rig.motor
    if m is None or not program.has_motor_axis:
        return None

    def in_travel(x: float) -> float:  # the compiler checked travel; remove floating-point excess
        return min(max(float(program.motor_position(x)), m.travel_m[0]), m.travel_m[1])

    if seg.move is not None:
        if not first:
            return None
        target, v, a = seg.move
        return in_travel(target), v, a
    if seg.position is None:
        return None
    ahead = min(t + 2 * dt, seg.t_end)
    x_now, x_next = seg.position(np.array([t, ahead]))
    step = abs(float(x_next - x_now))
    v = min(m.max_velocity_m_per_s, max(step / max(ahead - t, dt), 1e-4))
    return in_travel(float(x_next)), v, m.max_acceleration_m_per_s2
