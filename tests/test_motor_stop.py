"""A stop stops the motor at once, not after the voltage's ramp-down, and the file says where it came to rest.

Found by an exploratory run: Ctrl-C during the 50-mm/s move of lsdea-isometric-short on the served
lsdea-motor-daq-sim rig left the carriage moving for the whole ramp-down (the shutdown ramped the voltage first and
stopped the motor only after it); the file's last motor sample was 13 mm short of where the drive stopped, and it
had no account of the stop at all.

The bound is the drive's, not the engine's: the abort telegram (a LinRS control word, 9 bytes, and its 16-byte
default response at the rig file's 115,200 Bd, a few ms with the drive's turnaround) reaches the drive within
``REACT_S`` of the request, and the drive then decelerates at its quick-stop deceleration (the twin's
``quick_stop_decel`` parameter, MC-SW §3.12) from the move's velocity (the protocol's): at rest
``REACT_S + v / a`` after the request, ``v·REACT_S + v² / 2a`` beyond where it was — against a ramp-down of
``shutdown_ramp_s``. The carriage's motion is the plant's (the twin's own state machine moves it), read through a
spy on the twin's halt, not from the run file.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import RunFile, open_run
from sim_devices.linmot_drive import LinMotDriveSim
from tests.conftest import ROOT

ISOMETRIC = ROOT / "protocols" / "short" / "lsdea-isometric-short.toml"  # first step: to 100 mm at 0.05 m/s
T_STOP = 0.5  # run time [s] of the stop: mid-move (the move from the home position takes about 1.1 s)
REACT_S = 0.02  # the abort's way to the drive: wire time of one LinRS exchange and the drive's turnaround, with margin
BOUND_S = 0.2  # README: the ramp-down starts within 0.2 s of a stop request; 0 V within ramp + 0.2 s


@dataclass
class Stopped:
    """A virtual-time run stopped at ``T_STOP``, and what the twin's drive did."""

    run: RunFile
    result: Any
    sim: Any
    engine: Engine
    t_req: float = float("nan")  # run time of the request
    t_req_rig: float = float("nan")  # the same on the rig clock
    at_req: tuple[float, float] = (float("nan"), float("nan"))  # the plant's (position, velocity) then
    halts: list[tuple[float, float, float, float]] = field(default_factory=list)  # rig time, position, velocity, dec

    def first_halt(self) -> tuple[float, float, float, float]:
        """The drive's first halt after the request: (rig time, position, velocity, deceleration)."""
        after = [h for h in self.halts if h[0] >= self.t_req_rig]
        assert after, "the drive never halted after the stop request"
        return after[0]

    def events(self, kind: str) -> list[tuple[float, str]]:
        return [(t, text) for t, _, k, text in self.run.event_list() if k == kind]


def spy_halts(monkeypatch: pytest.MonkeyPatch) -> list[tuple[float, float, float, float]]:
    """The LinMot twin's halts from now on, as (rig time, position, velocity, deceleration): the drive's own account
    of when and how fast it began to stop."""
    halts: list[tuple[float, float, float, float]] = []
    halt = LinMotDriveSim._halt

    def spy(self: LinMotDriveSim, dec: float) -> None:
        p, v = self.plant.motor_state(self._now)
        halts.append((self._now, p, v, dec))
        halt(self, dec)

    monkeypatch.setattr(LinMotDriveSim, "_halt", spy)
    return halts


