"""LabJack T7 multifunction DAQ: Modbus TCP command-response and hardware-timed stream (in and out).

Sources: LabJack T-Series Datasheet §3.2 (stream mode, §3.2.1/3.2.3 stream-out, §3.2.2/3.2.4 low-level
streaming), the register map (``ljm_constants.json`` in labjack/ljm_constants, which the datasheet's
register tables are generated from) and LabJack's own low-level TCP stream example
(``t7_modbus_tcp_stream_example.c`` with ``stream.c``/``calibration.c``). Every number below is marked:

Datasheet [D] = T-Series Datasheet §3.2 and its register map (ljm_constants.json); example [E] = LabJack's
low-level TCP stream example; [A] = assumed, to check on a real T7.

* [E] ports: command-response TCP 502, spontaneous stream TCP 702; Modbus unit id 1.
* [D] big-endian bytes, 32-bit values high word first.
* [D] AIN#(0:249) 0+2n F32 R; DAC#(0:1) 1000+2n F32 RW; AIN#_RANGE 40000+2n F32 (10/1/0.1/0.01);
  AIN#_NEGATIVE_CH 41000+n U16 (199 = single-ended); LAST_ERR_DETAIL 55000 U16; PRODUCT_ID 60000 F32 (7);
  HARDWARE_VERSION 60002 F32; FIRMWARE_VERSION 60004 F32; SERIAL_NUMBER 60028 U32.
* [D] watchdog: WATCHDOG_ENABLE_DEFAULT 61600 U32, _TIMEOUT_S_DEFAULT 61604 U32 (whole seconds),
  _DAC0_ENABLE_DEFAULT 61640 U32, _DAC0_DEFAULT 61642 F32, _DAC1_ENABLE_DEFAULT 61650, _DAC1_DEFAULT 61652;
  "must be disabled before writing any of the other watchdog registers"; any communication clears the timer.
  [A] the _DEFAULT registers live in flash: the driver reads them and writes only what differs.
* [D] STREAM_SCANRATE_HZ 4002 F32, _NUM_ADDRESSES 4004, _SAMPLES_PER_PACKET 4006, _SETTLING_US 4008 F32,
  _RESOLUTION_INDEX 4010, _BUFFER_SIZE_BYTES 4012 (power of 2, T7 ≤ 32768), _CLOCK_SOURCE 4014,
  _AUTO_TARGET 4016 (bit 0: packets to port 702), STREAM_DATATYPE 4018 = 0, _NUM_SCANS 4020 (0: continuous),
  STREAM_SCANLIST_ADDRESS#(0:127) 4100+2i, STREAM_ENABLE 4990 written last.
* [D] stream-out: STREAM_OUT#(0:3) 4800+n in the scan list (returns no data); _TARGET 4040+2n,
  _BUFFER_ALLOCATE_NUM_BYTES 4050+2n (power of 2, 32…16384; usable = bytes/2 − 1 values), _LOOP_NUM_VALUES
  4060+2n, _SET_LOOP 4070+2n (1 = use new data now), _BUFFER_STATUS 4080+2n, _ENABLE 4090+2n,
  _BUFFER_U16 4420+n; order: target, allocate, enable, loop size, data, set-loop; after the data the last
  LOOP_NUM_VALUES values repeat (1: the output holds the end value exactly). The driver keeps at most
  ``StreamSpec.out_ahead_s`` of values in the device ahead of the scan its scan clock may have reached (t0 + k/rate
  on the host clock, t0 known to the enable request's round trip; a lost host then stops the drive within it),
  topping up in chunks of at most a packet and at least a quarter of that; the device past the values written
  (the scan clock's lower bound) is an underrun (``out_underrun_scans``).
* [A] a buffer register takes k values in one Modbus Feedback write frame of k registers at its address
  ([D] register map: STREAM_OUT#_BUFFER_U16 is a buffer register, "a sequence of values to a single address").
* [D] Modbus Feedback (MBFB), function 76: after the function code, frames of type (1 byte: 0 read, 1 write),
  address (2), number of registers (1), then for a write 2·n data bytes; the reply carries the function code
  and the read frames' data in order. [D] T7 Ethernet packets ≤ 1040 bytes (LabJackM.h,
  LJM_MAX_ETHERNET_PACKET_NUM_BYTES_T7). [A] an error is answered as a Modbus exception (function 0xCC and a
  code, anything after it ignored); the stream-out buffer is topped up through MBFB (510 values a packet, not
  120 — four times fewer exchanges per second of waveform).
* [E] packet: TransID(2) ProtoID(2)=0 Length(2) Unit(1)=1 Function(1)=76 Type(1)=16 Reserved(1)
  Backlog(2, bytes) Status(2) AddInfo(2), then samples (2 bytes, MSB first, scan-list order, STREAM_OUT
  entries excluded); TransID 0 at STREAM_ENABLE, +1 per packet. [A] Length = 10 + 2·samples (MBAP rule).
* [D][E] status 2940 auto-recover active, 2941 end (AddInfo = scans skipped; one dummy scan of 0xFFFF first
  [E, U3 manual]), 2942 scan overlap, 2943 skip-counter overflow, 2944 burst complete, 2945 buffer full.
* [A] a burst's last packet may be shorter than STREAM_SAMPLES_PER_PACKET; a stop discards a partial packet.
* [D] first scan one scan period after STREAM_ENABLE = 1 (STREAM_START_TIME_STAMP); scan rate > 152.588 Hz
  is 10 MHz / round(10 MHz / rate), read back from 4002.
* [E] calibration: flash pointer 61810 ← 0x3C4000 + 52·i, reads of 61812 of 26, 26, 26, 4 registers = 41
  F32 (HS[4], HR[4] × PSlope/NSlope/Center/Offset, DAC[2] × Slope/Offset, temperature, current sources,
  I_bias); raw → V = (raw − Center)·PSlope if raw ≥ Center else (Center − raw)·NSlope, gain 0..3 = ±10/1/0.1/
  0.01 V. [A] DAC code = V·Slope + Offset; [D] the 12-bit DAC ignores the low 4 bits of DAC#_BINARY.
* [D] error names (LAST_ERR_DETAIL); [A] which Modbus exception code carries them (the driver reads 55000
  after any exception).

Why spontaneous stream on its own socket rather than command-response stream (STREAM_DATA_CR 4500): the
datasheet documents the spontaneous packet byte by byte (and LabJack's example parses it); the C-R read
format is not given in the material we have. The Modbus client (pymodbus via :class:`ModbusLink`) carries
configuration and stream-out buffer updates; a plain TCP socket carries the packets.

Engine API (bluesky-style): :meth:`LabJackT7.arm` (stage: configure inputs, scan list, preload stream-out),
:meth:`~LabJackT7.kickoff` (STREAM_ENABLE = 1; returns the rig time of scan 0), :meth:`~LabJackT7.collect`
(complete scans received so far, numbered, refilling the stream-out buffer), :meth:`~LabJackT7.complete`
(wait until the burst or the waveform is done), :meth:`~LabJackT7.stop`.
"""

