"""On a hardware-timed (DAQ) rig a restart's ramp up (a resume after a pause) is played by the DAQ's stream-out and
the inputs recorded through it on the scan clock, every scan supervised as a step's are: before, it went out as ten
host set-points, the monitors only polled between them. A trip during it ends the run at 0 V, latched.

Expected values come from the protocol below (5 kV at the ramp step's end, held by the hold step the pause restarts),
the rig file (10 kHz scans, ``shutdown_ramp_s`` 0.25 s, the 8-kV limit) and the plant's own output history, never
from the engine's account of itself."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.runtime.engine import RESTART_SETTLE_S, Engine, RunResult
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import RunFile, open_run
from tests.conftest import ROOT
from tests.load_trips import load_trip

PROTOCOL = """[protocol]
name = "restart-up"
description = "a ramp to 5 kV, a hold (paused and resumed), a relax"
rig = "{rig}"

[recording]
displacement_Hz = 2000
setpoint_Hz = 20

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "5 kV"
duration_s = 1.0

[[steps]]
type = "hold"
name = "hold"
duration_s = 2.0

[[steps]]
type = "relax"
name = "down"
duration_s = 0.5
"""
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"
V_HOLD = 5000.0  # the ramp step's end value: the hold step starts from it
SCAN = 1e-4  # s, 10 kHz (the rig file)
RAMP_S = 0.25  # the rig's shutdown_ramp_s: a restart ramps up over it
PAUSE_AT, RESUME_AT = 1.5, 2.5  # run time: in the hold step (program 1.0–3.0 s), then resumed
ZERO_V = 50.0  # |output| at or below this counts as 0 V (the rig's 50-V touch limit)
NOISE_V = 20.0  # monitor noise and DAC-code dither, bounded (one 12-bit code ≈ 5 V of output)


def _events(run: RunFile, kind: str) -> list[tuple[float, int, str, str]]:
    return [e for e in run.event_list() if e[2] == kind]


Outcome = tuple[RunResult, RunFile, np.ndarray, np.ndarray, dict[str, float], Any]


def _run(tmp: Path, fault_after_resume_s: float | None = None, stop: bool = False,
         gain: float | None = None, virtual: bool = True) -> Outcome:
    """The protocol, paused at ``PAUSE_AT`` and resumed at ``RESUME_AT`` (run time), on the simulated DAQ rig in
    virtual time (``virtual=False``: on the wall clock, the pause and resume asked from the plant's thread);
    ``fault_after_resume_s``: the dielectric breaks down (``stop``: a stop is requested) that long
    after the resume was asked for; ``gain``: instead, the amplifier's gain becomes ``gain`` × its own then.
    Returns (result, run file, plant times on the run clock, plant output, what the hook saw, the plant)."""
    proto = tmp / "restart-up.toml"
    proto.write_text(PROTOCOL.format(rig=DAQ_RIG.as_posix()))
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    seen: dict[str, float] = {}
    sims: list[Any] = []

    def hook(engine: Engine, sim: Any) -> None:
        sims.append(sim)
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and "t0" not in seen:
                seen["t0"] = sim.clock.now() - engine.now()
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= PAUSE_AT:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= RESUME_AT:
                engine.request_resume("the test")
            if (fault_after_resume_s is not None and engine.pauses == 1 and "fault" not in seen
                    and engine.now() >= RESUME_AT + fault_after_resume_s):
                seen["fault"] = engine.now()
                if stop:
                    engine.request_stop("the test")
                elif gain is not None:
                    sim.plant.hv = dataclasses.replace(sim.plant.hv, gain=sim.plant.hv.gain * gain)
                else:
                    sim.plant.inject_breakdown()
        if virtual:
            sim.clock.subscribe(at)
        else:
            sim.plant.listeners.append(lambda _b: at(0.0))

    result = execute(plan_run(proto), tmp / "run.h5", virtual=virtual, on_engine=hook)
    t = np.concatenate([b[0] for b in blocks]) - seen["t0"]
    v = np.concatenate([b[1] for b in blocks])
    return result, open_run(result.path), t, v, seen, sims[0].plant


def test_a_resumed_steps_ramp_up_is_played_by_the_daq_and_recorded_on_the_scan_clock(tmp_path: Path) -> None:
    result, run, t_plant, v_plant, _, _ = _run(tmp_path)
    assert result.state == "completed", result.reason
    kinds = [e[2] for e in run.event_list() if e[2] in ("pause", "resume", "restart", "offset")]
    assert kinds == ["pause", "resume", "restart", "offset"]
    (t_restart, step, _, text), = _events(run, "restart")
    assert step == 1 and f"output to {V_HOLD:.0f} V" in text
    (t_step, _, _, offset_text), = _events(run, "offset")  # the hold step starts again here
    # a timing event names the ramp's stream, between the restart and the step's own start; the step plays on that
    # stream (no kickoff of its own after the restart), its start at the scan after the ramp's 0.25 s and the
    # settle's, which the program's offset names to within half a scan (the hold step's program start is 1.0 s)
    kickoffs = [(t, txt) for t, _, _, txt in _events(run, "timing") if t >= t_restart and "scan 0 at" in txt]
    assert len(kickoffs) == 1 and "ramp up" in kickoffs[0][1] and kickoffs[0][0] <= t_step, kickoffs
    t0_ramp = float(re.findall(r"scan 0 at ([\d.]+) s", kickoffs[0][1])[0])
    offset = float(offset_text.rsplit("+", 1)[1].split()[0])
    assert offset + 1.0 == pytest.approx(t0_ramp + RAMP_S + RESTART_SETTLE_S, abs=SCAN / 2)
    # the plant: 0 V at the restart, V_HOLD reached no sooner than the ramp's duration allows (a ramp, not a jump)
    assert np.abs(v_plant[(t_plant > t_restart - 0.1) & (t_plant <= t_restart)]).max() <= ZERO_V
    t_up = t_plant[(t_plant > t_restart) & (v_plant >= 0.9 * V_HOLD)][0]
    assert t_up >= t_restart + 0.9 * RAMP_S - 2 * SCAN
    assert t_up < t_step

    amp = run.streams["amplifier"]
    span = RAMP_S + 0.05  # the ramp, then 50 ms at V_HOLD before the step starts again
    w = (amp.t >= t_restart) & (amp.t <= t_restart + span)
    ts, v, cmd = amp.t[w], amp.columns["voltage"][w], amp.columns["commanded"][w]
    # the ramp up, scan by scan, on the 10-kHz clock
    assert ts.size >= 0.9 * span / SCAN
    assert np.diff(ts).min() > 0.5 * SCAN and np.diff(ts).max() < 1.5 * SCAN
    # from ~0 V to V_HOLD, rising monotonically (means of 5-ms windows: 100 V apart on the ramp) within the noise
    assert np.abs(v[:20]).max() <= ZERO_V
    assert v[-20:].mean() == pytest.approx(V_HOLD, rel=0.02)
    means = v[: v.size // 50 * 50].reshape(-1, 50).mean(axis=1)
    assert np.diff(means).min() >= -NOISE_V
    # what the engine says it commanded is what the DAC played (the plant's output, scan by scan)
    assert np.abs(cmd - np.interp(ts, t_plant, v_plant)).max() <= NOISE_V
    # the set-point rows: the ramp's start (0 V, the value the DAC held) and its end (V_HOLD)
    sp = run.streams["setpoints"]
    within = (sp.t >= t_restart) & (sp.t < t_step)
    volts = sp.columns["voltage"][within]
    assert abs(volts[0]) <= ZERO_V and volts[-1] == pytest.approx(V_HOLD)
    assert np.all(np.diff(volts) >= 0)


def test_the_resumed_step_plays_on_the_ramp_ups_stream_with_no_hole_at_high_voltage(tmp_path: Path) -> None:
    """On the wall clock: the resumed step is appended to the ramp up's stream, so every scan from the restart to the
    step's end is recorded, 0.1 ms apart. Before, the ramp's stream stopped after its settle and the step armed a
    stream of its own, and arming one takes the host ~0.1 s: the recording had a hole at 5 kV, no scan recorded or
    supervised (an outside tester: 113 ms at 3 kV)."""
    result, run, *_ = _run(tmp_path, virtual=False)
    if load_trip(run):
        pytest.skip(f"the loaded host tripped the wall-clock run first: {run.reason}")
    assert result.state == "completed", result.reason
    (t_restart, *_), = _events(run, "restart")
    (t_offset, _, _, text), = _events(run, "offset")
    t_end = next(t for t, step, kind, _ in run.event_list() if kind == "end" and step == 1 and t > t_restart)
    amp = run.streams["amplifier"]
    w = (amp.t >= t_restart) & (amp.t <= t_end)
    gaps = np.diff(amp.t[w])
    assert gaps.max() < 1.5 * SCAN, f"{gaps.max() * 1e3:.1f} ms without a scan at {amp.t[w][np.argmax(gaps)]:.3f} s"
    # the step restarts on the scan clock, ``RAMP_S`` plus the settle after the ramp's scan 0: the program's offset is
    # that scan's time less the step's program start (1.0 s), not the host's later reading of its clock
    t0_ramp, = [float(re.findall(r"scan 0 at ([\d.]+) s", txt)[0]) for *_, txt in _events(run, "timing")
                if "ramp up" in txt]
    offset = float(text.rsplit("+", 1)[1].split()[0])
    assert t_restart <= t0_ramp + RAMP_S < offset + 1.0 <= t_offset


def test_a_trip_during_the_ramp_up_ends_the_run_at_0_v_latched(tmp_path: Path) -> None:
    """The dielectric breaks down mid-ramp: the scans the ramp's stream records trip the supervisor's current limit
    (the ramp is supervised as a step is) before the step starts again; the output goes to 0 V and the rig stays
    latched."""
    result, run, t_plant, v_plant, seen, plant = _run(tmp_path, fault_after_resume_s=0.1)
    assert result.state == "tripped" and "current" in result.reason, result.reason
    (t_restart, *_), = _events(run, "restart")
    (t_tripped, *_), = _events(run, "tripped")
    assert t_restart <= seen["fault"] <= t_tripped <= t_restart + RAMP_S  # the fault came and tripped in the ramp up
    assert _events(run, "offset") == []  # the step never started again
    # the ramp up was recorded on the scan clock until the trip (the current that tripped it among those scans)
    amp = run.streams["amplifier"]
    w = (amp.t > t_restart) & (amp.t <= t_tripped)
    assert w.sum() >= 0.9 * (t_tripped - t_restart) / SCAN
    assert np.abs(amp.columns["current"][w]).max() > 5e-3  # beyond the rig's 5-mA limit
    # latched, 0 V commanded and verified: the DAC's last value, the amplifier's input, the plant's output
    assert result.latched and any("latched" in txt for *_, txt in _events(run, "interlock"))
    assert "verified" in _events(run, "safe")[0][3]
    assert abs(amp.columns["commanded"][-1]) <= ZERO_V
    assert abs(plant.v_in) * 1000.0 <= ZERO_V  # the TREK's gain: 1 kV per input volt
    assert np.abs(v_plant[t_plant > t_tripped + RAMP_S + 0.2]).max() <= ZERO_V


def test_a_stop_during_the_ramp_up_ramps_down_from_the_value_last_played(tmp_path: Path) -> None:
    """A stop request mid-ramp ends the run as in a step: the shutdown's ramp (played by the stream-out) starts from
    the value the ramp up had reached, between 0 V and V_HOLD, and the output is at 0 V after it."""
    result, run, t_plant, v_plant, seen, plant = _run(tmp_path, fault_after_resume_s=0.1, stop=True)
    assert result.state == "interrupted", result.reason
    (t_restart, *_), = _events(run, "restart")
    assert t_restart <= seen["fault"] <= t_restart + RAMP_S
    assert _events(run, "offset") == []  # the step never started again
    ramps = [txt for *_, txt in _events(run, "ramp") if txt.startswith("ramp from")]
    assert len(ramps) == 1 and "stream-out" in ramps[0]
    v0 = float(ramps[0].split()[2])
    assert 0.1 * V_HOLD < v0 < 0.9 * V_HOLD  # cut short mid-ramp (0.1 s of the 0.25-s ramp: 40 %)
    amp = run.streams["amplifier"]
    w = (amp.t > t_restart) & (amp.t <= seen["fault"])
    assert w.sum() >= 0.9 * (seen["fault"] - t_restart) / SCAN  # the ramp up on the scan clock until the request
    assert abs(plant.v_in) * 1000.0 <= ZERO_V
    assert np.abs(v_plant[t_plant > seen["fault"] + 2 * RAMP_S + 0.2]).max() <= ZERO_V
    assert "verified" in _events(run, "safe")[0][3]


def test_an_output_mismatch_during_the_ramp_up_ends_at_0_v(tmp_path: Path) -> None:
    """The amplifier's gain drops 25 % mid-ramp: the scan-clock monitors trip the output check, the stream stops and
    0 V is commanded at once. The host's 0-V DAC write comes at the instant the stopped stream's last scan was
    counted played (its time a rounding later): before the fix the twin's plant kept that stale scan in force and the
    output stayed at ~2 kV ("monitor still reads 1495 V", 2026-11-28); the rig's 50-V touch limit bounds it after."""
    result, run, t_plant, v_plant, seen, plant = _run(tmp_path, fault_after_resume_s=0.01, gain=0.75)
    assert result.state == "tripped" and "output mismatch" in result.reason, result.reason
    (t_restart, *_), = _events(run, "restart")
    (t_tripped, *_), = _events(run, "tripped")
    assert t_restart <= seen["fault"] <= t_tripped <= t_restart + RAMP_S  # tripped within the ramp up
    assert result.latched
    safe = _events(run, "safe")[0][3]
    assert "verified" in safe and "WARNING" not in safe, safe
    assert abs(plant.v_in) * 1000.0 <= ZERO_V  # the TREK's gain: 1 kV per input volt
    assert np.abs(v_plant[t_plant > t_tripped + RAMP_S]).max() <= ZERO_V
