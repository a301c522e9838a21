"""LS-DEA design map (Moretti Fig. 2): regions checked against physics.md §2.1 written out independently here.

The reference below evaluates the energy Ψ(λ1, λ2), the capacitance C(x) and the forces F_el = Ω dΨ/dx,
F_es = −½V² dC/dx by finite differences of the printed definitions — not through the model's kernels.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.design_map import MapSettings, compute_map, plot_map

# physics.md §2.1 (Table 1 material, prototype geometry)
MU, JM, C2, EPS, T0, E0, R = 312.6e3, 30.58, 183.5e3, 2.72 * 8.85e-12, 260e-6, 81e6, 0.86
L = 0.120


def _stretches(x: float, l2p: float, xp: float) -> tuple[float, float]:
    y, yp = math.sqrt(4 * L * L - x * x), math.sqrt(4 * L * L - xp * xp)
    return l2p**-0.5 * x / xp, l2p * y / yp


def _psi(l1: float, l2: float) -> float:
    l3 = 1 / (l1 * l2)
    return (-(MU * JM / 2) * math.log(1 - (l1**2 + l2**2 + l3**2 - 3) / JM)
            + C2 * math.log((l1**-2 + l2**-2 + l3**-2) / 3))


def _force(x: float, l2p: float, xp: float, V: float = 0.0) -> float:
    """F = Ω dΨ/dx − ½V² dC/dx by central differences."""
    yp = math.sqrt(4 * L * L - xp * xp)
    omega = xp * yp * T0 / (2 * l2p**-0.5 * l2p)

    def cap(x: float) -> float:
        return EPS * l2p**-0.5 * l2p * x * x * (4 * L * L - x * x) / (2 * T0 * xp * yp)

    d = 1e-7
    dpsi = (_psi(*_stretches(x + d, l2p, xp)) - _psi(*_stretches(x - d, l2p, xp))) / (2 * d)
    return omega * dpsi - 0.5 * V * V * (cap(x + d) - cap(x - d)) / (2 * d)


def _min_stiffness(l2p: float, xp: float, stroke: tuple[float, float] = (0.050, 0.140)) -> float:
    x = np.linspace(max(stroke[0], xp * 1.001), stroke[1], 181)
    F = np.array([_force(float(v), l2p, xp) for v in x])
    return float(np.min(np.gradient(F, x)))


def _stresses(x: float, l2p: float, xp: float, V: float) -> tuple[float, float]:
    """Cauchy stresses σj = λj ∂Ψ/∂λj − εE² (λ3 eliminated), E = Vλ1λ2/t0."""
    l1, l2 = _stretches(x, l2p, xp)
    d = 1e-7
    p1 = (_psi(l1 + d, l2) - _psi(l1 - d, l2)) / (2 * d)
    p2 = (_psi(l1, l2 + d) - _psi(l1, l2 - d)) / (2 * d)
    E = V * l1 * l2 / T0
    return l1 * p1 - EPS * E * E, l2 * p2 - EPS * E * E


def _region(k: float, flat: float) -> str:
    return "stiff" if k > flat else "negative" if k < -flat else "near-zero"


REPORTED: list[float] = []  # the fractions compute_map reported while the fixture's map was computed


@pytest.fixture(scope="module")
def dmap():
    REPORTED.clear()
    return compute_map(MapSettings(lambda2p=(2.0, 2.5, 2.75, 3.0, 3.5), xp=(0.025, 0.040, 0.055)),
                       progress=REPORTED.append)


def test_the_map_reports_its_progress_row_by_row(dmap) -> None:
    """Issue 26 item 7: one report per λ2p row (5 rows), rising to 1 (the command line draws it as a bar)."""
    assert REPORTED == [0.2, 0.4, 0.6, 0.8, 1.0]


def test_prototypes_fall_in_the_regions_physics_md_states(dmap) -> None:
    """#1 stiff (min 20.3 N/m), #2 almost flat (4.9 N/m), #3 negative (−9.6 N/m): physics.md §2.2, B4."""
    flat = dmap.settings.flat
    expected = {2.5: "stiff", 2.75: "near-zero", 3.0: "negative"}
    for l2p, region in expected.items():
        k_ref = _min_stiffness(l2p, 0.040)
        assert _region(k_ref, flat) == region
        assert dmap.design(l2p, 0.040).min_stiffness == pytest.approx(k_ref, rel=0.02, abs=0.2)
    assert _min_stiffness(2.5, 0.040) == pytest.approx(20.3, rel=0.03)
    assert _min_stiffness(2.75, 0.040) == pytest.approx(4.9, rel=0.03)
    assert _min_stiffness(3.0, 0.040) == pytest.approx(-9.6, rel=0.03)


