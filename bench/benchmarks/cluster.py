"""Scale-out of the campaign fit's search (issue 24): the same differential evolution in-process on N numba
threads and on a LocalCluster of N single-threaded worker processes (``--workers N``), for each N of ``--sizes``
(default 1 and 2, the development machine's cores; 1, 2, 4, 8, 16 on a 16-core machine), in one run.

The configurations take turns within each repeat (a change of the machine's load touches all alike), in the
reverse order every other repeat (none always first where there are two repeats or more: not in ``--quick``),
best of the repeats; each is warmed first (JIT cache loaded in the workers, the records scattered). The figure is
the search's own time (:attr:`bench.identify.core.FitResult.search_time`); beside it the load average and the CPUs
the integrating processes got (their CPU seconds over the fit's wall time): on a shared machine whose other
sessions hold the cores, two workers get no more CPU than one, and the ratio says so.
"""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from bench.benchmarks import best_of
from bench.benchmarks.acquisition import Figure
from bench.identify.core import FitResult, FitSettings, fit
from bench.identify.distributed import cluster_client, tile_cost, tiles
from bench.identify.problems import MembraneProblem
from bench.models.batch_plan import CHUNK_OVERHEAD, LANES, chunk_cost, makespan
from bench.models.membrane_batch import membrane_batch_records
from bench.resources import protocols_dir
from bench.runtime.run import execute, plan_run

if TYPE_CHECKING:
    from distributed import Client

SCALE_TARGETS = {2: 1.7, 16: 10.0}  # issue 24: --workers N ≥ this × --workers 1 (2 cores: N = 2; 16 cores: N = 16)
DEFAULT_SIZES = (1, 2)
CAMPAIGN = ("thesis-voltage-sweep.toml", "thesis-frequency-sweep.toml", "thesis-temperature-sweep.toml")
QUICK = ("short/thesis-sweeps-short.toml", "short/thesis-identification-short.toml")


def parse_sizes(text: str) -> tuple[int, ...]:
    """``"1,2,4"`` → (1, 2, 4): worker counts, each also the in-process fit's numba thread count, so none may
    exceed the threads numba was started with; 1 is always measured (the ratios' base)."""
    try:
        sizes = sorted({int(s) for s in text.split(",") if s.strip()} | {1})
    except ValueError:
        raise ValueError(f"--sizes: {text!r} is not a comma-separated list of whole numbers") from None
    most = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    if sizes[0] < 1 or sizes[-1] > most:
        raise ValueError(f"--sizes: {text!r}: each size must be 1…{most} (numba's threads on this machine)")
    return tuple(sizes)


def _runs(tmp: Path, quick: bool) -> list[str | Path]:
    paths: list[str | Path] = []
    for name in QUICK if quick else CAMPAIGN:
        res = execute(plan_run(protocols_dir() / name), tmp / (Path(name).stem + ".h5"), virtual=True)
        if res.state != "completed":
            raise RuntimeError(f"benchmark run {name} ended {res.state}: {res.reason}")
        paths.append(Path(res.path))
    return paths


def _balance(steps: list[int], threads: int) -> tuple[int, float]:
    """(tiles of a 50-set generation, the even share of its work — every record one chunk of all 50 — over the
    finish of its tiles run longest first, each on the first thread free, under the plans' cost model): 1.0 is
    perfect balance at no cost of cutting, whatever the machine's load."""
    plan = tiles(50, steps, threads)
    whole = sum(chunk_cost(n, 50) for n in steps)
    return len(plan), whole / threads / makespan((tile_cost(steps, t) for t in plan), threads)


def _cpu(client: Client | None) -> float:
    """CPU seconds used so far by the processes that integrate: the workers', or this one's (in-process)."""
    if client is None:
        return time.process_time()
    return float(sum(client.run(time.process_time).values()))


@contextlib.contextmanager
def _threads(n: int) -> Iterator[None]:
    """numba's thread count set to ``n`` for the in-process fit, restored after."""
    was = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(was)


def chunk_widths(problem: MembraneProblem, repeats: int = 3) -> list[Figure]:
    """One thread, one record: the vectorised kernel on chunks 1…7 registers wide, and the fixed per-step cost of
    a chunk fitted to them (time = a·(registers + overhead)): the figure behind the plans' cost model
    (:data:`bench.models.batch_plan.CHUNK_OVERHEAD`), on this CPU."""
    rec = problem.records[0]
    lo, hi = problem.lower, problem.upper
    Z = lo + (hi - lo) * np.random.default_rng(1).random((7 * LANES, lo.size))
    P = np.stack([problem.params_of(z).pack() for z in Z])
    cal = problem.calibration(Z)
    Y0, steps = rec.y0[None], rec.U.shape[0]

    def chunk(k: int) -> None:
        membrane_batch_records(P[:k * LANES], Y0, [rec.U], problem.h, rec.stride, 0,
                               None if cal is None else cal[:1, :k * LANES])

    regs = np.arange(1, 8)
    with _threads(1):
        chunk(1)
        per_step = np.array([best_of(functools.partial(chunk, int(k)), repeats) for k in regs]) / steps
    slope, intercept = np.polyfit(regs, per_step, 1)
    overhead = intercept / slope
    return [Figure("a chunk's fixed cost per step (one thread, chunks 1…7 registers wide)", overhead, "registers",
                   f"fitted to time = a·(registers + overhead); per register and step {per_step[0] * 1e9:.0f} ns at 1 "
                   f"register, {per_step[-1] / 7 * 1e9:.0f} ns at 7; the plans' cost model uses {CHUNK_OVERHEAD:g}")]


