"""The plant: the specimen model plus the rig's high-voltage output stage and motor coupling.

All simulated instruments of a rig share one :class:`Plant` and one clock. The plant is lazy: it advances
its physical model (fixed step h, compiled streaming integrator of :mod:`bench.models`) up to the clock's
present whenever an instrument reads it or changes an input, so the same code serves wall-clock
(hardware-in-the-loop) and virtual-time runs. Every advanced block is passed to listeners (device-side
buffers such as the LK-G data storage and the ADAM-4017+ conversions).

Specimens: the thesis membrane (output: in-plane displacement u) or the LS-DEA in one of three
configurations — ``motor`` (aperture x = x0 + motor position, load-cell force), ``blocked`` (x fixed) and
``hung`` (free end under a hung mass; output x).
"""

from __future__ import annotations

import copy
import math
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from bench.core.amplifier_dynamics import lowpass, monitor_response, monitors, output_response, step_targets
from bench.core.clock import Clock
from bench.core.motion import MotionProfile, motion_into, motions_into
from bench.core.noise import TREK_DYNAMICS, Realism
from bench.models.lozenge import LozengeParams
from bench.models.lozenge_runs import LozengeStream
from bench.models.membrane import MembraneParams
from bench.models.membrane_runs import MembraneStream
from bench.numbers import mv_per_m


def _without_when(failure: str) -> str:
    """A model's failure text without its own 'at sample k' / 'at t = … s' (times of its block)."""
    return re.sub(r" at (sample [0-9]+|t = [-+0-9.e]+ s)", "", failure)


def _membrane_failure(t: np.ndarray, lam: np.ndarray, field: np.ndarray, p: MembraneParams,
                      runaway_at: float = math.inf) -> tuple[str, float]:
    """What failed first in a block and when: breakdown (|E| > E_B), runaway stretch (pull-in; from
    ``runaway_at`` on when the integrator stopped there) or a non-finite state — the tests of
    ``membrane.failure_reason``, taken in time order (the model's text names the first kind in its own
    priority order, which can be a later sample)."""
    with np.errstate(invalid="ignore"):
        kinds = [(np.abs(field) > p.breakdown_field, f"true field above breakdown {mv_per_m(p.breakdown_field)} MV/m"),
                 ((lam > p.runaway_stretch) | (t >= runaway_at),
                  f"runaway stretch: λ above {p.runaway_stretch} (pull-in)"),
                 (~np.isfinite(lam), "non-finite stretch (Gent lock-up or numerical blow-up)")]
    firsts = [(int(np.argmax(bad)), text) for bad, text in kinds if bad.any()]
    i, text = min(firsts, key=lambda f: f[0]) if firsts else (t.size - 1, kinds[2][1])
    return f"specimen failure: {text}", float(t[i])


def _first(t: np.ndarray, bad: np.ndarray) -> float | None:
    """Time of the first failing sample of a block (None: the model failed on a test not repeated here)."""
    return float(t[int(np.argmax(bad))]) if bad.any() else None

Listener = Callable[["PlantBlock"], None]
BLOCK_STEPS = 20_000  # longest block handed to the compiled integrator at once
PIECES_NUMPY = 32  # more pending motion events (or pieces) than this: a block split and filled in batches


@dataclass(frozen=True)
class AmplifierSpec:
    """A TREK HS amplifier as the plant and the monitor wiring see it."""

    model: str
    max_output: float  # V
    max_current: float  # A (DC)
    gain: float  # V out per V in
    vmon_ratio: float  # V of output per V of monitor
    imon_ratio: float  # A of output per V of monitor


# TREK HS datasheets (Advanced Energy 2022): ±10 kV, 10 mA / 40 mA DC, gain 1000 V/V. Monitor ratios
# [assumed: the operator manual was not read; calibrate and set them in the rig file].
TREK_DATASHEET = {"10/10B-HS": AmplifierSpec("10/10B-HS", 10e3, 10e-3, 1000.0, 1000.0, 1e-3),
                  "10/40A-HS": AmplifierSpec("10/40A-HS", 10e3, 40e-3, 1000.0, 1000.0, 4e-3)}


