"""MBFB (Modbus Feedback, function 76) as the T7 serves it, and pymodbus' TCP server taking T7-sized packets.

[D] Modbus Feedback, function 76: frames of type (0 read, 1 write), address (2 bytes), number of registers (1),
write data; processed in order as FC3 reads / FC16 writes; the reply is the function code and the read frames' data
in order. [D] a packet is at most 1040 bytes (T7 Ethernet). [A] a longer packet, an unknown frame type or a cut
frame is refused with exception 3 (illegal data value); a frame the registers refuse ends the packet with that
frame's exception (the frames before it took effect).
[D] LAST_ERR_FRAME (55002, register map): "the frame number that caused the last error"; [A] frames are numbered
from 1 in the packet as sent (the register's default 0 then means no frame, as LAST_ERR_DETAIL's 0 means no error).
[D] a reply longer than the packet limit: error 2300 MODBUS_RSP_OVERFLOW (register map's errors); [A] refused before
any frame runs, with exception 3 and no frame (0), LAST_ERR_DETAIL 2300.
[L] write frames in a row to one buffer register run as one write (:meth:`FeedbackPDU.bound_to`): a refusal there
names the first of them. [A] a malformed packet names no frame (0).
"""

from __future__ import annotations

import struct
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler

from sim_devices.t7.registers import E_RSP_OVERFLOW, FC_FEEDBACK, FEEDBACK_MAX_PACKET

_FRAME_HEAD = struct.Struct(">BHB")  # [D] a frame's type, address, number of registers


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
    # told the frame (from 1) that ended a packet, its exception code and an error detail (0: the register's own)
    failed: Callable[[int, int, int], None] | None = None

    def __init__(self, dev_id: int = 0, transaction_id: int = 0) -> None:
        super().__init__(dev_id=dev_id, transaction_id=transaction_id)
        self.frames: list[tuple[int, int, int, Any]] = []  # (type, address, registers, write words: a list, or
        # for a buffer register an array of them)
        self.malformed = False
        self.read_registers = 0  # what the read frames read, in all (the reply's size)
        self.reply = b""

    @classmethod
    def bound_to(cls, unit: int, action: Callable[..., Awaitable[ExcCodes | None]],
                 buffers: frozenset[int] = frozenset(),
                 failed: Callable[[int, int, int], None] | None = None) -> type[FeedbackPDU]:
        """The PDU class a twin registers: MBFB frames for ``unit`` run through ``action``. ``buffers``: the
        addresses where write frames in a row go to the action as one write (each value appends, so that is
        the same: a buffer takes as many values as fit and refuses the rest, in one frame or in two).
        ``failed``: called with the number of the frame that ended a packet (the device's LAST_ERR_FRAME),
        the exception code and an error detail for LAST_ERR_DETAIL (0: what the refusing register set)."""
        return type("FeedbackPDU", (cls,), {"unit": unit, "action": staticmethod(action), "buffers": buffers,
                                            "failed": None if failed is None else staticmethod(failed)})

    def decode(self, data: bytes) -> None:
        """Frames from the bytes after the function code; malformed unless they split exactly."""
        i, n = 0, len(data)
        self.malformed = n + 8 > FEEDBACK_MAX_PACKET or n == 0
        frames, buffers = self.frames, self.buffers
        while i < n and not self.malformed:
            if i + 4 > n or data[i] not in (0, 1):
                self.malformed = True
                break
            kind, address, count = _FRAME_HEAD.unpack_from(data, i)
            i += 4
            words: Any = []
            if kind == 1:
                if i + 2 * count > n:
                    self.malformed = True
                    break
                if address in buffers:  # values appended to a buffer: kept as one array, not 2·n objects
                    words = np.frombuffer(data, ">u2", count, i).astype(np.int64)
                else:
                    words = list(struct.unpack_from(f">{count}H", data, i))
                i += 2 * count
            else:
                self.read_registers += count
            frames.append((kind, address, count, words))

    def encode(self) -> bytes:
        """The reply: the read frames' data."""
        return self.reply

    async def run(self, action: Callable[..., Awaitable[ExcCodes | None]]) -> bytes | ExcCodes:
        """Run the frames in order through a device's ``action`` (as FC3 reads / FC16 writes): the read frames'
        data, or the exception that ended the packet (the frames before it took effect)."""
        if self.malformed:
            return self._refused(ExcCodes.ILLEGAL_VALUE, 0)
        if 8 + 2 * self.read_registers > FEEDBACK_MAX_PACKET:
            return self._refused(ExcCodes.ILLEGAL_VALUE, 0, E_RSP_OVERFLOW)  # MBAP 7 + function 1 + the reads
        data = bytearray()
        for number, (kind, address, count, words) in self._merged():
            if kind == 1:
                rc = await action(16, address, address, count, [], words)
                if rc:
                    return self._refused(rc, number)
            else:
                regs = [0] * count
                rc = await action(3, address, address, count, regs, None)
                if rc:
                    return self._refused(rc, number)
                data += struct.pack(f">{count}H", *regs)
        return bytes(data)

    def _refused(self, rc: ExcCodes, number: int, detail: int = 0) -> ExcCodes:
        """The exception that ends the packet, its frame number (and ``detail``, if any) told to the device."""
        if self.failed is not None:
            self.failed(number, int(rc), detail)
        return rc

    def _merged(self) -> list[tuple[int, tuple[int, int, int, Any]]]:
        """The frames with their numbers (from 1), write frames in a row to one buffer register joined (numbered
        as the first of them)."""
        out: list[tuple[int, tuple[int, int, int, Any]]] = []
        for number, (kind, address, count, words) in enumerate(self.frames, 1):
            prev = out[-1][1] if out else None
            if prev and kind == 1 and prev[0] == 1 and prev[1] == address and address in self.buffers:
                out[-1] = (out[-1][0], (1, address, prev[2] + count, np.concatenate([prev[3], words])))
            else:
                out.append((number, (kind, address, count, words)))
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


class T7Server(ModbusTcpServer):
    """pymodbus' TCP server reading whole packets of any MBAP length: its socket framer silently drops a request
    over 264 bytes (the Modbus limit), a T7 takes MBFB packets up to 1040 and the twin answers a longer one."""

    def callback_new_connection(self) -> ServerRequestHandler:
        handler = ServerRequestHandler(
            self, self.trace_packet, self.trace_pdu, self.trace_connect)
        handler.max_buffer_size = 6 + 0xFFFF  # MBAP: 6 header bytes + a 16-bit length
        return handler

