"""The watch server's cost and freshness (``bench benchmark watch``).

* CPU and lag: a wall-clock run of ``protocols/short/thesis-identification-short.toml`` on the simulated LabJack T7
  rig (voltage, current, commanded voltage and displacement at 10 kHz: 4 × 10 kHz) in its own process, and
  ``bench watch`` on its file in another, polled as the page polls it (every 0.5 s, only what it lacks). The
  server's CPU share of one core is its process's CPU time (``/proc/PID/stat``) over the wall time from its first
  answer to the run's end. Its lag behind the file is, just before each poll (the page's oldest moment), the last
  confirmed time in the file (read here through SWMR) less the last time the page was sent.
* Page data: what a page opening the file is sent (JSON), for a short and a long synthetic file written through
  the recorder (as the export benchmark does). The long one spans 12 hours at a rate this machine's disk allows
  in a benchmark (a 12-hour 4 × 10 kHz file is about 100 GB uncompressed); the page's size depends on the screen
  (bins per stream), not on the rate or the length, which the two rows show.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

from bench.benchmarks import copy_protocol
from bench.benchmarks.acquisition import Figure
from bench.resources import protocols_dir
from bench.storage.recorder import Column, Recorder
from bench.storage.runfile import open_h5, valid_counts
from bench.watch import free_port
from bench.watch.follow import PIXELS

POLL_S = 0.5  # as the page (bench/watch/static/watch.js)
QUICK_DRIVE_S = 1.5  # --quick: the followed run's drive [s] (the full run: the protocol's 10 s)
BLOCK = 50_000


def write_file(path: Path, seconds: float, rate: float) -> int:
    """A synthetic run file: 4 analog channels (voltage, current, commanded, displacement) at ``rate`` for
    ``seconds``; returns the scans."""
    streams = {"amplifier": [Column("voltage", "V", ""), Column("current", "A", ""), Column("commanded", "V", "")],
               "laser": [Column("displacement", "m", ""), Column("valid", "1", "", "u1")]}
    rng = np.random.default_rng(0)
    n = int(seconds * rate)
    rec = Recorder(path, {"protocol_name": "benchmark-watch"}, streams, [], dict.fromkeys(streams, rate))
    for a in range(0, n, BLOCK):
        t = np.arange(a, min(a + BLOCK, n)) / rate
        v = 3500.0 * (1 - np.cos(2 * np.pi * t / 9))
        noise = rng.normal(0.0, 1.0, t.size)
        rec.append("amplifier", t, voltage=v + 0.5 * noise, current=1e-4 * np.sin(2 * np.pi * t / 9), commanded=v)
        rec.append("laser", t, displacement=1e-3 * v / 7000 + 1e-8 * noise, valid=np.ones(t.size, "u1"))
        rec.maybe_flush()
    rec.finish("completed", "benchmark")
    return n


def page_bytes(path: Path) -> tuple[int, int]:
    """(bytes of JSON, bins) a page opening ``path`` is sent."""
    from bench.watch.follow import Follower

    f = Follower(path, budget=10**12)
    f.look()
    data = f.payload({})
    f.close()
    return len(json.dumps(data).encode()), max(len(s["t_lo"]) for s in data["streams"].values())


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _file_end(path: Path) -> float:
    """The last confirmed time of the amplifier stream (run clock)."""
    with open_h5(path) as f:
        n = valid_counts(f).get("amplifier", 0)
        if n == 0:
            return 0.0
        t = f["amplifier/t"]
        t.refresh()
        return float(t[n - 1])


def _protocol(tmp: Path, quick: bool) -> tuple[Path, float]:
    """The run the server follows and its length [s]: the short thesis identification (10 s of drive, 1 s of rest);
    ``quick``: a copy cut to :data:`QUICK_DRIVE_S` of drive (the CPU share and the lag are rates, over fewer polls)."""
    import tomlkit

    source = protocols_dir() / "short" / "thesis-identification-short.toml"
    if quick:
        def cut(doc: Any) -> None:
            doc["steps"][0]["duration_s"] = QUICK_DRIVE_S

        source = copy_protocol(source, tmp / "watch-quick.toml", cut)
    steps: Any = tomlkit.parse(source.read_text(encoding="utf-8"))["steps"]
    return source, float(sum(step["duration_s"] for step in steps))


def live(tmp: Path, protocol: Path) -> tuple[float, float, float, int]:
    """(CPU share %, worst lag s, median lag s, polls) of ``bench watch`` following a wall-clock 4 × 10 kHz run of
    ``protocol``: the server is started on the run's folder as the run starts (both processes load at once), and
    serves the run's file once it is there."""
    env = {**os.environ, "BENCH_STATE_DIR": str(tmp / "state")}
    folder = tmp / "runs"
    folder.mkdir()
    port = free_port()
    run = subprocess.Popen([sys.executable, "-m", "bench", "run", str(protocol), "--no-live", "--out", str(folder)],
                           env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    watch = subprocess.Popen([sys.executable, "-m", "bench", "watch", str(folder), "--port", str(port)], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 120
        while not list(folder.glob("*.h5")):
            if run.poll() is not None or time.monotonic() > end:
                raise RuntimeError("the benchmark run did not start")
            time.sleep(0.05)
        path = next(folder.glob("*.h5"))
        url = f"http://127.0.0.1:{port}/api/runs/{path.name}"
        have: dict[str, tuple[int, int]] = {}
        lags: list[float] = []
        sent_end, cpu0, wall0 = None, 0.0, 0.0
        while run.poll() is None:
            if sent_end is not None:
                lags.append(_file_end(path) - sent_end)
            query = ",".join(f"{k}:{g}:{n}" for k, (g, n) in have.items())
            try:
                with urllib.request.urlopen(f"{url}?have={query}", timeout=10) as r:
                    data = json.loads(r.read())
            except OSError:  # the server is starting
                time.sleep(0.1)
                continue
            if sent_end is None:
                cpu0, wall0 = _cpu_s(watch.pid), time.monotonic()
            for k, s in data["streams"].items():
                have[k] = (s["generation"], s["from"] + len(s["t_lo"]))
            amp = data["streams"].get("amplifier")
            sent_end = amp["t_hi"][-1] if amp and amp["t_hi"] else (sent_end or 0.0)
            time.sleep(POLL_S)
        share = 100 * (_cpu_s(watch.pid) - cpu0) / max(time.monotonic() - wall0, 1e-9)
    finally:
        for p in (run, watch):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=10)
    if not lags:
        raise RuntimeError("the watch server never answered during the run")
    return share, max(lags), float(np.median(lags)), len(lags)


def run_all(quick: bool = False) -> list[Figure]:
    """The server's CPU share and lag during a wall-clock run; the page's data for a short and a 12-hour file."""
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError:
        return [Figure("bench watch (needs the web extra: pip install 'dea-bench[web]')", float("nan"), "")]
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        protocol, run_s = _protocol(Path(tmp), quick)
        share, worst, median, polls = live(Path(tmp), protocol)
        figures.append(Figure(f"watch server CPU, wall-clock 4 × 10 kHz run of {run_s:g} s", share, "% of a core",
                              f"bench watch in its own process, polled every {POLL_S:g} s as the page does; "
                              "target ≤ 10 %"))
        figures.append(Figure("  its lag behind the file (worst)", worst, "s",
                              f"median {median:.2f} s over {polls} polls, each just before the page asks again "
                              "(the file's last confirmed time − the page's); target ≤ 1 s"))
        short_s = 20.0 if quick else 600.0  # (quick: 200,000 scans a channel, still 100 × the screen's bins)
        long_rate = 5.0 if quick else 100.0
        for seconds, rate in ((short_s, 10_000.0), (12 * 3600.0, long_rate)):
            path = Path(tmp) / f"page-{seconds:g}.h5"
            scans = write_file(path, seconds, rate)
            size, bins = page_bytes(path)
            length = f"{seconds / 3600:g}-h" if seconds >= 3600 else f"{seconds / 60:g}-min" if seconds >= 60 else \
                f"{seconds:g}-s"
            figures.append(Figure(f"page data, {length} file at 4 × {rate:g} Hz" if seconds >= 3600 else
                                  f"page data, {length} file at 4 × {rate / 1e3:g} kHz", size / 1e3, "kB",
                                  f"{scans:,} scans per channel → {bins} bins per stream (bounded by the screen: "
                                  f"≤ 2 × {PIXELS} whatever the record)"))
            path.unlink()
    return figures

