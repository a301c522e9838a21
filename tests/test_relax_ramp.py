"""A relax step's ramp to 0 V is a schema field with a stated default (issue 23 item 7).

Expected values come from the schema's documentation (README "Protocol files", the schema module's docstring):
``ramp_down_s`` when given, else 0.5 s or a tenth of the step, whichever is shorter.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from bench.protocol.program import voltage_at
from bench.protocol.schema import ProtocolFileError
from bench.runtime.run import plan_run
from tests.conftest import ROOT
from tests.test_protocols import SAFE_HEAD, SAFE_THESIS_RIG

RAMP_UP = '[[steps]]\ntype = "ramp"\nchannel = "voltage"\nto = "2 kV"\nduration_s = 1.0\n\n'


def _protocol(tmp: Path, relax: str) -> Path:
    f = tmp / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=SAFE_THESIS_RIG) + RAMP_UP + '[[steps]]\ntype = "relax"\n' + relax)
    return f


@pytest.mark.parametrize(("relax", "ramp"), [("duration_s = 60.0\n", 0.5),  # the default: 0.5 s
                                             ("duration_s = 2.0\n", 0.2),  # a tenth of a 2-s step
                                             ("duration_s = 60.0\nramp_down_s = 3.0\n", 3.0)])
def test_the_voltage_reaches_zero_at_the_end_of_the_stated_ramp(tmp_path: Path, relax: str, ramp: float) -> None:
    seg = plan_run(_protocol(tmp_path, relax)).program.segments[1]
    assert seg.kind == "relax" and seg.t_start == pytest.approx(1.0)
    assert voltage_at(seg, seg.t_start) == pytest.approx(2000.0)
    assert voltage_at(seg, seg.t_start + ramp / 2) == pytest.approx(1000.0)  # linear: half-way at half the time
    assert voltage_at(seg, seg.t_start + ramp) == pytest.approx(0.0, abs=1e-9)
    assert seg.stream_until == pytest.approx(seg.t_start + ramp)  # set-points at the full rate during the ramp


@pytest.mark.parametrize(("body", "fragment"), [
    ('[[steps]]\ntype = "hold"\nduration_s = 5.0\nramp_down_s = 1.0\n', "ramp_down_s applies to a relax step"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = 2.0\n', "longer than the step's duration_s"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = 0\n', "ramp_down_s"),
    ('[[steps]]\ntype = "relax"\nduration_s = 1.0\nramp_down_s = nan\n', "ramp_down_s"),
])
def test_a_wrong_ramp_down_is_refused_in_one_line_naming_the_field(tmp_path: Path, body: str, fragment: str) -> None:
    f = tmp_path / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=SAFE_THESIS_RIG) + RAMP_UP + body)
    with pytest.raises(ProtocolFileError) as err:
        plan_run(f)
    text = str(err.value)
    assert str(f) in text and fragment in text and "\n" not in text, text


def test_validate_shows_the_relax_ramp(tmp_path: Path) -> None:
    f = _protocol(tmp_path, "duration_s = 60.0\nramp_down_s = 3.0\n")
    proc = subprocess.run([sys.executable, "-m", "bench", "validate", str(f)], capture_output=True, text=True,
                          cwd=ROOT, env={"COLUMNS": "300", "PATH": ""}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "relax steps" in proc.stdout and "voltage to 0 V over 3 s" in proc.stdout
