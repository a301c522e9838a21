"""What `bench pause`, `bench resume` and `bench run --resume` say of a file: a hint never suggests a command
that cannot work (a manual-control session, a campaign whose every step completed), a resume that would change
nothing is refused in one line (not paused) while a second pause is sent and said (already paused), and a resumed
file names the protocol file the
campaign was planned from, not the temporary copy its resume was planned from."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import load_rig
from bench.runtime.control import control_path
from bench.runtime.engine import Engine
from bench.runtime.manual import ManualSession
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.runfile import open_run
from tests.campaign_kill import wait_for
from tests.conftest import ROOT
from tests.load_trips import load_trip

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
RIG = ROOT / "rigs" / "thesis-sim.toml"
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "300"}
runner = CliRunner()


def said(res) -> str:  # type: ignore[no-untyped-def]
    return " ".join(res.output.split())


def test_a_manual_control_session_file_is_no_campaign_to_resume_or_pause(tmp_path: Path) -> None:
    log = tmp_path / "m1.log"
    with ManualSession(load_rig(RIG), log, virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 1kV").status == "ok"
        m1 = s.data_file
    assert m1 is not None
    assert open_run(m1, streams=False).attrs["session_log"]
    res = runner.invoke(app, ["run", "--resume", str(m1), "--virtual-time", "--no-live"])
    assert res.exit_code == 2, res.output
    assert said(res) == f"error: run file {m1}: a manual-control session, not a protocol run: nothing to resume"
    for cmd in (["resume", str(m1), "--why", "x"], ["pause", str(m1)]):
        res = runner.invoke(app, cmd)
        assert res.exit_code == 2 and "manual-control session" in said(res), res.output
        assert "bench run --resume" not in said(res)
    # listed with no steps (its own `end` line, at step −1, read as a completed step: "steps 1/0", outside tester)
    res = runner.invoke(app, ["runs", "list", "--dir", str(tmp_path), "--json"],
                        env={"BENCH_CATALOG": f"sqlite:///{tmp_path / 'cat.sqlite'}"})
    assert res.exit_code == 0, res.output
    assert [(r["steps_completed"], r["steps_total"]) for r in json.loads(res.stdout)] == [(0, 0)], res.stdout


def test_hints_suggest_a_resume_only_where_one_can_continue_the_campaign(tmp_path: Path) -> None:
    plan = plan_run(SWEEPS, RIG)
    done = execute(plan, tmp_path / "done.h5", virtual=True)
    assert done.state == "completed", done.reason
    res = runner.invoke(app, ["pause", done.path])
    assert res.exit_code == 2 and "every step completed" in said(res), res.output
    assert "bench run --resume" not in said(res)
    # a pause is refused as a pause (an outside tester: pausing a completed run said "nothing to resume")
    assert said(res) == f"error: run file {done.path}: no run is writing it (completed): nothing to pause; every " \
        "step completed (completed)", res.output

    def stop_at_3(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        sim.clock.subscribe(lambda _now: engine.request_stop("the test") if engine.now() >= 3.0 else None)

    stopped = execute(plan, tmp_path / "stopped.h5", virtual=True, on_engine=stop_at_3)
    assert stopped.state == "interrupted", stopped.reason
    res = runner.invoke(app, ["resume", stopped.path, "--why", "x"])
    assert res.exit_code == 2 and f"bench run --resume {stopped.path}" in said(res), res.output


def test_a_resumed_file_names_the_protocol_file_its_campaign_was_planned_from(tmp_path: Path) -> None:
    """Its ``protocol_path`` is the original file's (the resume plans from a temporary copy of the stored text,
    deleted once planned)."""
    plan = plan_run(SWEEPS, RIG)

    def stop_at_3(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        sim.clock.subscribe(lambda _now: engine.request_stop("the test") if engine.now() >= 3.0 else None)

    stopped = execute(plan, tmp_path / "stopped.h5", virtual=True, on_engine=stop_at_3)
    assert stopped.state == "interrupted", stopped.reason
    original = open_run(stopped.path, streams=False).attrs["protocol_path"]
    assert original == str(SWEEPS)
    plan2, link, _ = plan_resume(stopped.path)
    assert str(plan2.protocol.path) == original
    resumed = execute(plan2, tmp_path / "resumed.h5", virtual=True, resume=link)
    assert resumed.state == "completed", resumed.reason
    assert open_run(resumed.path, streams=False).attrs["protocol_path"] == original
    res = runner.invoke(app, ["inspect", resumed.path])
    # no temporary folder of the resume's planning (tempfile's tmpXXXXXXXX), wherever the checkout lives (/tmp in CI)
    assert str(SWEEPS) in said(res) and not re.search(r"/tmp[a-z0-9_]{8}/", said(res)), res.output


def test_pause_and_resume_refuse_what_would_change_nothing(tmp_path: Path) -> None:
    """A run in its own process, on the wall clock (it holds still long enough for a command to look at it):
    `bench resume` while it runs is refused in one line and sends nothing; a second `bench pause` once it is paused
    is sent all the same (it would withdraw a resume on its way) and recorded as a request that changed nothing; the
    pause and the resume that do something are recorded as such."""
    bench = [sys.executable, "-m", "bench"]
    proc = subprocess.Popen([*bench, "run", str(SWEEPS), "--rig", str(RIG), "--out", str(tmp_path), "--no-live",
                             "--yes"], cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*bench, *args], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)

    def cli_here(*args: str) -> subprocess.CompletedProcess[str]:
        """The same command through typer's runner in this process (the control word is a file beside the run's:
        this process is another terminal as much as a new one); the refused resume below is a process of its own,
        and tests/test_pause_resume.py runs pause and resume as processes. A fresh interpreter per command costs
        seconds, on a run that holds still in wall time."""
        from typer.testing import CliRunner

        from bench.cli import app

        res = CliRunner().invoke(app, list(args))
        leaked = "" if res.exception is None or isinstance(res.exception, SystemExit) else repr(res.exception)
        return subprocess.CompletedProcess(args, res.exit_code, res.stdout, res.stderr + leaked)

    try:
        wait_for(lambda: any(tmp_path.glob("*.log")) and "step 0 start" in next(tmp_path.glob("*.log")).read_text(),
                 120, "the run to start")
        run_file = next(tmp_path.glob("*.h5"))
        log = run_file.with_suffix(".log")
        not_paused = cli("resume", str(run_file), "--why", "go on")
        assert not_paused.returncode == 2, not_paused.stdout + not_paused.stderr
        assert f"run file {run_file}: not paused: nothing to resume" in " ".join(not_paused.stderr.split())
        assert not control_path(run_file).exists()  # nothing sent
        first = cli_here("pause", str(run_file), "--why", "adjust the laser", "--operator", "ada")
        if first.returncode != 0 and load_trip(open_run(run_file, streams=False)):  # the wall-clock run tripped on its
            pytest.skip(f"the loaded host tripped the wall-clock run before its pause: {first.stderr}")  # starved host
        assert first.returncode == 0 and "pause asked" in first.stdout, first.stdout + first.stderr
        wait_for(lambda: " pause: " in log.read_text() or "interlock: host stall" in log.read_text(), 60,
                 "the pause event")
        if " pause: " not in log.read_text():  # the wall-clock run found its host stalled first and latched (seen
            pytest.skip("the loaded host stalled the wall-clock run before its pause")  # beside a loaded suite)
        again = cli_here("pause", str(run_file), "--why", "twice", "--operator", "bo")
        # a pause is never refused (a resume may be on its way that the file does not show yet): sent, and said
        assert again.returncode == 0 and "already paused" in again.stdout, again.stdout + again.stderr
        assert "ada" in again.stdout  # who paused it
        assert json.loads(control_path(run_file).read_text())["why"] == "twice"
        wait_for(lambda: "pause asked by bo" in log.read_text(), 60, "the second pause's request event")
        resumed = cli_here("resume", str(run_file), "--why", "laser fixed", "--operator", "cy")
        assert resumed.returncode == 0, resumed.stdout + resumed.stderr
        wait_for(lambda: " resume: " in log.read_text(), 60, "the resume event")
        proc.send_signal(signal.SIGINT)  # the rest of the campaign in wall time would add nothing here
        out, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 1 and "Traceback" not in out, out
    run = open_run(run_file, streams=False)
    assert run.state == "interrupted", run.reason
    kinds = [(kind, text) for _t, _s, kind, text in run.event_list()
             if kind in ("pause", "resume", "request") and not text.startswith("stop requested")]
    assert [k for k, _ in kinds] == ["pause", "request", "resume"], kinds
    assert "ada" in kinds[0][1] and "bo" in kinds[1][1] and "already paused" in kinds[1][1] and "cy" in kinds[2][1]


def test_the_readme_says_what_a_second_pause_does() -> None:
    """The README said a second `bench pause` on a paused run "sends nothing … exit 2" (found by an outside tester),
    while the command sends it and exits 0 by design (tests above: a resume may be on its way that the file does not
    show yet). The README's paragraph on pause and resume now says what the command does."""
    text = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    para = text[text.index("**Pause and resume.**"):]
    para = para[:para.index("**", len("**Pause and resume.**"))]
    assert "already paused" in para and "the pause is sent anyway" in para and "exit 0" in para, para
    assert "is not, send nothing" not in para  # the old sentence that put pause among the refusals


