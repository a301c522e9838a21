"""The batch kernels' common task plan (bench.models.batch_plan): every candidate of every record in exactly one
task, chunks of whole SIMD registers, enough tasks for the threads, outputs side by side."""

from __future__ import annotations

import numpy as np
import pytest

from bench.models.batch_plan import LANES, candidate_bounds, chunks_per_record, plan


# chunks per record, worked by hand from the cost model (a chunk's step costs its registers + a fixed part f, run
# longest first on the threads); each holds for any f from 1 to 3 registers, the range CPUs have printed:
# - 50 sets (7 registers), one record, 2 threads: 4 + 3 registers finish at 4 + f; whole, 7 + f; three chunks
#   (2, 3, 2) put two on one thread, 4 + 2f;
# - the same on 16 threads: 1 + f a register each, 7 chunks; the long record cut so, the 250-step one whole
#   finishes at 250·(7 + f) ≤ 1000·(1 + f), the 7-step one too;
# - 3 sets: one register, never cut; one thread: cutting only adds the fixed part;
# - 200 sets (25 registers) on 4 threads: 6, 6, 7, 6 registers, 7 + f; 5 chunks put two on a thread; 7 or 8
#   chunks put 4 + 3 registers on one, 7 + 2f.
@pytest.mark.parametrize(("m", "steps", "stride", "threads", "chunks"), [
    (50, [1000], 10, 2, [2]), (50, [1000, 250, 7], 10, 16, [7, 1, 1]), (3, [100], 1, 8, [1]),
    (64, [10, 10], 5, 1, [1, 1]), (200, [99], 3, 4, [4])])
def test_every_candidate_of_every_record_is_in_exactly_one_task(m: int, steps: list[int], stride: int,
                                                                threads: int, chunks: list[int]) -> None:
    tasks, columns = plan(m, steps, stride, threads)
    assert columns == sum(n // stride + 1 for n in steps)  # an output at the start and every stride steps
    u_off = np.concatenate([[0], np.cumsum(steps)])
    c_off = np.concatenate([[0], np.cumsum([n // stride + 1 for n in steps])])
    for r in range(len(steps)):
        rows = tasks[tasks[:, 0] == r]
        assert np.all(rows[:, 1] == u_off[r]) and np.all(rows[:, 2] == u_off[r + 1])
        assert np.all(rows[:, 3] == c_off[r]) and np.all(rows[:, 4] == c_off[r + 1])
        covered = np.zeros(m, int)
        for a, b in rows[:, 5:7]:
            covered[a:b] += 1
            assert a % LANES == 0 and (b % LANES == 0 or b == m)  # whole registers, only the last one cut
        assert np.all(covered == 1)
        assert len(rows) == chunks[r]


def test_equal_records_on_more_threads_than_records_stay_whole() -> None:
    """12 equal records of 50 sets on 16 threads (the thesis campaign on a 16-core machine): whole, each 7 + f;
    cut in two, 24 chunks of 4 + f and 3 + f leave eight to a second round, 7 + 2f at best."""
    assert chunks_per_record(50, (80_000,) * 12, 16) == (1,) * 12
    assert chunks_per_record(50, (80_000,), 16) == (7,)  # one record: a register per thread


def test_fifty_sets_on_two_threads_are_four_and_three_registers() -> None:
    assert list(candidate_bounds(50, 2)) == [0, 4 * LANES, 50]
