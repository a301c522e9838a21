"""Output people and scripts rely on: units kept in help and tables, no truncation when redirected, --json."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.runtime.run import execute, plan_run

ROOT = Path(__file__).resolve().parent.parent
SHORT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
runner = CliRunner()


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory, short_run: Path) -> Path:
    # a long folder name: a redirected table must print it whole, not cut or wrapped at 80 columns
    out = tmp_path_factory.mktemp("output") / ("a-rather-long-folder-name-for-the-campaign-" * 3).strip("-")
    out.mkdir()
    # the session's run of SHORT on its rig (conftest's short_run, made once), copied: not the same run made again
    shutil.copy2(short_run, out / "run.h5")
    return out / "run.h5"


@pytest.mark.parametrize(("args", "units"), [
    (["simulate", "thesis", "--help"], ["Simulated time [s]", "Peak voltage Vmax [V]", "Temperature [K]"]),
    (["simulate", "lsdea", "--help"], ["Hung mass [kg]", "Blocked aperture [mm]", "from 50 mm [mm]"]),
])
def test_help_pages_keep_their_units(args: list[str], units: list[str]) -> None:
    res = runner.invoke(app, args, env={"COLUMNS": "300"})
    assert res.exit_code == 0
    for text in units:
        assert text in " ".join(res.output.split()), text


def test_shell_completion_is_offered() -> None:
    res = runner.invoke(app, ["--help"])
    assert "--install-completion" in res.output and "--show-completion" in res.output


def test_simulate_table_headers_keep_units() -> None:
    res = runner.invoke(app, ["simulate", "thesis", "--duration", "9"])
    assert res.exit_code == 0, res.output
    assert "peak u [mm]" in res.output and "at t [s]" in res.output and "lag [s]" in res.output


def test_redirected_inspect_prints_whole_paths_and_columns(run_file: Path) -> None:
    res = runner.invoke(app, ["inspect", str(run_file)])  # CliRunner: stdout is not a terminal
    assert res.exit_code == 0, res.output
    assert str(run_file) in res.output  # on one line, not cut at 80 columns
    assert "from [s]" in res.output and "displacement (m)" in res.output
    assert all("…" not in line for line in res.output.splitlines() if "sha256" not in line)  # no cut values


def test_inspect_and_validate_json(run_file: Path) -> None:
    res = runner.invoke(app, ["inspect", str(run_file), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output)  # nothing but the JSON on stdout
    assert data["state"] == "completed" and data["complete"] is True
    laser = data["streams"]["laser"]
    assert laser["units"]["displacement"] == "m" and laser["samples"] > 50_000
    assert data["events"][0]["kind"] == "run"
    res = runner.invoke(app, ["validate", str(SHORT), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output)
    assert data["valid"] is True and data["rig"] == "thesis-daq-sim"
    assert data["duration_s"] == pytest.approx(11.0) and 6000 < data["peak_voltage_V"] <= data["voltage_limit_V"]


def test_report_json_and_figures_in_png_pdf_svg(run_file: Path, tmp_path: Path) -> None:
    res = runner.invoke(app, ["report", str(run_file), "--out", str(tmp_path), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output)
    (run,) = data["runs"]
    (step,) = [s for s in run["steps"] if s["kind"] == "thesis"]
    assert data["units"]["peak_first"] == "m" and 0.004 < step["figures"]["peak_first"] < 0.01
    pngs = [Path(p) for p in data["figures"]]
    assert pngs and all(p.suffix == ".png" and p.exists() for p in pngs)
    for png in pngs:
        assert png.with_suffix(".pdf").read_bytes()[:4] == b"%PDF"
        assert b"<svg" in png.with_suffix(".svg").read_bytes()[:2000]
    from PIL import Image

    with Image.open(pngs[0]) as im:
        assert im.info["dpi"][0] == pytest.approx(300, abs=1)
    svg = (tmp_path / "displacement_vs_time.svg").read_text(encoding="utf-8")
    assert "measured displacement (laser)" in svg and "measured voltage (amplifier monitor)" in svg
    assert "commanded voltage (DAQ output, every scan)" in svg  # the default rig is hardware-timed


def test_run_writes_a_log_beside_the_run_file_and_quiet_prints_only_its_path(tmp_path: Path) -> None:
    res = runner.invoke(app, ["-q", "run", str(SHORT), "--virtual-time", "--out", str(tmp_path), "--no-live"])
    assert res.exit_code == 0, res.output
    (run_file,) = tmp_path.glob("*.h5")
    assert res.stdout == f"{run_file}\n"  # f=$(bench -q run …): the run file's path, one line, nothing else
    log = run_file.with_suffix(".log").read_text(encoding="utf-8")
    # the run stops when the stream's last packet (≤ 17 ms of scans) has come: 11.00–11.03 s
    assert "planned: 2 steps, 11.0 s" in log
    assert re.search(r"event t=11\.0[0-3]\d s step 1 stop: protocol completed", log)
    assert "completed: protocol completed; high voltage: 0 V commanded" in log
    res = runner.invoke(app, ["run", str(SHORT), "--dry-run"])
    assert res.exit_code == 0 and "dry run" in res.output  # -q does not stick to the next command


def test_fit_json_is_the_stored_fit(tmp_path: Path) -> None:
    """`bench fit --json`: one JSON document on stdout (nothing else) that matches the fit file written beside
    the run — names, values and rms read back with the store's reader."""
    from bench.identify.store import read_fits

    # the short protocol with a 0.7-s identification step: the intervals' profiles cost in proportion to the record,
    # and what is tested here is the JSON against the stored fit, not the fit (this record's intervals still come
    # in all three statuses: determined, bounded on one side only, not determined); 0.7 s, not 0.5 s: a fit needs
    # ten measured points per parameter (160; the 0.5-s record held 151)
    protocol = tmp_path / "identification-0s7.toml"
    protocol.write_text(SHORT.read_text(encoding="utf-8").replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/')
                        .replace("duration_s = 10.0", "duration_s = 0.7"), encoding="utf-8")
    result = execute(plan_run(protocol), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    run = Path(result.path)
    res = runner.invoke(app, ["fit", str(run), "--population", "6", "--generations", "2", "--starts", "2", "--json",
                              "--polish-iterations", "20"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    (stored,) = read_fits(run)
    assert data["model"] == "membrane" and data["rms_unit"] == "m"
    assert [p["name"] for p in data["parameters"]] == stored["names"]
    assert [p["value"] for p in data["parameters"]] == pytest.approx(list(stored["values"]), rel=1e-12)
    assert data["rms"] == pytest.approx(stored["rms"], rel=1e-12)
    # the intervals: method and level stated in both, the same ends, a status per parameter, both starts listed
    assert stored["interval_method"] == "profile likelihood" and stored["confidence"] == 0.95
    for j, p in enumerate(data["parameters"]):
        assert p["interval_method"] == "profile likelihood" and p["confidence"] == 0.95
        assert p["interval"] == pytest.approx([stored["interval_lower"][j], stored["interval_upper"][j]], rel=1e-12)
        assert p["status"] == stored["status"][j]
        assert p["status"] in ("determined", "bounded on one side only", "not determined")
        assert p["interval"][0] <= p["value"] <= p["interval"][1] or p["name"] in data["intervals"]["disagree"]
    assert [s["seed"] for s in data["intervals"]["starts"]] == [1, 2] == [s["seed"] for s in stored["trust"]["starts"]]
    assert all(p["unit"] for p in data["parameters"])


def test_benchmark_json_prints_figures_only() -> None:
    res = runner.invoke(app, ["benchmark", "run", "--quick", "--json"])
    assert res.exit_code == 0, res.output
    tables = json.loads(res.stdout)  # {table title: [figure, …]}
    figures = [f for rows in tables.values() for f in rows]
    assert figures and all({"name", "value", "unit"} <= set(f) for f in figures)
    assert any(f["unit"] == "× real time" and f["value"] > 0 for f in figures)
    # every ratio names the CPU it was measured on (issue 24: a speed-up is one CPU's), as the kernel reports it
    ratios = [f for f in figures if f["unit"] in ("×", "× real time")]
    assert ratios and all(f["cpu"] == ratios[0]["cpu"] for f in ratios)
    cpu = ratios[0]["cpu"]
    info = Path("/proc/cpuinfo").read_text()
    model = next(line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name"))
    flags = set(next(line.split(":", 1)[1].split() for line in info.splitlines() if line.startswith("flags")))
    assert cpu["model"] == model and cpu["flags"] and set(cpu["flags"]) <= flags
    assert ("avx2" in cpu["flags"]) == ("avx2" in flags) and ("avx512f" in cpu["flags"]) == ("avx512f" in flags)
    assert cpu["logical_cpus"] == len(os.sched_getaffinity(0)) and cpu["numba_threads"] >= 1 and cpu["numba_target"]


def test_a_width_in_the_environment_when_the_console_is_made_does_not_stick(monkeypatch: pytest.MonkeyPatch) -> None:
    """The console is made on first print: COLUMNS at that moment (some earlier command's) must not cut a later
    redirected output to its width."""
    import io

    from bench.cli.console import REDIRECTED_WIDTH, BenchConsole

    monkeypatch.setenv("COLUMNS", "80")
    console = BenchConsole(file=io.StringIO())  # not a terminal
    assert console.size.width == 80  # COLUMNS sets the width while it is there
    monkeypatch.delenv("COLUMNS")
    assert console.size.width == REDIRECTED_WIDTH
    assert BenchConsole(file=io.StringIO(), width=100).size.width == 100  # an explicit width stays


def test_a_run_that_latched_its_rig_says_so_and_how_to_reset_it() -> None:
    from bench.cli.common import console
    from bench.cli.run import _print_result
    from bench.runtime.engine import RunResult

    def shown(result: RunResult) -> str:
        with console.capture() as cap:
            _print_result(result, "thesis-daq-sim")
        return " ".join(cap.get().split())

    ended = RunResult("runs/x.h5", "error", "lost link: amplifier", 3.0, 1.0, 10, safe_path="0 V NOT commanded",
                      latched="interlock: output path dead: 0 V could not be commanded")
    text = shown(ended)
    assert "rig thesis-daq-sim latched: interlock: output path dead" in text
    assert "bench interlock reset thesis-daq-sim --why" in text
    assert "latched" not in shown(RunResult("runs/y.h5", "completed", "protocol completed", 3.0, 1.0, 10))


@pytest.mark.parametrize(("args", "named"), [
    (["report", "--out", "", "x.h5"], "--out"),
    (["report", "--out=", "x.h5"], "--out"),
    (["runs", "list", "--dir", ""], "--dir"),
    (["report", ""], "argument 2 of the command line"),
    # after an option that takes no value, the empty word is an argument of its own (a reviewer: "--yes: empty")
    (["run", "--yes", ""], "argument 3 of the command line"),
    (["run", "--no-live", "--out", ""], "--out"),
])
def test_an_empty_argument_is_refused_naming_it(args: list[str], named: str, tmp_path: Path) -> None:
    """``--out ''`` was taken as the current folder (Path('') is '.'; outside tester): an empty argument — an unset
    shell variable, most often — is refused before any command runs, naming it, with nothing made."""
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        res = runner.invoke(app, args)
    finally:
        os.chdir(here)
    assert res.exit_code == 2, res.output
    assert res.output.startswith(f"error: {named}: empty") and res.output.count("\n") == 1, res.output
    assert not list(tmp_path.iterdir())  # nothing made
