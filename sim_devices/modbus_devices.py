"""Simulated Modbus modules (pymodbus 3.16 ``SimDevice`` with actions), backed by the shared plant.

* :class:`Adam4024Sim` — ADAM-4024 analog outputs; the amplifier's channel drives the TREK input;
* :class:`Adam4017PSim` — ADAM-4017+ analog inputs wired to the TREK voltage and current monitors,
  converting round-robin over the enabled channels at the module's total rate (10 S/s, datasheet); each
  conversion integrates its input over 20 ms (an integrating ADC with 50/60-Hz rejection), so current
  spikes of a few tens of µs, such as a set-point step charging the DEA, read as their mean;
* :class:`Dgt1sSim` — Dini Argeo DGT1S weight transmitter on the load cell: gross/net/status input
  registers, zero and tare through the command register with the processed-command counter.

Register maps as in :mod:`drivers.adam` and :mod:`drivers.dini`. Each module can be put in a device-error
state (``failed``), in which every request is answered with Modbus exception 4 (device failure).
"""

from __future__ import annotations

import math
import threading
from collections import deque

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.adam import REG_CHANNEL_ENABLE, REG_MODULE_NAME, REG_TYPE_CODE, REG_VALUE, RawScale
from drivers.dini import (
    CMD_PRESET_TARE,
    CMD_TARE,
    CMD_ZERO,
    HR_COMMAND,
    HR_PARAM1,
    IR_GROSS,
    ST_GROSS_NEG,
    ST_NET_NEG,
    ST_OVERLOAD,
    ST_STABLE,
    ST_TARE,
    ST_UNDERLOAD,
    STANDARD_GRAVITY,
)
from drivers.trek import TrekModel
from sim_devices.clock import Clock
from sim_devices.plant import Plant, PlantBlock

WRITE_FCS = (5, 6, 15, 16, 22, 23)


def _bits(n: int) -> list[SimData]:
    return [SimData(0, count=n, values=False, datatype=DataType.BITS)]


