"""Prepare and execute a run: protocol + rig → validation, dry run, instruments, recorder, engine."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from bench import __version__
from bench.core.clock import Clock, WallClock
from bench.protocol.link_budget import check_links
from bench.protocol.predict import Prediction, predict
from bench.protocol.program import (
    Program,
    ProtocolLimitError,
    change_specimen,
    compile_program,
    recording_shortfalls,
)
from bench.protocol.schema import (
    MAX_OPERATOR,
    MAX_SPECIMEN_ID,
    Protocol,
    ProtocolFileError,
    check_label,
    check_notes,
    load_protocol,
    missing_rig_ref,
)
from bench.rig import RigConfig, load_rig_text, rig_to_toml
from bench.runtime import hardware_timed
from bench.runtime.control import control_path
from bench.runtime.engine import MONITOR_REREAD_S, SAFE_STATE, Engine, OperatorFn, RunResult, termination_raises
from bench.runtime.hardware_timed import describe_streams
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.interlock import watchdog_period
from bench.runtime.latch import (
    STATE_ENV,
    Drive,
    arm,
    disarm,
    drive_of,
    latch,
    note,
    note_paused,
    refuse_if_changed,
    refuse_if_latched,
    release,
    reset,
    state_dir,
)
from bench.runtime.polls import SENSOR_PERIOD_S
from bench.runtime.rig_lock import campaign_claimed, claimed
from bench.runtime.safety import Supervisor
from bench.storage import catalog
from bench.storage.chain import chain, continued_in
from bench.storage.recorder import Column, Recorder, now_iso
from bench.storage.recover import recover
from bench.storage.runfile import RunFile, open_run
from drivers.errors import InstrumentError, OperationCancelledError
from drivers.interfaces import StreamDescription

if TYPE_CHECKING:
    from bench.models.lozenge import LozengeParams
    from bench.models.membrane import MembraneParams
    from bench.runtime.sim_rig import SimRig

log = logging.getLogger(__name__)
SIM_MODBUS_POLL_S = 5e-5  # RTU receive poll interval against twins on ptys (they answer at once)


@dataclass
class Plan:
    """A protocol checked against a rig: everything known before an instrument is touched."""

    protocol: Protocol
    rig: RigConfig
    program: Program
    prediction: Prediction
    link_problems: list[str] = field(default_factory=list)  # what the rig's lines cannot carry (see plan_run)
    shortfalls: list[str] = field(default_factory=list)  # streams recorded below the asked rate (software-timed rigs)
    rig_text: str = ""  # the rig file as written (comments, order): recorded, the source of a fitted rig


def resolve_rig(protocol: Protocol, rig_path: str | Path | None = None, simulate: bool = False) -> RigConfig:
    """The rig to run on: ``rig_path`` or the protocol's rig; ``simulate`` makes it the simulated twin."""
    return _resolve_rig(protocol, rig_path, simulate)[0]


def _resolve_rig(protocol: Protocol, rig_path: str | Path | None, simulate: bool) -> tuple[RigConfig, str]:
    """(:func:`resolve_rig`, the rig file's text: the simulated twin keeps the file's text)."""
    if rig_path is None and not protocol.rig_path().is_file():  # named by the protocol: said so, with its field
        ref = protocol.protocol.rig
        raise ProtocolFileError(f"protocol file {protocol.path}: protocol.rig = {ref!r}: "
                                + missing_rig_ref(Path(protocol.path).parent, ref))
    rig, text = load_rig_text(rig_path if rig_path is not None else protocol.rig_path())
    if simulate and not rig.simulated:
        rig = RigConfig.model_validate({**rig.model_dump(), "simulated": True, "name": f"{rig.name}-simulated"})
    return rig, text


def plan_run(protocol_path: str | Path, rig_path: str | Path | None = None, simulate: bool = False,
             progress: Callable[[float], None] | None = None) -> Plan:
    """Load, validate, compile and dry-run a protocol; raise ValueError (one line) if it must not run."""
    protocol = load_protocol(protocol_path)
    rig, rig_text = _resolve_rig(protocol, rig_path, simulate)
    program = compile_program(protocol, rig)
    links = check_links(program)
    if links and not rig.simulated:
        raise ProtocolLimitError(f"protocol file {protocol.path}: {links[0]}")
    prediction = predict(program, progress)
    if prediction.failure:
        raise ProtocolLimitError(f"protocol file {protocol.path}: {prediction.failure}")
    if prediction.problems:
        raise ProtocolLimitError(f"protocol file {protocol.path}: {prediction.problems[0]}")
    return Plan(protocol, rig, program, prediction, links, recording_shortfalls(program), rig_text)


