"""A silent instrument during high voltage: the run ends as that instrument's fault, not as a host stall.

On the motor bench (rigs/lsdea-motor-sim.toml) the load cell has a bus of its own ("scale") beside the set-point
module's ("io"). Its twin muted over the real transport (sim_devices.transport.Faults ``mute``: the request is
taken, no reply comes), the driver waits its timeout on each of its attempts while the host sends the set-point
module nothing. The run must say that the load cell went silent — a researcher reading "host stall" looks for a
CPU or OS fault — end at 0 V at the plant with the motor stopped, and, when the set-point module's watchdog did
fire while the host waited, latch naming the load cell. A real host stall still latches as one
(tests/test_interlock.py).
"""

from __future__ import annotations

from pathlib import Path

from bench.runtime.engine import Engine
from tests.conftest import ROOT
from tests.test_interlock import ZERO_V, events, run_with_fault

RIG = ROOT / "rigs" / "lsdea-motor-sim.toml"
MUTE_AT = 1.0  # run time [s] of the mute: in the 3-kV hold (the ramp ends at 0.3 s)
PROTOCOL = f"""[protocol]
name = "silent-load-cell"
description = "3 kV held while the load cell is read at 100 Hz"
rig = "{RIG}"

[recording]
setpoint_Hz = 20
force_Hz = 100
position_Hz = 20
monitors_Hz = 5

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "3 kV"
duration_s = 0.3

[[steps]]
type = "hold"
name = "hold"
duration_s = 2.5

[[steps]]
type = "relax"
name = "end"
duration_s = 0.2
"""


def mute_scale(_engine: Engine, sim) -> None:
    sim.faults["scale"].mute = True


def _run(tmp_path: Path, rig: Path, wire: list[str] | None = None):
    """The protocol on ``rig`` with the load cell muted at :data:`MUTE_AT`; ``wire``: gets, in order, "io" for
    each reply of the amplifier's bus and "scale muted" for each load-cell request left unanswered."""
    protocol = tmp_path / "silent-load-cell.toml"
    protocol.write_text(PROTOCOL.replace(str(RIG), str(rig)), encoding="utf-8")

    def action(engine: Engine, sim) -> None:
        if wire is not None:
            for bus in ("io", "scale"):
                faults = sim.faults[bus]
                process = faults.process

                def logged(reply: bytes, request_len: int = 0, bus: str = bus, faults=faults, process=process):
                    out = process(reply, request_len)
                    if bus == "io" or (reply and out[0] is None and faults.mute):
                        wire.append(bus if bus == "io" else "scale muted")
                    return out
                faults.process = logged
        mute_scale(engine, sim)
    return run_with_fault(rig, tmp_path, MUTE_AT, action, virtual=False, protocol=protocol)


def _ends_safe(result, run, plant) -> None:
    """0 V at the plant at the end (high voltage before the mute), the motor's stop sent, the file's reason set."""
    assert plant.last_high() > plant.t_fault - 1.0  # the output was on when the load cell went silent
    _t, v = plant.arrays()
    assert abs(float(v[-1])) <= ZERO_V
    assert any("stop sent" in text for text in events(run, "motor"))
    assert run.reason.startswith(result.reason)


def test_a_silent_load_cell_ends_the_run_as_the_load_cells_fault(tmp_path: Path) -> None:
    """The shipped bus settings (0.5-s timeout, one retry: 1 s of waiting, longer than the 0.8-s stall bound).
    Between the load cell's two unanswered attempts the set-point module gets a request (its keep-alive is not
    starved by the wait); the run ends as the load cell's timeout."""
    wire: list[str] = []
    result, run, plant = _run(tmp_path, RIG, wire)
    first = wire.index("scale muted")
    second = wire.index("scale muted", first + 1)
    assert "io" in wire[first + 1:second], wire[first:second + 1]
    assert result.state in ("error", "tripped"), result.reason
    assert "host stall" not in result.reason and "host stall" not in result.latched, (result.reason, result.latched)
    assert not any("host stall" in text for text in events(run, "interlock"))
    assert "load cell" in result.reason, result.reason  # the cause names the instrument that went silent
    assert "no valid reply" in result.reason  # the driver's own words: its timeout, not a refusal
    _ends_safe(result, run, plant)


def test_a_watchdog_that_fires_while_the_host_waits_on_the_load_cell_latches_naming_it(tmp_path: Path) -> None:
    """One attempt longer than the set-point module's 1-s watchdog (``timeout_s = 1.5``, no retry): no keep-alive
    can go out during that wait, so the watchdog fires; the latch names the load cell, not a host stall."""
    text = RIG.read_text(encoding="utf-8")
    assert "[buses.scale]\nport = \"sim\"\n" in text
    rig = tmp_path / "lsdea-motor-sim-slow-scale.toml"
    rig.write_text(text.replace("[buses.scale]\nport = \"sim\"\n",
                                "[buses.scale]\nport = \"sim\"\ntimeout_s = 1.5\nretries = 0\n"), encoding="utf-8")
    result, run, plant = _run(tmp_path, rig)
    assert result.latched.startswith("interlock: load cell silent"), result.latched
    assert result.state in ("error", "tripped") and "load cell" in result.reason, result.reason
    assert "host stall" not in result.reason and "host stall" not in result.latched
    assert "its watchdog fired" in result.latched  # the ADAM-4024's own flag (40216, ADAM-4000 manual app. G)
    assert any("load cell silent" in text for text in events(run, "interlock"))
    _ends_safe(result, run, plant)

