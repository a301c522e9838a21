"""Simulated LabJack T7 on loopback: Modbus TCP registers (pymodbus 3.16 ``SimDevice``) and spontaneous stream
packets on a second socket, backed by the shared plant and clock.

Written from the T-Series Datasheet and LabJack's low-level stream example, independently of
:mod:`drivers.labjack` (own tables; the conformance tests check these bytes against the manual's):

[D] datasheet / register map, [E] LabJack's low-level stream example, [A] assumed, [L] twin limitation.

* [D] registers: AIN#(0:13) 0+2n F32 R; DAC#(0:1) 1000+2n F32 RW; AIN#_RANGE 40000+2n F32; AIN#_NEGATIVE_CH
  41000+n U16; STREAM_* 4002–4022, 4100+2i, 4990; STREAM_OUT#_* 4040/4050/4060/4070/4080/4090+2n,
  BUFFER_F32 4400+2n, BUFFER_U16 4420+n, STREAM_OUT# 4800+n; LAST_ERR_DETAIL 55000; PRODUCT_ID 60000 = 7.0;
  HARDWARE_VERSION 60002; FIRMWARE_VERSION 60004; SERIAL_NUMBER 60028; big-endian, high word first.
* [E] packet: TransID (0 at each STREAM_ENABLE = 1, +1 per packet), ProtoID 0, Length, unit 1, function
  76, type 16, reserved 0, backlog, status, AddInfo, samples MSB first. [A] Length = 10 + 2·n; backlog =
  bytes still buffered after this packet.
* [D] scan k at t_enable + (k+1)/rate; [A] all samples of a scan taken at that instant (the mux is µs apart).
* [D] actual rate 10 MHz / round(10 MHz / rate), computed when written; [A] at most 100 kS/s (inputs +
  stream-out entries), else STREAM_SCAN_RATE_INVALID.
* [D] stream-out: one buffer value per scan, written to the target when the scan runs; after the data the
  last LOOP_NUM_VALUES values repeat. [A] 0 or 1: the output holds; data written while it loops plays after
  the repetitions already queued (1 s ahead); SET_LOOP 2/3 act as 1; BUFFER_STATUS = bytes not yet played.
* [A] F32 buffer values → code = V·Slope + Offset (own calibration); [D] 12-bit DAC, low 4 bits ignored.
* [D] error codes 2600, 2605, 2607, 2608, 2611–2615, 2617, 2618, 2620, 2622, 2627 in LAST_ERR_DETAIL;
  [A] sent as Modbus exception 4; unknown address: exception 2.
* [E] auto-recovery: when more than STREAM_BUFFER_SIZE_BYTES wait unsent (the host does not read), new scans
  are dropped and packets carry 2940; when room returns the next packet carries 2941, AddInfo = scans
  skipped, and starts with one dummy scan of 0xFFFF.
* [A] burst (STREAM_NUM_SCANS > 0): the rest goes in a last, possibly short packet with status 2944, then the
  stream stops; on STREAM_ENABLE = 0 a partial packet is discarded.
* [D] Modbus Feedback (MBFB), function 76: frames of type (0 read, 1 write), address (2 bytes), number of
  registers (1), write data; processed in order as FC3 reads / FC16 writes; the reply is the function code and
  the read frames' data in order. [D] a packet is at most 1040 bytes (T7 Ethernet). [A] a longer packet, an
  unknown frame type or a cut frame is refused with exception 3 (illegal data value); a frame the registers
  refuse ends the packet with that frame's exception (the frames before it took effect).
* [E] calibration in flash at 0x3C4000 (41 F32); pointer 61810, read buffer 61812 ([A] the pointer advances).
* [L] command-response stream (STREAM_AUTO_TARGET ≠ 1: 2612), output-only streams and a STREAM_OUT# twice
  in one scan list (2607) are not simulated; a command-response write to a DAC that stream-out drives
  changes its register but not the plant.

Wiring: DAC ``dac`` drives the amplifier's input through the rig's conditioning stage
(``gain``·V + ``offset``); each wired AIN reads ``gain``·observable + ``offset`` of the plant (TREK voltage and
current monitors, load-cell bridge amplifier, laser analog output).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
import threading
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from scipy.signal import lfilter

from bench.core.clock import Clock
from bench.core.plant import Plant, PlantBlock
from sim_devices.transport import Faults, SocketRelay

# ---- the manual's numbers, written out here (never imported from the driver) ----
R_AIN, R_DAC, R_AIN_RANGE, R_AIN_NEG = 0, 1000, 40000, 41000
N_AIN = 14
R_RATE, R_NADDR, R_SPP, R_SETTLE, R_RES, R_BUFSIZE, R_CLKSRC, R_TARGET, R_DTYPE, R_NSCANS, R_EXTDIV = (
    4002, 4004, 4006, 4008, 4010, 4012, 4014, 4016, 4018, 4020, 4022)
R_SCANLIST, R_ENABLE = 4100, 4990
R_O_TARGET, R_O_ALLOC, R_O_LOOP, R_O_SETLOOP, R_O_STATUS, R_O_ENABLE = 4040, 4050, 4060, 4070, 4080, 4090
R_O_F32, R_O_U16, R_O_SCAN = 4400, 4420, 4800
R_LAST_ERR, R_PRODUCT, R_HW, R_FW, R_SERIAL = 55000, 60000, 60002, 60004, 60028
R_FLASH_PTR, R_FLASH_READ, FLASH_CAL = 61810, 61812, 0x3C4000
# [D] watchdog (LabJack Modbus map, WATCHDOG_*_DEFAULT): ENABLE 61600 U32, TIMEOUT_S 61604 U32, DAC0_ENABLE 61640
# U32, DAC0 61642 F32, DAC1_ENABLE 61650 U32, DAC1 61652 F32; "the watchdog must be disabled before writing any of
# the other watchdog registers"
R_WD_ENABLE, R_WD_TIMEOUT, R_WD_DAC_EN, R_WD_DAC = 61600, 61604, (61640, 61650), (61642, 61652)
E_WD_ENABLED = 2590  # [A] code for "write while the watchdog is enabled" (the datasheet names no number)
E_ACTIVE, E_CHN_LIST, E_RATE, E_DTYPE, E_TARGET, E_OUT_FULL, E_BUFSIZE, E_OUT_DNE, E_SPP, E_NOT_RUNNING, \
    E_LOOP_BIG, E_OUT_DISABLED, E_NO_CHN, E_OUT_TARGET = (
        2605, 2607, 2608, 2611, 2612, 2613, 2615, 2617, 2618, 2620, 2622, 2627, 2600, 2614)
S_RECOVER, S_RECOVER_END, S_BURST = 2940, 2941, 2944
UNIT = 1  # [E] the unit id of the device's Modbus replies and stream packets
FC_FEEDBACK, FEEDBACK_MAX_PACKET = 76, 1040  # [D] MBFB; T7 Ethernet packet bytes (MBAP header included)
MAX_SAMPLE_RATE = 100_000.0
RANGE_GAIN = {0.0: 0, 10.0: 0, 1.0: 1, 0.1: 2, 0.01: 3}
F32, U32, U16 = "f32", "u32", "u16"


def nominal_calibration() -> list[float]:
    """T7 nominal constants (LabJack example getNominalCalibration), flash order."""
    hs: list[float] = []
    for g in range(4):
        k = 10.0 ** -g
        hs += [0.000315805780 * k, -0.000315805800 * k, 33523.0, -10.58695652200 * k]
    return hs + hs + [13200.0, 0.0, 13200.0, 0.0, -92.379, 465.129, 10e-6, 200e-6, 0.0]


class FeedbackPDU(ModbusPDU):
    """MBFB as the T7 serves it: the request's frames, run in order through the device's registers.

    A twin serves the subclass :meth:`bound_to` its ``SimDevice`` action: the frames go straight to that action,
    as FC3 reads / FC16 writes. pymodbus' own path (``context.async_setValues``) first re-checks every register
    of a frame against the ``SimData`` flags — the twin's one block spans every address and marks none read-only,
    so the check never refuses, but it cost more per 255-register frame than the twin's own work; the
    T7's rules (which addresses exist, what they take) are the action's, on either path."""

    function_code = FC_FEEDBACK
    unit: int | None = None  # the device the bound action serves (others take pymodbus' path)
    action: Callable[..., Awaitable[ExcCodes | None]] | None = None
    buffers: frozenset[int] = frozenset()  # buffer registers: write frames in a row to one append as one write

    def __init__(self, dev_id: int = 0, transaction_id: int = 0) -> None:
        super().__init__(dev_id=dev_id, transaction_id=transaction_id)
        self.frames: list[tuple[int, int, int, list[int]]] = []  # (type, address, registers, write words)
        self.malformed = False
        self.reply = b""

    @classmethod
    def bound_to(cls, unit: int, action: Callable[..., Awaitable[ExcCodes | None]],
                 buffers: frozenset[int] = frozenset()) -> type[FeedbackPDU]:
        """The PDU class a twin registers: MBFB frames for ``unit`` run through ``action``. ``buffers``: the
        addresses where write frames in a row go to the action as one write (each value appends, so that is
        the same: a buffer takes as many values as fit and refuses the rest, in one frame or in two)."""
        return type("FeedbackPDU", (cls,), {"unit": unit, "action": staticmethod(action), "buffers": buffers})

    def decode(self, data: bytes) -> None:
        """Frames from the bytes after the function code; malformed unless they split exactly."""
        i, n = 0, len(data)
        self.malformed = n + 8 > FEEDBACK_MAX_PACKET or n == 0
        while i < n and not self.malformed:
            if i + 4 > n or data[i] not in (0, 1):
                self.malformed = True
                break
            kind, address, count = data[i], int.from_bytes(data[i + 1:i + 3], "big"), data[i + 3]
            i += 4
            words: list[int] = []
            if kind == 1:
                if i + 2 * count > n:
                    self.malformed = True
                    break
                words = list(struct.unpack(f">{count}H", data[i:i + 2 * count]))
                i += 2 * count
            self.frames.append((kind, address, count, words))

    def encode(self) -> bytes:
        """The reply: the read frames' data."""
        return self.reply

    async def run(self, action: Callable[..., Awaitable[ExcCodes | None]]) -> bytes | ExcCodes:
        """Run the frames in order through a device's ``action`` (as FC3 reads / FC16 writes): the read frames'
        data, or the exception that ended the packet (the frames before it took effect)."""
        if self.malformed:
            return ExcCodes.ILLEGAL_VALUE
        data = bytearray()
        for kind, address, count, words in self._merged():
            if kind == 1:
                rc = await action(16, address, address, count, [], words)
                if rc:
                    return rc
            else:
                regs = [0] * count
                rc = await action(3, address, address, count, regs, None)
                if rc:
                    return rc
                data += struct.pack(f">{count}H", *regs)
        return bytes(data)

    def _merged(self) -> list[tuple[int, int, int, list[int]]]:
        """The frames, with write frames in a row to one buffer register joined."""
        out: list[tuple[int, int, int, list[int]]] = []
        for kind, address, count, words in self.frames:
            if out and kind == 1 and out[-1][0] == 1 and out[-1][1] == address and address in self.buffers:
                prev = out[-1]
                out[-1] = (1, address, prev[2] + count, prev[3] + words)
            else:
                out.append((kind, address, count, words))
        return out

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        """Each frame as an FC3 read or FC16 write of the device's registers, in order."""
        if self.action is not None and device_id == self.unit:
            out = await self.run(self.action)
        else:
            async def through_context(fc: int, start: int, address: int, count: int, regs: list[int],
                                      values: list[int] | None) -> ExcCodes | None:
                if values is not None:
                    return await context.async_setValues(device_id, fc, address, values)
                got = await context.async_getValues(device_id, fc, address, count)
                if isinstance(got, ExcCodes):
                    return got
                regs[:] = got
                return None

            out = await self.run(through_context)
        if isinstance(out, ExcCodes):
            return ExceptionResponse(FC_FEEDBACK, out)
        reply = FeedbackPDU()
        reply.reply = out
        return reply

    @classmethod
    async def answer(cls, adu: bytes) -> bytes | None:
        """The whole reply ADU to a request ADU that is an MBFB packet for the bound unit (None: not one) — the
        bytes the server would send, made without it (:class:`~sim_devices.transport.SocketRelay` ``local``)."""
        if cls.action is None or adu[2:4] != b"\0\0" or adu[6] != cls.unit or adu[7] != FC_FEEDBACK:
            return None
        pdu = cls()
        pdu.decode(adu[8:])
        out = await pdu.run(cls.action)
        body = bytes([FC_FEEDBACK]) + out if isinstance(out, bytes) else bytes([FC_FEEDBACK | 0x80, int(out)])
        return adu[:4] + (1 + len(body)).to_bytes(2, "big") + adu[6:7] + body


