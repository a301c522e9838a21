"""Whole numbers in the engine's messages: a value that rounds to zero reads "0", never "-0" (outside tester: "ramp
from -0 V" after a drive whose last set-point was a few tenths of a volt, or a float residue, below zero)."""

from __future__ import annotations

import pytest

from bench.numbers import whole


@pytest.mark.parametrize("value, text", [(-0.3, "0"), (-1e-13, "0"), (-0.0, "0"), (0.4, "0"), (-2.4, "-2"),
                                         (-7000.4, "-7000"), (1500.6, "1501")])
def test_whole_volts_never_read_minus_zero(value: float, text: str) -> None:
    assert whole(value) == text


def test_the_ramp_event_uses_it() -> None:
    """The ramp's event text is built with :func:`whole` (the stop's ramp from the last set-point)."""
    import inspect

    from bench.runtime import engine

    source = inspect.getsource(engine)
    assert 'f"ramp from {whole(v0)} V to 0 V' in source and "ramp from {v0:.0f}" not in source
