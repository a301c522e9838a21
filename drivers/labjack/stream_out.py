"""T7 analog output: single DAC values and the stream-out — its values checked, coded through the calibration,
and kept at most ``StreamSpec.out_ahead_s`` ahead of the scan clock in the device's buffer ([D] §3.2.1/3.2.3)."""

from __future__ import annotations

import math

import numpy as np

from drivers.errors import InstrumentStateError, LimitError
from drivers.interfaces import DacCoding
from drivers.labjack.connection import T7Connection
from drivers.labjack.looping import Loop, plan_loop
from drivers.labjack.registers import (
    DAC0,
    DAC_RANGE,
    OUT_BUFFER_U16_0,
    OUT_LOOP0,
    OUT_SET_LOOP0,
    Words,
    f32_words,
    u32_words,
    words_f32,
)


class T7StreamOut(T7Connection):
    """DAC0/DAC1: a value at a time, or a waveform played on the stream's scan clock."""

    def dac_output(self, dac: int, volts: float, within: tuple[float, float] | None = None) -> tuple[float, float]:
        """(value :meth:`write_dac` sends, what the DAC then outputs) [V] for ``volts``, sending nothing.

        The T7 codes the FLOAT32 it receives as V·Slope + Offset (rounded) and its 12-bit converter ignores the low
        4 bits. ``within`` (lo, hi): the code is the nearest whose output lies within (one level toward the inside
        at the edge), sent as the middle of its level's codes, so that the T7's own rounding of the float cannot
        move it to another level; LimitError if that value is not one the DAC spans."""
        if dac not in (0, 1):
            raise ValueError(f"{self.name}: no DAC{dac}")
        if not DAC_RANGE[0] <= volts <= DAC_RANGE[1]:
            raise LimitError(self.name, f"DAC{dac} {volts:g} V outside {DAC_RANGE[0]:g}…{DAC_RANGE[1]:g} V")
        send = volts
        if within is not None:
            shift = 16 - self.dac_bits
            try:
                code = int(self.cal.dac_codes(np.array([volts]), dac, within, self.dac_bits)[0])
            except ValueError as exc:
                raise LimitError(self.name, str(exc)) from None
            s, o = self.cal.dac(dac)
            send = ((code >> shift << shift) + (1 << shift) / 2 - o) / s
        played = float(self.out_played(np.array([np.float32(send)]), dac)[0])
        if within is not None and not (DAC_RANGE[0] <= send <= DAC_RANGE[1] and within[0] <= played <= within[1]):
            raise LimitError(self.name, f"DAC{dac}: no value the DAC spans plays within {within[0]:g}…{within[1]:g} V")
        return send, played

    def out_played(self, volts: np.ndarray, dac: int, within: tuple[float, float] | None = None) -> np.ndarray:
        """What DAC ``dac`` outputs [V] for the values ``volts`` as the T7 codes them (rounded; ``within``: codes
        clipped as :meth:`Calibration.dac_codes` does): a stream-out's values as :meth:`arm` and :meth:`extend`
        play them."""
        return self.cal.dac_volts(self.cal.dac_codes(volts, dac, within, self.dac_bits), dac, self.dac_bits)

    def write_dac(self, dac: int, volts: float, within: tuple[float, float] | None = None, *,
                  always_send: bool = False) -> float:
        """Set DAC0/DAC1 [V]; refuses values outside the DAC's 0–5 V. Returns what the DAC outputs: the 12-bit
        level of the code the T7 makes of the value. ``within`` (lo, hi) [V]: that output lies within [lo, hi]
        (:meth:`dac_output` chooses the value sent). ``always_send``: goes out even after a stop request (a safe
        value)."""
        send, played = self.dac_output(dac, volts, within)
        self.feedback([(DAC0 + 2 * dac, f32_words(send))], always_send=always_send)  # MBFB: the T7's own format
        return played

    def dac_coding(self, dac: int, within: tuple[float, float]) -> DacCoding:
        """How DAC ``dac`` codes volts (its calibration; 16-bit codes, the low ``16 − dac_bits`` ignored) and its codes
        whose output lies within ``within`` (:meth:`Calibration.dac_code_range`)."""
        slope, offset = self.cal.dac(dac)
        lo, hi = self.cal.dac_code_range(dac, within, self.dac_bits)
        return DacCoding(float(slope), float(offset), 16 - self.dac_bits, lo, hi)

    def read_dac(self, dac: int) -> float:
        """The DAC's present value [V]."""
        return words_f32(self.feedback([(DAC0 + 2 * dac, 2)])[0])

    # ------------------------------------------------------------------ stream-out
    def _feed_out(self) -> None:
        """Top up the stream-out buffer with as many values as fit; close it with the hold loop. A stretch of whole
        periods that repeats (:mod:`.looping`) is written once and played from the device's loop."""
        s = self._stream
        assert s is not None
        codes = s.plan.out_codes
        if codes is None or s.out_final:
            return
        total = s.out_base + codes.size  # values given so far (the first out_base are no longer kept)
        pos = hi = s.scans  # values the device has played: at least the scans received, and …
        if self.streaming:  # … those its scan clock has reached by now: t0 is known late, by at most its uncertainty
            late = self.clock() - s.t0
            pos = max(pos, math.floor(late * s.plan.scan_rate) + 1)
            hi = max(pos, math.floor((late + s.t0_uncertainty) * s.plan.scan_rate) + 1)
        if s.looping:
            self._leave_loop(pos, hi, total)
            return
        if self.streaming and pos > s.out_written:  # the device ran past the data it had (surely: lower bound)
            s.underrun_scans = max(s.underrun_scans, pos - s.out_written)
        loop = self._next_loop(total)
        if loop is not None and self._enter_loop(loop, pos, hi):
            return
        stop = loop.at if loop is not None else total  # a planned loop's block goes in whole
        played = min(hi, s.out_written)  # ahead of where the device may be: a slow enable reply costs no margin
        # … but never more than the buffer surely holds: the device has played at least the scans it sent back
        # (one scan clock), so capacity − (written − scans received) is free whatever the clock says (a device that
        # started later than t0 says, or a twin whose thread lags a loaded host, refused a write as
        # STREAM_OUT_BUFF_FULL, 2613)
        sure = s.plan.out_capacity - (s.out_written - min(s.scans, s.out_written))
        free = min((s.plan.out_ahead or s.plan.out_capacity) - (s.out_written - played), sure)
        n = max(0, min(free, stop - s.out_written))
        if n < s.plan.out_chunk and s.out_written + n < stop:
            return  # wait until a whole chunk fits
        k = s.out_written - s.out_base
        writes: list[tuple[int, Words]] = [(OUT_BUFFER_U16_0, codes[k:k + n])] if n else []
        s.out_written += n
        if s.out_written == total and s.out_closed:
            assert s.spec.output is not None
            writes.append((OUT_LOOP0, u32_words(s.spec.output.hold)))
            s.out_final = True
        if n:
            writes.append((OUT_SET_LOOP0, u32_words(1)))
        if writes:
            self.write_feedback(writes)

    def _next_loop(self, total: int) -> Loop | None:
        """The looped stretch planned from the next value to write on (searched again when values were given or
        the search point moved by a block)."""
        s = self._stream
        assert s is not None and s.plan.out_codes is not None
        if s.loop is not None and s.loop.at >= s.out_written:
            return s.loop
        s.loop = None
        ahead = s.plan.out_ahead
        if not (s.spec.out_loops and ahead and s.plan.out_capacity > ahead):
            return None
        at, given = s.loop_searched
        if given == total and s.out_written - at < ahead:
            return None
        s.loop_searched = (s.out_written, total)
        # a block at least the values kept ahead (a collect or more between a loop's ends: it is left safely),
        # and small enough that the buffer holds it and a packet of the data after it
        s.loop = plan_loop(s.plan.out_codes[s.out_written - s.out_base:], s.out_written, ahead,
                           s.plan.out_capacity - 1 - s.plan.out_chunk)
        return s.loop

    def _enter_loop(self, loop: Loop, pos: int, hi: int) -> bool:
        """Write the data up to the loop and its block, LOOP_NUM_VALUES = the block, SET_LOOP: when the buffer
        holds them all and the device surely has not reached the loop yet. False: not now (a loop the device
        is about to reach without it is given up: the values are refilled as any others)."""
        s = self._stream
        assert s is not None and s.plan.out_codes is not None
        if self.streaming and hi + s.plan.out_chunk >= loop.at:  # too late to be sure the block arrives first
            s.loop = None
            s.loop_searched = (loop.end, s.loop_searched[1])
            return False
        if loop.at + loop.block - pos > s.plan.out_capacity:
            return False
        k = s.out_written - s.out_base
        values = s.plan.out_codes[k:loop.at + loop.block - s.out_base]
        s.out_written = loop.at + loop.block
        s.looping = True
        self.write_feedback([(OUT_LOOP0, u32_words(loop.block)), (OUT_BUFFER_U16_0, values),
                             (OUT_SET_LOOP0, u32_words(1))])
        return True

    def _leave_loop(self, pos: int, hi: int, total: int) -> None:
        """While the device repeats the block: in the last repetitions, when the one in progress is surely known
        (the values at both bounds of the scan clock, and a packet's margin, in the same repetition), write the
        values after it with SET_LOOP — the T7 plays them when that repetition is complete. A device past the
        last repetition has played values the program does not have there: an underrun (the run stops)."""
        s = self._stream
        assert s is not None and s.loop is not None and s.plan.out_codes is not None
        loop = s.loop
        margin = s.plan.out_chunk
        first = max(0, (pos - 1 - loop.at) // loop.block)  # the repetition the device plays (lower bound) …
        last = max(0, (hi - 1 + margin - loop.at) // loop.block)  # … and at most, when a request lands
        if first >= loop.blocks:
            s.underrun_scans = max(s.underrun_scans, pos - loop.end, 1)
            return
        leave_from = loop.blocks - 1 - max(1, (s.plan.out_ahead or s.plan.out_capacity) // loop.block)
        if first != last or first < leave_from:
            return
        e = loop.at + (first + 1) * loop.block  # the device plays the values from e on after this repetition
        n = min(total - e, s.plan.out_capacity - 1 - loop.block)
        writes: list[tuple[int, Words]] = []
        final = e + n == total and s.out_closed
        assert s.spec.output is not None
        writes.append((OUT_LOOP0, u32_words(s.spec.output.hold if final else 0)))
        if n:
            writes.append((OUT_BUFFER_U16_0, s.plan.out_codes[e - s.out_base:e + n - s.out_base]))
        writes.append((OUT_SET_LOOP0, u32_words(1)))
        s.out_written, s.looping, s.loop, s.out_final = e + n, False, None, final
        self.write_feedback(writes)
        if self.streaming:  # the request may have landed after the repetition ended: then the program slipped
            reached = math.floor((self.clock() - s.t0 + s.t0_uncertainty) * s.plan.scan_rate) + 1
            if reached > e:
                s.underrun_scans = max(s.underrun_scans, reached - e)

    def _checked_out(self, volts: np.ndarray, dac: int) -> np.ndarray:
        """Stream-out values as floats, refused (nothing sent) unless a non-empty finite 1-D array the DAC spans."""
        v = np.asarray(volts, dtype=float)
        if v.ndim != 1 or v.size < 1 or not np.all(np.isfinite(v)):
            raise ValueError(f"{self.name}: stream-out waveform must be a non-empty finite 1-D array")
        if v.min() < DAC_RANGE[0] or v.max() > DAC_RANGE[1]:
            raise LimitError(self.name, f"DAC{dac} waveform spans {v.min():g}…{v.max():g} V, "
                             f"the DAC gives {DAC_RANGE[0]:g}…{DAC_RANGE[1]:g} V")
        return v

    def extend(self, volts: np.ndarray, final: bool = True, within: tuple[float, float] | None = None) -> np.ndarray:
        """Append values [V at the DAC] to an open stream-out (armed with ``final=False``): they play on the
        scans right after the values already given, on the same scan clock — no gap, no restart. ``final``:
        nothing more follows (the hold loop is written after them). ``within``: as :attr:`StreamOut.within`
        (default: the armed stream-out's). Returns what the 12-bit DAC will output.

        Call it before the device has played the values it has (:attr:`StreamPlan.max_collect_interval`);
        a stream-out that already ran dry plays the new values late (``out_underrun_scans``)."""
        s = self._stream
        if s is None or s.spec.output is None or s.out_closed or s.plan.out_codes is None:
            raise InstrumentStateError(self.name, "extend needs an armed stream-out opened with final=False")
        v = self._checked_out(volts, s.spec.output.dac)
        window = s.spec.output.within if within is None else within
        codes = self.cal.dac_codes(v, s.spec.output.dac, window, self.dac_bits)
        played = self.cal.dac_volts(codes, s.spec.output.dac, self.dac_bits)
        assert s.plan.out_volts is not None
        cut = s.out_written - s.out_base  # values already in the device are dropped here (long campaigns)
        s.plan.out_codes = np.concatenate([s.plan.out_codes[cut:], codes])
        s.plan.out_volts = np.concatenate([s.plan.out_volts[cut:], played])
        s.out_base += cut
        s.out_closed = final
        self._feed_out()
        return played

    @property
    def out_open(self) -> bool:
        """An armed stream-out still takes :meth:`extend`."""
        s = self._stream
        return s is not None and s.spec.output is not None and not s.out_closed and not s.done

    @property
    def out_underrun_scans(self) -> int:
        """Scans the stream-out played past the data written (0 unless :meth:`collect` came too late)."""
        return self._stream.underrun_scans if self._stream else 0
