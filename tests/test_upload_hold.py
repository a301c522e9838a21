"""The dry run warns where a step that stores laser data ends with the output on (a software-timed rig): its last
stored values upload after it with the output held at its end value, up to the engine's 1-s bound, then ramped to
0 V (an outside tester: 3 kV held 1.18 s before a relax on a loaded host, the dry run silent).

The link's time, derived from the wire (8N1 = 10 bits a character; the LK-G's AN status query and one AO request,
16 + 3 + 3 + 16 characters, two 0.5-ms turnarounds [assumed], 9 characters a stored value, manual p. 5-6): 500 S/s
stored over one 50-ms fetch period (20 set-points/s) = 25 values, (38 + 25 × 9) × 10 / 115200 s + 1 ms = 23.8 ms:
the least the upload after the step can take (the engine polls the other instruments between its uploads)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import ROOT

PROTOCOL = """[protocol]
name = "store-then-relax"
description = "a ramp to 3 kV storing laser data, then a relax"
rig = "{rig}"

[recording]
displacement_Hz = 500
setpoint_Hz = 20

[[steps]]
type = "{kind}"
name = "up"
channel = "voltage"
{shape}
duration_s = 2.0

[[steps]]
type = "relax"
name = "down"
duration_s = 1.0
"""
RAMP = ("ramp", 'to = "3 kV"')
SINE = ("waveform", 'kind = "raised_cosine"\namplitude = "3 kV"\nfrequency_Hz = 1.0')  # two whole cycles: ends at 0 V
FLOOR_S = (38 + 25 * 9) * 10 / 115200 + 2 * 0.5e-3


def _write(tmp: Path, rig: str, kind_shape: tuple[str, str]) -> Path:
    path = tmp / f"{rig}-{kind_shape[0]}.toml"
    path.write_text(PROTOCOL.format(rig=(ROOT / "rigs" / f"{rig}.toml").as_posix(), kind=kind_shape[0],
                                    shape=kind_shape[1]), encoding="utf-8")
    return path


def test_a_storing_step_that_ends_energised_is_said_with_its_hold_and_the_run_keeps_within_it(tmp_path: Path) -> None:
    proto = _write(tmp_path, "thesis-sim", RAMP)
    plan = plan_run(proto)
    said = [w for w in plan.prediction.warnings if "storing laser data" in w]
    assert len(said) == 1 and "at 3000 V" in said[0] and "an upload past 1 s" in said[0], plan.prediction.warnings
    stated = float(re.search(r"~(\d+) ms at the rate the engine uploads", said[0])[1]) / 1e3  # type: ignore[index]
    assert stated >= FLOOR_S  # the link's time at least: the engine also polls between uploads
    # the rehearsal: the output held at the ramp's end while the upload went on, no less than the link's time (the
    # step is a whole number of fetch periods: one period's values are left) and within the bound
    result = execute(plan, tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    (text,) = [e[3] for e in open_run(result.path).event_list() if e[2] == "drain"]
    held = float(re.search(r"fetched for ([\d.]+) s", text)[1])  # type: ignore[index]
    assert "held at 3" in text and FLOOR_S <= stated <= held <= 1.0, (text, stated)


@pytest.mark.parametrize(("rig", "kind_shape"), [("thesis-sim", SINE), ("thesis-daq-sim", RAMP)])
def test_no_hold_is_said_where_none_comes(tmp_path: Path, rig: str, kind_shape: tuple[str, str]) -> None:
    """A storing step that ends at 0 V (whole raised-cosine cycles) holds nothing; on a DAQ rig the laser is an
    analog input on the scan clock and the device plays the next step on: no upload between steps."""
    plan = plan_run(_write(tmp_path, rig, kind_shape))
    assert not [w for w in plan.prediction.warnings if "storing laser data" in w], plan.prediction.warnings


def test_a_move_after_an_energising_step_holds_its_voltage_and_a_long_backlog_says_the_bound(tmp_path: Path) -> None:
    """A move step sets no voltage: it ends at the value the ramp before it left (3 kV), and it stores too (the
    LS-DEA software-timed rig). A link slower than the storage leaves the whole step's backlog: at 1000 S/s over
    10 s against the 670 S/s the thesis rig's link drains while a step runs (README, link budget), ~3300 values, past
    the 1-s bound — said as such, not as a time the output is held."""
    rig = tmp_path / "lsdea-motor-laser-sim.toml"  # the isometric bench with the isotonic bench's laser: a laser
    laser = re.search(r"\[laser\][^[]*", (ROOT / "rigs" / "lsdea-isotonic-sim.toml").read_text(encoding="utf-8"))
    assert laser is not None  # and a motor on one software-timed rig (no shipped rig has both)
    rig.write_text((ROOT / "rigs" / "lsdea-motor-sim.toml").read_text(encoding="utf-8")
                   .replace('name = "lsdea-motor-sim"', 'name = "lsdea-motor-laser-sim"') + "\n" + laser[0],
                   encoding="utf-8")
    proto = tmp_path / "move.toml"
    proto.write_text(f"""[protocol]
name = "ramp-move"
description = "a ramp to 3 kV, a move at 3 kV, a relax"
rig = "{rig.as_posix()}"

[recording]
displacement_Hz = 200
setpoint_Hz = 20
force_Hz = 10

[[steps]]
type = "move"
name = "to start"
position = "50 mm"
velocity = "0.05 m/s"

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "3 kV"
duration_s = 1.0

[[steps]]
type = "move"
name = "stretch"
position = "60 mm"
velocity = "0.01 m/s"

[[steps]]
type = "relax"
name = "down"
duration_s = 1.0
""", encoding="utf-8")
    said = [w for w in plan_run(proto).prediction.warnings if "storing laser data" in w]
    assert len(said) == 1 and said[0].startswith("2 steps storing laser data end with the output on"), said
    long = _write(tmp_path, "thesis-sim", RAMP)
    long.write_text(long.read_text(encoding="utf-8").replace("displacement_Hz = 500", "displacement_Hz = 1000")
                    .replace("duration_s = 2.0", "duration_s = 10.0"), encoding="utf-8")
    said = [w for w in plan_run(long).prediction.warnings if "storing laser data" in w]
    assert len(said) == 1 and "past the 1-s bound: the output held 1 s, then ramped to 0 V" in said[0], said
