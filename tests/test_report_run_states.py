"""`bench report` on what a lab's runs/ folder holds besides completed runs: a temperature sweep (each step at the
temperature its set step logged), a stopped run and the file that resumed it (state, reason, steps left, the
step numbering `bench run --resume` uses), a manual-control session's readings (skipped, or refused alone; `bench
fit` refuses it).

Expected temperatures and step counts come from protocols/short/thesis-sweeps-short.toml: a sweep of two points
(5 kV at 266 K, 7 kV at 316 K), each a 0-s chamber step, a 5-s drive and a 2-s recovery (6 steps).
"""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from bench.analysis.runs import analyse
from bench.cli import app
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
THESIS_RIG = ROOT / "rigs" / "thesis-sim.toml"
GRID = tomllib.loads(SWEEPS.read_text(encoding="utf-8"))["steps"][0]
TEMPERATURES = GRID["over"]["T"]  # [266.0, 316.0]: one per sweep point, set before its drive
STEPS = len(TEMPERATURES) * len(GRID["steps"])  # 6


def _cli(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return res.exit_code, res.output


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A completed sweep; one stopped ("Ctrl-C") 2.3 s into its first drive, the `bench run --resume --dry-run`
    announcement of its continuation, and the file that continued it; a scripted manual session's readings."""
    d = tmp_path_factory.mktemp("states")
    done = execute(plan_run(SWEEPS), d / "done" / "sweep.h5", virtual=True)
    assert done.state == "completed", done.reason

    def ctrl_c(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        def at(_now: float) -> None:
            if engine.snapshot.step == 1 and engine.program_now() > 2.3:
                engine.request_stop("Ctrl-C")
        sim.clock.subscribe(at)

    stopped = execute(plan_run(SWEEPS), d / "camp" / "a.h5", virtual=True, on_engine=ctrl_c)
    assert stopped.state == "interrupted", stopped.reason
    code, announced = _cli("run", "--resume", str(stopped.path), "--virtual-time", "--dry-run")
    assert code == 0, announced
    (d / "announced.txt").write_text(announced, encoding="utf-8")
    plan, link, _ = plan_resume(stopped.path)
    resumed = execute(plan, d / "camp" / "b.h5", virtual=True, resume=link)
    assert resumed.state == "completed", resumed.reason
    script = d / "cmds.txt"
    script.write_text("voltage 2kV\nwatch 1 0.25\n", encoding="utf-8")
    code, out = _cli("devices", "control", str(THESIS_RIG), "--virtual-time", "--log", str(d / "session.log"),
                     "--script", str(script))
    assert code == 0, out
    return {"done": Path(done.path), "a": Path(stopped.path), "b": Path(resumed.path),
            "session": d / "session.h5", "announced": d / "announced.txt"}


def test_each_step_of_a_temperature_sweep_is_reported_at_the_temperature_set_before_it(runs: dict[str, Path],
                                                                                       tmp_path: Path) -> None:
    """The 7-kV point was reported at 266 K: its chamber step logs 316 K a little after the program time the
    drive starts at, and the report compared the change with the program time."""
    assert [s.temperature for s in analyse(runs["done"]).steps] == TEMPERATURES  # what --json and the plots show
    code, text = _cli("report", str(runs["done"]), "--out", str(tmp_path))
    assert code == 0, text
    row = next(line for line in text.splitlines() if "T [K]" in line)
    assert [c.strip() for c in row.split("│") if c.strip()] == ["T [K]", *(f"{T:g}" for T in TEMPERATURES)], row
    assert "run completed" not in text and "interrupted" not in text  # a completed run: no state line
    # the fit reads the same history: the 7-kV drive's inputs at 316 K from its recorded start
    r = open_run(runs["done"], streams=False)
    assert float(r.temperature_at(r.step_starts()[4])) == TEMPERATURES[1]


def test_a_stopped_run_says_so_and_a_resumed_campaign_is_numbered_as_bench_run_resume_announces_it(
        runs: dict[str, Path], tmp_path: Path) -> None:
    code, out = _cli("report", str(runs["a"]), "--out", str(tmp_path / "j"), "--json")
    assert code == 0, out
    run, _ = json.loads(out)["runs"]  # the stopped file, then the one that continued it (the campaign)
    assert run["state"] == "interrupted" and run["reason"].startswith("Ctrl-C")
    assert run["complete"] is True  # the file was finalised: all that ran is in it
    # the campaign's report (the stopped file, then the one that resumed it)
    code, text = _cli("report", str(runs["b"]), "--out", str(tmp_path / "c"))
    assert code == 0, text
    line = next(x for x in text.splitlines() if x.startswith("run interrupted"))
    assert "Ctrl-C" in line and "in step 2 of 6 (index 1, drive" in line  # stopped in the 5-kV drive
    assert f"steps 2–{STEPS} of {STEPS} not run to their end" in line and "the campaign goes on in b.h5" in line
    assert "run completed" not in text
    index = int(open_run(runs["b"], streams=False).attrs["resumed_at_step"])
    assert index == 1  # the 5-kV drive, the second step of the program
    said = f"step {index + 1} of {STEPS} (index {index})"
    assert f"resumed at {said}" in " ".join(text.split()), text
    assert said in " ".join(runs["announced"].read_text(encoding="utf-8").split())
    code, text = _cli("inspect", str(runs["b"]))
    assert f"resumed at {said}" in " ".join(text.split()), text
    (restart,) = [text for _, _, kind, text in open_run(runs["b"], streams=False).event_list() if kind == "restart"]
    assert f"{said[:-1]}, drive [voltage=5 kV, T=266.0]) restarts from its start" in restart, restart


def test_the_first_file_of_a_resumed_campaign_reports_and_inspects_as_the_whole_campaign(
        runs: dict[str, Path], tmp_path: Path) -> None:
    """The tester's morning: `bench report FIRST --json` listed only the first file ("INCOMPLETE … 9 of 80
    steps") and `inspect FIRST` showed no continuation; the last file gave the whole chain. The continuation
    links back only (b.h5's previous_file names a.h5), so the first file finds it in its folder."""
    assert open_run(runs["b"], streams=False).attrs["previous_file"] == "a.h5"  # the link the fixture wrote
    for given in ("a", "b"):
        code, out = _cli("report", str(runs[given]), "--out", str(tmp_path / given), "--json")
        assert code == 0, out
        got = json.loads(out)["runs"]
        assert [Path(r["file"]).name for r in got] == ["a.h5", "b.h5"], (given, got)
        assert [r["state"] for r in got] == ["interrupted", "completed"]
    code, text = _cli("inspect", str(runs["a"]))
    assert code == 0, text
    flat = " ".join(text.split())
    assert f"continued in {runs['b']}" in flat, text
    assert "a.h5 (interrupted" in flat and "b.h5 (completed" in flat, text  # the campaign's line
    code, out = _cli("inspect", str(runs["a"]), "--json")
    assert code == 0, out
    rec = json.loads(out)
    rec = rec[0] if isinstance(rec, list) else rec
    assert rec["continued_in"] == str(runs["b"])
    assert [Path(str(c["file"])).name for c in rec["campaign"]] == ["a.h5", "b.h5"]
    code, out = _cli("inspect", str(runs["b"]), "--json")  # the last file: nothing after it
    rec = json.loads(out)
    rec = rec[0] if isinstance(rec, list) else rec
    assert rec["continued_in"] is None


def test_a_fit_of_the_first_file_leaves_out_a_continuation_still_being_written(runs: dict[str, Path],
                                                                             tmp_path: Path) -> None:
    """`bench fit FIRST` took the files that continued it, also one still being written (its part so far, and the
    fit stored in it). Such a file (state `running`, no dead writer) is now left out of a fit, in one line;
    named, it is taken; a report still shows the whole campaign."""

    import h5py

    from bench.cli.analysis import runs_only

    folder = tmp_path / "camp"
    folder.mkdir()
    a, b = shutil.copy(runs["a"], folder / "a.h5"), shutil.copy(runs["b"], folder / "b.h5")
    with h5py.File(b, "r+") as f:  # as its writer leaves it while the run goes on
        f["status"]["state"][()] = b"running"
        f.attrs["complete"] = False
    from bench.cli.common import console

    with console.capture() as cap:
        got = runs_only([Path(a)], writing="fitting")
    text = " ".join(cap.get().split())
    assert got == [Path(a)], got
    assert f"leaving out {b}: still being written" in text, text
    assert runs_only([Path(a), Path(b)], writing="fitting") == [Path(a), Path(b)]  # named: taken
    assert runs_only([Path(a)]) == [Path(a), Path(b)]  # a report: the whole campaign


def test_a_manual_session_is_skipped_by_report_and_refused_alone_and_by_fit(runs: dict[str, Path],
                                                                            tmp_path: Path) -> None:
    session = runs["session"]
    assert open_run(session, streams=False).attrs.get("session_log")
    code, text = _cli("report", str(runs["a"]), str(session), "--out", str(tmp_path))
    assert code == 0, text
    skipped = [x for x in text.splitlines() if "manual-control session" in x]
    assert skipped == [f"skipping run file {session}: a manual-control session: no protocol steps to report"]
    assert "no step of a.h5 could be analysed" in text  # the other file reported (it stopped in its first drive)
    for cmd in (["report", str(session), "--out", str(tmp_path / "alone")], ["fit", str(session)]):
        code, text = _cli(*cmd)
        assert code == 2 and text.count("\n") == 1, text
        assert text.startswith(f"error: run file {session}: a manual-control session: "), text
        assert "protocol.toml" not in text and "valid data points" not in text
    assert not (tmp_path / "alone").exists()


def test_a_folder_of_stopped_runs_is_read_once_for_their_continuations(runs: dict[str, Path], tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """A reviewer: each stopped file searched its whole folder for a continuation, and report searched twice — 300
    files with 60 stopped ones, ~36k file opens. Six stopped runs (copies of a.h5 as other runs: their own run_id)
    beside a.h5 and b.h5: the folder is indexed once, so the opens grow with the files, not with their square."""

    import h5py

    import bench.storage.chain as chain_module

    folder = tmp_path / "camp"
    folder.mkdir()
    for name in ("a", "b"):
        shutil.copy(runs[name], folder / f"{name}.h5")
    others = []
    for k in range(6):
        other = folder / f"stopped{k}.h5"
        shutil.copy(runs["a"], other)
        with h5py.File(other, "r+") as h:
            h.attrs["run_id"] = f"stopped-run-{k}"
        others.append(other)
    opened: list[Path] = []
    real = chain_module.open_run

    def counting(path, streams=True):  # type: ignore[no-untyped-def]
        opened.append(Path(path))
        return real(path, streams=streams)

    monkeypatch.setattr(chain_module, "open_run", counting)
    chain_module._INDEX.clear()
    got = chain_module.with_chains([folder / "a.h5", *others])
    assert [p.name for p in got[:2]] == ["a.h5", "b.h5"] and len(got) == 8
    # 8 files: each opened for its chain, its run_id and its link (3 × 8), and the folder's index once (8);
    # searched per stopped file (7 of them × 8), the old way opened 56 for the search alone
    assert len(opened) <= 4 * 8, len(opened)


def test_a_run_stopped_at_once_is_refused_in_one_line_naming_the_file_and_why(tmp_path: Path) -> None:
    """`bench report` on a run interrupted before any drive ended exited 0 (outside tester): one line naming the
    file and why there is nothing to report, exit 2 as the other refusals (a manual session's file alone), nothing
    written. The step it stopped in follows from the protocol: its first step sets the chamber (a set step, no
    duration) for the first sweep point, so a stop at the first instant falls in the second, the 5-kV drive."""
    assert [x["type"] for x in GRID["steps"][:2]] == ["set", "waveform"]  # the premise, from the protocol file

    def at_once(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        sim.clock.subscribe(lambda _now: engine.request_stop("Ctrl-C"))

    stopped = execute(plan_run(SWEEPS), tmp_path / "a.h5", virtual=True, on_engine=at_once)
    assert stopped.state == "interrupted", stopped.reason
    code, text = _cli("report", str(stopped.path), "--out", str(tmp_path / "report"))
    assert code == 2 and text.count("\n") == 1, text
    assert text.startswith(f"error: run file {stopped.path}: nothing to report: no step of it could be analysed "
                           "(run interrupted at 0.00 s: Ctrl-C — in step 2 of "), text
    assert f"steps 2–{STEPS} of {STEPS} not run to their end" in text, text
    assert not (tmp_path / "report").exists()
    code, text = _cli("report", str(stopped.path), "--json")  # --json: the same refusal, no JSON half written
    assert code == 2 and text.startswith(f"error: run file {stopped.path}: nothing to report"), text
    # several files none of which has a step analysed: refused before any file's folder is written (each one's
    # report folder was made, then the campaign refused — last note's finding)
    twin = tmp_path / "copy" / "b.h5"
    twin.parent.mkdir()
    shutil.copy(stopped.path, twin)
    with h5py.File(twin, "r+") as h:  # another run stopped as at once (a copy of the same run is refused first)
        h.attrs["run_id"] = "stopped-at-once-2"
    code, text = _cli("report", str(stopped.path), str(twin), "--out", str(tmp_path / "several"))
    assert code == 2 and text.count("\n") == 1, text
    assert text.startswith(f"error: no step of {stopped.path}, {twin} could be analysed: nothing to report"), text
    assert not (tmp_path / "several").exists()
    code, text = _cli("report", str(stopped.path), str(twin))  # default folders: beside each file, none made
    assert code == 2 and not list(tmp_path.glob("**/*-report")), text


def test_a_file_killed_in_its_first_step_says_no_figures_not_an_empty_line(runs: dict[str, Path],
                                                                          tmp_path: Path) -> None:
    """`bench report` on a run killed (SIGKILL) as its first step began printed `figures: ` with nothing after it
    (outside tester): beside another run it says there are none; alone it is refused, saying why."""
    import os
    import subprocess
    import sys

    from tests.campaign_kill import kill_at_step

    # its own interlock state: the kill latches the rig, which no other test's run should find latched
    env = {**os.environ, "PYTHONPATH": str(ROOT), "BENCH_STATE_DIR": str(tmp_path / "state")}
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(ROOT / "protocols" / "short" /
                             "thesis-identification-short.toml"), "--no-live", "--out", str(tmp_path)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_at_step(proc, tmp_path, 0, 120)
    (killed,) = tmp_path.glob("*.h5")
    _, out = _cli("report", str(killed), str(runs["done"]), "--out", str(tmp_path / "report"))
    assert f"no step of {killed.name} could be analysed" in out, out  # the premise: nothing of it to plot
    figures = [ln for ln in out.splitlines() if ln.startswith("figures:")]
    assert figures[0] == "figures: none (nothing to plot)" and len(figures) == 2, out
    code, out = _cli("report", str(killed), "--out", str(tmp_path / "alone"))
    assert code == 2 and out.startswith(f"error: run file {killed}: nothing to report: no step of it could be "
                                        "analysed (incomplete file: "), out


def test_an_out_that_is_a_file_or_cannot_be_made_is_one_line_naming_it(short_run: Path, tmp_path: Path) -> None:
    """An outside tester: `bench report G.h5 --out G.h5` said "[Errno 17] File exists", `--out /proc/nope` "[Errno 2]",
    `bench plot --out p.txt` matplotlib's "Format 'txt' is not supported" naming no option. Each is one line naming
    what was given and why; nothing is written."""
    run = tmp_path / "G.h5"
    shutil.copy(short_run, run)
    before = run.read_bytes()
    code, text = _cli("report", str(run), "--out", str(run))
    assert code == 2 and text == f"error: {run}: a file, not a folder for the report: give a folder (a new one is " \
        "made)\n", text
    assert run.read_bytes() == before
    code, text = _cli("report", str(run), "--out", "/proc/nope")
    assert code == 2 and text.startswith("error: report folder /proc/nope: cannot be made (No such file or "
                                         "directory"), text
    code, text = _cli("plot", str(run), "--out", str(tmp_path / "p.txt"))
    assert code == 2 and text.startswith(f"error: --out {tmp_path / 'p.txt'}: '.txt' is not a figure format the "
                                         "plot writes (one of .png, "), text
    assert not (tmp_path / "p.txt").exists() and text.count("\n") == 1
    (tmp_path / "afile").write_text("mine")  # an existing file whose name has no type (a second tester; /dev/null)
    code, text = _cli("plot", str(run), "--out", str(tmp_path / "afile"))
    assert code == 2 and text == f"error: --out {tmp_path / 'afile'}: exists; bench plot does not overwrite files: " \
        "choose another name\n", text
    assert (tmp_path / "afile").read_text() == "mine"
