"""The ADAM-4017+ twin's integrating conversion: each conversion is the mean of its input over the 20 ms before it,
whatever pieces the plant's samples arrive in.

Expected values come from the definition of an integrating conversion (the twin's stated assumption, 20 ms: one
50-Hz period) and the charge of a pulse: a pulse of charge Q wholly inside the window reads Q / 20 ms. The pulse is
the one a tester's run tripped on: a 5-kV drop into an LS-DEA film of ~4.8 nF discharged at the TREK 10/10B-HS's
40-mA peak current (datasheet: ±40 mA peak for 1 ms) — 24 µC in 0.6 ms. The plant's blocks follow the host's
requests, so on a rig ticking set-points at 200 Hz they come 5 ms at a time.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench.core.plant import PlantBlock
from sim_devices.modbus_devices import Adam4017PSim, Scale

H = 1e-4  # plant step [s]
T = 0.02  # the conversion window [s]
IMON_RATIO = 1e-3  # A of output per monitor volt (TREK 10/10B-HS default of the rigs)
PEAK = 40e-3  # A: the TREK 10/10B-HS's peak current
PULSE_S = 0.6e-3
LSB_A = 20.0 / 65535 * IMON_RATIO  # one 16-bit code over ±10 V


def current_conversion(cuts: list[int]) -> float:
    """The current channel's conversion at t = 0.1 s (conversion 1 at 10 S/s, channels 0 and 1 enabled: the current
    monitor's), the plant's 2,000 samples over 0.2 s handed over in pieces ending at the sample indices ``cuts``;
    a 24-µC pulse ends 3 ms before the conversion."""
    plant = SimpleNamespace(h=H, listeners=[])
    adam = Adam4017PSim(2, plant, None, vmon_ratio=1000.0, imon_ratio=IMON_RATIO, noise_volts=0.0)  # type: ignore[arg-type]
    k = np.arange(1, 2001)
    t = k * H
    start = 1000 - 30 - round(PULSE_S / H)  # samples 965 … 970 (t in (0.0964, 0.097]): 6 steps of 0.1 ms
    current = np.where((k > start) & (k <= 970), PEAK, 0.0)
    zero = np.zeros_like(t)
    begin = 0
    for end in [*cuts, t.size]:
        s = slice(begin, end)
        adam._on_block(PlantBlock(t[s], zero[s], current[s], zero[s], zero[s], zero[s], zero[s], zero[s], current[s]))
        begin = end
    return Scale(bits=16).to_volts(adam.raw[1]) * IMON_RATIO


@pytest.mark.parametrize("cuts", [[], list(range(50, 2000, 50)), [3, 960, 968, 985, 999, 1500]],
                         ids=["one block", "5-ms blocks (200-Hz ticks)", "uneven blocks"])
def test_a_charge_pulse_reads_as_its_charge_over_20_ms_however_the_blocks_are_cut(cuts: list[int]) -> None:
    """24 µC in the window: 1.2 mA, as the dry run (MONITOR_INTEGRATION_S) computes it. Before the fix a block with
    no conversion due was left out of the window, so the 5-ms blocks read the pulse over 5 ms (4.8 mA) — what
    tripped a tester's run at "−5.92 mA" where the dry run said 1.2 mA."""
    charge = PEAK * PULSE_S
    assert current_conversion(cuts) == pytest.approx(charge / T, abs=LSB_A)
