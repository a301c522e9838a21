"""Run pymodbus 3.16 servers for simulated Modbus buses in a background event-loop thread.

A bus is a list of ``SimDevice`` (one per unit id: an RS-485 multidrop line) served either as Modbus RTU
on a pty bridge (the driver opens ``client_path`` like a USB–RS-485 adapter) or as Modbus TCP on loopback.
The bus's :class:`Faults` (latency, silence, garbled bytes, dropped link) act on every transport: a pty bridge
in front of the RTU server, a loopback :class:`SocketRelay` in front of the RTU-over-TCP and Modbus TCP
servers. ``endpoint`` is always the faulty side (bridge or relay), never the server itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from dataclasses import dataclass, field
from typing import Literal

from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import SimDevice

from sim_devices.transport import Faults, PtyBridge, SocketRelay

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@dataclass
class SimBus:
    """One simulated bus: its devices, transport and (after start) endpoint."""

    name: str
    devices: list[SimDevice]
    transport: Literal["rtu", "rtu-socket", "tcp"] = "rtu"
    baudrate: int = 19200
    port: int = 0  # TCP port of the endpoint (the relay; 0: ephemeral)
    faults: Faults = field(default_factory=Faults)
    endpoint: str = ""
    bridge: PtyBridge | None = None
    relay: SocketRelay | None = None


class ModbusHost:
    """Owns the event loop thread and the servers of all simulated Modbus buses of a rig."""

    def __init__(self, buses: list[SimBus]) -> None:
        self.buses = buses
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[ModbusSerialServer | ModbusTcpServer] = []
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def start(self, timeout: float = 10.0) -> None:
        """Start every bus; returns when all are listening (endpoints filled in)."""
        for bus in self.buses:
            if bus.transport == "rtu":
                bus.bridge = PtyBridge(bus.name, bus.faults).start()
                bus.endpoint = bus.bridge.client_path
        self._thread = threading.Thread(target=self._run, name="sim-modbus", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise RuntimeError("simulated Modbus servers did not start")
        if self._error is not None:
            raise RuntimeError(f"simulated Modbus servers failed to start: {self._error}")

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._serve())
            loop.run_forever()
        finally:
            loop.close()

    async def _serve(self) -> None:
        try:
            for bus in self.buses:
                server: ModbusSerialServer | ModbusTcpServer
                if bus.transport == "rtu":
                    assert bus.bridge is not None
                    server = ModbusSerialServer(bus.devices, framer=FramerType.RTU, port=bus.bridge.server_path,
                                                baudrate=bus.baudrate)
                    await server.serve_forever(background=True)
                elif bus.transport == "rtu-socket":
                    inner = _free_port()  # pymodbus' RTU-over-TCP server does not report an ephemeral port
                    server = ModbusSerialServer(bus.devices, framer=FramerType.RTU,
                                                port=f"socket://127.0.0.1:{inner}", baudrate=bus.baudrate)
                    await server.serve_forever(background=True)
                else:
                    server = ModbusTcpServer(bus.devices, address=("127.0.0.1", 0))
                    await server.serve_forever(background=True)
                    inner = server.transport.sockets[0].getsockname()[1]  # type: ignore[union-attr,attr-defined]
                self._servers.append(server)
                if bus.transport != "rtu":
                    framing: Literal["mbap", "stream"] = "mbap" if bus.transport == "tcp" else "stream"
                    bus.relay = await SocketRelay(bus.name, ("127.0.0.1", inner), bus.faults,
                                                  framing=framing).start(port=bus.port)
                    bus.port = bus.relay.port
                    scheme = "tcp" if bus.transport == "tcp" else "socket"
                    bus.endpoint = f"{scheme}://127.0.0.1:{bus.port}"
        except BaseException as exc:
            self._error = exc
        finally:
            self._ready.set()

    def stop(self) -> None:
        """Shut the servers down and stop the loop thread."""
        loop = self._loop
        if loop is not None and loop.is_running():
            async def shutdown() -> None:
                for bus in self.buses:
                    if bus.relay is not None:
                        await bus.relay.close()
                for server in self._servers:
                    await server.shutdown()

            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(shutdown(), loop).result(timeout=5)
            loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=5)
        for bus in self.buses:
            if bus.bridge is not None:
                bus.bridge.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
