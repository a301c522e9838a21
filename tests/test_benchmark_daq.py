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
