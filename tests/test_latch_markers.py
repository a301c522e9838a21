"""Armed markers judged by the lock their process holds, not by what a process ID means here.

* a bench killed while armed (SIGKILL: no handler runs) leaves a marker whose ``flock`` the kernel released: the
  next look latches its rig, even when the marker's host name is another (a container restarted under a new name);
* a live bench holds its marker's lock: no latch, the marker kept, and ``bench interlock status`` lists it, even
  when its process ID names no process here (another PID namespace);
* on Windows ``os.kill`` ends the process it is given, whatever the signal: a look at the markers never calls it;
* a user who may only read the state folder sees a dead marker as a latch (nothing written, no crash).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.runtime import latch as rig_latch
from bench.runtime.latch import latched
from tests.conftest import ROOT

# a child that arms rig-k, says where its marker is, then waits to be killed (or told to end)
CHILD = """
import sys
from bench.runtime import latch
path = latch.arm("rig-k", "run file child.h5")
print(path, flush=True)
sys.stdin.readline()
"""


def _child() -> tuple[subprocess.Popen[str], Path]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", CHILD], cwd=ROOT, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    return proc, Path(proc.stdout.readline().strip())


def _rewrite(path: Path, **changes: object) -> None:
    """Change the marker's record in place (the same file: its lock stays with its holder)."""
    record = json.loads(path.read_text())
    record.update(changes)
    with path.open("r+") as fh:
        fh.truncate(0)
        fh.write(json.dumps(record))


def test_a_killed_armed_child_latches_even_under_another_host_name() -> None:
    proc, marker = _child()
    try:
        assert marker.exists() and latched("rig-k") is None  # alive: it holds the lock
        _rewrite(marker, host="container-before-restart")  # the host name it had is not this one
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    was = latched("rig-k")
    assert was is not None and "killed?" in was["fault"] and was["where"] == "run file child.h5"
    assert not marker.exists()


def test_a_live_child_holding_its_marker_is_no_latch_and_is_listed(tmp_path: Path) -> None:
    proc, marker = _child()
    try:
        # its process ID names no process here (another PID namespace): the lock it holds says it runs
        _rewrite(marker, pid=2**22 + 11, started="1", boot="another-boot")
        assert latched("rig-k") is None and marker.exists()
        status = CliRunner().invoke(app, ["interlock", "status"], env={"COLUMNS": "300"})
        assert status.exit_code == 0, status.stdout + status.stderr
        assert f"armed by pid {2**22 + 11}" in status.stdout and "rig-k" in status.stdout, status.stdout
        assert "no rig latched" in status.stdout
        as_json = CliRunner().invoke(app, ["interlock", "status", "--json"])
        assert [m["rig"] for m in json.loads(as_json.stdout)["armed"]] == ["rig-k"]
    finally:
        proc.communicate("\n", timeout=30)  # it ends without disarming: now the lock is free
    assert latched("rig-k") is not None


def test_on_windows_a_look_at_the_markers_never_calls_os_kill(monkeypatch: pytest.MonkeyPatch) -> None:
    def kill(*_args: object) -> None:
        raise AssertionError("os.kill called on Windows: it would terminate the process")

    monkeypatch.setattr(sys, "platform", "win32")
    monkeypatch.setattr(os, "kill", kill)
    marker = rig_latch.arm("rig-w", "run file w.h5")  # no flock there: its process ID decides
    other = marker.with_name(marker.name.replace("armed-", "armed-x"))
    other.write_text(json.dumps({**json.loads(marker.read_text()), "pid": 4242}))  # another bench's marker
    assert latched("rig-w") is None
    assert "rig-w" not in rig_latch.all_latched()
    alive = rig_latch.armed()
    assert len(alive) == 2 and all(m["alive"] for m in alive)
    assert json.loads(marker.read_text())["flock"] is False
    rig_latch.disarm(marker)
    other.unlink()


def test_a_reader_of_the_state_folder_sees_a_dead_marker_as_latched(monkeypatch: pytest.MonkeyPatch) -> None:
    proc, marker = _child()
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)

    def denied(*_args: object) -> None:  # a folder this user may only read (root would write it all the same)
        raise PermissionError(13, "Permission denied")

    with monkeypatch.context() as mp:
        mp.setattr(rig_latch, "_write", denied)
        mp.setattr(rig_latch, "_history", denied)
        status = CliRunner().invoke(app, ["interlock", "status", "--json"])
        assert status.exit_code == 0, status.stdout + status.stderr
        was = json.loads(status.stdout)["latched"]["rig-k"]
        assert "killed?" in was["fault"] and "not written" in was["fault"]
        assert latched("rig-k") is not None
        assert marker.exists()  # nothing was written: the next look by a writer latches it
    assert latched("rig-k") is not None and not marker.exists()


