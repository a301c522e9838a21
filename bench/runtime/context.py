"""What the parts of one run share: the run clock, the waits and stop checks, the recorder, supervisor and live
snapshot, the set-point state and the instruments (typed by role).

The engine (bench/runtime/engine.py) owns one :class:`RunContext` and hands it to the polls
(bench/runtime/polls.py) and to the hardware-timed path (bench/runtime/hardware_timed.py); they read and write the
run's state through it and through nothing else of the engine. Stop and pause requests stay the engine's: it gives
the context the two checks that raise them.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

import numpy as np

from bench.core.clock import Clock
from bench.protocol.program import Program
from bench.runtime.instruments import Instruments
from bench.runtime.interlock import (
    OUTPUT_ON_V,
    InterlockTrip,
    MotionVerifier,
    OutputVerifier,
    SilentWait,
    check_contact,
    stall_bound,
)
from bench.runtime.safety import Supervisor
from bench.storage.recorder import Recorder
from drivers.errors import InstrumentError, InstrumentStateError, InstrumentTimeoutError
from drivers.interfaces import Amplifier, DisplacementSensor, ForceSensor, LinearMotor

LATE_TOLERANCE_S = 0.05  # an action later than this (run clock) counts as an overrun
STOP_POLL_S = 0.02  # real time: longest sleep between two looks at the stop request

T = TypeVar("T")


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


@dataclass
class Wait:
    """One wait on an instrument's reply (:meth:`RunContext.waiting_on`), on :func:`time.monotonic`."""

    role: str
    start: float
    due: float = math.nan  # run time the read was scheduled for (NaN: not scheduled)
    end: float | None = None  # None: under way
    unanswered: bool = False  # a request of it went unanswered (a timeout; its link may have retried)
    detail: str = ""  # the driver's words when the wait ended in a timeout
    feed_failed: bool = False  # a keep-alive sent during the wait failed: its error is the amplifier's


class Streaming(Protocol):
    """The hardware-timed side of a run as the polls see it (bench.runtime.hardware_timed.HardwareTimed)."""

    has_laser: bool  # the laser is sampled on the DAQ's scan clock
    has_force: bool  # the load cell's bridge amplifier is sampled on the DAQ's scan clock

    def collect(self) -> None:
        """Record the scans received so far and supervise them."""


def present(instrument: T | None, role: str) -> T:
    """The rig's instrument of ``role``; the compiler only schedules actions on instruments the rig has."""
    if instrument is None:
        raise InstrumentStateError(role, "the program uses an instrument this rig does not have")
    return instrument


