"""Runs of Model A: offline simulation, streaming, batched stretch histories for identification."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Literal, cast

import numpy as np

from bench.models.integrate import MODEL_MEMBRANE, FixedStepper, run_fixed, solve_offline
from bench.models.membrane import (
    P_BRANCHES,
    MembraneParams,
    MembraneTrace,
    membrane_jac,
    membrane_outputs,
    membrane_rhs,
)
from bench.models.membrane_batch import membrane_batch
from bench.models.rosenbrock import STATUS_STOPPED, rodas3_membrane

# voltage [V] of time [s], vectorised: an array of times in, the array of voltages out (a Waveform is one);
# one with a ``scalar(t)`` method has it used where the integrator asks for one time at a time
VoltageInput = Callable[[np.ndarray], np.ndarray]

# physics.md §1.5: λ̇ needs a loose absolute tolerance, λ and ξ a tight one
ATOL_SCALE_HEAD = (1e-3, 1e2)
ATOL_SCALE_UNIT = 1e-3
RODAS_RTOL = 3e-7  # compiled Rosenbrock: max|Δλ| 5e-7 on the base case (scipy Radau at its rtol 1e-6: 8e-7)


def atol_for(params: MembraneParams, rtol: float) -> np.ndarray:
    """Per-component absolute tolerance rtol·[1e-3, 1e2, 1e-3, …] for (λ, λ̇, ξ_i)."""
    return rtol * np.array([*ATOL_SCALE_HEAD, *([ATOL_SCALE_UNIT] * params.n_units)])


def _scalar(voltage: VoltageInput) -> Callable[[float], float]:
    scalar = getattr(voltage, "scalar", None)
    if callable(scalar):
        return cast(Callable[[float], float], scalar)
    return lambda t: float(voltage(np.asarray(t)))


def simulate_membrane(params: MembraneParams, voltage: VoltageInput, t_end: float, fs: float = 10_000.0,
                      T: float = 296.0, method: Literal["rodas", "radau", "bdf", "fixed"] = "rodas",
                      rtol: float | None = None, h: float = 1e-4) -> MembraneTrace:
    """Simulate the membrane under voltage(t) [V] for t_end [s], output sampled at fs [Hz].

    ``rodas`` (default): the compiled Rosenbrock integrator with error control (:mod:`bench.models.rosenbrock`,
    rtol 3e-7: max|Δλ| ≈ 5e-7 on the base case); the voltage is sampled every min(1/fs, 0.1 ms) and taken
    linear in between. ``radau``/``bdf``: scipy's stiff solvers with the analytic Jacobian (rtol 1e-6; the
    reference path, physics.md §1.5). ``fixed``: the streaming fixed-step scheme with step h (output every
    round(1/(fs·h)) steps). The run stops early (remaining samples NaN, ``failed`` set) at runaway stretch or
    Gent lock-up. ``rtol`` applies to the adaptive methods.
    """
    if not (t_end > 0 and fs > 0):
        raise ValueError(f"t_end and fs must be > 0, got {t_end} s and {fs} Hz")
    n_out = round(t_end * fs) + 1
    t_out: np.ndarray = np.arange(n_out) / fs
    phi = None
    if method == "fixed":
        stride = max(1, round(1.0 / (fs * h)))
        n_steps = (n_out - 1) * stride
        t_steps = np.arange(1, n_steps + 1) * h
        U = np.empty((n_steps, 2))
        U[:, 0] = voltage(t_steps)
        U[:, 1] = T
        Y, _ = run_fixed(MODEL_MEMBRANE, params.initial_state(), U, h, params.pack())
        Y = Y[::stride]
        t_out = np.arange(len(Y)) * h * stride
        stop_reason, t_stop = "", math.inf
    else:
        Y, stop_reason, phi, t_stop = integrate_membrane(params, voltage, t_out, T, method, rtol)
    if phi is None:
        phi = np.asarray(voltage(t_out), dtype=float)
    # a runaway stop is one failure among others: the trace names whichever came first (breakdown often does)
    trace = membrane_outputs(params, t_out, Y, phi, T, runaway_at=t_stop)
    if stop_reason and not math.isfinite(t_stop):
        trace.failed, trace.failure = True, stop_reason
    return trace


def integrate_membrane(params: MembraneParams, voltage: VoltageInput, t_out: np.ndarray, T: float = 296.0,
                       method: Literal["rodas", "radau", "bdf"] = "rodas",
                       rtol: float | None = None) -> tuple[np.ndarray, str, np.ndarray | None, float]:
    """States at the uniform times ``t_out`` (from 0) by an adaptive stiff integrator (see
    :func:`simulate_membrane`). Returns (Y, why the run stopped early or '', Φ at t_out when it was sampled, the
    time where it stopped at runaway stretch or inf)."""
    p = params.pack()
    y0 = params.initial_state()
    stop = f"runaway stretch: λ passed {params.runaway_stretch} at t = {{:.3f}} s (pull-in); the run was stopped there"
    if method == "rodas":
        rtol = RODAS_RTOL if rtol is None else rtol
        dt_out = float(t_out[1] - t_out[0]) if t_out.size > 1 else 1e-4
        k = max(1, int(np.ceil(dt_out / 1e-4 - 1e-9)))  # input samples per output interval (≤ 0.1 ms apart)
        dt = dt_out / k
        t_in = np.arange((t_out.size - 1) * k + 1) * dt
        phi_in = np.asarray(voltage(t_in), dtype=float)
        Y = np.empty((t_out.size, y0.size))
        status, _, _, t_stop = rodas3_membrane(y0, t_out, float(T), p, 0.0, dt, phi_in, rtol,
                                               atol_for(params, rtol), params.runaway_stretch, Y)
        reason = stop.format(t_stop) if status == STATUS_STOPPED else "" if status == 0 else \
            f"integration failed at t = {t_stop:.3f} s (step size underflow or non-finite state)"
        return Y, reason, phi_in[::k], float(t_stop) if status == STATUS_STOPPED else math.inf
    phi_of = _scalar(voltage)
    ny = y0.size

    def fun(t: float, y: np.ndarray) -> np.ndarray:
        dy = np.empty(ny)
        membrane_rhs(y, phi_of(t), T, p, dy)
        return dy

    def jac(t: float, y: np.ndarray) -> np.ndarray:
        J = np.empty((ny, ny))
        membrane_jac(y, phi_of(t), T, p, J)
        return J

    rtol = 1e-6 if rtol is None else rtol
    res = solve_offline(fun, jac, y0, t_out, atol=atol_for(params, rtol), rtol=rtol,
                        method="Radau" if method == "radau" else "BDF",
                        stop=lambda t, y: params.runaway_stretch - y[0])
    reason = stop.format(res.t_stop) if res.t_stop is not None else "" if res.success else \
        f"integration failed: {res.message}"
    return res.Y, reason, None, math.inf if res.t_stop is None else float(res.t_stop)


class MembraneStream:
    """Streaming membrane for the simulated rig: blocks of samples at the current Φ [V] and T [K].

    ``method``: ``fixed`` (the twins: the compiled fixed-step scheme, step h) or ``rodas`` (the dry run: each
    block by the compiled Rosenbrock integrator with error control, :mod:`bench.models.rosenbrock`, output on
    the same grid of step h; Φ linear between the grid points). A ``rodas`` block stopped at runaway stretch
    says when in ``trace.extra["runaway_at"]`` (the samples after it are NaN).
    """

    def __init__(self, params: MembraneParams, h: float = 1e-4, T: float = 296.0,
                 method: Literal["fixed", "rodas"] = "fixed") -> None:
        self.params = params
        self.T = T
        self.method = method
        self._stepper = FixedStepper(MODEL_MEMBRANE, params.pack(), params.initial_state(), h)
        self._phi_end = 0.0  # Φ at the end of the last block (where a rodas block's input starts)
        self._packed = (params, params.pack())  # the observables' parameter vector, made again if params change

    @property
    def t(self) -> float:
        """Simulated time [s]."""
        return self._stepper.t

    @property
    def state(self) -> np.ndarray:
        """Current state [λ, λ̇, ξ_1…ξ_n] (a view; do not modify)."""
        return self._stepper.y

    @property
    def stretch(self) -> float:
        """Current λ [-]."""
        return float(self._stepper.y[0])

    @property
    def displacement(self) -> float:
        """Current displacement u = L_d(λ − λ_pre) [m]."""
        return self.params.L_d * (float(self._stepper.y[0]) - self.params.lambda_pre)

    def step(self, phi: float, T: float | None = None) -> bool:
        """Advance one step with voltage φ [V] (and temperature T [K]); False once the model failed."""
        return self._stepper.step(phi, self.T if T is None else T)

    def advance(self, phi: np.ndarray, T: float | None = None) -> MembraneTrace:
        """Advance len(phi) steps (phi[k] is the voltage during step k) and return their trace."""
        phi = np.asarray(phi, dtype=float)
        if self.method == "rodas":
            return self._advance_rodas(phi, self.T if T is None else T)
        U = np.empty((phi.size, 2))
        U[:, 0] = phi
        U[:, 1] = self.T if T is None else T
        t0 = self._stepper.t
        Y = self._stepper.advance(U)
        t = t0 + self._stepper.h * np.arange(1, phi.size + 1)
        if self._packed[0] is not self.params:
            self._packed = (self.params, self.params.pack())
        return membrane_outputs(self.params, t, Y, phi, U[:, 1], self._packed[1])


    def _advance_rodas(self, phi: np.ndarray, T: float) -> MembraneTrace:
        st, params = self._stepper, self.params
        n, h, t0 = phi.size, st.h, st.t
        t_out = t0 + h * np.arange(n + 1)
        phi_in = np.concatenate([[self._phi_end], phi])  # Φ at t0 + k·h: step k ramps to phi[k]
        Y = np.empty((n + 1, st.y.size))
        status, _, _, t_stop = rodas3_membrane(st.y.copy(), t_out, float(T), params.pack(), t0, h, phi_in, RODAS_RTOL,
                                               atol_for(params, RODAS_RTOL), params.runaway_stretch, Y)
        finite = np.isfinite(Y[:, 0])
        last = int(np.flatnonzero(finite)[-1])
        st.y = Y[last].copy()  # a stopped run keeps its last finite state
        st.t = t0 + h * n
        self._phi_end = float(phi[-1]) if n else self._phi_end
        stopped = status == STATUS_STOPPED
        trace = membrane_outputs(params, t_out[1:], Y[1:], phi, T, runaway_at=float(t_stop) if stopped else math.inf)
        if stopped:  # the failure text names breakdown first where it came before the runaway
            trace.extra["runaway_at"] = float(t_stop)
        elif status != 0:
            trace.failed = True
            trace.failure = f"integration failed at t = {t_stop:.4f} s (step size underflow or non-finite state)"
        return trace


def batch_stretch(param_sets: Sequence[MembraneParams] | np.ndarray, voltage: np.ndarray, T: float,
                  h: float = 1e-4, stride: int = 1, template: MembraneParams | None = None) -> np.ndarray:
    """λ histories for many parameter sets under one voltage history (identification).

    ``voltage[k]`` is Φ at t = (k+1)h; returns (n_sets, len(voltage)//stride + 1) sampled every ``stride``
    steps from t = 0, computed in parallel on all cores. ``param_sets`` are MembraneParams or rows of packed
    vectors (then ``template`` gives λ_pre for the initial state).
    """
    if isinstance(param_sets, np.ndarray):
        P = np.ascontiguousarray(param_sets, dtype=np.float64)
        base = template or MembraneParams()
    else:
        P = np.stack([ps.pack() for ps in param_sets])
        base = param_sets[0]
    n_units = (P.shape[1] - P_BRANCHES) // 3
    y0 = np.full(2 + n_units, base.lambda_pre)
    y0[1] = 0.0
    Y0 = np.tile(y0, (P.shape[0], 1))
    U = np.empty((len(voltage), 2))
    U[:, 0] = voltage
    U[:, 1] = T
    return membrane_batch(P, Y0, U, h, stride)
