"""Many membrane parameter sets through one input history at once: candidates as the vectorised dimension.

The identification's inner loop. Same scheme as :func:`bench.models.membrane.membrane_step` (exponential
update of each Maxwell unit's elastic log-stretch, symplectic Euler for the membrane; physics.md §1.5), but
the state is stored structure-of-arrays (one array per state component, one entry per candidate) and each
step runs its loops *over the candidates*, innermost, with no calls that are not inlined: LLVM turns them
into SIMD loops (exp/log from :mod:`bench.models.vecmath`). Threads split the candidates into chunks of whole
registers (the GIL is released: concurrent searches in threads run side by side). The units' stresses are
summed as one fraction and the membrane's update puts springs, inertia and mass over one denominator: one
division per candidate per step besides one per unit for its relaxation rate (a SIMD division costs as much as
ten multiplications). A per-candidate input calibration (offset, inverse gain) corrects a measured voltage.

A candidate whose state leaves the model's domain (Gent lock-up, λ ≤ 0, non-finite) is marked dead, reset to
a harmless state so that it costs nothing further, and outputs NaN from that step on — as the scalar kernel
(:func:`bench.models.integrate.run_fixed_batch`, kept as the reference) does.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from bench.models.batch_plan import LANES, plan
from bench.models.jit import njit
from bench.models.kernel_args import kernel_array
from bench.models.membrane import (
    P_A,
    P_B,
    P_BRANCHES,
    P_C,
    P_EPS,
    P_J0,
    P_KAPPA,
    P_KF,
    P_L,
    P_L3,
    P_LPRE,
    P_MU0,
    P_RHO,
    P_SPRE,
)
from bench.models.vecmath import vexp, vlog


@njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _chunk(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, cal: np.ndarray, h: float, stride: int, window: int,
           out: np.ndarray) -> None:
    """Integrate the candidates of one chunk (rows of P, Y0; ``cal`` rows: the input's offset and inverse gain,
    Φ = (U − offset)·inverse gain) and write λ samples into ``out``."""
    c_in = P.shape[0]
    # lanes padded (copies of the last set) to whole registers: a scalar remainder loop costs as much as a register
    c = max(LANES, -(-c_in // LANES) * LANES)
    src = np.minimum(np.arange(c), c_in - 1)
    P = P[src]
    Y0 = Y0[src]
    off = cal[src, 0].copy()
    igain = cal[src, 1].copy()
    n_units = (P.shape[1] - P_BRANCHES) // 3
    n = U.shape[0]
    # parameters, structure of arrays
    mu0 = P[:, P_MU0].copy()
    iJ0 = 1.0 / P[:, P_J0]
    spre = P[:, P_SPRE].copy()
    kf = P[:, P_KF].copy()
    lpre = P[:, P_LPRE].copy()
    a = P[:, P_A].copy()
    b = P[:, P_B].copy()
    cc = P[:, P_C].copy()
    ka = P[:, P_KAPPA] * P[:, P_A]
    eps_l3 = P[:, P_EPS] / (P[:, P_L3] * P[:, P_L3])
    m_const = P[:, P_RHO] * P[:, P_L] * P[:, P_L] / 3.0
    rl3 = P[:, P_RHO] * P[:, P_L3] * P[:, P_L3]
    # per (unit, lane) pair, flattened unit-major (index i·c + j): the unit loop then runs over n_units·c
    # independent elements, enough work in flight even for a few candidates (the polish's Jacobians)
    nq = n_units * c
    mu = np.empty(nq)
    iJ = np.empty(nq)
    q = np.empty(nq)  # μ/(6η)
    r0 = np.empty(nq)  # μ/η
    for i in range(n_units):
        for j in range(c):
            mu[i * c + j] = P[j, P_BRANCHES + i]
            iJ[i * c + j] = 1.0 / P[j, P_BRANCHES + n_units + i]
            r0[i * c + j] = P[j, P_BRANCHES + i] / P[j, P_BRANCHES + 2 * n_units + i]
            q[i * c + j] = r0[i * c + j] / 6.0
    # state: λ, λ̇ and per unit its elastic stretch e = λ/ξ and u = ln e (kept current as λ moves, so a
    # step needs one log per candidate instead of one per unit)
    lam = Y0[:, 0].copy()
    v = Y0[:, 1].copy()
    el = np.empty(nq)
    ul = np.empty(nq)
    for i in range(n_units):
        for j in range(c):
            el[i * c + j] = lam[j] / Y0[j, 2 + i]
            ul[i * c + j] = vlog(el[i * c + j])
    tnum = np.empty(nq)  # per pair: the unit's stress times λ as a fraction μ(e⁶ − 1) / (G e⁴)
    tden = np.empty(nq)
    lane_ratio = np.empty(nq)  # per pair: its lane's λ ratio and log ratio
    lane_dlog = np.empty(nq)
    alive = np.ones(c)  # 1.0 alive, 0.0 dead (a float mask keeps the loops branch-free)
    num = np.empty(c)  # Σ over units of the stress fractions, as one fraction num/den
    den = np.empty(c)
    okd = np.empty(c)  # 1.0 while every unit's G e⁴ > 0
    ratio = np.empty(c)  # λ_{k+1}/λ_k
    dlog = np.empty(c)  # ln(λ_{k+1}/λ_k)
    acc = np.zeros(c)
    for j in range(c_in):
        out[j, 0] = lam[j]
    for k in range(n):
        phi = U[k, 0]
        iT = 1.0 / U[k, 1]
        for m in range(nq):  # Maxwell units: exponential update of u = ln(λ/ξ), then their stress
            # Gent terms times e⁴ (no reciprocal of e needed): (e² − e⁻⁴)/G = (e⁶ − 1)/(G e⁴)
            u = ul[m]
            e2 = el[m] * el[m]
            e4 = e2 * e2
            e6 = e4 * e2
            Ge4 = e4 - (2.0 * e6 + 1.0 - 3.0 * e4) * iJ[m]
            rate = q[m] * (e6 - 1.0) / (Ge4 * u) if abs(u) >= 1e-9 else r0[m]
            u = u * vexp(-h * rate)
            en = vexp(u)
            ul[m] = u
            el[m] = en
            e2 = en * en
            e4 = e2 * e2
            e6 = e4 * e2
            # stress times λ: μ(e⁶ − 1)/(G e⁴), kept as a fraction (one division per lane below)
            tnum[m] = mu[m] * (e6 - 1.0)
            tden[m] = e4 - (2.0 * e6 + 1.0 - 3.0 * e4) * iJ[m]
        for j in range(c):
            num[j] = 0.0
            den[j] = 1.0
            okd[j] = 1.0
        for i in range(n_units):  # Σ n_i/d_i as one fraction; a locked-up unit (d ≤ 0) marks its lane dead
            for j in range(c):
                d = tden[i * c + j]
                num[j] = num[j] * d + tnum[i * c + j] * den[j]
                den[j] = den[j] * d
                okd[j] = okd[j] if d > 0.0 else 0.0
        pos = (k + 1) % stride
        write = pos == 0
        add = window > 0 and (write or pos > stride - window)
        for j in range(c):  # springs, inertia, electrostatics, dead load, membrane update: one division
            lj = lam[j]
            vj = v[j]
            l2 = lj * lj
            l4 = l2 * l2
            l6 = l4 * l2
            g0 = l4 - (2.0 * l6 + 1.0 - 3.0 * l4) * iJ0[j]  # G0 λ⁴
            Ml6 = m_const[j] * l6 + 2.0 / 3.0 * rl3[j]  # M λ⁶
            er = a[j] * l2 + b[j] * iT + cc[j]
            ph = (phi - off[j]) * igain[j]
            s_es = eps_l3[j] * (ph * ph) * (er * l2 * lj + ka[j] * l4 * lj)
            R = spre[j] - kf[j] * (lj - lpre[j]) + s_es
            D = den[j]
            # f/M with every fraction over one denominator (numerator and denominator times λ⁷·G0λ⁴·D):
            # [(2ρL3²λ̇² + Rλ⁷) G0λ⁴ D − λ⁶ (μ0 (λ⁶ − 1) D + num G0λ⁴)] / (Mλ⁶ · G0λ⁴ D · λ)
            gD = g0 * D
            top = (2.0 * rl3[j] * vj * vj + R * l6 * lj) * gD - l6 * (mu0[j] * (l6 - 1.0) * D + num[j] * g0)
            MgD = Ml6 * gD
            inv = 1.0 / (MgD * lj)
            vn = vj + h * (top * inv)
            ln = lj + h * vn
            good = g0 > 0.0 and okd[j] > 0.0 and ln > 0.0 and ln < 1e300 and alive[j] > 0.0
            alive[j] = 1.0 if good else 0.0
            lam[j] = ln if good else lpre[j]
            v[j] = vn if good else 0.0
            rj = ln * (inv * MgD)  # ln/λ
            ratio[j] = rj if good else 1.0
            dlog[j] = vlog(rj) if good else 0.0
        for i in range(n_units):  # the units' elastic stretch follows λ: e ← e·λ_{k+1}/λ_k
            for j in range(c):
                lane_ratio[i * c + j] = ratio[j] if alive[j] > 0.0 else 0.0  # 0: reset a dead lane's units
                lane_dlog[i * c + j] = dlog[j]
        for m in range(nq):
            g = lane_ratio[m] > 0.0
            el[m] = el[m] * lane_ratio[m] if g else 1.0
            ul[m] = ul[m] + lane_dlog[m] if g else 0.0
        if add:
            for j in range(c):
                acc[j] += lam[j]
        if write:
            col = (k + 1) // stride
            if window > 0:
                for j in range(c_in):
                    out[j, col] = acc[j] / window if alive[j] > 0.0 else np.nan
                for j in range(c):
                    acc[j] = 0.0
            else:
                for j in range(c_in):
                    out[j, col] = lam[j] if alive[j] > 0.0 else np.nan


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _batch(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, cal: np.ndarray, h: float, stride: int, window: int,
           tasks: np.ndarray, out: np.ndarray) -> None:
    """Run the tasks (:func:`bench.models.batch_plan.plan`) in parallel; Y0 is (records, candidates, state), cal
    (records, candidates, 2)."""
    for s in prange(tasks.shape[0]):
        r, u0, u1, c0, c1, a, b = tasks[s]
        _chunk(P[a:b], Y0[r, a:b], U[u0:u1], cal[r, a:b], h, stride, window, out[a:b, c0:c1])


def membrane_batch_records(P: np.ndarray, Y0: np.ndarray, Us: list[np.ndarray], h: float, stride: int,
                           window: int = 0, cal: np.ndarray | None = None) -> np.ndarray:
    """λ of many parameter sets (rows of packed P) over several records at once, in parallel over records and
    candidate chunks. ``Y0`` is (records, len(P), state) or (records, state) (the same start for every set);
    ``Us[r]`` the inputs of record r. ``cal``: per record and set (records, len(P), 2) the voltage input's
    calibration, offset [V] and inverse gain — the specimen sees (U − offset)·inverse gain (None: as recorded).
    Returns the records' outputs side by side: (len(P), Σ(len(U_r)//stride + 1)).
    """
    P = kernel_array(P)  # every argument in one form: one compiled variant of _batch (kernel_args)
    m = P.shape[0]
    Y0 = np.asarray(Y0, dtype=np.float64)
    if Y0.ndim == 2:
        Y0 = Y0[:, None, :]
    Y0 = kernel_array(Y0, (Y0.shape[0], m, Y0.shape[2]))
    cal = kernel_array(np.array([0.0, 1.0]) if cal is None else cal, (len(Us), m, 2))
    U = kernel_array(Us[0] if len(Us) == 1 else np.concatenate(Us))  # one record: no copy
    tasks, columns = plan(m, [u.shape[0] for u in Us], stride, numba.get_num_threads())
    out = np.full((m, columns), np.nan)
    _batch(P, Y0, U, cal, float(h), int(stride), int(window), tasks, out)
    return out


def membrane_batch(P: np.ndarray, Y0: np.ndarray, U: np.ndarray, h: float, stride: int,
                   window: int = 0) -> np.ndarray:
    """λ of many membrane parameter sets (rows of packed P, initial states rows of Y0) under inputs U.

    Same contract as ``run_fixed_batch(MODEL_MEMBRANE, Y0, U, h, P, 0, stride, window)``: U[k] = (Φ, T) at the
    end of step k; returns (len(P), len(U)//stride + 1), NaN from the first sample after a set failed;
    ``window`` > 0 averages each output over the last ``window`` step ends.
    """
    return membrane_batch_records(P, np.asarray(Y0, dtype=np.float64)[None], [U], h, stride, window)
