"""Run pymodbus 3.16 servers for simulated Modbus buses in a background event-loop thread.

A bus is a list of ``SimDevice`` (one per unit id: an RS-485 multidrop line) served either as Modbus RTU
on a pty bridge (the driver opens ``client_path`` like a USB–RS-485 adapter) or as Modbus TCP on loopback.
Faults of an RTU bus (latency, silence, garbled bytes, dropped link) are applied by its bridge.
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

from sim_devices.transport import Faults, PtyBridge

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@dataclass
class SimBus:
    """One simulated bus: its devices, transport and (after start) endpoint."""

    name: str
    devices: list[SimDevice]
    transport: Literal["rtu", "rtu-socket", "tcp"] = "rtu"
    baudrate: int = 19200
    port: int = 0  # TCP port (0: ephemeral)
    faults: Faults = field(default_factory=Faults)
    endpoint: str = ""
    bridge: PtyBridge | None = None


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
            elif bus.transport == "rtu-socket":
                with socket.socket() as s:  # a free loopback port for the RTU-over-TCP server
                    s.bind(("127.0.0.1", 0))
                    bus.port = s.getsockname()[1]
                bus.endpoint = f"socket://127.0.0.1:{bus.port}"
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
                if bus.transport in ("rtu", "rtu-socket"):
                    port = bus.bridge.server_path if bus.bridge is not None else bus.endpoint
                    server: ModbusSerialServer | ModbusTcpServer = ModbusSerialServer(
                        bus.devices, framer=FramerType.RTU, port=port, baudrate=bus.baudrate)
                else:
                    server = ModbusTcpServer(bus.devices, address=("127.0.0.1", bus.port))
                await server.serve_forever(background=True)
                if bus.transport == "tcp":
                    port = server.transport.sockets[0].getsockname()[1]  # type: ignore[union-attr]
                    bus.endpoint = f"tcp://127.0.0.1:{port}"
                self._servers.append(server)
        except BaseException as exc:
            self._error = exc
        finally:
            self._ready.set()

    def stop(self) -> None:
        """Shut the servers down and stop the loop thread."""
        loop = self._loop
        if loop is not None and loop.is_running():
            async def shutdown() -> None:
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
