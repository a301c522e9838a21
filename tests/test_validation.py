"""Issue 8, "safe under every failure": finite values, limits within the instruments' capability, bounded input,
and no traceback on the known classes of bad input (each a one-line error naming the file and field, exit 2).

Expected figures come from the datasheets, not from the code: TREK 10/10B-HS 10 kV / 10 mA, 10/40A-HS
10 kV / 40 mA; standard gravity 9.80665 m/s² (CGPM 1901).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from bench.rig import RigFileError, load_rig
from tests.conftest import RIGS, ROOT

THESIS_SIM = (RIGS / "thesis-sim.toml").read_text()
MOTOR_SIM = (RIGS / "lsdea-motor-sim.toml").read_text()


def _set(text: str, table: str, key: str, value: str) -> str:
    """``text`` with ``key = value`` in ``[table]`` (replacing the key if present)."""
    lines = text.splitlines()
    start = lines.index(f"[{table}]")
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    body = [ln for ln in lines[start + 1:end] if ln.split("=")[0].strip() != key]
    return "\n".join([*lines[:start + 1], f"{key} = {value}", *body, *lines[end:]]) + "\n"


def _refused(tmp_path: Path, text: str) -> str:
    f = tmp_path / "rig.toml"
    f.write_text(text)
    with pytest.raises(RigFileError) as err:
        load_rig(f)
    msg = str(err.value)
    assert str(f) in msg and "\n" not in msg
    return msg


# ---------------------------------------------------------------------------------------------- rig files


@pytest.mark.parametrize("table, key, value", [
    ("laser", "offset_mm", "nan"),
    ("laser", "offset_mm", "-inf"),
    ("laser", "range_mm", "inf"),
    ("limits", "max_force_N", "inf"),
    ("limits", "max_current_A", "nan"),
    ("specimen", "displacement_length_m", "inf"),
    ("specimen", "temperature_K", "nan"),
])
def test_rig_floats_must_be_finite(tmp_path: Path, table: str, key: str, value: str) -> None:
    msg = _refused(tmp_path, _set(THESIS_SIM, table, key, value))
    assert f"{table}.{key}" in msg and "finite" in msg


@pytest.mark.parametrize("key, value", [("division_kg", "inf"), ("capacity_kg", "inf"), ("capacity_kg", "nan")])
def test_load_cell_floats_must_be_finite(tmp_path: Path, key: str, value: str) -> None:
    msg = _refused(tmp_path, _set(MOTOR_SIM, "load_cell", key, value))
    assert f"load_cell.{key}" in msg and "finite" in msg


def test_current_limit_within_the_amplifier(tmp_path: Path) -> None:
    ok = tmp_path / "ok.toml"
    # exactly the 10/10B-HS rating, on a current monitor that reads beyond it (2 mA/V × 10 V = 20 mA)
    ok.write_text(_set(_set(THESIS_SIM, "amplifier", "imon_ratio", "2e-3"), "limits", "max_current_A", "0.010"))
    assert load_rig(ok).limits.max_current_A == 0.010
    msg = _refused(tmp_path, _set(THESIS_SIM, "limits", "max_current_A", "0.02"))
    assert "limits.max_current_A" in msg and "0.02" in msg and "0.01 A" in msg
    # the 40 mA model can deliver 20 mA
    bigger = _set(_set(THESIS_SIM, "amplifier", "model", '"10/40A-HS"'), "limits", "max_current_A", "0.02")
    ok.write_text(bigger)
    assert load_rig(ok).limits.max_current_A == 0.02


def test_force_limit_within_the_load_cell(tmp_path: Path) -> None:
    text = _set(MOTOR_SIM, "load_cell", "capacity_kg", "1.0")
    ok = tmp_path / "ok.toml"
    ok.write_text(_set(text, "limits", "max_force_N", "9.8"))  # below 1 kg × 9.80665 m/s²
    assert load_rig(ok).limits.max_force_N == 9.8
    msg = _refused(tmp_path, _set(text, "limits", "max_force_N", "9.81"))
    assert "limits.max_force_N" in msg and "9.81" in msg and "9.807" in msg


def test_voltage_limits_within_the_amplifier(tmp_path: Path) -> None:
    msg = _refused(tmp_path, _set(THESIS_SIM, "amplifier", "max_voltage_V", "10001"))
    assert "amplifier.max_voltage_V" in msg
    msg = _refused(tmp_path, _set(THESIS_SIM, "limits", "max_voltage_V", "9000"))
    assert "limits.max_voltage_V" in msg and "9000" in msg and "8000" in msg


def test_motor_travel_within_the_stroke(tmp_path: Path) -> None:
    msg = _refused(tmp_path, _set(MOTOR_SIM, "motor", "travel_m", "[0.0, 0.13]"))  # stroke 0–120 mm
    assert "travel_m" in msg and "0.13" in msg and "0.12" in msg


def test_shipped_rigs_still_validate() -> None:
    for path in sorted(RIGS.glob("*.toml")):
        assert load_rig(path).name


def test_deeply_nested_rig_file_is_refused_in_one_line(tmp_path: Path) -> None:
    msg = _refused(tmp_path, "name = 'x'\nx = " + "[" * 1500 + "]" * 1500 + "\n")
    assert "nested" in msg


def test_cli_rig_refusal_is_one_line(tmp_path: Path) -> None:
    f = tmp_path / "rig.toml"
    f.write_text(_set(THESIS_SIM, "laser", "offset_mm", "nan"))
    proto = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    proc = subprocess.run([sys.executable, "-m", "bench", "validate", str(proto), "--rig", str(f)],
                          capture_output=True, text=True, timeout=120, env={"COLUMNS": "300", "PATH": ""})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "laser.offset_mm" in proc.stderr


def test_cli_error_text_is_not_eaten_as_markup(tmp_path: Path) -> None:
    """Messages quoting TOML headers ([buses], [[steps]]) reach the terminal verbatim (rich markup escaped)."""
    from typer.testing import CliRunner

    from bench.cli import app

    proto = tmp_path / "p.toml"
    proto.write_text(f'[protocol]\nname = "x"\nrig = "{RIGS / "thesis-sim.toml"}"\n')
    rig = tmp_path / "rig.toml"
    rig.write_text("name = 'x'\n[amplifier]\nbus = 'io'\n")
    runner = CliRunner()
    res = runner.invoke(app, ["validate", str(proto)], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and "give at least one [[steps]] table" in res.output
    res = runner.invoke(app, ["validate", str(ROOT / "protocols" / "short" / "thesis-identification-short.toml"),
                              "--rig", str(rig)], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and "is not defined under [buses]" in res.output


def test_control_characters_in_the_rig_path_are_refused_naming_the_field(tmp_path: Path) -> None:
    from bench.protocol.schema import ProtocolFileError, load_protocol

    f = tmp_path / "p.toml"
    f.write_text('[protocol]\nname = "x"\nrig = "\\u0000"\n[[steps]]\ntype = "hold"\nduration_s = 1\n')
    with pytest.raises(ProtocolFileError) as err:
        load_protocol(f)
    assert str(f) in str(err.value) and "protocol.rig" in str(err.value)


def test_special_and_oversized_files_are_refused_without_reading_them(tmp_path: Path) -> None:
    import os

    from bench.protocol.schema import ProtocolFileError, load_protocol
    from bench.tomlfile import MAX_FILE_BYTES

    for special in ("/dev/zero", "/dev/null"):  # refused by kind, never read (/dev/zero would be read forever)
        with pytest.raises(RigFileError, match=f"rig file {special}: not a regular file"):
            load_rig(special)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening it would block until a writer came
    with pytest.raises(ProtocolFileError, match="not a regular file"):
        load_protocol(fifo)
    big = tmp_path / "big.toml"
    big.write_text("name = 'x'\n" + "#" * MAX_FILE_BYTES + "\n")
    with pytest.raises(RigFileError, match="larger than"):
        load_rig(big)


def test_crlf_files_read_as_before(tmp_path: Path) -> None:
    import hashlib

    from bench.protocol.schema import load_protocol

    lf = (ROOT / "protocols" / "short" / "thesis-identification-short.toml").read_text()
    f = tmp_path / "crlf.toml"
    f.write_bytes(lf.replace("\n", "\r\n").replace("../../rigs", str(RIGS)).encode())
    p = load_protocol(f)
    assert p.sha256 == hashlib.sha256(lf.replace("../../rigs", str(RIGS)).encode()).hexdigest()


@pytest.mark.parametrize("rig, table", [("thesis-lab", "amplifier"), ("lsdea-motor-sim", "load_cell")])
def test_an_empty_bus_name_is_refused(tmp_path: Path, rig: str, table: str) -> None:
    """Found by the long fuzz run: bus = "" passed the [buses] check and raised KeyError in the link budget."""
    msg = _refused(tmp_path, _set((RIGS / f"{rig}.toml").read_text(), table, "bus", '""'))
    assert f"{table}.bus" in msg
