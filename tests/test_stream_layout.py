"""The run file's stream layout, now built from the instruments' ``describe()``, stays what every rig recorded before.

The expected tables are written out here (the layout of README "Run files" with each column's unit, description
and dtype, and each stream's source text), one per shipped rig family (lab and sim rigs record the same layout);
the column names and units are also checked against the README's table itself.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from bench.rig import load_rig
from bench.runtime.instruments import build_instruments
from bench.runtime.run import _streams
from tests.conftest import ROOT

C = tuple[str, str, str, str]  # name, units, description, dtype
LATE: C = ("late", "s", "software-timed: how long after its scheduled time the poll ran (NaN: not polled)", "f8")
SETPOINTS: list[C] = [("voltage", "V", "amplifier output commanded", "f8"),
                      ("aperture", "m", "LS-DEA aperture commanded (NaN: none)", "f8")]
VMON: C = ("voltage", "V", "output voltage from the TREK voltage monitor", "f8")
IMON: C = ("current", "A", "output current from the TREK current monitor", "f8")
COMMANDED: C = ("commanded", "V", "output commanded: the DAC code played in the same scan, through the conditioning "
                "stage and the amplifier's gain", "f8")
MOTOR: list[C] = [("position", "m", "motor encoder position", "f8"),
                  ("aperture", "m", "LS-DEA aperture from the motor position", "f8"), LATE]
T7 = "LabJack T7 stream, 10000 scans/s (one scan clock for every analog channel)"
U = "membrane in-plane displacement u"
X = "LS-DEA aperture x"


def keyence(measurand: str) -> list[C]:
    return [("displacement", "m", f"{measurand}, from the laser (offset and sign removed)", "f8"),
            ("valid", "1", "1 = measurement, 0 = over range / invalid", "u1"), LATE]


def analog_laser(measurand: str) -> list[C]:
    return [("displacement", "m", f"{measurand}, from the laser's analog output (offset and sign removed)", "f8"),
            ("valid", "1", "1 = measurement, 0 = invalid", "u1")]


EXPECTED: dict[str, tuple[dict[str, list[C]], dict[str, str]]] = {
    "thesis": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, LATE], "laser": keyence(U)},
               {"setpoints": "engine", "amplifier": "TREK 10/10B-HS via ADAM-4017+", "laser": "Keyence LK-G5000"}),
    "thesis-daq": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, COMMANDED], "laser": analog_laser(U)},
                   {"setpoints": "engine", "amplifier": f"TREK 10/10B-HS monitors on AIN0/AIN1; {T7}",
                    "laser": f"laser analog output on AIN2; {T7}"}),
    "lsdea-isotonic": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, LATE], "laser": keyence(X)},
                       {"setpoints": "engine", "amplifier": "TREK 10/10B-HS via ADAM-4017+",
                        "laser": "Keyence LK-G3000"}),
    "lsdea-isotonic-daq": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, COMMANDED], "laser": analog_laser(X)},
                           {"setpoints": "engine", "amplifier": f"TREK 10/10B-HS monitors on AIN0/AIN1; {T7}",
                            "laser": f"laser analog output on AIN2; {T7}"}),
    "lsdea-motor": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, LATE], "motor": MOTOR,
                     "load_cell": [("force", "N", "force on the load cell, tension positive", "f8"),
                                   ("ok", "1", "1 = stable reading", "u1"), LATE]},
                    {"setpoints": "engine", "amplifier": "TREK 10/10B-HS via ADAM-4017+", "motor": "LinMot LinRS",
                     "load_cell": "Dini Argeo DGT1S"}),
    "lsdea-motor-daq": ({"setpoints": SETPOINTS, "amplifier": [VMON, IMON, COMMANDED],
                         "load_cell": [("force", "N", "force from the load-cell bridge amplifier, tension positive",
                                        "f8"), ("ok", "1", "1 = every channel of the scan valid", "u1")],
                         "motor": MOTOR},
                        {"setpoints": "engine", "amplifier": f"TREK 10/10B-HS monitors on AIN0/AIN1; {T7}",
                         "load_cell": f"bridge amplifier on AIN2; {T7}", "motor": "LinMot LinRS"}),
}
# the shutdown's measured safe state (every shipped rig has an amplifier; the position where it has a motor)
SAFE_STATE: list[C] = [("voltage", "V", "output voltage from the voltage monitor, read by the shutdown to verify 0 V "
                        "(NaN: unreadable)", "f8"),
                       ("current", "A", "output current from the current monitor, read with it", "f8")]
SAFE_POSITION: C = ("position", "m", "motor position read once the carriage came to rest after the stop (the motor "
                    "event; NaN: not read)", "f8")
SAFE_SOURCE = ("engine: the shutdown's verifying reads of the voltage and current monitors (command-response: a DAQ's "
               "stream has stopped)")
for _streams_of, _sources_of in EXPECTED.values():
    _motor = "motor" in _streams_of
    _streams_of["safe_state"] = SAFE_STATE + ([SAFE_POSITION] if _motor else [])
    _sources_of["safe_state"] = SAFE_SOURCE + ("; the motor's position once at rest" if _motor else "")
RIGS = sorted((ROOT / "rigs").glob("*.toml"))


def layout(rig_path: Path) -> tuple[list[tuple[str, list[C]]], list[tuple[str, str]]]:
    rig = load_rig(rig_path)
    streams, sources = _streams(rig, build_instruments(rig))
    return ([(s, [(c.name, c.unit, c.description, c.dtype) for c in cols]) for s, cols in streams.items()],
            list(sources.items()))


@pytest.mark.parametrize("rig_path", RIGS, ids=[p.stem for p in RIGS])
def test_layout_from_descriptions_is_the_recorded_one(rig_path: Path) -> None:
    family = re.sub(r"-(lab|sim)$", "", rig_path.stem)
    assert family in EXPECTED, f"{rig_path}: write its expected layout here"
    streams, sources = EXPECTED[family]
    # order matters too: the file's groups and the sources attribute (JSON) keep it
    assert layout(rig_path) == (list(streams.items()), list(sources.items()))


def test_names_and_units_are_the_readmes() -> None:
    """Every ADAM rig's columns (besides `late`) with their units are those README "Run files" lists per group."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    readme = {g: re.findall(r"(\w+)(?: \[(\w+)\])?", re.sub(r"\([^)]*\)", "", cols.split("  ")[0]))
              for g, cols in re.findall(r"^/(setpoints|amplifier|laser|motor|load_cell|safe_state)/t, (.*)$", text,
                                        re.M)}
    assert set(readme) == {"setpoints", "amplifier", "laser", "motor", "load_cell", "safe_state"}
    for rig_path in (p for p in RIGS if "daq" not in p.stem):
        motor = load_rig(rig_path).motor is not None
        for stream, cols in layout(rig_path)[0]:
            got = [(name, "" if unit == "1" else unit) for name, unit, _, _ in cols if name != "late"]
            want = [(n, u) for n, u in readme[stream] if motor or stream != "safe_state" or n != "position"]
            assert got == want, (rig_path.stem, stream)


