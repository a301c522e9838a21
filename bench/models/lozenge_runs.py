"""Runs of Model B: statics, the three test configurations (imposed, blocked, hung mass), streaming."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from bench.models.integrate import MODEL_LOZENGE, FixedStepper, run_fixed, solve_offline
from bench.models.jit import njit
from bench.models.kernel_args import kernel_array
from bench.models.lozenge import (
    MODE_HUNG,
    MODE_IMPOSED,
    LozengeParams,
    elastic_force,
    electrostatic_force,
    lozenge_observe,
    lozenge_observe_rig,
    lozenge_rhs,
)
from bench.numbers import mv_per_m

Signal = Callable[[np.ndarray], np.ndarray]
Config = Literal["imposed", "blocked", "hung"]


@dataclass
class LozengeRigTrace:
    """What the simulated bench reads of a block of samples (units: m, N, F, C, V/m), and whether the model
    failed in it (left its domain, or the field broke down) and why."""

    position: np.ndarray
    force: np.ndarray
    capacitance: np.ndarray
    charge: np.ndarray
    field: np.ndarray
    breakdown_field: np.ndarray
    failed: bool = False
    failure: str = ""


@dataclass(kw_only=True)
class LozengeTrace(LozengeRigTrace):
    """Time series of one LS-DEA run: the rig's observables and the model's inside; units: s, m, m/s, V, N, F,
    C, V/m, Pa."""

    t: np.ndarray
    velocity: np.ndarray
    voltage: np.ndarray
    force_elastic: np.ndarray
    force_electrostatic: np.ndarray
    force_viscoelastic: np.ndarray
    stress1: np.ndarray
    stress2: np.ndarray
    states: np.ndarray

    @property
    def tension_lost(self) -> np.ndarray:
        """Per-sample loss-of-tension flag (σ1 ≤ 0 or σ2 ≤ 0)."""
        return (self.stress1 <= 0) | (self.stress2 <= 0)


def static_force(params: LozengeParams, x: float, V: float = 0.0) -> float:
    """Static force F_el(x) + F_es(x, V) [N] (eqs 4, 6) with relaxed branches and no damping."""
    p = params.pack()
    return float(elastic_force(x, p)[0] + electrostatic_force(x, V, p)[0])


def static_stiffness(params: LozengeParams, x: float, V: float = 0.0) -> float:
    """dF/dx of :func:`static_force` [N/m]."""
    p = params.pack()
    return float(elastic_force(x, p)[1] + electrostatic_force(x, V, p)[1])


def breakdown_voltage(params: LozengeParams, x: float) -> float:
    """V_B(x) = E0 t0 λ3^(1 − r/2) [V]: voltage at which the true field reaches E_B."""
    m = params.material
    y = math.sqrt(4 * params.l**2 - x * x)
    lam3 = 1.0 / ((params.lambda1p * x / params.xp) * (params.lambda2p * y / params.yp))
    return float(m.E0 * params.t0 * lam3 ** (1.0 - m.r / 2.0))


def isotonic_equilibrium(params: LozengeParams, V: float = 0.0, x_max: float | None = None) -> float | None:
    """First static equilibrium x0 > x_p [m] of the hung load: F_el + F_es = (m + M/2) g; None if none."""
    W = params.load
    x_hi = x_max if x_max is not None else 2 * params.l * 0.98
    grid = np.linspace(params.xp * 1.001, x_hi, 2000)
    r = np.array([static_force(params, float(x), V) - W for x in grid])
    sign = np.nonzero(np.sign(r[:-1]) != np.sign(r[1:]))[0]
    if sign.size == 0:
        return None
    from scipy.optimize import brentq  # here: scipy.optimize takes 0.3 s to import (every `bench run` would)

    i = int(sign[0])
    return float(brentq(lambda x: static_force(params, x, V) - W, grid[i], grid[i + 1], xtol=1e-12))


def _inputs(t: np.ndarray, voltage: Signal, position: Signal | float, velocity: Signal | None) -> np.ndarray:
    U = np.zeros((t.size, 3))
    U[:, 0] = voltage(t)
    if callable(position):
        U[:, 1] = position(t)
        U[:, 2] = velocity(t) if velocity is not None else np.gradient(U[:, 1], t)
    else:
        U[:, 1] = position
    return U


def simulate_lozenge(params: LozengeParams, config: Config, voltage: Signal, t_end: float,
                     fs: float = 10_000.0, position: Signal | float | None = None,
                     velocity: Signal | None = None, method: Literal["fixed", "radau"] = "fixed",
                     h: float = 1e-4, rtol: float = 1e-6) -> LozengeTrace:
    """Simulate an LS-DEA test for t_end [s], output at fs [Hz].

    * ``imposed``: x(t) = position(t) [m] from the motor, ẋ = velocity(t) (finite differences if omitted);
    * ``blocked``: x = position [m] constant;
    * ``hung``: free end with the params' hung mass, starting at rest at the 0-V equilibrium
      (or at ``position`` if given) with relaxed branches.
    ``fixed`` uses the streaming scheme with step h; ``radau`` the stiff solver with analytic Jacobian.
    """
    mode = MODE_HUNG if config == "hung" else MODE_IMPOSED
    p = params.pack(mode)
    n_out = round(t_end * fs) + 1
    t_out: np.ndarray = np.arange(n_out) / fs
    if config == "hung":
        x0 = position if isinstance(position, float | int) else isotonic_equilibrium(params, 0.0)
        if x0 is None:
            raise ValueError(f"no static equilibrium for load {params.load:.3f} N on this prototype")
        pos: Signal | float = float(x0)
    elif config == "blocked":
        if not isinstance(position, float | int):
            raise ValueError("a blocked (isometric) test needs a constant position [m]")
        pos = float(position)
    else:
        if position is None:
            raise ValueError("an imposed-motion test needs position(t)")
        pos = position
    x_start = float(pos(np.zeros(1))[0]) if callable(pos) else float(pos)
    y0 = params.relaxed_state(x_start)
    if method == "fixed":
        stride = max(1, round(1.0 / (fs * h)))
        n_steps = (n_out - 1) * stride
        t_steps = np.arange(0, n_steps + 1) * h
        U = _inputs(t_steps, voltage, pos, velocity)
        Y, _ = run_fixed(MODEL_LOZENGE, y0, U[1:], h, p)
        if config != "hung":
            Y[0, 0], Y[0, 1] = U[0, 1], U[0, 2]
        Y = Y[::stride]
        t_out = t_steps[::stride]
        U = U[::stride]
    else:
        U = _inputs(t_out, voltage, pos, velocity)
        ny = y0.size
        def v_of(t: float) -> float:
            return float(voltage(np.array([t]))[0])

        def x_of(t: float) -> float:
            return float(pos(np.array([t]))[0]) if callable(pos) else float(pos)

        dt = 1e-6

        def xdot_of(t: float) -> float:
            if velocity is not None:
                return float(velocity(np.array([t]))[0])
            return (x_of(t + dt) - x_of(t - dt)) / (2 * dt) if callable(pos) else 0.0

        dummy = np.empty((ny, ny))

        def fun(t: float, y: np.ndarray) -> np.ndarray:
            dy = np.empty(ny)
            lozenge_rhs(y, v_of(t), x_of(t), xdot_of(t), p, dy, dummy, False)
            return dy

        def jac(t: float, y: np.ndarray) -> np.ndarray:
            J = np.empty((ny, ny))
            lozenge_rhs(y, v_of(t), x_of(t), xdot_of(t), p, np.empty(ny), J, True)
            return J

        atol = rtol * np.array([1e-3, 1e-1, *([1e-3] * (ny - 2))])
        res = solve_offline(fun, jac, y0, t_out, atol=atol, rtol=rtol, method="Radau",
                            stop=lambda t, y: min(y[0] - 1e-4, 2 * params.l - 1e-4 - y[0]))
        Y = np.array(res.Y)
        if config != "hung":
            Y[:, 0], Y[:, 1] = U[:, 1], U[:, 2]
    return lozenge_outputs(params, t_out, Y, U[:, 0], mode)


def lozenge_outputs(params: LozengeParams, t: np.ndarray, Y: np.ndarray, V: np.ndarray,
                    mode: int = MODE_IMPOSED) -> LozengeTrace:
    """Observables of a state history (forces, capacitance, field, stresses) and the failure check."""
    Y = kernel_array(Y)  # one form: one compiled variant of lozenge_observe (kernel_args)
    V = kernel_array(V, np.shape(t))
    obs = np.empty((t.size, 12))
    lozenge_observe(Y, V, params.pack(mode), obs)
    trace = LozengeTrace(
        t=np.asarray(t, dtype=float), position=Y[:, 0], velocity=Y[:, 1], voltage=V, force=obs[:, 0],
        force_elastic=obs[:, 1], force_electrostatic=obs[:, 2], force_viscoelastic=obs[:, 3],
        capacitance=obs[:, 4], charge=obs[:, 4] * V, field=obs[:, 5], breakdown_field=obs[:, 6],
        stress1=obs[:, 7], stress2=obs[:, 8], states=Y,
    )
    trace.failure = _failure(lambda i: float(trace.t[i]), trace.position, obs[:, 11], trace.field,
                             trace.breakdown_field)
    trace.failed = bool(trace.failure)
    return trace


@njit(cache=True)
def _failed_rig(Y: np.ndarray, obs: np.ndarray) -> bool:
    """Whether :func:`_failure` finds anything in a rig block (position ``Y[:, 0]``; gent margin, field and breakdown
    field ``obs[:, 4]``, ``obs[:, 2]``, ``obs[:, 3]`` of :func:`lozenge_observe_rig`): the same comparisons in one
    pass, no arrays made (whole 2-D arrays: a block of one sample is not another compiled signature)."""
    for i in range(Y.shape[0]):
        x = Y[i, 0]
        if not math.isfinite(x) or not obs[i, 4] > 0 or abs(obs[i, 2]) > obs[i, 3]:
            return True
    return False


def _failure(time_of: Callable[[int], float], position: np.ndarray, gent_margin: np.ndarray, field: np.ndarray,
             breakdown: np.ndarray) -> str:
    """Why a block failed ("" if it did not): the state left the model's domain, or the field broke down.
    ``time_of(i)``: the time of sample i, asked only for the sample a message names."""
    bad = ~np.isfinite(position) | ~(gent_margin > 0)
    if bad.any():
        return f"state left the model's domain at t = {time_of(int(np.argmax(bad))):.4f} s"
    brk = np.abs(field) > breakdown
    if brk.any():
        i = int(np.argmax(brk))
        return (f"true field {mv_per_m(abs(field[i]))} MV/m above breakdown "
                f"{mv_per_m(breakdown[i])} MV/m at t = {time_of(i):.4f} s")
    return ""


class LozengeStream:
    """Streaming LS-DEA for the simulated rig: one call per sample with the current V, x_in, ẋ_in."""

    def __init__(self, params: LozengeParams, config: Config, x0: float | None = None,
                 h: float = 1e-4, y0: np.ndarray | None = None, t0: float = 0.0) -> None:
        """Start relaxed at x0 (hung: at the 0-V equilibrium if x0 is None), or from state ``y0`` at time t0."""
        self.params = params
        self.mode = MODE_HUNG if config == "hung" else MODE_IMPOSED
        if x0 is None and y0 is not None:
            x0 = float(y0[0])
        if x0 is None:
            if config != "hung":
                raise ValueError(f"{config} configuration needs a start position x0 [m]")
            x0 = isotonic_equilibrium(params, 0.0)
            if x0 is None:
                raise ValueError(f"no static equilibrium for load {params.load:.3f} N on this prototype")
        self._p = params.pack(self.mode)
        start = params.relaxed_state(x0) if y0 is None else np.array(y0, dtype=float)
        self._stepper = FixedStepper(MODEL_LOZENGE, self._p, start, h)
        self._stepper.t = t0
        self._obs = np.empty((1, 12))
        self._V = np.zeros(1)

    @property
    def t(self) -> float:
        """Simulated time [s]."""
        return self._stepper.t

    @property
    def position(self) -> float:
        """Current aperture x [m]."""
        return float(self._stepper.y[0])

    @property
    def state(self) -> np.ndarray:
        """Current state [x, ẋ, a_1..a_K, b_1..b_K] (a view; do not modify)."""
        return self._stepper.y

    def advance(self, U: np.ndarray) -> LozengeTrace:
        """Advance len(U) steps; U[k] = (V [V], x_in [m], ẋ_in [m/s]) during step k. Returns their trace."""
        t0 = self._stepper.t
        Y = self._stepper.advance(U)
        t = t0 + self._stepper.h * np.arange(1, len(U) + 1)
        return lozenge_outputs(self.params, t, Y, U[:, 0], self.mode)

    def advance_rig(self, U: np.ndarray) -> LozengeRigTrace:
        """As :meth:`advance`, returning only what the simulated bench reads: the same values, observed without
        the force split, stresses and stiffness (which cost more than the integration)."""
        t0 = self._stepper.t
        Y = self._stepper.advance(U)
        V = np.ascontiguousarray(U[:, 0], dtype=float)
        obs = np.empty((V.size, 5))
        lozenge_observe_rig(Y, V, self._p, obs)
        position = Y[:, 0]
        h = self._stepper.h
        failure = _failure(lambda i: t0 + h * (i + 1), position, obs[:, 4], obs[:, 2], obs[:, 3]) \
            if _failed_rig(Y, obs) else ""
        return LozengeRigTrace(position, obs[:, 0], obs[:, 1], obs[:, 1] * V, obs[:, 2], obs[:, 3],
                               bool(failure), failure)

    def observe(self, V: float = 0.0) -> LozengeTrace:
        """Observables of the current state at voltage V (one sample)."""
        return lozenge_outputs(self.params, np.array([self._stepper.t]), self._stepper.y.reshape(1, -1),
                               np.array([V]), self.mode)

    def step(self, V: float, x_in: float = 0.0, v_in: float = 0.0) -> bool:
        """Advance one step with voltage V [V] (and imposed x_in [m], ẋ_in [m/s]); False once failed."""
        return self._stepper.step(V, x_in, v_in)

    def force(self, V: float) -> float:
        """Force on the load cell at the current state and voltage V [N]."""
        self._V[0] = V
        lozenge_observe(self._stepper.y.reshape(1, -1), self._V, self._p, self._obs)
        return float(self._obs[0, 0])
