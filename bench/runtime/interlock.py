"""The latched interlock: faults after which the output is no longer what the host last commanded.

Three kinds, each raised as :class:`InterlockTrip` (a :class:`~bench.runtime.safety.SafetyTrip`):

* **host stall** — the module that sets the amplifier's input went unheard from the host for longer than the
  stall bound while the output was on (a frozen process, a stalled USB driver, a suspended laptop). Its
  communication watchdog may have zeroed the output behind the host's back; the next write would turn high
  voltage back on by itself. Seen on :func:`time.monotonic` before any next write (real time only: a virtual
  clock cannot stall). Where the host spent that time waiting on another instrument that did not answer, the
  fault is that instrument's (**<instrument> silent**, e.g. "load cell silent"), not a host stall.
* **output mismatch** — the measured output voltage left the band around what was commanded (see
  :class:`OutputVerifier`): a stream-out the device did not play, a refused or lost set-point, a dead monitor, a
  calibration outside the datasheet's tolerance, a watchdog that fired.
* **stream-out underrun** — the DAQ played past the values the host had written.

A trip latches: the engine commands 0 V *at once* (never a ramp from a set-point the output may no longer hold),
records when and what was seen, and nothing re-energises the output until an operator resets the latch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.core.monitor_chain import SAFE_TOUCH_V
from bench.core.motion import MotionProfile
from bench.rig import RigConfig
from bench.runtime.safety import SafetyTrip

STALL_FRACTION = 0.8  # default stall bound: this share of the module's communication watchdog
STALL_NO_WATCHDOG_S = 1.0  # default stall bound of a set-point module without a watchdog
DAQ_LAG_S = 1e-3  # default lag allowance on the scan clock (the TREK follows within one 10-kHz scan)
POLLED_LAG_S = 0.3  # default lag allowance of polled monitors (ADAM-4017+: 10 S/s for all channels)
POLLED_READINGS = 2  # a polled mismatch must be seen in this many readings in a row
MOTION_SAMPLES = 11  # the motion verifier compares a reading with the expected positions at this many times
# |commanded| above this: the output is on (a watchdog firing would change it; supervised, settled before a
# hand-over). A command is exact — no monitor error to allow for — so the safe touch limit itself applies, where a
# *reading* must be within the rig's monitor-derived threshold (bench.rig.safe_monitor_v) to verify 0 V.
OUTPUT_ON_V = SAFE_TOUCH_V


class InterlockTrip(SafetyTrip):
    """A latched fault: ``kind`` (host stall, <instrument> silent, output mismatch, …) and one line of detail."""

    def __init__(self, kind: str, detail: str) -> None:
        self.kind, self.detail = kind, detail
        super().__init__(f"interlock: {kind}: {detail}")


def watchdog_period(rig: RigConfig) -> float | None:
    """The communication watchdog of the module that drives the amplifier's input [s] (None: none configured)."""
    amp = rig.amplifier
    if amp is None:
        return None
    if amp.drive == "daq":
        return rig.daq.watchdog_s if rig.daq is not None else None
    return amp.comm_watchdog_s


def stall_bound(rig: RigConfig) -> float:
    """How long the set-point module may go unheard while the output is on before the interlock latches [s]."""
    if rig.interlock.host_stall_s is not None:
        return rig.interlock.host_stall_s
    watchdog = watchdog_period(rig)
    return STALL_FRACTION * watchdog if watchdog is not None else STALL_NO_WATCHDOG_S


@dataclass(frozen=True)
class SilentWait:
    """The host waited ``waited`` s on the instrument of ``role`` and at least one request went unanswered
    (``detail``: the driver's words, or what was seen)."""

    role: str
    waited: float
    detail: str

    @property
    def name(self) -> str:
        """The role as a researcher reads it ("load cell")."""
        return self.role.replace("_", " ")