class Adam4024Sim:
    """ADAM-4024 with channel ``amplifier_channel`` wired to the amplifier's analog input."""

    def __init__(self, unit: int, plant: Plant, *, amplifier_channel: int = 0, scale: RawScale | None = None) -> None:
        self.unit = unit
        self.plant = plant
        self.amplifier_channel = amplifier_channel
        self.scale = scale or RawScale(bits=12)
        self.failed = False
        zero = self.scale.to_raw(0.0)
        holding = [SimData(REG_VALUE, count=4, values=zero, datatype=DataType.REGISTERS),
                   SimData(REG_TYPE_CODE, count=4, values=0x32, datatype=DataType.REGISTERS),
                   SimData(REG_MODULE_NAME, values=[0x4024, 0x0000, 0xA200, 0x0000, 0x0000, 0x0000],
                           datatype=DataType.REGISTERS),
                   SimData(REG_CHANNEL_ENABLE, values=0x00FF, datatype=DataType.REGISTERS)]
        self.device = SimDevice(unit, (_bits(4), _bits(1), holding, [SimData(0, values=0)]), action=self.action)

    async def action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                     values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Apply output writes to the plant; refuse writes to read-only registers and out-of-range codes."""
        if self.failed:
            return ExcCodes.DEVICE_FAILURE
        self.plant.feed_watchdog()
        if fc not in WRITE_FCS or values is None:
            return None
        if fc in (5, 15):
            return ExcCodes.ILLEGAL_ADDRESS  # emergency-DI flags are read-only
        for i, raw in enumerate(values):
            reg = address + i
            if reg >= REG_MODULE_NAME and reg < REG_CHANNEL_ENABLE:
                return ExcCodes.ILLEGAL_ADDRESS
            if REG_VALUE <= reg < REG_VALUE + 4 and not 0 <= int(raw) <= self.scale.full:
                return ExcCodes.ILLEGAL_VALUE
        for i, raw in enumerate(values):
            if address + i == REG_VALUE + self.amplifier_channel:
                self.plant.set_amplifier_input(self.scale.to_volts(int(raw)))
        return None


class Adam4017PSim:
    """ADAM-4017+ with the amplifier monitors on ``vmon_channel`` and ``imon_channel``."""

    def __init__(self, unit: int, plant: Plant, clock: Clock, trek: TrekModel, *, vmon_channel: int = 0,
                 imon_channel: int = 1, scale: RawScale | None = None, rate: float = 10.0,
                 noise_volts: float = 0.5e-3, seed: int = 2, integration: float = 0.02) -> None:
        self.unit = unit
        self.plant = plant
        self.clock = clock
        self.trek = trek
        self.vmon_channel = vmon_channel
        self.imon_channel = imon_channel
        self.scale = scale or RawScale(bits=16)
        self.rate = rate
        self.noise_volts = noise_volts
        self.rng = np.random.default_rng(seed)
        self.failed = False
        self.enabled = [vmon_channel, imon_channel]
        self.raw = [self.scale.to_raw(0.0)] * 8
        self.integration = integration
        self._conversion = 0  # index of the next conversion (time = index / rate)
        self._tail = (np.zeros(0), np.zeros(0), np.zeros(0))  # the last `integration` s of (t, V, I)
        self._lock = threading.Lock()
        holding = [SimData(REG_VALUE, count=8, values=self.scale.to_raw(0.0), datatype=DataType.REGISTERS),
                   SimData(REG_TYPE_CODE, count=8, values=0x08, datatype=DataType.REGISTERS),
                   SimData(REG_MODULE_NAME, values=[0x4017, 0x5000, 0xA100, 0x0000, 0x0000, 0x0000],
                           datatype=DataType.REGISTERS),
                   SimData(REG_CHANNEL_ENABLE, values=(1 << vmon_channel) | (1 << imon_channel),
                           datatype=DataType.REGISTERS)]
        self.device = SimDevice(unit, (_bits(1), _bits(1), holding, [SimData(0, values=0)]), action=self.action)
        plant.listeners.append(self._on_block)

    def _on_block(self, block: PlantBlock) -> None:
        with self._lock:
            t_end = float(block.t[-1])
            k_last = math.floor(t_end * self.rate + 0.5 * self.plant.h * self.rate)  # due within half a step: now
            if k_last < self._conversion:
                return
            t_all = np.concatenate([self._tail[0], block.t])
            v_all = np.concatenate([self._tail[1], block.voltage])
            i_all = np.concatenate([self._tail[2], block.current])
            keep = t_all > t_end - self.integration - 1e-12
            self._tail = (t_all[keep], v_all[keep], i_all[keep])
            ks = np.arange(self._conversion, k_last + 1)
            ts = ks / self.rate
            # integrating conversion: the mean over (ts − integration, ts]
            cv = np.concatenate([[0.0], np.cumsum(v_all)])
            ci = np.concatenate([[0.0], np.cumsum(i_all)])
            hi = np.searchsorted(t_all, ts + 1e-12, side="right")
            lo = np.searchsorted(t_all, ts - self.integration + 1e-12, side="right")
            n = np.maximum(hi - lo, 1)
            v = (cv[hi] - cv[lo]) / n / self.trek.vmon_ratio
            i = (ci[hi] - ci[lo]) / n / self.trek.imon_ratio
            noise = self.rng.normal(0.0, self.noise_volts, ks.size)
            for k, vk, ik, nk in zip(ks, v, i, noise, strict=True):
                ch = self.enabled[int(k) % len(self.enabled)]
                value = (vk if ch == self.vmon_channel else ik if ch == self.imon_channel else 0.0) + nk
                self.raw[ch] = self.scale.to_raw(value)  # the module saturates at its range
            self._conversion = k_last + 1

    async def action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                     values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Fill the input registers with the latest conversions on reads; channel-enable writes re-plan."""
        if self.failed:
            return ExcCodes.DEVICE_FAILURE
        if fc in WRITE_FCS and values is not None:
            for i, raw in enumerate(values):
                reg = address + i
                if reg < REG_TYPE_CODE or REG_MODULE_NAME <= reg < REG_CHANNEL_ENABLE:
                    return ExcCodes.ILLEGAL_ADDRESS
                if reg == REG_CHANNEL_ENABLE:
                    with self._lock:
                        self.enabled = [c for c in range(8) if int(raw) >> c & 1] or [self.vmon_channel]
            return None
        if fc in (3, 4) and address < REG_VALUE + 8:
            self.plant.advance_to(self.clock.now())
            with self._lock:
                for ch in range(8):
                    idx = REG_VALUE + ch - start
                    if 0 <= idx < len(regs):
                        regs[idx] = self.raw[ch]
        return None


