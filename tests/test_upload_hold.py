"""The dry run warns where a step that stores laser data ends with the output on (a software-timed rig): its last
stored values upload after it with the output held at its end value, up to the engine's 1-s bound, then ramped to
0 V (an outside tester: 3 kV held 1.18 s before a relax on a loaded host, the dry run silent).

The link's time, derived from the wire (8N1 = 10 bits a character; the LK-G's AN status query and one AO request,
16 + 3 + 3 + 16 characters, two 0.5-ms turnarounds [assumed], 9 characters a stored value, manual p. 5-6): 500 S/s
stored over one 50-ms fetch period (20 set-points/s) = 25 values, (38 + 25 × 9) × 10 / 115200 s + 1 ms = 23.8 ms."""

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
    assert len(said) == 1 and "at 3000 V" in said[0] and "at most 1 s" in said[0], plan.prediction.warnings
    floor = float(re.search(r"at least (\d+) ms", said[0])[1]) / 1e3  # type: ignore[index]
    assert floor == pytest.approx(FLOOR_S, abs=1e-3)
    # the rehearsal: the output held at the ramp's end while the upload went on, no less than the link's time and
    # within the bound
    result = execute(plan, tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    (text,) = [e[3] for e in open_run(result.path).event_list() if e[2] == "drain"]
    held = float(re.search(r"fetched for ([\d.]+) s", text)[1])  # type: ignore[index]
    assert "held at 3" in text and FLOOR_S <= held <= 1.0, text


@pytest.mark.parametrize(("rig", "kind_shape"), [("thesis-sim", SINE), ("thesis-daq-sim", RAMP)])
def test_no_hold_is_said_where_none_comes(tmp_path: Path, rig: str, kind_shape: tuple[str, str]) -> None:
    """A storing step that ends at 0 V (whole raised-cosine cycles) holds nothing; on a DAQ rig the laser is an
    analog input on the scan clock and the device plays the next step on: no upload between steps."""
    plan = plan_run(_write(tmp_path, rig, kind_shape))
    assert not [w for w in plan.prediction.warnings if "storing laser data" in w], plan.prediction.warnings
