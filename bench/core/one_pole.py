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

