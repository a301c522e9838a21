"""``bench watch`` / ``bench run --web``: the server's min/max bins, its gate (token, served files only), the stop word
of the control file, and the page in a real browser (Debian's Chromium driven by Playwright) stopping a run.

Expected bins come from numpy over the records' index ranges (the definition: bin k holds records k·size …
(k+1)·size − 1), never from the code under test; how a stop ends a run, from the run file's own events.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.runtime.control import control_path, write_control
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from bench.storage.recorder import Column, Recorder
from bench.storage.runfile import open_run
from bench.watch.follow import Bins, Follower
from tests.conftest import ROOT
from tests.load_trips import load_trip as _load_trip

SHORT = ROOT / "protocols" / "short"
DAQ_RIG = ROOT / "rigs" / "thesis-daq-sim.toml"
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}
RIG_TOML = '[limits]\nmax_voltage_V = 8000.0\nmax_current_A = 0.005\n'


def expected_bins(v: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(v.size) // size
    return (np.array([v[k == j].min() for j in range(k[-1] + 1)]),
            np.array([v[k == j].max() for j in range(k[-1] + 1)]))


def test_bins_keep_every_extreme_and_stay_within_a_screen() -> None:
    rng = np.random.default_rng(3)
    n = 200_003
    t, v = np.arange(n) / 1e4, rng.normal(size=n)
    v[12_345] = 99.0  # one spike: a screen column must still show it
    b = Bins(["v"], pixels=64)
    a = 0
    while a < n:  # the writer's flushes: uneven blocks
        m = int(rng.integers(1, 7_000))
        b.add({"t": t[a:a + m], "v": v[a:a + m]})
        a += m
    assert b.records == n
    assert 64 <= b.t_lo.size <= 128  # between pixels and twice that, whatever the length
    lo, hi = expected_bins(v, b.size)
    t_lo, t_hi = expected_bins(t, b.size)
    np.testing.assert_array_equal(b.lo["v"], lo)
    np.testing.assert_array_equal(b.hi["v"], hi)
    np.testing.assert_array_equal(b.t_lo, t_lo)
    np.testing.assert_array_equal(b.t_hi, t_hi)
    assert b.hi["v"].max() == 99.0


def test_a_client_is_sent_only_what_it_lacks() -> None:
    b = Bins(["v"], pixels=8)
    v = np.arange(40.0)
    b.add({"t": v[:10], "v": v[:10]})
    first = b.since(-1, 0)
    assert first["from"] == 0 and len(first["t_lo"]) == b.t_lo.size
    b.add({"t": v[10:13], "v": v[10:13]})  # 13 records, size 1: 13 bins ≤ 16, no merge
    more = b.since(first["generation"], len(first["t_lo"]))
    assert more["generation"] == first["generation"] and more["from"] == 9  # the last bin held may have grown
    held = first["hi"]["v"][:more["from"]] + more["hi"]["v"]
    assert held == list(v[:13])
    b.add({"t": v[13:], "v": v[13:]})  # 40 records > 16 bins: merged, a new generation, all sent again
    again = b.since(more["generation"], len(held))
    assert again["generation"] != more["generation"] and again["from"] == 0
    assert again["hi"]["v"] == list(expected_bins(v, b.size)[1])


def write_run(path: Path, n: int, finish: bool = True) -> np.ndarray:
    """A small run file through the recorder: a 1-kHz voltage ramp with a rig whose limits are known."""
    streams = {"amplifier": [Column("voltage", "V", ""), Column("current", "A", "")],
               "laser": [Column("displacement", "m", ""), Column("valid", "1", "", "u1")]}
    rec = Recorder(path, {"protocol_name": "watch-test", "rig_name": "watch-rig", "rig_toml": RIG_TOML}, streams, [],
                   dict.fromkeys(streams, 1000.0))
    t = np.arange(n) / 1000.0
    v = 10.0 * np.arange(n)
    rec.append("amplifier", t, voltage=v, current=1e-6 * v)
    rec.append("laser", t, displacement=1e-7 * v, valid=np.ones(n, "u1"))
    rec.event(0.0, 0, "start", "ramp | steps[0](ramp)")
    if finish:
        rec.finish("completed", "test")
    else:
        rec.flush()
    return v


def test_the_follower_reads_a_file_in_bounded_looks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("bench.watch.follow.MIN_LOOK_S", 0.0)
    path = tmp_path / "run.h5"
    v = write_run(path, 5_000)
    f = Follower(path, pixels=100, budget=2_000)
    f.look()
    assert f.bins["amplifier"].records == 2_000 and f.info["behind"]["amplifier"] == 3_000
    f.look()
    f.look()
    data = f.payload({})
    f.close()
    amp = data["streams"]["amplifier"]
    assert amp["records"] == 5_000 and data["state"] == "completed"
    assert set(amp["lo"]) == {"voltage", "current"} and set(data["streams"]["laser"]["lo"]) == {"displacement"}
    assert min(amp["lo"]["voltage"]) == v.min() and max(amp["hi"]["voltage"]) == v.max()
    assert amp["units"]["voltage"] == "V" and data["limits"] == {"V": 8000.0, "A": 0.005}
    assert [e["kind"] for e in data["events"]] == ["start"]


# ---------------------------------------------------------------- the server's gate
@pytest.fixture
def served(tmp_path: Path) -> tuple[Path, Path]:
    folder, other = tmp_path / "served", tmp_path / "other"
    folder.mkdir()
    other.mkdir()
    write_run(folder / "a.h5", 300)
    write_run(other / "secret.h5", 300)
    return folder, other


def client(folder: Path, token: str | None = None, loopback: bool = True):
    from starlette.testclient import TestClient

    from bench.watch.server import Served, create_app

    return TestClient(create_app(Served([], [folder]), token=token, loopback=loopback))


def test_without_the_token_every_request_is_refused(served: tuple[Path, Path]) -> None:
    with client(served[0], token="s3cret", loopback=False) as c:
        for url in ("/", "/api/runs", "/api/runs/a.h5", "/static/watch.js"):
            assert c.get(url).status_code == 401, url
        assert c.get("/api/runs", headers={"X-Bench-Token": "wrong"}).status_code == 401
        assert c.post("/api/runs/a.h5/stop", headers={"X-Bench": "1"}).status_code == 401
        assert not control_path(served[0] / "a.h5").exists()
        assert c.get("/api/runs", headers={"X-Bench-Token": "s3cret"}).json() == {"runs": ["a.h5"]}
        page = c.get("/?token=s3cret")  # the printed address: the page loads and keeps the token as a cookie
        assert page.status_code == 200 and "bench watch" in page.text
        assert c.get("/static/watch.js").status_code == 200  # the cookie carries it


def test_a_path_outside_the_served_folder_is_refused(served: tuple[Path, Path]) -> None:
    folder, other = served
    with client(folder) as c:
        assert c.get("/api/runs/a.h5").json()["state"] == "completed"
        for name in ("secret.h5", "..%2Fother%2Fsecret.h5", "%2E%2E", str(other / "secret.h5").replace("/", "%2F")):
            r = c.get(f"/api/runs/{name}")
            assert r.status_code == 404 and "secret" not in r.text, name
        assert c.get("/static/..%2F..%2Fserver.py").status_code == 404
        assert c.get("/api/runs", headers={"Host": "attacker.example"}).status_code == 400  # DNS rebinding


def test_actions_are_pause_and_stop_only_and_need_a_live_run(served: tuple[Path, Path]) -> None:
    run = served[0] / "a.h5"
    with client(served[0]) as c:
        assert c.post("/api/runs/a.h5/resume", headers={"X-Bench": "1"}).status_code == 404
        assert c.post("/api/runs/a.h5/stop").status_code == 403  # no X-Bench header: a cross-site form
        r = c.post("/api/runs/a.h5/stop", headers={"X-Bench": "1"})
        assert r.status_code == 409 and "completed" in r.json()["error"]
    assert not control_path(run).exists()


def test_an_h5_that_is_no_run_file_is_one_line_on_the_page(served: tuple[Path, Path]) -> None:
    import h5py

    with h5py.File(served[0] / "other.h5", "w") as f:
        f["x"] = np.arange(3)
    with client(served[0]) as c:
        r = c.get("/api/runs/other.h5")
        assert r.status_code == 500 and r.json()["error"].startswith("other.h5: ") and "\n" not in r.json()["error"]


def test_a_status_bench_does_not_write_is_one_line_naming_the_field(served: tuple[Path, Path]) -> None:
    import h5py

    with h5py.File(served[0] / "a.h5", "r+") as f:  # a state no run writes: shown as if it were one before
        f["status/state"][0] = b"exploded"
    with client(served[0]) as c:
        r = c.get("/api/runs/a.h5")
        assert r.status_code == 500 and "/status/state" in r.json()["error"] and "\n" not in r.json()["error"]


def test_the_web_extra_missing_is_one_line(served: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from bench.cli import app

    monkeypatch.setitem(sys.modules, "uvicorn", None)
    result = CliRunner().invoke(app, ["watch", str(served[0] / "a.h5")])
    assert result.exit_code == 2 and "dea-bench[web]" in result.output and "Traceback" not in result.output


def test_without_the_web_extra_watch_is_one_line_in_a_fresh_process(served: tuple[Path, Path]) -> None:
    """A user's install without the extra: neither Starlette nor uvicorn importable, nothing imported before."""
    code = ("import runpy, sys; sys.modules['starlette'] = None; sys.modules['uvicorn'] = None; "
            f"sys.argv = ['bench', 'watch', {str(served[0] / 'a.h5')!r}]; "
            "runpy.run_module('bench', run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert [line for line in r.stderr.splitlines() if line.strip()] == [
        "error: bench watch needs the web extra: pip install 'dea-bench[web]'"], r.stderr


