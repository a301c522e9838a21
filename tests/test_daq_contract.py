"""A second DAQ through the contract (issue 22): an in-memory DAQ that is not the LabJack T7 plays a hardware-timed
protocol through the unchanged engine.

The fake implements :class:`drivers.interfaces.StreamingDaq` from the contract's words alone: an ideal 16-bit
0–5 V analog output, scan k plays stream-out value k (the last one held after a final append), every analog input
sampled on the same scan clock; what the inputs read comes from a simple model of the rig around it (the rig
file's conditioning stage, a 1000 V/V amplifier, its voltage monitor at 1 V/kV, no current). Its amplifier
implements :class:`drivers.interfaces.DaqAmplifier` with the same conversion. Expected values come from the
protocol's own definition of its waveform and from that conversion, not from the engine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from bench.core.clock import VirtualClock
from bench.runtime.context import Snapshot
from bench.runtime.engine import Engine
from bench.runtime.hardware_timed import describe_streams
from bench.runtime.instruments import Instruments
from bench.runtime.run import plan_run
from bench.runtime.safety import Supervisor
from bench.storage.recorder import Column, Recorder
from bench.storage.runfile import open_run
from bench.waveforms import Waveform
from drivers.interfaces import (
    CheckResult,
    DacCoding,
    DaqAmplifier,
    DataKey,
    Identity,
    Reading,
    StreamBlock,
    StreamDescription,
    StreamingDaq,
    StreamSpec,
)
from tests.conftest import ROOT

RATE = 1000.0  # scans/s of the fake (the rig file's scan_rate_Hz)
SLOPE = 65535 / 5.0  # codes per volt of an ideal 16-bit 0–5 V DAC
GAIN, OFFSET, TREK_GAIN = 4.0, -10.0, 1000.0  # the rig file's conditioning stage; the amplifier's V/V
AMPLITUDE, FREQ = 3000.0, 1.0  # the test protocol's raised cosine

RIG = f"""
name = "fake-daq-sim"
description = "the thesis membrane on a DAQ that is not a T7 (tests/test_daq_contract.py)"
simulated = true

[specimen]
kind = "membrane"
temperature_K = 296.0
displacement_length_m = 0.03
breakdown_field_V_per_m = 100e6

[limits]
max_voltage_V = 8000.0
max_current_A = 0.005
max_force_N = 20.0

[daq]
scan_rate_Hz = {RATE}
dac = 0
drive_gain = {GAIN}
drive_offset_V = {OFFSET}
vmon_ain = 0
imon_ain = 1

[amplifier]
model = "10/10B-HS"
drive = "daq"
max_voltage_V = 8000.0
"""

PROTOCOL = f"""
[protocol]
name = "fake-daq"
description = "a raised cosine and a rest, hardware-timed"
rig = "rig.toml"

[recording]
monitors_Hz = 5
setpoint_Hz = 20

[[steps]]
type = "waveform"
name = "cosine"
channel = "voltage"
kind = "raised_cosine"
amplitude = "{AMPLITUDE / 1000:g} kV"
frequency_Hz = {FREQ}
duration_s = 2.0

