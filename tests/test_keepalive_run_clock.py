"""Keep-alives count on the run's clock: the set-point modules' watchdogs count rig time, so a host that is fast
against a virtual clock must still feed them (issue 21).

The ADAM-4024's communication safety and the T7's watchdog zero the output after 1 s without a request (the rig
files' ``comm_watchdog_s`` / ``watchdog_s``, ADAM-4000 manual appendix G, T7 datasheet "Watchdog"); the run's
keep-alive period is a quarter of that (``HOLD_KEEPALIVE_S`` / ``KEEPALIVE_S``).
"""

from __future__ import annotations

import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import bench.runtime.engine as engine_mod
from bench.core.clock import VirtualClock
from bench.rig import load_rig
from bench.runtime.hardware_timed import HardwareTimed
from bench.runtime.polls import COLLECT_PERIOD_VIRTUAL_S
from bench.runtime.run import execute, plan_run
from drivers.interfaces import StreamBlock
from tests.conftest import ROOT

DRAIN_PROTOCOL = """[protocol]
name = "drain"
description = "a ramp to 3 kV with laser storage, then a hold"
rig = "thesis-sim"

[recording]
displacement_Hz = 1000
monitors_Hz = 10
setpoint_Hz = 20

[[steps]]
type = "ramp"
name = "up"
to = "3 kV"
duration_s = 1.0

[[steps]]
type = "hold"
name = "hold"
duration_s = 0.5

[[steps]]
type = "relax"
name = "end"
duration_s = 0.2
"""
UPLOADS = 15  # stored-data uploads the drain after the ramp takes, each …
UPLOAD_S = 0.2  # … this long on the wire (rig time): 3 s of draining at 3 kV, three watchdog periods


def test_a_long_laser_drain_in_virtual_time_keeps_the_adam_fed(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """After the ramp, the laser's stored data takes 3 s of rig time to upload (a slow wire) while the output
    holds 3 kV; the host itself takes next to no wall time. The module must hear a request at least every
    keep-alive period of rig time: no watchdog trip, the run completes."""
    proto = tmp_path / "drain.toml"
    proto.write_text(DRAIN_PROTOCOL)
    seen: dict[str, Any] = {}
    real = engine_mod.record_laser_block  # type: ignore[attr-defined]  # the name the engine calls
    left = [UPLOADS]

    def slow_upload(ctx: Any) -> int:
        n = real(ctx)
        if ctx.program_now() >= 1.0 and left[0] > 0:  # the drain after the ramp (engine's own calls only)
            left[0] -= 1
            seen["sim"].clock.advance(UPLOAD_S)
            return max(n, 1)
        return n

    monkeypatch.setattr(engine_mod, "record_laser_block", slow_upload)
    gaps: list[float] = []

    def hook(_engine: Any, sim: Any) -> None:
        seen["sim"] = sim
        plant = sim.plant
        feed = plant.feed_watchdog
        last = [sim.clock.now()]

        def fed(at: float | None = None) -> None:
            now = sim.clock.now() if at is None else at  # the request's instant (the ADAM twin passes it)
            gaps.append(now - last[0])
            last[0] = now
            feed(at)
        plant.feed_watchdog = fed

    result = execute(plan_run(proto, ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "run.h5", virtual=True,
                     on_engine=hook)
    assert left[0] == 0  # the long drain happened
    assert result.state == "completed", result.reason
    assert seen["sim"].plant.watchdog_trips == 0
    assert max(gaps) < 1.0  # the module's 1-s period (rig file) never passed without a request


class _Daq:
    """A DAQ whose stream delivers nothing new and whose command-response reads are counted."""

    timeout = 0.5
    out_underrun_scans = 0

    def __init__(self) -> None:
        self.reads = 0

    def collect(self, until: float | None = None, timeout: float = 1.0) -> StreamBlock:
        return StreamBlock(0, 0.0, 1e-4, ("vmon",), np.empty((0, 1)), np.empty((0, 1), bool))

    def read_dac(self, dac: int) -> float:
        self.reads += 1
        return 0.0


def test_the_stream_keepalive_counts_rig_time_not_wall_time() -> None:
    """Collects 0.25 s of virtual time apart, as fast as the host can make them: each one finds the T7 unheard for
    a keep-alive period of rig time and sends a command-response request (on today's main only the first did, the
    wall clock having hardly moved)."""
    clock = VirtualClock(100.0)
    daq = _Daq()
    ctx = types.SimpleNamespace(clock=clock, guard=lambda streaming=False: None)
    hw = HardwareTimed(load_rig(ROOT / "rigs" / "thesis-daq-sim.toml"), daq, object(), ctx)  # type: ignore[arg-type]
    hw._keepalive = clock.now()  # as kickoff leaves it
    for _ in range(8):
        clock.advance(COLLECT_PERIOD_VIRTUAL_S)
        hw.collect()
    assert daq.reads == 8
