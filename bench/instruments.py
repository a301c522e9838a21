"""Build a rig's drivers from its rig file (and, for a simulated rig, the twins' endpoints)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field

from bench.rig import RigConfig
from drivers.adam import Adam4017P, Adam4024, RawScale
from drivers.cancel import CancelToken
from drivers.dini import DiniDGT1S
from drivers.errors import InstrumentError
from drivers.interfaces import (
    Amplifier,
    ClockFn,
    DisplacementSensor,
    ForceSensor,
    Instrument,
    LinearMotor,
    SleepFn,
)
from drivers.keyence import KeyenceLKG
from drivers.linmot import LinMotDrive
from drivers.modbus_link import ModbusLink
from drivers.serial_link import SerialLink
from drivers.trek import TREK_MODELS, TrekAmplifier, TrekModel


@dataclass
class Instruments:
    """The drivers of one rig (absent roles are None)."""

    amplifier: Amplifier | None = None
    laser: DisplacementSensor | None = None
    motor: LinearMotor | None = None
    load_cell: ForceSensor | None = None
    links: dict[str, ModbusLink] = field(default_factory=dict)
    cancel: CancelToken = field(default_factory=CancelToken)  # shared by every link: one stop request reaches all

    def items(self) -> Iterator[tuple[str, Instrument]]:
        """(role, driver) of every instrument present, amplifier first."""
        for role in ("amplifier", "laser", "motor", "load_cell"):
            drv = getattr(self, role)
            if drv is not None:
                yield role, drv

    def _each(self, method: str) -> list[str]:
        errors = []
        for role, drv in self.items():
            try:
                getattr(drv, method)()
            except InstrumentError as exc:
                errors.append(f"{role}: {exc}")
        return errors

    def safe_state(self) -> list[str]:
        """Every instrument to its safe state (HV zero first); returns the errors met, one line each."""
        return self._each("safe_state")

    def close(self) -> list[str]:
        """Close every instrument (each zeroes / stops itself first); returns the errors met."""
        errors = self._each("close")
        for link in self.links.values():
            link.close()
        return errors


def build_instruments(rig: RigConfig, endpoints: dict[str, str] | None = None,
                      clock: ClockFn = time.monotonic, sleep: SleepFn = time.sleep,
                      modbus_poll: float | None = None) -> Instruments:
    """Create (not connect) the drivers; ``endpoints`` (role or bus name → port) override the file's ports.

    ``clock``/``sleep`` are the rig's time: wall time for hardware, the simulated rig's clock otherwise;
    ``modbus_poll`` is the RTU receive poll interval (None: pymodbus' default, right for real wires).
    """
    ep = endpoints or {}
    inst = Instruments()

    def bus(name: str) -> ModbusLink:
        if name not in inst.links:
            cfg = rig.buses[name]
            inst.links[name] = ModbusLink(ep.get(name, cfg.port), f"bus {name}", baudrate=cfg.baudrate,
                                          timeout=cfg.timeout_s, retries=cfg.retries, poll_interval=modbus_poll)
            inst.links[name].cancel = inst.cancel
        return inst.links[name]

    def serial(url: str, device: str, baudrate: int, timeout: float) -> SerialLink:
        link = SerialLink(url, device, baudrate=baudrate, timeout=timeout)
        link.cancel = inst.cancel  # type: ignore[attr-defined]  # (the attribute is part of SerialLink)
        return link

    if (a := rig.amplifier) is not None:
        link = bus(a.bus)
        base = TREK_MODELS[a.model]
        trek = TrekModel(base.model, base.max_output, base.max_current, base.gain,
                         a.vmon_ratio or base.vmon_ratio, a.imon_ratio or base.imon_ratio)
        ao = Adam4024(link, a.ao_unit, "amplifier AO", RawScale(bits=a.ao_bits, raw_format=a.raw_format))
        ai = Adam4017P(link, a.ai_unit, "amplifier AI", RawScale(bits=a.ai_bits, raw_format=a.raw_format))
        inst.amplifier = TrekAmplifier(ao, ai, model=a.model, trek=trek, ao_channel=a.ao_channel,
                                       vmon_channel=a.vmon_channel, imon_channel=a.imon_channel,
                                       max_voltage=min(a.max_voltage_V, rig.limits.max_voltage_V),
                                       slew_limit=a.slew_limit_V_per_s, clock=clock)
    if (lz := rig.laser) is not None:
        inst.laser = KeyenceLKG(serial(ep.get("laser", lz.port), "laser", lz.baudrate, lz.timeout_s),
                                model=lz.model, out=lz.out, clock=clock, storage_points=lz.storage_points)
    if (m := rig.motor) is not None:
        inst.motor = LinMotDrive(serial(ep.get("motor", m.port), "motor", m.baudrate, m.timeout_s),
                                 drive_id=m.drive_id, travel=m.travel_m, max_velocity=m.max_velocity_m_per_s,
                                 max_acceleration=m.max_acceleration_m_per_s2, clock=clock, sleep=sleep,
                                 checksum=m.checksum)
    if (c := rig.load_cell) is not None:
        inst.load_cell = DiniDGT1S(bus(c.bus), unit=c.unit, division=c.division_kg, clock=clock, sleep=sleep)
    return inst
