"""Quantities with units in protocol files, rig files and on the command line: ``"7 kV"``, ``"9 cm"``, ``"2 min"``,
``"25 °C"``, ``"5 N/m"``, ``"5 %"`` → SI floats.

Units are pint's (its default registry: every SI prefix, cm, min, h, °C and °F with their offsets, N/m, %, …).
The common forms, an SI prefix on one of the symbols of ``UNITS``, are read from that table, which agrees with pint
(tests/test_quantity_units.py checks every entry against pint): protocol sweeps parse thousands of quantities, and
pint's import (about half a second) is paid only by a process that reads some other unit. This module imports
nothing heavy itself: ``bench --help`` loads it.
"""

from __future__ import annotations

import functools
import math
import re
from typing import Any

PREFIX = {"": 1.0, "k": 1e3, "M": 1e6, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "n": 1e-9}
# unit symbol → (dimension, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "V": ("voltage", 1.0), "m": ("length", 1.0), "s": ("time", 1.0), "Hz": ("frequency", 1.0),
    "K": ("temperature", 1.0), "g": ("mass", 1e-3), "N": ("force", 1.0),
    "m/s": ("velocity", 1.0), "m/s2": ("acceleration", 1.0), "m/s^2": ("acceleration", 1.0),
    "V/m": ("field", 1.0), "V/s": ("slew", 1.0), "N/m": ("stiffness", 1.0), "A": ("current", 1.0),
}
BASE_UNIT = {dim: sym for sym, (dim, f) in UNITS.items() if f == 1.0 and "^" not in sym}
BASE_UNIT["mass"] = "kg"
# a dimension's SI unit as pint writes it ("ratio": dimensionless, e.g. "%")
SI_UNIT = {**{dim: sym.replace("s2", "s**2") for dim, sym in BASE_UNIT.items()}, "ratio": "dimensionless"}
_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")
# what may stand in a unit: names (µ, μ, Ω, ° included), products, quotients, small powers, brackets, %
_UNIT_TEXT = re.compile(r"^[A-Za-zµμΩ°%_ */·^()0-9]{1,64}$")
_POWER = re.compile(r"(?<=[A-Za-zµμΩ)])(\d{1,2})(?!\d)")  # m/s2 → m/s**2, as the table writes it
EXAMPLES = "e.g. '7 kV', '45 mm', '0.5 Hz'"
_LONGEST_FIRST = sorted(UNITS, key=len, reverse=True)  # "m/s" before "s", "V/m" before "m"


@functools.lru_cache(maxsize=4096)  # a sweep or a repeat expands the same few texts into thousands of steps
def parse_quantity(text: str | float | int, dimension: str | None = None) -> tuple[float, str]:
    """Parse ``"7 kV"`` → (7000.0, "voltage"), ``"25 °C"`` → (298.15, "temperature"). Plain numbers are refused:
    the unit must be explicit.

    Raises ValueError naming what is wrong (also for values that overflow to infinity: nan and inf cannot be
    written); with ``dimension``, also when the unit is of another kind.
    """
    if isinstance(text, bool) or not isinstance(text, str):
        raise ValueError(f"{text!r} has no unit; write it with one, {EXAMPLES}")
    m = _RE.match(text)
    if not m or not m.group(2):
        raise ValueError(f"{text!r} is not a number with a unit, {EXAMPLES}")
    number, unit = float(m.group(1)), m.group(2)
    if not math.isfinite(number):
        raise ValueError(f"{text!r}: the number must be finite")
    dim, factor, offset = _table_unit(unit) or _pint_unit(text, unit, dimension)
    value = number * factor + offset
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not a finite number")
    if dimension is not None and dim != dimension:
        raise ValueError(f"{text!r} is a {dim}, expected a {dimension}")
    return value, dim


def _table_unit(unit: str) -> tuple[str, float, float] | None:
    """(dimension, factor, offset 0) of an SI prefix on a symbol of ``UNITS``; None for any other unit."""
    for sym in _LONGEST_FIRST:
        if unit.endswith(sym) and unit[: -len(sym)] in PREFIX:
            dim, factor = UNITS[sym]
            return dim, PREFIX[unit[: -len(sym)]] * factor, 0.0
    return None


