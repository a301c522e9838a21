"""The README's standard, on the exits a run cannot record itself: a fault latches until an operator resets it.

* a bench process killed while it drives the rig (``kill -9``, a crash, a power cut) never commanded nor verified
  0 V: the next start on the rig finds the marker it left and latches the rig;
* a supervisor limit trip (current, voltage, position, force beyond the rig's limits) latches the rig, after its
  verified 0 V, as an interlock fault does;
* ``bench run --resume FILE --why …`` resets the latch only once the rig has connected: a resume that fails to start
  leaves the rig latched, and the history says why the reset was withheld.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime import latch as rig_latch
from bench.runtime import run as run_mod
from bench.runtime.latch import LatchedError, latched, refuse_if_latched
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SHORT = ROOT / "protocols" / "short"
IDENT = SHORT / "thesis-identification-short.toml"


# ---------------------------------------------------------------- a supervisor limit trip latches
def _tiny_current_limit(plan: run_mod.Plan) -> None:
    limits = {**plan.rig.limits.model_dump(), "max_current_A": 1e-7}  # any drive's charging current is beyond it
    plan.rig = plan.program.rig = RigConfig.model_validate({**plan.rig.model_dump(), "limits": limits})


def test_a_limit_trip_latches_the_rig_after_its_verified_zero(tmp_path: Path) -> None:
    plan = plan_run(IDENT, ROOT / "rigs" / "thesis-sim.toml")
    _tiny_current_limit(plan)
    result = execute(plan, tmp_path / "trip.h5", virtual=True)
    assert result.state == "tripped" and "beyond the trip level" in result.reason, result.reason
    run = open_run(result.path)
    assert "verified" in run.reason  # 0 V commanded and read back: the trip is no unverified output
    was = latched(plan.rig.name)
    assert was is not None and "current" in was["fault"] and "beyond the trip level" in was["fault"]
    assert was["where"] == str(result.path) and was["at"]
    assert any(kind == "interlock" and "safety trip" in text for _, _, kind, text in run.event_list())
    assert "beyond the trip level" in result.latched  # the command line says the rig latched
    with pytest.raises(LatchedError, match="bench interlock reset thesis-sim"):  # the next protocol is refused
        execute(plan_run(IDENT, ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "next.h5", virtual=True)
    assert not (tmp_path / "next.h5").exists()
    rig_latch.reset(plan.rig.name, "ada", "limit checked")
    refuse_if_latched(plan.rig.name)


def test_a_limit_trip_in_manual_control_latches_the_rig(tmp_path: Path) -> None:
    from bench.runtime.manual import ManualSession

    rig = load_rig(ROOT / "rigs" / "thesis-sim.toml")
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _line: None) as s:
        assert s.execute("voltage 5 kV").status == "ok"
        s._sim.plant.inject_breakdown()  # the specimen fails: the current monitor trips the supervisor
        trip = s.execute("watch 2 0.5")
        assert trip.status == "trip" and "current" in trip.text and "latched" in trip.text, trip
        assert s.execute("voltage 1 kV").status == "refused"  # nothing energises until `reset WHY`
        was = latched(rig.name)
        assert was is not None and "safety trip" in was["fault"] and was["where"] == str(tmp_path / "s.log")
    assert latched(rig.name) is not None  # the latch outlives the session
