"""Simulated Modbus buses: RS-485 lines of :class:`~sim_devices.modbus_devices.ModbusModule`\\ s on real ports.

Framing and behaviour from the Modbus specifications, not from pymodbus or the drivers: Modbus Application
Protocol v1.1b3 (PDUs of FC1–6/15/16, §6; exception responses, §7), Modbus over Serial Line v1.02 (RTU
frame, CRC-16 poly A001h, §2.5.1; 3.5-character silence between frames, fixed 1.75 ms above 19200 Bd,
§2.5.1.1; unicast vs broadcast: "broadcast requests … no response is returned", §2.1; a frame with a CRC
error, or for another address, is ignored by the slave, §2.4.1 / §2.5.1.2), Modbus Messaging on TCP/IP v1.0b
(MBAP header, §3.1.3; gateway exceptions 0Ah/0Bh, §4.4.1 of the application protocol).

A bus is one :class:`~sim_devices.transport.Line` at the bus baud rate: every transaction on it — from a
pty, an RTU-over-TCP socket or a Modbus TCP gateway — occupies the line for its character times, the
inter-frame silences and the module's turnaround, so the shipped sim rigs (Modbus TCP, as through a
TCP/RTU gateway) carry no more than the RS-485 line behind the gateway would.

* absent unit: silent on RTU (the master times out); through the gateway, exception 0Bh "gateway target
  device failed to respond" after ``gateway_timeout`` [assumed 0.2 s; real gateways make it a setting];
* unit 0: broadcast — writes are executed by every module, nobody replies (RTU and gateway);
* a CRC error or an unparseable frame on RTU: ignored (silence).

Transports: ``rtu`` (a pty served by a :class:`~sim_devices.transport.PtyDevice`), ``rtu-socket`` (raw RTU
over loopback TCP) and ``tcp`` (Modbus TCP); the socket servers sit behind a fault-injecting
:class:`~sim_devices.transport.SocketRelay`. ``endpoint`` is always the faulty side.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import socketserver
import struct
import threading
from dataclasses import dataclass, field
from typing import Literal, cast

from bench.core.clock import Clock, WallClock
from sim_devices.modbus_devices import (
    DEVICE_FAILURE,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    ModbusException,
    ModbusModule,
)
from sim_devices.transport import Faults, Line, PtyDevice, SocketRelay

GATEWAY_NO_RESPONSE = 0x0B  # "Gateway Target Device Failed to Respond"
RTU_GAP_CHARS = 3.5
SERVE_POLL_S = 0.05  # how often a server thread looks for shutdown: stop() waits up to this (socketserver: 0.5 s)


def crc16(frame: bytes) -> bytes:
    """Modbus RTU CRC (poly A001h reflected, init FFFFh), low byte first (Serial Line v1.02 §6.2.2)."""
    crc = 0xFFFF
    for b in frame:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def _exception(fc: int, code: int) -> bytes:
    return bytes([fc | 0x80, code])


def execute(module: ModbusModule, pdu: bytes, at: float | None = None) -> bytes:
    """One request PDU on one module → reply PDU (normal or exception), Application Protocol §6/§7; ``at``: the
    line time the request arrived (None: now), which everything the request does takes as its instant."""
    fc = pdu[0]
    if module.failed:
        return _exception(fc, DEVICE_FAILURE)  # a failed module does not feed its watchdog either
    module.heard(at)
    try:
        if fc in (1, 2, 3, 4):
            if len(pdu) != 5:
                raise ModbusException(ILLEGAL_VALUE)
            address, count = struct.unpack(">HH", pdu[1:5])
            if not 1 <= count <= (2000 if fc < 3 else 125):
                raise ModbusException(ILLEGAL_VALUE)
            values = module.read(fc, address, count)
            if fc >= 3:
                return bytes([fc, 2 * count]) + struct.pack(f">{count}H", *values)
            packed = bytearray((count + 7) // 8)
            for i, bit in enumerate(values):
                packed[i // 8] |= (1 if bit else 0) << (i % 8)
            return bytes([fc, len(packed)]) + bytes(packed)
        if fc in (5, 6):
            if len(pdu) != 5:
                raise ModbusException(ILLEGAL_VALUE)
            address, value = struct.unpack(">HH", pdu[1:5])
            if fc == 5 and value not in (0x0000, 0xFF00):
                raise ModbusException(ILLEGAL_VALUE)
            module.write(fc, address, [int(value == 0xFF00) if fc == 5 else value])
            return pdu
        if fc in (15, 16):
            if len(pdu) < 6:
                raise ModbusException(ILLEGAL_VALUE)
            address, count, nbytes = *struct.unpack(">HH", pdu[1:5]), pdu[5]
            limit = 1968 if fc == 15 else 123
            want = (count + 7) // 8 if fc == 15 else 2 * count
            if not 1 <= count <= limit or nbytes != want or len(pdu) != 6 + nbytes:
                raise ModbusException(ILLEGAL_VALUE)
            data = pdu[6:]
            values = ([data[i // 8] >> (i % 8) & 1 for i in range(count)] if fc == 15
                      else list(struct.unpack(f">{count}H", data)))
            module.write(fc, address, values)
            return pdu[:5]
        raise ModbusException(ILLEGAL_FUNCTION)
    except ModbusException as exc:
        return _exception(fc, exc.code)


def request_length(buf: bytes) -> int | None:
    """Length of the RTU request frame at the start of ``buf`` (None: not enough bytes to tell)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6):
        return 8
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else None
    return len(buf)  # unknown function: the silence after the chunk ends the frame


