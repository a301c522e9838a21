"""TREK 10/10B-HS and 10/40A-HS high-voltage amplifiers, driven through an analog I/O module.

The HS amplifiers have no digital port: a ±10 V analog input sets the output (gain 1000 V/V) and the
voltage and current monitors are analog outputs (../shared/instruments.md §3). This driver writes the
set-point through an ADAM-4024 analog output and reads the monitors through an ADAM-4017+; it never
pretends the TREK speaks a protocol. It enforces a software voltage limit (refusing, not clipping, a
set-point beyond it, and holding it on the code sent: never a code whose output lies beyond), a software slew
limit (clamping each step to slew·elapsed time), and zero on close.

Where the rig expects the ADAM-4024's communication watchdog (``comm_watchdog_s``: what zeroes the amplifier's
input when the host stalls or dies), :meth:`TrekAmplifier.connect` reads the module's communication-safety enable
(40215, ADAM-4000 manual appendix G p. G-7) and refuses a module that reports it off, as the T7 path reads its
watchdog settings back (:mod:`drivers.labjack.watchdog`). The period itself has no register in the pages read: it
is not checked.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from drivers.adam import A17_RATE_HZ, Adam4017P, Adam4024
from drivers.errors import InstrumentStateError, LimitError
from drivers.interfaces import CheckResult, ClockFn, DataKey, Identity, Reading, ReadingMap, StreamDescription


@dataclass(frozen=True)
class TrekModel:
    """Datasheet figures of one amplifier model and its monitor calibration."""

    model: str
    max_output: float  # V
    max_current: float  # A (DC)
    gain: float = 1000.0  # V out per V in
    vmon_ratio: float = 1000.0  # V out per V of monitor  (monitor ratios: operator manual, calibrate)
    imon_ratio: float = 1e-3  # A per V of monitor


# the oldest a monitor conversion may be when read: the interlock's lag allowance for polled monitors (0.3 s,
# bench.runtime.interlock.POLLED_LAG_S) covers three conversion slots, so at most three channels in turn
MAX_MONITOR_AGE_S = 0.3

TREK_MODELS = {
    "10/10B-HS": TrekModel("10/10B-HS", 10e3, 10e-3, imon_ratio=1e-3),
    "10/40A-HS": TrekModel("10/40A-HS", 10e3, 40e-3, imon_ratio=4e-3),
}


class TrekAmplifier:
    """Driver of a TREK HS amplifier on an ADAM-4024 / ADAM-4017+ pair (implements Amplifier)."""

    def __init__(self, ao: Adam4024, ai: Adam4017P, *, name: str = "amplifier", model: str = "10/10B-HS",
                 ao_channel: int = 0, vmon_channel: int = 0, imon_channel: int = 1, max_voltage: float = 10e3,
                 slew_limit: float = 1e6, clock: ClockFn = time.monotonic, trek: TrekModel | None = None,
                 comm_watchdog_s: float | None = None) -> None:
        if model not in TREK_MODELS and trek is None:
            raise ValueError(f"{name}: unknown TREK model {model!r}; known: {', '.join(TREK_MODELS)}")
        self.trek = trek or TREK_MODELS[model]
        for label, x in (("gain", self.trek.gain), ("vmon_ratio", self.trek.vmon_ratio),
                         ("imon_ratio", self.trek.imon_ratio)):
            if not (math.isfinite(x) and x != 0):
                raise ValueError(f"{name}: {label} must be finite and non-zero, got {x}")
        if not 0 < max_voltage <= self.trek.max_output:
            raise ValueError(f"{name}: max_voltage {max_voltage:g} V must lie in (0, {self.trek.max_output:g}] V")
        if not slew_limit > 0:
            raise ValueError(f"{name}: slew_limit must be > 0 V/s, got {slew_limit}")
        self.ao, self.ai = ao, ai
        self.name = name
        self.ao_channel, self.vmon_channel, self.imon_channel = ao_channel, vmon_channel, imon_channel
        self.max_voltage = max_voltage
        self.slew_limit = slew_limit
        self.comm_watchdog_s = comm_watchdog_s  # the rig expects the ADAM-4024's watchdog (None: not checked)
        self.clock = clock
        self._last_v = 0.0
        self._last_t: float | None = None

    @property
    def commanded(self) -> float:
        """Last voltage set-point sent [V]."""
        return self._last_v

    def connect(self) -> None:
        """Open the bus, check both modules are what the rig says, command 0 V, and (where the rig expects one)
        check the ADAM-4024's communication watchdog is on: InstrumentStateError, after the 0 V, if it reports
        it off."""
        self.ao.link.open()
        if self.ai.link is not self.ao.link:
            self.ai.link.open()
        self.ao.module_name()
        self.ai.module_name()
        if self.ao.safety_flag():  # fired while no host talked to it (the end of an earlier session): a fresh start
            self.ao.clear_safety_flag()
        self.zero()
        self._check_conversions()
        if self.comm_watchdog_s is not None and (on := self.ao.safety_enabled()) != 1:
            raise InstrumentStateError(self.ao.name, f"ADAM-4024 unit {self.ao.unit}: communication watchdog "
                                       f"reported off (register 40215 reads {on}, 1 = on) but the rig expects "
                                       f"one (amplifier.comm_watchdog_s = {self.comm_watchdog_s:g} s): enable "
                                       "the module's communication safety, or set comm_watchdog_s to none and "
                                       "run with --allow-no-watchdog")

    def _check_conversions(self) -> None:
        """The ADAM-4017+ converts its enabled channels in turn, 10 a second in all: with all eight on (as a module
        may come) each monitor is fresh only every 0.8 s, and a reading the interlock or a hand-over takes for the
        output now may be older than the zero it should show. Refused in one line unless both monitors are enabled
        and each is converted at least every :data:`MAX_MONITOR_AGE_S`."""
        on = self.ai.enabled_channels()
        missing = [c for c in (self.vmon_channel, self.imon_channel) if c not in on]
        if missing:
            raise InstrumentStateError(self.ai.name, f"ADAM-4017+ unit {self.ai.unit}: monitor channel(s) "
                                       f"{', '.join(map(str, missing))} not enabled (40221 enables "
                                       f"{on or 'none'}): enable channels {self.vmon_channel} and "
                                       f"{self.imon_channel}")
        if len(on) / A17_RATE_HZ > MAX_MONITOR_AGE_S:
            raise InstrumentStateError(self.ai.name, f"ADAM-4017+ unit {self.ai.unit}: {len(on)} channels enabled "
                                       f"({on}): at {A17_RATE_HZ:g} conversions/s in all each monitor is fresh only "
                                       f"every {len(on) / A17_RATE_HZ:g} s (at most {MAX_MONITOR_AGE_S:g} s): enable "
                                       f"only channels {self.vmon_channel} and {self.imon_channel} (register 40221)")

    def close(self) -> None:
        """Zero the output, then release the bus."""
        try:
            if self.ao.link.is_open:
                self.zero()
        finally:
            self.ao.link.close()
            self.ai.link.close()

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""
        return StreamDescription(self.name, (
            DataKey("voltage", "V", "output voltage from the TREK voltage monitor"),
            DataKey("current", "A", "output current from the TREK current monitor")),
            f"TREK {self.trek.model} via ADAM-4017+")

    def check(self) -> CheckResult:
        """Set-point and limit; the two monitors."""
        v, i = self.read_monitors()
        return CheckResult(f"set-point {self.commanded:.0f} V, limit ±{self.max_voltage:.0f} V",
                           (("voltage", v), ("current", i)))

    def identify(self) -> Identity:
        """Model from the rig file; the I/O modules from their name registers."""
        return Identity("TREK", self.trek.model, {"ao": f"ADAM-{self.ao.module_name()} unit {self.ao.unit}",
                                                  "ai": f"ADAM-{self.ai.module_name()} unit {self.ai.unit}"})

    def safe_state(self) -> None:
        """Command 0 V immediately (the amplifier sinks the DEA's charge)."""
        self.zero()

    def zero(self) -> None:
        """Command 0 V at once: bypasses the slew limit, and goes out even after a stop request."""
        raw = self.ao.write_volts(self.ao_channel, 0.0, always_send=True)
        self._last_v = self.ao.scale.to_volts(raw) * self.trek.gain  # ±half a code: 0 V has no code
        self._last_t = self.clock()

    def _output(self, raw: int) -> float:
        """Amplifier output [V] of the analog module's code ``raw``."""
        return self.ao.scale.to_volts(raw) * self.trek.gain

    def _code(self, volts: float, within: float | None) -> int:
        """The code for ``volts``: the nearest whose output lies within ±bound (``within``, at most and by default
        ``max_voltage``), so one code toward zero where the nearest lies just beyond. LimitError beyond
        ``max_voltage``, or when no code of the module lies within the bound."""
        if not abs(volts) <= self.max_voltage:  # also refuses NaN
            raise LimitError(self.name, f"{volts:.0f} V beyond the software limit ±{self.max_voltage:.0f} V")
        if within is not None and not within >= 0:
            raise ValueError(f"{self.name}: within must be a bound ≥ 0 V, got {within}")
        bound = self.max_voltage if within is None else min(within, self.max_voltage)
        target = min(max(volts, -bound), bound)
        inside = [c for c in self.ao.scale.neighbours(self.ao.scale.to_raw(target / self.trek.gain))
                  if abs(self._output(c)) <= bound]
        if not inside:
            raise LimitError(self.name, f"no code of the analog output lies within ±{bound:g} V")
        return min(inside, key=lambda c: abs(self._output(c) - target))

    def quantise(self, volts: float, within: float | None = None) -> float:
        """The output [V] a set-point of ``volts`` really commands (before the slew limit): the ADAM-4024's
        nearest code whose output lies within ±``within`` (default, and at most, ``max_voltage``) — one code
        toward zero where the nearest lies just beyond, so a set-point at the limit runs and never exceeds it.
        Refuses what :meth:`set_voltage` refuses."""
        return self._output(self._code(volts, within))

    def set_voltage(self, volts: float, within: float | None = None) -> float:
        """Command ``volts`` [V]; refuses |V| > max_voltage, clamps the step to the slew limit, then sends the
        code :meth:`quantise` chooses within ±``within``.

        Returns the output actually commanded: that code times the gain.
        """
        if not abs(volts) <= self.max_voltage:  # also refuses NaN
            raise LimitError(self.name, f"{volts:.0f} V beyond the software limit ±{self.max_voltage:.0f} V")
        now = self.clock()
        if self._last_t is not None:
            step = self.slew_limit * max(now - self._last_t, 0.0)
            volts = min(max(volts, self._last_v - step), self._last_v + step)
        raw = self.ao.write_raw(self.ao_channel, self._code(volts, within))
        commanded = self._output(raw)
        self._last_v, self._last_t = commanded, now
        return commanded

    def read(self) -> ReadingMap:
        """One :meth:`read_monitors` keyed as :meth:`describe`: ``voltage`` [V], ``current`` [A]."""
        v, i = self.read_monitors()
        return {"voltage": v, "current": i}

    def read_monitors(self) -> tuple[Reading, Reading]:
        """(output voltage [V], output current [A]) from one read of both monitor channels.

        A value that is not finite has status "invalid". Both are stamped at the start of the ADAM-4017+'s reply
        (:meth:`ModbusLink.reply_started`), not after its wire time."""
        first = min(self.vmon_channel, self.imon_channel)
        n = abs(self.vmon_channel - self.imon_channel) + 1
        with self.ai.link.lock:
            volts = self.ai.read_volts(first, n)
            t = self.ai.link.reply_started(self.clock())
        v = volts[self.vmon_channel - first] * self.trek.vmon_ratio
        i = volts[self.imon_channel - first] * self.trek.imon_ratio
        return (Reading(v, "V", t, "ok" if math.isfinite(v) else "invalid"),
                Reading(i, "A", t, "ok" if math.isfinite(i) else "invalid"))

    def heard_at(self) -> float | None:
        """When the ADAM-4024 (its unit on the bus) last answered a request (its watchdog's reference)."""
        return self.ao.link.heard_at(self.ao.unit)

    def watchdog_fired(self) -> bool | None:
        """The ADAM-4024's own word: its communication-safety flag (40216), set when its watchdog fired."""
        return self.ao.safety_flag()

    def hurry(self, reply_timeout: float) -> None:
        """Shorter reply waits, no retries, on the analog modules' bus (see the Amplifier contract)."""
        for link in {id(self.ao.link): self.ao.link, id(self.ai.link): self.ai.link}.values():
            link.timeout = min(link.timeout, reply_timeout)
            link.retries = 0

    def longest_silence(self) -> float:
        """The ADAM-4024's longest silence since the last call [s] (requests to its unit alone feed its watchdog)."""
        return self.ao.link.longest_silence(self.ao.unit)

    def read_voltage(self) -> Reading:
        """Output voltage from the voltage monitor [V]."""
        return self.read_monitors()[0]

    def read_current(self) -> Reading:
        """Output current from the current monitor [A]."""
        return self.read_monitors()[1]

