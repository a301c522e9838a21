"""A run file whose writer is gone is not shown, nor filtered, as a run still going (outside tester): a run that
ended on a full disk (its writer abandoned the file at the failed write, its end unstamped) was listed "running,
incomplete" by `bench runs list`, `inspect` and the campaign line, and under `--state running`; `report` and `plot`
said "(running)" for such files; `inspect` said "running" of a paused run.

Expected wording from README.md ("Reading while a run writes, and after a crash"): a storage-fault file is listed
"ended unstamped: disk full, incomplete" ("ended unstamped: write failed" for another failure), a killed one
"crashed or killed, incomplete"; `--state running` leaves both out; a paused run reads "paused".
"""

from __future__ import annotations

import errno
import json
import random
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from bench.cli import app
from tests.conftest import ROOT
from tests.test_storage import _env, _kill_once, _limit_file_size, _run_fault_writer, _tmpfs

SHOWN = {"disk-full": "ended unstamped: disk full", "file-size-limit": "ended unstamped: write failed",
         "killed": "crashed or killed"}


def _cli(*args: str, catalog: Path | None = None) -> tuple[int, str]:
    env = {"COLUMNS": "300"} | ({"BENCH_CATALOG": f"sqlite:///{catalog}"} if catalog else {})
    res = CliRunner().invoke(app, list(args), env=env)
    return res.exit_code, res.output


def _ended_file(tmp_path: Path, how: str) -> Path:
    """A file whose writer is gone: a disk filled (a 256-kB tmpfs), a file-size limit hit, or a kill -9."""
    folder = tmp_path / "runs"
    folder.mkdir()
    if how == "disk-full":
        with _tmpfs(tmp_path / "small", "256k") as disk:
            _, out = _run_fault_writer(disk / "run.h5")
            moved = Path(shutil.copy(disk / "run.h5", folder / "run.h5"))
        assert f"(errno {errno.ENOSPC})" in out["errors"][0], out["errors"]
        return moved
    if how == "file-size-limit":
        _, out = _run_fault_writer(folder / "run.h5", _limit_file_size(300_000))
        assert f"(errno {errno.EFBIG})" in out["errors"][0], out["errors"]
        return folder / "run.h5"
    _, path = _kill_once(folder, 0, random.Random(5))
    return path


@pytest.mark.parametrize("how", ["disk-full", "file-size-limit", "killed"])
def test_a_file_whose_writer_is_gone_is_not_listed_inspected_or_filtered_as_running(tmp_path: Path, how: str) -> None:
    from bench.storage.chain import chain, describe
    from bench.storage.runfile import open_run

    path = _ended_file(tmp_path, how)
    with h5py.File(path, "r", swmr=True) as f:
        assert f["status/state"][0] == b"running" and not f.attrs.get("complete", False)  # nothing stamped its end
    shown = SHOWN[how]
    assert open_run(path).state_shown == shown
    code, out = _cli("inspect", str(path))
    flat = " ".join(out.split())
    assert code == 1 and f"{shown} — INCOMPLETE" in flat and "running —" not in flat, out
    cat = tmp_path / "cat.sqlite"
    code, out = _cli("runs", "list", "--dir", str(path.parent), catalog=cat)
    assert code == 0, out
    row = next(ln for ln in out.splitlines() if path.name in ln)
    assert f"{shown}, incomplete" in row and "running" not in row, out
    code, out = _cli("runs", "list", "--dir", str(path.parent), "--state", "running", "--json", catalog=cat)
    assert code == 0 and json.loads(out) == [], out
    code, out = _cli("runs", "list", "--dir", str(path.parent), "--state", "ended", "--json", catalog=cat)
    assert code == 0 and [Path(r["path"]).name for r in json.loads(out)] == [path.name], out  # selectable (a reviewer)
    # --json says it too, beside the file's own state (an outside tester: a script read "running" there)
    assert [(r["state"], r["state_shown"]) for r in json.loads(out)] == [("running", shown)], out
    assert describe(chain(path)) == f"{path.name} ({shown}, incomplete)"  # inspect's and report's campaign line


