"""The end-of-run stamp: a full disk there loses nothing, and `bench recover` releases the file an earlier version
left unreadable there (its root object header pointing at attribute storage that never reached the disk).

The file-size limit (RLIMIT_FSIZE, soft only: the hard limit stays, so it can be lifted again) stands in for a full
disk from the moment the file is reopened for the stamp; the writes happen in this process (no HDF5 crash is
expected any more; tests/test_storage.py keeps the child-process check of the failure path).
"""

from __future__ import annotations

import contextlib
import os
import resource
from collections.abc import Callable, Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from bench.storage import recorder
from bench.storage.recover import recover
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


def _broken_at_the_stamp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, extra_attrs: int = 15) -> Path:
    """``old.h5`` as the old stamp left it (``old_style`` in force): the disk full 100 bytes past the file at the
    end stamp's reopen, the root attributes unreadable."""
    path = tmp_path / "old.h5"
    rec = _record(path, extra_attrs)
    with _disk_full_at_reopen(monkeypatch, 100), pytest.raises(recorder.StorageError):
        rec.finish("completed", "protocol completed")
    return path


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


def _old_stamp(f: h5py.File, end: str, state: str, reason: str) -> None:
    """How versions before the placeholders stamped the end: new root attributes (new space in the file)."""
    f.attrs["end_time"] = end
    f.attrs["exit_status"] = state
    f.attrs["exit_reason"] = reason
    f.attrs["complete"] = True