def stop_mid_move(tmp: Path, monkeypatch: pytest.MonkeyPatch, mute_motor: bool = False) -> Stopped:
    """Run lsdea-isometric-short in virtual time and request a stop at ``T_STOP`` (``mute_motor``: the drive
    answers nothing from the request on)."""
    seen: dict[str, Any] = {}
    halts = spy_halts(monkeypatch)

    def hook(engine: Engine, sim: Any) -> None:
        seen.update(engine=engine, sim=sim)

        def at(_t: float) -> None:
            if "t_req" not in seen and engine.snapshot.state == "running" and engine.now() >= T_STOP:
                seen.update(t_req=engine.now(), t_req_rig=sim.clock.now(),
                            at_req=sim.plant.motor_state(sim.clock.now()))
                if mute_motor:
                    sim.faults_of("motor").mute = True
                engine.request_stop("stopped by the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(ISOMETRIC), tmp / "run.h5", virtual=True, on_engine=hook)
    out = Stopped(open_run(result.path), result, seen["sim"], seen["engine"], seen["t_req"], seen["t_req_rig"],
                  seen["at_req"], halts)
    assert result.state == "interrupted" and result.reason == "stopped by the test", result.reason
    return out


def final_position(text: str) -> float:
    """The final position [m] a ``motor`` event gives."""
    m = re.search(r"final position (-?[0-9.]+) mm", text)
    assert m, text
    return float(m.group(1)) * 1e-3


def test_a_stop_mid_move_stops_the_carriage_at_once_not_after_the_ramp_down(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = stop_mid_move(tmp_path, monkeypatch)
    plan = plan_run(ISOMETRIC)
    _, v_move, _ = plan.program.segments[0].move or (0.0, 0.0, 0.0)
    assert s.at_req[1] == pytest.approx(v_move)  # stopped mid-move, at the protocol's velocity
    t_halt, _, v, dec = s.first_halt()
    assert dec == s.sim.twins["motor"].quick_stop_decel  # an abort: the drive's quick stop (MC-SW §3.12)
    at_rest = t_halt + abs(v) / dec
    ramp = plan.rig.limits.shutdown_ramp_s
    assert next(text for _, text in s.events("ramp")).startswith("ramp from")  # the shutdown did ramp the voltage
    assert at_rest - s.t_req_rig <= REACT_S + v_move / dec  # the drive's bound
    assert at_rest - s.t_req_rig < ramp / 4  # well before the ramp-down ends
    x_end = s.sim.plant.motor_state(s.sim.clock.now())[0]  # the plant: where the carriage came to rest
    assert x_end - s.at_req[0] <= v_move * REACT_S + v_move**2 / (2 * dec)


def test_the_file_says_when_the_motor_stopped_and_where_it_came_to_rest(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = stop_mid_move(tmp_path, monkeypatch)
    x_end = s.sim.plant.motor_state(s.sim.clock.now())[0]
    (t_motor, text), = s.events("motor")
    assert re.search(rf"stop sent at {s.t_req:.3f} s", text), text
    assert final_position(text) == pytest.approx(x_end, abs=1e-7)  # the drive's 0.1-µm increment
    motor = s.run.streams["motor"]  # its last sample: the final position, read after the stop
    assert motor.t[-1] == pytest.approx(t_motor, abs=1e-3)
    assert motor.columns["position"][-1] == pytest.approx(x_end, abs=1e-7)
    x_cmd = float(plan_run(ISOMETRIC).program.aperture(np.array(x_end)))
    assert motor.columns["aperture"][-1] == pytest.approx(x_cmd, abs=1e-7)


def test_a_silent_motor_link_delays_neither_the_ramp_down_nor_zero_volts_and_the_file_says_so(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = stop_mid_move(tmp_path, monkeypatch, mute_motor=True)
    ramp = plan_run(ISOMETRIC).rig.limits.shutdown_ramp_s
    (t_ramp, _), = s.events("ramp")
    assert t_ramp - s.t_req <= BOUND_S
    (_, safe), = s.events("safe")
    zero_at = float(re.search(r"0 V commanded by the host at ([0-9.]+) s", safe).group(1))  # type: ignore[union-attr]
    assert zero_at - s.t_req <= ramp + BOUND_S
    (_, text), = s.events("motor")
    assert "final position unreadable" in text, text
    assert any("motor stop" in note for _, note in s.events("fault")), s.events("fault")


def test_ctrl_c_mid_move_on_the_wall_clock_stops_the_carriage_while_the_voltage_ramps_down(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The wall-clock path (the motor's stop on its own thread, concurrent with the ramp), with a real SIGINT as
    in the report: the carriage is at rest before the first half of the voltage's ramp-down is over — it used to
    start stopping only when 0 V was commanded — and within the README's 0.2-s bound of the engine's stop request
    (the wall clock's allowance for a loaded host to end the wait under way) plus the abort's way to the drive and
    the drive's deceleration."""
    import os
    import signal
    import threading
    import time

    halts = spy_halts(monkeypatch)
    seen: dict[str, Any] = {}

    def hook(engine: Engine, sim: Any) -> None:
        seen.update(engine=engine, sim=sim)

        def fire() -> None:
            while engine.snapshot.state == "starting" or engine.now() < T_STOP:
                time.sleep(0.005)
            seen["t_action"] = sim.clock.now()
            os.kill(os.getpid(), signal.SIGINT)
        threading.Thread(target=fire, daemon=True).start()

    plan = plan_run(ISOMETRIC)
    result = execute(plan, tmp_path / "run.h5", virtual=False, on_engine=hook)
    run, sim, engine = open_run(result.path), seen["sim"], seen["engine"]
    if result.state == "tripped" and "t_action" not in seen:  # the interlock's verdict on a starved host, before it
        pytest.skip(f"the host stalled before the signal: {result.reason}")
    assert result.state == "interrupted" and result.reason.startswith("interrupted by Ctrl-C"), result.reason
    events: dict[str, tuple[float, str]] = {}
    for t, _, k, text in run.event_list():
        events.setdefault(k, (t, text))  # each kind's first
    requested = re.search(r"stop requested at ([0-9.]+) s", events["request"][1])
    assert requested, events["request"]
    t_req = float(requested.group(1)) + engine.ctx.t0  # the engine's stop request (the signal), on the rig clock
    ramp = plan.rig.limits.shutdown_ramp_s
    zero_at = float(re.search(r"at ([0-9.]+) s", events["safe"][1]).group(1)) + engine.ctx.t0  # type: ignore[union-attr]
    assert zero_at - t_req <= ramp + BOUND_S  # the voltage's bound holds with the motor stopping beside it
    after = [h for h in halts if h[0] >= seen["t_action"]]
    assert after, f"the drive never halted after the signal at {seen['t_action']:.3f} s: {halts}"
    t_halt, _, v, dec = after[0]
    v_move = plan.program.segments[0].move[1]  # type: ignore[index]
    if v == 0 and seen["t_action"] - engine.ctx.t0 > 1.0:  # the move (about 1.1 s) over before the signal went out
        pytest.skip(f"the host sent the signal at {seen['t_action'] - engine.ctx.t0:.3f} s, after the move")
    assert v == pytest.approx(v_move), halts  # stopped mid-move
    at_rest = t_halt + abs(v) / dec
    told = f"request {t_req:.4f}, at rest {at_rest:.4f}, 0 V {zero_at:.4f} s (rig clock); events {events}"
    assert at_rest - t_req <= BOUND_S + REACT_S + abs(v) / dec, told
    t_ramp, how = events["ramp"]
    if how.startswith("ramp from"):  # (a stall the interlock latched zeroes at once: then no ramp to beat)
        assert at_rest <= t_ramp + engine.ctx.t0 + ramp / 2, told  # before the ramp-down is half over
    x_end = sim.plant.motor_state(sim.clock.now())[0]
    assert final_position(events["motor"][1]) == pytest.approx(x_end, abs=1e-7)


def test_a_pause_mid_move_stops_the_carriage_before_the_voltage_ramp(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The pause stopped the motor only after ramping the voltage down (the same order the shutdown had)."""
    halts = spy_halts(monkeypatch)
    seen: dict[str, Any] = {}

    def hook(engine: Engine, sim: Any) -> None:
        def at(_t: float) -> None:
            if "t_req" not in seen and engine.snapshot.state == "running" and engine.now() >= T_STOP:
                seen.update(t_req=sim.clock.now(), v=sim.plant.motor_state(sim.clock.now())[1])
                engine.request_pause("paused by the test")
            elif "t_req" in seen and "stop" not in seen and sim.clock.now() >= seen["t_req"] + 3.0:
                seen["stop"] = True
                engine.request_stop("stopped by the test")
        sim.clock.subscribe(at)

    plan = plan_run(ISOMETRIC)
    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "interrupted", result.reason
    _, v_move, _ = plan.program.segments[0].move or (0.0, 0.0, 0.0)
    assert seen["v"] == pytest.approx(v_move)  # paused mid-move
    t_halt, _, v, dec = next(h for h in halts if h[0] >= seen["t_req"])
    run = open_run(result.path)
    assert any(k == "pause" for _, _, k, _ in run.event_list())
    assert t_halt + abs(v) / dec - seen["t_req"] < plan.rig.limits.shutdown_ramp_s / 4  # at rest before the ramp ends