class Dgt1sSim:
    """DGT1S weight transmitter reading the plant's load-cell force."""

    def __init__(self, unit: int, plant: Plant, clock: Clock, *, division: float = 0.001, capacity: float = 5.0,
                 g: float = STANDARD_GRAVITY, rate: float = 100.0, noise: float = 0.0002, zero_band: float = 0.02,
                 stable_divisions: float = 2.0, stable_window: float = 0.3, seed: int = 3) -> None:
        self.unit = unit
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
        self.rng = np.random.default_rng(seed)
        self.failed = False
        self.zero_kg = 0.0
        self.tare_kg = 0.0
        self.tare_active = False
        self.counter = 0
        self.last_command = 0
        self.last_result = 0
        self.raw_kg = 0.0  # latest conversion, before zero
        self._recent: deque[tuple[float, float]] = deque()
        self._conversion = 0
        self._lock = threading.Lock()
        inputs = [SimData(0, count=7, values=0, datatype=DataType.REGISTERS),
                  SimData(110, count=4, values=0, datatype=DataType.REGISTERS)]
        holding = [SimData(0, count=5, values=0, datatype=DataType.REGISTERS)]
        self.device = SimDevice(unit, (_bits(1), _bits(1), holding, inputs), action=self.action)
        plant.listeners.append(self._on_block)

    def _on_block(self, block: PlantBlock) -> None:
        with self._lock:
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

    def _execute(self, command: int, param1: int) -> int:
        gross = self.gross()
        if command == CMD_ZERO:
            if not self.stable:
                return 1
            if abs(self.raw_kg) > self.zero_band * self.capacity:
                return 2
            self.zero_kg = self.raw_kg
            return 0
        if command == CMD_TARE:
            if not self.stable:
                return 1
            if abs(gross) > self.capacity:
                return 3
            self.tare_kg, self.tare_active = gross, True
            return 0
        self.tare_kg, self.tare_active = param1 * self.division, True  # preset tare
        return 0

    async def action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                     values: list[int] | list[bool] | None) -> ExcCodes | None:
        """Fill gross/net/status on reads; execute commands written to 40001."""
        if self.failed:
            return ExcCodes.DEVICE_FAILURE
        self.plant.advance_to(self.clock.now())
        if fc in WRITE_FCS and values is not None:
            if address <= HR_COMMAND < address + len(values):
                command = int(values[HR_COMMAND - address])
                if command not in (0, CMD_ZERO, CMD_TARE, CMD_PRESET_TARE):
                    return ExcCodes.ILLEGAL_VALUE
                if command:
                    param1 = (regs[HR_PARAM1 - start] << 16) | regs[HR_PARAM1 + 1 - start]
                    with self._lock:
                        self.last_result = self._execute(command, param1)
                        self.last_command = command
                        self.counter = (self.counter + 1) & 0x0F
            return None
        if fc == 4:
            with self._lock:
                gross = self.gross()
                net = gross - (self.tare_kg if self.tare_active else 0.0)
                g_counts = min(round(abs(gross) / self.division), 0xFFFFFFFF)
                n_counts = min(round(abs(net) / self.division), 0xFFFFFFFF)
                status = (ST_NET_NEG if net < 0 else 0) | (ST_GROSS_NEG if gross < 0 else 0)
                status |= ST_STABLE if self.stable else 0
                status |= ST_OVERLOAD if gross > self.capacity else 0
                status |= ST_UNDERLOAD if gross < -self.capacity else 0
                status |= ST_TARE if self.tare_active else 0
                block = [g_counts >> 16, g_counts & 0xFFFF, n_counts >> 16, n_counts & 0xFFFF, status,
                         (self.last_command << 8) | (self.last_result << 4) | self.counter, 0]
            for i, v in enumerate(block):
                idx = IR_GROSS + i - start
                if 0 <= idx < len(regs):
                    regs[idx] = v
        return None
