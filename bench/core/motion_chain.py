"""A chain of go-tos planned in one compiled pass: each :meth:`MotionProfile.plan` from the state the previous
profile gives at its start (what :meth:`bench.core.plant.Plant.set_motion` does once per go-to).

The dry run streams a go-to per set-point tick (tens of thousands per campaign); planning them one Python call
at a time was most of its cost. The kernels repeat :meth:`MotionProfile.at` and :meth:`MotionProfile.plan`'s
doubles — the same operations in the same order, Python's ``min``/``max`` written out — so the profiles are
identical to the ones planned one by one.
"""

from __future__ import annotations

import math

import numpy as np

from bench.core.motion import MotionProfile, bisect_right_in
from bench.models.jit import njit

MAX_PHASES = 8  # a plan has at most 6 moving phases, plus the rest at its end


@njit(cache=True)
def _at(ts: np.ndarray, ps: np.ndarray, vs: np.ndarray, accs: np.ndarray, m: int, t: float) -> tuple[float, float]:
    """:meth:`MotionProfile.at` on the first m phases."""
    i = max(bisect_right_in(ts, m, t) - 1, 0)
    tau = t - ts[i]
    if 0.0 > tau:  # max(tau, 0.0)
        tau = 0.0
    return ps[i] + vs[i] * tau + 0.5 * accs[i] * tau * tau, vs[i] + accs[i] * tau


@njit(cache=True)
def _push(m: int, duration: float, a: float, T: np.ndarray, P: np.ndarray, V: np.ndarray, A: np.ndarray) -> int:
    """Append a phase of ``duration`` at acceleration a after phase m (none if duration ≤ 0); returns the last."""
    if duration > 0:
        p, v = P[m], V[m]
        A[m] = a
        T[m + 1] = T[m] + duration
        P[m + 1] = p + (v * duration + 0.5 * a * duration * duration)
        V[m + 1] = v + a * duration
        return m + 1
    return m


@njit(cache=True)
def _plan_into(t0: float, p0: float, v0: float, target: float, vmax: float, acc: float, dec: float,
               T: np.ndarray, P: np.ndarray, V: np.ndarray, A: np.ndarray) -> int:
    """:meth:`MotionProfile.plan` into T, P, V, A (start times, positions, velocities, accelerations); returns
    how many phases."""
    T[0], P[0], V[0] = t0, p0, v0
    m = 0
    p, v = p0, v0
    for _ in range(3):
        d = target - p
        s = math.copysign(1.0, d) if d != 0 else (-math.copysign(1.0, v) if v != 0 else 0.0)
        if s == 0.0:
            break
        u = s * v
        if u < 0:
            m = _push(m, -u / dec, s * dec, T, P, V, A)
        elif u * u / (2 * dec) > abs(d) * (1 + 1e-9) + 1e-12:
            m = _push(m, u / dec, -s * dec, T, P, V, A)  # cannot stop in time: stop beyond the target
        else:
            D = abs(d)
            if u > vmax:
                m = _push(m, (u - vmax) / dec, -s * dec, T, P, V, A)
                u = vmax
                D = abs(target - P[m])
            x = (D + u * u / (2 * acc)) / (1 / (2 * acc) + 1 / (2 * dec))
            vp = math.sqrt(0.0 if 0.0 > x else x)
            vp = vmax if vmax < vp else vp  # min(vp, vmax)
            vp = u if u > vp else vp  # max(…, u)
            m = _push(m, (vp - u) / acc, s * acc, T, P, V, A)
            cruise = abs(target - P[m]) - vp * vp / (2 * dec)
            m = _push(m, cruise / vp if vp > 0 else 0.0, 0.0, T, P, V, A)
            m = _push(m, vp / dec, -s * dec, T, P, V, A)
            break
        p, v = P[m], V[m]
    A[m] = 0.0
    P[m], V[m] = target, 0.0  # remove round-off at rest
    return m + 1


@njit(cache=True)
def plan_chain(ts0: np.ndarray, ps0: np.ndarray, vs0: np.ndarray, as0: np.ndarray, t: np.ndarray,
               target: np.ndarray, vmax: np.ndarray, acc: np.ndarray, T: np.ndarray, P: np.ndarray, V: np.ndarray,
               A: np.ndarray, count: np.ndarray) -> None:
    """Row j of T, P, V, A (``count[j]`` phases): the go-to to ``target[j]`` planned at ``t[j]`` from the state of
    row j − 1 there (row −1: the phases ts0, ps0, vs0, as0)."""
    for j in range(t.size):
        if j == 0:
            p, v = _at(ts0, ps0, vs0, as0, ts0.size, t[0])
        else:
            p, v = _at(T[j - 1], P[j - 1], V[j - 1], A[j - 1], count[j - 1], t[j])
        count[j] = _plan_into(t[j], p, v, target[j], vmax[j], acc[j], acc[j], T[j], P[j], V[j], A[j])


def chain(start: MotionProfile, t: np.ndarray, target: np.ndarray, vmax: np.ndarray,
          acc: np.ndarray) -> list[MotionProfile]:
    """The go-tos (target, vmax, acceleration = deceleration) commanded at times t (not decreasing), each planned
    from the state the previous one (the first: ``start``) gives at its time."""
    n = t.size
    T, P, V, A = (np.zeros((n, MAX_PHASES)) for _ in range(4))
    count = np.zeros(n, dtype=np.int64)
    f = np.float64
    plan_chain(np.asarray(start.t_start, f), np.asarray(start.p_start, f), np.asarray(start.v_start, f),
               np.asarray(start.acc, f), np.asarray(t, f), np.asarray(target, f), np.asarray(vmax, f),
               np.asarray(acc, f), T, P, V, A, count)
    return [MotionProfile(T[j, :c], P[j, :c], V[j, :c], A[j, :c], float(T[j, c - 1]), tg)
            for j, (c, tg) in enumerate(zip(count.tolist(), np.asarray(target, f).tolist(), strict=True))]
