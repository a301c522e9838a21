"""Every limit holds on the value actually sent — the module's code after rounding — on every path.

Expected values come from the datasheets' code formulas, written out here (never from the drivers):
ADAM-4024 12-bit offset binary over ±10 V: code = round((V + 10)/20 · 4095), output −10 + code·20/4095 V;
LabJack T7 DAC: 16-bit code = V·slope + offset (nominal calibration: 13,200 codes/V, offset 0), 12-bit converter
(low 4 bits ignored): output ((code >> 4) << 4 − offset)/slope; conditioning stage 4·DAC − 10 V; TREK 1000 V/V.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime.run import execute, plan_run
from bench.runtime.safety import SafetyTrip, Supervisor
from bench.storage.runfile import open_run
from tests.conftest import RIGS

TREK_GAIN = 1000.0


def adam_out(code: int) -> float:
    """ADAM-4024 datasheet: output of a 12-bit offset-binary code over ±10 V, times the TREK's gain [V]."""
    return (-10.0 + code * 20.0 / 4095.0) * TREK_GAIN


def at_the_limit(tmp: Path, rig: str | Path, kv: float, first: str = "") -> Path:
    """A protocol that ramps to +limit, holds it, ramps to −limit, holds it, relaxes (after the step ``first``)."""
    path = tmp / "at-the-limit.toml"
    path.write_text(f"""[protocol]
name = "at-the-limit"
description = "holds exactly the rig's voltage limit, both signs"
rig = "{RIGS / rig}"

[recording]
setpoint_Hz = 20
monitors_Hz = 5
{first}
[[steps]]
type = "ramp"
name = "up"
to = "{kv} kV"
duration_s = 0.3

[[steps]]
type = "hold"
name = "at +limit"
duration_s = 0.5

[[steps]]
type = "ramp"
name = "down"
to = "-{kv} kV"
duration_s = 0.5

[[steps]]
type = "hold"
name = "at -limit"
duration_s = 0.5

[[steps]]
type = "relax"
name = "rest"
duration_s = 0.3
""")
    return path


def run_recording(protocol: Path, tmp: Path, hook):
    plan = plan_run(protocol)
    result = execute(plan, tmp / "run.h5", virtual=True, on_engine=hook)
    return plan, result, open_run(result.path)


def test_adam_rig_at_an_8000_V_limit_never_sends_a_code_above_it(tmp_path: Path) -> None:
    """The issue: 8000 V requested on an 8000-V limit sent code 3686 (8002.4 V). By hand:
    (8 + 10)/20 · 4095 = 3685.5 → nearest 3686 → 8002.4 V > 8000 V, so 3685 → 7997.56 V;
    −8 kV: 409.5 → nearest 410 (−7997.56 V, within)."""
    codes: list[int] = []
    twins: list[object] = []

    def hook(_engine, sim) -> None:
        twin = sim.twins["amplifier AO"]
        twins.append(twin)
        written = twin.written

        def spy(address: int, values: list[int]) -> None:
            if address == twin.amplifier_channel:
                codes.extend(values)
            written(address, values)
        twin.written = spy

    plan, result, run = run_recording(at_the_limit(tmp_path, "thesis-sim.toml", 8), tmp_path, hook)
    assert plan.rig.limits.max_voltage_V == 8000.0
    assert result.state == "completed", result.reason
    sent = np.array([adam_out(c) for c in codes])
    assert max(codes) == 3685 and sent.max() == pytest.approx(7997.558, abs=1e-3)
    assert min(codes) == 410 and sent.min() == pytest.approx(-7997.558, abs=1e-3)
    twin = twins[0]
    assert max(twin.scale.to_volts(c) for c in codes) * TREK_GAIN <= 8000.0  # the twin's own register map
    recorded = run.streams["setpoints"].columns["voltage"]
    recorded = recorded[np.isfinite(recorded)]
    assert np.all(np.abs(recorded) <= 8000.0) and recorded.max() == pytest.approx(adam_out(3685), abs=1e-9)
    assert recorded[-1] == 0.0  # the shutdown's "0 V commanded" (the engine's own record of its safe state)
    assert {round(v, 6) for v in recorded[:-1]} <= {round(adam_out(c), 6) for c in range(4096)}  # codes' values


