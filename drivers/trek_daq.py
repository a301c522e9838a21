"""TREK HS amplifier driven by a hardware-timed DAQ (LabJack T7): the amplifier's analog input comes from a DAC
through the rig's conditioning stage, its voltage and current monitors go to two analog inputs.

Command-response here (set a voltage, read the monitors, zero); waveforms are played by the DAQ's stream-out
(:meth:`drivers.labjack.LabJackT7.arm`), for which :meth:`TrekOnDaq.dac_volts` converts a voltage waveform.

Conditioning: amplifier input [V] = ``gain`` · DAC [V] + ``offset`` (e.g. gain 4, offset −10 V maps the T7's
0–5 V DAC onto the TREK's ±10 V input); output = TREK gain (1000 V/V) × input.
"""

from __future__ import annotations

import math
import time

import numpy as np

from drivers.errors import LimitError
from drivers.interfaces import CheckResult, ClockFn, DataKey, Identity, Reading, ReadingMap, StreamDescription
from drivers.labjack import DAC_RANGE, UNIT, LabJackT7
from drivers.trek import TrekModel


class TrekOnDaq:
    """Driver of a TREK HS amplifier on a LabJack T7 (implements DaqAmplifier)."""

    def __init__(self, daq: LabJackT7, trek: TrekModel, *, name: str = "amplifier", dac: int = 0,
                 gain: float = 4.0, offset: float = -10.0, vmon_ain: int = 0, imon_ain: int = 1,
                 max_voltage: float = 10e3, clock: ClockFn = time.monotonic) -> None:
        if not (math.isfinite(gain) and gain > 0 and math.isfinite(offset)):
            raise ValueError(f"{name}: conditioning gain must be finite and > 0 and offset finite")
        if not 0 < max_voltage <= trek.max_output:
            raise ValueError(f"{name}: max_voltage {max_voltage:g} V must lie in (0, {trek.max_output:g}] V")
        self.daq, self.trek, self.name = daq, trek, name
        self.dac, self.gain, self.offset = dac, gain, offset
        self.vmon_ain, self.imon_ain = vmon_ain, imon_ain
        self.max_voltage = max_voltage
        self.clock = clock
        self._last_v = 0.0

    # ------------------------------------------------------------ conversions
    def dac_volts(self, volts: np.ndarray | float) -> np.ndarray:
        """DAC voltage [V] for amplifier output ``volts`` [V]."""
        return (np.asarray(volts, dtype=float) / self.trek.gain - self.offset) / self.gain

    def output_volts(self, dac_volts: np.ndarray | float) -> np.ndarray:
        """Amplifier output [V] for DAC voltage ``dac_volts`` [V]."""
        return (self.gain * np.asarray(dac_volts, dtype=float) + self.offset) * self.trek.gain

    def monitor_values(self, vmon: np.ndarray, imon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(output voltage [V], output current [A]) from the monitor inputs' volts (the TREK's monitor ratios)."""
        return vmon * self.trek.vmon_ratio, imon * self.trek.imon_ratio

    def dac_window(self, within: float) -> tuple[float, float]:
        """DAC volts (lo, hi) whose amplifier output lies within ±``within`` [V] (and within the DAC's 0–5 V): the
        ends moved inward by the last bits of a float where the conversion back would land just beyond."""
        lo, hi = sorted((float(self.dac_volts(-within)), float(self.dac_volts(within))))
        lo, hi = max(lo, DAC_RANGE[0]), min(hi, DAC_RANGE[1])
        while abs(float(self.output_volts(hi))) > within:
            hi = math.nextafter(hi, -math.inf)
        while abs(float(self.output_volts(lo))) > within:
            lo = math.nextafter(lo, math.inf)
        return lo, hi

    def _dac_request(self, volts: float, within: float | None) -> tuple[float, tuple[float, float]]:
        """(DAC volts for ``volts``, DAC window of the bound); refuses what :meth:`set_voltage` refuses."""
        if not math.isfinite(volts) or abs(volts) > self.max_voltage:
            raise LimitError(self.name, f"{volts:.0f} V beyond the software limit ±{self.max_voltage:.0f} V")
        if within is not None and not within >= 0:
            raise ValueError(f"{self.name}: within must be a bound ≥ 0 V, got {within}")
        dac_v = float(self.dac_volts(volts))
        if not DAC_RANGE[0] <= dac_v <= DAC_RANGE[1]:
            raise LimitError(self.name, f"{volts:.0f} V needs DAC {dac_v:.3f} V, outside the DAC's 0–5 V")
        window = self.dac_window(self.max_voltage if within is None else min(within, self.max_voltage))
        return dac_v, window

    # ------------------------------------------------------------ Instrument
    @property
    def commanded(self) -> float:
        """Last voltage commanded [V] (the DAC's code through the conditioning stage)."""
        return self._last_v

    def connect(self) -> None:
        """Connect the DAQ (if not yet), set the monitor inputs to ±10 V single-ended, command 0 V."""
        if not self.daq.link.is_open:
            self.daq.connect()
        for ain in (self.vmon_ain, self.imon_ain):
            self.daq.configure_ain(ain, 10.0)
        self.zero()

    def close(self) -> None:
        """Zero the output (the DAQ itself is closed by its own driver)."""
        if self.daq.link.is_open:
            self.zero()

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source (the scan clock's text is added by the run time)."""
        return StreamDescription(self.name, (
            DataKey("voltage", "V", "output voltage from the TREK voltage monitor"),
            DataKey("current", "A", "output current from the TREK current monitor"),
            DataKey("commanded", "V", "output commanded: the DAC code played in the same scan, through the "
                    "conditioning stage and the amplifier's gain")),
            f"TREK {self.trek.model} monitors on AIN{self.vmon_ain}/AIN{self.imon_ain}")

    def check(self) -> CheckResult:
        """Set-point and limit; the two monitors (command-response reads of their AINs)."""
        v, i = self.read_monitors()
        return CheckResult(f"set-point {self.commanded:.0f} V, limit ±{self.max_voltage:.0f} V",
                           (("voltage", v), ("current", i)))

    def identify(self) -> Identity:
        """Model from the rig file; the DAQ from its registers."""
        return Identity("TREK", self.trek.model, {"drive": f"LabJack T7 DAC{self.dac}",
                                                  "monitors": f"AIN{self.vmon_ain}/AIN{self.imon_ain}"})

    def safe_state(self) -> None:
        """Stop any stream and command 0 V at once."""
        if self.daq.streaming:
            self.daq.stop(always_send=True)
        self.zero()

    def zero(self) -> None:
        """Command 0 V (the DAC code nearest to 0 V at the amplifier input); goes out even after a stop request."""
        self._last_v = float(self.output_volts(self.daq.write_dac(self.dac, float(self.dac_volts(0.0)),
                                                                  always_send=True)))

    def quantise(self, volts: float, within: float | None = None) -> float:
        """The output [V] a set-point of ``volts`` really commands, sending nothing: the DAC's nearest code (code =
        V·Slope + Offset, 12-bit level) whose output lies within ±``within`` (default, and at most,
        ``max_voltage``) — one level toward zero where the nearest lies just beyond. Refuses what
        :meth:`set_voltage` refuses."""
        dac_v, window = self._dac_request(volts, within)
        return float(self.output_volts(self.daq.dac_output(self.dac, dac_v, window)[1]))

    def set_voltage(self, volts: float, within: float | None = None) -> float:
        """Command ``volts`` [V] on the code :meth:`quantise` chooses; refuses |V| > max_voltage or what the DAC
        cannot produce. Returns the output commanded (the DAC's level through the conditioning stage)."""
        dac_v, window = self._dac_request(volts, within)
        self._last_v = float(self.output_volts(self.daq.write_dac(self.dac, dac_v, window)))
        return self._last_v

    def read(self) -> ReadingMap:
        """One :meth:`read_monitors` keyed as :meth:`describe`, with the output ``commanded`` [V] at that time."""
        v, i = self.read_monitors()
        return {"voltage": v, "current": i, "commanded": Reading(self.commanded, "V", v.timestamp)}

    def read_monitors(self) -> tuple[Reading, Reading]:
        """(output voltage [V], output current [A]) from two command-response AIN reads; both "invalid" (NaN) unless
        both AIN readings are ok (the T7 driver flags values its converter cannot make) and finite once scaled."""
        v = self.daq.read_ain(self.vmon_ain)
        i = self.daq.read_ain(self.imon_ain)
        t = self.clock()
        vv, ii = v.value * self.trek.vmon_ratio, i.value * self.trek.imon_ratio
        if not (v.ok and i.ok and math.isfinite(vv) and math.isfinite(ii)):
            return Reading(math.nan, "V", t, "invalid"), Reading(math.nan, "A", t, "invalid")
        return Reading(vv, "V", t), Reading(ii, "A", t)

    def heard_at(self) -> float | None:
        """When the T7 last answered a request: any request feeds its watchdog (stream packets do not)."""
        return self.daq.heard_at()

    def watchdog_fired(self) -> bool | None:
        """None: the T7's register map has no flag for a watchdog that fired (only its configuration)."""
        return None

    def hurry(self, reply_timeout: float) -> None:
        """Shorter reply waits, no retries, on the T7's command-response link (see the Amplifier contract)."""
        self.daq.link.timeout = min(self.daq.link.timeout, reply_timeout)
        self.daq.link.retries = 0

    def longest_silence(self) -> float:
        """The T7's longest silence since the last call [s] (any command-response request feeds its watchdog)."""
        return self.daq.link.longest_silence(UNIT)

    def read_voltage(self) -> Reading:
        """Output voltage from the voltage monitor [V]."""
        return self.read_monitors()[0]

    def read_current(self) -> Reading:
        """Output current from the current monitor [A]."""
        return self.read_monitors()[1]
