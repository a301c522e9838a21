"""Campaign fits and design maps on a dask.distributed cluster (an existing scheduler, or a LocalCluster).

The fit's search stays in this process; each generation's model evaluations — every candidate over every
record — are split by record into tasks on the cluster's workers. The records' inputs are scattered to the
workers once; a task receives only the candidates' packed parameters. Every candidate is integrated
independently, so the result is the same as in-process, bit for bit.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from distributed import Client


@contextmanager
def cluster_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Client | None]:
    """A dask client: to ``scheduler`` (e.g. tcp://host:8786) when given, else to a LocalCluster of ``workers``
    single-threaded worker processes when ``workers`` is given, else None (in-process)."""
    if scheduler is None and not workers:
        yield None
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        with Client(scheduler) as client:
            yield client
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        yield client


def _lambda_part(part: tuple[list[np.ndarray], np.ndarray], P: np.ndarray, h: float, stride: int,
                 window: int, cal: np.ndarray | None = None) -> np.ndarray:
    """λ samples of one group of records (worker side)."""
    import numba
    from distributed import get_worker

    from bench.models.membrane_batch import membrane_batch_records

    Us, Y0 = part
    threads = int(getattr(get_worker(), "nthreads", 1) or 1)  # the worker's share of cores: no oversubscription
    most = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # numba.config sets its NUMBA_* at import
    numba.set_num_threads(max(1, min(threads, int(most))))
    return membrane_batch_records(P, Y0, Us, h, stride, window, cal)


class DistributedPredict:
    """Batched λ of a membrane problem's records, one task per group of records on a dask cluster."""

    def __init__(self, client: Client, Us: list[np.ndarray], Y0: np.ndarray, h: float, stride: int, window: int,
                 groups: int | None = None) -> None:
        self.client, self.h, self.stride, self.window = client, h, stride, window
        n = len(Us)
        k = min(n, groups or max(1, len(client.scheduler_info().get("workers", {})) * 2))
        bounds = np.linspace(0, n, k + 1).round().astype(int)
        self.ranges = [(a, b) for a, b in itertools.pairwise(bounds) if b > a]
        self.parts = [client.scatter(([Us[i] for i in range(a, b)], Y0[a:b]), broadcast=True) for a, b in self.ranges]

    def __call__(self, P: np.ndarray, cal: np.ndarray | None = None) -> np.ndarray:
        """λ of the packed sets P; ``cal``: the records' input calibration per set (records, len(P), 2) or None."""
        futures = [self.client.submit(_lambda_part, part, P, self.h, self.stride, self.window,
                                      None if cal is None else cal[a:b], pure=False)
                   for part, (a, b) in zip(self.parts, self.ranges, strict=True)]
        return np.concatenate(self.client.gather(futures), axis=1)
