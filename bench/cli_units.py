"""Quantities with units on the command line, as in protocol files: ``7kV``, ``7 kV``, ``45 mm``, ``150 g``.

A plain number is read in the option's documented unit (``--voltage 7000`` is 7000 V). Parsing goes through
:func:`bench.protocol.quantity.parse_quantity`, so the CLI accepts exactly what files accept.
"""

from __future__ import annotations

from collections.abc import Callable

from bench.protocol.quantity import parse_quantity

PLAIN_UNITS: dict[str, tuple[str, float]] = {"V": ("voltage", 1.0), "kV": ("voltage", 1e3), "s": ("time", 1.0),
                                             "mm": ("length", 1e-3), "m": ("length", 1.0), "Hz": ("frequency", 1.0),
                                             "K": ("temperature", 1.0), "kg": ("mass", 1.0), "N": ("force", 1.0),
                                             "mm/s": ("velocity", 1e-3), "m/s": ("velocity", 1.0)}


def to_si(text: str, plain_unit: str) -> float:
    """SI value of ``text`` (``"7kV"``, ``"7 kV"``, or a plain number in ``plain_unit``); ValueError otherwise."""
    dimension, factor = PLAIN_UNITS[plain_unit]
    try:
        value = float(text)
    except ValueError:
        try:
            return parse_quantity(text.strip(), dimension)[0]
        except ValueError as exc:
            raise ValueError(f"{text!r}: expected a {dimension} such as '7 kV', or a number in {plain_unit} "
                             f"({exc})") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{text!r} is not a finite number")
    return value * factor


def quantity_parser(plain_unit: str) -> Callable[[str], float]:
    """A typer ``parser=`` for an option in ``plain_unit`` that also takes quantities (``--voltage 7kV``)."""

    def parse(text: str) -> float:
        return to_si(str(text), plain_unit)

    parse.__name__ = f"quantity_{plain_unit}"
    return parse