@dataclass
class SimBus:
    """One simulated bus: its modules, line, transport and (after start) endpoint."""

    name: str
    devices: list[ModbusModule]
    transport: Literal["rtu", "rtu-socket", "tcp"] = "rtu"
    baudrate: int = 19200
    port: int = 0  # TCP port of the endpoint (the relay; 0: ephemeral)
    faults: Faults = field(default_factory=Faults)
    clock: Clock | None = None  # the rig clock (wire time passes on it); None: no wire time
    timing: bool = True  # emulate the line's wire time and turnarounds
    gateway_timeout: float = 0.2  # Modbus TCP: wait before exception 0Bh for an absent unit [assumed]
    endpoint: str = ""
    line: Line | None = None
    relay: SocketRelay | None = None
    pty: PtyDevice | None = None

    def __post_init__(self) -> None:
        baud = self.baudrate if self.timing and self.clock is not None else None
        self.line = Line(self.clock if self.clock is not None else WallClock(), baud, gap_chars=RTU_GAP_CHARS)
        self.units = {d.unit: d for d in self.devices}
        self._buf = b""

    # ------------------------------------------------------------ RTU (pty or raw socket)
    def rtu(self, data: bytes) -> bytes:
        """Bytes from the line → the reply frame(s) (b"" when nobody answers)."""
        self._buf += data
        out = b""
        while (n := request_length(self._buf)) is not None and len(self._buf) >= n:
            frame, self._buf = self._buf[:n], self._buf[n:]
            out += self._rtu_frame(frame)
        return out

    def _rtu_frame(self, frame: bytes) -> bytes:
        line = self.line
        assert line is not None
        with line.lock:  # one request at a time on the line (a reconnected socket's handler beside an old one)
            at = line.request(len(frame))
            if len(frame) < 4 or crc16(frame[:-2]) != frame[-2:]:
                self._buf = b""  # a damaged frame: ignored, and the rest of the chunk with it (resynchronise)
                return b""
            unit, pdu = frame[0], frame[1:-2]
            if unit == 0:
                for each in self.units.values():
                    execute(each, pdu, at)  # broadcast: executed, no reply
                return b""
            module = self.units.get(unit)
            if module is None:
                return b""  # another address (or nobody): silence
            line.ready(module.turnaround)  # a read takes the module's values as its reply starts; a write acts at `at`
            reply = bytes([unit]) + execute(module, pdu, at)
            reply += crc16(reply)
            line.reply(len(reply), module.turnaround)
            return reply

    # ------------------------------------------------------------ Modbus TCP gateway
    def gateway(self, unit: int, pdu: bytes) -> bytes | None:
        """A Modbus TCP request forwarded onto the RTU line behind the gateway → reply PDU (None: no reply)."""
        line = self.line
        assert line is not None
        with line.lock:  # the gateway forwards one request at a time onto the line
            at = line.request(len(pdu) + 3)
            if unit == 0:
                for each in self.units.values():
                    execute(each, pdu, at)
                return None
            module = self.units.get(unit)
            if module is None:
                line.silent(self.gateway_timeout)
                return _exception(pdu[0] if pdu else 0, GATEWAY_NO_RESPONSE)
            line.ready(module.turnaround)  # a read takes the module's values as its reply starts; a write acts at `at`
            reply = execute(module, pdu, at)
            line.reply(len(reply) + 3, module.turnaround)
            return reply


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True
    block_on_close = False
    bus: SimBus


