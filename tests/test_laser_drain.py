"""The upload of a step's stored laser data after the step (the drain) on the software-timed thesis rig: the run
stays supervised meanwhile, a long drain leaves the specimen at 0 V, and the next step is never cut short.

The drain's length is set by the test: each upload after the ramp takes ``UPLOAD_S`` more of rig time, as a slow
wire would (virtual time; the host takes next to no wall time). Expected values come from the protocol below
(5 kV at the ramp's end, a 2-s hold), the rig file (``shutdown_ramp_s``, the 8-kV limit, the ADAM-4024's code)
and the plant's own output history, never from the engine's account of itself.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import bench.runtime.engine as engine_mod
from bench.runtime.control import write_control
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import RunFile, open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "drain"
description = "a ramp to 5 kV with laser storage, then a hold"
rig = "thesis-sim"

[recording]
displacement_Hz = 200
monitors_Hz = 5
setpoint_Hz = 20

[[steps]]
type = "ramp"
name = "up"
to = "5 kV"
duration_s = 1.0

[[steps]]
type = "hold"
name = "hold"
duration_s = 2.0

[[steps]]
type = "relax"
name = "end"
duration_s = 0.5
"""
RIG = ROOT / "rigs" / "thesis-sim.toml"
RAMP_END = 1.0  # program time of the ramp's end (its duration): the drain begins there
HOLD_S = 2.0  # the hold step's duration
V_HOLD = 5000.0  # the ramp's target, held by the next step
MONITORS_HZ = 5.0
UPLOAD_S = 0.2  # rig time each upload after the ramp takes (the driver sizes one upload to ~0.2 s on the wire)
ZERO_V = 5.0  # |output| at or below this counts as 0 V (one ADAM-4024 code × the TREK gain)
CONTROL_LOOK_S = 0.12  # wall time: more than the engine's CONTROL_POLL_S between two looks at the control file


@dataclasses.dataclass
class Drained:
    """A virtual-time run whose drain after the ramp was made ``uploads`` × ``UPLOAD_S`` longer."""

    result: Any
    run: RunFile
    sim: Any
    t0: float  # rig-clock time of run time 0
    blocks: list[tuple[np.ndarray, np.ndarray]]
    t_fault: float = float("nan")  # run time of the fault injected during the drain, if any
    t_asked: float = float("nan")  # run time of the pause or stop request, as the test made it

    def output(self) -> tuple[np.ndarray, np.ndarray]:
        """The plant's output (run time, volts)."""
        self.sim.plant.observe()
        return (np.concatenate([b[0] for b in self.blocks]) - self.t0,
                np.concatenate([b[1] for b in self.blocks]))

    def events(self, kind: str) -> list[tuple[float, int, str]]:
        return [(t, step, text) for t, step, k, text in self.run.event_list() if k == kind]

    def step_span(self, index: int) -> tuple[float, float]:
        """Run times of the last start and the end of step ``index`` in the file."""
        (t_start, *_), = [e for e in self.events("start") if e[1] == index][-1:]
        (t_end, *_), = [e for e in self.events("end") if e[1] == index]
        return t_start, t_end


