"""The limits follow what changes during a run: a set step (the operator mounts a prototype, hangs a mass or sets the
chamber) only at 0 V, and the supervisor's limits follow the specimen it sets (LS-DEA prototypes: the paper's
Table 2, λ2p 2.5 / 2.75 / 3.0); on a streamed rig, a step after a motor move is supervised at the new aperture."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.protocol.program import compile_program
from bench.protocol.schema import load_protocol
from bench.rig import load_rig
from bench.runtime.run import execute, plan_run
from tests.conftest import ROOT

RIG = ROOT / "rigs" / "lsdea-motor-sim.toml"
HEAD = f"""[protocol]
name = "set-under-voltage"
rig = "{RIG}"

[specimen]
prototype = 1

[recording]
setpoint_Hz = 50
position_Hz = 10
force_Hz = 50
monitors_Hz = 5
"""
RAMP = """
[[steps]]
type = "ramp"
name = "voltage on"
channel = "voltage"
to = "{to}"
duration_s = 0.2
"""
SET = """
[[steps]]
type = "set"
name = "mount prototype 3"
prototype = 3
"""
WAIT = """
[[steps]]
type = "wait"
name = "settle"
duration_s = 0.2
"""


def _protocol(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "p.toml"
    path.write_text(HEAD + text, encoding="utf-8")
    return path


def test_a_specimen_change_under_voltage_is_refused_before_the_run(tmp_path: Path) -> None:
    path = _protocol(tmp_path, RAMP.format(to="3 kV") + SET)
    with pytest.raises(ValueError, match=r"needs the output at 0 V.*3000 V"):
        compile_program(load_protocol(path), load_rig(RIG))


def test_the_supervisor_s_limits_follow_the_prototype_a_set_step_mounts(tmp_path: Path) -> None:
    path = _protocol(tmp_path, RAMP.format(to="2 kV") + RAMP.format(to="0 kV") + SET + WAIT)
    engines: list[Any] = []
    result = execute(plan_run(path), tmp_path / "run.h5", virtual=True, on_engine=lambda e, _s: engines.append(e))
    assert result.state == "completed", result.reason
    assert engines[0].sup.specimen.lambda2p == pytest.approx(3.0)  # prototype #3, Table 2


MOVE_THEN_SINE = """[protocol]
name = "move-then-sine"
rig = "{rig}"

[recording]
setpoint_Hz = 250
points_per_cycle = 25
force_Hz = 100
position_Hz = 20
monitors_Hz = 5

[[steps]]
type = "move"
name = "out"
position = "115 mm"
velocity = "0.05 m/s"

