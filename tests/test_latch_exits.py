"""The README's standard, on the exits a run cannot record itself: a fault latches until an operator resets it.

* a bench process killed while it drives the rig (``kill -9``, a crash, a power cut) never commanded nor verified
  0 V: the next start on the rig finds the marker it left and latches the rig;
* a supervisor limit trip (current, voltage, position, force beyond the rig's limits) latches the rig, after its
  verified 0 V, as an interlock fault does;
* ``bench run --resume FILE --why …`` resets the latch only once the rig has connected: a resume that fails to start
  leaves the rig latched, and the history says why the reset was withheld.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import RigConfig, load_rig
from bench.runtime import latch as rig_latch
from bench.runtime import run as run_mod
from bench.runtime.engine import Engine
from bench.runtime.latch import LatchedError, latched, refuse_if_latched, state_dir
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from drivers.errors import InstrumentConnectionError
from tests.campaign_kill import kill_at_step
from tests.conftest import ROOT

SHORT = ROOT / "protocols" / "short"
SWEEPS = SHORT / "thesis-sweeps-short.toml"  # 5 kV, then 7 kV (step 4: the 7-kV drive), on thesis-daq-sim
IDENT = SHORT / "thesis-identification-short.toml"
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"


def _history() -> str:
    return (state_dir() / "interlock.log").read_text(encoding="utf-8")


# ---------------------------------------------------------------- kill -9 while the rig is energised
def test_a_run_killed_while_driving_latches_its_rig_until_an_operator_resets_it(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}  # this test's own state folder (conftest)
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(SWEEPS), "--virtual-time", "--out", str(runs),
                             "--no-live"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_at_step(proc, runs, 4, 180)  # once the run's log shows the 7-kV drive (step 4) started
    killed = next(runs.glob("*.h5"))
    assert open_run(killed, streams=False).state == "running"  # killed: no end recorded, no shutdown
    rig_name = load_rig(DAQ_RIG).name
    status = CliRunner().invoke(app, ["interlock", "status", "--json"])
    assert status.exit_code == 0, status.stdout + status.stderr
    found = json.loads(status.stdout)["latched"]
    assert rig_name in found, status.stdout
    fault = found[rig_name]["fault"]
    assert "killed?" in fault and "zero neither commanded nor verified" in fault and str(killed) in fault
    # the latch is stamped when found; when the process last wrote its file is said (an outside tester)
    last = datetime.fromtimestamp(killed.stat().st_mtime).astimezone().isoformat(timespec="seconds")
    assert f"{killed} (its file last written {last}): zero" in fault, fault
    assert found[rig_name]["where"] == str(killed)
    # a new run on the rig is refused before anything is touched, naming the reset command
    refused = subprocess.run([sys.executable, "-m", "bench", "run", str(IDENT), "--virtual-time", "--yes",
                              "--no-live", "--out", str(tmp_path / "next")], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=300)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert "interlock latched" in refused.stderr and f"bench interlock reset {rig_name}" in refused.stderr
    assert not (tmp_path / "next").exists()
    # the operator's reset lets it run again
    ok = CliRunner().invoke(app, ["interlock", "reset", rig_name, "--why", "output checked at 0 V", "--operator",
                                  "ada"])
    assert ok.exit_code == 0, ok.stdout + ok.stderr
    assert latched(rig_name) is None
    assert "by ada: output checked at 0 V" in _history()
    result = execute(plan_run(IDENT), tmp_path / "after.h5", virtual=True)
    assert result.state == "completed", result.reason
    assert latched(rig_name) is None and not list(state_dir().glob("armed-*.json"))  # a clean end disarms


def _marker(rig_name: str, **changes: object) -> Path:
    """This process's armed marker for ``rig_name``, its record changed by ``changes``."""
    path = rig_latch.arm(rig_name, "run file test.h5")
    record = json.loads(path.read_text())
    record.update({"flock": False, **changes} if changes else {})  # a changed one: as a marker without a lock
    path.write_text(json.dumps(record))
    return path


def test_a_marker_of_a_live_process_is_no_latch_and_a_dead_or_reused_pid_is() -> None:
    live = _marker("rig-a")  # this process: still running (another bench on the rig; its lock refuses)
    assert latched("rig-a") is None and live.exists()
    refuse_if_latched("rig-a")
    rig_latch.disarm(live)
    assert not live.exists()
    # two starts of one process on one rig (threads): one's end leaves the other's marker
    one, two = rig_latch.arm("rig-e", "run file one.h5"), rig_latch.arm("rig-e", "run file two.h5")
    rig_latch.disarm(one)
    assert two.exists()
    rig_latch.disarm(two)
    # the same process ID, started at another time: the ID was reused, the process that armed is gone
    _marker("rig-b", started="1")
    was = latched("rig-b")
    assert was is not None and "killed?" in was["fault"] and was["where"] == "run file test.h5"
    # a process ID that no process has: gone (a Linux pid is at most 2**22)
    _marker("rig-c", pid=2**22 + 7)
    with pytest.raises(LatchedError, match=r"killed\?.*bench interlock reset rig-c"):
        refuse_if_latched("rig-c")
    # another boot: gone whatever runs under that ID now
    _marker("rig-d", boot="another-boot")
    assert "rig-d" in rig_latch.all_latched()
    assert not list(state_dir().glob("armed-*.json"))  # each dead marker became a latch once
    assert rig_latch.reset("rig-c", "ada", "checked") is not None and latched("rig-c") is None


# ---------------------------------------------------------------- a supervisor limit trip latches
def _tiny_current_limit(plan: run_mod.Plan) -> None:
    limits = {**plan.rig.limits.model_dump(), "max_current_A": 1e-7}  # any drive's charging current is beyond it
    plan.rig = plan.program.rig = RigConfig.model_validate({**plan.rig.model_dump(), "limits": limits})


