"""Tester's issue, "limits that can be switched off or passed": every limit in a rig file is refused, in one line
naming the field, when it can never fire — not finite, ≤ 0, or at/above what the instrument can do or its measuring
channel can report — on every kind of rig (ADAM, DAQ, motor, isotonic); and `bench validate` says so, exit 2.

Expected figures come from the instruments' documents or a derivation, not from the code under test:
TREK 10/10B-HS ±10 kV, 10 mA DC, 10/40A-HS 40 mA, monitors 1 V per kV and 1 V per mA (10/40A-HS: 4 mA/V), slew
rate > 700 V/µs; analog inputs on the ±10 V range (ADAM-4017+, LabJack T7); load cell 5 kg × 9.80665 m/s²
(CGPM 1901) = 49.033 N; the DAQ rigs' bridge amplifier 1 V per N (rig file comment) → ±10 N; LinMot P01-37x120F
stroke 0–120 mm; LinRS positions int32 × 0.1 µm → ±214.748 m; the supervisor's output over-voltage trip at
1.02 V + 50 V, hence the highest voltage limit a ±10 kV monitor can watch: (10 000 − 50) / 1.02 = 9754.9 V.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import RigConfig, RigFileError, load_rig
from bench.runtime.safety import SafetyTrip, Supervisor
from tests.conftest import RIGS, ROOT
from tests.test_validation import _set

ADAM = (RIGS / "thesis-sim.toml").read_text()  # membrane, TREK on ADAM modules
DAQ = (RIGS / "thesis-daq-sim.toml").read_text()  # membrane, TREK on the T7
MOTOR = (RIGS / "lsdea-motor-sim.toml").read_text()  # LS-DEA, LinMot, DGT1S load cell, ADAM
MOTOR_DAQ = (RIGS / "lsdea-motor-daq-sim.toml").read_text()  # LS-DEA, LinMot, load cell on a T7 input
ISOTONIC = (RIGS / "lsdea-isotonic-sim.toml").read_text()  # LS-DEA under a hung mass, ADAM
ISOTONIC_DAQ = (RIGS / "lsdea-isotonic-daq-sim.toml").read_text()
KINDS = {"adam": ADAM, "daq": DAQ, "motor": MOTOR, "motor-daq": MOTOR_DAQ, "isotonic": ISOTONIC,
         "isotonic-daq": ISOTONIC_DAQ}
WITH_MOTOR = ("motor", "motor-daq")
FORCE_CHANNEL = ("motor", "motor-daq")  # a DGT1S load cell, or a load cell on a T7 input


def _load(tmp_path: Path, text: str) -> RigConfig:
    f = tmp_path / "rig.toml"
    f.write_text(text)
    return load_rig(f)


def _refused(tmp_path: Path, text: str, field: str) -> str:
    f = tmp_path / "rig.toml"
    f.write_text(text)
    with pytest.raises(RigFileError) as err:
        load_rig(f)
    msg = str(err.value)
    assert str(f) in msg and "\n" not in msg and field in msg, msg
    return msg


def _with(text: str, *edits: tuple[str, str, str]) -> str:
    for table, key, value in edits:
        text = _set(text, table, key, value)
    return text


# ------------------------------------------------------------------ the issue's case


@pytest.mark.parametrize("rig", ["lsdea-motor-daq-sim.toml", "lsdea-motor-daq-lab.toml"])
def test_issue_case_huge_force_and_slew_refused_on_the_daq_motor_rigs(tmp_path: Path, rig: str) -> None:
    text = (RIGS / rig).read_text()
    _refused(tmp_path, _set(text, "limits", "max_force_N", "1e308"), "limits.max_force_N")
    _refused(tmp_path, _set(text, "amplifier", "slew_limit_V_per_s", "1e308"), "amplifier.slew_limit_V_per_s")


def test_shipped_daq_motor_rigs_force_limit_within_the_input() -> None:
    for name in ("lsdea-motor-daq-sim.toml", "lsdea-motor-daq-lab.toml"):
        rig = load_rig(RIGS / name)
        assert rig.limits.max_force_N < 10.0  # 1 V per N on the ±10 V input


# ------------------------------------------------------------------ every limit: finite and > 0, every rig kind

LIMIT_KEYS = ("max_voltage_V", "max_current_A", "max_force_N", "max_field_V_per_m", "breakdown_margin",
              "shutdown_ramp_s")


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("key", LIMIT_KEYS)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0.0", "-1.0", "1e308"])
def test_limits_not_finite_or_not_positive_or_huge_are_refused(tmp_path: Path, kind: str, key: str,
                                                                value: str) -> None:
    text = _set(KINDS[kind], "limits", key, value)
    if key == "max_force_N" and value == "1e308" and kind not in FORCE_CHANNEL:
        # no load cell: nothing measures force, the limit only bounds the dry run's model force (open question)
        assert _load(tmp_path, text).limits.max_force_N == 1e308
        return
    _refused(tmp_path, text, f"limits.{key}")


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("value", ["nan", "inf", "-1.0", "1e308"])
def test_travel_tolerance_not_finite_negative_or_huge_is_refused(tmp_path: Path, kind: str, value: str) -> None:
    text = _set(KINDS[kind], "limits", "travel_tolerance_m", value)
    if kind in WITH_MOTOR or value != "1e308":
        _refused(tmp_path, text, "limits.travel_tolerance_m")
    else:  # no motor: nothing travels, the tolerance is unused
        assert _load(tmp_path, text).limits.travel_tolerance_m == 1e308


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("value", ["nan", "inf", "0.0", "-1.0", "1e308", "7.01e8"])
def test_slew_limit_not_finite_not_positive_or_beyond_the_trek_is_refused(tmp_path: Path, kind: str,
                                                                          value: str) -> None:
    _refused(tmp_path, _set(KINDS[kind], "amplifier", "slew_limit_V_per_s", value), "amplifier.slew_limit_V_per_s")


# ------------------------------------------------------------------ voltage


@pytest.mark.parametrize("kind", list(KINDS))
def test_voltage_limit_within_what_the_voltage_monitor_reads(tmp_path: Path, kind: str) -> None:
    text = _set(KINDS[kind], "amplifier", "max_voltage_V", "10000")
    ok = _load(tmp_path, _set(text, "limits", "max_voltage_V", "9754"))  # (10000 − 50) / 1.02 = 9754.9
    assert ok.limits.max_voltage_V == 9754
    msg = _refused(tmp_path, _set(text, "limits", "max_voltage_V", "9755"), "limits.max_voltage_V")
    assert "10000 V" in msg
    # a monitor calibrated at 0.5 kV/V reads only ±5 kV: a 6 kV limit could never be watched
    low = _set(_set(text, "amplifier", "vmon_ratio", "500"), "limits", "max_voltage_V", "6000")
    assert "amplifier.vmon_ratio" in _refused(tmp_path, low, "limits.max_voltage_V")


@pytest.mark.parametrize("kind", ["adam", "motor"])
def test_monitor_trip_fires_at_the_highest_accepted_voltage_limit(tmp_path: Path, kind: str) -> None:
    """The supervisor itself (not the rig check) trips on a full-scale monitor reading at 9754 V."""
    rig = _load(tmp_path, _with(KINDS[kind], ("amplifier", "max_voltage_V", "10000"),
                                ("limits", "max_voltage_V", "9754")))
    sup = Supervisor(rig, rig.specimen.membrane() if rig.specimen.kind == "membrane" else rig.specimen.lozenge())
    sup.field_and_breakdown = lambda volts: (0.0, 1.0)  # type: ignore[method-assign]  # the voltage trip alone
    with pytest.raises(SafetyTrip, match="beyond the voltage limit"):
        sup.check_monitors(10_000.0, 0.0)  # ±10 V × 1000 V/V: the most the monitor reads


# ------------------------------------------------------------------ current


@pytest.mark.parametrize("kind", list(KINDS))
def test_current_limit_within_the_current_monitor(tmp_path: Path, kind: str) -> None:
    text = KINDS[kind]
    assert _load(tmp_path, _set(text, "limits", "max_current_A", "0.0099")).limits.max_current_A == 0.0099
    msg = _refused(tmp_path, _set(text, "limits", "max_current_A", "0.01"), "limits.max_current_A")
    assert "imon_ratio" in msg  # 1 mA/V × 10 V = 10 mA: the most the monitor reads
    # the 10/40A-HS (4 mA/V monitor: 40 mA) watches 30 mA; 40 mA is its rating and its monitor's full scale
    big = _set(text, "amplifier", "model", '"10/40A-HS"')
    assert _load(tmp_path, _set(big, "limits", "max_current_A", "0.03")).limits.max_current_A == 0.03
    _refused(tmp_path, _set(big, "limits", "max_current_A", "0.04"), "limits.max_current_A")
    _refused(tmp_path, _set(big, "limits", "max_current_A", "0.05"), "limits.max_current_A")


def test_current_trip_fires_at_the_highest_accepted_limit(tmp_path: Path) -> None:
    rig = _load(tmp_path, _set(ADAM, "limits", "max_current_A", "0.0099"))
    sup = Supervisor(rig, rig.specimen.membrane())
    with pytest.raises(SafetyTrip, match="current"):
        sup.check_monitors(0.0, 0.010)  # 10 V × 1 mA/V


# ------------------------------------------------------------------ force


def test_force_limit_within_the_dgt1s_capacity(tmp_path: Path) -> None:
    assert _load(tmp_path, _set(MOTOR, "limits", "max_force_N", "49.03")).limits.max_force_N == 49.03
    msg = _refused(tmp_path, _set(MOTOR, "limits", "max_force_N", "49.04"), "limits.max_force_N")
    assert "load_cell.capacity_kg" in msg


def test_force_limit_within_the_daq_load_cell_input(tmp_path: Path) -> None:
    assert _load(tmp_path, _set(MOTOR_DAQ, "limits", "max_force_N", "9.99")).limits.max_force_N == 9.99
    msg = _refused(tmp_path, _set(MOTOR_DAQ, "limits", "max_force_N", "10"), "limits.max_force_N")
    assert "daq.force_N_per_V" in msg
    # 2 N/V: ±20 N
    wide = _set(MOTOR_DAQ, "daq", "force_N_per_V", "2.0")
    assert _load(tmp_path, _set(wide, "limits", "max_force_N", "19.9")).limits.max_force_N == 19.9
    _refused(tmp_path, _set(wide, "limits", "max_force_N", "20"), "limits.max_force_N")
    # an offset of 3 N: the input reads −7 … +13 N, so compression beyond 7 N is never seen
    off = _set(MOTOR_DAQ, "daq", "force_offset_N", "3.0")
    assert _load(tmp_path, _set(off, "limits", "max_force_N", "6.9")).limits.max_force_N == 6.9
    _refused(tmp_path, _set(off, "limits", "max_force_N", "7.0"), "limits.max_force_N")
    _refused(tmp_path, _set(MOTOR_DAQ, "daq", "force_offset_N", "10.0"), "daq.force_offset_N")


def test_force_limit_within_the_stated_rated_capacity(tmp_path: Path) -> None:
    rated = _set(MOTOR_DAQ, "daq", "force_capacity_N", "5.0")
    assert _load(tmp_path, _set(rated, "limits", "max_force_N", "5.0")).limits.max_force_N == 5.0
    assert "daq.force_capacity_N" in _refused(tmp_path, _set(rated, "limits", "max_force_N", "5.5"),
                                              "limits.max_force_N")
    for bad in ("nan", "inf", "0.0", "-2.0"):
        _refused(tmp_path, _set(MOTOR_DAQ, "daq", "force_capacity_N", bad), "daq.force_capacity_N")


def test_force_trip_fires_at_the_daq_input_full_scale(tmp_path: Path) -> None:
    rig = _load(tmp_path, _set(MOTOR_DAQ, "limits", "max_force_N", "9.99"))
    sup = Supervisor(rig, rig.specimen.lozenge())
    for reading in (10.0, -10.0):  # ±10 V × 1 N/V
        with pytest.raises(SafetyTrip, match="force"):
            sup.check_force(reading)


# ------------------------------------------------------------------ field


@pytest.mark.parametrize("kind", ["adam", "daq"])
def test_field_cap_below_the_membrane_breakdown_trip(tmp_path: Path, kind: str) -> None:
    text = KINDS[kind]  # E_B 100 MV/m, margin 1.1: the breakdown trip at 90.9 MV/m
    assert _load(tmp_path, _set(text, "limits", "max_field_V_per_m", "90e6")).limits.max_field_V_per_m == 90e6
    _refused(tmp_path, _set(text, "limits", "max_field_V_per_m", "91e6"), "limits.max_field_V_per_m")
    _refused(tmp_path, _set(text, "limits", "max_field_V_per_m", "1e308"), "limits.max_field_V_per_m")


@pytest.mark.parametrize("kind", ["motor", "motor-daq", "isotonic", "isotonic-daq"])
def test_field_cap_below_the_lsdea_breakdown_trip(tmp_path: Path, kind: str) -> None:
    text = KINDS[kind]  # E_B = 81 MV/m × (λ1λ2)^0.43 ≥ 81 MV/m while stretched: a 60 MV/m cap can fire
    assert _load(tmp_path, _set(text, "limits", "max_field_V_per_m", "60e6")).limits.max_field_V_per_m == 60e6
    _refused(tmp_path, _set(text, "limits", "max_field_V_per_m", "1e12"), "limits.max_field_V_per_m")


# ------------------------------------------------------------------ travel


@pytest.mark.parametrize("kind", WITH_MOTOR)
def test_travel_tolerance_must_leave_the_trip_room_before_the_stroke_end(tmp_path: Path, kind: str) -> None:
    text = KINDS[kind]  # travel 0–95 mm in a 0–120 mm stroke: 25 mm to spare at the upper end
    assert _load(tmp_path, _set(text, "limits", "travel_tolerance_m", "0.0249")).limits.travel_tolerance_m == 0.0249
    msg = _refused(tmp_path, _set(text, "limits", "travel_tolerance_m", "0.025"), "limits.travel_tolerance_m")
    assert "upper" in msg and "motor.stroke_m" in msg
    inner = _set(text, "motor", "travel_m", "[0.01, 0.095]")  # 10 mm to spare at the lower end
    _refused(tmp_path, _set(inner, "limits", "travel_tolerance_m", "0.01"), "limits.travel_tolerance_m")


@pytest.mark.parametrize("kind", WITH_MOTOR)
def test_stroke_within_what_linrs_reports(tmp_path: Path, kind: str) -> None:
    assert _load(tmp_path, _set(KINDS[kind], "motor", "stroke_m", "[0.0, 214.0]")).motor is not None
    _refused(tmp_path, _set(KINDS[kind], "motor", "stroke_m", "[0.0, 215.0]"), "stroke_m")
    _refused(tmp_path, _set(KINDS[kind], "motor", "stroke_m", "[0.0, 1e308]"), "stroke_m")


# ------------------------------------------------------------------ slew


def test_slew_limit_on_the_adam_drive_up_to_the_trek_slew_rate(tmp_path: Path) -> None:
    assert _load(tmp_path, _set(ADAM, "amplifier", "slew_limit_V_per_s", "7e8")).amplifier is not None


@pytest.mark.parametrize("kind", ["daq", "motor-daq", "isotonic-daq"])
def test_slew_limit_is_refused_where_it_is_not_applied(tmp_path: Path, kind: str) -> None:
    """The DAQ plays the protocol's waveform itself: a slew limit set in the rig file would be ignored."""
    msg = _refused(tmp_path, _set(KINDS[kind], "amplifier", "slew_limit_V_per_s", "2e6"),
                   "amplifier.slew_limit_V_per_s")
    assert "drive = 'daq'" in msg


