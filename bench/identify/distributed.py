"""Campaign fits and design maps on a dask.distributed cluster (an existing scheduler, or a LocalCluster).

The fit stays in this process; every batch of model evaluations it makes — a search generation, a polish
Jacobian, a batch of the intervals' Levenberg–Marquardt — is cut into tiles of candidates × records (:func:`tiles`:
a record is cut along its candidates only as far as that finishes sooner, since a narrow chunk costs more per
candidate), run longest first. Each record's inputs, data, σ and compared columns are scattered to every worker
once, and every worker loads the kernels then; a task receives the packed parameters of its candidates and returns
their outputs (:meth:`DistributedPredict.__call__`: the polish, the Jacobians, the intervals) or, for the search,
only their partial costs per record (:meth:`DistributedPredict.costs`, :mod:`bench.identify.record_costs`: the
outputs converted and compared on the worker, b − a numbers per tile and record instead of their samples). Every
candidate is integrated independently and each partial cost summed row by row, so the results are the same as
in-process, bit for bit. A task integrates on one numba thread: a worker's threads are its parallelism (``dask
worker --nthreads N`` runs N tiles at once, N × one thread, no oversubscription). The tiles a batch gives one worker
thread go there as one task that runs them in turn (:func:`_in_turn`): no scheduler round trip between them.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from bench.models.batch_plan import chunk_cost, register_splits, split_bounds

if TYPE_CHECKING:
    from distributed import Client, Future

WARM_TIMEOUT_S = 60.0  # the longest a new DistributedPredict waits for its workers to load the kernel
Tile = tuple[int, int, int, int]  # first record, end record, first candidate, end candidate
Slot = tuple[str, int]  # a worker thread: the worker's address, the thread's number there


@contextlib.contextmanager
def cluster_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Client | None]:
    """A dask client: to ``scheduler`` (e.g. tcp://host:8786) when given, else to a LocalCluster of ``workers``
    single-threaded worker processes when ``workers`` is given, else None (in-process)."""
    if scheduler is None and not workers:
        yield None
        return
    import dask
    from distributed import Client, LocalCluster

    _quiet_all_exit()
    if scheduler is not None:
        with Client(scheduler) as client:
            yield client
        return
    from bench.identify.worker_plugins import QuietClosingHeartbeat

    # our own workers sample no stacks: the profiler (every 10 ms, for the dashboard's profile page, which a fit
    # never shows) cost each worker a few per cent of a CPU in `bench benchmark cluster`; the nannies hand this
    # configuration to the worker processes they start
    # and their nannies leave glibc's malloc as it is: dask sets MALLOC_TRIM_THRESHOLD_ in a worker's environment
    # (to hand freed memory back to the system at once), which also switches off glibc's sliding mmap threshold,
    # so every tile's prediction buffers (a few MB, freed at the tile's end) were mapped afresh and page-faulted in
    # again: tens of thousands of page faults a search that the in-process fit never pays (README "On a cluster")
    with dask.config.set({"distributed.worker.profile.enabled": False,
                          "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        with _sigint_ignored_in_children():  # only while the worker processes are spawned
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
        stopped = _StoppedKillFilter()
        nanny = logging.getLogger("distributed.nanny")  # our nannies run in this process
        nanny.addFilter(stopped)
        try:
            with cluster, Client(cluster) as client:
                # our workers' closing heartbeats fail without a traceback on stderr (worker_plugins); another's
                # cluster (scheduler=) keeps its own plugins
                client.register_plugin(QuietClosingHeartbeat())
                try:
                    yield client
                except BaseException:
                    stopped.on = True
                    raise
        finally:
            nanny.removeFilter(stopped)


class _AllExitFilter(logging.Filter):
    """Drops asyncio's "Task exception was never retrieved" for dask's ``AllExit``: the sentinel its client raises in
    the tasks still gathering when it closes (a fit stopped by Ctrl-C during the polish printed two such
    tracebacks above its one line; an outside tester). Every other unretrieved task exception still logs."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[0] if record.exc_info else None
        return not (exc is not None and exc.__name__ == "AllExit" and exc.__module__ == "distributed.client")


def _quiet_all_exit() -> None:
    """:class:`_AllExitFilter` on the ``asyncio`` logger, once a process."""
    log = logging.getLogger("asyncio")
    if not any(isinstance(f, _AllExitFilter) for f in log.filters):
        log.addFilter(_AllExitFilter())


class _StoppedKillFilter(logging.Filter):
    """Drops the nanny's "Worker process still alive after N seconds, killing" once the fit has stopped (Ctrl-C,
    an error): a worker busy in a task (numba compiling its kernels while it warms up) cannot close in time and is
    killed, as it should be, and the warning said nothing to the person who stopped it. An ordinary close keeps it."""

    on = False

    def filter(self, record: logging.LogRecord) -> bool:
        return not (self.on and str(record.msg).startswith("Worker process still alive after"))


@contextlib.contextmanager
def _sigint_ignored_in_children() -> Iterator[None]:
    """SIGINT blocked while the cluster starts, so that its worker processes never take it: a terminal's Ctrl-C
    reaches the whole process group, and each worker died of it with dask's tracebacks (104 lines on stderr for two
    workers) while the fit itself stopped in one line. The signal mask survives fork and exec, and the threads dask
    starts meanwhile (its event loop, which spawns the workers) inherit it: the workers keep SIGINT blocked, and the
    fit's own process handles the stop and closes the cluster. Blocked, not ignored: a Ctrl-C while the cluster
    starts stays pending and is taken as the mask is restored (ignored, it was lost, and the fit ran to its end).
    The main thread only: elsewhere the mask is not the process's to change."""
    import signal

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield  # (Windows has no signal masks, and no process group for a Ctrl-C to reach)
        return
    from multiprocessing import resource_tracker

    # multiprocessing unblocks SIGINT in the thread that first starts its resource tracker (CPython's
    # resource_tracker.ensure_running: SIG_UNBLOCK, not the mask as it was): started here first, dask's event loop
    # thread keeps the mask, and so does every worker it spawns
    resource_tracker.ensure_running()
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def tile_cost(steps: Sequence[int], tile: Tile) -> float:
    """Cost of a tile in register-steps (:func:`bench.models.batch_plan.chunk_cost`: each of its records is one
    chunk of its candidates)."""
    r0, r1, a, b = tile
    return chunk_cost(int(sum(steps[r0:r1])), b - a)


def tiles(m: int, steps: Sequence[int], threads: int) -> list[Tile]:
    """Tiles covering ``m`` candidates × records of ``steps`` input steps each, longest first: each record cut
    along the candidates (chunks of whole registers) as :func:`bench.models.batch_plan.register_splits` finds
    that the batch finishes sooner on ``threads`` threads — a narrow chunk costs more per candidate — and no
    records grouped (a campaign has few records, and grouping would coarsen the longest-first schedule)."""
    if m == 0 or not steps:
        return []
    splits = register_splits(m, tuple(int(n) for n in steps), threads)
    out = [(r, r + 1, int(a), int(b)) for r in range(len(steps))
           for a, b in itertools.pairwise(split_bounds(m, splits[r])) if b > a]
    return sorted(out, key=lambda t: -tile_cost(steps, t))


_SERIAL = threading.Lock()  # numba's workqueue layer aborts on concurrent parallel launches: one tile at a time


def _tile(Us: list[np.ndarray], Y0: np.ndarray, P: np.ndarray, h: float, stride: int, window: int,
          cal: np.ndarray | None) -> np.ndarray:
    """λ samples of one tile (worker side): the candidates P over the records Us, on one numba thread."""
    import numba

    from bench.identify.core import _kernels_thread_safe
    from bench.models.membrane_batch import membrane_batch_records

    numba.set_num_threads(1)  # per calling thread: the worker runs one tile per thread of its own
    with contextlib.nullcontext() if _kernels_thread_safe() else _SERIAL:
        return membrane_batch_records(P, Y0, Us, h, stride, window, cal)


def _tile_costs(Us: list[np.ndarray], Y0: np.ndarray, P: np.ndarray, h: float, stride: int, window: int,
                cal: np.ndarray | None, gain: float, offset: float, data: list[np.ndarray], sigma: list[np.ndarray],
                mask: list[np.ndarray], kind: str) -> np.ndarray:
    """Partial costs of one tile (worker side; records × candidates): its λ samples (:func:`_tile`) converted to
    the outputs gain·(λ − offset) and compared with each record's data (:func:`bench.identify.record_costs.
    record_costs`)."""
    from bench.identify.record_costs import record_costs

    pred = gain * (_tile(Us, Y0, P, h, stride, window, cal) - offset)
    out = np.empty((len(data), P.shape[0]))
    c0 = 0
    for k, (d, s, m) in enumerate(zip(data, sigma, mask, strict=True)):
        out[k] = record_costs(pred, c0, d, s, m, kind)
        c0 += d.size
    return out


def _on(slot: Slot | None) -> dict[str, object]:
    """A task's placement on ``slot``'s worker: loose (a worker gone leaves it to any other); none for None."""
    return {} if slot is None else {"workers": [slot[0]], "allow_other_workers": True}


def _in_turn(task: Callable[..., np.ndarray], turn: list[tuple[object, ...]]) -> list[np.ndarray]:
    """Several tiles of a batch on one worker thread, one after the other (worker side): ``task(*args)`` each."""
    return [task(*args) for args in turn]


def _warm(U: np.ndarray, Y0: np.ndarray, P: np.ndarray, h: float, stride: int, data: np.ndarray, sigma: np.ndarray,
          mask: np.ndarray) -> bool:
    """Load the kernels on a worker (numba's cache, its threading layer) with a few steps of one set, compared
    with the first columns of a record scattered there (the arrays the tasks get): what the first tile on a cold
    worker would otherwise pay, while the other tiles of its batch wait."""
    n = U.shape[0] // stride + 1
    _tile_costs([U], Y0, P, h, stride, 0, None, 1.0, 0.0, [data[:n]], [sigma[:n]], [mask[:n]], "sae")
    return True


def kernel_ready() -> bool:
    """On a worker: whether the batch kernel and the cost kernel are loaded there (compiled or read from numba's
    cache)."""
    from bench.identify.record_costs import _partial
    from bench.models.membrane_batch import _batch

    return all(bool(cast(Any, kernel).signatures) for kernel in (_batch, _partial))  # numba dispatchers


class DistributedPredict:
    """Batched λ of a membrane problem's records on a dask cluster, tiled over candidates × records, or the
    candidates' partial costs against the records' data (``data``, ``sigma``: per record, NaN data not compared)."""

    def __init__(self, client: Client, Us: list[np.ndarray], Y0: np.ndarray, h: float, stride: int,
                 window: int, P0: np.ndarray, data: list[np.ndarray], sigma: list[np.ndarray]) -> None:
        self.client, self.h, self.stride, self.window = client, h, stride, window
        self.Y0 = Y0
        self.steps = [len(U) for U in Us]
        cols = np.array(self.steps) // stride + 1
        self.columns = np.concatenate([[0], np.cumsum(cols)]).astype(int)
        if [d.size for d in data] != cols.tolist() or [s.size for s in sigma] != cols.tolist():
            raise ValueError("each record's data and σ must have one value per output sample of the record")
        from distributed import wait

        # once, to every worker: the records' inputs, and what their outputs are compared with
        self.records: list[Future[np.ndarray]] = client.scatter(list(Us), broadcast=True)
        self.data: list[Future[np.ndarray]] = client.scatter([np.array(d, float) for d in data], broadcast=True)
        self.sigma: list[Future[np.ndarray]] = client.scatter([np.array(s, float) for s in sigma], broadcast=True)
        self.mask: list[Future[np.ndarray]] = client.scatter([np.isfinite(d) for d in data], broadcast=True)
        self.evaluations = 0  # candidates evaluated on the cluster
        self._count = threading.Lock()  # the starts evaluate from threads of their own
        workers = client.scheduler_info().get("workers", {})
        # the cost each worker thread (address, thread) has been given by batches still under way (:meth:`_placed`)
        self._loads: dict[Slot, float] = {}
        self._placing = threading.Lock()
        # every worker known now loads the kernel: a batch's tiles go to any worker, and a cold one holds up a
        # batch; a worker gone meanwhile leaves its warm-up to another, and a slow one is not waited for past
        # WARM_TIMEOUT_S (the warm-up only saves time, results do not depend on it)
        few = np.ascontiguousarray(Us[0][:2 * stride])
        warming = [client.submit(_warm, few, Y0[:1], np.atleast_2d(P0), h, stride, self.data[0], self.sigma[0],
                                 self.mask[0], workers=[address], allow_other_workers=True, pure=False)
                   for address in workers]
        with contextlib.suppress(TimeoutError):
            wait(warming, timeout=WARM_TIMEOUT_S)

    def __call__(self, P: np.ndarray, cal: np.ndarray | None = None) -> np.ndarray:
        """λ of the packed sets P (one row per set, every record's samples side by side); ``cal``: the records'
        input calibration per set (records, len(P), 2) or None."""
        m = P.shape[0]
        plan, parts = self._batch(m, _tile, lambda r0, r1, a, b: (
            self.records[r0:r1], self.Y0[r0:r1], P[a:b], self.h, self.stride, self.window,
            None if cal is None else cal[r0:r1, a:b]))
        out = np.empty((m, int(self.columns[-1])))
        for (r0, r1, a, b), part in zip(plan, parts, strict=True):
            out[a:b, self.columns[r0]:self.columns[r1]] = part
        return out

    def _batch(self, m: int, task: Callable[..., np.ndarray],
               args: Callable[[int, int, int, int], tuple[object, ...]]) -> tuple[list[Tile], list[np.ndarray]]:
        """One batch of ``m`` candidates: its tiles (longest first) and each tile's result, ``task(*args(tile))``
        run on the worker :meth:`_placed` gives it; the candidates counted as evaluated."""
        slots = self.slots()
        plan = tiles(m, self.steps, max(1, len(slots)))
        with self._placed(plan, slots) as where:
            # the tiles a worker thread is given run there one after another anyway: as one task, without a
            # scheduler round trip between them (a few ms each on a 2-core machine, where the scheduler's work also
            # takes CPU from the workers); no worker known (none registered yet): one task a tile, unrestricted
            # (dask refuses to make a restriction to no worker loose)
            turns: dict[Slot | None, list[int]] = {}
            for k, slot in enumerate(where):
                turns.setdefault(slot, []).append(k)
            groups = [(slot, ks) for slot, ks in turns.items() if slot is not None] \
                + [(None, [k]) for k in turns.get(None, [])]
            # keyed by the task (prediction or costs): dask's duration estimates go by the key's prefix
            futures = [self.client.submit(_in_turn, task, [args(*plan[k]) for k in ks], pure=False,
                                          key=f"{getattr(task, '__name__', 'tile')}-turn-{uuid.uuid4().hex}",
                                          priority=len(plan) - ks[0], **_on(slot)) for slot, ks in groups]
            parts: list[np.ndarray] = [np.empty(0)] * len(plan)
            for (_, ks), got in zip(groups, self.client.gather(futures), strict=True):
                for k, part in zip(ks, got, strict=True):
                    parts[k] = part
        with self._count:
            self.evaluations += m
        return plan, parts

    def slots(self) -> list[Slot]:
        """The cluster's worker threads now, one slot each (address, thread): the tiles' count, and where
        :meth:`_placed` puts them (read at every batch: workers come and go)."""
        workers = self.client.scheduler_info().get("workers", {})
        return [(address, k) for address, w in sorted(workers.items()) for k in range(int(w.get("nthreads", 1)))]

    @contextlib.contextmanager
    def _placed(self, plan: list[Tile], slots: list[Slot]) -> Iterator[list[Slot | None]]:
        """The worker thread of each tile of ``plan`` (longest first) while its batch is under way: the worker thread
        free first, as the plan's cost model counts (:func:`tile_cost`), counting the tiles that batches running
        beside it (the fit's parallel starts) were given. Left to itself the scheduler put up to three of a
        generation's 12 tiles on one of 16 idle workers. The placement is a loose restriction: a worker gone
        leaves its tiles to any other, and work stealing may still move one; results never depend on it."""
        if not slots:  # no worker known: the scheduler places them
            yield [None for _ in plan]
            return
        charges = self.assign(plan, slots)
        try:
            yield [slot for slot, _ in charges]
        finally:
            with self._placing:
                for slot, cost in charges:
                    left = self._loads.get(slot, 0.0) - cost
                    if left > 1e-9 * cost:
                        self._loads[slot] = left
                    else:  # this batch's share was the last (to rounding)
                        self._loads.pop(slot, None)

    def assign(self, plan: list[Tile], slots: list[Slot]) -> list[tuple[Slot, float]]:
        """Each tile of ``plan`` given to the slot least loaded (its load counted in :attr:`_loads`, which this
        adds to), with its cost: longest-first list scheduling over the worker threads."""
        with self._placing:
            free = [(self._loads.get(slot, 0.0), k) for k, slot in enumerate(slots)]
            heapq.heapify(free)
            out = []
            for tile in plan:
                load, k = heapq.heappop(free)
                cost = tile_cost(self.steps, tile)
                out.append((slots[k], cost))
                self._loads[slots[k]] = self._loads.get(slots[k], 0.0) + cost
                heapq.heappush(free, (load + cost, k))
            return out

    def costs(self, P: np.ndarray, cal: np.ndarray | None, gain: float, offset: float, kind: str) -> np.ndarray:
        """Each record's partial cost (records × len(P); :mod:`bench.identify.record_costs`) of the packed sets P,
        whose outputs are gain·(λ − offset); ``cal`` as for a call. Each task returns its tile's partial costs only,
        never its samples."""
        m = P.shape[0]
        plan, parts = self._batch(m, _tile_costs, lambda r0, r1, a, b: (
            self.records[r0:r1], self.Y0[r0:r1], P[a:b], self.h, self.stride, self.window,
            None if cal is None else cal[r0:r1, a:b], gain, offset, self.data[r0:r1], self.sigma[r0:r1],
            self.mask[r0:r1], kind))
        out = np.empty((len(self.steps), m))
        for (r0, r1, a, b), part in zip(plan, parts, strict=True):
            out[r0:r1, a:b] = part
        return out
