"""An analysis judges "no drive" on the run's own voltage-monitor chain, recorded with the run (its rig), not on the
widest band of all chains.

The same 19-V raised cosine is run in virtual time on the T7 rig and on the ADAM rig. Its peak lies between the two
chains' 0-V bands, derived by hand from the instruments' figures in tests/test_monitor_chain.py: 15.3 V for the TREK
monitor into a LabJack T7 AIN, 23.3 V into an ADAM-4017+. So the T7 run was driven (its monitor tells 19 V from
0 V: lag and creep are given) and the ADAM run was not (19 V is within what its monitor reads at a true 0 V). Before,
both were judged on the widest band (23.3 V) and the T7 run's drive was dismissed as noise. A file whose rig is not
known is still judged on the widest band.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from bench.analysis.runs import RunAnalysis, analyse
from tests.conftest import ROOT
from tests.test_monitor_chain import ADAM_BAND, T7_BAND

PROTOCOL = """[protocol]
name = "low-drive"
description = "a raised cosine whose peak lies between the T7 and ADAM monitor chains' 0-V bands"
rig = "{rig}"

[recording]
displacement_Hz = 1000
monitors_Hz = 5
setpoint_Hz = 20

[[steps]]
type = "waveform"
name = "low"
channel = "voltage"
kind = "raised_cosine"
amplitude = "19 V"
frequency_Hz = 1.0
duration_s = 2.0

[[steps]]
type = "relax"
name = "recovery"
duration_s = 0.5
"""
RIGS = {"t7": ROOT / "rigs" / "thesis-daq-sim.toml", "adam": ROOT / "rigs" / "thesis-sim.toml"}
BAND = {"t7": T7_BAND, "adam": ADAM_BAND}
WIDEST = ADAM_BAND  # both TREK HS models at 10 kV, 1000 V/V: the ADAM-4017+'s accuracy makes its chain the widest


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from bench.runtime.run import execute, plan_run

    out: dict[str, Path] = {}
    for name, rig in RIGS.items():
        d = tmp_path_factory.mktemp(name)
        proto = d / "low-drive.toml"
        proto.write_text(PROTOCOL.format(rig=rig.as_posix()), encoding="utf-8")
        result = execute(plan_run(proto), d / "run.h5", virtual=True)
        assert result.state == "completed", result.reason
        out[name] = Path(result.path)
    return out


def _step(a: RunAnalysis) -> tuple[float, bool, str]:
    """(the step's peak |V|, whether its lag is given, the notes' text)."""
    (s,) = a.steps
    return s.voltage, bool(np.isfinite(s.figures["lag_first"])), "\n".join(a.notes)


def test_the_bands_are_apart_and_the_drive_lies_between_them(runs: dict[str, Path]) -> None:
    assert T7_BAND < 19.0 - 2.0 and 19.0 + 2.0 < ADAM_BAND  # the trial tests something: 19 V is clear of both
    for name, path in runs.items():
        peak, _, _ = _step(analyse(path))
        assert T7_BAND < peak < ADAM_BAND, (name, peak)


@pytest.mark.parametrize("name", ["t7", "adam"])
def test_the_no_drive_level_is_the_runs_own_monitor_chains_band(runs: dict[str, Path], name: str) -> None:
    a = analyse(runs[name])
    _, lag_given, notes = _step(a)
    if name == "t7":  # driven: its monitor tells 19 V from 0 V
        assert lag_given and "not driven" not in notes, notes
    else:  # within the ADAM chain's band: the monitor's reading of a true 0 V can be that high
        assert not lag_given and "not driven" in notes and f"≤ {ADAM_BAND:.3g} V" in notes, notes
    assert a.no_drive_v == pytest.approx(BAND[name], abs=1e-6)
    assert a.steps[0].no_drive_v == pytest.approx(BAND[name], abs=1e-6)


def test_a_file_whose_rig_is_not_known_is_judged_on_the_widest_band(runs: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "no-rig.h5"
    shutil.copy(runs["t7"], copy)
    with h5py.File(copy, "a") as f:
        del f.attrs["rig_toml"]
    a = analyse(copy)
    assert a.no_drive_v == pytest.approx(WIDEST, abs=1e-6)
    _, lag_given, notes = _step(a)
    assert not lag_given and f"≤ {WIDEST:.3g} V" in notes, notes
