"""The distributed fit's tiles (bench.identify.distributed.tiles): every candidate of every record in exactly one
tile, longest first, a record cut only where that finishes sooner — checked against hand-worked cases and against
every uniform cut, scheduled longest first under the cost model the module states (a chunk's step costs its
registers plus a fixed part)."""

from __future__ import annotations

import heapq

import numpy as np
import pytest

from bench.identify.distributed import DistributedPredict, tile_cost, tiles
from bench.models.batch_plan import CHUNK_OVERHEAD, LANES, candidate_bounds

# input steps of 12 records as unequal as the thesis sweeps' (a few long slow cycles, many short fast ones)
CAMPAIGN = [180_000, 60_000, 45_000, 24_000, 16_000, 12_000, 240_000, 96_000, 30_000, 120_000, 120_000, 120_000]


def _makespan(costs: list[float], threads: int) -> float:
    """Finish time of tasks run in the given order, each on the first thread free (a dask queue, longest first)."""
    free = [0.0] * threads
    for c in costs:
        heapq.heappush(free, heapq.heappop(free) + c)
    return max(free)


def _cost(steps: int, sets: int) -> float:
    return steps * (-(-sets // LANES) + CHUNK_OVERHEAD)


def test_hand_worked_tiles() -> None:
    # one thread: cutting only adds the fixed part; every record whole, longest first
    assert tiles(50, [300, 100, 100, 100], threads=1) == [(0, 1, 0, 50), (1, 2, 0, 50), (2, 3, 0, 50), (3, 4, 0, 50)]
    # 16 sets = 2 registers on 2 threads, fixed part f: the long record whole finishes at 800·(2 + f), cut to one
    # register a thread at 900·(1 + f) with the short one cut too; left whole, the short one would end at
    # 800·(1 + f) + 100·(2 + f), later
    assert tiles(16, [800, 100], threads=2) == [(0, 1, 0, 8), (0, 1, 8, 16), (1, 2, 0, 8), (1, 2, 8, 16)]
    # a short record that fits beside the long one's chunks stays whole: 250·(7 + f) ≤ 1000·(1 + f) for f ≥ 1
    assert tiles(50, [1000, 250], threads=16) == [(0, 1, 8 * k, min(8 * k + 8, 50)) for k in range(7)] + [
        (1, 2, 0, 50)]
    # 12 equal records on 16 threads: whole, 12 threads finish at 7 + f and 4 idle; cut 4 + 3 (24 chunks) a
    # second round, 7 + 2f at best; the part-filled 7th register (sets 48-49) peeled off, 12 threads finish at
    # 6 + f and the other 4 take three 1-register chunks each, 3 + 3f: sooner than 7 + f for every f < 2
    assert CHUNK_OVERHEAD < 2
    assert tiles(50, [80_000] * 12, threads=16) == [(r, r + 1, 0, 48) for r in range(12)] + [
        (r, r + 1, 48, 50) for r in range(12)]


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
    assert costs == [_cost(sum(CAMPAIGN[r0:r1]), b - a) for r0, r1, a, b in plan]  # the stated cost model


@pytest.mark.parametrize(("m", "steps"), [(50, CAMPAIGN), (100, CAMPAIGN), (200, CAMPAIGN), (50, [1000, 2000]),
                                          (200, [1000, 2000]), (15, CAMPAIGN)])
@pytest.mark.parametrize("threads", [2, 3, 4, 5, 8, 10, 11, 12, 16])
def test_tiles_finish_no_later_than_any_uniform_cut(m: int, steps: list[int], threads: int) -> None:
    """Run longest first on ``threads`` threads, the tiles of a batch finish no later than every record cut into
    the same number of chunks, for every such number; for the campaign's 50 sets from 8 threads on, well before
    one task per record (the old plan: the longest record sets the pace)."""
    finish = _makespan(sorted((tile_cost(steps, t) for t in tiles(m, steps, threads)), reverse=True), threads)
    for s in range(1, -(-m // LANES) + 1):
        widths = np.diff(candidate_bounds(m, s))
        uniform = sorted((_cost(n, int(w)) for n in steps for w in widths), reverse=True)
        assert finish <= _makespan(uniform, threads) * (1 + 1e-9)
    if m == 50 and steps is CAMPAIGN and threads >= 8:
        assert _makespan(sorted((_cost(n, 50) for n in CAMPAIGN), reverse=True), threads) > 1.5 * finish


def test_no_candidates_no_tiles() -> None:
    assert tiles(0, CAMPAIGN, 4) == [] and tiles(50, [], 4) == []


@pytest.mark.parametrize(("c0", "n_data", "n_sigma"), [(8, 4, 4), (-1, 4, 4), (0, 4, 3)])
def test_a_record_outside_the_prediction_is_refused_not_read_past(c0: int, n_data: int, n_sigma: int) -> None:
    """The compiled per-record sum checks no bounds: columns beyond the prediction or a σ of another length are
    refused before it runs."""
    from bench.identify.record_costs import record_costs

    with pytest.raises(ValueError, match="record columns"):
        record_costs(np.zeros((3, 10)), c0, np.zeros(n_data), np.ones(n_sigma), np.ones(n_data, bool), "lsq")


def _placer(steps: list[int]) -> DistributedPredict:
    """A DistributedPredict with only what placing needs (no cluster): its record lengths and nothing placed yet."""
    import threading

    p = DistributedPredict.__new__(DistributedPredict)
    p.steps, p._loads, p._placing = steps, {}, threading.Lock()
    return p


def test_tiles_are_placed_longest_first_on_the_thread_free_first() -> None:
    """Worker a with one thread, b with two; four one-register tiles of 400, 300, 200 and 100 steps: by hand,
    400 → a, 300 → b's first thread, 200 → b's second, and 100 to the thread free first, b's second (200)."""
    plan = [(0, 1, 0, LANES), (1, 2, 0, LANES), (2, 3, 0, LANES), (3, 4, 0, LANES)]
    got = _placer([400, 300, 200, 100]).assign(plan, [("a", 0), ("b", 0), ("b", 1)])
    assert [slot for slot, _ in got] == [("a", 0), ("b", 0), ("b", 1), ("b", 1)]


STEPS_12 = [80960, 80280, 80340, 80400, 80980, 80600, 80380, 80200, 80960, 80380, 80380, 80380]
SLOTS_16 = [(f"w{k:02d}", 0) for k in range(16)]


def test_a_generation_of_the_campaign_works_all_sixteen_workers() -> None:
    """The campaign's generation (12 records of nearly equal length, each 48 + 2 sets: see the hand-worked tiles)
    on 16 single-thread workers: each 48-set tile alone on its worker, the twelve 2-set tiles three to each of the
    other four (the scheduler left to itself put up to three whole records on one worker while others idled)."""
    plan = tiles(50, STEPS_12, 16)
    placed = _placer(STEPS_12).assign(plan, SLOTS_16)
    on: dict[object, list[int]] = {}
    for (slot, _), (_, _, a, b) in zip(placed, plan, strict=True):
        on.setdefault(slot, []).append(b - a)
    assert len(on) == 16
    assert sorted(map(sorted, on.values())) == [[2, 2, 2]] * 4 + [[48]] * 12


def test_two_batches_under_way_together_share_the_threads_and_a_finished_one_frees_them() -> None:
    """Two starts' generations at once (twice the 24 tiles above, 16 threads): the second batch's tiles go to the
    threads the first loaded least, so no thread carries more than both batches' share of the busiest one;
    once both are done, the next batch is placed as on idle workers."""
    p = _placer(STEPS_12)
    plan = tiles(50, STEPS_12, 16)
    costs = [tile_cost(STEPS_12, t) for t in plan]
    with p._placed(plan, SLOTS_16) as first_slots:
        alone = dict(p._loads)
        with p._placed(plan, SLOTS_16) as second_slots:
            first, second = [s[0] for s in first_slots], [s[0] for s in second_slots]  # the workers' addresses
            assert set(first) == set(second) == {f"w{k:02d}" for k in range(16)}
            assert second[0] == min(alone, key=lambda slot: (alone[slot], slot))[0]  # the longest to the least loaded
            assert max(p._loads.values()) <= 2 * max(alone.values()) * (1 + 1e-12)
            assert sum(p._loads.values()) == pytest.approx(2 * sum(costs))
    assert p._loads == {}
    with p._placed(plan, SLOTS_16) as third:
        assert third == first_slots


def test_without_known_workers_the_scheduler_places_the_tiles() -> None:
    with _placer([100])._placed([(0, 1, 0, LANES)], []) as where:
        assert where == [None]


class _Client:
    """A stand-in for a dask client with no worker registered yet: it runs each task at once and refuses a loose
    restriction without workers, as distributed's Client.submit does (its docs: allow_other_workers "only used
    if workers is not None")."""

    def __init__(self, workers: dict | None = None) -> None:
        self.kwargs: list[dict] = []
        self.workers = workers or {}

    def scheduler_info(self) -> dict:
        return {"workers": self.workers}

    def submit(self, fn, *args, **kwargs):  # type: ignore[no-untyped-def]
        if kwargs.get("allow_other_workers") and kwargs.get("workers") is None:
            raise ValueError("Only use allow_other_workers= if using workers=")
        self.kwargs.append(kwargs)
        return fn(*args)

    def gather(self, futures: list) -> list:
        return futures


def test_a_batch_before_any_worker_registered_goes_to_the_scheduler_unrestricted() -> None:
    """The scheduler may list no worker yet (a cluster just started, under load): the batch is submitted without
    a placement, and runs."""
    import threading

    p = DistributedPredict.__new__(DistributedPredict)
    p.client, p.steps, p._loads, p._placing, p._count, p.evaluations = _Client(), [100, 50], {}, threading.Lock(), \
        threading.Lock(), 0
    plan, parts = p._batch(9, lambda r0, r1, a, b: (r0, a, b), lambda r0, r1, a, b: (r0, r1, a, b))
    assert parts == [(r0, a, b) for r0, _, a, b in plan]
    assert all("workers" not in k and "allow_other_workers" not in k for k in p.client.kwargs)
    assert p.evaluations == 9


def test_the_tiles_a_worker_thread_is_given_go_as_one_task_and_come_back_in_plan_order() -> None:
    """Two single-thread workers, five records of 400, 300, 200, 100 and 50 steps (a tile each, one register of
    candidates): by hand, longest first on the thread free first (a tie to the first), a gets 400, 100 and 50, b
    300 and 200: two tasks, each placed on its worker, and each tile's result where the plan has it."""
    import threading

    p = DistributedPredict.__new__(DistributedPredict)
    p.client = _Client({"a": {"nthreads": 1}, "b": {"nthreads": 1}})
    p.steps, p._loads, p._placing, p._count, p.evaluations = [400, 300, 200, 100, 50], {}, threading.Lock(), \
        threading.Lock(), 0
    plan, parts = p._batch(LANES, lambda r0, r1, a, b: (r0, a, b), lambda r0, r1, a, b: (r0, r1, a, b))
    assert [t[0] for t in plan] == [0, 1, 2, 3, 4]  # one tile a record, longest first
    assert parts == [(r0, a, b) for r0, _, a, b in plan]
    assert [k["workers"] for k in p.client.kwargs] == [["a"], ["b"]]
    assert p._loads == {} and p.evaluations == LANES


def test_a_worker_with_two_threads_gets_a_turn_for_each() -> None:
    """One worker with two threads: two slots, so two turns placed on that worker (run side by side there), each
    tile's result in plan order."""
    import threading

    p = DistributedPredict.__new__(DistributedPredict)
    p.client = _Client({"a": {"nthreads": 2}})
    p.steps, p._loads, p._placing, p._count, p.evaluations = [400, 300, 200, 100], {}, threading.Lock(), \
        threading.Lock(), 0
    plan, parts = p._batch(LANES, lambda r0, r1, a, b: (r0, a, b), lambda r0, r1, a, b: (r0, r1, a, b))
    assert parts == [(r0, a, b) for r0, _, a, b in plan]
    assert [k["workers"] for k in p.client.kwargs] == [["a"], ["a"]]
    assert p._loads == {}

