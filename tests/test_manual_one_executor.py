"""Manual control is a mode of the one executor (issue 21 item 5): a session's set-points go through the engine's
set-point code on both rig kinds, and its pause is the run's pause (output ramped to 0 V, held until resume).

Expected codes come from the datasheets' formulas (as in tests/test_limits_as_sent.py, written out there, never
from the drivers): ADAM-4024 12-bit offset binary over ±10 V; LabJack T7 16-bit DAC code at 13,200 codes/V, a
12-bit converter (low 4 bits ignored), conditioning 4·DAC − 10 V; TREK 1000 V/V. The ramp's length is the rig
file's ``shutdown_ramp_s`` (README "Pause and resume": a pause ramps the output to 0 V as a stop does).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime.engine import Engine
from bench.runtime.manual import ManualSession
from bench.storage.runfile import open_run
from tests.conftest import RIGS
from tests.test_limits_as_sent import adam_out, t7_out

ZERO_V = 5.0  # one code of either DAC times the TREK gain: 0 V itself has no code on the ADAM-4024 (±2.44 V)
# the nearest code at or inside an 8000-V limit: 8000 V is 8.0 V at the ADAM (code 3685.5 → 3685 inside), and
# 4.5 V at the T7's DAC (code 59400 = 3712.5 × 16 → 3712 × 16 inside)
AT_LIMIT = {"thesis-sim": adam_out(3685), "thesis-daq-sim": float(t7_out(np.array([3712 * 16]))[0])}


def _rig(name: str) -> RigConfig:
    rig = load_rig(RIGS / f"{name}.toml")
    assert rig.limits.max_voltage_V == 8000.0  # the figure the expected codes above assume
    return rig


@pytest.mark.parametrize("name", list(AT_LIMIT))
def test_a_manual_voltage_goes_through_the_engines_set_point_code_on_both_rig_kinds(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """`voltage 8kV` at an 8-kV limit sends the nearest code inside the limit, through Engine._set_voltage (the
    supervisor on the request and on the value after rounding, the host-stall guard, the output verifier); 8001 V
    is refused by the same supervisor before anything is sent."""
    sent: list[tuple[float, float]] = []
    set_voltage = Engine._set_voltage

    def spy(self: Engine, v: float, t: float, x_cmd: float = float("nan")) -> None:
        set_voltage(self, v, t, x_cmd)
        sent.append((v, self.ctx.v_cmd))
    monkeypatch.setattr(Engine, "_set_voltage", spy)
    with ManualSession(_rig(name), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        out = s.execute("voltage 8kV")
        assert out.status == "ok", out
        assert sent and sent[-1][0] == 8000.0
        assert sent[-1][1] == pytest.approx(AT_LIMIT[name], abs=1e-6) and sent[-1][1] <= 8000.0
        n = len(sent)
        out = s.execute("voltage 8001 V")
        assert out.status == "refused" and "beyond the voltage limit" in out.text and "not sent" in out.text
        assert len(sent) == n and s._amp().commanded == pytest.approx(AT_LIMIT[name], abs=1e-6)
        assert abs(float(s._sim.plant.observe().v_out[-1]) - AT_LIMIT[name]) < 30  # the plant holds the limit
    run = open_run(tmp_path / "s.h5")  # the readings' file, in the layout of a run on this rig, complete
    assert run.complete and run.state == "completed", (run.state, run.reason)
    assert run.streams["setpoints"].columns["voltage"].max() == pytest.approx(AT_LIMIT[name], abs=1e-6)


def _plant(sim: Any) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    sim.plant.listeners.append(lambda b: out.extend(zip(b.t.tolist(), b.v_out.tolist(), strict=True)))
    return out


def test_pause_in_manual_control_ramps_to_zero_and_holds_it_until_resume(tmp_path: Path) -> None:
    rig = _rig("thesis-sim")
    ramp_s = rig.limits.shutdown_ramp_s
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None, operator="ada") as s:
        trace = _plant(s._sim)
        assert s.execute("voltage 3kV").status == "ok"
        t_pause = s._sim.clock.now()
        out = s.execute("pause")
        assert out.status == "ok" and "paused by ada (`pause`)" in out.text, out
        t_paused = s._sim.clock.now()
        for line in ("voltage 1kV", "ramp 2kV 1s", "voltage -500 V"):
            refused = s.execute(line)
            assert refused.status == "refused" and "paused" in refused.text, refused
        assert s.execute("wait 2").status == "ok" and s.execute("read").status == "ok"  # reading goes on
        t_resume = s._sim.clock.now()
        assert s.execute("resume").status == "ok"
        assert s.execute("voltage 1kV").status == "ok"
        assert abs(float(s._sim.plant.observe().v_out[-1]) - 1000) < 30
    # ramped, not dropped: through the middle of the range, at 0 V by the ramp's end, and 0 V until the resume
    down = [(t, v) for t, v in trace if t_pause <= t <= t_paused]
    assert any(1000 < v < 2000 for _, v in down)
    assert t_paused - t_pause >= ramp_s * 0.999
    held = [v for t, v in trace if t_paused + 0.05 <= t < t_resume]
    assert held and max(abs(v) for v in held) <= ZERO_V
    run = open_run(tmp_path / "s.h5")
    marks = [kind for _, _, kind, _ in run.event_list() if kind in ("pause", "resume")]
    assert marks == ["pause", "resume"]  # the events a run's pause writes (bench watch marks them)
    sp = run.streams["setpoints"]  # the engine's ramp: ten set-points down to 0 V
    volts = sp.columns["voltage"][(sp.t > t_pause - s._t0 + 1e-6) & (sp.t <= t_paused - s._t0 + 1e-9)]  # type: ignore[operator]
    assert np.abs(volts - 3000 * (1 - np.arange(1, 11) / 10)).max() <= ZERO_V, volts


def test_a_pause_signal_ends_the_command_under_way_and_pauses(tmp_path: Path) -> None:
    """SIGUSR1 (as for a run) during a long watch: the watch ends, the output is ramped to 0 V and held."""
    rig = _rig("thesis-sim")
    count = [0]

    def echo(text: str) -> None:
        if text.startswith("t "):
            count[0] += 1
            if count[0] == 1:
                os.kill(os.getpid(), signal.SIGUSR1)

    s = ManualSession(rig, tmp_path / "s.log", virtual=True, echo=echo)
    with s.signal_handlers(), s:
        s.run_lines(["voltage 3kV", "watch 3600 0.5", "voltage 2kV", "read"], stop_on_trip=False)
        s._sim.clock.advance(0.2)  # the module's last conversion and the amplifier's response
        volts = float(s._sim.plant.observe().v_out[-1])
    assert [o.status for o in s.outcomes] == ["ok", "paused", "refused", "ok"], s.outcomes
    assert "paused by signal SIGUSR1" in s.outcomes[1].text
    assert abs(volts) <= ZERO_V


def test_a_pause_signal_at_the_prompt_pauses_before_the_next_set_point(tmp_path: Path) -> None:
    """SIGUSR1 between two commands: the next `voltage` pauses instead of sending (virtual time: no keep-alive
    thread runs between commands, so the pause comes with the next command)."""
    trace: list[tuple[float, float]] = []

    def echo(text: str) -> None:
        if text.startswith("ok: set-point"):
            os.kill(os.getpid(), signal.SIGUSR1)

    s = ManualSession(_rig("thesis-sim"), tmp_path / "s.log", virtual=True, echo=echo)
    with s.signal_handlers(), s:
        trace = _plant(s._sim)
        s.run_lines(["voltage 3kV", "voltage 6kV", "wait 1"], stop_on_trip=False)
    assert [o.status for o in s.outcomes] == ["ok", "paused", "ok"], s.outcomes
    assert max(abs(v) for _, v in trace) < 3100  # 6 kV never sent
    assert abs(trace[-1][1]) <= ZERO_V


def test_a_pause_signal_during_a_ramp_ends_the_ramp_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGUSR1 at the second set-point of a 10-s ramp (20 set-points per second, 200 in all): the ramp stops there,
    the output is ramped to 0 V and held — the ramp's remaining set-points are never sent."""
    from bench.runtime.manual_mode import ManualEngine

    checks = [0]
    original = ManualEngine.check_monitors

    def counted(self: ManualEngine) -> None:
        checks[0] += 1
        if checks[0] == 2:
            os.kill(os.getpid(), signal.SIGUSR1)
        original(self)

    monkeypatch.setattr(ManualEngine, "check_monitors", counted)
    s = ManualSession(_rig("thesis-sim"), tmp_path / "s.log", virtual=True)
    with s.signal_handlers(), s:
        s.run_lines(["ramp 4kV 10s", "read"], stop_on_trip=False)
        s._sim.clock.advance(0.2)
        volts = float(s._sim.plant.observe().v_out[-1])
    assert [o.status for o in s.outcomes] == ["paused", "ok"], s.outcomes
    assert checks[0] < 10  # the 2nd of 200, and the pause's own reads: not the whole ramp
    assert abs(volts) <= ZERO_V


