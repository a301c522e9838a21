"""Compile a validated protocol for a rig into a timed program of segments, with the static checks.

Each segment has a start time on the run clock, a duration, and what it does to the set-points:
``voltage(t)`` / ``position(t)`` functions of absolute run time (None: hold), a motor go-to, or specimen
changes. Static checks refuse, with one line naming the step and field, anything outside the rig's or
specimen's limits that can be known without the model: voltages, travel, channels the rig lacks,
set-point density of waveforms, and laser storage capacity per storing step. The run lasts at most
``MAX_DURATION_S`` (7 days) and records at most ``MAX_SAMPLES`` samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from bench.core.motion import MotionProfile
from bench.protocol.schema import (
    MAX_DURATION_S,
    RELAX_RAMP_S,
    RELAX_SETPOINTS,
    HoldStep,
    MoveStep,
    Protocol,
    RampStep,
    SetStep,
    WaveformStep,
)
from bench.rig import RigConfig
from bench.waveforms import Waveform

if TYPE_CHECKING:
    from bench.core.plant import Plant

Signal = Callable[[np.ndarray], np.ndarray]
MOVE_SETTLE_S = 0.05
MAX_SAMPLES = 10**10  # recorded samples over a whole run (all streams): ~ 1 TB uncompressed
PASSIVE_LASER_HZ = 10.0  # single laser reads while its data storage is idle (software-timed rigs)
FETCH_PERIOD_S = 0.25  # laser storage upload period while storing (run time; the engine's, the link budget's)
# a step's end value is held (supervised) at most this long (run time) while its stored laser data upload after it,
# then ramped to 0 V (the engine's drain; the dry run warns of the hold: bench/protocol/link_budget.py upload_hold)
DRAIN_HOLD_S = 1.0
HOLD_KEEPALIVE_S = 0.25  # set-point refresh during holds (keeps the analog module's watchdog fed)
# a set step's "output at 0 V", as a fraction of the rig's voltage limit: 1 ppm (7 mV at 7 kV) is far below one step
# of the finest set-point DAC a rig file allows (16 bits over ±limit: 30 ppm), so the code sent is the 0-V request's,
# and far above a waveform's floating-point end (a whole-cycle 5-kV sine ends at -2.4e-12 V)
ZERO_V_FRACTION = 1e-6


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
    ramp_down: float = 0.0  # a relax step's ramp of the voltage to 0 V [s]

    @property
    def t_end(self) -> float:
        """End time on the run clock [s]."""
        return self.t_start + self.duration



def change_specimen(plant: Plant, changes: Mapping[str, float | int]) -> None:
    """A set step's ``changes`` (the keys :meth:`Compiler.set` writes) on the simulated plant."""
    prototype = changes.get("prototype")
    plant.change_specimen(temperature_K=changes.get("temperature_K"), hung_mass_kg=changes.get("hung_mass_kg"),
                          prototype=None if prototype is None else int(prototype))


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

    @property
    def laser_Hz(self) -> float:
        """The rate [S/s] the laser's storage runs at in storing steps: ``recording.displacement_Hz`` as the
        controller can store it (:meth:`bench.rig.LaserConfig.stored_Hz`; a reviewer: 800 S/s asked, 1000 stored,
        while the storage and link checks counted 800)."""
        rate = self.protocol.recording.displacement_Hz
        return self.rig.laser.stored_Hz(rate) if self.rig.laser is not None and rate > 0 else rate

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


END_TOLERANCE_S = 1e-9  # a time this close to a step's end is its end (far below a scan period: 10 µs at 100 kHz)


