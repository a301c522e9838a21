"""Build a rig's drivers from its rig file (and, for a simulated rig, the twins' endpoints)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

from bench.rig import RigConfig
from drivers.adam import Adam4017P, Adam4024, RawScale
from drivers.bridge_daq import BridgeOnDaq
from drivers.cancel import CancelToken
from drivers.deadline import WALL, ReplyTimer
from drivers.dini import DiniDGT1S
from drivers.errors import InstrumentError
from drivers.interfaces import (
    Amplifier,
    ClockFn,
    DaqAmplifier,
    DisplacementSensor,
    ForceSensor,
    Instrument,
    LinearMotor,
    Readable,
    Sensor,
    SleepFn,
    StreamingDaq,
)
from drivers.keyence import KeyenceLKG
from drivers.labjack import LabJackT7
from drivers.linmot import LinMotDrive
from drivers.modbus_link import ModbusLink
from drivers.serial_link import SerialLink
from drivers.trek import TREK_MODELS, TrekAmplifier, TrekModel
from drivers.trek_daq import TrekOnDaq


@dataclass
class Instruments:
    """The drivers of one rig (absent roles are None)."""

    amplifier: Amplifier | None = None
    laser: DisplacementSensor | None = None
    motor: LinearMotor | None = None
    load_cell: ForceSensor | None = None
    daq: StreamingDaq | None = None  # hardware-timed drive and acquisition (the engine streams through it)
    sensors: dict[str, Sensor] = field(default_factory=dict)  # role → an instrument the run only reads (its stream)
    links: dict[str, ModbusLink] = field(default_factory=dict)
    cancel: CancelToken = field(default_factory=CancelToken)  # shared by every link: one stop request reaches all

    @property
    def stream_drive(self) -> tuple[StreamingDaq, DaqAmplifier] | None:
        """(the DAQ, the amplifier on its analog output) when the rig plays its steps hardware-timed — the
        amplifier's set-point is the DAQ's output (any :class:`~drivers.interfaces.StreamingDaq` and
        :class:`~drivers.interfaces.DaqAmplifier`); None: set-points are command-response."""
        if self.daq is not None and isinstance(self.amplifier, DaqAmplifier):
            return self.daq, self.amplifier
        return None

    def items(self) -> Iterator[tuple[str, Instrument]]:
        """(role, driver) of every instrument present, amplifier first."""
        for role in ("daq", "amplifier", "laser", "motor", "load_cell"):
            drv = getattr(self, role)
            if drv is not None:
                yield role, drv
        yield from self.sensors.items()

    def readables(self) -> Iterator[tuple[str, Readable]]:
        """(role, driver) of every instrument a run records through ``describe()`` / ``read()`` (all but the DAQ)."""
        roles: list[tuple[str, Readable | None]] = [("amplifier", self.amplifier), ("motor", self.motor),
                                                    ("load_cell", self.load_cell), ("laser", self.laser),
                                                    *self.sensors.items()]
        for role, drv in roles:
            if drv is not None:
                yield role, drv

    def _each(self, method: str) -> list[str]:
        """``method`` of every instrument — the output's path first (DAQ, amplifier), then the motor, then the
        rest — each tried whatever the one before raised: one failure (a driver's, or anything else a dead port
        lets out) must not leave the next instrument unsafe. Returns the errors met, one line each."""
        errors = []
        first = {"daq": 0, "amplifier": 1, "motor": 2}
        for role, drv in sorted(self.items(), key=lambda item: first.get(item[0], 3)):
            try:
                getattr(drv, method)()
            except InstrumentError as exc:  # its line names its device: the role again only where that differs
                errors.append(str(exc) if exc.device == role else f"{role}: {exc}")
            except Exception as exc:  # not a driver's error: said in the same line, never skipping the rest
                errors.append(f"{role}: {type(exc).__name__}: {exc}")
        return errors

    def safe_state(self) -> list[str]:
        """Every instrument to its safe state (HV zero first, then the motor); returns the errors met, one line
        each."""
        return self._each("safe_state")

    def close(self) -> list[str]:
        """Close every instrument (each zeroes / stops itself first); returns the errors met."""
        errors = self._each("close")
        for link in self.links.values():
            link.close()
        return errors


def build_instruments(rig: RigConfig, endpoints: dict[str, str] | None = None,
                      clock: ClockFn = time.monotonic, sleep: SleepFn = time.sleep,
                      modbus_poll: float | None = None, timers: Mapping[str, ReplyTimer] | None = None,
                      wire_time: bool = True) -> Instruments:
    """Create (not connect) the drivers; ``endpoints`` (role or bus name → port) override the file's ports.

    ``clock``/``sleep`` are the rig's time: wall time for hardware, the simulated rig's clock otherwise;
    ``modbus_poll`` is the RTU receive poll interval (None: pymodbus' default, right for real wires);
    ``timers`` (role, bus name or "daq" → :class:`~drivers.deadline.ReplyTimer`) decide when a link gives up on
    a reply — a virtual-time run's twins (:meth:`bench.runtime.sim_rig.SimRig.reply_timers`); the rest, and all of
    them on hardware, wait on the wall clock. ``wire_time``: whether the serial lines take their wire time (always on
    hardware; a simulated rig's :attr:`~bench.runtime.sim_rig.SimRig.wire_time`) — polled readings are stamped at
    the start of their reply, the arrival less the reply's wire time, and a line at pty speed has none to subtract.
    """
    ep = endpoints or {}
    tm = timers or {}
    wire_time = wire_time and rig.simulation.wire_time  # a rig of twins served at pty speed says so
    inst = Instruments()

    def bus(name: str) -> ModbusLink:
        if name not in inst.links:
            cfg = rig.buses[name]
            # a bus's modules (ADAM-4000, DGT1S) speak RS-485 only: on tcp:// to a real rig the rig file says
            # whether a TCP/RTU gateway's line is behind it (gateway_baudrate); a twin's endpoint is one, at the
            # bus's baud rate (the twins' Modbus TCP transport paces its frames so)
            gateway = cfg.baudrate if name in ep else cfg.gateway_baudrate
            inst.links[name] = ModbusLink(ep.get(name, cfg.port), f"bus {name}", baudrate=cfg.baudrate,
                                          timeout=cfg.timeout_s, retries=cfg.retries, poll_interval=modbus_poll,
                                          timer=tm.get(name, WALL), wire=wire_time, gateway_baud=gateway)
            inst.links[name].cancel = inst.cancel
            inst.links[name].clock = clock  # a reply's arrival, on the rig's clock (a retry's late reply's too)
        return inst.links[name]

    def serial(url: str, device: str, baudrate: int, timeout: float) -> SerialLink:
        link = SerialLink(url, device, baudrate=baudrate, timeout=timeout, timer=tm.get(device, WALL), wire=wire_time)
        link.cancel = inst.cancel
        return link

    if (d := rig.daq) is not None:
        host, port, stream_port = d.host, d.port, d.stream_port
        if "daq" in ep:  # "host:port:stream_port" of a running twin
            host, p1, p2 = ep["daq"].rsplit(":", 2)
            port, stream_port = int(p1), int(p2)
        a_cfg = rig.amplifier
        zero_dac = -d.drive_offset_V / d.drive_gain if a_cfg is not None and a_cfg.drive == "daq" else 0.0
        safe = (zero_dac, 0.0) if d.dac == 0 else (0.0, zero_dac)
        wd = None if d.watchdog_s is None else int(d.watchdog_s)  # RigConfig: whole seconds (the T7's unit)
        t7 = LabJackT7(host, port=port, stream_port=stream_port, timeout=d.timeout_s, cancel=inst.cancel,
                       clock=clock, sleep=sleep, safe_dac=safe, watchdog_s=wd, timer=tm.get("daq", WALL))
        inst.daq = t7
        if d.force_ain is not None:  # the load cell's bridge amplifier on an input: read on request (manual
            # control, `devices check`); a run's stream samples the same input on its scan clock instead
            inst.load_cell = BridgeOnDaq(t7, ain=d.force_ain, n_per_v=d.force_N_per_V, offset_n=d.force_offset_N,
                                         clock=clock)
    if (a := rig.amplifier) is not None:
        base = TREK_MODELS[a.model]
        trek = TrekModel(base.model, base.max_output, base.max_current, base.gain,
                         a.vmon_ratio or base.vmon_ratio, a.imon_ratio or base.imon_ratio)
        if a.drive == "daq":
            assert isinstance(inst.daq, LabJackT7) and rig.daq is not None  # RigConfig checks it
            inst.amplifier = TrekOnDaq(inst.daq, trek, dac=rig.daq.dac, gain=rig.daq.drive_gain,
                                       offset=rig.daq.drive_offset_V, vmon_ain=rig.daq.vmon_ain,
                                       imon_ain=rig.daq.imon_ain,
                                       max_voltage=min(a.max_voltage_V, rig.limits.max_voltage_V), clock=clock)
            return _rest(rig, inst, ep, clock, sleep, bus, serial)
        link = bus(a.bus)
        ao = Adam4024(link, a.ao_unit, "amplifier AO", RawScale(bits=a.ao_bits, raw_format=a.raw_format))
        ai = Adam4017P(link, a.ai_unit, "amplifier AI", RawScale(bits=a.ai_bits, raw_format=a.raw_format))
        inst.amplifier = TrekAmplifier(ao, ai, model=a.model, trek=trek, ao_channel=a.ao_channel,
                                       vmon_channel=a.vmon_channel, imon_channel=a.imon_channel,
                                       max_voltage=min(a.max_voltage_V, rig.limits.max_voltage_V),
                                       slew_limit=a.slew_limit_V_per_s, clock=clock,
                                       comm_watchdog_s=a.comm_watchdog_s)
    return _rest(rig, inst, ep, clock, sleep, bus, serial)


def _rest(rig: RigConfig, inst: Instruments, ep: dict[str, str], clock: ClockFn, sleep: SleepFn,
          bus: Callable[[str], ModbusLink], serial: Callable[[str, str, int, float], SerialLink]) -> Instruments:
    """The laser, motor and load cell drivers."""
    if (lz := rig.laser) is not None:
        inst.laser = KeyenceLKG(serial(ep.get("laser", lz.port), "laser", lz.baudrate, lz.timeout_s),
                                model=lz.model, out=lz.out, clock=clock, storage_points=lz.capacity)
    if (m := rig.motor) is not None:
        inst.motor = LinMotDrive(serial(ep.get("motor", m.port), "motor", m.baudrate, m.timeout_s),
                                 drive_id=m.drive_id, travel=m.travel_m, max_velocity=m.max_velocity_m_per_s,
                                 max_acceleration=m.max_acceleration_m_per_s2, clock=clock, sleep=sleep,
                                 checksum=m.checksum)
    if (c := rig.load_cell) is not None:
        inst.load_cell = DiniDGT1S(bus(c.bus), unit=c.unit, division=c.division_kg, clock=clock, sleep=sleep)
    return inst
