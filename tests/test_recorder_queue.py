"""The recorder's queue: a bad block is refused whole, and a flush whose thread cannot start is written anyway."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from bench.storage import recorder
from bench.storage.runfile import open_run

RATE = 1000.0


class _Unconvertible:
    """A column value whose conversion to an array raises (a driver's bad reading)."""

    def __array__(self, *args: object, **kwargs: object) -> np.ndarray:
        raise TypeError("no array of this")


def _recorder(path: Path, flush_interval: float = 60.0) -> recorder.Recorder:
    cols = [recorder.Column("voltage", "V", ""), recorder.Column("current", "A", "")]
    return recorder.Recorder(path, {"protocol_name": "queue"}, {"amplifier": cols}, [], {"amplifier": RATE},
                             flush_interval=flush_interval)


@pytest.mark.parametrize("bad", [
    {"voltage": np.zeros(10), "current": np.zeros(10), "charge": np.zeros(10)},  # a column the stream has not
    {"voltage": np.zeros(10), "current": np.zeros(9)},  # one value short
    {"voltage": np.zeros(10), "current": _Unconvertible()},  # the conversion fails half-way through the block
    {"voltage": np.zeros(10)},  # a column missing
], ids=["unknown-column", "short-column", "bad-values", "missing-column"])
def test_a_bad_block_is_refused_whole_and_the_stream_records_on(tmp_path: Path, bad: dict) -> None:
    path = tmp_path / "run.h5"
    rec = _recorder(path)
    t = np.arange(20) / RATE
    rec.append("amplifier", t[:10], voltage=t[:10], current=-t[:10])
    with pytest.raises((ValueError, TypeError)):
        rec.append("amplifier", t[10:], **bad)
    rec.append("amplifier", t[10:], voltage=t[10:], current=-t[10:])
    rec.finish("completed", "ok")
    amp = open_run(path).streams["amplifier"]
    np.testing.assert_array_equal(amp.t, t)
    np.testing.assert_array_equal(amp.columns["voltage"], t)
    np.testing.assert_array_equal(amp.columns["current"], -t)


class _NoThread(threading.Thread):
    def start(self) -> None:
        raise RuntimeError("can't start new thread")


def test_an_interval_flush_whose_thread_cannot_start_is_written_on_the_callers_thread(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "run.h5"
    rec = _recorder(path, flush_interval=0.0)  # every append flushes
    monkeypatch.setattr(recorder.threading, "Thread", _NoThread)
    t = np.arange(300) / RATE
    for k in range(3):
        part = t[k * 100:(k + 1) * 100]
        rec.append("amplifier", part, voltage=part, current=-part)
        assert rec.samples_written == (k + 1) * 100  # on disk already: not lost with the thread
    monkeypatch.undo()
    rec.finish("completed", "ok")
    amp = open_run(path).streams["amplifier"]
    np.testing.assert_array_equal(amp.t, t)
    np.testing.assert_array_equal(amp.columns["current"], -t)


def test_a_stream_with_eight_chunks_queued_is_written_at_once_in_whole_chunks(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Faster than real time the flush interval alone left a short run's whole file to its end: a stream with
    FLUSH_CHUNKS (8 here) chunks queued is written at once, every stream up to its last chunk boundary (no partial
    chunk written, so none rewritten), the rest at the finish. Chunks are 0.25 s of a stream, at least 256 samples:
    256 at 1 kHz, 1000 at 4 kHz. Writes on the caller's thread (no thread to be had), so their order is fixed."""
    monkeypatch.setattr(recorder, "FLUSH_CHUNKS", 8)
    path = tmp_path / "run.h5"
    cols = [recorder.Column("voltage", "V", "")]
    rec = recorder.Recorder(path, {"protocol_name": "chunks"}, {"amplifier": cols, "laser": cols}, [],
                            {"amplifier": 1000.0, "laser": 4000.0}, flush_interval=3600.0)
    writes: list[dict[str, int]] = []
    write = recorder.Recorder._write
    monkeypatch.setattr(recorder.Recorder, "_write",
                        lambda self, work: (writes.append({s: n for _, s, _, n in work[0]}), write(self, work))[1])
    amp_t, laser_t = np.arange(14 * 300) / 1000.0, np.arange(14 * 700) / 4000.0
    with monkeypatch.context() as m:
        m.setattr(recorder.threading, "Thread", _NoThread)
        for k in range(14):  # 300 amplifier and 700 laser samples a step
            rec.append("amplifier", amp_t[k * 300:(k + 1) * 300], voltage=-amp_t[k * 300:(k + 1) * 300])
            rec.append("laser", laser_t[k * 700:(k + 1) * 700], voltage=laser_t[k * 700:(k + 1) * 700])
    rec.finish("completed", "ok")
    # step 7's amplifier block makes 2100 ≥ 8 × 256 queued: 2048 of them written, and of the laser's 4200 the
    # 4000 up to its 4th chunk boundary; step 14's makes 52 + 2100 ≥ 2048 again: to 4096 (2048) and to 9000 (5000)
    assert writes == [{"amplifier": 2048, "laser": 4000}, {"amplifier": 2048, "laser": 5000},
                      {"amplifier": 104, "laser": 800}]
    run = open_run(path)
    np.testing.assert_array_equal(run.streams["amplifier"].t, amp_t)
    np.testing.assert_array_equal(run.streams["amplifier"].columns["voltage"], -amp_t)
    np.testing.assert_array_equal(run.streams["laser"].t, laser_t)
    np.testing.assert_array_equal(run.streams["laser"].columns["voltage"], laser_t)
    assert run.updated == max(amp_t[-1], laser_t[-1])  # the last sample's rig time
