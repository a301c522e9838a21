"""The voltage monitor's 0-V band and the verified-safe threshold, from the rig's monitor chain.

The output is *verified* at 0 V (before a specimen change, at the end of a run) when the voltage monitor, as the DAQ
converts it, reads at most the threshold. The chain is the TREK's voltage monitor (ratio ``vmon_ratio`` V of output
per V) into a DAQ input on its ±10 V range (an ADAM-4017+, or a LabJack T7 AIN). Its *zero band* is the largest
|reading| an output truly at 0 V can give, at the output's scale:

    band = a_trek · FS                      TREK monitor DC accuracy (gain and offset) × output full scale
         + r · (a_daq + q / 2)              DAQ absolute accuracy and half an LSB of rounding, × the ratio r
         + k · √(n_trek² + (r · n_daq)²)    k × the rms noise of one reading (monitor and input together)

with q = 20 V / 2^bits. The threshold is ``SAFE_TOUCH_V − band``: a reading at or below it bounds the true output by
:data:`SAFE_TOUCH_V`, which is what "verified" promises. A chain whose threshold would be below its band (band above
half the limit) cannot tell a true 0 V from an unsafe output, and its rig is refused. What a healthy amplifier's own
output offset at a 0-V input may be is in no page read: on the ADAM-4017+ chain (band 23.3 V, threshold 26.7 V) an
offset above 3.4 V could, with every error at its worst, read above the threshold — a false "not verified" trip,
which latches, and is safe; on the T7 chain (band 15.3 V, threshold 34.7 V) up to 19.4 V. (A review: a floor taken
as the offset, ``max(10 V, band)``, counted an output voltage as a monitor error, and left 0 V readings of a healthy
T7 rig with a 10-V offset at up to 25 V against a 15.3-V threshold.)

Figures, marked as in ``/work/shared/instruments.md`` ([V] read in a source, [U] unverified, [assumed] chosen):

* TREK monitor: :data:`bench.core.noise.TREK_DYNAMICS` — DC accuracy ±0.1 % of full scale and 1 V rms noise are
  [assumed] there: the operator manual's monitor specification is in no store searched (2026-11-28, queries
  "10/10B-HS voltage monitor ratio accuracy noise", "10/40A-HS datasheet voltage monitor"; the datasheets are
  stored to their first page only). Ratio 1000 V/V by default (:data:`bench.core.plant.TREK_DATASHEET`, [U]).
* ADAM-4017+: 16-bit, voltage accuracy "±0.1 % or better" [V: Advantech ADAM-4017+ specification, as quoted by
  star.ke.st/library/advantech-adam-4017-4018-4019-i-o], taken of the 10-V full scale: 10 mV. The module states no
  noise: [assumed] 1 LSB rms (an integrating converter at 10 S/s, NMR 100 dB at 50/60 Hz, same source).
* LabJack T7, ±10 V range: absolute accuracy ±0.01 % FS, ±2000 µV [V: T-Series Datasheet, App. A-3, Table A.3-1];
  16-bit converter, effective resolution 16 to 19 bits [V: T-Series Datasheet §14.3.0], so the rms noise is at most
  1 LSB of 16 bits (the worst resolution index).
* k = 3 [assumed]: a reading beyond 3 σ is rare (0.3 %), and the checks read again every 0.1 s for 2 s before they
  report: a noise excursion costs a reread, not a trip.
* ``SAFE_TOUCH_V`` = 50 V: the verified-safe bound this project has stated (README "Safety", step 5), kept as the
  ceiling. No touch-voltage standard is in the stores (IEC 61010-1's d.c. level for accessible parts is remembered
  as 70 V, [U]); it is not raised without a sourced figure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bench.core.noise import TREK_DYNAMICS

SAFE_TOUCH_V = 50.0  # V: a verified-safe output is at most this (README "Safety" 5); never raised unsourced
NOISE_SIGMAS = 3.0  # k: one reading's noise bound in rms units
DAQ_SPAN_V = 20.0  # the ±10 V input range both DAQs read the monitors on (bench.rig.AIN_FULL_SCALE_V)


@dataclass(frozen=True)
class DaqInput:
    """A DAQ input on its ±10 V range: converter bits, absolute accuracy [V] and rms noise [V] at its terminals."""

    name: str
    bits: int
    accuracy_V: float
    noise_rms_V: float

    @property
    def lsb_V(self) -> float:
        """One code of the converter over the 20-V span [V]."""
        return DAQ_SPAN_V / (1 << self.bits)


def adam_4017p(bits: int = 16) -> DaqInput:
    """The ADAM-4017+ at ``bits`` (the rig's ``amplifier.ai_bits``): ±0.1 % of 10 V; noise 1 LSB rms [assumed]."""
    return DaqInput("ADAM-4017+", bits, 1e-3 * 10.0, DAQ_SPAN_V / (1 << bits))


T7_AIN = DaqInput("LabJack T7", 16, 2000e-6, DAQ_SPAN_V / (1 << 16))  # Table A.3-1; ≥ 16 effective bits (§14.3.0)


def zero_band_v(model: str, full_scale_V: float, vmon_ratio: float, daq: DaqInput) -> float:
    """The largest |reading| [V] of an output at 0 V through TREK ``model``'s monitor (output full scale
    ``full_scale_V``, ratio ``vmon_ratio`` V/V) into ``daq``: the module docstring's sum."""
    trek = TREK_DYNAMICS[model]
    return (trek.vmon_accuracy * full_scale_V + vmon_ratio * (daq.accuracy_V + daq.lsb_V / 2)
            + NOISE_SIGMAS * math.hypot(trek.vmon_noise, vmon_ratio * daq.noise_rms_V))


def safe_threshold_v(model: str, full_scale_V: float, vmon_ratio: float, daq: DaqInput) -> float:
    """|monitor| at or below this [V] is the output verified at 0 V: ``SAFE_TOUCH_V − band`` (a reading at it bounds
    the true output by the limit). ValueError where that is below the band (a true 0 V could read above it)."""
    band = zero_band_v(model, full_scale_V, vmon_ratio, daq)
    threshold = SAFE_TOUCH_V - band
    if threshold < band:
        raise ValueError(f"the voltage monitor chain (TREK {model} at {vmon_ratio:g} V/V into the {daq.name}) reads "
                         f"0 V as up to ±{band:.1f} V: a reading within that band could hide {2 * band:.0f} V, above "
                         f"the {SAFE_TOUCH_V:g}-V safe limit, so it cannot verify a safe output")
    return threshold


def widest_band_v() -> float:
    """The widest 0-V band of the chains a rig file names by default (either TREK HS model at its datasheet full
    scale and monitor ratio, :data:`bench.core.plant.TREK_DATASHEET`, into either DAQ): what an analysis that does
    not know the rig takes for the monitor's reading of no drive. (The core imports no driver: tests/test_layers.py.)"""
    from bench.core.plant import TREK_DATASHEET

    return max(zero_band_v(m.model, m.max_output, m.vmon_ratio, daq)
               for m in TREK_DATASHEET.values() for daq in (adam_4017p(), T7_AIN))
