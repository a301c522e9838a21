"""On a hardware-timed (DAQ) rig the shutdown's and a pause's ramp to 0 V are played by the stream-out and the
inputs recorded through them on the scan clock: the specimen's response to the ramp is measured, not only
commanded (a tester's stopped run ended its amplifier and laser streams at 3235 V, the ramp to 0 V only as
set-points). During a pause the laser on the DAQ is read on with the monitors (10 Hz).

Expected values come from the plant's own output and from the rig's stated bounds, not the engine's account."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.runtime.engine import MONITOR_SETTLE_S, PAUSE_POLL_S, Engine
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"
SCAN = 1e-4  # s, 10 kHz (the rig file)
RAMP_S = 0.25  # the rig's shutdown_ramp_s
SAFE_V = 50.0


def _events(path: str, kind: str) -> list[tuple[float, int, str, str]]:
    return [e for e in open_run(path).event_list() if e[2] == kind]


def test_a_stop_records_the_ramp_to_0_v_on_the_scan_clock_until_0_v_is_verified(tmp_path: Path) -> None:
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    t0: list[float] = []

    def hook(engine: Engine, sim) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and not t0:
                t0.append(sim.clock.now() - engine.now())
            if engine.snapshot.state == "running" and engine.now() >= 3.9:
                engine.request_stop("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(SWEEPS, DAQ_RIG), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "interrupted", result.reason
    run = open_run(result.path)
    (t_req, *_), = _events(result.path, "request")
    # the plant: at 0 V within the stated bound (ramp within 0.2 s, 0 V within shutdown_ramp_s + 0.2 s)
    t = np.concatenate([b[0] for b in blocks]) - t0[0]
    v = np.concatenate([b[1] for b in blocks])
    assert np.abs(v[t < t_req]).max() > 1000.0
    t_zero_plant = t[(t > t_req) & (np.abs(v) <= SAFE_V)][0]
    assert t_zero_plant <= t_req + RAMP_S + 0.2
    for name in ("amplifier", "laser"):
        s = run.streams[name]
        # one scan clock with no hole through the stop: the ramp's stream takes up where the program's stopped
        assert np.all(np.diff(s.t) > 0) and np.diff(s.t).max() < 2.5 * SCAN, name
        # recorded through the ramp and until the zero is verified (the settle after 0 V)
        assert s.t[-1] >= t_zero_plant + MONITOR_SETTLE_S - 0.05, name
    amp = run.streams["amplifier"]
    ramp = (amp.t > t_req) & (amp.t < t_zero_plant)
    assert ramp.sum() >= 0.8 * (t_zero_plant - t_req) / SCAN  # the ramp itself, scan by scan
    assert np.abs(amp.columns["voltage"][ramp]).max() > 1000.0  # the monitor saw the ramp's high voltage
    assert np.abs(amp.columns["voltage"][-100:]).max() <= SAFE_V  # and the zero
    (safe,) = _events(result.path, "safe")
    assert "verified" in safe[3]


def test_a_pause_records_its_ramp_on_the_scan_clock_and_the_laser_while_paused(tmp_path: Path) -> None:
    def hook(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            if (engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= 3.0
                    and engine.ctx.v_cmd > 2000.0):  # paused under high voltage
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= 6.0:
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(SWEEPS, DAQ_RIG), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    (t_pause, *_), = _events(result.path, "pause")
    (t_resume, *_), = _events(result.path, "resume")
    amp, laser = run.streams["amplifier"], run.streams["laser"]
    ramp = (amp.t > t_pause) & (amp.t < t_pause + RAMP_S)
    assert ramp.sum() >= 0.9 * RAMP_S / SCAN  # the pause's ramp, scan by scan
    assert np.abs(amp.columns["voltage"][ramp]).max() > 1000.0
    paused = (laser.t > t_pause + RAMP_S + 0.2) & (laser.t < t_resume)
    expected = (t_resume - t_pause - RAMP_S - 0.2) / PAUSE_POLL_S
    assert paused.sum() >= 0.8 * expected  # the laser read on while paused, at the pause's rate
    assert laser.columns["valid"][paused].all()


def test_a_second_stop_during_the_ramp_zeroes_at_once_and_still_records_the_settle_after_0_v(tmp_path: Path) -> None:
    """A second stop request during the shutdown's ramp commands 0 V at once; the settle after 0 V is recorded on
    the scan clock all the same, as after the whole ramp (outside tester: only the verifying read landed in the
    file, in /safe_state). README: a second request skips the rest of the ramp; the inputs are recorded "for the
    0.5 s after 0 V that the verification waits". The times expected come from the plant's own output."""
    settle_s = 0.5  # README, "Stopping" (the verification's wait after 0 V)
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    t0: list[float] = []
    asked: list[float] = []

    def hook(engine: Engine, sim) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and not t0:
                t0.append(sim.clock.now() - engine.now())
            if engine.snapshot.state == "running" and engine.now() >= 3.9 and not asked:
                asked.append(engine.now())
                engine.request_stop("the test")
            elif engine.snapshot.state == "stopping" and len(asked) == 1 and engine.now() >= asked[0] + 0.1:
                asked.append(engine.now())  # mid-ramp: RAMP_S is 0.25 s
                engine.request_stop("the test, again")
        sim.clock.subscribe(at)

    result = execute(plan_run(SWEEPS, DAQ_RIG), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "interrupted", result.reason
    assert len(asked) == 2
    run = open_run(result.path)
    assert any("second stop request: 0 V at once" in e[3] for e in _events(result.path, "ramp"))
    t = np.concatenate([b[0] for b in blocks]) - t0[0]
    v = np.concatenate([b[1] for b in blocks])
    assert np.abs(v[(t > asked[1] - 0.01) & (t < asked[1])]).max() > 1000.0  # still high when the second came
    t_zero_plant = t[(t > asked[1]) & (np.abs(v) <= SAFE_V)][0]
    assert t_zero_plant <= asked[1] + 0.2  # at once: not the rest of the ramp (nor after the settle)
    (safe,) = _events(result.path, "safe")
    assert "verified" in safe[3]
    t_verify = float(run.streams["safe_state"].t[-1])
    assert t_verify >= t_zero_plant + settle_s - 0.05  # the verification still waited the settle
    for name in ("amplifier", "laser"):
        s = run.streams[name]
        after = s.t[s.t > t_zero_plant + 0.05]
        # recorded after 0 V, scan by scan, up to the verifying read (a gap only where the stream was restarted)
        assert after.size and after[-1] >= t_zero_plant + settle_s - 0.05 and after[-1] <= t_verify, name
        assert after.size >= 0.8 * (after[-1] - after[0]) / SCAN and np.diff(after).max() < 2.5 * SCAN, name
    amp = run.streams["amplifier"]
    assert np.abs(amp.columns["voltage"][-100:]).max() <= SAFE_V  # the zero, measured on the scan clock
