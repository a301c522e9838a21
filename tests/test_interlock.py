"""The latched interlock: a host stall, an output that is not what was commanded, a stream-out the DAQ did not
play, a refused output path — each ends at 0 V, never re-energised, and the file says why.

The output is read from the simulated plant (the amplifier's output stage as the twin integrates it), not from
the run file. Faults are injected into the twins (the host's drivers are untouched); a host stall freezes the
run's own thread while the twins and the plant run on, as a frozen process does to a real bench's modules.
"""

from __future__ import annotations

import dataclasses
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pymodbus.constants import ExcCodes

from bench.rig import load_rig
from bench.runtime.engine import Engine
from bench.runtime.interlock import OutputVerifier, stall_bound
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import RunFile, open_run
from tests.conftest import ROOT
from tests.load_trips import load_trip

THESIS = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
ADAM_RIG = ROOT / "rigs" / "thesis-sim.toml"
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"
ZERO_V = 5.0  # |output| at or below this counts as 0 V (one ADAM-4024 code × the TREK gain)
# DEVELOPERS.md / the interlock issue: after a fault seen at the plant, 0 V within 0.5 s
FAULT_BOUND_S = 0.5


class Plant:
    """The plant's output history, with the rig-clock time of the injected fault."""

    def __init__(self) -> None:
        self.blocks: list[tuple[np.ndarray, np.ndarray]] = []
        self.t_fault = float("nan")
        self.sim: object = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        self.sim.plant.observe()  # type: ignore[attr-defined]
        return np.concatenate([b[0] for b in self.blocks]), np.concatenate([b[1] for b in self.blocks])

    def last_high(self) -> float:
        t, v = self.arrays()
        high = np.abs(v) > ZERO_V
        assert high[t < self.t_fault].any(), "no high voltage before the fault: the trial tests nothing"
        return float(t[high][-1])

    def high_after(self, t_from: float) -> float:
        """Largest |output| from ``t_from`` (rig clock) to the end."""
        t, v = self.arrays()
        return float(np.abs(v[t >= t_from]).max())


def run_with_fault(rig: Path, tmp: Path, at: float, action: Callable[[Engine, object], None],
                   virtual: bool, protocol: Path = THESIS) -> tuple[object, RunFile, Plant]:
    """Run the short thesis protocol (or ``protocol``) with ``action`` done at run time ``at`` (on the engine's
    thread when it freezes the host; from the rig clock in virtual time; from a watcher thread in real time)."""
    plant = Plant()

    def hook(engine: Engine, sim) -> None:
        plant.sim = sim
        sim.plant.listeners.append(lambda b: plant.blocks.append((b.t.copy(), b.v_out.copy())))

        def act() -> None:
            plant.t_fault = sim.clock.now()
            action(engine, sim)

        if virtual:
            def at_time(_now: float) -> None:
                if np.isnan(plant.t_fault) and engine.snapshot.state == "running" and engine.now() >= at:
                    act()
            sim.clock.subscribe(at_time)
        else:
            def watch() -> None:
                while engine.snapshot.state == "starting" or (engine.now() < at and engine.snapshot.state == "running"):
                    time.sleep(0.002)
                if engine.snapshot.state == "running":  # a run already over (a loaded host's trip) is left alone:
                    act()  # a Ctrl-C sent after it reached the next test's run (CI beside a CPU hog, 2026-11-28)
            threading.Thread(target=watch, daemon=True).start()

    result = execute(plan_run(protocol, rig), tmp / "run.h5", virtual=virtual, on_engine=hook)
    return result, open_run(result.path), plant


def events(run: RunFile, kind: str) -> list[str]:
    return [text for _, _, k, text in run.event_list() if k == kind]


# ---------------------------------------------------------------- host stall
def freeze_host(seconds: float, began: list[float] | None = None) -> Callable[[Engine, object], None]:
    """Freeze the run's thread at its next recorder flush (a point between any two actions), as SIGSTOP does
    to a process: the twins, the plant and the module's watchdog run on. ``began``: the run time it froze at."""
    def action(engine: Engine, _sim: object) -> None:
        flush = engine.rec.maybe_flush
        frozen: list[bool] = []

        def stalled() -> None:
            if not frozen:
                frozen.append(True)
                if began is not None:
                    began.append(engine.now())
                time.sleep(seconds)
            flush()
        engine.rec.maybe_flush = stalled  # type: ignore[method-assign]
    return action


