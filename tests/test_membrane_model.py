"""Model A (thesis membrane): energies ↔ stresses, Jacobian, reference numbers of physics.md §4."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from bench.analysis.thesis import cycle_figures
from bench.models.gent import gent_h
from bench.models.membrane import (
    MembraneParams,
    capacitance,
    es_stress,
    failure_reason,
    membrane_jac,
    membrane_rhs,
)
from bench.models.membrane_runs import MembraneStream, batch_stretch, simulate_membrane
from bench.waveforms import Waveform

PARAMS = MembraneParams()
P = PARAMS.pack()
BASE = Waveform("raised_cosine", 7000.0, 1 / 9)


def gent_energy(lam: float, xi: float, mu: float, J: float) -> float:
    """Per-volume energy of a Gent unit, written independently of the kernels (physics.md §1.2)."""
    inv = 2 * lam**2 / xi**2 + xi**4 / lam**4 - 3
    return -(mu * J / 2) * math.log(1 - inv / J)


def kernel_stress(lam: float, xi: float, mu: float, J: float) -> float:
    h, _, _ = gent_h(math.log(lam / xi), J)
    return mu * h / lam


@pytest.mark.parametrize("lam, xi", [(2.0, 2.0), (2.3, 2.0), (1.7, 2.1), (3.0, 2.2), (2.05, 1.95)])
def test_branch_stress_is_half_derivative_of_energy(lam: float, xi: float) -> None:
    for mu, J in [(PARAMS.mu0, PARAMS.J0), *zip(PARAMS.mu, PARAMS.J, strict=True)]:
        d = 1e-6
        numeric = 0.5 * (gent_energy(lam + d, xi, mu, J) - gent_energy(lam - d, xi, mu, J)) / (2 * d)
        assert kernel_stress(lam, xi, mu, J) == pytest.approx(numeric, rel=1e-6)


def test_equilibrium_spring_matches_closed_form() -> None:
    lam = 2.2
    G0 = 1 - (2 * lam**2 + lam**-4 - 3) / PARAMS.J0
    expected = PARAMS.mu0 * (lam - lam**-5) / G0
    assert kernel_stress(lam, 1.0, PARAMS.mu0, PARAMS.J0) == pytest.approx(expected, rel=1e-12)


def test_flow_rule_dissipates_and_relaxes_towards_lambda() -> None:
    """ξ̇ has the sign of λ − ξ (the unit relaxes), so −∂W/∂ξ·ξ̇ ≥ 0."""
    y = PARAMS.initial_state()
    for lam in (1.8, 2.0, 2.4):
        y[0] = lam
        y[2:] = 2.0
        dy = np.empty_like(y)
        membrane_rhs(y, 0.0, 296.0, P, dy)
        assert np.all(np.sign(dy[2:]) == np.sign(lam - 2.0))
        # small-strain limit: ξ̇ ≈ (λ − ξ)/τ · ξ/λ-ish; check the rate order of magnitude of τ_i
        if lam != 2.0:
            rates = dy[2:] / (lam - 2.0)
            assert np.all(rates > 0)


def test_electrostatic_stress_is_derivative_of_capacitance() -> None:
    """Corrected s_es = (Φ²/(4L²L3)) dC/dλ; the thesis form has the aλ⁵ term 4× larger."""
    lam, phi, T, d = 2.2, 6500.0, 296.0, 1e-6
    dC_num = (capacitance(lam + d, T, P)[0] - capacitance(lam - d, T, P)[0]) / (2 * d)
    assert capacitance(lam, T, P)[1] == pytest.approx(dC_num, rel=1e-7)
    s, ds = es_stress(lam, phi, T, P)
    assert s == pytest.approx(phi**2 / (4 * PARAMS.L**2 * PARAMS.L3) * dC_num, rel=1e-7)
    ds_num = (es_stress(lam + d, phi, T, P)[0] - es_stress(lam - d, phi, T, P)[0]) / (2 * d)
    assert ds == pytest.approx(ds_num, rel=1e-6)
    thesis = es_stress(lam, phi, T, MembraneParams(electrostriction="thesis").pack())[0]
    er = PARAMS.a * lam**2 + PARAMS.b / T + PARAMS.c
    pre = PARAMS.eps_vac * (phi / PARAMS.L3) ** 2
    assert thesis - s == pytest.approx(pre * 1.5 * PARAMS.a * lam**5, rel=1e-9)
    assert s == pytest.approx(pre * (er * lam**3 + 0.5 * PARAMS.a * lam**5), rel=1e-12)


def test_analytic_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(1)
    for _ in range(5):
        y = np.array([2.2, 0.3, *rng.uniform(1.9, 2.3, PARAMS.n_units)])
        J = np.empty((y.size, y.size))
        membrane_jac(y, 6000.0, 280.0, P, J)
        num = np.empty_like(J)
        for j in range(y.size):
            d = 1e-7 * max(1.0, abs(y[j]))
            yp, ym = y.copy(), y.copy()
            yp[j] += d
            ym[j] -= d
            fp, fm = np.empty_like(y), np.empty_like(y)
            membrane_rhs(yp, 6000.0, 280.0, P, fp)
            membrane_rhs(ym, 6000.0, 280.0, P, fm)
            num[:, j] = (fp - fm) / (2 * d)
        scale = np.maximum(np.abs(num), 1e-6 * np.abs(num).max())
        assert np.max(np.abs(J - num) / scale) < 1e-4


def test_A1_dead_load() -> None:
    assert pytest.approx(130.731e3, rel=5e-4) == PARAMS.s_pre
    assert pytest.approx(3.922, rel=5e-4) == PARAMS.edge_load
    assert PARAMS.tau == pytest.approx((0.089513, 4.9967, 1.0e-5, 0.067572), rel=1e-4)


def test_A2_small_signal_modes() -> None:
    J = np.empty((6, 6))
    membrane_jac(PARAMS.initial_state(), 0.0, 296.0, P, J)
    ev = np.linalg.eigvals(J)
    osc = ev[np.abs(ev.imag) > 1][0]
    freq = abs(osc.imag) / (2 * math.pi)
    zeta = -osc.real / abs(osc)
    assert freq == pytest.approx(281.9, rel=0.01)
    assert zeta == pytest.approx(0.0108, rel=0.15)
    real = np.sort(ev[np.abs(ev.imag) <= 1].real)
    assert real == pytest.approx([-1.000e5, -12.06, -1.904, -0.1189], rel=0.01)


@pytest.fixture(scope="module")
def base_case() -> object:
    return simulate_membrane(PARAMS, BASE, 20.0, fs=10_000.0, rtol=1e-7)


def test_A4_base_case(base_case: object) -> None:
    tr = base_case
    lam = tr.stretch

    def at(t: float) -> float:
        return float(lam[round(t * 10_000)])

    assert at(4.5) == pytest.approx(2.2276, abs=2e-4)
    assert at(9.0) == pytest.approx(2.0367, abs=2e-4)
    assert at(18.0) == pytest.approx(2.0497, abs=2e-4)
    assert at(20.0) == pytest.approx(2.0543, abs=2e-4)
    i1 = int(np.argmax(lam[:90_000]))
    i2 = 90_000 + int(np.argmax(lam[90_000:]))
    assert lam[i1] == pytest.approx(2.2559, abs=2e-4)
    assert tr.t[i1] == pytest.approx(5.12, abs=0.02)
    assert lam[i2] == pytest.approx(2.2852, abs=2e-4)
    assert tr.t[i2] == pytest.approx(14.10, abs=0.02)
    assert not tr.failed


def test_T5_creep_and_lag(base_case: object) -> None:
    tr = base_case
    figs = cycle_figures(tr.t, tr.displacement, tr.voltage, 1 / 9)
    assert figs.peaks[0] * 1e3 == pytest.approx(7.68, abs=0.02)
    assert figs.peaks[1] * 1e3 == pytest.approx(8.56, abs=0.02)
    assert figs.creep == pytest.approx(0.115, abs=0.005)
    assert figs.residuals[0] * 1e3 == pytest.approx(1.10, abs=0.01)
    assert figs.residuals[1] * 1e3 == pytest.approx(1.49, abs=0.01)
    assert figs.lags[0] == pytest.approx(0.62, abs=0.02)


def test_observables_are_consistent(base_case: object) -> None:
    tr = base_case
    assert np.allclose(tr.field, tr.voltage * tr.stretch**2 / PARAMS.L3)
    # I = dQ/dt: compare with a numerical derivative of the charge
    dq = np.gradient(tr.charge, tr.t)
    assert np.allclose(tr.current[10:-10], dq[10:-10], rtol=1e-3, atol=1e-3 * np.abs(dq).max())
    assert np.max(np.abs(tr.field)) / 1e6 == pytest.approx(36.0, abs=0.5)  # physics.md §1.4: 36 MV/m at 7 kV


SWEEPS = {
    "voltage": ([5000.0, 6000.0, 7000.0, 8000.0], [3.37, 5.38, 8.56, 14.62], +1),
    "frequency": ([1 / 3, 1 / 6, 1 / 9, 1 / 12], [6.51, 7.87, 8.56, 9.24], +1),
    "temperature": ([266.0, 296.0, 306.0, 316.0], [9.19, 8.56, 8.38, 8.22], -1),
}


@pytest.mark.parametrize("sweep", list(SWEEPS))
def test_A5_sweeps_and_thesis_trends(sweep: str) -> None:
    values, expected, direction = SWEEPS[sweep]
    peaks = []
    for v in values:
        wave = Waveform("raised_cosine", v if sweep == "voltage" else 7000.0,
                        v if sweep == "frequency" else 1 / 9)
        T = v if sweep == "temperature" else 296.0
        tr = simulate_membrane(PARAMS, wave, 20.0, fs=1000.0, T=T)
        peaks.append(tr.peak_displacement() * 1e3)
    assert peaks == pytest.approx(expected, rel=0.02)
    # thesis trends: grows with V, grows as f falls (values listed in falling f), falls as T rises
    assert np.all(direction * np.diff(peaks) > 0)


def test_thesis_electrostriction_option_is_13_percent_larger() -> None:
    tr = simulate_membrane(MembraneParams(electrostriction="thesis"), BASE, 20.0, fs=1000.0)
    assert tr.peak_displacement() * 1e3 == pytest.approx(9.64, rel=0.01)


@pytest.mark.parametrize("kind, expected", [("triangle", 7.07), ("sine", 8.69)])
def test_waveform_variants(kind: str, expected: float) -> None:
    tr = simulate_membrane(PARAMS, Waveform(kind, 7000.0, 1 / 9), 20.0, fs=1000.0)  # type: ignore[arg-type]
    assert tr.peak_displacement() * 1e3 == pytest.approx(expected, rel=0.01)


def test_A8_streaming_matches_offline_with_first_order_convergence() -> None:
    ref = simulate_membrane(PARAMS, BASE, 20.0, fs=1000.0, rtol=1e-8)
    errors = []
    for h in (1e-4, 5e-5):
        fixed = simulate_membrane(PARAMS, BASE, 20.0, fs=1000.0, method="fixed", h=h)
        errors.append(float(np.max(np.abs(fixed.stretch - ref.stretch))))
    assert errors[0] < 1e-4
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.25)


def test_A9_zero_voltage_rest() -> None:
    zero = Waveform("raised_cosine", 0.0, 1 / 9)
    for method in ("radau", "fixed"):
        tr = simulate_membrane(PARAMS, zero, 20.0, fs=100.0, method=method)  # type: ignore[arg-type]
        assert np.max(np.abs(tr.stretch - 2.0)) < 1e-9
        assert np.max(np.abs(tr.current)) == 0.0


def test_dc_hold_above_7_14_kV_creeps_into_pull_in() -> None:
    """physics.md §1.4: no relaxed equilibrium above 7.14 kV; DC 8 kV reaches λ = 10 at ≈ 7.3 s."""
    dc = Waveform("square", 0.0, 1.0, offset=8000.0)
    tr = simulate_membrane(PARAMS, dc, 20.0, fs=1000.0)
    assert tr.failed and "runaway" in tr.failure
    # the run stops when λ passes runaway_stretch (4), before the λ = 10 time of physics.md
    assert np.isnan(tr.stretch[-1])
    t_fail = float(tr.failure.split("t = ")[1].split(" s")[0])
    assert 1.0 < t_fail < 7.3
    fixed = simulate_membrane(PARAMS, dc, 20.0, fs=1000.0, method="fixed")
    assert fixed.failed and "runaway" in fixed.failure
    # just below the limit the membrane settles
    ok = simulate_membrane(PARAMS, Waveform("square", 0.0, 1.0, offset=6500.0), 20.0, fs=100.0)
    assert not ok.failed


def test_breakdown_field_is_flagged() -> None:
    tr = simulate_membrane(MembraneParams(breakdown_field=30e6), BASE, 20.0, fs=100.0)
    assert tr.failed and "breakdown" in tr.failure


def test_streaming_step_equals_block_and_fixed_run() -> None:
    phi = BASE(np.arange(1, 20_001) * 1e-4)
    a = MembraneStream(PARAMS)
    for v in phi:
        a.step(float(v))
    b = MembraneStream(PARAMS)
    trace = b.advance(phi)
    assert np.array_equal(a.state, b.state)
    assert trace.stretch[-1] == a.stretch
    assert a.t == pytest.approx(2.0)
    assert a.displacement == pytest.approx(PARAMS.L_d * (a.stretch - 2.0))
    fixed = simulate_membrane(PARAMS, BASE, 2.0, fs=10_000.0, method="fixed")
    assert fixed.stretch[-1] == a.stretch


def test_batch_equals_individual_runs() -> None:
    sets = [PARAMS, PARAMS.with_units(70e3, 300.0, PARAMS.mu, PARAMS.J, PARAMS.eta),
            PARAMS.with_units(PARAMS.mu0, PARAMS.J0, (1e5, 3e4, 5e5, 4e5), PARAMS.J, (1e4, 1e5, 5.0, 2e4))]
    phi = BASE(np.arange(1, 50_001) * 1e-4)
    out = batch_stretch(sets, phi, 296.0, stride=10)
    for k, ps in enumerate(sets):
        s = MembraneStream(ps)
        tr = s.advance(phi)
        # the batched kernel vectorises over the sets with its own exp/log: equal to rounding
        np.testing.assert_allclose(out[k, 1:], tr.stretch[9::10], rtol=0, atol=1e-11)
    assert out.shape == (3, 5001)


def test_invalid_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="one entry per Maxwell unit"):
        MembraneParams(mu=(1.0, 2.0))
    with pytest.raises(ValueError, match="electrostriction"):
        MembraneParams(electrostriction="other")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="L3"):
        MembraneParams(L3=0.0)


def test_cycle_figures_ignore_a_partial_cycle_before_its_peak() -> None:
    t = np.linspace(0.0, 20.0, 20001)
    wave = Waveform("raised_cosine", 1.0, 1 / 9)
    u = wave(t) + 0.1 * t / 20  # slow drift: the second peak is higher
    figs = cycle_figures(t, u, wave(t), 1 / 9)
    assert figs.whole == 2 and len(figs.peaks) == 2  # 18–20 s is 22 % of a period: not a cycle
    assert figs.creep == pytest.approx((1 + 0.1 * 13.5 / 20) / (1 + 0.1 * 4.5 / 20) - 1, rel=1e-3)


def test_compiled_offline_integrator_matches_a_tight_reference() -> None:
    """Rodas3 (default of simulate_membrane) within 1e-6 in λ of Radau at rtol 1e-10 on the base case (A8-style),
    converging as rtol falls, and stopping a DC pull-in where Radau's event does."""
    ref = simulate_membrane(PARAMS, BASE, 20.0, fs=10_000.0, method="radau", rtol=1e-10)
    errors = [np.max(np.abs(simulate_membrane(PARAMS, BASE, 20.0, fs=10_000.0, rtol=r).stretch - ref.stretch))
              for r in (3e-6, 3e-7, 3e-8)]
    assert simulate_membrane(PARAMS, BASE, 20.0, fs=10_000.0).stretch[-1] == pytest.approx(ref.stretch[-1], abs=1e-6)
    assert errors[1] <= 1e-6
    assert errors[0] > errors[1] > errors[2]
    dc = Waveform("square", 0.0, 1.0, offset=8000.0)
    a = simulate_membrane(PARAMS, dc, 20.0, fs=1000.0)
    b = simulate_membrane(PARAMS, dc, 20.0, fs=1000.0, method="radau", rtol=1e-8)
    assert a.failed and b.failed and "runaway" in a.failure
    t_a = float(re.search(r"t = ([\d.]+) s", a.failure).group(1))  # type: ignore[union-attr]
    t_b = float(re.search(r"t = ([\d.]+) s", b.failure).group(1))  # type: ignore[union-attr]
    assert t_a == pytest.approx(t_b, abs=0.01)
    ok = np.isfinite(a.stretch) & np.isfinite(b.stretch) & (b.stretch < 3.0)  # before the runaway
    assert np.max(np.abs(a.stretch[ok] - b.stretch[ok])) < 1e-5


