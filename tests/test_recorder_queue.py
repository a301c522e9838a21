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