from __future__ import annotations

import contextlib
import functools
import math
import select
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from pymodbus.pdu import ModbusPDU

from drivers.cancel import CancelToken, check
from drivers.deadline import WALL, ReplyTimer
from drivers.errors import (
    ImplausibleValueError,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentStateError,
    InstrumentTimeoutError,
    LimitError,
    ProtocolError,
)
from drivers.interfaces import CheckResult, ClockFn, DacCoding, Identity, Reading, SleepFn
from drivers.interfaces import StreamBlock as StreamBlock  # the stream's types are the DAQ contract's
from drivers.interfaces import StreamIn as StreamIn
from drivers.interfaces import StreamOut as StreamOut
from drivers.interfaces import StreamSpec as StreamSpec
from drivers.modbus_link import ModbusLink

_T = TypeVar("_T")

UNIT = 1
CR_PORT, STREAM_PORT = 502, 702
AIN0, DAC0 = 0, 1000
AIN_RANGE0, AIN_NEG0 = 40000, 41000
SINGLE_ENDED = 199
SCANRATE, NUM_ADDRESSES, SAMPLES_PER_PACKET, SETTLING_US = 4002, 4004, 4006, 4008
RESOLUTION_INDEX, BUFFER_SIZE_BYTES, CLOCK_SOURCE, AUTO_TARGET, DATATYPE, NUM_SCANS = \
    4010, 4012, 4014, 4016, 4018, 4020
SCANLIST0, STREAM_ENABLE = 4100, 4990
OUT_SCAN0, OUT_TARGET0, OUT_ALLOC0, OUT_LOOP0, OUT_SET_LOOP0, OUT_STATUS0, OUT_ENABLE0 = \
    4800, 4040, 4050, 4060, 4070, 4080, 4090
OUT_BUFFER_U16_0 = 4420
LAST_ERR_DETAIL = 55000
PRODUCT_ID, HARDWARE_VERSION, FIRMWARE_VERSION, SERIAL_NUMBER = 60000, 60002, 60004, 60028
FLASH_POINTER, FLASH_READ, CAL_FLASH_ADDRESS = 61810, 61812, 0x3C4000
WATCHDOG_ENABLE, WATCHDOG_TIMEOUT_S = 61600, 61604
WATCHDOG_DAC_ENABLE, WATCHDOG_DAC = (61640, 61650), (61642, 61652)
CAL_READ_REGS = (26, 26, 26, 4)
TARGET_SPONTANEOUS = 0x01
STREAM_FUNCTION, STREAM_TYPE = 76, 16
HEADER_BYTES = 16
MAX_SCANLIST = 128
MAX_SAMPLES_PER_PACKET = 512  # TCP [example: STREAM_MAX_SAMPLES_PER_PACKET_TCP]
MAX_OUT_BUFFER_BYTES = 16384  # T7 [register map]
MAX_STREAM_BUFFER_BYTES = 32768  # T7 [register map]
MBFB_FUNCTION = 76  # [D] Modbus Feedback
MBFB_MAX_BYTES = 1040  # [D] T7 Ethernet packet, MBAP header included
MBFB_HEADER_BYTES = 8  # MBAP (7) + function code
MBFB_FRAME_BYTES = 4  # type, address, number of registers
MBFB_FRAME_REGS = 255  # the number of registers is one byte
OUT_PACKET_VALUES = 2 * MBFB_FRAME_REGS  # stream-out values one MBFB packet carries (two full frames)
DAC_RANGE = (0.0, 5.0)  # V [datasheet: T7 DACs 0–5 V]
DUMMY = 0xFFFF
ST_OK, ST_RECOVER_ACTIVE, ST_RECOVER_END, ST_SCAN_OVERLAP, ST_RECOVER_OVERFLOW, ST_BURST_COMPLETE, \
    ST_BUFFER_FULL = 0, 2940, 2941, 2942, 2943, 2944, 2945
RANGES = (10.0, 1.0, 0.1, 0.01)  # gain index 0..3
# [D] T-Series Datasheet App. A-3, Table A.3-1: typical input range at gain 1 is −10.5 … +10.1 V (the nominal
# calibration puts code 0 at −10.59 V, code 65535 at +10.11 V). A reading beyond 1.1 × its range (±11 V on ±10 V)
# is none the converter makes, whatever the unit's calibration: a sentinel (−9999), float32's end (±3.4e38),
# or a garbled reply.
AIN_SPAN = 1.1
PRODUCT_T7 = 7  # [D] PRODUCT_ID of a T7 (and T7-Pro)
ERRORS = {
    2600: "STREAM_NEED_AT_LEAST_ONE_CHN", 2605: "STREAM_IS_ACTIVE", 2606: "STREAM_CONFIG_INVALID",
    2607: "STREAM_CHN_LIST_INVALID", 2608: "STREAM_SCAN_RATE_INVALID", 2609: "STREAM_OUT_BUFF_TOO_BIG",
    2610: "STREAM_OUT_NUM_INVALID", 2612: "STREAM_TARGET_CONFIG_INVALID", 2613: "STREAM_OUT_BUFF_FULL",
    2614: "STREAM_OUT_TARGET_INVALID", 2615: "STREAM_BUFF_SIZE_INVALID", 2617: "STREAM_OUT_BUFF_DNE",
    2618: "STREAM_SAMPLES_PER_PKT_INVALID", 2620: "STREAM_NOT_RUNNING", 2621: "STREAM_SETTLING_INVALID",
    2622: "STREAM_OUT_LOOP_TOO_BIG", 2625: "STREAM_CHN_CAN_NOT_BE_STREAMED",
    2627: "STREAM_OUT_NEEDS_TO_BE_ENABLED",
    ST_RECOVER_ACTIVE: "STREAM_AUTO_RECOVER_ACTIVE", ST_RECOVER_END: "STREAM_AUTO_RECOVER_END",
    ST_SCAN_OVERLAP: "STREAM_SCAN_OVERLAP", ST_RECOVER_OVERFLOW: "STREAM_AUTO_RECOVER_END_OVERFLOW",
    ST_BURST_COMPLETE: "STREAM_BURST_COMPLETE", ST_BUFFER_FULL: "STREAM_BUFFER_FULL",
}


Words = list[int] | np.ndarray  # register values of one write: a list, or an integer array (a stream-out's codes)


def _u16_bytes(words: Words) -> bytes:
    """Register values as big-endian 16-bit words; a value outside 0…65535 is refused, not wrapped."""
    w = np.asarray(words)
    if w.size and (w.dtype.kind not in "iu" or int(w.min()) < 0 or int(w.max()) > 0xFFFF):
        raise ValueError(f"register values must be integers 0…65535, got {w.min()}…{w.max()}")
    return w.astype(">u2").tobytes()


