"""On a rig whose amplifier is driven by host set-points (the ADAM rig) the shutdown's ramp to 0 V reads the
amplifier's monitors as a step does — at the protocol's ``monitors_Hz``, into the amplifier stream — and supervises
them: the file has the ramp measured, not only commanded, and a fault during it (the output not following the ramp)
is seen when it happens, not left to the final verify. A read that fails never holds the ramp back from 0 V.

Before, the monitors were read no more once the stop began: the stream's last rows were the one before the request
and the verifying read after 0 V, and a gain fault that came with the stop went unseen (the final read, at 0 V,
verified the zero). Expected values come from the protocol below (5 kV held when the stop comes), the rig file
(``shutdown_ramp_s``), the README (the stop bound; two polled readings in a row out of band latch; the
ADAM-4017+ converts each monitor at 5 S/s, integrating 20 ms) and the plant's own output history, never from the
engine's account of itself. Virtual time."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.rig import RigConfig
from bench.runtime.engine import Engine, RunResult
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import RunFile, open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "stop-in-hold"
description = "a ramp to 5 kV, a hold (stopped in it)"
rig = "{rig}"

[recording]
displacement_Hz = 2000
setpoint_Hz = 20
monitors_Hz = {monitors_hz}

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "5 kV"
duration_s = 1.0

[[steps]]
type = "hold"
name = "hold"
duration_s = 3.0
"""
ADAM_RIG = ROOT / "rigs" / "thesis-sim.toml"
V_HOLD = 5000.0  # the ramp step's end value, held when the stop comes
STOP_AT = 2.0  # run time: in the hold (program 1.0–4.0 s)
RAMP_S = 0.25  # the rig's shutdown_ramp_s
SLOW_RAMP_S = 2.0  # a slower shutdown ramp (rig override): room for a fault to be seen in it
MONITORS_HZ = 5.0  # the ADAM-4017+'s rate per monitor (10 S/s over the two enabled channels)
CONVERSION_S = 2 / 10.0 + 0.02  # a reading is the mean over 20 ms ending at a conversion at most 0.2 s old
BOUND_S = 0.2  # README "Stopping": the ramp starts within 0.2 s, 0 V within shutdown_ramp_s + 0.2 s
ZERO_V = 5.0  # one code of the 12-bit ADAM-4024 times the TREK gain
NOISE_V = 25.0  # monitor noise, its gain/offset error and one 16-bit code of the ADAM-4017+, bounded


def _events(run: RunFile, kind: str) -> list[tuple[float, int, str, str]]:
    return [e for e in run.event_list() if e[2] == kind]


Outcome = tuple[RunResult, RunFile, np.ndarray, np.ndarray, np.ndarray, dict[str, float]]


def _run(tmp: Path, ramp_s: float = RAMP_S, fault: str | None = None, monitors_hz: float = MONITORS_HZ,
         patch: Any = None, pause: bool = False) -> Outcome:
    """The protocol on the simulated ADAM rig in virtual time, a stop requested at ``STOP_AT``; ``fault``:
    ``gain`` (the amplifier's gain 25 % high from the stop on), ``breakdown`` (the dielectric breaks down as the stop
    comes: the electrodes shorted, the output current-limited); ``pause``: a pause is asked for at ``STOP_AT``
    instead (its ramp to 0 V is the same ``shutdown_ramp_s``), the stop 3 s later. Returns (result, run file, the
    plant's times on the run clock, its true output, its voltage monitor's output, what the hook saw)."""
    proto = tmp / "stop-in-hold.toml"
    proto.write_text(PROTOCOL.format(rig=ADAM_RIG.as_posix(), monitors_hz=monitors_hz))
    plan = plan_run(proto)
    if ramp_s != plan.rig.limits.shutdown_ramp_s:
        fields = plan.rig.model_dump()
        fields["limits"] = {**fields["limits"], "shutdown_ramp_s": ramp_s}
        plan.rig = plan.program.rig = RigConfig.model_validate(fields)
    blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    seen: dict[str, float] = {}

    def hook(engine: Engine, sim: Any) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy(), b.voltage.copy())))
        if patch is not None:
            patch(engine, sim)

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and "t0" not in seen:
                seen["t0"] = sim.clock.now() - engine.now()
            if engine.snapshot.state == "running" and "stop" not in seen and engine.now() >= STOP_AT:
                seen["stop"] = engine.now()
                if fault == "gain":
                    sim.plant.hv = dataclasses.replace(sim.plant.hv, gain=sim.plant.hv.gain * 1.25)
                elif fault == "breakdown":
                    sim.plant.inject_breakdown()
                if pause:
                    engine.request_pause("the test")
                else:
                    engine.request_stop("the test")
            if pause and "stop" in seen and engine.now() >= seen["stop"] + 3.0 and "stopped" not in seen:
                seen["stopped"] = engine.now()
                engine.request_stop("the test")
        sim.clock.subscribe(at)

    result = execute(plan, tmp / "run.h5", virtual=True, on_engine=hook)
    t = np.concatenate([b[0] for b in blocks]) - seen["t0"]
    return (result, open_run(result.path), t, np.concatenate([b[1] for b in blocks]),
            np.concatenate([b[2] for b in blocks]), seen)


