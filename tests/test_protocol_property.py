"""Property over the protocol schema (tester's issue, "limits that can be switched off or passed"): every protocol
that validates and compiles has a finite set-point schedule within the rig's limits — the software-timed ticks
(``bench.protocol.program.ticks``), each step's voltage and position functions, and the hardware-timed waveform on
the DAQ's scan grid — on every kind of rig.

Random-but-plausible protocol files come from a seeded generator (bounded: a fixed number per rig, a few seconds in
all) that mixes ordinary values with edge values (subnormal, zero, negative, huge durations, frequencies, voltages,
positions, speeds). Expected limits come from the rig files, not from the compiler.
"""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.protocol.program import Program, ProtocolLimitError, Segment, compile_program, ticks
from bench.protocol.schema import ProtocolFileError, load_protocol
from bench.rig import RigConfig, load_rig
from tests.conftest import RIGS
from tests.fuzzing.files import to_toml

RIG_FILES = ("thesis-sim.toml", "thesis-daq-sim.toml", "lsdea-motor-sim.toml", "lsdea-motor-daq-sim.toml",
             "lsdea-isotonic-sim.toml", "lsdea-isotonic-daq-sim.toml")
EXAMPLES_PER_RIG = 60
SEED = 20240611
TINY = (5e-324, 1e-320, 1e-300, 1e-10, 1e-4, 9.99e-4)  # below any meaningful step: must be refused or harmless
MAX_TICKS = 20_000  # per segment walked tick by tick; longer ones are sampled


def _duration(rng: random.Random) -> float:
    r = rng.random()
    if r < 0.06:
        return rng.choice(TINY)
    if r < 0.08:
        return rng.choice([0.0, -1.0, 1e-3, 2e-3])
    return 10 ** rng.uniform(-3, 0.7)  # 1 ms … 5 s


def _volts(rng: random.Random, limit: float) -> str:
    r = rng.random()
    if r < 0.05:
        return rng.choice(["5e-324 V", "-0 V", "1e308 V", "1e-300 kV", f"{limit:g} V", f"-{limit:g} V"])
    return f"{rng.uniform(-1.3, 1.3) * limit:.6g} V"


def _aperture(rng: random.Random) -> str:
    if rng.random() < 0.05:
        return rng.choice(["5e-324 mm", "0 m", "1e308 m", "-45 mm", "240 mm"])
    return f"{rng.uniform(30.0, 160.0):.6g} mm"


def _positive(rng: random.Random, unit: str, lo: float, hi: float) -> str:
    if rng.random() < 0.05:
        return rng.choice([f"5e-324 {unit}", f"1e-300 {unit}", f"0 {unit}", f"-1 {unit}", f"1e308 {unit}"])
    return f"{10 ** rng.uniform(math.log10(lo), math.log10(hi)):.6g} {unit}"


def _step(rng: random.Random, rig: RigConfig) -> dict[str, Any]:
    limit, motor = _limits(rig), _has_motor_axis(rig)
    kind = rng.choice(["waveform", "waveform", "ramp", "ramp", "hold", "wait", "relax", "relax", "set"]
                      + ["move"] * motor)
    channel = "position" if motor and rng.random() < 0.3 else "voltage"
    if kind == "waveform":
        step: dict[str, Any] = {"type": "waveform", "channel": channel,
                                "kind": rng.choice(["sine", "raised_cosine", "triangle", "square"]),
                                "frequency_Hz": rng.choice([5e-324, 1e-300, 1e-3]) if rng.random() < 0.05
                                else 10 ** rng.uniform(-1, 1.5)}
        if channel == "voltage":
            step["offset"], step["amplitude"] = _volts(rng, limit / 2), _volts(rng, limit / 2)
        else:
            step["offset"], step["amplitude"] = _aperture(rng), f"{rng.uniform(-10, 10):.4g} mm"
        if rng.random() < 0.5:
            step["cycles"] = rng.choice(TINY) if rng.random() < 0.06 else rng.uniform(0.5, 3.0)
        else:
            step["duration_s"] = _duration(rng)
        return step
    if kind == "ramp":
        to = _volts(rng, limit) if channel == "voltage" else _aperture(rng)
        return {"type": "ramp", "channel": channel, "to": to, "duration_s": _duration(rng)}
    if kind == "move":
        return {"type": "move", "position": _aperture(rng), "velocity": _positive(rng, "m/s", 1e-3, 2.0),
                "acceleration": _positive(rng, "m/s2", 1e-2, 50.0)}
    if kind == "set":
        if rig.specimen.kind == "membrane":
            return {"type": "set", "temperature_K": rng.uniform(200, 400)}
        if rig.specimen.lsdea.configuration == "hung" and rng.random() < 0.5:
            return {"type": "set", "hung_mass_kg": rng.uniform(0, 0.5)}
        return {"type": "set", "prototype": rng.choice([1, 2, 3])}
    return {"type": kind, "duration_s": _duration(rng)}