class Feedback(ModbusPDU):
    """LabJack Modbus Feedback (MBFB, function 76) packet: write frames (address, registers) in order; its reply
    (decoded by the same class) carries the read frames' data, none for a write-only packet."""

    function_code = MBFB_FUNCTION

    def __init__(self, writes: tuple[tuple[int, Words], ...] = (), dev_id: int = 0,
                 transaction_id: int = 0) -> None:
        super().__init__(dev_id=dev_id, transaction_id=transaction_id)
        self.writes = writes
        self.data = b""

    def encode(self) -> bytes:
        """Write frames: 1, address, n, n registers (big-endian)."""
        return b"".join(struct.pack(">BHB", 1, a, len(w)) + _u16_bytes(w) for a, w in self.writes)

    def decode(self, data: bytes) -> None:
        """The reply: the data of the read frames (none here)."""
        self.data = bytes(data)


def feedback_packets(writes: list[tuple[int, Words]]) -> list[tuple[tuple[int, Words], ...]]:
    """Pack register writes, in order, into MBFB packets of at most :data:`MBFB_MAX_BYTES`; a write longer than a
    frame holds goes in several frames at the same address (for a buffer register: the values in order)."""
    frames = [(a, w[i:i + MBFB_FRAME_REGS]) for a, w in writes for i in range(0, len(w), MBFB_FRAME_REGS)]
    packets: list[tuple[tuple[int, Words], ...]] = []
    cur: list[tuple[int, Words]] = []
    size = MBFB_HEADER_BYTES
    for a, w in frames:
        need = MBFB_FRAME_BYTES + 2 * len(w)
        if cur and size + need > MBFB_MAX_BYTES:
            packets.append(tuple(cur))
            cur, size = [], MBFB_HEADER_BYTES
        cur.append((a, w))
        size += need
    if cur:
        packets.append(tuple(cur))
    return packets


