"""A request/response serial link (pyserial) that turns transport failures into named driver errors.

Ports are opened with ``serial.serial_for_url``, so a device path (``/dev/ttyUSB0``, ``/dev/pts/7``), a
``socket://host:port`` URL or a test URL scheme all work the same way.

Every read has a deadline on its *total* duration (a peer trickling bytes cannot stretch it) and blocks in
slices of at most ``POLL_SLICE_S``, checking the optional :class:`~drivers.cancel.CancelToken` before each.
A read abandoned by a timeout or a stop leaves the link "dirty": the next write first drops whatever has
arrived since, so a late reply is never taken for the answer to the next request.

A POSIX port (a device path: a USB adapter, a pty) is read and written on its file descriptor: a read takes
everything that has arrived in one call (what the caller did not ask for yet waits in the link for its next read,
so a reply read as header then body costs one wait, not two), and a write that the port takes whole returns at
once (pyserial's ``write`` follows every write with a wait for writability: a second system call, and a hand-off of
the GIL to any other thread, per request). Other ports (``socket://``, test schemes) go through pyserial.

A reading is stamped when the device sampled it, best estimated as the start of its reply: the time its last byte
arrived less the reply's wire time (:meth:`SerialLink.reply_started`; :func:`wire_time` is the one computation,
the Modbus link's RTU replies use it too). A simulated line served at pty speed (``wire=False``) has no wire time.

When a read gives up is the :class:`~drivers.deadline.ReplyTimer`'s business: the wall clock on hardware; in a
virtual-time simulation the twin's own account of the request (:mod:`drivers.deadline`), so that a host starved
of CPU never turns into a timeout. The port's write timeout is the timer's wall-clock bound.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
from pathlib import Path

import serial

from drivers.cancel import CancelToken
from drivers.deadline import WALL, Deadline, ReplyTimer
from drivers.errors import InstrumentConnectionError, InstrumentTimeoutError

try:  # pyserial's POSIX port lets termios.error (not an OSError) out of reset_input_buffer on a dead pty
    from termios import error as _termios_error
except ImportError:  # pragma: no cover - Windows
    _termios_error = OSError  # type: ignore[misc,assignment]  # the same name bound to another class there

PORT_ERRORS = (serial.SerialException, OSError, _termios_error)
"""What a serial port's calls raise when its line is gone: a lost link, not a crash of the caller."""

POLL_SLICE_S = 0.05  # longest single blocking read: a stop request is seen within one slice
QUIET_S = 0.02  # after an abandoned read: the line counts as quiet (late reply over) after this long
MAX_DRAIN_S = 0.25  # ... but a write waits at most this long for that
READ_CHUNK = 4096  # a POSIX port's read takes up to this much of what has arrived (a tty hands at most its 4-KiB
#                   line-discipline buffer per read); more only when a count asks for more


def char_bits(bytesize: int = 8, parity: str = "N", stopbits: float = 1) -> float:
    """Bits one character occupies on an asynchronous serial wire: a start bit, the data bits, a parity bit unless
    the parity is none ("N"), the stop bits — 10 for 8N1, 11 for 8E1, 8O1 and 8N2."""
    return 1 + bytesize + (0 if parity == "N" else 1) + stopbits


def wire_time(nbytes: int, baudrate: float, bits_per_char: float = 10.0) -> float:
    """Seconds ``nbytes`` characters take on the wire at ``baudrate``, back to back: bytes × bits per char ÷ baud."""
    return nbytes * bits_per_char / baudrate


USB_SERIAL_SYSFS = Path("/sys/bus/usb-serial/devices")  # Linux: one folder per USB-serial tty (FTDI's latency_timer)
log = logging.getLogger(__name__)


def usb_latency_ms(url: str, sysfs: Path = USB_SERIAL_SYSFS) -> int | None:
    """The latency timer [ms] of the USB-serial adapter behind ``url`` (a /dev path, a /dev/serial/by-id link
    too), or None where there is none to read (not a USB-serial tty, not Linux, a URL): an FTDI-type adapter holds
    a short reply up to that long before the host sees it, which no stamp can take off."""
    try:
        name = Path(os.path.realpath(url)).name
        return int((sysfs / name / "latency_timer").read_text().strip())
    except (OSError, ValueError):
        return None


def warn_usb_latency(url: str, device: str, sysfs: Path = USB_SERIAL_SYSFS) -> str | None:
    """Log (and return) a warning when ``url``'s USB-serial adapter holds replies longer than 1 ms."""
    ms = usb_latency_ms(url, sysfs)
    if ms is None or ms <= 1:
        return None
    tty = Path(os.path.realpath(url)).name
    text = (f"{device}: the USB-serial adapter {tty} holds a reply up to {ms} ms (its latency timer) before the host "
            f"sees it, so its readings' stamps lag by 0–{ms} ms: set it to 1 (echo 1 > "
            f"{sysfs / tty / 'latency_timer'}, or a udev rule)")
    log.warning(text)
    return text


