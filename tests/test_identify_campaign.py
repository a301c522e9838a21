"""Campaign fits: records cut at long rests, per-record identifiability, `bench fit` over a campaign's files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bench.identify.campaign import campaign_identifiability
from bench.identify.core import FitSettings, fit
from bench.identify.problems import _record_windows
from bench.identify.store import read_fits
from bench.runtime.run import run_protocol

ROOT = Path(__file__).resolve().parent.parent
SHORT = ROOT / "protocols" / "short"


def test_records_are_cut_at_long_rests_only() -> None:
    t = np.arange(0, 200, 0.05)
    v = np.where((t % 80) < 20, 7000 * np.sin(np.pi * (t % 80) / 20) ** 2, 2.44)  # 20-s drives, 60-s rests
    v[(t > 200 - 5)] = 2.44
    w = _record_windows(t, v, 200.0, split_rest=30.0, keep_rest=20.0)
    # the drive is "quiet" (< 1 % of the peak) for its first and last 0.64 s: sin²(πt/20) < 0.01
    np.testing.assert_allclose(np.array(w), [(0, 39.36), (80.64, 119.36), (160.64, 200)], atol=0.06)
    assert _record_windows(t, v, 200.0, split_rest=70.0, keep_rest=20.0) == [(0.0, 200.0)]  # no rest that long
    assert _record_windows(t, v, 200.0, split_rest=0.0, keep_rest=20.0) == [(0.0, 200.0)]


@dataclass
class _Rec:
    data: np.ndarray
    source: str
    U: np.ndarray
    template: np.ndarray


class _TwoRecords:
    """y1 = (a + b)t and y2 = (a − b)t: each record alone sees one combination of a and b, the pair sees both."""

    lower = np.array([0.0, 0.0])
    upper = np.array([4.0, 4.0])
    log = np.array([False, False])
    data_unit = "-"

    def __init__(self) -> None:
        self.names, self.units = ["a", "b"], ["-", "-"]
        self.t = np.linspace(0.1, 1.0, 40)
        self.records = [_Rec(3.0 * self.t, "sum", np.zeros((40, 2)), np.zeros(20)),
                        _Rec(1.0 * self.t, "difference", np.zeros((40, 2)), np.zeros(20))]
        self.data = np.concatenate([r.data for r in self.records])

    def predict(self, Z: np.ndarray) -> np.ndarray:
        Z = np.atleast_2d(Z)
        return np.hstack([(Z[:, :1] + Z[:, 1:]) * self.t, (Z[:, :1] - Z[:, 1:]) * self.t])


def test_campaign_determines_what_no_single_record_does() -> None:
    prob = _TwoRecords()
    res = fit(prob, FitSettings(population=20, generations=60, cost="lsq"))
    np.testing.assert_allclose(res.values, [2.0, 1.0], atol=1e-6)  # a + b = 3, a − b = 1
    report = campaign_identifiability(prob, res)
    assert report.undetermined == [["a", "b"], ["a", "b"]]  # each record: a and b perfectly correlated
    assert report.campaign_undetermined == []
    assert report.gained == ["a", "b"]


def _runs(tmp_path: Path, names: list[str]) -> list[str]:
    paths = []
    for name in names:
        res = run_protocol(SHORT / name, virtual=True, out=tmp_path / (Path(name).stem + ".h5"))
        assert res.state == "completed", res.reason
        paths.append(str(res.path))
    return paths


@pytest.mark.parametrize("names", [
    ["thesis-sweeps-short.toml", "thesis-identification-short.toml"],
    ["lsdea-isopotential-short.toml", "lsdea-isometric-short.toml", "lsdea-isotonic-short.toml"],
], ids=["thesis", "lsdea"])
def test_campaign_fit_cli_stores_the_joint_result_in_every_file(tmp_path: Path, names: list[str]) -> None:
    from typer.testing import CliRunner

    from bench.cli import app

    paths = _runs(tmp_path, names)
    # 2 polish evaluations: what is checked is the joint result's report and storage, not its values (20 cost more)
    out = CliRunner().invoke(app, ["fit", *paths, "--population", "12", "--generations", "4", "--starts", "1",
                                   "--no-intervals", "--polish-iterations", "2"],
                             env={"COLUMNS": "250"})
    assert out.exit_code == 0, out.output
    assert "what each record determines alone" in out.output
    assert "determined by the campaign but by no single record:" in out.output
    stored = [read_fits(p)[-1] for p in paths]
    for s in stored:
        assert s["values"].tolist() == stored[0]["values"].tolist()  # one joint result, the same in every file
        campaign = s["campaign"]
        assert len(campaign["records"]) == len(s["records"]) >= len(paths)
        assert {r.split(" [")[0] for r in campaign["records"]} == set(paths)  # every file's records took part
        assert len(campaign["undetermined_per_record"]) == len(campaign["records"])
        assert set(campaign["determined_only_by_the_campaign"]) <= set(s["names"])


class _Weak(_TwoRecords):
    """y1 = a·t and y2 = (a + 10⁻³ b)·t with noise 0.05 (a = 2, b = 1): b's trace is far below the noise, so a
    trusted fit's profile interval spans b's whole range — the campaign does not determine b, whatever each record
    says."""

    def __init__(self) -> None:
        super().__init__()
        self.t = np.linspace(0.1, 1.0, 60)
        rng = np.random.default_rng(3)
        self.records = [_Rec(2.0 * self.t + rng.normal(0, 0.05, 60), "a only", np.zeros((60, 2)), np.zeros(20)),
                        _Rec((2.0 + 1e-3) * self.t + rng.normal(0, 0.05, 60), "a and a trace of b (b = 1)",
                             np.zeros((60, 2)), np.zeros(20))]
        self.data = np.concatenate([r.data for r in self.records])

    def predict(self, Z: np.ndarray) -> np.ndarray:
        Z = np.atleast_2d(Z)
        return np.hstack([Z[:, :1] * self.t, (Z[:, :1] + 1e-3 * Z[:, 1:]) * self.t])


def test_a_parameter_the_trusted_fit_leaves_undetermined_is_not_gained_by_the_campaign() -> None:
    """The fit's table row said "not determined" while the campaign line said "determined by the campaign: … b"
    (outside tester, two short records): the campaign's verdict must be the trusted fit's."""
    prob = _Weak()
    res = fit(prob, FitSettings(population=20, generations=60, cost="lsq", intervals=True))
    assert any(f.startswith("b: not determined") for f in res.flags), res.flags  # the premise: the interval's
    report = campaign_identifiability(prob, res)
    assert "b" in report.campaign_undetermined and "b" not in report.gained, report
    # no record determines what the whole campaign does not (its data are a part of the campaign's): the table
    # ticked a parameter for a record and not for the campaign (a second tester)
    assert all("b" in u for u in report.undetermined), report.undetermined


class _OneDetermines(_TwoRecords):
    """y1 = a·t + b·t² determines a and b alone; y2 = a·t does not see b."""

    def __init__(self) -> None:
        super().__init__()
        self.records = [_Rec(2.0 * self.t + 1.0 * self.t**2, "both", np.zeros((40, 2)), np.zeros(20)),
                        _Rec(2.0 * self.t, "a only", np.zeros((40, 2)), np.zeros(20))]
        self.data = np.concatenate([r.data for r in self.records])

    def predict(self, Z: np.ndarray) -> np.ndarray:
        Z = np.atleast_2d(Z)
        return np.hstack([Z[:, :1] * self.t + Z[:, 1:] * self.t**2, Z[:, :1] * self.t])


def test_no_record_is_said_to_determine_what_the_whole_campaign_leaves_undetermined() -> None:
    """The campaign table ticked J0 for one record and not for the campaign (a second tester): a record's local
    analysis can call determined what the campaign's profile interval leaves open, yet a record's data are a part of
    the campaign's, so what the whole does not determine no part of it does. Here record "both" determines b on its
    own; a verdict of the campaign (a trusted fit's flag, in its words) that b is not determined wins for it too."""
    prob = _OneDetermines()
    res = fit(prob, FitSettings(population=20, generations=60, cost="lsq"))
    assert campaign_identifiability(prob, res).undetermined[0] == []  # the premise: "both" alone determines a, b
    res.flags.append("b: not determined (the data allow 0 … 4 -, 95 %)")  # as bench.identify.trust words it
    report = campaign_identifiability(prob, res)
    assert report.campaign_undetermined == ["b"] and report.undetermined[0] == ["b"], report


def test_a_sweeps_record_is_labelled_with_each_of_its_conditions() -> None:
    """The sweeps protocol's record (5 kV at 266 K, then 7 kV at 316 K) was labelled "7 kV, 266 K" — the highest
    voltage with the median temperature (a second tester). Each temperature level now names its own peak voltage, in
    the record's order; a thermometer's scatter does not split one level."""
    from types import SimpleNamespace

    from bench.identify.campaign import record_conditions

    t = np.linspace(0.0, 14.0, 1401)
    v = np.where(t < 7, 5000 * np.sin(np.pi * t / 5) ** 2, 7000 * np.sin(np.pi * (t - 7) / 5) ** 2)
    sweep = _Rec(np.zeros(t.size), "sweep", np.column_stack([v, np.where(t < 7, 266.0, 316.0)]), np.zeros(20))
    noisy = _Rec(np.zeros(t.size), "noisy", np.column_stack([v, 296 + np.random.default_rng(0).normal(0, 0.4, t.size)]),
                 np.zeros(20))
    assert record_conditions(SimpleNamespace(records=[sweep, noisy])) == ["5 kV, 266 K; 7 kV, 316 K", "7 kV, 296 K"]


def test_an_ls_dea_record_is_labelled_with_the_voltages_it_spans() -> None:
    """An isopotential prototype's record (0, 3, 5 and 7 kV held in turn, each for its tensile cycles) was labelled
    "7 kV", its peak, as if all of it were at 7 kV (an outside tester). Its label is the span of |V| it covers; a
    record at one voltage (within 5 %, a monitor's noise) names that one."""
    from types import SimpleNamespace

    from bench.identify.campaign import record_conditions

    template = np.zeros(20)
    template[10], template[13] = 3.2, 0.15  # λ2p, hung mass [kg]
    rng = np.random.default_rng(1)
    steps = np.abs(np.repeat([0.0, 3000.0, 5000.0, 7000.0], 500) + rng.normal(0, 3, 2000))  # a monitor's noise
    t = np.linspace(0.0, 10.0, 2000)
    drive = 3500.0 * (1 - np.cos(2 * np.pi * t))
    held = 5000.0 + rng.normal(0, 30, 2000)
    recs = [_Rec(np.zeros(2000), "r", np.column_stack([u, np.zeros(2000), np.zeros(2000)]), template)
            for u in (steps, drive, held)]
    labels = record_conditions(SimpleNamespace(records=recs))
    assert labels[0] == "λ2p 3.2, 150 g, 0–7.01 kV"  # to 10 V: the monitor's noise reads 7.01 kV at its peak
    assert labels[1] == "λ2p 3.2, 150 g, 0–7 kV" and labels[2] == "λ2p 3.2, 150 g, 5 kV", labels