class RunContext:
    """One run's shared state. ``check_stop`` raises when a stop was requested, ``check_pause`` when a pause was
    (the engine's requests); :meth:`wait_until` calls both while it waits."""

    def __init__(self, program: Program, inst: Instruments, clock: Clock, recorder: Recorder,
                 supervisor: Supervisor, snapshot: Snapshot, *, check_stop: Callable[[], None],
                 check_pause: Callable[[], None], streamed: bool = True) -> None:
        """``streamed``: the rig's DAQ (if it has one) plays the steps; False: every set-point is command-response
        (manual mode)."""
        self.program = program
        self.inst = inst
        self.clock = clock
        self.rec = recorder
        self.sup = supervisor
        self.snapshot = snapshot
        self.check_stop = check_stop
        self.check_pause = check_pause
        rig = program.rig
        self.t0 = 0.0  # rig-clock time of run time 0 [s]
        self.offset = 0.0  # run time − program time: a resumed start and each pause shift the program's schedule
        self.v_cmd = 0.0  # last voltage commanded (the module's code, as sent; on a DAQ rig the value it plays)
        self.v_req = 0.0  # last voltage requested by the program
        self.overruns = 0  # actions later than LATE_TOLERANCE_S (run clock: real or virtual)
        self.worst_lateness = 0.0
        self.stream: Streaming | None = None  # set by the engine on a rig that plays its steps hardware-timed
        hw = streamed and inst.stream_drive is not None
        self.verifier = OutputVerifier(rig, rig.daq.scan_rate_Hz if hw and rig.daq else None)
        self.motion = MotionVerifier(rig)  # the encoder against the go-tos (a rig without a motor never feeds it)
        self._laser_offset = (rig.laser.offset_mm * 1e-3) if rig.laser else 0.0
        self._laser_sign = float(rig.laser.sign) if rig.laser else 1.0
        self._late_streams = {name for name, cols in recorder.streams.items() if any(c.name == "late" for c in cols)}
        self._amp_commanded = any(c.name == "commanded" for c in recorder.streams.get("amplifier", []))
        self.laser_t_last = -math.inf  # run time of the last laser sample recorded (software-timed laser)
        self.laser_last = math.nan  # its displacement in specimen coordinates [m] (NaN: that sample was not valid)
        # how long the laser's single reads may give no displacement while the output is on before that trips (None:
        # never, a run's: its protocol was dry-run on the model; manual control's is set, no dry run covers it)
        self.laser_lost_s: float | None = None
        self.laser_lost_since = math.nan  # run time of the first of the present run of readings without one
        # the laser storage's upload in a step (bench.runtime.polls): the run time by which a fetch must be over (the
        # step's next action due: a set-point, another poll, its end; inf: no bound) and the program time of the
        # next fetch on FETCH_PERIOD_S's grid (between them, only a backlog a bounded fetch left is fetched; -inf as a
        # step's storage starts: its first fetch sets the grid)
        self.upload_until = math.inf
        self.fetch_next = -math.inf
        self.fetch_moved = -math.inf  # run time of the step's storage start or of its last fetch that uploaded values
        self._heard_mark: float | None = None  # the set-point module's driver's last ``heard_at`` seen
        self._heard_rig = -math.inf  # rig clock: no later than this the module last heard from the host
        self._looked_rig = -math.inf  # rig clock: the last look at ``heard_at``
        self._wait: Wait | None = None  # the wait on an instrument under way
        self._silent: Wait | None = None  # the last wait in which a request went unanswered

    # ------------------------------------------------------------ instruments the program uses (typed)
    @property
    def amp(self) -> Amplifier:
        return present(self.inst.amplifier, "amplifier")

    @property
    def laser(self) -> DisplacementSensor:
        return present(self.inst.laser, "laser")

    @property
    def motor(self) -> LinearMotor:
        return present(self.inst.motor, "motor")

    @property
    def cell(self) -> ForceSensor:
        return present(self.inst.load_cell, "load_cell")

    # ------------------------------------------------------------ time
    def now(self) -> float:
        """Run time [s]."""
        return self.clock.now() - self.t0

    def program_now(self) -> float:
        """Program time [s]: run time less the shifts of a resumed start and of the pauses."""
        return self.now() - self.offset

    def lateness(self, due: float) -> float:
        """How long after its scheduled program time ``due`` an action runs [s]."""
        return self.program_now() - due

    def wait_until(self, t: float) -> None:
        """Wait until program time ``t`` (checking for stop and pause requests meanwhile); an action later than
        ``LATE_TOLERANCE_S`` counts as an overrun — on a virtual clock too, where the wire time of the transactions
        before it (rig time) is what makes it late: a virtual run whose links outrun the schedule says so."""
        self.check_stop()
        self.check_pause()
        t += self.offset
        if not self.clock.virtual:
            while (left := t - self.now()) > 0:
                self.check_stop()
                self.check_pause()
                time.sleep(min(left, STOP_POLL_S))
        else:
            self.clock.wait_until(self.t0 + t)
        late = self.now() - t
        self.worst_lateness = max(self.worst_lateness, late)
        if late > LATE_TOLERANCE_S:
            self.overruns += 1

    def unheard_for(self) -> float:
        """How long [s of the run's clock] the set-point module may have gone without a request from this host: an
        upper bound (inf before its first answer and at the first look), what a keep-alive compares with its
        period. The driver stamps its requests on the wall clock (``heard_at``), which a virtual clock does not
        follow, so the time is counted on the run's clock here: a request the driver reports since the last look
        was sent no earlier than that look."""
        now = self.clock.now()
        heard = self.amp.heard_at()
        if heard is not None and heard != self._heard_mark:
            self._heard_mark = heard
            self._heard_rig = self._looked_rig  # the first look: not known, so as if long ago
        self._looked_rig = now
        return now - self._heard_rig if heard is not None else math.inf

    # ------------------------------------------------------------ waits on instruments
    @contextlib.contextmanager
    def waiting_on(self, role: str, due: float = math.nan) -> Iterator[None]:
        """Around a read of the instrument of ``role`` scheduled for run time ``due``: the wait is kept, so that a
        set-point module starved while the host waited on an instrument that did not answer is laid to that
        instrument, not to a host stall; a timeout is raised again naming the role ("load cell (bus scale): no
        valid reply …")."""
        w = self._wait = Wait(role, time.monotonic(), due)
        try:
            yield
        except InstrumentTimeoutError as exc:
            if w.feed_failed:
                raise
            w.unanswered, w.detail = True, str(exc)
            self._silent = w
            name = role.replace("_", " ")
            if exc.device.startswith(name):
                raise
            raise InstrumentTimeoutError(f"{name} ({exc.device})", exc.detail) from exc
        finally:
            w.end = time.monotonic()
            self._wait = None

    def unanswered(self) -> float:
        """A request of the instrument waited on went unanswered and its link retries it; returns the run time to
        record a set-point sent meanwhile at: the read's scheduled time (every set-point recorded so far is no
        later, every one to come later: the stream stays in time order), else now."""
        if (w := self._wait) is None:
            return self.now()
        w.unanswered = True
        self._silent = w
        return w.due if math.isfinite(w.due) else self.now()

    def feed_failed(self) -> None:
        """A keep-alive sent during the present wait failed (its error is the amplifier's, not the waited one's)."""
        if self._wait is not None:
            self._wait.feed_failed = True

    def _waited_on(self, away: float) -> SilentWait | None:
        """The unanswered wait on another instrument that explains a silence of the set-point module of ``away`` s
        ending now: the part of the silence the wait covers leaves no more than the stall bound uncovered (a
        freeze before the wait, or after a keep-alive fed during it, is the host's own stall)."""
        w = self._silent
        if w is None or w.role == "amplifier":
            return None
        now = time.monotonic()
        end = now if w.end is None else w.end
        covered = end - max(w.start, now - away)  # the wait within the silence
        if covered <= 0 or away - covered > stall_bound(self.program.rig):
            return None
        return SilentWait(w.role, end - w.start, w.detail or "a request went unanswered and its link retried")

    # ------------------------------------------------------------ interlock
    def guard(self, streaming: bool = False) -> None:
        """Before anything that can drive the output: latch when the set-point module went unheard for longer
        than the stall bound while the output is on (``streaming``: a DAQ stream plays), so that its watchdog may
        have zeroed the output and this write would turn high voltage back on by itself — a host stall, or the
        silence of the instrument the host was waiting on meanwhile."""
        amp = self.inst.amplifier
        if amp is None or self.clock.virtual:
            return
        try:
            away = amp.longest_silence()
            check_contact(self.program.rig, away, streaming or abs(self.v_cmd) > OUTPUT_ON_V, self._waited_on(away))
        except InterlockTrip as trip:
            try:
                fired = amp.watchdog_fired()
            except InstrumentError as exc:
                raise InterlockTrip(trip.kind, f"{trip.detail} (its watchdog flag unreadable: {exc.detail})") from None
            if fired is None:
                raise
            raise InterlockTrip(trip.kind, f"{trip.detail} (the module's own flag: its watchdog "
                                f"{'fired' if fired else 'did not fire'})") from None

    # ------------------------------------------------------------ recording
    def to_specimen(self, laser_value: np.ndarray) -> np.ndarray:
        """Laser readings [m] to the specimen's displacement (the rig file's offset and sign removed)."""
        return (laser_value - self._laser_offset) / self._laser_sign

    def late_columns(self, stream: str, late: float | np.ndarray) -> dict[str, float | np.ndarray]:
        """The ``late`` column of a software-timed stream: how long after its scheduled time a poll ran [s]."""
        return {"late": late} if stream in self._late_streams else {}

    def unpolled_monitor_columns(self) -> dict[str, float | np.ndarray]:
        """The amplifier stream's other columns for a monitor read outside the schedule (shutting down): no
        lateness (NaN: not a scheduled poll), and the output commanded where the layout has that column (a
        DAQ-driven amplifier; its polled reads carry it from the driver's ``read()``)."""
        cols = self.late_columns("amplifier", math.nan)
        if self._amp_commanded:
            cols["commanded"] = self.v_cmd
        return cols