def test_the_shutdown_ramp_is_measured_by_the_monitors_and_reaches_0_v_within_the_bound(tmp_path: Path) -> None:
    result, run, t_plant, v_plant, vmon_plant, _ = _run(tmp_path)
    assert result.state == "interrupted", result.reason
    (t_req, *_), = _events(run, "request")
    # the plant: under high voltage at the stop, at 0 V within the stated bound
    assert np.abs(v_plant[(t_plant > t_req - 0.1) & (t_plant <= t_req)]).min() >= 0.95 * V_HOLD
    t_zero = t_plant[(t_plant > t_req) & (np.abs(v_plant) <= ZERO_V)][0]
    assert t_zero <= t_req + RAMP_S + BOUND_S
    amp = run.streams["amplifier"]
    v, late = amp.columns["voltage"], amp.columns["late"]
    # monitor records within the ramp's span (the request to 0 V at the plant): a 5-Hz poll over the 0.25-s ramp
    within = (amp.t > t_req) & (amp.t <= t_zero)
    assert within.sum() >= int(RAMP_S * MONITORS_HZ)
    # scheduled reads (a lateness recorded), as a step's — not the final verify's unscheduled read after 0 V
    assert np.isfinite(late[within]).all()
    # each reading is what the plant's voltage monitor gave over the conversion's window before it: the recorded
    # voltage follows the plant's output, it is no copy of what was commanded
    for tk, vk in zip(amp.t[within], v[within], strict=True):
        w = (t_plant > tk - CONVERSION_S) & (t_plant <= tk)
        assert vmon_plant[w].min() - NOISE_V <= vk <= vmon_plant[w].max() + NOISE_V, (tk, vk)
        assert v_plant[w].min() - 2 * NOISE_V <= vk <= v_plant[w].max() + 2 * NOISE_V, (tk, vk)
    # the ramp itself was measured: a reading strictly between the held value and 0 V
    assert ((v[within] < 0.95 * V_HOLD) & (v[within] > 0.05 * V_HOLD)).any(), v[within]
    (safe,) = _events(run, "safe")
    assert "verified" in safe[3]
    assert not [e for e in _events(run, "fault") if "monitor" in e[3]], _events(run, "fault")


def test_an_output_that_does_not_follow_the_ramp_latches_and_goes_to_0_v_at_once(tmp_path: Path) -> None:
    """The amplifier's gain goes 25 % high as the stop comes (a 2-s ramp): two readings in a row out of the
    verifier's band latch the rig during the ramp and cut it short — 0 V at once, well before the ramp's end. The
    old shutdown read nothing in the ramp, and its final read at 0 V verified the zero: no latch at all."""
    result, run, t_plant, v_plant, _, _ = _run(tmp_path, ramp_s=SLOW_RAMP_S, fault="gain")
    assert result.latched and "output mismatch" in result.latched, (result.state, result.latched)
    # the run's state says so (it said "interrupted", the stop's, with the latch only an event: last note)
    assert result.state == run.state == "tripped", (result.state, run.state)
    assert run.reason.startswith("safety trip during the ramp to 0 V: ") and "(after: " in run.reason, run.reason
    (t_req, *_), = _events(run, "request")
    assert any("during the ramp to 0 V" in txt and "output mismatch" in txt for *_, txt in _events(run, "interlock"))
    # the gain fault shows at the plant (the trial tests something): above the held value after the stop
    assert np.abs(v_plant[(t_plant > t_req) & (t_plant < t_req + 0.2)]).max() > 1.15 * V_HOLD
    # seen by the second out-of-band reading (5 Hz, the first with the ramp's first set-point SLOW_RAMP_S / 10 in),
    # then 0 V at the ramp's next set-point: long before the 2-s ramp would have ended
    t_zero = t_plant[(t_plant > t_req) & (np.abs(v_plant) <= ZERO_V)][0]
    assert t_zero <= t_req + SLOW_RAMP_S / 10 + 3 / MONITORS_HZ + BOUND_S
    assert t_zero < t_req + 0.75 * SLOW_RAMP_S
    assert "verified" in _events(run, "safe")[0][3]


