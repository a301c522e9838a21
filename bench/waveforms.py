"""Periodic drive waveforms shared by the models, the simulator and the protocol engine.

All waveforms are functions of time t [s] returning the set-point in the channel's unit (V for voltage,
m for position). Kinds (physics.md §1.4):

* ``raised_cosine``: offset + A (1 − cos 2πft)/2 — unipolar, zero slope at t = 0 (thesis default);
* ``sine``: offset + A sin 2πft — bipolar for a voltage (mechanical response at 2f);
* ``triangle``: offset + A·tri(ft), linear 0 → A → 0 ramps;
* ``square``: offset + A for the first half period, offset for the second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

WaveKind = Literal["raised_cosine", "sine", "triangle", "square"]
WAVE_KINDS: tuple[WaveKind, ...] = ("raised_cosine", "sine", "triangle", "square")


@dataclass(frozen=True)
class Waveform:
    """A periodic set-point ``offset + amplitude·shape(frequency·t)``.

    amplitude and offset are in the channel's unit, frequency in Hz, phase in cycles (0…1).
    """

    kind: WaveKind = "raised_cosine"
    amplitude: float = 0.0
    frequency: float = 1.0
    offset: float = 0.0
    phase: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in WAVE_KINDS:
            raise ValueError(f"unknown waveform kind {self.kind!r}; expected one of {', '.join(WAVE_KINDS)}")
        if not self.frequency > 0:
            raise ValueError(f"waveform frequency must be > 0 Hz, got {self.frequency}")

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        """Value at time(s) t [s] (vectorised)."""
        c = self.frequency * np.asarray(t, dtype=float) + self.phase
        if self.kind == "raised_cosine":
            shape = 0.5 * (1.0 - np.cos(2.0 * np.pi * c))
        elif self.kind == "sine":
            shape = np.sin(2.0 * np.pi * c)
        elif self.kind == "triangle":
            frac = c - np.floor(c)
            shape = 1.0 - np.abs(2.0 * frac - 1.0)
        else:
            frac = c - np.floor(c)
            shape = (frac < 0.5).astype(float)
        return self.offset + self.amplitude * shape

    def scalar(self, t: float) -> float:
        """Fast scalar evaluation (used inside ODE right-hand sides)."""
        c = self.frequency * t + self.phase
        if self.kind == "raised_cosine":
            return self.offset + self.amplitude * 0.5 * (1.0 - math.cos(2.0 * math.pi * c))
        if self.kind == "sine":
            return self.offset + self.amplitude * math.sin(2.0 * math.pi * c)
        frac = c - math.floor(c)
        if self.kind == "triangle":
            return self.offset + self.amplitude * (1.0 - abs(2.0 * frac - 1.0))
        return self.offset + (self.amplitude if frac < 0.5 else 0.0)

    def end_value(self, t: float) -> float:
        """The value a step of this waveform that lasts ``t`` s ends on: the limit from the left at ``t``, where the
        waveform was during the step's last instant. The same as the value at ``t`` but where a square jumps there:
        a square of whole cycles ends low (its value at ``t`` is the next cycle's high, so 3 s of a 1-Hz square
        ended by jumping back to its amplitude and the relax after it ramped down from there) and one of a whole
        number of half cycles plus one high half ends high. A ``t`` within 1e-9 of a half cycle counts as on it
        (``frequency`` 1/9 Hz × 9 s is not exactly 1 in floating point)."""
        c = self.frequency * t + self.phase
        k = round(2.0 * c)
        if abs(2.0 * c - k) <= 1e-9 * max(1.0, abs(2.0 * c)):
            c = k / 2.0
        frac = c - math.ceil(c) + 1.0  # in (0, 1]: the end of a cycle is 1, not 0
        if self.kind == "square":
            return self.offset + (self.amplitude if frac <= 0.5 else 0.0)
        return float(self(t))

    @property
    def peak(self) -> float:
        """Largest absolute value the waveform reaches."""
        lo = self.offset + min(0.0, self.amplitude) if self.kind != "sine" else self.offset - abs(self.amplitude)
        hi = self.offset + max(0.0, self.amplitude) if self.kind != "sine" else self.offset + abs(self.amplitude)
        return max(abs(lo), abs(hi))


def sample(wave: Waveform, t_end: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``wave`` on ``[0, t_end]`` at ``fs`` Hz; returns (t [s], value)."""
    n = round(t_end * fs) + 1
    t = np.arange(n) / fs
    return t, wave(t)
