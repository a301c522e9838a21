"""The protocol engine: a compiled program executed on a rig's instruments under the safety supervisor.

The engine turns each step into set-points (voltage through the amplifier, aperture through the motor)
and acquisition (laser data storage during active steps, polled monitors, encoder, load cell and single
laser reads), all stamped on one run clock, and streams everything to the recorder. It runs in real time
against real or simulated instruments, or in virtual time against a simulated rig (the clock jumps to the
next scheduled action; the bytes on the wire are the same).

Every exit — end of the protocol, safety trip, instrument error or lost link, Ctrl-C, SIGTERM, SIGHUP,
SIGQUIT, a storage fault — goes through :meth:`Engine._shut_down`: motor stopped first (concurrently with what
follows on the wall clock: :meth:`Engine._stop_motor`), voltage ramped to zero (at once on a second signal, or if
the ramp fails), every other instrument put in its safe state, stored laser data fetched, and the safe state
*verified* (0 V on the voltage monitor, or the set-point module's communication watchdog waited out), then the
motor's final position read; the file records which path made the output safe, when, where the motor came to rest,
and why the run stopped.

Stop bound: a stop request cancels the rig's :class:`~drivers.cancel.CancelToken`, so whatever wait on an
instrument is under way ends within one driver poll slice; the engine checks the request before every action
and between waits of at most ``STOP_POLL_S``. The ramp-down then starts at once and 0 V is commanded at most
``shutdown_ramp_s`` later; a second request skips the rest of the ramp.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import numpy as np

from bench.core.clock import Clock
from bench.models.lozenge import LozengeParams
from bench.numbers import whole
from bench.protocol.program import (
    DRAIN_HOLD_S,
    HOLD_KEEPALIVE_S,
    Program,
    Segment,
    Tick,
    end_tick,
    largest_voltage_change,
    relax_at_zero,
    ticks,
    voltage_at,
)
from bench.rig import safe_monitor_v
from bench.runtime.context import LATE_TOLERANCE_S, STOP_POLL_S, RunContext, Snapshot, present
from bench.runtime.control import CONTROL_POLL_S, NO_WORD, ControlWord, read_control
from bench.runtime.hardware_timed import FINISH_POLL_S, HardwareTimed
from bench.runtime.instruments import Instruments
from bench.runtime.interlock import OUTPUT_ON_V, InterlockTrip, watchdog_period
from bench.runtime.polls import PAUSED, Poll, StepState, record_laser_block, rig_polls
from bench.runtime.ramp import ramp_to_zero
from bench.runtime.safety import SafetyTrip, Supervisor
from bench.storage.recorder import STEP_END_CHUNKS, Recorder
from drivers.errors import (
    InstrumentConnectionError,
    InstrumentError,
    InstrumentStateError,
    InstrumentTimeoutError,
    OperationCancelledError,
)
from drivers.interfaces import Amplifier, Reading

SHUTDOWN_REPLY_S = 0.1  # shutdown: a request to the set-point module (or the motor) waits this long for its reply, once
MOTOR_SETTLE_S = 0.2  # shutdown: the motor's final position is read at least this long after its abort went out
MOTOR_STOP_JOIN_S = 2.0  # shutdown, wall clock: how long the end waits for the motor's stop thread (its link's waits)
MONITOR_SETTLE_S = 0.5  # after zeroing, wait for fresh monitor conversions before the final read
RAMP_STEPS = 10  # shutdown ramp: set-points from the last voltage to 0 V
DISCHARGE_WAIT_S = 2.0  # how long to keep reading a monitor that is not yet at 0 V before reporting it
MONITOR_REREAD_S = 0.1  # a monitor not yet at 0 V is read again this often (shutdown and hand-over)
SAFE_STATE = "safe_state"  # the run file's stream of the shutdown's verifying monitor reads (_verify_safe)
WATCHDOG_MARGIN_S = 0.2  # wait past the module's communication-safety period before checking the output
LASER_DRAIN_BUDGET_S = 30.0  # at most this long (rig time) fetching a step's stored laser data after the step
LASER_SHUTDOWN_DRAIN_S = 5.0  # after a stop or fault (high voltage already at 0 V): then what is left is reported
PAUSE_POLL_S = 0.1  # while paused: the monitors and sensors are read this often (run time)
RESTART_STEP_V = 10.0  # a restart ramps the output to the step's start value unless it is this close already
RESTART_SETTLE_S = 0.1  # after a restart's ramp, before the step starts
STREAM_RAMP_POLL_S = 0.05  # rig time between the collects of a ramp to 0 V the DAQ plays (its stream-out tops up)
CATCH_UP = 2.0  # a go-to after skipped set-points goes at most this many times its path's own speed
SLIP_S = 1e-3  # a step that ends later than this after its scheduled end shifts the rest of the schedule (run time)
RESTART_MOVE_S = 30.0  # a restart's motor move to the step's start position must end within this (run time)
STOP_SIGNALS = {
    signal.SIGINT: "interrupted by Ctrl-C",
    signal.SIGTERM: "terminated by SIGTERM",
    signal.SIGHUP: "hang-up (SIGHUP: terminal closed or connection dropped)",
    signal.SIGQUIT: "quit requested (SIGQUIT)",
}

OperatorFn = Callable[[str], bool]


def supersedes(tick: Tick, later: Tick) -> bool:
    """Whether ``later`` makes ``tick`` pointless once both are due: it sends everything ``tick`` would (a voltage
    where ``tick`` has one, a go-to where ``tick`` has one; both are absolute), and it is not the step's end value
    (sent at the end, after the loop). A move step's one go-to is followed by ticks without one: never skipped."""
    return not later.end and (tick.voltage is None or later.voltage is not None) \
        and (tick.motor is None or later.motor is not None)


def turns_at(sent: Tick | None, tick: Tick, later: Tick) -> bool:
    """Whether ``tick`` is a turn of the voltage or of the go-to's target between the last tick ``sent`` and
    ``later``: a waveform's crest or trough, which a skip would cut off (the stroke or the peak voltage short by the
    path between two set-points), so it is sent even when ``later`` is due."""
    def values(k: Tick) -> tuple[float | None, float | None]:
        return k.voltage, None if k.motor is None else k.motor[0]

    if sent is None:
        return False
    return any(p is not None and a is not None and b is not None and (a - p) * (b - a) < 0
               for p, a, b in zip(values(sent), values(tick), values(later), strict=True))


@dataclass
class Skipped:
    """What a step behind its schedule skipped: set-points superseded before they went out, polls' missed slots."""

    setpoints: int = 0
    sent: int = 0
    polls: dict[str, int] = field(default_factory=dict)

    def text(self) -> str:
        """The ``skipped`` event's words (the event holds 200 bytes: the counts first)."""
        polls = ", ".join(f"{k} {n}" for k, n in self.polls.items())
        return (f"{self.setpoints} of {self.setpoints + self.sent} set-points skipped"
                + (f", missed slots of polls skipped: {polls}" if polls else "")
                + "; behind the schedule, each superseded by a later one already due")


@contextlib.contextmanager
def stop_signals(on_stop: Callable[[str, int], None], on_pause: Callable[[str], None],
                 on_resume: Callable[[str], None]) -> Iterator[None]:
    """Within: SIGINT/SIGTERM/SIGHUP/SIGQUIT call ``on_stop(reason, signal)`` (reasons: :data:`STOP_SIGNALS`),
    SIGUSR1 ``on_pause(by)``, SIGUSR2 ``on_resume(by)``; the old handlers after. Main thread only (elsewhere it
    installs nothing). The handlers of runs and of manual control."""
    old: list[tuple[signal.Signals, Any]] = []
    if threading.current_thread() is threading.main_thread():
        for sig, text in STOP_SIGNALS.items():
            def handler(s: int, _f: FrameType | None, text: str = text) -> None:
                on_stop(text, s)

            old.append((sig, signal.signal(sig, handler)))
        old.append((signal.SIGUSR1, signal.signal(signal.SIGUSR1, lambda *_a: on_pause("signal SIGUSR1"))))
        old.append((signal.SIGUSR2, signal.signal(signal.SIGUSR2, lambda *_a: on_resume("signal SIGUSR2"))))
    try:
        yield
    finally:
        for sig, handler in old:
            signal.signal(sig, handler)


