"""Compiled stiff integrator for offline membrane runs: Rodas3 (Rosenbrock, order 3, L-stable) with error control.

The whole loop — Jacobian, LU of (I/(hγ) − J), four stages, the embedded order-2 error estimate, step-size
control and cubic Hermite dense output onto the requested sample times — runs in one numba call, so there is
no per-step Python as in scipy's ``solve_ivp``. Coefficients: Sandu et al., Atmos. Environ. 31 (1997) 3459
(KPP's Rodas3), in the formulation

    (I/(hγ) − J) k_i = f(t + α_i h, y + Σ_j a_ij k_j) + Σ_j (c_ij/h) k_j + γ_i h ∂f/∂t
    y_{n+1} = y_n + Σ m_i k_i,  error = Σ e_i k_i.

The voltage is a piecewise-linear function of time given on a uniform grid (the output grid or finer); the
temperature is constant. Tolerances are per component as for Radau (physics.md §1.5: λ̇ needs a loose one).
"""

from __future__ import annotations

import math

import numpy as np

from bench.models.jit import njit
from bench.models.membrane import es_stress, inertia, membrane_jac, membrane_rhs

GAMMA = 0.5
A31, A32, A41, A42, A43 = 2.0, 0.0, 2.0, 0.0, 1.0  # a21 = 0: stage 2 reuses f(t, y)
C21, C31, C32, C41, C42, C43 = 4.0, 1.0, -1.0, 1.0, -1.0, -8.0 / 3.0
M1, M2, M3, M4 = 2.0, 0.0, 1.0, 1.0
E1, E2, E3, E4 = 0.0, 0.0, 0.0, 1.0
ALPHA = (0.0, 0.0, 1.0, 1.0)
GAMMAS = (0.5, 1.5, 0.0, 0.0)

STATUS_DONE, STATUS_STOPPED, STATUS_FAILED = 0, 1, 2


@njit(cache=True, inline="always")
def _phi(t: float, t0: float, dt: float, phi: np.ndarray) -> tuple[float, float]:
    """Voltage and its slope at t from samples phi[k] at t0 + k·dt (linear between them, held outside)."""
    s = (t - t0) / dt
    if s <= 0.0:
        return phi[0], 0.0
    k = int(s)
    if k >= phi.size - 1:
        return phi[phi.size - 1], 0.0
    slope = (phi[k + 1] - phi[k]) / dt
    return phi[k] + (s - k) * (phi[k + 1] - phi[k]), slope


@njit(cache=True)
def _lu(A: np.ndarray, piv: np.ndarray) -> None:
    """In-place LU with partial pivoting of a small dense matrix."""
    n = A.shape[0]
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        piv[k] = p
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
        inv = 1.0 / A[k, k]
        for i in range(k + 1, n):
            A[i, k] *= inv
            f = A[i, k]
            for j in range(k + 1, n):
                A[i, j] -= f * A[k, j]


@njit(cache=True)
def _solve(LU: np.ndarray, piv: np.ndarray, b: np.ndarray) -> None:
    """Solve in place with the factors of :func:`_lu`."""
    n = LU.shape[0]
    for k in range(n):
        p = piv[k]
        if p != k:
            b[k], b[p] = b[p], b[k]
    for i in range(n):
        for j in range(i):
            b[i] -= LU[i, j] * b[j]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, n):
            b[i] -= LU[i, j] * b[j]
        b[i] /= LU[i, i]


@njit(cache=True)
def _f(t: float, y: np.ndarray, T: float, p: np.ndarray, t0: float, dt: float, phi: np.ndarray,
       out: np.ndarray) -> None:
    v, _ = _phi(t, t0, dt, phi)
    membrane_rhs(y, v, T, p, out)


@njit(cache=True)
def _ft(t: float, y: np.ndarray, T: float, p: np.ndarray, t0: float, dt: float, phi: np.ndarray,
        out: np.ndarray) -> None:
    """∂f/∂t: only λ̈ depends on t, through s_es ∝ Φ²."""
    v, slope = _phi(t, t0, dt, phi)
    out[:] = 0.0
    if v != 0.0 and slope != 0.0:
        s, _ = es_stress(y[0], v, T, p)
        M, _ = inertia(y[0], p)
        out[1] = 2.0 * s / v * slope / M


