"""Quantities with units on the command line, as in protocol files: ``7kV``, ``45 mm``, ``9 cm``, ``2 min``,
``25 °C``, ``5 N/m``, ``5 %`` (any unit pint knows whose dimension fits the option).

A plain number is read in the option's documented unit (``--voltage 7000`` is 7000 V). Parsing goes through
:func:`bench.quantity.parse_quantity`, so the CLI accepts exactly what files accept.
"""

from __future__ import annotations

import math

from bench.quantity import parse_quantity

PLAIN_UNITS: dict[str, tuple[str, float]] = {"V": ("voltage", 1.0), "kV": ("voltage", 1e3), "s": ("time", 1.0),
                                             "mm": ("length", 1e-3), "m": ("length", 1.0), "Hz": ("frequency", 1.0),
                                             "K": ("temperature", 1.0), "kg": ("mass", 1.0), "N": ("force", 1.0),
                                             "mm/s": ("velocity", 1e-3), "m/s": ("velocity", 1.0),
                                             "N/m": ("stiffness", 1.0), "%": ("ratio", 1e-2)}

EXAMPLES = {"voltage": "7 kV", "time": "20 s", "length": "45 mm", "frequency": "0.5 Hz", "temperature": "296 K",
            "mass": "150 g", "force": "2 N", "velocity": "0.1 m/s", "stiffness": "5 N/m", "ratio": "5 %"}


def to_si(text: str, plain_unit: str) -> float:
    """SI value of ``text`` (``"7kV"``, ``"7 kV"``, or a plain number in ``plain_unit``); ValueError otherwise."""
    dimension, factor = PLAIN_UNITS[plain_unit]
    try:
        value = float(text)
    except ValueError:
        try:
            return parse_quantity(text.strip(), dimension)[0]
        except ValueError as exc:
            raise ValueError(f"{text!r}: expected a {dimension} such as '{EXAMPLES[dimension]}', or a number in "
                             f"{plain_unit} "
                             f"({exc})") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{text!r} is not a finite number")
    return value * factor


def option_si(text: str | float, plain_unit: str, option: str, lo: float | None = None,
              hi: float | None = None) -> float:
    """SI value of a command option given as a quantity or a plain number in ``plain_unit``, within ``lo`` … ``hi``
    (in ``plain_unit``, inclusive); ValueError naming the option (the CLI prints it on one line, exit 2).

    The commands parse these options themselves rather than through a click parser: click would print its usage
    block around the message, and its range checks would apply before the unit is known."""
    try:
        value = to_si(str(text), plain_unit)
    except ValueError as exc:
        raise ValueError(f"{option} {exc}") from None
    factor = PLAIN_UNITS[plain_unit][1]
    shown = value / factor
    if (lo is not None and not shown >= lo) or (hi is not None and not shown <= hi):
        limits = (f"{lo:g} … {hi:g} {plain_unit}" if lo is not None and hi is not None else
                  f"≥ {lo:g} {plain_unit}" if lo is not None else f"≤ {hi:g} {plain_unit}")
        raise ValueError(f"{option} {text}: {shown:g} {plain_unit} is outside {limits}")
    return value


PREFIXES = ((1e9, "G"), (1e6, "M"), (1e3, "k"), (1.0, ""), (1e-3, "m"), (1e-6, "µ"), (1e-9, "n"))


def si(value: float, unit: str) -> str:
    """A value with an SI prefix that keeps 1–3 digits before the point (6000 V → 6 kV, 3.2e-5 A → 32 µA)."""
    if not math.isfinite(value) or value == 0.0 or not unit:
        return f"{value:.4g} {unit}".rstrip()
    scale, prefix = next(((f, p) for f, p in PREFIXES if abs(value) >= f), PREFIXES[-1])
    if abs(value) < scale:  # below the smallest prefix: a few thousandths of it, not an exponent
        return f"{value / scale:.3f} {prefix}{unit}"
    return f"{value / scale:.4g} {prefix}{unit}"
