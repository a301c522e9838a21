"""Logging of the CLI: ``-v``/``-q`` on stderr, and a plain-text log file beside every run file.

Modules log to the ``bench`` logger tree (``logging.getLogger("bench.…")``); drivers and twins to theirs. The
stderr handler shows warnings by default, info with ``-v``, debug with ``-vv``, errors only with ``-q``.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

LOGGERS = ("bench", "drivers", "sim_devices")
FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
log = logging.getLogger("bench.cli")


def _reraise_stops(handler: logging.Handler, record: logging.LogRecord) -> None:
    """A handler's ``handleError``: a stop signal's exception raised while the handler wrote (the signal handlers
    of :func:`bench.runtime.engine.termination_raises` raise where the main thread is) goes on to the run, which
    makes the rig safe and says what it stopped; logging would print it as a "Logging error" traceback and swallow
    it, and the run would go on. Any other error is logging's as usual."""
    from drivers.errors import OperationCancelledError

    exc = sys.exc_info()[1]
    if isinstance(exc, OperationCancelledError):
        raise exc
    logging.Handler.handleError(handler, record)


class _RunLog(logging.FileHandler):
    """The run's log file (:func:`run_log`); a stop signal while it writes is not swallowed."""

    def handleError(self, record: logging.LogRecord) -> None:
        _reraise_stops(self, record)


class _Stderr(logging.StreamHandler[TextIO]):
    """Writes to the *current* sys.stderr (test runners swap it); a stop signal while it writes is not
    swallowed."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)

    def handleError(self, record: logging.LogRecord) -> None:
        _reraise_stops(self, record)


_stderr = _Stderr()
_stderr.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))


def configure_console(verbose: int = 0, quiet: bool = False) -> None:
    """Level of the stderr log: warnings (default), info (-v), debug (-vv), errors only (-q)."""
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO)[verbose] if verbose < 2 else logging.DEBUG
    _stderr.setLevel(level)
    for name in LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False
        if _stderr not in logger.handlers:
            logger.addHandler(_stderr)


def log_path(run_file: Path) -> Path:
    """The log file of a run file: ``RUN.log`` beside ``RUN.h5``."""
    return run_file.with_suffix(".log")


@contextlib.contextmanager
def run_log(run_file: Path, level: int = logging.INFO) -> Iterator[Path]:
    """Append everything logged while the block runs (info and above) to the run's log file."""
    path = log_path(run_file)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handler = _RunLog(path, encoding="utf-8")
    except OSError as exc:  # before anything runs: one line naming the run file's folder
        raise OSError(f"run file {run_file}: cannot create its folder or log ({exc.strerror or exc})") from None
    handler.setLevel(level)
    handler.setFormatter(logging.Formatter(FORMAT))
    configure_console(*_console_state())
    for name in LOGGERS:  # first: a stop signal raised in the console's write (re-raised) leaves the file its line
        logging.getLogger(name).handlers.insert(0, handler)
    try:
        yield path
    except Exception as exc:  # what ended the command (a dead port while connecting, …): the log's last line says it
        # info: the file's line only (stderr shows warnings and up, and the command prints its own one line there)
        log.info("not completed: %s", " ".join(str(exc).split()) or type(exc).__name__)
        raise
    finally:
        for name in LOGGERS:
            logging.getLogger(name).removeHandler(handler)
        handler.close()


def _console_state() -> tuple[int, bool]:
    """(verbose, quiet) equivalent of the stderr handler's present level."""
    level = _stderr.level or logging.WARNING
    if level >= logging.ERROR:
        return 0, True
    return {logging.WARNING: 0, logging.INFO: 1}.get(level, 2), False
