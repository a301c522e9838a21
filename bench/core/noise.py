"""Signal realism of the simulated instruments: datasheet figures, one seeded source, one switch.

Every twin that adds a random error to what it reads from the plant takes its figure from here, so that a rig's
instruments agree (the LK-G's serial reading and its analog output carry the same head noise; the DGT1S and the
bridge amplifier on a T7 input carry the same load-cell noise density, each over its own bandwidth).

Sources, marked as in ``/work/shared/instruments.md``: [V] a datasheet figure read there; [K] the Keyence LK-G
catalogue's specification table as remembered (not found in the searchable corpora — check it against the
catalogue); [assumed] found in no source, chosen here, with the reason.

Searched again 2026-11-26 (issue 23), nothing found that replaces a [K] or [assumed] figure: the LK-G manual
LK-G-M-NO5-E is stored page by page (azmanual.top / manualsdir.com …/657998/keyence-lk-g-series.html?page=N) but
no stored page holds its specification table (queries: "LK-G152 repeatability linearity sampling frequency",
"LK-G-M-NO5-E Specifications Repeatability", "LK-H152 LK-G5000 repeatability"); the LK-G Technology Book
(scribd 332178422) is stored to its opening only. The TREK HS datasheets (markdown copies, Advanced Energy 2022)
are stored to their first page (slew, large-signal bandwidth, currents: the [V] figures below); their technical
data and the operator manual (monitor ratios, accuracy, bandwidth, noise) are in no store (queries: "10/10B-HS
voltage monitor current monitor accuracy noise small signal bandwidth", "Trek 10/40A-HS operator manual voltage
monitor", "advancedenergy.com Trek 10/10B-HS technical data").

``Realism(noise=False)`` (rig file ``[simulation] noise = false``) switches every random part off — noise and the
monitors' drawn gain/offset errors — for golden tests; the deterministic dynamics (the amplifier's bandwidth,
slew and current limit, the monitors' bandwidth) stay, they are the instruments' physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# ---------------------------------------------------------------- Keyence LK-G heads
# [K] LK-G catalogue, specification table: repeatability of the LK-G152 head 0.5 µm (LK-G82 0.2 µm, LK-G32
# 0.05 µm, LK-G402 2 µm), with the averaging set to 4096 (the table's footnote). Taken as an rms [assumed: the
# table does not say rms or peak-to-peak].
LKG_REPEATABILITY_UM = {"LK-G32": 0.05, "LK-G82": 0.2, "LK-G152": 0.5, "LK-G402": 2.0}
LKG_REPEATABILITY_AVERAGING = 4096
# SW,OC averaging codes 0…9: 1, 4, 16, …, 262144 times (instruments.md §1.5 [C]: "averaging 1…262144")
LKG_AVERAGING = tuple(4 ** k for k in range(10))
LKG_DEFAULT_AVERAGING = 64  # [assumed] the controller's setting when the rig does not change it


def lkg_noise_mm(head: str = "LK-G152", averaging: int = LKG_DEFAULT_AVERAGING) -> float:
    """Rms noise [mm] of one reading of ``head`` at ``averaging``: the repeatability scaled by √(4096 / N)
    (independent samples averaged) [assumed: the catalogue gives the figure at 4096 only]."""
    if head not in LKG_REPEATABILITY_UM:
        raise ValueError(f"unknown LK-G head {head!r}; known: {', '.join(LKG_REPEATABILITY_UM)}")
    if averaging < 1:
        raise ValueError(f"LK-G averaging must be ≥ 1, got {averaging}")
    return LKG_REPEATABILITY_UM[head] * 1e-3 * math.sqrt(LKG_REPEATABILITY_AVERAGING / averaging)


# ---------------------------------------------------------------- load cell
# One noise density for the cell and its conditioning, seen over each reader's bandwidth (rate / 2): the DGT1S at
# its conversion rate, the bridge amplifier on a T7 input at the scan rate. [assumed] 0.2 g rms at the DGT1S's
# 100 conversions/s (the twin's figure so far; its datasheet gives the internal resolution, not a noise):
# 0.2 g / √(50 Hz) ≈ 28 mg/√Hz.
LOAD_CELL_DENSITY_KG = 0.0002 / math.sqrt(50.0)  # kg/√Hz


def load_cell_noise_kg(rate_Hz: float) -> float:
    """Rms load-cell noise [kg] of one conversion at ``rate_Hz`` samples/s (white over rate / 2)."""
    return LOAD_CELL_DENSITY_KG * math.sqrt(rate_Hz / 2.0)


# ---------------------------------------------------------------- TREK HS amplifiers
@dataclass(frozen=True)
class TrekDynamics:
    """Output stage and monitors of a TREK HS amplifier (datasheet figures, per model)."""

    bandwidth_Hz: float  # first-order corner of the output stage
    slew: float  # V/s
    dc_current: float  # A
    peak_current: float  # A, for at most ``peak_s``
    peak_s: float
    vmon_bandwidth_Hz: float
    imon_bandwidth_Hz: float
    vmon_accuracy: float  # fraction of full scale (gain and offset error bound)
    imon_accuracy: float
    vmon_noise: float  # rms at the output's scale [V] (monitor volts × ratio)
    imon_noise: float  # rms at the output's scale [A]


# [V] Advanced Energy TREK 10/10B-HS and 10/40A-HS datasheets (2022; instruments.md §3.1): slew > 700 V/µs and
# large-signal bandwidth DC to > 19.5 kHz (10/10B-HS), > 900 V/µs and > 23 kHz (10/40A-HS); ±10 mA DC, ±40 mA
# peak for 1 ms (10/10B-HS); ±40 mA DC, ±120 mA peak for 1 ms (10/40A-HS). The output stage is taken as first
# order with its corner at the large-signal bandwidth (a lower bound of the small-signal one: the model is at
# most as fast as the datasheet guarantees).
# [assumed] the monitors (their figures are in the operator manual, not read): corner 10 kHz for the voltage
# monitor, 1 kHz for the current monitor (a current sense of a capacitive HV load is filtered well below the
# output's bandwidth); DC accuracy ±0.1 % of full scale (V) and ±1 % (I); noise 1 V rms (V, 0.01 % of 10 kV)
# and 1 µA rms (I) at the output's scale.
TREK_DYNAMICS = {
    "10/10B-HS": TrekDynamics(19.5e3, 700e6, 10e-3, 40e-3, 1e-3, 10e3, 1e3, 1e-3, 1e-2, 1.0, 1e-6),
    "10/40A-HS": TrekDynamics(23e3, 900e6, 40e-3, 120e-3, 1e-3, 10e3, 1e3, 1e-3, 1e-2, 1.0, 1e-6),
}


@dataclass
class Realism:
    """The rig's one switch and seed for random errors; ``rng(k)`` gives stream ``k`` (one per instrument), so a
    seed reproduces every instrument's noise whatever the others draw."""

    noise: bool = True
    seed: int = 1
    _streams: dict[int, np.random.Generator] = field(default_factory=dict, repr=False)

    def rng(self, stream: int) -> np.random.Generator:
        """The generator of ``stream`` (created on first use from the seed)."""
        if stream not in self._streams:
            self._streams[stream] = np.random.default_rng([self.seed, stream])
        return self._streams[stream]
