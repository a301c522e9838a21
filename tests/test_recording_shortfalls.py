"""Software-timed rigs say what they record below the asked rate (issue 23 item 6); the warning tells the truth.

The rate stated for the steps outside the laser's storage is checked against what a run on the same rig records
in them, counted from the run file: the warning is judged by the file, not by the code that wrote it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.runtime.run import plan_run
from bench.storage.runfile import open_run
from tests.conftest import RIGS, ROOT

SHORT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"


def test_a_hardware_timed_rig_with_the_laser_on_the_daq_falls_short_nowhere() -> None:
    plan = plan_run(SHORT, RIGS / "thesis-daq-sim.toml")
    assert plan.shortfalls == []


def test_the_software_timed_rig_states_the_rate_it_records_outside_the_storage_and_does_record_it(
        tmp_path: Path) -> None:
    plan = plan_run(SHORT, RIGS / "thesis-sim.toml")
    (short,) = plan.shortfalls
    relax = [s for s in plan.program.segments if s.kind == "relax"]
    relax_s = sum(s.duration for s in relax)  # from the protocol's steps
    assert relax and f"relax steps ({relax_s:.1f} of" in short
    stated_hz = float(short.split("single laser reads at ")[1].split(" Hz")[0])
    proc = subprocess.run([sys.executable, "-m", "bench", "-q", "run", str(SHORT), "--rig",
                           str(RIGS / "thesis-sim.toml"), "--virtual-time", "--out", str(tmp_path)],
                          capture_output=True, text=True, cwd=ROOT, stdin=subprocess.DEVNULL, timeout=300)
    assert proc.returncode == 0, proc.stderr
    run = open_run(Path(proc.stdout.strip()))
    t = run.streams["laser"].t
    offsets = run.step_offsets()
    for seg in relax:  # the samples in each relax step, away from its edges (the storage upload ends there)
        t0 = seg.t_start + offsets.get(seg.index, 0.0) + 0.2
        t1 = t0 + seg.duration - 0.4
        n = int(np.count_nonzero((t >= t0) & (t < t1)))
        assert n == pytest.approx(stated_hz * (t1 - t0), abs=2), (seg.label, n)


def test_validate_prints_the_shortfall_and_json_lists_it(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "bench", "validate", str(SHORT), "--rig", str(RIGS / "thesis-sim.toml")]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={"COLUMNS": "400", "PATH": ""},
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "warning: displacement: recording.displacement_Hz" in proc.stdout + proc.stderr
    assert "recording" in proc.stdout and "polled at" in proc.stdout
    proc = subprocess.run([*cmd, "--json"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0 and len(json.loads(proc.stdout)["recording_shortfalls"]) == 1
