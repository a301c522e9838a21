"""What the engine reads from each instrument during a step, how often, and what it does with each reading.

One :class:`Poll` per kind of acquisition; the engine knows none of them by name: at every step it asks each of
:func:`rig_polls` for its period (None: not in this step) and calls it when it is due, on the run clock, with the
time it was due (its lateness goes to the stream's ``late`` column). A poll sees the run through the
:class:`~bench.runtime.context.RunContext` the engine hands it, nothing else of the engine.

Every instrument a run reads is polled by one generic poll (:func:`poll_once`): its ``read()`` is keyed exactly
as its ``describe()`` (bluesky's ``Readable``), so the row goes to the stream that names. What a role does beyond
recording — the supervisor's and the verifiers' checks, live values, the laser's offset and sign — is a small
:class:`Polled` declaration in :data:`ROLES`; a role without one (a thermometer) is recorded as read. Only the
block acquisitions have polls of their own: the laser storage's fetch and the DAQ stream's collect.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bench.protocol.program import FETCH_PERIOD_S, PASSIVE_LASER_HZ, Segment
from bench.runtime.context import RunContext, present
from bench.runtime.interlock import OUTPUT_ON_V, mismatch_trip, motion_trip
from bench.runtime.safety import SafetyTrip
from drivers.errors import InstrumentError, InstrumentStateError
from drivers.interfaces import Readable, ReadingMap, StreamDescription

COLLECT_PERIOD_S = 0.05  # hardware-timed rigs: collect the DAQ stream (and top up its output buffer) this often
COLLECT_PERIOD_VIRTUAL_S = 0.25  # virtual time: fewer, larger blocks (the output buffer holds ~0.8 s at 10 kHz)
SENSOR_PERIOD_S = 1.0  # a role the run time declares nothing for (a thermometer): read this often (run time)
BRIDGE_POLL_S = 0.1  # a DAQ rig's load cell outside its stream (paused, uploads): read on request at most this often


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
    ``first``: the first poll comes this many periods after the step's start (0: at the start). ``backlog``: it
    fetches what accumulated (stored laser data, a stream's scans), so a slot missed behind the schedule is never
    skipped (the engine skips a reading's missed slots, not a backlog's)."""

    name: str
    period: Callable[[RunContext, StepState], float | None]
    run: Callable[[RunContext, float], None]
    first: int = 0
    backlog: bool = False


Row = dict[str, float]  # the values one poll records, by column


def _as_read(e: RunContext, r: ReadingMap) -> Row | None:
    return {k: x.value for k, x in r.items()}


def _no_check(e: RunContext, r: ReadingMap, row: Row) -> None:
    return None


@dataclass(frozen=True)
class Polled:
    """How the generic poll treats one role's readings, declared once per role: ``name`` (the engine's name for
    the poll), ``period`` in a step (None: not in it), ``row``: the values to record from one ``read()`` (keyed as
    ``describe()``; derived columns added; None: nothing new to record), ``check``: what the run does with a
    recorded row (live values, supervisor, verifiers; raises to end the run). A role without a declaration is
    recorded as read every :data:`SENSOR_PERIOD_S`."""

    name: str
    period: Callable[[RunContext, StepState], float | None]
    row: Callable[[RunContext, ReadingMap], Row | None] = _as_read
    check: Callable[[RunContext, ReadingMap, Row], None] = _no_check


def poll_once(e: RunContext, drv: Readable, how: Polled, due: float, d: StreamDescription | None = None) -> None:
    """The software-timed poll of any readable instrument: one ``read()``, its row appended to the stream its
    ``describe()`` names (stamped with the reading's time, its lateness in ``late``), then the role's check — also
    when the row could not be recorded (the storage fault is raised after the check, unless the check raises a trip
    first). ``d``: the instrument's ``describe()``, where the caller has it already."""
    if d is None:
        d = drv.describe()
    r = drv.read()
    row = how.row(e, r)
    if row is None:
        return
    try:
        e.rec.append(d.stream, r[d.columns[0].name].timestamp - e.t0, **row,
                     **e.late_columns(d.stream, e.lateness(due)))
    except OSError:  # the file failed (it stays failed: the run ends on it); the reading is checked all the same:
        how.check(e, r, row)  # a trip or a latch it shows outranks the storage fault (which the run still reports)
        raise
    how.check(e, r, row)


def _rate(hz: float) -> float | None:
    return 1.0 / hz if hz else None


# ------------------------------------------------------------ amplifier: the monitors
def _monitors_period(e: RunContext, s: StepState) -> float | None:
    """The amplifier's monitors on a software-timed rig (a DAQ samples them on its scan clock)."""
    return _rate(e.program.protocol.recording.monitors_Hz) if e.stream is None else None


def _monitors_check(e: RunContext, r: ReadingMap, row: Row) -> None:
    v, i = r["voltage"], r["current"]
    e.snapshot.values["voltage"], e.snapshot.values["current"] = v.value, i.value
    e.sup.check_monitors(v.value, i.value)
    if (m := e.verifier.reading(v.timestamp - e.t0, v.value, v.ok)) is not None:
        raise mismatch_trip(m, "the voltage monitor")