def test_a_limit_trip_latches_the_rig_after_its_verified_zero(tmp_path: Path) -> None:
    plan = plan_run(IDENT, ROOT / "rigs" / "thesis-sim.toml")
    _tiny_current_limit(plan)
    result = execute(plan, tmp_path / "trip.h5", virtual=True)
    assert result.state == "tripped" and "beyond the trip level" in result.reason, result.reason
    run = open_run(result.path)
    assert "verified" in run.reason  # 0 V commanded and read back: the trip is no unverified output
    was = latched(plan.rig.name)
    assert was is not None and "current" in was["fault"] and "beyond the trip level" in was["fault"]
    assert was["where"] == str(result.path) and was["at"]
    assert any(kind == "interlock" and "safety trip" in text for _, _, kind, text in run.event_list())
    assert "beyond the trip level" in result.latched  # the command line says the rig latched
    with pytest.raises(LatchedError, match="bench interlock reset thesis-sim"):  # the next protocol is refused
        execute(plan_run(IDENT, ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "next.h5", virtual=True)
    assert not (tmp_path / "next.h5").exists()
    rig_latch.reset(plan.rig.name, "ada", "limit checked")
    refuse_if_latched(plan.rig.name)


def test_a_limit_trip_in_manual_control_latches_the_rig(tmp_path: Path) -> None:
    from bench.runtime.manual import ManualSession

    rig = load_rig(ROOT / "rigs" / "thesis-sim.toml")
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _line: None) as s:
        assert list(state_dir().glob("armed-*.json"))  # the session may energise the rig: armed
        assert s.execute("voltage 5 kV").status == "ok"
        s._sim.plant.inject_breakdown()  # the specimen fails: the current monitor trips the supervisor
        trip = s.execute("watch 2 0.5")
        assert trip.status == "trip" and "current" in trip.text and "latched" in trip.text, trip
        assert s.execute("voltage 1 kV").status == "refused"  # nothing energises until `reset WHY`
        was = latched(rig.name)
        assert was is not None and "safety trip" in was["fault"] and was["where"] == str(tmp_path / "s.log")
    assert not list(state_dir().glob("armed-*.json"))  # the session's end made the rig safe: disarmed
    assert latched(rig.name) is not None  # the latch outlives the session


# ---------------------------------------------------------------- a resume that fails to connect keeps the latch
def unplug_the_first_instrument(monkeypatch: pytest.MonkeyPatch) -> object:
    """Runs from here on build instruments whose first refuses to connect (an unplugged adapter); returns the real
    ``build_instruments`` to put back."""
    real = run_mod.build_instruments

    def unplugged(*args: object, **kwargs: object):  # type: ignore[no-untyped-def]
        inst = real(*args, **kwargs)  # type: ignore[arg-type]
        _role, drv = next(iter(inst.items()))

        def refuse() -> None:
            raise InstrumentConnectionError("daq", "cannot connect: adapter unplugged (test)")

        drv.connect = refuse  # type: ignore[method-assign]
        return inst

    monkeypatch.setattr(run_mod, "build_instruments", unplugged)
    return real


def test_a_resume_that_cannot_connect_leaves_the_latch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def stop_early(engine: Engine, _sim: object) -> None:
        engine.request_stop("test: stopped early")

    first = execute(plan_run(IDENT), tmp_path / "first.h5", virtual=True, on_engine=stop_early)
    assert first.state == "interrupted", first.reason
    rig_name = load_rig(DAQ_RIG).name
    rig_latch.latch(rig_name, "test fault", str(first.path))
    real = unplug_the_first_instrument(monkeypatch)
    args = ["run", "--resume", str(first.path), "--virtual-time", "--no-live", "--why", "fault cleared",
            "--operator", "ada"]
    failed = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert failed.exit_code == 2 and "cannot connect" in failed.stderr, failed.stdout + failed.stderr
    was = latched(rig_name)
    assert was is not None and was["fault"] == "test fault"  # nothing started: the latch stays
    assert "reset withheld\t" + rig_name + "\tby ada: fault cleared" in _history()
    assert "cannot connect: adapter unplugged (test)" in _history()
    assert "\treset\t" not in _history()
    monkeypatch.setattr(run_mod, "build_instruments", real)
    resumed = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert resumed.exit_code == 0, resumed.stdout + resumed.stderr
    assert latched(rig_name) is None
    assert "\treset\t" + rig_name + "\tby ada: fault cleared" in _history()
    second = next(p for p in tmp_path.glob("*.h5") if p.name != "first.h5")
    assert "ada: fault cleared" in open_run(second, streams=False).attrs["interlock_reset"]


def test_a_dead_manual_session_s_last_sign_is_its_readings_if_they_are_later(tmp_path: Path) -> None:
    """A session's log is written per command and its readings between them: the last sign of life is the later of
    the log and its readings' files (a reviewer: an hour of `wait` after the last command read as the log's time)."""
    log = tmp_path / "manual-x.log"
    log.write_text("")
    readings = tmp_path / "manual-x.h5"
    readings.write_bytes(b"")
    os.utime(log, (1_800_000_000, 1_800_000_000))
    os.utime(readings, (1_800_003_600, 1_800_003_600))  # an hour later
    said = rig_latch._last_sign(f"manual session {log}")
    last = datetime.fromtimestamp(1_800_003_600).astimezone().isoformat(timespec="seconds")
    assert said == f" (its file last written {last})", said
    assert rig_latch._last_sign(f"manual session {tmp_path / 'gone.log'}") == ""
