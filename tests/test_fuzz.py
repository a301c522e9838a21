"""Fuzzed rig and protocol files (tests/fuzzing/files.py): every mutant is refused in one line or accepted, never a
traceback or a hang; and the harness itself counts tracebacks and hangs (a hang is killed, not endured)."""

from __future__ import annotations

import time
import tomllib

import pytest

import bench.runtime.run
from tests.fuzzing.files import _mutate_text, make_cases, run_fuzz, to_toml


def test_short_fuzz_run_has_no_traceback_and_no_hang() -> None:
    report = run_fuzz(150, 150, seed=8)  # a hang is counted, not waited out: the harness kills it at its limit
    c = report.counts
    details = "\n".join(f"{o.kind}: {o.case.label}\n{o.detail}" for o in report.outcomes
                        if o.kind in ("traceback", "hang"))
    assert c["files"] == 300
    assert c["traceback"] == 0 and c["hang"] == 0, details
    assert c["refused"] > 0 and c["accepted"] > 0
    assert c["refused"] + c["accepted"] == 300
    assert all(o.detail.startswith(("protocol file ", "rig file ")) for o in report.outcomes if o.kind == "refused")


def test_mutants_are_reproducible_and_varied(tmp_path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    first, second = make_cases(40, 40, 3, a), make_cases(40, 40, 3, b)
    assert [c.mutation for c in first] == [c.mutation for c in second]
    assert [c.file.read_bytes() for c in first] == [c.file.read_bytes() for c in second]
    assert len({c.mutation for c in first}) > 40


def test_writer_round_trips_through_tomllib() -> None:
    doc = {"protocol": {"name": "x", "rig": "r.toml"}, "steps": [{"type": "hold", "duration_s": 1.5}],
           "n": -3, "f": float("inf"), "t": True, "s": 'a "quoted" \\ string', "deep": [[1, 2], {"k": []}]}
    assert tomllib.loads(to_toml(doc)) == doc


def test_text_mutations_cover_truncation_and_deep_nesting() -> None:
    import random

    rng = random.Random(0)
    kinds = {_mutate_text("name = 'x'\n[a]\nb = 1\n", rng)[1].split()[0] for _ in range(60)}
    assert {"truncated", "random", "duplicate", "array"} <= kinds


def test_harness_counts_tracebacks(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(bench.runtime.run, "plan_run", broken)  # the forked workers inherit the patch
    c = run_fuzz(3, 2, seed=1).counts
    assert (c["traceback"], c["refused"], c["accepted"], c["hang"]) == (5, 0, 0, 0)


def test_harness_kills_and_counts_hangs(monkeypatch: pytest.MonkeyPatch) -> None:
    def hang(*args: object, **kwargs: object) -> None:
        while True:
            time.sleep(1)

    monkeypatch.setattr(bench.runtime.run, "plan_run", hang)
    c = run_fuzz(2, 1, seed=1, limit=0.3).counts
    assert c["hang"] == 3 and c["files"] == 3  # each killed at its limit: counted, not waited out


def test_short_wire_fuzz_twins_survive_frames_and_drivers_survive_replies() -> None:
    """Issue 8: random and mutated frames to every twin (Modbus on RTU and TCP), mutated replies to every
    driver — no twin dies, every driver returns a finite reading or a named driver error, and all recover.
    The long run is ``python -m tests.fuzzing.wire --frames N --replies N``."""
    from tests.fuzzing.wire import Tally, fuzz_frames, fuzz_replies

    tally = Tally()
    fuzz_frames(10, 5, tally)
    fuzz_replies(10, 5, tally)
    assert tally.failures() == 0, tally.examples
    for role in ("amplifier", "laser", "motor", "load_cell", "daq"):
        assert tally.counts[role]["refused"] > 0, role  # the mutated replies did reach the driver
    assert sum(c["sent"] for who, c in tally.counts.items() if who.endswith("frames")) >= 60


def test_wire_fuzz_counts_an_exception_that_is_not_a_driver_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import tests.fuzzing.wire as fw

    def broken() -> float:
        raise KeyError("not a driver error")

    monkeypatch.setattr(fw, "RIGS", ("thesis-sim",))
    monkeypatch.setattr(fw, "_reads", lambda inst: {"laser": broken})
    tally = fw.Tally()
    fw.fuzz_replies(3, 1, tally)
    assert tally.counts["laser"]["traceback"] == 3 and tally.counts["laser"]["no recovery"] == 1
    assert tally.failures() == 4
