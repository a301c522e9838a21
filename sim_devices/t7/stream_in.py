"""The T7's stream-in engine: scans taken on the scan clock, packed into spontaneous packets on the stream socket.

[E] packet (LabJack's low-level stream example): TransID (0 at each STREAM_ENABLE = 1, +1 per packet), ProtoID 0,
Length, unit 1, function 76, type 16, reserved 0, backlog, status, AddInfo, samples MSB first. [A] Length = 10 + 2·n;
backlog = bytes still buffered after this packet.
[D] actual rate 10 MHz / round(10 MHz / rate), computed when written; [A] at most 100 kS/s (inputs + stream-out
entries), else STREAM_SCAN_RATE_INVALID.
[D] at STREAM_ENABLE: STREAM_RESOLUTION_INDEX > 8 → 2606 (STREAM_CONFIG_INVALID); STREAM_SETTLING_US > 4400 → 2621
(STREAM_SETTLING_INVALID); AIN14 (temperature sensor) in the scan list above 250 scans/s → 2631. [D] settling "does
not apply to the 1st channel in the scan list": [A] the n − 1 settlings of an explicit STREAM_SETTLING_US (≥ 1 µs)
must fit in one scan period, else 2608 (STREAM_SCAN_RATE_INVALID). [D] the resolution index (0: 1) bounds the
sample rate (scan rate × inputs) by the datasheet's stream table, else 2608 ("The scan rate times the number of
channels per scan is too great for this device"), and sets the ADC noise each sample carries (twin's ``noise`` on):
both from :mod:`~sim_devices.t7.resolution`, which says what was found and what was not.
[E] auto-recovery: when more than STREAM_BUFFER_SIZE_BYTES wait unsent (the host does not read), new scans are dropped
and packets carry 2940; when room returns the next packet carries 2941, AddInfo = scans skipped, and starts with one
dummy scan of 0xFFFF.
[E] 2943 (STREAM_AUTO_RECOVER_END_OVERFLOW): during auto-recovery the 16-bit skipped-scan counter overflowed; the
example stops reading ("unknown amount of skipped samples"). [A] it overflows at the 65536th skipped scan; the
packets still buffered leave first, then one last packet with the samples left (usually none), status 2943,
AddInfo 0, and the stream stops (STREAM_ENABLE reads 0; a stop then gets STREAM_NOT_RUNNING); packets kept for a
client not connected yet stay for it. Not simulated: 2942 (STREAM_SCAN_OVERLAP: the twin refuses at the enable the
rates it cannot scan) and 2945 (STREAM_BUFFER_FULL: the buffer filled with auto-recovery disabled, which the twin
does not offer); :meth:`StreamEngine.end_stream` injects any status that ends a stream (fault injection).
[A] burst (STREAM_NUM_SCANS > 0): the rest goes in a last, possibly short packet with status 2944, then the stream
stops; on STREAM_ENABLE = 0 the whole packets filled by then are sent and a partial packet is discarded.
[L] command-response stream (STREAM_AUTO_TARGET ≠ 1: 2612), output-only streams and a STREAM_OUT# twice in one scan
list (2607) are not simulated.
"""

from __future__ import annotations

import asyncio
import math
import struct
from collections import deque

import numpy as np

from sim_devices.t7 import resolution
from sim_devices.t7.analog import AIN_GROUND, AIN_TEMPERATURE, RANGE_GAIN
from sim_devices.t7.registers import (
    E_ACTIVE,
    E_BUFSIZE,
    E_CHN_LIST,
    E_DTYPE,
    E_NO_CHN,
    E_RATE,
    E_RES_INDEX,
    E_SETTLING,
    E_SPP,
    E_TARGET,
    E_TEMP_RATE,
    MAX_SETTLING_US,
    MAX_STREAM_RES_INDEX,
    MAX_TEMP_SCAN_HZ,
    N_AIN_ALL,
    R_BUFSIZE,
    R_DTYPE,
    R_NADDR,
    R_NSCANS,
    R_O_SCAN,
    R_RES,
    R_SETTLE,
    R_SPP,
    R_TARGET,
    S_BURST,
    S_RECOVER,
    S_RECOVER_END,
    S_RECOVER_OVERFLOW,
    SKIPPED_MAX,
    UNIT,
)
from sim_devices.t7.stream_out import StreamOut

MAX_SAMPLE_RATE = 100_000.0
STREAM_FUNCTION, STREAM_TYPE = 76, 16  # [E] a stream packet's function and type bytes
HEADER_WORDS = 8  # [E] a stream packet's header: 16 bytes


