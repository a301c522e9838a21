"""pyserial URL handler ``expect://NAME`` for byte-exact protocol tests (PyMeasure ``expected_protocol`` style).

A test registers a script — a list of (request bytes, reply bytes or None) — under NAME with
:func:`expected_protocol`; the driver opens ``expect://NAME`` like any serial port. Every byte written must
match the script exactly (else AssertionError at the write); each complete request releases its reply
(None: no reply, the driver times out). Leaving the context asserts the whole script was used.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import serial
from serial.serialutil import PortNotOpenError, SerialBase

Exchange = tuple[bytes, bytes | None]
SCRIPTS: dict[str, list[Exchange]] = {}
_LOCK = threading.Lock()

if "tests" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("tests")


class Serial(SerialBase):
    """Scripted fake port."""

    def open(self) -> None:
        name = self.portstr.split("://", 1)[1]
        if name not in SCRIPTS:
            raise serial.SerialException(f"no script registered for {self.portstr}")
        self._script = SCRIPTS[name]
        self._tx = b""
        self._rx = bytearray()
        self.is_open = True

    def _reconfigure_port(self, force_update: bool = False) -> None:
        pass

    def close(self) -> None:
        self.is_open = False

    def from_url(self, url: str) -> str:
        return url

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        self._rx.clear()

    def reset_output_buffer(self) -> None:
        pass

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        deadline = time.monotonic() + (self._timeout or 0)
        while len(self._rx) < size and time.monotonic() < deadline:
            time.sleep(0.001)
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        self._tx += bytes(data)
        with _LOCK:
            while self._tx:
                if not self._script:
                    raise AssertionError(f"unexpected bytes written after the script ended: {self._tx.hex(' ')}")
                expected, reply = self._script[0]
                if not expected.startswith(self._tx[: len(expected)]):
                    raise AssertionError(f"wrote {self._tx.hex(' ')}, expected {expected.hex(' ')}")
                if len(self._tx) < len(expected):
                    break
                self._script.pop(0)
                self._tx = self._tx[len(expected):]
                if reply:
                    self._rx += reply
        return len(data)


@contextlib.contextmanager
def expected_protocol(name: str, exchanges: list[Exchange]) -> Iterator[str]:
    """Register ``exchanges`` under ``name``; yields the URL to open; asserts every exchange happened."""
    SCRIPTS[name] = list(exchanges)
    try:
        yield f"expect://{name}"
        left = SCRIPTS[name]
        assert not left, f"{len(left)} expected exchanges did not happen, next: {left[0][0].hex(' ')}"
    finally:
        SCRIPTS.pop(name, None)


def crc16_modbus(frame: bytes) -> bytes:
    """Modbus RTU CRC-16 (poly 0xA001 reflected, init 0xFFFF), low byte first — written for the tests."""
    crc = 0xFFFF
    for b in frame:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def rtu(*parts: int | bytes) -> bytes:
    """An RTU frame from bytes/ints with its CRC appended."""
    body = b"".join(p if isinstance(p, bytes) else bytes([p]) for p in parts)
    return body + crc16_modbus(body)