def test_a_reason_or_a_name_that_is_not_one_line_of_text_is_refused_before_anything(tmp_path: Path) -> None:
    """An outside tester: `bench resume … --why $'x\\ay'` was accepted and its bell character went into the run's
    events, and `bench pause --operator ""` was taken as the login name where `bench run` refuses an empty operator;
    `devices control --script missing.txt` connected the rig first, then said "[Errno 2]" and left a session file
    marked error. Each is one line naming the option, exit 2, before any file is touched or any rig connected."""
    run = tmp_path / "run.h5"  # no such run: the options are refused before the file is looked at
    for args, line in ((["resume", str(run), "--why", "x\ay"], "error: --why: one line of printable text"),
                       (["pause", str(run), "--why", "a\nb"], "error: --why: one line of printable text"),
                       (["pause", str(run), "--operator", ""], "error: --operator: empty"),
                       (["resume", str(run), "--why", "ok", "--operator", " "], "error: --operator: empty")):
        res = runner.invoke(app, args, env={"COLUMNS": "300"})
        assert res.exit_code == 2 and res.output.startswith(line) and res.output.count("\n") == 1, (args, res.output)
    log = tmp_path / "s.log"
    res = runner.invoke(app, ["devices", "control", str(RIG), "--script", str(tmp_path / "missing.txt"), "--log",
                              str(log), "--virtual-time"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and res.output == f"error: --script {tmp_path / 'missing.txt'}: not found\n", res.output
    assert not log.exists() and not log.with_suffix(".h5").exists()
    if Path("/dev/null").exists():  # a device read as a file: an empty script, not "not found" (a later tester)
        res = runner.invoke(app, ["devices", "control", str(RIG), "--script", "/dev/null", "--log", str(log),
                                  "--virtual-time"], env={"COLUMNS": "300"})
        assert res.exit_code == 0 and "(0 commands)" in res.output, res.output


def test_a_resume_under_another_specimen_id_is_refused_with_nothing_touched(tmp_path: Path, short_run: Path) -> None:
    """`bench run --resume F --specimen-id M9` continued specimen M2's campaign under M9 with no word (outside
    tester): the campaign's history split over two specimens. A resume continues the same specimen: another ID is
    refused in one line before the file is touched; the campaign's own ID is accepted."""
    import shutil

    import h5py

    run = tmp_path / "m2.h5"
    shutil.copy2(short_run, run)
    with h5py.File(run, "r+") as f:
        f.attrs["specimen_id"] = "M2"
    before = run.read_bytes()
    res = runner.invoke(app, ["run", "--resume", str(run), "--specimen-id", "M9", "--virtual-time", "--dry-run"])
    assert res.exit_code == 2, res.output
    assert said(res).startswith(f"error: --specimen-id M9: {run} is a campaign on specimen M2"), res.output
    assert run.read_bytes() == before
    res = runner.invoke(app, ["run", "--resume", str(run), "--specimen-id", "M2", "--virtual-time", "--dry-run"])
    assert "--specimen-id" not in said(res), res.output  # (a completed run: nothing to resume, said as before)


def test_a_resume_on_a_rig_that_refuses_the_protocol_names_the_run_file(tmp_path: Path, short_run: Path) -> None:
    """`bench run --resume F --rig other.toml`, where the other rig refuses the campaign's protocol, named a
    temporary copy of the stored protocol (/tmp/tmp…/p.toml) that no longer exists (an outside tester): the line
    names the protocol stored in the run file."""
    import shutil

    run = tmp_path / "r.h5"
    shutil.copy2(short_run, run)
    low = tmp_path / "low.toml"
    text = (ROOT / "rigs" / "thesis-daq-sim.toml").read_text(encoding="utf-8")
    low.write_text(text.replace("max_voltage_V = 8000.0", "max_voltage_V = 1000.0"), encoding="utf-8")
    res = runner.invoke(app, ["run", "--resume", str(run), "--rig", str(low), "--virtual-time", "--dry-run"])
    assert res.exit_code == 2, res.output
    line = said(res)
    assert f"the protocol stored in {run}" in line and "exceeds the rig limit 1000 V" in line, res.output
    assert tempfile.gettempdir() + "/tmp" not in line.replace(str(tmp_path), ""), res.output