def check_contact(rig: RigConfig, away: float, output_on: bool, waited_on: SilentWait | None = None) -> None:
    """Latch when the set-point module went unheard for ``away`` s, longer than the bound, while the output was on:
    a host stall — or, where the host spent that time waiting on another instrument that did not answer
    (``waited_on``), that instrument's silence, named (the host did not stall; the wait starved the keep-alive)."""
    if not output_on:
        return
    bound = stall_bound(rig)
    if away > bound:
        watchdog = watchdog_period(rig)
        fired = (f"its {watchdog:g}-s communication watchdog {'has' if away >= watchdog else 'may have'} zeroed "
                 "the output" if watchdog is not None else "the output ran unsupervised")
        if waited_on is not None:
            raise InterlockTrip(f"{waited_on.name} silent", f"the host waited {waited_on.waited:.2f} s on the "
                                f"{waited_on.name}, which did not answer ({waited_on.detail}), and the set-point "
                                f"module went {away:.2f} s without a request meanwhile (bound {bound:.2f} s); "
                                f"{fired}; high voltage stays off until an operator resets")
        raise InterlockTrip("host stall", f"the set-point module went {away:.2f} s without a request from the "
                            f"host that it answered (bound {bound:.2f} s: a stalled host, or replies lost); {fired}; "
                            "high voltage stays off until an operator resets")


@dataclass
class Mismatch:
    """Where a verified output left its band: run time [s], measured and commanded voltage [V], how long [s]."""

    t: float
    measured: float
    commanded: float
    lasted: float


@dataclass(frozen=True)
class Verdict:
    """The last polled monitor reading as the verifier judged it: run time [s], measured [V], its band [V], whether
    the band is the last set-point's alone (``settled``: no earlier value within the lag may still show), and how
    many readings in a row were out of it (:data:`POLLED_READINGS` latch)."""

    t: float
    measured: float
    lo: float
    hi: float
    settled: bool
    bad: int

    @property
    def in_band(self) -> bool:
        return self.lo <= self.measured <= self.hi


