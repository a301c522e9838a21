"""The lab's daily work: operator, specimen ID and notes on every run; fits beside the run; quantities on the CLI.

Expected values come from what the test wrote (read back with plain h5py), from the file names the store
documents, and for the simulations from the figures of tests/test_cli.py (7 kV base case: first peak 7.675 mm;
LS-DEA #3 isometric at 6 kV, 5 Hz: force crest-to-trough 1.14 N).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.identify.store import read_fits
from bench.protocol.schema import ProtocolFileError, load_protocol

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()

PROTOCOL = """\
[protocol]
name = "metadata-short"
rig = "{rig}"
{header}
[recording]
displacement_Hz = 1000
monitors_Hz = 5
setpoint_Hz = 20

[[steps]]
type = "waveform"
amplitude = "3 kV"
frequency_Hz = 1.0
cycles = 2
"""
FILE_HEADER = 'operator = "Ann Other"\nspecimen_id = "VHB-07"\nnotes = "from the file"\n'


def _protocol(folder: Path, header: str = FILE_HEADER) -> Path:
    path = folder / "p.toml"
    path.write_text(PROTOCOL.format(rig=ROOT / "rigs" / "thesis-sim.toml", header=header), encoding="utf-8")
    return path


def _bench(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "bench", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env={"COLUMNS": "200", "PATH": ""})


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-s virtual-time run: the file's operator replaced, its specimen ID kept, two notes added."""
    folder = tmp_path_factory.mktemp("metadata")
    res = runner.invoke(app, ["run", str(_protocol(folder)), "--virtual-time", "--no-live", "--out",
                              str(folder / "runs"), "--operator", "Zoë Kraft", "--note", "second note",
                              "--note", "grip re-tightened"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    (path,) = (folder / "runs").glob("*.h5")
    return path


def test_operator_specimen_and_notes_are_utf8_root_attributes(run_file: Path) -> None:
    with h5py.File(run_file, "r") as f:
        assert f.attrs["operator"] == "Zoë Kraft"  # the option replaces the file's operator
        assert f.attrs["specimen_id"] == "VHB-07"  # kept from the file
        assert f.attrs["notes"] == "from the file\nsecond note\ngrip re-tightened"  # the file's, then the options'
        for key in ("operator", "specimen_id", "notes"):
            info = h5py.check_string_dtype(f.attrs.get_id(key).dtype)
            assert info is not None and info.encoding == "utf-8", key
    res = runner.invoke(app, ["inspect", str(run_file), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert (data["operator"], data["specimen_id"]) == ("Zoë Kraft", "VHB-07")
    assert data["notes"] == ["from the file", "second note", "grip re-tightened"]
    res = runner.invoke(app, ["inspect", str(run_file)], env={"COLUMNS": "200"})
    assert re.search(r"operator\s+│ Zoë Kraft", res.output) and re.search(r"specimen ID\s+│ VHB-07", res.output)


@pytest.mark.parametrize(("header", "field", "why"), [
    ('operator = ""', "protocol.operator", "empty"),
    ('specimen_id = "A\\nB"', "protocol.specimen_id", "one line"),
    (f'notes = ["ok", "{"x" * 1001}"]', "protocol.notes", "note 2: 1001 characters, at most 1000"),
    ("notes = []", "protocol.notes", "empty list"),
    ("operator = 7", "protocol.operator", "string"),
])
def test_the_schema_refuses_bad_metadata_naming_the_field(tmp_path: Path, header: str, field: str, why: str) -> None:
    with pytest.raises(ProtocolFileError) as err:
        load_protocol(_protocol(tmp_path, header + "\n"))
    msg = str(err.value)
    assert f": {field}: " in msg and why in msg and "\n" not in msg, msg


def test_a_bad_operator_option_is_one_line_and_nothing_runs(tmp_path: Path) -> None:
    proc = _bench("run", str(_protocol(tmp_path)), "--virtual-time", "--no-live", "--out", str(tmp_path / "runs"),
                  "--operator", "x" * 101)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0
    assert "--operator: 101 characters, at most 100 allowed" in proc.stderr
    assert not (tmp_path / "runs").exists()


def test_the_fit_goes_beside_the_run_and_report_and_inspect_find_it(run_file: Path, tmp_path: Path) -> None:
    sidecar = run_file.parent / (run_file.stem + ".fit.hdf5")  # the documented name
    fit_args = ["--population", "6", "--generations", "2", "--no-polish", "--starts", "1", "--no-intervals"]
    res = runner.invoke(app, ["fit", str(run_file), *fit_args], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert sidecar.exists()
    with h5py.File(run_file, "r") as f:
        assert "fit" not in f  # the run file is left as the run wrote it
        start = f.attrs["start_time"]
    with h5py.File(sidecar, "r") as f:
        assert f.attrs["format"] == "dea-bench fits 1" and f.attrs["run_start_time"] == start
        rms = float(f["fit/membrane-1"].attrs["rms"])
        mu0 = float(f["fit/membrane-1/values"][0])
    fits = read_fits(run_file)
    assert [(Path(x["file"]), x["group"]) for x in fits] == [(sidecar, "/fit/membrane-1")]
    data = json.loads(runner.invoke(app, ["inspect", str(run_file), "--json"]).stdout)
    assert data["fits"][0]["file"] == str(sidecar) and data["fits"][0]["parameters"]["mu0"] == mu0
    # the report plots the stored fit (its legend names the rms); a glob's fit file is skipped, not read as a run
    res = runner.invoke(app, ["report", str(run_file), str(sidecar), "--out", str(tmp_path / "report")],
                        env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "skipping 1 fit file" in res.output
    svg = (tmp_path / "report" / "displacement_vs_time.svg").read_text(encoding="utf-8")
    assert f"fitted model (fit membrane-1, rms {rms * 1e6:.1f} µm over this record)" in svg

    # --into: into the run file as before; both places are read
    res = runner.invoke(app, ["fit", str(run_file), *fit_args, "--into"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    with h5py.File(run_file, "r") as f:
        assert list(f["fit"]) == ["membrane-1"]
    with h5py.File(sidecar, "r") as f:
        assert list(f["fit"]) == ["membrane-1"]  # unchanged
    assert sorted(Path(x["file"]).name for x in read_fits(run_file)) == sorted([run_file.name, sidecar.name])
    data = json.loads(runner.invoke(app, ["inspect", str(run_file), "--json"]).stdout)
    assert len(data["fits"]) == 2


def test_a_fit_file_of_another_run_is_refused(run_file: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / run_file.name
    shutil.copy(run_file, copy)
    stale = tmp_path / (run_file.stem + ".fit.hdf5")
    with h5py.File(stale, "w") as f:
        f.attrs.update({"format": "dea-bench fits 1", "run_file": run_file.name,
                        "run_start_time": "2000-01-01T00:00:00.000+00:00", "protocol_sha256": "0" * 64})
    with pytest.raises(ValueError, match="belongs to another run"):
        read_fits(copy)
    res = runner.invoke(app, ["inspect", str(copy), "--json"])  # the run is still shown, the fit file named
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["fits"] == [] and "belongs to another run" in data["fits_error"] and data["state"] == "completed"
    # the report, too: the record's figures without the model, the title naming the fit file it could not read (it
    # exited 2 and left a folder holding only report.json, a second tester)
    res = runner.invoke(app, ["report", str(copy), "--out", str(tmp_path / "rep")], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert (tmp_path / "rep" / "displacement_vs_time.png").stat().st_size > 10_000


def _simulate(*args: str) -> str:
    res = runner.invoke(app, ["simulate", *args], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    return res.output


def test_quantities_with_units_equal_plain_numbers_on_the_command_line() -> None:
    with_units = _simulate("thesis", "--voltage", "7kV", "--duration", "9 s", "--temperature", "296 K",
                           "--frequency", "0.1111 Hz")
    plain = _simulate("thesis", "--voltage", "7000", "--duration", "9", "--temperature", "296", "--frequency",
                      "0.1111")
    assert with_units == plain
    assert re.search(r"│\s+1 │\s+7\.6\d\d │", plain)  # first peak at 7 kV [mm] (test_cli: 7.675 at 1/9 Hz)
    lsdea = _simulate("lsdea", "isometric", "--prototype", "3", "--voltage", "6 kV", "--frequency", "5Hz",
                      "--position", "0.1 m")
    assert lsdea == _simulate("lsdea", "isometric", "--prototype", "3", "--voltage", "6000", "--frequency", "5")
    assert re.search(r"force crest-to-trough 1\.14\d+ N", lsdea)


@pytest.mark.parametrize(("args", "says"), [
    (["thesis", "--voltage", "7kZ"], "--voltage '7kZ': expected a voltage such as '7 kV'"),
    (["thesis", "--temperature", "296 kV"], "--temperature '296 kV': expected a temperature"),
    (["thesis", "--voltage", "13kV"], "--voltage 13kV: 13000 V is outside 0 … 12000 V"),
    (["lsdea", "--mass", "3 kg"], "--mass 3 kg: 3 kg is outside 0 … 2 kg"),
])
def test_a_bad_unit_is_refused_in_one_line(args: list[str], says: str) -> None:
    proc = _bench("simulate", *args)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and says in proc.stderr, proc.stderr


def test_the_help_names_the_unit_and_the_quantity_form() -> None:
    out = " ".join(runner.invoke(app, ["simulate", "thesis", "--help"], terminal_width=200).output.split())
    assert "Peak voltage Vmax [V]. 0–12 kV; or with a unit: 7kV." in out
    out = " ".join(runner.invoke(app, ["fit", "--help"], terminal_width=200).output.split())
    assert "RUN.fit.hdf5" in out and "--into" in out and "campaign's fit is stored with every one" in out


def test_a_fit_checked_at_its_start_is_stored_whoever_holds_the_file_then(run_file: Path, tmp_path: Path) -> None:
    """`bench fit KILLED.h5` checked the killed file at its start (ended: no writer), fitted for 32 s, then refused to
    store ("not finalised … fit results go with ended runs only", exit 2) — the check was made again at the end, where
    a process holding the file open (a reader) makes a crashed file look written (a second tester). The fit stores
    what its start check accepted; without that check the file's state is still looked at."""
    import shutil

    from bench.identify.core import FitResult
    from bench.identify.store import write_fit

    copy = tmp_path / run_file.name
    shutil.copy(run_file, copy)
    with h5py.File(copy, "r+") as f:  # a file that reads as being written (its state running, not orphaned here)
        f.attrs["complete"] = False
        f["status/state"][0] = b"running"
    one = np.array([1.0])
    result = FitResult(["mu0"], ["Pa"], one, one * 0.0, one * 2.0, 0.0, "sae", 0.0, 1, 1, 1, 0.1, one, np.eye(1),
                       one * np.nan)
    with pytest.raises(ValueError, match="not finalised"):
        write_fit(copy, "membrane", result, [str(copy)], sidecar=True)
    assert write_fit(copy, "membrane", result, [str(copy)], sidecar=True, ended=True) == "/fit/membrane-1"
    # a fit across specimens carries the warning bench fit printed; the catalogue reads it (a specimen's history
    # leaves such a fit out: tests/test_catalog_rows.py)
    from bench.storage.catalog import _fits
    from bench.storage.runfile import open_run

    write_fit(copy, "membrane", result, [str(copy)], sidecar=True, ended=True, mixed="not of one specimen: S1 vs S7")
    fits = _fits(copy, open_run(copy, streams=False).attrs, in_file=False)
    assert [f["mixed_specimens"] for f in fits] == ["", "not of one specimen: S1 vs S7"], fits