def f32_words(x: float) -> list[int]:
    """FLOAT32 as two registers, high word first."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", x))
    return [hi, lo]


def u32_words(x: int) -> list[int]:
    """UINT32 as two registers, high word first."""
    return [(x >> 16) & 0xFFFF, x & 0xFFFF]


def words_f32(w: list[int]) -> float:
    """Two registers (high word first) as FLOAT32."""
    return float(struct.unpack(">f", struct.pack(">HH", w[0], w[1]))[0])


def words_u32(w: list[int]) -> int:
    """Two registers (high word first) as UINT32."""
    return (w[0] << 16) | w[1]


@functools.lru_cache(maxsize=16)
def _ain_table(p: float, n: float, c: float) -> np.ndarray:
    """Volts of every 16-bit stream code: (r − Center)·PSlope at or above the centre, (Center − r)·NSlope below."""
    r = np.arange(65536, dtype=float)
    table = np.where(r < c, (c - r) * n, (r - c) * p)
    table.setflags(write=False)
    return table


@dataclass(frozen=True)
class Calibration:
    """T7 calibration constants in flash order: HS[4]×(PSlope, NSlope, Center, Offset), HR[4]×4, DAC[2]×
    (Slope, Offset), temperature (slope, offset), current sources (10 µA, 200 µA), I_bias."""

    values: tuple[float, ...]

    @classmethod
    def nominal(cls) -> Calibration:
        """LabJack's nominal constants (getNominalCalibration in the example's calibration.c)."""
        hs: list[float] = []
        for g in range(4):
            s = 0.000315805780 * 10.0 ** -g
            hs += [s, -0.000315805800 * 10.0 ** -g, 33523.0, -10.58695652200 * 10.0 ** -g]
        return cls(tuple(hs + hs + [13200.0, 0.0, 13200.0, 0.0, -92.379, 465.129, 10e-6, 200e-6, 0.0]))

    def hs(self, gain: int) -> tuple[float, float, float, float]:
        """(PSlope, NSlope, Center, Offset) of the high-speed converter at gain index 0..3."""
        p, n, c, o = self.values[4 * gain:4 * gain + 4]
        return p, n, c, o

    def dac(self, channel: int) -> tuple[float, float]:
        """(Slope [codes/V], Offset [codes]) of DAC0/DAC1."""
        s, o = self.values[32 + 2 * channel:34 + 2 * channel]
        return s, o

    def ain_volts(self, raw: np.ndarray, gain: int) -> np.ndarray:
        """Stream samples (16-bit binary) to volts (through a table of all 65536 codes)."""
        p, n, c, _ = self.hs(gain)
        return _ain_table(p, n, c)[np.asarray(raw, dtype=np.uint16)]

    def dac_codes(self, volts: np.ndarray, channel: int, within: tuple[float, float] | None = None,
                  bits: int = 12) -> np.ndarray:
        """Volts to 16-bit DAC codes (code = V·Slope + Offset, rounded, clipped).

        ``within`` (lo, hi) [V]: codes are also clipped to those whose ``bits``-bit output (:meth:`dac_volts`) lies
        within [lo, hi] — the nearest such code, so one level toward the inside where a value's own code plays
        just beyond (:meth:`dac_code_range`)."""
        s, o = self.dac(channel)
        codes = np.clip(np.rint(np.asarray(volts, float) * s + o), 0, 0xFFFF)
        if within is not None:
            codes = np.clip(codes, *self.dac_code_range(channel, within, bits))
        return codes.astype(np.uint16)

    def dac_code_range(self, channel: int, within: tuple[float, float], bits: int = 12) -> tuple[int, int]:
        """The 16-bit codes (first, last) whose ``bits``-bit output lies within ``within`` = (lo, hi) [V]: the
        levels inside, each with all its codes (the low ``16 − bits`` bits the converter ignores)."""
        shift = 16 - bits
        levels = np.arange(1 << bits, dtype=np.int64) << shift
        out = self.dac_volts(levels, channel, bits)
        inside = np.flatnonzero((out >= within[0]) & (out <= within[1]))
        if not inside.size:
            raise ValueError(f"no {bits}-bit DAC{channel} level lies within {within[0]:g}…{within[1]:g} V")
        return int(levels[inside[0]]), int(levels[inside[-1]]) | ((1 << shift) - 1)

    def dac_volts(self, codes: np.ndarray, channel: int, bits: int = 12) -> np.ndarray:
        """What a ``bits``-bit DAC outputs for 16-bit codes (low bits ignored)."""
        s, o = self.dac(channel)
        c = (np.asarray(codes, dtype=np.int64) >> (16 - bits)) << (16 - bits)
        return (c - o) / s


@dataclass(frozen=True)
class StreamPacket:
    """One decoded spontaneous stream packet."""

    transaction_id: int
    backlog_bytes: int
    status: int
    additional: int
    samples: np.ndarray  # uint16


def parse_stream_packet(frame: bytes, device: str = "T7") -> StreamPacket:
    """Decode one whole packet (MBAP header included) or raise :class:`ProtocolError`."""
    if len(frame) < HEADER_BYTES:
        raise ProtocolError(device, f"stream packet of {len(frame)} bytes, header alone is {HEADER_BYTES}")
    tid, proto, length, unit, func, typ, _res, backlog, status, add = struct.unpack(">HHHBBBBHHH", frame[:16])
    if proto != 0 or unit != UNIT or func != STREAM_FUNCTION or typ != STREAM_TYPE:
        raise ProtocolError(device, f"not a stream packet (protocol {proto}, unit {unit}, function {func}, "
                            f"type {typ})")
    if length != len(frame) - 6 or (length - 10) % 2 or length < 10:
        raise ProtocolError(device, f"stream packet length field {length} for {len(frame)} bytes")
    samples = np.frombuffer(frame, dtype=">u2", offset=HEADER_BYTES).astype(np.uint16)
    return StreamPacket(tid, backlog, status, add, samples)


@dataclass
class StreamPlan:
    """What the device will do: actual scan rate, scan list, and the stream-out codes it will play."""

    scan_rate: float
    dt: float
    names: tuple[str, ...]
    scan_list: tuple[int, ...]
    samples_per_packet: int
    out_codes: np.ndarray | None
    out_volts: np.ndarray | None  # what the 12-bit DAC outputs for out_codes
    out_capacity: int  # values the stream-out buffer holds
    max_collect_interval: float  # call collect at least this often [s] so the out buffer never runs dry
    out_ahead: int = 0  # values kept in the device at most, ahead of the last scan received (≤ out_capacity)
    out_chunk: int = OUT_PACKET_VALUES  # a top-up waits until this many values fit (or the rest of the data)


@dataclass
class _Stream:
    plan: StreamPlan
    spec: StreamSpec
    n_in: int
    gains: tuple[int, ...]
    sock: socket.socket | None = None
    t_enable: float = 0.0
    t0: float = 0.0
    t0_uncertainty: float = math.nan
    next_tid: int = 0
    raw: bytearray = field(default_factory=bytearray)
    pending: list[int] = field(default_factory=list)  # samples of a scan split across packets
    scans: int = 0  # scan index of the next scan to hand out (skipped ones included)
    packets: int = 0
    out_written: int = 0
    out_base: int = 0  # index of plan.out_codes[0] among every value given (extend drops written ones)
    out_closed: bool = True  # no values will be appended: the hold loop follows the last one
    out_final: bool = False  # the hold loop is written: the device plays nothing more from the host
    underrun_scans: int = 0
    done: bool = False


class LabJackT7:
    """Driver of one LabJack T7 over Ethernet (command-response on ``port``, stream on ``stream_port``)."""

    def __init__(self, host: str, *, port: int = CR_PORT, stream_port: int = STREAM_PORT, name: str = "daq",
                 timeout: float = 0.5, cancel: CancelToken | None = None, clock: ClockFn = time.monotonic,
                 sleep: SleepFn = time.sleep, safe_dac: tuple[float, float] = (0.0, 0.0),
                 dac_bits: int = 12, watchdog_s: int | None = None, timer: ReplyTimer = WALL) -> None:
        """``safe_dac``: DAC0/DAC1 volts written by :meth:`safe_state` (the rig's zero through its conditioning).
        ``watchdog_s``: on connect, the device's watchdog is set to write ``safe_dac`` to both DACs after this
        many seconds without a request (None: left as the device has it). ``timer``: how a wait for a reply or
        for stream packets ends (:mod:`drivers.deadline`; the command-response link's too)."""
        self.host, self.port, self.stream_port = host, port, stream_port
        self.name = name
        self.timeout = timeout
        self.cancel = cancel
        self.clock, self.sleep = clock, sleep
        self.safe_dac = safe_dac
        self.dac_bits = dac_bits
        self.watchdog_s = watchdog_s
        self.timer = timer
        self.link = ModbusLink(f"tcp://{host}:{port}", name, timeout=timeout, cancel=cancel, timer=timer)
        self.link.register(Feedback)
        self.cal = Calibration.nominal()
        self.serial = 0
        self._ain_range: dict[int, float] = {}  # ±V of the inputs configured here (the rest: the ±10 V default)
        self._stream: _Stream | None = None
        self.streaming = False

    # ------------------------------------------------------------------ command-response
    def _lj(self, what: str, fn: Callable[..., _T], *args: object) -> _T:
        """Run one link call; a Modbus exception is re-raised with the device's LAST_ERR_DETAIL name."""
        try:
            return fn(UNIT, *args)
        except InstrumentStateError as exc:
            try:
                code = self.link.read_holding(UNIT, LAST_ERR_DETAIL, 1)[0]
            except Exception:  # the first error is the one to report
                raise exc from None
            raise InstrumentStateError(self.name, f"{what} refused: LabJack error {code} "
                                       f"({ERRORS.get(code, 'see the register map')})") from None

    def heard_at(self) -> float | None:
        """``time.monotonic()`` at which the last command-response request the T7 answered was sent."""
        return self.link.heard_at(UNIT)

    def read_regs(self, address: int, count: int) -> list[int]:
        """Read ``count`` registers from ``address`` (FC3)."""
        return self._lj(f"read {address}+{count}", self.link.read_holding, address, count)

    def write_regs(self, address: int, values: list[int]) -> None:
        """Write registers from ``address`` (FC16)."""
        self._lj(f"write {address}+{len(values)}", self.link.write_registers, address, values)

    def write_feedback(self, writes: list[tuple[int, Words]]) -> None:
        """Write registers in order through as few Modbus Feedback packets as hold them (:func:`feedback_packets`).

        Not retried: a packet appends to the stream-out buffer, and after a timeout the device may already have
        taken it — a second attempt would play its values twice and shift the rest of the waveform. A timeout is
        an :class:`InstrumentTimeoutError` (the run stops and makes the rig safe) rather than a drive played late.
        """
        for packet in feedback_packets(writes):
            n = sum(len(w) for _, w in packet)
            self._lj(f"feedback write of {n} registers at {packet[0][0]}",
                     lambda unit, pdu: self.link.execute(unit, pdu, retry=False), Feedback(packet))

    def read_f32(self, address: int) -> float:
        """One FLOAT32 register pair."""
        return words_f32(self.read_regs(address, 2))

    def read_u32(self, address: int) -> int:
        """One UINT32 register pair."""
        return words_u32(self.read_regs(address, 2))

    def write_f32(self, address: int, value: float) -> None:
        """Write one FLOAT32."""
        self.write_regs(address, f32_words(value))

    def write_u32(self, address: int, value: int) -> None:
        """Write one UINT32."""
        self.write_regs(address, u32_words(value))

    def read_calibration(self) -> Calibration:
        """Read the 41 calibration constants from flash (as LabJack's example does)."""
        values: list[float] = []
        for i, n in enumerate(CAL_READ_REGS):
            self.write_u32(FLASH_POINTER, CAL_FLASH_ADDRESS + i * 13 * 4)
            w = self.read_regs(FLASH_READ, n)
            values += [words_f32(w[j:j + 2]) for j in range(0, n, 2)]
        cal = Calibration(tuple(values))
        if not all(math.isfinite(v) for v in values) or cal.hs(0)[0] <= 0 or cal.dac(0)[0] <= 0:
            raise ProtocolError(self.name, "calibration constants read from flash are not plausible")
        for gain, rng in enumerate(RANGES):  # every stream code is converted through these: bound them all
            ends = cal.ain_volts(np.array([0, 0xFFFF]), gain)
            if not np.all(np.abs(ends) <= AIN_SPAN * rng):
                bad = float(ends[np.argmax(np.abs(ends))])
                raise ImplausibleValueError(self.name, f"calibration: ±{rng:g} V range full-scale code at", bad,
                                            (-AIN_SPAN * rng, AIN_SPAN * rng), "V",
                                            "the constants read from flash are not plausible")
        return cal

    # ------------------------------------------------------------------ Instrument
    def connect(self) -> None:
        """Open the Modbus link, check it is a T7, read its calibration, stop a stream left running."""
        self.link.open()
        product = self.read_f32(PRODUCT_ID)
        if not (math.isfinite(product) and round(product) == PRODUCT_T7):  # inf, NaN, negative: one line too
            raise InstrumentStateError(self.name, f"PRODUCT_ID (register {PRODUCT_ID}) reads {product:g}, "
                                       f"expected {PRODUCT_T7} (T7)")
        self.serial = self.read_u32(SERIAL_NUMBER)
        self.cal = self.read_calibration()
        if self.read_u32(STREAM_ENABLE):
            self.write_u32(STREAM_ENABLE, 0)
        if self.watchdog_s is not None:
            self.configure_watchdog(self.watchdog_s, self.safe_dac)

    def read_watchdog(self) -> tuple[int, int, tuple[tuple[int, float], ...]]:
        """(enabled, timeout [s], ((DAC0 action enabled, volts), (DAC1 …))) as the device holds them."""
        dacs = tuple((self.read_u32(WATCHDOG_DAC_ENABLE[k]), self.read_f32(WATCHDOG_DAC[k])) for k in (0, 1))
        return self.read_u32(WATCHDOG_ENABLE), self.read_u32(WATCHDOG_TIMEOUT_S), dacs

    def configure_watchdog(self, timeout_s: int, dac_volts: tuple[float, float]) -> bool:
        """Enable the watchdog: after ``timeout_s`` s without communication both DACs go to ``dac_volts``.
        Writes (disable, settings, enable) only when the device's settings differ; returns whether it wrote."""
        if not 1 <= int(timeout_s) == timeout_s:
            raise ValueError(f"{self.name}: watchdog timeout must be a whole number of seconds ≥ 1")
        want = (1, int(timeout_s), tuple((1, float(np.float32(v))) for v in dac_volts))
        if self.read_watchdog() == want:
            return False
        self.write_u32(WATCHDOG_ENABLE, 0)
        self.write_u32(WATCHDOG_TIMEOUT_S, int(timeout_s))
        for k, v in enumerate(dac_volts):
            self.write_u32(WATCHDOG_DAC_ENABLE[k], 1)
            self.write_f32(WATCHDOG_DAC[k], v)
        self.write_u32(WATCHDOG_ENABLE, 1)
        return True

    def check(self) -> CheckResult:
        """Whether a stream runs; AIN0 by command-response."""
        return CheckResult("stream running" if self.streaming else "idle", (("AIN0", self.read_ain(0)),))

    def identify(self) -> Identity:
        """PRODUCT_ID, serial number, firmware and hardware versions."""
        return Identity("LabJack", "T7", {"serial": str(self.read_u32(SERIAL_NUMBER)),
                                          "firmware": f"{self.read_f32(FIRMWARE_VERSION):.4f}",
                                          "hardware": f"{self.read_f32(HARDWARE_VERSION):.2f}"})

    def safe_state(self) -> None:
        """Stop the stream (the DACs stop updating) and write the safe DAC values."""
        if not self.link.is_open:
            return
        try:
            self.stop()
        finally:
            for ch, v in enumerate(self.safe_dac):
                self.write_dac(ch, v)

    def close(self) -> None:
        """Safe state, then release both sockets."""
        try:
            self.safe_state()
        finally:
            self._close_stream_socket()
            self.link.close()

    # ------------------------------------------------------------------ single values
    def configure_ain(self, ain: int, range_volts: float = 10.0, negative_channel: int = SINGLE_ENDED) -> None:
        """Range (±10/1/0.1/0.01 V) and negative channel (199: single-ended) of one input."""
        if range_volts not in RANGES:
            raise ValueError(f"{self.name}: AIN range must be one of {RANGES} V, got {range_volts}")
        self.write_f32(AIN_RANGE0 + 2 * ain, range_volts)
        self.write_regs(AIN_NEG0 + ain, [negative_channel])
        self._ain_range[ain] = range_volts

    def read_ain(self, ain: int) -> Reading:
        """One command-response reading of AIN ``ain`` [V].

        A value that is not finite or lies beyond 1.1 × the input's range (±11 V on the ±10 V range, the
        default of an input this driver has not configured) is no reading the converter makes (:data:`AIN_SPAN`):
        status "invalid", value NaN — one bad sample, not a broken link."""
        v = self.read_f32(AIN0 + 2 * ain)
        limit = AIN_SPAN * self._ain_range.get(ain, RANGES[0])
        if not abs(v) <= limit:
            return Reading(math.nan, "V", self.clock(), "invalid")
        return Reading(v, "V", self.clock())

    def dac_output(self, dac: int, volts: float, within: tuple[float, float] | None = None) -> tuple[float, float]:
        """(value :meth:`write_dac` sends, what the DAC then outputs) [V] for ``volts``, sending nothing.

        The T7 codes the FLOAT32 it receives as V·Slope + Offset (rounded) and its 12-bit converter ignores the low
        4 bits. ``within`` (lo, hi): the code is the nearest whose output lies within (one level toward the inside
        at the edge), sent as the middle of its level's codes, so that the T7's own rounding of the float cannot
        move it to another level; LimitError if that value is not one the DAC spans."""
        if dac not in (0, 1):
            raise ValueError(f"{self.name}: no DAC{dac}")
        if not DAC_RANGE[0] <= volts <= DAC_RANGE[1]:
            raise LimitError(self.name, f"DAC{dac} {volts:g} V outside {DAC_RANGE[0]:g}…{DAC_RANGE[1]:g} V")
        send = volts
        if within is not None:
            shift = 16 - self.dac_bits
            try:
                code = int(self.cal.dac_codes(np.array([volts]), dac, within, self.dac_bits)[0])
            except ValueError as exc:
                raise LimitError(self.name, str(exc)) from None
            s, o = self.cal.dac(dac)
            send = ((code >> shift << shift) + (1 << shift) / 2 - o) / s
        played = float(self.out_played(np.array([np.float32(send)]), dac)[0])
        if within is not None and not (DAC_RANGE[0] <= send <= DAC_RANGE[1] and within[0] <= played <= within[1]):
            raise LimitError(self.name, f"DAC{dac}: no value the DAC spans plays within {within[0]:g}…{within[1]:g} V")
        return send, played

    def out_played(self, volts: np.ndarray, dac: int, within: tuple[float, float] | None = None) -> np.ndarray:
        """What DAC ``dac`` outputs [V] for the values ``volts`` as the T7 codes them (rounded; ``within``: codes
        clipped as :meth:`Calibration.dac_codes` does): a stream-out's values as :meth:`arm` and :meth:`extend`
        play them."""
        return self.cal.dac_volts(self.cal.dac_codes(volts, dac, within, self.dac_bits), dac, self.dac_bits)

    def write_dac(self, dac: int, volts: float, within: tuple[float, float] | None = None) -> float:
        """Set DAC0/DAC1 [V]; refuses values outside the DAC's 0–5 V. Returns what the DAC outputs: the 12-bit
        level of the code the T7 makes of the value. ``within`` (lo, hi) [V]: that output lies within [lo, hi]
        (:meth:`dac_output` chooses the value sent)."""
        send, played = self.dac_output(dac, volts, within)
        self.write_f32(DAC0 + 2 * dac, send)
        return played

    def dac_coding(self, dac: int, within: tuple[float, float]) -> DacCoding:
        """How DAC ``dac`` codes volts (its calibration; 16-bit codes, the low ``16 − dac_bits`` ignored) and its codes
        whose output lies within ``within`` (:meth:`Calibration.dac_code_range`)."""
        slope, offset = self.cal.dac(dac)
        lo, hi = self.cal.dac_code_range(dac, within, self.dac_bits)
        return DacCoding(float(slope), float(offset), 16 - self.dac_bits, lo, hi)

    def read_dac(self, dac: int) -> float:
        """The DAC's present value [V]."""
        return self.read_f32(DAC0 + 2 * dac)

    # ------------------------------------------------------------------ stream
    def arm(self, spec: StreamSpec) -> StreamPlan:
        """Configure inputs, stream registers, scan list and stream-out; preload the out buffer.

        Nothing runs until :meth:`kickoff`. Refuses (nothing sent) what the T7 cannot do.
        """
        if self.streaming:
            raise InstrumentStateError(self.name, "arm while streaming: stop first")
        n_in = len(spec.inputs)
        out = spec.output
        if n_in < 1:
            raise ValueError(f"{self.name}: a stream needs at least one input")
        n_addr = n_in + (out is not None)
        if n_addr > MAX_SCANLIST:
            raise ValueError(f"{self.name}: scan list of {n_addr} addresses, at most {MAX_SCANLIST}")
        if not spec.scan_rate > 152.588:
            raise ValueError(f"{self.name}: scan rates ≤ 152.588 Hz are not supported by this driver")
        spp = spec.samples_per_packet or (MAX_SAMPLES_PER_PACKET // n_in) * n_in
        if not 1 <= spp <= MAX_SAMPLES_PER_PACKET:
            raise ValueError(f"{self.name}: samples_per_packet must be 1…{MAX_SAMPLES_PER_PACKET}")
        codes = volts = None
        capacity = 0
        if out is not None:
            v = self._checked_out(out.volts, out.dac)
            if not 1 <= out.hold <= v.size:
                raise ValueError(f"{self.name}: hold must be 1…{v.size} values")
            codes = self.cal.dac_codes(v, out.dac, out.within, self.dac_bits)
            volts = self.cal.dac_volts(codes, out.dac, self.dac_bits)
            capacity = (spec.out_buffer_bytes or MAX_OUT_BUFFER_BYTES) // 2 - 1
        gains = tuple(RANGES.index(i.range_volts) for i in spec.inputs)
        scan_list = tuple([OUT_SCAN0] if out is not None else []) + tuple(AIN0 + 2 * i.ain for i in spec.inputs)
        if self.read_u32(STREAM_ENABLE):
            self.write_u32(STREAM_ENABLE, 0)
        for i in spec.inputs:
            self.configure_ain(i.ain, i.range_volts)
        self.write_regs(SCANRATE, f32_words(spec.scan_rate) + u32_words(n_addr) + u32_words(spp)
                        + f32_words(spec.settling_us) + u32_words(spec.resolution_index)
                        + u32_words(spec.buffer_size_bytes or MAX_STREAM_BUFFER_BYTES))
        self.write_regs(AUTO_TARGET, u32_words(TARGET_SPONTANEOUS) + u32_words(0) + u32_words(spec.num_scans))
        self.write_u32(CLOCK_SOURCE, 0)
        self.write_regs(SCANLIST0, [w for a in scan_list for w in u32_words(a)])
        rate = self.read_f32(SCANRATE)
        if not rate > 0:
            raise ProtocolError(self.name, f"device reports scan rate {rate}")
        names = tuple(i.name or f"AIN{i.ain}" for i in spec.inputs)
        if spec.out_ahead_s < 0 or not math.isfinite(spec.out_ahead_s):
            raise ValueError(f"{self.name}: out_ahead_s must be a finite time ≥ 0")
        ahead = min(capacity, max(1, math.ceil(spec.out_ahead_s * rate))) if spec.out_ahead_s else capacity
        chunk = min(OUT_PACKET_VALUES, max(1, ahead // 4))  # a collect tops up every ~quarter of it
        interval = (ahead - chunk) / rate / 2 if out is not None else math.inf
        plan = StreamPlan(rate, 1.0 / rate, names, scan_list, spp, codes, volts, capacity, interval, ahead, chunk)
        self._stream = _Stream(plan, spec, n_in, gains, out_closed=out is None or out.final)
        if out is not None:
            o = 2 * out.dac
            self.write_u32(OUT_TARGET0, DAC0 + o)
            self.write_u32(OUT_ALLOC0, spec.out_buffer_bytes or MAX_OUT_BUFFER_BYTES)
            self.write_u32(OUT_ENABLE0, 1)
            self._feed_out()
        return plan

    def _feed_out(self) -> None:
        """Top up the stream-out buffer with as many values as fit; close it with the hold loop."""
        s = self._stream
        assert s is not None
        codes = s.plan.out_codes
        if codes is None or s.out_final:
            return
        total = s.out_base + codes.size  # values given so far (the first out_base are no longer kept)
        pos = hi = s.scans  # values the device has played: at least the scans received, and …
        if self.streaming:  # … those its scan clock has reached by now: t0 is known late, by at most its uncertainty
            late = self.clock() - s.t0
            pos = max(pos, math.floor(late * s.plan.scan_rate) + 1)
            hi = max(pos, math.floor((late + s.t0_uncertainty) * s.plan.scan_rate) + 1)
        if self.streaming and pos > s.out_written:  # the device ran past the data it had (surely: lower bound)
            s.underrun_scans = max(s.underrun_scans, pos - s.out_written)
        played = min(hi, s.out_written)  # ahead of where the device may be: a slow enable reply costs no margin
        free = (s.plan.out_ahead or s.plan.out_capacity) - (s.out_written - played)
        n = max(0, min(free, total - s.out_written))
        if n < s.plan.out_chunk and s.out_written + n < total:
            return  # wait until a whole chunk fits
        k = s.out_written - s.out_base
        writes: list[tuple[int, Words]] = [(OUT_BUFFER_U16_0, codes[k:k + n])] if n else []
        s.out_written += n
        if s.out_written == total and s.out_closed:
            assert s.spec.output is not None
            writes.append((OUT_LOOP0, u32_words(s.spec.output.hold)))
            s.out_final = True
        if n:
            writes.append((OUT_SET_LOOP0, u32_words(1)))
        if writes:
            self.write_feedback(writes)

    def _checked_out(self, volts: np.ndarray, dac: int) -> np.ndarray:
        """Stream-out values as floats, refused (nothing sent) unless a non-empty finite 1-D array the DAC spans."""
        v = np.asarray(volts, dtype=float)
        if v.ndim != 1 or v.size < 1 or not np.all(np.isfinite(v)):
            raise ValueError(f"{self.name}: stream-out waveform must be a non-empty finite 1-D array")
        if v.min() < DAC_RANGE[0] or v.max() > DAC_RANGE[1]:
            raise LimitError(self.name, f"DAC{dac} waveform spans {v.min():g}…{v.max():g} V, "
                             f"the DAC gives {DAC_RANGE[0]:g}…{DAC_RANGE[1]:g} V")
        return v

    def extend(self, volts: np.ndarray, final: bool = True, within: tuple[float, float] | None = None) -> np.ndarray:
        """Append values [V at the DAC] to an open stream-out (armed with ``final=False``): they play on the
        scans right after the values already given, on the same scan clock — no gap, no restart. ``final``:
        nothing more follows (the hold loop is written after them). ``within``: as :attr:`StreamOut.within`
        (default: the armed stream-out's). Returns what the 12-bit DAC will output.

        Call it before the device has played the values it has (:attr:`StreamPlan.max_collect_interval`);
        a stream-out that already ran dry plays the new values late (``out_underrun_scans``)."""
        s = self._stream
        if s is None or s.spec.output is None or s.out_closed or s.plan.out_codes is None:
            raise InstrumentStateError(self.name, "extend needs an armed stream-out opened with final=False")
        v = self._checked_out(volts, s.spec.output.dac)
        window = s.spec.output.within if within is None else within
        codes = self.cal.dac_codes(v, s.spec.output.dac, window, self.dac_bits)
        played = self.cal.dac_volts(codes, s.spec.output.dac, self.dac_bits)
        assert s.plan.out_volts is not None
        cut = s.out_written - s.out_base  # values already in the device are dropped here (long campaigns)
        s.plan.out_codes = np.concatenate([s.plan.out_codes[cut:], codes])
        s.plan.out_volts = np.concatenate([s.plan.out_volts[cut:], played])
        s.out_base += cut
        s.out_closed = final
        self._feed_out()
        return played

    @property
    def out_open(self) -> bool:
        """An armed stream-out still takes :meth:`extend`."""
        s = self._stream
        return s is not None and s.spec.output is not None and not s.out_closed and not s.done

    def _open_stream_socket(self) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, self.stream_port), timeout=self.timer.bound(self.timeout))
        except OSError as exc:
            raise InstrumentConnectionError(self.name, f"cannot open stream port {self.host}:{self.stream_port}: "
                                            f"{exc.strerror or exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def _close_stream_socket(self) -> None:
        s = self._stream
        if s is not None and s.sock is not None:
            s.sock.close()
            s.sock = None

    def kickoff(self) -> float:
        """Open the stream socket, write STREAM_ENABLE = 1; returns the rig time of scan 0.

        The time is the clock read after the device acknowledged the enable, plus one scan period; its
        uncertainty is one Modbus round trip.
        """
        s = self._stream
        if s is None or s.done:
            raise InstrumentStateError(self.name, "kickoff without arm")
        if self.streaming:
            raise InstrumentStateError(self.name, "stream already running")
        s.sock = self._open_stream_socket()
        asked = self.clock()
        self.write_u32(STREAM_ENABLE, 1)
        s.t_enable = self.clock()
        s.t0 = s.t_enable + s.plan.dt
        s.t0_uncertainty = s.t_enable - asked  # the device enabled somewhere within the request's round trip
        self.streaming = True
        return s.t0

    @property
    def scan_clock_uncertainty(self) -> float:
        """How well scan 0's time on the host clock is known [s]: the enable request's round trip (the times of
        the scans are t0 + k/rate with t0 taken at the acknowledgement; the true enable lies within this much
        before it)."""
        return self._stream.t0_uncertainty if self._stream is not None else math.nan

    def _receive(self, until_packets: int, timeout: float) -> list[StreamPacket]:
        """Packets available now, and (waiting until a deadline of ``timeout`` s expires: :mod:`drivers.deadline`)
        until ``until_packets`` total."""
        s = self._stream
        assert s is not None and s.sock is not None
        out: list[StreamPacket] = []
        deadline = self.timer.start(timeout)
        while True:
            check(self.cancel, self.name)
            wait = s.packets + len(out) < until_packets and not s.done
            r, _, _ = select.select([s.sock], [], [], min(deadline.left(), 0.05) if wait else 0.0)
            if r:
                try:
                    data = s.sock.recv(1 << 16)
                except OSError as exc:
                    raise InstrumentConnectionError(self.name, f"stream socket lost: {exc.strerror or exc}") \
                        from None
                if not data:
                    raise InstrumentConnectionError(self.name, "stream socket closed by the device")
                s.raw += data
                while len(s.raw) >= 6:
                    total = 6 + struct.unpack(">H", s.raw[4:6])[0]
                    if len(s.raw) < total:
                        break
                    pkt = parse_stream_packet(bytes(s.raw[:total]), self.name)
                    del s.raw[:total]
                    if pkt.transaction_id != (s.next_tid & 0xFFFF):
                        raise ProtocolError(self.name, f"stream packet {pkt.transaction_id} after "
                                            f"{(s.next_tid - 1) & 0xFFFF}: packets lost")
                    s.next_tid += 1
                    out.append(pkt)
                    if pkt.status in (ST_BURST_COMPLETE, ST_BUFFER_FULL, ST_SCAN_OVERLAP, ST_RECOVER_OVERFLOW):
                        s.done = True
                continue
            if not wait:
                return out
            if deadline.expired():
                raise InstrumentTimeoutError(self.name, f"stream packets up to #{until_packets} not received "
                                             f"within {timeout:g} s (have {s.packets + len(out)}){deadline.detail}")

    def _expected_packets(self, until: float) -> int:
        s = self._stream
        assert s is not None
        scans = math.floor((until - s.t_enable) * s.plan.scan_rate + 1e-6)
        if s.spec.num_scans:
            scans = min(scans, s.spec.num_scans)
        return max(scans, 0) * s.n_in // s.plan.samples_per_packet

    def collect(self, until: float | None = None, timeout: float = 1.0) -> StreamBlock:
        """Complete scans received since the last call (scan-numbered), after topping up the out buffer.

        ``until`` (rig time): first wait, up to ``timeout`` s (:mod:`drivers.deadline`), for every whole packet the
        device has filled by then — in virtual time, call it with the clock's present to get every scan so far.
        A gap in the packet sequence is a :class:`ProtocolError`; a device status that ends the stream
        (scan overlap, skip-counter overflow, buffer full) an :class:`InstrumentStateError` after the data.
        Samples are 16-bit codes converted through the calibration read at connect, which is refused unless
        every code of every range lies within 1.1 × the range (:data:`AIN_SPAN`): no streamed sample is beyond
        what the converter makes.
        """
        s = self._stream
        if s is None or s.sock is None:
            raise InstrumentStateError(self.name, "collect without kickoff")
        want = self._expected_packets(until) if until is not None else 0
        packets = self._receive(want, timeout)
        s.packets += len(packets)
        first = s.scans
        rows: list[np.ndarray] = []
        valid: list[np.ndarray] = []
        statuses: list[int] = []
        skipped = 0
        backlog = 0
        chunk: list[np.ndarray] = []  # samples of consecutive packets, converted together
        for pkt in packets:
            if pkt.status:
                statuses.append(pkt.status)
            backlog = pkt.backlog_bytes // (2 * s.n_in)
            samples = pkt.samples
            if pkt.status == ST_RECOVER_END:
                self._convert(chunk, rows, valid)
                if s.pending:
                    raise ProtocolError(self.name, "auto-recovery ended inside a scan")
                if samples.size < s.n_in or np.any(samples[:s.n_in] != DUMMY):
                    raise ProtocolError(self.name, "auto-recovery end without the dummy scan")
                samples = samples[s.n_in:]
                skipped += pkt.additional
                rows.append(np.full((pkt.additional, s.n_in), np.nan))
                valid.append(np.zeros((pkt.additional, s.n_in), bool))
                s.scans += pkt.additional
            chunk.append(samples)
        self._convert(chunk, rows, valid)
        v = np.concatenate(rows) if rows else np.empty((0, s.n_in))
        ok = np.concatenate(valid) if valid else np.empty((0, s.n_in), bool)
        if self.streaming and not s.done:
            self._feed_out()
        if s.done:
            self.streaming = False
        block = StreamBlock(first, s.t0, s.plan.dt, s.plan.names, v, ok, backlog, skipped, tuple(statuses), s.done)
        fatal = [c for c in statuses if c in (ST_SCAN_OVERLAP, ST_RECOVER_OVERFLOW, ST_BUFFER_FULL)]
        if fatal:
            self._last_block = block
            raise InstrumentStateError(self.name, f"stream ended by device status {fatal[0]} "
                                       f"({ERRORS[fatal[0]]}) at scan {s.scans}")
        return block

    def _convert(self, chunk: list[np.ndarray], rows: list[np.ndarray], valid: list[np.ndarray]) -> None:
        """Whole scans of the samples in ``chunk`` (after the samples left over from the last packet) to volts in
        ``rows``; the rest of a scan waits for the next packet. Empties ``chunk``."""
        s = self._stream
        assert s is not None
        if not chunk:
            return
        allsamp = np.concatenate([np.asarray(s.pending, np.uint16), *chunk])
        chunk.clear()
        whole = allsamp.size // s.n_in * s.n_in
        s.pending = allsamp[whole:].tolist()
        raw = allsamp[:whole].reshape(-1, s.n_in)
        volts = np.empty(raw.shape)
        for j, g in enumerate(s.gains):
            volts[:, j] = self.cal.ain_volts(raw[:, j], g)
        rows.append(volts)
        valid.append(np.ones(raw.shape, bool))
        s.scans += raw.shape[0]

    @property
    def scans_received(self) -> int:
        """Scan index of the next scan :meth:`collect` will return."""
        return self._stream.scans if self._stream else 0

    @property
    def out_underrun_scans(self) -> int:
        """Scans the stream-out played past the data written (0 unless :meth:`collect` came too late)."""
        return self._stream.underrun_scans if self._stream else 0

    def complete(self, timeout: float = 10.0, poll: float = 0.05) -> list[StreamBlock]:
        """Wait (on the rig clock: a virtual clock advances) until the burst completed or, for a continuous
        stream with an output, every waveform value has been played and its scan collected; returns the
        blocks collected meanwhile. ``timeout``: seconds without progress before giving up (:mod:`drivers.deadline`)."""
        s = self._stream
        if s is None or not self.streaming:
            raise InstrumentStateError(self.name, "complete without a running stream")
        codes = s.plan.out_codes
        if not s.spec.num_scans and codes is None:
            raise InstrumentStateError(self.name, "a continuous input-only stream never completes; use stop")
        target = s.spec.num_scans or (s.out_base + codes.size if codes is not None else 0)
        blocks: list[StreamBlock] = []
        while True:
            block = self.collect(until=self.clock(), timeout=timeout)
            blocks.append(block)
            if block.done or s.scans >= target:
                return blocks
            self.sleep(poll)

    def stop(self) -> StreamBlock | None:
        """STREAM_ENABLE = 0 (the DAC keeps its last value) and close the stream socket; returns the complete
        scans that had arrived (a partly filled packet is not sent by the device)."""
        s = self._stream
        if s is None or s.sock is None:
            return None
        block = None
        try:
            if self.streaming:
                self._lj("stop stream", self.link.write_registers, STREAM_ENABLE, u32_words(0))
            self.streaming = False
            with contextlib.suppress(InstrumentError):  # stopping must not fail on the data's account
                block = self.collect(timeout=0.0)
        finally:
            self.streaming = False
            s.done = True
            self._close_stream_socket()
        return block
