"""The catalogue's high-voltage statistics of a run (:mod:`bench.storage.catalog` says what they are): computed over
the measured amplifier voltage in groups of :data:`CHUNK` samples, by the catalogue reading a file and by the recorder
as it writes one — the same groups, so the same values bit for bit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HV_THRESHOLD_V = 500.0  # above the monitors' zero offset and noise (a few V), below any drive the protocols use
CHUNK = 1 << 20  # samples evaluated at a time: a long run's statistics in bounded memory


@dataclass
class HvStats:
    hv_time_s: float
    cycles: int
    max_voltage_V: float


class HvAccumulator:
    """The statistics over (t, V) given in pieces of any size, in order: evaluated in groups of :data:`CHUNK`
    samples, as :func:`bench.storage.catalog.hv_statistics` reads a file, so a recorder that feeds it what it writes
    gets the file's statistics bit for bit (the run's end need not read the data back)."""

    def __init__(self, threshold: float = HV_THRESHOLD_V) -> None:
        self.threshold = threshold
        self.hv, self.cycles, self.vmax = 0.0, 0, 0.0
        self.armed = True
        self.prev: tuple[float, float] | None = None  # the last (t, |v|) of the previous chunk
        self._t: list[np.ndarray] = []
        self._v: list[np.ndarray] = []
        self._n = 0

    def add(self, t: np.ndarray, v: np.ndarray) -> None:
        """The next samples (times, measured voltage as stored)."""
        self._t.append(t)
        self._v.append(v)
        self._n += t.size
        chunk = CHUNK
        if self._n >= chunk:
            t_all, v_all = np.concatenate(self._t), np.concatenate(self._v)
            k = 0
            while self._n - k >= chunk:
                self.chunk(t_all[k:k + chunk], v_all[k:k + chunk])
                k += chunk
            self._t, self._v, self._n = [t_all[k:]], [v_all[k:]], self._n - k

    def chunk(self, t_in: np.ndarray, v_in: np.ndarray) -> None:
        """One group of samples (at most :data:`CHUNK`), after those of the groups before."""
        t = np.asarray(t_in, dtype=float)
        v = np.abs(np.asarray(v_in, dtype=float))
        prev, threshold = self.prev, self.threshold
        if prev is not None:
            t, v = np.concatenate(([prev[0]], t)), np.concatenate(([prev[1]], v))
        ok = np.isfinite(v)
        if ok.any():
            self.vmax = max(self.vmax, float(np.max(v, where=ok, initial=-np.inf)))
        above = v > threshold
        self.hv += float(np.sum(np.diff(t)[above[:-1]]))
        first = 1 if prev is not None else 0  # the carried sample was counted in the previous chunk
        cycles_k, self.armed = _rises(v[first:], threshold, self.armed)
        self.cycles += cycles_k
        self.prev = (float(t[-1]), float(v[-1]))

    def stats(self) -> HvStats:
        """The statistics of every sample added (the samples still pending evaluated as the last group)."""
        if self._n:
            self.chunk(np.concatenate(self._t), np.concatenate(self._v))
            self._t, self._v, self._n = [], [], 0
        return HvStats(self.hv, self.cycles, self.vmax)


def _rises(v: np.ndarray, threshold: float, armed: bool) -> tuple[int, bool]:
    """Rises of ``v`` above ``threshold`` while armed; re-armed below threshold/2. Returns (rises, armed at end).

    Only the samples above the threshold or below its half change the state (NaN and the band between change
    nothing): a rise is such a sample above after one below (or after the start, when armed)."""
    high = v > threshold
    known = high | (v < threshold / 2)
    above = high[known]  # the state after each sample that sets it: True = above (disarmed)
    if not above.size:
        return 0, armed
    before = np.concatenate(([not armed], above[:-1]))
    return int(np.count_nonzero(above & ~before)), not bool(above[-1])
