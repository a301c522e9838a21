"""A stop request that reaches into every wait on an instrument.

The application owns one :class:`CancelToken` per rig and hands it to every link. Each loop that waits on
an instrument (a serial read, a Modbus transaction, a drive waiting for a state) calls :meth:`check` at least
once per poll, so a stop request ends the wait within one poll interval instead of one whole timeout. The
engine clears the token while it brings the rig to its safe state, so the shutdown commands themselves go out.
"""

from __future__ import annotations

import threading

from drivers.errors import OperationCancelledError


class CancelToken:
    """Set once a stop is requested; checked by every waiting loop of every driver that holds it."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.reason = ""

    @property
    def cancelled(self) -> bool:
        """Whether a stop has been requested (and not cleared)."""
        return self._event.is_set()

    def cancel(self, reason: str) -> None:
        """Request a stop (safe from a signal handler or another thread)."""
        if not self._event.is_set():
            self.reason = reason
        self._event.set()

    def clear(self) -> None:
        """Let instrument traffic through again (the shutdown sequence's own commands)."""
        self._event.clear()

    def check(self, device: str) -> None:
        """Raise :class:`OperationCancelledError` if a stop has been requested."""
        if self._event.is_set():
            raise OperationCancelledError(device, f"wait abandoned: {self.reason or 'stop requested'}")


def check(token: CancelToken | None, device: str) -> None:
    """:meth:`CancelToken.check` on an optional token."""
    if token is not None:
        token.check(device)
