"""Keyence LK-G3000 / LK-G5000 laser displacement controller over RS-232C (ASCII, CR-terminated).

Wire protocol (LK-G manual LK-G-M-NO5-E, ch. 5; see ../shared/instruments.md §1):

* request ``MAIN[,ID1[,ID2[,ID3]]]<CR>``; one outstanding request at a time;
* reply echoes the main command (and identifiers) then data: ``M1,+01.2345<CR>``;
* error reply ``ER,<MAIN>,<code><CR>``;
* measured values are 8 characters: sign + 7 characters with a decimal point, in mm (display unit);
  ``+FFFFFFF``/``-FFFFFFF`` = over range, ``XXXXXXXX`` = no valid value;
* general mode (measurement) vs communication mode (settings): ``Q0`` enters, ``R0`` leaves.

Measured values: ``M0`` (both OUTs), ``M1``/``M2`` on the LK-G3000; ``MS,nn`` on the LK-G5000.
Data storage (``AQ`` clear, ``AS`` start, ``AP`` stop, ``AN`` status, ``AO`` upload) is the way to high rates.
The storage commands' parameters are not in any manual page we could read; this driver and the simulated
controller agree on the following, to be checked against the unit before real use:

* ``SW,CA,<0..5>``: sampling cycle 20/50/100/200/500/1000 µs (from public drivers);
* ``SW,EB,<0..9>``: storage cycle ×1/2/5/10/20/50/100/200/500/1000 samplings (LKIF enum, code assumed);
* ``SW,EC,<sign+6 digits>``: number of points to store (assumed);
* ``AN`` → ``AN,<0|1 storing>,<stored count>``; ``AO,<out>,<first>,<n>`` → ``AO,<v>,<v>,…`` (assumed).
"""

from __future__ import annotations

import math
import re
import time
from typing import Literal

import numpy as np

from drivers.cancel import check
from drivers.errors import ImplausibleValueError, InstrumentStateError, ProtocolError
from drivers.interfaces import (
    CheckResult,
    ClockFn,
    DataKey,
    Identity,
    Reading,
    ReadingMap,
    SampleBlock,
    StreamDescription,
)
from drivers.serial_link import SerialLink, usb_latency_ms

Model = Literal["LK-G3000", "LK-G5000"]
SAMPLING_US = (20, 50, 100, 200, 500, 1000)  # SW,CA codes 0..5
STORAGE_CYCLES = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)  # SW,EB codes 0..9
ERROR_CODES: dict[Model, dict[str, str]] = {
    "LK-G3000": {"00": "command error", "01": "status error (wrong mode)", "20": "command length error",
                 "21": "parameter count error", "22": "invalid parameter", "88": "timeout error",
                 "99": "other error"},
    "LK-G5000": {"50": "command error", "51": "status error (wrong mode)", "60": "command length error",
                 "61": "parameter count error", "62": "parameter range error", "88": "timeout error",
                 "99": "other error"},
}
MAX_UPLOAD = 1000  # points per AO request
FETCH_BUDGET_S = 0.2  # one fetch_buffer call: at most about this long on the wire (the rest on the next call)
VALUE_BYTES = 9  # one stored value on the wire: 8 characters and a comma
# one fetch's fixed exchange: the AN status (3 + up to 16 characters) and the AO request and its reply's head
# (up to 16 + 3 characters) — the link budget's figure (bench/protocol/link_budget.py, laser_fetch_time)
FETCH_OVERHEAD_BYTES = 16 + 3 + 3 + 16
# per exchange, beyond its characters: the controller's turnaround, the host's latency; a USB-serial adapter whose
# latency timer holds replies longer (FTDI's default is 16 ms) gets its timer instead (:meth:`KeyenceLKG.__init__`)
EXCHANGE_ALLOWANCE_S = 2e-3
_NUMBER = re.compile(r"[+-](?=[0-9.]{7}$)[0-9]*\.[0-9]*")  # sign + 7 characters: digits and one point
_NUMBERS = re.compile(r"[+-][0-9.]{7}(?:,[+-][0-9.]{7})*")
# Data-storage capacity per OUT (points). Not from a manual page we could read: treat as an assumption.
# The LK-G5000 figure is the largest count the 6-digit setting format can carry.
STORAGE_CAPACITY: dict[Model, int] = {"LK-G3000": 65_536, "LK-G5000": 999_999}
MAX_STORAGE_SETTING = 999_999  # SW,EC takes sign + 6 digits: the most points any storage run asks for


