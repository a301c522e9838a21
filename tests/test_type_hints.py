"""A value of the wrong TOML type says what to write instead (a tester: `max_voltage_V = "5kV"` gave only pydantic's
"unable to parse string as a number"; `amplitude = 5000` "Input should be a valid string"; `port = ""` passed
validation and failed at connect as "cannot open Modbus link : no such device").

The expected hints follow the files' convention stated in the README: a rig field's unit is its name's suffix (a
plain number in it, or a quantity with any unit of its dimension); a protocol quantity is a string with its unit.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.protocol.schema import ProtocolFileError, load_protocol
from bench.rig import RigFileError, load_rig
from tests.conftest import ROOT


def _rig_with(tmp: Path, old: str, new: str) -> Path:
    text = (ROOT / "rigs" / "thesis-sim.toml").read_text()
    assert old in text
    f = tmp / "r.toml"
    f.write_text(text.replace(old, new, 1))
    return f


def test_a_number_written_with_its_unit_is_read_in_the_unit_its_name_gives(tmp_path: Path) -> None:
    """Rig files take quantities as protocol files do (README "Rig files"): "5kV" in `max_voltage_V` is 5000 V; a
    unit that is none ("kv": unit symbols are case-sensitive, kV) is refused naming the field and the unit; a
    field whose name carries no unit still says to write a plain number."""
    f = _rig_with(tmp_path, "max_voltage_V = 8000.0", 'max_voltage_V = "5kV"')
    assert load_rig(f).limits.max_voltage_V == 5000.0
    f = _rig_with(tmp_path, "max_voltage_V = 8000.0", 'max_voltage_V = "5 kv"')
    with pytest.raises(RigFileError) as e:
        load_rig(f)
    msg = str(e.value)
    assert "limits.max_voltage_V: '5 kv': unknown unit 'kv'" in msg and "\n" not in msg, msg
    f = _rig_with(tmp_path, "max_voltage_V = 8000.0", 'max_voltage_V = 8000.0\nbreakdown_margin = "1.2x"')
    with pytest.raises(RigFileError) as e:
        load_rig(f)
    msg = str(e.value)
    assert "limits.breakdown_margin" in msg and '"1.2x"' in msg and "write a plain number, without quotes" in msg, msg


def test_an_empty_port_is_refused_when_the_rig_is_read_not_at_connect(tmp_path: Path) -> None:
    f = _rig_with(tmp_path, 'port = "sim"', 'port = ""')
    with pytest.raises(RigFileError, match=r"port: String should have at least 1 character"):
        load_rig(f)


def test_a_quantity_written_as_a_bare_number_says_to_give_its_unit(tmp_path: Path) -> None:
    f = tmp_path / "p.toml"
    f.write_text(f'[protocol]\nname = "t"\nrig = "{ROOT / "rigs" / "thesis-sim.toml"}"\n\n[[steps]]\n'
                 'type = "waveform"\nchannel = "voltage"\nkind = "sine"\noffset = "2 kV"\namplitude = 1000\n'
                 'frequency_Hz = 1\ncycles = 1\n')
    with pytest.raises(ProtocolFileError) as e:
        load_protocol(f)
    assert 'amplitude = "1000 <unit>"' in str(e.value)


def test_a_ratio_field_names_its_whole_unit_and_a_plain_string_field_gets_no_unit_hint(tmp_path: Path) -> None:
    """A reviewer: `laser_m_per_V = "0.001 m/V"` was told "a plain number in V"; `port = 3` was told
    `port = "3 <unit>"`."""
    from bench.tomlfile import type_hint

    err = {"type": "float_parsing", "loc": ("daq", "laser_m_per_V"), "input": "0.001 m/V"}
    assert "plain number in m/V," in type_hint(err)
    assert "plain number in V/s," in type_hint({**err, "loc": ("amplifier", "slew_limit_V_per_s")})
    assert type_hint({"type": "string_type", "loc": ("buses", "io", "port"), "input": 3}) == ""
