"""Typed contracts shared by every driver of a role (bluesky-style small protocols).

A driver knows its instrument's wire protocol and behaviour, nothing about physics or test protocols.
Values are SI (V, A, m, N, s); every reading carries the time at which it was taken on the rig clock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

ClockFn = Callable[[], float]  # rig clock: seconds, monotonic
SleepFn = Callable[[float], None]  # waits on the rig clock (a virtual clock advances instead of sleeping)


@dataclass(frozen=True)
class Reading:
    """One value with its unit, rig-clock timestamp [s] and status.

    status is "ok", or names why the value is not a measurement ("over_range_positive",
    "over_range_negative", "invalid", "overload", "underload", "unstable", "error" — the instrument is in
    an error state); then value may be NaN. A value that is not finite is never "ok": drivers report it
    as "invalid" (or raise ProtocolError when the wire format cannot carry it).
    """

    value: float
    unit: str
    timestamp: float
    status: str = "ok"

    @property
    def ok(self) -> bool:
        """True when the value is a valid measurement."""
        return self.status == "ok"


@dataclass(frozen=True)
class Identity:
    """What an instrument says (or the rig file says) it is."""

    vendor: str
    model: str
    details: dict[str, str] = field(default_factory=dict)

    def __str__(self) -> str:
        extra = ", ".join(f"{k} {v}" for k, v in self.details.items())
        return f"{self.vendor} {self.model}" + (f" ({extra})" if extra else "")


@dataclass(frozen=True)
class SampleBlock:
    """A block of equally spaced samples from a device-side buffer.

    Sample k (0-based within the whole acquisition) was taken at ``t0 + k·dt`` on the rig clock;
    ``first_index`` is the acquisition index of ``values[0]``; ``valid`` flags samples that are measurements.
    """

    t0: float
    dt: float
    first_index: int
    values: np.ndarray
    valid: np.ndarray
    unit: str

    def times(self) -> np.ndarray:
        """Rig-clock times of the samples [s]."""
        return self.t0 + self.dt * (self.first_index + np.arange(self.values.size))


@dataclass(frozen=True)
class DataKey:
    """One recorded quantity: column name, unit (SI, "1" for flags), what it is, numpy dtype."""

    name: str
    unit: str
    description: str
    dtype: str = "f8"


@dataclass(frozen=True)
class StreamDescription:
    """What an instrument records: the stream (its role's name), its columns besides time, and the source text."""

    stream: str
    columns: tuple[DataKey, ...]
    source: str


@dataclass(frozen=True)
class CheckResult:
    """What ``devices check`` shows of a connected instrument: its state in words and a first reading of each
    quantity it measures (SI values, each with its unit)."""

    state: str
    readings: tuple[tuple[str, Reading], ...]  # (quantity, reading)


@dataclass(frozen=True)
class MotorStatus:
    """Decoded drive state: main state name, flags and position [m]."""

    state: str
    enabled: bool
    homed: bool
    moving: bool
    in_target: bool
    error: bool
    error_code: int
    position: float
    error_text: str = ""  # the drive's meaning of error_code ("" when no error)


@runtime_checkable
class Instrument(Protocol):
    """Common part of every driver."""

    name: str

    def connect(self) -> None:
        """Open the link and check that the instrument answers."""

    def close(self) -> None:
        """Bring the instrument to its safe state (where it has one) and release the link."""

    def identify(self) -> Identity:
        """Ask the instrument what it is."""

    def safe_state(self) -> None:
        """Put the instrument in its safe state (zero high voltage, motor stopped)."""

    def check(self) -> CheckResult:
        """State and a first reading of everything it measures (``bench devices check``)."""


@runtime_checkable
class Amplifier(Instrument, Protocol):
    """High-voltage amplifier: voltage set-point, voltage and current monitors."""

    max_voltage: float

    @property
    def commanded(self) -> float:
        """Last output voltage commanded [V] (as the set-point module really outputs it)."""

    def quantise(self, volts: float, within: float | None = None) -> float:
        """The output [V] a set-point of ``volts`` really commands, sending nothing: the set-point module's code
        nearest to ``volts`` among those whose output lies within ±``within`` (default, and at most,
        ``max_voltage``) — one code toward zero where the nearest lies just beyond the bound. Refuses
        (LimitError) what :meth:`set_voltage` refuses; no slew limit applied."""

    def set_voltage(self, volts: float, within: float | None = None) -> float:
        """Command an output voltage [V] on the code :meth:`quantise` chooses (after slew limiting); returns the
        value actually commanded, never beyond ±``within``."""

    def zero(self) -> None:
        """Command 0 V at once (no slew limit); goes out even after a stop request."""

    def read_monitors(self) -> tuple[Reading, Reading]:
        """(output voltage [V], output current [A]) read together."""

    def heard_at(self) -> float | None:
        """``time.monotonic()`` at which the module that sets the output last received a request from this host
        (the send time of the last one it answered; None: none yet). Its communication watchdog counts from
        there: the run time's keep-alive uses it."""

    def watchdog_fired(self) -> bool | None:
        """The set-point module's own word on its communication watchdog: True once it fired (since it was
        connected), False if not, None when the module keeps no such flag."""

    def hurry(self, reply_timeout: float) -> None:
        """From now on, requests to the set-point module wait at most ``reply_timeout`` [s] for their reply and are
        sent once (shutdown: a request takes effect when it arrives; a reply that never comes must not hold the
        zeroing back)."""

    def longest_silence(self) -> float:
        """The longest time [s] that module went without a request from this host since the last call (the present
        silence included), counting again from here: the run time's interlock uses it to tell whether the
        module's communication watchdog may have zeroed the output behind the host's back."""

    def read_voltage(self) -> Reading:
        """Output voltage from the voltage monitor [V]."""

    def read_current(self) -> Reading:
        """Output current from the current monitor [A]."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""


@runtime_checkable
class DisplacementSensor(Instrument, Protocol):
    """Displacement sensor with single reads and a device-side buffer for high rates."""

    pending: int  # stored points known to the last fetch and not uploaded yet (a fetch may be partial)

    def read(self) -> Reading:
        """One displacement value [m]."""

    def start_buffer(self, interval: float) -> float:
        """Start buffered acquisition every ``interval`` [s]; returns the interval the device uses."""

    def fetch_buffer(self) -> SampleBlock:
        """Samples stored since the last fetch (possibly none)."""

    def stop_buffer(self) -> None:
        """Stop buffered acquisition (samples already stored stay fetchable)."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source (its displacement's description says how it is measured;
        the application prefixes what is measured)."""


@runtime_checkable
class LinearMotor(Instrument, Protocol):
    """Position-controlled linear motor."""

    def enable(self) -> None:
        """Switch the drive on (and home it if needed) so that it accepts motion commands."""

    def quantise(self, position: float) -> float:
        """The target [m] :meth:`move_to` really sends for ``position`` (the drive's nearest increment, one toward
        the inside where that lies just beyond the travel), sending nothing."""

    def move_to(self, position: float, velocity: float, acceleration: float,
                deceleration: float | None = None) -> None:
        """Start a move to ``position`` [m] (sent as :meth:`quantise` gives it) with the given limits [m/s, m/s²];
        returns when accepted."""

    def read_position(self) -> Reading:
        """Actual position [m]."""

    def status(self) -> MotorStatus:
        """Decoded drive state."""

    def stop(self) -> None:
        """Abort the current motion and hold position."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""


@runtime_checkable
class ForceSensor(Instrument, Protocol):
    """Load cell read through a transmitter."""

    def read(self) -> Reading:
        """Force [N], tension positive."""

    def zero(self) -> None:
        """Zero the gross weight."""

    def tare(self) -> None:
        """Tare (net weight = 0 at the present load)."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""