def test_shipped_rigs_still_validate() -> None:
    names = sorted(p.name for p in RIGS.glob("*.toml"))
    assert len(names) == 12
    for name in names:
        assert load_rig(RIGS / name).name == name.removesuffix(".toml")


# ------------------------------------------------------------------ bench validate


CLI_CASES = [
    ("motor-daq", "limits", "max_force_N", "1e308", "limits.max_force_N"),
    ("motor-daq", "amplifier", "slew_limit_V_per_s", "1e308", "amplifier.slew_limit_V_per_s"),
    ("motor", "limits", "max_force_N", "1e308", "limits.max_force_N"),
    ("adam", "amplifier", "slew_limit_V_per_s", "1e308", "amplifier.slew_limit_V_per_s"),
    ("adam", "limits", "max_current_A", "0.01", "limits.max_current_A"),
    ("daq", "limits", "max_field_V_per_m", "1e308", "limits.max_field_V_per_m"),
    ("isotonic", "limits", "max_voltage_V", "1e308", "limits.max_voltage_V"),
    ("motor", "limits", "travel_tolerance_m", "1e308", "limits.travel_tolerance_m"),
    ("motor", "motor", "stroke_m", "[0.0, 1e308]", "stroke_m"),
    ("motor-daq", "daq", "force_capacity_N", "1.0", "daq.force_capacity_N"),
]


