"""Benchmarks of whole runs: the engine in virtual time, and the recorder's throughput and CPU share."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.benchmarks.acquisition import Figure
from bench.resources import protocols_dir
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from bench.storage.recorder import Column, Recorder


def thesis_virtual(repeats: int = 3) -> list[Figure]:
    """Thesis identification protocol (25 s) on the simulated rig in virtual time, end to end."""
    path = protocols_dir() / "thesis-identification.toml"
    t0 = time.perf_counter()
    plan = plan_run(path)
    t_plan = time.perf_counter() - t0
    best = float("inf")
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            t0 = time.perf_counter()
            result = execute(plan, Path(tmp) / f"run{k}.h5", virtual=True)
            best = min(best, time.perf_counter() - t0)
    duration = plan.program.duration
    return [Figure("thesis identification run, virtual time (start rig, connect, run, finalise file)",
                   duration / best, "× real time", f"{duration:g} s in {best:.3f} s, {result.samples:,} samples"),
            Figure("  validation and dry run on the model, before it", duration / t_plan, "× real time",
                   f"{t_plan:.3f} s")]


def campaign_dry_run(name: str = "lsdea-isopotential.toml") -> list[Figure]:
    """Validation and dry run of the longest shipped campaign (the LS-DEA isopotential one: a motor go-to per
    set-point tick), against its run time on the rig."""
    path = protocols_dir() / name
    plan_run(protocols_dir() / "short" / "lsdea-isopotential-short.toml")  # kernels loaded: not what is timed
    t0 = time.perf_counter()
    plan = plan_run(path)
    took = time.perf_counter() - t0
    duration = plan.program.duration
    return [Figure(f"{Path(name).stem}: validation and dry run on the model", duration / took, "× real time",
                   f"{duration:,.0f} s of protocol in {took:.2f} s")]


def recorder_throughput(seconds: float = 20.0) -> Figure:
    """Samples per second through Recorder.append + flush for a thesis-like stream mix (10-kHz laser)."""
    streams = {"laser": [Column("displacement", "m", ""), Column("valid", "1", "", "u1")],
               "amplifier": [Column("voltage", "V", ""), Column("current", "A", "")],
               "setpoints": [Column("voltage", "V", ""), Column("aperture", "m", "")]}
    rng = np.random.default_rng(0)
    block = 2500  # 0.25 s of 10-kHz laser data per fetch
    n_blocks = int(seconds * 10_000 / block)
    with tempfile.TemporaryDirectory() as tmp:
        rec = Recorder(Path(tmp) / "t.h5", {"protocol_name": "bench"}, streams, [], {"laser": 10_000.0})
        t0 = time.perf_counter()
        for k in range(n_blocks):
            t = (k * block + np.arange(block)) * 1e-4
            rec.append("laser", t, displacement=rng.normal(0, 1e-3, block), valid=np.ones(block, "u1"))
            rec.append("amplifier", t[-1], voltage=7000.0, current=1e-6)
            rec.append("setpoints", t[::500], voltage=np.full(5, 7000.0), aperture=np.full(5, np.nan))
            rec.maybe_flush()
        rec.finish("completed", "benchmark")
        wall = time.perf_counter() - t0
        samples = rec.samples_written
    return Figure("recorder throughput (append, gzip, SWMR flush)", samples / wall, "samples/s",
                  f"{samples:,} samples in {wall:.2f} s")


def recorder_cpu_share() -> list[Figure]:
    """Recorder CPU during a wall-clock run (short thesis run, 11 s, 10-kHz laser): as a share of one core
    over the run, and as a share of the process's own CPU (simulated twins included)."""
    plan = plan_run(protocols_dir() / "short" / "thesis-identification-short.toml")
    engines: list[Engine] = []
    with tempfile.TemporaryDirectory() as tmp:
        c0, w0 = time.process_time(), time.perf_counter()
        execute(plan, Path(tmp) / "run.h5", virtual=False, on_engine=lambda e, _s: engines.append(e))
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    rec = engines[0].rec
    note = f"recorder {rec.cpu_seconds:.3f} s CPU, process {cpu:.2f} s CPU, run {wall:.1f} s"
    return [Figure("recorder CPU during a wall-clock 10-kHz run, share of one core", 100 * rec.cpu_seconds / wall,
                   "% of a core", note),
            Figure("  same, share of the process's CPU (twins included; mostly idle waits)",
                   100 * rec.cpu_seconds / cpu, "% of process CPU", "")]


def run_all(quick: bool = False) -> list[Figure]:
    """All run benchmarks (``quick``: one repeat, no wall-clock run)."""
    figs = thesis_virtual(1 if quick else 3)
    figs.append(recorder_throughput(5.0 if quick else 20.0))
    if not quick:
        figs += recorder_cpu_share()
        figs += campaign_dry_run()
    return figs
