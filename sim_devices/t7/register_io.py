"""The T7 twin's register dispatch: every Modbus read and write (FC3/4, FC6/16, MBFB frames) checked against the
map's access (:data:`~sim_devices.t7.registers.REGISTERS`) and applied to the stream engine, stream-out, watchdog,
DIO and identity state.

[D] register semantics (ljm_constants.json): a read of a register the map marks write-only, a write to one it marks
read-only, and any address the twin does not serve get Modbus exception 2 (illegal data address) with
LAST_ERR_DETAIL = 1202 (LJME_MBE2_ILLEGAL_DATA_ADDRESS: "… illegal access to a device register such as trying to
write to a read only register"); [A] the device stores that code as it stores its own error codes.
[D] LAST_MB_ERR 55001 ("the last Modbus TCP error code"): [A] the exception code sent; LAST_ERR_FRAME 55002 ("the
frame number that caused the last error"): [A] numbered from 1 in an MBFB packet (:mod:`~sim_devices.t7.feedback`),
0 after a refused plain (FC3/FC16) request.
[D] error codes 2600, 2605, 2607, 2608, 2611–2615, 2617, 2618, 2620, 2622, 2627 in LAST_ERR_DETAIL; [A] sent as
Modbus exception 4.
[D] TEST 55100 reads 0x00112233, and "allows you to read a single word from 55100 or 55101"; TEST_UINT16/UINT32/
INT32/FLOAT32 keep what is written (defaults as the map).
[D] AIN_ALL_RANGE writes every input's range; reads the common range or −9999 when they differ.
[D] AIN#_RESOLUTION_INDEX (0–8; 0 = 8) sets the ADC noise of a command-response read of that input
(:mod:`~sim_devices.t7.resolution`); AIN_ALL_RESOLUTION_INDEX writes every input's, reads the common one or 0xFFFF;
[A] a value above 8 (T7-Pro indices 9–12 included: the twin is a T7) answers exception 3, as a range not in the
list does; [D] LAST_ERR_DETAIL then holds 2375 AIN_RESOLUTION_INVALID or 2370 AIN_RANGE_INVALID (register map's
errors). [L] a read returns at once (the index's sample time is not spent).
[D] CORE_TIMER: 32-bit timer at half the 80-MHz core clock, [A] 0 at the twin's creation, on the rig's clock.
[D] DIO: FIO#/EIO#/CIO#/MIO# (2000+n) read makes the line an input, write an output at that level; _STATE (2500+p)
and DIO_STATE (2800) do not configure direction; the upper 8 bits of a port _STATE/_DIRECTION write are inhibits.
[A] nothing is wired to the DIO lines: an input reads 1 (unconnected, pulled up), an output reads what it drives;
factory state all inputs. [L] DIO_INHIBIT is not served (DIO_STATE/DIO_DIRECTION writes are unfiltered).
[E] calibration in flash at 0x3C4000 (41 F32); pointer 61810 (RW), read buffer 61812 ([A] the pointer advances).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar, cast

import numpy as np
from pymodbus.constants import ExcCodes

from sim_devices.t7 import resolution
from sim_devices.t7.analog import RANGE_GAIN
from sim_devices.t7.registers import (
    AIN_ALL_MIXED,
    CORE_CLOCK_HZ,
    DIO_PORTS,
    E_ACTIVE,
    E_AIN_RANGE,
    E_AIN_RESOLUTION,
    E_ILLEGAL_ADDRESS,
    E_NOT_RUNNING,
    F32,
    FLASH_CAL,
    N_AIN_ALL,
    N_DIO,
    R_AIN_ALL_RANGE,
    R_AIN_ALL_RES,
    R_AIN_NEG,
    R_AIN_RANGE,
    R_AIN_RES,
    R_BOOT,
    R_BUFSIZE,
    R_CLKSRC,
    R_CORE_TIMER,
    R_DAC,
    R_DIO,
    R_DIO_DIR,
    R_DIO_STATE,
    R_DTYPE,
    R_ENABLE,
    R_EXTDIV,
    R_FIO_DIR,
    R_FIO_STATE,
    R_FLASH_PTR,
    R_FLASH_READ,
    R_FW,
    R_HW,
    R_LAST_ERR,
    R_LAST_ERR_FRAME,
    R_LAST_MB_ERR,
    R_NADDR,
    R_NSCANS,
    R_O_ALLOC,
    R_O_ENABLE,
    R_O_F32,
    R_O_LOOP,
    R_O_SCAN,
    R_O_STATUS,
    R_O_TARGET,
    R_O_U16,
    R_PRODUCT,
    R_RATE,
    R_RATE_ACTUAL,
    R_RES,
    R_SCANLIST,
    R_SERIAL,
    R_SETTLE,
    R_SPP,
    R_TARGET,
    R_TEST,
    REGISTERS,
    TEST_DEFAULTS,
    TEST_VALUE,
    Kind,
    value_of,
    words,
)
from sim_devices.t7.stream_in import StreamEngine
from sim_devices.t7.watchdog import Watchdog

FIRMWARE, HARDWARE, BOOTLOADER = 1.0299, 1.30, 0.94  # [A] the versions the twin reports
_T = TypeVar("_T")


class RegisterIO(StreamEngine):
    """Register reads and writes of one T7 twin, and the state only registers hold."""

    def _init_registers(self, serial: int) -> None:
        self.serial = serial
        self.regs: dict[int, float] = {R_RATE: 0.0, R_NADDR: 0, R_SPP: 0, R_SETTLE: 0.0, R_RES: 0,
                                       R_BUFSIZE: 0, R_CLKSRC: 0, R_TARGET: 0, R_DTYPE: 0, R_NSCANS: 0,
                                       R_EXTDIV: 1}
        self.scanlist = [0] * 128
        self.ain_range = [10.0] * N_AIN_ALL
        self.ain_neg = [199] * N_AIN_ALL
        self.ain_res = [0] * N_AIN_ALL  # AIN#_RESOLUTION_INDEX as written (0: the default, 8)
        self.dac_volts = [0.0, 0.0]
        self.watchdog = Watchdog()
        self.tests: dict[int, float] = dict(TEST_DEFAULTS)
        self.dio_state = 0  # output latches, bit n = DIO n
        self.dio_dir = 0  # 1 = output
        self.t_created = self.clock.now()
        self.last_err = 0
        self.last_mb_err = 0  # LAST_MB_ERR: the Modbus exception code last sent
        self.last_err_frame = 0  # LAST_ERR_FRAME: the MBFB frame (from 1) that caused it, 0 for a plain request
        self.flash_ptr = 0

    @property
    def wd(self) -> dict[int, float]:
        """The watchdog registers by address."""
        return self.watchdog.regs

    def _dio_level(self) -> int:
        """Every line's level: outputs what they drive, inputs 1 ([A] unconnected, pulled up)."""
        return (self.dio_state & self.dio_dir) | (~self.dio_dir & ((1 << N_DIO) - 1))

    def _read_value(self, a: int) -> tuple[Kind, float] | None:
        """(type, value) of the register starting at ``a``; None if there is none readable there."""
        reg = REGISTERS.get(a)
        if reg is None or "R" not in reg.access:
            return None
        kind = reg.kind
        now = self.clock.now()
        if a < 2 * N_AIN_ALL:
            ain = a // 2
            obs = self._observe(np.array([now]))
            rms = resolution.noise_rms(self.ain_range[ain], resolution.command_index(self.ain_res[ain]))
            return kind, float(self._ain_volts(ain, obs, 1, rms)[0])
        if a in (R_DAC, R_DAC + 2):
            if self.streaming:  # what a stream-out driving it has played by now (pumps may be rarer than reads)
                for k in self._out_indices():
                    if self.outs[k].target == a:
                        self._advance_out(k, now)
            return kind, self.dac_volts[(a - R_DAC) // 2]
        if R_DIO <= a < R_DIO + N_DIO:
            self.dio_dir &= ~(1 << (a - R_DIO))  # [D] a read makes the line an input
            return kind, self._dio_level() >> (a - R_DIO) & 1
        if R_FIO_STATE <= a < R_FIO_STATE + 4:
            first, n = DIO_PORTS[a - R_FIO_STATE]
            return kind, self._dio_level() >> first & ((1 << n) - 1)
        if R_FIO_DIR <= a < R_FIO_DIR + 4:
            first, n = DIO_PORTS[a - R_FIO_DIR]
            return kind, self.dio_dir >> first & ((1 << n) - 1)
        if a == R_DIO_STATE:
            return kind, self._dio_level()
        if a == R_DIO_DIR:
            return kind, self.dio_dir
        if R_AIN_RANGE <= a < R_AIN_RANGE + 2 * N_AIN_ALL:
            return kind, self.ain_range[(a - R_AIN_RANGE) // 2]
        if R_AIN_NEG <= a < R_AIN_NEG + N_AIN_ALL:
            return kind, self.ain_neg[a - R_AIN_NEG]
        if a == R_AIN_ALL_RANGE:
            return kind, self.ain_range[0] if len(set(self.ain_range)) == 1 else AIN_ALL_MIXED
        if R_AIN_RES <= a < R_AIN_RES + N_AIN_ALL:
            return kind, self.ain_res[a - R_AIN_RES]
        if a == R_AIN_ALL_RES:
            return kind, self.ain_res[0] if len(set(self.ain_res)) == 1 else resolution.ALL_MIXED
        if a == R_RATE:
            return kind, self.rate
        if a == R_RATE_ACTUAL:
            return kind, self.rate
        if a in self.regs:
            return kind, self.regs[a]
        if R_SCANLIST <= a < R_SCANLIST + 256:
            return kind, self.scanlist[(a - R_SCANLIST) // 2]
        if a == R_ENABLE:
            return kind, int(self.streaming)
        if R_O_TARGET <= a < R_O_ENABLE + 8:
            k = (a - R_O_TARGET) % 10 // 2
            o = self.outs[k]
            base = a - 2 * k
            value = {R_O_TARGET: o.target, R_O_ALLOC: o.alloc, R_O_LOOP: o.loop_num,
                     R_O_STATUS: 2 * self._level(k, now), R_O_ENABLE: o.enable}[base]
            return kind, value
        if R_O_SCAN <= a < R_O_SCAN + 4:
            return kind, 0
        if a == R_LAST_ERR:
            return kind, self.last_err
        if a == R_LAST_MB_ERR:
            return kind, self.last_mb_err
        if a == R_LAST_ERR_FRAME:
            return kind, self.last_err_frame
        if a == R_TEST:
            return kind, TEST_VALUE
        if a in self.tests:
            return kind, self.tests[a]
        if a == R_CORE_TIMER:
            return kind, int((now - self.t_created) * CORE_CLOCK_HZ / 2) & 0xFFFFFFFF
        fixed = {R_PRODUCT: 7.0, R_HW: HARDWARE, R_FW: FIRMWARE, R_BOOT: BOOTLOADER, R_SERIAL: self.serial,
                 R_FLASH_PTR: self.flash_ptr}
        if a in fixed:
            return kind, fixed[a]
        if a in self.watchdog:
            return kind, self.watchdog.read(a)
        return None

    def _arm_watchdog(self) -> None:
        """The plant's input watchdog as the registers configure it: enabled with a timeout and a DAC action on
        the DAC that drives the amplifier ([L] modelled as the amplifier input going to 0 V: the rig's host writes
        the DAC value of 0 V through the conditioning stage; another value is recorded as a twin error)."""
        act = self.watchdog.action(self.dac)
        self.plant.input_watchdog = act[0] if act else None
        if act:
            k = self.dac
            v_in = float(self.conditioning(np.array([self._code_volts(self._code(act[1], k), k)]))[0])
            if abs(v_in) > 0.01 * abs(self.conditioning.gain) + 1e-9:
                self.errors.append(RuntimeError(f"watchdog DAC{k} value gives {v_in:.3f} V at the amplifier "
                                                "input; the twin models 0 V"))

    def _illegal(self) -> ExcCodes:
        """Exception 2 for an address the twin does not serve or an access the map does not allow."""
        self.last_err = E_ILLEGAL_ADDRESS
        return ExcCodes.ILLEGAL_ADDRESS

    def _lapsed(self, now: float) -> None:
        """A request after the watchdog's timeout finds it fired ([D] the timeout acts when it ends, not at the next
        request): a stream-out loop it stops is played up to ``now`` first, so the request cannot restart it (a
        twin pumping on demand may not have played that far yet)."""
        act = self.watchdog.action(self.dac)
        if act is None or not self.streaming or now < self.heard + act[0]:
            return
        with self.plant.lock, self.lock:
            self._play_out(now)

    def request(self, serve: Callable[[], _T]) -> _T:
        """Run ``serve`` as one request the device receives (a plain one, or an MBFB packet with all its frames):
        every request resets the T7 watchdog ([D] WATCHDOG_*_DEFAULT registers: on timeout the device writes its
        configured DAC value — for a rig, the code of 0 V at the amplifier input); the twin arms the plant's input
        watchdog from those registers as the host writes them (:meth:`_arm_watchdog`). ``serve`` runs under the
        plant's lock, then ours, the time read inside both (:meth:`serve_frame`)."""
        self._lapsed(self.clock.now())
        self.plant.feed_watchdog()
        self.heard = self.clock.now()
        # The plant's lock first, then ours, and the time read inside both: the plant cannot integrate past
        # ``now`` while the request schedules DAC values from the next scan on (the device plays them on its own
        # clock; a plant that had moved on would take late values as one step, which a T7 never plays).
        with self.plant.lock, self.lock:
            self._pumped_at = None  # a request may change what the next pump does, at any time
            return serve()

    def serve_frame(self, fc: int, start: int, address: int, count: int, regs: list[int],
                    values: list[int] | list[bool] | None) -> ExcCodes | None:
        """One read (FC3/4) or write (FC6/16) of the registers, within a :meth:`request`: reads computed into
        ``regs``, writes applied (an MBFB packet's frames come here one by one, in one request)."""
        if fc in (3, 4):
            rc = self._read(address, count, start, regs)
        elif fc in (6, 16) and values is not None:
            rc = self._write_regs(address, cast(list[int], values))  # register values: ints (an MBFB buffer
            # frame's: an integer array)
        else:
            rc = ExcCodes.ILLEGAL_FUNCTION
        if rc:
            self.last_mb_err, self.last_err_frame = int(rc), 0  # an MBFB frame's number: :meth:`frame_failed`
        return rc

    async def action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                     values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Serve reads by computing the registers, writes by applying them (pymodbus stores nothing we use): one
        plain request (:meth:`request` of :meth:`serve_frame`)."""
        return self.request(lambda: self.serve_frame(fc, start, address, count, regs, values))

    def frame_failed(self, number: int, code: int, detail: int = 0) -> None:
        """LAST_ERR_FRAME and LAST_MB_ERR after an MBFB packet ended at frame ``number`` (from 1; 0: a malformed
        or too large packet) with exception ``code``; LAST_ERR_DETAIL ← ``detail`` where the packet, not a
        register, was refused."""
        with self.lock:
            self.last_err_frame, self.last_mb_err = number, code
            if detail:
                self.last_err = detail

    def _read(self, address: int, count: int, start: int, regs: list[int]) -> ExcCodes | None:
        if address == R_FLASH_READ:
            out: list[int] = []
            for _ in range(0, count, 2):
                i = (self.flash_ptr - FLASH_CAL) // 4
                v = self.cal[i] if 0 <= i < len(self.cal) else float("nan")
                out += words(F32, v)
                self.flash_ptr += 4
        elif address == R_TEST + 1 and count == 1:  # [D] TEST: one word from 55101 (its low word)
            out = [TEST_VALUE & 0xFFFF]
        else:
            out = []
            a = address
            while len(out) < count:
                got = self._read_value(a)
                if got is None:
                    return self._illegal()
                w = words(*got)
                out += w
                a += len(w)
        for i in range(count):
            regs[address - start + i] = out[i]
        return None

    def _write_regs(self, address: int, data: list[int] | np.ndarray) -> ExcCodes | None:
        now = self.clock.now()
        if R_O_U16 <= address < R_O_U16 + 4:
            return self._buffer(address - R_O_U16, data, now)
        if isinstance(data, np.ndarray):  # only buffer frames come as arrays; anything else as a list of words
            data = [int(w) for w in data]
        if R_O_F32 <= address < R_O_F32 + 8 and address % 2 == 0:
            k = (address - R_O_F32) // 2
            ch = max((self.outs[k].target - R_DAC) // 2, 0)
            floats = [value_of(F32, data[i:i + 2]) for i in range(0, len(data), 2)]
            return self._buffer(k, [self._code(v, ch) for v in floats], now)
        a, i = address, 0
        while i < len(data):
            reg = REGISTERS.get(a)
            if reg is None or "W" not in reg.access:
                return self._illegal()
            w = data[i:i + reg.words]
            if len(w) < reg.words:
                return self._illegal()
            err = self._apply(a, value_of(reg.kind, w), now)
            if err:
                return err
            a, i = a + reg.words, i + reg.words
        return None

    def _write_dio(self, a: int, value: int) -> None:
        """DIO writes: one line (sets it an output), a port's state or direction (upper byte: inhibits), or all."""
        if R_DIO <= a < R_DIO + N_DIO:
            bit = 1 << (a - R_DIO)
            self.dio_dir |= bit
            self.dio_state = self.dio_state | bit if value else self.dio_state & ~bit
            return
        if a in (R_DIO_STATE, R_DIO_DIR):
            mask, bits = (1 << N_DIO) - 1, int(value)
        else:
            first, n = DIO_PORTS[a - (R_FIO_STATE if a < R_FIO_DIR else R_FIO_DIR)]
            mask = (~(int(value) >> 8) & ((1 << n) - 1)) << first
            bits = (int(value) & 0xFF) << first
        if a in (R_DIO_STATE,) or R_FIO_STATE <= a < R_FIO_STATE + 4:
            self.dio_state = (self.dio_state & ~mask) | (bits & mask)
        else:
            self.dio_dir = (self.dio_dir & ~mask) | (bits & mask)

    def _apply(self, a: int, value: float, now: float) -> ExcCodes | None:
        stream_cfg = R_RATE <= a <= R_EXTDIV or R_SCANLIST <= a < R_SCANLIST + 256
        if stream_cfg and self.streaming:
            return self._fail(E_ACTIVE)
        if a in (R_DAC, R_DAC + 2):
            ch = (a - R_DAC) // 2
            code = self._code(value, ch)
            self.dac_volts[ch] = self._code_volts(code, ch)
            driven = self.streaming and any(self.outs[k].target == a for k in self._out_indices())
            if ch == self.dac and not driven:
                self.plant.set_amplifier_input(float(self.conditioning(np.array([self.dac_volts[ch]]))[0]), at=now)
        elif R_DIO <= a < R_DIO + N_DIO or R_FIO_STATE <= a < R_FIO_STATE + 4 or R_FIO_DIR <= a < R_FIO_DIR + 4 \
                or a in (R_DIO_STATE, R_DIO_DIR):
            self._write_dio(a, int(value))
        elif R_AIN_RANGE <= a < R_AIN_RANGE + 2 * N_AIN_ALL or a == R_AIN_ALL_RANGE:
            # a FLOAT32 register: 0.1 and 0.01 arrive as their nearest float32, not the double
            rng = min(RANGE_GAIN, key=lambda r: abs(r - value))
            if abs(rng - value) > 1e-6 * max(rng, 1e-3):
                self.last_err = E_AIN_RANGE
                return ExcCodes.ILLEGAL_VALUE
            rng = 10.0 if rng == 0 else rng
            if a == R_AIN_ALL_RANGE:
                self.ain_range = [rng] * N_AIN_ALL
            else:
                self.ain_range[(a - R_AIN_RANGE) // 2] = rng
        elif R_AIN_NEG <= a < R_AIN_NEG + N_AIN_ALL:
            self.ain_neg[a - R_AIN_NEG] = int(value)
        elif R_AIN_RES <= a < R_AIN_RES + N_AIN_ALL or a == R_AIN_ALL_RES:
            if not 0 <= value <= resolution.MAX_INDEX:
                self.last_err = E_AIN_RESOLUTION
                return ExcCodes.ILLEGAL_VALUE
            if a == R_AIN_ALL_RES:
                self.ain_res = [int(value)] * N_AIN_ALL
            else:
                self.ain_res[a - R_AIN_RES] = int(value)
        elif a == R_RATE:
            self.regs[a] = value
            self.rate = 10e6 / max(round(10e6 / value), 1) if value > 152.588 else float(value)
        elif a in self.regs:
            self.regs[a] = value
        elif R_SCANLIST <= a < R_SCANLIST + 256:
            self.scanlist[(a - R_SCANLIST) // 2] = int(value)
        elif a == R_ENABLE:
            if value:
                err = self._start_stream()
                return self._fail(err) if err else None
            if not self.streaming:
                return self._fail(E_NOT_RUNNING)
            self._catch_up(now)
            if not self.streaming:  # the catch-up found the device had ended the stream itself (2943)
                return self._fail(E_NOT_RUNNING)
            ended = self._burst_ended()
            self._send(final=ended)  # the packets filled by now leave first (a twin pumping on demand holds them)
            if ended:  # a burst that ended before this request had stopped: as if the pump had seen it end
                return self._fail(E_NOT_RUNNING)
            self._stop_stream(now)
        elif a in self.tests:
            self.tests[a] = value
        elif a == R_FLASH_PTR:
            self.flash_ptr = int(value)
        elif a in self.watchdog:
            err = self.watchdog.write(a, value)
            if err:
                return self._fail(err)
            self._arm_watchdog()
        elif R_O_TARGET <= a < R_O_ENABLE + 8:
            return self._apply_out(a, int(value), now)
        else:
            return self._illegal()
        return None
