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
Request = Callable[[Callable[[], "bytes | ExcCodes"]], "bytes | ExcCodes"]  # runs its argument as one device request


class FeedbackPDU(ModbusPDU):
    """MBFB as the T7 serves it: the request's frames, run in order through the device's registers.

    A twin serves the subclass :meth:`bound_to` its registers: the frames go straight to the device's ``serve``
    (as FC3 reads / FC16 writes), all within one ``request`` of the device (a packet is one request: its watchdog,
    its locks), computed at once — no awaits. pymodbus' own path (``context.async_setValues``) first re-checks every
    register of a frame against the ``SimData`` flags — the twin's one block spans every address and marks none
    read-only, so the check never refuses, but it cost more per 255-register frame than the twin's own work; the
    T7's rules (which addresses exist, what they take) are the device's, on either path."""

    function_code = FC_FEEDBACK
    unit: int | None = None  # the device the bound registers serve (others take pymodbus' path)
    # one frame as an FC3 read / FC16 write: (function, start, address, count, registers read, values written)
    serve: Callable[..., ExcCodes | None] | None = None
    request: Request | None = None  # runs a packet's frames as one request of the device
    buffers: frozenset[int] = frozenset()  # buffer registers: write frames in a row to one append as one write
    # told the frame (from 1) that ended a packet, its exception code and an error detail (0: the register's own)
    failed: Callable[[int, int, int], None] | None = None

    def __init__(self, dev_id: int = 0, transaction_id: int = 0) -> None:
        super().__init__(dev_id=dev_id, transaction_id=transaction_id)
        # (number from 1, type, address, registers, write words: a list, or for a buffer register an array of them);
        # write frames in a row to one buffer register joined as they are read (numbered as the first of them)
        self.frames: list[tuple[int, int, int, int, Any]] = []
        self.malformed = False
        self.read_registers = 0  # what the read frames read, in all (the reply's size)
        self.reply = b""

    @classmethod
    def bound_to(cls, unit: int, serve: Callable[..., ExcCodes | None],
                 request: Request, buffers: frozenset[int] = frozenset(),
                 failed: Callable[[int, int, int], None] | None = None) -> type[FeedbackPDU]:
        """The PDU class a twin registers: MBFB frames for ``unit`` run through ``serve`` (one frame, as an FC3
        read or FC16 write), the packet's frames all within one call of ``request`` (one request of the device).
        ``buffers``: the addresses where write frames in a row go to the action as one write (each value appends,
        so that is the same: a buffer takes as many values as fit and refuses the rest, in one frame or in two).
        ``failed``: called with the number of the frame that ended a packet (the device's LAST_ERR_FRAME),
        the exception code and an error detail for LAST_ERR_DETAIL (0: what the refusing register set)."""
        return type("FeedbackPDU", (cls,), {"unit": unit, "serve": staticmethod(serve),
                                            "request": staticmethod(request), "buffers": buffers,
                                            "failed": None if failed is None else staticmethod(failed)})

    def decode(self, data: bytes) -> None:
        """Frames from the bytes after the function code; malformed unless they split exactly."""
        i, n = 0, len(data)
        self.malformed = n + 8 > FEEDBACK_MAX_PACKET or n == 0
        frames, buffers = self.frames, self.buffers
        number = 0
        while i < n and not self.malformed:
            if i + 4 > n or data[i] not in (0, 1):
                self.malformed = True
                break
            kind, address, count = _FRAME_HEAD.unpack_from(data, i)
            i += 4
            number += 1
            words: Any = []
            if kind == 1:
                if i + 2 * count > n:
                    self.malformed = True
                    break
                if address in buffers:  # values appended to a buffer: kept as one array, not 2·n objects
                    words = np.frombuffer(data, ">u2", count, i).astype(np.int64)
                    i += 2 * count
                    prev = frames[-1] if frames else None
                    if prev is not None and prev[1] == 1 and prev[2] == address:  # the same buffer again: one write
                        frames[-1] = (prev[0], 1, address, prev[3] + count, np.concatenate([prev[4], words]))
                        continue
                else:
                    words = list(struct.unpack_from(f">{count}H", data, i))
                    i += 2 * count
            else:
                self.read_registers += count
            frames.append((number, kind, address, count, words))

    def encode(self) -> bytes:
        """The reply: the read frames' data."""
        return self.reply

    def _checked(self) -> ExcCodes | None:
        """The exception that refuses the whole packet before any frame runs (None: it may run)."""
        if self.malformed:
            return self._refused(ExcCodes.ILLEGAL_VALUE, 0)
        if 8 + 2 * self.read_registers > FEEDBACK_MAX_PACKET:
            return self._refused(ExcCodes.ILLEGAL_VALUE, 0, E_RSP_OVERFLOW)  # MBAP 7 + function 1 + the reads
        return None

    def run_frames(self, serve: Callable[..., ExcCodes | None]) -> bytes | ExcCodes:
        """Run the frames in order through a device's ``serve`` (as FC3 reads / FC16 writes; the packet already
        :meth:`_checked`): the read frames' data, or the exception that ended the packet (the frames before it took
        effect)."""
        data = bytearray()
        for number, kind, address, count, words in self.frames:
            if kind == 1:
                rc = serve(16, address, address, count, [], words)
                if rc:
                    return self._refused(rc, number)
            else:
                regs = [0] * count
                rc = serve(3, address, address, count, regs, None)
                if rc:
                    return self._refused(rc, number)
                data += struct.pack(f">{count}H", *regs)
        return bytes(data)

    def run_bound(self) -> bytes | ExcCodes:
        """The packet through the bound device: refused whole, or its frames run as one request."""
        rc = self._checked()
        if rc is not None:
            return rc
        assert self.request is not None and self.serve is not None
        serve = self.serve
        return self.request(lambda: self.run_frames(serve))

    async def run(self, action: Callable[..., Awaitable[ExcCodes | None]]) -> bytes | ExcCodes:
        """Run the frames in order through an asynchronous ``action`` (as FC3 reads / FC16 writes; pymodbus' path
        for a unit no device is bound to): as :meth:`run_frames`."""
        rc = self._checked()
        if rc is not None:
            return rc
        data = bytearray()
        for number, kind, address, count, words in self.frames:
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

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        """Each frame as an FC3 read or FC16 write of the device's registers, in order."""
        if self.serve is not None and device_id == self.unit:
            out = self.run_bound()
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
    def answer(cls, adu: bytes) -> bytes | None:
        """The whole reply ADU to a request ADU that is an MBFB packet for the bound unit (None: not one) — the
        bytes the server would send, made at once without it (:class:`~sim_devices.transport.SocketRelay`
        ``local``)."""
        if cls.serve is None or adu[2:4] != b"\0\0" or adu[6] != cls.unit or adu[7] != FC_FEEDBACK:
            return None
        pdu = cls()
        pdu.decode(adu[8:])
        out = pdu.run_bound()
        if isinstance(out, bytes):
            return adu[:4] + (2 + len(out)).to_bytes(2, "big") + adu[6:8] + out
        return adu[:4] + b"\0\3" + adu[6:7] + bytes([FC_FEEDBACK | 0x80, int(out)])


class T7Server(ModbusTcpServer):
    """pymodbus' TCP server reading whole packets of any MBAP length: its socket framer silently drops a request
    over 264 bytes (the Modbus limit), a T7 takes MBFB packets up to 1040 and the twin answers a longer one."""

    def callback_new_connection(self) -> ServerRequestHandler:
        handler = ServerRequestHandler(
            self, self.trace_packet, self.trace_pdu, self.trace_connect)
        handler.max_buffer_size = 6 + 0xFFFF  # MBAP: 6 header bytes + a 16-bit length
        return handler

