"""Model A — pre-stretched VHB 4910 membrane (thesis Ch. 3, corrected as in physics.md §1).

Equibiaxial square membrane, stretch λ relative to the unstretched film, on a dead load that holds it at
the pre-stretch λ_pre. Rheology: Gent equilibrium spring (unit 0) in parallel with n Gent Maxwell units
(thesis: four). Inertia of the in-plane and thickness motion. Voltage Φ across the film; relative
permittivity ε_r(λ, T) = aλ² + b/T + c.

State ``y = [λ, λ̇, ξ_1 … ξ_n]`` (λ̇ in 1/s); inputs ``Φ`` [V] and ``T`` [K].

Equations (physics.md §1.2):

* s0(λ) = μ0 (λ − λ⁻⁵)/G0                                         equilibrium spring
* s_i(λ, ξ_i) = μ_i (λξ_i⁻² − λ⁻⁵ξ_i⁴)/G_i                          Maxwell springs
* s_es = ε_vac (Φ/L3)² [ε_r λ³ + κ a λ⁵], κ = 1/2 (corrected; the thesis eq 64/68 has κ = 2)
* s_ext = s0(λ_pre) − k_f (λ − λ_pre)                              dead load (+ optional frame spring)
* M(λ) λ̈ = 2ρL3²λ⁻⁷λ̇² − s0 − Σ s_i + s_ext + s_es,  M = ρL²/3 + (2/3)ρL3²λ⁻⁶
* ξ̇_i = (μ_i/6η_i)(λ²ξ_i⁻¹ − λ⁻⁴ξ_i⁵)/G_i

Numba kernels (rhs, Jacobian, fixed-step streaming step) take the parameters packed into a float array by
:meth:`MembraneParams.pack`; :mod:`bench.models.integrate` runs them offline, streaming and batched.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from bench.models.gent import gent_h, gent_h_e2, gent_h_G, relaxation_rate
from bench.models.jit import njit
from bench.models.kernel_args import kernel_array
from bench.numbers import mv_per_m

EPS_VAC = 8.85418e-12  # F/m, thesis Table 4.1

# Layout of the packed parameter vector (see MembraneParams.pack)
P_L, P_L3, P_RHO, P_EPS, P_A, P_B, P_C, P_KAPPA, P_LPRE, P_KF, P_SPRE, P_MU0, P_J0, P_N = range(14)
P_BRANCHES = 14  # then mu[n], J[n], eta[n]

Electrostriction = Literal["corrected", "thesis"]
ELECTROSTRICTIONS: tuple[Electrostriction, ...] = ("corrected", "thesis")


@dataclass(frozen=True)
class MembraneParams:
    """Parameters of the thesis membrane; defaults are thesis Table 4.1/4.4 (physics.md §1.1).

    Lengths in m, moduli in Pa, viscosities in Pa·s, temperature in K, fields in V/m.
    """

    L: float = 0.03  # m, reference side of the active square (inertia; and default L_d)
    L3: float = 1.0e-3  # m, reference thickness
    rho: float = 960.0  # kg/m³ (Table 4.1 prints J/m³: typo)
    lambda_pre: float = 2.0  # -, equibiaxial pre-stretch = initial λ and ξ_i
    mu0: float = 65.4472e3  # Pa, equilibrium Gent spring
    J0: float = 351.629  # -, its limit
    mu: tuple[float, ...] = (123.636e3, 30.8529e3, 499.622e3, 398.081e3)  # Pa, Maxwell units 1..n
    J: tuple[float, ...] = (400.619, 432.838, 405.422, 795.496)  # -
    eta: tuple[float, ...] = (1.10671e4, 1.54164e5, 4.99622, 2.68992e4)  # Pa·s
    eps_vac: float = EPS_VAC  # F/m
    a: float = 0.0533  # -, ε_r = aλ² + b/T + c
    b: float = 645.4224  # K
    c: float = 3.1834  # -
    electrostriction: Electrostriction = "corrected"  # "thesis" = eq 64/68 form, 4× too large
    k_f: float = 0.0  # Pa, optional frame stiffness (0 = thesis)
    L_d: float = 0.03  # m, length converting stretch to displayed displacement u = L_d(λ − λ_pre)
    breakdown_field: float = 100e6  # V/m, true-field failure threshold (VHB: order 1e8 when pre-stretched)
    runaway_stretch: float = 4.0  # -, λ above which the run is flagged as pull-in / runaway

    def __post_init__(self) -> None:
        n = len(self.mu)
        if len(self.J) != n or len(self.eta) != n:
            raise ValueError(f"mu, J and eta need one entry per Maxwell unit; got {n}, {len(self.J)}, "
                             f"{len(self.eta)}")
        if self.electrostriction not in ELECTROSTRICTIONS:
            raise ValueError(f"electrostriction must be 'corrected' or 'thesis', got {self.electrostriction!r}")
        for name in ("L", "L3", "rho", "lambda_pre", "mu0", "J0"):
            if not getattr(self, name) > 0:
                raise ValueError(f"membrane parameter {name} must be > 0, got {getattr(self, name)}")
        if any(m <= 0 for m in self.mu) or any(j <= 0 for j in self.J) or any(e <= 0 for e in self.eta):
            raise ValueError("Maxwell unit parameters mu, J, eta must all be > 0")

    @property
    def n_units(self) -> int:
        """Number of Maxwell units."""
        return len(self.mu)

    @property
    def tau(self) -> tuple[float, ...]:
        """Relaxation times τ_i = η_i/μ_i [s] (physics.md §1.1: 0.0895, 4.997, 1e-5, 0.0676 s)."""
        return tuple(e / m for e, m in zip(self.eta, self.mu, strict=True))

    @property
    def kappa(self) -> float:
        """Coefficient of aλ⁵ in the electrostatic stress (1/2 corrected, 2 as printed in the thesis)."""
        return 0.5 if self.electrostriction == "corrected" else 2.0

    @property
    def s_pre(self) -> float:
        """Dead-load nominal stress s_ext = s0(λ_pre) [Pa] (check A1: 130.731 kPa)."""
        h, _, _ = gent_h(math.log(self.lambda_pre), self.J0)
        return self.mu0 * h / self.lambda_pre

    @property
    def edge_load(self) -> float:
        """Dead load per edge P = s_ext·L·L3 [N] (3.922 N)."""
        return self.s_pre * self.L * self.L3

    def with_units(self, mu0: float, J0: float, mu: tuple[float, ...], J: tuple[float, ...],
                   eta: tuple[float, ...]) -> MembraneParams:
        """Copy with new rheology (used by identification)."""
        return replace(self, mu0=mu0, J0=J0, mu=tuple(mu), J=tuple(J), eta=tuple(eta))

    def pack(self) -> np.ndarray:
        """Flat float64 vector for the numba kernels (layout P_* in this module)."""
        head = np.zeros(P_BRANCHES)
        head[P_L], head[P_L3], head[P_RHO], head[P_EPS] = self.L, self.L3, self.rho, self.eps_vac
        head[P_A], head[P_B], head[P_C], head[P_KAPPA] = self.a, self.b, self.c, self.kappa
        head[P_LPRE], head[P_KF], head[P_SPRE] = self.lambda_pre, self.k_f, self.s_pre
        head[P_MU0], head[P_J0], head[P_N] = self.mu0, self.J0, self.n_units
        return np.concatenate([head, self.mu, self.J, self.eta]).astype(np.float64)

    def initial_state(self) -> np.ndarray:
        """Rest state: λ = ξ_i = λ_pre, λ̇ = 0 (thesis X0 = [2,2,2,2,2], V0 = 0)."""
        y = np.full(2 + self.n_units, self.lambda_pre)
        y[1] = 0.0
        return y


# ---------------------------------------------------------------- numba kernels (physics.md §1.2, §1.5)


@njit(cache=True)
def eps_r(lam: float, T: float, p: np.ndarray) -> float:
    """Relative permittivity ε_r(λ, T) = aλ² + b/T + c [-] (physics.md §1.3 item 5)."""
    return float(p[P_A] * lam * lam + p[P_B] / T + p[P_C])


@njit(cache=True)
def capacitance(lam: float, T: float, p: np.ndarray) -> tuple[float, float]:
    """Capacitance of the active square C = ε_vac ε_r L²λ⁴/L3 [F] and dC/dλ [F]."""
    geo = p[P_EPS] * p[P_L] ** 2 / p[P_L3]
    er = eps_r(lam, T, p)
    lam3 = lam * lam * lam
    return geo * er * lam3 * lam, geo * (2.0 * p[P_A] * lam3 * lam * lam + 4.0 * er * lam3)


@njit(cache=True)
def es_stress(lam: float, phi: float, T: float, p: np.ndarray) -> tuple[float, float]:
    """Electrostatic nominal stress s_es [Pa] and ds_es/dλ at voltage φ [V], temperature T [K].

    With κ = 1/2 this is (Φ²/(4L²L3)) dC/dλ, the net generalised force of a voltage source.
    """
    a = p[P_A]
    kappa = p[P_KAPPA]
    er = eps_r(lam, T, p)
    pre = p[P_EPS] * (phi / p[P_L3]) ** 2
    lam2 = lam * lam
    s = pre * (er * lam2 * lam + kappa * a * lam2 * lam2 * lam)
    ds = pre * (2.0 * a * lam2 * lam2 + 3.0 * er * lam2 + 5.0 * kappa * a * lam2 * lam2)
    return s, ds


@njit(cache=True)
def inertia(lam: float, p: np.ndarray) -> tuple[float, float]:
    """Generalised mass M(λ) = ρL²/3 + (2/3)ρL3²λ⁻⁶ [Pa·s²] and dM/dλ."""
    rho, L, L3 = p[P_RHO], p[P_L], p[P_L3]
    inv = 1.0 / lam
    inv6 = (inv * inv * inv) ** 2
    return rho * L * L / 3.0 + 2.0 / 3.0 * rho * L3 * L3 * inv6, -4.0 * rho * L3 * L3 * inv6 * inv


@njit(cache=True)
def membrane_rhs(y: np.ndarray, phi: float, T: float, p: np.ndarray, dy: np.ndarray) -> None:
    """dy/dt of the membrane ODE (physics.md §1.2) written into ``dy``."""
    lam = y[0]
    v = y[1]
    n = int(p[P_N])
    h0, _, _ = gent_h_e2(lam * lam, p[P_J0])
    force = 2.0 * p[P_RHO] * p[P_L3] ** 2 * lam**-7 * v * v - p[P_MU0] * h0 / lam
    for i in range(n):
        mu = p[P_BRANCHES + i]
        J = p[P_BRANCHES + n + i]
        eta = p[P_BRANCHES + 2 * n + i]
        xi = y[2 + i]
        h, _, _ = gent_h_e2((lam / xi) ** 2, J)
        force -= mu * h / lam
        dy[2 + i] = xi * mu / (6.0 * eta) * h
    s_es, _ = es_stress(lam, phi, T, p)
    force += p[P_SPRE] - p[P_KF] * (lam - p[P_LPRE]) + s_es
    M, _ = inertia(lam, p)
    dy[0] = v
    dy[1] = force / M


@njit(cache=True)
def membrane_jac(y: np.ndarray, phi: float, T: float, p: np.ndarray, jac: np.ndarray) -> None:
    """Analytic Jacobian ∂(dy/dt)/∂y of :func:`membrane_rhs` written into ``jac`` (zeroed here)."""
    lam = y[0]
    v = y[1]
    n = int(p[P_N])
    jac[:, :] = 0.0
    c_in = p[P_RHO] * p[P_L3] ** 2
    h0, dh0, _ = gent_h_e2(lam * lam, p[P_J0])
    force = 2.0 * c_in * lam**-7 * v * v - p[P_MU0] * h0 / lam
    dforce = -14.0 * c_in * lam**-8 * v * v - p[P_MU0] * (dh0 - h0) / (lam * lam)
    M, dM = inertia(lam, p)
    for i in range(n):
        mu = p[P_BRANCHES + i]
        J = p[P_BRANCHES + n + i]
        eta = p[P_BRANCHES + 2 * n + i]
        xi = y[2 + i]
        h, dh, _ = gent_h_e2((lam / xi) ** 2, J)
        force -= mu * h / lam
        dforce -= mu * (dh - h) / (lam * lam)
        jac[1, 2 + i] = mu * dh / (lam * xi) / M  # −(∂s_i/∂ξ_i)/M
        q = mu / (6.0 * eta)
        jac[2 + i, 0] = xi * q * dh / lam
        jac[2 + i, 2 + i] = q * (h - dh)
    s_es, ds_es = es_stress(lam, phi, T, p)
    force += p[P_SPRE] - p[P_KF] * (lam - p[P_LPRE]) + s_es
    dforce += -p[P_KF] + ds_es
    jac[0, 1] = 1.0
    jac[1, 0] = (dforce * M - force * dM) / (M * M)
    jac[1, 1] = 4.0 * c_in * lam**-7 * v / M


@njit(cache=True)
def membrane_step(y: np.ndarray, phi: float, T: float, h: float, p: np.ndarray) -> bool:
    """Advance ``y`` in place by one fixed step h [s] with input φ_{n+1}, T (physics.md §1.5).

    Maxwell units: exponential update of the elastic log-stretch (exact for the linearised unit,
    unconditionally stable, so unit 3 with τ = 1e-5 s is handled at h = 1e-4 s). Membrane: symplectic
    Euler. Returns False when the state has left the model's domain (Gent lock-up, non-finite).
    """
    lam = y[0]
    v = y[1]
    n = int(p[P_N])
    h0, G0 = gent_h_G(lam * lam, p[P_J0])
    M, dM = inertia(lam, p)
    force = -0.5 * dM * v * v - p[P_MU0] * h0 / lam  # 2ρL3²λ⁻⁷λ̇² = −½ (dM/dλ) λ̇²
    ok = G0 > 0.0
    for i in range(n):
        mu = p[P_BRANCHES + i]
        J = p[P_BRANCHES + n + i]
        eta = p[P_BRANCHES + 2 * n + i]
        e = lam / y[2 + i]  # elastic stretch e = e^u
        u = math.log(e)
        hu, _ = gent_h_G(e * e, J)
        u *= math.exp(-h * relaxation_rate(u, hu, mu, eta))
        e2 = math.exp(2.0 * u)
        y[2 + i] = lam / math.sqrt(e2)  # ξ = λ e^{−u}
        hu, G = gent_h_G(e2, J)
        ok = ok and G > 0.0
        force -= mu * hu / lam
    s_es, _ = es_stress(lam, phi, T, p)
    force += p[P_SPRE] - p[P_KF] * (lam - p[P_LPRE]) + s_es
    v = v + h * force / M
    lam = lam + h * v
    y[0] = lam
    y[1] = v
    return ok and lam > 0.0 and math.isfinite(lam)


# ---------------------------------------------------------------- outputs


@dataclass
class MembraneTrace:
    """Time series of one membrane run; all arrays share the time base ``t``.

    Units: t [s], stretch λ [-], stretch rate [1/s], voltage [V], displacement [m], field [V/m],
    capacitance [F], charge [C], current [A], temperature [K].
    """

    t: np.ndarray
    stretch: np.ndarray
    stretch_rate: np.ndarray
    voltage: np.ndarray
    temperature: np.ndarray
    displacement: np.ndarray
    field: np.ndarray
    capacitance: np.ndarray
    charge: np.ndarray
    current: np.ndarray
    xi: np.ndarray  # (n_samples, n_units) inelastic stretches
    failed: bool = False
    failure: str = ""
    extra: dict[str, float] = dataclasses.field(default_factory=dict)

    def peak_displacement(self) -> float:
        """Maximum displacement [m]."""
        return float(np.max(self.displacement))


@njit(cache=True, nogil=True)
def membrane_observe(t: np.ndarray, Y: np.ndarray, phi: np.ndarray, T: np.ndarray, p: np.ndarray,
                     out: np.ndarray) -> None:
    """Per-sample observables into ``out`` (n×4): true field E = Φλ²/L3 [V/m], C [F], Q = CΦ [C] and
    I = dQ/dt = (dC/dλ)λ̇Φ + CΦ̇ [A], with Φ̇ by (central) finite differences of the input samples."""
    n = t.size
    for k in range(n):
        lam = Y[k, 0]
        C, dC = capacitance(lam, T[k], p)
        if n == 1:
            phidot = 0.0
        elif k == 0:
            phidot = (phi[1] - phi[0]) / (t[1] - t[0])
        elif k == n - 1:
            phidot = (phi[k] - phi[k - 1]) / (t[k] - t[k - 1])
        else:
            phidot = (phi[k + 1] - phi[k - 1]) / (t[k + 1] - t[k - 1])
        out[k, 0] = phi[k] * lam * lam / p[P_L3]
        out[k, 1] = C
        out[k, 2] = C * phi[k]
        out[k, 3] = dC * Y[k, 1] * phi[k] + C * phidot


@njit(cache=True)
def _any_failure(Y: np.ndarray, obs: np.ndarray, runaway: float, breakdown: float) -> bool:
    """Whether :func:`failure_reason` finds anything in λ = ``Y[:, 0]`` and E = ``obs[:, 0]`` (its comparisons in one
    pass, no arrays made; whole 2-D arrays, so that a block of one sample is not another compiled signature)."""
    for k in range(Y.shape[0]):
        lam = Y[k, 0]
        if lam > runaway or abs(obs[k, 0]) > breakdown or not math.isfinite(lam):
            return True
    return False


def membrane_outputs(params: MembraneParams, t: np.ndarray, Y: np.ndarray, phi: np.ndarray,
                     T: np.ndarray | float, packed: np.ndarray | None = None,
                     runaway_at: float = math.inf) -> MembraneTrace:
    """Observable quantities from the state history ``Y`` (n×(2+n_units)) and inputs (physics.md §1.2, §1.4).

    u = L_d(λ − λ_pre); E = Φλ²/L3 (true field); C = ε_vac ε_r L²λ⁴/L3; Q = CΦ; I = dQ/dt.
    Flags failure at the first sample with λ > runaway_stretch, E > breakdown_field or non-finite state (the
    earliest kind named first, :func:`failure_reason`). ``packed``: ``params.pack()`` where the caller keeps it (a
    stream, block after block). ``runaway_at``: the time where the integrator stopped at runaway stretch.
    """
    t = kernel_array(t)  # every array in one form: one compiled variant of each kernel (kernel_args)
    Y = kernel_array(Y)  # an offline solve's history is the solver's array transposed (F order): copied here
    phi = kernel_array(phi, t.shape)
    Tarr = kernel_array(T, t.shape)
    obs = np.empty((t.size, 4))
    membrane_observe(t, Y, phi, Tarr, params.pack() if packed is None else packed, obs)
    lam = Y[:, 0]
    trace = MembraneTrace(
        t=t, stretch=lam, stretch_rate=Y[:, 1], voltage=phi, temperature=Tarr,
        displacement=params.L_d * (lam - params.lambda_pre), field=obs[:, 0], capacitance=obs[:, 1],
        charge=obs[:, 2], current=obs[:, 3], xi=Y[:, 2:],
    )
    failed = math.isfinite(runaway_at) or _any_failure(Y, obs, float(params.runaway_stretch),
                                                        float(params.breakdown_field))
    reason = failure_reason(params, lam, obs[:, 0], t, runaway_at) if failed else ""
    if reason:
        trace.failed, trace.failure = True, reason
    return trace


def failure_reason(params: MembraneParams, lam: np.ndarray, E: np.ndarray, t: np.ndarray | None = None,
                   runaway_at: float = math.inf) -> str:
    """Return why the run failed ('' when it did not): breakdown, runaway stretch or a non-finite state, whichever
    came first in time; a second kind that followed is named after it ("…; then …").

    ``t``: the sample times (messages then say when, not which sample). ``runaway_at``: where the integrator stopped
    at runaway stretch (its later samples are NaN, the stop's and not a failure of their own)."""
    n = lam.size
    times = np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float)
    stopped = times >= runaway_at if t is not None else np.zeros(n, dtype=bool)
    with np.errstate(invalid="ignore"):
        over = lam > params.runaway_stretch
        brk = np.abs(E) > params.breakdown_field
    bad = ~np.isfinite(lam) & ~stopped

    def when(i: int) -> str:
        return f"at sample {i}" if t is None else f"at t = {times[i]:.3f} s"

    kinds: list[tuple[float, str]] = []
    if brk.any():
        i = int(np.argmax(brk))
        kinds.append((times[i], f"true field {mv_per_m(abs(E[i]))} MV/m above breakdown "
                                f"{mv_per_m(params.breakdown_field)} MV/m {when(i)}"
                                + ("" if t is None else f" (λ = {lam[i]:.3f})")))
    if over.any() or (t is not None and math.isfinite(runaway_at)):
        i = int(np.argmax(over)) if over.any() else n
        if i < n and times[i] < runaway_at:
            kinds.append((times[i], f"runaway stretch λ = {lam[i]:.3f} > {params.runaway_stretch} {when(i)} (pull-in)"))
        else:
            kinds.append((runaway_at, f"runaway stretch: λ passed {params.runaway_stretch} at t = {runaway_at:.3f} s "
                                      "(pull-in); the run was stopped there"))
    if bad.any():
        i = int(np.argmax(bad))
        kinds.append((times[i], f"non-finite stretch {when(i)} (Gent lock-up or numerical blow-up)"))
    kinds.sort(key=lambda k: k[0])  # stable: at one sample, breakdown before runaway before non-finite
    return "; then ".join(text for _, text in kinds[:2])