def test_lsdea_adam_rig_at_its_7_kV_limit_and_its_travel_end_sends_both_within(tmp_path: Path) -> None:
    """The issue's 7 kV → 7001 V on the LS-DEA bench: by hand (7 + 10)/20 · 4095 = 3480.75 → 3481 = 7001.2 V,
    beyond, so 3480 (6996.3 V). And a go-to at the travel's end, 95.00007 mm (off the LinRS 0.1-µm grid):
    950000.7 increments → nearest 950001 = 95.0001 mm, beyond → 950000 sent."""
    rig = tmp_path / "rig.toml"
    rig.write_text((RIGS / "lsdea-motor-sim.toml").read_text().replace("travel_m = [0.0, 0.095]",
                                                                       "travel_m = [0.0, 0.09500007]"))
    move = """[[steps]]
type = "move"
name = "to the travel's end"
position = "140.00007 mm"
velocity = "0.1 m/s"
"""
    codes: list[int] = []
    targets: list[int] = []

    def hook(_engine, sim) -> None:
        ao, drive = sim.twins["amplifier AO"], sim.twins["motor"]
        written, motion = ao.written, drive._motion_command

        def spy_ao(address: int, values: list[int]) -> None:
            if address == ao.amplifier_channel:
                codes.extend(values)
            written(address, values)

        def spy_motion(data: bytes) -> None:
            if len(data) >= 6:
                targets.append(struct.unpack("<i", data[2:6])[0])  # LinRS VAI go-to: SInt32 position [0.1 µm]
            motion(data)
        ao.written, drive._motion_command = spy_ao, spy_motion

    plan, result, run = run_recording(at_the_limit(tmp_path, rig, 7, move), tmp_path, hook)
    assert plan.rig.limits.max_voltage_V == 7000.0
    assert result.state == "completed", result.reason
    assert max(codes) == 3480 and adam_out(3480) <= 7000.0
    assert max(targets) == 950_000 and max(targets) * 1e-7 <= 0.09500007
    sp = run.streams["setpoints"]
    assert np.nanmax(sp.columns["voltage"]) == pytest.approx(adam_out(3480), abs=1e-9)
    assert np.nanmax(sp.columns["aperture"]) == pytest.approx(0.045 + 0.095, abs=1e-12)  # aperture as sent


def test_the_setpoint_bound_is_the_field_limit_where_that_binds_first() -> None:
    """Membrane at rest (u = 0): E = V·λ_pre²/L3 with λ_pre = 2, L3 = 1 mm. A field cap of 24 MV/m bounds |V| by
    24e6 · 1e-3 / 2² = 6000 V, below the 8000-V voltage limit: the drivers choose codes within it, and the
    supervisor passes every value up to it."""
    base = load_rig(RIGS / "thesis-sim.toml")
    assert Supervisor(base, base.specimen.membrane()).setpoint_bound() == 8000.0  # the voltage limit binds
    rig = RigConfig.model_validate({**base.model_dump(),
                                    "limits": {**base.limits.model_dump(), "max_field_V_per_m": 24e6}})
    p = rig.specimen.membrane()
    assert (p.lambda_pre, p.L3) == (2.0, 1e-3)
    sup = Supervisor(rig, p)
    bound = sup.setpoint_bound()
    assert bound == pytest.approx(6000.0, rel=1e-12) and bound <= 8000.0
    sup.check_setpoint(bound)
    sup.check_setpoint(-bound)
    with pytest.raises(SafetyTrip, match="true field"):
        sup.check_setpoint(6000.001)