class _GatewayHandler(socketserver.BaseRequestHandler):
    def handle(self) -> None:
        bus = cast(_Server, self.server).bus
        sock: socket.socket = self.request
        buf = b""
        with contextlib.suppress(OSError):
            while True:
                while len(buf) < 7 or len(buf) < 6 + int.from_bytes(buf[4:6], "big"):
                    chunk = sock.recv(65536)
                    if not chunk:
                        return
                    buf += chunk
                size = 6 + int.from_bytes(buf[4:6], "big")
                adu, buf = buf[:size], buf[size:]
                tid, proto, _ = struct.unpack(">HHH", adu[:6])
                if proto != 0 or size < 8:
                    continue  # not Modbus: ignored
                reply = bus.gateway(adu[6], adu[7:])
                if reply is not None:
                    sock.sendall(struct.pack(">HHHB", tid, 0, len(reply) + 1, adu[6]) + reply)


class _RtuSocketHandler(socketserver.BaseRequestHandler):
    def handle(self) -> None:
        bus = cast(_Server, self.server).bus
        sock: socket.socket = self.request
        with contextlib.suppress(OSError):
            while data := sock.recv(65536):
                if reply := bus.rtu(data):
                    sock.sendall(reply)


class ModbusHost:
    """Owns the servers of all simulated Modbus buses of a rig (socket servers in threads, relays in an
    asyncio loop thread, RTU on ptys)."""

    def __init__(self, buses: list[SimBus]) -> None:
        self.buses = buses
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[_Server] = []

    def start(self, timeout: float = 10.0) -> None:
        """Start every bus; returns when all are listening (endpoints filled in)."""
        for bus in self.buses:
            if bus.transport == "rtu":
                bus.pty = PtyDevice(bus.rtu, bus.name, bus.faults).start()
                if bus.line is not None:
                    bus.line.crosses_pty()  # the bus's frames cross the pty, not a wire
                bus.endpoint = bus.pty.path
        socket_buses = [b for b in self.buses if b.transport != "rtu"]
        if not socket_buses:
            return
        loop = asyncio.new_event_loop()
        self._loop = loop
        self._thread = threading.Thread(target=loop.run_forever, name="sim-modbus-relays", daemon=True)
        self._thread.start()
        for bus in socket_buses:
            handler = _GatewayHandler if bus.transport == "tcp" else _RtuSocketHandler
            server = _Server(("127.0.0.1", 0), handler)
            server.bus = bus
            threading.Thread(target=server.serve_forever, kwargs={"poll_interval": SERVE_POLL_S},
                             name=f"sim-modbus-{bus.name}", daemon=True).start()
            self._servers.append(server)
            inner = server.server_address[1]
            framing: Literal["mbap", "stream"] = "mbap" if bus.transport == "tcp" else "stream"
            relay = SocketRelay(bus.name, ("127.0.0.1", inner), bus.faults, framing=framing)
            bus.relay = asyncio.run_coroutine_threadsafe(relay.start(port=bus.port), loop).result(timeout)
            bus.port = relay.port
            bus.endpoint = f"{'tcp' if bus.transport == 'tcp' else 'socket'}://127.0.0.1:{bus.port}"

    def stop(self) -> None:
        """Shut the servers and relays down."""
        loop = self._loop
        if loop is not None and loop.is_running():
            async def shutdown() -> None:
                for bus in self.buses:
                    if bus.relay is not None:
                        await bus.relay.close()

            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(shutdown(), loop).result(timeout=5)
            loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=5)
        for server in self._servers:
            server.shutdown()
            server.server_close()
        for bus in self.buses:
            if bus.pty is not None:
                bus.pty.stop()
