"""The batch kernels' common task plan (bench.models.batch_plan): every candidate of every record in exactly one
task, chunks of whole SIMD registers, enough tasks for the threads, outputs side by side."""

from __future__ import annotations

import numpy as np
import pytest

from bench.models.batch_plan import LANES, candidate_bounds, plan


@pytest.mark.parametrize(("m", "steps", "stride", "threads"), [
    (50, [1000], 10, 2), (50, [1000, 333, 7], 10, 16), (3, [100], 1, 8), (64, [10, 10], 5, 1), (200, [99], 3, 4)])
def test_every_candidate_of_every_record_is_in_exactly_one_task(m: int, steps: list[int], stride: int,
                                                                threads: int) -> None:
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
        # enough chunks for the threads (shared by the records), never one narrower than a register
        assert len(rows) == min(-(-threads // len(steps)), -(-m // LANES))


def test_fifty_sets_on_two_threads_are_four_and_three_registers() -> None:
    assert list(candidate_bounds(50, 2)) == [0, 4 * LANES, 50]
