"""The T7's resolution index: what it maps to, the ADC noise it leaves on a sample, and the stream rates it allows.

[D] the map (ljm_constants.json): STREAM_RESOLUTION_INDEX "Valid values: 0-8. Default value of 0 corresponds to an
index of 1"; AIN#_RESOLUTION_INDEX / AIN_ALL_RESOLUTION_INDEX "Valid values: 0-8 for T7, 0-12 for T7-Pro. Default
value of 0 corresponds to an index of 8 (T7)"; AIN_ALL_RESOLUTION_INDEX reads 0xFFFF when the inputs differ.
[D] T-Series Datasheet A-3-1 "Noise and Resolution" (https://labjack.com/support/datasheets/t7/appendix-a-3-1;
A-3-2-2 "T7 Noise and Resolution" in the current numbering): the effective resolution is the RMS noise expressed in
bits, effective resolution [µV] = span / 2^bits; 14.3.0: "AIN15 is internally connected to GND. Useful for
measuring noise". The ±10 V figures below are the datasheet's table (±10 V column: bits and µV per resolution
index) as quoted by labjackcontroller (university-of-southern-maine-physics/labjack-controller,
labjackcontroller/labtools.py, T7_TYPE "command_response"): every stored copy of the datasheet pages (A-3-1,
A-3-2-2, the old t7 and t7old copies, searched 2026-11-26 for the table's ±1/±0.1/±0.01 V columns and for
"resolution index … effective resolution … gain") ends before its tables, and no project quotes the other columns.
[A] ±1, ±0.1 and ±0.01 V: the ±10 V column's µV figure, input-referred, at every gain. Reason (conservative: the
twin is never quieter than the hardware): behind an instrumentation amplifier of gain G the input-referred noise
is √((n_ADC / G)² + n_amp(G)²), between n₁₀ / G (ADC-limited: the ±10 V bits kept) and n₁₀ (amplifier-limited,
n_amp(1) ≤ n₁₀); the datasheet's general specs (A-3, Table A.3-1) give only the best case ("Noise (Peak-To-Peak)
<1 µV", "Effective Resolution (RMS) 22 bits", T7-Pro), so the upper bound is taken: at ±0.01 V and index 8 that is
36.8 µV rms, 9.1 effective bits — pessimistic by up to the gain; replace with the table when a copy is found.
[A] the command-response figures are applied in stream as well (the stream noise table was not found); T7-Pro
indices 9–12 are not served (the twin is a T7).
[D] stream rates, Appendix A-1 "Data Rates" (stream table), as quoted by the same project (calculate_max_speed,
"derived from https://labjack.com/support/datasheets/t-series/appendix-a-1"; A-1-1 "Stream Data Rates" in the
current numbering, whose stored copy also ends before its table): the maximum sample rate of a single-address
stream per resolution index, and of a multi-address stream per range and resolution index; 3.2 Stream Mode: "The
T7 max sample rate is 100 ksamples/second. This is achievable for any single-address stream, but for a
multi-address stream this is only true when resolution index = 0 or 1 and when range = ±10V for all analog
inputs." The quoted table has no multi-address entry for ±0.1 V above index 2 nor for ±0.01 V (-1 there).
[A] those entries: one gain decade costs what it costs from ±1 V to ±0.1 V at index 2, the last index both rows
give (7200 → 800 S/s, ×1/9; at index 1 it is ×0.21): ±0.1 V index i ≥ 3 = ±1 V index i / 9, ±0.01 V = ±0.1 V / 9.
Reason (conservative: a rate the twin accepts the hardware should accept too): the rate never rises with the gain
in the quoted table, ×1/9 is the steepest fall it shows, and A-3 Table A.3-1 gives the ±0.01 V range's -3 dB
frequency as 63 kHz against 337 kHz at ±0.1 V (slower settling, not faster). [A] a multi-address stream is bound by
the slowest of its inputs' ranges.
"""

from __future__ import annotations

