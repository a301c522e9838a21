"""The noise model's datasheet side (issue 27): each record's σ is the larger of the record's own estimate and its
instrument's datasheet floor, read from the rig stored in the run file.

Expected floors are computed here by hand from the rig files and the catalogue figures (LK-G152 repeatability
0.5 µm at averaging 4096, scaled by √(4096/N); load cell 0.2 g rms at 100 S/s, white: × √(rate/100)) and the
sample counts the protocols set (laser at 10 kHz, one 10-ms window per 100-Hz data point) — not from the code
under test."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from bench.benchmarks import noise_free_rig
from bench.identify.problems import LozengeProblem, MembraneProblem

ROOT = Path(__file__).resolve().parent.parent
G = 9.80665
# thesis-daq-sim.toml: LK-G152 head (the rig default), averaging 64 (default); 10-kHz laser samples (the T7's scan),
# MembraneProblem's 100-Hz window means → 100 samples a window
HEAD_M = 0.5e-6 * math.sqrt(4096 / 64)
MEMBRANE_FLOOR_M = HEAD_M / math.sqrt(10_000 / 100)


def _run(protocol: str, rig: Path | None, out: Path) -> Path:
    from bench.runtime.run import execute, plan_run

    res = execute(plan_run(ROOT / "protocols" / "short" / protocol, rig), out / "run.h5", virtual=True,
                  operator=lambda _msg: True)
    assert res.state == "completed", res.reason
    return Path(res.path)


@pytest.fixture(scope="module")
def membrane_runs(tmp_path_factory: pytest.TempPathFactory, short_run: Path) -> dict[str, Path]:
    """The short thesis identification on its T7 rig: noise off, and noise on (the latter is the session's run of
    it, conftest's short_run, made once: copied here)."""
    out = tmp_path_factory.mktemp("floor-membrane")
    quiet = noise_free_rig(ROOT / "rigs" / "thesis-daq-sim.toml", out)
    (out / "quiet").mkdir()
    (out / "noisy").mkdir()
    shutil.copy2(short_run, out / "noisy" / "run.h5")
    return {"quiet": _run("thesis-identification-short.toml", quiet, out / "quiet"), "noisy": out / "noisy" / "run.h5"}


def _with_rig_toml(run: Path, out: Path, edit: str | None) -> Path:
    """A copy of ``run`` whose stored rig has ``averaging = 64`` replaced by ``edit`` (None: no rig stored)."""
    copy = out / f"{run.stem}-edited.h5"
    assert copy != run
    shutil.copy(run, copy)
    with h5py.File(copy, "r+") as f:
        text = f.attrs["rig_toml"]
        text = text.decode() if isinstance(text, bytes) else str(text)
        if edit is None:
            del f.attrs["rig_toml"]
        else:
            assert "averaging = 64" in text
            f.attrs["rig_toml"] = text.replace("averaging = 64", edit)
    return copy


def test_a_noise_free_record_is_weighed_by_the_laser_datasheet(membrane_runs: dict[str, Path]) -> None:
    """Noise off, the record's own estimate is its quantisation (far below the head's figure): σ is the datasheet
    floor, the head's noise over √(samples per window); the trust JSON's floor is the same figure."""
    prob = MembraneProblem([membrane_runs["quiet"]])
    assert len(prob.records) == 1
    assert prob.noise_datasheet == pytest.approx([MEMBRANE_FLOOR_M], rel=0.01)  # 100 or 101 samples a window
    assert prob.noise_datasheet[0] <= MEMBRANE_FLOOR_M * (1 + 1e-9)  # never above the hand figure
    assert np.all(prob.sigma == prob.noise_datasheet[0])
    # point values (no averaging): one sample's noise, the samples on the grid
    point = MembraneProblem([membrane_runs["quiet"]], average=False)
    assert point.noise_datasheet == pytest.approx([HEAD_M], rel=1e-6)
    assert np.all(point.sigma == point.noise_datasheet[0])


def test_a_noisier_record_than_its_datasheet_keeps_its_own_sigma(membrane_runs: dict[str, Path],
                                                                  tmp_path: Path) -> None:
    """A rig stored as averaging 4096 (floor 8× lower) over a record taken at 64: σ is the record's own estimate,
    which is near the noise the twin added (the head's at 64 over √100), not the floor."""
    claimed = _with_rig_toml(membrane_runs["noisy"], tmp_path, "averaging = 4096")
    prob = MembraneProblem([claimed])
    floor = 0.5e-6 / math.sqrt(100)
    assert prob.noise_datasheet == pytest.approx([floor], rel=0.01)
    assert 0.7 * MEMBRANE_FLOOR_M < prob.sigma[0] < 1.5 * MEMBRANE_FLOOR_M
    assert np.all(prob.sigma == prob.sigma[0])


def test_a_file_without_its_rig_has_no_floor(tmp_path: Path) -> None:
    """Older files store no rig: no datasheet floor (0), σ is the record's own estimate; with its rig, the same
    record's σ is the larger of that and the floor. On the serial rig (its voltage the set-point: the monitor's
    calibration needs no rig) the problem reads such a file."""
    quiet = noise_free_rig(ROOT / "rigs" / "thesis-sim.toml", tmp_path)
    run = _run("thesis-identification-short.toml", quiet, tmp_path)
    with_rig = MembraneProblem([run])
    bare = MembraneProblem([_with_rig_toml(run, tmp_path, None)])
    assert with_rig.noise_datasheet[0] > 0.0 and bare.noise_datasheet == [0.0]
    assert bare.sigma[0] > 0.0 and np.all(bare.sigma == bare.sigma[0])
    assert np.all(with_rig.sigma == max(bare.sigma[0], with_rig.noise_datasheet[0]))
    assert with_rig.noise_datasheet == pytest.approx([MEMBRANE_FLOOR_M], rel=0.01)  # the same head, 10 kHz


def test_a_noise_free_force_record_is_weighed_by_the_load_cell_datasheet(tmp_path: Path) -> None:
    """LS-DEA on the motor (force from the bridge amplifier on the T7 at 10 kHz, points on the samples): noise off,
    σ of every record is the load cell's figure at the scan rate, 0.2 g × √(10000/100) × g."""
    rig = noise_free_rig(ROOT / "rigs" / "lsdea-motor-daq-sim.toml", tmp_path)
    prob = LozengeProblem([_run("lsdea-isometric-short.toml", rig, tmp_path)])
    want = 0.2e-3 * math.sqrt(10_000 / 100) * G
    assert prob.records and prob.noise_datasheet == pytest.approx([want] * len(prob.records), rel=1e-6)
    start = 0
    for rec, floor in zip(prob.records, prob.noise_datasheet, strict=True):
        assert np.all(prob.sigma[start:start + rec.data.size] == floor)
        start += rec.data.size
