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


def _two_streams(path: Path, name: str, laser_hz: float, virtual: bool = False) -> recorder.Recorder:
    """A recorder of one voltage column on an amplifier stream at 1 kHz and a laser stream at ``laser_hz``, with no
    timed flush: only chunk counts and the finish write."""
    cols = [recorder.Column("voltage", "V", "")]
    return recorder.Recorder(path, {"protocol_name": name}, {"amplifier": cols, "laser": cols}, [],
                             {"amplifier": 1000.0, "laser": laser_hz}, flush_interval=3600.0, virtual=virtual)


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
    monkeypatch.setattr(recorder, "QUEUED_MAX_S", np.inf)  # the chunk count alone (the rig-time rule: below)
    path = tmp_path / "run.h5"
    rec = _two_streams(path, "chunks", 4000.0)
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


def test_a_stream_whose_queue_spans_queued_max_s_of_rig_time_is_written_at_once_in_whole_chunks(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Faster than real time FLUSH_CHUNKS chunks (4 s of a stream) waited for their write, and a storage fault was
    found only then: a stream whose queued samples span QUEUED_MAX_S (1 s) of the run clock is written at once, its
    whole chunks (256 samples at 1 kHz), the tail left queued. No timed flush; writes on the caller's thread."""
    path = tmp_path / "run.h5"
    rec = _two_streams(path, "span", 4000.0)
    works = _spy_on_writes(monkeypatch)
    t = np.arange(1200) / 1000.0
    with monkeypatch.context() as m:
        m.setattr(recorder.threading, "Thread", _NoThread)
        rec.append("amplifier", t[:900], voltage=t[:900])  # 0.899 s queued: nothing yet
        rec.append("amplifier", t[900:1000], voltage=t[900:1000])  # 0.999 s
        assert works == []
        rec.append("amplifier", t[1000:], voltage=t[1000:])  # 1.199 s ≥ 1 s: 4 whole chunks (1024) written
        assert works == [({"amplifier": 1024}, 0, 0.0)]
    rec.finish("completed", "ok")
    np.testing.assert_array_equal(open_run(path).streams["amplifier"].t, t)


def _spy_on_writes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[dict[str, int], int, float]]:
    """Each write the recorder makes, as (samples per stream, events, valid-up-to time), in order."""
    works: list[tuple[dict[str, int], int, float]] = []
    write = recorder.Recorder._write

    def spy(self: recorder.Recorder, work: recorder._Work) -> None:
        blocks, events, last_t = work
        works.append(({s: n for _, s, _, n in blocks}, 0 if events is None else events.size, last_t))
        write(self, work)

    monkeypatch.setattr(recorder.Recorder, "_write", spy)
    return works


def test_a_whole_chunk_write_takes_no_event_and_no_valid_time_ahead_of_another_stream_s_tail(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A write of whole chunks leaves each stream's tail queued, so it must leave the events (a step's end) and the
    valid-up-to time queued too: a kill after it would otherwise leave a step ended on disk without its last
    samples, and resume would never rerun it (review finding). Laser: step 0's 1000 samples at 1 kHz (3 chunks of
    256 and 232 queued), its end, then the amplifier reaching FLUSH_CHUNKS (8) chunks: 2048 of 2100 written, the
    laser's first 768, no event, the valid time still 0; the finish writes the rest with both events."""
    monkeypatch.setattr(recorder, "FLUSH_CHUNKS", 8)
    path = tmp_path / "run.h5"
    rec = _two_streams(path, "events", 1000.0)
    works = _spy_on_writes(monkeypatch)
    laser_t, amp_t = np.arange(1000) / 1000.0, np.arange(2100) / 1000.0
    with monkeypatch.context() as m:
        m.setattr(recorder.threading, "Thread", _NoThread)
        rec.event(0.0, 0, "start", "drive")
        rec.append("laser", laser_t, voltage=laser_t)
        rec.event(1.0, 0, "end", "drive")
        rec.append("amplifier", amp_t, voltage=amp_t)
        assert works == [({"amplifier": 2048, "laser": 768}, 0, 0.0)]
        assert open_run(path).completed_steps() == set()  # what a reader (or a kill) finds now
    rec.finish("completed", "ok")
    assert works[1] == ({"amplifier": 52, "laser": 232}, 2, amp_t[-1])
    run = open_run(path)
    assert run.completed_steps() == {0}
    np.testing.assert_array_equal(run.streams["laser"].t, laser_t)