def _streams(rig: RigConfig, inst: Instruments, polled: bool = False) -> tuple[dict[str, list[Column]], dict[str, str]]:
    """The recorder's layout from the instruments' own descriptions (drivers' ``describe()``; on a DAQ-driven rig
    the scans time the amplifier and the analog inputs wired to the DAQ, unless ``polled``: manual control reads
    every instrument on request): the engine's set-points first; the rig names what a displacement measures; the
    engine adds the aperture it derives from the motor position and, on software-timed streams, how late each poll
    ran."""
    measurand = "membrane in-plane displacement u" if rig.specimen.kind == "membrane" else "LS-DEA aperture x"
    described: list[StreamDescription] = []
    if (not polled and rig.daq is not None and inst.amplifier is not None and rig.amplifier
            and rig.amplifier.drive == "daq"):
        described = describe_streams(rig.daq, inst.amplifier)
    timed = {d.stream for d in described}
    described += [drv.describe() for _, drv in inst.readables() if drv.name not in timed]
    streams: dict[str, list[Column]] = {"setpoints": [Column("voltage", "V", "amplifier output commanded"),
                                                      Column("aperture", "m", "LS-DEA aperture commanded (NaN: none)")]}
    sources = {"setpoints": "engine"}
    late = Column("late", "s", "software-timed: how long after its scheduled time the poll ran (NaN: not polled)")
    for d in described:
        cols = [replace(k, description=f"{measurand}, {k.description}") if k.name == "displacement" else k
                for k in d.columns]
        if d.stream == "motor":
            cols.append(Column("aperture", "m", "LS-DEA aperture from the motor position"))
        streams[d.stream] = cols + ([] if d.stream in timed else [late])
        sources[d.stream] = d.source
    if inst.amplifier is not None:
        streams[SAFE_STATE] = safe_state_columns(inst.motor is not None)
        sources[SAFE_STATE] = ("engine: the shutdown's verifying reads of the voltage and current monitors (command-"
                               "response: a DAQ's stream has stopped)" + ("; the motor's position once at rest"
                                                                          if inst.motor is not None else ""))
    return streams, sources


def safe_state_columns(motor: bool) -> list[Column]:
    """The columns of the :data:`SAFE_STATE` stream: the measured state the shutdown left the rig in."""
    return [Column("voltage", "V", "output voltage from the voltage monitor, read by the shutdown to verify 0 V "
                   "(NaN: unreadable)"),
            Column("current", "A", "output current from the current monitor, read with it"),
            *([Column("position", "m", "motor position read once the carriage came to rest after the stop (the "
                      "motor event; NaN: not read)")] if motor else [])]


