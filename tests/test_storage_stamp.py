"""The end-of-run stamp: a full disk there loses nothing.

The file-size limit (RLIMIT_FSIZE, soft only: the hard limit stays, so it can be lifted again) stands in for a full
disk from the moment the file is reopened for the stamp; the writes happen in this process (no HDF5 crash is
expected any more; tests/test_storage.py keeps the child-process check of the failure path).
"""

from __future__ import annotations

import contextlib
import os
import resource
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from bench.storage import recorder
from bench.storage.runfile import open_run

RATE = 1000.0  # Hz: sample k is recorded at k / RATE s with voltage = sin(t)
N = 2000


def _record(path: Path, extra_attrs: int = 0) -> recorder.Recorder:
    """A run file with N amplifier samples (flushed in blocks), not yet finished."""
    attrs = {"start_time": recorder.now_iso(), "protocol_text": "x" * 5000,
             **{f"meta{i}": f"v{i}" for i in range(extra_attrs)}}
    rec = recorder.Recorder(path, attrs, {"amplifier": [recorder.Column("voltage", "V", "")]},
                            [(0, "a", "a", "hold", 0.0, 1.0)], {"amplifier": RATE})
    for b in range(0, N, 500):
        t = np.arange(b, b + 500) / RATE
        rec.append("amplifier", t, voltage=np.sin(t))
        rec.flush()
    return rec


@contextlib.contextmanager
def _disk_full_at_reopen(monkeypatch: pytest.MonkeyPatch, margin: int) -> Iterator[None]:
    """From the reopen of the file for the stamp (mode r+), no write may reach past its size + ``margin`` bytes."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    opener = h5py.File

    def reopen(path: object, mode: str = "r", *args: object, **kwargs: object) -> h5py.File:
        if mode == "r+":
            resource.setrlimit(resource.RLIMIT_FSIZE, (os.path.getsize(str(path)) + margin, hard))
        return opener(path, mode, *args, **kwargs)

    monkeypatch.setattr(recorder.h5py, "File", reopen)
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        monkeypatch.setattr(recorder.h5py, "File", opener)


def _check_samples(path: Path) -> None:
    run = open_run(path)
    t = np.arange(N) / RATE  # what _record wrote, computed here anew
    np.testing.assert_array_equal(run.streams["amplifier"].t, t)
    np.testing.assert_array_equal(run.streams["amplifier"].columns["voltage"], np.sin(t))


def test_a_disk_full_from_the_reopen_on_still_stamps_the_run_complete(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The stamp overwrites placeholders made with the file: not one byte more is needed (limit = the size)."""
    path = tmp_path / "run.h5"
    rec = _record(path)
    with _disk_full_at_reopen(monkeypatch, 0):
        rec.finish("completed", "protocol completed")
    run = open_run(path)
    assert run.complete and run.state == "completed" and run.attrs["exit_status"] == "completed"
    assert run.attrs["exit_reason"] == "protocol completed" and run.attrs["end_time"] == run.end_time != ""
    _check_samples(path)


def test_the_stamp_is_empty_while_the_run_goes_on_and_cut_like_the_status(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    rec = _record(path)
    running = open_run(path)
    assert not running.complete and running.state == "running" and "no end recorded" in running.incomplete_reason
    assert (running.attrs["end_time"], running.attrs["exit_status"], running.attrs["exit_reason"]) == ("", "", "")
    rec.finish("error", "ü" * 300)  # 600 bytes of UTF-8: /status/reason and the stamp keep 400, whole characters
    run = open_run(path)
    assert run.complete and run.attrs["exit_reason"] == run.reason == "ü" * 200