@pytest.mark.parametrize("kind, table, key, value, field", CLI_CASES)
def test_bench_validate_shows_each_refused_limit_in_one_line(tmp_path: Path, kind: str, table: str, key: str,
                                                             value: str, field: str) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(_set(KINDS[kind], table, key, value))
    proto = tmp_path / "p.toml"
    proto.write_text(f'[protocol]\nname = "x"\nrig = "{rig}"\n\n[[steps]]\ntype = "hold"\nduration_s = 1.0\n')
    res = CliRunner().invoke(app, ["validate", str(proto)], env={"COLUMNS": "400"})
    out = res.output.strip()
    assert res.exit_code == 2, out
    assert "Traceback" not in out and "\n" not in out and field in out and str(rig) in out, out


def test_bench_validate_in_a_process_exits_2_without_a_traceback(tmp_path: Path) -> None:
    import subprocess
    import sys

    rig = tmp_path / "rig.toml"
    rig.write_text(_set(MOTOR_DAQ, "limits", "max_force_N", "1e308"))
    proto = tmp_path / "p.toml"
    proto.write_text(f'[protocol]\nname = "x"\nrig = "{rig}"\n\n[[steps]]\ntype = "hold"\nduration_s = 1.0\n')
    proc = subprocess.run([sys.executable, "-m", "bench", "validate", str(proto)], capture_output=True, text=True,
                          timeout=120, cwd=ROOT, env={"COLUMNS": "400", "PATH": ""})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr + proc.stdout
    assert proc.stderr.strip().count("\n") == 0 and "limits.max_force_N" in proc.stderr