@dataclass(frozen=True)
class HVStage:
    """High-voltage amplifier output stage (TREK HS datasheet figures, :data:`bench.core.noise.TREK_DYNAMICS`).

    Output = gain × analog input, clipped to ±max_output, through a first-order stage (corner ``bandwidth_Hz``)
    that moves at most at min(slew, current limit / C) — the current limit ``peak_current`` for ``peak_s``, then
    ``max_current`` (DC) — into the specimen's capacitance (:mod:`bench.core.amplifier_dynamics`); after
    dielectric breakdown the load is a short ``r_short``. Defaults: the 10/10B-HS.
    """

    gain: float = 1000.0
    max_output: float = 10e3  # V
    max_current: float = 10e-3  # A (DC)
    slew: float = 700e6  # V/s (> 700 V/µs)
    r_short: float = 1e3  # Ω, electrodes after breakdown
    bandwidth_Hz: float = 19.5e3
    peak_current: float = 40e-3  # A
    peak_s: float = 1e-3
    model: str = "10/10B-HS"  # whose monitors (bandwidths, accuracy, noise) the plant reports through

    @classmethod
    def of(cls, amplifier: AmplifierSpec) -> HVStage:
        """The output stage of this amplifier (gain, limits and dynamics from its datasheet)."""
        dyn = TREK_DYNAMICS[amplifier.model]
        return cls(gain=amplifier.gain, max_output=amplifier.max_output, max_current=amplifier.max_current,
                   slew=dyn.slew, bandwidth_Hz=dyn.bandwidth_Hz, peak_current=dyn.peak_current, peak_s=dyn.peak_s,
                   model=amplifier.model)


@dataclass(frozen=True)
class PlantBlock:
    """Samples of one advanced block (one per model step): times [s] and observables (SI).

    ``voltage`` and ``current`` are what the amplifier's monitors report (bandwidth, gain/offset error and noise
    of :mod:`bench.core.amplifier_dynamics`, at the output's scale): every instrument wired to the monitors reads
    them. ``v_out`` and ``i_out`` are the true output (what the specimen gets)."""

    t: np.ndarray
    voltage: np.ndarray  # amplifier output as its voltage monitor reports it [V]
    current: np.ndarray  # amplifier output current as its current monitor reports it [A]
    displacement: np.ndarray  # membrane u, or LS-DEA aperture x [m]
    force: np.ndarray  # force on the load cell [N] (0 when not coupled)
    field: np.ndarray  # true electric field in the film [V/m]
    breakdown: np.ndarray  # breakdown field at the present stretch [V/m]
    v_out: np.ndarray  # true amplifier output [V]
    i_out: np.ndarray  # true amplifier output current [A]


PLANT_FIELDS = ("t", "voltage", "current", "displacement", "force", "field", "breakdown", "v_out", "i_out")


