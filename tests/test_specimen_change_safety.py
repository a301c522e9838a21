"""A set step (the operator mounts a prototype, hangs a mass or sets the chamber) only at 0 V, and the supervisor's
limits follow the specimen it sets (LS-DEA prototypes: the paper's Table 2, λ2p 2.5 / 2.75 / 3.0)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from bench.protocol.program import compile_program
from bench.protocol.schema import load_protocol
from bench.rig import load_rig
from bench.runtime.run import execute, plan_run
from tests.conftest import ROOT

RIG = ROOT / "rigs" / "lsdea-motor-sim.toml"
HEAD = f"""[protocol]
name = "set-under-voltage"
rig = "{RIG}"

[specimen]
prototype = 1

[recording]
setpoint_Hz = 50
position_Hz = 10
force_Hz = 50
monitors_Hz = 5
"""
RAMP = """
[[steps]]
type = "ramp"
name = "voltage on"
channel = "voltage"
to = "{to}"
duration_s = 0.2
"""
SET = """
[[steps]]
type = "set"
name = "mount prototype 3"
prototype = 3
"""
WAIT = """
[[steps]]
type = "wait"
name = "settle"
duration_s = 0.2
"""


def _protocol(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "p.toml"
    path.write_text(HEAD + text, encoding="utf-8")
    return path


def test_a_specimen_change_under_voltage_is_refused_before_the_run(tmp_path: Path) -> None:
    path = _protocol(tmp_path, RAMP.format(to="3 kV") + SET)
    with pytest.raises(ValueError, match=r"needs the output at 0 V.*3000 V"):
        compile_program(load_protocol(path), load_rig(RIG))


def test_the_supervisor_s_limits_follow_the_prototype_a_set_step_mounts(tmp_path: Path) -> None:
    path = _protocol(tmp_path, RAMP.format(to="2 kV") + RAMP.format(to="0 kV") + SET + WAIT)
    engines: list[Any] = []
    result = execute(plan_run(path), tmp_path / "run.h5", virtual=True, on_engine=lambda e, _s: engines.append(e))
    assert result.state == "completed", result.reason
    assert engines[0].sup.specimen.lambda2p == pytest.approx(3.0)  # prototype #3, Table 2