def test_breakdown_before_runaway_is_reported_first() -> None:
    """At 10 kV (raised cosine, 1/9 Hz) the true field E = Φ/l3 with l3 = L3 λ⁻² (physics.md §1.2, incompressible
    film) passes the breakdown field before λ passes 4: the failure named first is the breakdown, at its time."""
    tr = simulate_membrane(PARAMS, Waveform("raised_cosine", 10_000.0, 1 / 9), 5.0, fs=1000.0)
    assert tr.failed
    thickness = PARAMS.L3 / tr.stretch**2  # l3 = L3 λ⁻², from the simulated λ series
    with np.errstate(invalid="ignore"):
        above = np.abs(tr.voltage / thickness) > PARAMS.breakdown_field
    assert above.any()
    i = int(np.argmax(above))
    assert tr.stretch[i] < PARAMS.runaway_stretch  # breakdown first: λ has not yet run away there
    first, _, then = tr.failure.partition("; then ")
    assert "breakdown" in first and f"t = {tr.t[i]:.3f} s" in first
    assert "runaway" in then  # and the runaway that followed is named second


def test_failure_reason_names_the_earlier_failure_first() -> None:
    lam = np.full(20, 2.0)
    E = np.zeros(20)
    lam[12:] = PARAMS.runaway_stretch + 0.5  # runaway from sample 12
    E[5:] = 2 * PARAMS.breakdown_field  # breakdown from sample 5
    reason = failure_reason(PARAMS, lam, E)
    assert reason.startswith("true field") and "sample 5" in reason
    assert "then runaway" in reason and "sample 12" in reason
    E[:] = 0.0
    E[15:] = 2 * PARAMS.breakdown_field  # now the runaway comes first
    assert failure_reason(PARAMS, lam, E).startswith("runaway stretch")
