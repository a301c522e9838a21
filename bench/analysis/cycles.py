"""Cycle-based figures of merit: hysteresis loss of a force–displacement loop, crest-to-trough; smoothing and
phase for noisy records (peak times and lags measured on a fit, not on single noisy samples)."""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter


def smooth(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """``x`` smoothed by a centred cubic Savitzky–Golay fit over ``window_s`` (zero phase: a peak is neither
    shifted nor flattened to third order, so its time and value hold on a noisy record); unchanged when the
    window spans fewer than 5 samples."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    n = int(window_s / dt) if dt > 0 else 0
    n -= 1 - n % 2  # odd
    if n < 5 or x.size < n:
        return x
    return np.asarray(savgol_filter(x, n, 3, mode="interp"))


def phase_lag(t: np.ndarray, x: np.ndarray, y: np.ndarray, frequency: float) -> float:
    """Time [s] by which ``y``'s component at ``frequency`` lags ``x``'s (least-squares fit of offset, drift,
    sine and cosine to each; wrapped to ±half a period) — a lag measured from the whole record, which noise on
    single samples does not move."""
    t = np.asarray(t, dtype=float)
    tau = t - t[0]
    w = 2 * np.pi * frequency * tau
    basis = np.column_stack([np.ones_like(tau), tau, np.sin(w), np.cos(w)])

    def phase(s: np.ndarray) -> float:
        coef, *_ = np.linalg.lstsq(basis, np.asarray(s, dtype=float), rcond=None)
        return float(np.arctan2(coef[3], coef[2]))  # s ≈ A sin(w + φ): φ = atan2(cos part, sin part)

    d = (phase(x) - phase(y) + np.pi) % (2 * np.pi) - np.pi
    return d / (2 * np.pi * frequency)


def last_cycles(t: np.ndarray, frequency: float, n_cycles: int = 1) -> np.ndarray:
    """Boolean mask of the samples in the last ``n_cycles`` whole periods of a record at ``frequency`` [Hz].

    A record sampled every dt over whole periods ends one sample before its last period's end (15 periods at
    2 Hz sampled at 10 kHz end at 7.4999 s, t·f = 14.9998): the span counts up to one sample interval more."""
    t = np.asarray(t, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    n_total = int(np.floor((t[-1] - t[0] + dt) * frequency + 1e-9))
    if n_total < n_cycles:
        raise ValueError(f"record holds {n_total} whole cycles, {n_cycles} requested")
    start = t[0] + (n_total - n_cycles) / frequency
    end = t[0] + n_total / frequency
    inside: np.ndarray = (t >= start - 1e-12) & (t <= end + 1e-12)
    return inside


def hysteresis_loss(x: np.ndarray, force: np.ndarray) -> float:
    """Hysteresis loss of one closed force–displacement cycle: enclosed area / loading work [-].

    The loading branch is where x increases (work done on the actuator, ∫F dx over dx > 0); the enclosed
    area is |∮F dx| (Moretti et al., Table 3). Trapezoidal integration.
    """
    x = np.asarray(x, dtype=float)
    force = np.asarray(force, dtype=float)
    dx = np.diff(x)
    fm = 0.5 * (force[1:] + force[:-1])
    work = fm * dx
    loading = float(np.sum(work[dx > 0]))
    if loading <= 0:
        raise ValueError("loading work is not positive: the cycle has no loading branch with F > 0")
    return abs(float(np.sum(work))) / loading


def crest_to_trough(t: np.ndarray, signal: np.ndarray, frequency: float | None = None, harmonics: int = 6) -> float:
    """Crest-to-trough amplitude max − min of ``signal``; with ``frequency`` [Hz], after removing a linear drift.

    The drift is fitted jointly with the periodic part (offset, slope and the first ``harmonics`` harmonics of
    ``frequency``), so that a periodic signal whose phase does not start at a crest is not tilted by the fit, as a
    plain least-squares line through it would be; the part the fit leaves is smoothed (noise does not count).
    """
    t = np.asarray(t, dtype=float)
    s = np.asarray(signal, dtype=float)
    if frequency is not None and s.size > 2 * harmonics + 2:
        tau = t - t[0]
        w = 2 * np.pi * frequency * tau
        cols = [np.ones_like(tau), tau]
        for k in range(1, harmonics + 1):
            cols += [np.sin(k * w), np.cos(k * w)]
        basis = np.column_stack(cols)
        coef, *_ = np.linalg.lstsq(basis, s, rcond=None)
        periodic = basis[:, 2:] @ coef[2:] + coef[0]
        # the periodic fit plus what it leaves, smoothed over a tenth of a period: noise on single samples does
        # not widen the swing, and what is not periodic (a transient, a cycle unlike the others) still counts
        s = periodic + smooth(t, s - periodic - coef[1] * tau, 0.1 / frequency)
    return float(np.max(s) - np.min(s))
