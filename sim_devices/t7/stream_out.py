"""The T7's stream-out: four channels, each a buffer of codes played one per scan on its target DAC.

[D] one buffer value per scan, written to the target when the scan runs; after the data the last LOOP_NUM_VALUES
values repeat (register map, ljm_constants.json: STREAM_OUT#_LOOP_NUM_VALUES "the number of values, from the end of
the array, that will be repeated after reaching the end of supplied data array"; T-Series Datasheet §3.2.1
Stream-Out: "the buffer can be read ... in a looping mode to generate a periodic waveform"). [D] SET_LOOP "controls
when new data and loop size are used. 1 = use new data immediately" (register map), and LabJack's stream-out update
example: once values and SET_LOOP are written, "that set of values will continue to be output in order and will not
be interrupted until their loop is complete. Only once that set of values have been output in their entirety will
the next set of values that have been set using STREAM_OUT#_SET_LOOP start being used." So, while a loop repeats,
data written waits; at SET_LOOP it plays from the end of the repetition in progress (the end of the data if the
loop has not started repeating), and the new LOOP_NUM_VALUES applies after it.
[A] (the datasheet is silent; chosen to be checked on a real T7): LOOP_NUM_VALUES 0 or 1: the output holds;
LOOP_NUM_VALUES larger than the values written since the buffer was allocated: all of those repeat;
SET_LOOP 2/3 act as 1; BUFFER_STATUS = bytes not yet played, the loop's values counted while it repeats;
BUFFER_ALLOCATE_NUM_BYTES empties the buffer and forgets the loop (the stream-out is reconfigured); a watchdog
timeout with a DAC action stops a repeating loop (the DAC takes the watchdog's value, the loop does not overwrite
it) — the safe reading: the T7's watchdog is the lost-host bound of a looped drive. [L] a command-response write to
a DAC that stream-out drives changes its register but not the plant.
"""

from __future__ import annotations

import math
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
from sim_devices.t7.watchdog import Watchdog


@dataclass
class Played:
    """Codes scheduled from scan ``first`` on: data, or a loop's repetitions; ``y``: the reconstruction filter's
    output after each (None without a filter), to restart it where a loop is cut."""

    first: int
    codes: np.ndarray
    loop: bool = False
    y: np.ndarray | None = None


class Tail:
    """The last ``size`` values written to a stream-out buffer, for SET_LOOP's LOOP_NUM_VALUES (a ring of codes: a
    packet's values go in as one array copy, not one Python integer each)."""

    def __init__(self, size: int = 0) -> None:
        self.size = size
        self._ring = np.zeros(max(size, 1), np.int64)
        self._count = 0  # values written since the buffer was allocated

    def __len__(self) -> int:
        return min(self._count, self.size)

    def extend(self, values: np.ndarray) -> None:
        """Append ``values`` (the oldest fall out)."""
        start = self._count % max(self.size, 1)
        if values.size <= self.size - start:  # they fit before the ring's end (a packet, mostly): one copy
            self._ring[start:start + values.size] = values
            self._count += values.size
            return
        v = values[values.size - min(values.size, self.size):]
        start = (self._count + values.size - v.size) % max(self.size, 1)  # ring index of v[0]
        first = min(v.size, self.size - start)
        self._ring[start:start + first] = v[:first]
        self._ring[:v.size - first] = v[first:]
        self._count += values.size

    def last(self, n: int) -> np.ndarray:
        """The last ``n`` values written, oldest first (fewer if fewer are kept)."""
        n = min(n, len(self))
        return self._ring[(self._count - n + np.arange(n)) % max(self.size, 1)]


@dataclass
class OutChannel:
    """One stream-out channel."""

    target: int = 0
    alloc: int = 0
    enable: int = 0
    loop_num: int = 0
    queue: deque[int] = field(default_factory=deque)  # codes written, not yet scheduled (stopped, or waiting on a loop)
    sched: deque[Played] = field(default_factory=deque)  # codes scheduled, not yet played
    tail: Tail = field(default_factory=Tail)  # last values written (for the loop)
    loop: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    loop_pos: int = 0
    next_scan: int = 0
    loop_until: int = 0  # the scan after the last loop repetition scheduled (none left to play once it is reached)
    code: int = 0  # last code played
    y: float | None = None  # the reconstruction filter's output after it (None without a filter)
    underrun_scans: int = 0
    loop_active: bool = False  # the loop repeats (the data ran out)
    anchor: int = 0  # scan of the loop's first repetition
    buffer_writes: int = 0  # write frames (MBFB or FC16) to the buffer register: what a host sent
    values_written: int = 0  # values those frames carried
    loops_set: int = 0  # SET_LOOP writes that set a loop of more than one value (a repeating waveform)



