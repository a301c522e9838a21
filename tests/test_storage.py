"""Storage faults (file-size limit, disk full, unwritable folder) and kill -9: the run file stays readable up
to its last flush, never shows zero-filled records as data, and `bench recover` releases a killed run's file.

Writers run in subprocesses: a failing HDF5 write used to end in a segfault, which must not take pytest along.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from bench.storage.runfile import open_run
from bench.storage.superblock import hashlittle
from tests.conftest import ROOT

RATE = 1000.0  # Hz: the test writers stamp sample k at k / RATE s and record displacement = t * 1e-3 m
BLOCK = 500  # samples per flush in the fault writer

FAULT_WRITER = textwrap.dedent(f"""
    import json, sys
    from pathlib import Path
    import numpy as np
    from bench.storage.recorder import Column, Recorder, StorageError
    rec = Recorder(Path(sys.argv[1]), {{"protocol_name": "storage test"}},
                   {{"laser": [Column("displacement", "m", "")]}}, [], {{"laser": {RATE}}})
    confirmed, errors = 0, []
    try:
        for b in range(100_000):
            t = (b * {BLOCK} + np.arange({BLOCK})) / {RATE}
            rec.append("laser", t, displacement=t * 1e-3)
            rec.event(float(t[-1]), b, "block", "x" * 150)
            rec.flush()
            confirmed += {BLOCK}
    except StorageError as exc:
        errors.append(str(exc))
    for call in (lambda: rec.append("laser", 0.0, displacement=0.0), lambda: rec.event(0.0, 0, "k", "t"),
                 rec.flush, rec.maybe_flush, lambda: rec.set_state("error", "x"), lambda: rec.finish("error", "x")):
        try:
            call()
        except Exception as exc:  # every call after the failure must be a quiet no-op
            errors.append(f"{{type(exc).__name__}}: {{exc}}")
    print(json.dumps({{"confirmed": confirmed, "errors": errors}}))
""")

KILL_WRITER = textwrap.dedent(f"""
    import sys, time
    from pathlib import Path
    import numpy as np
    from bench.storage.recorder import Column, Recorder
    t0 = float(sys.argv[2])  # time.monotonic() of the parent at the start: one clock for both processes
    rec = Recorder(Path(sys.argv[1]), {{"protocol_name": "kill test"}},
                   {{"laser": [Column("displacement", "m", "")], "amplifier": [Column("voltage", "V", "")]}},
                   [], {{"laser": {RATE}}})
    k = 0
    print("ready", flush=True)
    while True:
        n = int((time.monotonic() - t0) * {RATE}) - k
        if n > 0:
            t = (k + np.arange(n)) / {RATE}
            rec.append("laser", t, displacement=t * 1e-3)
            rec.append("amplifier", t[-1], voltage=1.0)
            k += n
        time.sleep(0.005)  # appends only, never maybe_flush: the recorder keeps to its interval on its own
""")


BACKGROUND_FAULT_WRITER = textwrap.dedent(f"""
    import json, sys
    from pathlib import Path
    import numpy as np
    from bench.storage.recorder import Column, Recorder, StorageError
    rec = Recorder(Path(sys.argv[1]), {{"protocol_name": "storage test"}},
                   {{"laser": [Column("displacement", "m", "")]}}, [], {{"laser": {RATE}}}, flush_interval=0.0)
    errors, blocks = [], 0
    try:  # appends only: every write happens on the recorder's background thread
        for b in range(100_000):
            t = (b * {BLOCK} + np.arange({BLOCK})) / {RATE}
            rec.append("laser", t, displacement=t * 1e-3)
            rec.event(float(t[-1]), b, "block", "x" * 150)
            blocks += 1
    except StorageError as exc:
        errors.append(str(exc))
    for call in (lambda: rec.append("laser", 0.0, displacement=0.0), rec.maybe_flush, rec.flush,
                 lambda: rec.finish("error", "x")):
        try:
            call()
        except Exception as exc:
            errors.append(f"{{type(exc).__name__}}: {{exc}}")
    print(json.dumps({{"blocks": blocks, "errors": errors}}))
""")


def _limit_file_size(limit: int):
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "300"}


def _run_fault_writer(path: Path, preexec=None) -> tuple[subprocess.CompletedProcess, dict]:
    proc = subprocess.run([sys.executable, "-c", FAULT_WRITER, str(path)], capture_output=True, text=True,
                          timeout=120, preexec_fn=preexec, env=_env(), cwd=ROOT)
    assert proc.returncode == 0, f"exit {proc.returncode}: {proc.stderr[-2000:]}"
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr[-2000:]
    return proc, json.loads(proc.stdout.strip().splitlines()[-1])


def _check_known_record(path: Path, confirmed: int) -> None:
    """The file reads exactly the samples whose flush succeeded, each equal to what the writer wrote."""
    run = open_run(path)
    assert not run.complete and run.state == "running"
    laser = run.streams["laser"]
    assert len(laser) == confirmed
    expected_t = np.arange(confirmed) / RATE
    np.testing.assert_array_equal(laser.t, expected_t)
    np.testing.assert_array_equal(laser.columns["displacement"], expected_t * 1e-3)
    assert len(run.events) == confirmed // BLOCK  # one event per confirmed block, none zero-filled
    assert all(e["kind"] == b"block" for e in run.events)


def test_lookup3_matches_the_reference_vectors() -> None:
    """Values printed by the driver in Bob Jenkins' lookup3.c."""
    assert hashlittle(b"") == 0xDEADBEEF
    assert hashlittle(b"Four score and seven years ago") == 0x17770551
    assert hashlittle(b"Four score and seven years ago", 1) == 0xCD628161


