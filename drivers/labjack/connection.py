"""T7 command-response: the Modbus TCP link, register reads and writes (plain and Modbus Feedback), the
calibration read from flash, single analog inputs. The base of :class:`drivers.labjack.LabJackT7`, which holds
the driver's state."""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
from pymodbus.pdu import ModbusPDU

from drivers.cancel import CancelToken
from drivers.deadline import WALL, ReplyTimer
from drivers.errors import ImplausibleValueError, InstrumentStateError, ProtocolError
from drivers.interfaces import ClockFn, Reading, SleepFn
from drivers.labjack.calibration import Calibration
from drivers.labjack.plan import StreamState
from drivers.labjack.registers import (
    AIN0,
    AIN_NEG0,
    AIN_RANGE0,
    AIN_SPAN,
    CAL_FLASH_ADDRESS,
    CAL_READ_REGS,
    CR_PORT,
    ERRORS,
    FLASH_POINTER,
    FLASH_READ,
    LAST_ERR_DETAIL,
    LAST_ERR_FRAME,
    RANGES,
    SINGLE_ENDED,
    STREAM_PORT,
    UNIT,
    Feedback,
    Frame,
    Words,
    f32_words,
    feedback_packets,
    frame_name,
    frames_summary,
    read_count,
    u32_words,
    words_f32,
    words_u32,
)
from drivers.modbus_link import ModbusLink

_T = TypeVar("_T")