def test_a_busy_web_port_is_one_line_before_the_run(tmp_path: Path) -> None:
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "bench", "run", str(SHORT / "thesis-identification-short.toml"),
                            "--web", "--web-port", str(port), "--no-live", "--virtual-time", "--out", str(tmp_path)],
                           cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and f"cannot serve on 127.0.0.1:{port}" in r.stderr and "Traceback" not in r.stderr
    assert not list(tmp_path.glob("*.h5"))  # refused before the run started


# ---------------------------------------------------------------- the stop word of the control file
def test_the_stop_word_ends_the_run_safely_and_says_who_asked(tmp_path: Path) -> None:
    out = tmp_path / "run.h5"

    def hook(engine: Engine, sim) -> None:
        def at(_now: float) -> None:
            if engine.now() >= 2.0 and not control_path(out).exists():
                write_control(out, True, "web 10.0.0.7", "the stop button of the watch page", stop=True)
        sim.clock.subscribe(at)

    result = execute(plan_run(SHORT / "thesis-identification-short.toml", DAQ_RIG), out, virtual=True, on_engine=hook)
    assert result.state == "interrupted" and "web 10.0.0.7" in result.reason
    run = open_run(result.path)
    kinds = [e[2] for e in run.event_list()]
    assert "pause" not in kinds  # a stop, not a pause first
    (request,) = [e for e in run.event_list() if e[2] == "request"]
    assert 2.0 <= request[0] < 10.0 and "web 10.0.0.7" in request[3] and "stop button" in request[3]
    assert kinds[-1] == "safe" and run.state == "interrupted"