def _pint_unit(text: str, unit: str, dimension: str | None) -> tuple[str, float, float]:
    """(dimension, factor, offset) of any unit pint knows of a dimension bench uses; ValueError quoting ``text``
    otherwise (naming the ``dimension`` expected, if any)."""
    if not _UNIT_TEXT.match(unit):
        raise ValueError(f"{text!r}: unknown unit {unit!r}")
    found = _pint_conversion(unit)
    if isinstance(found, str):
        raise ValueError(f"{text!r}: {found}")
    if found[0] not in SI_UNIT:
        raise ValueError(f"{text!r} is {found[0]}, " + (f"expected a {dimension}" if dimension else
                                                          "not a quantity bench uses"))
    return found


@functools.lru_cache(maxsize=512)
def _pint_conversion(unit: str) -> tuple[str, float, float] | str:
    """(dimension, factor, offset) so that SI = factor · x + offset (pint's conversions are affine, offset units
    included), or why not; cached per unit text."""
    ureg = _registry()
    written = _POWER.sub(r"**\1", unit.replace("·", "*").replace("^", "**"))
    try:
        zero, one = ureg.Quantity(0.0, written), ureg.Quantity(1.0, written)
        dimensionality = one.dimensionality
    except Exception:  # pint raises several kinds (undefined unit, syntax, offset calculus)
        return f"unknown unit {unit!r}"
    for dim, si_unit in SI_UNIT.items():
        if dimensionality == ureg.Quantity(1.0, si_unit).dimensionality:
            if dim == "ratio" and not one.unitless and ("radian" in str(one.to_base_units().units)
                                                        or "degree" in str(one.units)):
                return f"{unit!r} is an angle, not a ratio"  # pint counts angles dimensionless
            try:
                offset = float(zero.to(si_unit).magnitude)
                factor = float(one.to(si_unit).magnitude) - offset
                two = float(ureg.Quantity(2.0, written).to(si_unit).magnitude)
            except Exception:  # pint refuses some conversions of offset units
                return f"cannot convert {unit!r} to {si_unit}"
            if not math.isclose(two, 2.0 * factor + offset, rel_tol=1e-12, abs_tol=1e-300):
                return f"{unit!r} is not a linear unit (e.g. a logarithmic one)"  # dB, neper, …
            return dim, factor, offset
    return f"{dimensionality} ({one.units})", math.nan, math.nan  # a dimension bench has no name for


@functools.cache
def _registry() -> Any:
    """pint's default unit registry, made on first use (its import is what ``bench --help`` must not pay)."""
    import pint

    return pint.UnitRegistry()


def format_quantity(value: float, dimension: str) -> str:
    """SI value as a quantity string in the base unit (round-trips through :func:`parse_quantity`)."""
    if dimension == "ratio":
        return f"{value * 100:.12g} %"
    return f"{value:.12g} {BASE_UNIT[dimension]}"


def takes_bool(annotation: Any) -> bool:
    """Whether a field's type admits true/false (``bool``, ``bool | None``)."""
    from typing import get_args

    return annotation is bool or any(takes_bool(a) for a in get_args(annotation))


def takes_number(annotation: Any) -> bool:
    """Whether a field's type admits a number (``float``, ``int``, ``Hertz``, ``float | None``, …)."""
    from typing import get_args

    return annotation in (float, int) or any(takes_number(a) for a in get_args(annotation))


def refuse_bool(v: Any, annotation: Any) -> None:
    """ValueError for true/false given where a number goes and no bool: pydantic reads true as 1 (outside testers: a
    rig's ``shutdown_ramp_s = true`` was a 1-s ramp, a protocol's ``duration_s = true`` a 1-s step). A text field
    keeps pydantic's own refusal (a reviewer: ``name = true`` read "true is not a number")."""
    if isinstance(v, bool) and takes_number(annotation) and not takes_bool(annotation):
        raise ValueError(f"{'true' if v else 'false'} is not a number: write the value")
