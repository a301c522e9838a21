"""A resumed file names the protocol file the campaign was planned from, not the temporary copy its resume was
planned from."""

from __future__ import annotations

import os
from pathlib import Path

from typer.testing import CliRunner

from bench.cli import app
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
RIG = ROOT / "rigs" / "thesis-sim.toml"
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "300"}
runner = CliRunner()


def said(res) -> str:  # type: ignore[no-untyped-def]
    return " ".join(res.output.split())


def test_a_resumed_file_names_the_protocol_file_its_campaign_was_planned_from(tmp_path: Path) -> None:
    """Its ``protocol_path`` is the original file's (the resume plans from a temporary copy of the stored text,
    deleted once planned)."""
    plan = plan_run(SWEEPS, RIG)

    def stop_at_3(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        sim.clock.subscribe(lambda _now: engine.request_stop("the test") if engine.now() >= 3.0 else None)

    stopped = execute(plan, tmp_path / "stopped.h5", virtual=True, on_engine=stop_at_3)
    assert stopped.state == "interrupted", stopped.reason
    original = open_run(stopped.path, streams=False).attrs["protocol_path"]
    assert original == str(SWEEPS)
    plan2, link, _ = plan_resume(stopped.path)
    assert str(plan2.protocol.path) == original
    resumed = execute(plan2, tmp_path / "resumed.h5", virtual=True, resume=link)
    assert resumed.state == "completed", resumed.reason
    assert open_run(resumed.path, streams=False).attrs["protocol_path"] == original
    res = runner.invoke(app, ["inspect", resumed.path])
    assert str(SWEEPS) in said(res) and "/tmp" not in said(res).replace(str(tmp_path), ""), res.output