@pytest.mark.parametrize("rig", [ADAM_RIG, DAQ_RIG], ids=["adam", "daq"])
def test_a_host_stall_longer_than_the_watchdog_latches_and_never_reenergises(tmp_path: Path, rig: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """A real-time run: beside a CPU hog its host may fall behind the DAQ's stream-out before the freeze (CI: a
    mismatch read at 2.128 s, the freeze later) — rightly tripped, latched, but not this test's story: said, and run
    once more with a latch folder of its own; a mismatch read after the freeze began (the stall's own) fails it."""
    for attempt in range(2):
        began: list[float] = []
        folder = tmp_path / f"try{attempt}"
        folder.mkdir()
        monkeypatch.setenv("BENCH_STATE_DIR", str(folder / "state"))
        result, run, plant = run_with_fault(rig, folder, 2.0, freeze_host(2.5, began), virtual=False)
        read = re.search(r"read -?[\d.]+ V at ([\d.]+) s", result.reason)
        if attempt == 0 and "output mismatch" in result.reason and read and began and float(read[1]) < began[0]:
            print(f"the host fell behind before the freeze at {began[0]:.3f} s (a loaded machine): {result.reason}")
            continue
        if not began:  # over before the freeze: a twin the loaded host starved (CI beside a hog, 2026-11-28: "laser:
            if attempt == 0:  # no reply within 0.502 s" at 1.1 s) — the premise, a run still going, lost
                print(f"the run ended before the freeze (a loaded machine): {result.reason}")
                continue
            pytest.skip(f"twice the run ended before the freeze (a loaded machine): {result.reason}")
        break
    assert result.state == "tripped" and "interlock: host stall" in result.reason, result.reason
    if rig == ADAM_RIG:  # the ADAM-4024 keeps a flag of its own (40216, ADAM-4000 manual appendix G); the T7 none
        assert "the module's own flag: its watchdog fired" in result.reason
    assert run.state == "tripped" and "host stall" in run.reason
    assert any("latched" in text for text in events(run, "interlock"))
    assert any("0 V at once" in text for text in events(run, "ramp"))  # no ramp from a set-point it no longer holds
    # the module's watchdog zeroed the output during the freeze (its 1-s period from the rig file, after the
    # freeze began at the next flush and the specimen discharged at the current limit); from then on nothing
    # turned high voltage back on
    t, v = plant.arrays()
    after = t > plant.t_fault
    zeroed = float(t[after][np.argmax(np.abs(v[after]) <= ZERO_V)])
    assert zeroed <= plant.t_fault + 1.0 + 0.3
    assert plant.high_after(zeroed) <= ZERO_V
    (safe,) = events(run, "safe")
    assert "verified: voltage monitor" in safe


def test_a_short_pause_of_the_host_is_not_a_stall(tmp_path: Path) -> None:
    """Below the stated bound (0.8 × the 1-s watchdog) the run goes on: a late action, not a fault. (On the DAQ
    rig: the ADAM rig's serial laser storage, at 10 kHz, never catches up with a pause at 115200 Bd.) On the DAQ
    rig the stream-out holds only OUT_AHEAD_S (0.5 s) ahead of the scan clock in real time, topped up every 0.05 s:
    a pause of more than ~0.4 s starves it (an underrun, latched — README "Interlock"), so the pause here is 0.15 s.
    The run is in wall time and must end on its own: the short protocol with a 4-s drive (not 10 s), so it goes on
    2 s past the pause (a stall latches at the first action after it, an underrun within the 0.5 s ahead)."""
    bound = stall_bound(load_rig(DAQ_RIG))
    assert bound == pytest.approx(0.8)  # README "Interlock": 80 % of the module's communication watchdog
    protocol = tmp_path / "identification-4s.toml"
    protocol.write_text(THESIS.read_text(encoding="utf-8").replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/')
                        .replace("duration_s = 10.0", "duration_s = 4.0"), encoding="utf-8")
    assert "duration_s = 4.0" in protocol.read_text(encoding="utf-8")
    result, _run, _plant = run_with_fault(DAQ_RIG, tmp_path, 2.0, freeze_host(0.15), virtual=False, protocol=protocol)
    assert result.state == "completed", result.reason


def test_a_host_late_past_the_stream_outs_lead_trips_as_an_underrun_not_a_mismatch(tmp_path: Path) -> None:
    """The host frozen 1.5 s (under the stall bound) while the DAQ plays the rising raised cosine: the
    stream-out's 0.5 s of values run out and the DAC holds the last one while the program moves on. The next
    collect's scans show the output off the commanded band, and the verifier's "output mismatch" was the trip
    recorded (CI beside a CPU hog: a host 1.2 s late, the output held at 4491 V while 4881 V was commanded), a
    reason the tests' load-trip rule did not know. The cause is named: a stream-out underrun, latched."""
    rig = tmp_path / "thesis-daq-sim-4s.toml"  # a 4-s watchdog: a 3.2-s stall bound, so the 1.5-s freeze is no stall
    rig.write_text(DAQ_RIG.read_text(encoding="utf-8").replace("watchdog_s = 1.0 ", "watchdog_s = 4.0 "),
                   encoding="utf-8")
    assert stall_bound(load_rig(rig)) == pytest.approx(3.2)
    result, run, _plant = run_with_fault(rig, tmp_path, 2.0, freeze_host(1.5), virtual=False)
    assert result.state == "tripped" and "stream-out underrun" in result.reason, result.reason
    assert any("latched" in text and "stream-out underrun" in text for text in events(run, "interlock"))


# ---------------------------------------------------------------- verified outputs on the T7 rig (virtual time)
def gain_off(factor: float) -> Callable[[Engine, object], None]:
    """The conditioning stage between DAC and amplifier drifts: the output is ``factor`` × what the host sets."""
    def action(_engine: Engine, sim) -> None:
        twin = sim.twins["daq"]
        c = twin.conditioning
        twin.conditioning = dataclasses.replace(c, gain=c.gain * factor, offset=c.offset * factor)
    return action


def refuse_writes(engine: Engine, sim) -> None:
    """The T7 refuses every DAC and stream-out buffer write (exception 4, device failure) from now on."""
    from sim_devices.labjack_t7 import R_DAC, R_O_U16  # the twin's own register map

    twin = sim.twins["daq"]
    write = twin._write_regs

    def refused(address: int, words: list[int]):
        if address in (R_DAC, R_DAC + 2) or R_O_U16 <= address < R_O_U16 + 4:
            return ExcCodes.DEVICE_FAILURE
        return write(address, words)
    twin._write_regs = refused


def drop_stream_out(engine: Engine, sim) -> None:
    """The T7 acknowledges stream-out buffer writes but plays none of them: the waveform stops being played."""
    from sim_devices.labjack_t7 import R_O_U16

    twin = sim.twins["daq"]
    write = twin._write_regs
    twin._write_regs = lambda address, words: None if R_O_U16 <= address < R_O_U16 + 4 else write(address, words)


def first_mismatch(run: RunFile, tol_v: float = 100.0, tol_rel: float = 0.05) -> float:
    """Run time of the first scan whose measured output is off the commanded one by more than the rig's
    tolerance (README "Interlock": 100 V + 5 % of the commanded value, the defaults)."""
    a = run.streams["amplifier"]
    v, c = a.columns["voltage"], a.columns["commanded"]
    off = np.abs(v - c) > tol_v + tol_rel * np.abs(c)
    assert off.any()
    return float(a.t[np.argmax(off)])


def test_an_amplifier_gain_25_percent_off_latches_within_the_bound(tmp_path: Path) -> None:
    result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, gain_off(1.25), virtual=True)
    assert result.state == "tripped" and "interlock: output mismatch" in result.reason, result.reason
    t0 = plant.t_fault - 3.0  # rig clock of run time 0 (virtual time: the action ran at run time 3.0 exactly)
    seen = first_mismatch(run) + t0
    assert seen >= plant.t_fault - 1e-9
    assert plant.last_high() <= seen + FAULT_BOUND_S
    # never past the supervisor's over-voltage trip on the rig's 8-kV limit (1.02 × limit + 50 V, README "Safety")
    assert plant.high_after(plant.t_fault) < 8000.0 * 1.02 + 50.0