@pytest.fixture
def old_style(monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Make the recorder write files as earlier versions did: no stamp placeholders, the stamp added at the end."""
    def apply() -> None:
        monkeypatch.setattr(recorder.Recorder, "_create_stamp", staticmethod(lambda f: None), raising=False)
        monkeypatch.setattr(recorder, "stamp", _old_stamp, raising=False)  # (absent before the placeholders)
    return apply


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


READER = """
import sys
from pathlib import Path
from bench.storage.runfile import open_h5
f = open_h5(Path(sys.argv[1]))  # as bench watch's follower opens it: an SWMR reader, kept open
print(f["status/state"][0].decode(), flush=True)
sys.stdin.read()  # held open until the test closes stdin
f["status/state"].refresh()
print(f["status/state"][0].decode(), flush=True)
"""


def test_a_reader_holding_the_file_open_does_not_keep_the_end_unstamped(tmp_path: Path) -> None:
    """A reader in another process (bench run --web's page server) holds HDF5's shared file lock while the run ends;
    the reopen for the stamp, refused with EAGAIN until then (CI, 2026-11-27), stamps the file complete."""
    import subprocess
    import sys

    path = tmp_path / "run.h5"
    rec = _record(path)
    root = Path(__file__).resolve().parents[1]
    reader = subprocess.Popen([sys.executable, "-c", READER, str(path)], cwd=root, stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "running", reader.stderr
        with open("/proc/locks", encoding="ascii") as locks:  # the lock the reader holds (Linux): what the writer meets
            assert f":{os.stat(path).st_ino} " in locks.read()
        rec.finish("completed", "protocol completed")
        out, err = reader.communicate("", timeout=60)  # the reader, still open, reads the final state
    finally:
        reader.kill()
    assert reader.returncode == 0 and out.strip() == "completed", err
    run = open_run(path)
    assert run.complete and run.state == "completed" and run.attrs["exit_status"] == "completed"
    assert run.attrs["exit_reason"] == "protocol completed"
    _check_samples(path)


@pytest.mark.parametrize("extra_attrs", [0, 15], ids=["compact-root-attrs", "dense-root-attrs"])
def test_recover_releases_the_file_an_earlier_version_broke_at_the_stamp(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, old_style: Callable[[], None], extra_attrs: int) -> None:
    """The old stamp, run out of space 100 bytes past the file, left the root attributes unreadable (and the file
    marked open): recover identifies the run by its structure, rebuilds the root from /status, keeps every sample."""
    old_style()
    path = tmp_path / "old.h5"
    rec = _record(path, extra_attrs)
    with _disk_full_at_reopen(monkeypatch, 100), pytest.raises(recorder.StorageError) as err:
        rec.finish("completed", "protocol completed")
    assert str(err.value).startswith(f"run file {path}: cannot stamp the end of the run") and "\n" not in str(err.value)
    with pytest.raises(ValueError) as unreadable:  # what the earlier version left
        open_run(path)
    assert str(unreadable.value).startswith(f"run file {path}: its root attributes are unreadable")
    assert str(unreadable.value).endswith("`bench recover` rebuilds them") and "\n" not in str(unreadable.value)
    report = recover(path)
    assert report.state == "completed" and report.samples == {"amplifier": N}
    with h5py.File(path, "r") as f:  # every HDF5 tool opens it again
        assert f.attrs["format"] == recorder.FORMAT and f.attrs["exit_status"] == "completed"
    run = open_run(path)
    assert run.state == "completed" and run.reason.startswith("protocol completed | recovered")
    assert not run.complete and "finished (completed) but not finalised" in run.incomplete_reason
    if extra_attrs:  # in dense storage already: what could still be read one by one is written back
        assert run.attrs["protocol_text"] == "x" * 5000 and run.attrs["start_time"].startswith("20")
        assert [run.attrs[f"meta{i}"] for i in range(extra_attrs)] == [f"v{i}" for i in range(extra_attrs)]
    else:  # the stamp's four attributes moved the root's into dense storage that never reached the disk: none left
        assert "protocol_text" not in run.attrs and any("0 of them read one by one" in a for a in report.actions)
    _check_samples(path)


def test_a_recover_stopped_half_way_leaves_a_file_the_next_recover_finishes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, old_style: Callable[[], None]) -> None:
    """Ctrl-C after the root attributes were dropped and before they were rebuilt (in the copy the rebuild works on):
    the file is as it was, names the cure in one line, and the next `bench recover` rebuilds the root from /status,
    every sample kept."""
    from bench.storage import recover as recover_module

    old_style()
    path = _broken_at_the_stamp(tmp_path, monkeypatch)

    def interrupted(*args: object) -> list[str]:
        raise KeyboardInterrupt

    before = path.read_bytes()
    with monkeypatch.context() as m:
        m.setattr(recover_module, "_rebuild_root", interrupted)
        with pytest.raises(KeyboardInterrupt):
            recover(path)
    # the rebuild works on a copy: the file is as it was, no copy left behind
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["old.h5"]
    with pytest.raises(ValueError) as half:
        open_run(path)
    assert str(half.value).startswith(f"run file {path}: its root attributes are unreadable")
    report = recover(path)
    assert report.state == "completed" and report.samples == {"amplifier": N}
    run = open_run(path)
    assert run.attrs["format"] == recorder.FORMAT and run.attrs["exit_status"] == "completed"
    _check_samples(path)


def test_a_recover_that_fails_on_damage_it_cannot_rebuild_leaves_the_file_as_it_was(tmp_path: Path) -> None:
    """An outside tester overwrote bytes of a run file's global heap (its root attributes' strings): recover patched
    the file, then failed in HDF5 ("bad global heap collection signature") and left it worse — marked open for
    write, refused by plain h5py. The rebuild works on a copy: a failure leaves the file byte for byte as it was,
    one line saying so, and no copy behind."""
    path = tmp_path / "run.h5"
    _record(path).finish("completed", "protocol completed")
    data = bytearray(path.read_bytes())
    at = data.index(b"GCOL")  # HDF5 file format spec, III.E "Global Heap": the collection's signature
    data[at:at + 4] = b"XXXX"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError) as unreadable:
        open_run(path)
    assert "root attributes are unreadable" in str(unreadable.value)
    with pytest.raises(ValueError) as failed:
        recover(path)
    assert str(failed.value).startswith(f"run file {path}: ") and "\n" not in str(failed.value)
    assert str(failed.value).endswith("(nothing was changed: the damage is beyond what recover rebuilds)")
    assert path.read_bytes() == bytes(data) and sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]


def test_a_rebuilt_file_keeps_its_permissions_and_a_link_to_it_stays_a_link(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, old_style: Callable[[], None]) -> None:
    """The rebuild replaces the file with its copy (a reviewer: the copy took the umask's mode, 0440 became 0644,
    and a symbolic link became a plain file while the file it named stayed damaged); a Ctrl-C during the copy left a
    partial copy behind."""
    from bench.storage import recover as recover_module

    old_style()
    path = _broken_at_the_stamp(tmp_path, monkeypatch)
    before = path.read_bytes()
    link = tmp_path / "link.h5"
    link.symlink_to(path)
    with monkeypatch.context() as m:  # interrupted while copying: nothing left behind, nothing changed
        def interrupted(*args: object, **kwargs: object) -> None:
            raise KeyboardInterrupt

        m.setattr(recover_module.shutil, "copy2", interrupted)
        with pytest.raises(KeyboardInterrupt):
            recover(link)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["link.h5", "old.h5"]
    path.chmod(0o640)
    report = recover(link)
    assert report.state == "completed"
    assert link.is_symlink() and (path.stat().st_mode & 0o777) == 0o640
    assert open_run(path).attrs["exit_status"] == "completed"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.h5", "old.h5"]


@pytest.mark.parametrize("lookalike", [False, True], ids=["other-structure", "status-events-program-groups"])
def test_recover_refuses_another_programs_file_with_unreadable_root_attributes(tmp_path: Path,
                                                                               lookalike: bool) -> None:
    """Broken the same way but without a run's structure — also one with groups named as a run's (/status with its
    four datasets, /events, /program) but not a run's program: one line, and the file is left as it was."""
    path = tmp_path / "other.h5"
    with h5py.File(path, "w", libver=("v110", "v110")) as f:
        f["x"] = np.arange(3)
        if lookalike:
            for k in ("state", "reason", "end_time", "updated"):
                f[f"status/{k}"] = np.array([b"running"])
            f.create_group("events")
            f["program/steps"] = np.arange(3)
        for i in range(6):
            f.attrs[f"a{i}"] = "v" * 50
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    recorder.ignore_sigxfsz()
    g = h5py.File(path, "r+")
    fd = int(g.id.get_vfd_handle())
    resource.setrlimit(resource.RLIMIT_FSIZE, (path.stat().st_size + 100, hard))
    try:
        for i in range(6, 12):
            g.attrs[f"a{i}"] = "w" * 50
        g.close()
    except Exception:
        recorder.abandon(g, fd)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    before = path.read_bytes()
    with pytest.raises(ValueError) as err:
        recover(path)
    assert str(err.value).startswith(f"run file {path}: not a") and "\n" not in str(err.value)
    assert path.read_bytes() == before


def test_a_file_of_an_earlier_version_without_placeholders_still_reads(
        tmp_path: Path, old_style: Callable[[], None]) -> None:
    old_style()
    path = tmp_path / "old.h5"
    _record(path).finish("completed", "protocol completed")
    with h5py.File(path, "r") as f:
        assert isinstance(f.attrs["exit_status"], str)  # variable-length, as earlier versions wrote it
    run = open_run(path)
    assert run.complete and run.attrs["exit_status"] == "completed" and run.attrs["exit_reason"] == "protocol completed"
    _check_samples(path)
    assert recover(path).actions == []
