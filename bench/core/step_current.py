"""The charging current a voltage step draws, as a DAQ's scan of the TREK's current monitor shows it.

A set-point written by command-response on a DAQ rig (manual control) is a step of the DAC: through the conditioning
stage's first-order reconstruction filter (``daq.drive_filter_Hz``; none: the step itself), the TREK's output stage
(first order at its large-signal bandwidth, bounded by the slew rate and the current limit into the load:
:func:`~bench.core.amplifier_dynamics.output_response`, the plant's own), the current C·dV/dt through the current
monitor's first-order low-pass. A protocol's run scans that monitor at 10 kHz and trips on it; a manual session polls
it a few times a second and never sees a pulse of a few ms, so the step is judged before it is sent.

The load is a constant capacitance (the specimen's at the present stretch): the specimen's own motion during the
charge (ms) is left out, as is its loss current (µA).
"""

from __future__ import annotations

import math

import numpy as np

from bench.core.amplifier_dynamics import lowpass, output_response
from bench.core.noise import TrekDynamics

SETTLED_TAUS = 8.0  # the step is followed for this many of its slowest time constants (e^-8: 0.03 % left)
MAX_STEPS = 200_000  # at most this many model steps per step judged (~1 ms of the kernels)


def monitor_peak(dv: float, c: float, dyn: TrekDynamics, filter_Hz: float | None) -> float:
    """The largest |current| [A] the current monitor shows for a step of ``dv`` [V at the output] into ``c`` [F]
    (the output at rest before it), behind a reconstruction filter with corner ``filter_Hz`` (None: none)."""
    if dv == 0.0 or c <= 0.0:
        return 0.0
    corners = [dyn.bandwidth_Hz, dyn.imon_bandwidth_Hz] + ([filter_Hz] if filter_Hz is not None else [])
    span = SETTLED_TAUS / (2.0 * math.pi * min(corners)) + abs(dv) / dyn.slew + abs(dv) * c / dyn.dc_current
    h = max(span / MAX_STEPS, 1e-8)
    t = h * np.arange(1, math.ceil(span / h) + 1)
    target = np.full(t.size, dv) if filter_Hz is None else dv * -np.expm1(-2.0 * math.pi * filter_Hz * t)
    out, _ = output_response(target, 0.0, h, 1.0 / (2.0 * math.pi * dyn.bandwidth_Hz), dyn.slew, c,
                             dyn.dc_current, dyn.peak_current, dyn.peak_s, 0.0)
    current = c * np.diff(out, prepend=0.0) / h  # the mean over each step: its charge over its length
    shown = lowpass(current, math.exp(-2.0 * math.pi * dyn.imon_bandwidth_Hz * h), 0.0)
    return float(np.max(np.abs(shown)))


def largest_step(c: float, dyn: TrekDynamics, filter_Hz: float | None, limit_A: float, most_V: float) -> float:
    """The largest step [V] up to ``most_V`` whose :func:`monitor_peak` stays at or below ``limit_A`` (to 1 V; the
    peak grows with the step)."""
    if monitor_peak(most_V, c, dyn, filter_Hz) <= limit_A:
        return most_V
    lo, hi = 0.0, most_V
    while hi - lo > 1.0:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if monitor_peak(mid, c, dyn, filter_Hz) <= limit_A else (lo, mid)
    return lo