class _T7Server(ModbusTcpServer):
    """pymodbus' TCP server reading whole packets of any MBAP length: its socket framer silently drops a request
    over 264 bytes (the Modbus limit), a T7 takes MBFB packets up to 1040 and the twin answers a longer one."""

    def callback_new_connection(self) -> ServerRequestHandler:
        handler = ServerRequestHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)
        handler.max_buffer_size = 6 + 0xFFFF  # MBAP: 6 header bytes + a 16-bit length
        return handler


@dataclass(frozen=True)
class Conditioning:
    """Rig's stage between a DAC (0–5 V) and the amplifier input: ``gain``·V + ``offset``, clipped ±``limit``,
    optionally through a first-order reconstruction low-pass of corner ``corner_Hz`` (applied to streamed
    values scan by scan; [L] a command-response write reaches the amplifier unfiltered, as a step)."""

    gain: float = 4.0
    offset: float = -10.0
    limit: float = 10.0
    corner_Hz: float | None = None

    def __call__(self, volts: np.ndarray) -> np.ndarray:
        # np.minimum/np.maximum: np.clip's values (NaN passes through) at a fraction of its call overhead
        return np.minimum(np.maximum(self.gain * np.asarray(volts, float) + self.offset, -self.limit), self.limit)


@dataclass(frozen=True)
class Signal:
    """What one AIN sees: ``gain``·(plant observable) + ``offset`` [V], with Gaussian noise [V rms]."""

    observable: str  # "voltage", "current", "force", "displacement"
    gain: float
    offset: float = 0.0
    noise: float = 0.0


