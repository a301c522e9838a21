"""The link budget's laser drain rate is what the engine and the driver upload, never more.

A reviewer: at set-point rates under ~5/s the budget counted one fetch a set-point period over the whole period
(1/s on the thesis rig: ~1,170 S/s claimed), but the engine fetches every ``FETCH_PERIOD_S`` (0.25 s), each fetch
ends at the step's next action — a set-point *or a poll* (the monitors every 0.2 s) — and the driver ends a call
after ``FETCH_BUDGET_S`` (0.2 s: one 256-value request at 115,200 Bd). The expected figures here are derived by
hand from the wire and those constants, event by event, not from the module: 8N1 = 10 bits a character; the
thesis rig's io bus at 19,200 Bd, FC6 = 8 + 8 characters and FC3 of two registers = 8 + 9, each with two
3.5-character silences and 1 ms turnaround [assumed]; the LK-G at 115,200 Bd, its AN exchange 3 + 16 characters
and an AO request 16 + 3 + 9 a value (manual p. 5-6, as the driver states it), the driver's allowance per exchange.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from bench.protocol.link_budget import check_links, laser_drain_rate
from bench.protocol.program import FETCH_PERIOD_S, Program, compile_program
from bench.protocol.schema import load_protocol
from bench.rig import load_rig
from drivers.keyence import EXCHANGE_ALLOWANCE_S, FETCH_BUDGET_S, VALUE_BYTES
from tests.conftest import RIGS, ROOT

CT = 10 / 115200  # one LK-G character
FC6 = (8 + 8) * 10 / 19200 + 2 * 3.5 * 10 / 19200 + 1e-3  # 12.98 ms: one set-point on the io bus
FC3 = (8 + 9) * 10 / 19200 + 2 * 3.5 * 10 / 19200 + 1e-3  # 13.5 ms: one read of the V and I monitors
CHUNK = int(FETCH_BUDGET_S * 115200 / (10 * VALUE_BYTES))  # 256 values: 0.2 s of wire, and one call's budget


def values_in(window: float) -> int:
    """Values one bounded fetch uploads in ``window`` seconds: the AN exchange (19 characters and an allowance),
    then one AO request (19 characters, an allowance, 9 a value) sized to end in it, at most a chunk; after a full
    chunk the call has spent its 0.2 s and stops, and a shorter request leaves no room for a second."""
    left = window - 2 * (19 * CT + EXCHANGE_ALLOWANCE_S)
    return max(0, min(CHUNK, int(left / (VALUE_BYTES * CT))))


def test_the_drain_at_one_set_point_a_second_counts_the_polls_and_the_call_budget() -> None:
    """1 set-point/s, monitors at 5/s: fetches at 0.25, 0.5 and 0.75 s end at the monitor reads at 0.4, 0.6 and
    0.8 s (windows of 150, 100 and 50 ms); the one at 1 s comes after the tick's FC6 and the monitors' FC3 and ends
    at the read at 1.2 s. Without the monitors every window is longer than a chunk's 0.2 s, and each fetch uploads
    one chunk: 4 × 256 a second, not the ~1,250 the wire would carry."""
    assert FETCH_PERIOD_S == 0.25
    by_hand = values_in(0.15) + values_in(0.10) + values_in(0.05) + values_in(0.2 - FC6 - FC3)
    assert by_hand == 182 + 118 + 54 + 212
    assert laser_drain_rate(115200, 1.0, ((5.0, FC3),), FC6) == by_hand
    assert laser_drain_rate(115200, 1.0, (), FC6) == 4 * CHUNK == 1024


def test_the_drain_at_twenty_set_points_a_second() -> None:
    """20 set-points/s, monitors at 5/s: a fetch every 50-ms tick after its FC6, to the next tick; every fourth
    tick the monitors are read first. 3 × 38 + 20 values each 0.2 s."""
    by_hand = (3 * values_in(0.05 - FC6) + values_in(0.05 - FC6 - FC3)) / 0.2
    assert by_hand == pytest.approx(5 * (3 * 38 + 20))
    assert laser_drain_rate(115200, 20.0, ((5.0, FC3),), FC6) == pytest.approx(by_hand)


def thesis_identification(**recording: float) -> Program:
    """thesis-identification on the software-timed simulated thesis rig, its recording changed."""
    protocol = load_protocol(ROOT / "protocols" / "thesis-identification.toml")
    protocol = protocol.model_copy(update={"recording": protocol.recording.model_copy(update=recording)})
    return compile_program(protocol, load_rig(RIGS / "thesis-sim.toml"))


def drained(line: str) -> float:
    """The drain rate a link-budget line states."""
    found = re.search(r"the link drains ([\d,]+) S/s", line)
    assert found is not None, line
    return float(found.group(1).replace(",", ""))


@pytest.mark.parametrize("setpoint_Hz", [1.0, 20.0])
def test_the_dry_run_refuses_a_storage_the_engine_cannot_drain_at_the_rate_derived_by_hand(setpoint_Hz: float) -> None:
    """1,000 S/s stored with the monitors at 5/s: the old model passed it at 1 set-point/s (~1,170 S/s claimed);
    the line now says the rate derived above (at 1/s, 5 set-points a cycle of its 0.11-Hz sweep: enough to compile)."""
    program = thesis_identification(displacement_Hz=1000.0, setpoint_Hz=setpoint_Hz, monitors_Hz=5.0,
                                    points_per_cycle=min(20, int(setpoint_Hz * 9)))
    (line,) = [p for p in check_links(program) if p.startswith("laser storage upload")]
    expected = (values_in(0.15) + values_in(0.10) + values_in(0.05) + values_in(0.2 - FC6 - FC3) if setpoint_Hz == 1
                else (3 * values_in(0.05 - FC6) + values_in(0.05 - FC6 - FC3)) / 0.2)
    assert drained(line) == expected, line


def test_the_budget_s_constants_are_the_driver_s_and_the_engine_s() -> None:
    """bench/protocol may import neither the driver nor the run time: its copies of their constants must agree."""
    from bench.protocol import link_budget as lb
    from bench.runtime.polls import COLLECT_PERIOD_S
    from drivers.keyence import FETCH_OVERHEAD_BYTES, MAX_UPLOAD, KeyenceLKG

    assert (lb.LKG_VALUE_BYTES, lb.LKG_UPLOAD_CHUNK_S, lb.LKG_EXCHANGE_ALLOWANCE_S, lb.LKG_FETCH_OVERHEAD_BYTES) \
        == (VALUE_BYTES, FETCH_BUDGET_S, EXCHANGE_ALLOWANCE_S, FETCH_OVERHEAD_BYTES)
    assert lb.COLLECT_PERIOD_S == COLLECT_PERIOD_S
    driver = SimpleNamespace(fetch_budget_s=FETCH_BUDGET_S, link=SimpleNamespace(baudrate=115200))
    assert lb._upload_chunk(115200) == KeyenceLKG.upload_chunk(driver) == min(MAX_UPLOAD, CHUNK)  # type: ignore[arg-type]


RAMP = """
[protocol]
name = "drain-1hz"
rig = "{rig}"

