"""The fitted rig file (issue 26 item 8): the source rig's comments, order and unwritten defaults survive, only the
fitted values change, the membrane's dashpots are written as the relaxation times the fit reports (no ``eta``), and
the result loads as a rig. The fitted values are made up here (any positive numbers): the test is about the file."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from bench.identify.fitted_rig import export_rig, fitted_rig_text
from bench.rig import load_rig, rig_from_toml
from tests.conftest import ROOT

MEMBRANE = ["mu0", "J0"] + [f"mu{i}" for i in range(1, 5)] + [f"J{i}" for i in range(1, 5)] + \
    [f"tau{i}" for i in range(1, 5)]
VALUES = np.array([40e3, 90.0, 5e3, 6e3, 7e3, 8e3, 100.0, 110.0, 120.0, 130.0, 0.1, 5.0, 2e-5, 0.07])
LSDEA = ["mu", "Jm", "C2", "mu_b1", "tau_b1", "c"]


def _comments(text: str) -> list[str]:
    return [line[line.index("#"):] for line in text.splitlines() if "#" in line]


def _keys(data: dict, prefix: str = "") -> list[str]:
    """Every key path of a parsed TOML file, in file order."""
    out = []
    for k, v in data.items():
        out.append(prefix + k)
        if isinstance(v, dict):
            out += _keys(v, f"{prefix}{k}.")
    return out


def test_a_shipped_rig_keeps_its_comments_and_order_and_only_the_fit_changes(tmp_path: Path) -> None:
    source = (ROOT / "rigs" / "thesis-sim.toml").read_text(encoding="utf-8")
    rig = export_rig(source, "membrane", MEMBRANE, VALUES, tmp_path / "fitted.toml", "runs/a.h5")
    text = (tmp_path / "fitted.toml").read_text(encoding="utf-8")
    assert text.splitlines()[0] == "# fitted by `bench fit` from runs/a.h5"
    assert _comments(text)[1:] == _comments(source)  # every comment, in order, as written
    before, after = tomllib.loads(source), tomllib.loads(text)
    fitted = after["specimen"].pop("membrane_model")
    assert fitted == {"mu0": 40e3, "J0": 90.0, "mu": [5e3, 6e3, 7e3, 8e3], "J": [100.0, 110.0, 120.0, 130.0],
                      "tau": [0.1, 5.0, 2e-5, 0.07]}
    assert after.pop("name") == "thesis-sim-fitted" and before.pop("name") == "thesis-sim"
    assert after == before and _keys(after) == _keys(before)  # nothing else changed, nor moved, nor was added
    assert "eta" not in text and "interlock" not in text  # no default written out ([interlock] is not in the source)
    # it loads as a rig, and the model it simulates has the fitted relaxation times (τ = η/μ)
    loaded = load_rig(tmp_path / "fitted.toml")
    assert loaded == rig and loaded.simulated
    assert loaded.specimen.membrane().tau == pytest.approx((0.1, 5.0, 2e-5, 0.07), rel=1e-12)
    assert loaded.specimen.membrane().mu0 == 40e3


def test_a_model_written_with_eta_is_replaced_by_tau_and_a_lab_rig_becomes_simulated() -> None:
    source = (ROOT / "rigs" / "thesis-lab.toml").read_text(encoding="utf-8") + (
        "\n[specimen.membrane_model]   # from last year's fit\nmu0 = 1.0   # Pa, a guess\nJ0 = 2.0\n"
        "mu = [1.0, 1.0, 1.0, 1.0]\nJ = [9.0, 9.0, 9.0, 9.0]\neta = [1.0, 1.0, 1.0, 1.0]\n")
    assert rig_from_toml(source).specimen.membrane_model is not None  # a valid rig with eta
    text = fitted_rig_text(source, "membrane", MEMBRANE, VALUES, "runs/b.h5")
    assert "# from last year's fit" in text and "mu0 = 40000.0   # Pa, a guess" in text
    model = tomllib.loads(text)["specimen"]["membrane_model"]
    assert "eta" not in model and model["tau"] == [0.1, 5.0, 2e-5, 0.07]
    assert tomllib.loads(text)["simulated"] is True
    again = fitted_rig_text(text, "membrane", MEMBRANE, VALUES, "runs/c.h5")  # fitted again: one header
    assert again.count("# fitted by `bench fit`") == 1 and "thesis-lab-fitted\"" in again


def test_an_lsdea_fit_writes_its_model_table(tmp_path: Path) -> None:
    source = (ROOT / "rigs" / "lsdea-motor-sim.toml").read_text(encoding="utf-8")
    rig = export_rig(source, "lsdea", LSDEA, np.array([30e3, 120.0, 1e3, 8e3, 2.5, 1.2]), tmp_path / "f.toml", "r")
    model = rig.specimen.lsdea_model
    assert model is not None and (model.mu, model.Jm, model.C2, model.damping) == (30e3, 120.0, 1e3, 1.2)
    assert (model.branch_mu, model.branch_tau) == ([8e3], [2.5])
    assert _comments((tmp_path / "f.toml").read_text(encoding="utf-8"))[1:] == _comments(source)


@pytest.mark.parametrize("dashpots", ["", "tau = [1.0]\neta = [1.0]\n"])
def test_a_membrane_model_needs_tau_or_eta(dashpots: str) -> None:
    table = f"name = 'x'\n[specimen.membrane_model]\nmu0 = 1.0\nJ0 = 2.0\nmu = [1.0]\nJ = [3.0]\n{dashpots}"
    with pytest.raises(ValueError, match=r"tau \[s\] or its eta"):
        rig_from_toml(table)


def test_a_rig_that_replayed_a_record_becomes_the_model_again() -> None:
    """A run made with ``[simulation] replay`` (a recorded run served instead of the model): its fitted rig is the
    fitted model, so the replay (a path relative to the source rig's folder, wrong beside the export) goes."""
    source = (ROOT / "rigs" / "thesis-sim.toml").read_text(encoding="utf-8").replace(
        "[simulation]", '[simulation]\nreplay = "runs/old.h5"  # a record of last week', 1)
    assert 'replay = "runs/old.h5"' in source
    text = fitted_rig_text(source, "membrane", MEMBRANE, VALUES, "runs/d.h5")
    assert "replay" not in tomllib.loads(text).get("simulation", {})
    assert rig_from_toml(text).simulation.replay is None


def test_a_fit_that_set_the_monitor_calibration_says_so_under_the_header() -> None:
    """A DAQ rig's fit also sets V_gain and V_offset (the voltage monitor's calibration), which no rig table holds;
    the specimen it exports is the one seen through that calibration (an outside tester's rerun on such a rig
    missed the record by 15× the fit's residual with V_gain poorly determined). The file says so, once."""
    source = (ROOT / "rigs" / "thesis-daq-sim.toml").read_text(encoding="utf-8")
    names, values = [*MEMBRANE, "V_gain", "V_offset"], np.append(VALUES, [8e-4, -2.5])
    text = fitted_rig_text(source, "membrane", names, values, "runs/e.h5")
    second = text.splitlines()[1]
    assert second.startswith("# the same fit set the voltage monitor's calibration")
    assert "V_gain = 0.0008, V_offset = -2.5 V" in second
    again = fitted_rig_text(text, "membrane", names, values, "runs/f.h5")
    assert again.count("voltage monitor's calibration") == 1 and again.count("# fitted by `bench fit`") == 1
    assert "voltage monitor's calibration" not in fitted_rig_text(source, "membrane", MEMBRANE, VALUES, "r")