def drained_run(tmp: Path, monkeypatch: pytest.MonkeyPatch, uploads: int, fault: bool = False,
                pause: tuple[float, float] | None = None, slow_pause: bool = True,
                stop_at: float | None = None, withhold: bool = False,
                also: Callable[[Any], None] | None = None, protocol: str = PROTOCOL) -> Drained:
    """``pause``: (run time of a pause request, of the resume request): then the uploads of the pause's drain are
    the slow ones, not the ramp's, unless not ``slow_pause`` (the request comes during the ramp's drain).
    ``stop_at``: run time at which the run's control file asks for a stop (the watch page's stop button); each
    upload then also takes a control-file look's worth of wall time, so the engine may see the file meanwhile.
    ``withhold``: the slow uploads bring nothing (the storage's data come only with the first upload after them),
    so that a drain cut short leaves stored data behind. ``also(engine)``: called at every tick of the rig's clock
    as well."""
    proto = tmp / "drain.toml"
    proto.write_text(protocol)
    real = engine_mod.record_laser_block  # type: ignore[attr-defined]  # the name the engine calls
    left = [uploads]
    seen: dict[str, Any] = {}

    def slow_upload(ctx: Any) -> int:
        draining = seen["engine"].snapshot.state == "paused" if pause and slow_pause else \
            ctx.program_now() >= RAMP_END
        n = 0 if withhold and draining and left[0] > 0 else real(ctx)
        if draining and left[0] > 0:  # the drain after the ramp or in the pause (the engine's own calls)
            if fault and "fault" not in seen:  # the amplifier's gain 25 % off, at the drain's first upload
                seen["fault"] = ctx.now()
                plant = seen["sim"].plant
                plant.hv = dataclasses.replace(plant.hv, gain=plant.hv.gain * 1.25)
            left[0] -= 1
            if stop_at is not None:
                time.sleep(CONTROL_LOOK_S)
            seen["sim"].clock.advance(UPLOAD_S)
            return max(n, 1)
        return n

    monkeypatch.setattr(engine_mod, "record_laser_block", slow_upload)
    blocks: list[tuple[np.ndarray, np.ndarray]] = []

    def hook(engine: Any, sim: Any) -> None:
        seen["sim"], seen["engine"] = sim, engine
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if "t0" not in seen and engine.snapshot.state == "running":
                seen["t0"] = sim.clock.now() - engine.now()
            if pause and engine.pauses == 0 and engine.snapshot.state == "running" and engine.now() >= pause[0] \
                    and "asked" not in seen:
                seen["asked"] = engine.now()
                engine.request_pause("the test")
            if stop_at is not None and engine.now() >= stop_at and "asked" not in seen:
                seen["asked"] = engine.now()
                write_control(tmp / "run.h5", False, "the test", "stop button", stop=True)
            if pause and engine.snapshot.state == "paused" and engine.now() >= pause[1]:
                engine.request_resume("the test")
            if also is not None:
                also(engine)
        sim.clock.subscribe(at)

    result = execute(plan_run(proto, RIG), tmp / "run.h5", virtual=True, on_engine=hook)
    assert left[0] == 0 or fault or stop_at is not None  # the drain took the uploads asked for (a fault or a stop
    # may end it sooner)
    return Drained(result, open_run(result.path), seen["sim"], seen["t0"], blocks, seen.get("fault", float("nan")),
                   seen.get("asked", float("nan")))