def test_a_limit_tripped_in_a_signalled_pause_s_ramp_latches(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The dielectric breaks down as SIGUSR1 comes: the pause's ramp (supervised as a step's) reads the current
    beyond the rig's limit — a trip, the output at 0 V and the rig latched (README: a fault latches until an operator
    resets it), so the next set-point is refused. Before, a trip in that ramp was an error made safe, not latched:
    the next `voltage` was accepted with no reset (a reviewer)."""
    monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / "state"))
    count = [0]
    s = ManualSession(_rig("thesis-sim"), tmp_path / "s.log", virtual=True, echo=lambda _t: None)

    def echo(text: str) -> None:
        if text.startswith("t "):
            count[0] += 1
            if count[0] == 1:
                s._sim.plant.inject_breakdown()
                os.kill(os.getpid(), signal.SIGUSR1)

    s.echo = echo
    with s.signal_handlers(), s:
        s.run_lines(["voltage 3kV", "watch 3600 0.5", "voltage 2kV"], stop_on_trip=False)
        s._sim.clock.advance(0.2)
        volts = float(s._sim.plant.observe().v_out[-1])
    statuses = [o.status for o in s.outcomes]
    assert statuses[:2] == ["ok", "trip"], s.outcomes
    assert "current" in s.outcomes[1].text and "latched" in s.outcomes[1].text, s.outcomes[1]
    assert statuses[2] == "refused" and "latched" in s.outcomes[2].text, s.outcomes[2]
    assert abs(volts) <= ZERO_V