def random_protocol(rng: random.Random, rig_path: Path, rig: RigConfig) -> dict[str, Any]:
    """One random protocol document for the rig at ``rig_path`` (voltages drawn around its limit)."""
    limit = _limits(rig)
    steps: list[dict[str, Any]] = [_step(rng, rig) for _ in range(rng.randint(1, 4))]
    if rng.random() < 0.2:
        steps = [{"type": "repeat", "count": rng.randint(1, 3), "steps": steps}]
    elif rng.random() < 0.2:
        steps.append({"type": "sweep", "over": {"d": [rng.choice(TINY), 0.05]},
                      "steps": [{"type": "ramp", "to": _volts(rng, limit), "duration_s": "{d}"},
                                {"type": "relax", "duration_s": "{d}"}]})
    return {"protocol": {"name": "random", "rig": str(rig_path)},
            "recording": {"setpoint_Hz": rng.choice([5.0, 50.0, 250.0, 2000.0]),
                          "points_per_cycle": rng.choice([4, 20]), "displacement_Hz": rng.choice([0.0, 100.0])},
            "steps": steps}


def _has_motor_axis(rig: RigConfig) -> bool:
    return rig.motor is not None and rig.specimen.kind == "lsdea" and rig.specimen.lsdea.configuration == "motor"


def _limits(rig: RigConfig) -> float:
    lim = rig.limits.max_voltage_V
    return min(lim, rig.amplifier.max_voltage_V) if rig.amplifier is not None else lim


def _check_voltages(where: str, v: np.ndarray, limit: float) -> None:
    assert np.all(np.isfinite(v)), f"{where}: voltage set-point not finite: {v[~np.isfinite(v)][:3]}"
    assert np.all(np.abs(v) <= limit + 1e-6), f"{where}: voltage {np.max(np.abs(v)):g} V beyond {limit:g} V"


def _check_motor(where: str, program: Program, motor: np.ndarray) -> None:
    m = program.rig.motor
    assert m is not None
    assert np.all(np.isfinite(motor)), f"{where}: motor set-point not finite"
    assert np.all((motor >= m.travel_m[0] - 1e-9) & (motor <= m.travel_m[1] + 1e-9)), \
        f"{where}: motor {motor.min():g}…{motor.max():g} m outside travel {m.travel_m}"


def _grid(seg: Segment, rate: float) -> np.ndarray:
    """Run times of the DAQ scans that play ``seg`` (at most ~200k of them, evenly picked, ends included)."""
    n = max(1, round(seg.duration * rate))
    k = np.arange(n + 1) if n <= 200_000 else np.unique(np.linspace(0, n, 200_001).round())
    return seg.t_start + k / rate


def check_program(program: Program) -> None:
    """The property: every set-point the program can produce is finite and within the rig's limits."""
    rig, limit = program.rig, _limits(program.rig)
    rate = rig.daq.scan_rate_Hz if rig.daq is not None else None
    t = 0.0
    for seg in program.segments:
        where = f"{program.protocol.path}: {seg.label}"
        assert math.isfinite(seg.t_start) and math.isfinite(seg.duration) and seg.duration >= 0, where
        assert seg.t_start == pytest.approx(t, abs=1e-9), where
        t = seg.t_end
        expected = seg.duration * program.protocol.recording.setpoint_Hz + seg.duration / 0.25
        if expected <= MAX_TICKS:
            for tick in ticks(program, seg):
                assert math.isfinite(tick.t), where
                if tick.voltage is not None:
                    _check_voltages(where, np.array([tick.voltage]), limit)
                if tick.motor is not None:
                    pos, vel, acc = tick.motor
                    _check_motor(where, program, np.array([pos]))
                    assert rig.motor is not None
                    assert 0 < vel <= rig.motor.max_velocity_m_per_s and 0 < acc <= rig.motor.max_acceleration_m_per_s2
        ts = _grid(seg, rate if rate is not None else 1000.0)
        if seg.voltage is not None:  # also the hardware-timed waveform on the scan grid
            _check_voltages(where, np.asarray(seg.voltage(ts), dtype=float), limit)
        if seg.position is not None:
            _check_motor(where, program, np.asarray(program.motor_position(seg.position(ts)), dtype=float))
        if seg.move is not None:
            target, vel, acc = seg.move
            _check_motor(where, program, np.array([program.motor_position(target)]))
            assert math.isfinite(vel) and vel > 0 and math.isfinite(acc) and acc > 0, where


