"""The interlock latch belongs to the exact rig name: rigs whose names clean up alike for a file name
(``thesis sim``, ``thesis-sim``) never share a latch, a latch file of the older form (no hash) is still honoured,
and resetting a rig that is not latched is an error, not a reset."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from bench.cli import app
from bench.runtime import latch as rig_latch

runner = CliRunner()


def test_names_that_clean_up_alike_have_their_own_latches() -> None:
    rig_latch.latch("thesis-sim", "interlock: host stall 2.5 s", "m1.h5")
    assert rig_latch.latched("thesis sim") is None
    assert rig_latch.latched("thesis/sim") is None
    assert rig_latch.latch_path("thesis sim") != rig_latch.latch_path("thesis-sim")
    res = runner.invoke(app, ["interlock", "reset", "thesis sim", "--why", "x", "--operator", "bo"])
    assert res.exit_code == 2, res.output
    assert "rig thesis sim: not latched: nothing to reset (latched: thesis-sim)" in " ".join(res.output.split())
    # the rig file where its name goes said "not latched (latched: thesis-sim)" (an outside tester)
    res = runner.invoke(app, ["interlock", "reset", "rigs/thesis-sim.toml", "--why", "x", "--operator", "bo"])
    assert res.exit_code == 2, res.output
    assert "rigs/thesis-sim.toml: give the rig's name, not its file (latched: thesis-sim)" in " ".join(
        res.output.split()), res.output
    was = rig_latch.latched("thesis-sim")  # the other rig's latch is untouched
    assert was is not None and was["fault"] == "interlock: host stall 2.5 s"
    res = runner.invoke(app, ["interlock", "reset", "thesis-sim", "--why", "x", "--operator", "bo"])
    assert res.exit_code == 0 and "rig thesis-sim: reset (was: interlock: host stall 2.5 s)" in res.output
    assert rig_latch.latched("thesis-sim") is None


def test_both_rigs_latched_are_listed_apart_and_reset_apart() -> None:
    rig_latch.latch("thesis-sim", "fault a", "a.h5")
    rig_latch.latch("thesis sim", "fault b", "b.h5")
    assert set(rig_latch.all_latched()) == {"thesis-sim", "thesis sim"}
    assert rig_latch.reset("thesis sim", "bo", "checked") is not None
    assert rig_latch.latched("thesis sim") is None
    was = rig_latch.latched("thesis-sim")
    assert was is not None and was["fault"] == "fault a"


def test_an_old_format_latch_file_still_latches_its_own_rig_only() -> None:
    old = rig_latch.state_dir() / "interlock-thesis-sim.json"  # as a bench before the hashed names wrote it
    old.parent.mkdir(parents=True, exist_ok=True)
    old.write_text(json.dumps({"rig": "thesis-sim", "fault": "old fault", "where": "r.h5", "at": "then"}))
    was = rig_latch.latched("thesis-sim")
    assert was is not None and was["fault"] == "old fault"
    assert rig_latch.latched("thesis sim") is None
    assert rig_latch.reset("thesis sim", "bo", "x") is None and old.exists()
    res = runner.invoke(app, ["interlock", "status", "--json"])
    assert res.exit_code == 0 and set(json.loads(res.output)["latched"]) == {"thesis-sim"}
    assert rig_latch.reset("thesis-sim", "bo", "x") is not None and not old.exists()
    assert rig_latch.latched("thesis-sim") is None


def test_status_prints_one_readable_line_per_latch_not_a_dict() -> None:
    """The tester's finding: ``bench interlock status`` printed the latch's raw Python dict. The latches are written
    here by hand, in the file form the state folder holds, so the values expected are the test's own."""
    folder = rig_latch.state_dir()
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "interlock-lab-rig.json").write_text(json.dumps({
        "rig": "lab-rig", "fault": "interlock: host stall 2.5 s", "where": "runs/r1.h5",
        "at": "2026-11-27T10:00:00+00:00", "drive": "/dev/ttyUSB0 unit 1 channel 0",
        "drive_ids": ["/dev/ttyUSB0 unit 1 channel 0"]}))
    (folder / "interlock-sim-rig.json").write_text(json.dumps({
        "rig": "sim-rig", "fault": "output verifier: monitor 3000 V, commanded 0 V", "where": "manual.log",
        "at": "2026-11-27T11:00:00+00:00"}))
    res = runner.invoke(app, ["interlock", "status"], terminal_width=60)
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines == [
        "latched lab-rig: interlock: host stall 2.5 s; at 2026-11-27T10:00:00+00:00; in runs/r1.h5; "
        "drive /dev/ttyUSB0 unit 1 channel 0",
        "latched sim-rig: output verifier: monitor 3000 V, commanded 0 V; at 2026-11-27T11:00:00+00:00; "
        "in manual.log"], res.output


def test_reset_without_why_of_a_rig_not_latched_says_not_latched_and_asks_nothing() -> None:
    """The tester's finding: ``bench interlock reset RIG`` without --why asked for a reason before saying the rig was
    not latched. Not latched is said first, with the exit of the not-latched path (2, as with --why above); the
    reason is asked for only where there is a latch to reset."""
    res = runner.invoke(app, ["interlock", "reset", "thesis-sim"])
    assert res.exit_code == 2, res.output
    assert "rig thesis-sim: not latched: nothing to reset" in " ".join(res.output.split())
    assert "--why" not in res.output
    rig_latch.latch("thesis-sim", "fault a", "a.h5")
    res = runner.invoke(app, ["interlock", "reset", "thesis-sim"])
    assert res.exit_code == 2 and "--why" in res.output and "not latched" not in res.output, res.output
    assert rig_latch.latched("thesis-sim") is not None
