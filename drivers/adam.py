"""Advantech ADAM-4024 (4 analog outputs) and ADAM-4017+ (8 analog inputs), Modbus RTU register maps.

ADAM-4000 manual, appendix G (Modbus mapping), 1-based register numbers → 0-based protocol addresses:

ADAM-4024: 40001–40004 output value ch0–3 (R/W) → 0–3; 40201–40204 type code → 200–203;
           40211/40212 module name (0x4024, 0x0000) → 210/211; 40213/40214 version; 40215 comm-safety enable;
           40216 comm-safety flag; 40221 channel enable → 220; coils 00001–00004 emergency-DI flags.
ADAM-4017+: 40001–40008 input value ch0–7 → 0–7; 40201–40208 type code; 40211/40212 module name (0x4017,
           0x5000 = "P"); 40221 channel enable.

The raw data format of the value registers is not in the pages we could read. Default assumption (change
``raw_format``/``bits`` in the rig file after checking the unit): offset binary over the range,
ADAM-4024 12-bit (0 = −10 V, 4095 = +10 V), ADAM-4017+ 16-bit (0 = −10 V, 65535 = +10 V).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from drivers.errors import LimitError, ProtocolError
from drivers.modbus_link import ModbusLink

REG_VALUE = 0
REG_MODULE_NAME = 210
REG_SAFETY_ENABLE = 214  # 40215 communication-safety (watchdog) enable: 1 = on (App. G p. G-7)
REG_SAFETY_FLAG = 215  # 40216 communication-safety flag: 1 once the module's watchdog has fired
REG_CHANNEL_ENABLE = 220  # 40221 ADAM-4017+ channel enable: bit c set = channel c converted
A17_RATE_HZ = 10.0  # ADAM-4017+ conversions per second, all enabled channels in turn (ADAM-4000 manual, 4017+ specs)


@dataclass(frozen=True)
class RawScale:
    """Linear mapping raw register ↔ volts over [lo, hi] V with ``bits`` resolution.

    offset: raw 0 = lo, raw 2^bits − 1 = hi; twos: signed raw, ±(2^(bits−1) − 1) = ±hi (symmetric ranges).
    """

    lo: float = -10.0
    hi: float = 10.0
    bits: int = 16
    raw_format: Literal["offset", "twos"] = "offset"

    @property
    def full(self) -> int:
        """Largest raw code (offset format)."""
        return (1 << self.bits) - 1

    def to_raw(self, volts: float) -> int:
        """Volts → register value (rounded, clipped to the range)."""
        v = min(max(volts, self.lo), self.hi)
        if self.raw_format == "offset":
            return round((v - self.lo) / (self.hi - self.lo) * self.full)
        half = (1 << (self.bits - 1)) - 1
        return round(v / self.hi * half) & 0xFFFF

    def to_volts(self, raw: int) -> float:
        """Register value → volts."""
        if self.raw_format == "offset":
            return self.lo + (raw & self.full) / self.full * (self.hi - self.lo)
        half = (1 << (self.bits - 1)) - 1
        signed = raw - 0x10000 if raw & 0x8000 else raw
        return signed / half * self.hi

    def neighbours(self, raw: int) -> list[int]:
        """``raw`` first, then the codes of the range one step below and above it."""
        if self.raw_format == "offset":
            return [raw] + [c for c in (raw - 1, raw + 1) if 0 <= c <= self.full]
        half = (1 << (self.bits - 1)) - 1
        signed = raw - 0x10000 if raw & 0x8000 else raw
        return [raw] + [c & 0xFFFF for c in (signed - 1, signed + 1) if -half <= c <= half]


class AdamModule:
    """Common part: module name and version registers."""

    expected_name = 0x0000

    def __init__(self, link: ModbusLink, unit: int, name: str) -> None:
        self.link = link
        self.unit = unit
        self.name = name

    def module_name(self) -> str:
        """Module name from 40211/40212, e.g. '4024' or '4017P'."""
        hi, lo = self.link.read_holding(self.unit, REG_MODULE_NAME, 2)
        text = f"{hi:04X}" + ("P" if lo == 0x5000 else "")
        if self.expected_name and hi != self.expected_name:
            raise ProtocolError(self.name, f"unit {self.unit} is ADAM-{text}, expected ADAM-{self.expected_name:04X}")
        return text


class Adam4024(AdamModule):
    """ADAM-4024 analog output module."""

    expected_name = 0x4024

    def __init__(self, link: ModbusLink, unit: int, name: str = "ao", scale: RawScale | None = None) -> None:
        super().__init__(link, unit, name)
        self.scale = scale or RawScale(bits=12)

    def write_volts(self, channel: int, volts: float, *, always_send: bool = False) -> int:
        """Set output ``channel`` (0–3) to ``volts``; returns the raw code written.

        ``always_send``: goes out even after a stop request (see :meth:`ModbusLink.write_register`)."""
        if not (math.isfinite(volts) and self.scale.lo <= volts <= self.scale.hi):
            raise LimitError(self.name, f"{volts:g} V outside the output range "
                             f"[{self.scale.lo:g}, {self.scale.hi:g}] V")
        return self.write_raw(channel, self.scale.to_raw(volts), always_send=always_send)

    def write_raw(self, channel: int, raw: int, *, always_send: bool = False) -> int:
        """Write the register value ``raw`` (a code the caller chose, :class:`RawScale`) to output ``channel``."""
        if not 0 <= channel <= 3:
            raise ValueError(f"{self.name}: ADAM-4024 has channels 0–3, got {channel}")
        if not 0 <= raw <= 0xFFFF:
            raise ValueError(f"{self.name}: register value {raw} outside 0…65535")
        self.link.write_register(self.unit, REG_VALUE + channel, raw, always_send=always_send)
        return raw

    def safety_enabled(self) -> int:
        """The communication-safety (watchdog) enable register 40215 as the module reports it: 1 = on, 0 = off
        (App. G p. G-7; any other value is not one the manual gives)."""
        return self.link.read_holding(self.unit, REG_SAFETY_ENABLE, 1)[0]

    def safety_flag(self) -> bool:
        """Whether the module's communication watchdog has fired since the flag was last cleared (40216)."""
        return self.link.read_holding(self.unit, REG_SAFETY_FLAG, 1)[0] != 0

    def clear_safety_flag(self) -> None:
        """Clear 40216 (writing 0: the manual pages read do not say more; the twin follows that)."""
        self.link.write_register(self.unit, REG_SAFETY_FLAG, 0)

    def read_volts(self, channel: int) -> float:
        """Read back the output value of ``channel`` [V]."""
        return self.scale.to_volts(self.link.read_holding(self.unit, REG_VALUE + channel, 1)[0])


class Adam4017P(AdamModule):
    """ADAM-4017+ analog input module."""

    expected_name = 0x4017

    def __init__(self, link: ModbusLink, unit: int, name: str = "ai", scale: RawScale | None = None) -> None:
        super().__init__(link, unit, name)
        self.scale = scale or RawScale(bits=16)

    def enabled_channels(self) -> list[int]:
        """The channels the module converts (40221's bits), in turn at :data:`A17_RATE_HZ` in all."""
        (mask,) = self.link.read_holding(self.unit, REG_CHANNEL_ENABLE, 1)
        return [c for c in range(8) if mask >> c & 1]

    def read_volts(self, first: int, count: int = 1) -> list[float]:
        """Read ``count`` consecutive input channels starting at ``first`` [V]."""
        if not (0 <= first and first + count <= 8):
            raise ValueError(f"{self.name}: ADAM-4017+ has channels 0–7, got {first}..{first + count - 1}")
        return [self.scale.to_volts(r) for r in self.link.read_holding(self.unit, REG_VALUE + first, count)]
