"""A software-timed rig's laser record has one time base without duplicates (issue 23 item 7): back-to-back storing
steps each start the laser's data storage at the time the step before ended on, and that time is recorded once. The
same holds for the polled streams: a step's last poll and the next step's first fall on one instant in virtual
time, and the same reading was recorded twice (found from outside: the amplifier at 5.0 s and 12.0 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "laser-time-base"
description = "storing steps back to back on the software-timed rig"
rig = "thesis-sim"

[recording]
displacement_Hz = 1000
monitors_Hz = 10
setpoint_Hz = 50

[[steps]]
type = "ramp"
name = "up"
to = "2 kV"
duration_s = 0.5

[[steps]]
type = "waveform"
name = "wave"
kind = "sine"
amplitude = "1 kV"
offset = "2 kV"
frequency_Hz = 2.0
duration_s = 1.0

[[steps]]
type = "ramp"
name = "down"
to = "0 V"
duration_s = 0.5
"""


@pytest.fixture(scope="module")
def run_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("time-base")
    proto = tmp / "p.toml"
    proto.write_text(PROTOCOL)
    result = execute(plan_run(proto, ROOT / "rigs" / "thesis-sim.toml"), tmp / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    return Path(result.path)


def test_back_to_back_storing_steps_leave_no_duplicate_laser_times(run_path: Path) -> None:
    laser = open_run(run_path).streams["laser"]
    t = laser.t
    assert np.all(np.diff(t) > 0)  # strictly increasing: no time twice (today's main: 0.5 s and 1.5 s twice)
    # nothing lost at the boundaries: 1-ms samples across each step end (the storage's own clock, 1 kHz)
    for boundary in (0.5, 1.5):
        near = t[(t > boundary - 0.0105) & (t < boundary + 0.0105)]
        assert np.allclose(np.diff(near), 1e-3)


def test_no_row_is_recorded_twice_at_a_step_boundary(run_path: Path) -> None:
    run = open_run(run_path)
    for name, stream in run.streams.items():
        t = np.asarray(stream.t)
        if name != "setpoints":  # measured: one reading per time
            assert np.all(np.diff(t) > 0), name
            continue
        # commanded: two commands at one instant of virtual time only where the second replaced the first (the
        # shutdown ramp's last value, then 0 V), never the same command twice
        cols = np.column_stack([np.asarray(c, dtype=float) for c in stream.columns.values()])
        for k in np.flatnonzero(np.diff(t) <= 0):
            assert t[k + 1] == t[k]
            assert not np.array_equal(cols[k], cols[k + 1], equal_nan=True), (name, t[k])
    amp = np.asarray(run.streams["amplifier"].t)
    for boundary in (0.5, 1.5):  # the boundary's reading is there, once (monitors at 10 Hz)
        assert np.count_nonzero(np.isclose(amp, boundary, atol=1e-9)) == 1, boundary
