"""The ADAM-4017+ converts its enabled channels in turn, 10 conversions a second in all (ADAM-4000 manual, ADAM-4017+
specifications; channel enable 40221, one bit a channel): a monitor is as old as the round robin is long. The
amplifier refuses to connect where either monitor channel is off or where more than three channels share the 10/s
(each monitor then older than the interlock's 0.3-s lag allowance for polled monitors) — a reviewer: with all eight
on, as a module may come, each channel is fresh every 0.8 s, and the hand-over's 0.5-s settle could read a monitor
from before the zero."""

from __future__ import annotations

import pytest

from drivers.errors import InstrumentStateError
from tests.conftest import start_rig

ENABLE = 220  # 40221, zero-based


@pytest.mark.parametrize(("mask", "refused"), [
    (0b11, None),  # V (ch 0) and I (ch 1): each every 0.2 s
    (0b111, None),  # three in turn: 0.3 s, the allowance
    (0b1111, "4 channels enabled ([0, 1, 2, 3]): at 10 conversions/s in all each monitor is fresh only every 0.4 s"),
    (0xFF, "8 channels enabled ([0, 1, 2, 3, 4, 5, 6, 7])"),
    (0b01, "monitor channel(s) 1 not enabled"),
])
def test_the_monitors_channels_are_checked_at_connect(mask: int, refused: str | None) -> None:
    rig = start_rig("thesis-sim")
    try:
        amp = rig.inst.amplifier
        assert amp is not None
        amp.ai.link.write_register(amp.ai.unit, ENABLE, mask)
        amp.close()
        if refused is None:
            amp.connect()
            assert abs(amp.commanded) <= 20_000 / 4095  # 0 V, to the ADAM-4024's code
        else:
            with pytest.raises(InstrumentStateError, match=refused.replace("(", r"\(").replace(")", r"\)")
                               .replace("[", r"\[").replace("]", r"\]")):
                amp.connect()
    finally:
        rig.inst.close()
        rig.sim.stop()
