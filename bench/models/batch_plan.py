"""The batch kernels' common skeleton: which candidates over which records each thread integrates.

Both vectorised kernels (:mod:`bench.models.membrane_batch`, :mod:`bench.models.lozenge_batch`) take a packed
parameter matrix (one row per candidate), records of inputs laid end to end, and write every record's outputs
side by side. Their parallel driver is the same loop over one task table: a task is one record's span of the
inputs and of the output columns and one chunk of candidates, a whole number of SIMD registers wide (only the last
chunk padded), with enough chunks per record to give every thread work. Each model keeps its own step function;
the plan below is theirs in common.
"""

from __future__ import annotations

import numpy as np

LANES = 8  # float64 lanes of an AVX-512 register: a chunk of candidates is a whole number of these

TASK_COLUMNS = ("record", "first step", "end step", "first column", "end column", "first set", "end set")


def candidate_bounds(m: int, chunks: int) -> np.ndarray:
    """Chunk bounds over ``m`` candidates: at most ``chunks`` chunks (at least one), each of whole registers
    (50 sets are 4 + 3 registers, not 2 × 4); returns the ``chunks + 1`` (or fewer) bounds, 0 … m."""
    regs = -(-m // LANES)
    n = max(1, min(chunks, regs))
    bounds: np.ndarray = np.minimum(np.linspace(0, regs, n + 1).round().astype(np.int64) * LANES, m)
    return bounds


def plan(m: int, steps: list[int], stride: int, threads: int) -> tuple[np.ndarray, int]:
    """The task table (rows as :data:`TASK_COLUMNS`, int64) for ``m`` candidates over records of ``steps`` input
    steps each, an output every ``stride`` steps (the start included), on ``threads`` threads; and the number of
    output columns of all records together."""
    n_steps = np.asarray(steps, dtype=np.int64)
    n_cols = n_steps // stride + 1
    u_off = np.concatenate([[0], np.cumsum(n_steps)])
    c_off = np.concatenate([[0], np.cumsum(n_cols)])
    bounds = candidate_bounds(m, -(-threads // len(steps)))  # enough tasks for the threads, none below a register
    tasks = np.array([(r, u_off[r], u_off[r + 1], c_off[r], c_off[r + 1], bounds[k], bounds[k + 1])
                      for r in range(len(steps)) for k in range(bounds.size - 1)], dtype=np.int64)
    return tasks, int(c_off[-1])