# ------------------------------------------------------------ motor: the encoder, the aperture it gives
def _position_row(e: RunContext, r: ReadingMap) -> Row | None:
    x = r["position"].value
    return {"position": x, "aperture": float(e.program.aperture(x)) if e.program.has_motor_axis else math.nan}


def _position_check(e: RunContext, r: ReadingMap, row: Row) -> None:
    p = r["position"]
    if not p.ok or not math.isfinite(p.value):
        raise InstrumentStateError("motor", f"drive reports {p.status}: {_drive_error_text(e)}")
    x = row["aperture"]
    e.snapshot.values["position"], e.snapshot.values["aperture"] = p.value, x
    e.sup.check_motor(p.value, x if e.program.has_motor_axis else e.sup.aperture or 0.0)
    if (m := e.motion.reading(p.timestamp - e.t0, p.value)) is not None:
        raise motion_trip(m)


# ------------------------------------------------------------ load cell
def _force_period(e: RunContext, s: StepState) -> float | None:
    """The load cell at the protocol's force rate — not while a run's DAQ samples its bridge amplifier on the scan
    clock (a streamed step); paused, or between streams, it is read on request as the monitors are (a reviewer: the
    force went unsupervised through a pause on a DAQ rig)."""
    rate = _rate(e.program.protocol.recording.force_Hz)
    if e.stream is None or not e.stream.has_force:
        return rate
    if s.streamed:
        return None
    return None if rate is None else max(rate, BRIDGE_POLL_S)  # one Modbus round trip each: no faster than this


def _force_check(e: RunContext, r: ReadingMap, row: Row) -> None:
    f = r["force"]
    e.snapshot.values["force"] = f.value
    if f.status in ("overload", "underload"):
        raise SafetyTrip(f"load cell {f.status}")
    if f.ok or f.status == "unstable":
        e.sup.check_force(f.value)


# ------------------------------------------------------------ laser: single reads while its storage is idle
def _laser_period(e: RunContext, s: StepState) -> float | None:
    """Single laser reads while its storage is idle (a DAQ samples the laser's analog output itself)."""
    return 1 / PASSIVE_LASER_HZ if s.laser_serial and not s.storing else None


def _laser_row(e: RunContext, r: ReadingMap) -> Row | None:
    raw = r["displacement"]
    if raw.timestamp - e.t0 <= e.laser_t_last:  # a time the stream already has (one time base, no duplicates)
        if raw.timestamp - e.t0 == e.laser_t_last and math.isfinite(e.laser_last):  # that very sample, read again
            e.snapshot.values["displacement"] = e.laser_last  # (manual `read` just after a poll said "n/a": tester)
        return None
    d = float(e.to_specimen(np.array([raw.value]))[0])
    return {"displacement": d, "valid": float(raw.ok and math.isfinite(d))}


def _laser_check(e: RunContext, r: ReadingMap, row: Row) -> None:
    """The stretch for the supervisor's field check. Where the context asks it (``laser_lost_s``: manual control),
    readings that are no measurement for that long with the output on trip: the true field is then not known (a
    held 8 kV crept the membrane past the laser's range, and on to runaway, with the field computed at the last
    stretch in range: an outside tester). A run records them (``valid`` 0): its protocol was dry-run on the model."""
    t = r["displacement"].timestamp - e.t0
    e.laser_t_last = t
    e.laser_last = row["displacement"] if row["valid"] else math.nan
    if row["valid"] or abs(e.v_cmd) <= OUTPUT_ON_V:
        e.laser_lost_since = math.nan
    elif math.isnan(e.laser_lost_since):
        e.laser_lost_since = t
    if row["valid"]:
        e.sup.update_displacement(row["displacement"])
        e.snapshot.values["displacement"] = row["displacement"]
        return
    status = r["displacement"].status
    # out of the laser's range at once (a measurement: the specimen is past it), any other reading without a
    # displacement once it has lasted (a glint, a dusty target); never where the voltage is safe at any stretch
    lost = status.startswith("over_range") or t - e.laser_lost_since >= (e.laser_lost_s or math.inf)
    if e.laser_lost_s is not None and lost and not e.sup.field_bounded(e.v_cmd):
        raise SafetyTrip(f"laser reads no displacement ({status}) at {e.v_cmd:.0f} V: the stretch, and with it the "
                         "true field, is not known")


def _sensor_period(e: RunContext, s: StepState) -> float | None:
    return SENSOR_PERIOD_S


ROLES: dict[str, Polled] = {
    "amplifier": Polled("monitors", _monitors_period, check=_monitors_check),
    "motor": Polled("position", lambda e, s: _rate(e.program.protocol.recording.position_Hz),
                    _position_row, _position_check),
    "load_cell": Polled("force", _force_period, check=_force_check),
    "laser": Polled("laser", _laser_period, _laser_row, _laser_check),
}
"""The roles whose readings the run does more with than record them (any other role: :data:`SENSOR_PERIOD_S`)."""