[recording]
displacement_Hz = 1000
monitors_Hz = 5
setpoint_Hz = 1

[[steps]]
type = "ramp"
name = "slow"
channel = "voltage"
to = "1 kV"
duration_s = 2
"""


def test_the_stated_drain_is_not_above_what_a_virtual_run_uploads_at_one_set_point_a_second(tmp_path: Path) -> None:
    """A 2-s ramp at 1 set-point/s storing 1,000 S/s on thesis-sim, run in virtual time with the twins' wire time
    (the budget's verdict lifted so that the run takes it): the LK-G twin's AO requests started in the step's
    second second (its schedule's repeat, the first one settled) carry at least the drain the dry run states —
    and the dry run states one, since 1,000 S/s is more than they carry."""
    from bench.runtime.run import execute, plan_run

    proto = tmp_path / "p.toml"
    proto.write_text(RAMP.format(rig=RIGS / "thesis-sim.toml"))
    plan = plan_run(proto)
    (line,) = [p for p in plan.link_problems if p.startswith("laser storage upload")]
    uploads: list[tuple[float, int]] = []  # (run time, values) of each AO the twin answered

    def hook(engine: Any, sim: Any) -> None:
        twin = sim.twins["laser"]
        dispatch = twin._dispatch

        def spy(main: str, args: list[str]) -> str:
            if main == "AO":
                uploads.append((sim.clock.now() - engine.ctx.t0, int(args[2])))
            return str(dispatch(main, args))
        twin._dispatch = spy

    result = execute(dataclasses.replace(plan, link_problems=[]), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    measured = sum(n for t, n in uploads if 1.0 <= t < 2.0)  # values/s over one whole second of the step
    assert 0 < drained(line) <= measured < 1000, (line, uploads)
    assert math.isclose(drained(line), measured, rel_tol=0.05), (line, uploads)  # and not far below it