def test_a_row_read_while_the_run_went_on_is_read_again_once_its_writer_is_gone(tmp_path: Path) -> None:
    """A row catalogued while the run was going ("still going") stayed so after its writer was killed: a killed
    run's file does not change, and an unchanged file's row was never read again."""
    from bench.storage.catalog import Catalog, catalog_url, row_from_file

    path = _ended_file(tmp_path, "killed")
    row = row_from_file(path)
    row["incomplete_reason"] = "no end recorded: the run is still going, or it crashed / was killed"  # as read live
    cat = tmp_path / "cat.sqlite"
    with Catalog(catalog_url(path.parent, f"sqlite:///{cat}")) as c:
        c.upsert([row])
    code, out = _cli("runs", "list", "--dir", str(path.parent), "--state", "running", "--json", catalog=cat)
    assert code == 0 and json.loads(out) == [], out
    code, out = _cli("runs", "list", "--dir", str(path.parent), catalog=cat)
    assert code == 0, out
    row_txt = next(ln for ln in out.splitlines() if path.name in ln)
    assert "crashed or killed, incomplete" in row_txt, out


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from bench.runtime.run import execute, plan_run

    d = tmp_path_factory.mktemp("sweep")
    done = execute(plan_run(ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"), d / "sweep.h5", virtual=True)
    assert done.state == "completed", done.reason
    return done.path


def _unstamped_on_full_disk(src: Path, dst: Path) -> Path:
    """``src`` as its writer leaves it when a write fails on a full disk: state running, the fault in
    /status/reason, the end never stamped (README: "storage fault: <the error>" put into /status/reason)."""
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        f["status/state"][0] = b"running"
        f["status/reason"][0] = f"storage fault: run file {dst}: write failed: No space left on device (errno 28)"
        f["status/end_time"][0] = b""
        f.attrs["complete"] = False
    return dst


def test_report_and_plot_say_an_unstamped_file_ended(sweep: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.figure

    from bench.analysis.quicklook import quicklook

    path = _unstamped_on_full_disk(sweep, tmp_path / "full.h5")
    _, out = _cli("report", str(path), "--out", str(tmp_path / "rep"))
    flat = " ".join(out.split())
    assert f"INCOMPLETE {path.name} (ended unstamped: disk full): no end recorded: the disk was full" in flat, out
    assert "(running)" not in flat, out
    _, out = _cli("report", str(path), "--out", str(tmp_path / "rep"), "--json")
    assert [r["state_shown"] for r in json.loads(out)["runs"]] == ["ended unstamped: disk full"], out
    titles: list[str] = []
    drawn: list[tuple[matplotlib.figure.Figure, matplotlib.text.Text]] = []
    real = matplotlib.figure.Figure.suptitle

    def suptitle(self, t, **kw):  # type: ignore[no-untyped-def]
        titles.append(t)
        text = real(self, t, **kw)
        drawn.append((self, text))
        return text

    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle", suptitle)
    quicklook(path, ["amplifier"], tmp_path / "plot.png")
    assert len(titles) == 1 and "(ended unstamped: disk full, INCOMPLETE:" in " ".join(titles[0].split()), titles
    # the whole title on the figure (an outside tester: a long state was cut off at both edges)
    fig, text = drawn[0]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    box = text.get_window_extent(renderer=FigureCanvasAgg(fig).get_renderer())
    assert 0 <= box.x0 and box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height, (box, fig.bbox)


PAUSED_WRITER = """
import sys
from pathlib import Path
from bench.storage.recorder import Column, Recorder
rec = Recorder(Path(sys.argv[1]), {"protocol_name": "pause test"}, {"laser": [Column("displacement", "m", "")]}, [],
               {"laser": 1000.0})
rec.append("laser", 0.0, displacement=0.0)
rec.event(0.5, 0, "pause", "paused in step 0 (a) by tester: output to 0 V")
rec.flush()
print("paused", flush=True)
sys.stdin.readline()
rec.event(1.0, 0, "resume", "resumed by tester after 0.5 s paused")
rec.flush()
print("resumed", flush=True)
sys.stdin.readline()
rec.event(1.5, 0, "pause", "paused in step 0 (a) by tester: output to 0 V")
rec.flush()
print("paused", flush=True)
sys.stdin.readline()
"""


def _listed(path: Path, cat: Path) -> str:
    """The state `bench runs list` shows for ``path`` (its cell in the table)."""
    code, out = _cli("runs", "list", "--dir", str(path.parent), catalog=cat)
    assert code == 0, out
    row = next(ln for ln in out.splitlines() if path.name in ln)
    return next(c.strip() for c in row.split("│") if "incomplete" in c or c.strip() in ("running", "completed"))


def _selected(path: Path, cat: Path, state: str) -> list[str]:
    """The file names `bench runs list --state STATE --json` lists in ``path``'s folder."""
    code, out = _cli("runs", "list", "--dir", str(path.parent), "--state", state, "--json", catalog=cat)
    assert code == 0, out
    return [Path(r["path"]).name for r in json.loads(out)]


def test_inspect_says_a_paused_run_is_paused_while_it_is(tmp_path: Path) -> None:
    path = tmp_path / "paused.h5"
    proc = subprocess.Popen([sys.executable, "-c", PAUSED_WRITER, str(path)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    try:
        assert proc.stdin is not None and proc.stdout is not None
        assert proc.stdout.readline().strip() == "paused", proc.stderr
        _, out = _cli("inspect", str(path))
        flat = " ".join(out.split())
        assert "state │ paused — INCOMPLETE" in flat and "running —" not in flat, out
        # the catalogue's listing too (it listed a paused run "running": last session's note)
        cat = tmp_path / "cat.sqlite"
        assert _listed(path, cat) == "paused, incomplete"
        assert _selected(path, cat, "paused") == [path.name]
        assert _selected(path, cat, "running") == [] and _selected(path, cat, "ended") == []
        proc.stdin.write("\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "resumed"
        _, out = _cli("inspect", str(path))
        assert "state │ running — INCOMPLETE" in " ".join(out.split()), out  # resumed: running again
        assert _listed(path, cat) == "running, incomplete"  # the row is read again: its file changed
        assert _selected(path, cat, "paused") == [] and _selected(path, cat, "running") == [path.name]
        proc.stdin.write("\n")  # paused once more, then killed while paused: its file stands still
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "paused"
        assert _listed(path, cat) == "paused, incomplete"
        proc.kill()
        proc.wait(30)
        # the unchanged file's row is read again: a paused row asks as a running one does (a reviewer: it stayed
        # "paused" for good, left out of --state ended)
        assert _listed(path, cat) == "crashed or killed, incomplete"
        assert _selected(path, cat, "ended") == [path.name] and _selected(path, cat, "paused") == []
    finally:
        proc.kill()
        proc.wait(30)


@pytest.mark.parametrize("how", ["file-size-limit", "killed"])
def test_the_watch_page_says_a_file_whose_writer_is_gone_ended(tmp_path: Path, how: str,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """`bench watch` on such a file showed it running for good (its page waited on a run that had ended): the
    follower says the state a listing shows — a failed write at once, a dead writer once the file's status has not
    moved for a while and no process holds it open."""
    import bench.watch.follow as follow

    monkeypatch.setattr(follow, "MIN_LOOK_S", 0.0)
    monkeypatch.setattr(follow, "GONE_AFTER_S", 0.0)  # the file's status stands still from the first look on
    f = follow.Follower(_ended_file(tmp_path, how), pixels=100, budget=2_000)
    try:
        f.look()
        f.look()
        assert f.info["state"] == SHOWN[how], f.info
    finally:
        f.close()


def test_a_damaged_catalogue_is_listed_from_the_files_and_rebuild_sets_it_aside(short_run: Path,
                                                                                 tmp_path: Path) -> None:
    """A catalogue file that is not a database (an outside tester wrote garbage into it): `runs list` and `catalog
    rebuild` both stopped at "run catalogue: file is not a database", naming no file, and nothing in the tool could
    mend it. The catalogue is an index of the run files: `runs list` lists from the files, saying the catalogue is
    damaged and what mends it; `catalog rebuild` moves the damaged file aside (kept) and makes a new one."""
    runs = tmp_path / "runs"
    runs.mkdir()
    shutil.copy(short_run, runs / "run.h5")
    cat = runs / "catalog.sqlite"  # the default catalogue of the folder
    garbage = b"this is not a database" * 300
    cat.write_bytes(garbage)
    res = CliRunner().invoke(app, ["runs", "list", "--dir", str(runs), "--json"], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    assert [Path(r["path"]).name for r in json.loads(res.stdout)] == ["run.h5"]
    assert f"run catalogue {cat} is damaged (file is not a database)" in " ".join(res.stderr.split()), res.stderr
    assert cat.read_bytes() == garbage  # a listing changes nothing
    res = CliRunner().invoke(app, ["catalog", "rebuild", str(runs)], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    (aside,) = runs.glob("catalog.sqlite.damaged-*")
    assert aside.read_bytes() == garbage and f"catalogue {cat} was damaged" in " ".join(res.output.split())
    res = CliRunner().invoke(app, ["runs", "list", "--dir", str(runs), "--json"])
    assert res.exit_code == 0 and "is damaged" not in res.stderr, res.stderr
    assert [Path(r["path"]).name for r in json.loads(res.stdout)] == ["run.h5"]
