"""Every limit holds on the value actually sent — the module's code after rounding — on every path.

Expected values come from the datasheets' code formulas, written out here (never from the drivers):
ADAM-4024 12-bit offset binary over ±10 V: code = round((V + 10)/20 · 4095), output −10 + code·20/4095 V;
LabJack T7 DAC: 16-bit code = V·slope + offset (nominal calibration: 13,200 codes/V, offset 0), 12-bit converter
(low 4 bits ignored): output ((code >> 4) << 4 − offset)/slope; conditioning stage 4·DAC − 10 V; TREK 1000 V/V.
"""

from __future__ import annotations

import math
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
T7_SLOPE, T7_OFFSET = 13200.0, 0.0  # LabJack's nominal DAC calibration (the twins' flash)


def adam_out(code: int) -> float:
    """ADAM-4024 datasheet: output of a 12-bit offset-binary code over ±10 V, times the TREK's gain [V]."""
    return (-10.0 + code * 20.0 / 4095.0) * TREK_GAIN


def t7_out(codes: np.ndarray) -> np.ndarray:
    """T7 datasheet: amplifier output [V] for 16-bit DAC codes (12-bit converter), conditioning 4·DAC − 10 V."""
    dac = ((np.asarray(codes, dtype=np.int64) >> 4 << 4) - T7_OFFSET) / T7_SLOPE
    return (4.0 * dac - 10.0) * TREK_GAIN


def low_pass(x: np.ndarray, fc: float, rate: float, y0: float) -> np.ndarray:
    """First-order RC reconstruction filter at the scan instants (exact step response), from y0."""
    a = 1.0 - math.exp(-2.0 * math.pi * fc / rate)
    y = np.empty_like(x)
    prev = y0
    for k, v in enumerate(x):
        prev = prev + a * (v - prev)
        y[k] = prev
    return y


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


def _t7_spies(codes: list[np.ndarray], inputs: list[np.ndarray]):
    """A hook recording the 16-bit codes the T7 twin plays and the amplifier input it gives the plant."""
    def hook(_engine, sim) -> None:
        twin = sim.twins["daq"]
        drive = twin._drive
        plant = sim.plant
        schedule, set_input = plant.schedule_amplifier_input, plant.set_amplifier_input

        def spy_drive(first: int, c: np.ndarray) -> None:
            codes.append(np.array(c, dtype=np.int64))
            drive(first, c)

        def spy_schedule(times, volts) -> None:
            inputs.append(np.array(volts, dtype=float))
            schedule(times, volts)

        def spy_set(volts: float, at: float | None = None) -> None:
            inputs.append(np.array([volts]))
            set_input(volts, at)
        twin._drive = spy_drive
        plant.schedule_amplifier_input, plant.set_amplifier_input = spy_schedule, spy_set
    return hook


def test_t7_rig_at_a_7000_V_limit_never_plays_a_code_beyond_it(tmp_path: Path) -> None:
    """LS-DEA motor bench, hardware-timed, 7-kV limit. By hand, −7 kV: DAC (−7 + 10)/4 = 0.75 V → code
    0.75 · 13200 = 9900 → 12-bit level 618 (9888) → 0.74909 V → −7003.6 V, beyond the limit: level 619
    (9904 → 0.75030 V → −6998.8 V). +7 kV: 4.25 V → 56100 → level 3506 → 6998.8 V, within."""
    codes: list[np.ndarray] = []
    inputs: list[np.ndarray] = []
    plan, result, run = run_recording(at_the_limit(tmp_path, "lsdea-motor-daq-sim.toml", 7), tmp_path,
                                      _t7_spies(codes, inputs))
    assert plan.rig.limits.max_voltage_V == 7000.0 and plan.rig.daq is not None
    assert plan.rig.daq.drive_filter_Hz is None
    assert result.state == "completed", result.reason
    played = t7_out(np.concatenate(codes))
    assert np.all(np.abs(played) <= 7000.0)
    assert played.max() == pytest.approx((4 * 3506 * 16 / T7_SLOPE - 10) * TREK_GAIN)
    assert played.min() == pytest.approx((4 * 619 * 16 / T7_SLOPE - 10) * TREK_GAIN)
    assert np.all(np.abs(np.concatenate(inputs)) * TREK_GAIN <= 7000.0)  # the twin's own conditioning
    commanded = run.streams["amplifier"].columns["commanded"]
    assert np.all(np.abs(commanded) <= 7000.0)


def test_t7_stream_through_the_drive_filter_stays_within_8000_V(tmp_path: Path) -> None:
    """Thesis bench, hardware-timed with the 30-Hz reconstruction filter: the engine pre-compensates the filter's
    lag (DAC values beyond the request) and diffuses the code error (single codes past the request); what the
    amplifier follows — the codes through the conditioning stage and the filter — stays within ±8000 V."""
    codes: list[np.ndarray] = []
    inputs: list[np.ndarray] = []
    plan, result, run = run_recording(at_the_limit(tmp_path, "thesis-daq-sim.toml", 8), tmp_path,
                                      _t7_spies(codes, inputs))
    daq = plan.rig.daq
    assert daq is not None and daq.drive_filter_Hz == 30.0 and plan.rig.limits.max_voltage_V == 8000.0
    assert result.state == "completed", result.reason
    raw = t7_out(np.concatenate(codes))
    zero = float(t7_out(np.array([2.5 * T7_SLOPE]))[0])  # the DAC held 0 V's code before the stream
    filtered = low_pass(raw, daq.drive_filter_Hz, daq.scan_rate_Hz, zero)
    assert np.all(np.abs(raw) <= 8000.0)
    assert np.all(np.abs(filtered) <= 8000.0)
    assert filtered.max() > 7990.0 and filtered.min() < -7990.0  # the limit is reached, not avoided
    assert np.all(np.abs(np.concatenate(inputs)) * TREK_GAIN <= 8000.0)
    assert np.all(np.abs(run.streams["amplifier"].columns["commanded"]) <= 8000.0)


def test_manual_control_sends_within_the_limit_too(tmp_path: Path) -> None:
    """`voltage 8kV` in manual control on a rig whose limit is 8000 V: the ADAM-4024's nearest code within the limit
    (12-bit offset binary over ±10 V, × 1000 V/V: code 3685 → 7997.56 V; 3686 would give 8002.4 V)."""
    from bench.rig import RigConfig, load_rig
    from bench.runtime.manual import ManualSession

    rig = load_rig(RIGS / "thesis-sim.toml")
    rig = RigConfig.model_validate({**rig.model_dump(), "limits": {**rig.limits.model_dump(), "max_voltage_V": 8000.0},
                                    "amplifier": {**rig.amplifier.model_dump(), "max_voltage_V": 9000.0}})
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        out = s.execute("voltage 8kV")
        assert out.status == "ok", out
        assert s._amp().commanded == pytest.approx((3685 / 4095 * 20 - 10) * 1000)
