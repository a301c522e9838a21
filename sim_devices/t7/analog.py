"""What the T7's analog channels see and how they convert: the rig's conditioning stage before the DAC's load, the
wiring of each AIN to the plant, the factory calibration constants, the ADC's and DAC's codes.

[E] calibration in flash at 0x3C4000 (41 F32, LabJack example getNominalCalibration's nominal constants);
[A] F32 stream-out values → code = V·Slope + Offset (own calibration); [D] 12-bit DAC, low 4 bits ignored;
[D] AIN14 reads the internal temperature sensor, AIN15 internal ground (T7 datasheet §14.0 AIN); [E] K = slope·V +
offset with the temperature constants of the calibration (flash words 36, 37); [A] the device at 25 °C.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.core.one_pole import one_pole
from bench.models.jit import njit

reconstruct = one_pole  # the reconstruction filter (an RC between DAC and amplifier on the rig): the twin applies it

RANGE_GAIN = {0.0: 0, 10.0: 0, 1.0: 1, 0.1: 2, 0.01: 3}  # [D] AIN#_RANGE values → gain index of the calibration
DEVICE_TEMPERATURE_K = 298.15  # [A] the device's own temperature (the datasheet's 25 °C specification point)
AIN_TEMPERATURE, AIN_GROUND = 14, 15
_DOUBLE_MAX = float(np.finfo(np.float64).max)  # np.nan_to_num's value for +inf


def nominal_calibration() -> list[float]:
    """T7 nominal constants (LabJack example getNominalCalibration), flash order."""
    hs: list[float] = []
    for g in range(4):
        k = 10.0 ** -g
        hs += [0.000315805780 * k, -0.000315805800 * k, 33523.0, -10.58695652200 * k]
    return hs + hs + [13200.0, 0.0, 13200.0, 0.0, -92.379, 465.129, 10e-6, 200e-6, 0.0]



def temperature_volts(cal: list[float], kelvin: float = DEVICE_TEMPERATURE_K) -> float:
    """AIN14's voltage at ``kelvin``: the inverse of the calibration's K = slope·V + offset (flash words 36, 37)."""
    slope, offset = cal[36], cal[37]
    return (kelvin - offset) / slope


def ain_codes(cal: list[float], volts: np.ndarray, gain: int) -> np.ndarray:
    """The 16-bit stream codes of ``volts`` on gain index ``gain`` (calibration: positive slope, negative slope,
    centre)."""
    p, nslope, c = cal[4 * gain:4 * gain + 3]
    # c + v/p where v ≥ 0, else c − v/nslope written as c + v/(−nslope): IEEE division and subtraction are
    # sign-symmetric, so the same doubles as the two branches, in four array passes instead of seven
    raw = volts / np.where(volts >= 0, p, -nslope)
    raw += c
    np.rint(raw, out=raw)
    np.maximum(raw, 0, out=raw)  # np.clip's result (a NaN stays NaN), without its call overhead
    np.minimum(raw, 65535, out=raw)
    return raw.astype(np.uint16)


def dac_code(cal: list[float], volts: float, ch: int) -> int:
    """DAC ``ch``'s 16-bit code for ``volts`` (flash DAC slope [codes/V], offset [codes])."""
    slope, off = cal[32 + 2 * ch:34 + 2 * ch]
    return int(min(max(round(volts * slope + off), 0), 65535))


def dac_volts(cal: list[float], code: int, ch: int) -> float:
    """One code's output, as :func:`dac_codes_volts` (the same double operations, without an array per value)."""
    slope, off = cal[32 + 2 * ch:34 + 2 * ch]
    return ((int(code) >> 4 << 4) - off) / slope


def dac_codes_volts(cal: list[float], codes: np.ndarray, ch: int) -> np.ndarray:
    """The outputs of DAC ``ch`` for ``codes`` (12-bit DAC: the low 4 bits ignored)."""
    slope, off = cal[32 + 2 * ch:34 + 2 * ch]
    return ((codes >> 4 << 4) - off) / slope


@njit(cache=True, nogil=True)
def ain_codes_of(x: np.ndarray, gain: float, offset: float, noise: np.ndarray, p: float, nslope: float, c: float,
                 out: np.ndarray) -> None:
    """``out`` ← the codes of gain·x + offset (+ ``noise``, where it has one value per sample): the doubles of
    :func:`ain_codes` on ``gain * x + offset + noise``, in one compiled pass over a stream block instead of a dozen
    array passes (the same IEEE operations in the same order; np.rint rounds half to even as numpy does). A
    non-finite x (a failed specimen's observable) reads as np.nan_to_num makes it: NaN 0, ±inf ± the largest
    double."""
    noisy = noise.size == x.size
    for k in range(x.size):
        xk = x[k]
        if not math.isfinite(xk):
            xk = 0.0 if xk != xk else (_DOUBLE_MAX if xk > 0 else -_DOUBLE_MAX)
        v = gain * xk + offset
        if noisy:
            v = v + noise[k]
        r = np.rint(v / (p if v >= 0 else -nslope) + c)
        if r != r:  # NaN: numpy's cast gives 0
            out[k] = 0
        else:
            out[k] = 0 if r < 0 else (65535 if r > 65535 else int(r))


