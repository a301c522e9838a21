"""A software-timed rig's laser record has one time base without duplicates (issue 23 item 7): back-to-back storing
steps each start the laser's data storage at the time the step before ended on, and that time is recorded once."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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


def test_back_to_back_storing_steps_leave_no_duplicate_laser_times(tmp_path: Path) -> None:
    proto = tmp_path / "p.toml"
    proto.write_text(PROTOCOL)
    result = execute(plan_run(proto, ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    laser = open_run(result.path).streams["laser"]
    t = laser.t
    assert np.all(np.diff(t) > 0)  # strictly increasing: no time twice (today's main: 0.5 s and 1.5 s twice)
    # nothing lost at the boundaries: 1-ms samples across each step end (the storage's own clock, 1 kHz)
    for boundary in (0.5, 1.5):
        near = t[(t > boundary - 0.0105) & (t < boundary + 0.0105)]
        assert np.allclose(np.diff(near), 1e-3)
