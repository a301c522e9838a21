"""What the engine reads from each instrument during a step, how often, and what it does with each reading.

One :class:`Poll` per kind of acquisition. The engine knows none of them by name: at every step it asks each
poll for its period (None: not in this step) and calls the poll when it is due, on the run clock, with the
time it was due (its lateness goes to the stream's ``late`` column). A poll sees the run through the
:class:`~bench.runtime.context.RunContext` the engine hands it, nothing else of the engine. A new instrument type
brings its poll here — with its driver, its twin and its rig-file section — and the engine does not change.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bench.protocol.program import PASSIVE_LASER_HZ, Segment
from bench.runtime.context import RunContext, present
from bench.runtime.interlock import mismatch_trip, motion_trip
from bench.runtime.safety import SafetyTrip
from drivers.errors import InstrumentError, InstrumentStateError

FETCH_PERIOD_S = 0.25  # laser storage upload period while storing (run time)
COLLECT_PERIOD_S = 0.05  # hardware-timed rigs: collect the DAQ stream (and top up its output buffer) this often
COLLECT_PERIOD_VIRTUAL_S = 0.25  # virtual time: fewer, larger blocks (the output buffer holds ~0.8 s at 10 kHz)


@dataclass(frozen=True)
class StepState:
    """What a step does with the rig, as the polls need it."""

    seg: Segment | None  # None: paused
    streamed: bool  # a hardware-timed stream plays this step
    laser_serial: bool  # the laser is read over its own line (not on the DAQ)
    storing: bool  # the laser's data storage runs


PAUSED = StepState(None, streamed=False, laser_serial=False, storing=False)  # a paused run: no step under way


@dataclass(frozen=True)
class Poll:
    """One kind of acquisition: its name, its period in a step (None: not in it) and what one poll does.
    ``first``: the first poll comes this many periods after the step's start (0: at the start)."""

    name: str
    period: Callable[[RunContext, StepState], float | None]
    run: Callable[[RunContext, float], None]
    first: int = 0


def _monitors(e: RunContext, due: float) -> None:
    v, i = e.amp.read_monitors()
    e.rec.append("amplifier", v.timestamp - e.t0, voltage=v.value, current=i.value,
                 **e.monitor_columns(e.lateness(due)))
    e.snapshot.values["voltage"], e.snapshot.values["current"] = v.value, i.value
    e.sup.check_monitors(v.value, i.value)
    if (m := e.verifier.reading(v.timestamp - e.t0, v.value, v.ok)) is not None:
        raise mismatch_trip(m, "the voltage monitor")


def _position(e: RunContext, due: float) -> None:
    r = e.motor.read_position()
    prog = e.program
    x = float(prog.aperture(r.value)) if prog.has_motor_axis else math.nan
    e.rec.append("motor", r.timestamp - e.t0, position=r.value, aperture=x, **e.late_columns("motor", e.lateness(due)))
    if not r.ok or not math.isfinite(r.value):
        raise InstrumentStateError("motor", f"drive reports {r.status}: {_drive_error_text(e)}")
    e.snapshot.values["position"], e.snapshot.values["aperture"] = r.value, x
    e.sup.check_motor(r.value, x if prog.has_motor_axis else e.sup.aperture or 0.0)
    if (m := e.motion.reading(r.timestamp - e.t0, r.value)) is not None:
        raise motion_trip(m)


def _force(e: RunContext, due: float) -> None:
    r = e.cell.read()
    e.rec.append("load_cell", r.timestamp - e.t0, force=r.value, ok=np.array(r.ok, dtype="u1"),
                 **e.late_columns("load_cell", e.lateness(due)))
    e.snapshot.values["force"] = r.value
    if r.status in ("overload", "underload"):
        raise SafetyTrip(f"load cell {r.status}")
    if r.ok or r.status == "unstable":
        e.sup.check_force(r.value)


def _laser(e: RunContext, due: float) -> None:
    r = e.laser.read()
    if r.timestamp - e.t0 <= e.laser_t_last:  # a time the stream already has (one time base, no duplicates)
        return
    e.laser_t_last = r.timestamp - e.t0
    d = float(e.to_specimen(np.array([r.value]))[0])
    ok = r.ok and math.isfinite(d)
    e.rec.append("laser", r.timestamp - e.t0, displacement=d, valid=np.array(ok, dtype="u1"),
                 **e.late_columns("laser", e.lateness(due)))
    if ok:
        e.sup.update_displacement(d)
        e.snapshot.values["displacement"] = d


def _drive_error_text(e: RunContext) -> str:
    """The drive's own account of its state (error code and text), for the file."""
    try:
        st = e.motor.status()
    except InstrumentError as exc:
        return f"status unreadable ({exc.detail})"
    return f"state {st.state}, error {st.error_code:#06x}" + (f" ({st.error_text})" if st.error_text else "")


def record_laser_block(e: RunContext) -> int:
    """Fetch and record one block of stored laser data; returns how many samples it held."""
    block = e.laser.fetch_buffer()
    t = block.times() - e.t0
    new = t > e.laser_t_last  # a step's storage starts at the time the step before ended on: that time is recorded
    if new.any():
        t, values = t[new], block.values[new]
        disp = e.to_specimen(values)
        valid = block.valid[new] & np.isfinite(disp)
        e.rec.append("laser", t, displacement=disp, valid=valid.astype("u1"),
                     **e.late_columns("laser", np.full(disp.size, np.nan)))  # the laser's own clock
        e.laser_t_last = float(t[-1])
        good = disp[valid]
        if good.size:
            e.sup.update_displacement(float(good[-1]))
            e.snapshot.values["displacement"] = float(good[-1])
    return int(block.values.size)


def _rate(hz: float) -> float | None:
    return 1.0 / hz if hz else None


def _monitors_period(e: RunContext, s: StepState) -> float | None:
    """The amplifier's monitors on a software-timed rig (a DAQ samples them on its scan clock)."""
    return _rate(e.program.protocol.recording.monitors_Hz) if e.inst.amplifier is not None and e.stream is None \
        else None


def _position_period(e: RunContext, s: StepState) -> float | None:
    return _rate(e.program.protocol.recording.position_Hz) if e.inst.motor is not None else None


def _force_period(e: RunContext, s: StepState) -> float | None:
    return _rate(e.program.protocol.recording.force_Hz) if e.inst.load_cell is not None else None


def _fetch_period(e: RunContext, s: StepState) -> float | None:
    return FETCH_PERIOD_S if s.storing else None


def _fetch(e: RunContext, due: float) -> None:
    record_laser_block(e)


def _laser_period(e: RunContext, s: StepState) -> float | None:
    """Single laser reads while its storage is idle (a DAQ samples the laser's analog output itself)."""
    return 1 / PASSIVE_LASER_HZ if s.laser_serial and not s.storing else None


def _collect_period(e: RunContext, s: StepState) -> float | None:
    return (COLLECT_PERIOD_VIRTUAL_S if e.clock.virtual else COLLECT_PERIOD_S) if s.streamed else None


def _collect(e: RunContext, due: float) -> None:
    present(e.stream, "daq").collect()


POLLS = (
    Poll("monitors", _monitors_period, _monitors),
    Poll("position", _position_period, _position),
    Poll("force", _force_period, _force),
    Poll("fetch", _fetch_period, _fetch, first=1),  # nothing is stored yet at the step's start
    Poll("laser", _laser_period, _laser),
    Poll("collect", _collect_period, _collect),
)
