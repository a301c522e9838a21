"""Protocol files: every shipped file validates; malformed or out-of-limit files are refused in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.protocol.program import ProtocolLimitError
from bench.protocol.schema import ProtocolFileError, json_schema, load_protocol
from bench.run import plan_run
from tests.conftest import ROOT

PROTOCOLS = sorted((ROOT / "protocols").rglob("*.toml"))
HEAD = """[protocol]
name = "t"
rig = "{rig}"

[recording]
displacement_Hz = 2000
setpoint_Hz = 20
"""
THESIS_RIG = str(ROOT / "rigs" / "thesis-sim.toml")
MOTOR_RIG = str(ROOT / "rigs" / "lsdea-motor-sim.toml")
ISOTONIC_RIG = str(ROOT / "rigs" / "lsdea-isotonic-sim.toml")


@pytest.mark.parametrize("path", PROTOCOLS, ids=lambda p: str(p.relative_to(ROOT / "protocols")))
def test_every_protocol_file_validates_and_dry_runs(path: Path) -> None:
    plan = plan_run(path)
    assert plan.prediction.ok and plan.program.duration > 0
    assert plan.prediction.peak_voltage > 0
    if plan.protocol.protocol.short_variant_of:
        assert plan.program.duration < 30  # CI variants stay short


def test_sweeps_expand_with_their_values() -> None:
    p = load_protocol(ROOT / "protocols" / "thesis-voltage-sweep.toml")
    drives = [s for s in p.steps if s.type == "waveform"]
    assert [s.amplitude_si for s in drives] == [5000.0, 6000.0, 7000.0, 8000.0]
    assert drives[0].name == "drive [voltage=5000 V]"
    iso = load_protocol(ROOT / "protocols" / "lsdea-isopotential.toml")
    cycles = [s for s in iso.steps if s.type == "waveform"]
    assert len(cycles) == 3 * 3 * 4  # prototypes × Δx × voltages (outer product)
    assert {round(s.amplitude_si, 3) for s in cycles} == {0.05, 0.07, 0.09}


def write(tmp: Path, body: str, rig: str = THESIS_RIG, head: str = HEAD) -> Path:
    f = tmp / "p.toml"
    f.write_text(head.format(rig=rig) + body)
    return f


WAVE = """
[[steps]]
type = "waveform"
channel = "{channel}"
kind = "raised_cosine"
amplitude = "{amp}"
frequency_Hz = {f}
duration_s = {d}
"""


@pytest.mark.parametrize("body, rig, message", [
    ("", THESIS_RIG, "steps: give at least one [[steps]] table"),
    ("[[steps]]\ntype = 'waveform'\nfrequency_Hz = 1\nduration_s = 1\n", THESIS_RIG,
     "steps[0](waveform).amplitude: Field required"),
    (WAVE.format(channel="voltage", amp="7000", f=0.5, d=2), THESIS_RIG, "'7000' is not a number with a unit"),
    (WAVE.format(channel="voltage", amp="45 mm", f=0.5, d=2), THESIS_RIG, "'45 mm' is a length, expected a voltage"),
    (WAVE.format(channel="voltage", amp="9 kV", f=0.5, d=2), THESIS_RIG,
     "peak voltage 9000 V exceeds the rig limit 8000 V"),
    (WAVE.format(channel="voltage", amp="5 kV", f=5.0, d=2), THESIS_RIG, "recording.setpoint_Hz ≥ 100"),
    (WAVE.format(channel="position", amp="20 mm", f=0.5, d=2), THESIS_RIG, "rig thesis-sim has no motor"),
    ("[[steps]]\ntype = 'move'\nposition = '150 mm'\n", MOTOR_RIG, "outside travel [0.0, 95.0] mm"),
    (WAVE.format(channel="voltage", amp="5 kV", f=0.5, d=40), ISOTONIC_RIG,
     "exceed the LK-G3000 storage of 65536 points"),
    ("[[steps]]\ntype = 'sweep'\nover = {v = {start = '1 kV'}}\n", THESIS_RIG,
     "a range needs start, stop and one of step"),
    ("[[steps]]\ntype = 'teleport'\n", THESIS_RIG, "steps[0](teleport): Input tag 'teleport' found"),
    ("[[steps]]\ntype = 'set'\nhung_mass_kg = 0.1\n", THESIS_RIG, "hung_mass_kg and prototype apply to the LS-DEA"),
    ("[[steps]]\ntype = 'waveform'\nkind = 'square'\noffset = '8 kV'\namplitude = '0 kV'\nfrequency_Hz = 0.05\n"
     "duration_s = 20\n", THESIS_RIG, "model predicts specimen failure: runaway stretch"),
])
def test_bad_protocols_are_refused_with_one_line(tmp_path: Path, body: str, rig: str, message: str) -> None:
    f = write(tmp_path, body, rig)
    with pytest.raises((ProtocolFileError, ProtocolLimitError)) as err:
        plan_run(f)
    text = str(err.value)
    assert message in text and str(f) in text and "\n" not in text


def test_breakdown_margin_is_enforced_by_the_dry_run(tmp_path: Path) -> None:
    rig = (ROOT / "rigs" / "lsdea-motor-sim.toml").read_text().replace(
        "max_force_N = 15.0", "max_force_N = 15.0\nbreakdown_margin = 1.5")
    (tmp_path / "rig.toml").write_text(rig)
    body = """
