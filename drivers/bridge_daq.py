"""A load cell's bridge amplifier wired to an analog input of a LabJack T7 (the DAQ rigs' ``daq.force_ain``).

A run samples that input on the DAQ's scan clock (bench/runtime/hardware_timed.py); this driver is the
command-response side of the same input — one AIN read per reading — so that manual control, which plays no
stream, reads, records and supervises the force as on a rig whose load cell has a transmitter of its own. Before,
a DAQ rig's load cell was no instrument at all outside a run: `bench devices control` moved the motor with the rig's
force limit printed in its header and never read the force (outside tester).

Conversion (the rig file's ``daq.force_N_per_V`` and ``daq.force_offset_N``, as the stream's): force [N] =
N/V × AIN volts + offset, tension positive. A reading the T7 reports as no conversion (not finite, or beyond its
range's span: :meth:`drivers.labjack.LabJackT7.read_ain`) is status ``invalid``; one at the input's full scale
(±10 V: the bridge amplifier's output may lie beyond) is ``overload`` or ``underload``, value NaN, as a
transmitter flags it: a force that may be anything beyond the range is not taken as the range's end.
"""

from __future__ import annotations

import math
import time

from drivers.errors import UnsupportedCommandError
from drivers.interfaces import CheckResult, ClockFn, DataKey, Identity, Reading, ReadingMap, StreamDescription
from drivers.labjack import LabJackT7

RANGE_V = 10.0  # the input's range: ±10 V, the one the stream uses for the force too
FULL_SCALE_V = 0.999 * RANGE_V  # a reading this close to the range's end may stand for any larger voltage


class BridgeOnDaq:
    """Driver of a load-cell bridge amplifier on a T7 analog input (implements ForceSensor)."""

    def __init__(self, daq: LabJackT7, *, ain: int, n_per_v: float = 1.0, offset_n: float = 0.0,
                 name: str = "load_cell", clock: ClockFn = time.monotonic) -> None:
        if not (math.isfinite(n_per_v) and n_per_v > 0 and math.isfinite(offset_n)):
            raise ValueError(f"{name}: N per V must be finite and > 0 and the offset finite")
        self.daq, self.ain, self.n_per_v, self.offset_n = daq, ain, n_per_v, offset_n
        self.name, self.clock = name, clock

    # ------------------------------------------------------------ Instrument
    def connect(self) -> None:
        """Connect the DAQ (if not yet) and set the input to ±10 V."""
        if not self.daq.link.is_open:
            self.daq.connect()
        self.daq.configure_ain(self.ain, RANGE_V)

    def close(self) -> None:
        """Nothing of its own to close (the DAQ is closed by its driver)."""

    def safe_state(self) -> None:
        """A sensor: nothing to make safe."""

    def identify(self) -> Identity:
        """What the rig file says is wired; the T7 itself answers for the DAQ."""
        return Identity("bridge amplifier", f"on LabJack T7 AIN{self.ain}",
                        {"scale": f"{self.n_per_v:g} N/V", "offset": f"{self.offset_n:g} N"})

    def check(self) -> CheckResult:
        """One force reading."""
        return CheckResult(f"AIN{self.ain}, {self.n_per_v:g} N/V", (("force", self.read_force()),))

    def describe(self) -> StreamDescription:
        """The stream it records: the force and whether the reading was valid."""
        return StreamDescription(self.name, (
            DataKey("force", "N", "force from the load-cell bridge amplifier, tension positive"),
            DataKey("ok", "1", "1 = a valid reading", "u1")),
            f"bridge amplifier on AIN{self.ain} (command-response reads)")

    # ------------------------------------------------------------ ForceSensor
    def read_force(self) -> Reading:
        """Force [N] from one read of the input; 'invalid' (NaN) where the T7 gave no conversion, 'overload' or
        'underload' (NaN) at the input's full scale."""
        v = self.daq.read_ain(self.ain)
        if not v.ok or not math.isfinite(v.value):
            return Reading(math.nan, "N", v.timestamp, "invalid")
        if abs(v.value) >= FULL_SCALE_V:
            # which of tension and compression the saturated input stands for depends on the sign of N/V (> 0)
            return Reading(math.nan, "N", v.timestamp, "overload" if v.value > 0 else "underload")
        return Reading(self.n_per_v * v.value + self.offset_n, "N", v.timestamp)

    def read(self) -> ReadingMap:
        """One :meth:`read_force` keyed as :meth:`describe`: ``force`` [N], ``ok`` (1: valid)."""
        r = self.read_force()
        return {"force": r, "ok": Reading(float(r.ok), "1", r.timestamp)}

    def zero(self) -> None:
        """Refused: a bridge amplifier has no command; its zero is the rig file's ``daq.force_offset_N``."""
        raise UnsupportedCommandError(self.name, "the bridge amplifier on the DAQ has no zero command: set "
                                   "daq.force_offset_N in the rig file (or the amplifier's own zero)")

    def tare(self) -> None:
        """Refused, as :meth:`zero`."""
        raise UnsupportedCommandError(self.name, "the bridge amplifier on the DAQ has no tare command: set "
                                   "daq.force_offset_N in the rig file (or the amplifier's own zero)")
