"""A whole simulated rig: one plant, one clock, a twin per instrument of the rig file, on real ports.

Real timing (``timing="real"``): every serial link and RS-485 bus is a :class:`Line` at the rig file's baud
rate, so requests and replies take their wire time, the inter-frame gaps and the devices' turnarounds —
slept on the wall clock, added to a virtual clock (a virtual run then takes the time a real one would).
``timing="none"`` serves at pty speed. Default (None): real on the wall clock (``bench sim serve``,
real-time runs); on a virtual clock "none" for now — several shipped protocols exceed their lines (see
:mod:`bench.protocol.link_budget`), so virtual runs opt in with ``timing="real"`` once they fit.
On the wall clock a background thread keeps the plant at the present, so a request after a long idle
time is answered without first integrating the idle time.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from bench.core.clock import Clock, VirtualClock, WallClock
from bench.core.noise import lkg_noise_mm, load_cell_noise_kg
from bench.core.plant import Plant
from bench.rig import RigConfig, amplifier_spec, plant_for
from bench.runtime.replay import Recording, ReplayError, ReplayPlant, check_fits
from sim_devices.keyence_lkg import TURNAROUND_S as LKG_TURNAROUND_S
from sim_devices.keyence_lkg import KeyenceLKGSim, LaserHead
from sim_devices.labjack_t7 import LabJackT7Sim
from sim_devices.linmot_drive import LinMotDriveSim
from sim_devices.modbus_devices import STANDARD_GRAVITY, Adam4017PSim, Adam4024Sim, Dgt1sSim, ModbusModule, Scale
from sim_devices.modbus_host import ModbusHost, SimBus
from sim_devices.transport import Faults, Line, PtyDevice, TwinTimer

T7_PORTS = (502, 702)  # the T7's own Modbus TCP and stream ports (T-Series Datasheet; ljm_constants STREAM_AUTO_TARGET)
UNPRIVILEGED_OFFSET = 10000  # where binding below 1024 is refused: 502/702 → 10502/10702
LINRS_TURNAROUND_S = 1e-3  # LinMot drive: telegram received → response [assumed]
PLANT_TICK_S = 0.02  # wall clock: the background thread advances the plant this often
Timing = Literal["real", "none"]


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
    timing: Timing | None = None
    daq_ports: tuple[int, int] = (0, 0)  # the T7 twin's (Modbus, stream) ports; 0: ephemeral; T7_PORTS: the T7's own
    clock: Clock = field(init=False)
    plant: Plant = field(init=False)
    twins: dict[str, object] = field(init=False, default_factory=dict)
    faults: dict[str, Faults] = field(init=False, default_factory=dict)
    _serial: dict[str, PtyDevice] = field(init=False, default_factory=dict)
    _modbus: ModbusHost | None = field(init=False, default=None)
    _daq_ports: tuple[int, int] = field(init=False, default=(0, 0))

    lines: dict[str, Line] = field(init=False, default_factory=dict)
    _ticker: threading.Thread | None = field(init=False, default=None)
    _stop_ticker: threading.Event = field(init=False, default_factory=threading.Event)

    def __post_init__(self) -> None:
        rig = self.rig
        self.clock = VirtualClock() if self.virtual else WallClock()
        if self.timing is None:
            self.timing = "none" if self.virtual else "real"
        self.plant = plant_for(rig, self.clock)
        self.replay: ReplayPlant | None = None
        if rig.simulation.replay is not None:
            self._start_replay(rig.simulation.replay)

    def _start_replay(self, path: str) -> None:
        """The plant replaced by a record's values (:mod:`bench.runtime.replay`); the twins' own noise off (the
        record has its own). Refused when the record lacks a stream one of the rig's twins serves."""
        rig = self.rig
        needs = {"laser": "laser twin"} if rig.laser is not None else {}
        if rig.amplifier is not None:
            needs["amplifier"] = "amplifier's monitors"
        if rig.load_cell is not None or (rig.daq is not None and rig.daq.force_ain is not None):
            needs["load_cell"] = "load cell"
        if rig.motor is not None:
            needs["motor"] = "motor drive"
        recording = Recording(path)
        try:
            check_fits(recording, needs)
        except ReplayError:
            recording.close()
            raise
        self.rig = rig.model_copy(update={"simulation": rig.simulation.model_copy(update={"noise": False})})
        self.replay = ReplayPlant(self.clock, recording, self.plant)
        self.plant = self.replay

    def start(self) -> dict[str, Endpoint]:
        """Start every twin; returns the endpoints by role (serial instruments) or bus name (Modbus)."""
        rig, sim = self.rig, self.rig.simulation
        self.plant.warm_up()  # before any twin answers: no compile inside a reply
        if rig.laser is not None:
            head = LaserHead(offset_mm=rig.laser.offset_mm, sign=rig.laser.sign, range_mm=rig.laser.range_mm)
            twin = KeyenceLKGSim(self.plant, self.clock, model=rig.laser.model, head=head,
                                 capacity=rig.laser.storage_points, seed=sim.seed, outs=max(1, rig.laser.out),
                                 head_model=rig.laser.head, averaging=rig.laser.averaging, noise=sim.noise)
            self._serve_serial("laser", twin, rig.laser.baudrate, LKG_TURNAROUND_S)
        if rig.motor is not None:
            m = rig.motor
            stroke = (min(m.travel_m[0], 0.0), max(m.travel_m[1], 0.12))
            self._serve_serial("motor", LinMotDriveSim(self.plant, self.clock, drive_id=m.drive_id, stroke=stroke,
                                                       checksum=m.checksum), m.baudrate, LINRS_TURNAROUND_S)
        if rig.daq is not None:
            self._start_daq()
        buses: dict[str, list[ModbusModule]] = {}
        if (a := rig.amplifier) is not None and a.drive == "adam":
            trek = amplifier_spec(self.rig)
            ao = Adam4024Sim(a.ao_unit, self.plant, self.clock, amplifier_channel=a.ao_channel,
                             scale=Scale(bits=a.ao_bits, raw_format=a.raw_format), watchdog_s=a.comm_watchdog_s)
            ai = Adam4017PSim(a.ai_unit, self.plant, self.clock, vmon_ratio=trek.vmon_ratio,
                              imon_ratio=trek.imon_ratio, vmon_channel=a.vmon_channel,
                              imon_channel=a.imon_channel, scale=Scale(bits=a.ai_bits, raw_format=a.raw_format),
                              seed=sim.seed + 1, noise_volts=0.5e-3 if sim.noise else 0.0)
            self.twins["amplifier AO"], self.twins["amplifier AI"] = ao, ai
            buses.setdefault(a.bus, []).extend([ao, ai])
        if (c := rig.load_cell) is not None:
            cell = Dgt1sSim(c.unit, self.plant, self.clock, division=c.division_kg, capacity=c.capacity_kg,
                            seed=sim.seed + 2)
            cell.noise = load_cell_noise_kg(cell.rate) if sim.noise else 0.0
            self.twins["load_cell"] = cell
            buses.setdefault(c.bus, []).append(cell)
        if buses:
            sim_buses = []
            for name, devices in buses.items():
                self.faults[name] = Faults(latency=sim.latency_s, clock=self.clock.now)
                bus = SimBus(name, devices, transport=sim.modbus_transport, baudrate=rig.buses[name].baudrate,
                             faults=self.faults[name], clock=self.clock, timing=self.timing == "real")
                assert bus.line is not None
                self.lines[name] = bus.line
                sim_buses.append(bus)
            self._modbus = ModbusHost(sim_buses)
            self._modbus.start()
        if not self.virtual:
            self._stop_ticker.clear()
            self._ticker = threading.Thread(target=self._keep_up, name="sim-plant", daemon=True)
            self._ticker.start()
        return self.endpoints()

    def _keep_up(self) -> None:
        """Wall clock: keep the plant at the present, so no request pays for integrating idle time."""
        while not self._stop_ticker.wait(PLANT_TICK_S):
            self.plant.advance_to(self.clock.now())

    def _start_daq(self) -> None:
        """The T7 twin: DAC → conditioning → amplifier input; AINs wired to the plant's observables."""
        from sim_devices.labjack_t7 import Conditioning, Signal

        d, rig, trek = self.rig.daq, self.rig, amplifier_spec(self.rig)
        assert d is not None
        noise = rig.simulation.noise
        # the monitors' noise and errors are the plant's (PlantBlock.voltage/current); the sensors' own noise is
        # what the bridge amplifier and the LK-G's analog output add before the AIN (bench.core.noise)
        signals = {d.vmon_ain: Signal("voltage", 1.0 / trek.vmon_ratio),
                   d.imon_ain: Signal("current", 1.0 / trek.imon_ratio)}
        if d.force_ain is not None:
            cell_n = load_cell_noise_kg(d.scan_rate_Hz) * STANDARD_GRAVITY if noise else 0.0  # N rms at the scan rate
            signals[d.force_ain] = Signal("force", 1.0 / d.force_N_per_V, -d.force_offset_N / d.force_N_per_V,
                                          noise=cell_n / d.force_N_per_V)
        if d.laser_ain is not None:  # the head reads sign·(specimen coordinate) + offset (as the serial twin)
            sign, offset = (rig.laser.sign, rig.laser.offset_mm * 1e-3) if rig.laser else (1, 0.0)
            head_n = lkg_noise_mm(rig.laser.head, rig.laser.averaging) * 1e-3 if rig.laser and noise else 0.0
            signals[d.laser_ain] = Signal("displacement", sign / d.laser_m_per_V,
                                          (offset - d.laser_offset_m) / d.laser_m_per_V, noise=head_n / d.laser_m_per_V)
        self.faults["daq"] = Faults(latency=rig.simulation.latency_s, clock=self.clock.now)
        cond = Conditioning(d.drive_gain, d.drive_offset_V, corner_Hz=d.drive_filter_Hz)
        def make() -> LabJackT7Sim:
            return LabJackT7Sim(self.plant, self.clock, dac=d.dac, conditioning=cond, signals=signals,
                                seed=rig.simulation.seed + 3, faults=self.faults["daq"],
                                noise=noise)  # [simulation] noise: the T7's own AIN noise per range, resolution index

        twin = self._start_t7(make)
        self._daq_ports = twin.port, twin.stream_port
        self.twins["daq"] = twin

    def _start_t7(self, make: Callable[[], LabJackT7Sim]) -> LabJackT7Sim:
        """A T7 twin serving on ``daq_ports``; ports below 1024 that this process may not bind (no root, no
        CAP_NET_BIND_SERVICE) move up by :data:`UNPRIVILEGED_OFFSET`, as the endpoint table then shows."""
        port, stream = self.daq_ports
        twin = make()
        try:
            twin.start(port=port, stream_port=stream)
            return twin
        except RuntimeError as exc:
            twin.stop()
            if not isinstance(exc.__cause__, PermissionError) or not 0 < min(port or 1024, stream or 1024) < 1024:
                raise
        twin = make()
        twin.start(port=port + UNPRIVILEGED_OFFSET if 0 < port < 1024 else port,
                   stream_port=stream + UNPRIVILEGED_OFFSET if 0 < stream < 1024 else stream)
        return twin

    def _serve_serial(self, role: str, twin: Callable[[bytes], bytes], baud: float, turnaround: float) -> None:
        self.faults[role] = Faults(latency=self.rig.simulation.latency_s, clock=self.clock.now)
        self.twins[role] = twin
        self.lines[role] = Line(self.clock, baud if self.timing == "real" else None, turnaround=turnaround)
        self._serial[role] = PtyDevice(twin, role, self.faults[role], self.lines[role]).start()

    @property
    def wire_time(self) -> bool:
        """Whether the twins' serial lines and buses take their wire time ("real" timing). The drivers are told
        (:func:`bench.runtime.instruments.build_instruments`): they stamp a polled reading at the start of its reply,
        its arrival less its wire time — at pty speed ("none") a reply arrives the moment it is made, and a stamp
        moved back by a wire time that never passed would be early by that much."""
        return self.timing == "real"

    def faults_of(self, name: str) -> Faults:
        """The :class:`Faults` of the link serving ``name``: a serial role (``laser``, ``motor``), a bus name
        (``io``), ``daq``, or a Modbus role (``amplifier``, ``load_cell``: its bus; the amplifier of a
        hardware-timed rig: the DAQ). Available once started."""
        rig = self.rig
        amp = rig.amplifier
        bus = {"amplifier": ("daq" if amp.drive == "daq" else amp.bus) if amp else None,
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

    def twin_errors(self) -> list[str]:
        """Exceptions a twin raised while serving (a twin must answer or ignore any bytes, never die)."""
        out = [f"{role}: {dev.error!r}" for role, dev in self._serial.items() if dev.error is not None]
        out += [f"{role}: twin thread stopped" for role, dev in self._serial.items()
                if dev.error is None and not dev.alive]
        if self._modbus is not None:
            out += [f"bus {b.name}: {b.pty.error!r}" for b in self._modbus.buses if b.pty is not None and b.pty.error]
        daq = self.twins.get("daq")
        out += [f"daq: {e!r}" for e in getattr(daq, "errors", [])]
        return out

    def reply_timers(self) -> dict[str, TwinTimer]:
        """Virtual time: a :class:`TwinTimer` per link (role, bus name, "daq"), for
        :func:`bench.runtime.instruments.build_instruments` — waits for a reply end on what the twin did with the
        request, never on the host's speed. Wall clock: none (the drivers' timeouts are real time, as on hardware).
        The T7 twin then pumps on demand (:meth:`LabJackT7Sim.on_demand`): when its link waits, not at every move
        of the clock (the other links' waits move it too)."""
        if not isinstance(self.clock, VirtualClock):
            return {}
        daq = self.twins.get("daq")
        return {name: TwinTimer(faults, self.clock,
                                waiting=daq.on_demand() if name == "daq" and isinstance(daq, LabJackT7Sim) else None)
                for name, faults in self.faults.items()}

    def port_map(self) -> dict[str, str]:
        """Role / bus name → port, for :func:`bench.runtime.instruments.build_instruments`."""
        return {name: ep.address for name, ep in self.endpoints().items()}

    def stop(self) -> None:
        """Stop every twin and close the ports (and a replayed record)."""
        self._stop_ticker.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2)
            self._ticker = None
        if (daq := self.twins.pop("daq", None)) is not None:
            from sim_devices.labjack_t7 import LabJackT7Sim  # loaded already: the twin was built from it

            assert isinstance(daq, LabJackT7Sim)
            daq.stop()
        for dev in self._serial.values():
            dev.stop()
        self._serial.clear()
        if isinstance(drive := self.twins.get("motor"), LinMotDriveSim):
            drive.close()  # the drive's own cycle (a thread on the wall clock)
        if self._modbus is not None:
            self._modbus.stop()
            self._modbus = None
        if self.replay is not None:
            self.replay.recording.close()

    def __enter__(self) -> SimRig:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