@pytest.mark.parametrize("mu, tau", [("[1e5]", "[0.0]"), ("[0.0]", "[1.0]"), ("[1e5]", "[-1.0]")])
def test_a_maxwell_branch_without_a_positive_modulus_and_time_is_refused_naming_the_file_and_field(
        tmp_path: Path, mu: str, tau: str) -> None:
    """physics.md §2.4: a branch (μ_k, τ_k) relaxes at rate 1/τ_k, so τ_k > 0 and μ_k > 0. The tester's rig file with
    branch_tau = [0.0] failed as "Maxwell branches need mu > 0 and tau > 0", naming neither file nor field."""
    text = MOTOR + f"\n[specimen.lsdea_model]\nmu = 312.6e3\nJm = 30.58\nC2 = 183.5e3\nbranch_mu = {mu}\n" \
                   f"branch_tau = {tau}\n"
    msg = _refused(tmp_path, text, "specimen.lsdea_model")
    assert "branch_mu and branch_tau" in msg, msg


def test_a_trip_message_shows_the_value_and_the_limit_apart(tmp_path: Path) -> None:
    """A 0.0235-mA current limit tripped with "current -0.02 mA beyond the trip level 0.02 mA" (found by an outside
    tester): both rounded to two decimals. Now 4 significant figures, more where those still read the same."""
    rig = _load(tmp_path, _set(ADAM, "limits", "max_current_A", "2.35e-5"))
    sup = Supervisor(rig, rig.specimen.membrane())
    with pytest.raises(SafetyTrip) as trip:
        sup.check_monitors(0.0, -2.351e-5)
    assert "current -0.02351 mA beyond the trip level 0.0235 mA" in trip.value.reason, trip.value.reason
    with pytest.raises(SafetyTrip) as trip:  # past the limit in the 6th figure: shown to the 6th
        sup.check_monitors(0.0, 2.350001e-5)
    assert "current 0.02350001 mA beyond the trip level 0.0235 mA" in trip.value.reason, trip.value.reason
    force = _load(tmp_path, _set(MOTOR_DAQ, "limits", "max_force_N", "2.345"))
    sup = Supervisor(force, force.specimen.lozenge())
    with pytest.raises(SafetyTrip) as trip:
        sup.check_force(-2.3452)
    assert "force -2.3452 N beyond the limit ±2.345 N" in trip.value.reason, trip.value.reason
