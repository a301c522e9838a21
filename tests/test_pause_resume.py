"""Pause and resume a run; continue a crashed or stopped campaign in a linked file (``bench run --resume``).

Expected values come from the protocol files (the voltage and aperture a step starts from) and from the plant's
own output history, never from the engine's account of itself.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.analysis.runs import analyse
from bench.runtime.control import NO_WORD, control_path, read_control, write_control
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.chain import chain
from bench.storage.runfile import RunFile, open_run
from tests.campaign_kill import kill_at_step, wait_for
from tests.conftest import ROOT
from tests.load_trips import load_trip

SHORT = ROOT / "protocols" / "short"
SWEEPS = SHORT / "thesis-sweeps-short.toml"  # 5 kV at 266 K, then 7 kV at 316 K: drive 5 s + recovery 2 s each
ISOPOTENTIAL = SHORT / "lsdea-isopotential-short.toml"
ADAM_RIG = ROOT / "rigs" / "thesis-sim.toml"
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"
ZERO_V = 5.0
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}


def events(run: RunFile, kind: str | None = None) -> list[tuple[float, int, str, str]]:
    return [e for e in run.event_list() if kind is None or e[2] == kind]


# ---------------------------------------------------------------- pause in a run (virtual time)
@pytest.mark.parametrize("rig", [ADAM_RIG, DAQ_RIG], ids=["adam", "daq"])
def test_a_pause_zeroes_the_output_records_on_and_restarts_the_step(tmp_path: Path, rig: Path) -> None:
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    t0: list[float] = []  # rig-clock time of run time 0

    def hook(engine: Engine, sim) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and not t0:
                t0.append(sim.clock.now() - engine.now())
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= 3.0:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= 6.0:
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    plan = plan_run(SWEEPS, rig)
    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    kinds = [k for _, _, k, _ in events(run) if k in ("pause", "resume", "restart", "offset")]
    assert kinds == ["pause", "resume", "restart", "offset"]
    (t_pause, step, _, text), = events(run, "pause")
    assert step == 1 and "by the test" in text  # step 1: the 5-kV drive (the protocol's second step)
    assert "ramping to 0 V over 0.25 s" in text  # (it said "output to 0 V" while 6 kV was still on: a tester)
    (t_resume, *_), = events(run, "resume")
    # the file says the output was seen at 0 V, not only asked to go there: the first reading of the pause
    (t_seen, _, _, seen), = events(run, "verify")
    v_seen = float(re.search(r"voltage monitor reads (-?\d+) V", seen).group(1))  # type: ignore[union-attr]
    assert t_pause + 0.25 < t_seen < t_resume and abs(v_seen) <= 50.0, seen  # the touch limit (README)
    # the plant's output: at 0 V from the end of the pause's ramp (shutdown_ramp_s 0.25 s) until the resume
    t = np.concatenate([b[0] for b in blocks]) - t0[0]
    v = np.concatenate([b[1] for b in blocks])
    assert np.abs(v[(t > t_pause + 0.25 + 0.05) & (t < t_resume)]).max() <= ZERO_V
    assert np.abs(v[t < t_pause]).max() > 1000.0  # it was under high voltage when paused
    # recording went on while paused
    amp = run.streams["amplifier"]
    assert ((amp.t > t_pause + 0.5) & (amp.t < t_resume)).sum() >= 10
    # the step restarted from its start: analysed once, on the window after the restart, both drives present
    (_, _, _, offset_text), = events(run, "offset")
    offset = float(offset_text.rsplit("+", 1)[1].split()[0])
    steps = {s.index: s for s in analyse(result.path).steps}
    assert sorted(steps) == [1, 4]
    # where the restarted step's waveform began: on a DAQ rig its stream's scan 0 (the `timing` event after the
    # restart), else its program time shifted by the offset
    scan_0 = [float(re.search(r"scan 0 at ([\d.]+) s", text).group(1))  # type: ignore[union-attr]
              for _, step_i, kind, text in run.event_list() if kind == "timing" and step_i == 1
              and "polled channels" in text]
    assert steps[1].t_start == pytest.approx(scan_0[-1] if scan_0 else plan.program.segments[1].t_start + offset)
    assert steps[1].t_start >= t_resume
    assert steps[1].voltage == pytest.approx(5000.0, rel=0.02) and steps[4].voltage == pytest.approx(7000.0, rel=0.02)
    assert result.run_time >= plan.program.duration + (t_resume - t_pause)


RELAX_LOOPS = """
[protocol]
name = "relax-loops"
description = "a 7-kV raised cosine, a relax the T7 plays from its stream-out loop, the raised cosine again"
rig = "{rig}"

