"""Figures of a thesis-style membrane run: per-cycle peaks (creep), residual at zero voltage, lag."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.analysis.cycles import smooth
from bench.core.monitor_chain import widest_band_v

SMOOTH_PERIODS = 50  # the smoothing window is this fraction of a period
NO_DISPLACEMENT_M = 1e-12  # peaks below 1 pm are rounding, not a displacement (no sensor resolves them)
# a step (or run) whose peak |V| stays at or below its monitor's 0-V band was not driven: the band is the largest
# |reading| of a true 0 V (bench.core.monitor_chain.zero_band_v: TREK monitor and DAQ accuracy, rounding and noise).
# Below it a "voltage peak" is the monitor's noise, so a lag from it to the displacement's peak, a creep of the
# response to it, or a fitted parameter of the response means nothing. A run file records its rig (``rig_toml``):
# its analysis takes that rig's own band (:func:`no_drive_v_of`: 15.3 V on a T7 rig, 23.3 V on an ADAM rig). Where
# the rig is not known (`simulate --voltage`, a file whose rig does not read) it takes the widest band of the chains
# a rig can have (bench.core.monitor_chain.widest_band_v), NO_DRIVE_V.
NO_DRIVE_V = widest_band_v()


def no_drive_v_of(attrs: Mapping[str, Any]) -> float:
    """The no-drive level [V] of a run file whose root attributes are ``attrs``: the 0-V band of the monitor chain of
    the rig it records (``rig_toml``, :func:`bench.rig.monitor_band_v`); :data:`NO_DRIVE_V` where it records none,
    one that no longer reads as a rig, or one without an amplifier."""
    from bench.rig import monitor_band_v, rig_from_toml

    text = attrs.get("rig_toml")
    if not isinstance(text, str) or not text.strip():
        return NO_DRIVE_V
    try:
        band = monitor_band_v(rig_from_toml(text))
    except (ValueError, TypeError, KeyError):  # a TOML or validation error (an older schema): not known
        return NO_DRIVE_V
    return NO_DRIVE_V if band is None else band


def undriven(peak_voltage: float, band: float = NO_DRIVE_V) -> bool:
    """Whether a peak |V| [V] is no drive at all (at or below ``band``, the monitor's 0-V band: :data:`NO_DRIVE_V`
    where the rig is not known)."""
    return not abs(peak_voltage) > band


def undriven_note(what: str, peak_voltage: float, band: float = NO_DRIVE_V) -> str:
    """One line saying why ``what``'s drive-dependent figures are not given."""
    return (f"{what}: peak voltage {abs(peak_voltage):.3g} V is within the monitor's 0-V band (≤ {band:.3g} V): "
            "not driven, so lag and creep (figures relative to the drive) are not given")


@dataclass(frozen=True)
class CycleFigures:
    """Per-cycle figures of a periodic unipolar-voltage run.

    peaks [m] and peak_times [s] per cycle; residuals [m] = displacement at the ends of cycles (Φ = 0 for a
    raised cosine); lags [s] = time of the displacement peak minus time of the voltage peak in that cycle.
    """

    peaks: tuple[float, ...]
    peak_times: tuple[float, ...]
    residuals: tuple[float, ...]
    lags: tuple[float, ...]
    whole: int = 0  # number of whole cycles (the first ``whole`` entries of peaks)

    @property
    def creep(self) -> float:
        """Peak growth from the first to the last whole cycle, relative to the first [-]."""
        if self.whole <= 1 or abs(self.peaks[0]) <= NO_DISPLACEMENT_M:
            return 0.0  # one cycle, or no displacement at all (rounding of a model at rest): no creep
        return self.peaks[self.whole - 1] / self.peaks[0] - 1.0


def cycle_figures(t: np.ndarray, displacement: np.ndarray, voltage: np.ndarray, frequency: float,
                  span: tuple[float, float] | None = None) -> CycleFigures:
    """Split a record into periods 1/frequency from the start of ``span`` (the step's start and end on ``t``'s
    clock; None: the record's first and last sample) and take each period's peak, lag and end value. A period is
    whole when it ends within the span and the record reaches its end (to within one sample: a record's last sample
    comes up to one scan before the step's end). Anchored at the first sample, a step starting at the run's start
    (its first scan one scan after it) lost its last whole cycle (an outside tester: creep "–" for two cycles).

    A last, partial period contributes its peak only if it covers ≥ 60 % of a period (past the drive's peak).
    Both records are smoothed first (:func:`bench.analysis.cycles.smooth`, 1/50 period).
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(displacement, dtype=float)
    v = np.asarray(voltage, dtype=float)
    finite = np.isfinite(u)  # a run stopped early (failure) is analysed up to its last valid sample
    t, u, v = t[finite], u[finite], v[finite]
    period = 1.0 / frequency
    origin, stop = (float(t[0]), float(t[-1])) if span is None else span
    reach = float(t[-1]) + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)  # the record's end, one sample on
    # peaks, their times and the residuals from the smoothed records: on a noisy record the largest sample is
    # noise riding on the crest (value biased up, time scattered); a cubic fit over 1/50 period keeps the crest.
    # Each period is smoothed on its own (a step between periods — a new specimen state — is not blurred).
    cycle = np.floor((t - origin) / period + 1e-9)
    u, v = u.copy(), v.copy()
    for k in np.unique(cycle):
        m = cycle == k
        u[m], v[m] = smooth(t[m], u[m], period / SMOOTH_PERIODS), smooth(t[m], v[m], period / SMOOTH_PERIODS)
    peaks, times, residuals, lags = [], [], [], []
    whole_cycles = 0
    k = 0
    while origin + k * period < t[-1]:
        start, end = origin + k * period, origin + (k + 1) * period
        m = (t >= start) & (t < end)
        if m.sum() < 3:  # a period without a record (the laser out of range): none of its figures, on to the next
            k += 1
            continue
        iv = int(np.argmax(v[m]))
        whole = end <= min(stop, reach) + 1e-9
        whole_cycles += whole
        if whole or t[m][-1] - start >= 0.6 * period:
            iu = int(np.argmax(u[m]))
            peaks.append(float(u[m][iu]))
            times.append(float(t[m][iu]))
            lags.append(float(t[m][iu] - t[m][iv]))
        if whole:
            residuals.append(float(np.interp(end, t, u)))
        k += 1
    return CycleFigures(tuple(peaks), tuple(times), tuple(residuals), tuple(lags), whole_cycles)
