"""Gent spring of the equibiaxial membrane in log-stretch form (physics.md §1.2, §1.5).

A Gent unit sees the elastic stretch ``e = λ/ξ`` (ξ = 1 for the equilibrium spring). With ``u = ln e``:

    g(u)  = e^{2u} − e^{−4u}
    G(u)  = 1 − (2e^{2u} + e^{−4u} − 3)/J          (Gent lock-up when G → 0)
    h(u)  = g/G,   h'(u) = g'/G + 4g²/(J G²)         (G' = −4g/J)

so that the unit's nominal stress is ``s = μ h(u)/λ`` (= μ(λξ⁻² − λ⁻⁵ξ⁴)/G, physics.md §1.2) and its
Maxwell flow rule is ``d ln ξ/dt = (μ/6η) h(u)`` (corrected thesis eq 60/65). Every use of the Gent unit in
the membrane model (stress, flow, Jacobian, streaming step) goes through this one function.
"""

from __future__ import annotations

import math

from bench.models.jit import njit


@njit(cache=True)
def gent_h_G(e2: float, J: float) -> tuple[float, float]:
    """(h, G) of a Gent unit with limit J, given e2 = e^{2u}, without dh/du (:func:`gent_h_e2` adds it): what a
    fixed step needs."""
    e4 = 1.0 / (e2 * e2)
    g = e2 - e4
    G = 1.0 - (2.0 * e2 + e4 - 3.0) / J
    return g / G, G


@njit(cache=True)
def gent_h_e2(e2: float, J: float) -> tuple[float, float, float]:
    """(h, dh/du, G) of a Gent unit with limit J, given e2 = e^{2u} = (elastic stretch)²."""
    h, G = gent_h_G(e2, J)
    e4 = 1.0 / (e2 * e2)  # e^{−4u}
    g = e2 - e4
    dh = (2.0 * e2 + 4.0 * e4) / G + 4.0 * g * g / (J * G * G)
    return h, dh, G


@njit(cache=True)
def gent_h(u: float, J: float) -> tuple[float, float, float]:
    """Return (h, dh/du, G) of a Gent unit with limit J at elastic log-stretch u [-]."""
    return gent_h_e2(math.exp(2.0 * u), J)


@njit(cache=True)
def relaxation_rate(u: float, h: float, mu: float, eta: float) -> float:
    """Rate r [1/s] with du/dt = −r·u at fixed λ (r → μ/η as u → 0), from the unit's h(u)."""
    if abs(u) < 1e-9:
        return mu / eta  # h/u → 6/G(0) = 6 as u → 0
    return mu / (6.0 * eta) * h / u

