"""Trapezoidal point-to-point motion (velocity, acceleration, deceleration limits), evaluated vectorised.

A :class:`MotionProfile` is a list of constant-acceleration phases starting from a known position and
velocity; it handles a start while moving (towards, away from, or overshooting the target).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from bench.models.jit import njit


@njit(cache=True, inline="always")
def bisect_right_in(ts: np.ndarray, m: int, t: float) -> int:
    """``bisect_right(ts[:m], t)`` (``np.searchsorted(ts[:m], t, side="right")``) in compiled code."""
    lo, hi = 0, m
    while lo < hi:
        mid = (lo + hi) // 2
        if t < ts[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True)
def motion_into(t_start: np.ndarray, p_start: np.ndarray, v_start: np.ndarray, acc: np.ndarray, t: np.ndarray,
                a: int, b: int, x0: float, sign: float, U: np.ndarray) -> None:
    """``U[k, 1]`` ← x0 + sign·position, ``U[k, 2]`` ← sign·velocity at ``t[k]`` for a ≤ k < b, of the profile with
    these phases: :meth:`MotionProfile.evaluate`'s doubles (the same operations in the same order), in one pass —
    the plant's motor input, without a dozen array passes per block."""
    last = t_start.size - 1
    for k in range(a, b):
        tk = t[k]
        i = min(max(bisect_right_in(t_start, t_start.size, tk) - 1, 0), last)
        tau = tk - t_start[i]
        if tau < 0.0:
            tau = 0.0
        pos = p_start[i] + v_start[i] * tau + 0.5 * acc[i] * tau * tau
        vel = v_start[i] + acc[i] * tau
        U[k, 1] = x0 + sign * pos
        U[k, 2] = sign * vel


@njit(cache=True)
def motions_into(t_start: np.ndarray, p_start: np.ndarray, v_start: np.ndarray, acc: np.ndarray,
                 offsets: np.ndarray, a: np.ndarray, b: np.ndarray, t: np.ndarray, x0: float, sign: float,
                 U: np.ndarray) -> None:
    """:func:`motion_into` for many pieces in one call: piece k is the profile of phases ``offsets[k]`` up to
    ``offsets[k + 1]`` of the joined phase arrays, over the steps ``a[k]`` ≤ k < ``b[k]``."""
    for k in range(a.size):
        o, e = offsets[k], offsets[k + 1]
        motion_into(t_start[o:e], p_start[o:e], v_start[o:e], acc[o:e], t, a[k], b[k], x0, sign, U)


@dataclass(frozen=True)
class MotionProfile:
    """Phases of constant acceleration: start times [s], start positions [m], velocities [m/s], accelerations."""

    t_start: np.ndarray
    p_start: np.ndarray
    v_start: np.ndarray
    acc: np.ndarray
    t_end: float  # time at which the target is reached and the axis is at rest
    target: float

    @classmethod
    def hold(cls, t: float, position: float) -> MotionProfile:
        """Stand still at ``position`` from t on."""
        return cls(np.array([t]), np.array([position]), np.array([0.0]), np.array([0.0]), t, position)

    @classmethod
    def plan(cls, t0: float, p0: float, v0: float, target: float, vmax: float, acc: float,
             dec: float) -> MotionProfile:
        """Time-optimal trapezoid from (p0, v0) at t0 to rest at ``target``."""
        phases: list[tuple[float, float]] = []  # (duration, acceleration)
        p, v = p0, v0

        def push(duration: float, a: float) -> None:
            nonlocal p, v
            if duration > 0:
                phases.append((duration, a))
                p += v * duration + 0.5 * a * duration * duration
                v += a * duration

        for _ in range(3):  # at most: stop moving away / stop after overshoot, then the trapezoid
            d = target - p
            s = math.copysign(1.0, d) if d != 0 else (-math.copysign(1.0, v) if v != 0 else 0.0)
            if s == 0.0:
                break
            u = s * v  # speed towards the target
            if u < 0:
                push(-u / dec, s * dec)
                continue
            if u * u / (2 * dec) > abs(d) * (1 + 1e-9) + 1e-12:
                push(u / dec, -s * dec)  # cannot stop in time: stop beyond the target, then come back
                continue
            D = abs(d)
            if u > vmax:
                push((u - vmax) / dec, -s * dec)
                u = vmax
                D = abs(target - p)
            vp = math.sqrt(max((D + u * u / (2 * acc)) / (1 / (2 * acc) + 1 / (2 * dec)), 0.0))
            vp = max(min(vp, vmax), u)
            push((vp - u) / acc, s * acc)
            cruise = abs(target - p) - vp * vp / (2 * dec)
            push(cruise / vp if vp > 0 else 0.0, 0.0)
            push(vp / dec, -s * dec)
            break
        starts = [t0]
        ps, vs, accs = [p0], [v0], []
        pp, vv = p0, v0
        for dur, a in phases:
            accs.append(a)
            pp += vv * dur + 0.5 * a * dur * dur
            vv += a * dur
            starts.append(starts[-1] + dur)
            ps.append(pp)
            vs.append(vv)
        accs.append(0.0)
        ps[-1], vs[-1] = target, 0.0  # remove round-off at rest
        return cls(np.array(starts), np.array(ps), np.array(vs), np.array(accs), starts[-1], target)

    def evaluate(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(position [m], velocity [m/s]) at times t (before the profile start: its start state)."""
        t = np.asarray(t, dtype=float)
        i = np.clip(np.searchsorted(self.t_start, t, side="right") - 1, 0, self.t_start.size - 1)
        tau = np.maximum(t - self.t_start[i], 0.0)
        pos = self.p_start[i] + self.v_start[i] * tau + 0.5 * self.acc[i] * tau * tau
        vel = self.v_start[i] + self.acc[i] * tau
        return pos, vel

    @cached_property
    def _phases(self) -> tuple[list[float], list[float], list[float], list[float]]:
        return self.t_start.tolist(), self.p_start.tolist(), self.v_start.tolist(), self.acc.tolist()

    @cached_property
    def rest(self) -> tuple[float, float] | None:
        """(time [s], position [m]) from which the profile stands still, the position exactly what :meth:`at` gives
        at any later time; None if its last phase moves (then no such time)."""
        ts, ps, vs, accs = self._phases
        if vs[-1] != 0.0 or accs[-1] != 0.0:
            return None
        return ts[-1], ps[-1] + vs[-1] * 0.0 + 0.5 * accs[-1] * 0.0 * 0.0  # at()'s sum for any τ ≥ 0 (signed zeros too)

    def at(self, t: float) -> tuple[float, float]:
        """(position [m], velocity [m/s]) at one time t, as floats: :meth:`evaluate`'s arithmetic on one sample without
        numpy's per-call cost (a drive polled for its position, a go-to planned from the present state)."""
        ts, ps, vs, accs = self._phases
        i = max(bisect_right(ts, t) - 1, 0)
        tau = max(t - ts[i], 0.0)
        return ps[i] + vs[i] * tau + 0.5 * accs[i] * tau * tau, vs[i] + accs[i] * tau

    def stop(self, t: float, dec: float) -> MotionProfile:
        """Profile that decelerates at ``dec`` from the state at t and holds where it comes to rest."""
        p, v = self.at(t)
        if v == 0.0:
            return MotionProfile.hold(t, p)
        return MotionProfile.plan(t, p, v, p + v * abs(v) / (2 * dec), abs(v) + 1e-12, dec, dec)