def test_a_limit_exceeded_during_the_ramp_is_a_trip_and_the_ramp_still_ends_at_0_v(tmp_path: Path) -> None:
    """The dielectric breaks down as the stop comes (a 2-s ramp): the monitors read in the ramp show the current
    beyond the rig's 5-mA limit — a trip recorded when it is read, and the rig latched — and the ramp goes on to
    0 V within its bound, verified."""
    result, run, t_plant, v_plant, _, _ = _run(tmp_path, ramp_s=SLOW_RAMP_S, fault="breakdown")
    (t_req, *_), = _events(run, "request")
    trips = _events(run, "tripped")
    assert len(trips) == 1 and "current" in trips[0][3], trips
    # seen in the ramp (its first reading comes with its first set-point, SLOW_RAMP_S / 10 in), not at its end
    assert t_req < trips[0][0] <= t_req + SLOW_RAMP_S / 10 + 1 / MONITORS_HZ + BOUND_S
    assert result.latched.startswith("safety trip") and "current" in result.latched, result.latched
    assert result.state == run.state == "tripped", (result.state, run.state)  # not the stop's "interrupted"
    assert run.reason.startswith("safety trip during the ramp to 0 V: ") and "current" in run.reason, run.reason
    amp = run.streams["amplifier"]
    ramp = (amp.t > t_req) & (amp.t < t_req + SLOW_RAMP_S)
    assert np.abs(amp.columns["current"][ramp]).max() > 5e-3  # the reading that tripped it is in the file
    t_zero = t_plant[(t_plant > t_req) & (np.abs(v_plant) <= ZERO_V)][0]
    assert t_zero <= t_req + SLOW_RAMP_S + BOUND_S
    assert "verified" in _events(run, "safe")[0][3]


@pytest.mark.parametrize("how", ["timeout", "bug"])
def test_a_monitor_read_that_fails_in_the_ramp_is_noted_and_the_ramp_goes_on_to_0_v(tmp_path: Path,
                                                                                    how: str) -> None:
    """The monitors' read raises in the ramp (a reply lost on the bus, or anything a driver lets out): said as a
    fault, the ramp's set-points go on to 0 V over the ramp (not cut short, not held back)."""
    from drivers.errors import InstrumentTimeoutError

    def patch(engine: Engine, sim: Any) -> None:
        amp = engine.inst.amplifier
        read = amp.read

        def failing() -> Any:
            if engine._stopping:  # the shutdown has begun
                raise InstrumentTimeoutError("ADAM-4017+", "no reply") if how == "timeout" else RuntimeError("bug")
            return read()
        amp.read = failing

    result, run, t_plant, v_plant, _, _ = _run(tmp_path, ramp_s=SLOW_RAMP_S, patch=patch)
    assert result.state == "interrupted", result.reason
    (t_req, *_), = _events(run, "request")
    faults = [txt for *_, txt in _events(run, "fault") if "monitor read during the ramp" in txt]
    assert len(faults) == 1, faults  # said once: the ramp goes on unread
    # the ramp went on: the plant still above half the held value half-way through it, and at 0 V within the bound
    mid = (t_plant > t_req + 0.4 * SLOW_RAMP_S) & (t_plant < t_req + 0.45 * SLOW_RAMP_S)
    assert np.abs(v_plant[mid]).min() > 0.4 * V_HOLD
    t_zero = t_plant[(t_plant > t_req) & (np.abs(v_plant) <= ZERO_V)][0]
    assert t_zero <= t_req + SLOW_RAMP_S + BOUND_S
    assert "verified" in _events(run, "safe")[0][3]


def test_a_pause_s_ramp_is_measured_by_the_monitors_and_an_output_not_following_it_latches(tmp_path: Path) -> None:
    """A pause ramps the output to 0 V over the same ``shutdown_ramp_s``: its set-points are supervised as a step's
    (the restart's ramp up already was), so the monitors are read and recorded through it and a gain 25 % high
    latches the rig during it. Before, the pause's ramp read nothing: the fault went unseen until a paused reading
    at 0 V (which verifies the zero)."""
    result, run, t_plant, v_plant, _, seen = _run(tmp_path, ramp_s=SLOW_RAMP_S, fault="gain", pause=True)
    t_pause = seen["stop"]
    assert result.latched and "output mismatch" in result.latched, (result.state, result.latched)
    amp = run.streams["amplifier"]
    within = (amp.t > t_pause) & (amp.t <= t_pause + 0.75 * SLOW_RAMP_S)
    assert within.sum() >= 2  # read in the ramp: two out-of-band readings in a row latch (README)
    (t_tripped, *_), = [e for e in run.event_list() if e[2] in ("tripped", "interlock")][:1]
    assert t_pause < t_tripped < t_pause + 0.75 * SLOW_RAMP_S  # latched during the pause's ramp, not after it
    t_zero = t_plant[(t_plant > t_pause) & (np.abs(v_plant) <= ZERO_V)][0]
    assert t_zero < t_pause + 0.75 * SLOW_RAMP_S + BOUND_S
    assert "verified" in _events(run, "safe")[0][3]
