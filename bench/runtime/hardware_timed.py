"""Hardware-timed segments: the DAQ plays a step's voltage waveform on its own scan clock and samples every analog
channel on the same clock (bluesky's kickoff / collect / complete pattern).

For each step the engine calls :meth:`HardwareTimed.start` (compile the step's voltage to a DAC buffer with the
exact end value as its last sample, check it with the supervisor, arm, kick off), :meth:`~HardwareTimed.collect`
while the step runs (record the scans, supervise them, top up the output buffer, feed the watchdog) and
:meth:`~HardwareTimed.finish` at its end (collect until the end value has been played, stop the stream; the DAC
holds the end value). Software-timed actions (motor go-tos, encoder polls) keep running in the engine beside it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from bench.core.one_pole import one_pole
from bench.models.jit import njit
from bench.protocol.program import Segment, plays_on, voltage_at
from bench.rig import DaqConfig, RigConfig
from bench.runtime.context import RunContext
from bench.runtime.interlock import OUTPUT_ON_V, InterlockTrip, mismatch_trip
from bench.runtime.safety import SafetyTrip
from bench.storage import scan_clock
from drivers.errors import InstrumentTimeoutError, StreamEndedError
from drivers.interfaces import (
    Amplifier,
    DaqAmplifier,
    DataKey,
    StreamBlock,
    StreamDescription,
    StreamIn,
    StreamingDaq,
    StreamOut,
    StreamSpec,
)

KEEPALIVE_S = 0.25  # a command-response request at least this often (run clock) keeps the device's watchdog fed
# wall-clock runs: stream-out values in the device at most this far ahead of the scan its clock may have reached, so
# that a lost host (link dropped, process dead) stops the drive within it — the T7 then holds its last value until
# its watchdog zeroes the output; ten collect periods (polls.COLLECT_PERIOD_S), so a collect may come ~0.4 s late
# before an underrun (0.2–0.4 s latched underruns in real-time tests: collects 0.3–0.45 s late on the 2-core
# development host at load 8–14, where the old 0.8 s did not). Virtual time too: a rehearsal of a lost link must
# stop the drive as the bench would (its collects, every 0.25 s of rig time, keep two periods queued).
OUT_AHEAD_S = 0.5
# simulated rigs in virtual time, with the T7's watchdog configured: whole periods that repeat play from the T7's
# stream-out loop, written once (not refilled). Not on a lab rig until checked on the hardware: the datasheet does not
# say that the watchdog's DAC action stops a repeating loop (the twin assumes it does), and a loop that outlived a lost
# host would drive the amplifier on. Not in wall-clock runs either: a rehearsal on the simulated rig (lost link,
# stalled host) then takes the lab rig's path — the last value held after at most OUT_AHEAD_S, until the watchdog —
# and loops are a speed device for virtual time only
OUT_LOOPS = True
FINISH_TIMEOUT_S = 5.0  # rig time allowed for the last scans of a step to arrive (wall time on hardware)
FINISH_POLL_S = 0.01  # rig time between collects while waiting for a step's last scans


@njit(cache=True)
def _diffuse(dac: np.ndarray, slope: float, offset: float, shift: int, lo: int,
             hi: int) -> np.ndarray:  # pragma: no cover - numba
    """First-order error diffusion of DAC volts onto the codes the DAC plays (16-bit codes, low ``shift`` bits
    ignored by the converter), each code kept within [lo, hi] (the codes whose output lies within the limit); a
    code clipped there carries no error on (no wind-up at a limit); returns the volts played."""
    out = np.empty_like(dac)
    err = 0.0
    for k in range(dac.size):
        want = dac[k]
        code = int(np.round((want + err) * slope + offset))
        clipped = min(max(code, lo), hi)
        played = (((clipped >> shift) << shift) - offset) / slope
        err = 0.0 if clipped != code else err + want - played
        out[k] = played
    return out


def warm_up() -> None:
    """Compile (or load from the cache) the host's kernels of a hardware-timed run now, with the argument types a
    run passes: a first compile holds the interpreter for ~0.3 s on the development machine, which inside a
    wall-clock run is time every twin's thread and the stream wait through."""
    _diffuse(np.zeros(1), 1.0, 0.0, 0, 0, 1)
    one_pole(np.zeros(1), 0.5, 0.0)


