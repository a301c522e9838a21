"""Numbers in messages that compare a value with its limit ("current 0.02351 mA beyond the trip level 0.0235 mA").

Rounded to a fixed number of decimals, a value just past its limit reads as the limit itself, or a small limit as
a rounded figure ("current -0.02 mA beyond the trip level 0.02 mA" for a 0.0235-mA limit, found by an outside
tester). :func:`against` gives both at 4 significant figures, more where that still shows them equal.
"""

from __future__ import annotations

import math

MIN_DIGITS = 4  # significant figures at least
MAX_DIGITS = 12  # beyond this a float's own rounding shows


def against(value: float, limit: float, scale: float = 1.0) -> tuple[str, str]:
    """``value`` and ``limit`` (each times ``scale``, e.g. 1e3 for mA from A) as text with as many significant figures,
    at least :data:`MIN_DIGITS`, as make the value's magnitude visibly differ from the limit's when they differ."""
    v, lim = value * scale, limit * scale
    for digits in range(MIN_DIGITS, MAX_DIGITS + 1):
        a, b = f"{v:.{digits}g}", f"{lim:.{digits}g}"
        if not (math.isfinite(v) and math.isfinite(lim)) or abs(v) == abs(lim) or a.lstrip("-") != b.lstrip("-"):
            return a, b
    return a, b


def whole(value: float) -> str:
    """``value`` to the nearest whole number, as ``f"{value:.0f}"`` but never "-0" (a set-point of -0.3 V read
    "ramp from -0 V", found by an outside tester): a value that rounds to zero is "0"."""
    text = f"{value:.0f}"
    return "0" if text == "-0" else text


def mv_per_m(field: float) -> str:
    """An electric field [V/m] in MV/m: one decimal, as the papers give fields, or three significant figures where one
    decimal would show a field that is not zero as "0.0" (a breakdown field of 1e3 V/m read "0.0 MV/m", found by an
    outside tester)."""
    mv = field / 1e6
    return f"{mv:.3g}" if mv != 0 and abs(mv) < 0.05 and math.isfinite(mv) else f"{mv:.1f}"