[recording]
displacement_Hz = 2000
setpoint_Hz = 20

[[steps]]
type = "repeat"
count = 2

  [[steps.steps]]
  type = "waveform"
  name = "drive"
  channel = "voltage"
  kind = "raised_cosine"
  amplitude = "7 kV"
  frequency_Hz = 0.5
  duration_s = 2.0

  [[steps.steps]]
  type = "relax"
  name = "recovery"
  duration_s = 3.0
"""


@pytest.mark.parametrize(("pause_s", "paused_s"), [(1.5, 0.5), (0.05, 0.0)], ids=["mid-relax", "relax-start"])
def test_a_pause_in_a_relax_the_daq_loops_resumes_and_the_run_completes(
        tmp_path: Path, pause_s: float, paused_s: float) -> None:
    """A pause in a relax whose 0 V the T7 repeats from its stream-out loop (virtual time, watchdog set), resumed
    after ``paused_s``: the relax restarts and the campaign runs to its end — the outside tester's run ended on the
    resume's first top-up, refused as STREAM_OUT_BUFF_FULL (2613). Expected from the protocol: both drives reach
    7 kV, the output is at 0 V while paused (after the pause's 0.25-s ramp)."""
    proto = tmp_path / "relax-loops.toml"
    proto.write_text(RELAX_LOOPS.format(rig=DAQ_RIG.as_posix()))
    plan = plan_run(proto)
    relax = plan.program.segments[1]
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    t0: list[float] = []
    looping: list[bool] = []  # the twin's loop at the pause

    def hook(engine: Engine, sim) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))
        out = sim.twins["daq"].outs[0]

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and not t0:
                t0.append(sim.clock.now() - engine.now())
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= relax.t_start + pause_s:
                looping.append(out.loop_active)
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= relax.t_start + pause_s + paused_s:
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    (t_pause, step, _, _), = events(run, "pause")
    (t_resume, *_), = events(run, "resume")
    assert step == 1  # in the relax
    if pause_s > 1.0:
        assert looping == [True]  # the device repeated the relax's loop when the pause stopped its stream
    t = np.concatenate([b[0] for b in blocks]) - t0[0]
    v = np.concatenate([b[1] for b in blocks])
    if t_resume > t_pause + 0.3:
        assert np.abs(v[(t > t_pause + 0.25 + 0.05) & (t < t_resume)]).max() <= ZERO_V
    assert v[t < t_pause].max() > 6500.0 and v[t > t_resume].max() > 6500.0  # both drives played


