"""The verified-safe threshold derived from the rig's voltage-monitor chain, not a fixed 50 V.

Expected values are worked out here by hand from the instruments' figures (each with its source), not read from the
code:

* TREK HS voltage monitor: 1000 V of output per V (the rig default), DC accuracy ±0.1 % of the 10-kV full scale
  = ±10 V, noise 1 V rms at the output's scale — both [assumed] in bench/core/noise.py, the operator manual not
  being in any store.
* ADAM-4017+ on ±10 V: ±0.1 % (Advantech specification) of 10 V = ±10 mV; 16 bits over 20 V: 1 LSB = 305.2 µV;
  noise 1 LSB rms [assumed: none stated].
* LabJack T7 AIN on ±10 V: absolute accuracy ±2000 µV (T-Series Datasheet App. A-3, Table A.3-1); 16-bit, ≥ 16
  effective bits (§14.3.0): noise ≤ 1 LSB rms = 305.2 µV.
* a reading's noise bound: 3 σ; half an LSB of rounding; a reading at the threshold must bound the true output by
  the 50-V safe touch limit the README states (Safety, 5): threshold = 50 V − band, refused below the band.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.core.monitor_chain import SAFE_TOUCH_V, T7_AIN, adam_4017p, safe_threshold_v, zero_band_v
from bench.rig import load_rig, safe_monitor_v
from bench.storage.runfile import open_run
from tests.conftest import RIGS

LSB = 20.0 / 2**16  # V at the DAQ's terminals
TREK_ZERO = 0.001 * 10e3  # V: ±0.1 % of 10 kV
NOISE = 3.0 * math.sqrt(1.0**2 + (1000.0 * LSB) ** 2)  # V: 3 σ of the monitor's 1 V and the input's 1 LSB
ADAM_BAND = TREK_ZERO + 1000.0 * (0.001 * 10.0 + LSB / 2) + NOISE  # 10 + 10.153 + 3.137 = 23.29 V
T7_BAND = TREK_ZERO + 1000.0 * (2000e-6 + LSB / 2) + NOISE  # 10 + 2.153 + 3.137 = 15.29 V


def test_the_bands_by_hand() -> None:
    assert ADAM_BAND == pytest.approx(23.289, abs=1e-3) and T7_BAND == pytest.approx(15.289, abs=1e-3)
    assert zero_band_v("10/10B-HS", 10e3, 1000.0, adam_4017p()) == pytest.approx(ADAM_BAND, rel=1e-12)
    assert zero_band_v("10/40A-HS", 10e3, 1000.0, T7_AIN) == pytest.approx(T7_BAND, rel=1e-12)


ADAM_THRESHOLD, T7_THRESHOLD = 50.0 - ADAM_BAND, 50.0 - T7_BAND  # 26.71 V, 34.71 V


@pytest.mark.parametrize(("rig", "expected"), [("thesis-sim", ADAM_THRESHOLD), ("thesis-lab", ADAM_THRESHOLD),
                                               ("lsdea-motor-sim", ADAM_THRESHOLD), ("thesis-daq-sim", T7_THRESHOLD),
                                               ("thesis-daq-lab", T7_THRESHOLD),
                                               ("lsdea-isotonic-daq-sim", T7_THRESHOLD)])
def test_each_rig_gets_its_chains_threshold(rig: str, expected: float) -> None:
    """Every shipped rig: a reading at its threshold bounds the output by 50 V, and a true 0 V reads within it."""
    v = safe_monitor_v(load_rig(RIGS / f"{rig}.toml"))
    assert v == pytest.approx(expected, rel=1e-12)
    band = ADAM_BAND if expected == ADAM_THRESHOLD else T7_BAND
    assert v + band == pytest.approx(SAFE_TOUCH_V) and v > band and SAFE_TOUCH_V == 50.0


def test_a_chain_too_coarse_to_verify_is_refused() -> None:
    """A monitor at 2000 V/V into the ADAM: 10 + 2000 × (0.01 + LSB/2) + 3 √(1 + (2000 LSB)²) = 33.8 V, above half
    the 50-V limit: its threshold (16.2 V) would be below what a true 0 V can read. A 12-bit input (LSB 4.88 mV):
    10 + 1000 × (0.01 + 2.44 mV) + 3 √(1 + 4.88²) = 37.4 V, likewise."""
    with pytest.raises(ValueError, match="cannot verify a safe output"):
        safe_threshold_v("10/10B-HS", 10e3, 2000.0, adam_4017p())
    with pytest.raises(ValueError, match="cannot verify a safe output"):
        safe_threshold_v("10/10B-HS", 10e3, 1000.0, adam_4017p(12))


def test_a_fine_chain_bounds_the_output_by_the_limit_too() -> None:
    """A chain with a narrow band (a 1-kV full scale, monitor at 100 V/V, into the T7: 1 + 100 × (2 mV + LSB/2) +
    3 √(1 + (100 LSB)²) = 4.2 V): its threshold 45.8 V, a reading at it still bounds the output by 50 V."""
    band = 1e3 * 0.001 + 100.0 * (2000e-6 + LSB / 2) + 3.0 * math.sqrt(1.0 + (100.0 * LSB) ** 2)
    assert band == pytest.approx(4.217, abs=1e-3)
    assert zero_band_v("10/10B-HS", 1e3, 100.0, T7_AIN) == pytest.approx(band, rel=1e-12)
    assert safe_threshold_v("10/10B-HS", 1e3, 100.0, T7_AIN) == pytest.approx(50.0 - band, rel=1e-12)


def test_the_rig_file_refuses_a_chain_that_cannot_verify(tmp_path: Path) -> None:
    text = (RIGS / "thesis-sim.toml").read_text(encoding="utf-8").replace("[amplifier]\n",
                                                                          "[amplifier]\nvmon_ratio = 2000.0\n", 1)
    assert "vmon_ratio = 2000.0" in text
    f = tmp_path / "coarse.toml"
    f.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match="cannot verify a safe output"):
        load_rig(f)


@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_a_42_V_residual_is_not_handed_over(tmp_path: Path, rig: str) -> None:
    """42 V on the output (42 mV in at the TREK's 1000 V/V) when a campaign is taken up again at its set step:
    within the old fixed 50 V (the prompt came), above either chain's threshold (26.7 V, 34.7 V): the hand-over
    trips, latches and prompts nobody."""
    from tests.test_handover_zero import REREAD_S, _resume

    result, changes = _resume(tmp_path, rig, "operator", residual=True, volts_in=0.042)
    assert changes == []
    assert result.state == "tripped" and "output not verified" in result.reason, result.reason
    amp = open_run(result.path).streams["amplifier"]
    v = np.abs(amp.columns["voltage"][amp.t <= REREAD_S + 0.1])
    threshold = ADAM_THRESHOLD if rig == "thesis-sim" else T7_THRESHOLD
    assert v.size >= 2 and np.all((v > threshold) & (v < 50.0)), v  # what the old threshold would have passed


def test_the_cores_trek_figures_are_the_drivers() -> None:
    """The widest band is taken over the core's TREK datasheet figures (the core imports no driver): they are
    the driver's models, full scale and monitor ratio alike."""
    from bench.core.plant import TREK_DATASHEET
    from drivers.trek import TREK_MODELS

    assert TREK_DATASHEET.keys() == TREK_MODELS.keys()
    for name, m in TREK_MODELS.items():
        assert (TREK_DATASHEET[name].max_output, TREK_DATASHEET[name].vmon_ratio) == (m.max_output, m.vmon_ratio)