def test_a_stream_out_that_is_not_played_latches_instead_of_completing(tmp_path: Path) -> None:
    result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, drop_stream_out, virtual=True)
    assert result.state == "tripped" and "interlock" in result.reason, result.reason
    seen = first_mismatch(run) + plant.t_fault - 3.0
    assert plant.last_high() <= seen + FAULT_BOUND_S


def test_a_refused_output_path_stops_feeding_the_watchdog_and_the_run_ends_at_zero(tmp_path: Path) -> None:
    result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, refuse_writes, virtual=True)
    assert result.state == "error" and "refused" in result.reason, result.reason
    assert any("output path dead" in text for text in events(run, "watchdog"))
    assert any(text.startswith("latched at") and "output path dead" in text for text in events(run, "interlock"))
    from bench.runtime.latch import latched
    latch = latched(run.attrs["rig_name"])  # the next run and manual control are refused until a reset
    assert latch is not None and "output path dead" in latch["fault"]
    (safe,) = events(run, "safe")
    assert "verified: voltage monitor" in safe, safe
    # 0 V by the T7's own watchdog (1 s, the rig file) counted from the last request the host made before it
    # went silent — which followed the refusal within a few exchanges
    assert plant.sim.plant.watchdog_tripped  # type: ignore[attr-defined]
    assert plant.last_high() <= plant.t_fault + 1.0 + 0.1
    assert abs(plant.sim.plant.observe().v_out[-1]) <= ZERO_V  # type: ignore[attr-defined]