def test_every_pause_and_resume_request_is_recorded_even_one_that_changes_nothing(tmp_path: Path) -> None:
    """A pause (ada), a second pause while paused (bo), the resume (ada), then a resume while running (cy), and a
    pause asked for while the completed run is being made safe (dee): one pause and one resume, and each request
    that changed nothing is a ``request`` event that says why (README: no pause or resume request is lost without a
    word)."""
    asked: list[str] = []
    plan = plan_run(SWEEPS, ADAM_RIG)

    def hook(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            t, state = engine.now(), engine.snapshot.state
            if not asked and state == "running" and t >= 3.0:
                asked.append("ada pause")
                engine.request_pause("ada")
            elif asked == ["ada pause"] and state == "paused" and t >= 4.0:
                asked.append("bo pause")
                engine.request_pause("bo")
            elif asked == ["ada pause", "bo pause"] and t >= 6.0:
                asked.append("ada resume")
                engine.request_resume("ada")
            elif len(asked) == 3 and state == "running" and t >= 9.0:
                asked.append("cy resume")
                engine.request_resume("cy")
            elif len(asked) == 4 and state == "stopping":
                asked.append("dee pause")
                engine.request_pause("dee")
        sim.clock.subscribe(at)

    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    assert len(asked) == 5, asked
    run = open_run(result.path)
    (_, _, _, paused), = events(run, "pause")
    (_, _, _, resumed), = events(run, "resume")
    assert "by ada" in paused and "by ada" in resumed
    texts = [text for *_, text in events(run, "request")]
    assert len(texts) == 3, texts
    assert "pause asked by bo" in texts[0] and "already paused" in texts[0]
    assert "resume asked by cy" in texts[1] and "not paused" in texts[1]
    assert "pause asked by dee" in texts[2] and "ended" in texts[2]


@pytest.mark.parametrize("rig", [ADAM_RIG, DAQ_RIG], ids=["adam", "daq"])
def test_a_paused_output_that_stays_up_latches(tmp_path: Path, rig: Path) -> None:
    """The amplifier's input sticks at 3 V (3 kV out, TREK gain 1000) from the pause's ramp on: the host commands
    0 V and the monitors, read while paused, say 3 kV. The verifier sees those readings (not only the supervisor,
    whose 8-kV limit 3 kV is well within): the run latches while paused, before the resume the test asks for."""
    stuck: list[float] = []  # run time of the fault

    def hook(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= 3.0:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and not stuck:  # the pause's ramp to 0 V is under way
                stuck.append(engine.now())
                set_input = sim.plant.set_amplifier_input
                set_input(3.0)
                sim.plant.set_amplifier_input = lambda _volts, at=None: set_input(3.0, at)
            if stuck and engine.now() >= stuck[0] + 2.0:
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(SWEEPS, rig), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "tripped" and "interlock: output mismatch" in result.reason, result.reason
    run = open_run(result.path)
    assert [k for _, _, k, _ in events(run) if k in ("pause", "resume")] == ["pause"]  # latched while paused
    amp = run.streams["amplifier"]
    paused = (amp.t > stuck[0]) & (amp.t < stuck[0] + 2.0)
    assert np.nanmax(amp.columns["voltage"][paused]) > 2500.0  # the file has what the monitors said


def test_the_control_file_is_read_only_when_whole(tmp_path: Path) -> None:
    run_file = tmp_path / "r.h5"
    seen = NO_WORD
    path = control_path(run_file)
    assert read_control(path, seen) == seen  # absent: nothing changes
    path.write_text('{"pause": tr', encoding="utf-8")  # half written
    assert read_control(path, seen) == seen
    path.write_text('{"pause": "yes"}', encoding="utf-8")  # not a boolean
    assert read_control(path, seen) == seen
    write_control(run_file, True, "ada", "check the clamp")
    first = read_control(path, seen)
    _, pause, who, stop = first
    assert pause and not stop and "ada" in who and "check the clamp" in who
    # a second word in the same second, on a filesystem that keeps whole seconds: still a new word (its inode)
    stamp = os.stat(path).st_mtime_ns
    write_control(run_file, False, "bo", "clamp fixed")
    os.utime(path, ns=(stamp, stamp))
    second = read_control(path, first)
    assert second != first and second[1] is False and "bo" in second[2]


def _paused_run(tmp_path: Path, why: str, until: str, env: dict[str, str],
                **popen: Any) -> tuple[subprocess.Popen[Any], Path, Path]:
    """A virtual-time run of the short thesis identification in its own process, paused from the start by its
    control file (what `bench pause` writes, by "ada" for ``why``), once its log has ``until``: the process, its
    run file and its log."""
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(SHORT / "thesis-identification-short.toml"),
                             "--virtual-time", "--out", str(tmp_path), "--no-live"], cwd=ROOT, env=env, **popen)
    try:
        wait_for(lambda: any(tmp_path.glob("*.h5")), 60, "the run file")
        run_file = next(tmp_path.glob("*.h5"))
        write_control(run_file, True, "ada", why)
        log = run_file.with_suffix(".log")
        wait_for(lambda: until in log.read_text(), 60, f"{until.strip()} in the run's log")
    except BaseException:
        proc.kill()
        raise
    return proc, run_file, log


