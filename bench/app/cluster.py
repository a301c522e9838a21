"""The dask cluster seam of the use cases that compute in parallel (fit, design map): in-process by default."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from distributed import Client

CLUSTER_EXTRA = "dea-bench[cluster]"


@contextlib.contextmanager
def cluster_client(scheduler: str | None, workers: int | None) -> Iterator[Client | None]:
    """:func:`bench.identify.distributed.cluster_client`, refused in one line naming the extra when ``--scheduler``
    or ``--workers`` asks for a cluster and dask.distributed is not installed (it is an optional dependency)."""
    if scheduler is not None or workers:
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise ValueError(f"--scheduler/--workers compute on dask.distributed, which is not installed: "
                             f"pip install '{CLUSTER_EXTRA}'") from None
    from bench.identify.distributed import cluster_client as client_of

    with client_of(scheduler, workers) as client:
        yield client
