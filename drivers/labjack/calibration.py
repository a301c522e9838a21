"""T7 calibration constants: stream codes to volts, volts to DAC codes and back ([E] calibration.c; [A] the DAC
coding, see :mod:`drivers.labjack`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@functools.lru_cache(maxsize=16)
def _ain_table(p: float, n: float, c: float) -> np.ndarray:
    """Volts of every 16-bit stream code: (r − Center)·PSlope at or above the centre, (Center − r)·NSlope below."""
    r = np.arange(65536, dtype=float)
    table = np.where(r < c, (c - r) * n, (r - c) * p)
    table.setflags(write=False)
    return table


@dataclass(frozen=True)
class Calibration:
    """T7 calibration constants in flash order: HS[4]×(PSlope, NSlope, Center, Offset), HR[4]×4, DAC[2]×
    (Slope, Offset), temperature (slope, offset), current sources (10 µA, 200 µA), I_bias."""

    values: tuple[float, ...]

    @classmethod
    def nominal(cls) -> Calibration:
        """LabJack's nominal constants (getNominalCalibration in the example's calibration.c)."""
        hs: list[float] = []
        for g in range(4):
            s = 0.000315805780 * 10.0 ** -g
            hs += [s, -0.000315805800 * 10.0 ** -g, 33523.0, -10.58695652200 * 10.0 ** -g]
        return cls(tuple(hs + hs + [13200.0, 0.0, 13200.0, 0.0, -92.379, 465.129, 10e-6, 200e-6, 0.0]))

    def hs(self, gain: int) -> tuple[float, float, float, float]:
        """(PSlope, NSlope, Center, Offset) of the high-speed converter at gain index 0..3."""
        p, n, c, o = self.values[4 * gain:4 * gain + 4]
        return p, n, c, o

    def dac(self, channel: int) -> tuple[float, float]:
        """(Slope [codes/V], Offset [codes]) of DAC0/DAC1."""
        s, o = self.values[32 + 2 * channel:34 + 2 * channel]
        return s, o

    def ain_volts(self, raw: np.ndarray, gain: int) -> np.ndarray:
        """Stream samples (16-bit binary) to volts (through a table of all 65536 codes), in the shape of ``raw``."""
        p, n, c, _ = self.hs(gain)
        # take: the same gather as indexing the table with the codes, without the indexing machinery (a third less)
        return np.take(_ain_table(p, n, c), np.asarray(raw, dtype=np.uint16))

    def dac_codes(self, volts: np.ndarray, channel: int, within: tuple[float, float] | None = None,
                  bits: int = 12) -> np.ndarray:
        """Volts to 16-bit DAC codes (code = V·Slope + Offset, rounded, clipped).

        ``within`` (lo, hi) [V]: codes are also clipped to those whose ``bits``-bit output (:meth:`dac_volts`) lies
        within [lo, hi] — the nearest such code, so one level toward the inside where a value's own code plays
        just beyond (:meth:`dac_code_range`)."""
        s, o = self.dac(channel)
        codes = np.clip(np.rint(np.asarray(volts, float) * s + o), 0, 0xFFFF)
        if within is not None:
            codes = np.clip(codes, *self.dac_code_range(channel, within, bits))
        return codes.astype(np.uint16)

    def dac_code_range(self, channel: int, within: tuple[float, float], bits: int = 12) -> tuple[int, int]:
        """The 16-bit codes (first, last) whose ``bits``-bit output lies within ``within`` = (lo, hi) [V]: the
        levels inside, each with all its codes (the low ``16 − bits`` bits the converter ignores)."""
        shift = 16 - bits
        levels = np.arange(1 << bits, dtype=np.int64) << shift
        out = self.dac_volts(levels, channel, bits)
        inside = np.flatnonzero((out >= within[0]) & (out <= within[1]))
        if not inside.size:
            raise ValueError(f"no {bits}-bit DAC{channel} level lies within {within[0]:g}…{within[1]:g} V")
        return int(levels[inside[0]]), int(levels[inside[-1]]) | ((1 << shift) - 1)

    def dac_volts(self, codes: np.ndarray, channel: int, bits: int = 12) -> np.ndarray:
        """What a ``bits``-bit DAC outputs for 16-bit codes (low bits ignored)."""
        s, o = self.dac(channel)
        c = (np.asarray(codes, dtype=np.int64) >> (16 - bits)) << (16 - bits)
        return (c - o) / s

