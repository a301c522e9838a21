"""Manual control's rule for a laser that reads no displacement while the output is on (bench/runtime/polls.py
``_laser_check``): the supervisor's true field needs the stretch. Out of the laser's range trips at once (the specimen
is past it: a held 8 kV crept the thesis membrane out of range and on to runaway within 0.2 s, an outside tester);
any other reading without a displacement trips once it has lasted ``LASER_LOST_S`` (a glint is not a fault); a
voltage whose field is within the limit at any stretch up to runaway never trips (E = |V|·λ²/L3, physics.md §1.2);
and a run never trips on it (its protocol was dry-run on the model; it records ``valid`` 0, README)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from bench.rig import load_rig
from bench.runtime.manual_mode import LASER_LOST_S
from bench.runtime.polls import _laser_check
from bench.runtime.safety import SafetyTrip, Supervisor
from drivers.interfaces import Reading
from tests.conftest import ROOT


def _context(volts: float, lost_s: float | None) -> SimpleNamespace:
    rig = load_rig(ROOT / "rigs" / "thesis-sim.toml")
    return SimpleNamespace(t0=0.0, v_cmd=volts, laser_lost_s=lost_s, laser_lost_since=math.nan, laser_t_last=-1.0,
                           laser_last=math.nan, snapshot=SimpleNamespace(values={}),
                           sup=Supervisor(rig, rig.specimen.membrane()))


def _read(e: SimpleNamespace, t: float, status: str) -> None:
    _laser_check(e, {"displacement": Reading(math.nan, "mm", t, status)}, {"displacement": math.nan, "valid": 0.0})


def _safe_at_any_stretch(e: SimpleNamespace) -> float:
    """The largest voltage whose field stays within the limit up to the runaway stretch (physics.md §1.2)."""
    p, lim = e.sup.specimen, e.sup.rig.limits
    limit = min(lim.max_field_V_per_m or math.inf, p.breakdown_field / lim.breakdown_margin)
    return limit * p.L3 / p.runaway_stretch ** 2


def test_out_of_range_at_high_voltage_trips_at_once() -> None:
    e = _context(7998.0, LASER_LOST_S)
    with pytest.raises(SafetyTrip, match=r"laser reads no displacement \(over_range_positive\) at 7998 V"):
        _read(e, 1.0, "over_range_positive")


def test_another_reading_without_a_displacement_trips_once_it_has_lasted() -> None:
    e = _context(7998.0, LASER_LOST_S)
    _read(e, 1.0, "invalid")
    _read(e, 1.0 + LASER_LOST_S - 0.1, "invalid")  # a glint: not yet
    with pytest.raises(SafetyTrip, match=r"\(invalid\) at 7998 V"):
        _read(e, 1.0 + LASER_LOST_S, "invalid")


def test_a_voltage_safe_at_any_stretch_and_a_run_never_trip() -> None:
    e = _context(0.0, LASER_LOST_S)
    low = 0.9 * _safe_at_any_stretch(e)
    assert low > 50.0  # (about 5 kV on the thesis membrane: 90.9 MV/m × 1 mm / 4²)
    e.v_cmd = low
    for k in range(20):
        _read(e, k * 0.1, "over_range_positive")
    run = _context(7998.0, None)
    for k in range(20):
        _read(run, k * 0.1, "over_range_positive")


@pytest.mark.parametrize("rig_name", ["lsdea-isotonic-sim", "lsdea-motor-sim"])
def test_an_ls_dea_voltage_within_the_limit_at_every_aperture_never_trips(rig_name: str) -> None:
    """An LS-DEA's field had no bound: a laser out of range on an isotonic rig tripped manual control at any voltage
    (the field needs the aperture). Its bound is the supervisor's own field check taken over every aperture it
    judges: on a fine grid of x over [1.0001 xp, 1.999 l], the largest voltage within the limit at each (E = Vλ1λ2/t0
    against E0 (λ1λ2)^(r/2) / margin, physics.md §2) — the least of those. Just below it the laser may be lost;
    just above it, it trips (a bound beyond these rigs' voltage limits: a thinner film or a lower E0 brings it
    within them)."""
    import numpy as np

    rig = load_rig(ROOT / "rigs" / f"{rig_name}.toml")
    sup = Supervisor(rig, rig.specimen.lozenge())
    q = sup.specimen
    worst = math.inf
    for x in np.linspace(1.0001 * q.xp, 1.999 * q.l, 4001):
        sup.aperture = float(x)
        e_per_volt, limit = sup.field_and_breakdown(1.0)
        worst = min(worst, limit / e_per_volt)
    # the shipped prototype's film holds the rig's whole voltage range at any aperture: a lost laser is no danger
    # there (7.82 kV against 5 and 7 kV), and manual control no longer trips on it
    assert worst > sup.voltage_limit and sup.field_bounded(sup.voltage_limit)
    assert sup.field_bounded(0.995 * worst) and sup.field_bounded(-0.995 * worst)
    assert not sup.field_bounded(1.005 * worst)
    e = SimpleNamespace(t0=0.0, v_cmd=0.99 * worst, laser_lost_s=LASER_LOST_S, laser_lost_since=math.nan,
                        laser_t_last=-1.0, laser_last=math.nan, snapshot=SimpleNamespace(values={}), sup=sup)
    _read(e, 1.0, "over_range_positive")  # within the bound: no trip
    e.v_cmd = 1.01 * worst
    with pytest.raises(SafetyTrip, match=r"laser reads no displacement \(over_range_positive\)"):
        _read(e, 1.1, "over_range_positive")