class StreamEngine(StreamOut):
    """Stream-in: scan list, packets, backlog and auto-recovery, on top of the stream-out channels."""

    ain_range: list[float]

    def _init_stream_in(self) -> None:
        self.tid = 0
        self.produced = 0  # scans taken
        self.fifo = np.zeros(0, np.uint16)  # samples waiting for a packet
        self.skipped = 0
        self.recovering = False
        self.packets_sent = 0
        self.scans_skipped_total = 0
        self._writer: asyncio.StreamWriter | None = None
        # [A] packets due while no client is connected to the stream port: kept in the device's stream buffer
        # (it streams spontaneously to the connected client) and sent when one connects; counted as unsent, so
        # auto-recovery starts when they exceed STREAM_BUFFER_SIZE_BYTES as for a client that does not read
        self._held: list[bytes] = []
        self._next_packet_t = math.inf  # rig time at which the next whole stream packet is due
        self._pumped_at: float | None = None  # rig time of the last pump (None: a request came since)
        self._worked_at = -math.inf  # rig time of the last pump of a running stream (on demand: the step's start)
        self._ins: list[int] = []  # the running stream's analog inputs (_start_stream)

    def _in_addresses(self) -> list[int]:
        """The scan list's analog inputs (AIN addresses), in scan order (while streaming, the running stream's: its
        scan list cannot change then)."""
        if self.streaming:
            return self._ins
        return [a for a in self.scanlist[:int(self.regs[R_NADDR])] if a < 2 * N_AIN_ALL]

    def pump(self) -> None:
        """Take the scans due by now, play stream-out, send whole packets (called every ``poll`` s, and on a virtual
        clock also as soon as a whole packet is due: :meth:`_on_clock`; on demand when the host waits)."""
        with self.plant.lock, self.lock:  # plant first (see ``action``)
            if not self.streaming:
                return
            now = self.clock.now()
            if now == self._pumped_at:  # pumped at this very time, no request since: nothing new is due (a virtual
                return  # clock that has not moved between polls)
            self._catch_up(now)
            if self.streaming:  # (not a stream the catch-up found ended: :meth:`_end` sent its last packet)
                self._send(final=self._burst_ended())
            self._next_packet_t = self._packet_due()
            self._pumped_at = self._worked_at = now

    def _burst_ended(self) -> bool:
        """Whether a burst (STREAM_NUM_SCANS > 0) has taken its last scan."""
        nscans = int(self.regs[R_NSCANS])
        return bool(nscans) and self.produced >= nscans

    def _play_out(self, now: float) -> None:
        """Play every stream-out up to ``now``."""
        for k in self._out_indices():
            self._advance_out(k, now)

    def _catch_up(self, now: float) -> None:
        """Play stream-out and take the scans due by ``now`` (a burst's: up to its last)."""
        self._play_out(now)
        due = self._cur_scan(now) + 1
        nscans = int(self.regs[R_NSCANS])
        if nscans:
            due = min(due, nscans)
        if due > self.produced:
            self._take_scans(due)

    def _packet_due(self) -> float:
        """Rig time of the scan that completes the next whole packet, or a burst's last scan if that comes first
        (its short last packet leaves then); inf when not streaming."""
        if not self.streaming or not self._ins:
            return math.inf
        n_in = len(self._ins)
        missing = max(int(self.regs[R_SPP]) - self.fifo.size, 1)
        scans = -(-missing // n_in)  # scan k is taken at t_enable + (k + 1) / rate
        nscans = int(self.regs[R_NSCANS])
        k = min(self.produced + scans, nscans) if nscans else self.produced + scans
        # the instant the k-th scan counts as taken, with :meth:`_cur_scan`'s tolerance of a millionth of a scan: a
        # clock a rounding short of t_enable + k / rate takes the scan there, so the packet is due there too — else
        # a host waiting on demand for the packet its own count (the same tolerance) says is due waited out its
        # timeout, the twin never woken (a second Ctrl-C's settle stream: 30 s of wall time in virtual time)
        return self.t_enable + (k - 1e-6) / self.rate


    def _take_scans(self, due: int) -> None:
        ks = np.arange(self.produced + 1, due + 1)  # k + 1 for the scans k due: scan k at t_enable + (k + 1) / rate
        times = self.t_enable + ks / self.rate
        ains = [a // 2 for a in self._in_addresses()]
        wired = {sig.observable for a in ains if (sig := self.signals.get(a)) is not None
                 and a not in (AIN_TEMPERATURE, AIN_GROUND)}  # the observables the inputs read, no others
        obs = self._observe(times, wired)
        index = resolution.stream_index(self.regs[R_RES])
        adc_rms = [resolution.noise_rms(self.ain_range[a], index) for a in ains]
        gains = [RANGE_GAIN[self.ain_range[a]] for a in ains]
        data = self._ain_scan_block(ains, obs, ks.size, adc_rms, gains)  # the wired inputs' usual block: one pass
        if data is None:
            cols = np.empty((len(ains), ks.size), np.uint16)  # one row per input, then interleaved in scan order
            for j, a in enumerate(ains):
                self._ain_stream_codes(a, obs, ks.size, adc_rms[j], j, gains[j], cols[j])
            data = cols.T.reshape(-1)
        self.produced = due
        unsent = self._unsent_bytes()  # the host does not read: the device buffer fills
        cap = int(self.regs[R_BUFSIZE]) or 4096
        if self.recovering or unsent > cap:
            if self.recovering and unsent < cap // 2:
                self.recovering = False
                dummy = np.full(len(ains), 0xFFFF, np.uint16)
                self._send(status=S_RECOVER_END, extra=self.skipped, prefix=dummy)
                self.scans_skipped_total += self.skipped
                self.skipped = 0
                self.fifo = np.concatenate([self.fifo, data])
                return
            self.recovering = True
            self.skipped += ks.size
            if self.skipped > SKIPPED_MAX:  # the counter overflowed: the device ends the stream
                self._end(S_RECOVER_OVERFLOW)
            return
        self.fifo = np.concatenate([self.fifo, data])

    def _unsent_bytes(self) -> int:
        w = self._writer
        if w is None:
            return sum(len(b) for b in self._held)
        return 0 if w.transport is None else int(w.transport.get_write_buffer_size())

    def _packet(self, samples: np.ndarray, status: int, extra: int) -> bytes:
        return self._head(samples.size, min(int(self.fifo.size * 2), 0xFFFF), status, extra) \
            + samples.astype(">u2").tobytes()

    def _head(self, n: int, backlog: int, status: int, extra: int) -> bytes:
        """The header of the next packet, of ``n`` samples, ``backlog`` bytes still buffered after it."""
        head = struct.pack(">HHHBBBBHHH", self.tid & 0xFFFF, 0, 10 + 2 * n, UNIT, STREAM_FUNCTION, STREAM_TYPE, 0,
                           backlog, status, extra)
        self.tid += 1
        return head

    def _send(self, *, final: bool = False, status: int = 0, extra: int = 0,
              prefix: np.ndarray | None = None) -> None:
        spp = int(self.regs[R_SPP])
        w = self._writer
        if prefix is not None:  # the auto-recovery-end packet: dummy scan, then buffered data
            take = max(spp - prefix.size, 0)
            samples, self.fifo = np.concatenate([prefix, self.fifo[:take]]), self.fifo[take:]
            self._write(w, self._packet(samples, status, extra))
            return
        size = self.fifo.size
        whole = size // spp
        count = whole + (final and size > whole * spp)  # a burst's last packet may be short
        if count:  # one socket write for the packets a pump has filled (the bytes a T7 sends, fewer syscalls)
            n = min(size, count * spp)
            short = n - whole * spp if count > whole else 0  # samples of a short last packet (0: none)
            # the whole packets at once: header words ([E] TransID, ProtoID, Length, unit·function, type·reserved,
            # backlog, status, AddInfo) and samples, one row each, big-endian as on the wire
            rows = np.empty((whole, HEADER_WORDS + spp), ">u2")
            i = np.arange(whole)
            rows[:, 0] = (self.tid + i) & 0xFFFF
            rows[:, 1] = 0
            rows[:, 2] = 10 + 2 * spp
            rows[:, 3] = UNIT << 8 | STREAM_FUNCTION
            rows[:, 4] = STREAM_TYPE << 8
            rows[:, 5] = np.minimum(2 * (size - (i + 1) * spp), 0xFFFF)  # bytes still buffered after the packet
            rows[:, 6] = S_RECOVER if self.recovering else 0
            rows[:, 7] = 0
            if final and not short and whole:
                rows[-1, 6] = S_BURST
            rows[:, HEADER_WORDS:] = self.fifo[:whole * spp].reshape(whole, spp)
            self.tid += whole
            data = rows.tobytes()
            if short:
                data += self._head(short, 0, S_BURST, 0) + self.fifo[whole * spp:n].astype(">u2").tobytes()
            self.fifo = self.fifo[n:]
            self._write(w, data, count)
        if final:
            self._stop_stream(self.clock.now())

    def end_stream(self, status: int) -> None:
        """Fault injection: the device ends the running stream now with ``status`` (a stream error that stops it,
        as 2942, 2943 or 2945), the scans due by now sent first (:meth:`_end`)."""
        with self.plant.lock, self.lock:
            if not self.streaming:
                return
            self._catch_up(self.clock.now())
            if self.streaming:  # (the catch-up may have ended it itself)
                self._end(status)

    def _end(self, status: int) -> None:
        """The device ends the stream with ``status``: the whole packets waiting leave, then one last packet with the
        samples left (possibly none) carrying it; packets kept for a client not connected yet stay for it."""
        self._send()
        rest, self.fifo = self.fifo, np.zeros(0, np.uint16)
        self._write(self._writer, self._head(rest.size, 0, status, 0) + rest.astype(">u2").tobytes())
        self._stop_stream(self.clock.now(), keep_held=True)

    def _write(self, w: asyncio.StreamWriter | None, data: bytes, packets: int = 1) -> None:
        self.packets_sent += packets
        if w is not None and not w.is_closing():
            w.write(data)
        elif w is None and self.streaming:
            self._held.append(data)

    def _start_stream(self) -> int:
        n = int(self.regs[R_NADDR])
        if self.streaming:
            return E_ACTIVE
        self._filter_y = None  # the filter starts from the amplifier input in force
        if n < 1:
            return E_NO_CHN
        entries = self.scanlist[:n]
        outs = [a - R_O_SCAN for a in entries if R_O_SCAN <= a < R_O_SCAN + 4]
        for a in entries:
            if not ((a < 2 * N_AIN_ALL and a % 2 == 0) or R_O_SCAN <= a < R_O_SCAN + 4):
                return E_CHN_LIST
        if len(outs) != len(set(outs)) or any(not self.outs[k].enable for k in outs) or len(outs) == n:
            return E_CHN_LIST
        if self.rate * n > MAX_SAMPLE_RATE or self.rate <= 0:
            return E_RATE
        if self.regs[R_RES] > MAX_STREAM_RES_INDEX:
            return E_RES_INDEX
        ins = [a // 2 for a in entries if a < 2 * N_AIN_ALL]
        table = resolution.max_sample_rate([self.ain_range[i] for i in ins], resolution.stream_index(self.regs[R_RES]))
        if ins and table is not None and self.rate * len(ins) > table * (1 + 1e-9):
            return E_RATE
        settle = self.regs[R_SETTLE]  # [D] below 1: automatic
        if settle > MAX_SETTLING_US:
            return E_SETTLING
        if settle >= 1 and (n - 1) * settle * 1e-6 * self.rate >= 1:  # the settlings between a scan's channels
            return E_RATE
        if 2 * AIN_TEMPERATURE in entries and self.rate > MAX_TEMP_SCAN_HZ:
            return E_TEMP_RATE
        if self.regs[R_TARGET] != 1:
            return E_TARGET
        if self.regs[R_DTYPE] != 0:
            return E_DTYPE
        spp = int(self.regs[R_SPP])
        if not 1 <= spp <= 512:
            return E_SPP
        size = int(self.regs[R_BUFSIZE])
        if size and (size & (size - 1) or size > 32768):
            return E_BUFSIZE
        now = self.clock.now()
        self._streamed, self._ins = outs, [a for a in entries if a < 2 * N_AIN_ALL]
        self.t_enable, self.streaming, self.tid, self.produced = now, True, 0, 0
        self._held = []  # a stream the device ended may have left packets no client took: not this stream's
        self.fifo = np.zeros(0, np.uint16)
        self.recovering, self.skipped = False, 0
        for k in outs:
            o = self.outs[k]
            o.next_scan, o.sched, o.loop_pos, o.anchor, o.loop_until = 0, deque(), 0, 0, 0
            o.loop_active = False
            codes, o.queue = np.array(o.queue, np.int64), deque()
            self._schedule(k, codes, now)
            self._advance_out(k, now)  # a loop's repetitions queued at once: they follow the data without a gap
        self._next_packet_t = self._packet_due()
        self._worked_at = now
        self.plant.stream_started(now + 1.0 / self.rate)  # scan 0, one scan period after the enable
        return 0

    def _stop_stream(self, now: float, keep_held: bool = False) -> None:
        if not keep_held:
            self._held = []
        cur = self._cur_scan(now)
        for k in self._out_indices():
            self._advance_out(k, now)
            o = self.outs[k]
            unplayed = [int(c) for p in o.sched if not p.loop for c in p.codes[max(cur + 1 - p.first, 0):]]
            o.queue.extendleft(reversed(unplayed))
            o.sched, o.loop_until = deque(), 0
        self.streaming = False
        self._next_packet_t = math.inf
        self._undrive_after(now)

