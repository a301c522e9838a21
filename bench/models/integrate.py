"""Time integration shared by both models: offline (stiff, adaptive), streaming (fixed step), batched.

One model definition (the numba kernels of :mod:`membrane` and :mod:`lozenge`) feeds three integrators:

* :func:`solve_offline` — whole input known in advance: ``solve_ivp`` Radau with the analytic Jacobian and
  per-component absolute tolerances (physics.md §1.5 item 1), dense output at any rate;
* :class:`FixedStepper` / :func:`run_fixed` — the fixed-step semi-implicit scheme, one call per sample
  (the simulated rig) or a compiled loop over a block of samples;
* :func:`run_fixed_batch` — many parameter sets at once on all cores (identification).

Input convention of the fixed-step path: ``U[k]`` holds the inputs at t_{k+1}; step k takes the state
from t_k to t_{k+1} (the voltage is a zero-order hold updated at the start of the step).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import prange

from bench.models.jit import njit
from bench.models.lozenge import lozenge_force, lozenge_step
from bench.models.membrane import membrane_step

MODEL_MEMBRANE = 0
MODEL_LOZENGE = 1
N_INPUTS = {MODEL_MEMBRANE: 2, MODEL_LOZENGE: 3}  # (Φ, T) and (V, x_in, ẋ_in)


@njit(cache=True)
def step_model(model: int, y: np.ndarray, u: np.ndarray, h: float, p: np.ndarray) -> bool:
    """One fixed step of the model with id ``model`` (MODEL_*) and inputs ``u``."""
    if model == MODEL_MEMBRANE:
        return membrane_step(y, u[0], u[1], h, p)
    return lozenge_step(y, u[0], u[1], u[2], h, p)


OBSERVE_FORCE = -1  # run_fixed_batch channel: the LS-DEA force instead of a state component


@njit(cache=True)
def observe_model(model: int, y: np.ndarray, u: np.ndarray, p: np.ndarray, channel: int, grad: np.ndarray) -> float:
    """State component ``channel`` of y, or (OBSERVE_FORCE, LS-DEA) the force F(y, x, ẋ, V)."""
    if channel >= 0:
        return float(y[channel])
    return lozenge_force(y, y[0], y[1], u[0], p, grad)


@njit(cache=True, nogil=True)
def run_fixed(model: int, y0: np.ndarray, U: np.ndarray, h: float, p: np.ndarray) -> tuple[np.ndarray, int]:
    """Integrate len(U) fixed steps from y0. Returns (Y with len(U)+1 rows, number of valid rows).

    Rows after the first step that left the model's domain are NaN.
    """
    n = U.shape[0]
    Y = np.full((n + 1, y0.size), np.nan)
    y = y0.copy()
    for i in range(y.size):  # element loops, not Y[0] = y: an array-to-array slice assignment makes numba compile
        Y[0, i] = y[i]  # its shape check and error formatting into every kernel that has one (seconds a cold process)
    for k in range(n):
        ok = step_model(model, y, U[k], h, p)
        for i in range(y.size):
            Y[k + 1, i] = y[i]
        if not ok:
            return Y, k + 2
    return Y, n + 1


@njit(cache=True, parallel=True)
def run_fixed_batch_calibrated(model: int, Y0: np.ndarray, U: np.ndarray, h: float, P: np.ndarray, cal: np.ndarray,
                               channel: int, stride: int, window: int = 0) -> np.ndarray:
    """:func:`run_fixed_batch` where set j sees input 0 as (U[:, 0] − cal[j, 0]) · cal[j, 1] (a monitor's offset
    and inverse gain, fitted per set), in parallel over the sets; each step's input is made per set."""
    m = P.shape[0]
    n = U.shape[0]
    n_out = n // stride + 1
    out = np.full((m, n_out), np.nan)
    for j in prange(m):
        y = Y0[j].copy()
        grad = np.empty(y.size)
        u = U[0].copy()
        u[0] = (U[0, 0] - cal[j, 0]) * cal[j, 1]
        out[j, 0] = observe_model(model, y, u, P[j], channel, grad)
        acc = 0.0
        for k in range(n):
            for i in range(1, u.size):  # (an element loop: see run_fixed)
                u[i] = U[k, i]
            u[0] = (U[k, 0] - cal[j, 0]) * cal[j, 1]
            if not step_model(model, y, u, h, P[j]):
                break
            pos = (k + 1) % stride
            if window > 0 and (pos == 0 or pos > stride - window):
                acc += y[channel] if channel >= 0 else observe_model(model, y, u, P[j], channel, grad)
            if pos == 0:
                if window > 0:
                    out[j, (k + 1) // stride] = acc / window
                    acc = 0.0
                else:
                    out[j, (k + 1) // stride] = observe_model(model, y, u, P[j], channel, grad)
    return out


@njit(cache=True)
def run_fixed_batch(model: int, Y0: np.ndarray, U: np.ndarray, h: float, P: np.ndarray, channel: int,
                    stride: int, window: int = 0) -> np.ndarray:
    """Integrate one input history for many parameter sets (rows of P, initial states rows of Y0) in parallel.

    Returns state component ``channel`` (or OBSERVE_FORCE) every ``stride`` steps, shape
    (len(P), len(U)//stride + 1); NaN from the first sample after a set leaves the model's domain.
    ``window`` > 0: each output (after the first) is the mean over the last ``window`` step ends (≤ stride),
    as a window average of a densely sampled record is. (:func:`run_fixed_batch_calibrated` with every set's
    input as recorded: x − 0 and x · 1 are x.)
    """
    cal = np.zeros((P.shape[0], 2))
    cal[:, 1] = 1.0
    return run_fixed_batch_calibrated(model, Y0, U, h, P, cal, channel, stride, window)


class FixedStepper:
    """Streaming integrator: advance one model instance sample by sample from the current inputs.

    ``step(*inputs)`` costs one compiled call; ``advance(U)`` runs a block of samples in compiled code.
    """

    def __init__(self, model: int, p: np.ndarray, y0: np.ndarray, h: float) -> None:
        if not h > 0:
            raise ValueError(f"step h must be > 0 s, got {h}")
        self.model = model
        self.p = np.ascontiguousarray(p, dtype=np.float64)
        self.y = np.array(y0, dtype=np.float64)
        self.h = float(h)
        self.t = 0.0
        self.ok = True
        self._u = np.zeros(N_INPUTS[model])

    def step(self, u0: float, u1: float, u2: float = 0.0) -> bool:
        """Advance by h with inputs (u0, u1[, u2]) held over the step; False once the model failed."""
        u = self._u
        u[0] = u0
        u[1] = u1
        if u.size > 2:
            u[2] = u2
        self.ok = step_model(self.model, self.y, u, self.h, self.p) and self.ok
        self.t += self.h
        return self.ok

    def advance(self, U: np.ndarray) -> np.ndarray:
        """Advance len(U) steps (U[k] = inputs at the end of step k); returns the states after each step."""
        Y, valid = run_fixed(self.model, self.y, np.ascontiguousarray(U, dtype=np.float64), self.h, self.p)
        self.y = Y[-1].copy() if valid == len(Y) else Y[valid - 1].copy()
        self.ok = self.ok and valid == len(Y)
        self.t += self.h * len(U)
        return Y[1:]


@dataclass
class OfflineResult:
    """Output of :func:`solve_offline`: sample times [s], states (n×ny), solver status and message."""

    t: np.ndarray
    Y: np.ndarray
    success: bool
    message: str
    nfev: int
    njev: int
    t_stop: float | None = None


def solve_offline(fun: Callable[[float, np.ndarray], np.ndarray],
                  jac: Callable[[float, np.ndarray], np.ndarray],
                  y0: np.ndarray, t_eval: np.ndarray, *, atol: np.ndarray, rtol: float = 1e-7,
                  method: str = "Radau", stop: Callable[[float, np.ndarray], float] | None = None,
                  max_step: float = np.inf) -> OfflineResult:
    """Integrate dy/dt = fun(t, y) over ``t_eval`` with a stiff implicit solver and analytic Jacobian.

    ``stop(t, y)`` is a terminal event (the run ends where it crosses zero, e.g. runaway stretch);
    samples after the stop are NaN so the output always has len(t_eval) rows.
    """
    from scipy.integrate import solve_ivp  # here: only the offline path needs scipy (a run's start does not)

    events = None
    if stop is not None:
        def event(t: float, y: np.ndarray) -> float:
            return stop(t, y)
        event.terminal = True  # type: ignore[attr-defined]  # scipy's solve_ivp reads this function attribute
        events = [event]
    sol = solve_ivp(fun, (float(t_eval[0]), float(t_eval[-1])), np.asarray(y0, dtype=float), method=method,
                    t_eval=t_eval, jac=jac, rtol=rtol, atol=atol, events=events, max_step=max_step)
    if sol.y.shape[1] == len(t_eval):
        Y = sol.y.T  # (n, ny) view of the solver's array: no copy of a 10-kHz history
    else:
        Y = np.full((len(t_eval), len(y0)), np.nan)
        Y[: sol.y.shape[1]] = sol.y.T
    stopped = stop is not None and sol.status == 1
    message = "stopped by event" if stopped else sol.message
    t_stop = float(sol.t_events[0][0]) if stopped else None
    return OfflineResult(t=np.asarray(t_eval, dtype=float), Y=Y, success=sol.status == 0, message=message,
                         nfev=sol.nfev, njev=sol.njev, t_stop=t_stop)