# ---------------------------------------------------------------- the page in a real browser
def _chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None or not _has("playwright"):
        if os.environ.get("CI"):
            pytest.fail("CI: Chromium (apt) and playwright (test extra) are required for the browser test")
        pytest.skip("no system Chromium or no playwright")
    return found


def _has(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


ENDED = "!['waiting', 'running', 'paused'].includes(window.benchWatch.state)"  # the page: the run has ended


class _LoadTripError(Exception):
    """The run tripped because the loaded host fell behind, before the page's buttons were pressed."""


def test_the_page_follows_a_run_and_its_stop_button_makes_it_safe(tmp_path: Path) -> None:
    """A wall-clock run on the simulated DAQ rig with --web; the page's plots grow; its pause button pauses the run,
    its stop button ends it; both recorded in the file as coming from the page's address.

    A wall-clock run on a starved host trips (a stream-out underrun: CI, 2026-11-27), as the lab's would: such a run
    is checked to have ended tripped, stamped and safe, and the page is tried again on a new run (three runs at most;
    then skipped, as the other wall-clock tests are on a host too loaded for their premise).
    """
    chromium = _chromium()
    tripped = ""
    for attempt in range(3):
        folder = tmp_path / f"try{attempt}"
        folder.mkdir()
        try:
            proc, output = _page_pauses_and_stops(folder, chromium)
            break
        except _LoadTripError as trip:
            tripped = str(trip)
            run = open_run(next(folder.glob("*.h5")))
            assert run.complete and _load_trip(run), tripped
            assert [e[2] for e in run.event_list()][-1] == "safe", tripped
    else:  # each checked tripped, stamped and safe: the page's premise (a run that goes on) lost on this host,
        pytest.skip(f"three wall-clock runs tripped by the loaded host; the last:\n{tripped}")  # as elsewhere
    _check_the_page_s_stop(folder, proc, output)


def _page_pauses_and_stops(tmp_path: Path, chromium: str) -> tuple[subprocess.Popen[str], str]:
    """Run with --web in ``tmp_path``; the page sees the plots grow, pauses the run, then stops it."""
    from playwright.sync_api import sync_playwright

    # the short identification protocol with a 60-s drive, so a loaded machine (the server starting, the browser)
    # cannot see it end before the page stops it
    text = (SHORT / "thesis-identification-short.toml").read_text(encoding="utf-8")
    protocol = tmp_path / "identification-60s.toml"
    protocol.write_text(text.replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/').replace(
        'name = "thesis-identification-short"', 'name = "identification-60s"').replace(
        "duration_s = 10.0", "duration_s = 60.0"), encoding="utf-8")
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(protocol),
                             "--web", "--web-port", "0", "--no-live", "--out", str(tmp_path)], cwd=ROOT,
                            env={**ENV, "BENCH_STATE_DIR": str(tmp_path / "state")}, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            m = re.search(r"watch the run at (http://127\.0\.0\.1:\d+/)", line)
            if m:
                address = m.group(1)
                break
        else:
            raise AssertionError("no address printed:\n" + "".join(lines))
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=_nicer(chromium, tmp_path), args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            end = time.monotonic() + 60
            while True:  # the server process starts beside the run
                try:
                    page.goto(address)
                    break
                except Exception:
                    if time.monotonic() > end:
                        raise
                    time.sleep(0.3)
            servers = _children(proc.pid)  # the page's server yields the CPU to the run that feeds the DAQ
            run_nice = os.getpriority(os.PRIO_PROCESS, proc.pid)  # 19: the lowest already, none can be lower
            assert servers and all(os.getpriority(os.PRIO_PROCESS, c) > run_nice or run_nice == 19
                                   for c in servers), servers
            page.wait_for_function("(window.benchWatch.records.amplifier || 0) > 0", timeout=60_000)
            first = page.evaluate("window.benchWatch.records.amplifier")
            page.wait_for_function(  # or the run ended (a trip: said at once, not after the timeout)
                f"window.benchWatch.records.amplifier > {first} + 20000 || {ENDED}", timeout=30_000)
            grown = page.evaluate("window.benchWatch")
            assert grown["state"] == "running" and grown["panels"] >= 3 and grown["points"] > 0
            if os.environ.get("BENCH_SCREENSHOT"):
                page.screenshot(path=str(ROOT / "docs" / "watch.png"))
            page.click("#pause")
            page.wait_for_function(f"window.benchWatch.state === 'paused' || {ENDED}", timeout=30_000)
            assert page.evaluate("window.benchWatch.state") == "paused"
            assert "pause asked" in page.inner_text("#message")
            page.click("#stop")
            page.wait_for_function("window.benchWatch.state === 'interrupted'", timeout=30_000)
            assert "stop asked" in page.inner_text("#message")
            browser.close()
        rest, _ = proc.communicate(timeout=60)
    except Exception as exc:  # say how the run went: a wait that timed out alone says nothing
        try:  # a run that tripped is ending (its file being stamped): read on, a full pipe would block it
            rest = proc.communicate(timeout=10)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            rest = proc.communicate()[0]  # with what the first call had read
        printed = f"{exc}\nbench run printed:\n{''.join(lines)}{rest}"
        if _tripped_by_load_before_the_page(tmp_path):
            raise _LoadTripError(printed) from exc
        raise AssertionError(printed) from exc
    finally:
        proc.kill()
    return proc, "".join(lines) + rest


