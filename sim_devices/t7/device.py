"""The T7 twin: Modbus TCP registers (pymodbus 3.16 ``SimDevice``) and spontaneous stream packets on a second
socket, backed by the shared plant and clock; composed of :mod:`~sim_devices.t7.registers` (the map),
:mod:`~sim_devices.t7.coupling` (plant and analog channels), :mod:`~sim_devices.t7.stream_out`,
:mod:`~sim_devices.t7.stream_in` (the stream engine), :mod:`~sim_devices.t7.watchdog` and
:mod:`~sim_devices.t7.feedback` (MBFB), with :mod:`~sim_devices.t7.register_io` (the register dispatch) on top;
this module serves it.

[D] ports: Modbus TCP 502, stream 702; the twin listens on ephemeral loopback ports unless given others
(:meth:`LabJackT7Sim.start`).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from bench.core.clock import Clock
from bench.core.plant import Plant
from sim_devices.t7.analog import Conditioning, Signal, warm_up
from sim_devices.t7.feedback import FeedbackPDU, T7Server
from sim_devices.t7.register_io import RegisterIO
from sim_devices.t7.registers import R_O_U16, UNIT
from sim_devices.transport import Faults, SocketRelay

DEMAND_STEP_S = 0.5  # on demand, the twin still pumps after this much rig time without a pump: a lost host's
# device plays on (its loop refills, its watchdog acts) — shorter than the 1 s of stream-out a loop keeps queued
# at least (StreamOut._advance_out) and the 2 s of plant history a late scan is read from
_LAYOUT: dict[int, Any] = {}  # the built register space of a T7 (the same for every twin): pymodbus' build, once


class _T7Device(SimDevice):
    """pymodbus' ``SimDevice`` of a T7: every address 0…65534 a register, served through the twin's action.
    pymodbus builds that space in Python, one register at a time (milliseconds, at every twin start); it is the same
    for every T7 twin, so the first build is kept and each twin gets its own copy of its lists."""

    def build_device(self) -> Any:
        if UNIT not in _LAYOUT:
            _LAYOUT[UNIT] = super().build_device()
        start, registers, flags = _LAYOUT[UNIT]
        return start, list(registers), list(flags)


class LabJackT7Sim(RegisterIO):
    """The T7 twin: registers, stream engine, stream-out to the plant, watchdog; served on TCP."""

    def __init__(self, plant: Plant, clock: Clock, *, serial: int = 470012345, dac: int = 0,
                 conditioning: Conditioning | None = None, signals: dict[int, Signal] | None = None,
                 calibration: list[float] | None = None, seed: int = 7, poll: float = 0.002,
                 faults: Faults | None = None, noise: bool = True) -> None:
        super().__init__(plant, clock, dac=dac, conditioning=conditioning, signals=signals, calibration=calibration,
                         seed=seed, noise=noise)
        self.poll = poll
        self.faults = faults or Faults()
        self._init_registers(serial)
        self._init_stream_out()
        self._init_stream_in()
        words_ = [SimData(0, count=65535, values=0, datatype=DataType.REGISTERS)]
        self.device = _T7Device(UNIT, words_, action=self.action)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._server: ModbusTcpServer | None = None
        self._relay: SocketRelay | None = None
        self._stream_server: asyncio.Server | None = None
        self._poll_handle: asyncio.Handle | None = None  # the pump's next poll (_poll)
        self.host = "127.0.0.1"
        self.port = 0
        self.stream_port = 0
        self._wake_pending = False
        self.demand = False  # pump on demand (:meth:`on_demand`), not at every move of a virtual clock
        self._cpu_lock = threading.Lock()
        self._cpu_final = math.nan  # the serving thread's CPU time when it ended

    # ------------------------------------------------------------------ serving
    def start(self, timeout: float = 10.0, *, host: str = "127.0.0.1", port: int = 0,
              stream_port: int = 0) -> tuple[int, int]:
        """Serve Modbus TCP and the stream socket on ``host`` (ports 0: ephemeral; the T7's own are
        :data:`~sim_devices.t7.registers.MODBUS_PORT` 502 and :data:`~sim_devices.t7.registers.STREAM_PORT` 702);
        returns (Modbus port, stream port). A port that cannot be bound (in use, or below 1024 without the
        privilege) raises RuntimeError naming it."""
        self.host = host
        warm_up()  # before the first request: no compile inside a reply
        self._thread = threading.Thread(target=self._run, args=(port, stream_port), name="sim-labjack", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout) or not self.port:
            raise RuntimeError(f"simulated T7 did not start on {host} (Modbus port {port or 'any'}, stream port "
                               f"{stream_port or 'any'}): {'; '.join(str(e) for e in self.errors) or 'timeout'}"
                               ) from (self.errors[0] if self.errors else None)
        return self.port, self.stream_port

    def _run(self, port: int, stream_port: int) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._serve(port, stream_port))
            loop.run_forever()
        finally:
            loop.close()
            with self._cpu_lock:  # the thread's CPU clock is read from other threads only while it lives
                self._cpu_final = time.thread_time()

    async def _serve(self, port: int, stream_port: int) -> None:
        try:
            feedback = FeedbackPDU.bound_to(UNIT, self.serve_frame, self.request,
                                            frozenset(range(R_O_U16, R_O_U16 + 4)), self.frame_failed)
            self._server = T7Server(self.device, address=("127.0.0.1", 0), custom_pdu=[feedback])
            await self._server.serve_forever(background=True)
            inner = self._server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]  # asyncio transport
            self._relay = await SocketRelay("T7", ("127.0.0.1", inner), self.faults, framing="mbap",
                                            local=feedback.answer).start(self.host, port)
            self._stream_server = await asyncio.start_server(self._on_stream_client, self.host, stream_port)
            self.stream_port = self._stream_server.sockets[0].getsockname()[1]
            self._poll_handle = asyncio.get_running_loop().call_soon(self._poll)
            subscribe = getattr(self.clock, "subscribe", None)
            if subscribe is not None:  # a virtual clock says when it moves: packets leave when they are due
                subscribe(self._on_clock)
            self.port = self._relay.port
        except BaseException as exc:  # reported by start()
            self.errors.append(exc)
            if self._relay is not None:  # the Modbus port bound, the stream port did not: free it
                await self._relay.close()
        finally:
            self._ready.set()

    async def _on_stream_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with self.lock:
            old, self._writer = self._writer, writer  # the latest connection gets the packets
            held, self._held = self._held, []
            for data in held:
                writer.write(data)
        if old is not None:
            old.close()
        with contextlib.suppress(Exception):
            await reader.read()  # until the host closes
        with self.lock:
            if self._writer is writer:
                self._writer = None
        writer.close()

    def cpu_seconds(self) -> float:
        """CPU time [s] the serving thread (requests, stream packets, the plant it advances) has used so far, read
        from any thread (benchmarks: what the twin costs its host); once it has stopped, what it used in all; NaN
        before it starts or where the platform cannot say."""
        with self._cpu_lock:  # the thread cannot end (and its id be reused) while its clock is read
            if not math.isnan(self._cpu_final):
                return self._cpu_final
            thread = self._thread
            getcpu = getattr(time, "pthread_getcpuclockid", None)
            if thread is None or thread.ident is None or getcpu is None:
                return math.nan
            return time.clock_gettime(getcpu(thread.ident))

    def on_demand(self) -> Callable[[], None]:
        """Virtual time: pump when the host waits on the twin instead of at every move of the clock; returns the
        callback the host's link calls before each blocking read (:class:`~sim_devices.transport.TwinTimer`'s
        ``waiting``). A T7 sends a packet the moment it fills, but in virtual time nobody sees it before the host
        reads: the same packets (bytes, numbers, statuses) leave in fewer pumps — only the backlog words differ,
        as they do for a host that reads late. Without a host wait the twin still pumps every
        :data:`DEMAND_STEP_S` of rig time."""
        self.demand = True
        return self.host_waits

    def host_waits(self) -> None:
        """The host is about to block on this twin (a reply, stream packets; any thread): pump now if a packet is
        due."""
        if self.clock.now() >= self._next_packet_t:
            self._post_wake()

    def _stepped(self, now: float) -> bool:
        """Whether a pump is due without a host wait: always, unless on demand (then after a rig-time step)."""
        return not self.demand or now >= self._worked_at + DEMAND_STEP_S

    def _on_clock(self, now: float) -> None:
        """The virtual clock moved (in the thread that moved it): pump at once if a whole packet is now due, as a
        T7 sends a packet when it fills — rather than up to ``poll`` of wall time later (on demand: only once a
        step has passed since the last pump)."""
        if now >= self._next_packet_t and self._stepped(now):
            self._post_wake()

    def _post_wake(self) -> None:
        """Pump on the serving thread, soon (from any thread; one pending wake at a time)."""
        loop = self._loop
        if self._wake_pending or loop is None:
            return
        self._wake_pending = True
        with contextlib.suppress(RuntimeError):  # the loop has closed: the twin is stopping
            loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        self._wake_pending = False
        if self.clock.now() < self._next_packet_t:  # a wake asked for while a pump ran (it read the time that pump
            return  # then sent for): nothing is due now
        try:
            self.pump()
        except Exception as exc:  # as in the pump loop: keep serving; tests inspect errors
            self.errors.append(exc)

    def _poll(self) -> None:
        """Pump (when a step is due), then again ``poll`` s of wall time later: a timer callback that sets the next
        one (a task sleeping between pumps took a future and a second pass of the loop at every poll)."""
        if self._stepped(self.clock.now()):
            try:
                self.pump()
            except Exception as exc:  # keep serving; tests inspect errors
                self.errors.append(exc)
        loop = self._loop
        if loop is not None:
            self._poll_handle = loop.call_later(self.poll, self._poll)

    def stop(self) -> None:
        """Stop serving."""
        loop = self._loop
        if loop is not None and loop.is_running():
            async def shutdown() -> None:
                if self._poll_handle is not None:
                    self._poll_handle.cancel()
                if self._relay is not None:
                    await self._relay.close()
                if self._stream_server is not None:
                    self._stream_server.close()
                if self._writer is not None:
                    self._writer.close()
                if self._server is not None:
                    await self._server.shutdown()

            with contextlib.suppress(Exception):
                asyncio.run_coroutine_threadsafe(shutdown(), loop).result(timeout=5)
            loop.call_soon_threadsafe(loop.stop)
        unsubscribe = getattr(self.clock, "unsubscribe", None)
        if unsubscribe is not None:
            unsubscribe(self._on_clock)
        if self._thread is not None:
            self._thread.join(timeout=5)
        with contextlib.suppress(ValueError):
            self.plant.listeners.remove(self._on_block)
