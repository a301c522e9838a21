"""A relax step's ramp to 0 V is a schema field with a stated default (issue 23 item 7).

Expected values come from the schema's documentation (README "Protocol files", the schema module's docstring):
``ramp_down_s`` when given, else the longest of 0.5 s or a tenth of the step (whichever is shorter), 10 set-point
periods, the rig's ``limits.shutdown_ramp_s`` and the voltage over the amplifier's slew limit, in whole set-point
periods, at most the step — and from the protocol's and the rig's numbers.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.protocol.program import Segment, compile_program, ticks, voltage_at
from bench.protocol.schema import ProtocolFileError, load_protocol
from bench.rig import load_rig
from bench.runtime.run import plan_run
from tests.conftest import ROOT
from tests.test_protocols import SAFE_HEAD, SAFE_THESIS_RIG

RAMP_UP = '[[steps]]\ntype = "ramp"\nchannel = "voltage"\nto = "2 kV"\nduration_s = 1.0\n\n'


def _protocol(tmp: Path, relax: str) -> Path:
    f = tmp / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=SAFE_THESIS_RIG) + RAMP_UP + '[[steps]]\ntype = "relax"\n' + relax)
    return f


@pytest.mark.parametrize(("relax", "ramp"), [("duration_s = 60.0\n", 0.5),  # the default: 0.5 s
                                             # a tenth of a 2-s step is 0.2 s, 4 set-points at 20/s: the
                                             # ramp takes 10 (0.5 s)
                                             ("duration_s = 2.0\n", 0.5),
                                             ("duration_s = 60.0\nramp_down_s = 3.0\n", 3.0)])
def test_the_voltage_reaches_zero_at_the_end_of_the_stated_ramp(tmp_path: Path, relax: str, ramp: float) -> None:
    seg = plan_run(_protocol(tmp_path, relax)).program.segments[1]
    assert seg.kind == "relax" and seg.t_start == pytest.approx(1.0)
    assert voltage_at(seg, seg.t_start) == pytest.approx(2000.0)
    assert voltage_at(seg, seg.t_start + ramp / 2) == pytest.approx(1000.0)  # linear: half-way at half the time
    assert voltage_at(seg, seg.t_start + ramp) == pytest.approx(0.0, abs=1e-9)
    assert seg.stream_until == pytest.approx(seg.t_start + ramp)  # set-points at the full rate during the ramp


@pytest.mark.parametrize(("body", "fragment"), [
    ('[[steps]]\ntype = "hold"\nduration_s = 5.0\nramp_down_s = 1.0\n', "ramp_down_s applies to a relax step"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = 2.0\n', "longer than the step's duration_s"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = 0\n', "ramp_down_s"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = nan\n', "ramp_down_s"),
])
def test_a_wrong_ramp_down_is_refused_in_one_line_naming_the_field(tmp_path: Path, body: str, fragment: str) -> None:
    f = tmp_path / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=SAFE_THESIS_RIG) + RAMP_UP + body)
    with pytest.raises(ProtocolFileError) as err:
        plan_run(f)
    text = str(err.value)
    assert str(f) in text and fragment in text and "\n" not in text, text


def test_validate_shows_the_relax_ramp(tmp_path: Path) -> None:
    f = _protocol(tmp_path, "duration_s = 60.0\nramp_down_s = 3.0\n")
    proc = subprocess.run([sys.executable, "-m", "bench", "validate", str(f)], capture_output=True, text=True,
                          cwd=ROOT, env={"COLUMNS": "300", "PATH": ""}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "relax steps" in proc.stdout and "voltage to 0 V over 3 s" in proc.stdout


RAMP_5KV = '[[steps]]\ntype = "ramp"\nchannel = "voltage"\nto = "5 kV"\nduration_s = 1.0\n\n'
DT = 1 / 20  # SAFE_HEAD's recording.setpoint_Hz


def _relax(tmp: Path, relax: str, **rig_changes: dict[str, float]) -> tuple[Segment, list[float], list[float]]:
    """The relax step after a ramp to 5 kV at 20 set-points/s on thesis-sim (its [limits] / [amplifier] changed by
    ``rig_changes``), and the times and voltages of its set-point schedule up to its first 0 V."""
    f = tmp / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=SAFE_THESIS_RIG) + RAMP_5KV + '[[steps]]\ntype = "relax"\n' + relax)
    rig = load_rig(SAFE_THESIS_RIG)
    for table, change in rig_changes.items():
        rig = rig.model_copy(update={table: getattr(rig, table).model_copy(update=change)})
    program = compile_program(load_protocol(f), rig)
    seg = program.segments[1]
    t, v = [], []
    for tick in ticks(program, seg):
        assert tick.voltage is not None
        t.append(tick.t)
        v.append(tick.voltage)
        if tick.voltage == pytest.approx(0.0, abs=1e-9):
            break
    return seg, t, v


def test_a_short_relax_ramps_down_over_ten_set_points_not_one(tmp_path: Path) -> None:
    """The testers' case: a 0.5-s relax at 20 set-points/s took a tenth of the step, 0.05 s — one set-point, 5 kV to
    0 V in one tick. Now at least 10 set-points (0.5 s ≥ the rig's 0.25-s shutdown ramp), none more than 500 V."""
    seg, t, v = _relax(tmp_path, "duration_s = 0.5\n")
    assert v[0] == pytest.approx(5000.0)
    steps = -np.diff(v)
    assert len(steps) >= 10 and np.all(steps > 0)  # a ramp: ≥ 10 set-points, each lower
    assert np.max(steps) <= 5000.0 / 10 + 1e-6
    assert np.allclose(np.diff(t), DT)  # at the set-point rate, 0 V at the end of the step (the whole step here)
    assert t[-1] == pytest.approx(seg.t_end)


def test_the_default_ramp_down_is_never_steeper_than_the_rigs_shutdown_ramp(tmp_path: Path) -> None:
    """limits.shutdown_ramp_s = 2 s: a 60-s relax at 20/s ramps from 5 kV over 2 s, 40 set-points of 125 V."""
    _, t, v = _relax(tmp_path, "duration_s = 60.0\n", limits={"shutdown_ramp_s": 2.0})
    assert t[-1] - t[0] == pytest.approx(2.0)
    assert np.max(-np.diff(v)) <= 5000.0 * DT / 2.0 + 1e-6  # 125 V


def test_the_default_ramp_down_keeps_to_the_amplifiers_slew_limit(tmp_path: Path) -> None:
    """amplifier.slew_limit_V_per_s = 2 kV/s: from 5 kV the ramp takes 2.5 s, steps of 2 kV/s × 0.05 s = 100 V,
    none of which the driver's slew limit holds back."""
    _, t, v = _relax(tmp_path, "duration_s = 60.0\n", amplifier={"slew_limit_V_per_s": 2000.0})
    assert t[-1] - t[0] == pytest.approx(5000.0 / 2000.0)
    assert np.max(-np.diff(v)) <= 2000.0 * DT + 1e-6


def test_the_default_ramp_down_ends_on_a_set_point_not_a_keep_alive_later(tmp_path: Path) -> None:
    """limits.shutdown_ramp_s = 0.53 s is 10.6 set-point periods at 20/s: the ramp takes 11 (0.55 s), so its last
    set-point (0 V) comes one period after the one before — unrounded, 283 V would stand for a 0.25-s keep-alive."""
    _, t, v = _relax(tmp_path, "duration_s = 2.0\n", limits={"shutdown_ramp_s": 0.53})
    assert t[-1] - t[0] == pytest.approx(11 * DT)
    assert np.allclose(np.diff(t), DT)
    assert np.allclose(-np.diff(v), 5000.0 / 11)  # 11 equal steps, the last to 0 V


def test_a_relax_shorter_than_its_ramp_ramps_over_its_whole_length(tmp_path: Path) -> None:
    """A 0.2-s relax at 20/s has room for 4 set-points: the ramp takes the whole step (1250 V each, steeper than the
    rule; the dry run's current check judges it), and 0 V at its end."""
    seg, t, v = _relax(tmp_path, "duration_s = 0.2\n")
    assert seg.stream_until == pytest.approx(seg.t_end)
    assert t[-1] == pytest.approx(seg.t_end) and len(t) == 5
    assert np.max(-np.diff(v)) == pytest.approx(5000.0 / 4)


def test_a_stated_ramp_down_off_the_set_point_grid_reaches_0_v_on_the_next_set_point(tmp_path: Path) -> None:
    """ramp_down_s = 0.12 s at 20/s ends between two set-points (0.10 and 0.15 s): 0 V goes out at 0.15 s, the
    first set-point at or after the ramp's end — not at the next keep-alive, 0.25 s after the one at 0.10 s, with
    5 kV × (1 − 0.10/0.12) ≈ 833 V standing until then."""
    _, t, v = _relax(tmp_path, "duration_s = 2.0\nramp_down_s = 0.12\n")
    assert np.allclose(np.asarray(t) - t[0], [0.0, 0.05, 0.10, 0.15])
    assert np.allclose(v, [5000.0, 5000.0 * (1 - 0.05 / 0.12), 5000.0 * (1 - 0.10 / 0.12), 0.0])