[[steps]]
type = "move"
position = "50 mm"

[[steps]]
type = "ramp"
channel = "voltage"
to = "7 kV"
duration_s = 1

[[steps]]
type = "waveform"
channel = "position"
offset = "50 mm"
amplitude = "90 mm"
frequency_Hz = 0.5
cycles = 1
"""
    f = write(tmp_path, body, str(tmp_path / "rig.toml"), HEAD.replace("setpoint_Hz = 20", "setpoint_Hz = 100"))
    with pytest.raises(ProtocolLimitError, match=r"margin 1\.2\d below limits.breakdown_margin 1\.5"):
        plan_run(f)


def test_cli_validate_prints_the_prediction_and_refuses_cleanly(tmp_path: Path) -> None:
    ident = ROOT / "protocols" / "thesis-identification.toml"
    ok = subprocess.run([sys.executable, "-m", "bench", "validate", str(ident)], capture_output=True, text=True,
                        timeout=120, env={"COLUMNS": "200", "PATH": ""})
    assert ok.returncode == 0, ok.stderr
    assert "peak true field" in ok.stdout and "36.0 MV/m" in ok.stdout and "laser 200,050" in ok.stdout
    bad = write(tmp_path, WAVE.format(channel="voltage", amp="9 kV", f=0.5, d=2))
    proc = subprocess.run([sys.executable, "-m", "bench", "run", str(bad), "--dry-run"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().startswith("error: protocol file") and proc.stderr.strip().count("\n") == 0


def test_json_schema_is_exported_and_committed() -> None:
    schema = json.loads(json_schema())
    assert schema["title"] == "dea-bench protocol file"
    assert {"protocol", "recording", "steps"} <= set(schema["properties"])
    committed = ROOT / "protocols" / "protocol.schema.json"
    hint = "regenerate: bench protocol schema --out protocols/protocol.schema.json"
    assert json.loads(committed.read_text()) == schema, hint


def test_repeat_and_zip_sweeps_expand(tmp_path: Path) -> None:
    body = """
[[steps]]
type = "repeat"
count = 3

  [[steps.steps]]
  type = "ramp"
  channel = "voltage"
  to = "1 kV"
  duration_s = 1

  [[steps.steps]]
  type = "relax"
  duration_s = 1

[[steps]]
type = "sweep"
mode = "zip"
over = { v = ["2 kV", "3 kV"], f = [0.5, 1.0] }

  [[steps.steps]]
  type = "waveform"
  channel = "voltage"
  kind = "sine"
  amplitude = "{v}"
  frequency_Hz = "{f}"
  cycles = 2
"""
    p = load_protocol(write(tmp_path, body))
    assert [s.type for s in p.steps] == ["ramp", "relax"] * 3 + ["waveform"] * 2
    assert [(s.amplitude_si, s.frequency_Hz) for s in p.steps[6:]] == [(2000.0, 0.5), (3000.0, 1.0)]
    assert p.labels[2].startswith("steps[0](repeat)#2/")
    assert plan_run(p.path).program.duration == pytest.approx(3 * 2 + 4 + 2)
