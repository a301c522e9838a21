"""`bench benchmark faults`: a few cases of the fault matrix through the command's own path (virtual time), and
the matrix's verdict on outputs that were not at 0 V.

What a case must show is independent of the benchmark's bookkeeping: the simulated amplifier's output, read here
from the plant by a listener of this test's own, is at most 5 V when the run returns.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from bench.benchmarks import faults
from bench.cli import app

runner = CliRunner()
ZERO_V = 5.0  # one ADAM-4024 code × the TREK gain
CASES = {("run", "ADAM", "io: dropped", "hold"),  # the module's watchdog zeroes the output
         ("run", "T7", "gain ×1.25", "waveform"),  # a trip (the current, or the interlock's mismatch)
         ("run", "T7", "T7 writes refused", "shutdown")}  # during the ramp-down: the T7's watchdog


@pytest.fixture
def three_cases(monkeypatch: pytest.MonkeyPatch) -> list[tuple[float, float]]:
    """The matrix cut to CASES, run in this process; returns, per run, (largest |output|, |output| at return)
    as the plant reported them to this fixture's listener."""
    full = faults.matrix
    monkeypatch.setattr(faults, "matrix", lambda quick=False: [s for s in full() if s.key in CASES])
    monkeypatch.setattr(faults, "JOBS", 1)
    seen: list[tuple[float, float]] = []
    real = faults.execute

    def execute(plan: Any, out: Path, **kwargs: Any) -> Any:
        hook = kwargs.pop("on_engine")
        volts: list[np.ndarray] = []
        sims: list[Any] = []

        def both(engine: Any, sim: Any) -> None:
            sims.append(sim)
            sim.plant.listeners.append(lambda b: volts.append(np.abs(b.v_out)))
            hook(engine, sim)

        result = real(plan, out, on_engine=both, **kwargs)
        sims[0].plant.observe()  # virtual clock: up to the moment execute returned
        seen.append((float(max(v.max() for v in volts)), float(volts[-1][-1])))
        return result

    monkeypatch.setattr(faults, "execute", execute)
    return seen


def test_three_cases_end_at_zero_volts_in_json_and_table(three_cases: list[tuple[float, float]]) -> None:
    res = runner.invoke(app, ["benchmark", "faults", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)["faults"]
    assert len(three_cases) == 3
    for peak, last in three_cases:
        assert peak > 1000.0 and last <= ZERO_V  # high voltage was on, and off when the run returned
    cases = data["cases"]
    assert {(c["mode"], c["rig"], c["fault"], c["phase"]) for c in cases} == CASES
    for c in cases:
        assert c["clock"] == "virtual" and c["injected"] and c["zero_at_return"], c
        assert c["state"] in ("error", "tripped", "interrupted") and c["reason"]
        assert 0.0 <= c["to_zero_s"] <= c["returned_s"] and c["peak_after_V"] > ZERO_V
    summary = data["summary"]
    assert summary["cases"] == summary["injected"] == summary["safe"] == 3 and summary["all_safe"]
    assert not summary["findings"]
    assert set(summary["worst"]) == {"dropped link", "gain off", "refused writes"}

    res = runner.invoke(app, ["benchmark", "faults"], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    rows = [line for line in res.output.splitlines() if line.startswith("│ run ")]
    assert len(rows) == 3 and all("│ yes " in row for row in rows), res.output
    assert "3 cases (3 injected): 3 at 0 V when the run returned, 0 findings; all safe: yes" in res.output


class _Plant:
    def observe(self) -> None:
        pass


def test_an_output_still_high_or_back_on_is_a_finding() -> None:
    """The verdict itself, on made-up output histories (fault at 1 s): 3 kV left on at return; 0 V from 1.2 s,
    then 2 kV again from 1.7 s to 1.8 s — after the run began to stop, after a watchdog zeroed it, or neither
    (the protocol's own 0-V stretch, as a run the fault did not stop plays it)."""
    t = np.arange(0.0, 2.0, 1e-3)
    still_on = np.where(t < 1.0, 5000.0, 3000.0)
    dip = np.where((t >= 1.2) & (t < 1.7), 0.0, 2000.0)
    dip[t >= 1.8] = 0.0
    cases = []
    for name, v, t_stop, trips in (("still on", still_on, None, []), ("stop", dip, 1.1, []),
                                   ("watchdog", dip, None, [1.2]), ("protocol", dip, None, [])):
        trace = faults.Trace()
        trace.blocks.append((t, v))
        trace.t_stop, trace.trips = t_stop, trips
        case = faults.Case("run", "ADAM", name, "test", "hold", "virtual", injected=True, state="error")
        trace.judge(case, _Plant(), t_fault=1.0, t_return=float(t[-1]))
        cases.append(case)
    on, stop, watchdog, protocol = cases
    assert not on.zero_at_return and on.to_zero_s == pytest.approx(t[-1] - 1.0)
    assert stop.zero_at_return and stop.reenergised_V == watchdog.reenergised_V == 2000.0
    assert protocol.reenergised_V == 0.0 and protocol.to_zero_s == pytest.approx(0.799)
    summary = faults.summarise(cases)
    assert not summary.all_safe and summary.safe == 3 and len(summary.findings) == 3
    lines = faults.summary_lines(summary)
    assert "all safe: NO" in lines[0]
    assert any("still on hold: output NOT at 0 V" in line for line in lines)
    assert sum("output back at 2000 V" in line for line in lines) == 2


def test_quick_is_a_subset_of_the_matrix_with_every_fault_kind_both_rigs_and_both_modes() -> None:
    """``--quick`` leaves cases out, never a kind of fault, a rig kind or a mode (the set of kinds is the full
    matrix's own, not a list of this test's)."""
    full = {spec.key: spec for spec in faults.matrix()}
    quick = faults.matrix(quick=True)
    assert len({spec.key for spec in quick}) == len(quick) < len(full)
    assert all(spec.key in full for spec in quick)
    assert {spec.fault.kind for spec in quick} == {spec.fault.kind for spec in full.values()}
    assert {spec.rig for spec in quick} == {spec.rig for spec in full.values()} == set(faults.RIGS)
    assert {spec.mode for spec in quick} == {spec.mode for spec in full.values()} == {"run", "control"}
    for rig in faults.RIGS:  # a fault only one rig kind has (the T7's output writes) is in quick on that rig
        own = {s.fault.kind for s in full.values() if s.rig == rig} - {s.fault.kind for s in full.values()
                                                                       if s.rig != rig}
        assert own <= {spec.fault.kind for spec in quick if spec.rig == rig}