def test_the_elastic_stiffness_is_at_0_V_whichever_voltages_are_asked_for() -> None:
    """`design-map --voltages 3` classed #2 "stiff" (5.2 N/m, the stiffness at 3 kV) where physics.md §2.2 gives
    4.9 N/m at 0 V: the regions are the elastic (0 V) stiffness's, never the first voltage's."""
    flat = MapSettings().flat
    for volts in ((3000.0,), (7000.0, 5000.0)):
        m = compute_map(MapSettings(lambda2p=(2.75, 3.0), xp=(0.040,), voltages=volts))
        for l2p in (2.75, 3.0):
            k_ref = _min_stiffness(l2p, 0.040)
            assert m.design(l2p, 0.040).min_stiffness == pytest.approx(k_ref, rel=0.02, abs=0.2)
        assert list(m.regions()[:, 0]) == [_region(_min_stiffness(2.75, 0.040), flat), "negative"]


def test_map_regions_agree_with_the_independent_model_over_the_grid(dmap) -> None:
    """Stiff at low λ2p and xp, negative at large values, a near-zero band between."""
    s = dmap.settings
    regions = dmap.regions()
    ref = np.array([[_region(_min_stiffness(l2p, xp), s.flat) for xp in s.xp] for l2p in s.lambda2p])
    np.testing.assert_array_equal(regions, ref)
    assert ref[0, 0] == "stiff" and ref[-1, -1] == "negative"
    assert "near-zero" in ref
    k = dmap.min_stiffness()
    assert np.all(np.diff(k, axis=0) < 0) and np.all(np.diff(k, axis=1) < 0)  # softer with λ2p and with xp


def test_breakdown_curve_and_loss_of_tension(dmap) -> None:
    d = dmap.design(3.0, 0.040)
    i = int(np.argmin(np.abs(d.x - 0.100)))
    x = float(d.x[i])
    l1, l2 = _stretches(x, 3.0, 0.040)
    VB = E0 * T0 * (1 / (l1 * l2)) ** (1 - R / 2)  # E = V λ1λ2/t0 reaches E0 λ3^(−r/2)
    assert d.breakdown_voltage[i] == pytest.approx(VB, rel=1e-9)
    assert d.breakdown_force[i] == pytest.approx(_force(x, 3.0, 0.040, VB), rel=1e-4)
    v7 = dmap.settings.voltages.index(7000.0)
    assert d.force[v7, i] == pytest.approx(_force(x, 3.0, 0.040, 7000.0), rel=1e-4)
    # at xp = 55 mm the stroke starts in the uniaxial mounting state: σ1 ≤ 0 just above xp, taut further out
    d = dmap.design(3.0, 0.055)
    for j in (0, len(d.x) // 2):
        s1, s2 = _stresses(float(d.x[j]), 3.0, 0.055, 7000.0)
        assert bool(d.tension_lost[v7, j]) == (s1 <= 0 or s2 <= 0)
    assert d.tension_lost[v7, 0] and not d.tension_lost[v7, len(d.x) // 2]
    assert not dmap.design(2.5, 0.040).tension_lost.any()  # σ1 > 0 for x ≥ 50 mm (physics.md §2.2)


def test_plot_writes_the_map_and_the_curves(dmap, tmp_path: Path) -> None:
    paths = plot_map(dmap, tmp_path)
    assert [p.name for p in paths] == ["design-map.png", "design-map-curves.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_simulate_lsdea_map_cli_prints_the_prototypes_and_writes_the_figures(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from bench.cli import app

    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["simulate", "lsdea", "map"], env={"COLUMNS": "200"})
    assert out.exit_code == 0, out.output
    for line in ("prototype #1 (λ2p 2.5, xp 40 mm): stiff", "prototype #2 (λ2p 2.75, xp 40 mm): near-zero",
                 "prototype #3 (λ2p 3, xp 40 mm): negative"):
        assert line in out.output
    assert (tmp_path / "runs" / "design-map" / "design-map.png").exists()
    assert "replaced" not in out.output
    # a design's options are refused with the map (they were ignored without a word), before any computing
    out = CliRunner().invoke(app, ["simulate", "lsdea", "map", "--voltage", "3kV", "--prototype", "2"],
                             env={"COLUMNS": "200"})
    assert out.exit_code == 2 and "takes no --prototype, --voltage" in out.output and "figures" not in out.output
    # the map again into its own folder: it says that it replaced the earlier figures
    out = CliRunner().invoke(app, ["design-map", "--voltages", "0,7"], env={"COLUMNS": "200"})
    assert out.exit_code == 0, out.output
    assert "replaced the earlier map's design-map.png" in " ".join(out.output.split())