@njit(cache=True, nogil=True)
def ain_scan_codes(xs: np.ndarray, params: np.ndarray, normals: np.ndarray, out: np.ndarray) -> None:
    """``out[k, j]`` ← the stream code of input j's sample k, every input of a stream block in one compiled pass,
    written in scan order (the packets' interleaving): :func:`ain_codes_of` of row j of ``xs`` with
    ``params[j]`` = (gain, offset, noise rms, p, nslope, c) and, where that rms is not 0, the noise
    0.0 + rms·``normals[j, k]`` — the doubles of ``Generator.normal(0.0, rms)`` ([numpy] loc + scale · a standard
    normal) from the same draws of the input's own generator."""
    n_in, n = xs.shape
    for j in range(n_in):
        gain, offset, rms, p, nslope, c = params[j, 0], params[j, 1], params[j, 2], params[j, 3], params[j, 4], \
            params[j, 5]
        for k in range(n):
            xk = xs[j, k]
            if not math.isfinite(xk):
                xk = 0.0 if xk != xk else (_DOUBLE_MAX if xk > 0 else -_DOUBLE_MAX)
            v = gain * xk + offset
            if rms != 0.0:
                v = v + (0.0 + rms * normals[j, k])
            r = np.rint(v / (p if v >= 0 else -nslope) + c)
            if r != r:  # NaN: numpy's cast gives 0
                out[k, j] = 0
            else:
                out[k, j] = 0 if r < 0 else (65535 if r > 65535 else int(r))


@njit(cache=True, nogil=True)
def dac_drive(first: int, codes: np.ndarray, t_enable: float, rate: float, slope: float, off: float, gain: float,
              offset: float, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, amplifier inputs) of DAC ``codes`` played at scans ``first``, ``first`` + 1, … ([D] scan k at
    t_enable + (k + 1)/rate): :func:`dac_codes_volts` through :class:`Conditioning` (``gain``, ``offset``,
    ``limit``), the same doubles in one compiled pass (a stream-out packet's values at a time)."""
    n = codes.size
    times = np.empty(n)
    volts = np.empty(n)
    for k in range(n):
        times[k] = (first + 1 + k) / rate + t_enable
        v = ((codes[k] >> 4 << 4) - off) / slope
        v = v * gain + offset
        if v < -limit:  # np.maximum / np.minimum: a NaN stays
            v = -limit
        if v > limit:
            v = limit
        volts[k] = v
    return times, volts


@njit(cache=True, nogil=True)
def held_index(t: np.ndarray, times: np.ndarray) -> np.ndarray:
    """For each of ``times``, the index of the last of the samples at ``t`` (increasing) at or before it (+1 ns),
    within 0…t.size − 1: np.searchsorted(t, times + 1e-9, side="right") − 1, clipped — in one merge-like pass
    when ``times`` increase (a stream block's scans), the search restarting where they do not."""
    m = t.size
    idx = np.empty(times.size, np.int64)
    j = 0
    prev = -math.inf
    for i in range(times.size):
        x = times[i] + 1e-9
        if x != x:  # NaN: numpy sorts it after everything
            j = m
        else:
            if not x >= prev:
                j = 0
            while j < m and t[j] <= x:
                j += 1
        prev = x
        k = j - 1
        idx[i] = 0 if k < 0 else (m - 1 if k > m - 1 else k)
    return idx


def warm_up() -> None:
    """Compile :func:`ain_codes_of`, :func:`ain_scan_codes`, :func:`dac_drive`, :func:`held_index` and
    :func:`reconstruct` now (a fresh install has no numba cache: compiling at the first stream pump would take
    seconds inside the twin's reply, with its locks held, and the host would wait)."""
    ain_codes_of(np.zeros(1), 1.0, 0.0, np.zeros(1), 1.0, 1.0, 0.0, np.zeros(1, np.uint16))
    ain_scan_codes(np.zeros((1, 1)), np.ones((1, 6)), np.zeros((1, 1)), np.zeros((1, 1), np.uint16))
    dac_drive(0, np.zeros(1, np.int64), 0.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0)
    held_index(np.zeros(2), np.zeros(2))
    reconstruct(np.zeros(2), 0.5, 0.0)


@dataclass(frozen=True)
class Conditioning:
    """Rig's stage between a DAC (0–5 V) and the amplifier input: ``gain``·V + ``offset``, clipped ±``limit``,
    optionally through a first-order reconstruction low-pass of corner ``corner_Hz`` (applied to streamed
    values scan by scan; [L] a command-response write reaches the amplifier unfiltered, as a step)."""

    gain: float = 4.0
    offset: float = -10.0
    limit: float = 10.0
    corner_Hz: float | None = None

    def __call__(self, volts: np.ndarray) -> np.ndarray:
        # np.minimum/np.maximum: np.clip's values (NaN passes through) at a fraction of its call overhead
        return np.minimum(np.maximum(self.gain * np.asarray(volts, float) + self.offset, -self.limit), self.limit)


@dataclass(frozen=True)
class Signal:
    """What one AIN sees: ``gain``·(plant observable) + ``offset`` [V], with Gaussian noise [V rms]."""

    observable: str  # "voltage", "current", "force", "displacement"
    gain: float
    offset: float = 0.0
    noise: float = 0.0


def default_signals(vmon_ratio: float = 1000.0, imon_ratio: float = 1e-3, force_gain: float = 1.0,
                    laser_gain: float = 200.0, laser_offset: float = 0.0) -> dict[int, Signal]:
    """AIN0 TREK V monitor, AIN1 I monitor, AIN2 bridge amplifier [V/N], AIN3 laser analog output [V/m]."""
    return {0: Signal("voltage", 1.0 / vmon_ratio), 1: Signal("current", 1.0 / imon_ratio),
            2: Signal("force", force_gain), 3: Signal("displacement", laser_gain, laser_offset)}

