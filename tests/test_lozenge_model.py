"""Model B (LS-DEA): forces as derivatives, Jacobian, and the reference checks of physics.md §4."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from bench.analysis.cycles import crest_to_trough, hysteresis_loss, last_cycles
from bench.models.integrate import MODEL_LOZENGE, OBSERVE_FORCE, run_fixed_batch
from bench.models.lozenge import (
    MODE_HUNG,
    MODE_IMPOSED,
    LozengeParams,
    MaxwellBranch,
    capacitance,
    elastic_force,
    electrostatic_force,
    gentgent,
    kinematics,
    lozenge_rhs,
    volume,
)
from bench.models.lozenge_batch import lozenge_batch
from bench.models.lozenge_runs import (
    LozengeStream,
    breakdown_voltage,
    isotonic_equilibrium,
    simulate_lozenge,
    static_force,
    static_stiffness,
)
from bench.waveforms import Waveform

PROTOS = {n: LozengeParams.prototype(n) for n in (1, 2, 3)}
X_MM = (50, 70, 90, 100, 120, 140)
F_EL = {1: (2.663, 5.085, 5.713, 5.921, 6.343, 6.818), 2: (2.057, 4.092, 4.418, 4.476, 4.577, 4.694),
        3: (1.455, 3.147, 3.206, 3.131, 2.955, 2.774)}
F_7KV = {1: (1.666, 3.817, 4.301, 4.497, 5.034, 5.842), 2: (1.012, 2.762, 2.938, 2.982, 3.204, 3.670),
         3: (0.363, 1.759, 1.659, 1.570, 1.521, 1.705)}


def psi_independent(l1: float, l2: float, mat: LozengeParams) -> float:
    """Gent–Gent energy written from eq 2 directly (λ3 from incompressibility)."""
    m = mat.material
    l3 = 1 / (l1 * l2)
    return (-(m.mu * m.Jm / 2) * math.log(1 - (l1**2 + l2**2 + l3**2 - 3) / m.Jm)
            + m.C2 * math.log((l1**-2 + l2**-2 + l3**-2) / 3))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_B1_elastic_and_7kV_force_tables(n: int) -> None:
    P = PROTOS[n]
    assert [static_force(P, x / 1e3) for x in X_MM] == pytest.approx(F_EL[n], rel=2e-3)
    assert [static_force(P, x / 1e3, 7000.0) for x in X_MM] == pytest.approx(F_7KV[n], rel=2e-3, abs=1e-3)


@pytest.mark.parametrize("n", [1, 3])
def test_B2_forces_are_derivatives_of_energy_and_capacitance(n: int) -> None:
    P = PROTOS[n]
    p = P.pack()
    om = volume(p)
    for x in (0.05, 0.08, 0.11, 0.14):
        d = 1e-7

        def energy(xx: float) -> float:
            l1, l2, *_ = kinematics(xx, p)
            return om * psi_independent(l1, l2, P)

        assert elastic_force(x, p)[0] == pytest.approx((energy(x + d) - energy(x - d)) / (2 * d), rel=1e-6)
        dC = (capacitance(x + d, p)[0] - capacitance(x - d, p)[0]) / (2 * d)
        assert electrostatic_force(x, 7000.0, p)[0] == pytest.approx(-0.5 * 7000.0**2 * dC, rel=1e-6)
        # Hessian/stiffness and dF_es/dx against differences of the forces
        k_num = (elastic_force(x + d, p)[0] - elastic_force(x - d, p)[0]) / (2 * d)
        assert elastic_force(x, p)[1] == pytest.approx(k_num, rel=1e-5)
        kes = (electrostatic_force(x + d, 5e3, p)[0] - electrostatic_force(x - d, 5e3, p)[0]) / (2 * d)
        assert electrostatic_force(x, 5e3, p)[1] == pytest.approx(kes, rel=1e-5)


def test_gentgent_gradient_and_hessian() -> None:
    p = PROTOS[2].pack()
    for l1, l2 in [(0.8, 2.4), (1.5, 2.1), (2.2, 1.9)]:
        d = 1e-6
        psi, P1, P2, P11, P12, P22, _ = gentgent(l1, l2, p)
        assert psi == pytest.approx(psi_independent(l1, l2, PROTOS[2]), rel=1e-12)
        g = lambda a, b: np.array(gentgent(a, b, p)[1:3])  # noqa: E731
        assert P1 == pytest.approx((gentgent(l1 + d, l2, p)[0] - gentgent(l1 - d, l2, p)[0]) / (2 * d), rel=1e-6)
        assert P2 == pytest.approx((gentgent(l1, l2 + d, p)[0] - gentgent(l1, l2 - d, p)[0]) / (2 * d), rel=1e-6)
        h1 = (g(l1 + d, l2) - g(l1 - d, l2)) / (2 * d)
        h2 = (g(l1, l2 + d) - g(l1, l2 - d)) / (2 * d)
        assert [P11, P12] == pytest.approx(h1, rel=1e-5)
        assert [P12, P22] == pytest.approx(h2, rel=1e-5)


@pytest.mark.parametrize("mode", [MODE_HUNG, MODE_IMPOSED])
def test_analytic_jacobian_matches_finite_differences(mode: int) -> None:
    P = LozengeParams(branches=(*LozengeParams().branches, *LozengeParams().branches[:1]), hung_mass=0.15)
    p = P.pack(mode)
    y = P.relaxed_state(0.075, 0.05)
    y[2:] += np.array([0.05, -0.03, 0.02, 0.04])  # unrelaxed branches
    ny = y.size
    J = np.empty((ny, ny))
    lozenge_rhs(y, 4000.0, 0.08, 0.02, p, np.empty(ny), J, True)
    num = np.empty_like(J)
    for j in range(ny):
        d = 1e-7
        yp, ym = y.copy(), y.copy()
        yp[j] += d
        ym[j] -= d
        fp, fm = np.empty(ny), np.empty(ny)
        lozenge_rhs(yp, 4000.0, 0.08, 0.02, p, fp, J.copy(), False)
        lozenge_rhs(ym, 4000.0, 0.08, 0.02, p, fm, J.copy(), False)
        num[:, j] = (fp - fm) / (2 * d)
    assert np.allclose(J, num, rtol=1e-5, atol=1e-6 * np.abs(num).max())


def test_M1_M2_masses_and_loads() -> None:
    assert [PROTOS[n].membrane_mass * 1e3 for n in (1, 2, 3)] == pytest.approx([0.778, 0.742, 0.710], abs=1e-3)
    loads = [LozengeParams(hung_mass=m).load for m in (0.0, 0.15, 0.18)]
    assert loads == pytest.approx([3.090, 4.562, 4.856], abs=1e-3)


def test_B3_max_electrostatic_force() -> None:
    x_star = 0.120 * math.sqrt(2 / 3)
    assert x_star * 1e3 == pytest.approx(97.98, abs=0.01)
    for n, expected in zip((1, 2, 3), (1.426, 1.495, 1.562), strict=True):
        p = PROTOS[n].pack()
        assert -electrostatic_force(x_star, 7000.0, p)[0] == pytest.approx(expected, rel=2e-3)
        grid = np.linspace(0.05, 0.14, 901)
        assert grid[np.argmax([-electrostatic_force(x, 7000.0, p)[0] for x in grid])] == pytest.approx(x_star, abs=1e-4)


def test_B4_stiffness_sign() -> None:
    grid = np.linspace(0.05, 0.14, 181)
    k = {n: np.array([static_stiffness(PROTOS[n], x) for x in grid]) for n in (1, 2, 3)}
    assert np.all(k[1] > 0) and k[1].min() == pytest.approx(20.3, rel=0.03)
    assert np.all(k[2] > 0) and k[2].min() == pytest.approx(4.9, rel=0.03)
    crossing = grid[np.argmax(k[3] < 0)]
    assert crossing * 1e3 == pytest.approx(81.0, abs=1.0)
    assert np.all(k[3][grid > crossing] < 0)
    assert k[3].min() == pytest.approx(-9.6, rel=0.03)


def test_breakdown_voltage_range() -> None:
    for n, (v50, v140) in zip((1, 2, 3), ((14.35, 8.87), (13.96, 8.63), (13.62, 8.42)), strict=True):
        assert breakdown_voltage(PROTOS[n], 0.05) / 1e3 == pytest.approx(v50, abs=0.01)
        assert breakdown_voltage(PROTOS[n], 0.14) / 1e3 == pytest.approx(v140, abs=0.01)


def test_tension_loss_only_near_mounting_state() -> None:
    P = PROTOS[1]
    tr = simulate_lozenge(P, "blocked", lambda t: np.full_like(t, 7000.0), 0.01, fs=1000.0, position=0.0414)
    assert tr.tension_lost.all()
    tr = simulate_lozenge(P, "blocked", lambda t: np.full_like(t, 7000.0), 0.01, fs=1000.0, position=0.0416)
    assert not tr.tension_lost.any()


def test_B6_isotonic_statics() -> None:
    for m, x0, x5 in ((0.0, 51.85, 54.74), (0.15, 62.24, 73.04), (0.18, 66.04, 83.52)):
        P = LozengeParams(hung_mass=m)
        assert isotonic_equilibrium(P, 0.0) * 1e3 == pytest.approx(x0, abs=0.1)
        assert isotonic_equilibrium(P, 5000.0) * 1e3 == pytest.approx(x5, abs=0.1)
    assert isotonic_equilibrium(LozengeParams.prototype(3, hung_mass=0.18), x_max=0.168) is None


LOSSES = {1: (24.3, 25.3, 27.3, 30.9), 2: (30.5, 32.2, 35.8, 42.9), 3: (40.9, 44.3, 52.0, 70.4)}
PAPER_LOSSES = {1: (23.3, 24.4, 26.0, 29.5), 2: (31.9, 33.5, 37.1, 43.3)}


def isopotential_loss(P: LozengeParams, V: float, method: str = "fixed") -> float:
    w = math.pi  # 0.5 Hz

    tr = simulate_lozenge(P, "imposed", lambda t: np.full_like(t, V), 20.0, fs=1000.0,
                          position=lambda t: 0.095 - 0.045 * np.cos(w * t),
                          velocity=lambda t: 0.045 * w * np.sin(w * t), method=method)  # type: ignore[arg-type]
    m = last_cycles(tr.t, 0.5, 1)
    return 100 * hysteresis_loss(tr.position[m], tr.force[m])


@pytest.mark.parametrize("n", [1, 2, 3])
def test_B7_isopotential_losses(n: int) -> None:
    losses = [isopotential_loss(PROTOS[n], V) for V in (0.0, 3000.0, 5000.0, 7000.0)]
    assert losses == pytest.approx(LOSSES[n], abs=1.0)
    assert np.all(np.diff(losses) > 0)  # loss grows with voltage
    if n in PAPER_LOSSES:
        assert losses == pytest.approx(PAPER_LOSSES[n], abs=3.0)


def test_isopotential_offline_and_streaming_agree() -> None:
    assert isopotential_loss(PROTOS[2], 5000.0, "radau") == pytest.approx(isopotential_loss(PROTOS[2], 5000.0), abs=0.1)


def isotonic_amplitude(m: float, f: float, method: str = "fixed", h: float = 1e-4, reference: bool = True) -> float:
    """Crest-to-trough of the last 3 of 15 cycles [mm].

    ``reference``: detrended the way physics.md's B8 table evidently was (a least-squares line through the
    window, which tilts a periodic signal that does not start at a crest; see the test below); otherwise as the
    bench's analysis does (drift fitted jointly with the harmonics of f).
    """
    tr = simulate_lozenge(LozengeParams(hung_mass=m), "hung", Waveform("raised_cosine", 5000.0, f), 15 / f,
                          fs=2000.0, method=method, h=h)  # type: ignore[arg-type]
    mask = last_cycles(tr.t, f, 3)
    t, x = tr.t[mask], tr.position[mask]
    if reference:
        return float(np.ptp(x - np.polyval(np.polyfit(t - t[0], x, 1), t - t[0]))) * 1e3
    return crest_to_trough(t, x, f) * 1e3


def test_B8_isotonic_amplitudes_at_1Hz() -> None:
    amps = [isotonic_amplitude(m, 1.0) for m in (0.0, 0.15, 0.18)]
    assert amps == pytest.approx([1.64, 4.56, 6.69], rel=0.10)
    assert np.all(np.diff(amps) > 0)  # M12: amplitude grows with the hung mass


@pytest.mark.parametrize("m, f_peak, a_peak", [(0.18, 2.75, 22.5), (0.15, 3.5, 18.8)])
def test_B8_isotonic_resonance(m: float, f_peak: float, a_peak: float) -> None:
    freqs = np.arange(2.25, 4.01, 0.25)
    amps = [isotonic_amplitude(m, f) for f in freqs]
    assert freqs[int(np.argmax(amps))] == pytest.approx(f_peak, abs=0.25)
    assert max(amps) == pytest.approx(a_peak, rel=0.10)


def test_B8_peak_amplitude_without_the_line_fit_artefact() -> None:
    # the bench's detrend agrees with the per-cycle crest-to-trough (19.1–19.6 mm over the last 3 cycles); the
    # reference procedure reads about 14 % higher at the 180-g resonance because the line tilts the window
    bench = isotonic_amplitude(0.18, 2.75, reference=False)
    assert bench == pytest.approx(19.5, abs=0.3)
    assert isotonic_amplitude(0.18, 2.75) / bench == pytest.approx(1.14, abs=0.03)


def test_B8_no_load_stays_small() -> None:
    assert max(isotonic_amplitude(0.0, f) for f in (0.5, 1.0, 2.0, 3.0, 4.0)) < 4.0


def test_isometric_force_variation_independent_of_frequency() -> None:
    P = PROTOS[3]
    swings = []
    for f in (1.0, 10.0):
        tr = simulate_lozenge(P, "blocked", Waveform("sine", 6000.0, f), 3 / f, fs=2000.0, position=0.100)
        m = last_cycles(tr.t, f, 1)
        swings.append(crest_to_trough(tr.t[m], tr.force[m]))
    assert swings == pytest.approx([1.147, 1.147], rel=5e-3)


def test_zero_voltage_rest() -> None:
    P = LozengeParams(hung_mass=0.15)
    tr = simulate_lozenge(P, "hung", lambda t: np.zeros_like(t), 5.0, fs=100.0)
    x0 = isotonic_equilibrium(P)
    assert np.max(np.abs(tr.position - x0)) < 1e-9
    blocked = simulate_lozenge(P, "blocked", lambda t: np.zeros_like(t), 5.0, fs=100.0, position=0.09)
    assert np.allclose(blocked.force, static_force(P, 0.09), rtol=0, atol=1e-12)


def test_isotonic_streaming_converges_to_offline() -> None:
    P, wave = LozengeParams(hung_mass=0.18), Waveform("raised_cosine", 5000.0, 2.0)
    ref = simulate_lozenge(P, "hung", wave, 5.0, fs=1000.0, method="radau", rtol=1e-9).position
    errors = [np.max(np.abs(simulate_lozenge(P, "hung", wave, 5.0, fs=1000.0, h=h).position - ref))
              for h in (1e-4, 5e-5)]
    assert errors[0] < 1e-4  # m: below 0.1 mm at the rig's 10-kHz step
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.25)


def test_stream_matches_fixed_run_and_reports_force() -> None:
    P = LozengeParams(hung_mass=0.18)
    wave = Waveform("raised_cosine", 5000.0, 2.0)
    s = LozengeStream(P, "hung")
    for k in range(1, 10_001):
        s.step(wave.scalar(k * 1e-4))
    tr = simulate_lozenge(P, "hung", wave, 1.0, fs=10_000.0)
    assert s.position == tr.position[-1]
    assert s.force(wave.scalar(1.0)) == pytest.approx(tr.force[-1], rel=1e-12)
    with pytest.raises(ValueError, match="start position"):
        LozengeStream(P, "blocked")


@pytest.mark.parametrize("config", ["imposed", "hung"])
def test_the_rig_observation_is_the_full_observation(config: str) -> None:
    # The simulated bench reads force, capacitance, charge, field and breakdown field through a lighter observer;
    # it must give the same doubles as the full one (whose forces the tests above pin to physics.md), and the
    # same failure: here the ±6-kV 10-Hz isometric drive, then twice the breakdown voltage at 100 mm.
    P = PROTOS[3] if config == "imposed" else LozengeParams(hung_mass=0.18)
    x0 = 0.1 if config == "imposed" else None
    full, rig = LozengeStream(P, config, x0), LozengeStream(P, config, x0)  # type: ignore[arg-type]
    k = np.arange(1, 2501)
    U = np.zeros((k.size, 3))
    U[:, 1] = full.position
    for V in (6000.0 * np.sin(2 * np.pi * 10.0 * k * 1e-4), np.full(k.size, 2 * breakdown_voltage(P, 0.1))):
        U[:, 0] = V
        a, b = full.advance(U), rig.advance_rig(U)
        for name in ("position", "force", "capacitance", "charge", "field", "breakdown_field"):
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
        assert (b.failed, b.failure) == (a.failed, a.failure)
    assert b.failed and "above breakdown" in b.failure


def test_invalid_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="prototype"):
        LozengeParams.prototype(4)
    with pytest.raises(ValueError, match="xp"):
        LozengeParams(xp=0.3)
    with pytest.raises(ValueError, match="constant position"):
        simulate_lozenge(PROTOS[1], "blocked", lambda t: t, 1.0)


@pytest.mark.parametrize("mode", [MODE_IMPOSED, MODE_HUNG])
def test_vectorised_batch_equals_the_scalar_kernel(mode: int) -> None:
    """The LS-DEA batch kernel (candidates as SIMD lanes, its own exp/log) gives the scalar kernel's outputs
    to rounding in both modes, and NaN where a set leaves the domain (a Gent limit reached on the way)."""
    base = LozengeParams.prototype(2, hung_mass=0.15 if mode == MODE_HUNG else 0.0)
    rng = np.random.default_rng(5)
    sets = [replace(base, damping=rng.uniform(0.5, 3.0),
                    branches=tuple(MaxwellBranch(10 ** rng.uniform(3, 6), 10 ** rng.uniform(-2, 2)) for _ in range(2)))
            for _ in range(11)]
    sets.append(replace(sets[0], material=replace(base.material, Jm=6.0)))  # locks up at the larger apertures
    P = np.stack([s.pack(mode) for s in sets])
    n, h = 8000, 1e-4
    t = np.arange(1, n + 1) * h
    U = np.zeros((n, 3))
    U[:, 0] = 5000.0 * (t % 0.2 < 0.1)  # 5-Hz square voltage
    U[:, 1] = base.xp + 0.03 * np.sin(2 * np.pi * 2.0 * t)  # imposed aperture (hung: unused)
    U[:, 2] = 0.06 * np.pi * np.cos(2 * np.pi * 2.0 * t)
    Y0 = np.stack([s.relaxed_state(base.xp) for s in sets])
    channel = OBSERVE_FORCE if mode == MODE_IMPOSED else 0
    # window 0 given, not left to its default: the same int argument the fits pass, so the parallel reference
    # kernel compiled (cold cache: a CI clone) for them serves here too instead of a second, literal-0 compile
    ref = run_fixed_batch(MODEL_LOZENGE, Y0, U, h, P, channel, 10, 0)
    out = lozenge_batch(P, Y0, U, h, channel, 10)
    assert np.isfinite(ref[:-1]).all()
    assert np.isnan(ref[-1, -1]) == (mode == MODE_IMPOSED)  # the imposed stroke reaches the Gent limit
    assert np.array_equal(np.isnan(out), np.isnan(ref))
    np.testing.assert_allclose(out, ref, rtol=1e-10, atol=1e-12)
