"""The run catalogue's rows: the start row on its own thread, the end row from the recorder's account, a catalogue
that cannot be written, refused folders and states, and which files a folder's listing shows (SQLite and a real
PostgreSQL server). The specimen history of a killed and resumed campaign is in tests/test_catalog.py; the two files
share tests/catalog_helpers.py and are two so that the two test workers can share them.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from tests import catalog_helpers
from tests.catalog_helpers import (
    COLUMNS,
    IDENT,
    THRESHOLD_V,
    Catalog,
    _bench,
    _bench_here,
    _env,
    _expected,
    _new_pg_db,
    row_from_attrs,
    sa,
)
from tests.conftest import ROOT

pg_server = catalog_helpers.pg_server  # the shared fixtures (pytest finds them by name in the module)
catalog_url = catalog_helpers.catalog_url


def test_a_catalogue_that_cannot_be_written_does_not_stop_a_run(tmp_path: Path) -> None:
    dead = "postgresql+psycopg://nobody@127.0.0.1:1/none"  # nothing listens on port 1
    out = _bench("run", str(IDENT), "--virtual-time", "--out", str(tmp_path), "--no-live", "--catalog", dead,
                 env=_env(tmp_path / "state"))
    env = {**_env(tmp_path / "state"), "BENCH_CATALOG": dead}
    assert out.returncode == 0, out.stdout + out.stderr
    assert "run catalogue not written" in out.stdout + out.stderr
    assert "Traceback" not in out.stdout + out.stderr
    assert not (tmp_path / "catalog.sqlite").exists()  # --catalog, not the default beside the runs
    listed = _bench("runs", "list", "--dir", str(tmp_path), env=env)  # and asked to list: one line, exit 2
    # naming the catalogue (an outside tester: "run catalogue: file is not a database" named none)
    assert listed.returncode == 2 and listed.stderr.startswith(f"error: run catalogue {dead}: "), listed.stderr
    assert listed.stderr.count("\n") == 1



@pytest.mark.parametrize("chunk", [97, 1 << 20])
def test_the_recorders_statistics_are_the_files_bit_for_bit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            chunk: int) -> None:
    """The run's end catalogues the statistics the recorder counted while writing (no read-back): equal to a read
    of the file bit for bit, whatever the pieces written and the read's chunks; and to the plain loop."""
    from bench.storage import catalog, hv_stats
    from bench.storage.recorder import Column, Recorder

    monkeypatch.setattr(hv_stats, "CHUNK", chunk)
    rng = np.random.default_rng(3)
    path = tmp_path / "hv.h5"
    rec = Recorder(path, {"protocol_name": "hv"}, {"amplifier": [Column("voltage", "V", "")]}, [], {"amplifier": 1e4})
    k = 0
    for size in rng.integers(1, 400, 40):  # pieces of every size, across the read's chunks
        t = (k + np.arange(size)) * 1e-4
        rec.append("amplifier", t, voltage=3000.0 * np.sin(2 * np.pi * 7.0 * t) + rng.normal(0.0, 300.0, size))
        k += size
        rec.flush()
    rec.finish("completed", "")
    got = rec.hv_stats()
    assert got is not None and got == catalog.hv_statistics(path)
    hv, rises, peak = _expected(path)
    assert (got.cycles, got.max_voltage_V) == (rises, peak) and got.hv_time_s == pytest.approx(hv, rel=1e-9)


