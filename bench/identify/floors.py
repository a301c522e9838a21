"""Datasheet noise floors of the identification records (issue 27: the noise model).

A record's σ is the larger of its own estimate (:func:`bench.identify.core.noise_of`) and the floor its instrument's
datasheet figure sets (:mod:`bench.core.noise`), read from the rig stored in the run file (``rig_toml``; older files
and replays without it: no floor). A floor too low is harmless (the record's estimate wins), one too high would
down-weigh a record below its real precision; so every choice here takes the lower side: readings averaged into a
comparison point count as independent (an LK-G's moving average correlates neighbouring fast samples, which only
makes the true noise of their mean larger), and the readers' own noise (the T7's AIN, the DGT1S's rounding to a
division) is left out.
"""

from __future__ import annotations

import math

import numpy as np

from bench.core.noise import lkg_noise_mm, load_cell_noise_kg
from bench.rig import STANDARD_GRAVITY_M_PER_S2, RigConfig, rig_from_toml
from bench.storage.runfile import RunFile

DGT1S_RATE_HZ = 100.0  # [assumed] the DGT1S twin's conversion rate (sim_devices.modbus_devices.Dgt1sSim)


def stored_rig(run: RunFile) -> RigConfig | None:
    """The rig a run file records, or None where it records none; ValueError (one line naming the file) for one
    that today's rig schema refuses."""
    text = str(run.attrs.get("rig_toml", ""))
    if not text:
        return None
    try:
        return rig_from_toml(text)
    except ValueError as exc:  # pydantic's ValidationError is one: many lines, no file name
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"run file {run.path}: its recorded rig cannot be read ({first})") from None


def laser_noise_m(rig: RigConfig | None) -> float | None:
    """Rms noise [m] of one laser reading: the head's repeatability at the rig's averaging (serial reading and
    analog output alike); None without a [laser] table."""
    if rig is None or rig.laser is None:
        return None
    return lkg_noise_mm(rig.laser.head, rig.laser.averaging) * 1e-3


def force_noise_N(rig: RigConfig | None) -> float | None:
    """Rms noise [N] of one load-cell reading: the cell's noise density over the reader's bandwidth — the T7's scan
    rate where the bridge amplifier is on a T7 input, else the DGT1S's conversion rate; None without either."""
    if rig is None:
        return None
    if rig.daq is not None and rig.daq.force_ain is not None:
        rate = rig.daq.scan_rate_Hz
    elif rig.load_cell is not None:
        rate = DGT1S_RATE_HZ
    else:
        return None
    return load_cell_noise_kg(rate) * STANDARD_GRAVITY_M_PER_S2


def of_window_means(sigma: float | None, t_grid: np.ndarray, t_data: np.ndarray) -> float:
    """Floor of a record of window means over (t − Δ, t]: ``sigma`` / √(the most readings one window holds);
    0 without a figure."""
    if sigma is None or t_grid.size < 2 or t_data.size == 0:
        return 0.0
    width = float(t_grid[1] - t_grid[0])
    count = np.searchsorted(t_data, t_grid + 1e-9, side="right") - \
        np.searchsorted(t_data, t_grid - width + 1e-9, side="right")
    return sigma / math.sqrt(max(int(count.max()), 1))


def of_points(sigma: float | None, t_grid: np.ndarray, t_data: np.ndarray) -> float:
    """Floor of a record of values interpolated between readings: ``sigma`` × the least √(f² + (1 − f)²) over its
    points (f: the fraction of the way to the next reading; 1/√2 midway); 0 without a figure."""
    if sigma is None or t_data.size < 2 or t_grid.size == 0:
        return 0.0
    j = np.clip(np.searchsorted(t_data, t_grid), 1, t_data.size - 1)
    inside = (t_grid >= t_data[0]) & (t_grid <= t_data[-1])
    if not inside.any():
        return 0.0
    f = ((t_grid - t_data[j - 1]) / (t_data[j] - t_data[j - 1]))[inside]
    return sigma * float(np.sqrt(f * f + (1.0 - f) ** 2).min())
