"""Load cell read through a Dini Argeo DGT1S / DGT4X weight transmitter over Modbus RTU.

Register map (DGT4X/DGT1S manuals; ../shared/instruments.md §4.1), 1-based → 0-based:

* input registers (FC4): 30001–30002 gross weight, 30003–30004 net weight (32-bit, MSW first, absolute
  value in display divisions, no decimal point); 30005 status (bit0 net negative, bit1 gross negative,
  bit2 stable, bit3 underload, bit4 overload, bit5 tare active, bit7 scale unloaded); 30006 command status
  (high byte last command, low byte bits 4–7 result, bits 0–3 processed-command counter); 30007 outputs;
* holding registers (FC3/6/16): 40001 command (1 zero, 2 tare, 3 preset tare), 40002–40005 parameters.

Zero and tare use the processed-command counter as handshake: write the command, wait for the counter
to change, check the result nibble (0 = done; other values: command refused, e.g. unstable or out of range).
"""

from __future__ import annotations

import math
import time

from drivers.cancel import check
from drivers.errors import ImplausibleValueError, InstrumentStateError, InstrumentTimeoutError
from drivers.interfaces import CheckResult, ClockFn, DataKey, Identity, Reading, ReadingMap, SleepFn, StreamDescription
from drivers.modbus_link import ModbusLink

IR_GROSS, IR_STATUS, IR_COMMAND_STATUS = 0, 4, 5
HR_COMMAND = 0
CMD_ZERO, CMD_TARE, CMD_PRESET_TARE = 0x01, 0x02, 0x03
ST_NET_NEG, ST_GROSS_NEG, ST_STABLE, ST_UNDERLOAD, ST_OVERLOAD, ST_TARE = 0x01, 0x02, 0x04, 0x08, 0x10, 0x20
RESULT_TEXT = {1: "not executed: weight unstable", 2: "not executed: outside the zero range",
               3: "not executed: overload or underload"}
STANDARD_GRAVITY = 9.80665
# [A] the transmitter shows a weight in at most 6 digits: a count beyond 999 999 divisions is no weight it reports
# (its 32-bit register could carry 4 294 967 295) — to check against the unit's display and manual
MAX_DIVISIONS = 999_999


class DiniDGT1S:
    """Driver of a DGT1S-class weight transmitter (implements ForceSensor).

    ``division`` is the weight of one count [kg] (e.g. 0.001 kg = 1 g display resolution);
    the force is ``weight × g`` [N], positive for tension on the cell.
    """

    def __init__(self, link: ModbusLink, *, name: str = "load_cell", unit: int = 1, division: float = 0.001,
                 g: float = STANDARD_GRAVITY, use_net: bool = True, clock: ClockFn = time.monotonic,
                 sleep: SleepFn = time.sleep, command_timeout: float = 2.0) -> None:
        if not (math.isfinite(division) and division > 0):
            raise ValueError(f"{name}: division must be > 0 kg, got {division}")
        if not (math.isfinite(g) and g > 0):
            raise ValueError(f"{name}: g must be > 0 m/s², got {g}")
        self.link = link
        self.name = name
        self.unit = unit
        self.division = division
        self.g = g
        self.use_net = use_net
        self.clock = clock
        self.sleep = sleep
        self.command_timeout = command_timeout

    def connect(self) -> None:
        """Open the bus and read the status once."""
        self.link.open()
        self.read_force()

    def close(self) -> None:
        """Release the bus (the transmitter has no unsafe state)."""
        self.link.close()

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""
        return StreamDescription(self.name, (
            DataKey("force", "N", "force on the load cell, tension positive"),
            DataKey("ok", "1", "1 = stable reading", "u1")), "Dini Argeo DGT1S")

    def check(self) -> CheckResult:
        """Whether the weight is stable; the force."""
        r = self.read_force()
        return CheckResult("stable" if r.ok else r.status, (("force", r),))

    def identify(self) -> Identity:
        """No identification register in the map: report the configured model and the scale status."""
        regs = self.link.read_input(self.unit, IR_STATUS, 2)
        return Identity("Dini Argeo", "DGT1S", {"unit": str(self.unit), "status": f"{regs[0]:#06x}"})

    def safe_state(self) -> None:
        """Nothing to make safe."""

    def read_weight(self) -> tuple[float, int]:
        """(signed weight [kg], status register) from one read of gross, net and status.

        A count beyond :data:`MAX_DIVISIONS` is an :class:`ImplausibleValueError`, not a reading: the value
        passed the frame's CRC, so the transmitter itself sent what it cannot display — a fault of the device
        or its configuration, which stops a run (the load cell guards the specimen) rather than one sample."""
        regs = self.link.read_input(self.unit, IR_GROSS, 5)
        gross = (regs[0] << 16) | regs[1]
        net = (regs[2] << 16) | regs[3]
        status = regs[4]
        value, negative = (net, ST_NET_NEG) if self.use_net else (gross, ST_GROSS_NEG)
        if value > MAX_DIVISIONS and not status & (ST_OVERLOAD | ST_UNDERLOAD):
            raise ImplausibleValueError(self.name, "net weight" if self.use_net else "gross weight", value,
                                        (0, MAX_DIVISIONS), "divisions", "the display's 6 digits")
        return (-value if status & negative else value) * self.division, status

    def read(self) -> ReadingMap:
        """One :meth:`read_force` keyed as :meth:`describe`: ``force`` [N], ``ok`` (1: stable)."""
        r = self.read_force()
        return {"force": r, "ok": Reading(float(r.ok), "1", r.timestamp)}

    def read_force(self) -> Reading:
        """Force on the cell [N]; status 'overload'/'underload' (value NaN) or 'unstable' when flagged,
        'invalid' if the value is not finite. Stamped at the start of the transmitter's reply
        (:meth:`ModbusLink.reply_started`), not after its wire time."""
        with self.link.lock:
            weight, status = self.read_weight()
            t = self.link.reply_started(self.clock())
        if status & ST_OVERLOAD:
            return Reading(float("nan"), "N", t, "overload")
        if status & ST_UNDERLOAD:
            return Reading(float("nan"), "N", t, "underload")
        force = weight * self.g
        if not math.isfinite(force):
            return Reading(math.nan, "N", t, "invalid")
        return Reading(force, "N", t, "ok" if status & ST_STABLE else "unstable")

    def _command(self, code: int, label: str) -> None:
        before = self.link.read_input(self.unit, IR_COMMAND_STATUS, 1)[0] & 0x0F
        self.link.write_register(self.unit, HR_COMMAND, code)
        deadline = self.clock() + self.command_timeout
        while True:
            check(self.link.cancel, self.name)
            cs = self.link.read_input(self.unit, IR_COMMAND_STATUS, 1)[0]
            if cs & 0x0F != before:
                result = (cs >> 4) & 0x0F
                if result:
                    raise InstrumentStateError(self.name, f"{label} {RESULT_TEXT.get(result, f'result {result}')}")
                return
            if self.clock() > deadline:
                raise InstrumentTimeoutError(self.name, f"{label} not processed within {self.command_timeout:g} s")
            self.sleep(0.005)

    def zero(self) -> None:
        """Zero the gross weight (command 1)."""
        self._command(CMD_ZERO, "zero")

    def tare(self) -> None:
        """Tare: net = 0 at the present load (command 2)."""
        self._command(CMD_TARE, "tare")
