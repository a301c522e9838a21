"""The T7's stream-out: four channels, each a buffer of codes played one per scan on its target DAC.

[D] one buffer value per scan, written to the target when the scan runs; after the data the last LOOP_NUM_VALUES
values repeat. [A] 0 or 1: the output holds; data written while it loops plays after the repetitions already queued
(1 s ahead); SET_LOOP 2/3 act as 1; BUFFER_STATUS = bytes not yet played. [L] a command-response write to a DAC that
stream-out drives changes its register but not the plant.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from pymodbus.constants import ExcCodes

from sim_devices.t7.coupling import PlantCoupling
from sim_devices.t7.registers import (
    E_BUFSIZE,
    E_LOOP_BIG,
    E_OUT_DISABLED,
    E_OUT_DNE,
    E_OUT_FULL,
    E_OUT_TARGET,
    R_DAC,
    R_NADDR,
    R_O_ALLOC,
    R_O_ENABLE,
    R_O_LOOP,
    R_O_SCAN,
    R_O_SETLOOP,
    R_O_TARGET,
)


@dataclass
class OutChannel:
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



class StreamOut(PlantCoupling):
    """Stream-out channels: their registers, buffers and the codes they schedule on the amplifier input."""

    regs: dict[int, float]
    dac_volts: list[float]
    scanlist: list[int]
    last_err: int

    def _init_stream_out(self) -> None:
        self.outs = [OutChannel() for _ in range(4)]

    def _fail(self, code: int) -> ExcCodes:
        """Refuse with Modbus exception 4, the LabJack error code in LAST_ERR_DETAIL."""
        self.last_err = code
        return ExcCodes.DEVICE_FAILURE

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