def default_output(plan: Plan, out_dir: str | Path) -> Path:
    """runs/<protocol>-<YYYYmmdd-HHMMSS>.h5, or the first free :func:`numbered` name after it (a name, not a claim:
    :func:`reserve_output` claims it)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", plan.protocol.protocol.name)
    path = Path(out_dir) / f"{safe}-{stamp}.h5"
    k = 0
    while numbered(path, k).exists():
        k += 1
    return numbered(path, k)


def numbered(path: Path, k: int) -> Path:
    """``path`` (k = 0), else ``NAME-k.h5`` beside it."""
    return path if k == 0 else path.with_name(f"{path.stem}-{k}{path.suffix}")


def reserve_output(path: Path) -> Path:
    """The run file a new run writes: ``path``, or the next free :func:`numbered` name when another run took it
    since it was named. The claim is the run's log file (``RUN.log``, which every run writes), created here
    exclusively: two runs started in one second into one folder named the same file, and one's data was lost
    (the Recorder also never overwrites a file). OSError (one line, naming the file) when the folder cannot take it."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        k = 0
        while True:
            candidate = numbered(path, k)
            if not candidate.exists():
                try:
                    os.close(os.open(candidate.with_suffix(".log"), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
                    return candidate
                except FileExistsError:
                    pass
            k += 1
    except OSError as exc:
        raise OSError(f"run file {path}: cannot create its folder or log ({exc.strerror or exc})") from None


def check_watchdog(rig: RigConfig, allow_no_watchdog: bool = False) -> str:
    """Refuse a rig whose voltage set-point module has no communication watchdog, unless overridden.

    The watchdog is the last line of defence when the host cannot command 0 V (lost bus, failed module,
    crashed host). Returns the line the run file records about it. This checks the rig file; the drivers check the
    module at connect (the ADAM-4024's enable register 40215, :meth:`drivers.trek.TrekAmplifier.connect`; the T7's
    settings read back, :mod:`drivers.labjack.watchdog`) and refuse one that reports it off.
    """
    amp = rig.amplifier
    if amp is None:
        return "no amplifier"
    period = watchdog_period(rig)
    module, field = (("LabJack T7", "daq.watchdog_s") if amp.drive == "daq"
                     else ("ADAM-4024", "amplifier.comm_watchdog_s"))
    if period is not None:
        return f"{module} communication watchdog {period:g} s"
    if not allow_no_watchdog:
        raise ValueError(f"rig {rig.name}: {field} is not set — without the set-point module's "
                         "communication watchdog nothing zeroes the high voltage if the host loses the bus; "
                         "configure it (and the module), or pass --allow-no-watchdog to run anyway (recorded)")
    return "NO communication watchdog: run allowed by an explicit override (--allow-no-watchdog)"


def run_metadata(protocol: Protocol, operator: str | None = None, specimen_id: str | None = None,
                 notes: list[str] | None = None) -> dict[str, str]:
    """Who ran it, on which specimen, and the notes: the ``[protocol]`` fields, ``operator`` and ``specimen_id``
    replacing the file's, ``notes`` added after the file's; ValueError (one line naming the option) if one is empty,
    not one line of printable text, or too long.

    Returned as the run file's root attributes ``operator``, ``specimen_id`` and ``notes`` (one note per line);
    absent ones are left out."""
    head = protocol.protocol
    out: dict[str, str] = {}
    for key, option, given, limit in (("operator", "--operator", operator, MAX_OPERATOR),
                                      ("specimen_id", "--specimen-id", specimen_id, MAX_SPECIMEN_ID)):
        if given is not None:
            try:
                out[key] = check_label(given, limit)
            except ValueError as exc:
                raise ValueError(f"{option}: {exc}") from None
        elif getattr(head, key) is not None:
            out[key] = getattr(head, key)
    try:
        all_notes = head.note_list() + (check_notes(notes) if notes else [])
        if all_notes:
            out["notes"] = "\n".join(check_notes(all_notes))
    except ValueError as exc:
        raise ValueError(f"--note: {exc}") from None
    return out


def execute(plan: Plan, out: Path, *, virtual: bool = False, operator: OperatorFn | None = None,
            on_engine: Callable[[Engine, Any], None] | None = None, allow_no_watchdog: bool = False,
            metadata: dict[str, str] | None = None, resume: Resume | None = None) -> RunResult:
    """Connect the rig (starting its twins if simulated), record, run; returns how the run ended.

    A real rig's instruments are claimed first (:func:`~bench.runtime.rig_lock.claimed`): RigInUseError, before
    anything is touched, while another process drives one of them.
    Errors while connecting (before anything is recorded) propagate as InstrumentError.
    ``on_engine(engine, sim)`` is called before the run starts (sim: the SimRig, or None for a real rig).
    ``metadata``: operator, specimen ID and notes (:func:`run_metadata`; default: the protocol file's).
    ``resume``: continue the campaign of an earlier file from its first step that did not complete
    (:func:`plan_resume`); the new file is linked to it. The run's control file (``bench pause``) is
    :func:`~bench.runtime.control.control_path` of ``out``.
    """
    with claimed(plan.rig), campaign_claimed(resume.previous) if resume is not None else contextlib.nullcontext():
        if resume is not None and (later := continued_in(resume.previous)) is not None:  # resumed since it was planned
            raise ValueError(f"run file {resume.previous}: its campaign was already resumed in {later}: resume the "
                             "campaign's latest file instead")
        return _execute_claimed(plan, out, virtual=virtual, operator=operator, on_engine=on_engine,
                                allow_no_watchdog=allow_no_watchdog, metadata=metadata, resume=resume)


def _execute_claimed(plan: Plan, out: Path, *, virtual: bool, operator: OperatorFn | None,
                     on_engine: Callable[[Engine, Any], None] | None, allow_no_watchdog: bool,
                     metadata: dict[str, str] | None, resume: Resume | None) -> RunResult:
    """:func:`execute` with the rig's instruments claimed."""
    rig, program = plan.rig, plan.program
    meta = metadata if metadata is not None else run_metadata(plan.protocol)
    if virtual and not rig.simulated:
        raise ValueError(f"rig {rig.name} is real: virtual time needs a simulated rig (use --sim)")
    watchdog = check_watchdog(rig, allow_no_watchdog)
    drive = drive_of(rig)  # its port's names now, while it is there: a latch written after a lost adapter keeps them
    pending = resume.reset if resume is not None else None  # the operator's reset of a latch: once connected
    seen = resume.reset_seen if resume is not None else frozenset()
    _state_writable()  # before anything: a run that cannot arm its interlock writes no run file
    if pending is None:
        refuse_if_latched(rig.name, drive)
    else:  # the reset is for the latch seen when the resume was planned: a later one refuses
        refuse_if_changed(rig.name, drive, seen)
    reset_done = False
    sim: SimRig | None = None
    inst: Instruments | None = None
    recorder: Recorder | None = None
    start_row: threading.Thread | None = None
    end_row: dict[str, Any] | None = None  # the catalogue's end row, once the file has its end (record_end's args)
    marker: Path | None = None  # the armed marker (latch.arm), once the engine is about to run
    try:
        # until the engine has its own handlers a stop signal raises (naming what was under way), and the rig is made
        # safe below; from engine.run() on the engine's shutdown does that
        try:
            with termination_raises("loading the host's kernels") as phase:
                if rig.daq is not None:
                    hardware_timed.warm_up()  # the host's kernels, before any instrument (or twin) runs
                clock: Clock
                if rig.simulated:
                    phase.what = "starting the simulated rig"
                    sim, meta = _start_sim(plan, virtual, meta)
                    clock = sim.clock
                    inst = build_instruments(rig, sim.port_map(), clock=clock.now, sleep=clock.sleep,
                                             modbus_poll=SIM_MODBUS_POLL_S, timers=sim.reply_timers(),
                                             wire_time=sim.wire_time)
                else:
                    clock = WallClock()
                    inst = build_instruments(rig, clock=clock.now, sleep=clock.sleep)
                phase.what = "connecting the instruments"
                log.info("connecting the instruments of %s", rig.name)
                for _, drv in inst.items():
                    drv.connect()
                if pending is not None:  # the start got past connecting: the resume's reset now, not before
                    reset(rig.name, pending[0], pending[1], drive, seen)
                    reset_done = True
                if inst.motor is not None and program.has_motor_axis:
                    phase.what = "enabling and homing the motor"
                    log.info("enabling and homing the motor")
                    inst.motor.enable()
                phase.what = "creating the run file"
                spec = rig.specimen
                over = plan.protocol.specimen  # the protocol's prototype and hung mass: the limits follow them
                params = spec.membrane() if spec.kind == "membrane" else spec.lozenge(over.prototype,
                                                                                       over.hung_mass_kg)
                if sim is not None:
                    params = sim.plant.specimen
                supervisor = Supervisor(rig, params)
                streams, sources = _streams(rig, inst)
                r = plan.protocol.recording
                rates = {"setpoints": r.setpoint_Hz, "amplifier": r.monitors_Hz, "laser": program.laser_Hz,
                         "motor": r.position_Hz, "load_cell": r.force_Hz, SAFE_STATE: 1.0 / MONITOR_REREAD_S,
                         **{role: 1.0 / SENSOR_PERIOD_S for role in inst.sensors}}  # the generic poll (polls.py)
                if rig.daq is not None and rig.amplifier is not None and rig.amplifier.drive == "daq":
                    hw = {"amplifier", *(["load_cell"] if rig.daq.force_ain is not None else []),
                          *(["laser"] if rig.daq.laser_ain is not None else [])}
                    rates.update({k: rig.daq.scan_rate_Hz for k in hw})
                attrs: dict[str, Any] = {
                    "software": f"dea-bench {__version__}", "start_time": now_iso(),
                    "protocol_name": plan.protocol.protocol.name, "protocol_path": str(plan.protocol.path),
                    "protocol_text": plan.protocol.text, "protocol_sha256": plan.protocol.sha256,
                    "rig_name": rig.name, "rig_toml": rig_to_toml(rig), "rig_text": plan.rig_text,
                    "simulated": rig.simulated,
                    "clock": "virtual" if virtual else "wall", "specimen_kind": spec.kind,
                    "specimen": json.dumps({**spec.model_dump(), "overrides": plan.protocol.specimen.model_dump(),
                                            "model": _model_params(params)}),
                    "recording": json.dumps(plan.protocol.recording.model_dump()),
                    "sources": json.dumps(sources), "duration_planned": program.duration, "hv_watchdog": watchdog,
                    "run_id": uuid.uuid4().hex, **meta,
                }
                attrs["campaign_id"] = attrs["run_id"]
                if resume is not None:
                    attrs.update(resume.attrs(out))
                if sim is not None and sim.replay is not None:  # measured signals are a record's, not the model's
                    attrs.update(replay_of=str(sim.replay.recording.path),
                                 replay_of_run_id=sim.replay.recording.run_id)
                prog_rows = [(s.index, s.label, s.name, s.kind, s.t_start, s.duration) for s in program.segments]
                recorder = Recorder(out, attrs, streams, prog_rows, rates, virtual=virtual)
                try:  # until the engine runs, the file's end is this function's to record (the engine's from then on)
                    start_row = _start_row(out, attrs)
                    apply = partial(change_specimen, sim.plant) if sim is not None else None
                    engine = Engine(program, inst, clock, recorder, supervisor, apply_specimen=apply,
                                    operator=operator, start_step=resume.step if resume is not None else 0,
                                    control=control_path(out))
                    if on_engine is not None:
                        on_engine(engine, sim)
                    if sim is not None and sim.replay is not None:
                        sim.replay.anchor(clock.now())  # record time 0 = this run's time 0 (the engine starts now)
                    # from engine.run() on the rig may be energised: a process that dies before its shutdown
                    # verified 0 V leaves this marker, and the next start latches the rig (bench/runtime/latch.py);
                    # armed here, where a marker that cannot be written still ends the file unstarted
                    marker = _arm(rig.name, out, drive)
                    engine.on_paused = partial(note_paused, marker)
                    phase.check()
                except BaseException as exc:  # Ctrl-C included: no file may say "running" for a run that never ran
                    disarm(marker)  # nothing was energised
                    recorder.end_unstarted(exc)
                    end_row = {}
                    raise
        except InstrumentError:
            disarm(marker)  # a stop as the phase ended, past the try above: the engine never ran, nothing energised
            if phase.stopped is None:
                raise
            # a stop signal before the engine ran: the rig is made safe here, and one line says what was done
            safe, inst = _made_safe(inst), None
            if sim is not None:
                sim.stop()
                sim = None
            kept = "nothing recorded" if recorder is None else f"run file {out} ended 'interrupted'"
            done = f"{phase.stopped}; {kept}; {safe}"
            log.info("not run: %s", done)
            raise OperationCancelledError("run", done) from None
        ended: BaseException | None = None
        try:
            result = engine.run()
        except BaseException as exc:
            ended = exc
            raise
        finally:  # a fault latches even when the run ends by an exception the engine let through
            fault = engine.latch_fault
            if fault is None and ended is not None and inst.amplifier is not None and not engine.zero_verified:
                fault = (f"the run ended by {type(ended).__name__}: {' '.join(str(ended).split())} before its "
                         "shutdown verified 0 V")
            try:
                if fault is not None:
                    latch(rig.name, fault, str(out), drive)
            except BaseException:
                release(marker)  # the latch not written: the marker stays, unlocked, and the next look latches
                raise
            disarm(marker)  # 0 V verified, or the rig latched (a rig without an amplifier has no output to verify)
        end_row = {"hv": recorder.hv_stats(), "written": recorder.written()}  # the file, as it was written
        return result
    finally:
        if pending is not None and not reset_done:
            try:
                note(f"reset withheld\t{rig.name}\tby {pending[0]}: {pending[1]}\t(the resumed run did not get "
                     f"past connecting: {_failure()}): the latch stays")
            except OSError as exc:  # an unwritable state folder: the run's own error is the one to see
                log.warning("interlock history not written (%s): reset withheld, the latch stays", exc)
        if inst is not None:
            inst.close()  # first: no wait on the catalogue keeps an instrument open
        if sim is not None:
            sim.stop()
        with contextlib.suppress(OSError):  # its last word (a pause, a stop) meant nothing once the run ended
            control_path(out).unlink(missing_ok=True)
        _catalogue_end(out, start_row, end_row)


def _state_writable() -> None:
    """ValueError (one line, as :func:`_arm`'s) where the state folder cannot take the armed marker — checked
    before the instruments are touched and the run file is made (outside tester: a run with an unwritable state
    folder left a run file whose reason was this error)."""
    folder = state_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-") as probe:
            probe.write(b"\0" * 4096)  # a marker's bytes, on disk: a full disk fails here, not after the run file
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as exc:
        raise ValueError(f"state folder {folder}: the interlock's armed marker cannot be written there "
                         f"({exc.strerror or exc}); nothing was energised — make it writable or set "
                         f"{STATE_ENV} to a writable folder") from None


def _arm(rig_name: str, out: Path, drive: Drive | None) -> Path:
    """The armed marker of this run (:func:`~bench.runtime.latch.arm`); ValueError (one line, naming the state
    folder) where it cannot be written: a run that could die energised without a trace does not start."""
    try:
        return arm(rig_name, os.path.abspath(out), drive)  # (read from any folder: the latch's text, its file's time)
    except OSError as exc:
        raise ValueError(f"state folder {state_dir()}: the interlock's armed marker cannot be written there "
                         f"({exc.strerror or exc}); nothing was energised — make it writable or set "
                         f"{STATE_ENV} to a writable folder") from None


def _failure() -> str:
    """The exception being handled, in one line ("stopped" if none)."""
    exc = sys.exc_info()[1]
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}" if exc is not None else "stopped"


def _start_sim(plan: Plan, virtual: bool, meta: dict[str, str]) -> tuple[SimRig, dict[str, str]]:
    """The rig's twins started (the protocol's specimen applied to the plant), and the run's metadata with how the
    wire is timed. Twins that a signal or an error interrupts while they start are stopped again here."""
    from bench.runtime.sim_rig import SimRig

    # wire time (baud rates, gaps, turnarounds) also in virtual time, so that a virtual run takes the time a real
    # one would — unless the protocol outruns the rig's lines (the plan says which), where a virtual run at wire
    # time would only be late everywhere: then pty speed, as the console and the file say
    timing: Literal["real", "none"] = "real" if not virtual or not plan.link_problems else "none"
    sim = SimRig(plan.rig, virtual=virtual, timing=timing)
    meta = {**meta, "wire_time": "real" if timing == "real" else "off (the protocol outruns the rig's lines)"}
    changes = {k: v for k, v in plan.protocol.specimen.model_dump().items() if v is not None}
    if changes:
        sim.plant.change_specimen(**changes)
    try:
        sim.start()
    except BaseException:
        sim.stop()
        raise
    return sim, meta


def _made_safe(inst: Instruments | None) -> str:
    """Close the instruments after a stop before the run (:meth:`Instruments.close`: each made safe first — output
    zeroed, motor aborted — then closed), and say what that did."""
    if inst is None:
        return "no instrument was connected yet"
    errors = inst.close()
    if not errors:
        return "rig safe: every instrument made safe and closed (output zeroed, motor stopped)"
    return "rig NOT confirmed safe, closing failed: " + "; ".join(errors)


def _catalogue_end(out: Path, start_row: threading.Thread | None, end_row: dict[str, Any] | None) -> None:
    """With the instruments closed: wait for the start row, then write the end row (``end_row``: its arguments;
    None: the run ended by an exception the engine let through, and `bench runs list` reconciles its row from the
    file). Ctrl-C here skips what is left with a warning: the file already holds the run's end."""
    try:
        _join(start_row)  # the end row replaces the start row, never the other way round
        if end_row is not None:
            catalog.record_end(out, **end_row)
    except KeyboardInterrupt:
        catalog.log.warning("run catalogue not written at the end (Ctrl-C; `bench runs list` reconciles it from the "
                            "files)")


# the longest a run's end waits for its start row before writing its end row. A start row later than that (a
# catalogue held by another writer) never replaces the end row (`Catalog.upsert(start=True)`), so the order of the
# rows does not rest on this wait, which only keeps the end row from being written first and then rewritten
START_ROW_WAIT_S = 10.0


def _start_row(out: Path, attrs: dict[str, Any]) -> threading.Thread | None:
    """Catalogue the run's start on a thread of its own (:func:`catalog.record_start`: never raises): its
    synchronous commit overlaps the run's first steps instead of holding them up. Where no thread can be started
    (process or memory limits) the row is written here: a run never depends on its catalogue."""
    row = threading.Thread(target=catalog.record_start, args=(out, dict(attrs)), name="catalogue start row",
                           daemon=True)
    try:
        row.start()
    except RuntimeError:
        catalog.record_start(out, attrs)
        return None
    return row


JOIN_SLICE_S = 0.1  # the wait for the start row returns to Python this often: see _join


def _join(row: threading.Thread | None) -> None:
    """Wait for the start row's thread, at most :data:`START_ROW_WAIT_S`, in slices of :data:`JOIN_SLICE_S`: a
    Ctrl-C that the kernel gave another thread of the process does not wake a thread blocked in one long join, and
    Python runs the handler only when the main thread gets back to Python (tests/test_catalog.py sends the signal to
    the start row's thread: one long join waits the row out)."""
    if row is None:
        return
    deadline = time.monotonic() + START_ROW_WAIT_S
    while row.is_alive():
        left = deadline - time.monotonic()
        if left <= 0:
            return
        row.join(min(left, JOIN_SLICE_S))


@dataclass
class Resume:
    """Where a crashed or interrupted campaign goes on: the earlier file, its run and campaign IDs, and the
    first step that did not complete there."""

    previous: Path
    run_id: str
    campaign_id: str
    step: int
    steps: int
    reset: tuple[str, str] | None = None  # (who, why): the operator's reset of the rig's latch, done once connected
    reset_seen: frozenset[str] = frozenset()  # the latches (latch.latch_key) that reset is for: those seen at planning

    def attrs(self, out: Path) -> dict[str, Any]:
        """The new file's link to the earlier one (``previous_file`` relative to the new file's folder)."""
        try:
            rel = os.path.relpath(self.previous.resolve(), out.resolve().parent)
        except ValueError:  # another drive (Windows)
            rel = str(self.previous.resolve())
        return {"previous_file": rel, "previous_run_id": self.run_id, "campaign_id": self.campaign_id,
                "resumed_at_step": self.step}


def plan_resume(run_file: str | Path, rig_path: str | Path | None = None, simulate: bool = False,
                progress: Callable[[float], None] | None = None) -> tuple[Plan, Resume, list[str]]:
    """Plan the rest of the campaign of ``run_file``: recover it if a crash left it open (one that ``bench recover``
    already released is resumed as it is), re-plan its stored protocol on its stored rig (or ``rig_path``), and
    find the first step that did not complete. Returns the plan, the link, and what was done to the file (recovery
    lines). ValueError (one line) if there is nothing to resume or the file cannot be read."""
    p = Path(run_file)
    notes: list[str] = []
    run = open_run(p, streams=False)
    if (why := _not_a_campaign(p, run)) is not None:  # before a crashed file is recovered: nothing is touched
        raise ValueError(f"run file {p}: {why}")
    if run.state == "running" and run.orphaned:
        notes = recover(p).lines()
        run = open_run(p, streams=False)
    elif run.state == "running" and not run.recovered_at:  # recovered: `bench recover` found no writer (a crash)
        raise ValueError(f"run file {p}: a run is still writing it (stop it first, or pause it with bench pause)")
    stored = str(run.attrs.get("protocol_path", ""))
    with tempfile.TemporaryDirectory() as tmp:
        proto = Path(tmp) / (Path(stored).name or "protocol.toml")
        proto.write_text(str(run.attrs["protocol_text"]), encoding="utf-8")
        rig_file = Path(rig_path) if rig_path is not None else Path(tmp) / "rig.toml"
        if rig_path is None:
            rig_file.write_text(str(run.attrs["rig_toml"]), encoding="utf-8")
        try:
            plan = plan_run(proto, rig_file, simulate, progress)
        except ValueError as exc:  # named by the run file, not by this folder's copies (deleted): a refusal of a
            text = str(exc).replace(str(proto), f"the protocol stored in {p}")  # --rig named a temporary file
            if rig_path is None:  # (an outside tester)
                text = text.replace(str(rig_file), f"the rig stored in {p}")
            raise _same_kind(exc, text) from None
    if plan.protocol.sha256 != run.attrs["protocol_sha256"]:
        raise ValueError(f"run file {p}: its stored protocol no longer reads the same (hash differs)")
    if stored:  # the protocol file the campaign was planned from, not the temporary copy planned here (deleted)
        plan.protocol = plan.program.protocol = plan.protocol.model_copy(update={"path": stored})
    done: set[int] = set()  # over the whole campaign: a resumed file holds only the steps from its start on
    for link in chain(p):
        done |= open_run(link.path, streams=False).completed_steps()
    indices = [s.index for s in plan.program.segments]
    todo = next((k for k, i in enumerate(indices) if i not in done), None)
    if todo is None:
        raise ValueError(f"run file {p}: every step completed ({run.state}): nothing to resume")
    rid = str(run.attrs.get("run_id", "")) or p.stem
    resume = Resume(p, rid, str(run.attrs.get("campaign_id", "")) or rid, todo, len(indices))
    return plan, resume, notes


def _same_kind(exc: ValueError, text: str) -> ValueError:
    """``exc``'s kind of error (a protocol file's or its limits') with ``text``, else a ValueError."""
    try:
        return type(exc)(text)
    except TypeError:
        return ValueError(text)


def _not_a_campaign(p: Path, run: RunFile) -> str | None:
    """Why run file ``p`` is no campaign that can be resumed (a manual-control session, a file without its protocol
    and rig, a campaign already continued elsewhere), or None."""
    if run.attrs.get("session_log") or run.attrs.get("mode") == "manual control":
        return "a manual-control session, not a protocol run: nothing to resume"
    for key in ("protocol_text", "rig_toml", "protocol_sha256"):
        if not str(run.attrs.get(key, "")):
            return f"no {key} attribute: not a run file this version can resume"
    if (later := continued_in(p)) is not None:  # a second resume would fork the campaign into two chains
        return f"its campaign was already resumed in {later}: resume the campaign's latest file instead"
    return None


def resume_refusal(run_file: str | Path, run: RunFile | None = None) -> str | None:
    """Why ``bench run --resume`` cannot continue the campaign of ``run_file`` (the line's tail after "run file
    …: "), or None if it may (it plans the rest and checks again). From the files alone, without planning: quick
    enough to decide whether a hint may suggest it."""
    p = Path(run_file)
    run = run if run is not None else open_run(p, streams=False)
    if (why := _not_a_campaign(p, run)) is not None:
        return why
    done: set[int] = set()
    for link in chain(p):
        done |= open_run(link.path, streams=False).completed_steps()
    # the file's program holds the campaign's steps from its own start on; those before it completed earlier
    left = {int(i) for i in run.program["index"]} - done if len(run.program) else {-1}
    return None if left else f"every step completed ({run.state}): nothing to resume"


def _model_params(params: MembraneParams | LozengeParams) -> dict[str, Any]:
    out: dict[str, Any] = json.loads(json.dumps(asdict(params), default=lambda o: asdict(o)
                                                if hasattr(o, "__dataclass_fields__") else str(o)))
    return out


def run_protocol(protocol_path: str | Path, *, rig_path: str | Path | None = None, simulate: bool = False,
                 virtual: bool = False, out_dir: str | Path = "runs", out: Path | None = None,
                 operator: OperatorFn | None = None) -> RunResult:
    """Plan and execute in one call (used by tests and ``bench demo``)."""
    plan = plan_run(protocol_path, rig_path, simulate)
    t0 = time.perf_counter()
    result = execute(plan, out or default_output(plan, out_dir), virtual=virtual, operator=operator)
    result.wall_time = time.perf_counter() - t0
    return result
