"""The T7's spontaneous stream packet ([E] header layout; [A] its length rule, see :mod:`drivers.labjack`)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from drivers.errors import ProtocolError
from drivers.labjack.registers import HEADER_BYTES, STREAM_FUNCTION, STREAM_TYPE, UNIT


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