def test_a_locked_catalogue_table_on_the_shared_server_fails_the_row_instead_of_holding_the_run(
        pg_server: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Another client holds the runs table locked (a stuck transaction on the lab's server): the catalogue's write
    gives up after its statement/lock timeout (the run's hooks turn that into one warning line) — the catalogue is
    an index and must never hold a run; before, nothing bounded the wait."""
    from bench.storage import catalog as cat_mod

    monkeypatch.setattr(cat_mod, "PG_STATEMENT_S", 1)
    url = _new_pg_db(pg_server)
    with Catalog(url):
        pass  # the schema exists
    blocker = sa.create_engine(url)
    with blocker.connect() as conn:
        conn.execute(sa.text("BEGIN"))
        conn.execute(sa.text("LOCK TABLE bench_runs IN ACCESS EXCLUSIVE MODE"))
        with Catalog(url) as locked, pytest.raises(sa.exc.OperationalError, match=r"(statement|lock) timeout"):
            locked.upsert([row_from_attrs(tmp_path / "r.h5", {"protocol_name": "x", "start_time": "2026-01-01"})])
        conn.execute(sa.text("ROLLBACK"))
    blocker.dispose()


# ---- the start row on its own thread -------------------------------------------------------------------------------


def _slow_start_row(monkeypatch: pytest.MonkeyPatch, delay_s: float) -> list[str]:
    """Make the catalogue's start row late by ``delay_s``; returns a list that gets "written" once it is."""
    from bench.storage import catalog

    done: list[str] = []
    real = catalog.record_start

    def late(path: Path, attrs: dict, url: str | None = None) -> None:
        import time

        time.sleep(delay_s)
        real(path, attrs, url)
        done.append("written")

    monkeypatch.setattr(catalog, "record_start", late)
    return done


def _rows(folder: Path) -> list[dict]:
    from bench.storage.catalog import catalog_url

    with Catalog(catalog_url(folder)) as cat:
        return cat.rows(under=folder)


def test_a_late_start_row_never_replaces_the_end_row(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The start row is written beside the run's first steps; the run's end waits for it, so the row left is the
    end's (read from the file: its signature set, complete), however late the start row was."""
    from bench.runtime.run import execute, plan_run

    monkeypatch.delenv("BENCH_CATALOG", raising=False)
    done = _slow_start_row(monkeypatch, 0.5)  # longer than this virtual-time run takes to stream
    result = execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed" and done == ["written"]
    (row,) = _rows(tmp_path)
    assert row["signature"] != "" and row["complete"] and row["state"] == "completed"


def test_ctrl_c_while_the_end_waits_for_the_start_row_skips_the_end_row_with_a_warning(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Ctrl-C while the run's end waits for a late start row ends the wait: the run returns its result (its file
    already holds the end), the catalogue's end row is skipped with a warning, and `bench runs list` reconciles
    the row from the file."""
    import signal
    import threading

    from bench.runtime import run as run_module
    from bench.runtime.run import execute, plan_run
    from bench.storage import catalog
    from bench.storage.catalog import catalog_url, reconcile

    monkeypatch.delenv("BENCH_CATALOG", raising=False)
    release, done = threading.Event(), []
    real_start, real_join = catalog.record_start, run_module._join

    def held(path: Path, attrs: dict, url: str | None = None) -> None:  # the start row, held until released
        release.wait(60)
        real_start(path, attrs, url)
        done.append("written")

    def ctrl_c_while_joining(row: threading.Thread | None) -> None:
        assert row is not None and row.is_alive() and row.ident is not None  # held: the join below waits
        # a real SIGINT, mid-wait, delivered to another thread than the waiting one (the kernel may pick any thread
        # of the process for a terminal's Ctrl-C; CI once saw the join wait the start row out)
        threading.Timer(0.2, signal.pthread_kill, (row.ident, signal.SIGINT)).start()
        real_join(row)

    monkeypatch.setattr(catalog, "record_start", held)
    monkeypatch.setattr(run_module, "_join", ctrl_c_while_joining)
    monkeypatch.setattr(run_module, "START_ROW_WAIT_S", 3600.0)  # only the signal can end the wait before release
    # SIGINT raising KeyboardInterrupt, as in a `bench` started from a terminal: a suite started as a background job
    # of a non-interactive shell (CI) inherits SIGINT ignored, and Python then installs no such handler
    was = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        result = execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True)
        at_return = list(done)
    finally:
        release.set()
        signal.signal(signal.SIGINT, was)
    assert at_return == []  # returned while the start row was held: the signal ended the wait
    assert result.state == "completed"
    assert any("run catalogue not written at the end (Ctrl-C" in r.getMessage() for r in caplog.records)
    for _ in range(600):  # the start row's thread goes on and writes its row
        if done:
            break
        threading.Event().wait(0.05)
    assert done == ["written"]
    with Catalog(catalog_url(tmp_path)) as cat:
        reconcile(cat, tmp_path)
    (row,) = _rows(tmp_path)
    assert row["signature"] != "" and row["complete"] and row["state"] == "completed"  # from the file


def test_a_run_that_raises_still_leaves_its_start_row(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from bench.runtime.engine import Engine
    from bench.runtime.run import execute, plan_run

    monkeypatch.delenv("BENCH_CATALOG", raising=False)
    done = _slow_start_row(monkeypatch, 0.2)

    def broken(self: Engine) -> None:
        raise RuntimeError("engine broke")

    monkeypatch.setattr(Engine, "run", broken)
    with pytest.raises(RuntimeError, match="engine broke"):
        execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True)
    assert done == ["written"]
    (row,) = _rows(tmp_path)
    assert row["signature"] == "" and row["protocol_name"] == "thesis-identification-short"


def test_a_start_row_replaces_only_a_start_row_or_another_runs_row(short_run: Path, catalog_url: str) -> None:
    """The end row (read from the file) is never replaced by the same run's start row, however late it comes; a
    start row still replaces an earlier run's row at the same path, and a row without a run ID (older files)."""
    from bench.storage.catalog import row_from_file
    from bench.storage.runfile import open_run

    attrs = dict(open_run(short_run, streams=False).attrs)
    with Catalog(catalog_url) as cat:
        cat.upsert([row_from_file(short_run)])
        cat.upsert([row_from_attrs(short_run, attrs)], start=True)  # late: after the end row
        (row,) = cat.rows()
        assert row["signature"] != "" and row["complete"] and row["run_id"] == attrs["run_id"]
        cat.upsert([row_from_attrs(short_run, {**attrs, "run_id": "f" * 32})], start=True)  # a new run, same path
        (row,) = cat.rows()
        assert row["signature"] == "" and row["run_id"] == "f" * 32 and not row["complete"]
        cat.upsert([{**row_from_file(short_run), "run_id": None}])  # an older file's row: no run ID
        cat.upsert([row_from_attrs(short_run, attrs)], start=True)
        (row,) = cat.rows()
        assert row["signature"] == "" and row["run_id"] == attrs["run_id"]


def test_a_run_whose_start_row_gets_no_thread_writes_it_in_line(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Where no thread can be started the run goes on and writes its start row itself (a run never depends on its
    catalogue); the end row follows."""
    import threading
    import types

    from bench.runtime import run as run_module
    from bench.runtime.run import execute, plan_run
    from bench.storage import catalog

    monkeypatch.delenv("BENCH_CATALOG", raising=False)

    class NoThread(threading.Thread):
        def start(self) -> None:
            raise RuntimeError("can't start new thread")

    monkeypatch.setattr(run_module, "threading", types.SimpleNamespace(Thread=NoThread))
    callers: list[str] = []
    real = catalog.record_start
    monkeypatch.setattr(catalog, "record_start",
                        lambda *a, **k: (callers.append(threading.current_thread().name), real(*a, **k))[1])
    result = execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed" and callers == [threading.main_thread().name]
    (row,) = _rows(tmp_path)
    assert row["signature"] != "" and row["complete"]


@pytest.mark.parametrize("ending", ["completed", "stopped before the engine ran"])
def test_the_instruments_are_closed_before_the_run_waits_on_its_catalogue(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch,
                                                                          ending: str) -> None:
    """A catalogue held by another writer may keep its rows waiting for seconds: the run closes its instruments
    (and stops its twins) first, then waits for the start row and writes the end row."""
    from bench.runtime.instruments import Instruments
    from bench.runtime.run import execute, plan_run
    from bench.storage import catalog

    monkeypatch.delenv("BENCH_CATALOG", raising=False)
    order: list[str] = []
    _slow_start_row(monkeypatch, 0.3)
    closing, ending_row = Instruments.close, catalog.record_end
    monkeypatch.setattr(Instruments, "close", lambda self: (order.append("instruments closed"), closing(self))[1])
    monkeypatch.setattr(catalog, "record_end", lambda *a, **k: (order.append("end row"), ending_row(*a, **k))[1])

    def refuse(engine: object, sim: object) -> None:
        raise RuntimeError("refused before the run")

    if ending == "completed":
        assert execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True).state == "completed"
    else:
        with pytest.raises(RuntimeError, match="refused before the run"):
            execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True, on_engine=refuse)
    assert order == ["instruments closed", "end row"]
    (row,) = _rows(tmp_path)
    assert row["signature"] != "" and row["state"] == ("completed" if ending == "completed" else "error")


# ---- the end row from the recorder's account of the file it wrote ---------------------------------------------------


def _recorded(path: Path, reason: str) -> object:
    """A file written by a recorder: metadata, a membrane model, a campaign link, three steps (one restarted and
    not ended again, one ended, one never started) and a measured voltage; finished with ``reason``."""
    from bench.storage.recorder import Column, Recorder

    attrs = {"protocol_name": "p", "start_time": "2026-01-02T03:04:05.000+00:00", "run_id": "a" * 32,
             "campaign_id": "b" * 32, "protocol_sha256": "c" * 64, "rig_name": "rig", "operator": "ada",
             "specimen_id": "S9", "notes": "first\nsecond", "previous_file": "../old/run.h5",
             "specimen": {"model": {"L3": 5e-5, "breakdown_field": 2e8}}}
    program = [(0, "0", "drive", "waveform", 0.0, 1.0), (1, "1", "rest", "relax", 1.0, 1.0),
               (2, "2", "drive", "waveform", 2.0, 1.0)]
    rec = Recorder(path, attrs, {"amplifier": [Column("voltage", "V", "")]}, program, {"amplifier": 10.0})
    for step, kind in ((0, "start"), (0, "end"), (1, "start"), (1, "end"), (1, "start"), (-1, "stop")):
        rec.event(float(step), step, kind, f"step {step}")
    t = np.arange(40) * 0.1
    rec.append("amplifier", t, voltage=3000.0 * np.sin(2 * np.pi * t))
    rec.finish("interrupted", reason)
    return rec


@pytest.mark.parametrize("reason", ["stop requested", "é" * 250 + " cut at 400 bytes, between two characters"])
def test_the_end_row_from_the_recorders_account_is_the_row_read_from_the_file(tmp_path: Path, reason: str) -> None:
    """Every column of the end row the run's end builds from what its recorder wrote equals the row read back from
    the file (the reason as the file's 400-byte field holds it)."""
    from bench.storage import catalog

    rec = _recorded(tmp_path / "run.h5", reason)
    written = rec.written()  # type: ignore[attr-defined]
    assert written is not None
    ours = catalog.row_from_written(tmp_path / "run.h5", written, rec.hv_stats())  # type: ignore[attr-defined]
    read = catalog.row_from_file(tmp_path / "run.h5")
    assert {c: ours[c] for c in COLUMNS} == {c: read[c] for c in COLUMNS}
    assert (read["steps_completed"], read["steps_total"], read["state"]) == (1, 3, "interrupted")


def test_a_file_changed_after_its_recorder_closed_it_is_catalogued_from_the_file(tmp_path: Path) -> None:
    """A fit written into the run file before its end row (another process): the recorder's account is no longer
    the file's, so the row is read from the file, fit included."""
    from bench.storage import catalog

    path = tmp_path / "run.h5"
    rec = _recorded(path, "stop requested")
    with h5py.File(path, "r+") as f:  # bench/identify/store.py's layout: /fit/<model>-<n>
        g = f.create_group("fit/membrane-1")
        g.attrs.update(model="membrane", created="2026-01-02T04:00:00", rms=0.5, records="[]")
        g["names"], g["values"] = np.array([b"mu"]), np.array([1.0])
    row = catalog.row_from_written(path, rec.written(), rec.hv_stats())  # type: ignore[attr-defined]
    assert [fit["model"] for fit in json.loads(row["fits"])] == ["membrane"]
    assert row == catalog.row_from_file(path)


@pytest.mark.parametrize("ending", ["completed", "interrupted"])
def test_a_runs_end_row_is_its_files_row_without_reading_the_file_back(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch,
                                                                        ending: str) -> None:
    """The run's end catalogues what its recorder wrote: the row equals the one read from the file afterwards, and
    the run never opens its file for reading (before: twice, the row's read and the fits' look-up)."""
    from bench.runtime.engine import Engine
    from bench.runtime.run import execute, plan_run
    from bench.storage.catalog import row_from_file

    monkeypatch.delenv("BENCH_CATALOG", raising=False)
    reads: list[str] = []
    opening = h5py.File.__init__

    def counted(self: h5py.File, name: object, mode: str = "r", *args: object, **kwargs: object) -> None:
        if isinstance(name, str | Path) and Path(name).name == "run.h5" and mode == "r":
            reads.append(str(name))
        opening(self, name, mode, *args, **kwargs)

    monkeypatch.setattr(h5py.File, "__init__", counted)

    def stop(engine: Engine, sim: object) -> None:
        if ending == "interrupted":
            engine.request_stop("stopped by the test")

    result = execute(plan_run(IDENT), tmp_path / "run.h5", virtual=True, on_engine=stop)
    assert result.state == ending and reads == []
    monkeypatch.undo()
    (row,) = _rows(tmp_path)
    assert {c: row[c] for c in COLUMNS} == {c: v for c, v in row_from_file(Path(result.path)).items() if c in COLUMNS}


def test_a_processs_catalogues_share_their_engine_and_survive_their_file_being_deleted(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run's two rows (and a benchmark's many runs) reuse one SQLite engine, its table and compiled statements
    (before: built again for every row); no connection outlives its transaction, so a catalogue file deleted
    between two rows is created again and gets the row."""
    from bench.storage import catalog

    made: list[str] = []
    real = sa.create_engine
    monkeypatch.setattr(sa, "create_engine", lambda *a, **k: (made.append(str(a[0])), real(*a, **k))[1])
    url = f"sqlite:///{tmp_path / 'catalog.sqlite'}"
    rows = [row_from_attrs(tmp_path / f"r{k}.h5", {"protocol_name": f"p{k}", "start_time": f"2026-01-0{k + 1}"})
            for k in range(2)]
    with Catalog(url) as cat:
        cat.upsert(rows[:1])
    (tmp_path / "catalog.sqlite").unlink()
    with Catalog(url) as cat:
        cat.upsert(rows[1:])
        assert [r["protocol_name"] for r in cat.rows()] == ["p1"]
    assert len(made) == 1 and (tmp_path / "catalog.sqlite").is_file()
    catalog.record_start(tmp_path / "r2.h5", {"protocol_name": "p2"}, url)
    assert len(made) == 1


def test_a_misspelt_runs_folder_or_state_is_refused_and_nothing_is_made(tmp_path: Path) -> None:
    """`runs list --dir typo` made the folder and a catalogue in it and listed nothing; `--state foo` listed nothing
    (found by an exploratory test)."""
    from bench.cli.catalog import RUN_STATES
    from bench.storage.recorder import STATES

    assert sorted(RUN_STATES) == sorted(STATES)  # the CLI's list is the recorder's (kept apart for a fast --help)
    env = {**os.environ, "BENCH_STATE_DIR": str(tmp_path / "state")}
    for args, said in ((["runs", "list", "--dir", str(tmp_path / "typo")], "runs folder"),
                       (["catalog", "rebuild", str(tmp_path / "typo")], "runs folder"),
                       (["runs", "list", "--dir", str(tmp_path), "--state", "finished"], "is not a run state")):
        res = subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 2 and said in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "typo").exists()


# ---- which files a folder's listing shows, and each run once --------------------------------------------------------


def _small_run(path: Path, run_id: str, specimen: str, start: str, amplitude_V: float,
               fit: dict[str, float] | None = None) -> None:
    """A completed run file written by a recorder: 4 s of a raised cosine 0 → ``amplitude_V`` at 1 Hz (4 rises above
    the 500-V threshold), sampled at 100 Hz; ``fit``: a fit stored in it (bench/identify/store.py's layout)."""
    from bench.storage.recorder import Column, Recorder

    attrs = {"protocol_name": "p", "start_time": start, "run_id": run_id, "campaign_id": run_id,
             "specimen_id": specimen, "specimen": {"model": {"L3": 1e-3, "breakdown_field": 1e8}}}
    rec = Recorder(path, attrs, {"amplifier": [Column("voltage", "V", "")]}, [], {"amplifier": 100.0})
    t = np.arange(400) * 0.01
    rec.append("amplifier", t, voltage=amplitude_V * (1 - np.cos(2 * np.pi * t)) / 2)
    rec.finish("completed", "")
    if fit:
        with h5py.File(path, "r+") as f:
            g = f.create_group("fit/membrane-1")
            g.attrs.update(model="membrane", created="2026-01-05T00:00:00", rms=0.1, records="[]")
            g["names"], g["values"] = np.array([n.encode() for n in fit]), np.array(list(fit.values()))


def _by_run(folder: Path, specimen: str | None = None) -> dict[str, list[Path]]:
    """The run files under ``folder`` by run ID, read here with h5py."""
    out: dict[str, list[Path]] = {}
    for p in sorted(folder.rglob("*.h5")):
        with h5py.File(p, "r") as f:
            attrs = {k: v.decode() if isinstance(v, bytes) else str(v) for k, v in f.attrs.items()}
        if specimen is None or attrs["specimen_id"] == specimen:
            out.setdefault(attrs["run_id"], []).append(p.resolve())
    return out


def test_a_folder_shows_only_its_files_and_each_run_once(tmp_path: Path) -> None:
    """`cp -a runs copy; bench specimen show S1 --dir copy` counted every run twice (the copied catalogue's rows of
    runs/ and those of copy/), and a shared catalogue kept counting a file deleted from another folder (found by an
    exploratory test). Now: the files under --dir, a run (a run ID) once whatever its copies, and with --everywhere
    the rows elsewhere whose file still exists."""
    env = _env(tmp_path / "state")
    runs = tmp_path / "runs"
    runs.mkdir()
    _small_run(runs / "r1.h5", "1" * 32, "S1", "2026-01-01T00:00:00.000+00:00", 3000.0)
    _small_run(runs / "r2.h5", "2" * 32, "S1", "2026-01-02T00:00:00.000+00:00", 5000.0)
    _small_run(runs / "r3.h5", "3" * 32, "S2", "2026-01-03T00:00:00.000+00:00", 5000.0)
    assert _bench("runs", "list", "--dir", str(runs), env=env).returncode == 0  # runs/catalog.sqlite, rows of runs/
    copy = tmp_path / "copy"
    shutil.copytree(runs, copy)  # `cp -a`: the files and the catalogue beside them
    (copy / "backup").mkdir()
    shutil.copy2(copy / "r1.h5", copy / "backup" / "r1.h5")  # and a copy of a run inside the folder

    out = _bench_here("specimen", "show", "S1", "--dir", str(copy), "--json", env=env)
    assert out.returncode == 0, out.stderr
    h = json.loads(out.stdout)
    mine = _by_run(copy, "S1")
    assert len(mine) == 2 and sum(map(len, mine.values())) == 3  # two runs, three files
    assert len(h["runs"]) == len(mine)
    for r in h["runs"]:
        assert Path(r["file"]).is_relative_to(copy.resolve())
        (run_id,) = [k for k, files in mine.items() if Path(r["file"]) in files]
        assert sorted([r["file"], *r["copies"]]) == sorted(map(str, mine[run_id]))
    per = [_expected(files[0]) for files in mine.values()]
    assert h["hv_time_s"] == pytest.approx(sum(e[0] for e in per), rel=1e-9)
    assert h["hv_cycles"] == sum(e[1] for e in per) == 2 * 4  # 4 s at 1 Hz, each run
    phi = math.acos(1 - 2 * THRESHOLD_V / 3000), math.acos(1 - 2 * THRESHOLD_V / 5000)
    assert h["hv_time_s"] == pytest.approx(sum(4 * (1 - p / math.pi) for p in phi), abs=0.1)  # 100-Hz sampling
    assert "copies of a run" in out.stderr and "outside" in out.stderr  # said, on stderr beside the JSON
    listed = _bench_here("runs", "list", "--dir", str(copy), "--json", env=env)
    assert listed.returncode == 0, listed.stderr
    rows = json.loads(listed.stdout)
    assert len(rows) == len(_by_run(copy)) == 3
    assert all(Path(r["path"]).is_relative_to(copy.resolve()) for r in rows)

    # a shared catalogue: a file deleted from a folder other than --dir is neither listed nor counted
    shared = f"sqlite:///{tmp_path / 'shared.sqlite'}"
    other = tmp_path / "other"
    other.mkdir()
    _small_run(other / "r4.h5", "4" * 32, "S1", "2026-01-04T00:00:00.000+00:00", 3000.0)
    from bench.storage.catalog import reconcile

    with Catalog(shared) as cat:
        reconcile(cat, runs)
        reconcile(cat, other)
    (runs / "r2.h5").unlink()
    here = _bench_here("specimen", "show", "S1", "--dir", str(other), "--catalog", shared, "--json", env=env)
    assert here.returncode == 0, here.stderr
    assert [r["file"] for r in json.loads(here.stdout)["runs"]] == [str(p) for p in _by_run(other)["4" * 32]]
    out = _bench_here("specimen", "show", "S1", "--dir", str(other), "--catalog", shared, "--everywhere", "--json",
                      env=env)
    assert out.returncode == 0, out.stderr
    h = json.loads(out.stdout)
    alive = {**_by_run(runs, "S1"), **_by_run(other, "S1")}  # r2.h5 is gone
    assert sorted(r["file"] for r in h["runs"]) == sorted(str(files[0]) for files in alive.values())
    assert h["hv_cycles"] == sum(_expected(files[0])[1] for files in alive.values()) == 2 * 4
    assert "no longer exist" in out.stderr


def test_specimens_whose_names_differ_only_in_replaced_characters_get_their_own_plots(tmp_path: Path) -> None:
    """`a b` and `a/b` both plotted to specimen-a-b.png by default, the second silently replacing the first (found by
    an exploratory test): each specimen's default plot is its own file."""
    env = _env(tmp_path / "state")
    runs = tmp_path / "runs"
    runs.mkdir()
    ids = ["a b", "a/b"]
    for k, specimen in enumerate(ids):
        _small_run(runs / f"r{k}.h5", f"{k}" * 32, specimen, f"2026-01-0{k + 1}T00:00:00.000+00:00", 3000.0,
                   fit={"mu": 1.0 + k})
    plots = []
    for specimen in ids:  # the first through `python -m bench`, the second in this process
        out = (_bench if specimen == ids[0] else _bench_here)("specimen", "show", specimen, "--dir", str(runs),
                                                              "--json", env=env)
        assert out.returncode == 0, out.stderr
        h = json.loads(out.stdout)
        assert [p["value"] for p in h["parameters"]["mu"]] == [1.0 + ids.index(specimen)]
        plots.append(Path(h["plot"]))
    assert len(set(plots)) == len(ids)  # two specimens, two files, neither overwritten
    assert all(p.parent == runs and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)
    from bench.cli.catalog import plot_name

    assert plot_name("a-b") == "specimen-a-b.png" not in {p.name for p in plots}  # a plain ID keeps its plain name


@pytest.mark.parametrize("specimen", ['{"model": {"L3": null}}', '{"model": "L3"}',
                                      '{"model": {"t0": 0.001, "material": null}}', '{"model": {"t0": "thin"}}'])
def test_an_edited_specimen_attribute_is_no_thickness_not_a_traceback(specimen: str) -> None:
    """The catalogue reads the model's reference thickness from the `specimen` attribute; an edited one (a null, a
    string where an object was) raised TypeError or AttributeError through `bench runs list` (found in review)."""
    from bench.storage.catalog import _specimen

    assert _specimen(Path("r.h5"), {"specimen": specimen}) == (None, None)


def test_a_run_file_linked_into_the_folder_is_inside_it(tmp_path: Path) -> None:
    """A run file reached through a symlink under --dir was listed as outside it (rows are keyed on the resolved
    path) and read again at every listing (found by an outside tester). Now it is one of the folder's runs, its one
    row shared with the folder it lives in."""
    env = _env(tmp_path / "state")
    store, lab = tmp_path / "store", tmp_path / "lab"
    store.mkdir()
    lab.mkdir()
    _small_run(store / "r1.h5", "1" * 32, "S1", "2026-01-01T00:00:00.000+00:00", 3000.0)
    _small_run(lab / "r2.h5", "2" * 32, "S1", "2026-01-02T00:00:00.000+00:00", 5000.0)
    (lab / "linked.h5").symlink_to(store / "r1.h5")
    shared = f"sqlite:///{tmp_path / 'shared.sqlite'}"
    from bench.storage.catalog import reconcile

    with Catalog(shared) as cat:
        reconcile(cat, store)  # the file's row, as its own folder catalogues it
    for url in (f"sqlite:///{lab / 'catalog.sqlite'}", shared):
        out = _bench("runs", "list", "--dir", str(lab), "--catalog", url, "--json", env=env)
        assert out.returncode == 0, out.stderr
        assert sorted(r["run_id"] for r in json.loads(out.stdout)) == ["1" * 32, "2" * 32]
        assert "outside" not in out.stderr
        shown = _bench("specimen", "show", "S1", "--dir", str(lab), "--catalog", url, "--json", env=env)
        assert shown.returncode == 0, shown.stderr
        assert len(json.loads(shown.stdout)["runs"]) == 2 and "outside" not in shown.stderr
    with Catalog(shared) as cat:
        again = reconcile(cat, lab)
        assert (again.added, again.updated, again.removed) == (0, 0, 0)  # the linked file's row is not read again
        assert sorted(Path(r["path"]).name for r in cat.rows()) == ["r1.h5", "r2.h5"]  # one row per file
    out = _bench("runs", "list", "--dir", str(store), "--catalog", shared, "--json", env=env)
    assert [r["run_id"] for r in json.loads(out.stdout)] == ["1" * 32]  # still its own folder's run too


# ---- reading a catalogue on a read-only or full medium ---------------------------------------------------------------


@pytest.fixture
def refuse_writes() -> Iterator[Callable[[Path, str], None]]:
    """``refuse(db, how)``: SQLite refuses every write to the catalogue file ``db`` from here on as a read-only folder
    does (``"readonly"``: "attempt to write a readonly database") or lets it grow no further, as a full disk does
    (``"full"``: "database or disk is full"). SQLite's own refusals, set on each new connection to that file: the
    tests run as root, whom a chmod'ed folder does not stop."""
    from sqlalchemy import event

    refused: dict[str, str] = {}

    def on_connect(dbapi_conn: Any, _record: Any) -> None:
        for _, _name, file in dbapi_conn.execute("PRAGMA database_list").fetchall():
            how = refused.get(file)
            if how == "readonly":
                dbapi_conn.execute("PRAGMA query_only = ON")
            elif how == "full":
                pages = dbapi_conn.execute("PRAGMA page_count").fetchone()[0]
                dbapi_conn.execute(f"PRAGMA max_page_count = {max(pages, 1)}")

    event.listen(sa.engine.Engine, "connect", on_connect)
    try:
        yield lambda db, how: refused.__setitem__(str(db.resolve()), how)
    finally:
        event.remove(sa.engine.Engine, "connect", on_connect)


@pytest.mark.parametrize("how", ["readonly", "full"])
def test_runs_list_and_specimen_show_read_a_catalogue_that_cannot_be_written(
        tmp_path: Path, refuse_writes: Callable[[Path, str], None], how: str) -> None:
    """`bench runs list --dir arch` on a read-only folder failed "error: run catalogue: attempt to write a readonly
    database" (exit 2), `specimen show` too, and "database or disk is full" on a full disk (found by an outside
    tester): the reconciliation's update was let fail the read. Now the listing is made from the files, said in a
    note, and the catalogue file is left as it was."""
    env = _env(tmp_path / "state")
    arch = tmp_path / "arch"
    arch.mkdir()
    _small_run(arch / "r1.h5", "1" * 32, "S1", "2026-01-01T00:00:00.000+00:00", 3000.0)
    assert _bench_here("runs", "list", "--dir", str(arch), env=env).returncode == 0  # its catalogue: r1's row
    db = arch / "catalog.sqlite"
    before = db.read_bytes()
    for k in range(2, 7):  # runs the catalogue has not seen: their rows would need writing (and room)
        _small_run(arch / f"r{k}.h5", str(k) * 32, "S1", f"2026-01-0{k}T00:00:00.000+00:00", 5000.0)
        with h5py.File(arch / f"r{k}.h5", "r+") as f:  # a long note: rows no free room in the file's pages holds
            f.attrs["notes"] = "n" * 20000
    refuse_writes(db, how)
    said = "attempt to write a readonly database" if how == "readonly" else "database or disk is full"
    out = _bench_here("runs", "list", "--dir", str(arch), "--json", env=env)
    assert out.returncode == 0, out.stderr
    assert sorted(r["run_id"] for r in json.loads(out.stdout)) == sorted(_by_run(arch))  # the files, read by h5py
    assert "cannot be written" in out.stderr and said in out.stderr and "not updated" in out.stderr, out.stderr
    shown = _bench_here("specimen", "show", "S1", "--dir", str(arch), "--json", env=env)
    assert shown.returncode == 0, shown.stderr
    assert len(json.loads(shown.stdout)["runs"]) == len(_by_run(arch, "S1")) == 6
    assert db.read_bytes() == before  # nothing written
    table = _bench_here("runs", "list", "--dir", str(arch), env=env)
    assert table.returncode == 0 and "r6.h5" in table.stdout and "cannot be written" in table.stdout, table.stdout


def test_a_read_only_folder_without_a_catalogue_is_listed_from_its_files(
        tmp_path: Path, refuse_writes: Callable[[Path, str], None]) -> None:
    """No catalogue in the folder yet and none can be made there: the listing is the files'."""
    arch = tmp_path / "arch"
    arch.mkdir()
    _small_run(arch / "r1.h5", "1" * 32, "S1", "2026-01-01T00:00:00.000+00:00", 3000.0)
    refuse_writes(arch / "catalog.sqlite", "readonly")
    out = _bench_here("runs", "list", "--dir", str(arch), "--json", env=_env(tmp_path / "state"))
    assert out.returncode == 0, out.stderr
    assert [r["run_id"] for r in json.loads(out.stdout)] == ["1" * 32]
    assert "cannot be written" in out.stderr, out.stderr


def test_specimen_show_skips_a_default_plot_it_cannot_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On a read-only archive the history is shown and the default plot beside the runs skipped, said in one line;
    a --plot asked for that cannot be written is the command's error."""
    from bench.storage import catalog

    arch = tmp_path / "arch"
    arch.mkdir()
    _small_run(arch / "r1.h5", "1" * 32, "S1", "2026-01-01T00:00:00.000+00:00", 3000.0, fit={"mu": 1.0})

    def refused(_h: object, _specimen: str, out: Path) -> Path:
        raise PermissionError(13, "Permission denied", str(out))

    monkeypatch.setattr(catalog, "plot_history", refused)
    env = _env(tmp_path / "state")
    out = _bench_here("specimen", "show", "S1", "--dir", str(arch), "--json", env=env)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["plot"] is None and "plot not written" in out.stderr, out.stderr
    asked = _bench_here("specimen", "show", "S1", "--dir", str(arch), "--plot", str(tmp_path / "p.png"), env=env)
    assert asked.returncode == 2 and "Permission denied" in asked.stderr, asked.stderr


def test_a_full_disk_is_one_short_warning_not_the_sql_statement(short_run: Path, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    """On a full disk the run's catalogue warning held SQLAlchemy's whole text: the INSERT statement and its
    parameters (outside tester). One line now with the database's own reason (SQLite's words for ENOSPC)."""
    import logging
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from bench.storage import catalog

    def full(self: object, rows: object, **kwargs: object) -> None:
        statement = "INSERT INTO runs (path, host, run_id, state) VALUES (?, ?, ?, ?)"
        raise OperationalError(statement, ("/x.h5", "h", "r", "completed"), sqlite3.OperationalError(
            "database or disk is full"))

    monkeypatch.setattr(catalog.Catalog, "upsert", full)
    with caplog.at_level(logging.WARNING, logger=catalog.log.name):
        catalog.record_end(short_run, f"sqlite:///{tmp_path / 'catalog.sqlite'}")
    (line,) = [r.getMessage() for r in caplog.records if "run catalogue" in r.getMessage()]
    assert line.endswith("reconciles it from the files): database or disk is full"), line
    assert "INSERT" not in line and "[SQL" not in line and "parameters" not in line


def test_a_catalogue_another_writer_holds_is_said_while_the_end_row_waits(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Another bench holds the SQLite catalogue in a write transaction: the run's end row waits for it up to the
    busy timeout — ~55 s in which the CLI said nothing (outside tester). A line now says what it waits for, and the
    row still gives up with its one warning."""
    import logging
    import sqlite3

    from bench.storage import catalog as cat_mod

    monkeypatch.setattr(cat_mod, "SQLITE_BUSY_S", 1.0)
    monkeypatch.setattr(cat_mod, "WAIT_NOTICE_S", 0.2)
    run = tmp_path / "r.h5"
    monkeypatch.setattr(cat_mod, "row_from_file", lambda path, hv=None: row_from_attrs(
        path, {"protocol_name": "x", "start_time": "2026-01-01"}))
    url = cat_mod.catalog_url(tmp_path)
    with Catalog(url):
        pass  # the schema exists
    holder = sqlite3.connect(tmp_path / cat_mod.FILE_NAME, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        with caplog.at_level(logging.WARNING, logger=cat_mod.log.name):
            cat_mod.record_end(run)
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    lines = [r.getMessage() for r in caplog.records]
    waiting = [m for m in lines if "waiting for it (another writer holds it" in m]
    assert waiting and str(tmp_path / cat_mod.FILE_NAME) in waiting[0], lines
    assert lines[-1].startswith("run catalogue not written at the end"), lines
    caplog.clear()
    cat_mod.record_end(run)  # free: no line at all
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    # a slow read of the run's own file is no wait for the catalogue (a reviewer: the line came after any delay)
    slow = row_from_attrs(run, {"protocol_name": "x", "start_time": "2026-01-01"})
    monkeypatch.setattr(cat_mod, "row_from_file", lambda path, hv=None: time.sleep(0.5) or slow)
    cat_mod.record_end(run)
    assert not caplog.records, [r.getMessage() for r in caplog.records]


def test_a_listing_of_an_empty_folder_leaves_no_catalogue_behind(tmp_path: Path) -> None:
    """`runs list` and `specimen show` in a folder with no run file made an empty catalog.sqlite there (outside
    tester): a read that keeps nothing writes nothing (a folder with run files gets its catalogue: the tests
    above)."""
    env = {**os.environ, "BENCH_STATE_DIR": str(tmp_path / "state")}
    env.pop("BENCH_CATALOG", None)
    folder = tmp_path / "runs"
    folder.mkdir()
    for args in (["runs", "list", "--dir", str(folder)], ["specimen", "show", "VE-A", "--dir", str(folder)]):
        res = _bench_here(*args, env=env)
        assert "Traceback" not in res.stderr, res.stderr
        assert not (folder / "catalog.sqlite").exists(), (args, res.stdout, res.stderr)


def test_a_run_stopped_before_its_end_is_among_a_specimens_runs_that_did_not_finish() -> None:
    """`specimen show` listed tripped, failed and incomplete runs under "failed / incomplete" but left out a run a
    SIGTERM had interrupted at 0/2 steps (outside tester): it did not finish its protocol either."""
    from bench.storage.catalog import specimen_history

    def row(name: str, state: str, steps: int) -> dict[str, Any]:
        return {"path": f"/runs/{name}.h5", "start_time": f"2026-11-28T09:0{steps}:00", "protocol_name": "p",
                "state": state, "complete": True, "incomplete_reason": "", "reason": state, "fits": "[]",
                "hv_time_s": 1.0, "hv_cycles": 1, "max_nominal_field_V_per_m": None, "breakdown_field_V_per_m": None,
                "steps_completed": steps, "steps_total": 2, "previous_file": None}

    h = specimen_history([row("done", "completed", 2), row("stopped", "interrupted", 0), row("trip", "tripped", 1)])
    assert sorted(f["file"] for f in h["failures"]) == ["/runs/stopped.h5", "/runs/trip.h5"]


def test_a_fit_across_specimens_is_no_point_of_a_specimens_history() -> None:
    """`bench fit ID.h5 S7.h5` warned "not of one specimen … (fitting anyway)", stored the fit, and `specimen show
    S7` listed it as an ageing point beside S7's own fit, unmarked (a second tester). A fit stored with the warning
    (``mixed_specimens``) is left out of the parameters' history, and counted."""
    from bench.storage.catalog import specimen_history

    own = {"model": "membrane", "created": "2026-11-28T10:00:00", "parameters": {"J0": 351.26}, "records": ["s7.h5"]}
    mixed = {**own, "created": "2026-11-28T10:05:00", "parameters": {"J0": 361.54}, "records": ["id.h5", "s7.h5"],
             "mixed_specimens": "the runs are not of one specimen: specimen_id 'S1' vs 'S7'"}
    row = {"path": "/runs/s7.h5", "start_time": "2026-11-28T09:00:00", "protocol_name": "p", "state": "completed",
           "complete": True, "incomplete_reason": "", "reason": "", "fits": json.dumps([own, mixed]),
           "hv_time_s": 1.0, "hv_cycles": 7, "max_nominal_field_V_per_m": None, "breakdown_field_V_per_m": None,
           "steps_completed": 1, "steps_total": 1, "previous_file": None}
    h = specimen_history([row])
    assert [p["value"] for p in h["parameters"]["J0"]] == [351.26] and h["fits_across_specimens"] == 1
