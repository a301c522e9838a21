"""T7 register map and Modbus encodings: addresses, device codes, FLOAT32/UINT32 words, Modbus Feedback packets.

Sources and the [D]/[E]/[A] marks: :mod:`drivers.labjack`.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Sequence

import numpy as np
from pymodbus.pdu import ModbusPDU

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
LAST_ERR_DETAIL, LAST_MB_ERR, LAST_ERR_FRAME = 55000, 55001, 55002  # [D] U16 R each: read together after an error
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
Frame = tuple[int, Words | int]  # one MBFB frame: (address, the registers to write) or (address, how many to read)


_FRAME_HEAD = struct.Struct(">BHB")  # [D] MBFB frame: type, address, number of registers


def _u16_bytes(words: Words) -> bytes:
    """Register values as big-endian 16-bit words; a value outside 0…65535 is refused, not wrapped."""
    if type(words) is np.ndarray and words.dtype == np.uint16:  # a stream-out's codes: in range by their type
        return words.astype(">u2").tobytes()
    if isinstance(words, list) and all(type(v) is int for v in words):  # a few registers: struct, not numpy
        with contextlib.suppress(struct.error):  # out of range: refused below, naming the values
            return struct.pack(f">{len(words)}H", *words)
    w = np.asarray(words)
    if w.dtype == np.uint16:  # a stream-out's codes (Calibration.dac_codes): every value in range by its type
        return w.astype(">u2").tobytes()
    # one pass: the OR of all values has a bit above 15 (or is negative) exactly when one of them lies outside
    if w.size and (w.dtype.kind not in "iu" or int(np.bitwise_or.reduce(w, axis=None)) >> 16):
        raise ValueError(f"register values must be integers 0…65535, got {w.min()}…{w.max()}")
    return w.astype(">u2").tobytes()


_COUNT = (int, np.integer)  # what the second item of a read frame is (a write's: the registers)


def read_count(frame: Frame) -> int | None:
    """The registers an MBFB frame reads (its second item a count), None for a write (the registers)."""
    w = frame[1]
    return int(w) if isinstance(w, _COUNT) else None


class Feedback(ModbusPDU):
    """LabJack Modbus Feedback (MBFB, function 76) packet: frames in order, each a write (address, registers) or a
    read (address, number of registers); its reply (decoded by the same class) carries the read frames' data in
    order, none for a write-only packet."""

    function_code = MBFB_FUNCTION

    def __init__(self, writes: tuple[Frame, ...] = (), dev_id: int = 0, transaction_id: int = 0) -> None:
        super().__init__(dev_id=dev_id, transaction_id=transaction_id)
        self.writes = writes
        self.data = b""

    def encode(self) -> bytes:
        """Write frames: 1, address, n, n registers (big-endian); read frames: 0, address, n."""
        parts: list[bytes] = []
        for a, w in self.writes:
            if isinstance(w, _COUNT):  # a read (read_count)
                parts.append(_FRAME_HEAD.pack(0, a, int(w)))
            else:
                parts += (_FRAME_HEAD.pack(1, a, len(w)), _u16_bytes(w))
        return b"".join(parts)

    def decode(self, data: bytes) -> None:
        """The reply: the data of the read frames."""
        self.data = bytes(data)


def frame_name(frame: Frame) -> str:
    """An MBFB frame as an error message names it: ``write 1000+2`` (address + registers) or ``read 0+2``."""
    a, w = frame
    return f"read {a}+{int(w)}" if isinstance(w, int | np.integer) else f"write {a}+{len(w)}"


def frames_summary(frames: Sequence[Frame], most: int = 6) -> str:
    """A packet's frames in order, compactly: runs of like frames as ``write 4420+255 ×2``, at most ``most``
    entries then how many more."""
    runs: list[tuple[str, int]] = []
    for f in frames:
        name = frame_name(f)
        runs[-1:] = [(name, runs[-1][1] + 1)] if runs and runs[-1][0] == name else [*runs[-1:], (name, 1)]
    parts = [f"{name} ×{k}" if k > 1 else name for name, k in runs[:most]]
    if len(runs) > most:
        parts.append(f"… {sum(k for _, k in runs[most:])} more")
    return ", ".join(parts)


def feedback_packets(frames: Sequence[Frame]) -> list[tuple[Frame, ...]]:
    """Pack register writes and reads, in order, into MBFB packets of at most :data:`MBFB_MAX_BYTES`, request and
    reply; a write longer than a frame holds goes in several frames at the same address (for a buffer register: the
    values in order). A read is one frame (at most :data:`MBFB_FRAME_REGS` registers)."""
    split: list[Frame] = []
    for a, w in frames:
        if isinstance(w, int | np.integer):
            if not 1 <= w <= MBFB_FRAME_REGS:
                raise ValueError(f"an MBFB read frame reads 1…{MBFB_FRAME_REGS} registers, not {w}")
            split.append((a, w))
        elif len(w) == 0:
            raise ValueError(f"an MBFB write frame at {a} writes at least one register, not none")
        else:
            split += [(a, w[i:i + MBFB_FRAME_REGS]) for i in range(0, len(w), MBFB_FRAME_REGS)]
    packets: list[tuple[Frame, ...]] = []
    cur: list[Frame] = []
    size = reply = MBFB_HEADER_BYTES
    for a, w in split:
        need = MBFB_FRAME_BYTES + (0 if isinstance(w, int | np.integer) else 2 * len(w))
        back = 2 * int(w) if isinstance(w, int | np.integer) else 0
        if cur and (size + need > MBFB_MAX_BYTES or reply + back > MBFB_MAX_BYTES):
            packets.append(tuple(cur))
            cur, size, reply = [], MBFB_HEADER_BYTES, MBFB_HEADER_BYTES
        cur.append((a, w))
        size += need
        reply += back
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


