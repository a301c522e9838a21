"""The T7's spontaneous stream packet ([E] header layout; [A] its length rule, see :mod:`drivers.labjack`)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.labjack.registers import HEADER_BYTES, STREAM_FUNCTION, STREAM_TYPE, UNIT

_HEAD = struct.Struct(">HHHBBBBHHH")  # [E] the header: TransID … AddInfo
_FIXED_MASK = np.array([0xFFFF, 0xFFFF, 0xFFFF, 0xFF00])  # header words 1–4 as checked: all but the reserved byte


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
    return parse_stream_packets(frame, [(0, len(frame))], device)[0]


def split_stream_packets(buf: bytes | bytearray) -> list[tuple[int, int]]:
    """(offset, size) of each whole packet at the start of ``buf``, by the MBAP length field; the rest is a packet
    still arriving."""
    out = []
    i, n = 0, len(buf)
    while n - i >= 6:
        total = 6 + int.from_bytes(buf[i + 4:i + 6], "big")
        if n - i < total:
            break
        out.append((i, total))
        i += total
    return out


def parse_stream_packets(frames: bytes, spans: list[tuple[int, int]], device: str = "T7") -> list[StreamPacket]:
    """Decode the packets at ``spans`` (offset, size; one after the other, as :func:`split_stream_packets` gives
    them) of ``frames``, in order, or raise :class:`ProtocolError` at the first that is not one; each packet's samples
    are a view of the batch's (:func:`parse_stream_batch`)."""
    batch = parse_stream_batch(frames, spans, device)
    return [batch.packet(i) for i in range(len(batch))]


@dataclass(frozen=True)
class StreamBatch:
    """Consecutive decoded packets: each header field an array (one value per packet), and all their samples in
    order as one array, packet ``i``'s ending before ``ends[i]``."""

    transaction_ids: np.ndarray
    backlog_bytes: np.ndarray
    statuses: np.ndarray
    additional: np.ndarray
    samples: np.ndarray  # uint16
    ends: np.ndarray

    def __len__(self) -> int:
        return int(self.ends.size)

    def packet(self, i: int) -> StreamPacket:
        """Packet ``i`` alone (its samples a view of the batch's)."""
        start = int(self.ends[i - 1]) if i else 0
        return StreamPacket(int(self.transaction_ids[i]), int(self.backlog_bytes[i]), int(self.statuses[i]),
                            int(self.additional[i]), self.samples[start:int(self.ends[i])])


def parse_stream_batch(frames: bytes, spans: list[tuple[int, int]], device: str = "T7") -> StreamBatch:
    """Decode the packets at ``spans`` (as :func:`parse_stream_packets`) into one :class:`StreamBatch`, or raise
    :class:`ProtocolError` at the first that is not a stream packet. Packets of one size (a running stream's) are
    read as the rows of one array: their headers checked and their samples copied out in a few passes over all of
    them, not packet by packet."""
    n = len(spans)
    if not n:
        empty = np.zeros(0, np.int64)
        return StreamBatch(empty, empty, empty, empty, np.zeros(0, np.uint16), empty)
    first, end = spans[0][0], spans[-1][0] + spans[-1][1]
    size = spans[0][1]
    if size >= HEADER_BYTES and not size % 2 and all(sz == size for _, sz in spans):
        rows = np.frombuffer(memoryview(frames)[first:end], ">u2").reshape(n, size // 2)
        head = rows[:, :HEADER_BYTES // 2].astype(np.int64)  # [E] TransID, ProtoID, Length, unit·function,
        # type·reserved, backlog, status, AddInfo: ProtoID … type (not the reserved byte) checked in one pass
        if not np.any(head[:, 1:5] & _FIXED_MASK != (0, size - 6, UNIT << 8 | STREAM_FUNCTION, STREAM_TYPE << 8)):
            per = size // 2 - HEADER_BYTES // 2
            samples = rows[:, HEADER_BYTES // 2:].astype(np.uint16).reshape(-1)
            return StreamBatch(head[:, 0], head[:, 5], head[:, 6], head[:, 7], samples,
                               np.arange(1, n + 1, dtype=np.int64) * per)
    # packets of several sizes (a burst's last, a cut one), or one that is not a stream packet: one at a time
    heads = []
    for off, sz in spans:
        if sz < HEADER_BYTES:
            raise ProtocolError(device, f"stream packet of {sz} bytes, header alone is {HEADER_BYTES}")
        tid, proto, length, unit, func, typ, _res, backlog, status, add = _HEAD.unpack_from(frames, off)
        if proto != 0 or unit != UNIT or func != STREAM_FUNCTION or typ != STREAM_TYPE:
            raise ProtocolError(device, f"not a stream packet (protocol {proto}, unit {unit}, function {func}, "
                                f"type {typ})")
        if length != sz - 6 or (length - 10) % 2 or length < 10:
            raise ProtocolError(device, f"stream packet length field {length} for {sz} bytes")
        heads.append((tid, backlog, status, add))
    allw = np.frombuffer(memoryview(frames)[first:end], ">u2")
    samples = np.concatenate([allw[(off - first + HEADER_BYTES) // 2:(off - first + sz) // 2] for off, sz in spans]
                             ).astype(np.uint16)
    fields = np.array(heads, np.int64).reshape(n, 4)
    ends = np.cumsum([(sz - HEADER_BYTES) // 2 for _, sz in spans], dtype=np.int64)
    return StreamBatch(fields[:, 0], fields[:, 1], fields[:, 2], fields[:, 3], samples, ends)