def test_a_stat_that_fails_after_the_stamp_leaves_the_finished_file_and_other_descriptors_alone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The file is stamped and closed when the recorder asks for its size and time (for the catalogue's end row):
    a stat failing then (the file moved, a network share) must neither abandon the closed file's descriptor
    number — by then it may be another open's — nor report the complete run as a storage fault; the end row then
    reads the file (``written()`` None) (review finding)."""
    path = tmp_path / "run.h5"
    rec = _recorder(path)
    rec.append("amplifier", np.arange(5) / RATE, voltage=np.zeros(5), current=np.zeros(5))
    abandoned: list[object] = []
    monkeypatch.setattr(recorder, "abandon", lambda *a: abandoned.append(a))
    real_stat = recorder.os.stat

    def stat(p: object, *a: object, **k: object) -> object:
        if Path(str(p)) == path and rec._f is None:  # once the file is stamped and closed (while it is written, each
            raise FileNotFoundError(2, "No such file or directory", str(p))  # flush checks it is still at its path)
        return real_stat(p, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(recorder.os, "stat", stat)
    rec.finish("completed", "ok")
    monkeypatch.setattr(recorder.os, "stat", real_stat)
    assert abandoned == [] and not rec.failure and rec.written() is None
    run = open_run(path)
    assert run.state == "completed" and run.complete


def test_write_ahead_writes_the_whole_chunks_queued_from_its_minimum_and_nothing_ahead_of_a_tail(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A step's or the run's end writes ahead of FLUSH_CHUNKS (16, none reached here): every stream's whole chunks
    once one stream has ``min_chunks`` of them and would not reach FLUSH_CHUNKS in the time still to come, its
    tail, the events and the valid-up-to time left queued, as a write of whole chunks does; the finish writes the
    rest. Chunks: 256 samples at 1 kHz, 1000 at 4 kHz. Writes on
    the caller's thread (no thread to be had), so their order is fixed."""
    monkeypatch.setattr(recorder, "QUEUED_MAX_S", np.inf)  # write_ahead's rule alone (the rig-time rule: below)
    path = tmp_path / "run.h5"
    rec = _two_streams(path, "ahead", 4000.0)
    works = _spy_on_writes(monkeypatch)
    amp_t, laser_t = np.arange(1100) / 1000.0, np.arange(4000) / 4000.0
    with monkeypatch.context() as m:
        m.setattr(recorder.threading, "Thread", _NoThread)
        rec.event(0.0, 0, "start", "drive")
        rec.append("amplifier", amp_t[:1000], voltage=-amp_t[:1000])  # 3 whole chunks of 256
        rec.append("laser", laser_t[:2500], voltage=laser_t[:2500])  # 2 whole chunks of 1000
        rec.write_ahead(4)
        assert works == []  # no stream has 4 whole chunks
        rec.append("amplifier", amp_t[1000:], voltage=-amp_t[1000:])  # 1100: 4 whole chunks
        rec.event(1.1, 0, "end", "drive")
        rec.write_ahead(4, remaining_s=3.0)  # 1100 + 3 s at 1 kHz reach 16 × 256: a FLUSH_CHUNKS write comes first
        assert works == []
        rec.write_ahead(4, remaining_s=2.9)  # 1100 + 2900 < 4096: none would come before the end
        assert works == [({"amplifier": 1024, "laser": 2000}, 0, 0.0)]  # the laser's 2 as well; tails stay
        assert open_run(path).completed_steps() == set()
        rec.write_ahead(4)
        rec.append("laser", laser_t[2500:], voltage=laser_t[2500:])  # 500 + 1500 queued: 2 whole chunks
        rec.write_ahead(4)
        assert len(works) == 1
        rec.write_ahead()  # the run's end: from one whole chunk
        assert works[1:] == [({"laser": 2000}, 0, 0.0)]
    rec.finish("completed", "ok")
    assert works[2:] == [({"amplifier": 76}, 2, amp_t[-1])]
    run = open_run(path)
    assert run.completed_steps() == {0}
    np.testing.assert_array_equal(run.streams["amplifier"].t, amp_t)
    np.testing.assert_array_equal(run.streams["amplifier"].columns["voltage"], -amp_t)
    np.testing.assert_array_equal(run.streams["laser"].t, laser_t)
    np.testing.assert_array_equal(run.streams["laser"].columns["voltage"], laser_t)


def test_write_ahead_during_a_write_under_way_writes_once_that_one_has_finished(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A step's end that finds the previous write still under way (a loaded host) is not lost: its whole chunks go
    at the first recorder call after that write, not at FLUSH_CHUNKS (16) chunks or at the finish."""
    path = tmp_path / "run.h5"
    rec = _recorder(path, flush_interval=3600.0)  # 1 kHz: chunks of 256
    sizes: list[int] = []
    write = recorder.Recorder._write
    monkeypatch.setattr(recorder.Recorder, "_write",
                        lambda self, work: (sizes.extend(n for _, _, _, n in work[0]), write(self, work))[1])
    release = threading.Event()
    under_way = threading.Thread(target=release.wait)
    under_way.start()
    rec._writing = under_way  # the previous write, still going
    t = np.arange(1100) / RATE
    with monkeypatch.context() as m:
        m.setattr(recorder.threading, "Thread", _NoThread)
        rec.append("amplifier", t[:1000], voltage=t[:1000], current=-t[:1000])  # 3 whole chunks
        rec.write_ahead(3)
        assert sizes == []  # waits for the write under way
        release.set()
        under_way.join()
        rec.append("amplifier", t[1000:], voltage=t[1000:], current=-t[1000:])  # 1100 queued: 4 whole chunks
        assert sizes == [1024]
    rec.finish("completed", "ok")
    assert sizes == [1024, 76]
    np.testing.assert_array_equal(open_run(path).streams["amplifier"].t, t)


@pytest.mark.parametrize("values", [
    0.25, np.float64(0.25), np.float32(0.25), np.array(0.25), [0.25, 0.5], np.arange(3.0),
    np.arange(3, dtype=np.float32), np.arange(3, dtype=np.uint8), np.arange(6.0).reshape(2, 3)[:, 1], np.zeros(0),
    np.arange(4.0)[::-1],
], ids=["float", "f8-scalar", "f4-scalar", "0-d", "list", "f8", "f4", "u1", "strided", "empty", "reversed"])
@pytest.mark.parametrize("dtype", [None, float], ids=["column", "time"])
def test_samples_are_what_numpy_makes_of_them(values: object, dtype: type | None) -> None:
    """Each form a value may come in (a poll's float, numpy scalars, a DAQ block's column, arrays of another type): the
    queued array is numpy's ``atleast_1d(asarray(values, dtype))``, its type, shape and values."""
    got = recorder._samples(values, dtype)  # type: ignore[arg-type]
    want = np.atleast_1d(np.asarray(values, dtype=dtype))
    assert got.dtype == want.dtype and got.shape == want.shape
    np.testing.assert_array_equal(got, want)


def test_a_file_whose_making_fails_is_removed_and_one_already_there_is_kept(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk filling while the file's layout is written left a half-made .h5 that readers then called damaged
    (found in review): the recorder made it ("w-"), so it removes it; a file already at the path is refused in one
    line and kept as it was."""
    import errno

    def full(self: recorder.Recorder, f: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    path = tmp_path / "run.h5"
    monkeypatch.setattr(recorder.Recorder, "_create_stamp", full)
    with pytest.raises(recorder.StorageError, match="cannot create: No space left on device"):
        _recorder(path)
    assert not path.exists()
    monkeypatch.undo()
    path.write_bytes(b"another run's file")
    with pytest.raises(recorder.StorageError, match="exists: a run file is never overwritten"):
        _recorder(path)
    assert path.read_bytes() == b"another run's file"


@pytest.mark.parametrize("state", ["running", "tripped"])
def test_a_storage_fault_marks_the_reason_only_of_a_run_without_an_end_state(tmp_path: Path, state: str) -> None:
    """A write failure marks "storage fault: …" in /status/reason, so readers do not call the file crashed; but once
    an end state is on disk (a trip and its cause) a fault at the final close kept the state and replaced the
    cause, and the report said "run tripped: storage fault" (found in review). The cause stays now."""
    import errno

    import h5py

    path = tmp_path / "run.h5"
    rec = _recorder(path)
    rec.append("amplifier", np.arange(5) / RATE, voltage=np.ones(5), current=np.zeros(5))
    rec.set_state(state, "breakdown at 3 kV" if state == "tripped" else "")
    rec._fail("write failed", OSError(errno.ENOSPC, "No space left on device"))  # the close's flush, say
    with h5py.File(path, "r", libver="latest", swmr=True) as f:
        reason = f["status/reason"][0].decode()
    if state == "tripped":
        assert reason == "breakdown at 3 kV"
    else:
        assert reason.startswith("storage fault: run file ") and "No space left on device" in reason


@pytest.mark.parametrize("virtual", [True, False], ids=["virtual", "real-time"])
def test_a_virtual_run_ahead_of_its_writer_by_queued_max_s_waits_for_the_write_under_way(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, virtual: bool) -> None:
    """A write under way let the caller queue on without bound: beside a CPU hog a virtual run's writer fell 2.25 s
    of rig time behind, and a full disk then left 2.25 s unwritten against the stated 1 s + one chunk (CI). Once a
    queue spans QUEUED_MAX_S while a write is under way, a virtual run waits for it (its clock waits too). A
    real-time run never waits: its thread would stall the rig (a reviewer: 2-s writes tripped the host-stall bound
    and latched the rig). The first write (4 chunks, taken at 1.199 s) is held at a gate; 0.5 s more returns (the
    queue spans 0.67 s), a further 0.5 s (1.17 s) must wait until the gate opens — virtual time — or returns at
    once, the samples queued for a later write — real time."""
    path = tmp_path / "run.h5"
    rec = _two_streams(path, "behind", 4000.0, virtual=virtual)
    gate, entered = threading.Event(), threading.Event()
    write = recorder.Recorder._write
    works: list[int] = []

    def slow(self: recorder.Recorder, work: recorder._Work) -> None:
        works.append(sum(n for _, _, _, n in work[0]))
        if len(works) == 1:
            entered.set()
            gate.wait(60.0)
        write(self, work)

    monkeypatch.setattr(recorder.Recorder, "_write", slow)
    t = np.arange(2200) / 1000.0
    rec.append("amplifier", t[:1200], voltage=t[:1200])  # 1.199 s: 1024 samples to the background writer
    assert entered.wait(60.0)
    rec.append("amplifier", t[1200:1700], voltage=t[1200:1700])  # queued 1.024-1.699 s: returns, the write held
    behind = threading.Thread(target=rec.append, args=("amplifier", t[1700:]), kwargs={"voltage": t[1700:]})
    behind.start()
    behind.join(0.5 if virtual else 60.0)
    if virtual:
        assert behind.is_alive(), "the virtual run ran on with its queue spanning over 1 s and a write under way"
        assert works == [1024]
        gate.set()
        behind.join(60.0)
        assert not behind.is_alive() and works == [1024, 1024]  # then 1.024-2.047 s: 4 whole chunks, tail queued
    else:
        assert not behind.is_alive() and works == [1024]  # returned with the write still held: nothing waited
        gate.set()
    rec.finish("completed", "ok")
    np.testing.assert_array_equal(open_run(path).streams["amplifier"].t, t)
