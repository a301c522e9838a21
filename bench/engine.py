"""The protocol engine: a compiled program executed on a rig's instruments under the safety supervisor.

The engine turns each step into set-points (voltage through the amplifier, aperture through the motor)
and acquisition (laser data storage during active steps, polled monitors, encoder, load cell and single
laser reads), all stamped on one run clock, and streams everything to the recorder. It runs in real time
against real or simulated instruments, or in virtual time against a simulated rig (the clock jumps to the
next scheduled action; the bytes on the wire are the same).

Every exit — end of the protocol, safety trip, instrument error or lost link, Ctrl-C, SIGTERM — goes
through :meth:`Engine._shut_down`: voltage ramped to zero (at once on a second Ctrl-C, or if the ramp
fails), motor stopped, stored laser data fetched, the reason recorded, the file finalised.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bench.instruments import Instruments
from bench.protocol.program import Program, Segment, motor_command, voltage_at
from bench.recorder import Recorder
from bench.safety import SafetyTrip, Supervisor
from drivers.errors import InstrumentConnectionError, InstrumentError
from sim_devices.clock import Clock

FETCH_PERIOD_S = 0.25  # laser storage upload period while storing (run time)
MONITOR_SETTLE_S = 0.5  # after zeroing, wait for fresh monitor conversions before the final read
PASSIVE_LASER_HZ = 10.0
HOLD_KEEPALIVE_S = 0.25  # set-point refresh during holds (keeps the analog module's watchdog fed)
LATE_TOLERANCE_S = 0.05  # real time: an action later than this counts as an overrun

OperatorFn = Callable[[str], bool]


class StopRequested(Exception):  # noqa: N818 - control flow, not a failure
    """Ctrl-C / SIGTERM / a stop request from another thread."""


@dataclass
class RunResult:
    """How a run ended."""

    path: str
    state: str
    reason: str
    run_time: float
    wall_time: float
    samples: int
    overruns: int = 0
    shutdown_notes: list[str] = field(default_factory=list)


@dataclass
class Snapshot:
    """Latest values for a live view (plain data, refreshed by the engine)."""

    t: float = 0.0
    duration: float = 0.0
    step: int = 0
    steps: int = 0
    step_name: str = ""
    values: dict[str, float] = field(default_factory=dict)
    headroom: dict[str, float] = field(default_factory=dict)
    state: str = "starting"


class Engine:
    """Runs one program on one rig's connected instruments."""

    def __init__(self, program: Program, inst: Instruments, clock: Clock, recorder: Recorder,
                 supervisor: Supervisor, *, apply_specimen: Callable[[dict[str, Any]], None] | None = None,
                 operator: OperatorFn | None = None) -> None:
        self.program = program
        self.inst = inst
        self.clock = clock
        self.rec = recorder
        self.sup = supervisor
        self.apply_specimen = apply_specimen
        self.operator = operator
        self.snapshot = Snapshot(duration=program.duration, steps=len(program.segments))
        self._t0 = 0.0
        self._stop_reason: str | None = None
        self._urgent = threading.Event()
        self._stopping = False
        self._v_cmd = 0.0
        self._storing = False
        self.overruns = 0
        rig = program.rig
        self._laser_offset = (rig.laser.offset_mm * 1e-3) if rig.laser else 0.0
        self._laser_sign = float(rig.laser.sign) if rig.laser else 1.0

    # ------------------------------------------------------------ stop requests (signals, other threads)
    def request_stop(self, reason: str) -> None:
        """Ask the run to stop; a second request while stopping makes the voltage go to zero at once."""
        if self._stop_reason is None:
            self._stop_reason = reason
        else:
            self._urgent.set()

    def _install_signals(self) -> list[tuple[int, Any]]:
        if threading.current_thread() is not threading.main_thread():
            return []
        old = []
        for sig, text in ((signal.SIGINT, "interrupted by Ctrl-C"), (signal.SIGTERM, "terminated by SIGTERM")):
            old.append((sig, signal.signal(sig, lambda *_a, text=text: self.request_stop(text))))
        return old

    # ------------------------------------------------------------ time
    def now(self) -> float:
        """Run time [s]."""
        return self.clock.now() - self._t0

    def _wait_until(self, t: float) -> None:
        if self._stop_reason is not None and not self._stopping:
            raise StopRequested(self._stop_reason)
        if not self.clock.virtual:
            while (left := t - self.now()) > 0:
                if self._stop_reason is not None and not self._stopping:
                    raise StopRequested(self._stop_reason)
                time.sleep(min(left, 0.05))
            if self.now() - t > LATE_TOLERANCE_S:
                self.overruns += 1
        else:
            self.clock.wait_until(self._t0 + t)

    # ------------------------------------------------------------ acquisition
    def _to_specimen(self, laser_value: np.ndarray) -> np.ndarray:
        return (laser_value - self._laser_offset) / self._laser_sign

    def _record_laser_block(self) -> None:
        block = self.inst.laser.fetch_buffer()  # type: ignore[union-attr]
        if block.values.size:
            disp = self._to_specimen(block.values)
            self.rec.append("laser", block.times() - self._t0, displacement=disp, valid=block.valid.astype("u1"))
            good = disp[block.valid]
            if good.size:
                self.sup.update_displacement(float(good[-1]))
                self.snapshot.values["displacement"] = float(good[-1])

    def _poll(self, kind: str) -> None:
        inst, snap = self.inst, self.snapshot
        if kind == "monitors":
            v, i = inst.amplifier.read_monitors()  # type: ignore[union-attr]
            self.rec.append("amplifier", v.timestamp - self._t0, voltage=v.value, current=i.value)
            snap.values["voltage"], snap.values["current"] = v.value, i.value
            self.sup.check_monitors(v.value, i.value)
        elif kind == "position":
            r = inst.motor.read_position()  # type: ignore[union-attr]
            x = float(self.program.aperture(r.value)) if self.program.has_motor_axis else math.nan
            self.rec.append("motor", r.timestamp - self._t0, position=r.value, aperture=x)
            snap.values["aperture"] = x
            self.sup.check_motor(r.value, x if self.program.has_motor_axis else self.sup.aperture or 0.0)
        elif kind == "force":
            r = inst.load_cell.read()  # type: ignore[union-attr]
            self.rec.append("load_cell", r.timestamp - self._t0, force=r.value, ok=np.uint8(r.ok))
            snap.values["force"] = r.value
            if r.status in ("overload", "underload"):
                raise SafetyTrip(f"load cell {r.status}")
            if r.ok or r.status == "unstable":
                self.sup.check_force(r.value)
        elif kind == "laser":
            r = inst.laser.read()  # type: ignore[union-attr]
            d = float(self._to_specimen(np.array([r.value]))[0])
            self.rec.append("laser", r.timestamp - self._t0, displacement=d, valid=np.uint8(r.ok))
            if r.ok:
                self.sup.update_displacement(d)
                self.snapshot.values["displacement"] = d
        elif kind == "fetch":
            self._record_laser_block()

    # ------------------------------------------------------------ set-points
    def _set_voltage(self, v: float, t: float, x_cmd: float = math.nan) -> None:
        self.sup.check_setpoint(v)
        sent = self.inst.amplifier.set_voltage(v)  # type: ignore[union-attr]
        self._v_cmd = sent
        self.rec.append("setpoints", t, voltage=sent, aperture=x_cmd)

    def _segment(self, seg: Segment) -> None:
        prog, inst, rec = self.program, self.inst, self.program.protocol.recording
        self.snapshot.step, self.snapshot.step_name = seg.index, seg.name
        self.rec.event(self.now(), seg.index, "start", f"{seg.name} | {seg.label}")
        if seg.changes:
            text = ", ".join(f"{k} = {v}" for k, v in seg.changes.items())
            if self.apply_specimen is not None:
                self.apply_specimen(seg.changes)
            elif self.operator is None or not self.operator(f"set the specimen: {text}"):
                raise StopRequested(f"operator did not confirm '{seg.name}' ({text})")
            self.rec.event(self.now(), seg.index, "specimen", text)
        if seg.storing:
            inst.laser.start_buffer(1.0 / rec.displacement_Hz)  # type: ignore[union-attr]
            self._storing = True
        dt = 1.0 / rec.setpoint_Hz
        periods = {"monitors": 1 / rec.monitors_Hz if inst.amplifier and rec.monitors_Hz else None,
                   "position": 1 / rec.position_Hz if inst.motor and rec.position_Hz else None,
                   "force": 1 / rec.force_Hz if inst.load_cell and rec.force_Hz else None,
                   "fetch": FETCH_PERIOD_S if seg.storing else None,
                   "laser": 1 / PASSIVE_LASER_HZ if inst.laser and not seg.storing else None}
        count = {k: (1 if k == "fetch" else 0) for k, p in periods.items() if p is not None}
        due = {k: seg.t_start + n * periods[k] for k, n in count.items()}  # from counts: no drift
        t_set, k_set = seg.t_start, 0
        while True:
            t_next = min([t_set, *due.values()])
            if seg.duration == 0 or t_next >= seg.t_end - 1e-12:
                break
            self._wait_until(t_next)
            if t_set <= t_next:
                v = voltage_at(seg, t_set)
                cmd = motor_command(prog, seg, t_set, dt, first=k_set == 0)
                x_cmd = math.nan
                if cmd is not None:
                    target, vel, acc = cmd
                    inst.motor.move_to(target, vel, acc)  # type: ignore[union-attr]
                    x_cmd = float(prog.aperture(target))
                if inst.amplifier is not None:
                    self._set_voltage(self._v_cmd if v is None else v, t_set, x_cmd)
                self.snapshot.values["setpoint"] = self._v_cmd
                k_set += 1
                t_set = seg.t_start + k_set * dt if t_set + dt <= seg.stream_until + 1e-12 else \
                    t_set + max(dt, HOLD_KEEPALIVE_S)
            for kind in [k for k, tk in due.items() if tk <= t_next + 1e-12]:
                self._poll(kind)
                count[kind] += 1
                due[kind] = seg.t_start + count[kind] * periods[kind]  # type: ignore[operator]
            self.snapshot.t = t_next
            self.snapshot.headroom = self.sup.headroom()
            self.rec.maybe_flush()
        self._wait_until(seg.t_end)
        if seg.storing:
            inst.laser.stop_buffer()  # type: ignore[union-attr]
            self._storing = False
            self._record_laser_block()
        self.rec.event(self.now(), seg.index, "end", seg.name)

    # ------------------------------------------------------------ run and shut down
    def run(self) -> RunResult:
        """Run the whole program; always returns with the rig safe and the file finalised."""
        wall0 = time.perf_counter()
        old = self._install_signals()
        self._t0 = self.clock.now()
        state, reason = "completed", "protocol completed"
        try:
            self.snapshot.state = "running"
            self.rec.event(0.0, -1, "run", "start")
            for seg in self.program.segments:
                self._segment(seg)
        except SafetyTrip as trip:
            state, reason = "tripped", f"safety trip: {trip.reason}"
        except StopRequested as stop:
            state, reason = "interrupted", str(stop)
        except InstrumentConnectionError as exc:
            state, reason = "error", f"lost link: {exc}"
        except InstrumentError as exc:
            state, reason = "error", f"instrument error: {exc}"
        except Exception as exc:
            state, reason = "error", f"internal error: {type(exc).__name__}: {exc}"
        notes = self._shut_down(state, reason)
        for sig, handler in old:
            signal.signal(sig, handler)
        return RunResult(str(self.rec.path), state, reason, self.now(), time.perf_counter() - wall0,
                         self.rec.samples_written, self.overruns, notes)

    def _shut_down(self, state: str, reason: str) -> list[str]:
        """Voltage to zero, motor stopped, stored data fetched, file finalised; returns notes on what failed."""
        self._stopping = True
        self.snapshot.state = "stopping"
        notes: list[str] = []
        t = self.now()
        self.rec.event(t, self.snapshot.step, "stop" if state == "completed" else state, reason)
        amp = self.inst.amplifier
        if amp is not None:
            ramp = self.program.rig.limits.shutdown_ramp_s
            v0 = self._v_cmd
            try:
                if v0 != 0.0 and not self._urgent.is_set():
                    n = 10
                    for k in range(1, n + 1):
                        if self._urgent.is_set():
                            break
                        self._wait_until(t + ramp * k / n)
                        v = v0 * (1 - k / n)
                        self._v_cmd = amp.set_voltage(v)
                        self.rec.append("setpoints", self.now(), voltage=self._v_cmd, aperture=math.nan)
            except InstrumentError as exc:
                notes.append(f"voltage ramp-down failed: {exc}")
            try:
                amp.zero()
                self._v_cmd = 0.0
                self.rec.append("setpoints", self.now(), voltage=0.0, aperture=math.nan)
            except InstrumentError as exc:
                notes.append(f"could not command 0 V: {exc}; the analog module's communication watchdog must "
                             "bring the output to 0 V")
        if self.inst.motor is not None:
            try:
                self.inst.motor.stop()
            except InstrumentError as exc:
                notes.append(f"could not stop the motor: {exc}")
        if self._storing and self.inst.laser is not None:
            try:
                self.inst.laser.stop_buffer()
                self._record_laser_block()
            except InstrumentError as exc:
                notes.append(f"stored laser data not fetched: {exc}")
        if amp is not None:
            try:
                self._wait_until(self.now() + MONITOR_SETTLE_S)  # HV is already at 0 V: record it
                self._poll("monitors")
            except (InstrumentError, SafetyTrip) as exc:
                notes.append(f"final monitor read failed: {exc}")
        full_reason = reason + ("" if not notes else " | " + "; ".join(notes))
        self.rec.finish(state, full_reason)
        self.snapshot.state = state
        return notes
