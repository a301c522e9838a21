"""Worker plugins for the LocalCluster that ``--workers N`` starts (imported only with the cluster extra).

:class:`QuietClosingHeartbeat`: a worker that is closing can still have a heartbeat to the scheduler in flight;
closing its own connections then fails that heartbeat, and dask logs it as an ERROR with a ``CommClosedError``
traceback on the worker's stderr (seen at the end of a ``--workers 16`` cluster on a 16-core machine, issue 24).
The worker is shutting down on purpose, so the failed heartbeat says nothing: the plugin drops that one record
while its worker is closing or closed. The same failure on a running worker (a scheduler really lost) still logs.

On a cluster of your own, ``dask worker --preload bench.identify.worker_plugins ADDRESS`` installs the same filter
(:func:`dask_setup`, dask's preload hook): the race is dask's and happens on any cluster's close.
"""

from __future__ import annotations

import logging
import weakref
from typing import Any

from distributed import WorkerPlugin
from distributed.core import Status

HEARTBEAT_FAILED = "Failed to communicate with scheduler during heartbeat"  # distributed/worker.py, Worker.heartbeat
# a worker that closes (not one retiring gracefully: it still runs, and its scheduler may really be lost)
CLOSING = frozenset({Status.closing, Status.closed})


class ClosingHeartbeatFilter(logging.Filter):
    """Drops the failed-heartbeat record of a worker that is closing or closed (the worker held weakly)."""

    def __init__(self, worker: Any) -> None:
        super().__init__()
        self._worker = weakref.ref(worker)

    def filter(self, record: logging.LogRecord) -> bool:
        if not str(record.msg).startswith(HEARTBEAT_FAILED):  # the format string: getMessage() may raise
            return True
        worker = self._worker()
        return worker is not None and getattr(worker, "status", None) not in CLOSING


class QuietClosingHeartbeat(WorkerPlugin):
    """Installs :class:`ClosingHeartbeatFilter` on the worker's logger when the worker starts."""

    name = "bench-quiet-closing-heartbeat"
    logger = "distributed.worker"  # the logger Worker.heartbeat logs to

    def setup(self, worker: Any) -> None:
        log = logging.getLogger(self.logger)
        for old in [f for f in log.filters if isinstance(f, ClosingHeartbeatFilter)]:  # an earlier worker's
            log.removeFilter(old)
        log.addFilter(ClosingHeartbeatFilter(worker))


def dask_setup(worker: Any) -> None:
    """dask's preload hook (``dask worker --preload bench.identify.worker_plugins``): the filter on this worker."""
    QuietClosingHeartbeat().setup(worker)