def _trailing_extremes(x: np.ndarray, width: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the ``width`` values of ``x`` ending at each of its last ``n`` (``x`` holds at least
    n + width − 1): extremes of power-of-two spans built by doubling, two of them cover a window — exact, and
    O(n log width) rather than a reduction over every window's values."""
    lo = hi = x
    size = 1
    while 2 * size <= width:  # then lo[i], hi[i]: the extremes of x[i:i + size]
        lo, hi = np.minimum(lo[:-size], lo[size:]), np.maximum(hi[:-size], hi[size:])
        size *= 2
    first = x.size - n - width + 1  # where the first window starts
    late = first + width - size  # where the span that ends with it starts
    return (np.minimum(lo[first:first + n], lo[late:late + n]),
            np.maximum(hi[first:first + n], hi[late:late + n]))


class OutputVerifier:
    """Compares the measured output voltage with what was commanded, through the path's stated dynamics.

    A sample is out of band when the measured voltage lies outside [lo − tol, hi + tol], where lo/hi are the
    smallest/largest value commanded over the last ``lag`` (the amplifier and the monitor follow with a delay;
    any value of that window may be what the monitor shows) and tol = tolerance_V + tolerance_rel × max(|lo|,
    |hi|). Hardware-timed scans: a fault when out-of-band scans follow each other for ``mismatch_s`` on the scan
    clock. Polled readings: a fault in :data:`POLLED_READINGS` readings in a row. Invalid samples neither count
    nor break a run of bad ones.
    """

    def __init__(self, rig: RigConfig, scan_rate: float | None) -> None:
        cfg = rig.interlock
        self.tol_v, self.tol_rel = cfg.output_tolerance_V, cfg.output_tolerance_rel
        self.scan_rate = scan_rate
        self.lag = cfg.output_lag_s if cfg.output_lag_s is not None else (
            DAQ_LAG_S if scan_rate is not None else POLLED_LAG_S)
        self.mismatch_s = cfg.output_mismatch_s
        self._tail = np.zeros(0)  # commanded values of the last scans of the previous block (the lag window)
        self._bad_since: float | None = None  # run time of the first out-of-band sample of the present run
        self._bad_count = 0
        self._history: list[tuple[float, float]] = []  # polled: (run time, commanded) of recent set-points
        self.last: Verdict | None = None  # polled: the last reading judged against a band

    def _band(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tol = self.tol_v + self.tol_rel * np.maximum(np.abs(lo), np.abs(hi))
        return lo - tol, hi + tol

    # ------------------------------------------------------------ hardware-timed: one block of scans
    def scans(self, t: np.ndarray, measured: np.ndarray, commanded: np.ndarray, ok: np.ndarray) -> Mismatch | None:
        """Check one block of scans (run times, measured and commanded output [V], validity); returns the first
        mismatch that lasted ``mismatch_s``, or None."""
        assert self.scan_rate is not None
        n = t.size
        if n == 0:
            return None
        width = max(2, math.ceil(self.lag * self.scan_rate) + 1)
        cmd = np.concatenate([self._tail, commanded])
        pad = width - 1 - self._tail.size
        if pad > 0:  # the first block of a stream: nothing earlier than its first scan was commanded
            cmd = np.concatenate([np.full(pad, cmd[0]), cmd])
        lo, hi = self._band(*_trailing_extremes(cmd, width, n))
        self._tail = cmd[-(width - 1):].copy()
        bad = ok & ((measured < lo) | (measured > hi))
        if not bad.any():
            if ok.any():
                self._bad_since = None
            return None
        # runs of out-of-band scans across the block; valid in-band scans end a run, invalid ones do not
        good = ok & ~bad
        for k in np.flatnonzero(bad | good):
            if good[k]:
                self._bad_since = None
                continue
            if self._bad_since is None:
                self._bad_since = float(t[k])
            if t[k] - self._bad_since + 1.0 / self.scan_rate >= self.mismatch_s - 1e-12:
                return Mismatch(float(t[k]), float(measured[k]), float(commanded[k]),
                                float(t[k] - self._bad_since + 1.0 / self.scan_rate))
        return None

    def restart(self) -> None:
        """A new stream (its first scan follows no earlier commanded value of the same stream)."""
        self._tail = np.zeros(0)
        self._bad_since = None

    # ------------------------------------------------------------ software-timed: set-points and polled readings
    def commanded(self, t: float, volts: float) -> None:
        """A set-point sent at run time ``t``."""
        self._history.append((t, volts))
        # keep what the lag window can still reach, and the last value before it
        cut = 0
        while cut + 1 < len(self._history) and self._history[cut + 1][0] <= t - self.lag:
            cut += 1
        del self._history[:cut]

    def reading(self, t: float, measured: float, valid: bool = True) -> Mismatch | None:
        """Check one polled monitor reading taken at run time ``t``; returns a mismatch after
        :data:`POLLED_READINGS` out-of-band readings in a row, else None."""
        if not valid or not math.isfinite(measured) or not self._history:
            return None
        edge = t - self.lag + 1e-9  # a set-point exactly lag before the reading is the one "before" it
        window = [v for tv, v in self._history if tv > edge]
        before = [v for tv, v in self._history if tv <= edge]
        if not before:  # what the output held before the first set-point known here may still show: unknown
            return None
        window.append(before[-1])
        lo, hi = self._band(np.array([min(window)]), np.array([max(window)]))
        settled = min(window) == max(window) == self._history[-1][1]
        if lo[0] <= measured <= hi[0]:
            self._bad_count, self._bad_since = 0, None
            self.last = Verdict(t, measured, float(lo[0]), float(hi[0]), settled, 0)
            return None
        self._bad_count += 1
        self.last = Verdict(t, measured, float(lo[0]), float(hi[0]), settled, self._bad_count)
        if self._bad_since is None:
            self._bad_since = t
        if self._bad_count >= POLLED_READINGS:
            return Mismatch(t, measured, self._history[-1][1], t - self._bad_since)
        return None


class MotionVerifier:
    """The motor's measured position against where its go-tos put it.

    The expected motion is the drive's time-optimal trapezoid (:class:`~bench.core.motion.MotionProfile`, the VAI
    go-to of the LinMot manual) from where the last one had it, recomputed at every go-to with its velocity and
    acceleration limits. A reading out of [min, max] of the expected positions over the last ``motor_lag_s``,
    widened by ``motor_tolerance_m``, in :data:`POLLED_READINGS` readings in a row is a fault: a carriage that does
    not follow (a jammed slider, a broken coupling, a drive that took the command and did not move). After a stop
    (the drive decelerates by its own ramp) the expectation starts again from the first reading ``motor_lag_s``
    later."""

    def __init__(self, rig: RigConfig) -> None:
        self.tol, self.lag = rig.interlock.motor_tolerance_m, rig.interlock.motor_lag_s
        self._profile: MotionProfile | None = None
        self._idle_until = -math.inf  # after a stop: no expectation before this run time
        self._bad = 0
        self._bad_since = 0.0

    @property
    def anchored(self) -> bool:
        """Whether the expectation has a starting point (a reading, or :meth:`anchor`)."""
        return self._profile is not None

    def anchor(self, t: float, position: float) -> None:
        """Where the motor stands at run time ``t`` (read before the first go-to after a start or a stop)."""
        self._profile = MotionProfile.hold(t, position)
        self._idle_until = -math.inf

    def commanded(self, t: float, target: float, vmax: float, acc: float) -> None:
        """A go-to sent at run time ``t`` (after :meth:`anchor` or a reading gave a starting point)."""
        if self._profile is None:
            return
        p, v = self._profile.at(t)
        self._profile = MotionProfile.plan(t, p, v, target, vmax, acc, acc)

    def expected_at(self, t: float) -> float | None:
        """Where the go-tos so far put the motor at run time ``t`` [m, motor coordinates] (None: no starting point)."""
        return None if self._profile is None else self._profile.at(t)[0]

    def stopped(self, t: float) -> None:
        """The motion was aborted at run time ``t`` (the drive's own deceleration): start again after it."""
        self._profile = None
        self._idle_until = t + max(self.lag, 0.5)

    def reading(self, t: float, position: float) -> Mismatch | None:
        """Check one encoder reading at run time ``t``; a mismatch after two in a row, else None."""
        if not math.isfinite(position) or t < self._idle_until:
            return None
        if self._profile is None:
            self._profile = MotionProfile.hold(t, position)
            return None
        expected = self._expected(t)
        if min(expected) - self.tol <= position <= max(expected) + self.tol:
            self._bad = 0
            return None
        self._bad += 1
        if self._bad == 1:
            self._bad_since = t
        if self._bad >= POLLED_READINGS:
            return Mismatch(t, position, expected[-1], t - self._bad_since)
        return None

    def _expected(self, t: float) -> list[float]:
        """The expected positions at ``MOTION_SAMPLES`` times evenly spaced over [t − lag, t], t last: the values
        ``profile.evaluate(np.linspace(t - lag, t, MOTION_SAMPLES))`` gives, computed as floats (the same
        operations in the same order) without numpy's per-call cost at every encoder poll."""
        assert self._profile is not None
        start = t - self.lag
        rest = self._profile.rest
        if rest is not None and min(start, t) >= rest[0]:  # at rest over the whole window: every sample the same
            return [rest[1]] * MOTION_SAMPLES
        at = self._profile.at
        step = (t - start) / (MOTION_SAMPLES - 1)
        return [at(k * step + start)[0] for k in range(MOTION_SAMPLES - 1)] + [at(t)[0]]


def motion_trip(m: Mismatch) -> InterlockTrip:
    """The interlock trip of a motor that does not follow its go-tos."""
    return InterlockTrip("motor mismatch", f"the motor encoder read {m.measured * 1e3:.2f} mm at {m.t:.3f} s where "
                         f"its go-tos put it at {m.commanded * 1e3:.2f} mm (off for {m.lasted * 1e3:.0f} ms): the "
                         "carriage does not follow the drive's commands")


def mismatch_trip(m: Mismatch, what: str) -> InterlockTrip:
    """The interlock trip of a verified-output mismatch, naming what was compared."""
    return InterlockTrip("output mismatch", f"{what} read {m.measured:.0f} V at {m.t:.4f} s where {m.commanded:.0f} "
                         f"V was commanded (out of the commanded band for {m.lasted * 1e3:.1f} ms): the output is not "
                         "what the host set (a refused or unplayed set-point, a dead monitor, a calibration off, a "
                         "watchdog that fired)")
