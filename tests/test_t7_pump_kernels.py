"""The T7 twin's compiled pump kernels against the array formulas they replaced: a failed specimen's observable (NaN,
±inf) reaches the inputs as np.nan_to_num makes it, each scan reads the plant sample that numpy's searchsorted
finds, and the reconstruction filter (bench.core.one_pole: the twin applies it, the host predicts through it) gives
scipy's lfilter's doubles."""

from __future__ import annotations

import math

import numpy as np

from sim_devices.t7 import analog


def test_non_finite_observables_read_as_nan_to_num_makes_them() -> None:
    cal = analog.nominal_calibration()
    rng = np.random.default_rng(11)
    x = rng.normal(0.0, 4.0, 5000)
    x[[10, 11, 500, 4999]] = [np.nan, np.inf, -np.inf, np.nan]
    noise = rng.normal(0.0, 1e-3, x.size)
    for g in range(4):
        for gain, offset, nz in ((1.0, 0.0, noise), (1e-308, 0.25, noise), (2.0, -0.5, np.zeros(0))):
            out = np.empty(x.size, np.uint16)
            analog.ain_codes_of(x, gain, offset, nz, *cal[4 * g:4 * g + 3], out)
            with np.errstate(over="ignore"):
                v = gain * np.nan_to_num(x) + offset + (nz if nz.size else 0.0)
                assert np.array_equal(out, analog.ain_codes(cal, v, g))
            assert out[10] == analog.ain_codes(cal, np.array([offset + (nz[10] if nz.size else 0.0)]), g)[0]  # NaN: 0
    out = np.empty(2, np.uint16)  # +inf as the largest double: through a tiny gain, ~1.8 V, not full scale
    analog.ain_codes_of(np.array([np.inf, -np.inf]), 1e-308, 0.0, np.zeros(0), *cal[0:3], out)
    assert out.tolist() == analog.ain_codes(cal, np.array([1.7976931348623157, -1.7976931348623157]), 0).tolist()


def test_a_stream_blocks_inputs_in_one_pass_give_each_inputs_codes_and_noise_draws() -> None:
    """ain_scan_codes (all inputs of a block, in scan order) against ain_codes_of per input with the noise its own
    generator's normal(0, rms) draws: the same codes (the draws as standard normals, scaled in the kernel)."""
    cal = analog.nominal_calibration()
    rng = np.random.default_rng(5)
    n = 3000
    xs = rng.normal(0.0, 3.0, (4, n))
    xs[1, [7, 8, 9]] = [np.nan, np.inf, -np.inf]
    inputs = [(1.0, 0.0, 1e-3, 0), (1e3, -0.5, 0.0, 1), (0.2, 0.1, 2.5e-5, 2), (200.0, 0.0, 7e-4, 3)]
    normals = np.zeros((4, n))
    params = np.empty((4, 6))
    want = np.empty((n, 4), np.uint16)
    for j, (gain, offset, rms, g) in enumerate(inputs):
        if rms:
            np.random.default_rng([7, j]).standard_normal(out=normals[j])
        params[j] = (gain, offset, rms, *cal[4 * g:4 * g + 3])
        noise = np.random.default_rng([7, j]).normal(0.0, rms, n) if rms else np.zeros(0)
        col = np.empty(n, np.uint16)
        analog.ain_codes_of(xs[j], gain, offset, noise, *cal[4 * g:4 * g + 3], col)
        want[:, j] = col
    out = np.empty((n, 4), np.uint16)
    analog.ain_scan_codes(xs, params, normals, out)
    assert np.array_equal(out, want)


def test_held_index_is_searchsorted_right_minus_one_clipped() -> None:
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.5e-4, 1.5e-4, 3000)) + 0.2  # plant step ends, increasing
    scans = 0.2 + (np.arange(-50, 3500) + 1) / 9_999.7  # a stream block, before, across and after the samples
    cases = [scans, t[100:900].copy(), t[100:900] - 1e-9, np.r_[scans[:800], scans[200:300], scans[900:1000]],
             np.array([t[0] - 1.0]), np.array([t[-1] + 1.0]), np.array([0.3, np.nan, 0.25, 0.31]), np.zeros(0)]
    for times in cases:
        want = np.searchsorted(t, times + 1e-9, side="right") - 1
        assert np.array_equal(analog.held_index(t, times), np.clip(want, 0, t.size - 1))


def test_reconstruct_is_lfilters_first_order_low_pass() -> None:
    from scipy.signal import lfilter

    rng = np.random.default_rng(9)
    for trial in range(300):
        n = int(rng.integers(1, 700))
        volts = rng.normal(0.0, 5.0, n)
        volts[rng.integers(0, n, 3)] = [0.0, -0.0, 10.0]
        alpha = 1.0 - math.exp(-2.0 * math.pi * rng.uniform(1.0, 20e3) / rng.uniform(1e3, 1e5))
        y0 = float(rng.normal(0.0, 5.0)) if trial % 4 else 0.0
        want, _ = lfilter([alpha], [1.0, alpha - 1.0], volts, zi=[(1.0 - alpha) * y0])
        got = analog.reconstruct(volts, alpha, y0)
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64))
