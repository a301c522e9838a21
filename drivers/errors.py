"""Errors raised by drivers. Every message names the device and fits on one line."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.interfaces import StreamBlock


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


class StreamEndedError(InstrumentStateError):
    """The device ended a running stream with a status of its own (a DAQ's scan overlap, skip-counter overflow,
    buffer full). ``block`` holds every complete scan received up to and with the packet that said so: measured
    data, which the caller records before it lets the error stop the run."""

    def __init__(self, device: str, message: str, block: StreamBlock) -> None:
        super().__init__(device, message)
        self.block = block


class UnsupportedCommandError(InstrumentError):
    """The instrument has no such command (a bridge amplifier read on a DAQ has no tare); nothing was sent."""


class LimitError(InstrumentError):
    """A requested setting lies outside the configured software limits; nothing was sent."""


class OperationCancelledError(InstrumentError):
    """A wait on the instrument was abandoned because the application requested a stop."""


class ImplausibleValueError(ProtocolError):
    """A reply that parses but carries a value the instrument cannot report: beyond what its register or units
    can hold, far outside its configured range, or not a number. The reply is wrong, not the world: the value is
    never passed on as a measurement. The message names the quantity, the value and the valid range."""

    def __init__(self, device: str, quantity: str, value: float, valid: tuple[float, float], unit: str,
                 why: str = "") -> None:
        self.quantity, self.value, self.valid, self.unit = quantity, value, valid, unit
        lo, hi = (_number(v) for v in valid)
        super().__init__(device, f"{quantity} {_number(value)} {unit} is not a value it reports (valid {lo} … {hi} "
                         f"{unit}{': ' + why if why else ''})")


def _number(x: float) -> str:
    """An integer (a register's count) in full, a float to 9 significant digits."""
    return str(x) if isinstance(x, int) else f"{x:.9g}"