class T7Connection:
    """One LabJack T7 over Ethernet, command-response on ``port`` (the stream's port is opened by
    :mod:`drivers.labjack.stream_in`)."""

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
        self._stream: StreamState | None = None
        self.streaming = False
        self.stop_unconfirmed = False  # a stream stop unanswered (or garbled): the device may still be streaming,
        # its stream-out playing over any DAC write of the host's; cleared by the next answered stop or enable
        self.answered_at = -math.inf  # rig time at which the last request the T7 answered was sent (its watchdog
        # counts from the request it last received)

    # ------------------------------------------------------------------ command-response
    def _lj(self, what: str, fn: Callable[..., _T], *args: object, packet: Sequence[Frame] = ()) -> _T:
        """Run one link call; a Modbus exception is re-raised with the device's LAST_ERR_DETAIL name. For an MBFB
        ``packet`` the message names the frame LAST_ERR_FRAME gives ([A] numbered from 1), or lists the packet's
        frames where that number is none of them or the error registers cannot be read."""
        try:
            sent = self.clock()
            result = fn(UNIT, *args)
            self.answered_at = sent
            return result
        except InstrumentStateError as exc:
            try:  # LAST_ERR_DETAIL, LAST_MB_ERR, LAST_ERR_FRAME in one request
                code, _, frame = self.link.read_holding(UNIT, LAST_ERR_DETAIL, LAST_ERR_FRAME - LAST_ERR_DETAIL + 1)
            except Exception:  # the first error is the one to report
                if not packet:
                    raise exc from None
                raise InstrumentStateError(self.name, f"feedback of {len(packet)} frames ({frames_summary(packet)})"
                                           f" refused: {exc.detail}") from None
            if packet:
                what = (f"feedback frame {frame} of {len(packet)} ({frame_name(packet[frame - 1])})"
                        if 1 <= frame <= len(packet) else
                        f"feedback of {len(packet)} frames ({frames_summary(packet)}; LAST_ERR_FRAME {frame})")
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
        self.feedback(writes, retry=False)

    def feedback(self, frames: Sequence[Frame], *, retry: bool = True, always_send: bool = False) -> list[list[int]]:
        """Reads and writes in order, in as few Modbus Feedback packets as hold them ([D] MBFB: the frames of a
        packet run in order, the reply carries the reads' data): one round trip where each register alone would
        take one. Returns the registers of each read frame, in order. ``retry``: a packet whose reply was lost is
        sent again (only for frames that may take effect twice: not a stream-out buffer's). ``always_send``: each
        packet's first attempt goes out even after a stop request (a command that makes the rig safe:
        :meth:`~drivers.modbus_link.ModbusLink.write_register`)."""
        out: list[list[int]] = []

        def execute(unit: int, pdu: Feedback) -> ModbusPDU:
            return self.link.execute(unit, pdu, retry=retry, always_send=always_send)

        for packet in feedback_packets(frames):
            counts = [n for f in packet if (n := read_count(f)) is not None]
            what = f"feedback of {len(packet)} frames at {packet[0][0]}"
            reply = self._lj(what, execute, Feedback(packet), packet=packet)
            data = getattr(reply, "data", b"")
            if len(data) != 2 * sum(counts):
                raise ProtocolError(self.name, f"{what}: {len(data)} bytes of read data, {2 * sum(counts)} expected")
            if not counts:  # a write-only packet (the stream-out's): no read data
                continue
            words = struct.unpack(f">{len(data) // 2}H", data)
            k = 0
            for n in counts:
                out.append(list(words[k:k + n]))
                k += n
        return out

    def read_f32(self, address: int) -> float:
        """One FLOAT32 register pair (an MBFB read: the T7's own command-response packet)."""
        return words_f32(self.feedback([(address, 2)])[0])

    def read_u32(self, address: int) -> int:
        """One UINT32 register pair (an MBFB read)."""
        return words_u32(self.feedback([(address, 2)])[0])

    def write_f32(self, address: int, value: float) -> None:
        """Write one FLOAT32 (an MBFB write)."""
        self.feedback([(address, f32_words(value))])

    def write_u32(self, address: int, value: int) -> None:
        """Write one UINT32 (an MBFB write)."""
        self.feedback([(address, u32_words(value))])

    def read_calibration(self) -> Calibration:
        """Read the 41 calibration constants from flash (as LabJack's example does: pointer, then a read, four times;
        here the eight in order in one MBFB packet)."""
        frames: list[Frame] = []
        for i, n in enumerate(CAL_READ_REGS):
            frames += [(FLASH_POINTER, u32_words(CAL_FLASH_ADDRESS + i * 13 * 4)), (FLASH_READ, n)]
        values = [words_f32(w[j:j + 2]) for w in self.feedback(frames) for j in range(0, len(w), 2)]
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

    # ------------------------------------------------------------------ single inputs
    def configure_ain(self, ain: int, range_volts: float = 10.0, negative_channel: int = SINGLE_ENDED) -> None:
        """Range (±10/1/0.1/0.01 V) and negative channel (199: single-ended) of one input."""
        self.feedback(self._ain_frames(ain, range_volts, negative_channel))
        self._ain_range[ain] = range_volts

    def _ain_frames(self, ain: int, range_volts: float, negative_channel: int = SINGLE_ENDED) -> list[Frame]:
        """The writes that configure one input (refused, nothing sent, for a range the T7 does not have)."""
        if range_volts not in RANGES:
            raise ValueError(f"{self.name}: AIN range must be one of {RANGES} V, got {range_volts}")
        return [(AIN_RANGE0 + 2 * ain, f32_words(range_volts)), (AIN_NEG0 + ain, [negative_channel])]

    def read_ain(self, ain: int) -> Reading:
        """One command-response reading of AIN ``ain`` [V].

        A value that is not finite or lies beyond 1.1 × the input's range (±11 V on the ±10 V range, the
        default of an input this driver has not configured) is no reading the converter makes (:data:`AIN_SPAN`):
        status "invalid", value NaN — one bad sample, not a broken link."""
        v = words_f32(self.read_regs(AIN0 + 2 * ain, 2))  # FC3
        limit = AIN_SPAN * self._ain_range.get(ain, RANGES[0])
        if not abs(v) <= limit:
            return Reading(math.nan, "V", self.clock(), "invalid")
        return Reading(v, "V", self.clock())