[[steps]]
type = "relax"
name = "rest"
duration_s = 0.5
"""


def amplifier_out(dac: np.ndarray | float) -> np.ndarray:
    """The rig around the DAQ: amplifier output [V] for DAC volts (conditioning stage, then 1000 V/V)."""
    return (GAIN * np.asarray(dac, dtype=float) + OFFSET) * TREK_GAIN


class FakeDaq:
    """An in-memory DAQ implementing StreamingDaq; ``inputs(dac_volts)`` models what its analog inputs read."""

    def __init__(self, clock: VirtualClock, inputs: Callable[[float], dict[int, float]]) -> None:
        self.name, self.timeout, self.streaming, self.stop_unconfirmed = "daq", 0.1, False, False
        self.clock, self.inputs = clock, inputs
        self.dac_now = 2.5  # [V] the output holds this between streams
        self.calls: list[str] = []
        self._spec: StreamSpec | None = None
        self._values = np.zeros(0)  # every stream-out value given, as played [V]
        self._final = True
        self._t0 = 0.0
        self._scans = 0  # next scan to hand out
        self._underrun = 0

    # ---- Instrument
    def connect(self) -> None:
        self.calls.append("connect")

    def close(self) -> None:
        self.safe_state()

    def identify(self) -> Identity:
        return Identity("test", "fake DAQ")

    def safe_state(self) -> None:
        if self.streaming:
            self.stop()
        self.dac_now = 2.5

    def check(self) -> CheckResult:
        return CheckResult("ok", ())

    # ---- command-response
    def dac_coding(self, dac: int, within: tuple[float, float]) -> DacCoding:
        lo, hi = max(0, math.ceil(within[0] * SLOPE)), min(65535, math.floor(within[1] * SLOPE))
        return DacCoding(SLOPE, 0.0, 0, lo, hi)

    def out_played(self, volts: np.ndarray, dac: int, within: tuple[float, float] | None = None) -> np.ndarray:
        codes = np.clip(np.rint(np.asarray(volts, dtype=float) * SLOPE), 0, 65535)
        if within is not None:
            c = self.dac_coding(dac, within)
            codes = np.clip(codes, c.lo, c.hi)
        return codes / SLOPE

    def write_dac(self, dac: int, volts: float, within: tuple[float, float] | None = None) -> float:
        self.dac_now = float(self.out_played(np.array([volts]), dac, within)[0])
        return self.dac_now

    def read_dac(self, dac: int) -> float:
        return self.dac_now

    def read_ain(self, ain: int) -> Reading:
        return Reading(self.inputs(self.dac_now)[ain], "V", self.clock.now())

    # ---- stream
    @property
    def out_open(self) -> bool:
        return self._spec is not None and not self._final

    @property
    def scans_received(self) -> int:
        return self._scans

    @property
    def out_underrun_scans(self) -> int:
        return self._underrun

    @property
    def scan_clock_uncertainty(self) -> float:
        return 0.0

    def arm(self, spec: StreamSpec) -> None:
        assert spec.output is not None and not self.streaming
        self.calls.append("arm")
        self._spec, self._scans, self._underrun = spec, 0, 0
        self._values = self.out_played(spec.output.volts, spec.output.dac, spec.output.within)
        self._final = spec.output.final

    def kickoff(self) -> float:
        assert self._spec is not None and not self.streaming
        self.calls.append("kickoff")
        self.streaming, self._t0 = True, self.clock.now()
        return self._t0

    def extend(self, volts: np.ndarray, final: bool = True, within: tuple[float, float] | None = None) -> np.ndarray:
        assert self._spec is not None and self._spec.output is not None and not self._final
        self.calls.append("extend")
        played = self.out_played(volts, self._spec.output.dac, within)
        self._values = np.concatenate([self._values, played])
        self._final = final
        return played

    def collect(self, until: float | None = None, timeout: float = 1.0) -> StreamBlock:
        assert self._spec is not None
        now = self.clock.now() if until is None else min(until, self.clock.now())
        end = math.floor((now - self._t0) * RATE + 1e-9) + 1 if self.streaming else self._scans
        k = np.arange(self._scans, max(end, self._scans))
        beyond = k >= self._values.size
        if beyond.any() and not self._final:
            self._underrun += int(beyond.sum())
        dac = self._values[np.minimum(k, self._values.size - 1)]
        if dac.size:
            self.dac_now = float(dac[-1])
        rows = [[self.inputs(float(d))[i.ain] for i in self._spec.inputs] for d in dac]
        volts = np.array(rows, dtype=float).reshape(k.size, len(self._spec.inputs))
        self._scans += k.size
        return StreamBlock(int(k[0]) if k.size else self._scans, self._t0, 1 / RATE,
                           tuple(i.name for i in self._spec.inputs), volts, np.ones(volts.shape, bool))

    def whole_packets_at(self) -> float:
        return self.clock.now()  # scan by scan: no packets

    def stop(self) -> StreamBlock | None:
        if not self.streaming:
            return None
        self.calls.append("stop")
        block = self.collect()
        self.streaming, self._final = False, True
        return block


class FakeAmplifier:
    """An amplifier on the fake DAQ's output 0 and inputs 0/1 (implements DaqAmplifier)."""

    def __init__(self, daq: FakeDaq, max_voltage: float) -> None:
        self.daq, self.name, self.max_voltage = daq, "amplifier", max_voltage

    def dac_volts(self, volts: np.ndarray | float) -> np.ndarray:
        return (np.asarray(volts, dtype=float) / TREK_GAIN - OFFSET) / GAIN

    def output_volts(self, dac_volts: np.ndarray | float) -> np.ndarray:
        return amplifier_out(dac_volts)

    def dac_window(self, within: float) -> tuple[float, float]:
        lo, hi = max(float(self.dac_volts(-within)), 0.0), min(float(self.dac_volts(within)), 5.0)
        while abs(float(self.output_volts(hi))) > within:
            hi = math.nextafter(hi, -math.inf)
        while abs(float(self.output_volts(lo))) > within:
            lo = math.nextafter(lo, math.inf)
        return lo, hi

    def monitor_values(self, vmon: np.ndarray, imon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return vmon * 1000.0, imon * 1e-3

    @property
    def commanded(self) -> float:
        return float(self.output_volts(self.daq.dac_now))

    def quantise(self, volts: float, within: float | None = None) -> float:
        window = self.dac_window(self.max_voltage if within is None else within)
        return float(self.output_volts(self.daq.out_played(self.dac_volts(volts), 0, window)[0]))

    def set_voltage(self, volts: float, within: float | None = None) -> float:
        window = self.dac_window(self.max_voltage if within is None else within)
        return float(self.output_volts(self.daq.write_dac(0, float(self.dac_volts(volts)), window)))

    def zero(self) -> None:
        self.daq.write_dac(0, float(self.dac_volts(0.0)))

    def read_monitors(self) -> tuple[Reading, Reading]:
        v, i = self.monitor_values(np.array(self.daq.read_ain(0).value), np.array(self.daq.read_ain(1).value))
        t = self.daq.clock.now()
        return Reading(float(v), "V", t), Reading(float(i), "A", t)

    def read(self) -> dict[str, Reading]:
        v, i = self.read_monitors()
        return {"voltage": v, "current": i, "commanded": Reading(self.commanded, "V", v.timestamp)}

    def read_voltage(self) -> Reading:
        return self.read_monitors()[0]

    def read_current(self) -> Reading:
        return self.read_monitors()[1]

    def heard_at(self) -> float | None:
        return None

    def watchdog_fired(self) -> bool | None:
        return None

    def hurry(self, reply_timeout: float) -> None:
        pass

    def longest_silence(self) -> float:
        return 0.0

    def connect(self) -> None:
        self.zero()

    def close(self) -> None:
        self.zero()

    def identify(self) -> Identity:
        return Identity("test", "amplifier on the fake DAQ")

    def safe_state(self) -> None:
        self.zero()

    def check(self) -> CheckResult:
        return CheckResult("ok", ())

    def describe(self) -> StreamDescription:
        return StreamDescription("amplifier", (
            DataKey("voltage", "V", "output voltage from the voltage monitor"),
            DataKey("current", "A", "output current from the current monitor"),
            DataKey("commanded", "V", "output commanded in the same scan")), "amplifier on the fake DAQ")


def test_the_fakes_are_what_the_contract_asks() -> None:
    clock = VirtualClock()
    daq = FakeDaq(clock, lambda dac: {0: 0.0, 1: 0.0})
    assert isinstance(daq, StreamingDaq) and isinstance(FakeAmplifier(daq, 8000.0), DaqAmplifier)
    assert Instruments(amplifier=FakeAmplifier(daq, 8000.0), daq=daq).stream_drive is not None
    assert Instruments(daq=daq).stream_drive is None  # no amplifier on its output: nothing is played through it


def test_a_hardware_timed_protocol_runs_on_a_second_daq_through_the_contract(tmp_path: Path) -> None:
    (tmp_path / "rig.toml").write_text(RIG, encoding="utf-8")
    (tmp_path / "fake.toml").write_text(PROTOCOL, encoding="utf-8")
    plan = plan_run(tmp_path / "fake.toml")
    rig, program = plan.rig, plan.program
    clock = VirtualClock()
    # the rig around the DAQ: the voltage monitor reads the amplifier output at 1 V/kV, no current flows
    daq = FakeDaq(clock, lambda dac: {0: float(amplifier_out(dac)) / 1000.0, 1: 0.0})
    amp = FakeAmplifier(daq, 8000.0)
    inst = Instruments(amplifier=amp, daq=daq)
    assert rig.daq is not None
    described = describe_streams(rig.daq, amp)
    streams: dict[str, list[Column]] = {"setpoints": [Column("voltage", "V", "commanded"),
                                                      Column("aperture", "m", "none")]}
    streams.update({d.stream: list(d.columns) for d in described})
    rows: list[tuple[int, str, str, str, float, float]] = [(s.index, s.label, s.name, s.kind, s.t_start, s.duration)
                                                          for s in program.segments]
    rec = Recorder(tmp_path / "fake.h5", {"rig_name": rig.name}, streams, rows,
                   {"setpoints": 20.0, "amplifier": RATE})
    for _, drv in inst.items():
        drv.connect()
    engine = Engine(program, inst, clock, rec, Supervisor(rig, rig.specimen.membrane()))
    assert isinstance(engine.snapshot, Snapshot)
    result = engine.run()
    assert result.state == "completed", result.reason
    f = open_run(result.path)
    assert f.complete and f.state == "completed"
    # the two steps play back to back on one stream: armed and kicked off once, the rest appended while it played
    assert daq.calls[:3] == ["connect", "arm", "kickoff"] and daq.calls.count("arm") == 1
    assert "extend" in daq.calls and daq.calls.count("stop") >= 1
    amp_rec = f.streams["amplifier"]
    (t_stop,) = [t for t, _, kind, _ in f.event_list() if kind == "stop"]
    scans = amp_rec.t < t_stop  # after it, the shutdown's own monitor reads
    t, v, cmd = amp_rec.t[scans], amp_rec.columns["voltage"][scans], amp_rec.columns["commanded"][scans]
    assert np.allclose(np.diff(t), 1 / RATE, atol=1e-9)  # every scan recorded once, none lost
    assert t.size >= 2.5 * RATE  # both steps, scan 0 at the start to the rest's end
    # the protocol's waveform, played within one code of the 16-bit DAC through the conditioning (4 V/V, 1000 V/V)
    code = 1 / SLOPE * GAIN * TREK_GAIN
    wave = Waveform("raised_cosine", AMPLITUDE, FREQ)
    cos = (t > 1 / RATE) & (t <= 2.0)
    assert np.max(np.abs(cmd[cos] - wave(t[cos]))) <= code + 1e-6
    assert np.max(np.abs(v[cos] - wave(t[cos]))) <= code + 1e-6  # the monitor model reads what the DAC plays
    rest = (t > 2.0 + 1 / RATE) & (t <= 2.5)
    assert np.all(np.abs(v[rest]) <= code)  # the rest holds the cosine's end value, 0 V
    assert abs(amp.commanded) <= code and not daq.streaming  # the stream stopped; the output held at 0 V


@pytest.mark.parametrize("path", ["bench/runtime/engine.py", "bench/runtime/hardware_timed.py",
                                  "bench/runtime/polls.py", "bench/runtime/context.py"])
def test_the_run_time_names_no_daq_model(path: str) -> None:
    """The hardware-timed path and the engine know a DAQ by the contract only: no driver class, no mode picked by
    the amplifier's type."""
    text = (ROOT / path).read_text(encoding="utf-8")
    for name in ("LabJackT7", "drivers.labjack", "TrekOnDaq", "drivers.trek_daq"):
        assert name not in text, (path, name)
