"""The TREK amplifier's output dynamics and its monitors, per model step.

Output: a first-order stage (corner ``bandwidth_Hz``) whose rate of change is bounded by the slew rate and by the
current limit into the load's capacitance (peak current for at most ``peak_s``, then the DC rating). Solved
exactly within each step (a ramp at the bound, then the exponential approach), so the step size does not change
the response; the current then follows from the specimen's charge (C·dV/dt and the model's own losses).

Monitors: first-order low-pass (corner per monitor) of the true output voltage and current, a gain and an offset
error drawn once within the datasheet accuracy, white noise — what the monitor outputs carry to any instrument
that samples them (ADAM-4017+, T7). Figures: :mod:`bench.core.noise`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.core.noise import Realism, TrekDynamics
from bench.models.jit import njit


@njit(cache=True)
def output_response(target: np.ndarray, v0: float, h: float, tau: float, slew: float, c: float, dc_current: float,
                    peak_current: float, peak_s: float, t_limited: float) -> tuple[np.ndarray, float]:
    """Output [V] at the end of each step for the step targets ``target`` from ``v0``; ``t_limited``: how long the
    output has been current-limited above its DC rating so far. Returns (outputs, new ``t_limited``)."""
    n = target.size
    out = np.empty(n)
    v = v0
    for k in range(n):
        i_lim = peak_current if t_limited < peak_s else dc_current
        rate = min(slew, i_lim / c)
        e = target[k] - v
        ae = abs(e)
        s = 1.0 if e >= 0.0 else -1.0
        band = rate * tau  # error below which the first-order stage moves slower than the bound
        if ae > band:
            t1 = (ae - band) / rate  # time spent on the bound
            if t1 >= h:
                v += s * rate * h
                limited = h
            else:
                v = target[k] - s * band * math.exp(-(h - t1) / tau)
                limited = t1
        else:
            v = target[k] - e * math.exp(-h / tau)
            limited = 0.0
        if limited > 0.0 and rate * c > dc_current:
            t_limited += limited
        elif limited == 0.0:
            t_limited = 0.0
        out[k] = v
    return out, t_limited


@njit(cache=True)
def lowpass(x: np.ndarray, a: float, y0: float) -> np.ndarray:
    """First-order low-pass y_k = a·y_{k−1} + (1 − a)·x_k from y0 (x held over each step; a NaN input — a failed
    specimen's current — counts as 0)."""
    y = np.empty(x.size)
    yk = y0
    for k in range(x.size):
        xk = x[k] if math.isfinite(x[k]) else 0.0
        yk = a * yk + (1.0 - a) * xk
        y[k] = yk
    return y


@njit(cache=True)
def step_targets(t: np.ndarray, v: np.ndarray, m: int, first: int, n: int, h: float, gain: float, max_output: float,
                 cap: float, prev: float) -> np.ndarray:
    """The output stage's target during each of the next ``n`` steps (from step ``first``): the amplifier inputs
    ``v[:m]`` that start at ``t[:m]`` (in time order), each from the step it falls in until the next one's,
    times ``gain`` and clipped to ±``max_output`` (then, ``cap`` ≥ 0, to ±``cap``: a shorted load); before the
    first of them, ``prev``. The doubles of the plant's former array passes (floor, ×, clip, copysign), one loop."""
    out = np.empty(n)
    for k in range(n):
        out[k] = prev
    for i in range(m):
        s = min(max(0, math.floor(t[i] / h + 1e-6) - first), n)
        e = n if i + 1 == m else min(max(0, math.floor(t[i + 1] / h + 1e-6) - first), n)
        if e <= s:
            continue
        x = gain * v[i]
        if x < -max_output:
            x = -max_output
        if x > max_output:
            x = max_output
        if cap >= 0.0:
            a = abs(x)
            if a > cap:
                a = cap
            x = math.copysign(a, x)
        for k in range(s, e):
            out[k] = x
    return out


@njit(cache=True)
def monitor_response(x: np.ndarray, a: float, y0: float, scale: float, offset: float,
                     noise: np.ndarray) -> tuple[np.ndarray, float]:
    """A monitor's samples: :func:`lowpass` of ``x`` from ``y0``, times ``scale`` plus ``offset`` plus ``noise``
    (where it has one value per sample), in one pass; returns (samples, the low-pass's last output)."""
    out = np.empty(x.size)
    noisy = noise.size == x.size
    yk = y0
    for k in range(x.size):
        xk = x[k] if math.isfinite(x[k]) else 0.0
        yk = a * yk + (1.0 - a) * xk
        o = scale * yk + offset
        if noisy:
            o = o + noise[k]
        out[k] = o
    return out, yk


_NO_NOISE = np.zeros(0)


@dataclass
class Monitor:
    """One monitor output (in the output's units): low-pass, gain and offset errors, noise."""

    corner_Hz: float
    gain_error: float = 0.0
    offset: float = 0.0
    noise: float = 0.0
    rng: np.random.Generator | None = None
    _y: float = 0.0

    def __call__(self, x: np.ndarray, h: float) -> np.ndarray:
        """Monitor samples at the step ends of the true signal ``x`` (held over each step: exact discretisation)."""
        a = math.exp(-2.0 * math.pi * self.corner_Hz * h)
        x = np.ascontiguousarray(x, dtype=float)
        noise = self.rng.normal(0.0, self.noise, x.size) if self.noise and self.rng is not None else _NO_NOISE
        out, self._y = monitor_response(x, a, self._y, 1.0 + self.gain_error, self.offset, noise)
        return out


def monitors(dyn: TrekDynamics, full_scale_V: float, full_scale_A: float,
             realism: Realism) -> tuple[Monitor, Monitor]:
    """The voltage and current monitors of an amplifier, their errors drawn from the rig's seed (none with noise
    off): gain and offset each uniform within half the DC accuracy (together within it). Each monitor's noise has a
    stream of its own (11, 12): one shared generator gave each monitor other draws whenever the plant's blocks, which
    follow the host's polling, were cut differently — a seed did not reproduce a run."""
    rng = realism.rng(10)
    vm, im = Monitor(dyn.vmon_bandwidth_Hz), Monitor(dyn.imon_bandwidth_Hz)
    if realism.noise:
        for k, (mon, acc, fs, noise) in enumerate(((vm, dyn.vmon_accuracy, full_scale_V, dyn.vmon_noise),
                                                   (im, dyn.imon_accuracy, full_scale_A, dyn.imon_noise))):
            mon.gain_error = float(rng.uniform(-acc / 2, acc / 2))
            mon.offset = float(rng.uniform(-acc / 2, acc / 2)) * fs
            mon.noise = noise
            mon.rng = realism.rng(11 + k)
    return vm, im