def test_file_size_limit_fails_once_cleanly_and_keeps_every_flushed_sample(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    _, out = _run_fault_writer(path, _limit_file_size(300_000))
    assert out["confirmed"] > 0
    assert len(out["errors"]) == 1, out["errors"]  # one StorageError; every later call a no-op
    (message,) = out["errors"]
    assert "\n" not in message and str(path) in message
    assert message.endswith(f"{os.strerror(errno.EFBIG)} (errno {errno.EFBIG})"), message
    _check_known_record(path, out["confirmed"])
    with h5py.File(path, "r", swmr=True) as f:  # beyond the confirmed count the file may hold zero-filled records
        assert f["laser/t"].shape[0] >= out["confirmed"]
    _check_recovers(path, out["confirmed"])


def test_a_failed_background_write_is_raised_once_by_the_next_call_and_the_file_keeps_whole_flushes(
        tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    proc = subprocess.run([sys.executable, "-c", BACKGROUND_FAULT_WRITER, str(path)], capture_output=True,
                          text=True, timeout=120, preexec_fn=_limit_file_size(300_000), env=_env(), cwd=ROOT)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(out["errors"]) == 1, out["errors"]  # raised on the caller's thread once; later calls are no-ops
    assert out["errors"][0].endswith(f"{os.strerror(errno.EFBIG)} (errno {errno.EFBIG})"), out["errors"]
    run = open_run(path)
    laser = run.streams["laser"]
    assert 0 < len(laser) < out["blocks"] * BLOCK and len(laser) % BLOCK == 0  # whole appends only
    np.testing.assert_array_equal(laser.t, np.arange(len(laser)) / RATE)  # each sample as written, none zero-filled
    np.testing.assert_array_equal(laser.columns["displacement"], laser.t * 1e-3)
    # a write takes what was queued: the event of the last block on file may have come after it
    assert len(laser) // BLOCK - 1 <= len(run.events) <= len(laser) // BLOCK
    assert all(e["kind"] == b"block" for e in run.events) and not run.complete and run.state == "running"


def test_an_interval_flush_writes_on_a_background_thread_and_flush_waits_for_it(tmp_path: Path) -> None:
    from bench.storage.recorder import Column, Recorder

    rec = Recorder(tmp_path / "run.h5", {"protocol_name": "background"}, {"laser": [Column("displacement", "m", "")]},
                   [], {"laser": RATE}, flush_interval=0.0)
    gate, write = __import__("threading").Event(), rec._write
    rec._write = lambda work: (gate.wait(10.0), write(work))  # type: ignore[method-assign]
    t = np.arange(BLOCK) / RATE
    rec.append("laser", t, displacement=t * 1e-3)  # the interval has passed: the data goes to the writer …
    writing = rec._writing
    assert writing is not None and writing.is_alive()  # … and append returned while the write waits
    rec._write = write  # type: ignore[method-assign]
    gate.set()
    rec.flush()  # waits for it, then writes what came since (nothing)
    assert not writing.is_alive() and rec.samples_written == BLOCK
    rec.finish("completed", "test")
    np.testing.assert_array_equal(open_run(tmp_path / "run.h5").streams["laser"].t, t)


def test_a_run_file_deleted_while_written_fails_the_next_write(tmp_path: Path) -> None:
    """The run's folder removed under it: the file lives on unlinked and takes every write, so nothing would stop the
    run before its end (found by an exploratory test: a run drove up to 7 kV to its end with nothing recorded). The
    next flush sees the file is no longer in any folder: a storage fault, raised once, naming the cause."""
    from bench.storage.recorder import Column, Recorder, StorageError

    folder = tmp_path / "campaign"
    rec = Recorder(folder / "run.h5", {"protocol_name": "deleted"}, {"laser": [Column("displacement", "m", "")]},
                   [], {"laser": RATE})
    t = np.arange(BLOCK) / RATE
    rec.append("laser", t, displacement=t * 1e-3)
    rec.flush()  # healthy
    shutil.rmtree(folder)
    rec.append("laser", t + 1, displacement=t * 1e-3)
    with pytest.raises(StorageError, match=r"write failed: the file \(or its folder\) was deleted or moved while"):
        rec.flush()
    assert rec.failed
    rec.flush()  # once: later calls are no-ops
    rec.finish("error", "test")


def _check_recovers(path: Path, confirmed: int) -> None:
    """`bench recover` (no size limit now) releases the file for every tool with exactly the confirmed records."""
    res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    assert res.returncode == 0 and f"laser: {confirmed:,} samples" in res.stdout, res.stdout + res.stderr
    with h5py.File(path, "r") as f:
        assert f["laser/t"].shape[0] == f["laser/displacement"].shape[0] == confirmed
        np.testing.assert_array_equal(f["laser/t"][:], np.arange(confirmed) / RATE)
        assert f["events/t"].shape[0] == f["events/text"].shape[0] == confirmed // BLOCK
    if shutil.which("h5dump"):
        dump = subprocess.run(["h5dump", "-H", str(path)], capture_output=True, text=True, timeout=30)
        assert dump.returncode == 0, dump.stderr
    _check_known_record(path, confirmed)


@contextlib.contextmanager
def _tmpfs(where: Path, size: str, options: str = "") -> Iterator[Path]:
    where.mkdir()
    opts = f"size={size}" + (f",{options}" if options else "")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip() or 'mount failed'}): needs root/CAP_SYS_ADMIN")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def test_disk_full_fails_once_cleanly_and_keeps_every_flushed_sample(tmp_path: Path) -> None:
    with _tmpfs(tmp_path / "small", "256k") as disk:
        path = disk / "run.h5"
        _, out = _run_fault_writer(path)
        assert len(out["errors"]) == 1, out["errors"]
        assert str(path) in out["errors"][0]
        assert out["errors"][0].endswith(f"{os.strerror(errno.ENOSPC)} (errno {errno.ENOSPC})"), out["errors"]
        _check_known_record(path, out["confirmed"])
        image = path.read_bytes()
        res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                             timeout=60, cwd=ROOT, env=_env())
        lines = res.stderr.strip().splitlines()  # on the full disk: one line, and the file is left as it was
        assert res.returncode == 2 and len(lines) == 1 and "free some space" in lines[0], res.stdout + res.stderr
        assert path.read_bytes() == image
        moved = shutil.copy(path, tmp_path / "run.h5")  # where there is space
    _check_recovers(Path(moved), out["confirmed"])


