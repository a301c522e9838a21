"""A rig's seed reproduces its amplifier monitors' noise however the plant's blocks are cut (they follow the host's
polling, which differs from run to run): the voltage and current monitors draw from streams of their own."""

from __future__ import annotations

import numpy as np

from bench.core.amplifier_dynamics import monitors
from bench.core.noise import TREK_DYNAMICS, Realism


def _record(cuts: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Both monitors over one 1-s ramp at 10 kHz, fed in blocks ending at ``cuts``, V block then I block as the
    plant feeds them."""
    vm, im = monitors(TREK_DYNAMICS["10/10B-HS"], 10e3, 10e-3, Realism(noise=True, seed=7))
    x = np.linspace(0.0, 7e3, 10_000)
    v, i = [], []
    for a, b in zip([0, *cuts], [*cuts, x.size], strict=True):
        v.append(vm(x[a:b], 1e-4))
        i.append(im(x[a:b] * 1e-7, 1e-4))
    return np.concatenate(v), np.concatenate(i)


def test_the_monitors_noise_does_not_depend_on_how_the_blocks_are_cut() -> None:
    v1, i1 = _record([2500, 5000, 7500])
    v2, i2 = _record([37, 4100, 4101, 9000])
    assert np.array_equal(v1, v2) and np.array_equal(i1, i2)
    assert np.std(np.diff(v1)) > 0  # noise is on: the test compares draws, not a noiseless signal