@njit(cache=True)
def rodas3_membrane(y0: np.ndarray, t_out: np.ndarray, T: float, p: np.ndarray, t0: float, dt: float,
                    phi: np.ndarray, rtol: float, atol: np.ndarray, lam_stop: float,
                    Y: np.ndarray) -> tuple[int, int, int, float]:
    """Integrate the membrane from y0 at t_out[0] over t_out, writing states at t_out into Y (NaN after a stop).

    Returns (status, accepted steps, rejected steps, stop time): status 0 done, 1 stopped (λ passed
    ``lam_stop``), 2 failed (step size underflow or non-finite state).
    """
    n = y0.size
    y = y0.copy()
    ynew = np.empty(n)
    f0 = np.empty(n)
    f1 = np.empty(n)
    ft = np.empty(n)
    tmp = np.empty(n)
    ytmp = np.empty(n)
    k1, k2, k3, k4 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    J = np.empty((n, n))
    LU = np.empty((n, n))
    piv = np.empty(n, dtype=np.int64)
    t = t_out[0]
    t_end = t_out[-1]
    for i in range(n):  # an element loop: no array-to-array slice assignment to compile (integrate.run_fixed)
        Y[0, i] = y[i]
    iout = 1
    _f(t, y, T, p, t0, dt, phi, f0)
    h = min(1e-5, t_end - t)
    accepted = rejected = 0
    h_min = 1e-14 * max(abs(t_end), 1.0)
    while t < t_end:
        if t + h > t_end:
            h = t_end - t
        v, _ = _phi(t, t0, dt, phi)
        membrane_jac(y, v, T, p, J)
        _ft(t, y, T, p, t0, dt, phi, ft)
        while True:
            inv = 1.0 / (h * GAMMA)
            for i in range(n):
                for j in range(n):
                    LU[i, j] = -J[i, j]
                LU[i, i] += inv
            _lu(LU, piv)
            # stage 1
            for i in range(n):
                k1[i] = f0[i] + GAMMAS[0] * h * ft[i]
            _solve(LU, piv, k1)
            # stage 2 (a21 = 0, α2 = 0: the same f as stage 1)
            for i in range(n):
                k2[i] = f0[i] + C21 / h * k1[i] + GAMMAS[1] * h * ft[i]
            _solve(LU, piv, k2)
            # stage 3
            for i in range(n):
                ytmp[i] = y[i] + A31 * k1[i] + A32 * k2[i]
            _f(t + ALPHA[2] * h, ytmp, T, p, t0, dt, phi, tmp)
            for i in range(n):
                k3[i] = tmp[i] + (C31 * k1[i] + C32 * k2[i]) / h + GAMMAS[2] * h * ft[i]
            _solve(LU, piv, k3)
            # stage 4
            for i in range(n):
                ytmp[i] = y[i] + A41 * k1[i] + A42 * k2[i] + A43 * k3[i]
            _f(t + ALPHA[3] * h, ytmp, T, p, t0, dt, phi, tmp)
            for i in range(n):
                k4[i] = tmp[i] + (C41 * k1[i] + C42 * k2[i] + C43 * k3[i]) / h + GAMMAS[3] * h * ft[i]
            _solve(LU, piv, k4)
            err = 0.0
            finite = True
            for i in range(n):
                ynew[i] = y[i] + M1 * k1[i] + M2 * k2[i] + M3 * k3[i] + M4 * k4[i]
                e = E1 * k1[i] + E2 * k2[i] + E3 * k3[i] + E4 * k4[i]
                sc = atol[i] + rtol * max(abs(y[i]), abs(ynew[i]))
                err += (e / sc) ** 2
                finite = finite and math.isfinite(ynew[i])
            err = math.sqrt(err / n) if finite else 1e10
            fac = 0.9 * err ** (-1.0 / 3.0) if err > 0.0 else 6.0
            fac = min(6.0, max(0.2, fac))
            if err <= 1.0:
                break
            rejected += 1
            h *= fac
            if h < h_min:
                return STATUS_FAILED, accepted, rejected, t
        t_new = t + h
        _f(t_new, ynew, T, p, t0, dt, phi, f1)
        # dense output: cubic Hermite on [t, t_new] from y, f0, ynew, f1
        while iout < t_out.size and t_out[iout] <= t_new:
            s = (t_out[iout] - t) / h
            h00 = (1.0 + 2.0 * s) * (1.0 - s) * (1.0 - s)
            h10 = s * (1.0 - s) * (1.0 - s)
            h01 = s * s * (3.0 - 2.0 * s)
            h11 = s * s * (s - 1.0)
            for i in range(n):
                Y[iout, i] = h00 * y[i] + h10 * h * f0[i] + h01 * ynew[i] + h11 * h * f1[i]
            iout += 1
        accepted += 1
        if ynew[0] > lam_stop:
            for k in range(iout, t_out.size):
                for i in range(n):
                    Y[k, i] = np.nan
            # stop time by the same Hermite cubic: bisect λ(t) = lam_stop
            a, b = 0.0, 1.0
            for _ in range(60):
                m = 0.5 * (a + b)
                lam = ((1.0 + 2.0 * m) * (1.0 - m) ** 2 * y[0] + m * (1.0 - m) ** 2 * h * f0[0]
                       + m * m * (3.0 - 2.0 * m) * ynew[0] + m * m * (m - 1.0) * h * f1[0])
                if lam > lam_stop:
                    b = m
                else:
                    a = m
            return STATUS_STOPPED, accepted, rejected, t + 0.5 * (a + b) * h
        t = t_new
        for i in range(n):
            y[i] = ynew[i]
            f0[i] = f1[i]
        h *= fac
    return STATUS_DONE, accepted, rejected, t
