"""`bench benchmark daq`: how many times a protocol is timed, and that nothing of a timed run is kept on disk."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from bench.benchmarks import daq


@pytest.mark.parametrize(("rig_time", "walls", "runs", "best"), [
    (25.8, [0.5, 0.3, 0.4], 3, 0.3),  # a short protocol: the best of 3, as the ceiling is taken
    (1985.6, [22.0, 1.0, 1.0], 1, 22.0),  # a whole campaign: once (seconds of wall; 3 would cost a minute more)
])
def test_a_protocol_is_timed_best_of_three_and_a_whole_campaign_once(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rig_time: float, walls: list[float], runs: int,
        best: float) -> None:
    calls: list[str] = []

    def timed(protocol: Path, rig: str, tmp: Path, virtual: bool, name: str,
              twins: list[Any] | None = None) -> tuple[Any, float]:
        (tmp / f"{name}.h5").write_bytes(b"a run file")
        calls.append(name)
        return SimpleNamespace(run_time=rig_time), walls[len(calls) - 1]

    monkeypatch.setattr(daq, "_timed", timed)
    result, wall, _ = daq._best(Path("campaign.toml"), "rig", tmp_path, 3)
    assert len(calls) == runs and wall == best and result.run_time == rig_time
    assert list(tmp_path.iterdir()) == []  # each file removed once timed: a campaign's file is hundreds of MB


def test_a_fixed_part_below_zero_is_said_to_be_noise() -> None:
    """The fixed part is the difference of two walls (wall = fixed + rig time / speed, solved from a long and a
    short run): 25.8 s in 0.40 s and 11.8 s in 0.25 s give 0.15 s per 14 s, so 0.25 − 11.8·0.15/14 = 123.6 ms; a
    short run in 0.18 s gives −5.4 ms, which the row must not let pass for a gain."""
    def rows(short_wall: float) -> list[Any]:
        return daq._fixed_cost((25.8, 0.40), (SimpleNamespace(run_time=11.8), short_wall, []))  # type: ignore[arg-type]

    fixed, speed = rows(0.25)
    assert fixed.value == pytest.approx(123.57, abs=0.01) and "noise" not in fixed.note
    assert speed.value == pytest.approx(14 / 0.15)
    fixed, _ = rows(0.18)
    assert fixed.value == pytest.approx(-5.43, abs=0.01) and "noise, not a gain" in fixed.note


def test_a_ceiling_sample_is_taken_just_before_each_timed_run(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The share divides a protocol's best run by the ceiling of the same minutes: one sample before each run
    (a whole campaign, timed once, gets as many, the others right after it)."""
    order: list[str] = []

    def timed(protocol: Path, rig: str, tmp: Path, virtual: bool, name: str,
              twins: list[Any] | None = None) -> tuple[Any, float]:
        order.append("run")
        return SimpleNamespace(run_time=float(protocol.stem)), 0.5

    monkeypatch.setattr(daq, "_timed", timed)
    monkeypatch.setattr(daq, "ceiling_sample", lambda: order.append("ceiling") or daq.CeilingSample(0.2, 0.1, 0.1))
    samples: list[daq.CeilingSample] = []
    daq._best(Path("25.8.toml"), "rig", tmp_path, 3, samples)
    assert order == ["ceiling", "run"] * 3 and len(samples) == 3
    order.clear()
    daq._best(Path("1985.6.toml"), "rig", tmp_path, 3, samples := [])
    assert order == ["ceiling", "run", "ceiling", "ceiling"] and len(samples) == 3


def test_each_share_divides_by_the_best_ceiling_sampled_beside_its_own_runs() -> None:
    """25× against samples of 10 s of rig time in 0.25, 0.20 and 0.40 s (best: 50×) is 50 %; 40× against one
    sample of 10 s in 0.125 s (80×) is 50 % too; a row that is no speed, or has no samples, gets no share."""
    runs = [daq.Figure("a on rig, virtual time", 25.0, "× real time", ""),
            daq.Figure("  its file", 10.0, "%", ""),
            daq.Figure("b on rig, virtual time", 40.0, "× real time", ""),
            daq.Figure("c on rig, virtual time", 30.0, "× real time", "")]
    beside = {"a on rig, virtual time": [daq.CeilingSample(w, 0.0, 0.0) for w in (0.25, 0.20, 0.40)],
              "  its file": [daq.CeilingSample(0.1, 0.0, 0.0)],
              "b on rig, virtual time": [daq.CeilingSample(0.125, 0.0, 0.0)]}
    rows = daq.share_rows(runs, beside)
    assert [r.name for r in rows] == [f"  {x}: share of the driver ↔ twin ceiling" for x in "ab"]
    assert [r.value for r in rows] == [pytest.approx(50.0), pytest.approx(50.0)]
    assert "50.0× (best of 3)" in rows[0].note and "80.0× (best of 1)" in rows[1].note


def test_every_speed_row_of_the_set_gets_a_share(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each "× real time" row of the protocols (the looped ones, the refilled one and the thesis run's speed beyond
    its fixed part) has ceiling samples of its own, so every one of them gets its share row."""
    rig_time = {"thesis-identification": 25.8, "thesis-identification-short": 11.8}

    def timed(protocol: Path, rig: str, tmp: Path, virtual: bool, name: str,
              twins: list[Any] | None = None) -> tuple[Any, float]:
        if twins is not None:
            twins += [SimpleNamespace(outs=[SimpleNamespace(loops_set=1, values_written=10)]),
                      SimpleNamespace(cpu_seconds=0.01)]
        t = rig_time.get(protocol.stem, 10.0)
        return SimpleNamespace(run_time=t), 0.1 + t / 50.0

    monkeypatch.setattr(daq, "_timed", timed)
    monkeypatch.setattr(daq, "ceiling_sample", lambda: daq.CeilingSample(0.2, 0.1, 0.1))
    beside: dict[str, list[daq.CeilingSample]] = {}
    runs = daq.virtual_speed(tmp_path, beside=beside)
    speeds = [r.name for r in runs if r.unit == "× real time"]
    assert len(speeds) == 5  # three protocols, the speed beyond the fixed part, the refilled run
    shares = daq.share_rows(runs, beside)
    assert [r.name for r in shares] == [f"  {n.split(' on ')[0].strip()}: share of the driver ↔ twin ceiling"
                                        for n in speeds]