STREAM_DEFAULT_INDEX = 1  # [D] STREAM_RESOLUTION_INDEX 0 → 1
COMMAND_DEFAULT_INDEX = 8  # [D] AIN#_RESOLUTION_INDEX 0 → 8 (T7)
MAX_INDEX = 8  # [D] T7: 0–8
ALL_MIXED = 0xFFFF  # [D] AIN_ALL_RESOLUTION_INDEX read when the inputs' indices differ

# [D] A-3-1, ±10 V: effective resolution [µV] (= RMS noise) per resolution index (bits 16.0 16.5 17.0 17.5 17.9
# 18.3 18.8 19.1)
NOISE_RMS_UV: dict[float, dict[int, float]] = {
    10.0: {1: 316.0, 2: 223.0, 3: 158.0, 4: 112.0, 5: 84.6, 6: 64.1, 7: 45.3, 8: 36.8},
}
# [A] ±1, ±0.1, ±0.01 V: not found; the ±10 V µV figures, input-referred (the upper bound, module docstring)
for _range in (1.0, 0.1, 0.01):
    NOISE_RMS_UV[_range] = dict(NOISE_RMS_UV[10.0])

# [D] A-1 stream table: single-address stream, max sample rate [S/s] per resolution index (any range)
SINGLE_MAX_HZ = {1: 100_000.0, 2: 48_000.0, 3: 22_000.0, 4: 11_000.0, 5: 5_500.0, 6: 2_500.0, 7: 1_200.0, 8: 600.0}
# [D] A-1 stream table: multi-address stream, max sample rate [S/s] per range and resolution index
MULTI_MAX_HZ: dict[float, dict[int, float]] = {
    10.0: {1: 100_000.0, 2: 39_600.0, 3: 19_800.0, 4: 9_800.0, 5: 4_400.0, 6: 2_600.0, 7: 1_300.0, 8: 630.0},
    1.0: {1: 8_200.0, 2: 7_200.0, 3: 2_800.0, 4: 2_600.0, 5: 1_300.0, 6: 640.0, 7: 440.0, 8: 400.0},
    0.1: {1: 1_700.0, 2: 800.0},
}
# [A] the entries the quoted table lacks (module docstring): one gain decade = ×(800 / 7200)
DECADE_FACTOR = MULTI_MAX_HZ[0.1][2] / MULTI_MAX_HZ[1.0][2]
for _i in range(3, MAX_INDEX + 1):
    MULTI_MAX_HZ[0.1][_i] = MULTI_MAX_HZ[1.0][_i] * DECADE_FACTOR
MULTI_MAX_HZ[0.01] = {i: hz * DECADE_FACTOR for i, hz in MULTI_MAX_HZ[0.1].items()}


def stream_index(value: float) -> int:
    """The resolution index a stream uses for STREAM_RESOLUTION_INDEX = ``value`` (0: the default, 1)."""
    return int(value) or STREAM_DEFAULT_INDEX


def command_index(value: int) -> int:
    """The resolution index a command-response read uses for AIN#_RESOLUTION_INDEX = ``value`` (0: 8)."""
    return int(value) or COMMAND_DEFAULT_INDEX


def noise_rms(range_volts: float, index: int) -> float:
    """RMS ADC noise [V] of one sample on ``range_volts`` (0: the default ±10 V) at resolution ``index`` (1–8):
    A-3-1's figure on ±10 V, its upper bound on the other ranges ([A] module docstring)."""
    return NOISE_RMS_UV[range_volts or 10.0].get(index, 0.0) * 1e-6


def max_sample_rate(ranges: list[float], index: int) -> float | None:
    """The table's maximum sample rate [S/s] of a stream of inputs on ``ranges`` (0: ±10 V) at resolution
    ``index``: the slowest entry of those ranges; None for an index outside 1–8."""
    if len(ranges) == 1:
        return SINGLE_MAX_HZ.get(index)
    known = [r for r in (MULTI_MAX_HZ.get(v or 10.0, {}).get(index) for v in ranges) if r is not None]
    return min(known) if known else None