def test_a_dropped_t7_link_stops_the_drive_within_the_buffer_ahead_and_the_watchdog_zeroes_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Real time (a host can be lost only there): the T7's link drops at run time 3 s, on the rising flank of the
    7-kV waveform. The T7 plays what it holds of the stream-out — at most OUT_AHEAD_S (README "Interlock": 0.5 s)
    ahead of the scan its clock had reached when the host last topped it up — then holds its last value until its
    own watchdog (1 s without a request, the rig file) zeroes the output. Measured at the plant: the output stops
    rising once that buffer is played (on today's main it rose for 0.8 s, the whole out buffer), and is 0 V within
    the watchdog period."""
    from bench.runtime.hardware_timed import OUT_AHEAD_S

    def drop(_engine: Engine, sim) -> None:
        sim.faults["daq"].drop = True

    for attempt in range(3):  # a host starved beside other loads may not drive at 3 s (the premise below): again
        monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / f"state{attempt}"))  # (each try latches its rig)
        (tmp_path / f"try{attempt}").mkdir()
        result, _run, plant = run_with_fault(DAQ_RIG, tmp_path / f"try{attempt}", 3.0, drop, virtual=False)
        t, v = plant.arrays()
        tf = plant.t_fault
        rising = np.abs(v[(t >= tf) & (t <= tf + 0.1)])
        if rising.size and rising[-1] > rising[0] + 100.0:
            break
    # the lost link, or the underrun it caused when the write that found it out took its reply timeout
    assert result.state in ("error", "tripped") and ("lost" in result.reason or "underrun" in result.reason), \
        result.reason
    assert rising[-1] > rising[0] + 100.0  # the drive was still rising when the link dropped: the trial tests something
    # the buffer played out (+ the 30-Hz filter and the amplifier settling), the output holds until the watchdog
    # (≥ 0.95 s: the last request came ≤ 50 ms before the drop)
    held = np.abs(v[(t >= tf + OUT_AHEAD_S + 0.1) & (t <= tf + 0.9)])
    assert held.max() - held.min() <= 10.0
    assert plant.last_high() <= tf + 1.0 + 0.1


def test_t7_replies_lost_then_ctrl_c_zeroes_without_waiting_for_replies(tmp_path: Path) -> None:
    """The T7 stops answering (its replies are lost; its requests still arrive) and the operator presses Ctrl-C:
    once the engine sees the first reply missing (its 0.5-s reply timeout), the shutdown waits at most 0.1 s for
    each further reply (SHUTDOWN_REPLY_S) and skips the ramp, so the zero write reaches the DAC ~0.1 s later."""
    import os
    import signal

    from bench.runtime.engine import SHUTDOWN_REPLY_S

    def lose_replies_then_stop(_engine: Engine, sim) -> None:
        sim.faults["daq"].mute = True
        time.sleep(0.2)
        os.kill(os.getpid(), signal.SIGINT)

    result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, lose_replies_then_stop, virtual=False)
    if np.isnan(plant.t_fault) and load_trip(run):  # the loaded host tripped the run before the replies were lost
        pytest.skip(f"the loaded host tripped the wall-clock run first: {result.reason}")
    assert result.state in ("error", "interrupted"), result.reason
    t0 = plant.t_fault - 3.0  # rig clock of run time 0 (the watcher acted at run time 3.0, within a few ms)
    (t_seen,) = [t for t, _, k, _ in run.event_list() if k in ("error", "interrupted")]
    assert any("did not answer: 0 V at once" in text for text in events(run, "ramp"))
    # 0 V at the plant: the stream stop's reply wait, then the zero write (+0.2 s: the README's stop bound margin)
    assert plant.last_high() <= t0 + t_seen + SHUTDOWN_REPLY_S + 0.2


# ---------------------------------------------------------------- verified outputs on the ADAM rig (polled)
def test_a_polled_monitor_that_disagrees_with_the_set_point_latches(tmp_path: Path) -> None:
    def amplifier_gain_off(_engine: Engine, sim) -> None:
        sim.plant.hv = dataclasses.replace(sim.plant.hv, gain=sim.plant.hv.gain * 1.25)

    result, _run, plant = run_with_fault(ADAM_RIG, tmp_path, 3.0, amplifier_gain_off, virtual=True)
    assert result.state == "tripped" and "interlock: output mismatch" in result.reason, result.reason
    # two monitor readings in a row (the monitors are polled at the protocol's monitors_Hz), then 0 V at once
    hz = plan_run(THESIS, ADAM_RIG).program.protocol.recording.monitors_Hz
    assert plant.last_high() <= plant.t_fault + 0.3 + 3 / hz + 0.05


# ---------------------------------------------------------------- the verifier itself (derived cases)
def verifier(rate: float | None = 10_000.0) -> OutputVerifier:
    return OutputVerifier(load_rig(DAQ_RIG if rate else ADAM_RIG), rate)


def test_a_monitor_one_scan_behind_the_drive_is_in_band() -> None:
    t = np.arange(2000) / 1e4
    cmd = 6000 * np.sin(2 * np.pi * 10 * t)  # 10 Hz, ±6 kV: up to 377 V per 0.1-ms scan
    measured = np.concatenate([[0.0], cmd[:-1]])
    assert verifier().scans(t, measured, cmd, np.ones(t.size, bool)) is None


def test_a_mismatch_must_last_the_stated_time_and_invalid_scans_do_not_end_it() -> None:
    rate = 1e4
    t = np.arange(1000) / rate
    cmd = np.full(t.size, 4000.0)
    measured = cmd.copy()
    measured[100:290] = 5000.0  # 19 ms out of band (> 100 V + 5 % of 4 kV = 300 V): shorter than 20 ms
    v = verifier()
    assert v.scans(t, measured, cmd, np.ones(t.size, bool)) is None
    measured2 = cmd.copy()
    measured2[100:400] = 5000.0
    ok = np.ones(t.size, bool)
    ok[150:160] = False  # an invalid stretch inside the bad run neither counts against nor ends it
    m = verifier().scans(t, measured2, cmd, ok)
    assert m is not None and m.t == pytest.approx(t[299]) and m.measured == 5000.0 and m.commanded == 4000.0


def test_a_mismatch_run_continues_across_blocks() -> None:
    v = verifier()
    t = np.arange(300) / 1e4
    cmd, bad = np.full(300, 4000.0), np.full(300, 0.0)
    ok = np.ones(300, bool)
    assert v.scans(t[:150], bad[:150], cmd[:150], ok[:150]) is None  # 15 ms
    m = v.scans(t[150:], bad[150:], cmd[150:], ok[150:])
    assert m is not None and m.t == pytest.approx(t[199])  # the 200th bad scan: 20 ms


def test_polled_readings_follow_the_set_points_within_the_lag() -> None:
    v = verifier(None)
    v.commanded(0.0, 5000.0)
    assert v.reading(0.1, 5000.0) is None
    v.commanded(1.0, 0.0)
    assert v.reading(1.1, 5000.0) is None  # still within 0.3 s of the 5-kV set-point: may be what it shows
    assert v.reading(1.2, 2000.0) is None
    assert v.reading(1.5, 5000.0) is None  # first reading out of band: not yet a fault
    m = v.reading(1.6, 5000.0)
    assert m is not None and m.commanded == 0.0 and m.t == 1.6


# ---------------------------------------------------------------- the latch outlives the run
def test_a_latched_rig_refuses_the_next_run_until_an_operator_resets_it(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    from bench.runtime.latch import LatchedError, latched, state_dir

    result, _run, _plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, gain_off(1.25), virtual=True)
    assert result.state == "tripped"
    rig_name = load_rig(DAQ_RIG).name
    was = latched(rig_name)
    assert was is not None and "output mismatch" in was["fault"] and was["where"] == str(result.path)
    with pytest.raises(LatchedError, match="interlock latched"):  # nothing is touched: no file is created
        execute(plan_run(THESIS, DAQ_RIG), tmp_path / "next.h5", virtual=True)
    assert not (tmp_path / "next.h5").exists()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    bench = [sys.executable, "-m", "bench"]
    # the command line refuses it before showing a plan or making the run's log
    cli = subprocess.run([*bench, "run", str(THESIS), "--rig", str(DAQ_RIG), "--virtual-time", "--yes", "--no-live",
                          "--out", str(tmp_path / "cli")], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert cli.returncode == 2 and "interlock latched" in cli.stderr, cli.stdout + cli.stderr
    assert "running" not in cli.stdout and not (tmp_path / "cli").exists(), cli.stdout
    # resuming the campaign needs the operator's reason; with it, the latch is reset and the reset recorded
    # (the refusals and the CLI resets go through typer's runner in this process, same app and arguments: the run
    # and the resumed run above and below are the processes; a fresh interpreter per refusal costs seconds)
    from typer.testing import CliRunner

    from bench.cli import app

    refused = CliRunner().invoke(app, ["run", "--resume", str(result.path), "--virtual-time", "--no-live"])
    assert refused.exit_code not in (0, None) and "--why" in refused.stdout + refused.stderr
    assert isinstance(refused.exception, SystemExit), refused.exception  # refused, not a traceback
    resumed = subprocess.run([*bench, "run", "--resume", str(result.path), "--virtual-time", "--no-live", "--why",
                              "conditioning stage recalibrated", "--operator", "ada"], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert latched(rig_name) is None
    second = next(p for p in tmp_path.glob("*.h5") if p.name != "run.h5")
    assert "ada: conditioning stage recalibrated" in open_run(second, streams=False).attrs["interlock_reset"]
    # a reset with the CLI is logged in the history with who and why
    from bench.runtime.latch import latch

    latch(rig_name, "test fault", "a test")
    no_why = CliRunner().invoke(app, ["interlock", "reset", rig_name])
    assert no_why.exit_code != 0 and isinstance(no_why.exception, SystemExit) and latched(rig_name) is not None
    ok = CliRunner().invoke(app, ["interlock", "reset", rig_name, "--why", "checked", "--operator", "bo"])
    assert ok.exit_code == 0 and latched(rig_name) is None, ok.stdout + ok.stderr
    history = (state_dir() / "interlock.log").read_text()
    assert "reset\t" + rig_name + "\tby bo: checked" in history and "ada: conditioning stage recalibrated" in history


# ---------------------------------------------------------------- the motor verified against its go-tos
def test_a_carriage_that_stops_following_its_go_tos_latches(tmp_path: Path) -> None:
    """The isopotential cycles at 7 kV: at run time 10 s the carriage jams (the drive takes its go-tos, the slider
    no longer moves). The encoder leaves the go-tos' trapezoid by more than 2 mm (README "Interlock"): latched,
    0 V at once."""
    from bench.core.motion import MotionProfile

    def jam(_engine: Engine, sim) -> None:
        plant = sim.plant
        plant.set_motion(lambda t, p, _v: MotionProfile.hold(t, p))
        plant.set_motion = lambda make: plant.motion  # later profiles never reach the slider

    plant = Plant()

    def hook(engine: Engine, sim) -> None:
        plant.sim = sim
        sim.plant.listeners.append(lambda b: plant.blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if np.isnan(plant.t_fault) and engine.snapshot.state == "running" and engine.now() >= 10.0:
                plant.t_fault = sim.clock.now()
                jam(engine, sim)
        sim.clock.subscribe(at)

    proto = ROOT / "protocols" / "short" / "lsdea-isopotential-short.toml"
    result = execute(plan_run(proto, ROOT / "rigs" / "lsdea-motor-sim.toml"), tmp_path / "run.h5", virtual=True,
                     on_engine=hook)
    assert result.state == "tripped" and "interlock: motor mismatch" in result.reason, result.reason
    run = open_run(result.path)
    t, v = plant.arrays()
    assert np.abs(v[t < plant.t_fault]).max() > 6500.0  # jammed under the 7-kV sweep point
    assert any("0 V at once" in text for text in events(run, "ramp"))
    assert plant.last_high() <= plant.t_fault + FAULT_BOUND_S


def test_the_motion_verifier_follows_the_drive_s_trapezoid() -> None:
    """Derived case: a go-to of 50 mm at 0.1 m/s and 1 m/s² from rest takes 0.1 s to reach speed (5 mm), 0.4 s of
    cruise and 0.1 s to stop; at 0.3 s the carriage is at 5 + 20 = 25 mm."""
    from bench.runtime.interlock import MotionVerifier

    v = MotionVerifier(load_rig(ROOT / "rigs" / "lsdea-motor-sim.toml"))
    v.anchor(0.0, 0.0)
    v.commanded(0.0, 0.050, 0.1, 1.0)
    assert v.reading(0.3, 0.025) is None
    assert v.reading(0.3, 0.0265) is None  # within 2 mm, and the last 50 ms had it 20–25 mm
    assert v.reading(0.31, 0.030) is None  # first reading off by more: not yet a fault
    m = v.reading(0.32, 0.031)
    assert m is not None and m.commanded == pytest.approx(0.027, abs=1e-6)
    v.stopped(0.4)
    assert v.reading(0.5, 0.04) is None and not v.anchored  # the drive's own stop ramp: no expectation yet


def test_the_motion_verifier_s_band_is_the_trapezoid_sampled_evenly_over_the_lag() -> None:
    """The expected positions a reading is judged against are the profile at 11 evenly spaced times over the last
    ``motor_lag_s``: exactly what numpy's linspace and the vectorised evaluation give, for go-tos from rest, reversals
    while moving and times before, inside and after every phase (the per-reading path is computed without numpy)."""
    from bench.runtime.interlock import MOTION_SAMPLES, MotionVerifier

    v = MotionVerifier(load_rig(ROOT / "rigs" / "lsdea-motor-sim.toml"))
    rng = np.random.default_rng(7)
    v.anchor(0.0, 0.02)
    t = 0.0
    for _ in range(12):
        v.commanded(t, float(rng.uniform(0.0, 0.095)), float(rng.uniform(0.01, 1.0)), float(rng.uniform(0.5, 20.0)))
        profile = v._profile
        assert profile is not None
        for when in np.concatenate([t + rng.uniform(-0.2, 1.5, 40), profile.t_start, profile.t_start + v.lag]):
            want = profile.evaluate(np.linspace(when - v.lag, when, MOTION_SAMPLES))[0].tolist()
            assert v._expected(float(when)) == want
        t += float(rng.uniform(0.01, 0.6))  # the next go-to may come while this one still moves


def test_one_sample_of_the_trapezoid_is_the_derived_state() -> None:
    """The derived go-to above, started at t = 1 s and sampled one time at a time as a drive's poll reads it: at rest
    at 0 before the start; at 1.3 s 25 mm at 0.1 m/s; at 1.55 s, 0.05 s into the stop that begins at 45 mm,
    45 + 0.1·0.05 − ½·1·0.05² m = 48.75 mm at 0.05 m/s; at 50 mm and rest after 1.6 s."""
    from bench.core.motion import MotionProfile

    m = MotionProfile.plan(1.0, 0.0, 0.0, 0.050, 0.1, 1.0, 1.0)
    assert m.at(0.5) == (0.0, 0.0)
    assert m.at(1.3) == pytest.approx((0.025, 0.1), abs=1e-12)
    assert m.at(1.55) == pytest.approx((0.045 + 0.1 * 0.05 - 0.5 * 0.05 ** 2, 0.05), abs=1e-12)
    assert m.at(2.0) == pytest.approx((0.050, 0.0), abs=1e-12)
    assert all(type(x) is float for x in m.at(1.3))


def test_a_ramp_from_rest_is_in_band_while_the_monitor_still_shows_rest() -> None:
    """Polled monitors lag (ADAM-4017+, 10 S/s): 0.13 s into a 20-Hz ramp from 0 V the monitor may still read the
    rest value. With what connecting left (0 V) known, that is in band; without any earlier value, a reading is not
    judged (the value before the first known set-point is unknown). Found by `bench benchmark faults` in manual
    control, where the verifier did not know the rest value."""
    v = verifier(None)
    v.commanded(0.0, 0.0)  # after connecting
    for k in range(1, 4):
        v.commanded(0.3 + 0.05 * k, 250.0 * k)
    assert v.reading(0.48, 2.0) is None and v.reading(0.53, 2.0) is None
    fresh = verifier(None)
    fresh.commanded(0.35, 250.0)
    fresh.commanded(0.40, 500.0)
    assert fresh.reading(0.48, 2.0) is None and fresh.reading(0.53, 2.0) is None


RISE_PROTOCOL = """[protocol]
name = "rise"
rig = "{rig}"

[[steps]]
type = "relax"
name = "set-up"
duration_s = 0.3

[[steps]]
type = "waveform"
name = "cycle"
kind = "raised_cosine"
amplitude = "6 kV"
frequency_Hz = 1.0
duration_s = 1.0

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "5 kV"
duration_s = 0.5

[[steps]]
type = "hold"
name = "hold"
duration_s = 0.5
"""


@pytest.mark.parametrize("at", [1.295, 1.2995, 1.3])
def test_a_full_disk_at_the_trough_before_a_ramp_up_never_lets_the_output_rise(tmp_path: Path, at: float) -> None:
    """The run file's disk fills at the end of a raised-cosine cycle (0 V), the next step a ramp up already in the
    T7's stream-out: the stop waited for whole packets (so that no scan is lost before the ramp's stream) and let
    the device play on — the fault matrix saw 0 V reached, then 222 V. After a storage fault no scan can be kept:
    the stream stops at once, and the output at the plant never rises after the fault by more than a DAC code or
    two (5 V). (Virtual time: the fault at run time ``at``, within a packet's time of the cycle's end at 1.3 s.)"""
    import errno

    protocol = tmp_path / "rise.toml"
    protocol.write_text(RISE_PROTOCOL.format(rig=DAQ_RIG.as_posix()), encoding="utf-8")

    def full(engine: Engine, _sim) -> None:
        def no_room(*_a: object, **_k: object) -> None:
            raise OSError(errno.ENOSPC, "No space left on device (the test)")

        engine.rec.append = no_room  # type: ignore[method-assign]  # the next write fails as on a full disk

    result, _run, plant = run_with_fault(DAQ_RIG, tmp_path, at, full, virtual=True, protocol=protocol)
    assert result.state == "error" and "storage fault" in result.reason, result.reason
    t, v = plant.arrays()
    was = float(np.abs(v[t <= plant.t_fault][-1]))
    assert was < 100.0  # the premise: asked near the trough
    assert plant.high_after(plant.t_fault) <= was + 5.0, (was, plant.high_after(plant.t_fault))


def test_a_stream_stop_the_t7_never_answers_leaves_the_output_to_its_watchdog(tmp_path: Path) -> None:
    """A stop at a raised-cosine cycle's crest, and the T7 neither acts on nor answers the stream stop
    (``STREAM_ENABLE = 0`` lost; CI beside a hog and a browser saw it unanswered, the monitor at 3043 V 2.5 s later):
    the stream-out may still be playing over any DAC write of the host's, so after its one 0-V write the host must
    send nothing more — the verification's reads fed the T7's watchdog and kept the played output up. The output
    at the plant is 0 V within the stop's reply waits plus the watchdog's period (+0.2 s, the engine's margin), and
    the rig latches: 0 V was not under the host's control."""
    from bench.runtime.engine import SHUTDOWN_REPLY_S
    from sim_devices.t7.registers import R_ENABLE

    protocol = tmp_path / "rise.toml"
    protocol.write_text(RISE_PROTOCOL.format(rig=DAQ_RIG.as_posix()), encoding="utf-8")
    lost: list[float] = []

    def lose_the_stream_stop(engine: Engine, sim) -> None:
        twin = sim.twins["daq"]
        write = twin._write_regs

        def written(address: int, words: list[int]) -> object:
            if address == R_ENABLE and not any(int(w) for w in words):
                lost.append(sim.clock.now())
                return None  # not acted on; its reply withheld below
            return write(address, words)

        def withheld(reply: bytes) -> bytes:  # FC16's echo of address 4990: never on the wire
            return b"" if len(reply) >= 10 and reply[7] == 0x10 and reply[8:10] == R_ENABLE.to_bytes(2, "big") \
                else reply
        twin._write_regs = written
        sim.faults["daq"].mutate = withheld
        engine.request_stop("stopped by the test")

    _result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 0.8, lose_the_stream_stop, virtual=True,
                                        protocol=protocol)
    assert lost, "the stream stop was never sent: the trial tests nothing"
    t, v = plant.arrays()
    assert float(np.abs(v[t <= plant.t_fault][-1])) > 1000.0  # the premise: high voltage when the stop came
    # the whole-packet wait (≤ 17 ms, README), the stop's and the zero write's reply waits, the watchdog, +0.2 s
    bound = plant.t_fault + 0.017 + 2 * SHUTDOWN_REPLY_S + load_rig(DAQ_RIG).daq.watchdog_s + 0.2
    assert plant.last_high() <= bound, (plant.last_high(), bound)
    assert plant.arrays()[0][-1] > plant.last_high() + 0.05  # the plant was followed past it: 0 V held
    assert "NOT under its control" in run.reason, run.reason
    assert [text for text in events(run, "interlock") if "output path dead" in text], events(run, "interlock")