def slice_s(left: float) -> float:
    """How long the next blocking read may last [s]: one poll slice, never more than ``left`` [s] (at least 1 ms)."""
    return max(min(POLL_SLICE_S, left), 0.001)


def set_slice_timeout(port: serial.Serial, left: float) -> None:
    """Let the port's next blocking read last at most one poll slice, and never more than ``left`` [s].

    Changing pyserial's timeout reconfigures the port (a tcsetattr), so it changes only by more than 5 ms."""
    want = slice_s(left)
    if port.timeout is None or abs(port.timeout - want) > 0.005:
        port.timeout = want


def posix_fd(port: serial.Serial) -> int | None:
    """The open file descriptor of pyserial's POSIX port (non-blocking, as pyserial opens it); None for any other
    kind of port (a URL scheme, or a subclass with a read of its own such as ``VTIMESerial``)."""
    posix = getattr(serial, "serialposix", None)
    if posix is None or type(port) is not posix.Serial:
        return None
    fd = port.fd
    return fd if isinstance(fd, int) and fd >= 0 else None


class SerialLink:
    """One serial port shared by one instrument; all exchanges are serialised by a lock."""

    bytesize, parity, stopbits = 8, "N", 1  # the framing :meth:`open` sets (8N1: every instrument here)

    def __init__(self, url: str, device: str, *, baudrate: int = 115200, timeout: float = 0.5,
                 exclusive: bool = True, cancel: CancelToken | None = None, timer: ReplyTimer = WALL,
                 wire: bool = True) -> None:
        """``timeout``: default reply timeout [s]; ``timer``: how a wait for a reply ends (:mod:`drivers.deadline`);
        ``wire``: whether bytes take their wire time at ``baudrate`` (False: a simulated line served at pty speed,
        where a reply arrives the moment it is made — :meth:`reply_started` then subtracts nothing)."""
        self.url = url
        self.device = device
        self.baudrate = baudrate
        self.wire = wire
        self._replied = 0  # bytes handed to the caller since the last write: the reply read so far
        self.timeout = timeout
        self.exclusive = exclusive
        self.cancel = cancel
        self.timer = timer
        self.lock = threading.RLock()
        self._port: serial.Serial | None = None
        self._fd: int | None = None  # a POSIX port's descriptor: read and written directly (module docstring)
        self._rest = b""  # bytes received and not yet read by the caller (after a terminator, or beyond a count)
        self._dirty = False  # a read was abandoned: a late reply may still arrive

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._port is not None

    def open(self) -> None:
        """Open the port (8N1, no flow control)."""
        if self._port is not None:
            return
        try:
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, bytesize=self.bytesize,
                                         parity=self.parity, stopbits=self.stopbits,
                                         timeout=min(self.timeout, POLL_SLICE_S),
                                         write_timeout=self.timer.bound(self.timeout),
                                         exclusive=self.exclusive)
            self._port = port
            self._fd = posix_fd(port)
            warn_usb_latency(self.url, self.device)
        except (*PORT_ERRORS, ValueError) as exc:
            errno = getattr(exc, "errno", None)
            reason = os.strerror(errno) if isinstance(errno, int) else str(exc)
            raise InstrumentConnectionError(self.device, f"cannot open {self.url}: {reason}") from None

    def close(self) -> None:
        """Close the port (idempotent)."""
        if self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None
                self._fd = None

    def _require(self) -> serial.Serial:
        if self._port is None:
            raise InstrumentConnectionError(self.device, f"port {self.url} is not open")
        return self._port

    def _lost(self, exc: Exception) -> InstrumentConnectionError:
        self.close()
        return InstrumentConnectionError(self.device, f"link on {self.url} lost: {exc}")

    def discard_input(self) -> None:
        """Drop stale bytes (e.g. a late reply to a timed-out request)."""
        port = self._require()
        self._rest = b""
        self._dirty = False
        try:
            port.reset_input_buffer()
        except PORT_ERRORS as exc:
            raise self._lost(exc) from None

    def _drain(self, port: serial.Serial) -> None:
        """Drop input until the line has been quiet for QUIET_S (at most MAX_DRAIN_S): a reply still
        streaming in for an abandoned read must not be taken for the next one."""
        self.discard_input()
        end = time.monotonic() + MAX_DRAIN_S
        quiet_since = time.monotonic()
        try:
            while (now := time.monotonic()) < end and now - quiet_since < QUIET_S:
                if port.in_waiting:
                    port.reset_input_buffer()
                    quiet_since = time.monotonic()
                else:
                    time.sleep(0.002)
        except PORT_ERRORS as exc:
            raise self._lost(exc) from None

    def write(self, data: bytes) -> None:
        """Send bytes (first dropping stale input if the previous read was abandoned).

        Not cancellable: a command always goes out (it may be the one that makes the rig safe); the wait
        for its reply is.
        """
        port = self._require()
        if self._dirty:
            self._drain(port)
        self._replied = 0
        self.timer.sending()
        try:
            if self._fd is not None:
                with contextlib.suppress(BlockingIOError):  # output buffer full: pyserial's write waits for room
                    data = data[os.write(self._fd, data):]
            if data:
                port.write(data)
        except serial.SerialTimeoutException:
            raise InstrumentTimeoutError(self.device, f"write to {self.url} timed out") from None
        except PORT_ERRORS as exc:
            raise self._lost(exc) from None

    def _receive(self, port: serial.Serial, deadline: Deadline, want: int, limit: int) -> bytes:
        """Wait at most one poll slice, never past the deadline (the stop request checked first), for input; return
        what came: at most ``want`` bytes through pyserial, from a POSIX port all that has arrived up to ``limit``
        (≥ ``want``) bytes. Empty: nothing came in the slice."""
        if self.cancel is not None and self.cancel.cancelled:
            self._dirty = True
            self.cancel.check(self.device)
        fd = self._fd
        if fd is None:
            set_slice_timeout(port, deadline.left())
            return port.read(want)
        ready, _, _ = select.select([fd], [], [], slice_s(deadline.left()))
        if not ready:
            return b""
        try:
            data = os.read(fd, limit)
        except BlockingIOError:  # readable, yet nothing there after all: as a slice that saw nothing
            return b""
        if not data:  # as pyserial: a vanished device (an unplugged adapter, a closed pty) reads ready and empty
            raise serial.SerialException("device reports readiness to read but returned no data (device "
                                         "disconnected or multiple access on port?)")
        return data

    def _timed_out(self, waited: float, deadline: Deadline, partial: bytes, need: str = "") -> InstrumentTimeoutError:
        self._dirty = True
        got = f" (partial reply {partial[:80]!r}{need})" if partial else ""
        return InstrumentTimeoutError(self.device, f"no reply within {waited:.3g} s{got}{deadline.detail}")

    def read_exact(self, n: int, timeout: float | None = None) -> bytes:
        """Read exactly n bytes within ``timeout`` [s] in total, or raise InstrumentTimeoutError."""
        port = self._require()
        rest = self._rest
        if len(rest) >= n:  # all there already (read with what came before): no wait, so no deadline to set
            self._rest = rest[n:]
            self._replied += n
            return rest[:n]
        buf = bytearray(rest)
        self._rest = b""
        waited = self.timeout if timeout is None else timeout
        deadline = self.timer.start(waited)
        try:
            while len(buf) < n:
                want = n - len(buf)
                buf += self._receive(port, deadline, want, max(want, READ_CHUNK))
                if len(buf) < n and deadline.expired():
                    raise self._timed_out(waited, deadline, bytes(buf), f", {len(buf)} of {n} bytes")
        except PORT_ERRORS as exc:
            raise self._lost(exc) from None
        if len(buf) > n:  # read beyond the count (the rest was empty before): kept for the next read
            self._rest = bytes(buf[n:])
            del buf[n:]
        self._replied += n
        return bytes(buf)

    def read_until(self, terminator: bytes, max_size: int = 1 << 20, timeout: float | None = None) -> bytes:
        """Read up to and including ``terminator`` within ``timeout`` [s] in total; else InstrumentTimeoutError.

        Reads whatever is waiting in one call (pyserial's own ``read_until`` makes one call per byte, which
        caps a bulk upload of LK-G storage at a few hundred kB/s).
        """
        port = self._require()
        waited = self.timeout if timeout is None else timeout
        deadline = self.timer.start(waited)
        buf = bytearray(self._rest)
        self._rest = b""
        searched = 0
        try:
            while True:
                end = buf.find(terminator, searched)
                if end >= 0:
                    end += len(terminator)
                    self._rest = bytes(buf[end:])
                    self._replied += end
                    return bytes(buf[:end])
                searched = max(0, len(buf) - len(terminator) + 1)
                if len(buf) >= max_size:
                    self._dirty = True
                    raise InstrumentTimeoutError(self.device, f"no terminator within {max_size} bytes")
                if deadline.expired():
                    raise self._timed_out(waited, deadline, bytes(buf))
                room = max_size - len(buf)
                if self._fd is not None:
                    buf += self._receive(port, deadline, 1, min(room, READ_CHUNK))
                else:
                    buf += self._receive(port, deadline, max(1, min(port.in_waiting, room)), room)
        except PORT_ERRORS as exc:
            raise self._lost(exc) from None

    def reply_wire_s(self) -> float:
        """Wire time [s] of the reply read since the last write (every byte read since: a reply read in parts counts
        whole), at this link's baud rate and framing; 0 where the link has no wire time (``wire=False``)."""
        if not self.wire:
            return 0.0
        return wire_time(self._replied, self.baudrate, char_bits(self.bytesize, self.parity, self.stopbits))

    def reply_started(self, arrived: float) -> float:
        """When the reply read since the last write started on the wire, given ``arrived``, the time (on the
        caller's clock) its last byte arrived: ``arrived`` less the reply's wire time. A device puts its reading
        into the reply as it starts sending it; the reply's own bytes take their wire time to follow, so this,
        not ``arrived``, is when the reading was taken (call it with the link's lock held since the exchange)."""
        return arrived - self.reply_wire_s()