def _tripped_by_load_before_the_page(folder: Path) -> bool:
    """Whether the run in ``folder`` ended tripped by a loaded host (tests/load_trips.py) before the page paused or
    stopped it (its file holds no pause and no stop request): what a starved host does, not the page."""
    found = sorted(folder.glob("*.h5"))
    try:
        run = open_run(found[0])
    except (IndexError, OSError, ValueError):  # no run file, or none readable: not such a trip
        return False
    kinds = [e[2] for e in run.event_list()]
    return _load_trip(run) and not {"pause", "request"} & set(kinds)


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux: /proc/PID/task/*/children)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _nicer(chromium: str, folder: Path) -> str:
    """A launcher of ``chromium`` at lower CPU priority: the test's browser, as the page's server, must not starve
    the run it watches on a loaded host (the lab's browser is not the test's to slow down)."""
    launcher = folder / "chromium-nice"
    launcher.write_text(f'#!/bin/sh\nexec nice -n 10 "{chromium}" "$@"\n', encoding="ascii")
    launcher.chmod(0o755)
    return str(launcher)


def _check_the_page_s_stop(tmp_path: Path, proc: subprocess.Popen[str], output: str) -> None:
    """The run that the page paused and stopped: the file says so and the output is at 0 V."""
    assert proc.returncode == 1, output  # interrupted
    run = open_run(next(tmp_path.glob("*.h5")))
    assert run.state == "interrupted" and "web 127.0.0.1" in run.reason, output
    (pause,) = [e for e in run.event_list() if e[2] == "pause"]
    (request,) = [e for e in run.event_list() if e[2] == "request"]
    assert "web 127.0.0.1" in pause[3] and "pause button" in pause[3]
    assert "web 127.0.0.1" in request[3] and "stop button" in request[3]
    assert [e[2] for e in run.event_list()][-1] == "safe"
    assert pause[0] < request[0] < 60.0  # paused, then stopped inside the 60-s drive
    assert "resume" not in [e[2] for e in run.event_list()]  # the stop ended the pause: no step restarted
    # the output left at 0 V: the last set-point sent within the fault matrix's 0-V band (bench.benchmarks.faults
    # ZERO_V, 5 V), and the monitor read back near 0 V. The set-points stream, not the amplifier stream's last scan:
    # a stop that lands during the pause's ramp-down ends the run before any paused reading, and a DAQ rig's
    # amplifier stream ends on its last streamed scan (still at the step's voltage), the ramp being command-response
    assert abs(run.streams["setpoints"].columns["voltage"][-1]) <= 5.0
    assert "verified: voltage monitor" in run.event_list()[-1][3], run.event_list()[-1]
    assert not control_path(run.path).exists()  # its stop word: the request event above (removed at the run's end)