def default_signals(vmon_ratio: float = 1000.0, imon_ratio: float = 1e-3, force_gain: float = 1.0,
                    laser_gain: float = 200.0, laser_offset: float = 0.0) -> dict[int, Signal]:
    """AIN0 TREK V monitor, AIN1 I monitor, AIN2 bridge amplifier [V/N], AIN3 laser analog output [V/m]."""
    return {0: Signal("voltage", 1.0 / vmon_ratio), 1: Signal("current", 1.0 / imon_ratio),
            2: Signal("force", force_gain), 3: Signal("displacement", laser_gain, laser_offset)}


@dataclass
class _Out:
    """One stream-out channel."""

    target: int = 0
    alloc: int = 0
    enable: int = 0
    loop_num: int = 0
    queue: deque[int] = field(default_factory=deque)  # codes written, not yet scheduled (stream stopped)
    sched: deque[tuple[int, np.ndarray]] = field(default_factory=deque)  # (first scan, codes) not yet played
    tail: deque[int] = field(default_factory=deque)  # last values written (for the loop)
    loop: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    loop_pos: int = 0
    next_scan: int = 0
    code: int = 0  # last code played
    underrun_scans: int = 0
    loop_active: bool = False


class LabJackT7Sim:
    """The T7 twin: registers, stream engine, stream-out to the plant."""

    def __init__(self, plant: Plant, clock: Clock, *, serial: int = 470012345, dac: int = 0,
                 conditioning: Conditioning | None = None, signals: dict[int, Signal] | None = None,
                 calibration: list[float] | None = None, seed: int = 7, poll: float = 0.002,
                 faults: Faults | None = None) -> None:
        self.plant, self.clock = plant, clock
        self.serial = serial
        self.dac = dac
        self.conditioning = conditioning or Conditioning()
        self.signals = default_signals() if signals is None else signals
        self.cal = list(calibration or nominal_calibration())
        self.rng = np.random.default_rng(seed)
        self.poll = poll
        self.faults = faults or Faults()
        self.lock = threading.RLock()
        self._hist_lock = threading.Lock()  # the plant's listener takes only this one (no lock cycle)
        self.regs: dict[int, float] = {R_RATE: 0.0, R_NADDR: 0, R_SPP: 0, R_SETTLE: 0.0, R_RES: 0,
                                       R_BUFSIZE: 0, R_CLKSRC: 0, R_TARGET: 0, R_DTYPE: 0, R_NSCANS: 0,
                                       R_EXTDIV: 1}
        self.scanlist = [0] * 128
        self.ain_range = [10.0] * N_AIN
        self.ain_neg = [199] * N_AIN
        self.dac_volts = [0.0, 0.0]
        # [A] factory state: watchdog disabled, no timeout actions (a rig's twin starts like a fresh device)
        self.wd: dict[int, float] = {R_WD_ENABLE: 0, R_WD_TIMEOUT: 0, R_WD_DAC_EN[0]: 0, R_WD_DAC[0]: 0.0,
                                     R_WD_DAC_EN[1]: 0, R_WD_DAC[1]: 0.0}
        self.outs = [_Out() for _ in range(4)]
        self.last_err = 0
        self.flash_ptr = 0
        self.rate = 0.0  # actual scan rate
        self.streaming = False
        self.t_enable = 0.0
        self.tid = 0
        self.produced = 0  # scans taken
        self.fifo = np.zeros(0, np.uint16)  # samples waiting for a packet
        self.skipped = 0
        self.recovering = False
        self.packets_sent = 0
        self.scans_skipped_total = 0
        self._hist_t: deque[np.ndarray] = deque()
        self._hist: deque[dict[str, np.ndarray]] = deque()
        last = plant.last
        self._on_block(last)
        plant.listeners.append(self._on_block)
        words = [SimData(0, count=65535, values=0, datatype=DataType.REGISTERS)]
        self.device = SimDevice(UNIT, words, action=self.action)
        self._writer: asyncio.StreamWriter | None = None
        # [A] packets due while no client is connected to the stream port: kept in the device's stream buffer
        # (it streams spontaneously to the connected client) and sent when one connects; counted as unsent, so
        # auto-recovery starts when they exceed STREAM_BUFFER_SIZE_BYTES as for a client that does not read
        self._held: list[bytes] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._server: ModbusTcpServer | None = None
        self._relay: SocketRelay | None = None
        self._stream_server: asyncio.Server | None = None
        self._pump_task: asyncio.Task[None] | None = None
        self.port = 0
        self.stream_port = 0
        self.errors: list[BaseException] = []
        self._filter_y: float | None = None  # reconstruction filter state [V at the amplifier input]
        self._next_packet_t = math.inf  # rig time at which the next whole stream packet is due
        self._wake_pending = False

    # ------------------------------------------------------------------ serving
    def start(self, timeout: float = 10.0) -> tuple[int, int]:
        """Serve Modbus TCP and the stream socket on loopback; returns (Modbus port, stream port)."""
        self._thread = threading.Thread(target=self._run, name="sim-labjack", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout) or not self.port:
            raise RuntimeError(f"simulated T7 did not start: {self.errors}")
        return self.port, self.stream_port

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
            feedback = FeedbackPDU.bound_to(UNIT, self.action, frozenset(range(R_O_U16, R_O_U16 + 4)))
            self._server = _T7Server(self.device, address=("127.0.0.1", 0), custom_pdu=[feedback])
            await self._server.serve_forever(background=True)
            inner = self._server.transport.sockets[0].getsockname()[1]  # type: ignore[union-attr,attr-defined]
            self._relay = await SocketRelay("T7", ("127.0.0.1", inner), self.faults, framing="mbap",
                                            local=feedback.answer).start()
            self._stream_server = await asyncio.start_server(self._on_stream_client, "127.0.0.1", 0)
            self.stream_port = self._stream_server.sockets[0].getsockname()[1]
            self._pump_task = asyncio.get_running_loop().create_task(self._pump_loop())
            subscribe = getattr(self.clock, "subscribe", None)
            if subscribe is not None:  # a virtual clock says when it moves: packets leave when they are due
                subscribe(self._on_clock)
            self.port = self._relay.port
        except BaseException as exc:  # reported by start()
            self.errors.append(exc)
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

    def _on_clock(self, now: float) -> None:
        """The virtual clock moved (in the thread that moved it): pump at once if a whole packet is now due, as a
        T7 sends a packet when it fills — rather than up to ``poll`` of wall time later."""
        loop = self._loop
        if self._wake_pending or now < self._next_packet_t or loop is None:
            return
        self._wake_pending = True
        with contextlib.suppress(RuntimeError):  # the loop has closed: the twin is stopping
            loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        self._wake_pending = False
        try:
            self.pump()
        except Exception as exc:  # as in the pump loop: keep serving; tests inspect errors
            self.errors.append(exc)

    async def _pump_loop(self) -> None:
        while True:
            try:
                self.pump()
            except Exception as exc:  # keep serving; tests inspect errors
                self.errors.append(exc)
            await asyncio.sleep(self.poll)

    def stop(self) -> None:
        """Stop serving."""
        loop = self._loop
        if loop is not None and loop.is_running():
            async def shutdown() -> None:
                if self._pump_task is not None:
                    self._pump_task.cancel()
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

    # ------------------------------------------------------------------ plant coupling
    def _on_block(self, block: PlantBlock) -> None:
        with self._hist_lock:
            self._hist_t.append(block.t.copy())
            self._hist.append({"voltage": block.voltage.copy(), "current": block.current.copy(),
                               "force": block.force.copy(), "displacement": block.displacement.copy()})
            while len(self._hist_t) > 2 and self._hist_t[1][-1] < self.clock.now() - 2.0:
                self._hist_t.popleft()
                self._hist.popleft()

    def _observe(self, times: np.ndarray) -> dict[str, np.ndarray]:
        """Plant observables held at the last model step at or before each time."""
        self.plant.advance_to(float(times[-1]))
        with self._hist_lock:
            first = len(self._hist_t) - 1  # only the blocks that cover the requested times (and the one before)
            while first > 0 and self._hist_t[first][0] > times[0]:
                first -= 1
            hist_t = [self._hist_t[i] for i in range(first, len(self._hist_t))]
            hist = [self._hist[i] for i in range(first, len(self._hist))]
            t = np.concatenate(hist_t)
            idx = np.clip(np.searchsorted(t, times + 1e-9, side="right") - 1, 0, t.size - 1)
            return {k: np.concatenate([h[k] for h in hist])[idx] for k in hist[0]}

    def _ain_volts(self, ain: int, obs: dict[str, np.ndarray], n: int) -> np.ndarray:
        sig = self.signals.get(ain)
        if sig is None:
            return np.zeros(n)
        v = sig.gain * np.nan_to_num(obs[sig.observable]) + sig.offset
        if sig.noise:
            v = v + self.rng.normal(0.0, sig.noise, n)
        return v

    def _raw(self, volts: np.ndarray, gain: int) -> np.ndarray:
        p, nslope, c = self.cal[4 * gain:4 * gain + 3]
        raw = np.where(volts >= 0, c + volts / p, c - volts / nslope)
        return np.clip(np.rint(raw), 0, 65535).astype(np.uint16)

    def _dac_cal(self, ch: int) -> tuple[float, float]:
        """DAC ``ch``'s calibration (slope [codes/V], offset [codes]) from the flash constants."""
        slope, off = self.cal[32 + 2 * ch:34 + 2 * ch]
        return slope, off

    def _code(self, volts: float, ch: int) -> int:
        slope, off = self._dac_cal(ch)
        return int(min(max(round(volts * slope + off), 0), 65535))

    def _code_volts(self, code: int, ch: int) -> float:
        """One code, as :meth:`_codes_volts` (the same double operations, without an array per value)."""
        slope, off = self._dac_cal(ch)
        return ((int(code) >> 4 << 4) - off) / slope

    def _codes_volts(self, codes: np.ndarray, ch: int) -> np.ndarray:
        slope, off = self._dac_cal(ch)
        return ((codes >> 4 << 4) - off) / slope  # 12-bit DAC

    def _drive(self, first: int, codes: np.ndarray) -> None:
        """Amplifier input events for DAC values played at scans ``first``, ``first`` + 1, …"""
        times = self.t_enable + (first + 1 + np.arange(codes.size)) / self.rate
        volts = self.conditioning(self._codes_volts(codes, self.dac))
        fc = self.conditioning.corner_Hz
        if fc is not None and volts.size:  # exact first-order low-pass at the scan instants
            alpha = 1.0 - math.exp(-2.0 * math.pi * fc / self.rate)
            y = self.plant.v_in if self._filter_y is None else self._filter_y
            volts, _ = lfilter([alpha], [1.0, alpha - 1.0], volts, zi=[(1.0 - alpha) * y])
            self._filter_y = float(volts[-1])
        try:
            self.plant.schedule_amplifier_input(times, volts)
        except ValueError as exc:  # cannot happen under the lock order; kept as a check
            self.errors.append(RuntimeError(f"DAC value: {exc}"))

    def _undrive_after(self, t: float) -> None:
        self.plant.unschedule_amplifier_input(t)

    # ------------------------------------------------------------------ stream engine
    def _cur_scan(self, now: float) -> int:
        """Index of the last scan that has run (−1: none)."""
        return math.floor((now - self.t_enable) * self.rate + 1e-6) - 1

    def _in_addresses(self) -> list[int]:
        """The scan list's analog inputs (AIN addresses), in scan order."""
        return [a for a in self.scanlist[:int(self.regs[R_NADDR])] if a < 2 * N_AIN]

    def _out_indices(self) -> list[int]:
        n = int(self.regs[R_NADDR])
        return [a - R_O_SCAN for a in self.scanlist[:n] if R_O_SCAN <= a < R_O_SCAN + 4]

    def _schedule(self, k: int, codes: np.ndarray, now: float) -> None:
        """Give stream-out ``k`` these codes at its next scans (after an underrun: from the next scan on)."""
        if not codes.size:
            return
        o = self.outs[k]
        start = max(o.next_scan, self._cur_scan(now) + 1)
        if start > o.next_scan and not o.loop_active:
            o.underrun_scans += start - o.next_scan
        o.sched.append((start, codes))
        o.next_scan = start + codes.size
        if o.target == R_DAC + 2 * self.dac:
            self._drive(start, codes)

    def _level(self, k: int, now: float) -> int:
        o = self.outs[k]
        if not self.streaming:
            return len(o.queue)
        cur = self._cur_scan(now)
        # scheduled scans after ``cur`` are contiguous up to next_scan − 1 (a gap only follows an underrun,
        # and then every earlier scan has been played)
        return max(0, min(sum(c.size for _, c in o.sched), o.next_scan - 1 - cur))

    def pump(self) -> None:
        """Take the scans due by now, play stream-out, send whole packets (called every ``poll`` s, and on a virtual
        clock also as soon as a whole packet is due: :meth:`_on_clock`)."""
        with self.plant.lock, self.lock:  # plant first (see ``action``)
            if not self.streaming:
                return
            now = self.clock.now()
            due = self._cur_scan(now) + 1
            nscans = int(self.regs[R_NSCANS])
            if nscans:
                due = min(due, nscans)
            for k in self._out_indices():
                self._advance_out(k, now)
            if due > self.produced:
                self._take_scans(due)
            self._send(final=bool(nscans) and self.produced >= nscans)
            self._next_packet_t = self._packet_due()

    def _packet_due(self) -> float:
        """Rig time of the scan that completes the next whole packet (inf when not streaming)."""
        n_in = len(self._in_addresses())
        if not self.streaming or not n_in:
            return math.inf
        missing = max(int(self.regs[R_SPP]) - self.fifo.size, 1)
        scans = -(-missing // n_in)  # scan k is taken at t_enable + (k + 1) / rate
        return self.t_enable + (self.produced + scans) / self.rate

    def _advance_out(self, k: int, now: float) -> None:
        o = self.outs[k]
        cur = self._cur_scan(now)
        while o.sched and o.sched[0][0] <= cur:  # the codes played by now; the last one is the output
            first, codes = o.sched[0]
            played = min(cur - first + 1, codes.size)
            o.code = int(codes[played - 1])
            if played < codes.size:
                o.sched[0] = (first + played, codes[played:])
                break
            o.sched.popleft()
        if o.target in (R_DAC, R_DAC + 2):
            self.dac_volts[(o.target - R_DAC) // 2] = self._code_volts(o.code, (o.target - R_DAC) // 2)
        if o.loop.size > 1 and o.next_scan <= cur + int(self.rate):  # periodic loop: keep 1 s queued
            o.loop_active = True
            n = cur + 2 * int(self.rate) - o.next_scan
            codes = o.loop[(o.loop_pos + np.arange(n)) % o.loop.size]
            o.loop_pos = (o.loop_pos + n) % o.loop.size
            self._schedule(k, codes, now)

    def _take_scans(self, due: int) -> None:
        ks = np.arange(self.produced, due)
        times = self.t_enable + (ks + 1) / self.rate
        ins = self._in_addresses()
        obs = self._observe(times)
        cols = [self._raw(self._ain_volts(a // 2, obs, ks.size), RANGE_GAIN[self.ain_range[a // 2]]) for a in ins]
        data = np.stack(cols, axis=1).reshape(-1)
        self.produced = due
        unsent = self._unsent_bytes()  # the host does not read: the device buffer fills
        cap = int(self.regs[R_BUFSIZE]) or 4096
        if self.recovering or unsent > cap:
            if self.recovering and unsent < cap // 2:
                self.recovering = False
                dummy = np.full(len(ins), 0xFFFF, np.uint16)
                self._send(status=S_RECOVER_END, extra=self.skipped, prefix=dummy)
                self.scans_skipped_total += self.skipped
                self.skipped = 0
                self.fifo = np.concatenate([self.fifo, data])
                return
            self.recovering = True
            self.skipped += ks.size
            return
        self.fifo = np.concatenate([self.fifo, data])

    def _unsent_bytes(self) -> int:
        w = self._writer
        if w is None:
            return sum(len(b) for b in self._held)
        return 0 if w.transport is None else int(w.transport.get_write_buffer_size())

    def _packet(self, samples: np.ndarray, status: int, extra: int) -> bytes:
        backlog = min(int(self.fifo.size * 2), 0xFFFF)
        head = struct.pack(">HHHBBBBHHH", self.tid & 0xFFFF, 0, 10 + 2 * samples.size, UNIT, 76, 16, 0, backlog,
                           status, extra)
        self.tid += 1
        return head + samples.astype(">u2").tobytes()

    def _send(self, *, final: bool = False, status: int = 0, extra: int = 0,
              prefix: np.ndarray | None = None) -> None:
        spp = int(self.regs[R_SPP])
        w = self._writer
        if prefix is not None:  # the auto-recovery-end packet: dummy scan, then buffered data
            take = max(spp - prefix.size, 0)
            samples, self.fifo = np.concatenate([prefix, self.fifo[:take]]), self.fifo[take:]
            self._write(w, self._packet(samples, status, extra))
            return
        packets = []
        while self.fifo.size >= spp or (final and self.fifo.size):
            samples, self.fifo = self.fifo[:spp], self.fifo[spp:]
            last = final and not self.fifo.size
            st = S_BURST if last else (S_RECOVER if self.recovering else 0)
            packets.append(self._packet(samples, st, 0))
        if packets:  # one socket write for the packets a pump has filled (the bytes a T7 sends, fewer syscalls)
            self._write(w, b"".join(packets), len(packets))
        if final:
            self._stop_stream(self.clock.now())

    def _write(self, w: asyncio.StreamWriter | None, data: bytes, packets: int = 1) -> None:
        self.packets_sent += packets
        if w is not None and not w.is_closing():
            w.write(data)
        elif w is None and self.streaming:
            self._held.append(data)

    def _start_stream(self) -> int:
        n = int(self.regs[R_NADDR])
        if self.streaming:
            return E_ACTIVE
        self._filter_y = None  # the filter starts from the amplifier input in force
        if n < 1:
            return E_NO_CHN
        entries = self.scanlist[:n]
        outs = [a - R_O_SCAN for a in entries if R_O_SCAN <= a < R_O_SCAN + 4]
        for a in entries:
            if not ((a < 2 * N_AIN and a % 2 == 0) or R_O_SCAN <= a < R_O_SCAN + 4):
                return E_CHN_LIST
        if len(outs) != len(set(outs)) or any(not self.outs[k].enable for k in outs) or len(outs) == n:
            return E_CHN_LIST
        if self.rate * n > MAX_SAMPLE_RATE or self.rate <= 0:
            return E_RATE
        if self.regs[R_TARGET] != 1:
            return E_TARGET
        if self.regs[R_DTYPE] != 0:
            return E_DTYPE
        spp = int(self.regs[R_SPP])
        if not 1 <= spp <= 512:
            return E_SPP
        size = int(self.regs[R_BUFSIZE])
        if size and (size & (size - 1) or size > 32768):
            return E_BUFSIZE
        now = self.clock.now()
        self.t_enable, self.streaming, self.tid, self.produced = now, True, 0, 0
        self.fifo = np.zeros(0, np.uint16)
        self.recovering, self.skipped = False, 0
        for k in outs:
            o = self.outs[k]
            o.next_scan, o.sched, o.loop_pos = 0, deque(), 0
            o.loop_active = False
            codes, o.queue = np.array(o.queue, np.int64), deque()
            self._schedule(k, codes, now)
        self._next_packet_t = self._packet_due()
        return 0

    def _stop_stream(self, now: float) -> None:
        self._held = []
        cur = self._cur_scan(now)
        for k in self._out_indices():
            self._advance_out(k, now)
            o = self.outs[k]
            unplayed = [int(c) for first, codes in o.sched for c in codes[max(cur + 1 - first, 0):]]
            o.queue.extendleft(reversed(unplayed))
            o.sched = deque()
        self.streaming = False
        self._next_packet_t = math.inf
        self._undrive_after(now)

    # ------------------------------------------------------------------ registers
    def _read_value(self, a: int) -> tuple[str, float] | None:
        """(type, value) of the register starting at ``a``; None if there is none."""
        now = self.clock.now()
        if 0 <= a < 2 * N_AIN and a % 2 == 0:
            obs = self._observe(np.array([now]))
            return F32, float(self._ain_volts(a // 2, obs, 1)[0])
        if a in (R_DAC, R_DAC + 2):
            return F32, self.dac_volts[(a - R_DAC) // 2]
        if R_AIN_RANGE <= a < R_AIN_RANGE + 2 * N_AIN and a % 2 == 0:
            return F32, self.ain_range[(a - R_AIN_RANGE) // 2]
        if R_AIN_NEG <= a < R_AIN_NEG + N_AIN:
            return U16, self.ain_neg[a - R_AIN_NEG]
        if a == R_RATE:
            return F32, self.rate
        if a == R_SETTLE:
            return F32, float(self.regs[a])
        if a in self.regs:
            return U32, int(self.regs[a])
        if R_SCANLIST <= a < R_SCANLIST + 256 and a % 2 == 0:
            return U32, self.scanlist[(a - R_SCANLIST) // 2]
        if a == R_ENABLE:
            return U32, int(self.streaming)
        for base in (R_O_TARGET, R_O_ALLOC, R_O_LOOP, R_O_STATUS, R_O_ENABLE):
            if base <= a < base + 8 and a % 2 == 0:
                k = (a - base) // 2
                o = self.outs[k]
                value = {R_O_TARGET: o.target, R_O_ALLOC: o.alloc, R_O_LOOP: o.loop_num,
                         R_O_STATUS: 2 * self._level(k, now), R_O_ENABLE: o.enable}[base]
                return U32, value
        if R_O_SCAN <= a < R_O_SCAN + 4:
            return U16, 0
        if a == R_LAST_ERR:
            return U16, self.last_err
        if a == R_PRODUCT:
            return F32, 7.0
        if a == R_HW:
            return F32, 1.30
        if a == R_FW:
            return F32, 1.0299
        if a == R_SERIAL:
            return U32, self.serial
        if a in self.wd:
            return (F32 if a in R_WD_DAC else U32), self.wd[a]
        return None

    @staticmethod
    def _words(kind: str, value: float) -> list[int]:
        if kind == F32:
            return list(struct.unpack(">HH", struct.pack(">f", value)))
        if kind == U32:
            v = int(value) & 0xFFFFFFFF
            return [v >> 16, v & 0xFFFF]
        return [int(value) & 0xFFFF]

    def _arm_watchdog(self) -> None:
        """The plant's input watchdog as the registers configure it: enabled with a timeout and a DAC action on
        the DAC that drives the amplifier ([L] modelled as the amplifier input going to 0 V: the rig's host writes
        the DAC value of 0 V through the conditioning stage; another value is recorded as a twin error)."""
        wd, k = self.wd, self.dac
        on = bool(wd[R_WD_ENABLE]) and wd[R_WD_TIMEOUT] > 0 and bool(wd[R_WD_DAC_EN[k]])
        self.plant.input_watchdog = float(wd[R_WD_TIMEOUT]) if on else None
        if on:
            v_in = float(self.conditioning(np.array([self._code_volts(self._code(wd[R_WD_DAC[k]], k), k)]))[0])
            if abs(v_in) > 0.01 * abs(self.conditioning.gain) + 1e-9:
                self.errors.append(RuntimeError(f"watchdog DAC{k} value gives {v_in:.3f} V at the amplifier "
                                                "input; the twin models 0 V"))

    def _fail(self, code: int) -> ExcCodes:
        self.last_err = code
        return ExcCodes.DEVICE_FAILURE

    async def action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                     values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Serve reads by computing the registers, writes by applying them (pymodbus stores nothing we use).

        Every request resets the T7 watchdog ([D] WATCHDOG_*_DEFAULT registers: on timeout the device writes
        its configured DAC value — for a rig, the code of 0 V at the amplifier input); the twin arms the
        plant's input watchdog from those registers as the host writes them (:meth:`_arm_watchdog`)."""
        self.plant.feed_watchdog()
        # The plant's lock first, then ours, and the time read inside both: the plant cannot integrate past
        # ``now`` while the request schedules DAC values from the next scan on (the device plays them on its own
        # clock; a plant that had moved on would take late values as one step, which a T7 never plays).
        with self.plant.lock, self.lock:
            if fc in (3, 4):
                return self._read(address, count, start, regs)
            if fc in (6, 16) and values is not None:
                return self._write_regs(address, cast(list[int], values))  # register values: ints
            return ExcCodes.ILLEGAL_FUNCTION

    def _read(self, address: int, count: int, start: int, regs: list[int]) -> ExcCodes | None:
        if address == R_FLASH_READ:
            words: list[int] = []
            for _ in range(0, count, 2):
                i = (self.flash_ptr - FLASH_CAL) // 4
                v = self.cal[i] if 0 <= i < len(self.cal) else float("nan")
                words += self._words(F32, v)
                self.flash_ptr += 4
        else:
            words = []
            a = address
            while len(words) < count:
                got = self._read_value(a)
                if got is None:
                    return ExcCodes.ILLEGAL_ADDRESS
                w = self._words(*got)
                words += w
                a += len(w)
        for i in range(count):
            regs[address - start + i] = words[i]
        return None

    def _write_regs(self, address: int, words: list[int]) -> ExcCodes | None:
        now = self.clock.now()
        if R_O_U16 <= address < R_O_U16 + 4:
            return self._buffer(address - R_O_U16, words, now)
        if R_O_F32 <= address < R_O_F32 + 8 and address % 2 == 0:
            k = (address - R_O_F32) // 2
            ch = max((self.outs[k].target - R_DAC) // 2, 0)
            floats = [struct.unpack(">f", struct.pack(">HH", *words[i:i + 2]))[0] for i in range(0, len(words), 2)]
            return self._buffer(k, [self._code(v, ch) for v in floats], now)
        a, i = address, 0
        while i < len(words):
            got = self._read_value(a)
            if got is None and a not in (R_FLASH_PTR,) and not (R_O_SETLOOP <= a < R_O_SETLOOP + 8):
                return ExcCodes.ILLEGAL_ADDRESS
            kind = got[0] if got else U32
            n = 1 if kind == U16 else 2
            w = words[i:i + n]
            if len(w) < n:
                return ExcCodes.ILLEGAL_ADDRESS
            value = struct.unpack(">f", struct.pack(">HH", *w))[0] if kind == F32 else \
                (w[0] << 16 | w[1] if n == 2 else w[0])
            err = self._apply(a, value, now)
            if err:
                return err
            a, i = a + n, i + n
        return None

    def _apply(self, a: int, value: float, now: float) -> ExcCodes | None:
        stream_cfg = R_RATE <= a <= R_EXTDIV or R_SCANLIST <= a < R_SCANLIST + 256
        if stream_cfg and self.streaming:
            return self._fail(E_ACTIVE)
        if a in (R_DAC, R_DAC + 2):
            ch = (a - R_DAC) // 2
            code = self._code(value, ch)
            self.dac_volts[ch] = self._code_volts(code, ch)
            driven = self.streaming and any(self.outs[k].target == a for k in self._out_indices())
            if ch == self.dac and not driven:
                self.plant.set_amplifier_input(float(self.conditioning(np.array([self.dac_volts[ch]]))[0]))
        elif R_AIN_RANGE <= a < R_AIN_RANGE + 2 * N_AIN:
            if value not in RANGE_GAIN:
                return ExcCodes.ILLEGAL_VALUE
            self.ain_range[(a - R_AIN_RANGE) // 2] = 10.0 if value == 0 else float(value)
        elif R_AIN_NEG <= a < R_AIN_NEG + N_AIN:
            self.ain_neg[a - R_AIN_NEG] = int(value)
        elif a == R_RATE:
            self.regs[a] = value
            self.rate = 10e6 / max(round(10e6 / value), 1) if value > 152.588 else float(value)
        elif a in self.regs:
            self.regs[a] = value
        elif R_SCANLIST <= a < R_SCANLIST + 256:
            self.scanlist[(a - R_SCANLIST) // 2] = int(value)
        elif a == R_ENABLE:
            if value:
                err = self._start_stream()
                return self._fail(err) if err else None
            if not self.streaming:
                return self._fail(E_NOT_RUNNING)
            self._stop_stream(now)
        elif a == R_FLASH_PTR:
            self.flash_ptr = int(value)
        elif a in self.wd:
            if a != R_WD_ENABLE and self.wd[R_WD_ENABLE]:
                return self._fail(E_WD_ENABLED)
            self.wd[a] = value
            self._arm_watchdog()
        elif R_O_TARGET <= a < R_O_ENABLE + 8:
            return self._apply_out(a, int(value), now)
        else:
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    def _apply_out(self, a: int, value: int, now: float) -> ExcCodes | None:
        base = a - (a - R_O_TARGET) % 10
        k = (a - base) // 2
        o = self.outs[k]
        if base == R_O_TARGET:
            if value not in (R_DAC, R_DAC + 2):
                return self._fail(E_OUT_TARGET)
            o.target = value
        elif base == R_O_ALLOC:
            if value < 32 or value & (value - 1) or value > 16384:
                return self._fail(E_BUFSIZE)
            o.alloc, o.queue, o.tail = value, deque(), deque(maxlen=value // 2 - 1)
        elif base == R_O_ENABLE:
            o.enable = int(bool(value))
        elif not o.enable:
            return self._fail(E_OUT_DISABLED)
        elif base == R_O_LOOP:
            if value > max(o.alloc // 2 - 1, 0):
                return self._fail(E_LOOP_BIG)
            o.loop_num = value
        elif base == R_O_SETLOOP:
            o.loop = np.array(list(o.tail)[len(o.tail) - o.loop_num:] if o.loop_num else [], np.int64)
            o.loop_pos = 0
        else:
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    def _buffer(self, k: int, codes: list[int], now: float) -> ExcCodes | None:
        o = self.outs[k]
        if not o.alloc:
            return self._fail(E_OUT_DNE)
        if not o.enable:
            return self._fail(E_OUT_DISABLED)
        room = o.alloc // 2 - 1 - self._level(k, now)
        take = codes[:max(room, 0)]
        o.tail.extend(take)
        if self.streaming and k in self._out_indices():
            self._advance_out(k, now)
            self._schedule(k, np.array(take, np.int64), now)
        else:
            o.queue.extend(take)
        return self._fail(E_OUT_FULL) if len(take) < len(codes) else None
