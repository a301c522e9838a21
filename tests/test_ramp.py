"""The one shutdown ramp (bench/runtime/ramp.py) that runs and manual control share."""

from __future__ import annotations

import pytest

from bench.runtime.ramp import ramp_to_zero


class CodedAmplifier:
    """Takes set-points and answers with the code it really outputs (steps of 10 V, as a DAC quantises)."""

    def __init__(self) -> None:
        self.asked: list[float] = []

    def set_voltage(self, volts: float) -> float:
        self.asked.append(volts)
        return round(volts / 10.0) * 10.0


def test_ten_equal_steps_to_zero_at_their_times_and_what_was_sent_is_recorded() -> None:
    amp, waits, sent = CodedAmplifier(), [], []
    done = ramp_to_zero(amp, 5005.0, 0.5, lambda offset: waits.append(offset) or True, sent.append, 10)  # type: ignore[arg-type]
    assert done
    # v0 × (1 − k/10) at 0.05 s × k after the start: written out by hand, not by the rule under test
    assert amp.asked == pytest.approx([4504.5, 4004.0, 3503.5, 3003.0, 2502.5, 2002.0, 1501.5, 1001.0, 500.5, 0.0])
    assert waits == pytest.approx([0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5])
    assert sent == [4500.0, 4000.0, 3500.0, 3000.0, 2500.0, 2000.0, 1500.0, 1000.0, 500.0, 0.0]  # the codes


def test_an_urgent_stop_ends_the_ramp_before_the_next_set_point() -> None:
    amp, sent = CodedAmplifier(), []
    calls = iter([True, True, True, False])
    assert not ramp_to_zero(amp, -2000.0, 1.0, lambda _o: next(calls), sent.append, 10)  # type: ignore[arg-type]
    assert amp.asked == [-1800.0, -1600.0, -1400.0] and sent == [-1800.0, -1600.0, -1400.0]
