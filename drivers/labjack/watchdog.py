"""The T7's watchdog: after a silence it writes the safe values to both DACs ([D] WATCHDOG_* registers; [A] they
live in flash, so only what differs is written)."""

from __future__ import annotations

import numpy as np

from drivers.errors import InstrumentStateError
from drivers.labjack.connection import T7Connection
from drivers.labjack.registers import (
    WATCHDOG_DAC,
    WATCHDOG_DAC_ENABLE,
    WATCHDOG_ENABLE,
    WATCHDOG_TIMEOUT_S,
    Frame,
    f32_words,
    u32_words,
    words_f32,
    words_u32,
)

_READS: list[Frame] = [*((a, 2) for k in (0, 1) for a in (WATCHDOG_DAC_ENABLE[k], WATCHDOG_DAC[k])),
                       (WATCHDOG_ENABLE, 2), (WATCHDOG_TIMEOUT_S, 2)]
Settings = tuple[int, int, tuple[tuple[int, float], ...]]


def _settings(w: list[list[int]]) -> Settings:
    """The watchdog's settings from the words of :data:`_READS`."""
    dacs = tuple((words_u32(w[2 * k]), words_f32(w[2 * k + 1])) for k in (0, 1))
    return words_u32(w[4]), words_u32(w[5]), dacs


class T7Watchdog(T7Connection):
    """Reading and setting the watchdog."""

    def read_watchdog(self) -> Settings:
        """(enabled, timeout [s], ((DAC0 action enabled, volts), (DAC1 …))) as the device holds them."""
        return _settings(self.feedback(_READS))  # one MBFB packet

    def configure_watchdog(self, timeout_s: int, dac_volts: tuple[float, float]) -> bool:
        """Enable the watchdog: after ``timeout_s`` s without communication both DACs go to ``dac_volts``.
        Writes (disable, settings, enable) only when the device's settings differ, then reads them back in the same
        MBFB packet (the frames run in order) and refuses settings the device did not take; returns whether it
        wrote."""
        if not 1 <= int(timeout_s) == timeout_s:
            raise ValueError(f"{self.name}: watchdog timeout must be a whole number of seconds ≥ 1")
        want = (1, int(timeout_s), tuple((1, float(np.float32(v))) for v in dac_volts))
        if self.read_watchdog() == want:
            return False
        writes: list[Frame] = [(WATCHDOG_ENABLE, u32_words(0)), (WATCHDOG_TIMEOUT_S, u32_words(int(timeout_s)))]
        for k, v in enumerate(dac_volts):
            writes += [(WATCHDOG_DAC_ENABLE[k], u32_words(1)), (WATCHDOG_DAC[k], f32_words(v))]
        got = _settings(self.feedback([*writes, (WATCHDOG_ENABLE, u32_words(1)), *_READS]))  # in order, one packet
        if got != want:
            raise InstrumentStateError(self.name, f"watchdog read back as (enabled, timeout s, DAC actions) {got}, "
                                       f"{want} written")
        return True
