"""A whole simulated rig: one plant, one clock, a twin per instrument of the rig file, on real ports."""

from __future__ import annotations

from dataclasses import dataclass, field

from bench.rig import RigConfig
from drivers.adam import RawScale
from drivers.keyence import STORAGE_CAPACITY
from drivers.trek import TREK_MODELS, TrekModel
from sim_devices.clock import Clock, VirtualClock, WallClock
from sim_devices.keyence_lkg import KeyenceLKGSim, LaserHead
from sim_devices.linmot_drive import LinMotDriveSim
from sim_devices.modbus_devices import Adam4017PSim, Adam4024Sim, Dgt1sSim
from sim_devices.modbus_host import ModbusHost, SimBus
from sim_devices.plant import HVStage, Plant
from sim_devices.transport import Faults, PtyDevice


@dataclass(frozen=True)
class Endpoint:
    """Where a simulated instrument (or bus) listens, and what speaks there."""

    name: str
    protocol: str
    address: str
    details: str = ""


@dataclass
class SimRig:
    """Simulated twins of every instrument in ``rig``, sharing one :class:`Plant` and one clock."""

    rig: RigConfig
    virtual: bool = False
    clock: Clock = field(init=False)
    plant: Plant = field(init=False)
    twins: dict[str, object] = field(init=False, default_factory=dict)
    faults: dict[str, Faults] = field(init=False, default_factory=dict)
    _serial: dict[str, PtyDevice] = field(init=False, default_factory=dict)
    _modbus: ModbusHost | None = field(init=False, default=None)
    _daq_ports: tuple[int, int] = field(init=False, default=(0, 0))

    def __post_init__(self) -> None:
        rig = self.rig
        self.clock = VirtualClock() if self.virtual else WallClock()
        spec = rig.specimen
        trek = self._trek()
        hv = HVStage(max_current=trek.max_current, max_output=trek.max_output, gain=trek.gain)
        if spec.kind == "membrane":
            self.plant = Plant(self.clock, spec.membrane(), temperature=spec.temperature_K, hv=hv)
        else:
            cfg = spec.lsdea
            x0 = cfg.blocked_position_m if cfg.configuration == "blocked" else cfg.x_at_motor_zero_m
            self.plant = Plant(self.clock, spec.lozenge(), configuration=cfg.configuration, x0=x0, hv=hv,
                               motor_sign=cfg.motor_sign)

    def _trek(self) -> TrekModel:
        a = self.rig.amplifier
        base = TREK_MODELS[a.model if a else "10/10B-HS"]
        if a is None:
            return base
        return TrekModel(base.model, base.max_output, base.max_current, base.gain,
                         a.vmon_ratio or base.vmon_ratio, a.imon_ratio or base.imon_ratio)

    def start(self) -> dict[str, Endpoint]:
        """Start every twin; returns the endpoints by role (serial instruments) or bus name (Modbus)."""
        rig, sim = self.rig, self.rig.simulation
        if rig.laser is not None:
            head = LaserHead(offset_mm=rig.laser.offset_mm, sign=rig.laser.sign, range_mm=rig.laser.range_mm)
            capacity = rig.laser.storage_points or STORAGE_CAPACITY[rig.laser.model]
            twin = KeyenceLKGSim(self.plant, self.clock, model=rig.laser.model, head=head, capacity=capacity,
                                 seed=sim.seed)
            self._serve_serial("laser", twin)
        if rig.motor is not None:
            m = rig.motor
            stroke = (min(m.travel_m[0], 0.0), max(m.travel_m[1], 0.12))
            self._serve_serial("motor", LinMotDriveSim(self.plant, self.clock, drive_id=m.drive_id, stroke=stroke,
                                                       checksum=m.checksum))
        if rig.daq is not None:
            self._start_daq()
        buses: dict[str, list] = {}
        if (a := rig.amplifier) is not None and a.drive == "adam":
            scale_ao = RawScale(bits=a.ao_bits, raw_format=a.raw_format)
            scale_ai = RawScale(bits=a.ai_bits, raw_format=a.raw_format)
            ao = Adam4024Sim(a.ao_unit, self.plant, amplifier_channel=a.ao_channel, scale=scale_ao)
            ai = Adam4017PSim(a.ai_unit, self.plant, self.clock, self._trek(), vmon_channel=a.vmon_channel,
                              imon_channel=a.imon_channel, scale=scale_ai, seed=sim.seed + 1)
            self.twins["amplifier AO"], self.twins["amplifier AI"] = ao, ai
            self.plant.input_watchdog = a.comm_watchdog_s
            buses.setdefault(a.bus, []).extend([ao.device, ai.device])
        if (c := rig.load_cell) is not None:
            cell = Dgt1sSim(c.unit, self.plant, self.clock, division=c.division_kg, capacity=c.capacity_kg,
                            seed=sim.seed + 2)
            self.twins["load_cell"] = cell
            buses.setdefault(c.bus, []).append(cell.device)
        if buses:
            sim_buses = []
            for name, devices in buses.items():
                self.faults[name] = Faults(latency=sim.latency_s, clock=self.clock.now)
                sim_buses.append(SimBus(name, devices, transport=sim.modbus_transport,
                                        baudrate=rig.buses[name].baudrate, faults=self.faults[name]))
            self._modbus = ModbusHost(sim_buses)
            self._modbus.start()
        return self.endpoints()

    def _start_daq(self) -> None:
        """The T7 twin: DAC → conditioning → amplifier input; AINs wired to the plant's observables."""
        from sim_devices.labjack_t7 import Conditioning, LabJackT7Sim, Signal

        d, rig, trek = self.rig.daq, self.rig, self._trek()
        assert d is not None
        signals = {d.vmon_ain: Signal("voltage", 1.0 / trek.vmon_ratio),
                   d.imon_ain: Signal("current", 1.0 / trek.imon_ratio)}
        if d.force_ain is not None:
            signals[d.force_ain] = Signal("force", 1.0 / d.force_N_per_V, -d.force_offset_N / d.force_N_per_V)
        if d.laser_ain is not None:  # the head reads sign·(specimen coordinate) + offset (as the serial twin)
            sign, offset = (rig.laser.sign, rig.laser.offset_mm * 1e-3) if rig.laser else (1, 0.0)
            signals[d.laser_ain] = Signal("displacement", sign / d.laser_m_per_V,
                                          (offset - d.laser_offset_m) / d.laser_m_per_V)
        self.faults["daq"] = Faults(latency=rig.simulation.latency_s, clock=self.clock.now)
        cond = Conditioning(d.drive_gain, d.drive_offset_V, corner_Hz=d.drive_filter_Hz)
        twin = LabJackT7Sim(self.plant, self.clock, dac=d.dac, conditioning=cond, signals=signals,
                            seed=rig.simulation.seed + 3, faults=self.faults["daq"])
        self._daq_ports = twin.start()
        self.twins["daq"] = twin
        if rig.amplifier is not None and rig.amplifier.drive == "daq":
            self.plant.input_watchdog = d.watchdog_s

    def _serve_serial(self, role: str, twin: object) -> None:
        self.faults[role] = Faults(latency=self.rig.simulation.latency_s, clock=self.clock.now)
        self.twins[role] = twin
        self._serial[role] = PtyDevice(twin, role, self.faults[role]).start()  # type: ignore[arg-type]

    def faults_of(self, name: str) -> Faults:
        """The :class:`Faults` of the link serving ``name``: a serial role (``laser``, ``motor``), a bus name
        (``io``), or a Modbus role (``amplifier``, ``load_cell``: its bus). Available once started."""
        rig = self.rig
        bus = {"amplifier": rig.amplifier.bus if rig.amplifier else None,
               "load_cell": rig.load_cell.bus if rig.load_cell else None}.get(name)
        key = bus or name
        if key not in self.faults:
            known = ", ".join(sorted(self.faults)) or "none (not started)"
            raise KeyError(f"no simulated link {name!r}; known: {known}")
        return self.faults[key]

    def endpoints(self) -> dict[str, Endpoint]:
        """Endpoints of the running twins."""
        out: dict[str, Endpoint] = {}
        rig = self.rig
        if "laser" in self._serial and rig.laser is not None:
            out["laser"] = Endpoint("laser", f"Keyence {rig.laser.model} RS-232C ASCII", self._serial["laser"].path,
                                    f"OUT{rig.laser.out}")
        if "motor" in self._serial and rig.motor is not None:
            out["motor"] = Endpoint("motor", "LinMot LinRS", self._serial["motor"].path,
                                    f"drive id {rig.motor.drive_id:#04x}")
        if "daq" in self.twins and rig.daq is not None:
            port, stream_port = self._daq_ports
            out["daq"] = Endpoint("daq", "LabJack T7 Modbus TCP + stream", f"127.0.0.1:{port}:{stream_port}",
                                  f"{rig.daq.scan_rate_Hz:g} scans/s")
        if self._modbus is not None:
            for bus in self._modbus.buses:
                units = []
                if rig.amplifier and rig.amplifier.bus == bus.name:
                    units += [f"ADAM-4024 unit {rig.amplifier.ao_unit}", f"ADAM-4017+ unit {rig.amplifier.ai_unit}"]
                if rig.load_cell and rig.load_cell.bus == bus.name:
                    units.append(f"DGT1S unit {rig.load_cell.unit}")
                proto = {"rtu": "Modbus RTU", "rtu-socket": "Modbus RTU over TCP", "tcp": "Modbus TCP"}[bus.transport]
                out[bus.name] = Endpoint(bus.name, proto, bus.endpoint, ", ".join(units))
        return out

    def port_map(self) -> dict[str, str]:
        """Role / bus name → port, for :func:`bench.instruments.build_instruments`."""
        return {name: ep.address for name, ep in self.endpoints().items()}

    def stop(self) -> None:
        """Stop every twin and close the ports."""
        if (daq := self.twins.pop("daq", None)) is not None:
            daq.stop()  # type: ignore[attr-defined]
        for dev in self._serial.values():
            dev.stop()
        self._serial.clear()
        if self._modbus is not None:
            self._modbus.stop()
            self._modbus = None

    def __enter__(self) -> SimRig:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