def _drive_error_text(e: RunContext) -> str:
    """The drive's own account of its state (error code and text), for the file."""
    try:
        st = e.motor.status()
    except InstrumentError as exc:
        return f"status unreadable ({exc.detail})"
    return f"state {st.state}, error {st.error_code:#06x}" + (f" ({st.error_text})" if st.error_text else "")


def record_laser_block(e: RunContext, within: float | None = None) -> int:
    """Fetch and record one block of stored laser data; returns how many samples it held. ``within``: the rig time
    [s] the fetch may take (None: the driver's own bound)."""
    block = e.laser.fetch_buffer(within)
    t = block.times() - e.t0
    new = t > e.laser_t_last  # a step's storage starts at the time the step before ended on: that time is recorded
    if new.any():
        t, values = t[new], block.values[new]
        disp = e.to_specimen(values)
        valid = block.valid[new] & np.isfinite(disp)
        e.rec.append("laser", t, displacement=disp, valid=valid.astype("u1"),
                     **e.late_columns("laser", np.full(disp.size, np.nan)))  # the laser's own clock
        e.laser_t_last = float(t[-1])
        e.laser_last = float(disp[-1]) if valid[-1] else math.nan  # (a single read at that time repeats it)
        good = disp[valid]
        if good.size:
            e.sup.update_displacement(float(good[-1]))
            e.snapshot.values["displacement"] = float(good[-1])
    return int(block.values.size)


STARVED_FETCHES = 2  # fetch periods without an uploaded value after which a fetch is not bounded by the next action


def _fetch_tick(e: RunContext) -> float:
    """The fetch poll's period while storing: every set-point tick, at most ``FETCH_PERIOD_S``."""
    return min(FETCH_PERIOD_S, 1.0 / e.program.protocol.recording.setpoint_Hz)


def _fetch_period(e: RunContext, s: StepState) -> float | None:
    """While the step stores: on every set-point tick (at most every ``FETCH_PERIOD_S``), so that what one bounded
    fetch left is fetched on the following ticks; :func:`_fetch` asks the laser only when a fetch is due on
    ``FETCH_PERIOD_S``'s grid or one left a backlog."""
    return _fetch_tick(e) if s.storing else None


def _fetch(e: RunContext, due: float) -> None:
    """Upload the laser's storage every ``FETCH_PERIOD_S``, each fetch bounded in rig time by the step's next action
    (``e.upload_until``: a set-point, another poll, the step's end): a fetch never holds a set-point back, and what
    it could not upload in time (``pending``) is fetched on the following ticks, from where it stopped — nothing
    lost, nothing twice."""
    if math.isinf(e.fetch_next):  # the step's first run (one tick after its start, the poll's ``first``): its grid
        e.fetch_next = due - _fetch_tick(e) + FETCH_PERIOD_S
    if due >= e.fetch_next - 1e-9:
        e.fetch_next += FETCH_PERIOD_S * (math.floor((due - e.fetch_next) / FETCH_PERIOD_S + 1e-9) + 1)
    elif e.laser.pending == 0:
        return  # caught up, and no fetch due on the grid yet
    # a host behind its schedule leaves no time before the next action, and every bounded fetch would upload nothing
    # to the step's end (a reviewer: a 4-s ramp's whole storage uploaded after it, 3.8 s at 0 V): after
    # STARVED_FETCHES periods without a value the fetch takes the driver's own bound once (the skips say the rest)
    starved = e.now() - e.fetch_moved > STARVED_FETCHES * FETCH_PERIOD_S
    bounded = math.isfinite(e.upload_until) and not starved
    if record_laser_block(e, e.upload_until - e.now() if bounded else None) or e.laser.pending == 0:
        e.fetch_moved = e.now()


def _collect_period(e: RunContext, s: StepState) -> float | None:
    return (COLLECT_PERIOD_VIRTUAL_S if e.clock.virtual else COLLECT_PERIOD_S) if s.streamed else None


def _collect(e: RunContext, due: float) -> None:
    present(e.stream, "daq").collect()


def _role_poll(role: str, drv: Readable, how: Polled) -> Poll:
    """The poll of the instrument of ``role``; its wait kept by the run (:meth:`RunContext.waiting_on`)."""
    described: list[StreamDescription] = []  # the instrument's describe(), asked once, at the first poll

    def run(e: RunContext, due: float) -> None:
        with e.waiting_on(role, due + e.offset):
            if not described:
                described.append(drv.describe())
            poll_once(e, drv, how, due, described[0])
    return Poll(how.name, how.period, run)


FETCH = Poll("fetch", _fetch_period, _fetch, first=1, backlog=True)  # nothing is stored yet at the step's start
COLLECT = Poll("collect", _collect_period, _collect, backlog=True)


def rig_polls(e: RunContext) -> tuple[Poll, ...]:
    """This rig's polls: the generic poll of each instrument it reads (:func:`poll_once`, as its role declares in
    :data:`ROLES`), then the laser storage's fetch and the DAQ stream's collect (blocks, not single reads)."""
    polls = [_role_poll(role, drv, ROLES.get(role) or Polled(role, _sensor_period)) for role, drv in e.inst.readables()]
    return (*polls, FETCH, COLLECT)