def test_pause_and_resume_from_another_terminal(tmp_path: Path) -> None:
    """A virtual-time run in its own process, paused from the start by its control file (what `bench pause` writes),
    then `bench pause` (already paused: sent all the same, recorded as a request) and `bench resume` from another
    process while it holds."""
    bench = [sys.executable, "-m", "bench"]
    proc, run_file, _ = _paused_run(tmp_path, "before the first step", " pause: ", ENV, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
    try:
        refused = subprocess.run([*bench, "resume", str(run_file)], cwd=ROOT, env=ENV, capture_output=True, text=True)
        assert refused.returncode != 0 and "--why" in refused.stdout + refused.stderr
        paused = subprocess.run([*bench, "pause", str(run_file), "--why", "adjust the laser", "--operator", "ada"],
                                cwd=ROOT, env=ENV, capture_output=True, text=True)
        assert paused.returncode == 0 and "already paused" in paused.stdout, paused.stdout + paused.stderr
        assert json.loads(control_path(run_file).read_text())["why"] == "adjust the laser"  # sent all the same
        assert proc.poll() is None  # still paused
        resumed = subprocess.run([*bench, "resume", str(run_file), "--why", "laser fixed", "--operator", "bo"],
                                 cwd=ROOT, env=ENV, capture_output=True, text=True)
        assert resumed.returncode == 0, resumed.stdout + resumed.stderr
        out, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, out
    # the control file's last word (a resume here; a pause or stop elsewhere) meant nothing once the run ended: gone
    # (outside tester: left behind, still saying pause)
    assert not control_path(run_file).exists()
    run = open_run(run_file)
    assert run.state == "completed"
    (_, _, _, p_text), = events(run, "pause")
    (_, _, _, r_text), = events(run, "resume")
    assert "ada" in p_text and "before the first step" in p_text and "bo" in r_text and "laser fixed" in r_text
    after = subprocess.run([*bench, "pause", str(run_file)], cwd=ROOT, env=ENV, capture_output=True, text=True)
    assert after.returncode != 0 and "no run is writing it" in after.stderr  # and every step completed: no resume
    assert "every step completed" in after.stderr and "bench run --resume" not in after.stdout + after.stderr
    assert not control_path(run_file).exists()  # a refused pause writes none


# ---------------------------------------------------------------- a crashed or stopped campaign goes on
def test_a_killed_campaign_resumes_in_a_linked_file_and_reports_as_one(tmp_path: Path) -> None:
    bench = [sys.executable, "-m", "bench"]
    proc = subprocess.Popen([*bench, "run", str(SWEEPS), "--virtual-time", "--out", str(tmp_path), "--no-live"],
                            cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_at_step(proc, tmp_path, 4, 120)  # kill -9 once the second sweep point (the 7-kV drive) has started
    first = next(tmp_path.glob("*.h5"))
    assert open_run(first, streams=False).state == "running"  # killed: no end recorded
    # a copy released first by `bench recover` (as the README's recovery section has it) resumes at the same step
    released = tmp_path / "released" / first.name
    released.parent.mkdir()
    shutil.copy2(first, released)
    recovered = subprocess.run([*bench, "recover", str(released)], cwd=ROOT, env=ENV, capture_output=True,
                               text=True, timeout=120)
    assert recovered.returncode == 0, recovered.stdout + recovered.stderr
    assert open_run(released, streams=False).recovered_at
    killed_in = min(set(range(6)) - open_run(first, streams=False).completed_steps())
    plan, link, notes = plan_resume(released)
    assert plan.program.segments[link.step].index == killed_in and notes == []  # nothing left to recover
    # killed while driving: the host neither commanded nor verified 0 V, so the rig latched; without the operator's
    # reason the resume is refused before the file is touched (a tester: it was recovered first), with it it resets
    # the latch (tests/test_latch_exits.py)
    bare = subprocess.run([*bench, "run", "--resume", str(first), "--virtual-time", "--no-live"], cwd=ROOT, env=ENV,
                          capture_output=True, text=True, timeout=300)
    assert bare.returncode == 2 and "--why" in bare.stderr and "recovered" not in bare.stdout, bare.stdout + bare.stderr
    assert not open_run(first, streams=False).recovered_at
    resumed = subprocess.run([*bench, "run", "--resume", str(first), "--virtual-time", "--no-live", "--why",
                              "output checked at 0 V after the kill"], cwd=ROOT, env=ENV, capture_output=True,
                             text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    second = next(p for p in tmp_path.glob("*.h5") if p != first)
    log_text = second.with_suffix(".log").read_text(encoding="utf-8")
    assert f"bench run --resume {first} on rig" in log_text and "bench run None" not in log_text  # (a tester)
    links = chain(second)
    assert [ln.path.name for ln in links] == [first.name, second.name]
    a, b = open_run(first, streams=False), open_run(second, streams=False)
    assert b.state == "completed" and b.attrs["campaign_id"] == a.attrs["run_id"]
    assert b.attrs["protocol_sha256"] == a.attrs["protocol_sha256"]
    # every step of the protocol completed once over the campaign (6 steps: chamber, drive, recovery × 2)
    assert sorted(a.completed_steps() | b.completed_steps()) == list(range(6))
    assert not a.completed_steps() & b.completed_steps()
    with pytest.raises(ValueError, match=f"already resumed in {second}"):  # a second resume would fork the campaign
        plan_resume(first)
    # the report of the last file is the campaign's: both drives, each once, at the protocol's voltages (report and
    # fit in this process through typer's runner, same app and arguments: the commands above went through
    # `python -m bench`, and a fresh interpreter with the analysis imports costs seconds per call)
    from typer.testing import CliRunner

    from bench.cli import app

    rep = CliRunner().invoke(app, ["report", str(second), "--json", "--out", str(tmp_path / "report")],
                             env={"COLUMNS": "200"})
    assert rep.exit_code == 0, rep.stderr + repr(rep.exception)
    data = json.loads(rep.stdout)
    assert [r["file"] for r in data["runs"]] == [str(first), str(second)]
    volts = sorted(s["voltage_V"] for r in data["runs"] for s in r["steps"])
    assert volts == [pytest.approx(5000.0, rel=0.02), pytest.approx(7000.0, rel=0.02)]
    # and the fit takes both files as records of one campaign
    fit = CliRunner().invoke(app, ["fit", str(second), "--population", "6", "--generations", "1", "--no-polish",
                                   "--starts", "1", "--no-intervals", "--json"], env={"COLUMNS": "200"})
    assert fit.exit_code == 0, fit.stderr + repr(fit.exception)
    assert json.loads(fit.stdout)["runs"] == [str(first), str(second)]


def test_a_stopped_motor_campaign_resumes_from_the_state_its_step_starts_in(tmp_path: Path) -> None:
    """Stopped during the 7-kV tensile cycles: the resumed file first moves the motor back to the aperture the
    cycles start from (50 mm, the waveform's offset) at 0 V, then ramps to 7 kV (the sweep's voltage), then
    restarts the step (lsdea-isopotential-short.toml)."""
    def stop_in_cycles(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            name = engine.snapshot.step_name
            if "tensile" in name and "7 kV" in name and engine.program_now() > engine.program.segments[
                    engine.snapshot.step].t_start + 1.0:
                engine.request_stop("stopped by the test")
        sim.clock.subscribe(at)

    first = execute(plan_run(ISOPOTENTIAL), tmp_path / "first.h5", virtual=True, on_engine=stop_in_cycles)
    assert first.state == "interrupted"
    plan, link, notes = plan_resume(first.path)
    seg = plan.program.segments[link.step]
    assert "tensile" in seg.name and "7 kV" in seg.name and notes == []
    second = execute(plan, tmp_path / "second.h5", virtual=True, resume=link)
    assert second.state == "completed", second.reason
    run = open_run(second.path)
    (_, _, _, text), = events(run, "restart")
    assert "output to 7000 V" in text
    (t_off, _, _, _), = events(run, "offset")
    motor = run.streams["motor"]
    x = np.interp(t_off, motor.t, motor.columns["aperture"])
    assert x == pytest.approx(0.050, abs=1e-3)  # the waveform's offset, 50 mm
    amp = run.streams["amplifier"]
    assert np.interp(t_off, amp.t, amp.columns["voltage"]) == pytest.approx(7000.0, rel=0.03)
    assert run.attrs["previous_file"] == "first.h5"
    with pytest.raises(ValueError, match="nothing to resume"):
        plan_resume(second.path)


def test_pause_and_resume_with_keys_at_the_live_view(tmp_path: Path) -> None:
    """`bench run` on a terminal (a pseudo-terminal here): `p` pauses, `r` resumes, without Enter. The run is in
    wall time: the short identification protocol with a 5-s drive (not 10 s), which the pause restarts — `p` comes
    1 s into it, 4 s before its end, and the whole run takes some 8 s instead of 13."""
    import pty

    protocol = tmp_path / "identification-5s.toml"
    protocol.write_text((SHORT / "thesis-identification-short.toml").read_text(encoding="utf-8")
                        .replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/')
                        .replace("duration_s = 10.0", "duration_s = 5.0"), encoding="utf-8")
    assert "duration_s = 5.0" in protocol.read_text(encoding="utf-8")
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(protocol),
                             "--out", str(tmp_path / "runs")], cwd=ROOT, env={**ENV, "TERM": "xterm"}, stdin=slave,
                            stdout=slave, stderr=slave, close_fds=True)
    os.close(slave)
    screen = bytearray()

    def read_some() -> None:
        import select

        while select.select([master], [], [], 0)[0]:
            try:
                screen.extend(os.read(master, 65536))
            except OSError:
                return

    def logged(text: str) -> bool:
        read_some()
        logs = list((tmp_path / "runs").glob("*.log"))
        return bool(logs) and text in logs[0].read_text()

    def load_tripped() -> str | None:
        """The run's end where a host starved of CPU ended it (tests/load_trips.py; three workers beside a hog, a
        session of 2026-11-28: no pause came because the run had tripped first), once the process is over."""
        with contextlib.suppress(AssertionError):
            wait_for(lambda: (read_some(), proc.poll() is not None)[1], 60, "the run to end")
        files = list((tmp_path / "runs").glob("*.h5"))
        run = open_run(files[0]) if proc.poll() is not None and files else None
        return run.reason if run is not None and load_trip(run) else None

    try:
        wait_for(lambda: logged("step 0 start"), 60, "the run to start")
        time.sleep(1.0)
        for _ in range(3):  # a key lost beside a loaded full suite (seen once: no pause in 30 s) is pressed again;
            os.write(master, b"p")  # a second press while pausing asks for the same pause (one pause event below)
            with contextlib.suppress(AssertionError):
                wait_for(lambda: logged(" pause: "), 10, "the pause")
                break
            if proc.poll() is not None:
                break
        try:
            wait_for(lambda: logged(" pause: "), 1, "the pause")
        except AssertionError:
            if (why := load_tripped()) is not None:
                pytest.skip(f"the loaded host tripped the wall-clock run before its pause: {why}")
            raise
        time.sleep(0.5)
        os.write(master, b"r")
        wait_for(lambda: logged(" resume: "), 30, "the resume")
        wait_for(lambda: (read_some(), proc.poll() is not None)[1], 120, "the run to end")
    finally:
        proc.kill()
        os.close(master)
    if proc.returncode != 0 and (why := load_tripped()) is not None:
        pytest.skip(f"the loaded host tripped the wall-clock run after its resume: {why}")
    assert proc.returncode == 0, screen.decode(errors="replace")[-2000:]
    assert b"p: pause" in screen  # the key help under the live panel
    run = open_run(next((tmp_path / "runs").glob("*.h5")))
    (_, _, _, p_text), = events(run, "pause")
    (_, _, _, r_text), = events(run, "resume")
    assert "live view (key p)" in p_text and "live view (key r)" in r_text


def test_a_resume_by_signal_answers_a_pause_the_control_file_asked_for(tmp_path: Path) -> None:
    """Paused by the control file (`bench pause`), resumed by SIGUSR2 / a key: the file's old word must not pause
    the run again — one pause, one resume, completed."""
    out = tmp_path / "run.h5"

    def hook(engine: Engine, sim) -> None:
        write_control(out, True, "ada", "from the control file")

        def at(_now: float) -> None:
            if engine.snapshot.state == "paused" and engine.now() >= 2.0:
                engine.request_resume("signal SIGUSR2")
        sim.clock.subscribe(at)

    result = execute(plan_run(SHORT / "thesis-identification-short.toml", DAQ_RIG), out, virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    assert len(events(run, "pause")) == 1 and len(events(run, "resume")) == 1


def test_a_daq_rigs_load_cell_is_read_and_supervised_while_paused(tmp_path: Path) -> None:
    """On a DAQ rig the load cell's bridge amplifier is sampled by the run's stream; a pause stops the stream, and the
    force went unread and unsupervised until the resume while the monitors were read on (a reviewer). Now it is read
    on request as they are, into the same stream, at the protocol's force rate or 10 per second at most."""
    isometric = SHORT / "lsdea-isometric-short.toml"
    rig = ROOT / "rigs" / "lsdea-motor-daq-sim.toml"
    window: list[float] = []

    def hook(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= 3.0:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and not window:
                window.append(engine.now())
            if engine.snapshot.state == "paused" and engine.now() >= window[0] + 2.0 and len(window) == 1:
                window.append(engine.now())
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(isometric, rig), tmp_path / "run.h5", virtual=True, on_engine=hook,
                     operator=lambda _m: True)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    (t_pause, *_), = events(run, "pause")
    (t_resume, *_), = events(run, "resume")
    cell = run.streams["load_cell"]
    inside = cell.t[(cell.t > t_pause + 0.5) & (cell.t < t_resume)]
    assert len(inside) >= 5, (t_pause, t_resume, len(inside))  # ~10 per second while paused (1.5 s and more)
    assert np.all(np.diff(inside) >= 0.1 - 1e-9)  # at most 10 per second: one Modbus round trip each
    assert np.all(np.isfinite(cell.columns["force"][(cell.t > t_pause + 0.5) & (cell.t < t_resume)]))


def test_a_run_killed_while_paused_latches_saying_the_pause_had_verified_0_v(tmp_path: Path) -> None:
    """kill -9 while a run is paused: the rig latches (nothing verified the output since), but the latch said "zero
    neither commanded nor verified" of a pause that had ramped it to 0 V and seen it there (an outside tester). The
    armed marker now carries the pause's verification, and the latch says it."""
    from bench.runtime.latch import all_latched

    proc, run_file, log = _paused_run(tmp_path, "look at the clamp", " verify: ",  # the pause's verified 0 V
                               {**ENV, "BENCH_STATE_DIR": os.environ["BENCH_STATE_DIR"]},  # this test's latches
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        verified = next(ln for ln in log.read_text().splitlines() if " verify: " in ln).split(" verify: ", 1)[1]
        wait_for(lambda: open_run(run_file, streams=False).updated > 1.0, 60, "a second paused on file")
    finally:
        proc.kill()
        proc.wait(timeout=30)
    (found,) = all_latched().values()
    assert "while paused" in found["fault"] and verified.strip() in found["fault"], (found["fault"], verified)
    assert "zero neither commanded nor verified" not in found["fault"]
    # its clock ran on through the pause, the plan's did not: inspect says how long it was paused (it read "18.250 s
    # of 14.0 s planned", an outside tester)
    from typer.testing import CliRunner

    from bench.cli import app

    shown = " ".join(CliRunner().invoke(app, ["inspect", str(run_file)], env={"COLUMNS": "300"}).output.split())
    assert re.search(r"of 11\.0 s planned, plus \d+\.\d s paused", shown), shown
    held = re.search(r"plus (\d+\.\d) s paused", shown)
    record = json.loads(CliRunner().invoke(app, ["inspect", str(run_file), "--json"]).output)
    assert held and abs(record["paused_s"] - float(held.group(1))) <= 0.05 + 1e-9 and record["paused_s"] > 1.0
