"""Quantities with units in protocol files: ``"7 kV"``, ``"45 mm"``, ``"0.5 m/s"``, ``"150 g"`` → SI floats."""

from __future__ import annotations

import math
import re

PREFIX = {"": 1.0, "k": 1e3, "M": 1e6, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "n": 1e-9}
# unit symbol → (dimension, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "V": ("voltage", 1.0), "m": ("length", 1.0), "s": ("time", 1.0), "Hz": ("frequency", 1.0),
    "K": ("temperature", 1.0), "g": ("mass", 1e-3), "N": ("force", 1.0),
    "m/s": ("velocity", 1.0), "m/s2": ("acceleration", 1.0), "m/s^2": ("acceleration", 1.0),
    "V/m": ("field", 1.0), "V/s": ("slew", 1.0),
}
BASE_UNIT = {dim: sym for sym, (dim, f) in UNITS.items() if f == 1.0 and "^" not in sym}
BASE_UNIT["mass"] = "kg"
_RE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ/^0-9]*)\s*$")


def parse_quantity(text: str | float | int, dimension: str | None = None) -> tuple[float, str]:
    """Parse ``"7 kV"`` → (7000.0, "voltage"). Plain numbers are refused: the unit must be explicit.

    Raises ValueError naming what is wrong (also for values that overflow to infinity: nan and inf cannot be
    written); with ``dimension``, also when the unit is of another kind.
    """
    if isinstance(text, bool) or not isinstance(text, str):
        raise ValueError(f"{text!r} has no unit; write it with one, e.g. '7 kV', '45 mm', '0.5 Hz'")
    m = _RE.match(text)
    if not m or not m.group(2):
        raise ValueError(f"{text!r} is not a number with a unit, e.g. '7 kV', '45 mm', '0.5 Hz'")
    number, unit = float(m.group(1)), m.group(2)
    if not math.isfinite(number):
        raise ValueError(f"{text!r}: the number must be finite")
    for sym in sorted(UNITS, key=len, reverse=True):
        if unit.endswith(sym) and unit[: -len(sym)] in PREFIX:
            dim, factor = UNITS[sym]
            value = number * PREFIX[unit[: -len(sym)]] * factor
            if not math.isfinite(value):
                raise ValueError(f"{text!r} is not a finite number")
            if dimension is not None and dim != dimension:
                raise ValueError(f"{text!r} is a {dim}, expected a {dimension}")
            return value, dim
    raise ValueError(f"{text!r}: unknown unit {unit!r}")


def format_quantity(value: float, dimension: str) -> str:
    """SI value as a quantity string in the base unit (round-trips through :func:`parse_quantity`)."""
    return f"{value:.12g} {BASE_UNIT[dimension]}"
