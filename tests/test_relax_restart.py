"""A relax step restarted after the output went to 0 V (a pause resumed in it) plays 0 V from its start: its ramp
from the step before's value is not played again. Before, the restart ramped the output back up to that value (a
relax's first value), only for the relax to ramp it down again: an unplanned high-voltage excursion in a recovery
record (outside tester, 2026-11-28: "recovery [T=296.0]) restarts from its start: … output to 2892 V").

Expected values come from the protocol below (3 kV at the ramp's end, then a 6-s relax), the rig's 50-V touch limit
and the plant's own output history. Virtual time, on both rig kinds (host set-points and a DAQ's stream-out)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "relax-paused"
description = "a ramp to 3 kV, a relax (paused and resumed in it)"
rig = "{rig}"

[recording]
displacement_Hz = 1000
setpoint_Hz = 20

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "3 kV"
duration_s = 1.0

[[steps]]
type = "relax"
name = "recovery"
duration_s = 6.0
"""
V_UP = 3000.0  # the ramp's end: the value the relax ramps down from
PAUSE_AT, RESUME_AT = 3.0, 4.0  # run time: in the relax (program 1.0–7.0 s), well after its ramp to 0 V
ZERO_V = 50.0  # the rig's touch limit: at or below, the output counts as 0 V


@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_a_relax_resumed_after_a_pause_stays_at_0_v(tmp_path: Path, rig: str) -> None:
    proto = tmp_path / "relax-paused.toml"
    proto.write_text(PROTOCOL.format(rig=(ROOT / "rigs" / f"{rig}.toml").as_posix()))
    blocks: list[tuple[np.ndarray, np.ndarray]] = []
    seen: dict[str, float] = {}

    def hook(engine: Engine, sim: Any) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy())))

        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and "t0" not in seen:
                seen["t0"] = sim.clock.now() - engine.now()
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= PAUSE_AT:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= RESUME_AT and "resume" not in seen:
                seen["resume"] = engine.now()
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(proto), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    t = np.concatenate([b[0] for b in blocks]) - seen["t0"]
    v = np.concatenate([b[1] for b in blocks])
    assert np.abs(v[(t > 0.9) & (t < 1.0)]).min() > 0.85 * V_UP  # the ramp drove the specimen up before the relax
    (t_restart, _, _, text), = [e for e in run.event_list() if e[2] == "restart"]
    assert "output to 0 V" in text and "not played again" in text, text
    # from the pause on, the output never came back: the relax went on at 0 V to the run's end
    assert np.abs(v[t > PAUSE_AT + 0.6]).max() <= ZERO_V
    ends = [e for e in run.event_list() if e[2] == "end" and e[3] == "recovery"]
    assert ends and ends[-1][0] > t_restart  # the relax ran again to its end after the restart