@pytest.mark.parametrize("rig_file", RIG_FILES)
def test_every_protocol_that_compiles_has_finite_setpoints_within_the_limits(tmp_path: Path, rig_file: str) -> None:
    rig_path = RIGS / rig_file
    rig = load_rig(rig_path)
    rng = random.Random(f"{SEED}-{rig_file}")
    outcome: dict[str, Any] = {"accepted": 0, "refused": 0, "why": []}
    for i in range(EXAMPLES_PER_RIG):
        f = tmp_path / f"p{i:03d}.toml"
        f.write_text(to_toml(random_protocol(rng, rig_path, rig)))
        try:
            program = compile_program(load_protocol(f), rig)
        except (ProtocolFileError, ProtocolLimitError) as exc:
            msg = str(exc)
            assert "\n" not in msg and msg.startswith(f"protocol file {f}"), msg
            outcome["refused"] += 1
            outcome["why"].append(msg.split(": ", 1)[1][:100])
            continue
        outcome["accepted"] += 1
        with np.errstate(divide="raise", invalid="raise", over="raise"):  # a NaN or inf raises here, not warns
            check_program(program)
    assert outcome["accepted"] >= EXAMPLES_PER_RIG // 5, outcome  # the property is not checked vacuously
    assert outcome["refused"] > 0, outcome


@pytest.mark.parametrize("step", [
    {"type": "relax", "duration_s": 5e-324},
    {"type": "ramp", "to": "1 kV", "duration_s": 5e-324},
    {"type": "hold", "duration_s": 1e-300},
    {"type": "waveform", "amplitude": "1 kV", "frequency_Hz": 1.0, "duration_s": 5e-324},
])
def test_subnormal_durations_are_refused_naming_the_field(tmp_path: Path, step: dict[str, Any]) -> None:
    """The issue's case: a relax of 5e-324 s after a ramp validated, then tripped on a NaN set-point at run time."""
    doc = {"protocol": {"name": "x", "rig": str(RIGS / "thesis-sim.toml")},
           "steps": [{"type": "ramp", "to": "1 kV", "duration_s": 1.0}, step]}
    f = tmp_path / "p.toml"
    f.write_text(to_toml(doc))
    with pytest.raises(ProtocolFileError) as err:
        load_protocol(f)
    msg = str(err.value)
    assert "\n" not in msg and "steps[1]" in msg and "duration_s" in msg and "0.001" in msg, msg


def test_cycles_shorter_than_the_shortest_step_are_refused(tmp_path: Path) -> None:
    doc = {"protocol": {"name": "x", "rig": str(RIGS / "thesis-sim.toml")},
           "steps": [{"type": "waveform", "amplitude": "1 kV", "frequency_Hz": 1000.0, "cycles": 0.5}]}  # 0.5 ms
    f = tmp_path / "p.toml"
    f.write_text(to_toml(doc))
    with pytest.raises(ProtocolFileError, match=r"steps\[0\].*below the shortest step"):
        load_protocol(f)


def test_bench_validate_refuses_the_subnormal_relax_in_one_line(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from bench.cli import app

    f = tmp_path / "p.toml"
    f.write_text(f'[protocol]\nname = "x"\nrig = "{RIGS / "thesis-sim.toml"}"\n\n[[steps]]\ntype = "ramp"\n'
                 'to = "1 kV"\nduration_s = 1.0\n\n[[steps]]\ntype = "relax"\nduration_s = 5e-324\n')
    res = CliRunner().invoke(app, ["validate", str(f)], env={"COLUMNS": "400"})
    out = res.output.strip()
    assert res.exit_code == 2 and "\n" not in out and "Traceback" not in out
    assert "steps[1](relax).duration_s" in out
