"""The charging current a voltage step shows on the TREK's current monitor (:mod:`bench.core.step_current`), against
first-order step responses derived by hand, and manual control's use of it on a DAQ rig: a step whose charging
current a run's scans would trip on is refused, with the ramp that keeps each of its set-points within the limit.

Derivations (single first-order stages, unit step dv at t = 0, load C): the output through one pole a moves as
dv(1 − e^(−at)), so the current is C·dv·a·e^(−at); the monitor's pole m turns a current C·dv·a·e^(−at) into
C·dv·a·m/(m − a)·(e^(−at) − e^(−mt)), largest at t* = ln(m/a)/(m − a). A current held at I for τ (the amplifier at
its current limit) reads I(1 − e^(−mτ)) at its end. Figures: the TREK 10/10B-HS datasheet as in
bench/core/noise.py (19.5 kHz, 700 V/µs, 40 mA peak for 1 ms); the current monitor's 1 kHz is that file's
assumption."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from bench.core.noise import TrekDynamics
from bench.core.step_current import largest_step, monitor_peak
from bench.rig import load_rig
from bench.runtime.manual import ManualSession
from tests.conftest import ROOT

TREK = TrekDynamics(19.5e3, 700e6, 10e-3, 40e-3, 1e-3, 10e3, 1e3, 1e-3, 1e-2, 1.0, 1e-6)
W_B, W_M = 2 * math.pi * 19.5e3, 2 * math.pi * 1e3  # rad/s: the output stage's and the current monitor's poles


def _two_poles(q: float, a: float, m: float) -> float:
    """The largest reading of a charge ``q`` delivered as q·a·e^(−at), through the monitor's pole ``m``."""
    t = math.log(m / a) / (m - a)
    return q * a * m / (m - a) * (math.exp(-a * t) - math.exp(-m * t))


def test_a_filtered_step_reads_the_filters_exponential_through_the_monitor() -> None:
    # 5 kV behind a 30-Hz reconstruction filter (the thesis DAQ rig's) into 0.71 nF: the filter's pole is the slow
    # one by far (the output stage's, 650 times faster, moves the answer by well under 1 %)
    c, dv, fc = 0.71e-9, 5000.0, 30.0
    assert monitor_peak(dv, c, TREK, fc) == pytest.approx(_two_poles(c * dv, 2 * math.pi * fc, W_M), rel=0.01)
    assert monitor_peak(-dv, c, TREK, fc) == pytest.approx(monitor_peak(dv, c, TREK, fc))  # a step down alike


def test_a_small_unfiltered_step_reads_the_output_stages_exponential() -> None:
    # 100 V into 1 nF: the output stage's own pole (C·dv·a = 12 mA, under the 40-mA limit; 100·a ≪ the slew rate)
    c, dv = 1e-9, 100.0
    assert c * dv * W_B < TREK.peak_current and dv * W_B < TREK.slew  # the premise: a linear response
    assert monitor_peak(dv, c, TREK, None) == pytest.approx(_two_poles(c * dv, W_B, W_M), rel=0.01)


def test_a_large_unfiltered_step_reads_the_current_limit_held_while_it_charges() -> None:
    # 5 kV into 4 nF: 40 mA for C·dv/I = 0.5 ms (under the 1-ms peak rating), then the output stage's last 8 µs
    c, dv = 4e-9, 5000.0
    tau = c * dv / TREK.peak_current
    assert monitor_peak(dv, c, TREK, None) == pytest.approx(TREK.peak_current * (1 - math.exp(-W_M * tau)),
                                                             rel=0.02)
    assert monitor_peak(0.0, c, TREK, None) == 0.0


def test_the_largest_step_is_the_last_within_the_limit() -> None:
    c = 0.87e-9
    step = largest_step(c, TREK, None, 5e-3, 8000.0)
    assert 0 < step < 8000
    assert monitor_peak(step, c, TREK, None) <= 5e-3 < monitor_peak(step + 1.0, c, TREK, None)
    assert largest_step(c, TREK, 30.0, 5e-3, 8000.0) == 8000.0  # behind a 30-Hz filter even 8 kV reads ~1 mA


def _volts(text: str) -> float:
    return float(re.search(r"voltage (-?\d+) V", text).group(1))  # type: ignore[union-attr]


def test_manual_control_refuses_a_step_a_run_would_trip_on_and_names_the_ramp(tmp_path: Path) -> None:
    """`voltage 0` then `voltage 5000` on the LS-DEA DAQ rig (no reconstruction filter) went out (an outside tester),
    where validate refuses a 1-kV square edge for its charging current (12 mA against 5 mA). The step is refused,
    nothing sent; the ramp the refusal names goes through, as does a step behind the thesis rig's 30-Hz filter."""
    rig = load_rig(ROOT / "rigs" / "lsdea-motor-daq-sim.toml")
    assert rig.daq is not None and rig.daq.drive_filter_Hz is None and rig.limits.max_current_A == 5e-3
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        step = s.execute("voltage 5000")
        assert step.status == "refused" and "mA on the current monitor" in step.text, step
        assert abs(_volts(s.execute("read").text)) < 50  # nothing sent
        too_fast = s.execute("ramp 5000 0.1")  # 2 set-points of 2.5 kV
        assert too_fast.status == "refused" and "ramp not started" in too_fast.text, too_fast
        ramp = re.search(r"`ramp (\d+) V ([\d.]+) s`", step.text)
        assert ramp is not None, step.text
        done = s.execute(f"ramp {ramp[1]} {ramp[2]}")
        assert done.status == "ok", done
        assert _volts(done.text) == pytest.approx(5000, abs=100)
        # letting the output down is never refused: a step toward 0 V (the same 5 kV the other way), and 0 V itself
        assert s.execute("voltage 200").status == "ok"
        assert s.execute("voltage 0").status == "ok"
        assert s.execute("voltage -5000").status == "refused"  # from 0 V: a step up in magnitude
    thesis = load_rig(ROOT / "rigs" / "thesis-daq-sim.toml")
    with ManualSession(thesis, tmp_path / "t.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 5000").status == "ok"
