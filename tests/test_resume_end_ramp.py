"""A resumed run that ends on its protocol's 0-V recovery logs no shutdown ramp (outside tester: its log ended
"ramp from 0 V to 0 V over 0.25 s"): there is nothing to ramp, 0 V is commanded and verified (the `safe` line).

protocols/short/thesis-sweeps-short.toml (as tests/test_report_run_states.py reads it): each sweep point ends with
a 2-s recovery at 0 V, so the run's output is at 0 V when its program ends."""

from __future__ import annotations

from pathlib import Path

from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"


def test_a_resumed_run_that_ends_at_0_v_logs_no_ramp_from_0_v(tmp_path: Path) -> None:
    def ctrl_c(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        def at(_now: float) -> None:
            if engine.snapshot.step == 1 and engine.program_now() > 2.3:
                engine.request_stop("Ctrl-C")
        sim.clock.subscribe(at)

    stopped = execute(plan_run(SWEEPS), tmp_path / "a.h5", virtual=True, on_engine=ctrl_c)
    assert stopped.state == "interrupted", stopped.reason
    plan, link, _ = plan_resume(stopped.path)
    resumed = execute(plan, tmp_path / "b.h5", virtual=True, resume=link)
    assert resumed.state == "completed", resumed.reason
    events = open_run(resumed.path).event_list()
    last_end = max(i for i, e in enumerate(events) if e[2] == "end")
    after = [(kind, text) for _, _, kind, text in events[last_end:]]
    assert not [e for e in after if e[0] == "ramp"], after  # nothing to ramp
    assert [e for e in after if e[0] == "safe" and "verified" in e[1]], after  # 0 V commanded and verified