def test_the_live_view_shows_what_the_instruments_describe_in_their_units() -> None:
    """Issue 9: the live view takes its quantities and units from the run's layout (describe()), so a reading
    appears with its driver's SI unit, shown with a prefix; a quantity the layout does not hold is not shown."""
    from rich.console import Console

    from bench.runtime.context import Snapshot
    from bench.runtime.live import LiveView, units_of

    rig = load_rig(ROOT / "rigs" / "lsdea-motor-sim.toml")
    streams, _ = _streams(rig, build_instruments(rig))
    units = units_of(streams)
    assert (units["current"], units["aperture"], units["force"], units["setpoint"]) == ("A", "m", "N", "V")
    snap = Snapshot(duration=10.0, steps=1, values={"voltage": 6000.0, "current": 3.2e-5, "aperture": 0.1,
                                                     "force": -1.05, "setpoint": 6000.0, "colour": 3.0})
    console = Console(width=200, record=True)
    console.print(LiveView("run", snap, units))
    text = console.export_text()
    for shown in ("voltage 6 kV", "current 32 µA", "aperture 100 mm", "force -1.05 N", "setpoint 6 kV"):
        assert shown in text, shown
    assert "colour" not in text


@pytest.mark.parametrize("state", ["tripped", "latched", "error", "completed"])
def test_a_run_that_ended_shows_no_eta(state: str) -> None:
    """A tester's last frame after a trip read "ETA 0:00:09" from the speed before the trip: a run that ended has no
    time left to estimate."""
    from rich.console import Console

    from bench.runtime.context import Snapshot
    from bench.runtime.live import LiveView

    view = LiveView("run", Snapshot(t=1.0, duration=10.0, steps=1, state=state), {})
    view._wall0 -= 1.0  # one second of wall time: 1× real time, 9 s of the run left had it gone on
    console = Console(width=200, record=True)
    console.print(view)
    text = console.export_text()
    assert "ETA –" in text and f"[{state}]" in text
    running = LiveView("run", Snapshot(t=1.0, duration=10.0, steps=1, state="running"), {})
    running._wall0 -= 1.0
    console.print(running)
    assert "ETA 0:00:09" in console.export_text()