def scaling(quick: bool = False, sizes: tuple[int, ...] = DEFAULT_SIZES, copies: int = 1) -> list[Figure]:
    """The campaign search (full thesis sweeps, 12 records; quick: the short campaign, 2 records; ``copies``: its
    records that many times over, the same work per record), a few generations of 50, for each size N of
    ``sizes``: in-process on N numba threads against ``--workers N``. Each cluster is started for its turn and
    closed after it (untimed), so that no idle worker or scheduler shares the machine with the configuration
    timed."""
    generations, repeats = (3, 1) if quick else (4, 2)
    settings = FitSettings(generations=generations, polish=False, stall_generations=0, tol=0.0)
    configs = [(kind, n) for n in sizes for kind in ("in-process", "workers")]
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        problem = MembraneProblem(_runs(Path(tmp), quick) * copies, h=5e-4)
        widths = chunk_widths(problem)
        lo, hi = problem.lower, problem.upper
        warm = lo + (hi - lo) * np.random.default_rng(0).random((50, lo.size))  # a generation's worth
        best = dict.fromkeys(configs, float("inf"))
        used = dict.fromkeys(configs, 0.0)  # CPU seconds of the fit's integrating processes
        cores = dict.fromkeys(configs, 0.0)  # the same per wall second: the CPUs they got
        results: dict[tuple[str, int], FitResult] = {}
        for repeat in range(repeats):  # the configurations take turns within each repeat, first and last in turn
            for kind, n in configs if repeat % 2 == 0 else configs[::-1]:
                with cluster_client(workers=n if kind == "workers" else None) as client, \
                        _threads(n) if client is None else contextlib.nullcontext():
                    problem.distribute(client)
                    problem.costs(warm, settings.cost)  # JIT caches loaded (model and costs), records scattered
                    cpu0 = _cpu(client)
                    r = results[kind, n] = fit(problem, settings)
                    if r.search_time < best[kind, n]:
                        best[kind, n] = r.search_time
                        used[kind, n] = _cpu(client) - cpu0
                        cores[kind, n] = used[kind, n] / r.wall_time
                    problem.distribute(None)
        steps = [r.U.shape[0] for r in problem.records]
    load1 = os.getloadavg()[0]
    first = results[configs[0]]
    what = f"{len(problem.records)} records{f' (the campaign {copies} times over)' if copies > 1 else ''}, " \
           f"{generations} generations of 50"
    out = list(widths)
    for n in sizes:
        plan, even = _balance(steps, n)
        inproc, workers = ("in-process", n), ("workers", n)
        out += [Figure(f"campaign search ({what}), in-process, numba {n} thread{'s' if n > 1 else ''}", best[inproc],
                       "s", f"best of {repeats}; {cores[inproc]:.2f} CPUs busy, {used[inproc]:.1f} CPU-s"),
                Figure(f"  same, --workers {n} (LocalCluster, single-threaded processes)", best[workers], "s",
                       f"{plan} tiles a generation (a worker thread's as one task), {100 * even:.0f} % balanced; "
                       f"the workers got {cores[workers]:.2f} CPUs, {used[workers]:.1f} CPU-s"),
                Figure(f"  --workers {n} against the in-process threads, same run", best[inproc] / best[workers], "×",
                       "target ≥ 1× (issue 24: never slower than in-process): "
                       + ("ok" if best[inproc] >= best[workers] else "BELOW"))]
    for n in sizes[1:]:
        scale = best["workers", 1] / best["workers", n]
        target = SCALE_TARGETS.get(n) if copies == 1 else None  # the targets: the campaign as it is
        verdict = f"target ≥ {target:g}×: {'ok' if scale >= target else 'BELOW TARGET'}; " if target else ""
        out.append(Figure(f"--workers {n} against --workers 1, same run", scale, "×",
                          f"{verdict}load average {load0:.1f} → {load1:.1f} on {os.cpu_count()} CPUs"))
    n16, even16 = _balance(steps, 16)
    by_record = sum(steps) / 16 / makespan(steps, 16)  # one task per record, longest first
    agree = sum(np.array_equal(r.values, first.values) for r in results.values())
    out += [Figure("configurations whose result is the first's bit for bit", agree, f"of {len(results)}",
                   "the same result bit for bit in all" if agree == len(results) else "RESULTS DIFFER"),
            Figure("planned for 16 worker threads: the even share over the tiles' finish", 100 * even16, "%",
                   f"{n16} tiles a generation (a property of the plan, not a timing); one task per record: "
                   f"{100 * by_record:.0f} %")]
    return out


def run_all(quick: bool = False, sizes: tuple[int, ...] = DEFAULT_SIZES, copies: int = 1) -> list[Figure]:
    """The scale-out figures (``quick``: on the short campaign; ``sizes``: the worker counts; ``copies``: the
    campaign's records that many times over)."""
    return scaling(quick, sizes, copies)
