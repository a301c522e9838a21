"""Worker plugins for the LocalCluster that ``--workers N`` starts (imported only with the cluster extra).

:class:`QuietClosingHeartbeat`: a worker that is closing can still have a heartbeat to the scheduler in flight;
closing its own connections then fails that heartbeat, and dask logs it as an ERROR with a ``CommClosedError``
traceback on the worker's stderr (seen at the end of a ``--workers 16`` cluster on a 16-core machine, issue 24).
The worker is shutting down on purpose, so the failed heartbeat says nothing: the plugin drops that one record
while its worker is closing or closed. The same failure on a running worker (a scheduler really lost) still logs.

Likewise a task cancelled by the worker's close (a fit stopped by Ctrl-C while its workers were warming up): dask
logs "Async instruction for <Task …> ended with CancelledError" as a WARNING ("should exclusively happen in
Worker.close()", its source says), one line per worker under the fit's own line; dropped while its worker closes.

On a cluster of your own, ``dask worker --preload bench.identify.worker_plugins ADDRESS`` installs the same filter
(:func:`dask_setup`, dask's preload hook): the race is dask's and happens on any cluster's close.
"""

from __future__ import annotations

import logging
import weakref
from typing import Any, ClassVar

from distributed import WorkerPlugin
from distributed.core import Status

HEARTBEAT_FAILED = "Failed to communicate with scheduler during heartbeat"  # distributed/worker.py, Worker.heartbeat
# a worker that closes (not one retiring gracefully: it still runs, and its scheduler may really be lost)
CLOSING = frozenset({Status.closing, Status.closed})


CANCELLED_ON_CLOSE = ("Async instruction for ", " ended with CancelledError")  # worker_state_machine.py,
# BaseWorker._handle_stimulus_from_task: a task cancelled by Worker.close()


class ClosingHeartbeatFilter(logging.Filter):
    """Drops the failed-heartbeat record of a worker that is closing or closed (the worker held weakly)."""

    starts, ends = HEARTBEAT_FAILED, ""

    def __init__(self, worker: Any) -> None:
        super().__init__()
        self._worker = weakref.ref(worker)

    def filter(self, record: logging.LogRecord) -> bool:
        msg = str(record.msg)  # the format string: getMessage() may raise
        if not (msg.startswith(self.starts) and msg.endswith(self.ends)):
            return True
        worker = self._worker()
        return worker is not None and getattr(worker, "status", None) not in CLOSING


class CancelledOnCloseFilter(ClosingHeartbeatFilter):
    """Drops the record of a task cancelled by its worker's close, while the worker is closing or closed."""

    starts, ends = CANCELLED_ON_CLOSE


class QuietClosingHeartbeat(WorkerPlugin):
    """Installs :class:`ClosingHeartbeatFilter` and :class:`CancelledOnCloseFilter` on the loggers dask logs them to
    when the worker starts."""

    name = "bench-quiet-closing-heartbeat"
    loggers: ClassVar[dict[str, type[ClosingHeartbeatFilter]]] = {
        "distributed.worker": ClosingHeartbeatFilter,  # Worker.heartbeat
        "distributed.worker.state_machine": CancelledOnCloseFilter}

    def setup(self, worker: Any) -> None:
        for name, kind in self.loggers.items():
            log = logging.getLogger(name)
            for old in [f for f in log.filters if type(f) is kind]:  # an earlier worker's
                log.removeFilter(old)
            log.addFilter(kind(worker))


def dask_setup(worker: Any) -> None:
    """dask's preload hook (``dask worker --preload bench.identify.worker_plugins``): the filter on this worker."""
    QuietClosingHeartbeat().setup(worker)
