"""The distributed fit's tiles (bench.identify.distributed.tiles): every candidate of every record in exactly one
tile, about equal costs, longest first — checked against hand-worked cases and a longest-first schedule."""

from __future__ import annotations

import heapq

import numpy as np
import pytest

from bench.identify.distributed import tile_cost, tiles
from bench.models.batch_plan import LANES

# input steps of 12 records as unequal as the thesis sweeps' (a few long slow cycles, many short fast ones)
CAMPAIGN = [180_000, 60_000, 45_000, 24_000, 16_000, 12_000, 240_000, 96_000, 30_000, 120_000, 120_000, 120_000]


def _makespan(costs: list[int], threads: int) -> int:
    """Finish time of tasks run in the given order, each on the first thread free (a dask queue, longest first)."""
    free = [0] * threads
    for c in costs:
        heapq.heappush(free, heapq.heappop(free) + c)
    return max(free)


def test_hand_worked_tiles() -> None:
    # 50 sets = 7 registers; costs 2100 | 700 700 700 against a share of 7·600/2 = 2100: one tile each side
    assert tiles(50, [300, 100, 100, 100], threads=1, per_thread=2) == [(0, 1, 0, 50), (1, 4, 0, 50)]
    # 16 sets = 2 registers: the long record is split to single registers (no finer), the short one stays whole
    assert tiles(16, [800, 100], threads=2, per_thread=2) == [(0, 1, 0, 8), (0, 1, 8, 16), (1, 2, 0, 16)]


@pytest.mark.parametrize(("m", "threads"), [(50, 1), (50, 2), (50, 16), (15, 2), (15, 16), (3, 4), (200, 8)])
def test_every_candidate_of_every_record_is_in_exactly_one_tile(m: int, threads: int) -> None:
    plan = tiles(m, CAMPAIGN, threads)
    covered = np.zeros((len(CAMPAIGN), m), int)
    for r0, r1, a, b in plan:
        assert 0 <= r0 < r1 <= len(CAMPAIGN) and 0 <= a < b <= m
        assert a % LANES == 0 and (b % LANES == 0 or b == m)  # whole registers, only the last one cut
        covered[r0:r1, a:b] += 1
    assert np.all(covered == 1)
    costs = [tile_cost(CAMPAIGN, t) for t in plan]
    assert costs == sorted(costs, reverse=True)  # longest first
    assert len(plan) <= 2 * 3 * threads + len(CAMPAIGN)  # a few per thread, not one per register and record


@pytest.mark.parametrize("threads", [2, 4, 8, 16])
def test_a_generation_of_fifty_finishes_near_the_even_share(threads: int) -> None:
    """Run longest first on ``threads`` threads, the tiles of a 50-set generation finish within 15 % of the even
    share of the work — or of the longest record on one register, which cannot be split (time is sequential)."""
    plan = tiles(50, CAMPAIGN, threads)
    regs = -(-50 // LANES)
    bound = max(regs * sum(CAMPAIGN) / threads, max(CAMPAIGN))
    assert _makespan([tile_cost(CAMPAIGN, t) for t in plan], threads) <= 1.15 * bound
    if threads >= 8:  # split by record alone (the old plan: a task per record), the longest one sets the pace
        assert _makespan(sorted((regs * n for n in CAMPAIGN), reverse=True), threads) > 1.5 * bound


def test_no_candidates_no_tiles() -> None:
    assert tiles(0, CAMPAIGN, 4) == [] and tiles(50, [], 4) == []