@pytest.mark.parametrize("stop_lost", [False, True], ids=["stop-answered", "stop-lost-too"])
def test_a_stream_start_the_t7_took_but_never_answered_is_stopped_or_left_to_its_watchdog(
        tmp_path: Path, stop_lost: bool) -> None:
    """The reply to the enable (STREAM_ENABLE = 1) is lost while the T7 took it: the stream runs and plays its
    preloaded stream-out (the set-up's 0 V, then the cycle up to 6 kV) while the host believes none runs, sends no
    stop and feeds the watchdog with its verification's reads (a reviewer). The driver now sends one stop at once;
    answered, the run ends at 0 V as any error does; lost too, the output is left to the watchdog as after an
    unanswered stop. Either way the plant's output is at 0 V within the reply waits plus the watchdog's period."""
    from bench.runtime.engine import SHUTDOWN_REPLY_S
    from sim_devices.t7.registers import R_ENABLE

    protocol = tmp_path / "rise.toml"
    protocol.write_text(RISE_PROTOCOL.format(rig=DAQ_RIG.as_posix()), encoding="utf-8")
    plant, lost = Plant(), []

    def hook(_engine: Engine, sim) -> None:
        plant.sim = sim
        sim.plant.listeners.append(lambda b: plant.blocks.append((b.t.copy(), b.v_out.copy())))
        twin = sim.twins["daq"]
        write = twin._write_regs
        withhold: list[bool] = []  # the reply to the request just handled never goes on the wire

        def written(address: int, words: list[int]) -> object:
            enable = address == R_ENABLE and any(int(w) for w in words)
            if enable and not lost:  # the first enable: acted on, its reply lost (the link's retry is answered)
                lost.append(sim.clock.now())
                plant.t_fault = sim.clock.now()
                withhold.append(True)
            elif stop_lost and lost and address == R_ENABLE and not enable:
                withhold.append(True)
                return None  # a stop: lost, not acted on
            return write(address, words)

        def mutate(reply: bytes) -> bytes:
            if withhold:
                withhold.clear()
                return b""
            return reply
        twin._write_regs = written
        sim.faults["daq"].mutate = mutate

    result = execute(plan_run(protocol, DAQ_RIG), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert lost, "the stream was never started: the trial tests nothing"
    assert result.state == "error", (result.state, result.reason)
    run = open_run(result.path)
    t, v = plant.arrays()
    bound = plant.t_fault + 3 * (load_rig(DAQ_RIG).daq.timeout_s + SHUTDOWN_REPLY_S) \
        + load_rig(DAQ_RIG).daq.watchdog_s + 0.2
    high = np.abs(v) > ZERO_V
    assert not high[t > bound].any(), (t[high][-1], bound)
    assert t[-1] > bound or not high[t > plant.t_fault + 0.05].any()  # followed long enough, or never up
    if stop_lost:
        assert "NOT under its control" in run.reason, run.reason
