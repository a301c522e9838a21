"""The T7's hardware-timed stream: arm (inputs, scan list, stream-out preloaded), kickoff, collect the
spontaneous packets from the stream port as numbered scans, complete, stop ([D] §3.2, [E] the packet stream)."""

from __future__ import annotations

import math
import select
import socket

import numpy as np

from drivers.cancel import check
from drivers.errors import (
    InstrumentConnectionError,
    InstrumentError,
    InstrumentStateError,
    InstrumentTimeoutError,
    ProtocolError,
    StreamEndedError,
)
from drivers.interfaces import StreamBlock, StreamSpec
from drivers.labjack.packets import StreamBatch, parse_stream_batch, split_stream_packets
from drivers.labjack.plan import StreamPlan, StreamState
from drivers.labjack.registers import (
    AIN0,
    AUTO_TARGET,
    CLOCK_SOURCE,
    DAC0,
    DUMMY,
    ERRORS,
    MAX_OUT_BUFFER_BYTES,
    MAX_SAMPLES_PER_PACKET,
    MAX_SCANLIST,
    MAX_STREAM_BUFFER_BYTES,
    OUT_ALLOC0,
    OUT_ENABLE0,
    OUT_LOOP0,
    OUT_PACKET_VALUES,
    OUT_SCAN0,
    OUT_TARGET0,
    RANGES,
    SCANLIST0,
    SCANRATE,
    ST_BUFFER_FULL,
    ST_BURST_COMPLETE,
    ST_RECOVER_END,
    ST_RECOVER_OVERFLOW,
    ST_SCAN_OVERLAP,
    STREAM_ENABLE,
    TARGET_SPONTANEOUS,
    Frame,
    f32_words,
    u32_words,
    words_f32,
)
from drivers.labjack.stream_out import T7StreamOut

STOP_DRAIN_S = 0.05  # a stop waits at most this long for the packets filled before it was sent
# the statuses after which the device sends no more packets
_ENDING = (ST_BURST_COMPLETE, ST_BUFFER_FULL, ST_SCAN_OVERLAP, ST_RECOVER_OVERFLOW)


