"""Model B — lozenge-shaped DEA on a four-bar mechanism (Moretti et al., eqs 1–6; physics.md §2).

Coordinates: x [m] is the aperture of the lozenge (distance O–A along the actuation axis), l the link
length, (x_p, λ1p, λ2p) the pre-stretch configuration. The membrane stretches are

    y = √(4l² − x²),  λ1 = λ1p x/x_p,  λ2 = λ2p y/y_p,  λ3 = 1/(λ1λ2)                 (eq 1)

Forces are along +x at A, positive when the DEA pulls A toward O (a positive force must be *applied*):

    F_el = Ω dΨ/dx                     Gent–Gent equilibrium energy Ψ(λ1, λ2)          (eqs 2–4)
    F_es = −½V² dC/dx,  C = ε λ1pλ2p x²(4l²−x²)/(2 t0 x_p y_p)                        (eqs 5–6)
    F_ve = Ω Σ_k dW_k/dx               neo-Hookean Maxwell branches (physics.md §2.4)
    F    = F_el + F_es + F_ve + c ẋ    (c: lumped end-effector damper)

Dynamics (one state layout for every configuration): ``y = [x, ẋ, a_1..a_K, b_1..b_K]`` with
a_k = ln ξk1, b_k = ln ξk2 the inelastic log-stretches. Inputs ``(V, x_in, ẋ_in)``:

* ``MODE_IMPOSED`` — motor-imposed position (isopotential) or blocked position (isometric, x_in constant):
  x, ẋ follow the inputs, the force is the output a load cell reads;
* ``MODE_HUNG`` — free end carrying a hung mass m (isotonic), physics.md §2.3:
  m_eff(x) ẍ + ½ m_eff'(x) ẋ² = (m + M/2) g − F,  m_eff = m + α(x) M.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from bench.models.jit import njit

EPS_VAC_PAPER = 8.85e-12  # F/m, as written in the paper's Table 1
PROTOTYPE_LAMBDA2P = {1: 2.5, 2: 2.75, 3: 3.0}  # Table 2, prototypes #1–#3

MODE_IMPOSED = 0
MODE_HUNG = 1

# packed parameter layout
(Q_MU, Q_JM, Q_C2, Q_EPS, Q_T0, Q_E0, Q_R, Q_L, Q_XP, Q_L1P, Q_L2P, Q_C, Q_M, Q_MHUNG, Q_G, Q_ALPHA_HALF,
 Q_MODE, Q_K) = range(18)
Q_BRANCHES = 18  # then mu_k[K], tau_k[K]


@dataclass(frozen=True)
class GentGentMaterial:
    """Equilibrium material of Table 1 (Theraband Yellow 11726). Pa, -, F/m, V/m, -."""

    mu: float = 312.6e3  # Pa, Gent shear modulus
    Jm: float = 30.58  # -, Gent limit
    C2: float = 183.5e3  # Pa, second-invariant (Gent–Gent) coefficient
    eps_r: float = 2.72  # -, relative permittivity
    eps_vac: float = EPS_VAC_PAPER  # F/m
    E0: float = 81e6  # V/m, breakdown field of the unstretched film (92 % reliability)
    r: float = 0.86  # -, E_B = E0 λ3^(−r/2)

    @property
    def permittivity(self) -> float:
        """Absolute permittivity ε [F/m]."""
        return self.eps_r * self.eps_vac


@dataclass(frozen=True)
class MaxwellBranch:
    """Neo-Hookean Maxwell branch: modulus μ [Pa], relaxation time τ [s]."""

    mu: float
    tau: float


VE_A: tuple[MaxwellBranch, ...] = (MaxwellBranch(150e3, 1.0),)  # with c = 1.5 N·s/m (recommended)
VE_B: tuple[MaxwellBranch, ...] = tuple(MaxwellBranch(84.4e3, tau) for tau in (0.03, 0.3, 3.0, 30.0))  # c = 0


@dataclass(frozen=True)
class LozengeParams:
    """LS-DEA prototype, material, rheology and mechanism (defaults: prototype #1 with VE-A).

    Lengths in m, masses in kg, damping in N·s/m, g in m/s².
    """

    lambda2p: float = 2.5  # -, pre-stretch across the actuation axis (#1 2.5, #2 2.75, #3 3.0)
    l: float = 0.120  # m, link length
    xp: float = 0.040  # m, aperture at which the membrane was pre-stretched
    t0: float = 260e-6  # m, unstretched membrane thickness
    rho: float = 1000.0  # kg/m³, membrane density (mass check only)
    material: GentGentMaterial = field(default_factory=GentGentMaterial)
    branches: tuple[MaxwellBranch, ...] = VE_A
    damping: float = 1.5  # N·s/m, lumped end-effector damper c
    mechanism_mass: float = 0.630  # kg, M
    hung_mass: float = 0.0  # kg, m (isotonic tests)
    g: float = 9.81  # m/s²
    inertia: Literal["links", "half"] = "links"  # α(x) of four uniform links, or M/2

    def __post_init__(self) -> None:
        if not 0 < self.xp < 2 * self.l:
            raise ValueError(f"xp must lie in (0, 2l) = (0, {2 * self.l}) m, got {self.xp}")
        for name in ("lambda2p", "l", "t0", "mechanism_mass"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LS-DEA parameter {name} must be > 0, got {getattr(self, name)}")
        if any(b.mu <= 0 or b.tau <= 0 for b in self.branches):
            raise ValueError("Maxwell branches need mu > 0 and tau > 0")
        if self.inertia not in ("links", "half"):
            raise ValueError(f"inertia must be 'links' or 'half', got {self.inertia!r}")

    @classmethod
    def prototype(cls, number: int, **overrides: Any) -> LozengeParams:
        """Prototype #1–#3 of the paper's Table 2 (λ2p = 2.5 / 2.75 / 3.0)."""
        if number not in PROTOTYPE_LAMBDA2P:
            raise ValueError(f"unknown LS-DEA prototype #{number}; known: 1, 2, 3")
        return cls(lambda2p=PROTOTYPE_LAMBDA2P[number], **overrides)

    def changed(self, prototype: int | None = None, hung_mass: float | None = None) -> LozengeParams:
        """These parameters after a set step: another prototype of the same material (its λ2p, the fitted
        material and rheology kept) and/or another hung mass."""
        params = self
        if prototype is not None:
            if int(prototype) not in PROTOTYPE_LAMBDA2P:
                raise ValueError(f"unknown LS-DEA prototype #{prototype}; known: 1, 2, 3")
            params = replace(params, lambda2p=PROTOTYPE_LAMBDA2P[int(prototype)])
        if hung_mass is not None:
            params = replace(params, hung_mass=float(hung_mass))
        return params

    @property
    def lambda1p(self) -> float:
        """λ1p = λ2p^(−1/2) (uniaxial mounting state)."""
        return float(self.lambda2p**-0.5)

    @property
    def yp(self) -> float:
        """y_p = √(4l² − x_p²) [m]."""
        return math.sqrt(4 * self.l**2 - self.xp**2)

    @property
    def volume(self) -> float:
        """Membrane volume Ω = x_p y_p t0/(2λ1pλ2p) [m³]."""
        return self.xp * self.yp * self.t0 / (2 * self.lambda1p * self.lambda2p)

    @property
    def membrane_mass(self) -> float:
        """Active DE mass ρΩ [kg] (Table 2: 0.78 / 0.74 / 0.71 g)."""
        return self.rho * self.volume

    @property
    def load(self) -> float:
        """Gravity load on A, W = (m + M/2) g [N] (3.09 / 4.56 / 4.86 N for m = 0 / 150 / 180 g)."""
        return (self.hung_mass + 0.5 * self.mechanism_mass) * self.g

    def pack(self, mode: int = MODE_IMPOSED) -> np.ndarray:
        """Flat float64 vector for the numba kernels (layout Q_* in this module)."""
        m = self.material
        head = np.zeros(Q_BRANCHES)
        head[Q_MU], head[Q_JM], head[Q_C2], head[Q_EPS] = m.mu, m.Jm, m.C2, m.permittivity
        head[Q_T0], head[Q_E0], head[Q_R] = self.t0, m.E0, m.r
        head[Q_L], head[Q_XP], head[Q_L1P], head[Q_L2P] = self.l, self.xp, self.lambda1p, self.lambda2p
        head[Q_C], head[Q_M] = self.damping, self.mechanism_mass
        head[Q_MHUNG], head[Q_G] = self.hung_mass, self.g
        head[Q_ALPHA_HALF] = 1.0 if self.inertia == "half" else 0.0
        head[Q_MODE], head[Q_K] = mode, len(self.branches)
        mus = [b.mu for b in self.branches]
        taus = [b.tau for b in self.branches]
        return np.concatenate([head, mus, taus]).astype(np.float64)

    def relaxed_state(self, x: float, v: float = 0.0) -> np.ndarray:
        """State at aperture x [m] with every branch relaxed (ξ_k = (λ1, λ2))."""
        K = len(self.branches)
        y = np.empty(2 + 2 * K)
        y[0], y[1] = x, v
        y[2:2 + K] = math.log(self.lambda1p * x / self.xp)
        y[2 + K:] = math.log(self.lambda2p * math.sqrt(4 * self.l**2 - x * x) / self.yp)
        return y


# ---------------------------------------------------------------- numba kernels


@njit(cache=True)
def kinematics(x: float, p: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """Return (λ1, λ2, dλ1/dx, dλ2/dx, d²λ2/dx², y) at aperture x [m] (eq 1)."""
    l, xp, l1p, l2p = p[Q_L], p[Q_XP], p[Q_L1P], p[Q_L2P]
    yp = math.sqrt(4.0 * l * l - xp * xp)
    y = math.sqrt(4.0 * l * l - x * x)
    return (l1p * x / xp, l2p * y / yp, l1p / xp, -l2p * x / (yp * y), -l2p * 4.0 * l * l / (yp * y**3), y)


@njit(cache=True)
def volume(p: np.ndarray) -> float:
    """Membrane volume Ω [m³]."""
    l, xp = p[Q_L], p[Q_XP]
    return float(xp * math.sqrt(4.0 * l * l - xp * xp) * p[Q_T0] / (2.0 * p[Q_L1P] * p[Q_L2P]))


@njit(cache=True)
def _invariants(l1: float, l2: float) -> tuple[float, float, float, float, float, float, float]:
    """(λ3², I1, ∂I1/∂λ1, ∂I1/∂λ2, I2, ∂I2/∂λ1, ∂I2/∂λ2) at (λ1, λ2), λ3 eliminated (eq 2)."""
    a = 1.0 / (l1 * l1 * l2 * l2)  # λ3²
    I1 = l1 * l1 + l2 * l2 + a
    I2 = 1.0 / (l1 * l1) + 1.0 / (l2 * l2) + l1 * l1 * l2 * l2
    return (a, I1, 2.0 * (l1 - a / l1), 2.0 * (l2 - a / l2), I2, -2.0 / l1**3 + 2.0 * l1 * l2 * l2,
            -2.0 / l2**3 + 2.0 * l2 * l1 * l1)


@njit(cache=True)
def gentgent(l1: float, l2: float, p: np.ndarray) -> tuple[float, float, float, float, float, float, float]:
    """Gent–Gent energy per volume Ψ(λ1, λ2) with λ3 eliminated (eq 2): (Ψ, Ψ1, Ψ2, Ψ11, Ψ12, Ψ22, G) in Pa.

    Ψ = −(μJm/2) ln G + C2 ln(I2/3),  G = 1 − (I1 − 3)/Jm,
    I1 = λ1² + λ2² + λ1⁻²λ2⁻²,  I2 = λ1⁻² + λ2⁻² + λ1²λ2².
    """
    mu, Jm, C2 = p[Q_MU], p[Q_JM], p[Q_C2]
    a, I1, I1_1, I1_2, I2, I2_1, I2_2 = _invariants(l1, l2)
    I1_11 = 2.0 + 6.0 * a / (l1 * l1)
    I1_12 = 4.0 * a / (l1 * l2)
    I1_22 = 2.0 + 6.0 * a / (l2 * l2)
    G = 1.0 - (I1 - 3.0) / Jm
    I2_11 = 6.0 / l1**4 + 2.0 * l2 * l2
    I2_12 = 4.0 * l1 * l2
    I2_22 = 6.0 / l2**4 + 2.0 * l1 * l1
    psi = -0.5 * mu * Jm * math.log(G) + C2 * math.log(I2 / 3.0)
    h = 0.5 * mu
    P1 = h * I1_1 / G + C2 * I2_1 / I2
    P2 = h * I1_2 / G + C2 * I2_2 / I2
    P11 = h * (I1_11 / G + I1_1 * I1_1 / (Jm * G * G)) + C2 * (I2_11 / I2 - I2_1 * I2_1 / (I2 * I2))
    P12 = h * (I1_12 / G + I1_1 * I1_2 / (Jm * G * G)) + C2 * (I2_12 / I2 - I2_1 * I2_2 / (I2 * I2))
    P22 = h * (I1_22 / G + I1_2 * I1_2 / (Jm * G * G)) + C2 * (I2_22 / I2 - I2_2 * I2_2 / (I2 * I2))
    return psi, P1, P2, P11, P12, P22, G


@njit(cache=True)
def gent_stress(l1: float, l2: float, p: np.ndarray) -> tuple[float, float, float]:
    """(Ψ1, Ψ2, G) of :func:`gentgent` in its very operations, without the energy's two logarithms and the second
    derivatives: what a fixed step and a rig's force need, the same doubles."""
    mu, Jm, C2 = p[Q_MU], p[Q_JM], p[Q_C2]
    _, I1, I1_1, I1_2, I2, I2_1, I2_2 = _invariants(l1, l2)
    G = 1.0 - (I1 - 3.0) / Jm
    h = 0.5 * mu
    P1 = h * I1_1 / G + C2 * I2_1 / I2
    P2 = h * I1_2 / G + C2 * I2_2 / I2
    return P1, P2, G


@njit(cache=True)
def rig_force(y: np.ndarray, x: float, v: float, V: float, p: np.ndarray, d1: float, d2: float, yy: float,
              ll1: float, ll2: float, P1: float, P2: float, dC: float) -> float:
    """The total force of :func:`lozenge_force` in its very operations (the same double), from what the caller has
    at x (:func:`kinematics`' dλ1/dx, dλ2/dx and y, ln λ1, ln λ2, :func:`gent_stress`' Ψ1, Ψ2, dC/dx), without the
    stiffness and gradient: a step's and a rig's force."""
    K = int(p[Q_K])
    om = volume(p)
    F = om * (P1 * d1 + P2 * d2)
    F += -0.5 * V * V * dC + p[Q_C] * v
    q = x / (yy * yy)
    for i in range(K):
        W1, W2, _, _, _ = branch_energy_derivs(ll1 - y[2 + i], ll2 - y[2 + K + i], p[Q_BRANCHES + i])
        F += om * (W1 / x - W2 * q)
    return float(F)


@njit(cache=True)
def elastic_force(x: float, p: np.ndarray) -> tuple[float, float]:
    """F_el = Ω dΨ/dx [N] and its stiffness dF_el/dx [N/m] (eq 4)."""
    l1, l2, d1, d2, dd2, _ = kinematics(x, p)
    _, P1, P2, P11, P12, P22, _ = gentgent(l1, l2, p)
    om = volume(p)
    return om * (P1 * d1 + P2 * d2), om * (P11 * d1 * d1 + 2.0 * P12 * d1 * d2 + P22 * d2 * d2 + P2 * dd2)


@njit(cache=True)
def capacitance(x: float, p: np.ndarray) -> tuple[float, float, float]:
    """C(x) [F], dC/dx [F/m], d²C/dx² [F/m²] (eq 5)."""
    l = p[Q_L]
    xp = p[Q_XP]
    k = p[Q_EPS] * p[Q_L1P] * p[Q_L2P] / (2.0 * p[Q_T0] * xp * math.sqrt(4.0 * l * l - xp * xp))
    return (k * x * x * (4.0 * l * l - x * x), 4.0 * k * x * (2.0 * l * l - x * x),
            4.0 * k * (2.0 * l * l - 3.0 * x * x))


@njit(cache=True)
def electrostatic_force(x: float, V: float, p: np.ndarray) -> tuple[float, float]:
    """F_es = −½V² dC/dx [N] and dF_es/dx [N/m] (eq 6)."""
    _, dC, ddC = capacitance(x, p)
    return -0.5 * V * V * dC, -0.5 * V * V * ddC


@njit(cache=True)
def branch_energy_derivs(p1: float, p2: float, mu: float) -> tuple[float, float, float, float, float]:
    """Neo-Hookean branch W = (μ/2)(e1² + e2² + e3² − 3) in elastic log-stretches p_j = ln e_j.

    Returns (W_p1, W_p2, W_p1p1, W_p1p2, W_p2p2) [Pa]; ∂W/∂λj = W_pj/λj.
    """
    e1 = math.exp(2.0 * p1)
    e2 = math.exp(2.0 * p2)
    e3 = 1.0 / (e1 * e2)
    return (mu * (e1 - e3), mu * (e2 - e3), 2.0 * mu * (e1 + e3), 2.0 * mu * e3, 2.0 * mu * (e2 + e3))


@njit(cache=True)
def branch_flow(p1: float, p2: float, tau: float) -> tuple[float, float, float, float, float, float]:
    """Maxwell flow (thesis eq 60/61 with J → ∞): d ln ξ1/dt, d ln ξ2/dt [1/s] and their ∂/∂p1, ∂/∂p2."""
    e1 = math.exp(2.0 * p1)
    e2 = math.exp(2.0 * p2)
    e3 = 1.0 / (e1 * e2)
    k = 1.0 / (6.0 * tau)
    return (k * (2.0 * e1 - e2 - e3), k * (2.0 * e2 - e1 - e3),
            k * (4.0 * e1 + 2.0 * e3), k * (2.0 * e3 - 2.0 * e2),
            k * (2.0 * e3 - 2.0 * e1), k * (4.0 * e2 + 2.0 * e3))


@njit(cache=True)
def effective_mass(x: float, p: np.ndarray) -> tuple[float, float, float]:
    """m_eff(x) = m + α(x)M [kg] and its first two x-derivatives (physics.md §2.3).

    α = 9/32 + (5l²/24 + x²/32)/(4l² − x²) for four uniform pinned links (α' = (2/3)l²x/(4l²−x²)²),
    or α = 1/2 (the M/2 alternative).
    """
    M = p[Q_M]
    m = p[Q_MHUNG]
    if p[Q_ALPHA_HALF] > 0.5:
        return m + 0.5 * M, 0.0, 0.0
    l2 = p[Q_L] ** 2
    D = 4.0 * l2 - x * x
    alpha = 9.0 / 32.0 + (5.0 * l2 / 24.0 + x * x / 32.0) / D
    d1 = 2.0 / 3.0 * l2 * x / (D * D)
    d2 = 2.0 / 3.0 * l2 * (4.0 * l2 + 3.0 * x * x) / D**3
    return m + alpha * M, d1 * M, d2 * M


@njit(cache=True)
def lozenge_force(y: np.ndarray, x: float, v: float, V: float, p: np.ndarray, grad: np.ndarray) -> float:
    """Total force F = F_el + F_es + F_ve + c ẋ [N] at aperture x, speed v, voltage V, branch state in y.

    ``grad`` receives ∂F/∂x, ∂F/∂v and ∂F/∂a_k, ∂F/∂b_k (same layout as y).
    """
    K = int(p[Q_K])
    F, k = elastic_force(x, p)
    Fes, kes = electrostatic_force(x, V, p)
    F += Fes + p[Q_C] * v
    k += kes
    l1, l2, _, _, _, yy = kinematics(x, p)
    om = volume(p)
    q = x / (yy * yy)  # −(dλ2/dx)/λ2 ;  (dλ1/dx)/λ1 = 1/x
    dq = (yy * yy + 2.0 * x * x) / yy**4
    ll1 = math.log(l1)
    ll2 = math.log(l2)
    for i in range(K):
        mu = p[Q_BRANCHES + i]
        p1 = ll1 - y[2 + i]
        p2 = ll2 - y[2 + K + i]
        W1, W2, W11, W12, W22 = branch_energy_derivs(p1, p2, mu)
        F += om * (W1 / x - W2 * q)
        k += om * ((W11 / x - W12 * q) / x - W1 / (x * x) - (W12 / x - W22 * q) * q - W2 * dq)
        grad[2 + i] = om * (-W11 / x + W12 * q)
        grad[2 + K + i] = om * (-W12 / x + W22 * q)
    grad[0] = k
    grad[1] = p[Q_C]
    return float(F)


@njit(cache=True)
def lozenge_rhs(y: np.ndarray, V: float, x_in: float, v_in: float, p: np.ndarray, dy: np.ndarray,
                jac: np.ndarray, want_jac: bool) -> None:
    """dy/dt (and, if ``want_jac``, the analytic Jacobian) of the LS-DEA dynamics."""
    K = int(p[Q_K])
    hung = int(p[Q_MODE]) == MODE_HUNG
    if hung:
        x, v = y[0], y[1]
    else:
        x, v = x_in, v_in
    if want_jac:
        jac[:, :] = 0.0
    grad = np.empty(y.size)
    F = lozenge_force(y, x, v, V, p, grad)
    l1, l2, _, _, _, yy = kinematics(x, p)
    q = x / (yy * yy)
    ll1 = math.log(l1)
    ll2 = math.log(l2)
    for i in range(K):
        tau = p[Q_BRANCHES + K + i]
        p1 = ll1 - y[2 + i]
        p2 = ll2 - y[2 + K + i]
        fa, fb, fa1, fa2, fb1, fb2 = branch_flow(p1, p2, tau)
        dy[2 + i] = fa
        dy[2 + K + i] = fb
        if want_jac:
            jac[2 + i, 2 + i] = -fa1
            jac[2 + i, 2 + K + i] = -fa2
            jac[2 + K + i, 2 + i] = -fb1
            jac[2 + K + i, 2 + K + i] = -fb2
            if hung:
                jac[2 + i, 0] = fa1 / x - fa2 * q
                jac[2 + K + i, 0] = fb1 / x - fb2 * q
    if hung:
        me, dme, ddme = effective_mass(x, p)
        R = (p[Q_MHUNG] + 0.5 * p[Q_M]) * p[Q_G] - F - 0.5 * dme * v * v
        dy[0] = v
        dy[1] = R / me
        if want_jac:
            jac[0, 1] = 1.0
            jac[1, 0] = (-grad[0] - 0.5 * ddme * v * v) / me - R * dme / (me * me)
            jac[1, 1] = (-grad[1] - dme * v) / me
            for j in range(2, y.size):
                jac[1, j] = -grad[j] / me
    else:
        dy[0] = 0.0
        dy[1] = 0.0


@njit(cache=True)
def lozenge_step(y: np.ndarray, V: float, x_in: float, v_in: float, h: float, p: np.ndarray) -> bool:
    """Advance ``y`` in place by one fixed step h [s] with inputs at t_{n+1}.

    Branches: exponential Euler on the elastic log-stretches (linear part −p/τ exact, so any τ > 0 is
    stable). Hung mass: symplectic Euler. Imposed mode: x, ẋ are taken from the inputs first.
    Returns False outside the model's domain (Gent lock-up, mechanism singularity, non-finite).
    """
    K = int(p[Q_K])
    hung = int(p[Q_MODE]) == MODE_HUNG
    if not hung:
        y[0] = x_in
        y[1] = v_in
    x = y[0]
    v = y[1]
    if not 0.0 < x < 2.0 * p[Q_L]:
        return False
    l1, l2, d1, d2, _, yy = kinematics(x, p)
    ll1 = math.log(l1)
    ll2 = math.log(l2)
    for i in range(K):
        tau = p[Q_BRANCHES + K + i]
        p1 = ll1 - y[2 + i]
        p2 = ll2 - y[2 + K + i]
        fa, fb, _, _, _, _ = branch_flow(p1, p2, tau)
        decay = math.exp(-h / tau)
        p1n = p1 * decay - (1.0 - decay) * (tau * fa - p1)
        p2n = p2 * decay - (1.0 - decay) * (tau * fb - p2)
        y[2 + i] = ll1 - p1n
        y[2 + K + i] = ll2 - p2n
    P1, P2, G = gent_stress(l1, l2, p)
    if hung:
        _, dC, _ = capacitance(x, p)
        F = rig_force(y, x, v, V, p, d1, d2, yy, ll1, ll2, P1, P2, dC)  # lozenge_force's value, branches updated
        me, dme, _ = effective_mass(x, p)
        R = (p[Q_MHUNG] + 0.5 * p[Q_M]) * p[Q_G] - F - 0.5 * dme * v * v
        v = v + h * R / me
        x = x + h * v
        y[0] = x
        y[1] = v
    return G > 0.0 and math.isfinite(x) and math.isfinite(v)


@njit(cache=True, nogil=True)
def lozenge_observe(Y: np.ndarray, V: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """Per-sample observables of a state history Y (n×ny) at voltages V (n) into ``out`` (n×12).

    Columns: F, F_el, F_es, F_ve, C, E, E_B, σ1, σ2, λ1, λ2, G. Stresses are Cauchy stresses including the
    Maxwell stress, σj = λj ∂(Ψ + ΣW_k)/∂λj − εE² [Pa]; E = Vλ1λ2/t0 the true field, E_B = E0 λ3^(−r/2).
    """
    K = int(p[Q_K])
    grad = np.empty(Y.shape[1])
    for n in range(Y.shape[0]):
        x, v = Y[n, 0], Y[n, 1]
        F = lozenge_force(Y[n], x, v, V[n], p, grad)
        Fel, _ = elastic_force(x, p)
        Fes, _ = electrostatic_force(x, V[n], p)
        l1, l2, _, _, _, _ = kinematics(x, p)
        _, P1, P2, _, _, _, G = gentgent(l1, l2, p)
        s1 = l1 * P1
        s2 = l2 * P2
        for i in range(K):
            W1, W2, _, _, _ = branch_energy_derivs(math.log(l1) - Y[n, 2 + i], math.log(l2) - Y[n, 2 + K + i],
                                                   p[Q_BRANCHES + i])
            s1 += W1
            s2 += W2
        E = V[n] * l1 * l2 / p[Q_T0]
        maxwell = p[Q_EPS] * E * E
        C, _, _ = capacitance(x, p)
        out[n, 0] = F
        out[n, 1] = Fel
        out[n, 2] = Fes
        out[n, 3] = F - Fel - Fes - p[Q_C] * v
        out[n, 4] = C
        out[n, 5] = E
        out[n, 6] = p[Q_E0] * (l1 * l2) ** (0.5 * p[Q_R])  # λ3^(−r/2) = (λ1λ2)^(r/2)
        out[n, 7] = s1 - maxwell
        out[n, 8] = s2 - maxwell
        out[n, 9] = l1
        out[n, 10] = l2
        out[n, 11] = G


@njit(cache=True, nogil=True)
def lozenge_observe_rig(Y: np.ndarray, V: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """What a rig measures of a state history, into ``out`` (n×5): F, C, E, E_B, G — the columns of
    :func:`lozenge_observe` the simulated bench needs, each computed once per sample (no force split, stresses or
    stiffness). F follows :func:`lozenge_force` operation for operation, so the values are the same doubles."""
    for n in range(Y.shape[0]):
        x, v = Y[n, 0], Y[n, 1]
        l1, l2, d1, d2, _, yy = kinematics(x, p)
        P1, P2, G = gent_stress(l1, l2, p)
        C, dC, _ = capacitance(x, p)
        out[n, 0] = rig_force(Y[n], x, v, V[n], p, d1, d2, yy, math.log(l1), math.log(l2), P1, P2, dC)
        out[n, 1] = C
        out[n, 2] = V[n] * l1 * l2 / p[Q_T0]
        out[n, 3] = p[Q_E0] * (l1 * l2) ** (0.5 * p[Q_R])
        out[n, 4] = G


OBSERVABLES = ("force", "force_elastic", "force_electrostatic", "force_viscoelastic", "capacitance", "field",
               "breakdown_field", "stress1", "stress2", "stretch1", "stretch2", "gent_margin")
