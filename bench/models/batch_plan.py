"""The batch kernels' common skeleton: which candidates over which records each thread integrates.

Both vectorised kernels (:mod:`bench.models.membrane_batch`, :mod:`bench.models.lozenge_batch`) take a packed
parameter matrix (one row per candidate), records of inputs laid end to end, and write every record's outputs
side by side. Their parallel driver is the same loop over one task table: a task is one record's span of the
inputs and of the output columns and one chunk of candidates, a whole number of SIMD registers wide (only the last
chunk padded). How many chunks a record is cut into follows a cost model (:func:`chunk_cost`): a chunk's step costs
its registers plus a fixed part (the loops' set-up around the lanes, :data:`CHUNK_OVERHEAD`), so a narrow chunk
costs more per candidate than a wide one, and a record is cut only as far as that finishes the batch sooner on the
threads there are. Each model keeps its own step function; the plan below is theirs in common.
"""

from __future__ import annotations

import functools
import heapq
import itertools
from collections.abc import Callable, Iterable, Sequence
from typing import TypeVar

import numpy as np

LANES = 8  # float64 lanes of an AVX-512 register: a chunk of candidates is a whole number of these

T = TypeVar("T")

TASK_COLUMNS = ("record", "first step", "end step", "first column", "end column", "first set", "end set")


Split = tuple[int, ...]  # one record's chunks, each its width in registers, in order (their sum: the record's)


def even_split(regs: int, chunks: int) -> Split:
    """``regs`` registers in at most ``chunks`` chunks (at least one) as even as whole registers allow (7 in two:
    4 + 3)."""
    n = max(1, min(chunks, regs))
    return tuple(int(w) for w in np.diff(np.linspace(0, regs, n + 1).round().astype(np.int64)) if w > 0)


def split_bounds(m: int, split: Split) -> np.ndarray:
    """Candidate bounds 0 … m of a record's chunks of ``split`` registers each (only the last register part
    filled)."""
    bounds: np.ndarray = np.minimum(np.concatenate([[0], np.cumsum(split, dtype=np.int64)]) * LANES, m)
    return bounds


