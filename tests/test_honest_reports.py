"""Reports that say what they are built from: incomplete files flagged in `inspect` and `report` (text and --json),
the Table-3 grid in `report --json` and as CSV, never mixing strokes without saying so.

The strokes expected are the protocols' imposed amplitudes; the losses in the CSV are checked against the
analysis of each file, the grid's source.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from bench.analysis.runs import analyse
from bench.cli import app
from bench.runtime.run import execute, plan_run
from tests.conftest import ROOT

ISO = ROOT / "protocols" / "short" / "lsdea-isopotential-short.toml"  # prototype #1, Δx 90 mm, 0 and 7 kV


@pytest.fixture(scope="module")
def iso_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """#1 at the protocol's 90 mm; #2 at 70 mm (the same protocol, another prototype and stroke); an unfinished
    copy of the first (``complete`` cleared, as a run that died before stamping its end leaves it)."""
    d = tmp_path_factory.mktemp("iso")
    text = ISO.read_text().replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/')
    proto2 = d / "iso-p2-70mm.toml"
    proto2.write_text(text.replace('amplitude = "90 mm"', 'amplitude = "70 mm"')
                      .replace("[recording]", "[specimen]\nprototype = 2\n\n[recording]"))
    out = {}
    for name, proto in (("p1", ISO), ("p2", proto2)):
        res = execute(plan_run(proto), d / f"{name}.h5", virtual=True, operator=lambda _msg: True)
        assert res.state == "completed", res.reason
        out[name] = Path(res.path)
    unfinished = d / "unfinished.h5"
    unfinished.write_bytes(out["p1"].read_bytes())
    with h5py.File(unfinished, "r+") as f:
        f.attrs["complete"] = False
    out["unfinished"] = unfinished
    return out


def _cli(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return res.exit_code, res.output


def test_the_table3_grid_is_in_the_json_and_a_csv_and_says_when_strokes_differ(iso_runs: dict[str, Path],
                                                                               tmp_path: Path) -> None:
    code, out = _cli("report", str(iso_runs["p1"]), str(iso_runs["p2"]), "--out", str(tmp_path), "--json")
    assert code == 0, out
    grid = json.loads(out)["table3"]
    assert [r["prototype"] for r in grid["rows"]] == [1, 2]
    assert [r["stroke_m"] for r in grid["rows"]] == [pytest.approx(0.090), pytest.approx(0.070)]
    assert grid["voltages_kV"] == [0, 7]
    assert any("different strokes" in w and "#1 90 mm" in w and "#2 70 mm" in w for w in grid["warnings"])
    with open(grid["csv"], newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["prototype"], r["stroke_mm"]) for r in rows] == [("1", "90"), ("2", "70")]
    for row, name in zip(rows, ("p1", "p2"), strict=True):
        steps = [s for s in analyse(iso_runs[name]).steps if s.kind == "isopotential"]
        by_kv = {round(s.voltage / 1e3): s.figures["loss_last"] for s in steps}
        for kv in (0, 7):
            assert float(row[f"loss_{kv}kV_percent"]) == pytest.approx(100 * by_kv[kv], rel=1e-3)
    code, text = _cli("report", str(iso_runs["p1"]), str(iso_runs["p2"]), "--out", str(tmp_path / "t"))
    assert code == 0 and "grid warning" in text and "different strokes" in text and "table3.csv" in text
    # one prototype at one stroke: no warning
    code, out = _cli("report", str(iso_runs["p1"]), "--out", str(tmp_path / "one"), "--json")
    assert code == 0 and json.loads(out)["table3"]["warnings"] == []


def test_an_incomplete_file_is_flagged_by_report_and_inspect(iso_runs: dict[str, Path], tmp_path: Path) -> None:
    code, out = _cli("report", str(iso_runs["unfinished"]), "--out", str(tmp_path), "--json")
    assert code == 0, out
    (run,) = json.loads(out)["runs"]
    assert run["complete"] is False and "not finalised" in run["incomplete_reason"]
    code, text = _cli("report", str(iso_runs["unfinished"]), "--out", str(tmp_path / "t"))
    assert "INCOMPLETE" in text and "not finalised" in text
    code, text = _cli("report", str(iso_runs["p1"]), "--out", str(tmp_path / "c"))
    assert code == 0 and "INCOMPLETE" not in text
    # inspect takes many files: a list in --json, exit 1 when any is incomplete
    code, out = _cli("inspect", str(iso_runs["p1"]), str(iso_runs["unfinished"]), "--json")
    assert code == 1
    assert [(r["file"], r["complete"]) for r in json.loads(out)] == [(str(iso_runs["p1"]), True),
                                                                     (str(iso_runs["unfinished"]), False)]
    code, out = _cli("inspect", str(iso_runs["p1"]), "--json")
    assert code == 0 and json.loads(out)["file"] == str(iso_runs["p1"])  # one file: one object, as before
    code, text = _cli("inspect", str(iso_runs["p1"]), str(iso_runs["p2"]))
    assert code == 0 and text.count("run file") >= 2 and "p2.h5" in text
