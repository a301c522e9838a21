"""A one-pole low-pass in scipy's own operations: the rig's reconstruction filter (an RC between the DAQ's DAC and
the amplifier's input), which the host predicts and the T7 twin applies, each on its side of the wire."""

from __future__ import annotations

import numpy as np

from bench.models.jit import njit


@njit(cache=True, nogil=True)
def one_pole(volts: np.ndarray, alpha: float, y0: float) -> np.ndarray:  # pragma: no cover - numba
    """The filter's output at each sample: scipy.signal.lfilter([alpha], [1, alpha − 1], volts, zi=[(1 − alpha)·y0])
    computed as lfilter computes it (direct form II transposed: y = z + alpha·x, then z = 0·x − (alpha − 1)·y), the
    same doubles without its per-call cost or importing scipy.signal (0.4–0.6 s) into every run."""
    out = np.empty(volts.size)
    a1 = alpha - 1.0
    z = (1.0 - alpha) * y0
    for k in range(volts.size):
        x = volts[k]
        y = z + alpha * x
        z = 0.0 * x - a1 * y
        out[k] = y
    return out


@njit(cache=True, nogil=True)
def followed(wanted: np.ndarray, alpha: float, y0: float, bound: float) -> np.ndarray:  # pragma: no cover - numba
    """What the filter's output does when its input is the pre-compensation the engine plays (the input that makes
    the output ``wanted`` one sample later, ``y + (w − y)/alpha``), held to ±``bound``: ``wanted`` where that input
    is within the bound, else the filter's move towards the bound. A filter too slow for the waveform shows here as
    an output that falls short of it (the DAQ rig's engine: bench/runtime/hardware_timed.py)."""
    out = np.empty(wanted.size)
    y = y0
    for k in range(wanted.size):
        x = y + (wanted[k] - y) / alpha
        x = min(max(x, -bound), bound)
        y = y + alpha * (x - y)
        out[k] = y
    return out
