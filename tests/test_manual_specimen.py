"""A manual session names its specimen (`bench devices control RIG --specimen-id S`): its time at high voltage is in
the specimen's history, as a run's is (an outside tester: manual sessions took no specimen ID, so a specimen driven
by hand for an afternoon showed none of it)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.storage.hv_stats import HV_THRESHOLD_V
from tests.conftest import ROOT

THESIS_RIG = ROOT / "rigs" / "thesis-sim.toml"


def test_a_manual_session_s_high_voltage_time_is_in_its_specimen_s_history(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    script, log = tmp_path / "s.txt", runs / "session.log"
    script.write_text("voltage 2000\nwait 3\nzero\nwait 1\n", encoding="utf-8")
    runner = CliRunner()
    res = runner.invoke(app, ["devices", "control", str(THESIS_RIG), "--script", str(script), "--virtual-time",
                              "--log", str(log), "--specimen-id", "M1"])
    assert res.exit_code == 0, res.output
    assert "specimen M1" in log.read_text(encoding="utf-8").splitlines()[0]
    shown = runner.invoke(app, ["specimen", "show", "M1", "--dir", str(runs), "--json"])
    assert shown.exit_code == 0, shown.output
    h = json.loads(shown.output)
    (run,) = h["runs"]
    assert run["file"] == str(log.with_suffix(".h5").resolve())
    # the script held 2 kV (above the history's threshold) for 3 s, after the set-point's verification (a few tenths
    # of a second); a session's readings are irregular, each weighted up to the next (catalog.py): the last reading at
    # 2 kV counts up to the first after the zero's (a few tenths of a second more)
    assert 2000 > HV_THRESHOLD_V and 3.0 <= run["hv_time_s"] <= 3.6, run


@pytest.mark.parametrize("given", ["a\nb", "x" * 101])
def test_a_bad_specimen_id_is_refused_before_the_rig_is_touched(tmp_path: Path, given: str) -> None:
    log = tmp_path / "s.log"
    res = CliRunner().invoke(app, ["devices", "control", str(THESIS_RIG), "--script", "/dev/null", "--virtual-time",
                                   "--log", str(log), "--specimen-id", given])
    assert res.exit_code == 2, res.output
    assert res.output.startswith("error: --specimen-id: ") and res.output.count("\n") == 1, res.output
    assert not log.exists()


def test_a_rig_name_with_path_separators_stays_in_the_session_s_folder(tmp_path: Path) -> None:
    """A rig named ``x/../../../../escape`` wrote its manual session's log and readings outside the lab (an outside
    tester): the default name keeps only letters, digits, ``_``, ``.`` and ``-`` of it, as a run's file name does."""
    from bench.rig import load_rig
    from bench.runtime.manual import session_log_name

    text = THESIS_RIG.read_text(encoding="utf-8")
    rig_file = tmp_path / "odd.toml"
    rig_file.write_text(text.replace('name = "thesis-sim"', 'name = "x/../../../../escape"'), encoding="utf-8")
    name = session_log_name(load_rig(rig_file))
    assert name.startswith("manual-x-..-..-..-..-escape-") and "/" not in name and name.endswith(".log"), name