def candidate_bounds(m: int, chunks: int) -> np.ndarray:
    """Chunk bounds over ``m`` candidates: at most ``chunks`` chunks (at least one), each of whole registers
    (50 sets are 4 + 3 registers, not 2 × 4); returns the ``chunks + 1`` (or fewer) bounds, 0 … m."""
    return split_bounds(m, even_split(-(-m // LANES), chunks))


# a chunk's fixed cost per input step, in registers' worth: `bench benchmark cluster` fits it per CPU from one-thread
# timings of chunks 1…7 registers wide ("a chunk's fixed cost per step"; 1.8 on the development machine's EPYC)
CHUNK_OVERHEAD = 1.8


def chunk_cost(steps: int, candidates: int) -> float:
    """Cost of integrating ``candidates`` over ``steps`` input steps as one chunk, in register-steps: steps ×
    (its SIMD registers + :data:`CHUNK_OVERHEAD`)."""
    return steps * (-(-candidates // LANES) + CHUNK_OVERHEAD)


def makespan(costs: Iterable[float], threads: int) -> float:
    """When tasks of these costs finish, run longest first, each on the first of ``threads`` threads free."""
    free = [0.0] * max(1, threads)
    for c in sorted(costs, reverse=True):
        heapq.heappush(free, heapq.heappop(free) + c)
    return max(free)


REFINE_RECORDS = 64  # up to this many records each is cut no further than needed; beyond, all alike (the cost grows)


def _finish(m: int, steps: tuple[int, ...], chunks: list[int], threads: int) -> float:
    """When the chunks of every record (``chunks[r]`` of record r) finish, run longest first on ``threads``."""
    return makespan((chunk_cost(n, int(w)) for n, s in zip(steps, chunks, strict=True)
                     for w in np.diff(candidate_bounds(m, s))), threads)


@functools.lru_cache(maxsize=512)
def chunks_per_record(m: int, steps: tuple[int, ...], threads: int) -> tuple[int, ...]:
    """How many chunks of ``m`` candidates each record of ``steps`` input steps is cut into on ``threads`` threads:
    the one count for all records that finishes soonest under :func:`chunk_cost` (the fewest chunks among equals),
    then, shortest record first, each cut into fewer where the whole schedule still finishes no later."""
    regs = -(-m // LANES)
    if not steps or regs == 0:
        return tuple(1 for _ in steps)
    most = max(1, min(regs, 2 * threads))  # a record in more chunks than twice the threads cannot finish sooner
    best, finish = 1, float("inf")
    for s in range(1, most + 1):
        span = _finish(m, steps, [s] * len(steps), threads)
        if span < finish * (1 - 1e-9):
            best, finish = s, span
    out = [best] * len(steps)
    if len(steps) > REFINE_RECORDS:
        return tuple(out)
    _cut_no_further(steps, out, range(1, best), lambda trial: _finish(m, steps, trial, threads), finish)
    return tuple(out)


def _cut_no_further(steps: tuple[int, ...], out: list[T], fewer: Sequence[T], finish_of: Callable[[list[T]], float],
                    finish: float) -> None:
    """Shortest record first, each record's cut in ``out`` replaced by the first of ``fewer`` (fewest chunks first)
    with which the schedule (``finish_of``) still finishes no later than ``finish``."""
    for r in sorted(range(len(steps)), key=lambda i: steps[i]):
        for cut in fewer:
            if finish_of([*out[:r], cut, *out[r + 1:]]) <= finish * (1 + 1e-9):
                out[r] = cut
                break


def _splits(regs: int, most: int) -> list[Split]:
    """The cuts of a record of ``regs`` registers into at most ``most`` chunks that :func:`register_splits`
    weighs, fewest chunks first: each even cut, and each even cut with a narrower chunk peeled off its end (50
    sets: 6 + 1, the part-filled register alone)."""
    out = {even_split(regs, s) for s in range(1, most + 1)}
    out |= {(*even, k) for s in range(1, most) for k in range(1, regs - s + 1)
            if k < min(even := even_split(regs - k, s))}
    return sorted(out, key=lambda split: (len(split), split != even_split(regs, len(split)), split))


def _finish_split(steps: tuple[int, ...], splits: list[Split], threads: int) -> float:
    """When the chunks of every record (``splits[r]``: record r's widths in registers) finish, run longest first
    on ``threads`` threads, under :func:`chunk_cost`."""
    return makespan((n * (w + CHUNK_OVERHEAD) for n, split in zip(steps, splits, strict=True) for w in split),
                    threads)


@functools.lru_cache(maxsize=512)
def register_splits(m: int, steps: tuple[int, ...], threads: int) -> tuple[Split, ...]:
    """Each record's cut into chunks of whole registers for a schedule run longest first on ``threads`` threads
    (the distributed fit places its tiles so): the cut for all records alike that finishes soonest under
    :func:`chunk_cost` among the even cuts and the even cuts with a narrower chunk peeled off (the fewest chunks
    among equals), then, shortest record first, each cut into fewer chunks where the schedule still finishes no
    later. 12 equal records of 50 sets on 16 threads: 6 + 1 registers each, the twelve 2-set chunks on the four
    threads the whole records would leave idle (6 + f a thread against 7 + f). The in-process kernel
    (:func:`plan`) keeps :func:`chunks_per_record`: numba hands its threads contiguous runs of the task table,
    not the longest task first."""
    regs = -(-m // LANES)
    if not steps or regs == 0:
        return tuple(() if regs == 0 else (regs,) for _ in steps)
    family = _splits(regs, max(1, min(regs, 2 * threads)))
    best, finish = family[0], float("inf")
    for split in family:
        span = _finish_split(steps, [split] * len(steps), threads)
        if span < finish * (1 - 1e-9):
            best, finish = split, span
    out = [best] * len(steps)
    if len(steps) > REFINE_RECORDS:
        return tuple(out)
    _cut_no_further(steps, out, [split for split in family if len(split) < len(best)],
                    lambda trial: _finish_split(steps, trial, threads), finish)
    return tuple(out)


def plan(m: int, steps: list[int], stride: int, threads: int) -> tuple[np.ndarray, int]:
    """The task table (rows as :data:`TASK_COLUMNS`, int64) for ``m`` candidates over records of ``steps`` input
    steps each, an output every ``stride`` steps (the start included), on ``threads`` threads; and the number of
    output columns of all records together."""
    if not steps:
        return np.zeros((0, len(TASK_COLUMNS)), dtype=np.int64), 0
    n_steps = np.asarray(steps, dtype=np.int64)
    n_cols = n_steps // stride + 1
    u_off = np.concatenate([[0], np.cumsum(n_steps)])
    c_off = np.concatenate([[0], np.cumsum(n_cols)])
    split = chunks_per_record(m, tuple(int(n) for n in steps), threads)
    tasks = np.array([(r, u_off[r], u_off[r + 1], c_off[r], c_off[r + 1], a, b)
                      for r in range(len(steps))
                      for a, b in itertools.pairwise(candidate_bounds(m, split[r]).tolist())], dtype=np.int64)
    return tasks, int(c_off[-1])