# ---------------------------------------------------------------- a state folder the marker cannot be written to
def test_a_state_folder_that_cannot_hold_the_marker_refuses_in_one_line(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("BENCH_STATE_DIR", str(blocker / "state"))  # not a directory: nothing can be written there
    runs = tmp_path / "runs"
    ident = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    result = CliRunner().invoke(app, ["run", str(ident), "--virtual-time", "--no-live", "--yes", "--out", str(runs)],
                                env={"COLUMNS": "400"})
    assert result.exit_code == 2, result.stdout + result.stderr
    error = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(error) == 1, result.stderr
    assert f"state folder {blocker / 'state'}" in error[0] and "armed marker cannot be written" in error[0], error
    # checked before the run file is made (outside tester, 2026-11-28: a run file was left, its reason this error)
    assert not list(runs.glob("*.h5")), list(runs.glob("*.h5"))


# ---------------------------------------------------------------- a resume's reset is for the latch seen at planning
@pytest.mark.parametrize("when", ["check_watchdog", "build_instruments"])  # before the start's check / before connect
def test_a_resume_reset_refuses_a_latch_that_came_after_planning(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                  when: str) -> None:
    from bench.rig import load_rig
    from bench.runtime import run as run_mod
    from bench.runtime.engine import Engine
    from bench.runtime.run import execute, plan_run

    def stop_early(engine: Engine, _sim: object) -> None:
        engine.request_stop("test: stopped early")

    ident = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    first = execute(plan_run(ident), tmp_path / "first.h5", virtual=True, on_engine=stop_early)
    assert first.state == "interrupted", first.reason
    rig_name = load_rig(ROOT / "rigs" / "thesis-daq-sim.toml").name
    rig_latch.latch(rig_name, "fault seen at planning", str(first.path))
    real = getattr(run_mod, when)

    def relatch(*args: object, **kwargs: object) -> object:  # another fault latches the rig after the plan
        rig_latch.reset(rig_name, "bob", "cleared elsewhere")
        rig_latch.latch(rig_name, "a later fault", "manual session other.log")
        monkeypatch.setattr(run_mod, when, real)
        return real(*args, **kwargs)

    monkeypatch.setattr(run_mod, when, relatch)
    args = ["run", "--resume", str(first.path), "--virtual-time", "--no-live", "--why", "fault cleared",
            "--operator", "ada"]
    refused = CliRunner().invoke(app, args, env={"COLUMNS": "400"})
    assert refused.exit_code == 2, refused.stdout + refused.stderr
    error = [line for line in refused.stderr.splitlines() if line.strip()]
    assert len(error) == 1 and "latched again" in error[0] and "a later fault" in error[0], refused.stderr
    was = latched(rig_name)
    assert was is not None and was["fault"] == "a later fault"  # not reset by ada's --why, given for the other
    history = (rig_latch.state_dir() / "interlock.log").read_text(encoding="utf-8")
    assert f"\treset\t{rig_name}\tby ada" not in history


def test_an_unwritable_history_does_not_hide_why_a_resume_failed(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from bench.rig import load_rig
    from bench.runtime import run as run_mod
    from bench.runtime.engine import Engine
    from bench.runtime.run import execute, plan_run

    def stop_early(engine: Engine, _sim: object) -> None:
        engine.request_stop("test: stopped early")

    ident = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    first = execute(plan_run(ident), tmp_path / "first.h5", virtual=True, on_engine=stop_early)
    rig_latch.latch(load_rig(ROOT / "rigs" / "thesis-daq-sim.toml").name, "test fault", str(first.path))
    from tests.test_latch_exits import unplug_the_first_instrument

    def denied(_line: str) -> None:  # the state folder became read-only: the history cannot take the line
        raise PermissionError(13, "Permission denied", "interlock.log")

    unplug_the_first_instrument(monkeypatch)
    monkeypatch.setattr(run_mod, "note", denied)
    args = ["run", "--resume", str(first.path), "--virtual-time", "--no-live", "--why", "fault cleared"]
    failed = CliRunner().invoke(app, args, env={"COLUMNS": "400"})
    assert failed.exit_code == 2, failed.stdout + failed.stderr
    error = [line for line in failed.stderr.splitlines() if line.startswith("error:")]
    assert len(error) == 1 and "cannot connect: adapter unplugged" in error[0], failed.stderr  # the run's own error


# a child that arms rig-f, forks a grandchild that lives on (multiprocessing's fork start does this), says both
# PIDs, then waits to be killed
FORKING = """
import os, sys, time
from bench.runtime import latch
path = latch.arm("rig-f", "run file forking.h5")
r, w = os.pipe()
pid = os.fork()
if pid == 0:  # the fork's handlers have run once the child runs its own code: it says so
    os.write(w, b"x")
    time.sleep(60)
    os._exit(0)
os.read(r, 1)  # (under load the child may not have run at all when its parent is killed: a race of the test's)
print(path, pid, flush=True)
sys.stdin.readline()
"""


def test_a_forked_child_does_not_keep_a_killed_bench_s_marker_alive() -> None:
    """A reviewer: a fork copies the marker's descriptor, and an flock belongs to the open file the copies share —
    the bench killed, its still-running grandchild kept the lock and the rig read as armed, not latched."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", FORKING], cwd=ROOT, env=env, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    path, grandchild = proc.stdout.readline().split()
    try:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        was = latched("rig-f")
        assert was is not None and "killed?" in was["fault"], was
        assert not Path(path).exists()
    finally:
        if proc.poll() is None:
            proc.kill()
        os.kill(int(grandchild), signal.SIGKILL)


def test_a_marker_disarmed_between_a_look_s_open_and_its_lock_is_no_latch(monkeypatch: pytest.MonkeyPatch) -> None:
    """A reviewer's forced interleaving: a look opens the marker, the owner disarms (unlinks, then lets go of the
    lock), the look's lock succeeds — and a clean end was latched as a killed bench."""
    marker = rig_latch.arm("rig-r", "run file clean.h5")
    real_flock = rig_latch._flock

    def disarm_first(fd: int, exclusive: bool) -> bool | None:
        rig_latch.disarm(marker)  # the owner's clean end, after the look opened the file
        return real_flock(fd, exclusive)

    monkeypatch.setattr(rig_latch, "_flock", disarm_first)
    assert rig_latch._lock_free(marker) is False
    monkeypatch.setattr(rig_latch, "_flock", real_flock)
    assert latched("rig-r") is None
