"""A run that ends on its protocol's 0-V recovery logs no shutdown ramp (outside tester: a resumed run's log ended
"ramp from 0 V to 0 V over 0.25 s"): there is nothing to ramp — the set-point the DAQ left is under 0.5 V, a DAC
code's rounding — so 0 V is commanded and verified (the `safe` line) with no ramp line and no ramp's set-point rows.

The session's short identification run (protocols/short/thesis-identification-short.toml on its DAQ rig) ends with
a relax step at 0 V, as the tester's resumed sweep did; any run ending so takes that path, resumed or not (the
resumed sweep itself took 31 s of the suite)."""

from __future__ import annotations

from pathlib import Path

from bench.storage.runfile import open_run


def test_a_run_that_ends_at_0_v_logs_no_ramp_from_0_v(short_run: Path) -> None:
    run = open_run(short_run)
    assert run.state == "completed", run.reason
    events = run.event_list()
    last_end = max(i for i, e in enumerate(events) if e[2] == "end")
    assert events[last_end][3] == "recovery"  # the protocol's 0-V relax ended the program
    after = [(kind, text) for _, _, kind, text in events[last_end:]]
    assert not [e for e in after if e[0] == "ramp"], after  # nothing to ramp
    assert [e for e in after if e[0] == "safe" and "verified" in e[1]], after  # 0 V commanded and verified
    sp = run.streams["setpoints"]
    assert len(sp) == 1 and sp.columns["voltage"][0] == 0.0  # the end's 0 V alone: no ramp's rows
