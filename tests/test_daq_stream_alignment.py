"""On a hardware-timed rig every stream ends on the last scan, and the `commanded` column's alignment with the
protocol is what the README states (issue 23 item 7), measured against the protocol's own waveform: a linear ramp
of 2 kV over 1 s (slope 2000 V/s) after 0.2 s at 0 V."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "ramp-alignment"
description = "a linear ramp: the commanded column against the protocol's waveform"
rig = "thesis-daq-sim"

[recording]
displacement_Hz = 10000
monitors_Hz = 10
setpoint_Hz = 20

[[steps]]
type = "relax"
name = "rest"
duration_s = 0.2

[[steps]]
type = "ramp"
name = "up"
to = "2 kV"
duration_s = 1.0

[[steps]]
type = "hold"
name = "hold"
duration_s = 0.3
"""
SLOPE = 2000.0  # V/s, the protocol's ramp
SCAN = 1e-4  # s, 10 kHz (the rig file)


def test_streams_end_on_the_last_scan_and_commanded_lags_the_program_by_one_scan(tmp_path: Path) -> None:
    proto = tmp_path / "ramp.toml"
    proto.write_text(PROTOCOL)
    result = execute(plan_run(proto, ROOT / "rigs" / "thesis-daq-sim.toml"), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    amp, laser = run.streams["amplifier"], run.streams["laser"]
    # one scan clock: the same time array for every DAQ stream (no software-timed sample after the last scan)
    assert len(amp) == len(laser) and np.array_equal(amp.t, laser.t)
    # the program's stream, then the shutdown's ramp to 0 V on a stream of its own
    timing, ramp = [text for _, _, k, text in run.event_list() if k == "timing"]
    assert "ramp to 0 V" in ramp
    assert "scan 0 at 0.000100 s" in timing  # one scan period after the enable, at run time 0 in virtual time
    t, c = amp.t, amp.columns["commanded"]
    ramp = (t > 0.3) & (t < 1.1)  # clear of the corners (the drive filter's pre-compensation)
    program = (t[ramp] - 0.2) * SLOPE  # the protocol's voltage at the row's run time (= program time here)
    lag = np.median((program - c[ramp]) / SLOPE)
    # README "Two kinds of rig": row k (scan k, at t0 + k/rate) holds the value the DAC takes at scan k, which is the
    # program's voltage one scan period earlier (scan 0 plays the step's start value)
    assert abs(lag - SCAN) < 0.05 * SCAN