def _peak(volts: np.ndarray) -> float:
    """The value of largest magnitude [V]."""
    return float(volts[np.argmax(np.abs(volts))])


def describe_streams(cfg: DaqConfig, amplifier: Amplifier) -> list[StreamDescription]:
    """The streams the DAQ's scans time: the amplifier's (its driver's columns) and the analog inputs the rig file
    wires to the DAQ (load cell, laser); each source names its channels and the one scan clock."""
    clock = f"LabJack T7 stream, {cfg.scan_rate_Hz:g} scans/s (one scan clock for every analog channel)"
    amp = amplifier.describe()
    out = [replace(amp, source=f"{amp.source}; {clock}")]
    if cfg.force_ain is not None:
        out.append(StreamDescription("load_cell", (
            DataKey("force", "N", "force from the load-cell bridge amplifier, tension positive"),
            DataKey("ok", "1", "1 = every channel of the scan valid", "u1")),
            f"bridge amplifier on AIN{cfg.force_ain}; {clock}"))
    if cfg.laser_ain is not None:
        out.append(StreamDescription("laser", (
            DataKey("displacement", "m", "from the laser's analog output (offset and sign removed)"),
            DataKey("valid", "1", "1 = measurement, 0 = invalid", "u1")),
            f"laser analog output on AIN{cfg.laser_ain}; {clock}"))
    return out


@dataclass(frozen=True)
class _Next:
    """A step's values prepared to follow those the stream-out has (:meth:`HardwareTimed._prepare`)."""

    seg: Segment
    dac: np.ndarray  # DAC volts to play
    commanded: np.ndarray  # the amplifier output they command, scan by scan
    window: tuple[float, float]  # the DAC volts within the supervisor's bound
    final: bool  # nothing follows them in the stream
    end: float  # the step's end value [V]