class Phase:
    """What a run is doing before its engine has its own stop handlers (:func:`termination_raises`); the
    message of a stop signal then names it."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.stopped: str | None = None  # the first stop signal's account, once one came

    def stop(self, sig: int) -> NoReturn:
        """A stop signal: noted, and raised as an :class:`OperationCancelledError` naming it and the phase."""
        if self.stopped is None:
            self.stopped = f"{STOP_SIGNALS[signal.Signals(sig)]} while {self.what}"
        raise OperationCancelledError("run", self.stopped)

    def check(self) -> None:
        """Raise as :meth:`stop` did if a stop signal came (a library that caught the first raise, and retried or
        turned it into an error of its own, must not lose it)."""
        if self.stopped is not None:
            raise OperationCancelledError("run", self.stopped)


@contextlib.contextmanager
def termination_raises(what: str) -> Iterator[Phase]:
    """Within (before the engine has its own handlers: starting a simulated rig, connecting, enabling and homing
    the motor): SIGINT, SIGTERM, SIGHUP and SIGQUIT raise an :class:`OperationCancelledError` naming the signal
    and what was under way (``what``, or what the caller set the yielded :class:`Phase` to since) — so the
    caller's ``finally`` closes the instruments (output zeroed, motor aborted) instead of the process dying with a
    homing motor. Ctrl-C too: a bare KeyboardInterrupt left the command line silent (exit 130, nothing said, nothing
    in the run log) where the other signals print one line. The old handlers after; main thread only."""
    phase = Phase(what)
    old: list[tuple[signal.Signals, Any]] = []
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            def handler(s: int, _f: FrameType | None) -> None:
                phase.stop(s)

            old.append((sig, signal.signal(sig, handler)))
    try:
        yield phase
    finally:
        for sig, h in old:
            signal.signal(sig, h)


class StopRequested(Exception):  # noqa: N818 - control flow, not a failure
    """Ctrl-C / SIGTERM / a stop request from another thread."""


class PauseRequested(Exception):  # noqa: N818 - control flow, not a failure
    """A pause request (signal, control file, another thread): the step under way is left at once."""


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
    safe_path: str = ""
    latched: str = ""  # the interlock fault the run latched its rig for ('' if none)
    skipped: int = 0  # set-points skipped because the run was behind its schedule (each step's `skipped` event)


@dataclass
class _MotorStop:
    """The motor's stop at the start of a shutdown: when it was sent, when its telegrams were answered (NaN: not
    yet), what went wrong; on the wall clock the thread that sends it."""

    sent_at: float
    done_at: float = math.nan
    error: str | None = None
    thread: threading.Thread | None = None


def next_slot(due: float, now: float, period: float) -> float:
    """A poll's next run time on its grid (``due`` + a whole number of ``period``) after it ran at ``now`` for the slot
    ``due``: the slots it fell behind are skipped, not run in a burst (one that fell due within the 1e-12 tolerance
    counts as run)."""
    return due + period * (max(0, math.floor((now - due) / period)) + 1)

class Engine:
    """Runs one program on one rig's connected instruments."""

    def __init__(self, program: Program, inst: Instruments, clock: Clock, recorder: Recorder,
                 supervisor: Supervisor, *, apply_specimen: Callable[[dict[str, Any]], None] | None = None,
                 operator: OperatorFn | None = None, start_step: int = 0, control: Path | None = None,
                 commands: bool = False) -> None:
        """``start_step``: run the program from this step on (a resumed campaign; the steps before it ran in the
        file it continues). ``control``: the run's control file (``bench pause`` / ``bench resume`` write it).
        ``commands``: manual mode (:class:`bench.runtime.manual_mode.ManualEngine`) — set-points come one command
        at a time, command-response (no DAQ stream plays), through the same set-point, ramp, move, interlock and
        shutdown code as a program's."""
        if not 0 <= start_step < max(len(program.segments), 1):
            raise ValueError(f"start step {start_step} outside the program's {len(program.segments)} steps")
        self.program = program
        # |voltage monitor| at or below this is the output verified at 0 V (hand-over, shutdown): from the rig's
        # monitor chain (bench.core.monitor_chain), never above its 50-V safe touch limit
        self.safe_v = safe_monitor_v(program.rig)
        self.commands = commands
        self.start_step = start_step
        # told the pause's verified 0 V (its text) and, None, the resume: the run's armed marker says so (run.py)
        self.on_paused: Callable[[str | None], None] | None = None
        self.control = control
        self.inst = inst
        self.clock = clock
        self.rec = recorder
        self.sup = supervisor
        self.apply_specimen = apply_specimen
        self.operator = operator
        self.snapshot = Snapshot(duration=program.duration, steps=len(program.segments))
        self.ctx = RunContext(program, inst, clock, recorder, supervisor, self.snapshot,
                              check_stop=self._check_stop, check_pause=self._check_pause, streamed=not commands)
        self._stop_reason: str | None = None
        self._stop_at: float | None = None  # run time of the first stop request
        self._urgent = threading.Event()
        self._stopping = False
        self._in_prompt = False
        self._storing = False
        self._storage_failed = False
        drive = inst.stream_drive if not commands else None  # steps played hardware-timed on a DAQ's stream
        self._stream = HardwareTimed(program.rig, *drive, self.ctx) if drive is not None else None
        self.ctx.stream = self._stream
        self.verifier, self.motion = self.ctx.verifier, self.ctx.motion
        self.latched: InterlockTrip | None = None  # the interlock fault that ended the run (0 V at once, no ramp)
        self.tripped: SafetyTrip | None = None  # the supervisor's limit trip that ended the run (latches it too)
        self._output_dead = False  # 0 V could not be commanded: no request may feed the module's watchdog
        self._stream_lost = False  # … or 0 V was written but a stream stop went unanswered (may play over it)
        self._zero_verified = False  # the shutdown read 0 V back from the voltage monitor
        # run time of the last set-point (software-timed) that commanded the output on (|V| > OUTPUT_ON_V), or
        # that commanded it off from there: the hand-over check's settle counts from it (_hand_over)
        self._live_at = -math.inf
        self._safe_reads: list[tuple[float, float, float]] = []  # the shutdown's verifying reads: (run time, V, A)
        self._final_position = math.nan  # the motor's position read by the shutdown once at rest [m]
        self._streamed_settle = False  # the shutdown's stream recorded the monitors through the settle after 0 V
        self._settle_recorded = False  # 0 V commanded at once, the settle after it recorded on a stream of inputs
        self._ramp_fault: SafetyTrip | InterlockTrip | None = None  # a trip the shutdown ramp's monitor reads saw
        self.ended: tuple[str, str] = ("", "")  # the state and reason the shutdown recorded (:meth:`_shut_down`)
        self._pause_by: str | None = None  # who asked for a pause (signal, another thread); None: nobody
        self._resume_by: str | None = None
        self._control_seen: ControlWord = NO_WORD  # control file: (stamp, pause?, by/why, stop?)
        self._control_checked = 0.0
        # a run's pause and resume requests, each taken in (:meth:`_take_requests`) in the order they came: what the
        # run wants, or a ``request`` event saying why it changed nothing (none is lost without a word)
        self._asked: deque[tuple[bool, str]] = deque()  # (pause?, by whom) not yet taken in
        self._pending_pause: str | None = None  # a pause asked for (by whom) and not yet taken
        self._paused_by: str | None = None  # while paused: who asked for the pause
        self._resume_asked: str | None = None  # while paused: who asked it to go on (not yet taken)
        self.pauses = 0
        # manual mode (commands instead of a program): a Ctrl-C while a command runs ends the command, not the
        # session (``interruptible``); ``_interrupt`` is that request until the command has ended
        self.interruptible = False
        self._interrupt: str | None = None
        self.on_event: Callable[[str, str], None] | None = None  # shutdown events go here instead (manual: its log)
        self._setpoint_t = -math.inf  # run time of the last set-point recorded (a keep-alive is recorded no earlier)
        self.skipped = 0  # set-points skipped in the run, each superseded by a later one already due
        amp = program.rig.amplifier
        amp_bus = amp.bus if amp is not None and amp.drive != "daq" else None
        for name, link in inst.links.items():  # a retry on another bus: the set-point module fed before it
            if name != amp_bus:
                link.retrying = self._between_attempts

    # ------------------------------------------------------------ stop requests (signals, other threads)
    def request_stop(self, reason: str) -> None:
        """Ask the run to stop; a second request while stopping makes the voltage go to zero at once.

        Safe from a signal handler or another thread: it sets flags and cancels instrument waits, nothing more.
        """
        if self._stop_reason is None:
            self._stop_reason = reason
            self._stop_at = self.now()
            if not self._stopping:
                self.inst.cancel.cancel(reason)
        else:
            self._urgent.set()

    def request_pause(self, by: str) -> None:
        """Ask the run to pause (output to 0 V, motor held, recording on); safe from a signal handler or thread."""
        self._resume_by = None
        self._pause_by = by
        if not self.commands:  # manual mode answers its own pause and resume commands
            self._asked.append((True, by))

    def request_resume(self, by: str) -> None:
        """Ask a paused run to go on (its step restarts from its beginning)."""
        self._pause_by = None
        self._resume_by = by
        if not self.commands:
            self._asked.append((False, by))

    def _take_requests(self, ending: str | None = None) -> None:
        """A run's pause and resume requests (signals, keys, other threads, a new word in the control file, looked
        at every 0.1 s wall time), in the order they came: each one either changes what the run wants (a pause
        to take, a pause to leave) or is recorded as a ``request`` event saying why it changed nothing. The same
        request repeated before the run took it (a key held down, a hook asking at every tick) counts once.
        ``ending``: the run's end (its state); what is left is answered as too late, the control file read once
        more."""
        if self.control is not None and (ending is not None
                                         or time.monotonic() - self._control_checked >= CONTROL_POLL_S):
            self._control_checked = time.monotonic()
            seen, self._control_seen = self._control_seen, read_control(self.control, self._control_seen)
            if self._control_seen[0] != seen[0]:  # a new word
                _, pause, who, stop = self._control_seen
                if not stop:
                    self._asked.append((pause, who))
                elif ending is not None:
                    self._request_event(f"stop asked by {who} as the run ended ({ending}): nothing more to do")
                elif self._stop_reason is None:  # a stop word (bench watch): as Ctrl-C
                    self.request_stop(f"stop asked by {who}")
                    self._check_stop()
        while self._asked:
            pause, by = self._asked.popleft()
            what = f"{'pause' if pause else 'resume'} asked by {by}"
            if ending is not None or self._stopping:
                self._request_event(f"{what} as the run ended ({ending or 'stopping'}): no effect")
            elif self._paused_by is not None:  # paused
                if not pause and self._resume_asked in (None, by):
                    self._resume_asked = by
                elif not pause:
                    self._request_event(f"{what}: already resuming (asked by {self._resume_asked}): nothing "
                                        "more changes")
                elif self._resume_asked is not None:
                    self._request_event(f"{what} before the resume asked by {self._resume_asked} was taken: "
                                        "that resume withdrawn, the run stays paused")
                    self._resume_asked = None
                else:
                    self._request_event(f"{what}: already paused (by {self._paused_by}): nothing changes")
            elif self._pending_pause is not None:  # asked for, not yet taken
                if pause and by != self._pending_pause:
                    self._request_event(f"{what}: a pause asked by {self._pending_pause} is being taken: one pause")
                elif not pause:
                    self._request_event(f"{what} before the pause asked by {self._pending_pause} was taken: that "
                                        "pause withdrawn, the run went on")
                    self._pending_pause = None
            elif pause:
                self._pending_pause = by
            else:
                self._request_event(f"{what}: the run is not paused: nothing to resume")
        if ending is not None:
            if self._pending_pause is not None:
                self._request_event(f"pause asked by {self._pending_pause}: the run ended ({ending}) before it "
                                    "paused")
            if self._paused_by is not None and self._resume_asked is not None:
                self._request_event(f"resume asked by {self._resume_asked}: the run ended ({ending}) before it "
                                    "resumed")
            self._pending_pause = self._resume_asked = None

    def _request_event(self, text: str) -> None:
        """A pause, resume or stop request that changed nothing, and why (a ``request`` event)."""
        if self._stopping:
            self._event("request", text)
        else:
            self.rec.event(self.now(), self.snapshot.step, "request", text)

    def _paused_wanted(self) -> tuple[bool, str]:
        """(pause wanted?, by whom and why). A run: its requests as :meth:`_take_requests` took them in; manual
        mode: a request by signal or another thread (its ``pause`` and ``resume`` commands answer for
        themselves)."""
        if not self.commands:
            self._take_requests()
        return self._wanted_now()

    def _wanted_now(self) -> tuple[bool, str]:
        """:meth:`_paused_wanted` as the requests already taken in say, none taken in: what the pause's start and
        end name (taking requests there could record a request as undoing what the run then did anyway)."""
        if not self.commands:
            if self._paused_by is not None:
                return self._resume_asked is None, self._resume_asked or self._paused_by
            return self._pending_pause is not None, self._pending_pause or ""
        if self._pause_by is not None:
            return True, self._pause_by
        return False, self._resume_by or ""

    def _check_pause(self) -> None:
        if not self._stopping and self._stop_reason is None and self._paused_wanted()[0]:
            raise PauseRequested

    def _on_signal(self, reason: str, sig: int | None = None) -> None:
        """A stop signal: a stop request (an interrupt of the command under way in manual mode, interactive); at an
        operator prompt (``input()`` blocks) leave it now."""
        if (sig == signal.SIGINT and self.interruptible and self._interrupt is None and self._stop_reason is None
                and not self._stopping):
            self._interrupt = reason
            self.inst.cancel.cancel(reason)
            return
        self.request_stop(reason)
        if self._in_prompt and not self._stopping:
            self._in_prompt = False
            raise StopRequested(reason)

    def signals(self) -> contextlib.AbstractContextManager[None]:
        """Within: the engine's stop, pause and resume requests by signal (:func:`stop_signals`)."""
        return stop_signals(self._on_signal, self.request_pause, self.request_resume)

    @contextlib.contextmanager
    def prompt(self) -> Iterator[None]:
        """Within: waiting for an operator (``input()``); a stop signal leaves the wait at once (StopRequested)."""
        self._in_prompt = True
        try:
            self._check_stop()
            yield
        finally:
            self._in_prompt = False

    def _check_stop(self) -> None:
        if self._stopping:
            return
        if self._stop_reason is not None:
            raise StopRequested(self._stop_reason)
        if self._interrupt is not None:
            raise StopRequested(self._interrupt)

    @property
    def overruns(self) -> int:
        """Actions later than ``LATE_TOLERANCE_S`` on the run clock (real or virtual)."""
        return self.ctx.overruns

    @property
    def _hw(self) -> HardwareTimed:
        return present(self._stream, "daq")

    def _keep_fed(self) -> None:
        """During long host-side work (fetching stored laser data) on a software-timed rig: re-send the set-point
        whenever the module has gone ``HOLD_KEEPALIVE_S`` of the run's clock unheard, as a hold's keep-alive ticks
        do (in virtual time a laser upload takes the wire's time on that clock, however fast the host is)."""
        amp = self.inst.amplifier
        if amp is None or self._stream is not None or self._stopping:
            return
        if self.ctx.unheard_for() >= HOLD_KEEPALIVE_S:  # run clock: the module's watchdog counts rig time
            self._set_voltage(self.ctx.v_req, self.now())

    def _between_attempts(self) -> None:
        """Before a retry of a request another instrument left unanswered (its link, not the set-point module's):
        the wait noted (a watchdog that fires meanwhile is laid to that instrument), and the module kept fed, so
        that one silent instrument's timeout and retry do not starve its keep-alive (as :meth:`_keep_fed`, the
        set-point recorded at the read's scheduled time, or after the last set-point recorded if that is later: the
        stream stays in time order)."""
        t = max(self.ctx.unanswered(), self._setpoint_t)
        if self.inst.amplifier is None or self._stream is not None or self._stopping:
            return
        try:
            if self.ctx.unheard_for() >= HOLD_KEEPALIVE_S:
                self._set_voltage(self.ctx.v_req, t)
        except InstrumentError:
            self.ctx.feed_failed()
            raise

    # ------------------------------------------------------------ time
    def now(self) -> float:
        """Run time [s]."""
        return self.ctx.now()

    def program_now(self) -> float:
        """Program time [s]: run time less the shifts of a resumed start and of the pauses."""
        return self.ctx.program_now()

    def _pause_until(self, t: float, urgent_aborts: bool = True) -> bool:
        """Shutdown wait: returns False at once if an urgent (second) stop request comes and ``urgent_aborts``."""
        if self.clock.virtual:
            self.clock.wait_until(self.ctx.t0 + t)
            return not (urgent_aborts and self._urgent.is_set())
        while (left := t - self.now()) > 0:
            if urgent_aborts and self._urgent.is_set():
                return False
            time.sleep(min(left, STOP_POLL_S))
        return not (urgent_aborts and self._urgent.is_set())

    # ------------------------------------------------------------ acquisition
    def _drain_laser(self, budget: float, hold: float = math.inf, due: dict[str, float] | None = None) -> bool:
        """Fetch stored laser data until the storage is empty, ``budget`` s pass, or a stop request comes; returns
        whether the output was ramped to 0 V meanwhile.

        The budget is rig time: real time on hardware; in virtual time the wire time the uploads take (the time in
        which the storage fills on), so that a host starved of CPU cannot exhaust it.

        Unless the run is stopping (0 V is commanded then, and verified right after), the run stays supervised
        between uploads as in a step: the polls of :meth:`_drain_polls` run at their step rates (``due``: each
        one's next run time, the step's schedule continued), recorded and checked by the supervisor and the
        verifiers — a trip ends the run as any trip does — and the set-point module is kept fed.

        An output still above ``RESTART_STEP_V`` ``hold`` s after the drain began is ramped to 0 V (supervised
        set-points, as a pause does). A drain that long means the link cannot upload as fast as the storage fills
        (the link budget says so before the run): holding a high voltage the protocol did not ask for, for up to
        the drain budget, loads the specimen (creep, time under field towards breakdown) in a way nobody planned,
        on an overnight run nobody watches; 0 V is the state every other unplanned wait (pause, stop) leaves it
        in, and the caller restarts the next step as after a resume. A short drain — the last upload of a step on
        a link that carries the protocol — holds the value: a ramp down and up after every stored step would add
        load cycles the protocol did not ask for."""
        start = self.now()
        end = start + budget
        supervise = self._supervised(due)
        zeroed = False
        while record_laser_block(self.ctx) > 0 or self.ctx.laser.pending > 0:
            if self._stopping and self._urgent.is_set():
                return zeroed
            # pause and stop requests (the control file's stop word included: it raises here) are seen on every
            # upload, not only once the drain is over — a pause zeroes the output within the README's 0.1 s
            pausing = not self._stopping and self._paused_wanted()[0]
            self._check_stop()
            self._keep_fed()
            supervise()
            if (not zeroed and (self.now() - start >= hold or pausing) and self.inst.amplifier is not None
                    and abs(self.ctx.v_cmd) > RESTART_STEP_V and not self._streaming()):
                why = ("a pause was asked for" if pausing and self.now() - start < hold else
                       "the link cannot upload as fast as the storage fills")
                self.rec.event(self.now(), self.snapshot.step, "drain", f"stored laser data still uploading "
                               f"{self.now() - start:.3f} s after the step's end: output ramped from "
                               f"{self.ctx.v_cmd:.0f} V to 0 V while the upload goes on ({why})")
                self._ramp_to(0.0, self.program.rig.limits.shutdown_ramp_s, after=supervise)
                zeroed = True
            if self.now() > end:
                raise InstrumentStateError("laser", f"stored data not fetched within {budget:g} s: the link "
                                           "cannot upload as fast as the storage fills")
        return zeroed

    def _supervised(self, due: dict[str, float] | None = None) -> Callable[[], None]:
        """A supervised reading for host-side work outside a step (a drain, a restart's ramp): each call runs the
        polls of :meth:`_drain_polls` that are due (``due``: each one's next run time, a step's schedule continued;
        else now), recorded and checked by the supervisor and the verifiers; nothing while stopping (0 V is
        commanded then, and verified right after)."""
        return self._supervision(due)[0]

    def _supervision(self, due: dict[str, float] | None = None) -> tuple[Callable[[], None], dict[str, float]]:
        """:meth:`_supervised`'s call, and its schedule: each poll's next run time, advanced by the call (a manual
        session waits until the earliest of them, between commands as in a ``wait``)."""
        start = self.now()
        polls = {} if self._stopping else self._drain_polls()
        nxt = {name: (due or {}).get(name, start) for name in polls}

        def supervise() -> None:
            now = self.now()
            for name, (poll, period) in polls.items():
                if nxt[name] <= now + 1e-12:
                    self._check_stop()
                    poll.run(self.ctx, nxt[name] - self.ctx.offset)  # its lateness: against this schedule
                    nxt[name] = next_slot(nxt[name], now, period)
            if polls:
                self.snapshot.headroom = self.sup.headroom()
                self.rec.maybe_flush()
        return supervise, nxt

    def _streaming(self) -> bool:
        """Whether a DAQ stream plays (the next step already in it): the output is the device's, not a set-point's."""
        return self._stream is not None and self._hw.daq.streaming

    def _laser_free(self) -> bool:
        """Whether the laser's own line is free for single reads outside a step: not in a run, whose upload of the
        laser's stored data is what goes on there (in manual control it is: :class:`.manual_mode.ManualEngine`)."""
        return False

    def _drain_polls(self) -> dict[str, tuple[Poll, float]]:
        """The polls that go on while stored laser data upload outside a step, with their periods (run time): every
        reading the run supervises (monitors, encoder, load cell, other sensors) at its step rate; on a DAQ rig
        the stream's collect while it still plays (the next step already in it), else the monitors by
        command-response every ``PAUSE_POLL_S``, as a pause reads them (the DAC holds the value it played last,
        which the output verifier is told of)."""
        playing = self._streaming()
        state = StepState(None, streamed=playing, laser_serial=self._laser_free(), storing=False)
        out: dict[str, tuple[Poll, float]] = {}
        for poll in rig_polls(self.ctx):
            period = poll.period(self.ctx, state)
            if period is None and poll.name == "monitors" and self._stream is not None and not playing:
                period = PAUSE_POLL_S
                self.verifier.commanded(self.now(), self.ctx.v_cmd)
            if period is not None:
                out[poll.name] = (poll, period)
        return out

    def _drain_after(self, seg: Segment, due: dict[str, float]) -> bool:
        """Fetch the stored laser data of ``seg``, just ended (``due``: the next run time of each of its polls),
        and account for the time it took: the program's schedule is shifted by it (an ``offset`` event, as a
        pause's), so that the next step runs whole, never cut short by the upload; a ``drain`` event says how
        long, at what output. Returns whether the output went to 0 V meanwhile (:meth:`_drain_laser`): then the
        next step restarts as after a resume. On a DAQ rig whose stream plays on into the next step, the program
        runs on the device's clock and cannot shift: the event says how late the host's own actions are."""
        t_end = seg.t_end + self.ctx.offset  # the step's scheduled end (run time)
        v, start = self.ctx.v_cmd, self.now()
        playing = self._streaming()
        if start - t_end > LATE_TOLERANCE_S and not playing:  # the step's own lateness, before the upload's
            self._late(start, seg, start - t_end, "by it and by the laser's upload (the drain event)")
        zeroed = self._drain_laser(LASER_DRAIN_BUDGET_S, math.inf if playing else DRAIN_HOLD_S, due)
        behind = self.now() - t_end
        if behind <= 1e-9:  # nothing to upload (or no time on the run's clock)
            return zeroed
        took = f"stored laser data fetched for {self.now() - start:.3f} s after the step's end"
        if playing:
            self.rec.event(self.now(), seg.index, "drain", f"{took} while the DAQ played the next step on its own "
                           f"clock: that step's host-side actions (motor, polls) start {behind:.3f} s late")
        elif zeroed:
            then = "the next step restarts from its start" if seg is not self.program.segments[-1] else "the run ends"
            self.rec.event(self.now(), seg.index, "drain", f"{took}, the output at 0 V for the rest of it; {then}")
        else:
            held = f"the output held at {v:.0f} V under supervision" if self.inst.amplifier is not None else \
                "sensors supervised"
            self.ctx.offset += behind
            self.rec.event(self.now(), seg.index, "drain", f"{took}, {held}; the program's schedule shifted by the "
                           f"{behind:.3f} s the run is behind it (the step's own lateness included) so that the next "
                           "step runs whole")
            self.rec.event(self.now(), seg.index, "offset", f"run time = program time + {self.ctx.offset:.9f} s")
        return zeroed

    def _keep_schedule(self, seg: Segment) -> None:
        """After ``seg``'s last action: if it ends more than ``SLIP_S`` after its scheduled end — its set-points and
        polls needed more time on the wires than the schedule gave them (the link budget warns before the run when
        it can tell), or its end value's own request spilled past the end — shift the program's schedule by that
        lateness, as a pause or a drain does (an ``offset`` event the analysis applies), so that the next step runs
        whole instead of being cut short by the time this one overran; a ``late`` event says how late and that the
        schedule moved. (Shifting only beyond ``LATE_TOLERANCE_S`` would let every step lose up to 50 ms, and a
        step after a slightly late ramp lost that much in the tester's run.) A late end also follows a step that
        waited for the operator (a specimen change confirmed at the prompt). Software-timed rigs only: on a DAQ rig
        the device plays each step with a duration whole on its own clock (the host's finish waits for its end
        value), and a chained next step is already playing."""
        behind = self.now() - (seg.t_end + self.ctx.offset)
        if behind <= SLIP_S:
            return
        self.ctx.offset += behind
        if behind > LATE_TOLERANCE_S:  # a slip of a few ms (a ramp's end value sent at its end) shifts, unsaid
            self._late(self.now(), seg, behind, f"by {behind:.3f} s")
        self.rec.event(self.now(), seg.index, "offset", f"run time = program time + {self.ctx.offset:.9f} s")

    def _steps_of(self, seg: Segment, polls: dict[str, tuple[Poll, float]], count: dict[str, int],
                  due: dict[str, float], schedule: Iterator[Tick], ahead: tuple[Tick | None, Tick | None],
                  skipped: Skipped, streamed: bool, jump: float) -> None:
        """The body of a step up to its end: each tick of ``schedule`` (``ahead``: its first two) and each poll
        when due, in time order. Behind the schedule (the links slower than it), a set-point whose successor is
        already due is skipped, never sent late — within ``jump`` [V] of the last voltage sent, as sent
        (:meth:`_skip_within`) — so that the step keeps its times (its waveform sampled more coarsely), not
        stretched; a reading's missed slots likewise (one read at the latest, not a burst)."""
        tick, following = ahead
        sent: Tick | None = None  # the last tick sent (a turn between it and a later one is never skipped)
        while True:
            t_set = tick.t if tick is not None and not tick.end else math.inf
            t_next = min([t_set, *due.values()])
            if seg.duration == 0 or t_next >= seg.t_end - 1e-12:
                break
            self.ctx.wait_until(t_next)
            if tick is not None and t_set <= t_next:
                behind = skipped.setpoints
                while following is not None and supersedes(tick, following) and following.t <= self.program_now() \
                        and self._skip_within(following, jump) and not turns_at(sent, tick, following):
                    tick, following = following, next(schedule, None)
                    skipped.setpoints += 1
                self._send_tick(tick, streamed, catch_up=skipped.setpoints > behind)
                sent = tick
                skipped.sent += 1
                tick, following = following, next(schedule, None)
            for kind in [k for k, tk in due.items() if tk <= t_next + 1e-12]:
                self._check_stop()
                poll, period = polls[kind]
                while not poll.backlog and (nxt := seg.t_start + (count[kind] + 1) * period) <= self.program_now() \
                        and nxt < seg.t_end - 1e-12:
                    count[kind] += 1
                    skipped.polls[kind] = skipped.polls.get(kind, 0) + 1
                # a poll (the laser's upload) that bounds itself ends before the step's next action: the next tick,
                # another poll's next slot (one due now runs right after it), the step's end
                self.ctx.upload_until = self.ctx.offset + min(
                    [tick.t if tick is not None else math.inf, seg.t_end,
                     *(d for k, d in due.items() if k != kind and d > t_next + 1e-12)])
                poll.run(self.ctx, seg.t_start + count[kind] * period)
                count[kind] += 1
                due[kind] = seg.t_start + count[kind] * period
            self.snapshot.t = t_next
            self.snapshot.headroom = self.sup.headroom()
            self.rec.maybe_flush()

    def _skip_within(self, later: Tick, jump: float) -> bool:
        """Whether a skip to ``later`` moves the output at most ``jump`` [V] as the file records it, or by one code
        of the module (the least any change moves it: where twice a step's own change is under a code, a skip
        bound below it refused every change and the step went late instead, 5.2 s in 10 s for a 1.2-V-per-set-point
        ramp on the ADAM-4024's 4.9-V codes): the module's code for ``later``'s voltage (:meth:`_check_voltage`'s,
        within the supervisor's bound) against the value last sent. Compared as requested (``later`` against the
        last request), the recorded jump could exceed the bound by a code (a tester's 83.0 V against 2 × 40 V); the
        slew limit only shortens what goes out."""
        if later.voltage is None or math.isinf(jump):
            return True
        within = self.sup.setpoint_bound()
        try:
            sent = self.ctx.amp.quantise(later.voltage, within=within)
            if abs(sent - self.ctx.v_cmd) <= jump:
                return True
            # the next code: no code lies between the two, so their midpoint's nearest code is one of them (both
            # inside the bound: outside it the midpoint is clamped to the bound's code, which says nothing)
            return abs(self.ctx.v_cmd) <= within and \
                self.ctx.amp.quantise((sent + self.ctx.v_cmd) / 2, within=within) in (sent, self.ctx.v_cmd)
        except InstrumentError:  # refused as a set-point: not skipped to (sent in turn, refused there)
            return False

    def _late(self, t: float, seg: Segment, behind: float, shift: str) -> None:
        """The ``late`` event of a step that ended ``behind`` s after its scheduled end; ``shift``: by what the
        program's schedule shifted."""
        self.rec.event(t, seg.index, "late", f"step {seg.index} ({seg.name}) ended {behind:.3f} s after its "
                       f"scheduled end: the program's schedule shifted {shift} so that the next step runs whole")

    # ------------------------------------------------------------ set-points
    def _sent_at(self, due: float) -> float:
        """The run time to record a set-point due at ``due`` at: its scheduled time while it goes out on time, the
        time it went out once it is later than ``LATE_TOLERANCE_S`` (a step whose wires outran the schedule: the
        file must not say it was commanded earlier than it was), and never before the set-point before it (sent
        before it)."""
        now = self.now()
        return max(now if now - due > LATE_TOLERANCE_S else due, self._setpoint_t)  # never before the one before it

    def _set_voltage(self, v: float, t: float, x_cmd: float = math.nan) -> None:
        """Send a supervised voltage set-point and record the value sent.

        The supervisor checks the request, then the value the module will really output: the driver's nearest code
        within the supervisor's bound (one code toward zero at a limit, so a set-point at the limit runs and never
        exceeds it). A step the slew limit held back is checked as sent."""
        bound, want = self._check_voltage(v)
        self.ctx.guard()
        sent = self.ctx.amp.set_voltage(v, within=bound)
        if abs(sent) > OUTPUT_ON_V or abs(self.ctx.v_cmd) > OUTPUT_ON_V:
            self._live_at = self.now()
        self.ctx.v_cmd, self.ctx.v_req = sent, v
        self.verifier.commanded(self.now(), sent)
        self._record_setpoint(t, sent, x_cmd)
        if sent != want:
            self.sup.check_setpoint(sent)

    def _record_setpoint(self, t: float, voltage: float, aperture: float) -> None:
        """A set-point row at run time ``t``, remembered as the last (a keep-alive is recorded no earlier)."""
        self.rec.append("setpoints", t, voltage=voltage, aperture=aperture)
        self._setpoint_t = max(self._setpoint_t, t)

    def _send_tick(self, tick: Tick, streamed: bool, catch_up: bool = False) -> None:
        """Send one tick of a step's schedule (its go-to, its voltage unless a DAQ stream plays it) and record it
        (:meth:`_sent_at`). ``catch_up``: set-points were skipped just before it, so the motor lags the path its
        go-tos had it on: the go-to's speed is raised (to ``CATCH_UP`` times the path's own and the rig's limit at
        most) to reach the target when the path does, two ticks on, instead of the path's own speed, which would
        keep the lag and cut every turn short (a tester's isopotential stroke lost 2 mm at each end)."""
        t_rec = self._sent_at(tick.t + self.ctx.offset)
        motor = tick.motor
        if catch_up and motor is not None and (at := self.motion.expected_at(self.now())) is not None:
            dt = 1.0 / self.program.protocol.recording.setpoint_Hz
            left = max(tick.t + 2 * dt + self.ctx.offset - self.now(), dt)
            v_max = self.program.rig.motor.max_velocity_m_per_s if self.program.rig.motor is not None else motor[1]
            # at most twice the path's own speed: a carriage far behind catches up over a few set-points rather
            # than at the rig's top speed, a force on the specimen the dry run never saw
            motor = (motor[0], min(v_max, CATCH_UP * motor[1], max(motor[1], abs(motor[0] - at) / left)), motor[2])
        x_cmd = self._move_motor(*motor) if motor is not None else math.nan
        if self.inst.amplifier is not None and not streamed:
            self._set_voltage(self.ctx.v_req if tick.voltage is None else tick.voltage, t_rec, x_cmd)
        elif tick.motor is not None:
            self._record_setpoint(t_rec, math.nan, x_cmd)
        self.snapshot.values["setpoint"] = self.ctx.v_cmd

    def _check_voltage(self, v: float) -> tuple[float, float]:
        """The supervisor's checks of a voltage set-point before it is sent: the request and the value the module
        will output (SafetyTrip if either is refused); returns (the bound, that value)."""
        self.sup.check_setpoint(v)
        bound = self.sup.setpoint_bound()
        want = self.ctx.amp.quantise(v, within=bound)
        self.sup.check_setpoint(want)
        return bound, want

    def _move_motor(self, target: float, vel: float, acc: float) -> float:
        """Send a supervised go-to; returns the commanded aperture [m]. The position checked and sent is the one the
        drive receives (its nearest increment, one toward the inside at a travel limit)."""
        target = self.ctx.motor.quantise(target)
        x_cmd = float(self.program.aperture(target)) if self.program.has_motor_axis else math.nan
        self.sup.check_motor_setpoint(target, x_cmd, self.ctx.v_cmd)
        if not self.motion.anchored:  # where the motor stands before its first go-to (after a start or a stop)
            r = self.ctx.motor.read_position()
            self.motion.anchor(r.timestamp - self.ctx.t0, r.value)
        self.ctx.motor.move_to(target, vel, acc)
        self.motion.commanded(self.now(), target, vel, acc)
        return x_cmd

    def _operator_confirms(self, text: str) -> bool:
        if self.operator is None:
            return False
        with self.prompt():
            return self.operator(f"set the specimen: {text}")

    def _hand_over(self, seg: Segment, what: str) -> None:
        """Before the rig goes to a person (a specimen change: the operator's prompt, or on a simulated rig the
        twin's change that rehearses it): the output *measured* at 0 V, as the shutdown verifies it
        (:meth:`_verify_safe`), not assumed from the 0 V the program commands — a relax shorter than its ramp rule
        commands 0 V at its last instant, and the prompt came at once.

        The voltage monitor (and the current monitor) is read once ``MONITOR_SETTLE_S`` have passed since the
        output was last commanded on (|V| above the interlock's ``OUTPUT_ON_V``) or off from there (fresh
        conversions of the output at 0 V: the shutdown's settle, counted from then, so a long relax costs no
        wait), then every ``MONITOR_REREAD_S`` until it reads at most ``safe_v`` (the rig's verified-safe threshold,
        :func:`bench.rig.safe_monitor_v`), for at most ``DISCHARGE_WAIT_S`` — the shutdown's threshold and bound.
        Every reading is
        recorded in the amplifier stream (a DAQ rig's stream has stopped: a set step never plays on, so its AINs
        are read by command-response, as while paused) and checked by the supervisor; the verdict is a ``handover``
        event. An output not read at 0 V within the bound (or a monitor that cannot be read) raises an
        :class:`InterlockTrip` ("output not verified", as the shutdown's): the run ends at 0 V at once and the rig
        latches; no prompt is shown, no specimen touched. Run time throughout: a virtual clock is advanced, never
        waited on."""
        amp = self.inst.amplifier
        if amp is None:
            return
        if self._streaming():  # a step that needs a person never plays on in a stream; should one play, it stops
            self._hw.stop()
            self._hw.forget()
        live = max(self._live_at, self._stream.live_at if self._stream is not None else -math.inf)
        self._wait_stoppable(live + MONITOR_SETTLE_S)
        deadline = self.now() + DISCHARGE_WAIT_S
        while True:
            self._check_stop()
            try:
                v, i = amp.read_monitors()
            except OperationCancelledError:  # a stop cancelled the link's wait: a stop, not an unverified output
                self._check_stop()
                raise
            except InstrumentError as exc:
                raise InterlockTrip("output not verified", f"before {what}: the voltage monitor could not be read "
                                    f"({exc}); the rig is not handed over") from None
            t = v.timestamp - self.ctx.t0
            self.rec.append("amplifier", t, voltage=v.value, current=i.value, **self.ctx.unpolled_monitor_columns())
            if math.isfinite(v.value) and math.isfinite(i.value):
                self.snapshot.values["voltage"], self.snapshot.values["current"] = v.value, i.value
                self.sup.check_monitors(v.value, i.value)
            if math.isfinite(v.value) and abs(v.value) <= self.safe_v:
                # the reading first: the event's 200 bytes cut the step's description, never the numbers
                self.rec.event(self.now(), seg.index, "handover", f"voltage monitor {v.value:.0f} V, current "
                               f"{i.value * 1e6:.2f} µA at {t:.3f} s: 0 V verified (|V| ≤ {self.safe_v:.3g} V) "
                               f"before {what}")
                return
            if self.now() >= deadline:
                raise InterlockTrip("output not verified", f"before {what}: the voltage monitor still read "
                                    f"{v.value:.0f} V at {t:.3f} s, {DISCHARGE_WAIT_S:g} s after the first reading "
                                    f"(safe: |V| ≤ {self.safe_v:.3g} V); the rig is not handed over")
            self._wait_stoppable(self.now() + MONITOR_REREAD_S)

    def _wait_stoppable(self, until: float) -> None:
        """Wait until run time ``until`` (a virtual clock advanced), a stop request seen every ``STOP_POLL_S``."""
        while self.now() < until - 1e-9:  # run time is rig time less t0: it may read one rounding short of it
            self._check_stop()
            self._pause_until(min(until, self.now() + STOP_POLL_S), urgent_aborts=False)

    def _segment(self, seg: Segment) -> None:
        prog, inst, rec = self.program, self.inst, self.program.protocol.recording
        self.snapshot.step, self.snapshot.step_name = seg.index, seg.name
        self.rec.event(self.now(), seg.index, "start", f"{seg.name} | {seg.label}")
        if seg.changes:
            text = ", ".join(f"{k} = {v}" for k, v in seg.changes.items())
            if self.apply_specimen is not None or self.operator is not None:
                self._hand_over(seg, f"the specimen change of step {seg.index} ({seg.name}: {text})")
            if self.apply_specimen is not None:
                self.apply_specimen(seg.changes)
            elif not self._operator_confirms(text):
                raise StopRequested(f"operator did not confirm '{seg.name}' ({text})")
            if isinstance(self.sup.specimen, LozengeParams):  # the limits follow the specimen now mounted
                proto, mass = seg.changes.get("prototype"), seg.changes.get("hung_mass_kg")
                self.sup.specimen = self.sup.specimen.changed(None if proto is None else int(proto), mass)
            self.rec.event(self.now(), seg.index, "specimen", text)
        streamed = self._stream is not None and seg.duration > 0
        laser_serial = inst.laser is not None and not (self._stream is not None and self._stream.has_laser)
        storing = seg.storing and laser_serial
        if storing:
            self.ctx.laser.start_buffer(1.0 / rec.displacement_Hz)
            self._storing = True
            self.ctx.fetch_next = -math.inf  # the step's uploads start their own grid (the fetch poll's first run)
            self.ctx.fetch_moved = self.now()
        if streamed:
            self.ctx.wait_until(seg.t_start)
            self._hw.start(seg)
        state = StepState(seg, streamed, laser_serial, storing)
        polls = {p.name: (p, per) for p in rig_polls(self.ctx) if (per := p.period(self.ctx, state)) is not None}
        count = {k: p.first for k, (p, _) in polls.items()}
        due = {k: seg.t_start + n * polls[k][1] for k, n in count.items()}  # from counts: no drift
        schedule = ticks(prog, seg)  # the set-point schedule the dry run also executes
        if streamed:  # the device plays the voltage: a tick without a go-to has nothing to send, so no wake-up
            schedule = (tk for tk in schedule if tk.motor is not None or tk.end) \
                if seg.move is not None or seg.position is not None else iter([end_tick(seg)])
        tick, following = next(schedule, None), next(schedule, None)
        skipped = Skipped()
        # a skip never moves the output (as sent: the module's code) further in one set-point than twice the step's
        # own largest move as planned
        jump = 2 * largest_voltage_change(prog, seg) + 1e-6 if inst.amplifier is not None and not streamed \
            else math.inf
        try:
            self._steps_of(seg, polls, count, due, schedule, (tick, following), skipped, streamed, jump)
        finally:  # a stop, a trip or a pause inside the step: what it skipped so far is said too
            if skipped.setpoints or skipped.polls:
                self.skipped += skipped.setpoints
                self._record(self.rec.event, self.now(), seg.index, "skipped", skipped.text())
        self.ctx.wait_until(seg.t_end)
        v_end = end_tick(seg).voltage if seg.duration > 0 else None  # the schedule's end value (ticks' last)
        if streamed:
            self._hw.finish()  # the device played the end value itself
        elif inst.amplifier is not None and v_end is not None and v_end != self.ctx.v_req:
            # ticks stop before t_end: a ramp must reach its end
            self._set_voltage(v_end, self._sent_at(seg.t_end + self.ctx.offset))
        zeroed = False
        if storing:
            self.ctx.laser.stop_buffer()
            zeroed = self._drain_after(seg, {k: d + self.ctx.offset for k, d in due.items()})
            self._storing = False  # only now: a stop in the drain leaves what is left to the shutdown's fetch
        if not zeroed and self._stream is None:  # zeroed: the next step restarts, its schedule set by the restart;
            self._keep_schedule(seg)  # a DAQ rig: the device plays each step whole on its own clock
        self.rec.event(self.now(), seg.index, "end", seg.name)
        segs = self.program.segments
        # a pause asked for during the drain: no ramp back up to the next step's value — the next step's first
        # wait raises PauseRequested, and the resume restarts that step
        if zeroed and (k := segs.index(seg) + 1) < len(segs) and not self._paused_wanted()[0]:
            self._restart(segs[k], f"the output went to 0 V while step {seg.index}'s stored laser data uploaded")
        # the last steps' data compresses while the next steps run (where no FLUSH_CHUNKS write comes before the end)
        self.rec.write_ahead(STEP_END_CHUNKS, max(0.0, self.program.duration - seg.t_end))

    # ------------------------------------------------------------ pause, resume, a resumed start
    def _state_before(self, seg: Segment) -> tuple[float, float | None]:
        """(voltage, motor position) ``seg`` starts from: its own first value where it sets one (a waveform, a
        ramp), else the last end value of a step before it that sets one (0 V, no motor move when none does) —
        a restart never brings back a value the step itself leaves at once (a raised cosine from 0 V after a
        ramp's 5 kV: a pulse the protocol does not ask for there)."""
        # (a relax's own first value is the value it ramps down from: its first set-point sends it, so a restart
        # ramps up to it first, never leaving the step to jump there)
        own_v, own_x = voltage_at(seg, seg.t_start), self._start_position(seg)
        volts, motor = self._end_state_before(seg)
        return (volts if own_v is None else own_v), (motor if own_x is None else own_x)

    def _start_position(self, seg: Segment) -> float | None:
        """The motor position a waveform or ramp on the aperture starts at (None: the step sets none itself)."""
        m = self.program.rig.motor
        if m is None or not self.program.has_motor_axis or seg.position is None:
            return None
        x = float(self.program.motor_position(float(seg.position(np.array([seg.t_start]))[0])))
        return min(max(x, m.travel_m[0]), m.travel_m[1])

    def _end_state_before(self, seg: Segment) -> tuple[float, float | None]:
        """(voltage, motor position) the program holds when ``seg`` starts: the last end value of a step before
        it that sets one (0 V, no motor move when none does)."""
        prog, volts, motor = self.program, 0.0, None
        m = prog.rig.motor
        for s in prog.segments[:prog.segments.index(seg)]:
            end = voltage_at(s, s.t_end)
            if end is not None:
                volts = end
            if m is not None and prog.has_motor_axis:
                x = s.move[0] if s.move is not None else float(s.position(np.array([s.t_end]))[0]) \
                    if s.position is not None else None
                if x is not None:
                    motor = min(max(float(prog.motor_position(x)), m.travel_m[0]), m.travel_m[1])
        return volts, motor

    def _resume_specimen(self, seg: Segment) -> None:
        """A resumed campaign: the specimen as the steps before ``seg`` left it (temperature, prototype, load),
        applied to a simulated rig or confirmed by the operator, and recorded as a ``specimen`` event."""
        changes: dict[str, float | int] = {}
        for s in self.program.segments[:self.program.segments.index(seg)]:
            changes.update(s.changes)
        if not changes:
            return
        text = ", ".join(f"{k} = {v}" for k, v in changes.items())
        if self.apply_specimen is not None or self.operator is not None:
            self._hand_over(seg, f"the resumed campaign's specimen check ({text})")
        if self.apply_specimen is not None:
            self.apply_specimen(changes)
        elif not self._operator_confirms(text):
            raise StopRequested(f"operator did not confirm the specimen for the resumed campaign ({text})")
        self.rec.event(self.now(), seg.index, "specimen", text)

    def _ramp_to(self, target: float, seconds: float, steps: int = RAMP_STEPS,
                 after: Callable[[], object] | None = None) -> None:
        """Supervised set-points from the present one to ``target`` in ``steps`` equal steps, the k-th ``seconds``
        × k/steps after the ramp began (command-response); ``after()`` follows each set-point."""
        v0, t0 = self.ctx.v_cmd, self.now()
        for k in range(1, steps + 1):
            self._pause_until(t0 + seconds * k / steps, urgent_aborts=False)
            self._check_stop()
            # the last one the target itself: from a start one code off 0 V, v0 + (target − v0)·1 came out
            # 8000.000000000001 for 8 kV, which the driver refused at the limit after the whole ramp (an outside tester)
            self._set_voltage(target if k == steps else v0 + (target - v0) * k / steps, self.now())
            if after is not None:
                after()

    def _step_text(self, seg: Segment) -> str:
        """A step as the CLI names it (``bench run --resume``, ``report``): from 1, with its 0-based index (the
        events' step column) and name."""
        return f"step {seg.index + 1} of {len(self.program.segments)} (index {seg.index}, {seg.name})"

    def _restart(self, seg: Segment, why: str) -> None:
        """Bring the rig to the state the program holds at the start of ``seg`` (motor to its position with the
        output at 0 V, then the voltage ramped up over ``shutdown_ramp_s``) and shift the program so that ``seg``
        starts now; recorded as events."""
        ramped = relax_at_zero(seg)
        volts, motor = self._state_before(seg)
        rest = "" if ramped is None or abs(ramped) <= OUTPUT_ON_V else (
            f" (a relax: its ramp from {ramped:.0f} V to 0 V is not played again, the output is at 0 V already)")
        self.rec.event(self.now(), seg.index, "restart", f"{why}; {self._step_text(seg)} restarts from its "
                       f"start: {'' if motor is None else f'motor to {motor * 1e3:.2f} mm, '}output to {volts:.0f} V"
                       + rest)
        if motor is not None and self.inst.motor is not None:
            m = self.program.rig.motor
            assert m is not None
            self._move_motor(motor, 0.25 * m.max_velocity_m_per_s, m.max_acceleration_m_per_s2)
            deadline = self.now() + RESTART_MOVE_S
            while abs(self.ctx.motor.read_position().value - motor) > self.program.rig.limits.travel_tolerance_m:
                self._check_stop()
                if self.now() > deadline:
                    raise InstrumentStateError("motor", f"did not reach {motor * 1e3:.2f} mm within "
                                               f"{RESTART_MOVE_S:g} s to restart {self._step_text(seg)}")
                self._pause_until(self.now() + 0.02, urgent_aborts=False)
        ramp = self.program.rig.limits.shutdown_ramp_s
        up = self.inst.amplifier is not None and abs(volts - self.ctx.v_cmd) > RESTART_STEP_V
        start = None  # run time at which the step starts on the scan clock (its values appended to the ramp's)
        if up and self._stream is not None:  # a DAQ rig: the DAQ plays the ramp, recorded on its scan clock
            start = self._stream_ramp_up(volts, ramp, RESTART_SETTLE_S,
                                         seg if seg.duration > 0 and not seg.changes else None)
        elif up:
            # supervised as a step is: the monitors (and the other polled sensors) read, recorded and checked
            # after every set-point of the ramp up, not only once the next step has started
            supervise = self._supervised()
            self._ramp_to(volts, ramp, after=supervise)
            # the last step's charging current (at the amplifier's current limit for tens of µs) is over before
            # the step's own acquisition starts
            self._pause_until(self.now() + RESTART_SETTLE_S, urgent_aborts=False)
            supervise()
        self.ctx.v_req = volts
        self.ctx.offset = (self.now() if start is None else start) - seg.t_start
        self.rec.event(self.now(), seg.index, "offset", f"run time = program time + {self.ctx.offset:.9f} s")

    def _pause(self, seg: Segment) -> None:
        """Paused: the step under way is left, the output ramped to 0 V, the motor held where it is, the monitors
        and sensors read on; on resume the step restarts from its start. A stop request ends the run."""
        _, by = self._wanted_now()
        by = by or "a pause request"
        self._paused_by, self._pending_pause, self._resume_asked = by, None, None
        t_pause = self.now()
        self.pauses += 1
        self.snapshot.state = "paused"
        self.rec.event(t_pause, seg.index, "pause", f"paused in step {seg.index} ({seg.name}) by {by}: output "
                       f"ramping to 0 V over {self.program.rig.limits.shutdown_ramp_s:g} s, motor held, recording "
                       "goes on")  # (it said "output to 0 V" while 6 kV was still on: outside tester)
        self._make_paused()
        due = self.now() + RESTART_SETTLE_S  # the ramp's last charging current is over before the first reading
        said = False
        while self._paused_wanted()[0]:
            self._check_stop()
            if self.now() >= due - 1e-9:  # run time is rig time less t0: it may read one rounding short of due
                self._paused_readings()
                due += PAUSE_POLL_S
                said = said or self._paused_at_zero(seg)
            self._pause_until(min(due, self.now() + STOP_POLL_S), urgent_aborts=False)
        _, by = self._wanted_now()  # the resume the loop ended on
        self._pause_by = self._resume_by = self._paused_by = self._resume_asked = None
        if self.on_paused is not None:
            self.on_paused(None)
        self.rec.event(self.now(), seg.index, "resume", f"resumed by {by} after {self.now() - t_pause:.3f} s paused")
        self.snapshot.state = "running"
        self._restart(seg, "resumed after a pause")

    def _make_paused(self) -> None:
        """The paused state, a run's or a manual session's: a playing stream stopped, the motor stopped where it is
        (first: a move under way does not go on through the ramp), the output ramped to 0 V over ``shutdown_ramp_s``
        (supervised set-points), then stored laser data fetched (supervised, :meth:`_drain_laser`)."""
        if self._stream is not None:
            self._stream.stop(whole=True)  # no scan lost before the ramp's stream takes over
            self._stream.forget()
        if self.inst.motor is not None and (self.program.has_motor_axis or self.commands):
            self.ctx.motor.stop()
            self.motion.stopped(self.now())
        if self.inst.amplifier is not None and self._stream is not None and abs(self.ctx.v_cmd) > OUTPUT_ON_V:
            # the DAQ plays the ramp and records the specimen's response through it, on the scan clock
            self._stream_ramp(self.ctx.v_cmd, self.program.rig.limits.shutdown_ramp_s, RESTART_SETTLE_S, pause=True)
            self._set_voltage(0.0, self.now())  # the DAC already holds 0 V: the host's record of it, verified
        elif self.inst.amplifier is not None:
            # supervised as a step is (as the restart's ramp up): the monitors read, recorded and checked after
            # every set-point, so that an output not following the ramp to 0 V latches during it
            self._ramp_to(0.0, self.program.rig.limits.shutdown_ramp_s, after=self._supervised())
        if self._storing and self.inst.laser is not None:  # at 0 V: the pause does not wait on the upload
            self.inst.laser.stop_buffer()
            # a pause is no stop or fault: the run goes on, supervised, so its upload has a step's drain budget
            # (LASER_SHUTDOWN_DRAIN_S is the shutdown's, past which what is left is only reported)
            self._drain_laser(LASER_DRAIN_BUDGET_S)
            self._storing = False  # only now: a stop in the upload leaves what is left to the shutdown's fetch

    def _paused_at_zero(self, seg: Segment) -> bool:
        """After the pause's first reading: a ``verify`` event with the voltage monitor's reading at the 0 V
        commanded (the verifier has judged it: an output that stays up latches), so that the file says the output
        was seen at 0 V, not only that 0 V was asked for; False where no monitor was read."""
        v = self.snapshot.values.get("voltage")
        if self.inst.amplifier is None or v is None or not math.isfinite(v):
            return False
        text = f"0 V commanded: the voltage monitor reads {v:.0f} V at {self.now():.3f} s"
        self._record(self.rec.event, self.now(), seg.index, "verify", text)
        if self.on_paused is not None:
            self.on_paused(text)
        return True

    def _paused_readings(self) -> None:
        """One reading of every polled channel while paused, through the run's polls: the monitors (by
        command-response on a DAQ rig; no lateness, the pause schedules them, not the program) recorded,
        supervised and verified against the 0 V commanded — an output that stays up latches — and the set-point
        module kept fed."""
        if self.inst.amplifier is not None and self._stream is None and self.ctx.unheard_for() >= HOLD_KEEPALIVE_S:
            self._set_voltage(0.0, self.now())
        if self._stream is not None and self._stream.has_laser:
            self._stream.read_laser()  # the laser's AIN by command-response, at the pause's rate (README: pause)
        for poll in rig_polls(self.ctx):
            if poll.name == "monitors":
                poll.run(self.ctx, math.nan)
            elif poll.name in ("position", "force") and poll.period(self.ctx, PAUSED) is not None:
                poll.run(self.ctx, self.program_now())

    # ------------------------------------------------------------ run and shut down
    def run(self) -> RunResult:
        """Run the whole program; always returns with the rig safe and the file finalised."""
        wall0 = time.perf_counter()
        signals = self.signals()
        signals.__enter__()
        self.ctx.t0 = self.clock.now()
        state, reason = "completed", "protocol completed"
        try:
            self.snapshot.state = "running"
            self.rec.event(0.0, -1, "run", "start")
            if self.inst.amplifier is not None:  # what connecting left the output at (0 V)
                self.verifier.commanded(0.0, self.ctx.v_cmd)
            segs = self.program.segments
            k = self.start_step
            if k > 0:
                self._resume_specimen(segs[k])
                self._restart(segs[k], f"resumed campaign: steps 1–{k} of {len(segs)} ran in the previous file"
                              if k > 1 else f"resumed campaign: step 1 of {len(segs)} ran in the previous file")
            while k < len(segs):
                try:
                    self._segment(segs[k])
                    k += 1
                except PauseRequested:
                    self._pause(segs[k])
        except InterlockTrip as trip:
            self.latched = trip
            state, reason = "tripped", f"safety trip: {trip.reason}"
        except SafetyTrip as trip:
            self.tripped = trip
            state, reason = "tripped", f"safety trip: {trip.reason}"
        except StopRequested as stop:
            state, reason = "interrupted", str(stop)
        except OperationCancelledError:
            state, reason = "interrupted", self._stop_reason or "stop requested"
        except InstrumentConnectionError as exc:
            state, reason = "error", f"lost link: {exc}"
        except InstrumentError as exc:
            state, reason = "error", f"instrument error: {exc}"
        except Exception as exc:
            if _is_storage_fault(exc):
                self._storage_failed = True
                state, reason = "error", f"storage fault: {exc}"
            else:
                state, reason = "error", f"internal error: {type(exc).__name__}: {exc}"
        try:
            safe_path = self._shut_down(state, reason)
            state, reason = self.ended  # a trip during the ramp to 0 V: "tripped", not "completed"
        finally:
            signals.__exit__(None, None, None)
        if (self._storage_failed or self.rec.failed) and state != "error":
            # the run itself ended, but the file could not record its end: it is not a complete record
            state, reason = "error", f"storage fault: {self.rec.failure or 'run file not finalised'} (after: {reason})"
        return RunResult(str(self.rec.path), state, reason, self.now(), time.perf_counter() - wall0,
                         self.rec.samples_written, self.overruns, safe_path, self.latch_fault or "", self.skipped)

    @property
    def latch_fault(self) -> str | None:
        """The fault the run latches its rig for: an interlock fault, else the supervisor's limit trip (the
        README's standard: a fault latches until an operator resets it); None if the run ended without one."""
        if self.latched is not None:
            return self.latched.reason
        if self.tripped is not None:
            return f"safety trip: {self.tripped.reason}"
        return None

    @property
    def zero_verified(self) -> bool:
        """Whether the shutdown read 0 V back from the voltage monitor."""
        return self._zero_verified

    def _record(self, fn: Callable[..., object], *args: Any, **kwargs: Any) -> None:
        """A recorder call during shutdown: a storage fault must not stop the rig being made safe."""
        if self._storage_failed:
            return
        try:
            fn(*args, **kwargs)
        except Exception as exc:
            if not _is_storage_fault(exc):
                raise
            self._storage_failed = True

    def _event(self, kind: str, text: str) -> None:
        if self.on_event is not None:
            self.on_event(kind, text)
            return
        self._record(self.rec.event, self.now(), self.snapshot.step, kind, text)

    def _shut_down(self, state: str, reason: str, finish: bool = True) -> str:
        """Motor stopped, voltage to zero, instruments safe, safe state verified, the motor's final position read,
        file finalised (unless not ``finish``: manual mode ends its file after its last log line).

        Returns the account of how the output was made safe (also in the file's events and reason).
        """
        self._stopping = True
        self.inst.cancel.clear()  # the shutdown's own commands must go out
        motor = self._stop_motor()  # first of all: a commanded move must not go on through the voltage's ramp
        self.snapshot.state = "stopping"
        notes: list[str] = []
        t = self.now()
        if self._stop_at is not None:
            self._event("request", f"stop requested at {self._stop_at:.3f} s: {self._stop_reason}")
        self._event("stop" if state == "completed" else state, reason)
        if self.latched is not None:
            self._event("interlock", f"latched at {t:.3f} s ({self.latched.kind}); the output stays at 0 V until an "
                        "operator resets the latch")
        zero_at = self._zero_voltage(t, notes)
        if zero_at is not None:  # the live view's last frame: what is commanded now, not the set-point before the stop
            self.snapshot.values["setpoint"] = self.ctx.v_cmd
        self._record(self.rec.write_ahead)  # 0 V commanded: the file's tail compresses while the rest is made safe
        notes += self._others_safe()
        if self._storing and self.inst.laser is not None:
            try:
                self.inst.laser.stop_buffer()
                self._storing = False
                self._drain_laser(LASER_SHUTDOWN_DRAIN_S)
            except (InstrumentError, SafetyTrip, StopRequested) as exc:
                notes.append(f"stored laser data not (all) fetched: {exc}")
            except Exception as exc:
                if not _is_storage_fault(exc):
                    raise
                self._storage_failed = True
        safe_path = self._verify_safe(zero_at, notes)
        self._latch_unproven(zero_at, safe_path)
        if self.latched is None and self.tripped is not None:  # a limit trip latches too, once 0 V was verified
            self._event("interlock", f"latched at {self.now():.3f} s (safety trip, 0 V verified): nothing energises "
                        "the rig until an operator resets the latch")
        self._motor_stopped(motor, notes)
        self._record_safe_state()
        if not self.clock.virtual or self.overruns or self.skipped:  # virtual: said when the wires outran it
            self._event("timing", f"{self.overruns} late actions (> {LATE_TOLERANCE_S * 1e3:.0f} ms), worst "
                        f"lateness {self.ctx.worst_lateness * 1e3:.1f} ms"
                        + (" of rig time (virtual clock)" if self.clock.virtual else "")
                        + (f"; {self.skipped} set-points skipped, behind the schedule" if self.skipped else ""))
        for note in notes:
            self._event("fault", note)
        if not self.commands:  # a request that came too late to change anything is recorded, not lost
            self._take_requests(ending=state)
        self._event("safe", safe_path)
        if self._ramp_fault is not None and state in ("completed", "interrupted"):  # the run's end was not clean:
            # a limit trip or an interlock fault in the ramp to 0 V (ADAM rigs' monitor reads) said "completed"
            why = self._ramp_fault.reason
            state, reason = "tripped", f"safety trip during the ramp to 0 V: {why} (after: {reason})"
        self.ended = (state, reason)
        if finish:
            self._record(self.rec.finish, state, f"{reason} | {safe_path}")
        self.snapshot.state = state
        return safe_path

    def _zero_voltage(self, t: float, notes: list[str]) -> float | None:
        """Ramp the set-point to 0 V (cut short by a second stop request) and command 0 V.

        Returns the run time at which 0 V was confirmed commanded by the module, or None if it could not be.
        """
        amp = self.inst.amplifier
        if amp is None:
            return None
        amp.hurry(SHUTDOWN_REPLY_S)
        unanswered = False
        streamed: float | None = None
        cut_short = False  # a second stop request cut short a ramp the DAQ's stream-out was to play
        if self._stream is not None:
            try:
                # the DAC holds the last value played; the ramp continues from it. Whole packets first (at most
                # one packet's time), so that no scan is lost before the ramp's stream — not when 0 V is due at once,
                # nor after a storage fault: no scan could be kept, and the device would play on meanwhile (the fault
                # matrix: a full disk at a cycle's trough let the next step's ramp up drive 0 V to 222 V)
                self._stream.stop(whole=self.latched is None and not self._urgent.is_set()
                                  and not self._storage_failed)
            except InstrumentError as exc:
                notes.append(f"stopping the DAQ stream failed: {exc}")
                unanswered = True  # the request may have arrived; a ramp of unanswered requests only delays 0 V
        ramp = self.program.rig.limits.shutdown_ramp_s
        v0 = self.ctx.v_cmd
        if self.latched is None:
            try:
                self.ctx.guard(streaming=self._stream is not None)  # a stall before a stop: the ramp would re-energise
            except InterlockTrip as trip:
                self.latched = trip
                self._event("interlock", trip.reason)
        if whole(v0) == "0":  # nothing to ramp: a set-point under 0.5 V (a resumed run's log ended "ramp from 0 V
            v0 = 0.0  # to 0 V", outside tester); 0 V is commanded below all the same (safe_state), with no ramp line
        if self.latched is not None and v0 != 0.0:
            self._event("ramp", f"interlock latched ({self.latched.kind}): 0 V at once, no ramp from a set-point the "
                        "output may no longer hold")
            v0 = 0.0
        elif unanswered and v0 != 0.0:
            self._event("ramp", "the set-point module did not answer: 0 V at once, no ramp")
            v0 = 0.0
        try:
            if v0 != 0.0 and self._urgent.is_set():
                self._event("ramp", "second stop request before the ramp began: 0 V at once")
                cut_short = self._stream is not None and abs(v0) > OUTPUT_ON_V
            if v0 != 0.0 and not self._urgent.is_set():
                self._event("ramp", f"ramp from {whole(v0)} V to 0 V over {ramp:g} s" + (
                    f", played by the DAQ's stream-out; the inputs recorded on its scan clock until "
                    f"{MONITOR_SETTLE_S:g} s after 0 V" if self._stream is not None and abs(v0) > OUTPUT_ON_V
                    else ""))

                monitors = self._ramp_monitors(notes)

                def record(sent: float) -> None:
                    self.ctx.v_cmd = sent
                    self.verifier.commanded(self.now(), sent)  # the monitors' reads are judged against the ramp
                    self._record(self.rec.append, "setpoints", self.now(), voltage=sent, aperture=math.nan)
                    monitors()

                if self._stream is not None and abs(v0) > OUTPUT_ON_V:  # (a program that ended at 0 V: no stream)
                    streamed = self._stream_ramp(v0, ramp, MONITOR_SETTLE_S)
                    if streamed is None:
                        self._event("ramp", "second stop request: 0 V at once")
                        cut_short = True
                    else:
                        self._streamed_settle = True
                        self.ctx.v_cmd = 0.0
                        self._record(self.rec.append, "setpoints", streamed, voltage=0.0, aperture=math.nan)
                elif not ramp_to_zero(amp, v0, ramp, lambda offset: self._ramp_pause(t + offset), record, RAMP_STEPS):
                    self._event("ramp", "second stop request: 0 V at once" if self.latched is None else
                                f"interlock latched during the ramp ({self.latched.kind}): 0 V at once")
        except InstrumentError as exc:
            notes.append(f"voltage ramp-down failed: {exc}")
        finally:
            if self._stream is not None:
                try:
                    self._stream.stop(whole=True)  # the ramp's stream: its last scans recorded
                except InstrumentError as exc:
                    notes.append(f"stopping the DAQ stream failed: {exc}")
                except OSError:
                    self._storage_failed = True
        try:
            amp.safe_state()
        except InstrumentError as exc:
            notes.append(f"could not command 0 V: {exc}")
            self._output_dead = True
            self._event("watchdog", "output path dead: no further request to the set-point module, so that its "
                        "communication watchdog zeroes the output as early as it can")
            return None
        if self._stream_unstopped():
            return None
        self.ctx.v_cmd = 0.0
        t_zero = self.now()
        if self._streamed_settle:  # the stream played 0 V (its set-point row is recorded) and recorded the settle
            return streamed
        self._record(self.rec.append, "setpoints", t_zero, voltage=0.0, aperture=math.nan)
        if cut_short:  # 0 V is commanded: now the settle after it, recorded as the ramp's stream would have
            self._stream_settle(t_zero, notes)
        return t_zero

    def _stream_unstopped(self) -> bool:
        """After the host's 0-V write: whether a stream stop went unanswered (the DAQ may stream on, its stream-out
        playing over that write). Then the output path is not under the host's control, as when 0 V cannot be
        written: no further request to the DAQ, so that its watchdog (which ends a stream-out's loop and takes the
        DAC to its safe value) runs out. Before, the verification's reads fed the watchdog and kept a played 3 kV up
        through the whole discharge wait (CI beside a hog and a browser: 3043 V 2.5 s after the stop). A rig whose
        DAQ has no watchdog keeps the verification's reads: they are all it has."""
        if self._stream is None or not self._hw.daq.stop_unconfirmed or watchdog_period(self.program.rig) is None:
            return False
        self._output_dead = self._stream_lost = True
        self._event("watchdog", "output path not under the host's control: the DAQ's stream stop went unanswered, "
                    "so its stream-out may play over the 0 V the host wrote; no further request to the DAQ, so that "
                    "its communication watchdog zeroes the output as early as it can")
        return True

    def _stream_settle(self, t_zero: float, notes: list[str]) -> None:
        """After 0 V commanded at once on a second stop request (the ramp's stream cut short, outside tester: the
        settle after 0 V then went unrecorded, the verifying read alone in /safe_state): the inputs recorded on the
        scan clock of a stream with no stream-out (:meth:`HardwareTimed.record_zero`) until ``MONITOR_SETTLE_S``
        after 0 V, as after a ramp the DAQ plays; the verifying read follows its last scan. 0 V is not delayed:
        the host commanded it before. A stream that fails leaves the settle to the verification's wait, said."""
        hw, end = self._hw, t_zero + MONITOR_SETTLE_S
        try:
            hw.record_zero()
            give_up = end + 1.0  # rig time: packets that stop coming end the wait
            while hw.recorded_to() < end - 1e-9 and self.now() < give_up:
                self._pause_until(max(self.now() + FINISH_POLL_S, min(end, self.now() + STREAM_RAMP_POLL_S)),
                                  urgent_aborts=False)
                hw.collect_quiet()
            hw.stop(whole=True)
        except (InstrumentError, OSError) as exc:
            if isinstance(exc, OSError):  # a storage fault: the rig is made safe all the same
                self._storage_failed = True
            else:
                notes.append(f"the inputs after 0 V not recorded on the scan clock: {exc}")
            with contextlib.suppress(InstrumentError, OSError):
                hw.stop()
            return
        self._settle_recorded = True

    def _ramp_monitors(self, notes: list[str]) -> Callable[[], None]:
        """The shutdown ramp's monitor reads on a rig whose set-points the host sends (the ADAM rigs; a DAQ rig's
        ramp is played and recorded on its scan clock, :meth:`_stream_ramp`): called after each of the ramp's
        set-points, the monitors poll runs when due at its step period (the protocol's monitor rate, the first with
        the ramp's first set-point), recorded in the amplifier stream as a step's reads are (its columns, its
        lateness) and checked by the supervisor and the output verifier, so that the file has the output's ramp to
        0 V measured, not only commanded, and a fault during it is seen when it happens, not at the final verify.

        Nothing here holds the ramp back from 0 V: a read that fails (or raises anything) is noted (a ``fault``
        event) and the ramp goes on unread; a limit trip is recorded (``tripped``, the rig latched after the
        verified 0 V, as a step's trip) and the ramp goes on, as it does after a step's trip; an interlock fault
        (the output not following the ramp) latches and the next pause of the ramp ends it: 0 V at once."""
        poll = next((p for p in rig_polls(self.ctx) if p.name == "monitors"), None)
        period = poll.period(self.ctx, PAUSED) if poll is not None else None
        if poll is None or period is None:
            return lambda: None
        run = poll.run
        nxt: list[float] = []  # the next read's run time (set by the first set-point)
        said: set[str] = set()

        def read() -> None:
            now = self.now()
            if "failed" in said:
                return
            if not nxt:
                nxt.append(now)
            if nxt[0] > now + 1e-12:
                return
            due = nxt[0]
            nxt[0] = next_slot(due, now, period)
            try:
                run(self.ctx, due - self.ctx.offset)
            except InterlockTrip as trip:
                if self.latched is None:
                    self.latched = self._ramp_fault = trip
                    self._event("interlock", f"latched at {now:.3f} s, during the ramp to 0 V ({trip.kind}): "
                                f"{trip.detail}; 0 V at once, and the output stays at 0 V until an operator resets "
                                "the latch")
            except SafetyTrip as trip:
                if self.tripped is None and self.latched is None:
                    self.tripped = self._ramp_fault = trip
                    self._event("tripped", f"during the ramp to 0 V at {now:.3f} s: safety trip: {trip.reason}; "
                                "the ramp goes on to 0 V")
                elif "limit" not in said:
                    self._event("ramp", f"{trip.reason} during the ramp to 0 V at {now:.3f} s")
                said.add("limit")
            except Exception as exc:
                if _is_storage_fault(exc):  # the file failed: the reads go on, checked (poll_once)
                    self._storage_failed = True
                    return
                said.add("failed")
                text = str(exc) if isinstance(exc, InstrumentError) else f"{type(exc).__name__}: {exc}"
                notes.append(f"monitor read during the ramp to 0 V failed at {now:.3f} s ({text}): the ramp went "
                             "on without its monitor reads")
        return read

    def _stream_ramp(self, v0: float, ramp: float, settle: float, pause: bool = False) -> float | None:
        """The ramp from ``v0`` to 0 V played by the DAQ's stream-out (:meth:`HardwareTimed.ramp_down`), the inputs
        recorded on the scan clock through it and ``settle`` s after 0 V: the specimen's response to the ramp is
        measured, not only commanded. Returns the run time of the scan that played 0 V; None when a second stop
        request cut it short (the caller then commands 0 V at once). In a pause (``pause``) a stop request ends
        it as at any other time (:class:`StopRequested`: the shutdown ramps on from the value last played)."""
        hw = self._hw
        t_zero = hw.ramp_down(v0, ramp)
        self._record(self.rec.append, "setpoints", max(hw.ramp_start, self._setpoint_t), voltage=v0, aperture=math.nan)
        end = t_zero + settle
        give_up = end + 1.0  # rig time: packets that stop coming end the wait (the DAC plays the ramp regardless)
        while hw.recorded_to() < end - 1e-9 and self.now() < give_up:
            if pause:
                self._check_stop()
                self._pause_until(max(self.now() + FINISH_POLL_S, min(end, self.now() + STREAM_RAMP_POLL_S)),
                                  urgent_aborts=False)
            elif not self._pause_until(max(self.now() + FINISH_POLL_S, min(end, self.now() + STREAM_RAMP_POLL_S))):
                hw.stop()
                return None
            try:
                hw.collect_quiet()
            except OSError:  # a storage fault: the rig is made safe all the same (a run's own collect raises it)
                if pause:
                    raise
                self._storage_failed = True
        hw.stop(whole=True)
        return t_zero

    def _stream_ramp_up(self, v1: float, ramp: float, settle: float, then: Segment | None) -> float | None:
        """A restart's ramp up on a DAQ rig, played by the DAQ's stream-out (:meth:`HardwareTimed.ramp_up`) from the
        value the DAC holds to ``v1`` over ``ramp`` s, the inputs recorded on the scan clock through it and ``settle``
        s after it and supervised as a step's are (every scan checked by the supervisor and the output verifier; the
        other polled sensors at their step rates). A stop request or a trip meanwhile ends the run as in a step: the
        shutdown ramps to 0 V from the value last played. ``then``: the step that starts next, played on the same
        stream from ``settle`` s after ``v1`` (returns the run time of the scan that plays its start); without it
        (None returned) the stream is stopped after the settle (the DAC holds ``v1``) and the step arms its own."""
        hw, v0 = self._hw, self.ctx.v_cmd
        self._check_stop()
        t_end, start = hw.ramp_up(v1, ramp, settle, then)
        self._record_setpoint(max(hw.ramp_start, self._setpoint_t), v0, math.nan)
        supervise = self._supervised()  # the stream plays now: its collect is among the polls
        end = t_end + settle
        give_up = end + 1.0  # rig time: packets that stop coming end the run (the DAC holds v1 meanwhile)
        # with the step in the stream its collects go on recording the settle's last scans, so the wait is on the
        # clock (the step starts on time) and give_up cannot come first: packets that stop coming end the run in
        # the collect's own timeout then
        while (self.now() if then is not None else hw.recorded_to()) < end - 1e-9:
            self._check_stop()
            if self.now() > give_up:
                raise InstrumentTimeoutError(hw.daq.name, f"the restart's ramp up: scans recorded to "
                                             f"{hw.recorded_to():.3f} s of {end:.3f} s")
            self._pause_until(max(self.now() + FINISH_POLL_S, min(end, self.now() + STREAM_RAMP_POLL_S)),
                              urgent_aborts=False)
            supervise()
            hw.collect()
        if then is None:
            hw.stop(whole=True)
        self._record_setpoint(max(t_end, self._setpoint_t), v1, math.nan)
        self.snapshot.values["setpoint"] = self.ctx.v_cmd
        return None if then is None else start

    def _ramp_pause(self, until: float) -> bool:
        """The shutdown ramp's wait before its next set-point: False (0 V at once) on a second stop request, or when
        the set-point module went unheard past the stall bound meanwhile (the next step would re-energise an
        output its watchdog zeroed)."""
        if not self._pause_until(until):
            return False
        if self.latched is not None:  # latched by the ramp's own monitor reads (:meth:`_ramp_monitors`): 0 V at once
            return False
        try:
            self.ctx.guard()
        except InterlockTrip as trip:
            self.latched = trip
            self._event("interlock", trip.reason)
            return False
        return True

    def _others_safe(self) -> list[str]:
        """Every instrument but the amplifier and the motor (:meth:`_stop_motor`) to its safe state, each
        independently."""
        notes, drivers = [], dict(self.inst.items())  # by role: the rig's extra sensors are no attribute of inst
        roles = [r for r in drivers if r not in ("amplifier", "motor")
                 and not (r == "daq" and self._output_dead)]  # a dead output path: the DAQ's watchdog must run out
        for role in roles:
            try:
                drivers[role].safe_state()
            except InstrumentError as exc:
                notes.append(f"{role} safe state failed: {exc}")
            except Exception as exc:  # anything a dead port lets out: said, and the next instrument still made safe
                notes.append(f"{role} safe state failed: {type(exc).__name__}: {exc}")
        return notes

    def _latch_unproven(self, zero_at: float | None, safe_path: str) -> None:
        """Latch the rig when the host could not command 0 V (a dead output path: its watchdog had to zero it) or
        could not read 0 V back at the end: the output was not under the host's control, so nothing may energise the
        rig again until an operator has looked at it and reset the latch. A fault latched earlier stays the one
        named."""
        if self.latched is not None or self.inst.amplifier is None:
            return
        if zero_at is None:
            trip = InterlockTrip("output path dead", ("0 V not under the host's control" if self._stream_lost else
                                                      "0 V could not be commanded by the host") + f" ({safe_path})")
        elif not self._zero_verified:
            trip = InterlockTrip("output not verified", f"0 V was commanded but not read back ({safe_path})")
        else:
            return
        self.latched = trip
        self._event("interlock", f"latched at {self.now():.3f} s ({trip.kind}): {trip.detail}; nothing energises "
                    "the rig until an operator resets the latch")

    def _stop_motor(self) -> _MotorStop | None:
        """Stop the motor at once — the start of every shutdown — without holding the voltage's zeroing back.

        Before, the motor was stopped only after the voltage's ramp-down (``shutdown_ramp_s``), so a go-to under way
        went on through the whole ramp, and a slow motor link could not have been put first without delaying the
        ramp. Now the motor's safe state (the LinMot's abort: the drive decelerates on its own quick-stop ramp and
        holds) goes out first, with the driver's reply waits cut to ``SHUTDOWN_REPLY_S`` (the abort acts when it
        arrives; its reply only confirms it), and:

        * on the wall clock on a thread of its own, concurrently with the ramp: a serial write goes out at once
          whatever the line does next, while a silent drive (its reply timeout) or a dirty link (the driver first
          drains a reply a cancelled read left, up to its quiet-line bound) would otherwise delay the ramp's start
          past the 0.2-s bound. Sending it first in line with a short timeout keeps the motor's bound but not the
          voltage's; the thread keeps both;
        * in virtual time in line, before the ramp: the rig clock moves only with the bytes on the wire, so a thread
          racing the ramp's jumps of the clock would stamp the abort wherever the host's scheduling put it (up to
          the whole ramp late); in line it costs its wire time (ms), or ``SHUTDOWN_REPLY_S`` when the drive stays
          silent — within the ramp's bound.

        :meth:`_motor_stopped` waits for it, reads the final position and records both."""
        motor = self.inst.motor
        if motor is None:
            return None
        stop = _MotorStop(self.now())

        def send() -> None:
            try:
                motor.hurry(SHUTDOWN_REPLY_S)
                motor.safe_state()
                stop.done_at = self.now()
            except InstrumentError as exc:
                stop.error = str(exc)
            except Exception as exc:  # anything a dead port lets out: said, and the rest of the stop goes on
                stop.error = f"{type(exc).__name__}: {exc}"

        if self.clock.virtual:
            send()
        else:
            stop.thread = threading.Thread(target=send, name="motor-stop", daemon=True)
            stop.thread.start()
        if self.program.has_motor_axis or self.commands:
            self.motion.stopped(stop.sent_at)
        return stop

    def _motor_stopped(self, stop: _MotorStop | None, notes: list[str]) -> None:
        """The motor's stop, accounted for: waited for (its thread), tried once more if it failed, then the drive's
        position read once (at least ``MOTOR_SETTLE_S`` after the abort: the drive's own deceleration is over) and
        recorded — a ``motor`` event with the stop's times and the final position, and the motor stream's last
        sample (the polls before the stop may have left the carriage well short of where it came to rest)."""
        motor = self.inst.motor
        if stop is None or motor is None:
            return
        if stop.thread is not None:
            stop.thread.join(MOTOR_STOP_JOIN_S)
            if stop.thread.is_alive():
                notes.append(f"motor stop sent at {stop.sent_at:.3f} s still unanswered after {MOTOR_STOP_JOIN_S:g} "
                             "s")
                self._event("motor", f"stop sent at {stop.sent_at:.3f} s, unanswered; final position not read")
                return
        sent = f"stop sent at {stop.sent_at:.3f} s"
        if stop.error is not None:
            notes.append(f"motor stop at {stop.sent_at:.3f} s failed: {stop.error}")
            try:
                motor.safe_state()
                sent += f" (failed: {stop.error}; sent again at {self.now():.3f} s)"
            except Exception as exc:
                notes.append(f"motor safe state failed again: {exc}")
                sent += f", failed: {stop.error}"
        else:
            sent += f", answered at {stop.done_at:.3f} s"
        self._pause_until(max(self.now(), stop.sent_at + MOTOR_SETTLE_S), urgent_aborts=False)
        try:
            st = motor.status()
        except InstrumentError as exc:
            notes.append(f"motor final position unreadable: {exc}")
            self._event("motor", f"{sent}; final position unreadable")
            return
        t = self.now()
        self._final_position = st.position
        x = float(self.program.aperture(st.position)) if self.program.has_motor_axis else math.nan
        state = f"drive {st.state}" + (" and still moving" if st.moving else ", at rest") + (
            f", error {st.error_code:#06x} ({st.error_text})" if st.error else "")
        self._event("motor", f"{sent}; final position {st.position * 1e3:.4f} mm at {t:.3f} s"
                    + (f" (aperture {x * 1e3:.4f} mm)" if math.isfinite(x) else "") + f"; {state}")
        stream = motor.describe().stream
        if stream in self.rec.streams:
            self._record(self.rec.append, stream, t, position=st.position, aperture=x,
                         **self.ctx.late_columns(stream, math.nan))

    def _record_safe_state(self) -> None:
        """The shutdown's verifying monitor reads as the run file's :data:`SAFE_STATE` stream — one row per read
        (time, voltage, current; the last is the verdict), with the motor's position once at rest where the rig has
        a motor — so that every file, a DAQ rig's too (its streams end on the last scan), holds the measured safe
        state, not only the ``safe`` event's words."""
        if not self._safe_reads or SAFE_STATE not in self.rec.streams:
            return
        t, v, i = (np.array(col, dtype=float) for col in zip(*self._safe_reads, strict=True))
        motor = {"position": np.full(t.size, self._final_position)} \
            if any(c.name == "position" for c in self.rec.streams[SAFE_STATE]) else {}
        self._record(self.rec.append, SAFE_STATE, t, voltage=v, current=i, **motor)

    def _verify_safe(self, zero_at: float | None, notes: list[str]) -> str:
        """Check the output really is at 0 V and say which path made it so."""
        amp = self.inst.amplifier
        if amp is None:
            return "safe: no amplifier on this rig"
        watchdog = watchdog_period(self.program.rig)
        if zero_at is not None and self._streamed_settle:
            path = f"0 V commanded by the host at {zero_at:.3f} s (the end of the ramp the DAQ's stream-out played)"
            # the stream recorded the monitors through the settle: the read follows its last scan
        elif zero_at is not None:
            path = f"0 V commanded by the host at {zero_at:.3f} s"
            if not self._settle_recorded:  # (recorded: the stream of inputs waited it out, the read follows it)
                # fresh monitor conversions at the zeroed output
                self._pause_until(self.now() + MONITOR_SETTLE_S, urgent_aborts=False)
        elif watchdog is not None:
            # No request to the set-point module from here on: its communication-safety timer must run out.
            path = ("0 V written by the host but NOT under its control (the DAQ's stream stop went unanswered)"
                    if self._stream_lost else "0 V NOT commanded by the host")
            path += f": left to the set-point module's communication watchdog ({watchdog:g} s)"
            self._pause_until(self.now() + watchdog + WATCHDOG_MARGIN_S, urgent_aborts=False)
        else:
            # nothing brings the output to 0 V: what it measures is what the file and the operator need most
            path = "UNSAFE: 0 V could not be commanded and the set-point module has no communication watchdog"
            if (read := self._safe_read(amp, notes)) is None:
                return f"{path}; voltage monitor unreadable"
            return f"{path}; voltage monitor {read[0].value:.0f} V at {read[0].timestamp - self.ctx.t0:.3f} s"
        deadline = self.now() + DISCHARGE_WAIT_S
        while True:
            if (read := self._safe_read(amp, notes)) is None:
                return f"{path}; output NOT verified (voltage monitor unreadable)"
            v, i = read
            if self._stream is None:  # a DAQ rig's streams end on the last scan: the reading is in the safe event
                self._record(self.rec.append, "amplifier", v.timestamp - self.ctx.t0, voltage=v.value,
                             current=i.value, **self.ctx.unpolled_monitor_columns())
            if math.isfinite(v.value) and abs(v.value) <= self.safe_v:
                self._zero_verified = True
                return f"{path}; verified: voltage monitor {v.value:.0f} V at {self.now():.3f} s"
            if self.now() >= deadline:
                return f"{path}; WARNING: voltage monitor still reads {v.value:.0f} V at {self.now():.3f} s"
            self._pause_until(self.now() + MONITOR_REREAD_S, urgent_aborts=False)


    def _safe_read(self, amp: Amplifier, notes: list[str]) -> tuple[Reading, Reading] | None:
        """One of the shutdown's monitor reads, kept for :data:`SAFE_STATE` (NaN where it failed: None, said)."""
        try:
            v, i = amp.read_monitors()
        except InstrumentError as exc:
            notes.append(f"final monitor read failed: {exc}")
            self._safe_reads.append((self.now(), math.nan, math.nan))
            return None
        self._safe_reads.append((v.timestamp - self.ctx.t0, v.value, i.value))
        return v, i


def _is_storage_fault(exc: BaseException) -> bool:
    """Whether ``exc`` came from writing the run file: the recorder raises :class:`~bench.storage.recorder.StorageError`
    (an OSError); drivers turn their own OSErrors into InstrumentErrors, so any OSError here is the file's."""
    return isinstance(exc, OSError)