class StreamOut(PlantCoupling):
    """Stream-out channels: their registers, buffers and the codes they schedule on the amplifier input."""

    regs: dict[int, float]
    watchdog: Watchdog
    dac_volts: list[float]
    scanlist: list[int]
    last_err: int

    def _init_stream_out(self) -> None:
        self.outs = [OutChannel() for _ in range(4)]
        self.heard = self.clock.now()  # rig time of the last request (the watchdog counts from it)
        self._streamed: list[int] = []  # the stream-outs in the scan list of the running stream (_start_stream)

    def _fail(self, code: int) -> ExcCodes:
        """Refuse with Modbus exception 4, the LabJack error code in LAST_ERR_DETAIL."""
        self.last_err = code
        return ExcCodes.DEVICE_FAILURE

    def _out_indices(self) -> list[int]:
        """The stream-outs in the scan list, in its order (while streaming, those of the running stream: its scan
        list cannot change then — a write to it is refused, STREAM_IS_ACTIVE)."""
        if self.streaming:
            return self._streamed
        n = int(self.regs[R_NADDR])
        return [a - R_O_SCAN for a in self.scanlist[:n] if R_O_SCAN <= a < R_O_SCAN + 4]

    def _schedule(self, k: int, codes: np.ndarray, now: float, loop: bool = False) -> None:
        """Give stream-out ``k`` these codes at its next scans (after an underrun: from the next scan on)."""
        if not codes.size:
            return
        o = self.outs[k]
        start = max(o.next_scan, self._cur_scan(now) + 1)
        if start > o.next_scan and not o.loop_active:
            o.underrun_scans += start - o.next_scan
        y = self._drive(start, codes) if o.target == R_DAC + 2 * self.dac else None
        o.sched.append(Played(start, codes, loop, y))
        o.next_scan = start + codes.size
        if loop:
            o.loop_until = o.next_scan

    def _level(self, k: int, now: float) -> int:
        o = self.outs[k]
        if not self.streaming:
            return len(o.queue)
        cur = self._cur_scan(now)
        data = 0
        for p in o.sched:  # the data scheduled and not played yet (a loop's repetitions are not values written)
            if not p.loop:
                size = p.codes.size
                left = p.first + size - 1 - cur
                if left > 0:
                    data += left if left < size else size
        return data + len(o.queue) + (o.loop.size if o.loop_active and o.loop.size > 1 else 0)


    def _advance_out(self, k: int, now: float) -> None:
        o = self.outs[k]
        cur = self._cur_scan(now)
        while o.sched and o.sched[0].first <= cur:  # the codes played by now; the last one is the output
            p = o.sched[0]
            played = min(cur - p.first + 1, p.codes.size)
            o.code = int(p.codes[played - 1])
            o.y = None if p.y is None else float(p.y[played - 1])
            if played < p.codes.size:
                o.sched[0] = Played(p.first + played, p.codes[played:], p.loop,
                                    None if p.y is None else p.y[played:])
                break
            o.sched.popleft()
        if o.target in (R_DAC, R_DAC + 2):
            self.dac_volts[(o.target - R_DAC) // 2] = self._code_volts(o.code, (o.target - R_DAC) // 2)
        if o.loop.size > 1 and o.next_scan <= cur + int(self.rate):  # periodic loop: keep 1–2 s queued
            end = cur + 2 * int(self.rate)
            act = self.watchdog.action(self.dac) if o.target == R_DAC + 2 * self.dac else None
            if act is not None:  # [A] the watchdog's timeout stops the loop: nothing queued past it
                deadline = self.heard + act[0]
                if deadline <= now:
                    o.loop, o.loop_active = np.zeros(0, np.int64), False
                    return
                end = min(end, math.ceil((deadline - self.t_enable) * self.rate) - 1)  # scans played before it
            if not o.loop_active:
                o.loop_active, o.anchor = True, max(o.next_scan, cur + 1)
            elif o.next_scan <= cur:  # not pumped for longer than was queued: the device repeated on regardless
                o.loop_pos = (o.loop_pos + cur + 1 - o.next_scan) % o.loop.size
                o.next_scan, o.y = cur + 1, None  # the filter restarts from the code playing now
                o.code = int(o.loop[(o.loop_pos - 1) % o.loop.size])
                if o.target in (R_DAC, R_DAC + 2):
                    self.dac_volts[(o.target - R_DAC) // 2] = self._code_volts(o.code, (o.target - R_DAC) // 2)
            n = end - o.next_scan
            if n > 0:
                codes = o.loop[(o.loop_pos + np.arange(n)) % o.loop.size]
                o.loop_pos = (o.loop_pos + n) % o.loop.size
                self._schedule(k, codes, now, loop=True)

    def _cut_loop(self, k: int, now: float) -> None:
        """SET_LOOP while a loop repeats: drop its repetitions after the one in progress (LabJack: a loop is not
        interrupted until it is complete); the data waiting in the queue plays from there."""
        o = self.outs[k]
        cur = self._cur_scan(now)
        size = o.loop.size
        b = o.anchor if cur < o.anchor else o.anchor + size * ((cur - o.anchor) // size + 1)
        kept: deque[Played] = deque()
        y_end = o.y  # the filter's state after scan b − 1: the last code played, or the last one kept below
        for p in o.sched:
            if p.first >= b:
                break
            n = min(p.codes.size, b - p.first)
            kept.append(Played(p.first, p.codes[:n], p.loop, None if p.y is None else p.y[:n]))
            if p.y is not None and n:
                y_end = float(p.y[n - 1])
        o.sched, o.next_scan = kept, b
        if o.target == R_DAC + 2 * self.dac:
            self._undrive_after(self.t_enable + b / self.rate)  # scan b − 1 plays at t_enable + b / rate
            if y_end is not None:
                self._filter_y = y_end
        o.loop_active, o.loop_pos = False, 0
        codes, o.queue = np.array(o.queue, np.int64), deque()
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
            o.alloc, o.queue, o.tail = value, deque(), Tail(value // 2 - 1)
            o.loop, o.loop_active = np.zeros(0, np.int64), False
        elif base == R_O_ENABLE:
            o.enable = int(bool(value))
        elif not o.enable:
            return self._fail(E_OUT_DISABLED)
        elif base == R_O_LOOP:
            if value > max(o.alloc // 2 - 1, 0):
                return self._fail(E_LOOP_BIG)
            o.loop_num = value
        elif base == R_O_SETLOOP:
            if self.streaming and o.loop_active and k in self._out_indices():
                self._advance_out(k, now)
                if o.loop_active:  # still repeating (a watchdog timeout stops it)
                    self._cut_loop(k, now)
            o.loop = o.tail.last(o.loop_num) if o.loop_num else np.zeros(0, np.int64)
            o.loop_pos = 0
            o.loops_set += o.loop.size > 1
            if self.streaming and k in self._out_indices():
                self._advance_out(k, now)  # repetitions queued at once: they follow the data without a gap
        else:
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    def _buffer(self, k: int, codes: list[int] | np.ndarray, now: float) -> ExcCodes | None:
        """Append ``codes`` (a list, or an integer array from an MBFB frame) to stream-out ``k``'s buffer."""
        o = self.outs[k]
        if not o.alloc:
            return self._fail(E_OUT_DNE)
        if not o.enable:
            return self._fail(E_OUT_DISABLED)
        if self.streaming and o.loop.size <= 1 and k in self._streamed:  # the usual packet: one step
            return self._append(k, codes, now)
        room = o.alloc // 2 - 1 - self._level(k, now)
        take = np.asarray(codes[:max(room, 0)], np.int64)  # a frame's array as it is (no copy), a list converted
        o.tail.extend(take)
        o.buffer_writes += 1
        o.values_written += len(take)
        played = self.streaming and k in self._out_indices()
        if played and o.loop_active and o.loop.size > 1:
            self._advance_out(k, now)
            o.queue.extend(take.tolist())  # waits for SET_LOOP: the loop in progress is not interrupted
        elif played:
            self._advance_out(k, now)
            self._schedule(k, take, now)
        else:
            o.queue.extend(take.tolist())  # the queue holds ints
        return self._fail(E_OUT_FULL) if len(take) < len(codes) else None

    def _append(self, k: int, codes: list[int] | np.ndarray, now: float) -> ExcCodes | None:
        """:meth:`_buffer` while stream-out ``k`` plays in a running stream and no loop of more than one value is
        set (nothing waits for a SET_LOOP): what the device has played by ``now`` is played, the values that fit
        are kept for the loop and scheduled on the next scans, in one pass — the same codes, times and counts as
        the general path (``_level`` after ``_advance_out``: every value still scheduled is after the scan now)."""
        o = self.outs[k]
        self._advance_out(k, now)
        # the data waiting, as BUFFER_STATUS counts it: counting the scans up to next_scan instead took the empty
        # scans a cut loop leaves before its repetition's end for data, and refused writes as full (found in review)
        cur = self._cur_scan(now)
        level = self._level(k, now)
        room = o.alloc // 2 - 1 - level
        take = np.asarray(codes[:max(room, 0)], np.int64)  # a frame's array as it is (no copy), a list converted
        o.tail.extend(take)
        o.buffer_writes += 1
        o.values_written += take.size
        if take.size:
            start = max(o.next_scan, cur + 1)
            if start > o.next_scan and not o.loop_active:
                o.underrun_scans += start - o.next_scan
            y = self._drive(start, take) if o.target == R_DAC + 2 * self.dac else None
            o.sched.append(Played(start, take, False, y))
            o.next_scan = start + take.size
        return self._fail(E_OUT_FULL) if take.size < len(codes) else None