class HardwareTimed:
    """The DAQ side of a run on a rig whose amplifier is driven through a hardware-timed DAQ: any
    :class:`~drivers.interfaces.StreamingDaq` with a :class:`~drivers.interfaces.DaqAmplifier` on its output
    (``Instruments.stream_drive``), wired as the rig file's ``[daq]`` section says."""

    def __init__(self, rig: RigConfig, daq: StreamingDaq, amp: DaqAmplifier, ctx: RunContext) -> None:
        cfg = rig.daq
        if cfg is None:
            raise ValueError(f"rig {rig.name}: hardware-timed steps need a [daq] section")
        self.cfg = cfg
        self.simulated = rig.simulated
        self.daq, self.amp, self.ctx = daq, amp, ctx
        inputs = [StreamIn(cfg.vmon_ain, 10.0, "vmon"), StreamIn(cfg.imon_ain, 10.0, "imon")]
        if cfg.force_ain is not None:
            inputs.append(StreamIn(cfg.force_ain, 10.0, "force"))
        if cfg.laser_ain is not None:
            inputs.append(StreamIn(cfg.laser_ain, 10.0, "laser"))
        self.inputs = tuple(inputs)
        self.has_laser = cfg.laser_ain is not None
        self.has_force = cfg.force_ain is not None
        self._commanded = np.zeros(0)  # amplifier output [V] the DAC plays, scan by scan, from scan _base on
        self._base = 0  # scan index of _commanded[0] (older values are dropped as the stream goes on)
        self._n = 0  # index of the scan that plays the step's end value
        self._tail = 0.0  # the last value given to the stream-out (the end value of the last step appended)
        self._appended: tuple[Segment, int] | None = None  # the next step, already in the stream: (step, end scan)
        self._positions: dict[int, int] = {}  # id(step) → its place in the program
        self._keepalive = 0.0
        self.scans = 0  # scans recorded over the run
        # run time of the last recorded scan that commanded the output on (|V| > OUTPUT_ON_V) or the first after
        # such a scan (-inf: none yet): the engine's hand-over check waits for fresh monitor conversions after it
        # (Engine._hand_over)
        self.live_at = -np.inf
        self._last_commanded = 0.0  # the commanded output of the last scan recorded (connecting commands 0 V)
        self.ramp_start = 0.0  # run time of scan 0 of the ramp's stream (:meth:`ramp_down`)

    # ------------------------------------------------------------ one step
    def start(self, seg: Segment) -> None:
        """Play the step: a step already in the running stream (appended while the one before played) just
        moves the end mark; otherwise compile its voltage to a DAC buffer (end value last), supervise it, arm
        and kick off. Then append the next step when it follows at once, so that the device plays the steps
        back to back on one scan clock (no restart, no gap, no drift of the program's time grid)."""
        nxt = self._next_chainable(seg)
        if self._appended is not None and self._appended[0] is seg and self.daq.streaming:
            self._n = self._appended[1]
        else:
            volts = self._wanted(seg, self.ctx.v_req, first=True)
            xs = self._apertures(seg, seg)  # where the step's own move or path takes the LS-DEA while they play
            self.ctx.sup.check_setpoint_over(_peak(volts), xs)
            bound, window = self._window(xs)
            dac = self._dac_values(volts, self.ctx.v_cmd, bound, window)
            commanded = self._follows(dac, window, self.ctx.v_cmd)
            self.ctx.sup.check_setpoint_over(_peak(commanded), xs)
            self.ctx.guard()
            self.daq.arm(StreamSpec(self.cfg.scan_rate_Hz, self.inputs,
                                    StreamOut(self.cfg.dac, dac, hold=1, final=nxt is None, within=window),
                                    out_ahead_s=OUT_AHEAD_S, out_loops=self._loops()))
            self._base = 0
            self._commanded = commanded
            self._tail = float(volts[-1])
            self._n = volts.size - 1
            self.ctx.verifier.restart()
            t0 = self.daq.kickoff()
            self._keepalive = self.ctx.clock.now()
            self.ctx.rec.event(self.ctx.now(), seg.index, scan_clock.KIND,
                               scan_clock.kickoff_text(t0 - self.ctx.t0, self.daq.scan_clock_uncertainty))
        self.ctx.v_req = self._tail  # this step's end value: the last one in the stream until the next is appended
        self._appended = None
        if nxt is not None and self.daq.out_open:
            self._append(seg, nxt)

    def _wanted(self, seg: Segment, hold: float, first: bool) -> np.ndarray:
        """The step's amplifier output on the scan grid [V]: from its start (``first``: a new stream plays the
        value at t_start on its first scan) or from one scan after it (appended: the value at t_start is the
        step before's end value), to its end value exactly."""
        rate = self.cfg.scan_rate_Hz
        n = max(1, round(seg.duration * rate))
        k = np.arange(0 if first else 1, n + 1)
        if seg.voltage is not None:
            volts = np.asarray(seg.voltage(seg.t_start + k / rate), dtype=float)
            end = voltage_at(seg, seg.t_end)
            volts[-1] = hold if end is None else end
        else:
            volts = np.full(k.size, hold)
        return volts

    def _next_chainable(self, seg: Segment) -> Segment | None:
        """The step after ``seg`` when the stream can play it straight on: it starts where ``seg`` ends, lasts,
        and needs no specimen change (an operator's action stops the stream)."""
        segs = self.ctx.program.segments
        pos = self._positions.get(id(seg))
        if pos is None:
            self._positions = {id(s): i for i, s in enumerate(segs)}
            pos = self._positions[id(seg)]
        if pos + 1 >= len(segs):
            return None
        nxt = segs[pos + 1]
        return nxt if plays_on(seg, nxt) else None

    def _append(self, seg: Segment, nxt: Segment) -> None:
        """Append the next step's values to the running stream-out (supervised like a new step's), checked and
        windowed at every aperture the LS-DEA passes while they play (:meth:`_apertures`), not only at the present
        one: appended while ``seg`` moves the motor, they play where the move ends."""
        self._extend(self._prepare(seg, nxt))

    def _prepare(self, seg: Segment, nxt: Segment) -> _Next:
        """``nxt``'s values to follow what the stream-out holds (its last commanded value, ``_tail``), compiled and
        checked by the supervisor: the costly half of :meth:`_append`, which a stream about to start does before its
        kickoff (:meth:`ramp_up`: a long step compiled after it could outlast the ramp's 0.35 s of values)."""
        volts = self._wanted(nxt, self._tail, first=False)
        xs = self._apertures(seg, nxt)
        self.ctx.sup.check_setpoint_over(_peak(volts), xs)
        present = float(self._commanded[-1]) if self._commanded.size else self.ctx.v_cmd
        bound, window = self._window(xs)
        dac = self._dac_values(volts, self._tail, bound, window)
        new = self._follows(dac, window, present)
        self.ctx.sup.check_setpoint_over(_peak(new), xs)
        return _Next(nxt, dac, new, window, self._next_chainable(nxt) is None, float(volts[-1]))

    def _extend(self, step: _Next) -> None:
        """Give the stream-out a prepared step's values (:meth:`_prepare`): played right after those it has."""
        self.ctx.guard(streaming=True)
        self.daq.extend(step.dac, final=step.final, within=step.window)
        keep = max(0, self.daq.scans_received - 1 - self._base)  # the scans still to be recorded, and the last
        self._commanded = np.concatenate([self._commanded[keep:], step.commanded])
        self._base += keep
        self._appended = (step.seg, self._base + self._commanded.size - 1)
        self._tail = step.end

    def _loops(self) -> bool:
        """Whether repeating periods may play from the T7's stream-out loop (OUT_LOOPS: simulated rigs in virtual
        time whose watchdog is configured)."""
        return OUT_LOOPS and self.simulated and self.ctx.clock.virtual and self.cfg.watchdog_s is not None

    def _window(self, apertures: Sequence[float] = ()) -> tuple[float, tuple[float, float]]:
        """(the supervisor's bound on |V| now and at each of ``apertures``, the DAC volts whose output lies within
        it)."""
        bound = self.ctx.sup.setpoint_bound_over(apertures)
        return bound, self.amp.dac_window(bound)

    @staticmethod
    def _apertures(seg: Segment, nxt: Segment) -> list[float]:
        """The apertures [m] the LS-DEA reaches while ``nxt``'s values play behind ``seg``: where ``seg``'s move or
        path ends, and the extremes of ``nxt``'s own (the present one is the supervisor's, which also checks the
        field's peak where they span it: :meth:`~bench.runtime.safety.Supervisor.setpoint_bound_over`)."""
        xs = []
        if seg.move is not None:
            xs.append(seg.move[0])
        if seg.position is not None:
            xs.append(float(np.asarray(seg.position(np.array([seg.t_end])))[0]))
        if nxt.move is not None:
            xs.append(nxt.move[0])
        if nxt.position is not None:
            path = np.asarray(nxt.position(nxt.t_start + np.linspace(0.0, nxt.duration, 513)), dtype=float)
            xs += [float(np.min(path)), float(np.max(path))]
        return xs

    def _dac_values(self, volts: np.ndarray, present: float, bound: float,
                    window: tuple[float, float]) -> np.ndarray:
        """DAC volts that make the amplifier output ``volts`` behind the conditioning stage and its filter, within
        ``window`` (the DAC volts of ±``bound``): the pre-compensation is clipped at ±bound, the diffused codes to
        the window's."""
        dac = np.clip(self.amp.dac_volts(self._precompensate(volts, present, bound)), *window)
        return self._error_diffused(dac, window) if self.cfg.drive_filter_Hz is not None else dac

    def _follows(self, dac: np.ndarray, window: tuple[float, float], present: float) -> np.ndarray:
        """What the amplifier follows for DAC values ``dac`` [V out]: the levels the T7 plays for them (codes
        clipped to ``window``, as the DAQ's ``arm``/``extend`` code them) through the
        conditioning stage and the reconstruction filter, from ``present``. Supervised before anything is sent."""
        return self._filtered(self.amp.output_volts(self.daq.out_played(dac, self.cfg.dac, window)), present)

    def collect(self) -> None:
        """Record the scans received so far and supervise them; keep the device's watchdog fed."""
        self.ctx.guard(streaming=True)  # the collect tops up the stream-out: no write after a stall
        block = self._collected()
        late = self.daq.out_underrun_scans
        try:
            self._record(block)
        except InterlockTrip as trip:
            # the scans of an underrun show the output held at the last value written while the program moved on:
            # the verifier's mismatch, whose cause is the underrun (CI beside a CPU hog: a host 1.2 s late was
            # latched as "output mismatch", which the tests' load-trip rule did not know)
            if late > 0 and trip.kind == "output mismatch":
                raise self._underrun(late) from None
            raise
        if late > 0:
            raise self._underrun(late)
        # the run's clock: the T7's watchdog counts rig time; any request feeds it (a stream-out top-up too)
        heard = max(self._keepalive, getattr(self.daq, "answered_at", -np.inf))
        if self.ctx.clock.now() - heard >= KEEPALIVE_S:
            self.daq.read_dac(self.cfg.dac)
            self._keepalive = self.ctx.clock.now()

    @staticmethod
    def _underrun(late: int) -> InterlockTrip:
        return InterlockTrip("stream-out underrun", f"the DAQ played {late} scans past the values the host had "
                             "written: the output did not follow the program")

    def _collected(self, supervise: bool = True) -> StreamBlock:
        """The scans the DAQ has received so far. A stream the DAQ ended with a status of its own: the scans up to
        it are recorded first (supervised as any others, as ``supervise`` says), then its error stops the run —
        unless those scans trip the supervisor: the trip (it latches) stops it, and a ``fault`` event names the
        status."""
        try:
            return self.daq.collect(until=self.ctx.clock.now(), timeout=max(1.0, 4 * self.daq.timeout))
        except StreamEndedError as ended:
            try:
                self._record(ended.block, supervise=supervise)
            except SafetyTrip:
                self.ctx.rec.event(self.ctx.now(), self.ctx.snapshot.step, "fault", str(ended))
                raise
            raise

    def finish(self) -> None:
        """Collect until the end value has been played, then stop the stream (the DAC holds it) — unless the
        next step is already in the stream: then it just goes on."""
        if self._appended is not None and self.daq.streaming:
            self.collect()
            return
        end = self.ctx.now() + FINISH_TIMEOUT_S  # rig time: each pass below moves a virtual clock on by FINISH_POLL_S
        while self.daq.scans_received <= self._n:
            self.ctx.check_stop()
            if self.ctx.now() > end:
                raise InstrumentTimeoutError(self.daq.name, f"stream stopped short: {self.daq.scans_received} "
                                             f"scans received, {self._n + 1} needed")
            self.ctx.wait_until(self.ctx.program_now() + FINISH_POLL_S)
            self.collect()
        self.stop()

    # ------------------------------------------------------ the shutdown's and a pause's ramp to 0 V, a restart's up
    def ramp_down(self, v0: float, ramp_s: float) -> float:
        """Play the ramp from ``v0`` to 0 V over ``ramp_s`` on a new stream (the running one stopped first, its last
        scans recorded), 0 V held after it: the monitors and the laser are recorded on the scan clock through the
        ramp and after it, as long as :meth:`collect_quiet` is called. Returns the run time of the scan that plays
        0 V (the DAC commands it itself)."""
        return self._ramp(v0, 0.0, ramp_s, "the ramp to 0 V's stream")

    def ramp_up(self, v1: float, ramp_s: float, settle_s: float = 0.0,
                then: Segment | None = None) -> tuple[float, float]:
        """A restart's ramp (after a pause, in a resumed campaign): from the value the DAC holds to ``v1`` over
        ``ramp_s`` on a new stream, ``v1`` held after it. Supervised as a step's start is (the values checked before
        anything is armed); the engine collects it with :meth:`collect`, every scan supervised. ``then``: the step
        the restart starts, appended to the same stream ``settle_s`` after ``v1`` is reached (the scan there plays
        its start): no stream is re-armed at ``v1``, which on a wall clock left the recording ~110 ms without a
        scan at high voltage (an outside tester: 113 ms at 3 kV). Returns (the run time of the scan that plays
        ``v1``, that of the scan that plays ``then``'s start: the first plus ``settle_s``)."""
        t1 = self._ramp(self.ctx.v_cmd, v1, ramp_s, "the restart's ramp up's stream", supervise=True,
                        hold_s=settle_s if then is not None else 0.0, then=then)
        return t1, self.ramp_start + self._n / self.cfg.scan_rate_Hz  # _n: the ramp's and the hold's last scan

    def _ramp(self, v0: float, v1: float, ramp_s: float, what: str, supervise: bool = False, hold_s: float = 0.0,
              then: Segment | None = None) -> float:
        """Play a straight ramp from ``v0`` (scan 0) to ``v1`` (scan n, held after it) over ``ramp_s`` on a new
        stream, the running one stopped first (its last scans recorded); ``supervise``: the wanted and the followed
        values checked by the supervisor before it is armed; ``hold_s``: ``v1`` played that much longer; ``then``: a
        step whose values follow (compiled and checked before the kickoff, given to the stream-out after it). Returns
        the run time of scan n; a ``timing`` event names the stream's scan 0 on the run clock (:attr:`ramp_start`)."""
        self.stop(whole=True)
        rate = self.cfg.scan_rate_Hz
        n = max(1, round(ramp_s * rate))
        volts = v0 + (v1 - v0) * (np.arange(n + 1) / n)  # scan 0 plays v0 (the value the DAC holds), scan n v1
        volts[-1] = v1
        volts = np.concatenate([volts, np.full(round(hold_s * rate), v1)])
        bound, window = self._window()
        if supervise:
            self.ctx.sup.check_setpoint_over(_peak(volts), ())
        dac = self._dac_values(volts, self.ctx.v_cmd, bound, window)
        commanded = self._follows(dac, window, self.ctx.v_cmd)
        if supervise:
            self.ctx.sup.check_setpoint_over(_peak(commanded), ())
        self._base, self._commanded, self._n, self._appended = 0, commanded, volts.size - 1, None
        self._tail = v1
        step = None if then is None else self._prepare(then, then)  # follows the values above: before the kickoff
        if supervise:
            self.ctx.guard()  # after the compiling, right before the stream is armed (as a step's start)
        self.ctx.v_req = v1
        # (a step's periods may play from the stream-out's loop, as on a step's own stream)
        self.daq.arm(StreamSpec(rate, self.inputs, StreamOut(self.cfg.dac, dac, hold=1, final=then is None,
                                                             within=window),
                                out_ahead_s=OUT_AHEAD_S, out_loops=then is not None and self._loops()))
        t = self._kickoff_own(what) + n / rate
        if step is not None:
            self._extend(step)
        return t

    def _kickoff_own(self, what: str) -> float:
        """Kick off a stream of its own (a ramp's, the inputs after 0 V): the verifier restarted, its scan 0 said in
        a ``timing`` event naming ``what`` it is for; returns that scan's run time (:attr:`ramp_start`)."""
        self.ctx.verifier.restart()
        t0 = self.daq.kickoff()
        self._keepalive = self.ctx.clock.now()
        self.ramp_start = t0 - self.ctx.t0
        self.ctx.rec.event(self.ctx.now(), self.ctx.snapshot.step, scan_clock.KIND,
                           scan_clock.kickoff_text(self.ramp_start, self.daq.scan_clock_uncertainty, what))
        return self.ramp_start

    def record_zero(self) -> float:
        """After the host commanded 0 V itself (a second stop request cut the ramp's stream short): the inputs on a
        new stream with no stream-out — the DAC holds the 0 V the host wrote, nothing more is played — so that the
        settle after 0 V is recorded on the scan clock as after a ramp the DAQ played (collected with
        :meth:`collect_quiet`, up to :meth:`recorded_to`). Returns the run time of its scan 0 (:attr:`ramp_start`)."""
        self.stop(whole=True)
        self.daq.arm(StreamSpec(self.cfg.scan_rate_Hz, self.inputs))
        self._base, self._commanded, self._n, self._appended = 0, np.zeros(1), 0, None
        self._tail = self.ctx.v_req = 0.0
        return self._kickoff_own("the inputs after 0 V (no stream-out: the DAC holds the 0 V the host commanded)")

    def recorded_to(self) -> float:
        """Run time of the last scan recorded from the stream a ramp started (:meth:`ramp_down`, :meth:`ramp_up`;
        −inf before its first)."""
        k = self.daq.scans_received - 1
        return self.ramp_start + k / self.cfg.scan_rate_Hz if k >= 0 else -np.inf

    def collect_quiet(self) -> None:
        """Record the scans received so far, unsupervised (the shutdown's and a pause's ramp: nothing may raise a
        trip there; the zero is verified afterwards), the device's watchdog kept fed."""
        if not self.daq.streaming:
            return
        self._record(self._collected(supervise=False), supervise=False)
        heard = max(self._keepalive, getattr(self.daq, "answered_at", -np.inf))
        if self.ctx.clock.now() - heard >= KEEPALIVE_S:
            self.daq.read_dac(self.cfg.dac)
            self._keepalive = self.ctx.clock.now()

    def read_laser(self) -> None:
        """One laser reading by command-response (the stream stopped: a pause), recorded as a laser row."""
        assert self.cfg.laser_ain is not None
        r = self.daq.read_ain(self.cfg.laser_ain)
        head = self.cfg.laser_m_per_V * r.value + self.cfg.laser_offset_m
        disp = self.ctx.to_specimen(np.array([head]))
        ok = r.status == "ok" and bool(np.isfinite(disp).all())
        self.ctx.rec.append("laser", r.timestamp - self.ctx.t0, displacement=disp, valid=np.array([ok], "u1"))

    def forget(self) -> None:
        """After a stop that was not the program's (a pause): no step is in the stream any more."""
        self._appended = None

    def stop(self, whole: bool = False) -> None:
        """Stop a running stream and record its last scans (the DAC holds the last value played). ``whole``: first
        wait (at most one packet's time, on the rig clock) until the scans taken fill whole packets, so that the
        stop loses no scan before it (the device sends no partly filled packet): a stream that another follows at
        once (the ramp to 0 V) then leaves no hole of up to a packet between them."""
        if not self.daq.streaming:
            return
        if whole:
            t = self.daq.whole_packets_at()
            if self.ctx.clock.virtual:
                self.ctx.clock.wait_until(t)
            elif (left := t - self.ctx.clock.now()) > 0:
                time.sleep(left)
        block = self.daq.stop()
        if block is not None:
            self._record(block, supervise=False)
        self.ctx.v_cmd = self._played()

    # ------------------------------------------------------------ reconstruction filter of the conditioning stage
    def _alpha(self) -> float | None:
        fc = self.cfg.drive_filter_Hz
        return None if fc is None else 1.0 - float(np.exp(-2.0 * np.pi * fc / self.cfg.scan_rate_Hz))

    def _precompensate(self, wanted: np.ndarray, present: float, bound: float) -> np.ndarray:
        """DAC sequence whose first-order-filtered version, scan by scan, is ``wanted`` (output volts), within
        ±``bound``."""
        alpha = self._alpha()
        if alpha is None:
            return wanted
        prev = np.concatenate([[present], wanted[:-1]])
        out = prev + (wanted - prev) / alpha
        # a jump the filter cannot follow at once is approached, never overshot
        return np.asarray(np.clip(out, -bound, bound))

    def _error_diffused(self, dac: np.ndarray, window: tuple[float, float]) -> np.ndarray:
        """DAC values on the DAC's own levels whose running sum follows ``dac`` (first-order error diffusion):
        behind the reconstruction filter the code steps average out instead of leaving the output up to one
        code (≈ 5 V of high voltage on a 12-bit DAC) off a slow waveform. No level outside ``window`` is used."""
        c = self.daq.dac_coding(self.cfg.dac, window)
        return _diffuse(np.ascontiguousarray(dac, dtype=float), c.slope, c.offset, c.shift, c.lo, c.hi)

    def _filtered(self, played: np.ndarray, present: float) -> np.ndarray:
        """What the amplifier follows: the DAC's played sequence through the reconstruction filter."""
        alpha = self._alpha()
        if alpha is None:
            return played
        # y[k] = y[k−1] + α(x[k] − y[k−1]), from y[−1] = present
        return one_pole(np.ascontiguousarray(played, dtype=float), alpha, present)

    # ------------------------------------------------------------ data
    def _played(self) -> float:
        k = min(max(self.daq.scans_received - 1 - self._base, 0), self._commanded.size - 1)
        return float(self._commanded[k]) if self._commanded.size else 0.0

    def _commanded_at(self, first: int, n: int) -> np.ndarray:
        """The output commanded at scans ``first`` … ``first + n − 1`` (a scan before or after the values kept: the
        first or last of them); a copy, never a view of the values kept."""
        lo, last = first - self._base, self._commanded.size - 1
        if 0 <= lo and lo + n - 1 <= last:  # the usual block: every scan's value kept, in one slice
            return self._commanded[lo:lo + n].copy()
        return self._commanded[np.clip(lo + np.arange(n), 0, last)]

    def _note_live(self, t: np.ndarray, commanded: np.ndarray) -> None:
        """Keep :attr:`live_at`: the time of this block's last scan that commanded the output on, or that followed
        one that did (the last scan of the block before, for its first)."""
        on = np.abs(commanded) > OUTPUT_ON_V
        was = np.concatenate(([abs(self._last_commanded) > OUTPUT_ON_V], on[:-1]))
        marked = np.flatnonzero(on | was)
        if marked.size:
            self.live_at = float(t[marked[-1]])
        self._last_commanded = float(commanded[-1])

    def _record(self, block: StreamBlock, supervise: bool = True) -> None:
        n = block.n
        if n == 0:
            return
        self.scans += n
        t = block.times() - self.ctx.t0
        commanded = self._commanded_at(block.first_scan, n)
        self._note_live(t, commanded)
        col = {name: block.volts[:, i] for i, name in enumerate(block.names)}
        # a scan is valid when every channel is: a block whose every sample is valid (the rule) needs no reduction
        # scan by scan, which costs far more on a few channels than one over the whole block
        every = bool(block.valid.all())
        ok = np.ones(n, bool) if every else block.valid.all(axis=1)
        v, i = self.amp.monitor_values(col["vmon"], col["imon"])
        rec, snap = self.ctx.rec, self.ctx.snapshot
        rec.append("amplifier", t, voltage=v, current=i, commanded=commanded)
        disp = force = None
        if self.has_force:
            force = self.cfg.force_N_per_V * col["force"] + self.cfg.force_offset_N
            rec.append("load_cell", t, force=force, ok=ok.astype("u1"))
        if self.has_laser:
            head = self.cfg.laser_m_per_V * col["laser"] + self.cfg.laser_offset_m
            disp = self.ctx.to_specimen(head)
            rec.append("laser", t, displacement=disp, valid=(ok & np.isfinite(disp)).astype("u1"))
        self.ctx.v_cmd = self._played()
        snap.values["setpoint"] = self.ctx.v_cmd
        if not every and not ok.any():
            return
        last = n - 1 if every else int(np.flatnonzero(ok)[-1])
        snap.values["voltage"], snap.values["current"] = float(v[last]), float(i[last])
        if disp is not None:
            self.ctx.sup.update_displacement(float(disp[last]))
            snap.values["displacement"] = float(disp[last])
        if force is not None:
            snap.values["force"] = float(force[last])
        if not supervise:
            return
        good = slice(None) if every else np.flatnonzero(ok)  # every scan valid (the rule): no copies
        self.ctx.sup.check_monitors(_peak(v[good]), _peak(i[good]))
        if force is not None:
            self.ctx.sup.check_force(_peak(force[good]))
        if (m := self.ctx.verifier.scans(t, v, commanded, np.asarray(ok))) is not None:
            raise mismatch_trip(m, "the voltage monitor (scan clock)")