class T7Stream(T7StreamOut):
    """The stream's life: arm, kickoff, collect, complete, stop (the stream-out it plays: :class:`T7StreamOut`)."""

    def arm(self, spec: StreamSpec) -> StreamPlan:
        """Configure inputs, stream registers, scan list and stream-out; preload the out buffer.

        Nothing runs until :meth:`kickoff`. Refuses (nothing sent) what the T7 cannot do.
        """
        if self.streaming:
            raise InstrumentStateError(self.name, "arm while streaming: stop first")
        n_in = len(spec.inputs)
        out = spec.output
        if n_in < 1:
            raise ValueError(f"{self.name}: a stream needs at least one input")
        n_addr = n_in + (out is not None)
        if n_addr > MAX_SCANLIST:
            raise ValueError(f"{self.name}: scan list of {n_addr} addresses, at most {MAX_SCANLIST}")
        if not spec.scan_rate > 152.588:
            raise ValueError(f"{self.name}: scan rates ≤ 152.588 Hz are not supported by this driver")
        spp = spec.samples_per_packet or (MAX_SAMPLES_PER_PACKET // n_in) * n_in
        if not 1 <= spp <= MAX_SAMPLES_PER_PACKET:
            raise ValueError(f"{self.name}: samples_per_packet must be 1…{MAX_SAMPLES_PER_PACKET}")
        codes = volts = None
        capacity = 0
        if out is not None:
            v = self._checked_out(out.volts, out.dac)
            if not 1 <= out.hold <= v.size:
                raise ValueError(f"{self.name}: hold must be 1…{v.size} values")
            if spec.out_loops and spec.out_ahead_s > 0 and self.watchdog_s is None:
                raise ValueError(f"{self.name}: stream-out loops need the T7's watchdog (watchdog_s): a loop that "
                                 "outlives a lost host plays on until the watchdog stops it")
            codes = self.cal.dac_codes(v, out.dac, out.within, self.dac_bits)
            volts = self.cal.dac_volts(codes, out.dac, self.dac_bits)
            capacity = (spec.out_buffer_bytes or MAX_OUT_BUFFER_BYTES) // 2 - 1
        gains = tuple(RANGES.index(i.range_volts) for i in spec.inputs)
        scan_list = tuple([OUT_SCAN0] if out is not None else []) + tuple(AIN0 + 2 * i.ain for i in spec.inputs)
        if self.read_u32(STREAM_ENABLE):
            self.write_u32(STREAM_ENABLE, 0)
        # the inputs, the stream's registers and its scan list in order, and the scan rate read back: one MBFB packet
        frames: list[Frame] = [f for i in spec.inputs for f in self._ain_frames(i.ain, i.range_volts)]
        frames += [(SCANRATE, f32_words(spec.scan_rate) + u32_words(n_addr) + u32_words(spp)
                    + f32_words(spec.settling_us) + u32_words(spec.resolution_index)
                    + u32_words(spec.buffer_size_bytes or MAX_STREAM_BUFFER_BYTES)),
                   (AUTO_TARGET, u32_words(TARGET_SPONTANEOUS) + u32_words(0) + u32_words(spec.num_scans)),
                   (CLOCK_SOURCE, u32_words(0))]
        frames += [(SCANLIST0 + 2 * k, [w for a in scan_list[k:k + 64] for w in u32_words(a)])
                   for k in range(0, len(scan_list), 64)]  # a frame holds 255 registers: 64 addresses at a time
        rate = words_f32(self.feedback([*frames, (SCANRATE, 2)])[0])
        for i in spec.inputs:
            self._ain_range[i.ain] = i.range_volts
        if not rate > 0:
            raise ProtocolError(self.name, f"device reports scan rate {rate}")
        names = tuple(i.name or f"AIN{i.ain}" for i in spec.inputs)
        if spec.out_ahead_s < 0 or not math.isfinite(spec.out_ahead_s):
            raise ValueError(f"{self.name}: out_ahead_s must be a finite time ≥ 0")
        ahead = min(capacity, max(1, math.ceil(spec.out_ahead_s * rate))) if spec.out_ahead_s else capacity
        chunk = min(OUT_PACKET_VALUES, max(1, ahead // 4))  # a collect tops up every ~quarter of it
        interval = (ahead - chunk) / rate / 2 if out is not None else math.inf
        plan = StreamPlan(rate, 1.0 / rate, names, scan_list, spp, codes, volts, capacity, interval, ahead, chunk)
        self._stream = StreamState(plan, spec, n_in, gains, out_closed=out is None or out.final)
        if out is not None:
            # in this order, one MBFB packet ([D] stream-out: configure — target, allocate, enable — then each
            # buffer update starts with LOOP_NUM_VALUES). LOOP_NUM_VALUES 0 here: the preload is data, not a loop.
            # [A] (the datasheet does not say allocating resets it) the register keeps what the last stream wrote —
            # one stopped while its loop repeated (a pause in a relax) left that loop's block, the preload's
            # SET_LOOP then repeated its last values in the device, in buffer room this driver does not count, and
            # the next top-up was refused (STREAM_OUT_BUFF_FULL, 2613). Later updates write it themselves (a loop
            # entered or left, the hold loop)
            self.feedback([(OUT_TARGET0, u32_words(DAC0 + 2 * out.dac)),
                           (OUT_ALLOC0, u32_words(spec.out_buffer_bytes or MAX_OUT_BUFFER_BYTES)),
                           (OUT_ENABLE0, u32_words(1)), (OUT_LOOP0, u32_words(0))])
            self._feed_out()
        return plan

    def _open_stream_socket(self) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, self.stream_port), timeout=self.timer.bound(self.timeout))
        except OSError as exc:
            raise InstrumentConnectionError(self.name, f"cannot open stream port {self.host}:{self.stream_port}: "
                                            f"{exc.strerror or exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def _close_stream_socket(self) -> None:
        s = self._stream
        if s is not None and s.sock is not None:
            s.sock.close()
            s.sock = None

    def kickoff(self) -> float:
        """Open the stream socket, write STREAM_ENABLE = 1; returns the rig time of scan 0.

        The time is the clock read after the device acknowledged the enable, plus one scan period; its
        uncertainty is one Modbus round trip.
        """
        s = self._stream
        if s is None or s.done:
            raise InstrumentStateError(self.name, "kickoff without arm")
        if self.streaming:
            raise InstrumentStateError(self.name, "stream already running")
        s.sock = self._open_stream_socket()
        asked = self.clock()
        try:
            self.write_u32(STREAM_ENABLE, 1)
        except InstrumentError:  # unanswered or garbled: the enable may have started the stream (and its preloaded
            # stream-out) while this host believes none runs (a reviewer); refused — by STREAM_IS_ACTIVE too, when
            # the link's retry found the stream its lost first request had started: one stop settles which
            self._unsure_start()
            raise
        self.stop_unconfirmed = False  # an enable the device took: no stream of before ran on
        s.t_enable = self.clock()
        s.t0 = s.t_enable + s.plan.dt
        s.t0_uncertainty = s.t_enable - asked  # the device enabled somewhere within the request's round trip
        self.streaming = True
        return s.t0

    def _unsure_start(self) -> None:
        """After an enable that went unanswered: one stop (sent even after a stop request); answered — done, or
        refused as no stream running — the device is known not to stream. Otherwise :attr:`stop_unconfirmed`: the
        run's shutdown then leaves the output to the T7's watchdog. The stream socket is closed either way."""
        self.stop_unconfirmed = True
        try:
            self._lj("stop stream", lambda unit, *a: self.link.write_registers(unit, *a, always_send=True),
                     STREAM_ENABLE, u32_words(0))
        except InstrumentStateError:  # STREAM_NOT_RUNNING: the enable never took
            self.stop_unconfirmed = False
        except InstrumentError:
            pass
        else:
            self.stop_unconfirmed = False
        finally:
            if self._stream is not None:
                self._stream.done = True
            self._close_stream_socket()

    @property
    def scan_clock_uncertainty(self) -> float:
        """How well scan 0's time on the host clock is known [s]: the enable request's round trip (the times of
        the scans are t0 + k/rate with t0 taken at the acknowledgement; the true enable lies within this much
        before it)."""
        return self._stream.t0_uncertainty if self._stream is not None else math.nan

    def _receive(self, until_packets: int, timeout: float) -> list[StreamBatch]:
        """Packets available now, and (waiting until a deadline of ``timeout`` s expires: :mod:`drivers.deadline`)
        until ``until_packets`` total: the whole packets of each receive as one batch."""
        s = self._stream
        assert s is not None and s.sock is not None
        # the batches of a receive that raised (a stop request, a timeout) are kept in the stream's state: their
        # packet numbers are taken, so dropping them would leave a hole no scan number or NaN row shows
        out = s.received
        got = sum(len(b) for b in out)
        self.timer.sending()  # what is waited for from here: the packets, not the reply to the last request (one the
        deadline = self.timer.start(timeout)  # twin withheld says nothing of the stream, which a T7 sends regardless)
        while True:
            check(self.cancel, self.name)
            wait = s.packets + got < until_packets and not s.done
            r, _, _ = select.select([s.sock], [], [], min(deadline.left(), 0.05) if wait else 0.0)
            if r:
                try:
                    data = s.sock.recv(1 << 16)
                except OSError as exc:
                    raise InstrumentConnectionError(self.name, f"stream socket lost: {exc.strerror or exc}") \
                        from None
                if not data:
                    raise InstrumentConnectionError(self.name, "stream socket closed by the device")
                s.raw += data
                spans = split_stream_packets(s.raw)
                if spans:  # every whole packet received, parsed together (one conversion of their samples)
                    end = spans[-1][0] + spans[-1][1]
                    frames = bytes(s.raw[:end])
                    del s.raw[:end]
                    batch = parse_stream_batch(frames, spans, self.name)
                    n = len(batch)
                    # numbered on from the last packet: the packets up to the first that is not are taken (a device
                    # status that ends the stream among them counts), then the gap is an error
                    lost = np.flatnonzero(batch.transaction_ids != (s.next_tid + np.arange(n)) & 0xFFFF)
                    ok = int(lost[0]) if lost.size else n
                    taken = batch.statuses[:ok]
                    if taken.any() and not s.done:  # (np.isin costs more than the rest of these checks)
                        s.done = any(status in _ENDING for status in taken.tolist())
                    s.next_tid += ok
                    if lost.size:
                        raise ProtocolError(self.name, f"stream packet {int(batch.transaction_ids[ok])} after "
                                            f"{(s.next_tid - 1) & 0xFFFF}: packets lost")
                    out.append(batch)
                    got += n
                continue
            if not wait:
                s.received = []
                return out
            if deadline.expired():
                raise InstrumentTimeoutError(self.name, f"stream packets up to #{until_packets} not received "
                                             f"within {timeout:g} s (have {s.packets + got}){deadline.detail}")

    def _expected_packets(self, until: float) -> int:
        s = self._stream
        assert s is not None
        scans = math.floor((until - s.t_enable) * s.plan.scan_rate + 1e-6)
        spp = s.plan.samples_per_packet
        if s.spec.num_scans and scans >= s.spec.num_scans:  # [A] a burst ends with its last packet, short or whole
            return -(-s.spec.num_scans * s.n_in // spp)
        return max(scans, 0) * s.n_in // spp

    def collect(self, until: float | None = None, timeout: float = 1.0) -> StreamBlock:
        """Complete scans received since the last call (scan-numbered), after topping up the out buffer.

        ``until`` (rig time): first wait, up to ``timeout`` s (:mod:`drivers.deadline`), for every whole packet the
        device has filled by then — in virtual time, call it with the clock's present to get every scan so far.
        A gap in the packet sequence is a :class:`ProtocolError`; a device status that ends the stream
        (scan overlap, skip-counter overflow, buffer full) a :class:`StreamEndedError` whose ``block`` holds the
        scans this call received, up to and with that packet's (what it would have returned).
        Samples are 16-bit codes converted through the calibration read at connect, which is refused unless
        every code of every range lies within 1.1 × the range (:data:`AIN_SPAN`): no streamed sample is beyond
        what the converter makes.
        """
        s = self._stream
        if s is None or s.sock is None:
            raise InstrumentStateError(self.name, "collect without kickoff")
        want = self._expected_packets(until) if until is not None else 0
        batches = self._receive(want, timeout)
        s.packets += sum(len(b) for b in batches)
        first = s.scans
        rows: list[np.ndarray] = []
        valid: list[np.ndarray] = []
        statuses: list[int] = []
        skipped = 0
        backlog = 0
        chunk: list[np.ndarray] = []  # samples of consecutive packets, converted together
        for batch in batches:
            seen = batch.statuses[batch.statuses != 0].tolist()
            statuses += seen
            backlog = int(batch.backlog_bytes[-1]) // (2 * s.n_in)
            if ST_RECOVER_END not in seen:  # the usual batch: its samples in one piece
                chunk.append(batch.samples)
                continue
            for i in range(len(batch)):
                pkt = batch.packet(i)
                samples = pkt.samples
                if pkt.status == ST_RECOVER_END:
                    self._convert(chunk, rows, valid)
                    if s.pending:
                        raise ProtocolError(self.name, "auto-recovery ended inside a scan")
                    if samples.size < s.n_in or np.any(samples[:s.n_in] != DUMMY):
                        raise ProtocolError(self.name, "auto-recovery end without the dummy scan")
                    samples = samples[s.n_in:]
                    skipped += pkt.additional
                    rows.append(np.full((pkt.additional, s.n_in), np.nan))
                    valid.append(np.zeros((pkt.additional, s.n_in), bool))
                    s.scans += pkt.additional
                chunk.append(samples)
        self._convert(chunk, rows, valid)
        # one piece (the usual collect) is returned as made: no copy
        v = (rows[0] if len(rows) == 1 else np.concatenate(rows)) if rows else np.empty((0, s.n_in))
        ok = (valid[0] if len(valid) == 1 else np.concatenate(valid)) if valid else np.empty((0, s.n_in), bool)
        if self.streaming and not s.done:
            self._feed_out()
        if s.done:
            self.streaming = False
        block = StreamBlock(first, s.t0, s.plan.dt, s.plan.names, v, ok, backlog, skipped, tuple(statuses), s.done)
        fatal = [c for c in statuses if c in (ST_SCAN_OVERLAP, ST_RECOVER_OVERFLOW, ST_BUFFER_FULL)]
        if fatal:  # the scans measured up to the fault go with the error: the caller records them
            raise StreamEndedError(self.name, f"stream ended by device status {fatal[0]} ({ERRORS[fatal[0]]}) at "
                                   f"scan {s.scans}", block)
        return block

    def _convert(self, chunk: list[np.ndarray], rows: list[np.ndarray], valid: list[np.ndarray]) -> None:
        """Whole scans of the samples in ``chunk`` (after the samples left over from the last packet) to volts in
        ``rows``; the rest of a scan waits for the next packet. Empties ``chunk``."""
        s = self._stream
        assert s is not None
        if not chunk:
            return
        allsamp = chunk[0] if len(chunk) == 1 and not s.pending else \
            np.concatenate([np.asarray(s.pending, np.uint16), *chunk])
        chunk.clear()
        whole = allsamp.size // s.n_in * s.n_in
        s.pending = allsamp[whole:].tolist()
        raw = allsamp[:whole].reshape(-1, s.n_in)
        if len(set(s.gains)) == 1:  # every input on one range: one table look-up for all
            volts = self.cal.ain_volts(raw, s.gains[0])
        else:
            volts = np.empty(raw.shape)
            for j, g in enumerate(s.gains):
                volts[:, j] = self.cal.ain_volts(raw[:, j], g)
        rows.append(volts)
        valid.append(np.ones(raw.shape, bool))
        s.scans += raw.shape[0]

    @property
    def scans_received(self) -> int:
        """Scan index of the next scan :meth:`collect` will return."""
        return self._stream.scans if self._stream else 0

    def complete(self, timeout: float = 10.0, poll: float = 0.05) -> list[StreamBlock]:
        """Wait (on the rig clock: a virtual clock advances) until the burst completed or, for a continuous
        stream with an output, every waveform value has been played and its scan collected; returns the
        blocks collected meanwhile. ``timeout``: seconds without progress before giving up (:mod:`drivers.deadline`).
        A device status that ends the stream: a :class:`StreamEndedError` whose ``block`` holds every scan this call
        received (the blocks collected before it and the last, as one)."""
        s = self._stream
        if s is None or not self.streaming:
            raise InstrumentStateError(self.name, "complete without a running stream")
        codes = s.plan.out_codes
        if not s.spec.num_scans and codes is None:
            raise InstrumentStateError(self.name, "a continuous input-only stream never completes; use stop")
        target = s.spec.num_scans or (s.out_base + codes.size if codes is not None else 0)
        blocks: list[StreamBlock] = []
        while True:
            try:
                block = self.collect(until=self.clock(), timeout=timeout)
            except StreamEndedError as exc:  # the blocks collected before it are measured data too
                raise StreamEndedError(self.name, exc.detail, _joined([*blocks, exc.block])) from None
            blocks.append(block)
            if block.done or s.scans >= target:
                return blocks
            self.sleep(poll)

    def whole_packets_at(self) -> float:
        """Rig time at which the scans due by now fill whole packets (scan k is taken (k + 1) scan periods after the
        enable): a stop sent then loses no scan taken before it but those of the packet it interrupts, which the
        device does not send. Now, when no stream runs."""
        s = self._stream
        now = self.clock()
        if s is None or not self.streaming:
            return now
        scans = max(math.floor((now - s.t_enable) * s.plan.scan_rate + 1e-6), 0)
        spp = s.plan.samples_per_packet
        samples = -(-scans * s.n_in // spp) * spp  # up to the end of the packet being filled
        return s.t_enable + -(-samples // s.n_in) * s.plan.dt

    def stop(self, *, always_send: bool = False) -> StreamBlock | None:
        """STREAM_ENABLE = 0 (the DAC keeps its last value) and close the stream socket; returns the complete
        scans that had arrived (a partly filled packet is not sent by the device), also those of a stream the
        device had ended with a status of its own (:class:`StreamEndedError`, not raised here: the stream stops as
        asked, the status is in the block's ``statuses``). ``always_send``: the stop goes out even after a stop
        request (making the rig safe)."""
        s = self._stream
        if s is None or s.sock is None:
            return None
        block = None
        refused: InstrumentStateError | None = None
        asked = self.clock()
        try:
            if self.streaming:
                try:
                    self._lj("stop stream", lambda unit, *a: self.link.write_registers(unit, *a,
                                                                                      always_send=always_send),
                             STREAM_ENABLE, u32_words(0))
                except InstrumentStateError as exc:  # refused (STREAM_NOT_RUNNING): a device that ended the stream
                    refused = exc  # itself has sent its last packets all the same
                    self.stop_unconfirmed = False  # (answered: no stream runs)
                except InstrumentError:  # unanswered, garbled or cancelled: it may not have arrived, and then the
                    self.stop_unconfirmed = True  # device streams on, its stream-out over any DAC write of ours
                    raise
                else:
                    self.stop_unconfirmed = False
            self.streaming = False
            try:
                try:  # the packets filled before the stop was sent are on their way: a short wait for them
                    block = self.collect(until=asked, timeout=STOP_DRAIN_S)
                except InstrumentTimeoutError:  # what did arrive (kept by the receive) and no more
                    block = self.collect(timeout=0.0)
            except StreamEndedError as exc:  # the device had ended the stream: its last scans are measured data
                block = exc.block
            except InstrumentError:  # stopping must not fail on the data's account
                pass
        finally:
            self.streaming = False
            s.done = True
            self._close_stream_socket()
        if refused is not None and (block is None or not any(c in _ENDING for c in block.statuses)):
            raise refused  # not a stream the device had ended: the refusal stands
        return block


def _joined(blocks: list[StreamBlock]) -> StreamBlock:
    """Consecutive blocks of one stream (each collect's continues the last's scan numbers) as one."""
    if len(blocks) == 1:
        return blocks[0]
    a, z = blocks[0], blocks[-1]
    return StreamBlock(a.first_scan, a.t0, a.dt, a.names, np.concatenate([b.volts for b in blocks]),
                       np.concatenate([b.valid for b in blocks]), z.backlog_scans,
                       sum(b.skipped_scans for b in blocks), tuple(c for b in blocks for c in b.statuses), z.done)
