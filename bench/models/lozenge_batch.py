"""Many LS-DEA parameter sets through one input history at once: candidates as the vectorised dimension.

The LS-DEA identification's inner loop, as :mod:`bench.models.membrane_batch` is the membrane's: the scheme of
:func:`bench.models.lozenge.lozenge_step` (exponential Euler on the branches' elastic log-stretches, symplectic
Euler for a hung mass), with the state stored structure-of-arrays and every loop running over the candidates
(for the branches: over (branch, candidate) pairs, branch-major), innermost, so that LLVM makes SIMD loops of
them (exp/log from :mod:`bench.models.vecmath`). Threads split the candidates into chunks of whole registers.
A per-candidate input calibration (offset, inverse gain) corrects a measured voltage.

A candidate that leaves the model's domain (aperture outside (0, 2l), Gent lock-up, non-finite) is marked dead,
reset to a harmless state and outputs NaN from that step on, as with the scalar kernel
(:func:`bench.models.integrate.run_fixed_batch`, kept as the reference).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from bench.models.batch_plan import LANES, plan
from bench.models.jit import njit
from bench.models.kernel_args import kernel_array
from bench.models.lozenge import (
    MODE_HUNG,
    Q_ALPHA_HALF,
    Q_BRANCHES,
    Q_C,
    Q_C2,
    Q_EPS,
    Q_G,
    Q_JM,
    Q_K,
    Q_L,
    Q_L1P,
    Q_L2P,
    Q_M,
    Q_MHUNG,
    Q_MODE,
    Q_MU,
    Q_T0,
    Q_XP,
)
from bench.models.vecmath import vexp, vlog


@njit(cache=True, inline="always", error_model="numpy")
def _force(x: float, v: float, V: float, l1: float, l2: float, yy: float, s1: float, s2: float, mu: float,
           Jm: float, C2: float, om: float, d1: float, l2p_yp: float, kc: float, l: float,
           c: float) -> float:
    """F = F_el + F_es + c ẋ + F_ve at aperture x (kinematics l1, l2, y given) from the branches' summed
    ∂W/∂ln λ1, ∂W/∂ln λ2 (s1, s2); as :func:`bench.models.lozenge.lozenge_force`."""
    a = 1.0 / (l1 * l1 * l2 * l2)
    I1 = l1 * l1 + l2 * l2 + a
    G = 1.0 - (I1 - 3.0) / Jm
    I2 = 1.0 / (l1 * l1) + 1.0 / (l2 * l2) + l1 * l1 * l2 * l2
    I2_1 = -2.0 / (l1 * l1 * l1) + 2.0 * l1 * l2 * l2
    I2_2 = -2.0 / (l2 * l2 * l2) + 2.0 * l2 * l1 * l1
    hm = 0.5 * mu
    P1 = hm * (2.0 * (l1 - a / l1)) / G + C2 * I2_1 / I2
    P2 = hm * (2.0 * (l2 - a / l2)) / G + C2 * I2_2 / I2
    d2 = -l2p_yp * x / yy
    F = om * (P1 * d1 + P2 * d2)
    F += -0.5 * V * V * (4.0 * kc * x * (2.0 * l * l - x * x)) + c * v
    q = x / (yy * yy)
    return F + om * (s1 / x - s2 * q)


@njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _chunk(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, cal: np.ndarray, h: float, stride: int, channel: int,
           out: np.ndarray) -> None:
    """Integrate the candidates of one chunk (rows of P, Y0; one mode; ``cal`` rows: the voltage input's offset
    and inverse gain, V = (U − offset)·inverse gain) and write the output channel (a state component, or -1: the
    force) every ``stride`` steps into ``out``."""
    c_in = P.shape[0]
    c = max(LANES, -(-c_in // LANES) * LANES)
    src = np.minimum(np.arange(c), c_in - 1)
    P = P[src]
    Y0 = Y0[src]
    off = cal[src, 0].copy()
    igain = cal[src, 1].copy()
    K = int(P[0, Q_K])
    hung = int(P[0, Q_MODE]) == MODE_HUNG
    n = U.shape[0]
    mu = P[:, Q_MU].copy()
    Jm = P[:, Q_JM].copy()
    C2 = P[:, Q_C2].copy()
    l = P[:, Q_L].copy()
    xp = P[:, Q_XP].copy()
    damp = P[:, Q_C].copy()
    Mm = P[:, Q_M].copy()
    mh = P[:, Q_MHUNG].copy()
    load = (P[:, Q_MHUNG] + 0.5 * P[:, Q_M]) * P[:, Q_G]
    half = P[:, Q_ALPHA_HALF] > 0.5
    yp = np.sqrt(4.0 * l * l - xp * xp)
    om = xp * yp * P[:, Q_T0] / (2.0 * P[:, Q_L1P] * P[:, Q_L2P])  # volume Ω
    l1_x = P[:, Q_L1P] / xp  # λ1 = λ1p x/x_p
    l2p_yp = P[:, Q_L2P] / yp  # λ2 = λ2p y/y_p
    kc = P[:, Q_EPS] * P[:, Q_L1P] * P[:, Q_L2P] / (2.0 * P[:, Q_T0] * xp * yp)
    nq = K * c
    bmu = np.empty(nq)  # per (branch, lane) pair, branch-major
    btau = np.empty(nq)
    bk = np.empty(nq)  # 1/(6τ)
    dec = np.empty(nq)  # e^{−h/τ}
    A = np.empty(nq)  # a_k = ln ξk1
    B = np.empty(nq)  # b_k = ln ξk2
    for i in range(K):
        for j in range(c):
            m = i * c + j
            bmu[m] = P[j, Q_BRANCHES + i]
            btau[m] = P[j, Q_BRANCHES + K + i]
            bk[m] = 1.0 / (6.0 * btau[m])
            dec[m] = np.exp(-h / btau[m])
            A[m] = Y0[j, 2 + i]
            B[m] = Y0[j, 2 + K + i]
    X = Y0[:, 0].copy()
    Vx = Y0[:, 1].copy()
    alive = np.ones(c)
    ok = np.ones(c)
    l1 = np.empty(c)
    l2 = np.empty(c)
    yy = np.empty(c)
    ll1 = np.empty(c)
    ll2 = np.empty(c)
    s1 = np.empty(c)
    s2 = np.empty(c)
    lane_ll1 = np.empty(nq)
    lane_ll2 = np.empty(nq)
    W1 = np.empty(nq)
    W2 = np.empty(nq)
    want_force = channel < 0
    for k in range(-1, n):  # k = −1: the initial output at the initial state (inputs U[0])
        first = k < 0
        kk = 0 if first else k
        V = U[kk, 0]
        for j in range(c):  # kinematics at the step's aperture
            x = X[j] if hung or first else U[kk, 1]
            X[j] = x
            if not (hung or first):
                Vx[j] = U[kk, 2]
            yj = np.sqrt(4.0 * l[j] * l[j] - x * x)
            a1 = l1_x[j] * x
            a2 = l2p_yp[j] * yj
            in_range = x > 0.0 and x < 2.0 * l[j]
            a1 = a1 if in_range else 1.0
            a2 = a2 if in_range else 1.0
            yj = yj if in_range else 1.0
            l1[j] = a1
            l2[j] = a2
            yy[j] = yj
            ll1[j] = vlog(a1)
            ll2[j] = vlog(a2)
            G = 1.0 - (a1 * a1 + a2 * a2 + 1.0 / (a1 * a1 * a2 * a2) - 3.0) / Jm[j]
            ok[j] = 1.0 if in_range and G > 0.0 else 0.0
        for i in range(K):
            for j in range(c):
                lane_ll1[i * c + j] = ll1[j]
                lane_ll2[i * c + j] = ll2[j]
        if not first:
            for m in range(nq):  # branches: exponential Euler on the elastic log-stretches
                p1 = lane_ll1[m] - A[m]
                p2 = lane_ll2[m] - B[m]
                e1 = vexp(2.0 * p1)
                e2 = vexp(2.0 * p2)
                e3 = 1.0 / (e1 * e2)
                fa = bk[m] * (2.0 * e1 - e2 - e3)
                fb = bk[m] * (2.0 * e2 - e1 - e3)
                d = dec[m]
                A[m] = lane_ll1[m] - (p1 * d - (1.0 - d) * (btau[m] * fa - p1))
                B[m] = lane_ll2[m] - (p2 * d - (1.0 - d) * (btau[m] * fb - p2))
        pos = (k + 1) % stride
        write = pos == 0
        if hung or (want_force and write):
            for m in range(nq):  # the branches' ∂W/∂ln λ at the (new) state
                e1 = vexp(2.0 * (lane_ll1[m] - A[m]))
                e2 = vexp(2.0 * (lane_ll2[m] - B[m]))
                e3 = 1.0 / (e1 * e2)
                W1[m] = bmu[m] * (e1 - e3)
                W2[m] = bmu[m] * (e2 - e3)
            for j in range(c):
                s1[j] = 0.0
                s2[j] = 0.0
            for i in range(K):
                for j in range(c):
                    s1[j] += W1[i * c + j]
                    s2[j] += W2[i * c + j]
        if hung and not first:
            for j in range(c):  # hung mass: symplectic Euler
                x = X[j]
                v = Vx[j]
                Vj = (V - off[j]) * igain[j]  # the output the monitor's reading stands for
                F = _force(x, v, Vj, l1[j], l2[j], yy[j], s1[j], s2[j], mu[j], Jm[j], C2[j], om[j], l1_x[j],
                           l2p_yp[j], kc[j], l[j], damp[j])
                D = 4.0 * l[j] * l[j] - x * x
                alpha = 0.5 if half[j] else 9.0 / 32.0 + (5.0 * l[j] * l[j] / 24.0 + x * x / 32.0) / D
                dalpha = 0.0 if half[j] else 2.0 / 3.0 * l[j] * l[j] * x / (D * D)
                me = mh[j] + alpha * Mm[j]
                R = load[j] - F - 0.5 * dalpha * Mm[j] * v * v
                v = v + h * R / me
                x = x + h * v
                fin = x - x == 0.0 and v - v == 0.0  # finite
                ok[j] = ok[j] if fin else 0.0
                X[j] = x
                Vx[j] = v
        if not first:
            for j in range(c):  # dead lanes: NaN from here on, reset to a harmless state
                good = alive[j] > 0.0 and ok[j] > 0.0
                alive[j] = 1.0 if good else 0.0
                X[j] = X[j] if good else xp[j]
                Vx[j] = Vx[j] if good else 0.0
            for i in range(K):
                for j in range(c):
                    m = i * c + j
                    A[m] = A[m] if alive[j] > 0.0 else lane_ll1[m]
                    B[m] = B[m] if alive[j] > 0.0 else lane_ll2[m]
        if write:
            col = (k + 1) // stride
            for j in range(c_in):
                if want_force:
                    Vj = (V - off[j]) * igain[j]
                    val = _force(X[j], Vx[j], Vj, l1[j], l2[j], yy[j], s1[j], s2[j], mu[j], Jm[j], C2[j], om[j],
                                 l1_x[j], l2p_yp[j], kc[j], l[j], damp[j])
                else:
                    val = X[j] if channel == 0 else Vx[j]
                out[j, col] = val if alive[j] > 0.0 else np.nan


@njit(cache=True, parallel=True)
def _batch(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, cal: np.ndarray, h: float, stride: int, channel: int,
           tasks: np.ndarray, out: np.ndarray) -> None:
    """Run the tasks (:func:`bench.models.batch_plan.plan`) in parallel; Y0 is (candidates, state), cal
    (candidates, 2)."""
    for s in prange(tasks.shape[0]):
        _, u0, u1, c0, c1, a, b = tasks[s]
        _chunk(P[a:b], Y0[a:b], U[u0:u1], cal[a:b], h, stride, channel, out[a:b, c0:c1])


def lozenge_batch(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, h: float, channel: int, stride: int,
                  cal: np.ndarray | None = None) -> np.ndarray:
    """Same contract as ``run_fixed_batch(MODEL_LOZENGE, Y0, U, h, P, channel, stride)`` (channel 0 or 1: a
    state component, OBSERVE_FORCE = −1: the force), for parameter sets of one mode (that of P's first row).
    ``cal``: per set (len(P), 2) the voltage input's calibration, offset [V] and inverse gain — the specimen sees
    (U − offset)·inverse gain (None: as recorded)."""
    P, Y0, U = kernel_array(P), kernel_array(Y0), kernel_array(U)  # one form: one compiled variant (kernel_args)
    if channel not in (-1, 0, 1):
        raise ValueError(f"channel must be -1 (force), 0 or 1, got {channel}")
    if np.any(P[:, Q_MODE] != P[0, Q_MODE]) or np.any(P[:, Q_K] != P[0, Q_K]):
        raise ValueError("lozenge_batch: every parameter set needs the same mode and number of branches")
    if channel == -1 and int(P[0, Q_MODE]) == MODE_HUNG:
        raise ValueError("lozenge_batch: the force is an output of the imposed mode only (hung: channel 0 or 1)")
    m = P.shape[0]
    cal = kernel_array(np.array([0.0, 1.0]) if cal is None else cal, (m, 2))
    tasks, columns = plan(m, [U.shape[0]], stride, numba.get_num_threads())
    out = np.full((m, columns), np.nan)
    _batch(P, Y0, U, cal, float(h), int(stride), int(channel), tasks, out)
    return out