class Plant:
    """Specimen + HV stage + motor coupling, advanced lazily to the clock (thread-safe)."""

    def __init__(self, clock: Clock, specimen: MembraneParams | LozengeParams, *,
                 configuration: Literal["membrane", "motor", "blocked", "hung"] = "membrane",
                 temperature: float = 296.0, x0: float = 0.05, h: float = 1e-4, hv: HVStage | None = None,
                 motor_sign: float = 1.0, membrane_method: Literal["fixed", "rodas"] = "fixed",
                 realism: Realism | None = None) -> None:
        """``membrane_method``: how the membrane model advances (``MembraneStream``): ``fixed`` for the twins,
        ``rodas`` (error-controlled, in blocks) for the dry run; ``realism``: noise on or off and its seed (default:
        off — ideal monitors, for the twins' own conformance tests; a rig's plant, :func:`bench.rig.plant_for`,
        has the rig file's ``[simulation] noise``, on by default)."""
        self.clock = clock
        self.specimen = specimen
        self.configuration = configuration
        self.temperature = temperature
        self.x0 = x0
        self.h = h
        self.hv = hv or HVStage()
        self.motor_sign = motor_sign
        self.realism = realism or Realism(noise=False)
        dyn = TREK_DYNAMICS.get(self.hv.model, TREK_DYNAMICS["10/10B-HS"])
        self.vmon, self.imon = monitors(dyn, self.hv.max_output, self.hv.max_current, self.realism)
        self._t_limited = 0.0  # time the output has spent current-limited above its DC rating
        self._target = 0.0  # the output stage's last target [V]
        self.lock = threading.RLock()
        self.listeners: list[Listener] = []
        self.v_out = 0.0  # amplifier output [V]
        # input histories not yet integrated: (time, value) — the model integrates lazily, in large blocks
        # amplifier analog input [V] not yet integrated: chunks of (times, values), merged in time order on use
        self._v_chunks: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(1), np.zeros(1))]
        self._v_ordered = True  # the chunks joined are in time order: nothing to merge, the last one ends them
        self._motions: list[tuple[float, MotionProfile]] = [(0.0, MotionProfile.hold(0.0, 0.0))]
        self.input_watchdog: float | None = None  # analog module's communication safety period [s]
        self._last_feed = 0.0
        self.watchdog_tripped = False
        self.watchdog_trips = 0  # how often the watchdog zeroed the input (the module's flag register follows it)
        self.broken = False
        self.failure = ""
        self.t = 0.0
        self._n = 0  # steps done
        self._q_prev = 0.0
        if isinstance(specimen, MembraneParams):
            if configuration != "membrane":
                raise ValueError("the membrane specimen has only the 'membrane' configuration")
            self._membrane: MembraneStream | None = MembraneStream(specimen, h=h, T=temperature,
                                                                   method=membrane_method)
            self._lozenge: LozengeStream | None = None
            # capacitance at rest (bounds the first step's current): one step of a copy at 0 V
            c0 = copy.deepcopy(self._membrane).advance(np.zeros(1), temperature).capacitance
            self._C = float(c0[-1]) if c0.size and np.isfinite(c0[-1]) and c0[-1] > 0 else 1e-9
        else:
            if configuration not in ("motor", "blocked", "hung"):
                raise ValueError(f"LS-DEA configuration must be motor, blocked or hung, got {configuration!r}")
            self._membrane = None
            mode: Literal["hung", "imposed"] = "hung" if configuration == "hung" else "imposed"
            self._lozenge = LozengeStream(specimen, mode, None if configuration == "hung" else x0, h=h)
            self._C = 1e-10
        self._refresh_last_at_rest()

    # ------------------------------------------------------------------ inputs
    @property
    def v_in(self) -> float:
        """Latest amplifier analog input [V]."""
        with self.lock:
            return float(self._v_last()[1])

    @property
    def motion(self) -> MotionProfile:
        """The motor's current motion profile."""
        return self._motions[-1][1]

    def set_amplifier_input(self, volts: float, at: float | None = None) -> None:
        """New analog input of the amplifier [V], effective from ``at`` (default: the clock's present; integrated
        lazily). A twin passes the instant the request arrived: a virtual clock may have moved on while its thread
        worked (a host that stopped waiting for the reply), and the write happened when it arrived."""
        t = self.clock.now() if at is None else at
        with self.lock:
            self._add_input(np.array([t]), np.array([float(volts)]), True)

    def schedule_amplifier_input(self, times: np.ndarray | list[float], volts: np.ndarray | list[float]) -> None:
        """Analog inputs of the amplifier at given times (a hardware-timed output's samples, played by its own
        clock), none of them in the plant's past; integrated lazily like :meth:`set_amplifier_input`."""
        t = np.array(times, dtype=float)
        v = np.array(volts, dtype=float)
        if t.shape != v.shape or t.ndim != 1:
            raise ValueError("amplifier input: times and values must be 1-D arrays of one length")
        if not t.size:
            return
        # one pass in the usual case (a DAQ twin's packet of scan times): every time ≥ the one before it holds no
        # NaN (a comparison with NaN is false), so its ends alone say whether all are finite
        ordered = bool((t[1:] >= t[:-1]).all())
        finite = math.isfinite(t[0]) and math.isfinite(t[-1]) if ordered else bool(np.isfinite(t).all())
        if not finite:  # a NaN time would stop every later input from playing (review finding)
            raise ValueError("amplifier input: every scheduled time must be finite")
        with self.lock:
            if t[0] < self.t - 1e-9:
                raise ValueError(f"amplifier input scheduled {self.t - t[0]:.6f} s in the plant's past")
            self._add_input(t, v, ordered)  # finite: not all ≥ is some <

    def stream_started(self, t: float) -> None:
        """A hardware-timed stream's scan 0 falls at plant time ``t`` (the T7 twin's enable): the model needs nothing
        of it (a replayed record aligns its own kickoffs to it: :class:`bench.runtime.replay.ReplayPlant`)."""

    def schedule_amplifier_scans(self, times: np.ndarray, volts: np.ndarray) -> None:
        """:meth:`schedule_amplifier_input` of samples on a scan clock, as a DAQ twin makes them for the plant: 1-D
        float arrays of one length, its own (kept as they are, never written again), times that do not decrease
        (scan k at t0 + k / rate); what is still checked: every time finite, none in the plant's past."""
        if not times.size:
            return
        if not (math.isfinite(times[0]) and math.isfinite(times[-1])):  # not decreasing: the ends bound the rest
            raise ValueError("amplifier input: every scheduled time must be finite")
        with self.lock:
            if times[0] < self.t - 1e-9:
                raise ValueError(f"amplifier input scheduled {self.t - times[0]:.6f} s in the plant's past")
            self._add_input(times, volts, True)

    def unschedule_amplifier_input(self, after: float) -> None:
        """Drop the scheduled amplifier inputs later than ``after`` (a hardware-timed output stopped).

        The first pending input is the value in force (:meth:`_input_pieces`), kept even when its time is later
        than ``after`` — a scan the stopped stream counted as played at ``after``, its time a rounding later
        (t_enable + k / rate): it is moved to ``after``, so that an input set at ``after`` (the host's 0-V DAC write
        just after the stop) comes after it in time order, not before it, where the stale scan would stay in force
        (a T7 twin tie, 2026-11-28: a trip during a resume's ramp up left the output at 2 kV)."""
        with self.lock:
            t, v = self._v_inputs()
            keep = int(np.searchsorted(t, after, side="right"))
            if keep == 0:
                t, v, keep = np.array([min(float(t[0]), after)]), v[:1], 1
            self._v_chunks = [(t[:keep], v[:keep])]

    def feed_watchdog(self, at: float | None = None) -> None:
        """The analog output module heard from the host at ``at`` (default: the clock's present), which resets its
        communication-safety timer — after noting a timeout that came first: the model integrates lazily, and a
        request after a long silence must not undo a watchdog that fired in it (a virtual clock has no ticker
        that would have seen it)."""
        now = self.clock.now() if at is None else at
        if self.input_watchdog is not None and now - self._last_feed >= self.input_watchdog:
            self._check_watchdog(now)
        self._last_feed = max(self._last_feed, now)

    def _check_watchdog(self, t_end: float) -> None:
        """Communication safety: with no request for ``input_watchdog`` s, the module outputs 0 V."""
        if self.input_watchdog is None:
            return
        deadline = self._last_feed + self.input_watchdog
        with self.lock:
            t_last, v_last = self._v_last()
            if deadline <= t_end and deadline > t_last and v_last != 0.0:
                self._add_input(np.array([deadline]), np.zeros(1), True)
                self.watchdog_tripped = True
                self.watchdog_trips += 1

    def set_motion(self, make: Callable[[float, float, float], MotionProfile]) -> MotionProfile:
        """Replace the motor's motion from now: ``make(t, position, velocity)`` returns the new profile."""
        with self.lock:
            now = self.clock.now()
            p, v = self.motion.at(now)
            profile = make(now, p, v)
            self._motions.append((now, profile))
            return profile

    def add_motions(self, motions: list[tuple[float, MotionProfile]]) -> None:
        """Profiles planned ahead, each (time, profile) replacing the motion from its time on — not before the last
        one's: what :meth:`set_motion` does at each of those times (the dry run plans a segment's go-tos at once)."""
        with self.lock:
            self._motions.extend(motions)

    def motor_state(self, t: float | None = None) -> tuple[float, float]:
        """Motor (position [m], velocity [m/s]) at t (default: now).

        Kinematic, so without the plant's lock: a drive polled for its position does not wait for an integration
        under way (the profile in force is one atomic read; profiles are only appended or dropped from the front)."""
        return self.motion.at(self.clock.now() if t is None else t)

    def change_specimen(self, temperature_K: float | None = None, hung_mass_kg: float | None = None,
                        prototype: int | None = None) -> None:
        """Between tests: new temperature (membrane), hung mass or mounted prototype (LS-DEA), from now on.

        A new hung mass keeps the present state (the mass is hung on the actuator where it is); a new prototype
        starts relaxed at the present aperture.
        """
        with self.lock:
            self.advance_to(self.clock.now())
            if temperature_K is not None:
                if self._membrane is None:
                    raise ValueError("temperature acts on the membrane model only")
                self.temperature = float(temperature_K)
                self._membrane.T = self.temperature
            if hung_mass_kg is None and prototype is None:
                return
            params = self.specimen
            if self._lozenge is None or not isinstance(params, LozengeParams):
                raise ValueError("hung mass and prototype apply to the LS-DEA")
            params = params.changed(prototype, hung_mass_kg)  # another prototype keeps the fitted material
            y = self._lozenge.state.copy()
            lmode: Literal["hung", "imposed"] = "hung" if self.configuration == "hung" else "imposed"
            stream = LozengeStream(params, lmode, float(y[0]), h=self.h,
                                   y0=None if prototype is not None else y, t0=self._lozenge.t)
            self.specimen, self._lozenge = params, stream
            self.broken, self.failure = False, ""
            self._refresh_last_at_rest()

    def inject_breakdown(self) -> None:
        """Fault injection: the dielectric breaks down now (electrodes shorted from here on)."""
        with self.lock:
            self.advance_to(self.clock.now())
            self._break("dielectric breakdown (injected)")

    def _break(self, why: str, at: float | None = None) -> None:
        """The specimen fails at ``at`` (default: now) — the model's own sample of failure when it is known,
        not the start of the integration block that found it."""
        if not self.broken:
            self.broken = True
            self.failure = f"{why} at t = {self.t if at is None else at:.4f} s"

    # ------------------------------------------------------------------ stepping
    def warm_up(self) -> None:
        """Compile the model's kernels now, on a copy (a fresh install has no numba cache: compiling on the
        first request would take seconds inside a twin's reply and the host would time out)."""
        with self.lock:
            output_response(np.zeros(2), 0.0, self.h, 1e-5, 1e8, 1e-9, 1e-2, 4e-2, 1e-3, 0.0)  # the output stage
            lowpass(np.zeros(2), 0.5, 0.0)  # and its monitors
            monitor_response(np.zeros(2), 0.5, 0.0, 1.0, 0.0, np.zeros(2))
            step_targets(np.zeros(2), np.zeros(2), 2, 0, 2, float(self.h), 1.0, 1.0, -1.0, 0.0)
            motion_into(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(2), 0, 2, 0.0, 1.0,
                        np.zeros((2, 3)))
            motions_into(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.array([0, 1]), np.zeros(1, np.int64),
                         np.full(1, 2, np.int64), np.zeros(2), 0.0, 1.0, np.zeros((2, 3)))  # > PIECES_NUMPY events
            if self._membrane is not None:
                copy.deepcopy(self._membrane).advance(np.zeros(2), self.temperature)
            if self._lozenge is not None:
                copy.deepcopy(self._lozenge).advance(np.tile(np.array([0.0, self.x0, 0.0]), (2, 1)))
                copy.deepcopy(self._lozenge).advance_rig(np.tile(np.array([0.0, self.x0, 0.0]), (2, 1)))

    def observe(self) -> PlantBlock:
        """Advance to now and return the last sample (arrays of length 1)."""
        with self.lock:
            self.advance_to(self.clock.now())
            return self.last

    def advance_to(self, t: float) -> None:
        """Advance the model to time t in whole steps (no-op if already there)."""
        with self.lock:
            n_total = math.floor((t - self.t) / self.h + 1e-6)  # clock sums drift by ~1e-12 s
            while n_total > 0:
                n = min(n_total, BLOCK_STEPS)
                self._advance(n)
                n_total -= n

    def _pieces(self, events: list[tuple[float, MotionProfile]], n: int) -> list[tuple[int, int, MotionProfile]]:
        """Split the next n steps at the input events: [(first step, end step, value)], dropping used history."""
        if len(events) > PIECES_NUMPY:
            return self._many_pieces(events, n)
        first_step = self._n
        starts = [max(0, math.floor(te / self.h + 1e-6) - first_step) for te, _ in events]
        out: list[tuple[int, int, MotionProfile]] = []
        for i, (_, value) in enumerate(events):
            a = min(starts[i], n)
            b = min(starts[i + 1], n) if i + 1 < len(events) else n
            if b > a or (i == len(events) - 1 and a < n):
                out.append((a, b, value))
        keep = max(i for i, st in enumerate(starts) if st <= n)  # the value in force at the block's end
        del events[:keep]
        return out

    def _many_pieces(self, events: list[tuple[float, MotionProfile]], n: int) -> list[tuple[int, int, MotionProfile]]:
        """:meth:`_pieces` in numpy passes (the dry run queues a segment's thousands of go-tos before it advances)."""
        t = np.fromiter((te for te, _ in events), dtype=float, count=len(events))
        starts = np.maximum(np.floor(t / self.h + 1e-6).astype(np.int64) - self._n, 0)
        a = np.minimum(starts, n)
        b = np.append(a[1:], n)  # each piece ends where the next one starts (the last: at the block's end)
        out = [(int(a[i]), int(b[i]), events[i][1]) for i in np.flatnonzero(b > a).tolist()]
        keep = max(np.flatnonzero(starts <= n).tolist())
        del events[:keep]
        return out

    def _add_input(self, t: np.ndarray, v: np.ndarray, ordered: bool) -> None:
        """Append amplifier inputs (``ordered``: their times do not decrease), noting whether all the pending
        ones are still in time order (then nothing has to be merged or sorted: :meth:`_input_pieces`)."""
        chunks = self._v_chunks
        self._v_ordered = self._v_ordered and ordered and not (chunks and t[0] < chunks[-1][0][-1])
        chunks.append((t, v))

    def _v_last(self) -> tuple[float, float]:
        """The last pending amplifier input in time order: (time, value)."""
        t, v = self._v_chunks[-1] if self._v_ordered else self._v_inputs()
        return float(t[-1]), float(v[-1])

    def _v_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """The pending amplifier inputs as one (times, values) pair in time order (equal times: in the order
        they were given)."""
        chunks = self._v_chunks
        if len(chunks) > 1:
            t = np.concatenate([c[0] for c in chunks])
            v = np.concatenate([c[1] for c in chunks])
            if np.any(t[1:] < t[:-1]):
                order = np.argsort(t, kind="stable")
                t, v = t[order], v[order]
            self._v_chunks = chunks = [(t, v)]
            self._v_ordered = True
        return chunks[0]

    def _input_pieces(self, n: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The amplifier inputs that start up to the end of the next ``n`` steps: (times, values, how many) in
        time order, the value in force at the block's end kept pending. Only the inputs that start within the
        block are looked at and joined (a DAQ twin schedules ~1 s of 10-kHz inputs ahead, in chunks in time
        order: those are not merged again at every block)."""
        bound = (self._n + n + 1 - 1e-6) * self.h
        chunks = self._v_chunks
        if not self._v_ordered:
            chunks = [self._v_inputs()]
        j = 1  # the chunks that hold the inputs before the bound (in time order: a prefix of them)
        while j < len(chunks) and chunks[j][0][0] < bound:
            j += 1
        if j == 1:
            t, v = chunks[0]
        else:
            t, v = np.concatenate([c[0] for c in chunks[:j]]), np.concatenate([c[1] for c in chunks[:j]])
        m = int(np.searchsorted(t, bound, side="left"))
        keep = max(m - 1, 0)  # keep the value in force at the block's end
        self._v_chunks = [(t[keep:], v[keep:]), *chunks[j:]]
        return t, v, m

    def _hv_output(self, n: int) -> np.ndarray:
        self._check_watchdog((self._n + n) * self.h)
        hv = self.hv
        t, v, m = self._input_pieces(n)
        per_step = step_targets(t, v, m, self._n, n, float(self.h), float(hv.gain), float(hv.max_output),
                                float(hv.max_current * hv.r_short) if self.broken else -1.0, self._target)
        self._target = float(per_step[-1])
        v, self._t_limited = output_response(per_step, self.v_out, self.h, 1.0 / (2.0 * math.pi * hv.bandwidth_Hz),
                                             hv.slew, max(self._C, 1e-15), hv.max_current,
                                             max(hv.peak_current, hv.max_current), hv.peak_s, self._t_limited)
        return v

    def _motor_into(self, t: np.ndarray, U: np.ndarray) -> None:
        """The motor's inputs at the step ends ``t``: ``U[:, 1]`` ← x0 + sign·position, ``U[:, 2]`` ← sign·velocity
        (:meth:`MotionProfile.evaluate`'s values, compiled; many pieces in one call, their phases joined)."""
        x0, sign = float(self.x0), float(self.motor_sign)
        pieces = self._pieces(self._motions, t.size)
        if len(pieces) > PIECES_NUMPY:
            starts, ends, profiles = zip(*pieces, strict=True)
            ts, ps, vs, accs = zip(*((pr.t_start, pr.p_start, pr.v_start, pr.acc) for pr in profiles), strict=True)
            offsets = np.zeros(len(ts) + 1, dtype=np.int64)
            np.cumsum(np.fromiter(map(len, ts), np.int64, len(ts)), out=offsets[1:])
            t0, p0, v0, a0 = (np.concatenate(c, dtype=np.float64) for c in (ts, ps, vs, accs))
            motions_into(t0, p0, v0, a0, offsets, np.array(starts, dtype=np.int64), np.array(ends, dtype=np.int64),
                         t, x0, sign, U)
            return
        for a, b, pr in pieces:
            motion_into(np.asarray(pr.t_start, np.float64), np.asarray(pr.p_start, np.float64),
                        np.asarray(pr.v_start, np.float64), np.asarray(pr.acc, np.float64), t, a, b, x0, sign, U)

    def _advance(self, n: int) -> None:
        k = np.arange(1, n + 1, dtype=float)
        t = (self._n + k) * self.h
        v_amp = self._hv_output(n)
        v_dea = np.zeros_like(v_amp) if self.broken else v_amp
        force = np.zeros(n)
        if self._membrane is not None:
            spec = self.specimen
            assert isinstance(spec, MembraneParams)  # the membrane stream is built for membrane parameters only
            tr = self._membrane.advance(v_dea, self.temperature)
            disp = tr.displacement
            charge = tr.charge
            cap = tr.capacitance
            field = tr.field
            breakdown = np.full(n, spec.breakdown_field)
            if tr.failed and not self.broken:
                self._break(*_membrane_failure(t, tr.stretch, field, spec, tr.extra.get("runaway_at", math.inf)))
        else:
            U = np.zeros((n, 3))
            U[:, 0] = v_dea
            if self.configuration == "motor":
                self._motor_into(t, U)
            elif self.configuration == "blocked":
                U[:, 1] = self.x0
            if self.configuration != "motor":
                self._pieces(self._motions, n)  # the motor is not coupled: only drop used history
            assert self._lozenge is not None  # one of the two streams is always built
            lt = self._lozenge.advance_rig(U)
            disp = lt.position
            charge = lt.charge
            cap = lt.capacitance
            field = lt.field
            breakdown = lt.breakdown_field
            if self.configuration != "hung":
                force = lt.force
            if lt.failed and not self.broken:
                with np.errstate(invalid="ignore"):
                    bad = ~np.isfinite(lt.position) | (np.abs(field) > breakdown)  # lozenge_runs' tests
                self._break(f"specimen failure: {_without_when(lt.failure)}", _first(t, bad))
        if self.broken:
            current = v_amp / self.hv.r_short
        else:  # dQ/dt over each step: np.diff of the charge after the last block's, without joining them
            current = np.empty(n)
            current[0] = charge[0] - self._q_prev
            np.subtract(charge[1:], charge[:-1], out=current[1:])
            current /= self.h
        q_end, c_end = float(charge[-1]), float(cap[-1])
        self._q_prev = q_end if math.isfinite(q_end) else self._q_prev
        if math.isfinite(c_end) and c_end > 0:
            self._C = c_end
        self.v_out = float(v_amp[-1])
        self._n += n
        self.t = self._n * self.h
        block = PlantBlock(t, self.vmon(v_amp, self.h), self.imon(current, self.h), disp, force, field, breakdown,
                           v_amp, current)
        self.last = PlantBlock(*(getattr(block, f)[-1:] for f in PLANT_FIELDS))
        for listener in self.listeners:
            listener(block)

    def _refresh_last_at_rest(self) -> None:
        """Initial observables (t = 0, no voltage)."""
        disp = force = 0.0
        breakdown = getattr(self.specimen, "breakdown_field", np.inf)
        if self._lozenge is not None:
            tr = self._lozenge.observe(0.0)
            disp = float(tr.position[0])
            force = 0.0 if self.configuration == "hung" else float(tr.force[0])
            breakdown = float(tr.breakdown_field[0])
            self._C = float(tr.capacitance[0])
        z = np.zeros(1)
        self.last = PlantBlock(np.array([self.t]), np.array([self.v_out]), z.copy(), np.array([disp]),
                               np.array([force]), z.copy(), np.array([breakdown]), np.array([self.v_out]), z.copy())