[[steps]]
type = "waveform"
name = "sine"
channel = "voltage"
kind = "sine"
amplitude = "9.5 kV"
frequency_Hz = 2
cycles = 2
"""


def test_a_step_after_a_motor_move_on_a_daq_rig_is_supervised_at_the_aperture_the_move_reached(
        tmp_path: Path) -> None:
    """On the streamed (T7) rig the next step used to be appended when the move began, its values checked and its
    DAC window chosen at the aperture before the move. A 9.5-kV sine after a move to 115 mm, on a rig allowed
    9.7 kV (the field limit binds there), must be refused before its first value is sent — the dry run's model
    prediction, which would refuse this protocol too, is bypassed here to test the run itself."""
    from bench.protocol.predict import Prediction
    from bench.runtime.run import Plan, _resolve_rig
    from bench.storage.runfile import open_run

    rig_text = (ROOT / "rigs" / "lsdea-motor-daq-sim.toml").read_text(encoding="utf-8")
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_text.replace("max_voltage_V = 7000.0", "max_voltage_V = 9700.0"), encoding="utf-8")
    path = tmp_path / "p.toml"
    path.write_text(MOVE_THEN_SINE.format(rig=rig_path), encoding="utf-8")
    protocol = load_protocol(path)
    rig, text = _resolve_rig(protocol, None, False)
    program = compile_program(protocol, rig)
    plan = Plan(protocol, rig, program, Prediction(program.duration, {}, 0), [], [], text)
    result = execute(plan, tmp_path / "run.h5", virtual=True)
    assert result.state == "tripped" and "would give a true field" in result.reason, result.reason
    commanded = open_run(result.path).streams["amplifier"].columns["commanded"]
    assert commanded.size == 0 or float(np.max(np.abs(commanded))) < 100.0  # nothing of the sine was played


def test_a_motor_go_to_is_refused_where_its_path_passes_the_field_s_peak(tmp_path: Path) -> None:
    """λ1·λ2, and with it the LS-DEA's true field at a voltage, peaks at the aperture √2·l (l = 120 mm: 169.7 mm):
    on a rig whose travel crosses it, a go-to from 100 to 220 mm at a voltage both ends allow must still be refused,
    because the path passes the peak."""
    import math

    from bench.runtime.safety import SafetyTrip, Supervisor

    text = (ROOT / "rigs" / "lsdea-motor-sim.toml").read_text(encoding="utf-8")
    text = text.replace("travel_m = [0.0, 0.095]", "travel_m = [0.0, 0.12]").replace(
        "x_at_motor_zero_m = 0.045", "x_at_motor_zero_m = 0.1").replace("max_voltage_V = 7000.0",
                                                                        "max_voltage_V = 9700.0")
    path = tmp_path / "rig.toml"
    path.write_text(text, encoding="utf-8")
    rig = load_rig(path)
    sup = Supervisor(rig, rig.specimen.lozenge())
    bounds = {}
    for x in (0.10, math.sqrt(2.0) * 0.120, 0.22):
        sup.aperture = x
        bounds[x] = sup.setpoint_bound()
    ends, peak = min(bounds[0.10], bounds[0.22]), bounds[math.sqrt(2.0) * 0.120]
    assert peak < ends  # the set-up: the field limit binds hardest in the middle of the path
    volts = (peak + ends) / 2
    sup.aperture = 0.10
    sup.check_motor_setpoint(0.0, 0.102, volts)  # a short go-to, well short of the peak: allowed
    with pytest.raises(SafetyTrip, match="passing"):
        sup.check_motor_setpoint(0.12, 0.22, volts)


def test_the_field_model_follows_each_new_aperture_and_specimen_at_once() -> None:
    """The supervisor remembers the stretch of the last aperture it was asked about (the live view's headroom asks at
    every engine wake-up): a new aperture, a new prototype and a return to an earlier aperture are each judged at
    their own stretch. Expected: the paper's eq 1 and the true field E = V·λ1·λ2/t0, E_B = E0·(λ1λ2)^(r/2),
    λ1 = λ1p·x/xp, λ2 = λ2p·√(4l² − x²)/√(4l² − xp²), written out here from the parameters."""
    from bench.runtime.safety import Supervisor

    rig = load_rig(RIG)
    sup = Supervisor(rig, rig.specimen.lozenge(1))
    margin = rig.limits.breakdown_margin

    def paper(q: Any, x: float, volts: float) -> tuple[float, float]:
        l1 = q.lambda2p ** -0.5 * x / q.xp
        l2 = q.lambda2p * np.sqrt(4 * q.l ** 2 - x * x) / np.sqrt(4 * q.l ** 2 - q.xp ** 2)
        return volts * l1 * l2 / q.t0, q.material.E0 * (l1 * l2) ** (q.material.r / 2) / margin

    q1 = sup.specimen
    x_a, x_b = 1.2 * q1.xp, 1.6 * q1.xp
    for specimen, x in ((q1, x_a), (q1, x_b), (q1.changed(prototype=3), x_b), (q1, x_a)):
        sup.specimen, sup.aperture = specimen, x
        for volts in (3000.0, -5000.0):
            e, e_max = sup.field_and_breakdown(volts)
            want = paper(specimen, x, abs(volts))
            assert (e, e_max) == pytest.approx(want, rel=1e-12)
    assert sup.headroom()["field"] == pytest.approx(0.0)  # no voltage measured yet


def test_the_headroom_follows_each_value_it_reads_and_each_specimen() -> None:
    """The live view's headroom, asked at every engine wake-up, gives its last answer again only while nothing it
    reads has changed: a new monitor reading, force, aperture or prototype each shows at once, and a caller's change
    to one answer is not in the next. Expected: each reading over its limit (rig file), the field from eq 1 (above)."""
    from bench.runtime.safety import Supervisor

    rig = load_rig(RIG)
    lim = rig.limits
    sup = Supervisor(rig, rig.specimen.lozenge(1))
    q1 = sup.specimen

    def field(q: Any, x: float, volts: float) -> float:
        l1 = q.lambda2p ** -0.5 * x / q.xp
        l2 = q.lambda2p * np.sqrt(4 * q.l ** 2 - x * x) / np.sqrt(4 * q.l ** 2 - q.xp ** 2)
        return volts * l1 * l2 / q.t0 / (q.material.E0 * (l1 * l2) ** (q.material.r / 2) / lim.breakdown_margin)

    def want(q: Any, x: float, volts: float, amps: float, newtons: float) -> dict[str, Any]:
        return {"voltage": pytest.approx(abs(volts) / min(lim.max_voltage_V, rig.amplifier.max_voltage_V)),
                "field": pytest.approx(field(q, x, abs(volts)), rel=1e-12),
                "current": pytest.approx(abs(amps) / lim.max_current_A), "force": pytest.approx(abs(newtons) /
                                                                                                 lim.max_force_N)}

    x = 1.3 * q1.xp
    sup.aperture = x
    sup.check_monitors(2000.0, 1e-3)
    for _ in range(3):  # the answer, then the same twice: each the caller's own copy
        answer = sup.headroom()
        assert answer == want(q1, x, 2000.0, 1e-3, 0.0)
        answer["voltage"] = 99.0
    sup.check_monitors(-3000.0, 1e-3)
    assert sup.headroom() == want(q1, x, -3000.0, 1e-3, 0.0)
    sup.check_monitors(-3000.0, -2e-3)
    assert sup.headroom() == want(q1, x, -3000.0, -2e-3, 0.0)
    sup.check_force(1.5)
    assert sup.headroom() == want(q1, x, -3000.0, -2e-3, 1.5)
    sup.update_displacement(1.5 * q1.xp)  # the laser's aperture
    assert sup.headroom() == want(q1, 1.5 * q1.xp, -3000.0, -2e-3, 1.5)
    q3 = q1.changed(prototype=3)
    sup.specimen = q3
    assert sup.headroom() == want(q3, 1.5 * q1.xp, -3000.0, -2e-3, 1.5)


SINE = """
[[steps]]
type = "waveform"
name = "two whole cycles"
kind = "sine"
channel = "voltage"
amplitude = "5 kV"
frequency_Hz = 0.1111111111111111
cycles = 2
"""


def test_a_set_step_after_whole_sine_cycles_is_allowed_and_a_volt_left_on_still_refused(tmp_path: Path) -> None:
    """A whole-cycle sine ends at 0 V up to floating point (the tester's "leaves it at -2.44929e-12 V"): the set
    step is allowed within 1 ppm of the rig's voltage limit (7000 V in the rig file: 7 mV), not beyond."""
    import math
    import re

    end = 5000 * math.sin(2 * math.pi * 2)  # where the sine's formula lands after 2 cycles, in floating point
    assert end != 0.0 and abs(end) < 1e-9
    limit = float(re.search(r"^max_voltage_V = ([\d.]+)", RIG.read_text(encoding="utf-8"), re.M).group(1))  # type: ignore[union-attr]
    program = compile_program(load_protocol(_protocol(tmp_path, SINE + SET + SINE)), load_rig(RIG))
    assert [s.kind for s in program.segments] == ["waveform", "set", "waveform"]
    for to, allowed in ((f"{0.5e-6 * limit:g} V", True), (f"{2e-6 * limit:g} V", False), ("1 V", False)):
        path = _protocol(tmp_path, RAMP.format(to=to) + SET)
        if allowed:
            compile_program(load_protocol(path), load_rig(RIG))
        else:
            with pytest.raises(ValueError, match=r"needs the output at 0 V.*1 ppm of the rig's 7000 V limit"):
                compile_program(load_protocol(path), load_rig(RIG))
