"""The T7's watchdog: after a silence it writes the safe values to both DACs ([D] WATCHDOG_* registers; [A] they
live in flash, so only what differs is written)."""

from __future__ import annotations

import numpy as np

from drivers.labjack.connection import T7Connection
from drivers.labjack.registers import WATCHDOG_DAC, WATCHDOG_DAC_ENABLE, WATCHDOG_ENABLE, WATCHDOG_TIMEOUT_S


class T7Watchdog(T7Connection):
    """Reading and setting the watchdog."""

    def read_watchdog(self) -> tuple[int, int, tuple[tuple[int, float], ...]]:
        """(enabled, timeout [s], ((DAC0 action enabled, volts), (DAC1 …))) as the device holds them."""
        dacs = tuple((self.read_u32(WATCHDOG_DAC_ENABLE[k]), self.read_f32(WATCHDOG_DAC[k])) for k in (0, 1))
        return self.read_u32(WATCHDOG_ENABLE), self.read_u32(WATCHDOG_TIMEOUT_S), dacs

    def configure_watchdog(self, timeout_s: int, dac_volts: tuple[float, float]) -> bool:
        """Enable the watchdog: after ``timeout_s`` s without communication both DACs go to ``dac_volts``.
        Writes (disable, settings, enable) only when the device's settings differ; returns whether it wrote."""
        if not 1 <= int(timeout_s) == timeout_s:
            raise ValueError(f"{self.name}: watchdog timeout must be a whole number of seconds ≥ 1")
        want = (1, int(timeout_s), tuple((1, float(np.float32(v))) for v in dac_volts))
        if self.read_watchdog() == want:
            return False
        self.write_u32(WATCHDOG_ENABLE, 0)
        self.write_u32(WATCHDOG_TIMEOUT_S, int(timeout_s))
        for k, v in enumerate(dac_volts):
            self.write_u32(WATCHDOG_DAC_ENABLE[k], 1)
            self.write_f32(WATCHDOG_DAC[k], v)
        self.write_u32(WATCHDOG_ENABLE, 1)
        return True
