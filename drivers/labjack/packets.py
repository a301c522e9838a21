"""The T7's spontaneous stream packet ([E] header layout; [A] its length rule, see :mod:`drivers.labjack`)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.labjack.registers import HEADER_BYTES, STREAM_FUNCTION, STREAM_TYPE, UNIT

_HEAD = struct.Struct(">HHHBBBBHHH")  # [E] the header: TransID … AddInfo


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
    them) of ``frames``, in order, or raise :class:`ProtocolError` at the first that is not one. The samples of all
    are converted in one pass (a packet is whole 16-bit words: 16 header bytes, 2 per sample); each packet's are a
    view of them."""
    heads = []
    for off, size in spans:
        if size < HEADER_BYTES:
            raise ProtocolError(device, f"stream packet of {size} bytes, header alone is {HEADER_BYTES}")
        tid, proto, length, unit, func, typ, _res, backlog, status, add = _HEAD.unpack_from(frames, off)
        if proto != 0 or unit != UNIT or func != STREAM_FUNCTION or typ != STREAM_TYPE:
            raise ProtocolError(device, f"not a stream packet (protocol {proto}, unit {unit}, function {func}, "
                                f"type {typ})")
        if length != size - 6 or (length - 10) % 2 or length < 10:
            raise ProtocolError(device, f"stream packet length field {length} for {size} bytes")
        heads.append((tid, backlog, status, add))
    if not spans:
        return []
    first, end = spans[0][0], spans[-1][0] + spans[-1][1]
    allw = np.frombuffer(memoryview(frames)[first:end], ">u2").astype(np.uint16)
    words = [allw[(off - first + HEADER_BYTES) // 2:(off - first + size) // 2] for off, size in spans]
    return [StreamPacket(*h, w) for h, w in zip(heads, words, strict=True)]

