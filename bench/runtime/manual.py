"""Manual control of a rig's instruments on the one executor, every action in a session log.

A session is the command parser, log and prompt on top of the engine in manual mode
(:class:`~bench.runtime.manual_mode.ManualEngine`, labscript BLACS's ``transition_to_manual`` as the model): each
set-point, ramp, move, pause, reading, stop signal and the session's end go through the code a run uses.

Commands (one per line; ``#`` starts a comment; quantities as in files, plain numbers in the unit shown):

    voltage V                    set the amplifier output (e.g. ``voltage 3kV``)
    ramp V DURATION              ramp from the present set-point to V over DURATION (20 set-points per second)
    zero                         output to 0 V at once
    move POSITION [SPEED]        motor position [mm], not the aperture, at SPEED [mm/s] (20 mm/s; ≤ rig's limit)
    move motor POSITION [SPEED]  the same, said explicitly
    move aperture X [SPEED]      motor to where the LS-DEA aperture is X [mm] (a protocol move step's position)
    jog DELTA [SPEED]            motor position by DELTA [mm] from where it is
    stop                         stop the motor
    tare | zero-cell             load cell: tare (net = 0) or zero (gross = 0)
    read                         read every channel once
    watch DURATION [EVERY]       read every channel every EVERY [s] (default 0.5 s) for DURATION [s]
    wait DURATION                let time pass
    reset WHY...                 clear a latched interlock (the reason and the --operator name are logged)
    pause | resume               output ramped to 0 V and held there, motor stopped | high voltage allowed again
    help | quit

Motor coordinates: ``move POSITION`` and ``jog`` are in the drive's own coordinates (0 … the rig's travel), while a
protocol's move step gives the LS-DEA's aperture (aperture = ``x_at_motor_zero_m`` + ``motor_sign`` × motor
position); ``move aperture X`` takes the protocol's coordinate, and every move's answer names both ("motor position
50.000 mm = aperture 95.000 mm").

Every set-point passes the engine's set-point code: :meth:`bench.runtime.safety.Supervisor.check_setpoint` on the
request and on the value the module will output after DAC rounding (voltage, field at the present stretch), or
:meth:`~bench.runtime.safety.Supervisor.check_motor_setpoint` on the drive's increment (travel, field at the new
aperture); a refused command is not sent. Every reading is one of the run's polls (:mod:`bench.runtime.polls`:
recorded, supervised, the monitors and the encoder verified against what was commanded); a reading beyond a limit
(a trip) zeroes the output and stops the motor. A driver error of any kind, or an unexpected error in a command,
is one ``error`` line (output zeroed, motor stopped; 0 V not commanded latches) and the session goes on; a command
whose instrument the rig lacks is refused (nothing sent).

Latched interlock (:mod:`bench.runtime.interlock`, as in a run): before every write that can drive the output
(set-points, keep-alives, ramps) a host stall is checked — the set-point module unheard for longer than 0.8 × its
communication watchdog while the output was on (a frozen process, a suspended laptop): its watchdog may have
zeroed the output, and the next keep-alive would turn high voltage back on by itself. Every monitor reading is
compared with the voltage commanded (:class:`~bench.runtime.interlock.OutputVerifier`). Either fault zeroes the
output at once (no ramp) and latches: every command that would energise is refused, in one line naming the
fault, until the operator types ``reset WHY…`` (logged with the reason and the ``--operator`` name).

A trip in a script (``--script``, or commands piped in: :meth:`ManualSession.run_lines` with ``stop_on_trip``) — a
latched fault or a limit the supervisor trips on — ends the script there: the commands after it are not run (an
unattended script does not go on after a trip), a ``stopped`` line in the log says so, and the session ends through
its safe exit. So does a command refused because the rig is latched (a session started on a rig a run latched), and
a ``reset`` in a script is refused: an operator who has looked at the rig resets it (outside tester: a script went
on past the latch's refusal and its own ``reset`` re-energised the rig). At a prompt the session goes on (latched:
refusing what would energise until ``reset``).

Pause: ``pause`` (or SIGUSR1, as for a run) is the run's pause — the output ramped to 0 V over the rig's
``shutdown_ramp_s``, the motor stopped — and every set-point but 0 V is refused, in one line, until ``resume`` is typed
(never by a signal: an operator is at the prompt); reading goes on. A SIGUSR1 during a command ends that
command and pauses.

Between commands and in every wait (``wait``, ``watch``, a set-point's settling, a move), while the output is on or
the motor moves, the session is supervised as a run's hold step is (:meth:`ManualEngine.idle`): the keep-alive, and
the rig's polls at their recording rates — a fault trips and latches within two monitor readings with nothing
typed (at the prompt: a ``trip`` line, ``(at the prompt)``; a script stops at it). At 0 V they slow to the
keep-alive's pace. ``voltage`` and ``ramp`` say what the output verifier made of the reading after them (status
``unsettled`` where the monitor is outside the set-point's band).

Readings: every reading of the session (``read``, ``watch``, the monitors after set-points, in ramps and while
energised, the motor during moves) and every set-point sent (keep-alives and the exit ramp included) go to an HDF5
file beside the log (``<log>.h5``; never overwritten: ``<log>-1.h5``…), in a run file's stream layout
(:mod:`bench.storage.recorder`), with one event per log line (commands, refusals, trips, the operator, the
engine's stop account, the exit) and the end state; ``bench inspect`` and :func:`bench.storage.runfile.open_run`
read it. A file that cannot be created ends the session before any command (as a run that cannot create its
file does not start); a storage fault later is one ``error`` line and the session goes on with the log alone.

Leaving the session (quit, end of input, error, a stop signal) is the engine's bounded stop
(:meth:`~bench.runtime.engine.Engine._shut_down`): the motor stopped first, the output ramped to 0 V over
``shutdown_ramp_s`` (at once on a second stop signal or a latched fault), every instrument in its safe state, 0 V
verified on the voltage monitor; the log then has the stop's lines (``request``, why it stopped, ``ramp``,
``motor``, ``safe``) and its last line is the ``end`` line, naming the signal if one ended the session.

Signals (:meth:`ManualSession.signal_handlers`, installed by ``bench devices control``; the engine's handler table,
:func:`~bench.runtime.engine.stop_signals`): SIGTERM, SIGHUP and SIGQUIT end the session through that safe exit,
whatever it is doing. Ctrl-C (SIGINT) at an interactive prompt ends the command under way (``watch``, ``wait``,
``ramp``, ``move``…): the motor is stopped, the output held at the last set-point sent (0 V if paused), and the
prompt comes back; a second Ctrl-C during the same command, or a Ctrl-C at the prompt, ends the session. In script
mode (``--script``, or commands piped in) Ctrl-C ends the session through the safe exit. SIGUSR1 pauses; SIGUSR2
does not resume a manual session (``resume`` is typed).

At a terminal prompt (:func:`prompt_lines`) lines can be edited and ↑/↓ recall earlier commands, through the
stdlib :mod:`readline` where Python has it; the history is kept in ``~/.bench_history`` (the user's home folder,
shared by all the user's sessions and lab folders). Anything that is not a command, an escape sequence
included, is a one-line refusal.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import math
import os
import re
import shlex
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

from bench import __version__
from bench.core.clock import Clock, WallClock
from bench.rig import RigConfig, rig_to_toml
from bench.runtime import latch as rig_latch
from bench.runtime.engine import stop_signals
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.interlock import POLLED_READINGS, InterlockTrip
from bench.runtime.manual_mode import (
    IDLE_MIN_S,
    KEEPALIVE_S,
    RAMP_HZ,
    LatchRefused,
    ManualEngine,
    PauseRequested,
    Refused,
    StopRequested,
    manual_program,
)
from bench.runtime.rig_lock import claimed
from bench.runtime.safety import SafetyTrip, Supervisor
from bench.storage.recorder import Recorder, now_iso
from bench.units import to_si
from drivers.errors import InstrumentError, LimitError, OperationCancelledError, UnsupportedCommandError

DEFAULT_SPEED = 0.02  # m/s
SETTLE_S = 0.3  # after a voltage set-point: the monitors convert at 10 S/s (ADAM-4017+)
HISTORY_FILE = ".bench_history"  # in the user's home folder: what was typed at the interactive prompt
HISTORY_LENGTH = 1000
HELP = "\n".join(line[4:].replace("``", "") for line in (__doc__ or "").splitlines() if line.startswith("    "))
PROMPT = "(at the prompt)"  # the log's command column for what happened between commands

__all__ = ["HELP", "ManualSession", "Outcome", "Refused", "data_path", "prompt_lines", "session_log_name"]


@dataclass
class Outcome:
    """What one command did: status ok | unsettled (a set-point sent, the output not verified on its monitor) |
    refused | trip | error | interrupted | paused, and one line of text."""

    command: str
    status: str
    text: str
    latched: bool = False  # refused because the rig is latched (or a reset a script asked for): a script stops


@dataclass
class ManualSession:
    """A connected rig (its simulated twins started if it is simulated) driven one command at a time by the
    engine in manual mode (:class:`~bench.runtime.manual_mode.ManualEngine`)."""

    rig: RigConfig
    log_file: Path
    virtual: bool = False
    echo: Callable[[str], None] = print
    operator: str | None = None  # who runs the session (in the log's header and the file's attributes)
    specimen_id: str | None = None  # the specimen on the rig (the file's attributes: its history counts the session)
    data_file: Path | None = None  # the readings' HDF5 file (default: beside the log, see data_path)
    outcomes: list[Outcome] = field(default_factory=list)
    engine: ManualEngine | None = None  # the executor, once connected
    _end: str | None = None  # what ended the session before the engine existed (a signal while connecting)
    _sim: Any = None
    _inst: Instruments | None = None
    _claim: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)  # the rig's instruments, held
    _log: TextIO | None = None
    _clock: Clock = field(default_factory=WallClock)
    _t0: float | None = None
    _lock: threading.RLock = field(default_factory=threading.RLock)
    _stop: threading.Event = field(default_factory=threading.Event)
    _keepalive: threading.Thread | None = None
    _interactive: bool = False  # Ctrl-C ends the command under way, not the session
    _scripted: bool = False  # the commands come from a script (run_lines with stop_on_trip): no reset from it
    _outside_pause: str | None = None  # who paused the session from outside it (a signal): a script may not resume
    _ending: bool = False  # leaving the session: making the rig safe
    _rec: Recorder | None = None  # the readings' file (None: not open, or its storage failed)
    _early: list[tuple[float, str, str, str]] | None = field(default_factory=list)  # log lines before the file
    _drive: rig_latch.Drive | None = None  # the amplifier drive's names at the start (while its port is there)
    _told: bool = False  # a fault between commands was made safe and told: no polls until the next command
    _armed: Path | None = None  # the marker that this process may energise the rig (latch.arm), until a safe end
    safe_path: str = ""  # how the session's end made the output safe (its stop's "0 V commanded …; verified: …")

    @property
    def end_reason(self) -> str | None:
        """The stop signal (or exception) that ended the session, if any."""
        if self.engine is not None and self.engine.stop_reason is not None:
            return self.engine.stop_reason
        return self._end

    def _engine(self) -> ManualEngine:
        if self.engine is None:
            raise Refused("not connected")
        return self.engine

    # ------------------------------------------------------------ life cycle
    def __enter__(self) -> ManualSession:
        self.log_file.parent.mkdir(parents=True, exist_ok=True)
        self._log = self.log_file.open("a", encoding="utf-8")
        self._write("session", "start", f"rig {self.rig.name} ({'simulated' if self.rig.simulated else 'real'}, "
                    f"{'virtual' if self.virtual else 'wall'} clock)"
                    + (f", operator {self.operator}" if self.operator else "")
                    + (f", specimen {self.specimen_id}" if self.specimen_id else ""))
        if self.operator:
            self._write("session", "operator", self.operator)
        try:
            self._connect()
        except BaseException as exc:
            self.__exit__(type(exc), exc, None)
            raise
        return self

    def _open_recorder(self, sup: Supervisor) -> Recorder:
        """The readings' file, in a run file's layout (every stream polled: nothing is hardware-timed here)."""
        from bench.runtime.interlock import watchdog_period
        from bench.runtime.run import _model_params, _streams

        assert self._inst is not None
        if self.data_file is None:
            self.data_file = data_path(self.log_file)
        rig, spec = self.rig, self.rig.specimen
        streams, sources = _streams(rig, self._inst, polled=True)
        watchdog = watchdog_period(rig)
        monitors_hz = manual_program(rig).protocol.recording.monitors_Hz
        attrs: dict[str, Any] = {
            "software": f"dea-bench {__version__}", "start_time": now_iso(), "mode": "manual control",
            "protocol_name": "manual control", "protocol_path": "", "protocol_text": "", "protocol_sha256": "",
            "session_log": str(self.log_file), "rig_name": rig.name, "rig_toml": rig_to_toml(rig),
            "simulated": rig.simulated, "clock": "virtual" if self.virtual else "wall", "specimen_kind": spec.kind,
            "specimen": json.dumps({**spec.model_dump(), "model": _model_params(sup.specimen)}),
            "recording": json.dumps({"readings": "on request (read, watch, after set-points) and polled between "
                                                 f"them: while energised at the recording rates (monitors "
                                                 f"{monitors_hz:g} S/s), at 0 V with the motor still at most every "
                                                 f"{KEEPALIVE_S:g} s"}),
            "sources": json.dumps(sources), "duration_planned": 0.0,
            "hv_watchdog": f"communication watchdog {watchdog:g} s" if watchdog is not None else "NO watchdog",
            **({"operator": self.operator} if self.operator else {}),
            **({"specimen_id": self.specimen_id} if self.specimen_id else {}),
        }
        # a file that cannot be created: the session does not start (as a run), one line naming the file
        return Recorder(self.data_file, attrs, streams, [], dict.fromkeys(streams, 0.0))  # 0: irregular

    def _connect(self) -> None:
        rig = self.rig
        if self.virtual and not rig.simulated:
            raise ValueError(f"rig {rig.name} is real: virtual time needs a simulated rig")
        if rig.simulated:
            from bench.runtime.sim_rig import SimRig

            self._sim = SimRig(rig, virtual=self.virtual)
            self._sim.start()
            self._clock = self._sim.clock
            self._inst = build_instruments(rig, self._sim.port_map(), clock=self._clock.now,
                                           sleep=self._clock.sleep, modbus_poll=0.0005,
                                           timers=self._sim.reply_timers(), wire_time=self._sim.wire_time)
        else:  # claimed before any is touched, held until they are closed (one process per instrument)
            self._claim.enter_context(claimed(rig))
            self._inst = build_instruments(rig, clock=self._clock.now, sleep=self._clock.sleep)
        self._t0 = self._clock.now()
        if self._end is not None:  # a stop signal while the twins started
            raise StopRequested(self._end)
        for role, drv in self._inst.items():
            drv.connect()
            self._write("connect", "ok", f"{role}: {drv.identify()}")
        if self._inst.motor is not None:
            self._inst.motor.enable()
        spec = rig.specimen
        params = self._sim.plant.specimen if self._sim is not None else (
            spec.membrane() if spec.kind == "membrane" else spec.lozenge())
        sup = Supervisor(rig, params)
        self._rec = self._open_recorder(sup)
        early, self._early = self._early or [], None
        for t, status, command, text in early:
            self._rec_call(self._rec.event, t, -1, status, f"{command}: {text}")
        engine = ManualEngine(rig, self._inst, self._clock, self._rec, sup, self._t0)
        engine.on_event = lambda kind, text: self._write("session", kind, text)
        if self._end is not None:  # a stop signal while connecting
            engine.request_stop(self._end)
        self.engine = engine
        self._drive = rig_latch.drive_of(rig)  # its port's names while it is there (a lost adapter has fewer)
        was = rig_latch.latched(rig.name, self._drive)
        if was is not None:  # a run or an earlier session latched this rig: it stays off until `reset WHY`
            engine.latched_before(f"{was.get('fault')} (in {was.get('where')}, at {was.get('at')})")
            assert engine.latched is not None
            self._write("interlock", "latched", f"{engine.latch_text()}; {engine.latched.reason}")
            self.echo(f"{engine.latch_text()}: {engine.latched.reason}")
        # from here on the operator may energise the rig: a process that dies before the session's safe end leaves
        # this marker, and the next start latches the rig
        self._armed = rig_latch.arm(rig.name, f"manual session {os.path.abspath(self.log_file)}", self._drive)
        if not self.virtual:  # wall clock: hold the set-point between commands (a human types slowly)
            self._keepalive = threading.Thread(target=self._feed, name="manual-keepalive", daemon=True)
            self._keepalive.start()
        self.echo(f"connected to {rig.name}; limits: ±{sup.voltage_limit:.0f} V, "
                  f"{rig.limits.max_current_A * 1e3:g} mA, ±{rig.limits.max_force_N:g} N"
                  + (f", motor {rig.motor.travel_m[0] * 1e3:g} … {rig.motor.travel_m[1] * 1e3:g} mm"
                     if rig.motor is not None else ""))

    def _feed(self) -> None:
        """Between commands (wall clock): what a run's hold does (:meth:`ManualEngine.idle`) — the set-point re-sent
        every KEEPALIVE_S and, while the output is on or the motor moves, the rig's polls at their rates (current
        limit, output against the commanded band, encoder, load cell); a trip zeroes the output and a fault latches
        at once, without waiting for a command."""
        wait = KEEPALIVE_S
        while not self._stop.wait(wait):
            wait = KEEPALIVE_S
            with self._lock, contextlib.suppress(Refused, StopRequested, PauseRequested):
                engine = self.engine
                if engine is None or self._told or self._leaving(engine):
                    continue
                out: Outcome | None = None
                try:
                    engine.idle()
                    wait = min(KEEPALIVE_S, max(IDLE_MIN_S, engine.idle_due() - engine.now()))
                except InterlockTrip as trip:  # between commands: the operator is told at the prompt
                    out = Outcome(PROMPT, "trip", self._latch(trip))
                except SafetyTrip as exc:  # latched as after a command (a reviewer: at the prompt it did not)
                    out = Outcome(PROMPT, "trip", f"{exc.reason}; {self._trip_made_safe(engine, exc)}")
                except InstrumentError as exc:
                    if self._leaving(engine):
                        # a stop signal cancelled the poll in flight: not a fault. The main thread's stop ramps the
                        # output over shutdown_ramp_s; a make_safe here would drop it in one step and clear the
                        # stop's cancel token (found by review: "wait abandoned: SIGTERM; output zeroed")
                        continue
                    out = Outcome(PROMPT, "error", f"{exc}; {self._made_safe(engine)}")
                except PauseRequested:  # SIGUSR1 at the prompt: paused now, not at the next command
                    out = self._paused("(SIGUSR1 at the prompt)", engine, engine.pause_asked_by())
                except OSError as exc:  # the readings' file: said once, as after a command; the log goes on alone
                    if self._rec is not None:
                        self._storage_failed(exc)
                if out is not None:
                    out.text = _printable(" ".join(out.text.splitlines()))
                    if out.status not in ("paused", "interrupted"):
                        self.outcomes.append(out)  # counted as a command's trip: a script stops at it
                        # made safe (0 V, nothing to keep alive) and told: the next command reads again — not one
                        # more line (and a dead link's timeouts under the session's lock) every 0.25 s meanwhile
                        self._told = True
                    self._write(out.command, out.status, out.text)  # a pause that failed latched or made safe
                    self.echo(f"{out.status}: {out.text}")

    def _leaving(self, engine: ManualEngine) -> bool:
        """The session is ending (a stop asked for, or its stop begun): what the keep-alive thread meets then (a
        cancelled wait, a refused set-point) is the stop's, not a fault — the main thread's stop makes the rig safe."""
        return self._ending or engine.stop_reason is not None or engine.stopping

    def __exit__(self, exc_type: type[BaseException] | None, *_exc: object) -> None:
        self._ending = True
        if self.end_reason is None and exc_type is not None and exc_type is not StopRequested:
            self._end = f"ended by {exc_type.__name__}"
        self._stop.set()
        if self._keepalive is not None:
            if self._inst is not None:  # a tick's wait on the bus abandoned now (the stop clears this for its own
                self._inst.cancel.cancel("the session is ending")  # commands): not a fault, as _ending says
            self._keepalive.join(timeout=2.0)
        engine, errors = self.engine, []
        safe = ""
        if engine is not None:
            was_latched = engine.latched is not None
            state = ("interrupted" if self.end_reason else "tripped" if was_latched else "completed")
            # under the session's lock: a tick that outlasted the join (a bus wait that does not look at the cancel)
            # ends first, and nothing of the keep-alive thread (a make_safe, a latch) runs during the stop
            with self._lock:
                try:
                    safe = engine.end(state, self.end_reason or "session ended")
                except Exception as exc:  # the engine's stop reports driver faults; anything else is said
                    errors.append(f"{type(exc).__name__}: {exc}")
                    if self._inst is not None:
                        self._inst.cancel.clear()  # the safe-state commands must go out
                        errors += self._inst.safe_state()
            try:
                if engine.latched is not None and not was_latched:  # a stall seen at the exit
                    engine.latched_at = engine.now()  # the engine's stop latched it: the time is the session's end
                    self._latched_line(engine.latched)
                if engine.latched is None and engine.ended[0] == "tripped":  # a limit read in the exit ramp (a
                    # breakdown): latched as a command's trip is (a reviewer: the file said completed, no latch file)
                    trip = InterlockTrip("safety trip", engine.ended[1])
                    engine.latched, engine.latched_at = trip, engine.now()
                    self._latched_line(trip)
                if engine.latched is None and not engine.zero_verified and self._inst is not None \
                        and self._inst.amplifier is not None:  # the end did not verify 0 V (it raised): latched here
                    trip = InterlockTrip("output not verified", f"the session's end did not verify 0 V "
                                         f"({'; '.join(errors) or safe or 'no reading'})")
                    engine.latched, engine.latched_at = trip, engine.now()
                    self._latched_line(trip)
            except BaseException:
                rig_latch.release(self._armed)  # the latch not written: the marker, unlocked, latches at the next look
                self._armed = None
                raise
            rig_latch.disarm(self._armed)  # 0 V verified, or the rig latched
            self._armed = None
            self.safe_path = safe
        elif self._inst is not None:
            self._inst.cancel.clear()
            errors += self._inst.safe_state()
        if self._inst is not None:
            errors += self._inst.close()
            self._inst = None
        self._claim.close()
        if self._sim is not None:
            self._sim.stop()
            self._sim = None
        end = ((f"{self.end_reason}; " if self.end_reason else "") + "instruments safe and closed"
               + (f"; {'; '.join(errors)}" if errors else ""))
        if self._log is not None:
            self._write("session", "end", end)
        if self._rec is not None:
            latched = engine is not None and engine.latched is not None
            ramp_trip = engine is not None and engine.ended[0] == "tripped"  # a trip in the exit ramp: as a run's
            state = ("error" if exc_type not in (None, StopRequested, KeyboardInterrupt) else
                     "tripped" if ramp_trip else
                     "interrupted" if self.end_reason else "tripped" if latched else "completed")
            why = f"{engine.latch_text()}; {end}" if engine is not None and engine.latched is not None else end
            self._rec_call(self._rec.finish, state, f"{why} | {safe}" if safe else why)
            self._rec = None
        if self._log is not None:
            self._log.close()
            self._log = None

    # ------------------------------------------------------------ stop requests
    @contextlib.contextmanager
    def signal_handlers(self, interactive: bool = False) -> Iterator[None]:
        """Within: the engine's signal handlers (:func:`~bench.runtime.engine.stop_signals`; module docstring).

        Enter it before the session and leave it after, so that a signal during the safe exit only cuts the
        exit ramp short. Main thread only (elsewhere it installs nothing)."""
        self._interactive = interactive
        with stop_signals(self._on_signal, self._on_pause, self._on_resume):
            yield

    def _on_signal(self, reason: str, sig: int) -> None:
        """A stop signal, to the engine (which sets flags, cancels the rig's waits and leaves a prompt)."""
        if self._ending and self.engine is not None:  # making the rig safe: a request cuts the exit ramp short
            self.engine.urgent()
            return
        if self.engine is None:  # still connecting
            if self._end is None:
                self._end = reason
            if self._inst is not None:
                self._inst.cancel.cancel(reason)
            return
        self.engine.on_stop_signal(reason, sig)

    def _on_pause(self, by: str) -> None:
        if self.engine is not None:
            self.engine.request_pause(by)

    def _on_resume(self, by: str) -> None:
        """SIGUSR2 resumes a run, not a manual session: there ``resume`` is typed by the operator at the prompt
        (a signal would also override a pause asked for and not yet taken)."""

    # ------------------------------------------------------------ log
    def _now(self) -> float:
        return self._clock.now() - self._t0 if self._t0 is not None else 0.0

    def _write(self, command: str, status: str, text: str) -> None:
        """One log line; also an event in the readings' file (but a watch's readings: they are in its streams)."""
        t = self._now()
        if command != "watch":
            if self._rec is not None:
                self._rec_call(self._rec.event, t, -1, status, f"{command}: {text}")
            elif self._early is not None:  # before the file opens: replayed into it then
                self._early.append((t, status, command, text))
        if self._log is None:
            return
        stamp = datetime.now().astimezone().isoformat(timespec="milliseconds")
        self._log.write(f"{stamp}\tt={t:.3f} s\t{status}\t{command}\t{text}\n")
        self._log.flush()

    # ------------------------------------------------------------ readings' file
    def _rec_call(self, fn: Callable[..., object], *args: Any) -> None:
        """A recorder call (one thread at a time); a storage fault is one error line, then the log goes on alone."""
        with self._lock:
            if self._rec is None:
                return
            try:
                fn(*args)
            except OSError as exc:
                self._storage_failed(exc)

    def _storage_failed(self, exc: OSError) -> None:
        self._rec = None  # the recorder stays silent after its first failure; the engine's writes with it
        self._write("readings", "error", f"{exc}; the session goes on, readings in this log only")
        self.echo(f"error: {exc}; readings in the session log only")

    # ------------------------------------------------------------ commands
    def run_lines(self, lines: Iterable[str], stop_on_trip: bool = True) -> list[Outcome]:
        """Execute commands until ``quit``, the end or a stop signal; after a trip, stop if ``stop_on_trip`` (a
        script: an unattended session does not go on after a trip), saying so in the log and to the operator."""
        it = iter(lines)
        engine = self._engine()
        self._scripted = stop_on_trip
        checked = len(self.outcomes)  # outcomes looked at for a trip (a command's, or one between commands)
        try:
            while self.end_reason is None:
                with engine.prompt():  # a stop signal while waiting for a line leaves the wait at once
                    raw = next(it, None)
                if raw is None:
                    break
                line = raw.split("#", 1)[0].strip()
                if not line or self.end_reason is not None:
                    continue
                if line in ("quit", "exit"):
                    break
                # a trip between commands (the keep-alive thread's polls) stops a script too: the (re-entrant) lock
                # held from the check through the command, so no trip comes between them
                with self._lock:
                    trips = [o for o in self.outcomes[checked:] if o.status == "trip"]
                    checked = len(self.outcomes)
                    if not trips and self._outside_pause is not None and engine.paused:  # paused between the
                        # script's lines (the keep-alive thread's pause is no command's outcome): its next lines
                        # were refused one by one and the script ran on to "completed" (a reviewer)
                        trips = [Outcome("(between the script's lines)", "paused", "")]
                    if not (trips and stop_on_trip):
                        self.execute(line)
                        trips += [o for o in self.outcomes[checked:] if o.status in ("trip", "paused") or o.latched]
                        checked = len(self.outcomes)
                if trips and stop_on_trip:
                    why = {"trip": "trip", "paused": "pause"}.get(trips[0].status, "refusal")
                    text = (f"the script stops at the {why} of '{trips[0].command}': the commands after it are not "
                            "run (an unattended script does not go on after a trip, an operator's pause or on a "
                            "latched rig); the session ends through its safe exit")
                    self._write("session", "stopped", text)
                    self.echo(f"stopped: {text}")
                    if self._end is None and why != "trip" and engine.latched is None:  # a trip or a latch says
                        # so in the end state; a pause must too: the file read "completed", the script not run out
                        by = f" ({self._outside_pause} paused the session)" if self._outside_pause else ""
                        self._end = (f"the script stopped at the {why} of '{trips[0].command}'{by}; the commands "
                                     "after it were not run")
                    break
        except StopRequested:
            pass
        finally:
            close = getattr(it, "close", None)
            if close is not None:  # a prompt saves its history now, not when collected
                close()
        return self.outcomes

    def execute(self, line: str) -> Outcome:
        """Run one command; log and return its outcome (refusals, trips, errors, stops and pauses are outcomes).

        Whatever a command raises (a driver's error of any class included) becomes one line; only
        KeyboardInterrupt and SystemExit pass."""
        shown = _printable(line)
        engine = self.engine
        self._told = False  # the keep-alive thread's polls go on after this command
        # the lock is held until the outcome is handled: the keep-alive thread cannot re-send a set-point between
        # a command's error (or trip) and its handler's make_safe or latch
        with self._lock:
            try:
                words = _join_units(shlex.split(line))
                if not words:
                    raise Refused("empty command")
                name, args = words[0].lower(), words[1:]
                handler = getattr(self, f"_cmd_{name.replace('-', '_')}", None)
                if handler is None:
                    raise Refused(f"unknown command '{_printable(words[0])}' (help lists them)")
                try:
                    inspect.signature(handler).bind(*args)
                except TypeError:
                    raise Refused(f"wrong arguments for '{_printable(words[0])}' (help lists them)") from None
                engine = self._engine()
                engine.interruptible = self._interactive
                try:
                    said = handler(*args) or ""
                finally:
                    engine.interruptible = False
                out = Outcome(shown, *said) if isinstance(said, tuple) else Outcome(shown, "ok", said)
            except (StopRequested, OperationCancelledError) as exc:
                assert engine is not None
                if self.end_reason is not None:
                    out = Outcome(shown, "interrupted", f"{self.end_reason}: the session ends")
                elif engine.interrupted is not None:
                    out = Outcome(shown, "interrupted", engine.end_interrupt())
                else:  # a cancelled wait nobody asked for
                    out = Outcome(shown, "error", f"{exc}; {self._made_safe(engine)}")
            except PauseRequested:
                assert engine is not None
                out = self._paused(shown, engine, engine.pause_asked_by())
            except (Refused, ValueError, LimitError) as exc:
                out = Outcome(shown, "refused", str(exc), latched=isinstance(exc, LatchRefused))
            except InterlockTrip as trip:
                out = Outcome(shown, "trip", self._latch(trip))
            except SafetyTrip as exc:
                assert engine is not None
                out = Outcome(shown, "trip", f"{exc.reason}; {self._trip_made_safe(engine, exc)}")
            except InstrumentError as exc:
                assert engine is not None
                out = Outcome(shown, "error", f"{exc}; {self._made_safe(engine)}")
            except OSError as exc:  # the readings' file (drivers raise InstrumentErrors): the log goes on alone
                self._storage_failed(exc)
                out = Outcome(shown, "error", f"{exc}; the session goes on, readings in this log only")
            except Exception as exc:  # a program error must not end the session with the output on
                safe = self._made_safe(engine) if engine is not None else "no instruments connected"
                out = Outcome(shown, "error", f"internal error: {type(exc).__name__}: {exc}; {safe}")
            if engine is not None:
                engine.clear_interrupt()
        out.text = _printable(" ".join(out.text.splitlines()))
        self.outcomes.append(out)
        self._write(out.command, out.status, out.text)
        if self._rec is not None:
            self._rec_call(self._rec.flush)  # on disk before the next prompt
        self.echo(f"{out.status}: {out.text}" if out.text else out.status)
        return out

    def _paused(self, shown: str, engine: ManualEngine, by: str) -> Outcome:
        """A pause request (SIGUSR1, or ``bench pause`` on a run) ended the command under way: paused — by someone
        outside the script, whose ``resume`` it then refuses (:meth:`_cmd_resume`)."""
        try:
            out = Outcome(shown, "paused", engine.pause(by))
            self._outside_pause = by
            return out
        except (StopRequested, InstrumentError) as exc:
            if not self._leaving(engine):
                return Outcome(shown, "error", f"pause: {exc}; {self._made_safe(engine)}")
            # a stop signal cut the pause's ramp short: the stop ramps on from there (no make_safe: one step)
            return Outcome(shown, "interrupted", f"pause: {self.end_reason}: the session ends")
        except InterlockTrip as trip:
            return Outcome(shown, "trip", self._latch(trip))
        except SafetyTrip as exc:  # a limit read in the supervised pause ramp (a breakdown): latched, as a command's
            return Outcome(shown, "trip", f"pause: {exc.reason}; {self._trip_made_safe(engine, exc)}")
        except PauseRequested as exc:
            return Outcome(shown, "error", f"pause: {exc}; {self._made_safe(engine)}")
        except OSError as exc:  # the readings' file: the output is made safe all the same
            self._storage_failed(exc)
            return Outcome(shown, "error", f"pause: {exc}; {self._made_safe(engine)}")
        except Exception as exc:  # a program error must not leave the output on
            safe = self._made_safe(engine)
            return Outcome(shown, "error", f"pause: internal error: {type(exc).__name__}: {exc}; {safe}")

    def _made_safe(self, engine: ManualEngine) -> str:
        """``engine.make_safe()``, and where it latched (0 V could not be commanded) the latch recorded as any other:
        the log's ``latched`` line and the rig's latch file, which also refuses runs until a reset."""
        done = engine.make_safe()
        if engine.unproven is not None:
            trip, engine.unproven = engine.unproven, None
            self._latched_line(trip)
            done += "; latched"
        return done

    def _trip_made_safe(self, engine: ManualEngine, exc: SafetyTrip) -> str:
        """A limit trip: :meth:`_made_safe`, then the rig latched for the trip as for any fault (the README's
        standard: a fault latches until an operator resets it), unless making it safe latched it already."""
        done = self._made_safe(engine)
        if engine.latched is None:
            trip = InterlockTrip("safety trip", exc.reason)
            engine.latch(trip)  # holds the output at 0 V just made: nothing energises until `reset WHY`
            self._latched_line(trip)
            done += "; latched"
        # every channel once more, the rig made safe: the file had the force up to the tripping reading and none
        # while the carriage came to rest (a second tester); a channel that fails now is the trip's, said already
        with contextlib.suppress(Exception):
            engine.read_all(math.nan)
        return done

    # ------------------------------------------------------------ latched interlock
    def _latch(self, trip: InterlockTrip) -> str:
        """Latch ``trip`` (the engine zeroes the output at once and holds it), a ``latched`` line in the log and the
        rig's latch file (which also refuses runs until a reset); returns the outcome."""
        done = self._engine().latch(trip)
        self._latched_line(trip)
        return f"{trip.reason}; {done}; latched"

    def _drive_now(self) -> rig_latch.Drive | None:
        """The amplifier drive as the session found it at its start (a lost adapter's port has fewer names now)."""
        return self._drive if self._drive is not None else rig_latch.drive_of(self.rig)

    def _latched_line(self, trip: InterlockTrip) -> None:
        self._write("interlock", "latched", f"{self._engine().latch_text()}; {trip.reason}")
        rig_latch.latch(self.rig.name, trip.reason, str(self.log_file), self._drive_now())

    def _cmd_reset(self, *why: str) -> str:
        engine = self._engine()
        if engine.latched is None:
            raise Refused("no interlock latched: nothing to reset")
        reason = " ".join(why).strip()
        if not reason:
            raise Refused("reset needs a reason: reset WHY... (logged with the operator's name)")
        if self._scripted:  # an operator who has looked at the rig resets it, not a line written before the fault
            raise LatchRefused(f"reset from a script: a latch is reset by an operator at a prompt, or by `bench "
                               f"interlock reset {self.rig.name} --why …` before the script runs again")
        who = self.operator or "an operator not named (no --operator)"
        try:
            rig_latch.reset(self.rig.name, who, reason, self._drive_now())
        except ValueError as exc:  # a latch file it may not remove: the rig stays latched
            raise Refused(str(exc)) from None
        kind = engine.reset_latch()
        return f"interlock ({kind}) reset by {who}: {reason}"

    # ------------------------------------------------------------ pause
    def _who(self, command: str) -> str:
        return f"{self.operator or 'an operator not named (no --operator)'} (`{command}`)"

    def _cmd_pause(self) -> str:
        return self._engine().pause(self._who("pause"))

    def _cmd_resume(self) -> str:
        if self._scripted and self._outside_pause is not None:  # an operator's pause outranks a line written before
            raise LatchRefused(f"resume from a script: the session was paused by {self._outside_pause}, not by the "
                               "script; resume it at a prompt (a script's resume turned high voltage back on "
                               "0.35 s after an operator's SIGUSR1, outside tester)")
        said = self._engine().resume(self._who("resume"))
        self._outside_pause = None
        return said

    # ------------------------------------------------------------ each _cmd_* returns one line of text
    def _cmd_help(self) -> str:
        return "commands: " + "; ".join(line.split("  ")[0].strip() for line in HELP.splitlines())

    def _amp(self) -> Any:
        if self._inst is None or self._inst.amplifier is None:
            raise Refused("this rig has no amplifier")
        return self._inst.amplifier

    def _cmd_voltage(self, value: str) -> str | tuple[str, str]:
        target = to_si(value, "V")
        self._amp()  # refused on a rig without one, before anything is sent or kept alive
        engine = self._engine()
        sent = engine.reach(target)
        return self._settled(f"set-point {sent:.0f} V")

    def _cmd_ramp(self, value: str, duration: str) -> str | tuple[str, str]:
        target, seconds = to_si(value, "V"), to_si(duration, "s")
        if not 0 < seconds <= 3600:
            raise Refused(f"ramp duration {seconds:g} s: give 0 < DURATION ≤ 3600 s")
        start = float(self._amp().commanded)
        engine = self._engine()
        n = engine.ramp(target, seconds, RAMP_HZ)
        return self._settled(f"ramped {start:.0f} → {target:.0f} V in {seconds:g} s ({n} set-points)")

    def _settled(self, what: str) -> str | tuple[str, str]:
        """After a set-point: the output let settle (SETTLE_S, at least the verifier's lag: its band is then the
        set-point's alone), every channel read, and the output verifier's judgement of that reading said — ``ok``
        only where the voltage monitor is within the set-point's band; else status ``unsettled``, the reading and
        the band (the interlock latches when it stays out: :data:`~bench.runtime.interlock.POLLED_READINGS`)."""
        engine = self._engine()
        t_sent = engine.now()
        engine.hold(max(SETTLE_S, engine.verifier.lag))
        read = self._cmd_read()
        v = engine.verifier.last
        if v is None or v.t < t_sent:
            return "unsettled", f"{what}, not verified: no valid voltage-monitor reading since it; {read}"
        band = f"{v.lo:.0f} … {v.hi:.0f} V"
        if not v.in_band:
            return "unsettled", (f"{what}, not verified: the voltage monitor reads {v.measured:.0f} V, outside "
                                 f"{band} ({v.bad} of {POLLED_READINGS} readings in a row; the interlock latches at "
                                 f"{POLLED_READINGS}); {read}")
        if not v.settled:
            return "unsettled", f"{what}, not yet settled: the band still spans an earlier set-point ({band}); {read}"
        return f"{what}, verified on the voltage monitor (within {band}); {read}"

    def _cmd_zero(self) -> str:
        self._amp()
        engine = self._engine()
        engine.zero()
        return f"output to {engine.ctx.v_cmd:.1f} V (the set-point sent and recorded: the DAC's code nearest 0 V)"

    def _motor(self) -> Any:
        if self._inst is None or self._inst.motor is None:
            raise Refused("this rig has no motor")
        return self._inst.motor

    def _speed(self, text: str) -> float:
        """The speed asked for; none given: DEFAULT_SPEED, or the rig's limit where that is lower (a speed typed
        beyond the limit is refused by the engine, as a protocol's move step is)."""
        if text:
            return to_si(text, "mm/s")
        m = self.rig.motor
        return min(DEFAULT_SPEED, m.max_velocity_m_per_s) if m is not None else DEFAULT_SPEED

    def _where(self, motor_position: float) -> str:
        """``motor position X mm = aperture Y mm`` (the aperture only where the motor drives an LS-DEA's)."""
        prog = self._engine().program
        text = f"motor position {motor_position * 1e3:.3f} mm"
        if prog.has_motor_axis:
            text += f" = aperture {float(prog.aperture(motor_position)) * 1e3:.3f} mm"
        return text

    def _go(self, target: float, speed: float) -> str:
        self._motor()  # refused on a rig without one
        here = self._engine().move(target, speed)
        return f"{self._where(here)} (target {self._where(target)}); " + self._cmd_read()

    def _cmd_move(self, *args: str) -> str:
        """``move [motor|aperture] POSITION [SPEED]``: a bare POSITION is the motor's (as it always was)."""
        self._motor()
        axis = "motor"
        if args and args[0].lower() in ("motor", "aperture"):
            axis, args = args[0].lower(), args[1:]
        if not 1 <= len(args) <= 2:
            raise Refused("wrong arguments for 'move': move [motor|aperture] POSITION [SPEED] (help lists them)")
        value, speed = to_si(args[0], "mm"), self._speed(args[1] if len(args) == 2 else "")
        if axis == "motor":
            return self._go(value, speed)
        prog = self._engine().program
        if not prog.has_motor_axis:
            raise Refused(f"move aperture: the motor of rig {self.rig.name} does not set an LS-DEA aperture "
                          "(specimen.lsdea.configuration is not \"motor\"); give its position: move motor POSITION")
        return self._go(float(prog.motor_position(value)), speed)

    def _cmd_jog(self, delta: str, speed: str = "") -> str:
        here = float(self._motor().read_position().value)
        return self._go(here + to_si(delta, "mm"), self._speed(speed))

    def _cmd_stop(self) -> str:
        self._motor()
        self._engine().stop_motor()
        return "motor stopped"

    def _cell_command(self, what: str) -> None:
        """The load cell's ``tare`` or ``zero``; a cell that has no such command (a bridge amplifier on the DAQ) is
        a refusal in its driver's words: nothing was sent."""
        try:
            getattr(self._cell(), what)()
        except UnsupportedCommandError as exc:
            raise Refused(str(exc)) from None

    def _cell(self) -> Any:
        if self._inst is None or self._inst.load_cell is None:
            raise Refused("this rig has no load cell")
        return self._inst.load_cell

    def _cmd_tare(self) -> str:
        self._cell_command("tare")
        self._engine().hold(0.2)
        return "load cell tared; " + self._cmd_read()

    def _cmd_zero_cell(self) -> str:
        self._cell_command("zero")
        self._engine().hold(0.2)
        return "load cell zeroed; " + self._cmd_read()

    def _cmd_read(self, due: float = math.nan) -> str:
        """Every channel once (the engine's polls: recorded, supervised, verified); one line with units."""
        assert self._inst is not None
        got, drive = self._engine().read_all(due)
        parts = []
        if self._inst.amplifier is not None:
            parts.append(f"voltage {got['voltage']:.0f} V, current {got['current'] * 1e6:.2f} µA")
        if self._inst.laser is not None:
            parts.append(f"displacement {got['displacement'] * 1e3:.4f} mm" if "displacement" in got
                         else "displacement n/a (no valid reading)")
        if self._inst.motor is not None and drive:
            parts.append(f"motor n/a ({drive})")
        elif self._inst.motor is not None:
            x = got.get("aperture", math.nan)
            parts.append(f"motor {got['position'] * 1e3:.3f} mm"
                         + (f" (aperture {x * 1e3:.2f} mm)" if math.isfinite(x) else ""))
        if self._inst.load_cell is not None:
            parts.append(f"force {got['force']:.3f} N")
        return f"t {self._now():.2f} s: " + ", ".join(parts)

    def _cmd_watch(self, duration: str, every: str = "0.5") -> str:
        seconds, interval = to_si(duration, "s"), to_si(every, "s")
        if not (0 < seconds <= 86_400 and 0.05 <= interval <= seconds):
            raise Refused("watch DURATION [EVERY]: 0 < DURATION ≤ 86400 s, 0.05 s ≤ EVERY ≤ DURATION")
        engine = self._engine()
        n = max(1, int(seconds / interval))
        t_begin = engine.now()
        for k in range(1, n + 1):
            due = t_begin + k * interval
            engine.hold(max(0.0, due - engine.now()))
            line = self._cmd_read(due)
            self._write("watch", "read", line)
            self.echo(line)
        return f"watched {n} readings over {seconds:g} s"

    def _cmd_wait(self, duration: str) -> str:
        seconds = to_si(duration, "s")
        if not 0 <= seconds <= 86_400:
            raise Refused("wait DURATION: 0 … 86400 s")
        self._engine().hold(seconds)
        return f"waited {seconds:g} s"


def _printable(text: str) -> str:
    """``text`` with every control character written as an escape (``\\x1b``): one line, safe in a tab-separated
    log and on a terminal."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def _join_units(words: list[str]) -> list[str]:
    """``["jog", "-5", "mm"]`` → ``["jog", "-5 mm"]``: a unit after a number belongs to it."""
    out: list[str] = []
    for w in words:
        if len(out) > 1 and w and (w[0].isalpha() or w[0] in "µ°Ω%") and _is_number(out[-1]):
            out[-1] = f"{out[-1]} {w}"
        else:
            out.append(w)
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def prompt_lines(prompt: str, history: Path | None = None) -> Iterator[str]:
    """Lines typed at a terminal prompt until end of input (Ctrl-D).

    With the stdlib :mod:`readline` (imported here, so only for a terminal) the line can be edited and ↑/↓ walk
    the history, kept in ``history`` (default ``~/.bench_history``, the last HISTORY_LENGTH lines)."""
    try:
        import readline
    except ImportError:  # a Python without GNU readline / libedit: a plain prompt
        rl = None
    else:
        rl = readline
    path = history if history is not None else Path.home() / HISTORY_FILE
    if rl is not None:
        with contextlib.suppress(OSError):
            rl.read_history_file(path)
        rl.set_history_length(HISTORY_LENGTH)
    try:
        while True:
            try:
                line = input(prompt)
            except EOFError:
                print()
                return
            yield line
    finally:
        if rl is not None:
            with contextlib.suppress(OSError):
                rl.write_history_file(path)


def session_log_name(rig: RigConfig) -> str:
    """Default file name of a session log: ``manual-<rig>-<local time>.log``, the rig's name with every character
    but letters, digits, ``_``, ``.`` and ``-`` replaced (a name with ``/../`` wrote the session outside the lab:
    an outside tester)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", rig.name)
    return f"manual-{safe}-{datetime.now().strftime('%Y%m%d-%H%M%S')}.log"


def data_path(log_file: Path) -> Path:
    """The readings' HDF5 file of a session log: ``<log>.h5`` beside it, or ``<log>-1.h5``… (a log is appended to
    when reused; a file of readings is never overwritten)."""
    path, k = log_file.with_suffix(".h5"), 1
    while path.exists():
        path = log_file.with_name(f"{log_file.stem}-{k}.h5")
        k += 1
    return path
