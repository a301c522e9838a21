"""Simulated Modbus modules backed by the shared plant, each owning its register map.

* :class:`Adam4024Sim` — ADAM-4024 analog outputs; the amplifier's channel drives the TREK input; the
  communication-safety (watchdog) registers reflect the module's watchdog;
* :class:`Adam4017PSim` — ADAM-4017+ analog inputs wired to the TREK voltage and current monitors,
  converting round-robin over the enabled channels at the module's total rate (10 S/s, datasheet); each
  conversion integrates its input over 20 ms (an integrating ADC with 50/60-Hz rejection);
* :class:`Dgt1sSim` — Dini Argeo DGT1S weight transmitter on the load cell: gross/net/status input
  registers, µV per channel, zero and tare through the command register with the processed-command counter.

Written from the manuals, not from :mod:`drivers.adam` / :mod:`drivers.dini` (no constant is shared):
ADAM-4000 series manual, appendix G "Modbus mapping", ADAM-4024 table p. G-7 and ADAM-4017+ table
(manualsdir 33278, page 421 and neighbours); Dini Argeo DGT4X/DGT1S manuals (easymanua.ls dgt4x p. 57 input
registers, p. 13 command register; manualslook 672172 p. 10 DGT1S examples); Modbus Application Protocol
v1.1b3 §7 (exception codes). Register numbers below are the manuals' 1-based numbers; the protocol address is
the number minus 40001 (holding) or 30001 (input). ``[assumed]`` marks choices no source settles.

A module serves :meth:`read` / :meth:`write` by function code; :mod:`sim_devices.modbus_host` frames them.
Each module can be put in a device-error state (``failed``), answered with exception 04 (device failure).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from bench.core.clock import Clock
from bench.core.plant import Plant, PlantBlock

# Modbus exception codes (Modbus Application Protocol v1.1b3 §7)
ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 0x01, 0x02, 0x03, 0x04


class ModbusException(Exception):  # noqa: N818 - the protocol's name
    """A request the module answers with an exception response."""

    def __init__(self, code: int) -> None:
        super().__init__(f"Modbus exception {code}")
        self.code = code


@dataclass(frozen=True)
class Scale:
    """Raw register ↔ volts over [lo, hi]. ``offset``: 0 = lo, 2^bits − 1 = hi; ``twos``: signed,
    ±(2^(bits−1) − 1) = ±hi. [assumed] the ADAM manual pages read do not give the raw data format."""

    lo: float = -10.0
    hi: float = 10.0
    bits: int = 16
    raw_format: str = "offset"

    @property
    def full(self) -> int:
        """Largest raw code (offset format)."""
        return (1 << self.bits) - 1

    def to_raw(self, volts: float) -> int:
        """Volts → register (rounded, saturated at the range)."""
        v = min(max(volts, self.lo), self.hi)
        if self.raw_format == "offset":
            return round((v - self.lo) / (self.hi - self.lo) * self.full)
        return round(v / self.hi * ((1 << (self.bits - 1)) - 1)) & 0xFFFF

    def to_volts(self, raw: int) -> float:
        """Register → volts."""
        if self.raw_format == "offset":
            return self.lo + (raw & self.full) / self.full * (self.hi - self.lo)
        signed = raw - 0x10000 if raw & 0x8000 else raw
        return signed / ((1 << (self.bits - 1)) - 1) * self.hi

    def valid(self, raw: int) -> bool:
        """Whether ``raw`` is a code of this scale."""
        if self.raw_format == "offset":
            return 0 <= raw <= self.full
        half = (1 << (self.bits - 1)) - 1
        signed = raw - 0x10000 if raw & 0x8000 else raw
        return -half <= signed <= half


class ModbusModule:
    """A unit on a bus: tables of registers by 0-based address; subclasses add behaviour."""

    turnaround: float = 1e-3  # request received → reply starts [assumed: no figure in the pages read]

    def __init__(self, unit: int) -> None:
        self.unit = unit
        self.failed = False
        self.lock = threading.RLock()
        self.holding: dict[int, int] = {}
        self.inputs: dict[int, int] = {}
        self.coils: dict[int, int] = {}
        self.read_only: set[int] = set()  # holding addresses refused on write

    def read(self, fc: int, address: int, count: int) -> list[int]:
        """Registers (FC3/FC4) or bits (FC1/FC2) at ``address``; ModbusException if unmapped."""
        table = {1: self.coils, 2: self.coils, 3: self.holding, 4: self.inputs}.get(fc)
        if table is None:
            raise ModbusException(ILLEGAL_FUNCTION)
        self.refresh(fc, address, count)
        with self.lock:
            try:
                return [table[a] for a in range(address, address + count)]
            except KeyError:
                raise ModbusException(ILLEGAL_ADDRESS) from None

    def write(self, fc: int, address: int, values: list[int]) -> None:
        """FC5/6/15/16 write; ModbusException if unmapped, read-only or out of range."""
        if fc in (5, 15):
            raise ModbusException(ILLEGAL_ADDRESS)  # the modules' coils/flags are read-only [assumed]
        addresses = range(address, address + len(values))
        with self.lock:
            if any(a not in self.holding or a in self.read_only for a in addresses):
                raise ModbusException(ILLEGAL_ADDRESS)
            self.check_write(address, values)
            for a, v in zip(addresses, values, strict=True):
                self.holding[a] = v
        self.written(address, values)

    def heard(self, at: float | None = None) -> None:
        """Any request addressed to this unit arrived, at line time ``at`` (None: now); watchdogs are fed here."""

    def refresh(self, fc: int, address: int, count: int) -> None:
        """Bring computed registers up to date before a read."""

    def check_write(self, address: int, values: list[int]) -> None:
        """Raise ModbusException for values the module refuses."""

    def written(self, address: int, values: list[int]) -> None:
        """React to an accepted write."""


# ------------------------------------------------------------------ ADAM-4024 (App. G p. G-7)
A24_OUTPUT = 0  # 40001–40004 analog output value ch0–3 (R/W)
A24_TYPE_CODE = 200  # 40201–40204 output type code ch0–3
A24_MODULE_NAME = 210  # 40211/40212 module name: 0x4024, 0x0000
A24_VERSION = 212  # 40213/40214 firmware version
A24_SAFETY_ENABLE = 214  # 40215 communication-safety (WDT) enable: 1 = on
A24_SAFETY_FLAG = 215  # 40216 communication-safety flag: 1 = the watchdog fired (safe values output)
A24_CHANNEL_ENABLE = 220  # 40221
A24_TYPE_PM10V = 0x32  # ±10 V output type code [assumed code value]


class Adam4024Sim(ModbusModule):
    """ADAM-4024 with channel ``amplifier_channel`` wired to the amplifier's analog input.

    Communication safety (module watchdog): with no request for ``watchdog_s`` the outputs go to their safe
    value (0 V); 40215 reads 1 while the watchdog is on, 40216 reads 1 once it has fired and the output
    registers then read back the safe value's code. [assumed] 40216 is cleared by writing 0 to it; a new
    output write takes effect at once (the manual pages read do not say whether the flag must be cleared first).
    """

    def __init__(self, unit: int, plant: Plant, clock: Clock | None = None, *, amplifier_channel: int = 0,
                 scale: Scale | None = None, watchdog_s: float | None = None) -> None:
        super().__init__(unit)
        self.plant = plant
        self.clock = clock or plant.clock
        self.amplifier_channel = amplifier_channel
        self.scale = scale or Scale(bits=12)
        self.safe_code = self.scale.to_raw(0.0)
        plant.input_watchdog = watchdog_s
        self._trips_seen = plant.watchdog_trips
        self.holding.update({A24_OUTPUT + c: self.safe_code for c in range(4)})
        self.holding.update({A24_TYPE_CODE + c: A24_TYPE_PM10V for c in range(4)})
        self.holding.update({A24_MODULE_NAME: 0x4024, A24_MODULE_NAME + 1: 0x0000, A24_VERSION: 0xA200,
                             A24_VERSION + 1: 0x0000, A24_SAFETY_ENABLE: int(watchdog_s is not None),
                             A24_SAFETY_FLAG: 0, A24_CHANNEL_ENABLE: 0x000F})
        self.read_only = {A24_MODULE_NAME, A24_MODULE_NAME + 1, A24_VERSION, A24_VERSION + 1}
        self.coils.update({c: 0 for c in range(4)})  # 00001–00004 emergency-DI flags (read-only)
        self._period = watchdog_s or 1.0
        self._at = self.clock.now()  # the instant the request being served arrived (set by heard)

    def heard(self, at: float | None = None) -> None:
        """Any request to the module feeds its communication watchdog (after noting a trip that came first).

        Everything a request does happens at the instant it arrived, ``at`` (the line's time of the request's end;
        kept in :attr:`_at` for the request's read or write: the bus serves one request at a time, under its line's
        lock): on a virtual clock the host may stop waiting for the reply (a dropped link) and move the clock on
        while this thread still works, and a write applied at that later time would land after the watchdog's
        deadline and keep the output up past it [chosen: the modules act within milliseconds of a request]."""
        self._at = self.clock.now() if at is None else at
        self.refresh(3, 0, 0)
        self.plant.feed_watchdog(self._at)

    def refresh(self, fc: int, address: int, count: int) -> None:
        """After the watchdog fired: flag set, outputs read back their safe value (as of the request's instant)."""
        self.plant.advance_to(self._at)
        with self.lock:
            if self.plant.watchdog_trips > self._trips_seen:
                self._trips_seen = self.plant.watchdog_trips
                self.holding[A24_SAFETY_FLAG] = 1
                self.holding[A24_OUTPUT + self.amplifier_channel] = self.safe_code

    def check_write(self, address: int, values: list[int]) -> None:
        """Output codes must be codes of the range; enable and flag take 0 or 1."""
        for a, v in zip(range(address, address + len(values)), values, strict=True):
            if A24_OUTPUT <= a < A24_OUTPUT + 4 and not self.scale.valid(v):
                raise ModbusException(ILLEGAL_VALUE)
            if a in (A24_SAFETY_ENABLE, A24_SAFETY_FLAG) and v not in (0, 1):
                raise ModbusException(ILLEGAL_VALUE)

    def written(self, address: int, values: list[int]) -> None:
        """Output writes drive the plant; the safety enable switches the watchdog."""
        for a, v in zip(range(address, address + len(values)), values, strict=True):
            if a == A24_OUTPUT + self.amplifier_channel:
                self.refresh(3, a, 1)  # a trip before this write is accounted for first
                with self.lock:
                    self.holding[a] = v
                self.plant.set_amplifier_input(self.scale.to_volts(v), at=self._at)
            elif a == A24_SAFETY_ENABLE:
                self.plant.input_watchdog = self._period if v else None


# ------------------------------------------------------------------ ADAM-4017+ (App. G)
A17_INPUT = 0  # 40001–40008 analog input value ch0–7 (read-only)
A17_TYPE_CODE = 200  # 40201–40208 input type code
A17_MODULE_NAME = 210  # 40211/40212 module name: 0x4017, 0x5000 ("P")
A17_VERSION = 212  # 40213/40214
A17_CHANNEL_ENABLE = 220  # 40221 channel enable bit mask
A17_TYPE_PM10V = 0x08  # ±10 V input type code [assumed code value]


class Adam4017PSim(ModbusModule):
    """ADAM-4017+ with the amplifier monitors on ``vmon_channel`` and ``imon_channel``."""

    def __init__(self, unit: int, plant: Plant, clock: Clock, *, vmon_ratio: float, imon_ratio: float,
                 vmon_channel: int = 0, imon_channel: int = 1, scale: Scale | None = None, rate: float = 10.0,
                 noise_volts: float = 0.5e-3, seed: int = 2, integration: float = 0.02) -> None:
        """``rate``: conversions per second over all enabled channels (datasheet: 10 S/s);
        ``vmon_ratio`` / ``imon_ratio``: amplifier output (V, A) per monitor volt."""
        super().__init__(unit)
        self.plant = plant
        self.clock = clock
        self.vmon_ratio, self.imon_ratio = vmon_ratio, imon_ratio
        self.vmon_channel = vmon_channel
        self.imon_channel = imon_channel
        self.scale = scale or Scale(bits=16)
        self.rate = rate
        self.noise_volts = noise_volts
        self.rng = np.random.default_rng(seed)
        self.enabled = [vmon_channel, imon_channel]
        self.raw = [self.scale.to_raw(0.0)] * 8
        self.integration = integration
        self._conversion = 0  # index of the next conversion (time = index / rate)
        self._tail = (np.zeros(0), np.zeros(0), np.zeros(0))  # the last `integration` s of (t, V, I)
        self.holding.update({A17_INPUT + c: self.raw[c] for c in range(8)})
        self.holding.update({A17_TYPE_CODE + c: A17_TYPE_PM10V for c in range(8)})
        self.holding.update({A17_MODULE_NAME: 0x4017, A17_MODULE_NAME + 1: 0x5000, A17_VERSION: 0xA100,
                             A17_VERSION + 1: 0x0000,
                             A17_CHANNEL_ENABLE: (1 << vmon_channel) | (1 << imon_channel)})
        self.read_only = {A17_INPUT + c for c in range(8)} | {A17_MODULE_NAME, A17_MODULE_NAME + 1, A17_VERSION,
                                                               A17_VERSION + 1}
        self.coils[0] = 0
        plant.listeners.append(self._on_block)

    def _on_block(self, block: PlantBlock) -> None:
        """Convert what is due by the block's end. Every block joins the tail first, also one with no conversion
        due: the plant's blocks follow the host's requests (a 5-ms set-point tick each), and a tail kept only from
        blocks with a conversion left the window (ts − T, ts] holding just the last block, so a charging pulse
        read as its charge over that block's few ms instead of over T."""
        with self.lock:
            t_end = float(block.t[-1])
            t_all = np.concatenate([self._tail[0], block.t])
            v_all = np.concatenate([self._tail[1], block.voltage])
            i_all = np.concatenate([self._tail[2], block.current])
            keep = t_all > t_end - self.integration - 1e-12
            self._tail = (t_all[keep], v_all[keep], i_all[keep])
            k_last = math.floor(t_end * self.rate + 0.5 * self.plant.h * self.rate)  # due within half a step: now
            if k_last < self._conversion:
                return
            ks = np.arange(self._conversion, k_last + 1)
            ts = ks / self.rate
            cv = np.concatenate([[0.0], np.cumsum(v_all)])  # integrating conversion: mean over (ts − T, ts]
            ci = np.concatenate([[0.0], np.cumsum(i_all)])
            hi = np.searchsorted(t_all, ts + 1e-12, side="right")
            lo = np.searchsorted(t_all, ts - self.integration + 1e-12, side="right")
            n = np.maximum(hi - lo, 1)
            v = (cv[hi] - cv[lo]) / n / self.vmon_ratio
            i = (ci[hi] - ci[lo]) / n / self.imon_ratio
            noise = self.rng.normal(0.0, self.noise_volts, ks.size)
            for k, vk, ik, nk in zip(ks, v, i, noise, strict=True):
                ch = self.enabled[int(k) % len(self.enabled)]
                value = (vk if ch == self.vmon_channel else ik if ch == self.imon_channel else 0.0) + nk
                self.raw[ch] = self.scale.to_raw(value)  # the module saturates at its range
            self._conversion = k_last + 1

    def refresh(self, fc: int, address: int, count: int) -> None:
        """Latest conversions into 40001–40008."""
        if fc == 3 and address < A17_INPUT + 8:
            self.plant.advance_to(self.clock.now())
            with self.lock:
                self.holding.update({A17_INPUT + c: self.raw[c] for c in range(8)})

    def written(self, address: int, values: list[int]) -> None:
        """A new channel-enable mask re-plans the round robin."""
        for a, v in zip(range(address, address + len(values)), values, strict=True):
            if a == A17_CHANNEL_ENABLE:
                with self.lock:
                    self.enabled = [c for c in range(8) if int(v) >> c & 1] or [self.vmon_channel]


# ------------------------------------------------------------------ Dini Argeo DGT1S (DGT4X manual p. 57, p. 13)
DGT_GROSS = 0  # 30001–30002 gross weight, 32-bit MSW first, absolute value in divisions
DGT_NET = 2  # 30003–30004 net weight
DGT_STATUS = 4  # 30005 status bits
DGT_COMMAND_STATUS = 5  # 30006 high byte last command, low byte: bits 4–7 result, bits 0–3 counter
DGT_OUTPUTS = 6  # 30007 output status
DGT_MICROVOLT = 110  # 30111–30114 µV per channel
ST_NET_NEG, ST_GROSS_NEG, ST_STABLE, ST_UNDERLOAD, ST_OVERLOAD, ST_TARE, ST_UNLOADED = 1, 2, 4, 8, 16, 32, 128
DGT_COMMAND = 0  # 40001 command register
DGT_PARAM1 = 1  # 40002–40003 parameter 1 (absolute, MSB first)
DGT_PARAM2 = 3  # 40004–40005 parameter 2
CMD_NONE, CMD_ZERO, CMD_TARE, CMD_PRESET_TARE = 0x00, 0x01, 0x02, 0x03
CMD_SETPOINT1, CMD_SETPOINT2, CMD_OUTPUTS, CMD_REBOOT = 0x0A, 0x0B, 0x19, 0x22
# Result nibble of 30006 [assumed: the result codes are not in the pages read]
RES_DONE, RES_UNSTABLE, RES_ZERO_RANGE, RES_OVERLOAD = 0, 1, 2, 3
STANDARD_GRAVITY = 9.80665


class Dgt1sSim(ModbusModule):
    """DGT1S weight transmitter reading the plant's load-cell force.

    ``sensitivity_mV_per_V`` × ``excitation_V`` is the cell's output at ``capacity`` (30111, µV, signed 16-bit)
    [assumed: 2 mV/V at 5 V; one register per channel, channel 1 wired].
    """

    def __init__(self, unit: int, plant: Plant, clock: Clock, *, division: float = 0.001, capacity: float = 5.0,
                 g: float = STANDARD_GRAVITY, rate: float = 100.0, noise: float = 0.0002, zero_band: float = 0.02,
                 stable_divisions: float = 2.0, stable_window: float = 0.3, seed: int = 3,
                 sensitivity_mV_per_V: float = 2.0, excitation_V: float = 5.0) -> None:
        """``rate``: conversions per second [assumed 100 S/s, the DGT1S offers several rates]."""
        super().__init__(unit)
        self.plant = plant
        self.clock = clock
        self.division = division
        self.capacity = capacity
        self.g = g
        self.rate = rate
        self.noise = noise
        self.zero_band = zero_band
        self.stable_divisions = stable_divisions
        self.stable_window = stable_window
        self.full_scale_uV = sensitivity_mV_per_V * excitation_V * 1e3
        self.rng = np.random.default_rng(seed)
        self.zero_kg = 0.0
        self.tare_kg = 0.0
        self.tare_active = False
        self.counter = 0
        self.last_command = 0
        self.last_result = 0
        self.raw_kg = 0.0  # latest conversion, before zero
        self._recent: deque[tuple[float, float]] = deque()
        self._conversion = 0
        self.inputs.update({a: 0 for a in range(7)})
        self.inputs.update({DGT_MICROVOLT + c: 0 for c in range(4)})
        self.holding.update({a: 0 for a in range(5)})
        self.coils[0] = 0
        plant.listeners.append(self._on_block)

    def _on_block(self, block: PlantBlock) -> None:
        with self.lock:
            k_last = math.floor(float(block.t[-1]) * self.rate + 0.5 * self.plant.h * self.rate)
            if k_last < self._conversion:
                return
            ts = np.arange(self._conversion, k_last + 1) / self.rate
            kg = np.interp(ts, block.t, block.force) / self.g + self.rng.normal(0.0, self.noise, ts.size)
            keep = int(self.stable_window * self.rate) + 1
            self._recent.extend(zip(ts[-keep:].tolist(), kg[-keep:].tolist(), strict=True))
            while self._recent and self._recent[0][0] < ts[-1] - self.stable_window:
                self._recent.popleft()
            self.raw_kg = float(kg[-1])
            self._conversion = k_last + 1

    @property
    def stable(self) -> bool:
        """Weight varied by no more than ``stable_divisions`` over the stability window."""
        if not self._recent:
            return True
        w = [x for _, x in self._recent]
        return max(w) - min(w) <= self.stable_divisions * self.division

    def gross(self) -> float:
        """Gross weight [kg] (after zero)."""
        return self.raw_kg - self.zero_kg

    def microvolts(self) -> int:
        """Cell signal of channel 1 [µV] from the load (before zero and tare), signed 16-bit."""
        uv = round(self.raw_kg / self.capacity * self.full_scale_uV)
        return max(-32768, min(32767, uv)) & 0xFFFF

    def _execute(self, command: int, param1: int) -> int:
        gross = self.gross()
        if command == CMD_ZERO:
            if not self.stable:
                return RES_UNSTABLE
            if abs(self.raw_kg) > self.zero_band * self.capacity:
                return RES_ZERO_RANGE
            self.zero_kg = self.raw_kg
            return RES_DONE
        if command == CMD_TARE:
            if not self.stable:
                return RES_UNSTABLE
            if abs(gross) > self.capacity:
                return RES_OVERLOAD
            self.tare_kg, self.tare_active = gross, True
            return RES_DONE
        if command == CMD_PRESET_TARE:
            self.tare_kg, self.tare_active = param1 * self.division, True
        return RES_DONE  # set-points, outputs, reboot: accepted, no effect on the model

    def check_write(self, address: int, values: list[int]) -> None:
        """Unknown command codes are refused with exception 03 [assumed]."""
        known = (CMD_NONE, CMD_ZERO, CMD_TARE, CMD_PRESET_TARE, CMD_SETPOINT1, CMD_SETPOINT2, CMD_OUTPUTS, CMD_REBOOT)
        if address <= DGT_COMMAND < address + len(values) and values[DGT_COMMAND - address] not in known:
            raise ModbusException(ILLEGAL_VALUE)

    def written(self, address: int, values: list[int]) -> None:
        """A command written to 40001 executes and bumps the processed-command counter."""
        if not address <= DGT_COMMAND < address + len(values):
            return
        command = values[DGT_COMMAND - address]
        if command == CMD_NONE:
            return
        self.plant.advance_to(self.clock.now())
        with self.lock:
            param1 = (self.holding[DGT_PARAM1] << 16) | self.holding[DGT_PARAM1 + 1]
            self.last_result = self._execute(command, param1)
            self.last_command = command
            self.counter = (self.counter + 1) & 0x0F

    def refresh(self, fc: int, address: int, count: int) -> None:
        """Gross, net, status, command status and µV from the latest conversion."""
        if fc != 4:
            return
        self.plant.advance_to(self.clock.now())
        with self.lock:
            gross = self.gross()
            net = gross - (self.tare_kg if self.tare_active else 0.0)
            g_counts = min(round(abs(gross) / self.division), 0xFFFFFFFF)
            n_counts = min(round(abs(net) / self.division), 0xFFFFFFFF)
            status = (ST_NET_NEG if net < 0 else 0) | (ST_GROSS_NEG if gross < 0 else 0)
            status |= ST_STABLE if self.stable else 0
            status |= ST_OVERLOAD if gross > self.capacity else 0
            status |= ST_UNDERLOAD if gross < -self.capacity else 0
            status |= ST_TARE if self.tare_active else 0
            status |= ST_UNLOADED if g_counts == 0 else 0
            self.inputs.update({DGT_GROSS: g_counts >> 16, DGT_GROSS + 1: g_counts & 0xFFFF, DGT_NET: n_counts >> 16,
                                DGT_NET + 1: n_counts & 0xFFFF, DGT_STATUS: status,
                                DGT_COMMAND_STATUS: (self.last_command << 8) | (self.last_result << 4) | self.counter,
                                DGT_MICROVOLT: self.microvolts()})
