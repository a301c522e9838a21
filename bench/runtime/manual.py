"""Manual control of a rig's instruments under the run's safety supervisor, every action in a session log.

Commands (one per line; ``#`` starts a comment; quantities as in files, plain numbers in the unit shown):

    voltage V               set the amplifier output (e.g. ``voltage 3kV``)
    ramp V DURATION         ramp from the present set-point to V over DURATION (20 set-points per second)
    zero                    output to 0 V at once
    move POSITION [SPEED]   motor to POSITION [mm] (motor coordinates) at SPEED [mm/s] (default 20 mm/s)
    jog DELTA [SPEED]       motor by DELTA [mm] from where it is
    stop                    stop the motor
    tare | zero-cell        load cell: tare (net = 0) or zero (gross = 0)
    read                    read every channel once
    watch DURATION [EVERY]  read every channel every EVERY [s] (default 0.5 s) for DURATION [s]
    wait DURATION           let time pass
    reset WHY...            clear a latched interlock (the reason and the --operator name are logged)
    help | quit

Every set-point passes :meth:`bench.runtime.safety.Supervisor.check_setpoint` (voltage, field at the present stretch)
or :meth:`~bench.runtime.safety.Supervisor.check_motor_setpoint` (travel, field at the new aperture) before it is
sent; a refused command is not sent. Every reading passes the supervisor's sample checks; a reading beyond a
limit (a trip) zeroes the output and stops the motor. A driver error of any kind, or an unexpected error in a
command, is one ``error`` line (output zeroed, motor stopped) and the session goes on; a command whose
instrument the rig lacks is refused (nothing sent).

Latched interlock (:mod:`bench.runtime.interlock`, as in a run): before every write that can drive the output
(set-points, keep-alives, ramps) a host stall is checked — the set-point module unheard for longer than 0.8 × its
communication watchdog while the output was on (a frozen process, a suspended laptop): its watchdog may have
zeroed the output, and the next keep-alive would turn high voltage back on by itself. Every monitor reading is
compared with the voltage commanded (:class:`~bench.runtime.interlock.OutputVerifier`). Either fault zeroes the
output at once (no ramp) and latches: every command that would energise is refused, in one line naming the
fault, until the operator types ``reset WHY…`` (logged with the reason and the ``--operator`` name).

Readings: every reading of the session (``read``, ``watch``, the monitors after set-points and in ramps, the
motor during moves) and every set-point sent (keep-alives and the exit ramp included) go to an HDF5 file beside
the log (``<log>.h5``; never overwritten: ``<log>-1.h5``…), in a run file's stream layout
(:mod:`bench.storage.recorder`), with one event per log line (commands, refusals, trips, the operator, the
exit) and the end state; ``bench inspect`` and :func:`bench.storage.runfile.open_run` read it. A storage fault
is one ``error`` line; the session goes on with the log alone.

Leaving the session (quit, end of input, error, a stop signal) ramps the output to 0 V over the rig's
``shutdown_ramp_s`` (at once on a second stop signal), stops the motor, puts every instrument in its safe state
and closes it; the log's last line is the ``end`` line, naming the signal if one ended the session.

Signals (:meth:`ManualSession.signal_handlers`, installed by ``bench devices control``): SIGTERM, SIGHUP and
SIGQUIT end the session through that safe exit, whatever it is doing. Ctrl-C (SIGINT) at an interactive prompt
ends the command under way (``watch``, ``wait``, ``ramp``, ``move``…): the motor is stopped, the output held at
the last set-point sent, and the prompt comes back; a second Ctrl-C during the same command, or a Ctrl-C at the
prompt, ends the session. In script mode (``--script``, or commands piped in) Ctrl-C ends the session through
the safe exit, as it did before (then by KeyboardInterrupt, which could cut the safe exit short).

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
import shlex
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

import numpy as np

from bench import __version__
from bench.rig import RigConfig, rig_to_toml
from bench.runtime import latch as rig_latch
from bench.runtime.context import STOP_POLL_S
from bench.runtime.engine import RAMP_STEPS, STOP_SIGNALS
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.interlock import OUTPUT_ON_V, InterlockTrip, OutputVerifier, check_contact, mismatch_trip
from bench.runtime.ramp import ramp_to_zero
from bench.runtime.safety import SafetyTrip, Supervisor
from bench.storage.recorder import Recorder, now_iso
from bench.units import to_si
from drivers.errors import InstrumentError, InstrumentStateError, LimitError, OperationCancelledError

RAMP_HZ = 20.0
DEFAULT_SPEED = 0.02  # m/s
DEFAULT_ACCEL = 0.5  # m/s²
KEEPALIVE_S = 0.25  # set-point refresh while holding (feeds the analog module's communication watchdog)
SETTLE_S = 0.3  # after a voltage set-point: the monitors convert at 10 S/s (ADAM-4017+)
EXIT_RAMP_FROM_V = 50.0  # below this |set-point| the exit zeroes at once (no ramp)
HISTORY_FILE = ".bench_history"  # in the user's home folder: what was typed at the interactive prompt
HISTORY_LENGTH = 1000
HELP = "\n".join(line[4:] for line in (__doc__ or "").splitlines() if line.startswith("    "))


class Refused(Exception):  # noqa: N818 - a refusal is an outcome, not a program error
    """A command the supervisor (or its syntax) does not allow; nothing was sent."""


class Interrupted(Exception):  # noqa: N818 - control flow, not a failure
    """A stop request (Ctrl-C, a stop signal) ended the command under way."""


class SessionEnd(Exception):  # noqa: N818 - control flow, not a failure
    """Raised by a signal handler while the session waits for the next command: leave the prompt now."""


@dataclass
class Outcome:
    """What one command did: status ok | refused | trip | error, and one line of text."""

    command: str
    status: str
    text: str


@dataclass
class ManualSession:
    """A connected rig (its simulated twins started if it is simulated) driven one command at a time."""

    rig: RigConfig
    log_file: Path
    virtual: bool = False
    echo: Callable[[str], None] = print
    operator: str | None = None  # who runs the session (in the log's header)
    data_file: Path | None = None  # the readings' HDF5 file (default: beside the log, see data_path)
    outcomes: list[Outcome] = field(default_factory=list)
    end_reason: str | None = None  # the stop signal (or exception) that ended the session, if any
    _sim: Any = None
    _inst: Instruments | None = None
    _sup: Supervisor | None = None
    _log: TextIO | None = None
    _clock: Callable[[], float] = time.monotonic
    _sleep: Callable[[float], None] = time.sleep
    _t0: float | None = None
    _v_req: float = 0.0  # voltage set-point the operator asked for (re-sent to keep the module's watchdog fed)
    _lock: threading.RLock = field(default_factory=threading.RLock)
    _stop: threading.Event = field(default_factory=threading.Event)
    _keepalive: threading.Thread | None = None
    # stop requests (signal handlers set these and cancel the rig's CancelToken; nothing more)
    _interactive: bool = False  # Ctrl-C ends the command under way, not the session
    _busy: bool = False  # a command is under way
    _idle: bool = False  # waiting for the next command (a stop signal then leaves the wait at once)
    _ending: bool = False  # leaving the session: making the rig safe
    _interrupt: str | None = None  # Ctrl-C: end the command under way
    _urgent: threading.Event = field(default_factory=threading.Event)  # second stop request: 0 V at once
    _verifier: OutputVerifier | None = None  # measured output against what was commanded
    _latched: InterlockTrip | None = None  # the interlock fault that holds high voltage off until `reset`
    _latched_at: float = 0.0  # session time of the latch [s]
    _rec: Recorder | None = None  # the readings' file (None: not open, or its storage failed)
    _early: list[tuple[float, str, str, str]] | None = field(default_factory=list)  # log lines before the file
    _late: float = math.nan  # a watch's reading: how long after its scheduled time it was taken [s]

    # ------------------------------------------------------------ life cycle
    def __enter__(self) -> ManualSession:
        self.log_file.parent.mkdir(parents=True, exist_ok=True)
        self._log = self.log_file.open("a", encoding="utf-8")
        self._write("session", "start", f"rig {self.rig.name} ({'simulated' if self.rig.simulated else 'real'}, "
                    f"{'virtual' if self.virtual else 'wall'} clock)"
                    + (f", operator {self.operator}" if self.operator else ""))
        if self.operator:
            self._write("session", "operator", self.operator)
        try:
            self._connect()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        self._open_recorder()
        return self

    def _open_recorder(self) -> None:
        """The readings' file, in a run file's layout (every stream polled: nothing is hardware-timed here)."""
        from bench.runtime.interlock import watchdog_period
        from bench.runtime.run import _model_params, _streams

        assert self._inst is not None and self._sup is not None
        if self.data_file is None:
            self.data_file = data_path(self.log_file)
        rig, spec = self.rig, self.rig.specimen
        streams, sources = _streams(rig, self._inst, polled=True)
        watchdog = watchdog_period(rig)
        attrs: dict[str, Any] = {
            "software": f"dea-bench {__version__}", "start_time": now_iso(), "mode": "manual control",
            "protocol_name": "manual control", "protocol_path": "", "protocol_text": "", "protocol_sha256": "",
            "session_log": str(self.log_file), "rig_name": rig.name, "rig_toml": rig_to_toml(rig),
            "simulated": rig.simulated, "clock": "virtual" if self.virtual else "wall", "specimen_kind": spec.kind,
            "specimen": json.dumps({**spec.model_dump(), "model": _model_params(self._sup.specimen)}),
            "recording": json.dumps({"readings": "on request (read, watch, after set-points)"}),
            "sources": json.dumps(sources), "duration_planned": 0.0,
            "hv_watchdog": f"communication watchdog {watchdog:g} s" if watchdog is not None else "NO watchdog",
            **({"operator": self.operator} if self.operator else {}),
        }
        early, self._early = self._early or [], None
        try:
            self._rec = Recorder(self.data_file, attrs, streams, [], dict.fromkeys(streams, 0.0))  # 0: irregular
        except OSError as exc:
            self._write("readings", "error", f"{exc}; the session goes on, readings in this log only")
            self.echo(f"error: {exc}; readings in the session log only")
            return
        for t, status, command, text in early:
            self._rec_call(self._rec.event, t, -1, status, f"{command}: {text}")

    def _connect(self) -> None:
        rig = self.rig
        if self.virtual and not rig.simulated:
            raise ValueError(f"rig {rig.name} is real: virtual time needs a simulated rig")
        if rig.simulated:
            from bench.runtime.sim_rig import SimRig

            self._sim = SimRig(rig, virtual=self.virtual)
            self._sim.start()
            clock = self._sim.clock
            self._clock, self._sleep = clock.now, clock.sleep
            self._inst = build_instruments(rig, self._sim.port_map(), clock=clock.now, sleep=clock.sleep,
                                           modbus_poll=0.0005, timers=self._sim.reply_timers())
        else:
            self._inst = build_instruments(rig)
        self._t0 = self._clock()
        for role, drv in self._inst.items():
            drv.connect()
            self._write("connect", "ok", f"{role}: {drv.identify()}")
        if self._inst.motor is not None:
            self._inst.motor.enable()
        spec = rig.specimen
        params = self._sim.plant.specimen if self._sim is not None else (
            spec.membrane() if spec.kind == "membrane" else spec.lozenge())
        self._sup = Supervisor(rig, params)
        self._verifier = OutputVerifier(rig, None)  # polled monitors: manual control plays no stream
        if self._inst.amplifier is not None:  # what connecting left the output at (0 V): the first ramp starts there
            self._verifier.commanded(self._now(), float(self._inst.amplifier.commanded))
        was = rig_latch.latched(rig.name)
        if was is not None:  # a run or an earlier session latched this rig: it stays off until `reset WHY`
            self._latched = InterlockTrip("latched before this session", f"{was.get('fault')} (in "
                                          f"{was.get('where')}, at {was.get('at')})")
            self._latched_at = self._now()
            self._write("interlock", "latched", f"{self._latch_text()}; {self._latched.reason}")
            self.echo(f"{self._latch_text()}: {self._latched.reason}")
        if not self.virtual:  # wall clock: hold the set-point between commands (a human types slowly)
            self._keepalive = threading.Thread(target=self._feed, name="manual-keepalive", daemon=True)
            self._keepalive.start()
        self.echo(f"connected to {rig.name}; limits: ±{self._sup.voltage_limit:.0f} V, "
                  f"{rig.limits.max_current_A * 1e3:g} mA, ±{rig.limits.max_force_N:g} N"
                  + (f", motor {rig.motor.travel_m[0] * 1e3:g} … {rig.motor.travel_m[1] * 1e3:g} mm"
                     if rig.motor is not None else ""))

    def _feed(self) -> None:
        while not self._stop.wait(KEEPALIVE_S):
            with self._lock, contextlib.suppress(InstrumentError, SafetyTrip, Refused):
                if self._inst is not None and self._inst.amplifier is not None and self._v_req != 0.0:
                    try:
                        self._checked_voltage(self._v_req)
                    except InterlockTrip as trip:  # between commands: the operator is told at the prompt
                        self.echo(f"trip: {self._latch(trip)}")

    def _wait(self, seconds: float) -> None:
        """Let ``seconds`` pass on the rig clock, re-sending the set-point every KEEPALIVE_S."""
        end = self._clock() + seconds
        while (left := end - self._clock()) > 0:
            self._check_stop()
            self._sleep(min(left, KEEPALIVE_S))
            if self._v_req != 0.0 and self._inst is not None and self._inst.amplifier is not None:
                self._checked_voltage(self._v_req)
        self._check_stop()

    def __exit__(self, exc_type: type[BaseException] | None, *_exc: object) -> None:
        self._ending = True
        if self.end_reason is None and exc_type is not None and exc_type is not SessionEnd:
            self.end_reason = f"ended by {exc_type.__name__}"
        self._stop.set()
        if self._keepalive is not None:
            self._keepalive.join(timeout=2.0)
        errors: list[str] = []
        if self._inst is not None:
            self._inst.cancel.clear()  # the safe exit's own commands must go out
            errors += self._ramp_down()
            errors += self._inst.safe_state()
            if self._inst.amplifier is not None:
                self._commanded(float(self._inst.amplifier.commanded))
            errors += self._inst.close()
            self._inst = None
        if self._sim is not None:
            self._sim.stop()
            self._sim = None
        end = ((f"{self.end_reason}; " if self.end_reason else "") + "instruments safe and closed"
               + (f"; {'; '.join(errors)}" if errors else ""))
        if self._log is not None:
            self._write("session", "end", end)
        if self._rec is not None:
            state = ("error" if exc_type not in (None, SessionEnd, KeyboardInterrupt) else
                     "interrupted" if self.end_reason else "tripped" if self._latched is not None else "completed")
            self._rec_call(self._rec.finish, state, end if self._latched is None else f"{self._latch_text()}; {end}")
            self._rec = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def _ramp_down(self) -> list[str]:
        """Output from its set-point to 0 V over the rig's ``shutdown_ramp_s`` (cut short by a second stop
        request); the caller then commands 0 V at once. Returns the errors met."""
        amp = self._inst.amplifier if self._inst is not None else None
        v0 = float(amp.commanded) if amp is not None else 0.0
        if amp is None or abs(v0) < EXIT_RAMP_FROM_V:
            return []
        if self._latched is None:
            try:
                self._guard()  # a stall before the exit: the ramp's first set-point would re-energise
            except InterlockTrip as trip:
                self._latch(trip)
        if self._latched is not None:
            self._write("session", "ramp", f"interlock latched ({self._latched.kind}): 0 V at once, no ramp from a "
                        "set-point the output may no longer hold")
            return []
        if self._urgent.is_set():
            self._write("session", "ramp", f"second stop request: {v0:.0f} V to 0 V at once")
            return []
        ramp = self.rig.limits.shutdown_ramp_s
        self._write("session", "ramp", f"from {v0:.0f} V to 0 V over {ramp:g} s")
        t0 = self._clock()

        def pause(offset: float) -> bool:
            while (left := t0 + offset - self._clock()) > 0 and not self._urgent.is_set():
                self._sleep(min(left, STOP_POLL_S))
            try:
                self._guard()
            except InterlockTrip as trip:
                self._latch(trip)
                return False
            return not self._urgent.is_set()

        try:
            if not ramp_to_zero(amp, v0, ramp, pause, self._commanded, RAMP_STEPS):
                why = "interlock latched" if self._latched is not None else "second stop request"
                self._write("session", "ramp", f"{why}: {amp.commanded:.0f} V to 0 V at once")
        except InstrumentError as exc:
            return [f"voltage ramp-down failed: {exc}"]
        return []

    # ------------------------------------------------------------ stop requests
    @contextlib.contextmanager
    def signal_handlers(self, interactive: bool = False) -> Iterator[None]:
        """Within: SIGINT/SIGTERM/SIGHUP/SIGQUIT request a stop (module docstring); the old handlers after.

        Enter it before the session and leave it after, so that a signal during the safe exit only cuts the
        exit ramp short. Main thread only (elsewhere it installs nothing)."""
        self._interactive = interactive
        old: list[tuple[signal.Signals, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for sig, text in STOP_SIGNALS.items():
                def handler(_s: int, _f: FrameType | None, sig: signal.Signals = sig, text: str = text) -> None:
                    self._on_signal(sig, text)

                old.append((sig, signal.signal(sig, handler)))
        try:
            yield
        finally:
            for sig, handler in old:
                signal.signal(sig, handler)

    def _on_signal(self, sig: int, reason: str) -> None:
        """A stop signal: flags, the rig's cancel token, and (at the prompt) leave the prompt; nothing more."""
        if self._ending:  # already making the rig safe: a further request cuts the exit ramp short
            self._urgent.set()
            return
        if (sig == signal.SIGINT and self._interactive and self._busy and self._interrupt is None
                and self.end_reason is None):
            self._interrupt = reason  # end the command, not the session
        elif self.end_reason is None:
            self.end_reason = reason
        else:
            self._urgent.set()
        if self._inst is not None:
            self._inst.cancel.cancel(reason)
        if self._idle:
            self._idle = False
            raise SessionEnd(reason)

    def _check_stop(self) -> None:
        if self.end_reason is not None or self._interrupt is not None:
            raise Interrupted(self.end_reason or self._interrupt)

    def _after_interrupt(self) -> str:
        """The command a Ctrl-C ended: traffic let through again, motor stopped, output held; what was done."""
        assert self._inst is not None
        reason, self._interrupt = self._interrupt, None
        self._inst.cancel.clear()
        notes = []
        if self._inst.motor is not None:
            try:
                self._inst.motor.stop()
                notes.append("motor stopped")
            except InstrumentError as exc:
                notes.append(f"motor stop failed: {exc}")
        if self._inst.amplifier is not None:
            self._v_req = float(self._inst.amplifier.commanded)  # held (and kept alive) at the last set-point sent
            notes.append(f"output held at {self._v_req:.0f} V")
        return f"{reason}: command ended" + "".join(f"; {n}" for n in notes)

    # ------------------------------------------------------------ log
    def _now(self) -> float:
        return self._clock() - self._t0 if self._t0 is not None else 0.0

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
                self._rec = None
                self._write("readings", "error", f"{exc}; the session goes on, readings in this log only")
                self.echo(f"error: {exc}; readings in the session log only")

    def _record(self, stream: str, t: float, **values: float) -> None:
        """One sample of ``stream`` at session time ``t``; columns not given are NaN (flags 0)."""
        rec = self._rec
        if rec is None or stream not in rec.streams:
            return
        row = {c.name: values.get(c.name, math.nan if np.dtype(c.dtype).kind == "f" else 0)
               for c in rec.streams[stream]}
        self._rec_call(lambda: rec.append(stream, t, **row))

    # ------------------------------------------------------------ commands
    def run_lines(self, lines: Iterable[str], stop_on_trip: bool = True) -> list[Outcome]:
        """Execute commands until ``quit``, the end or a stop signal; after a trip, stop if ``stop_on_trip``."""
        it = iter(lines)
        try:
            while self.end_reason is None:
                try:
                    self._idle = True
                    raw = next(it, None)
                finally:
                    self._idle = False
                if raw is None:
                    break
                line = raw.split("#", 1)[0].strip()
                if not line or self.end_reason is not None:
                    continue
                if line in ("quit", "exit"):
                    break
                out = self.execute(line)
                if out.status == "trip" and stop_on_trip:
                    break
        except SessionEnd:
            pass
        finally:
            close = getattr(it, "close", None)
            if close is not None:  # a prompt saves its history now, not when collected
                close()
        return self.outcomes

    def execute(self, line: str) -> Outcome:
        """Run one command; log and return its outcome (refusals, trips, errors and stops are outcomes).

        Whatever a command raises (a driver's error of any class included) becomes one line; only
        KeyboardInterrupt and SystemExit pass."""
        shown = _printable(line)
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
            with self._lock:
                self._busy = True
                try:
                    text = handler(*args) or ""
                finally:
                    self._busy = False
            out = Outcome(shown, "ok", text)
        except (Interrupted, OperationCancelledError) as exc:
            if self.end_reason is not None:
                out = Outcome(shown, "interrupted", f"{self.end_reason}: the session ends")
            elif self._interrupt is not None:
                out = Outcome(shown, "interrupted", self._after_interrupt())
            else:  # a cancelled wait nobody asked for
                out = Outcome(shown, "error", f"{exc}; {self._make_safe()}")
        except (Refused, ValueError, LimitError) as exc:
            out = Outcome(shown, "refused", str(exc))
        except InterlockTrip as trip:
            out = Outcome(shown, "trip", self._latch(trip))
        except SafetyTrip as exc:
            out = Outcome(shown, "trip", f"{exc.reason}; {self._make_safe()}")
        except InstrumentError as exc:
            out = Outcome(shown, "error", f"{exc}; {self._make_safe()}")
        except Exception as exc:  # a program error must not end the session with the output on
            out = Outcome(shown, "error", f"internal error: {type(exc).__name__}: {exc}; {self._make_safe()}")
        if self._interrupt is not None and self.end_reason is None and self._inst is not None:
            self._interrupt = None  # a Ctrl-C as the command ended: nothing left to interrupt
            self._inst.cancel.clear()
        out.text = _printable(" ".join(out.text.splitlines()))
        self.outcomes.append(out)
        self._write(out.command, out.status, out.text)
        if self._rec is not None:
            self._rec_call(self._rec.flush)  # on disk before the next prompt
        self.echo(f"{out.status}: {out.text}" if out.text else out.status)
        return out

    def _make_safe(self) -> str:
        self._v_req = 0.0
        if self._inst is None:
            return "no instruments connected"
        self._inst.cancel.clear()  # after a cancelled wait the safe-state commands must still go out
        try:
            errors = self._inst.safe_state()
        except Exception as exc:  # safe_state reports driver errors; anything else is said, not raised
            errors = [f"{type(exc).__name__}: {exc}"]
        if self._inst.amplifier is not None:
            self._commanded(float(self._inst.amplifier.commanded))
        return "output zeroed, motor stopped" + (f" ({'; '.join(errors)})" if errors else "")

    # each _cmd_* returns one line of text (what was done / read)
    def _cmd_help(self) -> str:
        return "commands: " + "; ".join(line.split("  ")[0].strip() for line in HELP.splitlines())

    def _amp(self) -> Any:
        if self._inst is None or self._inst.amplifier is None:
            raise Refused("this rig has no amplifier")
        return self._inst.amplifier

    def _checked_voltage(self, volts: float) -> float:
        """Send a set-point the latch and the supervisor allow, after the host-stall check; returns what was sent."""
        assert self._sup is not None
        amp = self._amp()
        if self._latched is not None and volts != 0.0:
            self._v_req = 0.0  # held at 0 V: nothing to keep alive
            raise Refused(f"{self._latch_text()}; not sent")
        bound = self._sup.setpoint_bound()
        try:
            self._sup.check_setpoint(volts)
            self._sup.check_setpoint(amp.quantise(volts, within=bound))  # the value the module will output
        except SafetyTrip as exc:
            self._v_req = float(amp.commanded)
            raise Refused(f"{exc.reason}; not sent") from None
        self._guard()
        sent = float(amp.set_voltage(volts, within=bound))
        self._commanded(sent)
        return sent

    # ------------------------------------------------------------ latched interlock
    def _guard(self) -> None:
        """Before a write that can drive the output: latch a host stall (:func:`~bench.runtime.interlock.check_contact`
        on the amplifier's ``longest_silence``). Real time only: a virtual clock cannot stall."""
        amp = self._amp()
        if not self.virtual:
            check_contact(self.rig, amp.longest_silence(), abs(float(amp.commanded)) > OUTPUT_ON_V)

    def _commanded(self, sent: float) -> None:
        """A set-point the amplifier now outputs: what the monitors are checked against; recorded."""
        t = self._now()
        if self._verifier is not None:
            self._verifier.commanded(t, sent)
        self._record("setpoints", t, voltage=sent)

    def _latch(self, trip: InterlockTrip) -> str:
        """Latch ``trip``: output to 0 V at once, motor stopped, a ``latched`` line in the log; returns the outcome."""
        self._latched, self._latched_at = trip, self._now()
        done = self._make_safe()
        self._verifier = OutputVerifier(self.rig, None)  # readings counted afresh from the zeroed output
        self._verifier.commanded(self._now(), float(self._amp().commanded))
        self._write("interlock", "latched", f"{self._latch_text()}; {trip.reason}")
        rig_latch.latch(self.rig.name, trip.reason, str(self.log_file))  # also refuses runs until a reset
        return f"{trip.reason}; {done}; latched"

    def _latch_text(self) -> str:
        assert self._latched is not None
        return (f"interlock latched at t={self._latched_at:.3f} s ({self._latched.kind}): high voltage stays off "
                "until `reset WHY...`")

    def _cmd_reset(self, *why: str) -> str:
        if self._latched is None:
            raise Refused("no interlock latched: nothing to reset")
        reason = " ".join(why).strip()
        if not reason:
            raise Refused("reset needs a reason: reset WHY... (logged with the operator's name)")
        who = self.operator or "an operator not named (no --operator)"
        rig_latch.reset(self.rig.name, who, reason)
        kind, self._latched = self._latched.kind, None
        return f"interlock ({kind}) reset by {who}: {reason}"

    def _reach(self, volts: float) -> float:
        """Send ``volts``; if the amplifier's slew limit cut the step, re-send once the limit allows the whole step
        (after |gap| / slew limit on the rig clock). Returns the set-point finally sent.

        In virtual time no time passes between two commands, so a first send right after another set-point is cut
        to almost nothing: without this the answer named the previous set-point."""
        sent = self._checked_voltage(volts)
        slew = self.rig.amplifier.slew_limit_V_per_s if self.rig.amplifier is not None else math.inf
        need = abs(volts - sent) / slew
        while need > 0:
            nap = min(need, KEEPALIVE_S)
            self._sleep(nap)
            self._check_stop()
            sent = self._checked_voltage(volts)
            need = 0.0 if nap >= need else abs(volts - sent) / slew
        return sent

    def _cmd_voltage(self, value: str) -> str:
        target = to_si(value, "V")
        self._amp()  # refused on a rig without one, before anything is sent or kept alive
        self._v_req = target
        sent = self._reach(target)
        self._wait(SETTLE_S)
        return f"set-point {sent:.0f} V; " + self._cmd_read()

    def _cmd_ramp(self, value: str, duration: str) -> str:
        target, seconds = to_si(value, "V"), to_si(duration, "s")
        if not 0 < seconds <= 3600:
            raise Refused(f"ramp duration {seconds:g} s: give 0 < DURATION ≤ 3600 s")
        start = float(self._amp().commanded)
        assert self._sup is not None
        if self._latched is not None and target != 0.0:
            raise Refused(f"{self._latch_text()}; ramp not started")
        try:
            self._sup.check_setpoint(target)
        except SafetyTrip as exc:
            raise Refused(f"{exc.reason}; ramp not started") from None
        n = max(1, math.ceil(seconds * RAMP_HZ))
        t_begin = self._clock()
        for k in range(1, n + 1):
            self._check_stop()
            self._v_req = start + (target - start) * k / n
            self._checked_voltage(self._v_req)
            self._sleep(max(0.0, t_begin + k * seconds / n - self._clock()))
            self._check_monitors()
        return f"ramped {start:.0f} → {target:.0f} V in {seconds:g} s ({n} set-points); " + self._cmd_read()

    def _cmd_zero(self) -> str:
        self._v_req = 0.0
        amp = self._amp()
        amp.zero()
        self._commanded(float(amp.commanded))
        return "output 0 V"

    def _motor(self) -> Any:
        if self._inst is None or self._inst.motor is None:
            raise Refused("this rig has no motor")
        return self._inst.motor

    def _aperture(self, motor_position: float) -> float:
        spec = self.rig.specimen
        if spec.kind == "membrane" or spec.lsdea is None:
            return math.nan
        return spec.lsdea.x_at_motor_zero_m + spec.lsdea.motor_sign * motor_position

    def _go(self, target: float, speed: float) -> str:
        motor = self._motor()  # refused on a rig without one
        assert self._sup is not None and self.rig.motor is not None  # a motor driver comes from rig.motor
        speed = min(speed, self.rig.motor.max_velocity_m_per_s)
        if not speed > 0:
            raise Refused("speed must be positive")
        try:
            self._sup.check_motor_setpoint(target, self._aperture(target), float(self._amp().commanded)
                                           if self._inst and self._inst.amplifier else 0.0)
        except SafetyTrip as exc:
            raise Refused(f"{exc.reason}; not sent") from None
        motor.move_to(target, speed, min(DEFAULT_ACCEL, self.rig.motor.max_acceleration_m_per_s2))
        self._record("setpoints", self._now(), aperture=self._aperture(target))
        deadline = self._clock() + 2.0 + abs(target - motor.read_position().value) / speed * 1.5
        while self._clock() < deadline:
            self._wait(0.05)
            st = motor.status()
            self._record("motor", self._now(), position=st.position, aperture=self._aperture(st.position))
            self._sup.check_motor(st.position, self._aperture(st.position))
            if st.error:
                raise InstrumentStateError("motor", "drive error during the move: "
                                           + (st.error_text or f"code {st.error_code:#06x}"))
            if st.in_target and not st.moving:
                break
        else:
            motor.stop()
            raise Refused(f"motor did not reach {target * 1e3:.2f} mm in time; stopped")
        return f"motor at {motor.read_position().value * 1e3:.3f} mm (target {target * 1e3:.3f} mm); " + \
            self._cmd_read()

    def _cmd_move(self, position: str, speed: str = "") -> str:
        return self._go(to_si(position, "mm"), to_si(speed, "mm/s") if speed else DEFAULT_SPEED)

    def _cmd_jog(self, delta: str, speed: str = "") -> str:
        here = float(self._motor().read_position().value)
        return self._go(here + to_si(delta, "mm"), to_si(speed, "mm/s") if speed else DEFAULT_SPEED)

    def _cmd_stop(self) -> str:
        self._motor().stop()
        return "motor stopped"

    def _cell(self) -> Any:
        if self._inst is None or self._inst.load_cell is None:
            raise Refused("this rig has no load cell")
        return self._inst.load_cell

    def _cmd_tare(self) -> str:
        self._cell().tare()
        self._wait(0.2)
        return "load cell tared; " + self._cmd_read()

    def _cmd_zero_cell(self) -> str:
        self._cell().zero()
        self._wait(0.2)
        return "load cell zeroed; " + self._cmd_read()

    def _check_monitors(self) -> tuple[float, float]:
        """Both monitors, checked by the supervisor and against the voltage commanded (the interlock)."""
        assert self._sup is not None and self._verifier is not None
        amp = self._amp()
        v, i = amp.read_monitors()
        self._record("amplifier", v.timestamp - (self._t0 or 0.0), voltage=v.value, current=i.value,
                     commanded=float(amp.commanded), late=self._late)
        self._sup.check_monitors(v.value, i.value)
        if (m := self._verifier.reading(v.timestamp - (self._t0 or 0.0), v.value, v.ok)) is not None:
            raise mismatch_trip(m, "the voltage monitor")
        return v.value, i.value

    def _cmd_read(self) -> str:
        """Every channel once, each checked by the supervisor; one line with units."""
        assert self._inst is not None and self._sup is not None
        parts, t0 = [], self._t0 or 0.0
        if self._inst.amplifier is not None:
            v, i = self._check_monitors()
            parts.append(f"voltage {v:.0f} V, current {i * 1e6:.2f} µA")
        if self._inst.laser is not None:
            r = self._inst.laser.read_displacement()
            laser = self.rig.laser
            d = (r.value - laser.offset_mm * 1e-3) / laser.sign if laser is not None else r.value
            self._record("laser", r.timestamp - t0, displacement=d, valid=float(r.ok and math.isfinite(d)),
                         late=self._late)
            if r.ok and math.isfinite(d):
                self._sup.update_displacement(d)
                parts.append(f"displacement {d * 1e3:.4f} mm")
            else:
                parts.append(f"displacement n/a ({r.status})")
        if self._inst.motor is not None:
            r = self._inst.motor.read_position()
            self._record("motor", r.timestamp - t0, position=r.value, aperture=self._aperture(r.value), late=self._late)
            self._sup.check_motor(r.value, self._aperture(r.value))
            parts.append(f"motor {r.value * 1e3:.3f} mm" + (f" (aperture {self._aperture(r.value) * 1e3:.2f} mm)"
                                                          if math.isfinite(self._aperture(r.value)) else ""))
        if self._inst.load_cell is not None:
            r = self._inst.load_cell.read_force()
            self._record("load_cell", r.timestamp - t0, force=r.value, ok=float(r.ok), late=self._late)
            if r.status in ("overload", "underload"):
                raise SafetyTrip(f"load cell {r.status}")
            if r.ok or r.status == "unstable":
                self._sup.check_force(r.value)
            parts.append(f"force {r.value:.3f} N" + ("" if r.ok else f" ({r.status})"))
        return f"t {self._now():.2f} s: " + ", ".join(parts)

    def _cmd_watch(self, duration: str, every: str = "0.5") -> str:
        seconds, interval = to_si(duration, "s"), to_si(every, "s")
        if not (0 < seconds <= 86_400 and 0.05 <= interval <= seconds):
            raise Refused("watch DURATION [EVERY]: 0 < DURATION ≤ 86400 s, 0.05 s ≤ EVERY ≤ DURATION")
        n = max(1, int(seconds / interval))
        t_begin = self._clock()
        for k in range(1, n + 1):
            due = t_begin + k * interval
            self._wait(max(0.0, due - self._clock()))
            self._late = self._clock() - due
            try:
                line = self._cmd_read()
            finally:
                self._late = math.nan
            self._write("watch", "read", line)
            self.echo(line)
        return f"watched {n} readings over {seconds:g} s"

    def _cmd_wait(self, duration: str) -> str:
        seconds = to_si(duration, "s")
        if not 0 <= seconds <= 86_400:
            raise Refused("wait DURATION: 0 … 86400 s")
        self._wait(seconds)
        return f"waited {seconds:g} s"


def _printable(text: str) -> str:
    """``text`` with every control character written as an escape (``\\x1b``): one line, safe in a tab-separated
    log and on a terminal."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def _join_units(words: list[str]) -> list[str]:
    """``["jog", "-5", "mm"]`` → ``["jog", "-5 mm"]``: a unit after a number belongs to it."""
    out: list[str] = []
    for w in words:
        if len(out) > 1 and (w[:1].isalpha() or w[:1] == "µ") and _is_number(out[-1]):
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
    """Default file name of a session log: ``manual-<rig>-<local time>.log``."""
    return f"manual-{rig.name}-{datetime.now().strftime('%Y%m%d-%H%M%S')}.log"


def data_path(log_file: Path) -> Path:
    """The readings' HDF5 file of a session log: ``<log>.h5`` beside it, or ``<log>-1.h5``… (a log is appended to
    when reused; a file of readings is never overwritten)."""
    path, k = log_file.with_suffix(".h5"), 1
    while path.exists():
        path = log_file.with_name(f"{log_file.stem}-{k}.h5")
        k += 1
    return path
