"""Quantities in any unit pint knows, on the command line and in protocol files (issue 26 item 8): ``9 cm``,
``2 min``, ``25 °C`` (an offset unit), ``5 N/m``, ``%``; a wrong dimension or a non-finite value is a one-line error
naming the option.

Expected values are the units' definitions (SI brochure, 9th ed.: 1 cm = 0.01 m, 1 min = 60 s, 1 h = 3600 s,
t/°C = T/K − 273.15; NIST SP 811 B.8: t/°F = 1.8 t/°C + 32; 1 % = 0.01), not the parser's output.
"""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.quantity import PREFIX, UNITS, parse_quantity

runner = CliRunner()


@pytest.mark.parametrize(("text", "si", "dimension"), [
    ("9 cm", 0.09, "length"), ("2 min", 120.0, "time"), ("1.5 h", 5400.0, "time"),
    ("25 °C", 298.15, "temperature"), ("25 degC", 298.15, "temperature"), ("-40 °F", 233.15, "temperature"),
    ("5 N/m", 5.0, "stiffness"), ("5 N/mm", 5000.0, "stiffness"), ("5 %", 0.05, "ratio"),
    ("36 km/h", 10.0, "velocity"), ("2 kV/mm", 2e6, "field"), ("9.81 m/s2", 9.81, "acceleration"),
    ("7 kV", 7000.0, "voltage"), ("150 g", 0.15, "mass"), ("250 µm", 250e-6, "length"), ("250 μm", 250e-6, "length"),
])
def test_units_convert_to_si_by_their_definitions(text: str, si: float, dimension: str) -> None:
    value, dim = parse_quantity(text)
    assert dim == dimension and value == pytest.approx(si, rel=1e-12)
    assert parse_quantity(text, dimension)[0] == value


def test_the_fast_table_agrees_with_pint() -> None:
    """Every prefixed symbol read from the table (without pint) is what pint reads: the table is a shortcut only."""
    import pint

    ureg = pint.UnitRegistry()
    for sym, (dim, _) in UNITS.items():
        for prefix in PREFIX:
            unit = prefix + sym
            # pint's base units are SI's (the kilogram for mass, as bench's SI values)
            expected = ureg.Quantity(1.0, unit.replace("^", "**").replace("s2", "s**2")).to_base_units().magnitude
            assert parse_quantity(f"1 {unit}") == (pytest.approx(expected, rel=1e-12), dim), unit


@pytest.mark.parametrize(("text", "dimension", "says"), [
    ("9 cm", "voltage", "'9 cm' is a length, expected a voltage"),
    ("25 C", "temperature", "'25 C' is [current] * [time] (coulomb), expected a temperature"),
    ("3 °C/min", None, "[temperature] / [time] (delta_degree_Celsius / minute), not a quantity bench uses"),
    ("5 furlongs/fortnight ^ 999", None, "not a quantity bench uses"),
    ("5 zorks", "length", "unknown unit 'zorks'"),
    ("5 __import__('os')", None, "unknown unit"),
    ("1e308 km", None, "is not a finite number"),
    ("5", None, "is not a number with a unit"),
    # pint counts angles and logarithmic units dimensionless: neither is a ratio (5 dB is 10^(5/20) ≈ 178 %, not
    # a linear scale of any number)
    ("5 dB", "ratio", "'dB' is not a linear unit"),
    ("5 rad", "ratio", "'rad' is an angle, not a ratio"),
    ("30 deg", "ratio", "'deg' is an angle, not a ratio"),
])
def test_bad_quantities_are_refused(text: str, dimension: str | None, says: str) -> None:
    with pytest.raises(ValueError) as err:
        parse_quantity(text, dimension)
    assert says in str(err.value) and "\n" not in str(err.value)


def _simulate(*args: str) -> str:
    res = runner.invoke(app, ["simulate", *args], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    return res.output


def test_offset_and_non_si_units_through_the_command_line() -> None:
    with_units = _simulate("thesis", "--temperature", "25 °C", "--duration", "0.05 min", "--voltage", "0.6 kV")
    assert "298.15 K, 3 s" in with_units  # the title shows the SI values the options became
    assert with_units == _simulate("thesis", "--temperature", "298.15", "--duration", "3", "--voltage", "600")
    lsdea = ("lsdea", "isopotential", "--cycles", "2", "--frequency", "5 Hz")
    assert _simulate(*lsdea, "--stroke", "9 cm") == _simulate(*lsdea, "--stroke", "90")  # the help's own example


@pytest.mark.parametrize(("args", "says"), [
    (["--stroke", "9 kV"], "--stroke '9 kV': expected a length"),
    (["--stroke", "nan"], "--stroke 'nan' is not a finite number"),
    (["--mass", "1e999 g"], "--mass '1e999 g': expected a mass"),
    (["--frequency", "2 min"], "--frequency '2 min': expected a frequency"),
])
def test_a_wrong_dimension_or_a_non_finite_value_names_the_option(args: list[str], says: str) -> None:
    res = runner.invoke(app, ["simulate", "lsdea", *args], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and says in res.output, res.output
    assert res.output.strip().count("\n") == 0 and "Traceback" not in res.output
