"""A Modbus bus (RTU on a serial port, or TCP) shared by the modules on it, with named driver errors.

``url``: a serial device or pyserial URL (``/dev/ttyUSB0``, ``/dev/pts/7``, ``socket://host:port``) for RTU,
or ``tcp://host:port`` for Modbus TCP. Uses the pymodbus 3.16 synchronous clients.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import TypeVar

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse, ModbusPDU

from drivers.errors import InstrumentConnectionError, InstrumentStateError, InstrumentTimeoutError, ProtocolError

EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "device failure", 5: "acknowledge", 6: "device busy", 11: "gateway target failed to respond"}
T = TypeVar("T")

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported by the drivers, one line each


class _PromptSerialClient(ModbusSerialClient):
    """RTU client that hands over received bytes as soon as they arrive.

    pymodbus' own ``recv(None)`` waits until the byte count is stable over two polls; its transaction loop
    already accumulates partial frames until the framer finds a whole one, so returning early is safe and
    saves those polls (used for simulated rigs, whose ptys deliver at once).
    """

    def recv(self, size: int | None) -> bytes:
        if size is not None or not self.socket:
            return super().recv(size)
        deadline = time.monotonic() + self.comm_params.timeout_connect
        try:
            while not (waiting := self._in_waiting()):
                if time.monotonic() > deadline:
                    return b""
                time.sleep(self._recv_interval)
            return self.socket.read(waiting)
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None


class ModbusLink:
    """One Modbus client; serialises requests from every module on the bus."""

    def __init__(self, url: str, device: str, *, baudrate: int = 19200, timeout: float = 0.5,
                 retries: int = 1, poll_interval: float | None = None) -> None:
        """``poll_interval``: how often the RTU client polls for reply bytes (pymodbus default: 4 character
        times, at least 1 ms). Twins on a pty answer at once, so simulated rigs use a shorter one."""
        self.url = url
        self.device = device
        self.lock = threading.RLock()
        self._client: ModbusSerialClient | ModbusTcpClient
        if url.startswith("tcp://"):
            host, _, port = url[len("tcp://"):].rpartition(":")
            if not host or not port.isdigit():
                raise ValueError(f"{device}: Modbus TCP address must be tcp://host:port, got {url!r}")
            self._client = ModbusTcpClient(host, port=int(port), timeout=timeout, retries=retries)
        else:
            client_cls = ModbusSerialClient if poll_interval is None else _PromptSerialClient
            self._client = client_cls(url, baudrate=baudrate, timeout=timeout, retries=retries)
            if poll_interval is not None:
                self._client._recv_interval = poll_interval  # pymodbus 3.16 attribute (pinned)

    @property
    def is_open(self) -> bool:
        """Whether the client holds an open connection."""
        return bool(self._client.connected)

    def open(self) -> None:
        """Connect (RTU: open the port; TCP: connect the socket)."""
        if not self._client.connect():
            local = "://" not in self.url
            reason = "no such device" if local and not os.path.exists(self.url) else "connection refused or port busy"
            raise InstrumentConnectionError(self.device, f"cannot open Modbus link {self.url}: {reason}")

    def close(self) -> None:
        """Close the connection (idempotent)."""
        self._client.close()

    def _call(self, what: str, unit: int, fn: Callable[[], ModbusPDU]) -> ModbusPDU:
        with self.lock:
            try:
                resp = fn()
            except ModbusIOException:
                raise InstrumentTimeoutError(self.device, f"no valid reply from unit {unit} to {what} on {self.url}") \
                    from None
            except ConnectionException:
                raise InstrumentConnectionError(self.device, f"Modbus link {self.url} lost during {what}") from None
            except ModbusException as exc:
                raise ProtocolError(self.device, f"{what} on unit {unit}: {exc}") from None
        if isinstance(resp, ExceptionResponse) or resp.isError():
            code = getattr(resp, "exception_code", 0)
            raise InstrumentStateError(self.device, f"unit {unit} refused {what}: Modbus exception {code} "
                                       f"({EXCEPTION_TEXT.get(code, 'unknown')})")
        return resp

    def read_holding(self, unit: int, address: int, count: int = 1) -> list[int]:
        """FC3 read of ``count`` holding registers at 0-based ``address``."""
        resp = self._call(f"read holding {address}+{count}", unit,
                          lambda: self._client.read_holding_registers(address, count=count, device_id=unit))
        return self._registers(resp, count, "holding", unit)

    def read_input(self, unit: int, address: int, count: int = 1) -> list[int]:
        """FC4 read of ``count`` input registers at 0-based ``address``."""
        resp = self._call(f"read input {address}+{count}", unit,
                          lambda: self._client.read_input_registers(address, count=count, device_id=unit))
        return self._registers(resp, count, "input", unit)

    def write_register(self, unit: int, address: int, value: int) -> None:
        """FC6 write of one holding register."""
        self._call(f"write register {address}={value}", unit,
                   lambda: self._client.write_register(address, value, device_id=unit))

    def write_registers(self, unit: int, address: int, values: list[int]) -> None:
        """FC16 write of consecutive holding registers."""
        self._call(f"write registers {address}+{len(values)}", unit,
                   lambda: self._client.write_registers(address, values, device_id=unit))

    def _registers(self, resp: ModbusPDU, count: int, kind: str, unit: int) -> list[int]:
        regs = list(getattr(resp, "registers", []) or [])
        if len(regs) != count:
            raise ProtocolError(self.device, f"unit {unit} returned {len(regs)} {kind} registers, {count} asked")
        return regs