def _wave(t0: float, duration: float, w: Waveform) -> Signal:
    """A waveform step's set-point from ``t0`` on: at and after its end, the value it ends on
    (:meth:`Waveform.end_value`: what its last instant played, not the next cycle's first). The end is judged on
    the run clock, ``t0 + duration`` as :attr:`Segment.t_end` sums it, within ``END_TOLERANCE_S``: ``t_end − t0``
    can come out one rounding step short of ``duration``, and a square after a 2.3-s hold then read its next
    cycle's high at its end (a reviewer)."""
    end, t_end = w.end_value(duration), t0 + duration

    def f(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return np.where(t >= t_end - END_TOLERANCE_S, end, w(t - t0))

    return f


class _Compiler:
    """Lays steps on the run clock one at a time: one method per step type, each returning its segment and
    refusing (one line naming file, step and field) what the rig or specimen must not run."""

    def __init__(self, protocol: Protocol, rig: RigConfig) -> None:
        self.protocol, self.rig, self.rec = protocol, rig, protocol.recording
        self.program = Program(protocol, rig, [])
        self.where = f"protocol file {protocol.path}"
        self.v_limit = rig.limits.max_voltage_V
        if rig.amplifier is not None:
            self.v_limit = min(self.v_limit, rig.amplifier.max_voltage_V)
        self.t = 0.0  # run time at which the next step starts
        self.v_now = 0.0  # voltage set-point at that time
        self.x_now = rig.specimen.lsdea.x_at_motor_zero_m if self.program.has_motor_axis else None  # aperture

    def refuse(self, label: str, what: str) -> ProtocolLimitError:
        return ProtocolLimitError(f"{self.where}: {label}: {what}")

    def check_voltage(self, label: str, lo: float, hi: float) -> None:
        if self.rig.amplifier is None:
            raise self.refuse(label, f"channel voltage: rig {self.rig.name} has no amplifier")
        peak = max(abs(lo), abs(hi))
        if peak > self.v_limit:
            raise self.refuse(label, f"peak voltage {peak:.0f} V exceeds the rig limit {self.v_limit:.0f} V")

    def check_aperture(self, label: str, lo: float, hi: float) -> None:
        rig = self.rig
        if not self.program.has_motor_axis or rig.motor is None:
            raise self.refuse(label, f"channel position: rig {rig.name} has no motor driving the LS-DEA")
        m_lo, m_hi = sorted((float(self.program.motor_position(lo)), float(self.program.motor_position(hi))))
        tr = rig.motor.travel_m
        if m_lo < tr[0] - 1e-12 or m_hi > tr[1] + 1e-12:
            raise self.refuse(label, f"aperture {lo * 1e3:.1f}…{hi * 1e3:.1f} mm needs motor {m_lo * 1e3:.1f}…"
                              f"{m_hi * 1e3:.1f} mm, outside travel [{tr[0] * 1e3:.1f}, {tr[1] * 1e3:.1f}] mm")

    # ------------------------------------------------------------------ one compiler per step type
    def waveform(self, i: int, label: str, name: str, step: WaveformStep) -> Segment:
        rec = self.rec
        wave = Waveform(step.kind, step.amplitude_si, step.frequency_Hz, step.offset_si)
        lo, hi = (step.offset_si - abs(step.amplitude_si), step.offset_si + abs(step.amplitude_si)) \
            if step.kind == "sine" else sorted((step.offset_si, step.offset_si + step.amplitude_si))
        if step.frequency_Hz * rec.points_per_cycle > rec.setpoint_Hz:
            raise self.refuse(label, f"frequency_Hz {step.frequency_Hz:g} needs ≥ {rec.points_per_cycle} set-points "
                              f"per cycle, i.e. recording.setpoint_Hz ≥ {step.frequency_Hz * rec.points_per_cycle:g}")
        seg = Segment(i, label, name, "waveform", self.t, step.duration, frequency=step.frequency_Hz)
        end = wave.end_value(step.duration)
        if step.channel == "voltage":
            self.check_voltage(label, lo, hi)
            seg.voltage, self.v_now = _wave(self.t, step.duration, wave), end
        else:
            self.check_aperture(label, lo, hi)
            seg.position, self.x_now = _wave(self.t, step.duration, wave), end
        return seg

    def ramp(self, i: int, label: str, name: str, step: RampStep) -> Segment:
        seg = Segment(i, label, name, "ramp", self.t, step.duration_s)
        if step.channel == "voltage":
            self.check_voltage(label, self.v_now, step.to_si)
            seg.voltage, self.v_now = _ramp(self.t, step.duration_s, self.v_now, step.to_si), step.to_si
        else:
            x0 = float(self.x_now if self.x_now is not None else 0.0)
            self.check_aperture(label, x0, step.to_si)
            seg.position, self.x_now = _ramp(self.t, step.duration_s, x0, step.to_si), step.to_si
        return seg

    def hold(self, i: int, label: str, name: str, step: HoldStep) -> Segment:
        seg = Segment(i, label, name, step.type, self.t, step.duration_s)
        if step.type == "relax" and self.v_now != 0.0:
            seg.ramp_down = step.ramp_down_s if step.ramp_down_s is not None else self.relax_ramp(step)
            seg.voltage = _ramp(self.t, seg.ramp_down, self.v_now, 0.0)
            self.v_now = 0.0
        return seg

    def relax_ramp(self, step: HoldStep) -> float:
        """A relax step's default ramp of the voltage from ``v_now`` to 0 V [s] (no ``ramp_down_s``): the longest of

        * ``RELAX_RAMP_S`` (0.5 s) or a tenth of the step, whichever is shorter (the default as first stated);
        * ``RELAX_SETPOINTS`` (10) set-point periods, 1/``recording.setpoint_Hz`` each: a ramp of at least 10
          set-points, none moving the output more than a tenth of the way (the shutdown ramp's count). Alone, the
          first rule gave a 0.5-s relax at 20 set-points/s one set-point: 5 kV to 0 V in one tick, a charging
          pulse that a DAQ rig's monitor scan reads far beyond ``limits.max_current_A``;
        * ``limits.shutdown_ramp_s``: never steeper than the rig's own ramp to 0 V from the same voltage;
        * |``v_now``| / ``amplifier.slew_limit_V_per_s`` (ADAM drive, where the driver applies it): a ramp the
          slew limit would hold back ends late;

        rounded up to whole set-point periods (the ramp's last set-point is sent at its end, not a keep-alive
        later), and at most the step's ``duration_s``: a shorter relax ramps over its whole length, then steeper
        than the rules say (the dry run's current check judges it). The rig file gives no specimen capacitance
        (the model's varies with stretch), so the current limit is left to that check, not turned into a rate."""
        hz = self.rec.setpoint_Hz
        amp = self.rig.amplifier
        slew = amp.slew_limit_V_per_s if amp is not None and amp.drive == "adam" else math.inf
        want = max(min(RELAX_RAMP_S, step.duration_s / 10), RELAX_SETPOINTS / hz,
                   self.rig.limits.shutdown_ramp_s, abs(self.v_now) / slew)
        return min(step.duration_s, math.ceil(want * hz - 1e-9) / hz)

    def move(self, i: int, label: str, name: str, step: MoveStep) -> Segment:
        m = self.rig.motor
        if self.x_now is None or m is None:
            raise self.refuse(label, f"a move step needs the motor: rig {self.rig.name} has no motor driving the "
                              "LS-DEA")
        x0 = float(self.x_now)
        self.check_aperture(label, min(step.position_si, x0), max(step.position_si, x0))
        if step.velocity_si > m.max_velocity_m_per_s or step.acceleration_si > m.max_acceleration_m_per_s2:
            raise self.refuse(label, f"velocity/acceleration beyond the rig's {m.max_velocity_m_per_s:g} m/s, "
                              f"{m.max_acceleration_m_per_s2:g} m/s²")
        prof = MotionProfile.plan(0.0, x0, 0.0, step.position_si, step.velocity_si, step.acceleration_si,
                                  step.acceleration_si)
        self.x_now = step.position_si
        return Segment(i, label, name, "move", self.t, prof.t_end + MOVE_SETTLE_S,
                       move=(step.position_si, step.velocity_si, step.acceleration_si))

    def set(self, i: int, label: str, name: str, step: SetStep) -> Segment:
        changes = {k: v for k, v in (("temperature_K", step.temperature_K), ("hung_mass_kg", step.hung_mass_kg),
                                     ("prototype", step.prototype)) if v is not None}
        spec = self.rig.specimen
        if spec.kind == "membrane" and ({"hung_mass_kg", "prototype"} & set(changes)):
            raise self.refuse(label, "hung_mass_kg and prototype apply to the LS-DEA, the rig holds a membrane")
        if spec.kind == "lsdea" and "temperature_K" in changes:
            raise self.refuse(label, "temperature_K acts on the membrane model only")
        if "hung_mass_kg" in changes and spec.lsdea.configuration != "hung":
            raise self.refuse(label, "hung_mass_kg needs the hung-mass (isotonic) configuration")
        # the operator acts on the rig (mounts a prototype, hangs a mass, sets the chamber): at 0 V, to within
        # ZERO_V_FRACTION of the voltage limit (a whole-cycle sine ends at sin(2πn) ≈ -2e-12 V in floating point)
        if abs(self.v_now) > ZERO_V_FRACTION * self.v_limit:
            raise self.refuse(label, f"a specimen change needs the output at 0 V, and the step before leaves it at "
                              f"{self.v_now:g} V (0 V means within {ZERO_V_FRACTION * 1e6:g} ppm of the rig's "
                              f"{self.v_limit:.0f} V limit, {ZERO_V_FRACTION * self.v_limit * 1e3:g} mV): end that "
                              "step at 0 V (a relax step, or a ramp to 0)")
        return Segment(i, label, name, "set", self.t, 0.0, changes=changes)

    # ------------------------------------------------------------------ what every step gets
    def recording(self, seg: Segment) -> None:
        """Laser storage and set-point streaming of a segment, and the storage capacity check."""
        rig, rec = self.rig, self.rec
        seg.storing = bool(rig.laser and rec.displacement_Hz > 0 and seg.kind in ("waveform", "ramp", "move"))
        if seg.kind in ("waveform", "ramp"):
            seg.stream_until = seg.t_end
        elif seg.kind == "relax" and seg.voltage is not None:
            seg.stream_until = seg.t_start + seg.ramp_down
        else:
            seg.stream_until = seg.t_start
        if seg.storing and rig.laser is not None:
            stored = rig.laser.stored_Hz(rec.displacement_Hz)
            points = int(np.floor(seg.duration * stored)) + 1
            if points > rig.laser.capacity:
                at = "" if stored == rec.displacement_Hz else f" (stored at {stored:g} S/s, the nearest the LK-G sets)"
                raise self.refuse(seg.label, f"{points} laser points at recording.displacement_Hz = "
                                  f"{rec.displacement_Hz:g}{at} exceed the {rig.laser.model} storage of "
                                  f"{rig.laser.capacity} points; lower the rate or split the step")

    def specimen(self) -> None:
        """The protocol's ``[specimen]`` overrides against the rig's specimen, as a ``set`` step's are checked: an
        LS-DEA protocol's hung mass on a membrane rig was ignored and the run went ahead on the wrong specimen."""
        over, spec = self.protocol.specimen, self.rig.specimen
        if spec.kind == "membrane" and (over.hung_mass_kg is not None or over.prototype is not None):
            raise self.refuse("[specimen]", f"hung_mass_kg and prototype apply to the LS-DEA, rig {self.rig.name} "
                              "holds a membrane")
        if spec.kind == "lsdea" and over.temperature_K is not None:
            raise self.refuse("[specimen]", f"temperature_K acts on the membrane model only (rig {self.rig.name} "
                              "holds an LS-DEA)")
        if spec.kind == "lsdea" and over.hung_mass_kg is not None and spec.lsdea.configuration != "hung":
            raise self.refuse("[specimen]", f"hung_mass_kg needs the hung-mass (isotonic) configuration; rig "
                              f"{self.rig.name} is {spec.lsdea.configuration}")

    def compile(self) -> Program:
        self.specimen()
        steps: dict[type, Callable[..., Segment]] = {WaveformStep: self.waveform, RampStep: self.ramp,
                                                     HoldStep: self.hold, MoveStep: self.move, SetStep: self.set}
        for i, (step, label) in enumerate(zip(self.protocol.steps, self.protocol.labels, strict=True)):
            seg = steps[type(step)](i, label, step.name or step.type, step)
            self.recording(seg)
            self.program.segments.append(seg)
            self.t += seg.duration
            if not self.t <= MAX_DURATION_S:
                raise self.refuse(label, f"the run reaches {self.t:.4g} s here, beyond the limit of "
                                  f"{MAX_DURATION_S:.0f} s (7 days)")
        samples = sum(sample_counts(self.program).values())
        if samples > MAX_SAMPLES:
            raise ProtocolLimitError(f"{self.where}: recording: {samples:.3g} samples over the run exceed the limit "
                                     f"of {MAX_SAMPLES:.0e}; lower the recording rates")
        return self.program


def compile_program(protocol: Protocol, rig: RigConfig) -> Program:
    """Lay the protocol's steps on the run clock and apply the static checks."""
    return _Compiler(protocol, rig).compile()


def sample_counts(program: Program) -> dict[str, int]:
    """Samples per recorded stream for the whole run."""
    rig, rec, T = program.rig, program.protocol.recording, program.duration
    daq = rig.daq if rig.amplifier is not None and rig.amplifier.drive == "daq" else None
    if daq is not None:  # hardware-timed: every streamed step sampled on the DAQ's scan clock
        # one stream per run of back-to-back steps (bench.runtime.hardware_timed chains them): each plays scan 0 at its
        # start, then one scan per period
        segs = program.segments
        chained = [i > 0 and plays_on(segs[i - 1], s) for i, s in enumerate(segs)]
        scans = sum(max(1, round(s.duration * daq.scan_rate_Hz)) + (not c)
                    for s, c in zip(segs, chained, strict=True) if s.duration > 0)
        # the host's set-point rows: the motor's ticks, and the end's 0 V (the DAQ plays each step's voltage itself;
        # a shutdown ramp's rows come only where the output is up at the end)
        counts = {"setpoints": (int(T * rec.setpoint_Hz) if rig.motor is not None else 0) + 1, "amplifier": scans}
        if daq.laser_ain is not None:
            counts["laser"] = scans
        if daq.force_ain is not None:
            counts["load_cell"] = scans
        if rig.motor is not None and rec.position_Hz > 0:
            counts["motor"] = int(T * rec.position_Hz)
        return counts
    counts = {"setpoints": int(T * rec.setpoint_Hz) + len(program.segments)}
    if rig.amplifier is not None and rec.monitors_Hz > 0:
        counts["amplifier"] = int(T * rec.monitors_Hz)
    if rig.laser is not None:
        stored = sum(s.duration for s in program.segments if s.storing)
        counts["laser"] = int(stored * program.laser_Hz) + int((T - stored) * PASSIVE_LASER_HZ)
    if rig.motor is not None and rec.position_Hz > 0:
        counts["motor"] = int(T * rec.position_Hz)
    if rig.load_cell is not None and rec.force_Hz > 0:
        counts["load_cell"] = int(T * rec.force_Hz)
    return counts


def recording_rates(program: Program) -> str:
    """The rate each stream is recorded at on this rig for this protocol, in words (validate's fidelity row)."""
    rig, rec = program.rig, program.protocol.recording
    daq = rig.daq if rig.amplifier is not None and rig.amplifier.drive == "daq" else None
    parts = []
    if daq is not None:
        on_daq = ["voltage", "current"] + (["displacement"] if daq.laser_ain is not None else []) + \
            (["force"] if daq.force_ain is not None else [])
        parts.append(f"{', '.join(on_daq)} at {daq.scan_rate_Hz:g} scans/s on one clock")
    elif rig.amplifier is not None:
        parts.append(f"voltage, current polled at {rec.monitors_Hz:g} Hz")
    if rig.laser is not None and (daq is None or daq.laser_ain is None):
        stored = any(s.storing for s in program.segments)
        parts.append(f"displacement {program.laser_Hz:g} Hz in waveform/ramp/move steps, {PASSIVE_LASER_HZ:g} Hz "
                     "otherwise" if stored else f"displacement polled at {PASSIVE_LASER_HZ:g} Hz")
    if rig.load_cell is not None and (daq is None or daq.force_ain is None):
        parts.append(f"force polled at {rec.force_Hz:g} Hz")
    if rig.motor is not None:
        parts.append(f"motor position polled at {rec.position_Hz:g} Hz")
    return "; ".join(parts)


def recording_shortfalls(program: Program) -> list[str]:
    """What a software-timed rig records below the rates the protocol asks, one sentence per stream (empty: none).

    The LK-G's data storage runs only in steps that move something (waveform, ramp, move); in the other steps the
    laser is read one value at a time at ``PASSIVE_LASER_HZ``. A hardware-timed rig samples every analog channel on
    the scan clock and falls short nowhere.
    """
    rig, rec, T = program.rig, program.protocol.recording, program.duration
    if rig.amplifier is not None and rig.amplifier.drive == "daq" and rig.daq is not None and \
            rig.daq.laser_ain is not None:
        return []
    out = []
    if rig.laser is not None and rec.displacement_Hz > 0 and program.laser_Hz != rec.displacement_Hz \
            and any(s.storing for s in program.segments):
        out.append(f"displacement: recording.displacement_Hz = {rec.displacement_Hz:g} is stored at "
                   f"{program.laser_Hz:g} S/s, the nearest rate the {rig.laser.model} sets (sampling period × "
                   "storage cycle)")
    if rig.laser is not None and rec.displacement_Hz > PASSIVE_LASER_HZ:
        idle = [s for s in program.segments if not s.storing and s.duration > 0]
        idle_s = sum(s.duration for s in idle)
        if idle_s > 0:
            kinds = ", ".join(sorted({s.kind for s in idle}))
            out.append(f"displacement: recording.displacement_Hz = {rec.displacement_Hz:g} is recorded in waveform, "
                       f"ramp and move steps only; the {kinds} steps ({idle_s:.1f} of {T:.1f} s) get single laser "
                       f"reads at {PASSIVE_LASER_HZ:g} Hz (the {rig.laser.model}'s storage runs only while something "
                       "moves)")
    return out


def plays_on(prev: Segment, nxt: Segment) -> bool:
    """Whether a hardware-timed stream plays ``nxt`` straight after ``prev`` (appended, no restart): both last,
    ``nxt`` starts where ``prev`` ends and needs no specimen change (an operator's action stops the stream)."""
    return prev.duration > 0 and nxt.duration > 0 and not nxt.changes and abs(nxt.t_start - prev.t_end) <= 1e-9


def relax_at_zero(seg: Segment) -> float | None:
    """A relax step restarted after the output went to 0 V (a resume after a pause, a resumed campaign, a laser
    upload that zeroed it): its ramp from the step before's value to 0 V is not played again — the step plays 0 V
    from its start, on the same schedule — so that a restart never re-energises the specimen only to ramp it down
    (outside tester: a pause in a recovery step resumed with 2.9 kV back on, its recovery record changed).
    Returns the value its ramp started from (None: not a relax with a ramp, nothing changed)."""
    if seg.kind != "relax" or seg.voltage is None:
        return None
    v0 = float(seg.voltage(np.array([seg.t_start]))[0])
    seg.voltage = _ramp(seg.t_start, max(seg.ramp_down, 1.0), 0.0, 0.0)
    return v0


def voltage_at(seg: Segment, t: float) -> float | None:
    """Voltage set-point [V] of ``seg`` at run time t (None: keep the present one)."""
    return None if seg.voltage is None else float(seg.voltage(np.array([t]))[0])


@dataclass(frozen=True)
class Tick:
    """One set-point update of a segment's schedule (software-timed: what the host sends, and when)."""

    t: float  # run time [s]
    voltage: float | None  # voltage set-point [V] (None: the present one again, a keep-alive)
    motor: tuple[float, float, float] | None  # motor go-to (position [m], velocity, acceleration), or None
    end: bool = False  # the segment's end value, sent at its end (a ramp must reach its target)


def ticks(program: Program, seg: Segment) -> Iterator[Tick]:
    """The set-point schedule of one segment, executed by the engine on the instruments and by the dry run on
    the model: every 1/setpoint_Hz while the segment streams (waveforms, ramps, a relax step's ramp-down: up to the
    first set-point at or after its end, so that a ramp-down off the grid ends on a set-point), a keep-alive every
    ``HOLD_KEEPALIVE_S`` after, and the end value at the segment's end."""
    if seg.duration <= 0:
        return
    dt = 1.0 / program.protocol.recording.setpoint_Hz
    t, k = seg.t_start, 0
    while t < seg.t_end - 1e-12:
        yield Tick(t, voltage_at(seg, t), motor_command(program, seg, t, dt, first=k == 0))
        k += 1
        t = seg.t_start + k * dt if t < seg.stream_until - 1e-12 else t + max(dt, HOLD_KEEPALIVE_S)
    yield end_tick(seg)


def largest_voltage_change(program: Program, seg: Segment) -> float:
    """The largest voltage change [V] between two consecutive set-points of :func:`ticks` while ``seg`` streams
    (its end value included; 0 without a voltage): how far one set-point moves the output as planned."""
    if seg.voltage is None or seg.duration <= 0:
        return 0.0
    dt = 1.0 / program.protocol.recording.setpoint_Hz
    n = int(np.ceil((min(seg.stream_until, seg.t_end) - seg.t_start) / dt - 1e-9)) + 1  # ticks' streaming ones
    t = seg.t_start + np.arange(n) * dt
    v = np.append(seg.voltage(t[t < seg.t_end - 1e-12]), seg.voltage(np.array([seg.t_end])))
    return float(np.max(np.abs(np.diff(v)))) if v.size > 1 else 0.0


def end_tick(seg: Segment) -> Tick:
    """The last tick of :func:`ticks`: the segment's end value at its end."""
    return Tick(seg.t_end, voltage_at(seg, seg.t_end), None, end=True)


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