def test_a_long_drain_is_supervised_goes_to_zero_and_the_next_step_restarts_whole(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """3 s of uploads after the ramp to 5 kV (a link far behind its storage): monitor readings all through the
    drain; the output, at 5 kV when it began, at 0 V for the second half of it at least (high voltage the protocol
    did not ask for is not held while the link catches up); then the hold step restarts — the output back at
    5 kV — and runs its whole 2 s."""
    uploads = 15
    d = drained_run(tmp_path, monkeypatch, uploads)
    assert d.result.state == "completed", d.result.reason
    t_hold, t_hold_end = d.step_span(1)
    assert t_hold >= RAMP_END + uploads * UPLOAD_S  # the drain was as long as the test made it
    # monitor readings at the protocol's rate all through the drain: one period, plus one upload between two polls
    amp = d.run.streams["amplifier"]
    during = amp.t[(amp.t >= RAMP_END) & (amp.t <= t_hold)]
    assert during.size >= uploads * UPLOAD_S * MONITORS_HZ * 0.8
    gaps = np.diff(np.concatenate([[RAMP_END], during, [t_hold]]))
    assert gaps.max() <= 1 / MONITORS_HZ + UPLOAD_S + 0.1, gaps.max()
    # the output: at 5 kV when the drain began, at 0 V from half-way through it until the restart
    t, v = d.output()
    (t_restart, _, text), = d.events("restart")
    assert "output to 5000 V" in text
    assert abs(np.interp(RAMP_END + 0.05, t, v) - V_HOLD) < 0.02 * V_HOLD
    zero = (t > RAMP_END + uploads * UPLOAD_S / 2) & (t < t_restart)
    assert zero.any() and np.abs(v[zero]).max() <= ZERO_V
    # the hold step whole, at 5 kV, after the restart
    assert t_hold >= t_restart and t_hold_end - t_hold == pytest.approx(HOLD_S, abs=1e-6)
    held = (t > t_hold + 0.1) & (t < t_hold_end)
    assert np.abs(v[held] - V_HOLD).max() < 0.02 * V_HOLD
    assert d.run.step_offsets()[1] == pytest.approx(t_hold - RAMP_END, abs=1e-6)


def test_a_restarted_step_starts_from_its_own_first_value_not_the_step_before_its_end(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A tester's run: after the upload's 0 V, a raised cosine that starts at 0 V was restarted by ramping the output
    back to the ramp's 5 kV, which the step then dropped at once to its own 0 V — a 5-kV pulse the protocol never
    asks for in that place. The restart now brings the output to the step's own first value (0 V here: nothing
    to ramp), and the step runs whole."""
    cosine = PROTOCOL.replace('type = "hold"\nname = "hold"\nduration_s = 2.0',
                              'type = "waveform"\nname = "hold"\nkind = "raised_cosine"\namplitude = "3 kV"\n'
                              'frequency_Hz = 1.0\ncycles = 2')
    assert cosine != PROTOCOL
    d = drained_run(tmp_path, monkeypatch, 15, protocol=cosine)
    assert d.result.state == "completed", d.result.reason
    (t_restart, step, text), = d.events("restart")
    assert step == 1 and "output to 0 V" in text, text
    t_step, t_step_end = d.step_span(1)
    t, v = d.output()
    assert np.abs(v[(t > t_restart) & (t < t_step)]).max(initial=0.0) <= ZERO_V  # no pulse before the step
    assert t_step_end - t_step >= HOLD_S - 1e-6  # 2 cycles at 1 Hz, whole (its own upload before its end event)


def test_a_short_drain_holds_the_output_and_shifts_the_schedule_so_the_next_step_runs_whole(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two uploads (0.4 s) after the ramp: the output holds 5 kV through them (no ramp down and up for a short
    upload), monitored; the hold step then starts late but runs its whole 2 s, and the file says by how much the
    program's schedule moved (an ``offset`` event the analysis reads)."""
    uploads = 2
    d = drained_run(tmp_path, monkeypatch, uploads)
    assert d.result.state == "completed", d.result.reason
    t_hold, t_hold_end = d.step_span(1)
    assert t_hold >= RAMP_END + uploads * UPLOAD_S
    assert t_hold_end - t_hold == pytest.approx(HOLD_S, abs=1e-6)  # not cut short by the drain
    assert d.events("restart") == []
    t, v = d.output()
    drain = (t > RAMP_END + 0.05) & (t < t_hold)
    assert np.abs(v[drain] - V_HOLD).max() < 0.02 * V_HOLD  # held through the drain
    amp = d.run.streams["amplifier"]
    assert ((amp.t > RAMP_END) & (amp.t < t_hold)).sum() >= 2
    # the file's account: a drain event and the shift, which the analysis applies to the hold step
    assert [step for _, step, _ in d.events("drain")] == [0]
    shift = d.run.step_offsets()[1]
    assert shift == pytest.approx(t_hold - RAMP_END, abs=1e-6)
    assert d.result.run_time >= 3.5 + uploads * UPLOAD_S  # the protocol's 3.5 s, plus the drain


def test_a_fault_during_the_drain_trips_the_run_to_zero(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The amplifier's gain goes 25 % off at the drain's first upload, the output held at 5 kV (6.25 kV now): the
    monitors, read during the drain, disagree with the set-point; the run latches in the drain — the hold step
    never starts — and ends at 0 V within the polled verifier's bound (three reading periods at the protocol's
    rate after the 0.3-s lag, plus one upload between polls)."""
    d = drained_run(tmp_path, monkeypatch, 15, fault=True)
    assert d.result.state == "tripped" and "interlock: output mismatch" in d.result.reason, d.result.reason
    assert [e for e in d.events("start") if e[1] == 1] == []  # tripped in the drain, before the next step
    (t_trip, step, _), = d.events("tripped")
    assert step == 0 and t_trip < RAMP_END + 15 * UPLOAD_S
    t, v = d.output()
    assert np.abs(v[t < d.t_fault]).max() > 0.9 * V_HOLD  # it was at high voltage when the fault came
    last_high = float(t[np.abs(v) > ZERO_V][-1])
    assert last_high <= d.t_fault + 0.3 + 3 / MONITORS_HZ + UPLOAD_S + 0.05
    assert np.abs(v[t > last_high]).max(initial=0.0) <= ZERO_V
    assert d.run.streams["setpoints"].columns["voltage"][-1] == 0.0


def test_a_pause_zeroes_the_output_before_the_upload_not_after_it(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Paused half-way up the ramp (2.5 kV), with 3 s of stored data to upload: the output is at 0 V once the rig's
    shutdown ramp is over, all through the upload, until the resume — the pause does not hold the voltage while
    the laser catches up."""
    uploads = 15
    d = drained_run(tmp_path, monkeypatch, uploads, pause=(0.5, 6.0))
    assert d.result.state == "completed", d.result.reason
    (t_pause, *_), = d.events("pause")
    (t_resume, *_), = d.events("resume")
    assert t_resume - t_pause >= uploads * UPLOAD_S  # the upload was inside the pause
    t, v = d.output()
    assert np.abs(v[t < t_pause]).max() > 0.4 * V_HOLD  # under high voltage when paused
    ramp_s = plan_run(tmp_path / "drain.toml", RIG).rig.limits.shutdown_ramp_s
    paused = (t > t_pause + ramp_s + 0.05) & (t < t_resume)
    assert np.abs(v[paused]).max() <= ZERO_V
    amp = d.run.streams["amplifier"]  # and the monitors read on through the upload
    assert ((amp.t > t_pause + ramp_s) & (amp.t < t_pause + uploads * UPLOAD_S)).sum() >= uploads * UPLOAD_S * 2


def test_a_pause_during_the_drain_zeroes_the_output_at_once_and_the_resume_restarts_the_next_step(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A pause asked for 0.3 s into a 3-s drain after the ramp to 5 kV (before the drain's own 1-s hold is over):
    the output goes to 0 V at the next upload, over the rig's shutdown ramp, and stays there until the resume — no
    ramp back up to the hold's 5 kV when the upload ends; the resume then restarts the hold step, which runs whole."""
    uploads = 15
    d = drained_run(tmp_path, monkeypatch, uploads, pause=(RAMP_END + 0.3, 8.0), slow_pause=False)
    assert d.result.state == "completed", d.result.reason
    assert RAMP_END < d.t_asked < RAMP_END + 0.5  # asked for inside the drain, the output then at 5 kV
    (t_pause, step, _), = d.events("pause")
    (t_resume, *_), = d.events("resume")
    assert step == 1 and t_pause >= RAMP_END + uploads * UPLOAD_S  # the pause itself: after the drain, in the hold
    t, v = d.output()
    assert abs(np.interp(d.t_asked, t, v) - V_HOLD) < 0.02 * V_HOLD
    ramp_s = plan_run(tmp_path / "drain.toml", RIG).rig.limits.shutdown_ramp_s
    paused = (t > d.t_asked + UPLOAD_S + ramp_s + 0.05) & (t < t_resume)
    assert paused.any() and np.abs(v[paused]).max() <= ZERO_V  # 0 V from one upload + the ramp after the request
    # no restart before the pause (it would ramp the output back up); one after the resume, of the hold step
    (t_restart, step, text), = d.events("restart")
    assert step == 1 and t_restart >= t_resume and "output to 5000 V" in text
    t_hold, t_hold_end = d.step_span(1)
    assert t_hold >= t_restart and t_hold_end - t_hold == pytest.approx(HOLD_S, abs=1e-6)
    held = (t > t_hold + 0.1) & (t < t_hold_end)
    assert np.abs(v[held] - V_HOLD).max() < 0.02 * V_HOLD


def test_a_pause_withdrawn_during_the_drain_at_0_v_is_recorded_not_lost(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A pause, then a resume 0.3 s later, both while the drain after the ramp holds the output at 0 V (its own 1-s
    hold over, the upload going on until 3 s after the ramp): neither takes effect — the run never pauses — but
    both reach the file, as one ``request`` event saying the pause was withdrawn before it was taken (README:
    every pause and resume request the run receives is recorded)."""
    asked: dict[str, float] = {}

    def also(engine: Any) -> None:
        now = engine.now()
        if "pause" not in asked and now >= RAMP_END + 2.0:
            asked["pause"] = now
            asked["v"] = engine.ctx.v_cmd
            engine.request_pause("ada")
        elif "pause" in asked and "resume" not in asked and now >= asked["pause"] + 0.3:
            asked["resume"] = now
            engine.request_resume("bo")

    uploads = 15
    d = drained_run(tmp_path, monkeypatch, uploads, also=also)
    assert d.result.state == "completed", d.result.reason
    assert abs(asked["v"]) <= ZERO_V and asked["resume"] < RAMP_END + uploads * UPLOAD_S  # both inside the zeroed drain
    assert not d.events("pause") and not d.events("resume")
    (t, _, text), = d.events("request")
    assert asked["resume"] <= t <= RAMP_END + uploads * UPLOAD_S + 0.5
    assert "pause asked by ada" in text and "resume asked by bo" in text and "withdrawn" in text, text


def test_a_control_file_stop_during_the_drain_ends_the_run_without_raising_the_output(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The watch page's stop button (the control file's stop word) 0.3 s into a 3-s drain after the ramp to 5 kV:
    the run ends interrupted, by that request, at 0 V; the output never rises after the request (no restart of the
    hold step's 5 kV before the stop is seen), and the ramp down starts within one upload of it."""
    uploads = 15
    d = drained_run(tmp_path, monkeypatch, uploads, stop_at=RAMP_END + 0.3)
    assert d.result.state == "interrupted" and "stop asked by the test" in d.result.reason, d.result.reason
    assert RAMP_END < d.t_asked < RAMP_END + 0.5
    assert d.events("restart") == []
    t, v = d.output()
    v_asked = float(np.interp(d.t_asked, t, v))
    assert abs(v_asked - V_HOLD) < 0.02 * V_HOLD
    after = t > d.t_asked
    assert np.abs(v[after]).max() <= v_asked + 0.01 * V_HOLD  # never above its value at the request
    ramp_s = plan_run(tmp_path / "drain.toml", RIG).rig.limits.shutdown_ramp_s
    assert np.abs(v[t > d.t_asked + UPLOAD_S + ramp_s + 0.05]).max() <= ZERO_V
    assert d.run.streams["setpoints"].columns["voltage"][-1] == 0.0


def test_the_restart_ramp_after_a_long_drain_is_monitored(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The restart after a long drain ramps the output from 0 V to 5 kV over the rig's shutdown ramp: the monitors
    are read (and so supervised) during that ramp and its settle, at the protocol's rate, not only once the hold
    step has started — a fault that shows on the way up is seen on the way up."""
    d = drained_run(tmp_path, monkeypatch, 15)
    assert d.result.state == "completed", d.result.reason
    (t_restart, *_), = d.events("restart")
    t_hold, _ = d.step_span(1)
    ramp_s = plan_run(tmp_path / "drain.toml", RIG).rig.limits.shutdown_ramp_s
    assert t_hold - t_restart >= ramp_s  # the ramp up lies between the two
    amp = d.run.streams["amplifier"]
    during = amp.t[(amp.t > t_restart) & (amp.t < t_hold)]
    assert during.size >= int(ramp_s * MONITORS_HZ) + 1, during
    # readings on the way up: a monitored voltage between 0 V and the hold's 5 kV
    v_mon = amp.columns["voltage"][(amp.t > t_restart) & (amp.t < t_hold)]
    assert ((v_mon > 0.05 * V_HOLD) & (v_mon < 0.95 * V_HOLD)).any(), v_mon


def test_a_stop_during_the_drain_leaves_what_is_left_to_the_shutdowns_fetch(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A control-file stop 0.3 s into a drain whose uploads bring nothing yet (a link far behind): the shutdown,
    at 0 V, fetches the step's stored data that the drain did not — the file holds the ramp's displacement up to
    its end (200 Hz), not only what the step's own fetches brought."""
    d = drained_run(tmp_path, monkeypatch, 15, stop_at=RAMP_END + 0.3, withhold=True)
    assert d.result.state == "interrupted", d.result.reason
    laser = d.run.streams["laser"]
    assert laser.t.max() >= RAMP_END - 2 / 200 and laser.t.size >= 200 * RAMP_END, (laser.t.size, laser.t.max())


def test_a_pause_whose_upload_outlasts_the_shutdown_budget_goes_on(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """6 s of stored data to upload in a pause (more than the 5 s a stop's shutdown allows itself): the output is
    at 0 V and the run supervised, so the pause uploads it all with a step's drain budget, and the run completes
    after the resume instead of ending with an error."""
    uploads = 30
    d = drained_run(tmp_path, monkeypatch, uploads, pause=(0.5, 9.0))
    assert d.result.state == "completed", d.result.reason
    (t_pause, *_), = d.events("pause")
    (t_resume, *_), = d.events("resume")
    assert t_resume - t_pause >= uploads * UPLOAD_S