def format_value(mm: float | None, status: str = "ok") -> str:
    """Measured-value field of 8 characters (manual p. 5-6): sign + 7 characters incl. decimal point."""
    if status == "over_range_positive":
        return "+FFFFFFF"
    if status == "over_range_negative":
        return "-FFFFFFF"
    if status == "invalid" or mm is None:
        return "XXXXXXXX"
    sign = "-" if mm < 0 else "+"
    body = f"{abs(mm):07.4f}"  # 4 decimals = 0.1 µm display resolution of the LK-G heads used here
    if len(body) > 7:
        return sign + "FFFFFFF"
    return sign + body





def parse_values(text: str, device: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse comma-separated measured values → (mm, valid); one vectorised pass when all are numbers.

    Every field must be a manual-format field (:func:`parse_value`); the first that is not is named.
    """
    n = text.count(",") + 1
    if _NUMBERS.fullmatch(text) and text.count(".") == n:
        try:
            values = np.array(text.split(","), dtype=np.float64)
        except ValueError:
            pass  # a field with two points: the field-by-field parse names it
        else:
            return values, np.ones(values.size, dtype=bool)
    parsed = []
    for i, f in enumerate(text.split(",")):
        try:
            parsed.append(parse_value(f, device))
        except ProtocolError as exc:
            raise ProtocolError(device, f"{exc.detail} (field {i + 1} of {n})") from None
    return np.array([v for v, _ in parsed]), np.array([s == "ok" for _, s in parsed], dtype=bool)


def parse_value(field: str, device: str) -> tuple[float, str]:
    """Parse an 8-character measured value into (mm, status).

    Manual p. 5-6: sign + 7 characters including one decimal point (``+01.2345``), ``±FFFFFFF`` over
    range, ``XXXXXXXX`` no valid value. Anything else — ``+nan``, ``inf``, exponents, blanks — is a
    :class:`ProtocolError`, so a reading with status "ok" is always a finite number.
    """
    if len(field) != 8:
        raise ProtocolError(device, f"measured value {field!r} is not 8 characters")
    if field == "XXXXXXXX":
        return math.nan, "invalid"
    if field[0] not in "+-":
        raise ProtocolError(device, f"measured value {field!r} has no sign")
    if field[1:] == "FFFFFFF":
        return math.nan, "over_range_positive" if field[0] == "+" else "over_range_negative"
    if not _NUMBER.fullmatch(field):
        raise ProtocolError(device, f"measured value {field!r} is not a number (sign, digits, one point)")
    value = float(field)
    if not math.isfinite(value):  # cannot happen for a field that matched; kept as the rule's last guard
        raise ProtocolError(device, f"measured value {field!r} is not finite")
    return value, "ok"


class KeyenceLKG:
    """Driver for one OUT of a Keyence LK-G3000/LK-G5000 controller (implements DisplacementSensor)."""

    def __init__(self, link: SerialLink, *, name: str = "laser", model: Model = "LK-G3000", out: int = 1,
                 clock: ClockFn = time.monotonic, storage_points: int | None = None,
                 fetch_budget_s: float = FETCH_BUDGET_S, max_fetch_points: int | None = None) -> None:
        """``fetch_budget_s``: wall or rig time one :meth:`fetch_buffer` call may spend uploading (requests are
        sized to fit it at the link's baud rate); ``max_fetch_points``: optional cap on points per call."""
        if model not in ERROR_CODES:
            raise ValueError(f"unknown Keyence controller model {model!r}")
        self.link = link
        self.name = name
        self.model: Model = model
        self.out = out
        self.clock = clock
        self.storage_points = storage_points or STORAGE_CAPACITY[model]
        if not 0 < self.storage_points <= MAX_STORAGE_SETTING:
            raise ValueError(f"{name}: storage_points must be 1…999999, got {self.storage_points}")
        self._comm_mode = False
        self._t0 = 0.0
        self._dt = 0.0
        self._fetched = 0
        self.fetch_budget_s = fetch_budget_s
        # a bounded fetch's allowance per exchange: an adapter holding each reply up to its latency timer would
        # otherwise overrun the bound by that much an exchange (a reviewer: 50.9 ms in a 37-ms bound at 16 ms)
        latency = usb_latency_ms(link.url) if isinstance(getattr(link, "url", None), str) else None
        self.exchange_allowance_s = max(EXCHANGE_ALLOWANCE_S, (latency or 0) * 1e-3)
        self.max_fetch_points = max_fetch_points
        self.pending = 0  # stored points known to the last fetch and not uploaded yet

    # ----------------------------------------------------------- protocol
    def query(self, command: str, reply_bytes: int = 0) -> list[str]:
        """Send one command, return the reply's fields; raise on an error reply or a garbled echo.

        ``reply_bytes``: expected reply size, to add its wire time (10 bits per byte) to the timeout.
        """
        return self.query_text(command, reply_bytes).split(",")

    def query_text(self, command: str, reply_bytes: int = 0) -> str:
        """Like :meth:`query` but returns the checked reply as one string (for bulk uploads)."""
        main = command.split(",")[0].upper()
        timeout = self.link.timeout + 1.5 * 10 * (reply_bytes + len(command) + 1) / self.link.baudrate
        with self.link.lock:
            self.link.write(command.encode("ascii") + b"\r")
            raw = self.link.read_until(b"\r", timeout=timeout)
        try:
            text = raw[:-1].decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError(self.name, f"reply to {command!r} is not ASCII: {raw!r}") from None
        head = text.split(",", 3)
        if head[0] == "ER":
            code = head[2] if len(head) > 2 else "?"
            meaning = ERROR_CODES[self.model].get(code, "unknown error code")
            raise InstrumentStateError(self.name, f"{command!r} refused: ER {code} ({meaning})")
        if head[0].upper() != main:
            raise ProtocolError(self.name, f"reply {text[:60]!r} does not echo command {main!r}")
        return text

    def _settings_mode(self, on: bool) -> None:
        if on != self._comm_mode:
            self.query("Q0" if on else "R0")
            self._comm_mode = on

    # ----------------------------------------------------------- Instrument
    def connect(self) -> None:
        """Open the port, leave communication mode if a previous session left it there, probe once."""
        self.link.open()
        self.link.discard_input()
        self._comm_mode = True
        try:
            self._settings_mode(False)
        except InstrumentStateError:
            self._comm_mode = False  # already in general mode: R0 answered with a status error
        self.read_displacement()

    def close(self) -> None:
        """Release the port (the sensor has no unsafe state)."""
        self.link.close()

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""
        return StreamDescription(self.name, (
            DataKey("displacement", "m", "from the laser (offset and sign removed)"),
            DataKey("valid", "1", "1 = measurement, 0 = over range / invalid", "u1")), f"Keyence {self.model}")

    def check(self) -> CheckResult:
        """One displacement reading in general mode."""
        return CheckResult("general mode", (("displacement", self.read_displacement()),))

    def identify(self) -> Identity:
        """The controller has no identification command: report the configured model and program number."""
        program = self.query("PR")
        return Identity("Keyence", self.model, {"program": program[1] if len(program) > 1 else "?",
                                                "out": str(self.out)})

    def safe_state(self) -> None:
        """Stop data storage if it runs; nothing else is hazardous."""
        if self.link.is_open:
            self.query("AP")

    # ----------------------------------------------------------- measurement
    def _value_command(self) -> str:
        return f"M{self.out}" if self.model == "LK-G3000" else f"MS,{self.out:02d}"

    def read(self) -> ReadingMap:
        """One :meth:`read_displacement` keyed as :meth:`describe`: ``displacement`` [m], ``valid`` (1 / 0)."""
        r = self.read_displacement()
        return {"displacement": r, "valid": Reading(float(r.ok), "1", r.timestamp)}

    def read_displacement(self) -> Reading:
        """One measured value of the OUT [m] (status tells over-range / invalid), stamped at the start of the
        controller's reply (:meth:`SerialLink.reply_started`), not after its wire time."""
        with self.link.lock:
            self._settings_mode(False)
            fields = self.query(self._value_command())
            t = self.link.reply_started(self.clock())
        if len(fields) != (2 if self.model == "LK-G3000" else 3):
            raise ProtocolError(self.name, f"unexpected reply fields {fields!r}")
        mm, status = parse_value(fields[-1], self.name)
        return Reading(mm * 1e-3, "m", t, status)

    def set_sampling(self, microseconds: int) -> None:
        """Set the internal sampling cycle (20…1000 µs; enters and leaves communication mode)."""
        if microseconds not in SAMPLING_US:
            raise ValueError(f"{self.name}: sampling cycle must be one of {SAMPLING_US} µs, got {microseconds}")
        self._settings_mode(True)
        try:
            self.query(f"SW,CA,{SAMPLING_US.index(microseconds)}")
        finally:
            self._settings_mode(False)

    # ----------------------------------------------------------- buffered acquisition
    @staticmethod
    def storage_setting(interval: float) -> tuple[int, int]:
        """(sampling µs, storage cycle) whose product is closest to ``interval`` [s].

        Among equal products the smallest storage cycle wins: every measurement is stored, at the longest
        exposure (robust on translucent films such as VHB).
        """
        best = min(((s, c) for s in SAMPLING_US for c in STORAGE_CYCLES),
                   key=lambda sc: (abs(sc[0] * sc[1] * 1e-6 - interval), sc[1]))
        return best

    def start_buffer(self, interval: float) -> float:
        """Configure and start data storage every ``interval`` [s]; returns the interval used."""
        sampling, cycle = self.storage_setting(interval)
        self._settings_mode(True)
        try:
            self.query(f"SW,CA,{SAMPLING_US.index(sampling)}")
            self.query(f"SW,EB,{STORAGE_CYCLES.index(cycle)}")
            self.query(f"SW,EC,+{self.storage_points:06d}")
        finally:
            self._settings_mode(False)
        self.query("AQ")
        with self.link.lock:  # storage starts as the controller replies to AS (its start on the wire, as a read's)
            self.query("AS")
            self._t0 = self.link.reply_started(self.clock())
        self._dt = sampling * cycle * 1e-6
        self._fetched = 0
        self.pending = 0
        return self._dt

    def buffer_status(self) -> tuple[bool, int]:
        """(storing, number of points stored); a count outside 0 … 999 999 is an :class:`ImplausibleValueError`:
        the storage setting (``SW,EC``, 6 digits) asks for no more, so no controller stores more (the models'
        capacities themselves are assumptions, :data:`STORAGE_CAPACITY`, and do not bound it)."""
        fields = self.query("AN")
        if len(fields) != 3:
            raise ProtocolError(self.name, f"AN reply {fields!r} is not AN,<state>,<count>")
        try:
            count = int(fields[2])
        except ValueError:
            raise ProtocolError(self.name, f"AN reply {fields!r} has a non-numeric count") from None
        if not 0 <= count <= MAX_STORAGE_SETTING:
            raise ImplausibleValueError(self.name, "stored point count", count, (0, MAX_STORAGE_SETTING), "points",
                                        "the 6-digit storage setting")
        return fields[1] == "1", count

    def upload_chunk(self) -> int:
        """Points per AO request: at most ``fetch_budget_s`` of wire time at the link's baud rate."""
        wire_points = int(self.fetch_budget_s * self.link.baudrate / (10 * VALUE_BYTES))
        return max(1, min(MAX_UPLOAD, wire_points))

    def _wire_s(self, nbytes: int) -> float:
        """Seconds ``nbytes`` characters take at the link's baud rate (10 bits each)."""
        return 10 * nbytes / self.link.baudrate

    def _fitting(self, until: float | None, now: float) -> int:
        """How many stored values one AO request may ask for so that it ends by ``until`` from ``now`` (this
        driver's clock; None: no bound): its request and reply head, one exchange's allowance, 9 characters a
        value."""
        if until is None:
            return MAX_UPLOAD
        left = until - now - self._wire_s(16 + 3) - self.exchange_allowance_s
        return max(0, int(left / self._wire_s(VALUE_BYTES)))

    def fetch_buffer(self, within: float | None = None) -> SampleBlock:
        """Upload points stored since the last fetch, within a bounded time; the rest on the next call.

        One call sends AO requests of :meth:`upload_chunk` points until it has caught up, spent
        ``fetch_budget_s`` of wall time or of rig time (its clock: in a virtual run the wire time the twin
        takes, where the wall may pass much faster — a drain's fetch of a whole step's storage in one call starved
        the set-point module's keep-alive until its watchdog zeroed the output), reached ``max_fetch_points``,
        or a stop is requested (checked between requests); :attr:`pending` tells how many stored points are
        still to fetch. A call that fails uploads nothing: the next one starts again from the same point.

        ``within``: seconds of rig time (this driver's clock: the wall on hardware, the virtual clock — which
        the twins' wire time advances — in a virtual run) the whole call may take, status query included. Each
        request is sized from the wire time it will take (9 characters a value at the baud rate, plus its own
        characters and the exchange allowance, :data:`EXCHANGE_ALLOWANCE_S` or the adapter's latency timer) to
        end in it, counted from the later of the clock and the exchanges' own wire time so far (a clock the wire
        does not advance — a line at pty speed — still bounds the call by what the line would take); a call with
        too little time for the status query and one value touches no wire and returns no values, :attr:`pending`
        at least 1 (the storage was not asked: the caller comes back).
        """
        started = time.monotonic()
        begun = self.clock()
        until = None if within is None else begun + within
        least = self._wire_s(FETCH_OVERHEAD_BYTES + VALUE_BYTES) + 2 * self.exchange_allowance_s
        if within is not None and within < least:
            self.pending = max(self.pending, 1)
            return SampleBlock(self._t0, self._dt, self._fetched, np.zeros(0), np.zeros(0, dtype=bool), "m")
        storing, count = self.buffer_status()
        wired = self._wire_s(3 + 16) + self.exchange_allowance_s  # the exchanges' wire time so far: the status query
        values: list[np.ndarray] = []
        valid: list[np.ndarray] = []
        first = self._fetched
        limit = count if self.max_fetch_points is None else min(count, first + self.max_fetch_points)
        try:
            while self._fetched < limit:
                if values and (max(time.monotonic() - started, self.clock() - begun) >= self.fetch_budget_s
                               or (self.link.cancel is not None and self.link.cancel.cancelled)):
                    break  # the rest on the next call (a stop: the caller sees it at its next check)
                check(self.link.cancel, self.name)
                fits = self._fitting(until, max(self.clock(), begun + wired))
                n = min(self.upload_chunk(), limit - self._fetched, fits)
                if n < 1:
                    break  # no time left for one more value: the rest on the next call
                text = self.query_text(f"AO,{self.out},{self._fetched},{n}", reply_bytes=3 + VALUE_BYTES * n)
                mm, ok = parse_values(text[3:], self.name) if len(text) > 3 else (np.zeros(0), np.zeros(0, bool))
                if mm.size != n:
                    raise ProtocolError(self.name, f"AO returned {mm.size} values, {n} requested")
                wired += self._wire_s(16 + 3 + VALUE_BYTES * n) + self.exchange_allowance_s
                values.append(mm * 1e-3)
                valid.append(ok)
                self._fetched += n
        except BaseException:
            self._fetched = first
            raise
        self.pending = count - self._fetched
        overflow = not storing and count >= self.storage_points
        if overflow and first == count:
            raise InstrumentStateError(self.name, f"data storage full ({count} points): later samples lost")
        return SampleBlock(self._t0, self._dt, first, np.concatenate(values) if values else np.zeros(0),
                           np.concatenate(valid) if valid else np.zeros(0, dtype=bool), "m")

    def stop_buffer(self) -> None:
        """Stop data storage (stored points remain fetchable)."""
        self.query("AP")
