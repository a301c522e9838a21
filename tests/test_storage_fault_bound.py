"""A storage fault stops the run within the README's bound (README "Recording": a storage fault), measured as the
order of events on the run clock, not as wall-clock durations: the first write that fails (ENOSPC injected at the
writer), then 0 V commanded at most ``shutdown_ramp_s`` + 0.2 s + one collect later, and the file holds the data up
to at most ``QUEUED_MAX_S`` + one chunk before that write. A virtual-time run (faster than real time) queued up to
FLUSH_CHUNKS chunks (4 s of a stream) before writing: a tester's disk filled and the rig drove on 3.25 s of rig time
past the last data on file."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest

from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from bench.storage import recorder as recmod
from bench.storage.recorder import CHUNK_S, QUEUED_MAX_S
from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
RAMP_S = 0.25  # the rigs' shutdown_ramp_s
STOP_BOUND_S = 0.2  # README "Stopping": the ramp starts within 0.2 s, 0 V within shutdown_ramp_s + 0.2 s
COLLECT_S = 0.05  # the run's recorder calls (a DAQ rig's collects; the monitors' polls are no slower here)


@pytest.mark.parametrize("rig", ["thesis-daq-sim", "thesis-sim"])
def test_a_full_disk_stops_the_run_within_the_bound_after_the_first_failed_write(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rig: str) -> None:
    failed: list[float] = []  # run times at which the writes that failed were taken (the caller's thread)
    starts: list[float] = []  # the first sample time of each failed write's data
    now: list = []
    taken: dict[int, float] = {}  # id(work) → the run time it was taken at (the engine's thread: deterministic)
    real_take, real_write = recmod.Recorder._take, recmod.Recorder._write

    def take(self: recmod.Recorder, whole_chunks: bool = False) -> recmod._Work:
        work = real_take(self, whole_chunks)
        taken[id(work)] = now[0]() if now else -1.0
        return work

    def write(self: recmod.Recorder, work: recmod._Work) -> None:
        # the disk is full for every write taken from run time 4 s on (decided where the work was taken, not where
        # the background thread ran it: under load that thread runs late, and a virtual clock does not wait for it)
        t = taken.get(id(work), -1.0)
        if t >= 4.0 or failed:
            failed.append(t)
            starts.extend(float(data["t"][0]) for _, _, data, n in work[0] if n)
            raise OSError(errno.ENOSPC, "No space left on device")
        real_write(self, work)

    def hook(engine: Engine, _sim) -> None:
        now.append(engine.now)

    monkeypatch.setattr(recmod.Recorder, "_take", take)
    monkeypatch.setattr(recmod.Recorder, "_write", write)
    result = execute(plan_run(SWEEPS, ROOT / "rigs" / f"{rig}.toml"), tmp_path / "run.h5", virtual=True,
                     on_engine=hook)
    assert result.state == "error" and "storage fault" in result.reason and "No space left" in result.reason
    first = failed[0]
    zero_at = float(result.safe_path.split(" at ")[1].split(" s")[0])  # "0 V commanded by the host at T s …"
    assert first <= zero_at <= first + COLLECT_S + RAMP_S + STOP_BOUND_S, (first, zero_at)
    if rig != "thesis-daq-sim":
        return  # the laser's storage is fetched by its own poll (its data wait in the device), the monitors are slow
    run = open_run(result.path)
    for name in ("amplifier", "laser"):  # the scan clock's streams, 10 kHz: written in whole chunks
        t = run.streams[name].t
        assert t[-1] >= first - QUEUED_MAX_S - CHUNK_S - COLLECT_S, (name, t[-1], first)
        assert np.all(np.diff(t) > 0)
    assert min(starts) >= first - QUEUED_MAX_S - CHUNK_S - COLLECT_S  # what the failed write held: its queue's span
