"""A request/response serial link (pyserial) that turns transport failures into named driver errors.

Ports are opened with ``serial.serial_for_url``, so a device path (``/dev/ttyUSB0``, ``/dev/pts/7``), a
``socket://host:port`` URL or a test URL scheme all work the same way.
"""

from __future__ import annotations

import os
import threading
import time

import serial

from drivers.errors import InstrumentConnectionError, InstrumentTimeoutError


class SerialLink:
    """One serial port shared by one instrument; all exchanges are serialised by a lock."""

    def __init__(self, url: str, device: str, *, baudrate: int = 115200, timeout: float = 0.5,
                 exclusive: bool = True) -> None:
        self.url = url
        self.device = device
        self.baudrate = baudrate
        self.timeout = timeout
        self.exclusive = exclusive
        self.lock = threading.RLock()
        self._port: serial.SerialBase | None = None
        self._rest = b""  # bytes received after the last terminator

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._port is not None

    def open(self) -> None:
        """Open the port (8N1, no flow control)."""
        if self._port is not None:
            return
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, bytesize=8, parity="N",
                                               stopbits=1, timeout=self.timeout, write_timeout=self.timeout,
                                               exclusive=self.exclusive)
        except (serial.SerialException, OSError, ValueError) as exc:
            reason = os.strerror(exc.errno) if isinstance(getattr(exc, "errno", None), int) else str(exc)
            raise InstrumentConnectionError(self.device, f"cannot open {self.url}: {reason}") from None

    def close(self) -> None:
        """Close the port (idempotent)."""
        if self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None

    def _require(self) -> serial.SerialBase:
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
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None

    def write(self, data: bytes) -> None:
        """Send bytes."""
        port = self._require()
        try:
            port.write(data)
        except serial.SerialTimeoutException:
            raise InstrumentTimeoutError(self.device, f"write to {self.url} timed out") from None
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None

    def read_exact(self, n: int, timeout: float | None = None) -> bytes:
        """Read exactly n bytes or raise InstrumentTimeoutError."""
        port = self._require()
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        buf = bytearray(self._rest[:n])
        self._rest = self._rest[n:]
        try:
            while len(buf) < n:
                chunk = port.read(n - len(buf))
                if chunk:
                    buf += chunk
                elif time.monotonic() >= deadline:
                    raise InstrumentTimeoutError(self.device, f"no reply within {self.timeout:g} s "
                                            f"({len(buf)} of {n} bytes received)")
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None
        return bytes(buf)

    def read_until(self, terminator: bytes, max_size: int = 1 << 20, timeout: float | None = None) -> bytes:
        """Read up to and including ``terminator``; raise InstrumentTimeoutError if it does not come.

        Reads whatever is waiting in one call (pyserial's own ``read_until`` makes one call per byte, which
        caps a bulk upload of LK-G storage at a few hundred kB/s).
        """
        port = self._require()
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        buf = bytearray(self._rest)
        self._rest = b""
        try:
            while True:
                end = buf.find(terminator)
                if end >= 0:
                    end += len(terminator)
                    self._rest = bytes(buf[end:])
                    return bytes(buf[:end])
                if len(buf) >= max_size:
                    raise InstrumentTimeoutError(self.device, f"no terminator within {max_size} bytes")
                chunk = port.read(max(1, min(port.in_waiting, max_size - len(buf))))
                if chunk:
                    buf += chunk
                elif time.monotonic() >= deadline:
                    got = f" (partial reply {bytes(buf[:80])!r})" if buf else ""
                    waited = self.timeout if timeout is None else timeout
                    raise InstrumentTimeoutError(self.device, f"no reply within {waited:.3g} s{got}")
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None
