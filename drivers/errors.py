"""Errors raised by drivers. Every message names the device and fits on one line."""

from __future__ import annotations


class InstrumentError(Exception):
    """Base class: something went wrong talking to or operating an instrument."""

    def __init__(self, device: str, message: str) -> None:
        self.device = device
        self.detail = message
        super().__init__(f"{device}: {message}")


class InstrumentConnectionError(InstrumentError):
    """The port cannot be opened, or the link was lost (dead port, unplugged adapter, closed socket)."""


class InstrumentTimeoutError(InstrumentError):
    """No (complete) reply within the timeout."""


class ProtocolError(InstrumentError):
    """A reply that does not parse: garbled bytes, wrong echo, bad length or checksum."""


class InstrumentStateError(InstrumentError):
    """The instrument answered but refused: error reply, wrong state, fault latched."""


class LimitError(InstrumentError):
    """A requested setting lies outside the configured software limits; nothing was sent."""


class OperationCancelledError(InstrumentError):
    """A wait on the instrument was abandoned because the application requested a stop."""
