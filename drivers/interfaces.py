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


ReadingMap = dict[str, Reading]  # one reading of each column its describe() names, keyed by the column's name


@runtime_checkable
class Readable(Protocol):
    """What a run records of an instrument (bluesky's ``Readable``): :meth:`read` returns one :class:`Reading` of
    each column :meth:`describe` names, keyed by the column's name and in its unit (a flag column: 1.0 / 0.0,
    unit "1") — nothing more, nothing less. The run time's software-timed poll (bench/runtime/polls.py) records
    every readable instrument of a rig through these two methods alone."""

    name: str

    def describe(self) -> StreamDescription:
        """The stream it records: its name (the role's), columns, units, source."""

    def read(self) -> ReadingMap:
        """One reading of every column :meth:`describe` names, keyed by column name."""


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
class Amplifier(Instrument, Readable, Protocol):
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

    def read(self) -> ReadingMap:
        """The monitors (``voltage`` [V], ``current`` [A]) as :meth:`read_monitors` gives them, with any other column
        its :meth:`describe` names (a DAQ-driven amplifier: ``commanded`` [V])."""


@runtime_checkable
class DisplacementSensor(Instrument, Readable, Protocol):
    """Displacement sensor with single reads and a device-side buffer for high rates."""

    pending: int  # stored points known to the last fetch and not uploaded yet (a fetch may be partial)

    def read_displacement(self) -> Reading:
        """One displacement value [m] as the sensor measures it (its offset and sign are the run time's)."""

    def read(self) -> ReadingMap:
        """One :meth:`read_displacement` as ``displacement`` [m] and ``valid`` (1: a measurement)."""

    def start_buffer(self, interval: float) -> float:
        """Start buffered acquisition every ``interval`` [s]; returns the interval the device uses."""

    def fetch_buffer(self, within: float | None = None) -> SampleBlock:
        """Samples stored since the last fetch (possibly none, possibly not all: :attr:`pending`); ``within``: the
        rig time [s] the call may take (None: the driver's own bound)."""

    def stop_buffer(self) -> None:
        """Stop buffered acquisition (samples already stored stay fetchable)."""

    def describe(self) -> StreamDescription:
        """The stream it records: ``displacement``, ``valid`` (its displacement's description says how it is
        measured; the application prefixes what is measured)."""