@pytest.mark.parametrize("fault", ["disk-full", "file-size-limit"])
def test_a_file_whose_writing_failed_says_why_not_crashed_before_and_after_recover(tmp_path: Path,
                                                                                   fault: str) -> None:
    """Found by an outside tester: a file recovered after its disk filled was described as "the run crashed or was
    killed". The writer marks the failure in /status/reason (in place: no new space), so readers and `bench
    recover` say the disk was full (ENOSPC) — or, for another failure, that writing the file failed, and why."""
    if fault == "disk-full":
        with _tmpfs(tmp_path / "small", "256k") as disk:
            _, out = _run_fault_writer(disk / "run.h5")
            moved = Path(shutil.copy(disk / "run.h5", tmp_path / "run.h5"))  # where there is space to recover
        said, cause = "the disk was full", f"{os.strerror(errno.ENOSPC)} (errno {errno.ENOSPC})"
    else:
        _, out = _run_fault_writer(tmp_path / "run.h5", _limit_file_size(300_000))
        moved, said, cause = tmp_path / "run.h5", "writing the file failed", f"(errno {errno.EFBIG})"
    assert len(out["errors"]) == 1 and cause in out["errors"][0], out["errors"]
    run = open_run(moved)
    assert run.state == "running" and not run.complete
    for text in (run.incomplete_reason, " ".join(_inspect(moved).split())):
        assert said in text and cause in text and "crashed" not in text, text
    res = subprocess.run([sys.executable, "-m", "bench", "recover", str(moved)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    assert res.returncode == 0, res.stdout + res.stderr
    assert said in res.stdout and cause in res.stdout and "crashed" not in res.stdout, res.stdout
    assert (fault == "disk-full") == ("the disk was full" in res.stdout)
    with h5py.File(moved, "r") as f:
        reason = f["status/reason"][0].decode()
    assert reason.startswith("storage fault: run file ") and reason.endswith("| recovered after the storage fault")
    _check_known_record(moved, out["confirmed"])


def _inspect(path: Path) -> str:
    res = subprocess.run([sys.executable, "-m", "bench", "inspect", str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    assert res.returncode in (0, 1), res.stdout + res.stderr  # 1: an incomplete file
    return res.stdout


@pytest.mark.parametrize("limit", [
    300_000,  # the first flush in the run fails (a complete file of this run is ~840 kB)
    600_000,  # only the final flush fails: the run ended, but its end is not on file — still an error
], ids=["during-run", "at-finish"])
def test_cli_run_under_a_file_size_limit_ends_with_one_line_and_a_readable_file(tmp_path: Path, limit: int) -> None:
    proc = subprocess.run([sys.executable, "-m", "bench", "run",
                           str(ROOT / "protocols" / "short" / "thesis-identification-short.toml"),
                           "--virtual-time", "--no-live", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=180, cwd=ROOT, env=_env(),
                          preexec_fn=_limit_file_size(limit))
    text = proc.stdout + proc.stderr
    assert proc.returncode >= 0, f"killed by signal {-proc.returncode}: {text[-2000:]}"
    assert "Traceback" not in text and "Exception ignored" not in text, text[-2000:]
    (path,) = tmp_path.glob("*.h5")
    run = open_run(path)  # readable up to the last flush, and says it is incomplete
    assert not run.complete and run.state == "running" and run.incomplete_reason
    for s in run.streams.values():  # zero-filled records would show as a jump back to t = 0
        # (a stream's whole chunks may be written ahead of /status/updated: a queue spanning 1 s of the run clock
        # is written at once, bench.storage.recorder.QUEUED_MAX_S; readers say so, runfile.recorded_note)
        assert len(s) == 0 or (np.all(np.diff(s.t) > 0) and s.t[0] >= 0)
    with h5py.File(path, "r", swmr=True) as f:
        names = json.loads(f["status/samples"].attrs["names"])
        assert int(f["status/samples"][names.index("laser")]) == len(run.streams["laser"])
    assert proc.returncode in (1, 2), text[-2000:]
    lines = [line for line in text.splitlines() if "storage fault: run file" in line]
    assert lines, text[-2000:]  # one line naming the file and the cause, not HDF5's multi-line driver message
    assert all(str(path) in line and "File too large (errno 27)" in line for line in lines), text[-2000:]
    assert "Driver write request failed" not in text and "file descriptor =" not in text, text[-2000:]
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr  # the error; the summary is on stdout


def test_unwritable_folder_is_one_line_before_the_run(tmp_path: Path) -> None:
    ctx: contextlib.AbstractContextManager[Path]
    if os.geteuid() == 0:  # root writes through mode bits: a read-only file system instead
        ctx = _tmpfs(tmp_path / "ro", "1m", "ro")
    else:
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o555)
        ctx = contextlib.nullcontext(ro)
    with ctx as folder:
        proc = subprocess.run([sys.executable, "-m", "bench", "run",
                               str(ROOT / "protocols" / "short" / "thesis-identification-short.toml"),
                               "--virtual-time", "--no-live", "--out", str(folder / "runs")],
                              capture_output=True, text=True, timeout=120, cwd=ROOT, env=_env())
        assert proc.returncode == 2, proc.stdout + proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: run file ") and str(folder) in lines[0], proc.stderr
        assert "high voltage:" not in proc.stdout  # the engine never started
        assert not list(folder.rglob("*.h5"))


def _kill_once(tmp_path: Path, k: int, rng: random.Random) -> tuple[float, Path]:
    path = tmp_path / f"killed-{k}.h5"
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-c", KILL_WRITER, str(path), repr(t0)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready", proc.stderr
    time.sleep(rng.uniform(0.4, 1.5))
    t_kill = time.monotonic() - t0
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    run = open_run(path)  # bench's reader opens a killed file on its own …
    assert not run.complete and run.state == "running" and "crashed or was killed" in run.incomplete_reason
    assert "bench recover" in run.incomplete_reason  # … and says so
    laser = run.streams["laser"]
    n = len(laser)
    np.testing.assert_array_equal(laser.t, np.arange(n) / RATE)
    np.testing.assert_array_equal(laser.columns["displacement"], np.arange(n) / RATE * 1e-3)
    return t_kill - float(laser.t[-1]), path


def test_kill_9_loses_at_most_half_a_second_and_recover_releases_the_file(tmp_path: Path) -> None:
    rng = random.Random(8)
    h5dump, h5clear = shutil.which("h5dump"), shutil.which("h5clear")
    lost = []
    for k in range(8):
        loss, path = _kill_once(tmp_path, k, rng)
        lost.append(loss)
        with pytest.raises(OSError):
            h5py.File(path, "r")
        if h5clear is not None and k == 0:  # our flag clearing equals the HDF5 tool's, byte for byte
            ref = tmp_path / "h5clear.h5"
            shutil.copy(path, ref)
            subprocess.run([h5clear, "-s", str(ref)], check=True, capture_output=True)
            from bench.storage.superblock import clear_consistency_flags
            image = bytearray(path.read_bytes())
            assert clear_consistency_flags(image) and bytes(image) == ref.read_bytes()
        before = {name: len(s) for name, s in open_run(path).streams.items()}
        if k == 0:  # the command once; the others through the function it calls (a process start each saved)
            res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True,
                                 text=True, timeout=60, cwd=ROOT, env=_env())
            assert res.returncode == 0, res.stdout + res.stderr
            said = res.stdout
        else:
            from bench.storage.recover import recover

            said = "\n".join(recover(path).lines())
        assert "cleared the file consistency flags" in said, said
        assert f"laser: {before['laser']:,} samples" in said
        with h5py.File(path, "r") as f:  # plain h5py now
            assert f.attrs["recovered_at"] and f["status/reason"][0] == b"recovered after crash"
            assert f["laser/t"].shape[0] == before["laser"]
        if h5dump is not None:
            dump = subprocess.run([h5dump, "-H", str(path)], capture_output=True, text=True, timeout=30)
            assert dump.returncode == 0, dump.stderr
        after = open_run(path)
        assert not after.complete and "recovered at" in after.incomplete_reason
        assert {name: len(s) for name, s in after.streams.items()} == before
    print(f"kill -9 data lost [s]: {', '.join(f'{x:.3f}' for x in lost)}")
    assert max(lost) <= 0.5, lost


def test_the_recorded_up_to_note_says_which_streams_run_past_it() -> None:
    """/status/updated is the time to which every stream and the events are on file; whole-chunk writes carry a
    stream's samples past it. After a full disk, both streams reached 7.750 s while inspect said "every stream complete
    to 5.491 s; some stream's samples go on to 7.750 s" (an outside tester): where every stream runs past it, the
    note says so, with the earliest end."""
    from bench.storage.runfile import recorded_note

    assert recorded_note(5.491, []) == "" and recorded_note(5.491, [5.491, 5.4912]) == ""
    assert recorded_note(5.491, [7.75, 7.75]) == \
        " (the events are on file to here; every stream's samples go on to 7.750 s)"
    assert recorded_note(5.491, [6.5, 7.75]) == \
        " (the events are on file to here; every stream's samples go on to 6.500 s, some to 7.750 s)"
    assert recorded_note(5.491, [5.491, 7.75]) == \
        " (every stream and the events complete to here; some stream's samples go on to 7.750 s)"
    assert recorded_note(5.491, [7.75]) == \
        " (the events are on file to here; every stream's samples go on to 7.750 s)"


def test_a_killed_and_recovered_file_reads_as_killed_and_says_how_far_its_streams_go(tmp_path: Path) -> None:
    """After `bench recover`, a killed file still listed as "running, incomplete", and inspect said "recorded up to
    124.746 s" while its streams ended at 128.5 s (found by an outside tester): /status/updated is the time to which
    every stream is complete, and a stream's whole-chunk writes run ahead of it. Now the listing says the run crashed
    or was killed, and inspect and recover say how far the streams go."""
    from typer.testing import CliRunner

    from bench.cli import app
    from bench.storage.recover import recover

    _, path = _kill_once(tmp_path, 0, random.Random(5))
    recover(path)
    with h5py.File(path, "r+") as f:  # streams ahead of the time to which all are complete, as the tester's files
        last = float(f["laser/t"][-1])
        first = min(last, float(f["amplifier/t"][-1]))
        f["status/updated"][0] = first - 0.25
        state = f["status/state"][0]
    assert state == b"running"  # the file's state: nothing stamped its end
    said = "\n".join(recover(path).lines())  # already released: nothing to do, and what the file holds
    assert "state crashed or killed — INCOMPLETE" in said, said
    # both streams run past it (a second tester's disk-full file): said of every stream, with the earliest end
    assert f"recorded up to {first - 0.25:.3f} s (the events are on file to here; every stream's samples go on to " \
           f"{first:.3f} s" in said, said
    runner = CliRunner()
    out = runner.invoke(app, ["inspect", str(path)], env={"COLUMNS": "300"})
    flat = " ".join(out.output.split())
    assert f"{first - 0.25:.3f} s of" in flat and f"every stream's samples go on to {first:.3f} s" in flat, out.output
    assert "crashed or killed — INCOMPLETE" in flat, out.output
    out = runner.invoke(app, ["inspect", str(path), "--json"])
    rec = json.loads(out.output)
    rec = rec[0] if isinstance(rec, list) else rec
    assert rec["last_sample_s"] == last and rec["recorded_up_to_s"] == first - 0.25 and rec["state"] == "running"
    assert rec["state_shown"] == "crashed or killed"
    # pause / resume: no process writes it (a third tester: `pause` said "asked … within 0.1 s" to no process, exit
    # 0, once the file was recovered); export: one line says it is not complete, and its metadata the state shown
    for args in (["pause", str(path), "--why", "x"], ["resume", str(path), "--why", "x"]):
        out = runner.invoke(app, args, env={"COLUMNS": "300"})
        assert out.exit_code == 2 and "no run is writing it (crashed or killed)" in out.output, out.output
    out = runner.invoke(app, ["export", str(path), "--csv", str(tmp_path / "csv")], env={"COLUMNS": "300"})
    assert out.exit_code == 0 and "is not a complete record (crashed or killed" in " ".join(out.output.split()), \
        out.output
    meta = json.loads((tmp_path / "csv" / "metadata.json").read_text(encoding="utf-8"))
    assert meta["state"] == "running" and meta["state_shown"] == "crashed or killed" and meta["incomplete_reason"]
    out = runner.invoke(app, ["runs", "list", "--dir", str(tmp_path)],
                        env={"COLUMNS": "300", "BENCH_CATALOG": f"sqlite:///{tmp_path / 'cat.sqlite'}"})
    assert out.exit_code == 0, out.output
    row = next(ln for ln in out.output.splitlines() if path.name in ln)
    assert "crashed or killed, incomplete" in row and "running" not in row, out.output
    from bench.storage.chain import chain, describe  # inspect's and report's campaign line (a second tester)

    assert describe(chain(path)) == f"{path.name} (crashed or killed, incomplete)"


STAMP_KILLER = textwrap.dedent(f"""
    import os, signal, sys
    from pathlib import Path
    import h5py
    import numpy as np
    from bench.storage.recorder import Column, Recorder
    rec = Recorder(Path(sys.argv[1]), {{"protocol_name": "stamp test"}}, {{"laser": [Column("displacement", "m", "")]}},
                   [], {{"laser": {RATE}}})
    t = np.arange(2000) / {RATE}
    rec.append("laser", t, displacement=t * 1e-3)
    rec.set_state("completed", "protocol completed")
    rec._f.close()  # what finish() does before it stamps the root attributes outside SWMR mode …
    f = h5py.File(sys.argv[1], "r+")
    f.attrs["end_time"] = "x"
    f.flush()
    os.kill(os.getpid(), signal.SIGKILL)  # … and the process dies there
""")


def test_a_run_killed_while_stamping_its_end_is_read_and_recovered(tmp_path: Path) -> None:
    """Outside SWMR mode the writer's mark makes even an SWMR reader refuse the file; bench still reads it."""
    path = tmp_path / "stamped.h5"
    proc = subprocess.run([sys.executable, "-c", STAMP_KILLER, str(path)], capture_output=True, text=True, timeout=60,
                          env=_env(), cwd=ROOT)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    with pytest.raises(OSError):
        h5py.File(path, "r", swmr=True)
    run = open_run(path)
    assert run.state == "completed" and not run.complete and "not finalised" in run.incomplete_reason
    np.testing.assert_array_equal(run.streams["laser"].t, np.arange(2000) / RATE)
    res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    assert res.returncode == 0 and "laser: 2,000 samples" in res.stdout, res.stdout + res.stderr
    with h5py.File(path, "r") as f:
        assert f["status/reason"][0] == b"protocol completed | recovered after crash"
    assert not open_run(path).complete


def _complete_file(path: Path) -> None:
    from bench.storage.recorder import Column, Recorder

    rec = Recorder(path, {"protocol_name": "complete"}, {"laser": [Column("displacement", "m", "")]}, [],
                   {"laser": RATE})
    t = np.arange(300) / RATE
    rec.append("laser", t, displacement=t)
    rec.finish("completed", "protocol completed")


def test_recover_leaves_a_complete_file_as_it_is(tmp_path: Path) -> None:
    path = tmp_path / "done.h5"
    _complete_file(path)
    before = path.read_bytes()
    res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    assert res.returncode == 0 and "nothing to recover" in res.stdout and "laser: 300 samples" in res.stdout
    assert path.read_bytes() == before


def test_recover_refuses_a_file_a_writer_still_has_open(tmp_path: Path) -> None:
    path = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", KILL_WRITER, str(path), repr(time.monotonic())],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready", proc.stderr
        res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                             timeout=60, cwd=ROOT, env=_env())
        assert res.returncode == 2 and f"still open in process {proc.pid}" in res.stderr, res.stdout + res.stderr
        assert len(res.stderr.strip().splitlines()) == 1, res.stderr
        run = open_run(path)  # an SWMR reader meanwhile, and it knows the writer is alive
        assert run.state == "running" and not run.orphaned and "still going" in run.incomplete_reason
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_a_killed_file_a_reader_has_open_reads_as_killed_not_as_still_going(tmp_path: Path) -> None:
    """A crashed run's file counted as "being written" while any other process had it open — a viewer reading it
    (an outside tester). Only a descriptor open for writing is a writer."""
    _, path = _kill_once(tmp_path, 0, random.Random(3))
    reader = subprocess.Popen([sys.executable, "-c", "import sys, time; f = open(sys.argv[1], 'rb'); "
                               "print('open', flush=True); time.sleep(60)", str(path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "open"
        run = open_run(path)
        assert run.orphaned and "crashed or was killed" in run.incomplete_reason, run.incomplete_reason
        assert "still going" not in run.incomplete_reason
    finally:
        reader.kill()
        reader.wait(timeout=10)


@pytest.mark.parametrize(("content", "expected"), [
    (b"not hdf5 at all", "not an HDF5 file"),
    (None, "not a dea-bench run file"),
], ids=["text", "other-hdf5"])
def test_recover_names_a_file_that_is_not_a_run_file(tmp_path: Path, content: bytes | None, expected: str) -> None:
    path = tmp_path / "other.h5"
    if content is None:
        with h5py.File(path, "w") as f:
            f["x"] = np.arange(3)
    else:
        path.write_bytes(content)
    res = subprocess.run([sys.executable, "-m", "bench", "recover", str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=_env())
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and str(path) in lines[0] and expected in lines[0], res.stderr


def test_a_full_disk_at_the_final_stamp_is_a_storage_error_not_a_crash(tmp_path: Path) -> None:
    """The end of a run reopens the file to stamp its root attributes; when the disk fills there (RLIMIT_FSIZE at
    the file's size: EFBIG), the close fails half-way and asking the handle for its descriptor then crashed the
    interpreter (SIGSEGV) — everything after it (the latch, closing the instruments) was lost. The stamp's failure
    must be one StorageError, in a process that goes on (run in a child: a crash would take pytest with it), and the
    file keeps every sample and the end in /status. The stamp now overwrites placeholders in place (a disk full
    from the reopen on does not stop it: tests/test_storage_stamp.py), so here nothing past the superblock (48
    bytes in format version 3) can be written: the reopen works, its close fails half-way."""
    script = textwrap.dedent(f"""
        import os, resource
        import numpy as np
        from pathlib import Path
        import bench.storage.recorder as R
        p = Path({str(tmp_path / "run.h5")!r})
        rec = R.Recorder(p, {{"start_time": R.now_iso(), "protocol_text": "x" * 5000}},
                         {{"amplifier": [R.Column("voltage", "V", "")]}}, [(0, "a", "a", "hold", 0.0, 1.0)],
                         {{"amplifier": 1000.0}})
        for i in range(50):
            t = np.arange(i * 100, (i + 1) * 100) / 1000.0
            rec.append("amplifier", t, voltage=np.sin(t))
        File = R.h5py.File
        def reopen(path, mode="r", *a, **k):
            if mode == "r+":  # the disk is full from here on
                resource.setrlimit(resource.RLIMIT_FSIZE, (48, resource.RLIM_INFINITY))
            return File(path, mode, *a, **k)
        R.h5py.File = reopen
        try:
            rec.finish("completed", "ok")
        except R.StorageError as exc:
            print("StorageError:", exc)
        print("alive")
    """)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    path = tmp_path / "run.h5"
    assert f"StorageError: run file {path}: cannot stamp the end of the run" in out.stdout
    assert out.stdout.rstrip().endswith("alive") and len(out.stdout.strip().splitlines()) == 2, out.stdout
    run = open_run(path)
    assert run.state == "completed" and run.reason == "ok"
    assert not run.complete and "not finalised" in run.incomplete_reason
    t = np.arange(5000) / 1000.0
    np.testing.assert_array_equal(run.streams["amplifier"].t, t)
    np.testing.assert_array_equal(run.streams["amplifier"].columns["voltage"], np.sin(t))


def test_a_new_run_file_is_byte_for_byte_the_one_h5pys_attrs_would_write(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The recorder writes its texts through h5py's low-level calls (``set_attrs``: most of a file's creation went
    to h5py's ``attrs``, ~100 µs an attribute): the finished file is byte for byte the one ``attrs`` writes (types,
    spaces, order), and only what is no text — here 2 root values, ``complete``, each stream's ``rate_Hz``, a
    validity column's ``flag_values`` — still goes through ``attrs``."""
    from bench.storage import recorder
    from bench.storage.recorder import Column, Recorder

    monkeypatch.setattr(recorder, "now_iso", lambda: "2026-01-02T03:04:05.000+00:00")  # the end stamp, alike
    attrs = {"protocol_name": "bytes", "start_time": "2026-01-02T03:00:00.000+00:00", "operator": "Zoë",
             "specimen": {"model": {"L3": 5e-5}}, "simulated": True, "duration_planned": 12.5}
    streams = {"amplifier": [Column("voltage", "V", "amplifier output, measured")],
               "probe": [Column("valid", "1", "reading valid", "u1"), Column("x", "m", "", "f4")]}
    program = [(0, "0", "drive", "waveform", 0.0, 1.0)]
    rates = {"amplifier": 1000.0, "probe": 50.0}
    through_attrs: list[str] = []
    setitem = h5py.AttributeManager.__setitem__
    monkeypatch.setattr(h5py.AttributeManager, "__setitem__",
                        lambda self, name, value: (through_attrs.append(name), setitem(self, name, value))[1])

    def record(path: Path) -> bytes:
        rec = Recorder(path, attrs, streams, program, rates)
        rec.event(0.0, 0, "start", "drive")
        rec.append("amplifier", np.arange(5) / 1000.0, voltage=np.arange(5.0))
        rec.finish("completed", "ok")
        return path.read_bytes()

    ours = record(tmp_path / "ours.h5")
    assert sorted(through_attrs) == sorted(["simulated", "duration_planned", "complete", "rate_Hz", "rate_Hz",
                                            "flag_values"])
    monkeypatch.setattr(recorder, "set_attrs",
                        lambda obj, values: [obj.attrs.__setitem__(k, v) for k, v in values.items()] and None)
    assert record(tmp_path / "h5py.h5") == ours


@pytest.mark.parametrize("keep", [0.5, 0.002])
def test_a_finished_run_file_cut_short_is_refused_in_one_line_not_read_for_minutes(
        short_run: Path, tmp_path: Path, keep: float) -> None:
    """A copy cut short (an interrupted copy, a partial download): an SWMR reader skips HDF5's end-of-file check
    and retried its reads past the end for minutes, deaf to Ctrl-C (found by an exploratory test). The file says
    where it ends (its superblock's end-of-file address): shorter than that, and closed by its writer, it is refused."""
    data = short_run.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[:int(len(data) * keep)])
    for command in (["inspect"], ["recover"], ["export", "--csv", str(tmp_path / "x.csv")]):
        res = subprocess.run([sys.executable, "-m", "bench", command[0], str(cut), *command[1:]], cwd=ROOT,
                             env=_env(), capture_output=True, text=True, timeout=120)  # a guard: it hung before
        assert res.returncode == 2, (command, res.stdout, res.stderr)
        (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert f"truncated: {int(len(data) * keep):,} bytes" in line and f"{len(data):,}" in line, line
    assert cut.stat().st_size == int(len(data) * keep)  # recover changed nothing


def test_a_run_file_with_noise_written_into_it_is_one_line_naming_it_not_minutes_of_retries(
        short_run: Path, tmp_path: Path) -> None:
    """Noise written into a finished run file (a failing disk, a bad copy): HDF5's SWMR reader retried each
    damaged metadata read a hundred times with growing waits — `bench inspect` hung for ten minutes, deaf to Ctrl-C
    (found by an exploratory test). A few attempts now; the reader says which file and what it could not read."""
    data = bytearray(short_run.read_bytes())
    rng = np.random.default_rng(0)
    for at in range(8192, len(data) - 8192, 65536):  # 2 kB of noise every 64 kB past the superblock: object headers,
        data[at:at + 2048] = rng.bytes(2048)  # chunk indices and compressed chunks alike, whatever the layout
    bad = tmp_path / "noisy.h5"
    bad.write_bytes(bytes(data))
    for command in (["inspect"], ["report", "--out", str(tmp_path / "report")]):
        res = subprocess.run([sys.executable, "-m", "bench", command[0], str(bad), *command[1:]], cwd=ROOT,
                             env=_env(), capture_output=True, text=True, timeout=240)  # a guard: it hung before
        assert res.returncode == 2 and "Traceback" not in res.stderr, (command, res.stdout, res.stderr)
        (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert line.startswith(f"error: run file {bad}: "), line  # what it could not read depends on the layout


def test_paused_s_sums_each_pause_to_its_resume_and_an_open_pause_to_the_last_update(tmp_path: Path) -> None:
    """The time a run spent paused, from its events alone: pause at 2 s, resume at 5 s (3 s), a second pause at 7 s,
    a repeated pause at 8 s (the same pause) and a resume at 8.5 s (1.5 s), a last pause at 10 s still open when the
    file was last written at 12.25 s (2.25 s): 6.75 s in all. (What `inspect` and `inspect --json` make of it:
    tests/test_pause_resume.py.)"""
    from bench.storage.runfile import RunFile

    marks = [(1.0, "start"), (2.0, "pause"), (5.0, "resume"), (7.0, "pause"), (8.0, "pause"), (8.5, "resume"),
             (9.0, "resume"), (10.0, "pause")]
    events = np.array([(t, 0, k.encode(), b"") for t, k in marks],
                      dtype=[("t", "f8"), ("step", "i4"), ("kind", "S16"), ("text", "S64")])
    run = RunFile(path=tmp_path / "r.h5", attrs={}, state="running", reason="", end_time="", updated=12.25,
                  complete=False, events=events)
    assert run.paused and run.paused_s == pytest.approx(3.0 + 1.5 + 2.25)
    assert RunFile(path=tmp_path / "r.h5", attrs={}, state="completed", reason="", end_time="", updated=4.0,
                   complete=True, events=events[:1]).paused_s == 0.0


def test_a_daq_played_step_starts_where_its_stream_s_scan_0_is(tmp_path: Path) -> None:
    """On a wall-clock DAQ run a stream starts after its step's `start` event (arming it, a restart after a pause's
    ramp up): 48 ms at the first step, 108 ms after a resume, and the square's first edge came that much after where
    the analysis cut its cycles (an outside tester). A step the DAQ played on a stream it started is where the
    stream's scan 0 is (its `timing` event); a step appended to that stream keeps the stream's clock; an engine's own
    stream (the restart's ramp up), an `offset` event and a step of no duration end it. The events in the order the
    engine writes them (bench/runtime/engine.py `_restart`: restart, the ramp up's stream, offset, start). Program:
    steps at 0, 3 and 5 s, a 0-s `set` step at 8 s, a step at 8 s."""
    from bench.storage.runfile import RunFile

    scan = "DAQ scan clock: scan 0 at {} s on the run clock, known to 0.2 ms (the enable request's round trip)"
    marks = [(0.0, 0, "start", ""), (0.0, 0, "timing", scan.format("0.048000") + "; polled channels (motor …"),
             (3.05, 1, "start", ""),  # appended: the same scan clock
             (4.0, 1, "pause", ""), (7.0, 1, "resume", ""), (7.0, 1, "restart", "…"),
             (7.0, 1, "timing", scan.format("7.010000") + ": the restart's ramp up's stream"),
             (9.405, 1, "offset", "run time = program time + 6.405 s"),
             (9.405, 1, "start", ""), (9.405, 1, "timing", scan.format("9.513000") + "; polled channels (…"),
             (11.5, 2, "start", ""),  # appended
             (14.5, 3, "start", ""),  # a set step of no duration: the host's time again
             (14.6, 4, "start", "")]  # no timing event of its own
    events = np.array([(t, i, k.encode(), x.encode()) for t, i, k, x in marks],
                      dtype=[("t", "f8"), ("step", "i4"), ("kind", "S16"), ("text", "S256")])
    program = np.array([(0, 0.0, 3.0), (1, 3.0, 2.0), (2, 5.0, 3.0), (3, 8.0, 0.0), (4, 8.0, 1.0)],
                       dtype=[("index", "i4"), ("t_start", "f8"), ("duration", "f8")])
    run = RunFile(path=tmp_path / "r.h5", attrs={}, state="running", reason="", end_time="", updated=16.0,
                  complete=False, events=events, program=program)
    got = run.step_offsets()
    assert got[0] == pytest.approx(0.048) and got[1] == pytest.approx(9.513 - 3.0) and got[2] == got[1], got
    assert got[3] == got[4] == pytest.approx(6.405), got
    # the host's schedule (software-timed rigs; a position step's go-tos): the offset events alone
    assert run.step_offsets(scan_clock=False) == {0: 0.0, 1: pytest.approx(6.405), 2: pytest.approx(6.405),
                                                  3: pytest.approx(6.405), 4: pytest.approx(6.405)}
    assert run.step_offset_clocks() == (got, run.step_offsets(scan_clock=False))  # both from one pass
    # since 2026-11-28 a restarted step plays on the ramp up's stream: no kickoff of its own, its offset event from
    # that stream's scan clock (the scan that plays its start) — the step and the one appended after it take it
    marks = [*marks[:7], (7.36, 1, "offset", "run time = program time + 4.360000 s"), (7.36, 1, "start", ""),
             (9.36, 2, "start", "")]
    events = np.array([(t, i, k.encode(), x.encode()) for t, i, k, x in marks], dtype=events.dtype)
    run = RunFile(path=tmp_path / "r.h5", attrs={}, state="running", reason="", end_time="", updated=16.0,
                  complete=False, events=events, program=program)
    assert run.step_offsets() == {0: pytest.approx(0.048), 1: pytest.approx(4.36), 2: pytest.approx(4.36)}


def test_a_kickoffs_text_is_written_and_read_by_one_grammar() -> None:
    """The `timing` event of a stream's kickoff is written (bench/runtime/hardware_timed.py) and read (the analysis's
    offsets, replay) through bench/storage/scan_clock.py; before, each reader had its own regex and told a step's
    stream from a ramp's by a phrase of the prose. The texts of files already written read as they did: literal
    texts of a run file of 2026-11-28 (the thesis DAQ rig, a pause and resume)."""
    from bench.storage.scan_clock import kickoff_text, parse_kickoff

    old_step = ("DAQ scan clock: scan 0 at 2.881100 s on the run clock, known to 0.000 ms (the enable request's round "
                "trip); polled channels (motor encoder) are timestamped on the same run clock")
    old_ramp = ("DAQ scan clock: scan 0 at 2.507100 s on the run clock, known to 0.000 ms (the enable request's round "
                "trip): the restart's ramp up's stream")
    assert parse_kickoff(old_step) == (pytest.approx(2.8811), True)
    assert parse_kickoff(old_ramp) == (pytest.approx(2.5071), False)
    assert kickoff_text(2.8811, 0.0) == old_step  # the writer's text is the files' text
    assert kickoff_text(2.5071, 0.0, "the restart's ramp up's stream") == old_ramp
    assert parse_kickoff(kickoff_text(-0.25, 2e-4, "the ramp to 0 V's stream")) == (pytest.approx(-0.25), False)
    assert parse_kickoff("12 late actions (> 50 ms), worst 0.2 s") is None  # the engine's other timing events
