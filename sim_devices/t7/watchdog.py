"""The T7 watchdog's registers (WATCHDOG_*_DEFAULT) and the timeout action they configure.

[D] Modbus map: ENABLE 61600, TIMEOUT_S 61604, DAC0_ENABLE 61640, DAC0 61642, DAC1_ENABLE 61650, DAC1 61652; "the
watchdog must be disabled before writing any of the other watchdog registers"; any communication clears the
timer. [A] factory state: disabled, no timeout actions (a rig's twin starts like a fresh device).
"""

from __future__ import annotations

from sim_devices.t7.registers import E_WD_ENABLED, R_WD_DAC, R_WD_DAC_EN, R_WD_ENABLE, R_WD_TIMEOUT


class Watchdog:
    """The watchdog registers; :meth:`action` says what a timeout does to one DAC."""

    def __init__(self) -> None:
        self.regs: dict[int, float] = {R_WD_ENABLE: 0, R_WD_TIMEOUT: 0, R_WD_DAC_EN[0]: 0, R_WD_DAC[0]: 0.0,
                                       R_WD_DAC_EN[1]: 0, R_WD_DAC[1]: 0.0}

    def __contains__(self, address: int) -> bool:
        return address in self.regs

    def read(self, address: int) -> float:
        """A watchdog register's value."""
        return self.regs[address]

    def write(self, address: int, value: float) -> int:
        """Write a watchdog register: 0, or the LabJack error code that refuses it."""
        if address != R_WD_ENABLE and self.regs[R_WD_ENABLE]:
            return E_WD_ENABLED
        self.regs[address] = value
        return 0

    def action(self, dac: int) -> tuple[float, float] | None:
        """(timeout [s], DAC ``dac``'s value [V]) when enabled with a timeout and a DAC action on ``dac``, else None."""
        r = self.regs
        if r[R_WD_ENABLE] and r[R_WD_TIMEOUT] > 0 and r[R_WD_DAC_EN[dac]]:
            return float(r[R_WD_TIMEOUT]), float(r[R_WD_DAC[dac]])
        return None