@runtime_checkable
class LinearMotor(Instrument, Readable, Protocol):
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

    def read(self) -> ReadingMap:
        """One :meth:`read_position` as ``position`` [m]."""

    def status(self) -> MotorStatus:
        """Decoded drive state."""

    def stop(self) -> None:
        """Abort the current motion and hold position."""

    def hurry(self, reply_timeout: float) -> None:
        """From now on, requests to the drive wait at most ``reply_timeout`` [s] for their reply (shutdown: the abort
        takes effect when it arrives; a reply that never comes must not hold the rest of the stop back)."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""


@runtime_checkable
class ForceSensor(Instrument, Readable, Protocol):
    """Load cell read through a transmitter."""

    def read_force(self) -> Reading:
        """Force [N], tension positive."""

    def read(self) -> ReadingMap:
        """One :meth:`read_force` as ``force`` [N] and ``ok`` (1: a stable reading)."""

    def zero(self) -> None:
        """Zero the gross weight."""

    def tare(self) -> None:
        """Tare (net weight = 0 at the present load)."""

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""


@runtime_checkable
class Sensor(Instrument, Readable, Protocol):
    """An instrument the run time only reads (a thermometer, a hygrometer): a rig's
    :attr:`~bench.runtime.instruments.Instruments.sensors`, each recorded to its own stream by the generic poll."""


@dataclass(frozen=True)
class StreamIn:
    """One analog input in the scan list: AIN number, range (±V: 10, 1, 0.1, 0.01), label."""

    ain: int
    range_volts: float = 10.0
    name: str = ""


@dataclass(frozen=True)
class StreamOut:
    """A waveform [V at the DAC] played on analog output ``dac`` one value per scan; after the last value the
    last ``hold`` values repeat (1: the output stays exactly on the end value)."""

    dac: int
    volts: np.ndarray
    hold: int = 1
    final: bool = True  # False: more values follow through :meth:`StreamingDaq.extend`; no hold loop until then
    within: tuple[float, float] | None = None  # [V] no value plays outside (codes clipped: StreamingDaq.dac_coding)


@dataclass(frozen=True)
class StreamSpec:
    """What :meth:`StreamingDaq.arm` configures. ``num_scans`` > 0: a burst of that many scans. The fields after
    ``num_scans`` tune one device's stream (0: that device's default); another device ignores them."""

    scan_rate: float
    inputs: tuple[StreamIn, ...]
    output: StreamOut | None = None
    num_scans: int = 0
    samples_per_packet: int = 0  # 0: as many whole scans as fit in 512 samples
    resolution_index: int = 0
    settling_us: float = 0.0
    buffer_size_bytes: int = 0  # 0: the device's largest
    out_buffer_bytes: int = 0  # 0: the device's largest
    out_ahead_s: float = 0.0  # > 0: stream-out values written at most this far [s] ahead of the scan played now
    out_loops: bool = False  # with out_ahead_s: whole periods that repeat play from the device's loop, not refills
    # (the device's watchdog must be armed: a loop that outlives a lost host drives on until it fires)


@dataclass(frozen=True)
class StreamBlock:
    """Complete scans ``first_scan`` … ``first_scan + n − 1``; scan k was taken at ``t0 + k·dt``.

    ``volts`` has one column per input; rows of scans the device skipped (auto-recovery) are NaN and
    ``valid`` False. ``backlog_scans``: scans waiting in the device after the last packet; ``statuses``:
    non-zero packet statuses seen; ``done``: the burst completed or the stream stopped.
    """

    first_scan: int
    t0: float
    dt: float
    names: tuple[str, ...]
    volts: np.ndarray
    valid: np.ndarray
    backlog_scans: int = 0
    skipped_scans: int = 0
    statuses: tuple[int, ...] = ()
    done: bool = False

    @property
    def n(self) -> int:
        """Number of scans."""
        return int(self.volts.shape[0])

    def times(self) -> np.ndarray:
        """Rig-clock times of the scans [s]."""
        return self.t0 + self.dt * (self.first_scan + np.arange(self.n))

    def channel(self, i: int) -> SampleBlock:
        """One input as a :class:`SampleBlock` in volts (acquisition index = scan index)."""
        return SampleBlock(self.t0, self.dt, self.first_scan, self.volts[:, i].copy(), self.valid[:, i].copy(), "V")

@dataclass(frozen=True)
class DacCoding:
    """How an analog output turns volts into what it plays: code = round(V·``slope`` + ``offset``), the converter
    ignoring the low ``shift`` bits of the code; the codes ``lo`` … ``hi`` are those whose output lies within the
    window asked for (:meth:`StreamingDaq.dac_coding`)."""

    slope: float  # codes per volt
    offset: float  # code of 0 V
    shift: int  # low bits of a code the converter ignores (16-bit codes on a 12-bit DAC: 4)
    lo: int
    hi: int


@runtime_checkable
class StreamingDaq(Instrument, Protocol):
    """A DAQ that plays a waveform on an analog output and samples analog inputs on one scan clock (hardware-timed
    steps). The life of a stream, as ophyd-async's ``FlyerController`` composed by ``StandardFlyer``: :meth:`arm`
    (prepare and arm: configure inputs, scan clock and output, preload the output buffer; nothing runs),
    :meth:`kickoff` (scan 0), :meth:`collect` while it runs (and :meth:`extend` while the output is open),
    :meth:`stop`. The run time (bench/runtime/hardware_timed.py) knows a DAQ only through this contract."""

    timeout: float  # [s] a command-response request's reply timeout (a collect waits at least 4 times this)
    streaming: bool  # a stream runs (kicked off, not stopped)
    stop_unconfirmed: bool  # a stop went out unanswered: the device may stream (and play its stream-out) on

    @property
    def out_open(self) -> bool:
        """An armed stream-out still takes :meth:`extend`."""

    @property
    def scans_received(self) -> int:
        """Scan index of the next scan :meth:`collect` will return."""

    @property
    def out_underrun_scans(self) -> int:
        """Scans the stream-out played past the values written (0 unless a collect came too late)."""

    @property
    def scan_clock_uncertainty(self) -> float:
        """How well scan 0's time on the rig clock is known [s]."""

    def dac_coding(self, dac: int, within: tuple[float, float]) -> DacCoding:
        """How analog output ``dac`` codes volts, and its codes whose output lies within ``within`` (lo, hi) [V]."""

    def out_played(self, volts: np.ndarray, dac: int, within: tuple[float, float] | None = None) -> np.ndarray:
        """What analog output ``dac`` plays [V] for the stream-out values ``volts`` (codes clipped to ``within``),
        sending nothing."""

    def read_dac(self, dac: int) -> float:
        """The analog output's present value [V] (command-response: a request that also feeds the device's
        watchdog)."""

    def read_ain(self, ain: int) -> Reading:
        """One analog input now [V] (command-response)."""

    def arm(self, spec: StreamSpec) -> object:
        """Prepare and arm the stream ``spec`` describes; nothing runs until :meth:`kickoff`. Refuses (nothing
        sent) what the device cannot do."""

    def kickoff(self) -> float:
        """Start the armed stream; returns the rig time of scan 0."""

    def extend(self, volts: np.ndarray, final: bool = True, within: tuple[float, float] | None = None) -> np.ndarray:
        """Append values to the running stream-out (``final``: the last ones, the output then holds the last);
        returns what the output will play for them [V]."""

    def collect(self, until: float | None = None, timeout: float = 1.0) -> StreamBlock:
        """Complete scans received since the last call (waiting up to ``timeout`` s for those due by rig time
        ``until``); tops up the output buffer. A device status that ends the stream raises
        :class:`~drivers.errors.StreamEndedError` (one line naming the device and the status) whose ``block`` holds
        the scans this call received up to it: measured data, which the caller records before the error stops it."""

    def stop(self) -> StreamBlock | None:
        """Stop the stream (the output holds its last value); returns the scans that had arrived (also when the
        device had ended the stream itself: the stop raises no :class:`~drivers.errors.StreamEndedError`)."""

    def whole_packets_at(self) -> float:
        """Rig time at which the scans taken so far fill whole packets: a stop sent then loses none of them (the
        device sends no partly filled packet); at most one packet's time from now."""


@runtime_checkable
class DaqAmplifier(Amplifier, Protocol):
    """An amplifier whose set-point is a DAQ's analog output and whose monitors are two of its analog inputs: the
    run time plays its hardware-timed steps through the DAQ's stream (:attr:`Instruments.stream_drive`)."""

    def dac_volts(self, volts: np.ndarray | float) -> np.ndarray:
        """DAQ output [V] for amplifier output ``volts`` [V]."""

    def output_volts(self, dac_volts: np.ndarray | float) -> np.ndarray:
        """Amplifier output [V] for DAQ output ``dac_volts`` [V]."""

    def dac_window(self, within: float) -> tuple[float, float]:
        """DAQ output volts (lo, hi) whose amplifier output lies within ±``within`` [V]."""

    def monitor_values(self, vmon: np.ndarray, imon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(output voltage [V], output current [A]) from the monitor inputs' volts."""
