"""Rig files (TOML): which instrument on which port/address, calibration, limits, specimen.

A rig is *simulated* (``simulated = true``: ``bench`` starts the simulated twins and points the drivers at
them; the ports in the file are ignored) or real (the drivers open the ports given). Validation is done
with pydantic so that a malformed file is refused with one line naming the file and the field.
"""

from __future__ import annotations

import functools
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from bench.core.clock import Clock
from bench.core.monitor_chain import SAFE_TOUCH_V, T7_AIN, DaqInput, adam_4017p, safe_threshold_v, zero_band_v
from bench.core.noise import Realism
from bench.core.plant import TREK_DATASHEET, AmplifierSpec, HVStage, Plant
from bench.models.lozenge import LozengeParams, MaxwellBranch
from bench.models.membrane import MembraneParams
from bench.quantity import parse_quantity, refuse_bool
from bench.tomlfile import first_error, one_line, read_toml, type_hint

STANDARD_GRAVITY_M_PER_S2 = 9.80665  # CGPM 1901 (the load cell's kg → N)
# LK-G data storage per OUT [points] when the rig file does not say: not from a manual page we could read
# (assumed; the LK-G5000 figure is the largest count the 6-digit setting carries). Set storage_points to the
# controller's figure on a real rig.
LKG_STORAGE_POINTS = {"LK-G3000": 65_536, "LK-G5000": 999_999}
# The LK-G stores every sampling period (SW,CA) × storage cycle (SW,EB): the settings the driver chooses among
# (drivers/keyence.py SAMPLING_US, STORAGE_CYCLES; tests/test_rig.py checks that they agree), so a requested rate is
# stored at the nearest interval these make (800 S/s at 1000: 1 ms)
LKG_SAMPLING_US = (20, 50, 100, 200, 500, 1000)
LKG_STORAGE_CYCLES = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
# Analog inputs: the TREK monitors (ADAM-4017+ or T7 AIN) and the DAQ's load-cell input are read on the ±10 V range
# (drivers.adam.RawScale clips to ±10 V; bench.runtime.hardware_timed streams every AIN at range 10). A channel
# reads at most this, so a trip level at or above what it represents can never fire.
AIN_FULL_SCALE_V = 10.0
# The supervisor's output over-voltage trip (bench.runtime.safety.Supervisor.check_monitors): monitored |V| above
# factor × voltage limit + margin. Mirrored here so the rig can check the monitor channel reaches it
# (tests/test_rig_limits.py checks the supervisor against these figures).
MONITOR_TRIP_FACTOR = 1.02
MONITOR_TRIP_MARGIN_V = 50.0
# LinRS position registers: int32 counts of 0.1 µm (drivers/linmot.py), so a drive reports at most ±214.7 m.
LINRS_POSITION_SPAN_M = (2**31 - 1) * 1e-7


# a field name's unit suffix → (dimension, the field's unit per SI unit), longest first: "max_voltage_V = '8 kV'"
# is read as 8000 (the names that end in a ratio's unit, "_N_per_V" and "_m_per_V", take plain numbers only)
UNIT_SUFFIXES: tuple[tuple[str, tuple[str, float] | None], ...] = (
    ("_m_per_s2", ("acceleration", 1.0)), ("_V_per_m", ("field", 1.0)), ("_V_per_s", ("slew", 1.0)),
    ("_m_per_s", ("velocity", 1.0)), ("_N_per_V", None), ("_m_per_V", None), ("_Hz", ("frequency", 1.0)),
    ("_kg", ("mass", 1.0)), ("_mm", ("length", 1e3)), ("_m", ("length", 1.0)), ("_s", ("time", 1.0)),
    ("_V", ("voltage", 1.0)), ("_A", ("current", 1.0)), ("_N", ("force", 1.0)), ("_K", ("temperature", 1.0)))


def unit_of_name(name: str) -> tuple[str, float] | None:
    """(dimension, the field's unit per SI unit) of a field whose name ends in its unit (``timeout_s``,
    ``range_mm``); None for any other name."""
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), None)


def _in_unit_of_name(v: Any, name: str) -> Any:
    """A rig field's value written with a unit (``"8 kV"``, ``"250 ms"``, ``"25 °C"``; also each item of a pair
    such as ``stroke_m``) converted to the unit its name gives, as protocol files allow; a plain number (or a string
    of one) is in that unit, as before. ValueError names what is wrong (the field's name goes with it)."""
    if isinstance(v, list | tuple):
        return type(v)(_in_unit_of_name(x, name) for x in v)
    unit = unit_of_name(name)
    if not isinstance(v, str) or unit is None:
        return v  # numbers (and anything else) go to the field's own validation
    try:
        return float(v)
    except ValueError:
        return parse_quantity(v, unit[0])[0] * unit[1]


class _Strict(BaseModel):
    """Base of every rig table: unknown keys refused, immutable, every float finite (no nan / inf); a field whose
    name ends in its unit takes a quantity with any unit of its dimension (:func:`_in_unit_of_name`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _units(cls, v: Any, info: ValidationInfo) -> Any:
        name = info.field_name or ""
        if name in cls.model_fields:  # pydantic reads true as 1 (shutdown_ramp_s = true was a 1-s ramp)
            refuse_bool(v, cls.model_fields[name].annotation)
        return _in_unit_of_name(v, name)


class BusConfig(_Strict):
    """A Modbus bus: serial device / pyserial URL (RTU) or ``tcp://host:port``. On tcp:// the peer is either a
    Modbus TCP device or a TCP/RTU gateway to RS-485 modules (the ADAM-4000 and DGT1S speak RS-485 only): give the
    gateway's line rate as ``gateway_baudrate`` and a reading's stamp leaves out its reply's wire time on that line;
    without it nothing is taken off (a simulated rig's twins serve the bus as such a gateway at ``baudrate``)."""

    port: str = Field("sim", min_length=1)
    baudrate: int = Field(19200, gt=0)
    gateway_baudrate: int | None = Field(None, gt=0, description="tcp:// only: the RS-485 line behind a gateway")
    timeout_s: float = Field(0.5, gt=0, le=30)
    retries: int = Field(1, ge=0, le=5)


class AmplifierConfig(_Strict):
    """TREK amplifier on an ADAM-4024 (set-point) and an ADAM-4017+ (monitors) on one bus, or (``drive = "daq"``)
    on the rig's hardware-timed DAQ: input from a DAC through the conditioning stage, monitors on AINs."""

    model: Literal["10/10B-HS", "10/40A-HS"] = "10/10B-HS"
    drive: Literal["adam", "daq"] = "adam"
    bus: str = Field("io", min_length=1, description="name of a table under [buses]")
    ao_unit: int = Field(1, ge=1, le=247)
    ao_channel: int = Field(0, ge=0, le=3)
    ai_unit: int = Field(2, ge=1, le=247)
    vmon_channel: int = Field(0, ge=0, le=7)
    imon_channel: int = Field(1, ge=0, le=7)
    max_voltage_V: float = Field(8000.0, gt=0, le=10_000)
    slew_limit_V_per_s: float = Field(1e6, gt=0)
    vmon_ratio: float | None = Field(None, gt=0, description="V of output per V of monitor (default: model)")
    imon_ratio: float | None = Field(None, gt=0, description="A of output per V of monitor (default: model)")
    ao_bits: int = Field(12, ge=8, le=16)
    ai_bits: int = Field(16, ge=8, le=16)
    raw_format: Literal["offset", "twos"] = "offset"
    comm_watchdog_s: float | None = Field(1.0, gt=0, le=60, description="ADAM-4024 communication safety: output "
                                          "to 0 V after this long without a request (configure the module to match)")


class LaserConfig(_Strict):
    """Keyence LK-G controller on a serial port."""

    model: Literal["LK-G3000", "LK-G5000"] = "LK-G3000"
    port: str = Field("sim", min_length=1)
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0, le=30)
    out: int = Field(1, ge=1, le=12)
    storage_points: int | None = Field(None, ge=1, le=999_999, description="default: the controller's capacity")
    offset_mm: float = 0.0
    sign: Literal[-1, 1] = 1
    range_mm: float = Field(40.0, gt=0)
    head: Literal["LK-G32", "LK-G82", "LK-G152", "LK-G402"] = Field("LK-G152", description="sensor head (its "
                                                                     "repeatability sets the simulated noise)")
    averaging: Literal[1, 4, 16, 64, 256, 1024, 4096, 16384, 65536, 262144] = Field(
        64, description="controller averaging (SW,OC) the rig runs with: the head's noise scales as 1/√N")

    @property
    def capacity(self) -> int:
        """Points the controller stores per OUT for a run: storage_points, or the model's assumed capacity — the
        rig file is where the application learns instrument facts, so protocol compilation needs no driver."""
        return self.storage_points or LKG_STORAGE_POINTS[self.model]

    @staticmethod
    @functools.lru_cache(maxsize=256)  # asked once per storing step: 100,000 steps scanned 60 settings each (20 s)
    def stored_Hz(requested_Hz: float) -> float:
        """The rate [S/s] the controller stores at when ``requested_Hz`` is asked: the sampling period × storage cycle
        nearest to 1/``requested_Hz`` (among equal ones the smallest cycle), as the driver sets it."""
        interval = 1.0 / requested_Hz
        sampling, cycle = min(((s, c) for s in LKG_SAMPLING_US for c in LKG_STORAGE_CYCLES),
                              key=lambda sc: (abs(sc[0] * sc[1] * 1e-6 - interval), sc[1]))
        return 1e6 / (sampling * cycle)

    @staticmethod
    def storable_at_most(rate_Hz: float) -> float:
        """The fastest rate [S/s] the controller stores at that is at most ``rate_Hz`` (0: none is)."""
        rates = [1e6 / (s * c) for s in LKG_SAMPLING_US for c in LKG_STORAGE_CYCLES]
        return max((r for r in rates if r <= rate_Hz * (1 + 1e-12)), default=0.0)


class MotorConfig(_Strict):
    """LinMot drive on a LinRS serial link."""

    port: str = Field("sim", min_length=1)
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0, le=30)
    drive_id: int = Field(0x11, ge=0, le=255)
    checksum: bool = Field(False, description="LinRS checksum (drive UPID 2080h) — detects corrupted data bytes")
    travel_m: tuple[float, float] = (0.0, 0.09)
    stroke_m: tuple[float, float] = Field((0.0, 0.12), description="positions the drive can reach (LinMot "
                                          "P01-37x120F: 0–120 mm); travel_m must lie within it")
    max_velocity_m_per_s: float = Field(1.0, gt=0, le=10)
    max_acceleration_m_per_s2: float = Field(20.0, gt=0, le=500)

    @model_validator(mode="after")
    def _travel(self) -> MotorConfig:
        if not self.travel_m[0] < self.travel_m[1]:
            raise ValueError(f"travel_m must be increasing, got {list(self.travel_m)}")
        (lo, hi), (s_lo, s_hi) = self.travel_m, self.stroke_m
        if not s_lo < s_hi:
            raise ValueError(f"stroke_m must be increasing, got {list(self.stroke_m)}")
        if max(abs(s_lo), abs(s_hi)) > LINRS_POSITION_SPAN_M:
            raise ValueError(f"stroke_m {list(self.stroke_m)} m lies beyond the ±{LINRS_POSITION_SPAN_M:.1f} m a LinRS "
                             "drive reports (int32 of 0.1 µm): travel limits there could never fire")
        if lo < s_lo or hi > s_hi:
            raise ValueError(f"travel_m [{lo:g}, {hi:g}] m lies outside the drive's stroke_m [{s_lo:g}, {s_hi:g}] m")
        return self


class LoadCellConfig(_Strict):
    """Load cell through a DGT1S weight transmitter on a Modbus bus."""

    bus: str = Field("scale", min_length=1, description="name of a table under [buses]")
    unit: int = Field(1, ge=1, le=247)
    division_kg: float = Field(0.001, gt=0)
    capacity_kg: float = Field(5.0, gt=0)

    @model_validator(mode="after")
    def _division(self) -> LoadCellConfig:
        if self.division_kg >= self.capacity_kg:
            raise ValueError(f"division_kg {self.division_kg:g} must be below capacity_kg {self.capacity_kg:g}")
        return self


class LsdeaConfig(_Strict):
    """LS-DEA prototype and how it is mounted on the rig."""

    prototype: Literal[1, 2, 3] = 1
    configuration: Literal["motor", "blocked", "hung"] = "motor"
    hung_mass_kg: float = Field(0.0, ge=0, le=2)
    x_at_motor_zero_m: float = Field(0.05, gt=0.0, lt=0.24, description="aperture x when the motor is at 0")
    motor_sign: Literal[-1, 1] = 1
    blocked_position_m: float = Field(0.1, gt=0.0, lt=0.24)


class MembraneModelConfig(_Strict):
    """Fitted (or alternative) rheology of the thesis membrane: Gent spring and Maxwell units, each unit's dashpot
    given as a relaxation time ``tau`` [s] (what ``bench fit`` reports and writes) or a viscosity ``eta`` [Pa·s]
    (η = μτ)."""

    mu0: float = Field(gt=0, description="Pa")
    J0: float = Field(gt=0)
    mu: list[float] = Field(description="Pa")
    J: list[float]
    tau: list[float] | None = Field(None, description="s")
    eta: list[float] | None = Field(None, description="Pa·s")

    @model_validator(mode="after")
    def _lengths(self) -> MembraneModelConfig:
        if (self.tau is None) == (self.eta is None):
            raise ValueError("give each Maxwell unit's tau [s] or its eta [Pa·s], not both")
        dashpots = self.tau if self.tau is not None else self.eta or []
        if not len(self.mu) == len(self.J) == len(dashpots) or min([*self.mu, *self.J, *dashpots], default=1) <= 0:
            raise ValueError(f"mu, J and {'tau' if self.tau is not None else 'eta'} need one positive value per "
                             "Maxwell unit")
        return self

    def viscosities(self) -> tuple[float, ...]:
        """η_i [Pa·s] of the units (μ_i τ_i where the file gives τ)."""
        if self.tau is not None:
            return tuple(m * t for m, t in zip(self.mu, self.tau, strict=True))
        return tuple(self.eta or ())


class LsdeaModelConfig(_Strict):
    """Fitted (or alternative) material of the LS-DEA: Gent–Gent, Maxwell branches, lumped damper."""

    mu: float = Field(gt=0, description="Pa")
    Jm: float = Field(gt=0)
    C2: float = Field(ge=0, description="Pa")
    branch_mu: list[float] = Field(default_factory=list, description="Pa")
    branch_tau: list[float] = Field(default_factory=list, description="s")
    damping: float = Field(1.5, ge=0, description="N·s/m")

    @model_validator(mode="after")
    def _branches(self) -> LsdeaModelConfig:
        if len(self.branch_mu) != len(self.branch_tau):
            raise ValueError("branch_mu and branch_tau need the same length")
        if min([*self.branch_mu, *self.branch_tau], default=1) <= 0:  # as the membrane's units (physics.md §2.4)
            raise ValueError("branch_mu and branch_tau need one positive value per Maxwell branch")
        return self


class SpecimenConfig(_Strict):
    """The specimen on the rig (the simulated plant; for a real rig, metadata and safety limits)."""

    kind: Literal["membrane", "lsdea"] = "membrane"
    temperature_K: float = Field(296.0, gt=150, lt=450)
    displacement_length_m: float = Field(0.03, gt=0, description="membrane: u = L_d (λ − λ_pre)")
    breakdown_field_V_per_m: float = Field(100e6, gt=0, description="membrane: true-field breakdown")
    electrostriction: Literal["corrected", "thesis"] = "corrected"
    lsdea: LsdeaConfig = LsdeaConfig()
    membrane_model: MembraneModelConfig | None = None
    lsdea_model: LsdeaModelConfig | None = None

    def membrane(self) -> MembraneParams:
        """Model A parameters for this specimen (thesis Table 4.4, or ``membrane_model`` if given)."""
        p = MembraneParams(L_d=self.displacement_length_m, breakdown_field=self.breakdown_field_V_per_m,
                           electrostriction=self.electrostriction)
        m = self.membrane_model
        return p if m is None else p.with_units(m.mu0, m.J0, tuple(m.mu), tuple(m.J), m.viscosities())

    def lozenge(self, prototype: int | None = None, hung_mass: float | None = None) -> LozengeParams:
        """Model B parameters for this specimen (Table 1 + VE-A, or ``lsdea_model`` if given)."""
        p = LozengeParams.prototype(prototype or self.lsdea.prototype,
                                    hung_mass=self.lsdea.hung_mass_kg if hung_mass is None else hung_mass)
        m = self.lsdea_model
        if m is None:
            return p
        material = replace(p.material, mu=m.mu, Jm=m.Jm, C2=m.C2)
        branches = tuple(MaxwellBranch(mu, tau) for mu, tau in zip(m.branch_mu, m.branch_tau, strict=True))
        return replace(p, material=material, branches=branches, damping=m.damping)


class LimitsConfig(_Strict):
    """Safety limits enforced by the supervisor (the amplifier's own software limit is separate)."""

    max_voltage_V: float = Field(8000.0, gt=0, le=10_000)
    max_field_V_per_m: float | None = Field(None, gt=0, description="default: the specimen's breakdown field")
    max_current_A: float = Field(5e-3, gt=0)
    max_force_N: float = Field(20.0, gt=0)
    breakdown_margin: float = Field(1.1, ge=1.0, le=10.0, description="trip when E × margin > E_B")
    shutdown_ramp_s: float = Field(0.25, gt=0, le=10.0, description="voltage ramp to 0 V on every exit")
    travel_tolerance_m: float = Field(0.001, ge=0, description="motor beyond its travel by more: trip")


class InterlockConfig(_Strict):
    """``[interlock]``: faults that latch the output at 0 V (bench/runtime/interlock.py; README "Interlock").

    The output is verified against what was commanded: a measured voltage outside the commanded value's band
    (``output_tolerance_V`` + ``output_tolerance_rel`` × |commanded|, over the commanded values of the last
    ``output_lag_s``) for ``output_mismatch_s`` on the scan clock — or in two monitor readings in a row on a
    software-timed rig — is a fault. The defaults come from the TREK HS datasheets (gain 1000 V/V; slew > 700
    V/µs and bandwidth > 19.5 kHz, so the output follows a 10-kHz drive within one scan) and the monitors'
    conversion: the ADAM-4017+ converts at 10 S/s, so a polled reading may be up to ~0.3 s old."""

    host_stall_s: float | None = Field(None, gt=0, le=60, description="the set-point module unheard from the host "
                                       "for longer while the output is on: latch (default: 0.8 × its watchdog, "
                                       "or 1 s without one)")
    output_tolerance_V: float = Field(100.0, gt=0, le=2000, description="absolute band around the commanded "
                                      "voltage (1 % of the 10-kV full scale: monitor and conditioning tolerances)")
    output_tolerance_rel: float = Field(0.05, ge=0, le=0.5, description="relative band, × |commanded|")
    output_lag_s: float | None = Field(None, ge=0, le=5, description="how far back a commanded value may still "
                                       "be what the monitor shows (default: 1 ms on a DAQ rig, 0.3 s polled)")
    output_mismatch_s: float = Field(0.02, gt=0, le=5, description="a hardware-timed mismatch must last this long")
    motor_tolerance_m: float = Field(0.002, gt=0, le=0.05, description="motor position off the go-tos' trapezoid "
                                     "by more (after the lag window) in two readings in a row: a fault")
    motor_lag_s: float = Field(0.05, ge=0, le=2, description="how far back a position of the planned motion may "
                               "still be where the encoder is (the drive's following delay and the telegram's)")


class SimulationConfig(_Strict):
    """Options of the simulated twins."""

    seed: int = Field(1, ge=0)
    latency_s: float = Field(0.0, ge=0, le=1.0, description="extra reply latency of serial twins (wall time)")
    modbus_transport: Literal["rtu", "rtu-socket", "tcp"] = Field(
        "rtu", description="rtu: on a pty; rtu-socket: RTU frames over loopback TCP; tcp: Modbus TCP")
    noise: bool = Field(True, description="datasheet noise and monitor gain/offset errors of the twins (seeded by "
                        "seed); false: ideal readings for golden tests (the amplifier's and monitors' dynamics stay)")
    replay: str | None = Field(None, description="a run file (HDF5) whose measured signals the twins serve instead "
                               "of the model's, on the record's time base, noise off (bench.runtime.replay); "
                               "relative to the rig file")
    wire_time: bool = Field(True, description="false: the rig's ports are twins served at pty speed (`bench sim "
                            "serve --no-wire-time --write-rig` writes it): no wire time passes on them, so the "
                            "readings' stamps take none off")


class DaqConfig(_Strict):
    """Hardware-timed multifunction DAQ (LabJack T7 on Ethernet): one scan clock for the amplifier drive (stream-out
    on a DAC through the rig's conditioning stage) and every analog input (TREK monitors, load-cell bridge
    amplifier, laser analog output)."""

    model: Literal["T7"] = "T7"
    host: str = Field("sim", min_length=1)
    port: int = Field(502, ge=1, le=65535)
    stream_port: int = Field(702, ge=1, le=65535)
    timeout_s: float = Field(0.5, gt=0, le=30)
    scan_rate_Hz: float = Field(10_000.0, ge=100.0, le=20_000.0, description="one scan clock for every channel")
    dac: int = Field(0, ge=0, le=1, description="DAC driving the amplifier's analog input (0–5 V)")
    drive_gain: float = Field(4.0, gt=0, le=100, description="amplifier input [V] per DAC volt (conditioning stage)")
    drive_offset_V: float = Field(-10.0, ge=-50, le=50, description="amplifier input at DAC 0 V [V]")
    drive_filter_Hz: float | None = Field(None, gt=0, le=1e5, description="corner of the conditioning stage's "
                                          "first-order reconstruction low-pass (None: none); the engine "
                                          "pre-compensates its lag, so the amplifier follows the protocol's waveform")
    vmon_ain: int = Field(0, ge=0, le=13)
    imon_ain: int = Field(1, ge=0, le=13)
    force_ain: int | None = Field(None, ge=0, le=13, description="load-cell bridge amplifier output")
    force_N_per_V: float = Field(1.0, gt=0, le=1e4)
    force_offset_N: float = Field(0.0, ge=-1e4, le=1e4)
    force_capacity_N: float | None = Field(None, gt=0, le=1e5, description="the load cell's rated capacity [N] "
                                           "(limits.max_force_N must not exceed it)")
    laser_ain: int | None = Field(None, ge=0, le=13, description="laser controller's analog output")
    laser_m_per_V: float = Field(0.004, gt=0, le=1.0, description="laser head reading [m] per volt")
    laser_offset_m: float = Field(0.0, ge=-1.0, le=1.0, description="laser head reading at 0 V [m]")
    watchdog_s: float | None = Field(1.0, ge=1, le=60, multiple_of=1, description="T7 watchdog (whole seconds, "
                                     "WATCHDOG_TIMEOUT_S_DEFAULT): the DACs go to the 0-V code after this long "
                                     "without a request; the driver configures the device on connect")

    @model_validator(mode="after")
    def _distinct(self) -> DaqConfig:
        used = [a for a in (self.vmon_ain, self.imon_ain, self.force_ain, self.laser_ain) if a is not None]
        if len(set(used)) != len(used):
            raise ValueError(f"analog inputs must differ (vmon {self.vmon_ain}, imon {self.imon_ain}, "
                             f"force {self.force_ain}, laser {self.laser_ain})")
        zero = -self.drive_offset_V / self.drive_gain
        if not 0.0 <= zero <= 5.0:
            raise ValueError(f"the conditioning stage cannot produce 0 V at the amplifier input "
                             f"(DAC {zero:.3g} V needed, the DAC spans 0–5 V)")
        return self

    def force_span(self) -> float | None:
        """Largest |force| [N] the load-cell input reports in both directions (tension and compression) on its
        ±10 V range, or None without a load-cell input."""
        if self.force_ain is None:
            return None
        return AIN_FULL_SCALE_V * self.force_N_per_V - abs(self.force_offset_N)

    def input_range(self) -> tuple[float, float]:
        """Amplifier input [V] the DAC (0–5 V) can produce through the conditioning stage."""
        return self.drive_offset_V, self.drive_offset_V + 5.0 * self.drive_gain


MAX_RIG_NAME = 100  # characters of a rig's name


class RigConfig(_Strict):
    """A whole rig file."""

    name: str = Field(max_length=MAX_RIG_NAME, description="names the rig in messages, latches and file names")
    description: str = ""
    simulated: bool = True
    specimen: SpecimenConfig = SpecimenConfig()
    limits: LimitsConfig = LimitsConfig()
    interlock: InterlockConfig = InterlockConfig()
    simulation: SimulationConfig = SimulationConfig()
    buses: dict[str, BusConfig] = Field(default_factory=dict)
    amplifier: AmplifierConfig | None = None
    laser: LaserConfig | None = None
    motor: MotorConfig | None = None
    load_cell: LoadCellConfig | None = None
    daq: DaqConfig | None = None

    def drive_path(self) -> str | None:
        """The hardware that sets the amplifier's input on a real rig (set-point module port, unit and channel, or
        the T7's address and DAC), which a latch holds whatever the rig file is named; None on a simulated rig
        (its twins are its own) or without an amplifier."""
        amp = self.amplifier
        if self.simulated or amp is None:
            return None
        if amp.drive == "daq":
            return f"T7 {self.daq.host}:{self.daq.port} DAC{self.daq.dac}" if self.daq else None
        bus = self.buses.get(amp.bus)
        return f"{bus.port if bus else amp.bus} unit {amp.ao_unit} channel {amp.ao_channel}"

    @field_validator("name")
    @classmethod
    def _printable_name(cls, v: str) -> str:
        """One line of printable text: a NUL in it ended a manual session with "embedded null byte", naming nothing
        (an outside tester)."""
        if not v.strip():
            raise ValueError("empty: give the rig a name")
        if not v.isprintable():
            raise ValueError("one line of printable text (no newline, tab, NUL or other control character)")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> RigConfig:
        if self.amplifier and self.amplifier.drive == "daq":
            self._check_daq_drive(self.amplifier)
        adam = self.amplifier if self.amplifier and self.amplifier.drive == "adam" else None
        for role, bus in (("amplifier", adam.bus if adam else None),
                          ("load_cell", self.load_cell.bus if self.load_cell else None)):
            if bus is not None and bus not in self.buses:  # "" too: it names no bus
                raise ValueError(f"{role}.bus {bus!r} is not defined under [buses]")
        if self.amplifier and self.amplifier.vmon_channel == self.amplifier.imon_channel:
            raise ValueError("amplifier.vmon_channel and amplifier.imon_channel must differ")
        if self.amplifier and self.limits.max_voltage_V > self.amplifier.max_voltage_V:
            raise ValueError(f"limits.max_voltage_V {self.limits.max_voltage_V:g} exceeds "
                             f"amplifier.max_voltage_V {self.amplifier.max_voltage_V:g}")
        self._within_capability()
        if self.specimen.kind == "lsdea" and self.specimen.lsdea.configuration == "motor" and self.motor is None:
            raise ValueError("specimen.lsdea.configuration = 'motor' needs a [motor] section")
        if self.load_cell is not None and self.daq is not None and self.daq.force_ain is not None:
            # two force sources recording into one stream, one of them never supervised (a reviewer)
            raise ValueError(f"[load_cell] and daq.force_ain {self.daq.force_ain} both name the rig's load cell: "
                             "give one (a transmitter on a bus, or its bridge amplifier on a DAQ input)")
        if adam and adam.bus == (self.load_cell.bus if self.load_cell else None):
            au = {adam.ao_unit, adam.ai_unit}
            if self.load_cell and self.load_cell.unit in au:
                raise ValueError(f"load_cell.unit {self.load_cell.unit} collides with an amplifier module on the bus")
        return self

    def _check_daq_drive(self, amp: AmplifierConfig) -> None:
        """A DAQ-driven amplifier: the chain must produce every input the voltage limit allows."""
        if self.daq is None:
            raise ValueError("amplifier.drive = 'daq' needs a [daq] section")
        gain = 1000.0  # V/V: both TREK HS models (datasheets; drivers/trek.py)
        need = min(amp.max_voltage_V, self.limits.max_voltage_V) / gain
        lo, hi = self.daq.input_range()
        if lo > -need + 1e-9 or hi < need - 1e-9:
            raise ValueError(f"daq: DAC 0–5 V × drive_gain {self.daq.drive_gain:g} + drive_offset_V "
                             f"{self.daq.drive_offset_V:g} spans {lo:g}…{hi:g} V at the amplifier input, but "
                             f"±{need * gain:.0f} V needs ±{need:g} V")
        if max(abs(lo), abs(hi)) > 10.0 + 1e-9:
            raise ValueError(f"daq: the conditioning stage reaches {lo:g}…{hi:g} V, beyond the TREK input's ±10 V")

    def _within_capability(self) -> None:
        """Every limit within what the instrument can do and what its measuring channel can report: a trip level
        it cannot reach would never fire (tests/test_rig_limits.py: what "never" means for each limit)."""
        if self.amplifier is not None:
            self._amplifier_limits(self.amplifier)
        self._force_limits()
        self._field_limit()
        if self.motor is not None:
            self._travel_tolerance(self.motor)

    def _amplifier_limits(self, amp: AmplifierConfig) -> None:
        lim = self.limits
        trek = TREK_DATASHEET[amp.model]
        if amp.max_voltage_V > trek.max_output:
            raise ValueError(f"amplifier.max_voltage_V {amp.max_voltage_V:g} V exceeds the TREK "
                             f"{trek.model} output of {trek.max_output:g} V")
        if lim.max_current_A > trek.max_current:
            raise ValueError(f"limits.max_current_A {lim.max_current_A:g} A exceeds the {trek.max_current:g} A "
                             f"the TREK {trek.model} can deliver: the trip could never fire")
        imon = amp.imon_ratio or trek.imon_ratio
        i_span = AIN_FULL_SCALE_V * imon
        if lim.max_current_A >= i_span:
            raise ValueError(f"limits.max_current_A {lim.max_current_A:g} A is not below the {i_span:g} A the current "
                             f"monitor reads at full scale (±{AIN_FULL_SCALE_V:g} V × amplifier.imon_ratio {imon:g} "
                             "A/V): the trip could never fire")
        vmon = amp.vmon_ratio or trek.vmon_ratio
        v_span = min(AIN_FULL_SCALE_V * vmon, trek.max_output)
        v_lim = min(lim.max_voltage_V, amp.max_voltage_V)
        trip = MONITOR_TRIP_FACTOR * v_lim + MONITOR_TRIP_MARGIN_V
        if trip >= v_span:
            field = "limits.max_voltage_V" if lim.max_voltage_V <= amp.max_voltage_V else "amplifier.max_voltage_V"
            raise ValueError(f"{field} {v_lim:g} V: the output over-voltage trip at {MONITOR_TRIP_FACTOR:g} × "
                             f"{v_lim:g} + {MONITOR_TRIP_MARGIN_V:g} = {trip:.0f} V is not below the {v_span:.0f} V "
                             f"the voltage monitor reads (±{AIN_FULL_SCALE_V:g} V × amplifier.vmon_ratio {vmon:g} V/V, "
                             f"TREK output {trek.max_output:g} V): it could never fire")
        safe_monitor_v(self)  # a monitor chain too coarse to verify a safe output (ValueError, its reason)
        slew = HVStage().slew
        if amp.slew_limit_V_per_s > slew:
            raise ValueError(f"amplifier.slew_limit_V_per_s {amp.slew_limit_V_per_s:g} V/s exceeds the TREK "
                             f"{trek.model}'s own slew rate ({slew:g} V/s, datasheet > 700 V/µs): it could never bind")
        default = AmplifierConfig.model_fields["slew_limit_V_per_s"].default
        if amp.drive == "daq" and amp.slew_limit_V_per_s != default:
            raise ValueError(f"amplifier.slew_limit_V_per_s {amp.slew_limit_V_per_s:g} V/s is not applied with drive "
                             "= 'daq' (the DAQ plays the protocol's waveform on its scan clock): remove it")

    def _force_limits(self) -> None:
        f = self.limits.max_force_N
        if self.load_cell is not None:
            full_scale = self.load_cell.capacity_kg * STANDARD_GRAVITY_M_PER_S2
            if f > full_scale:
                raise ValueError(f"limits.max_force_N {f:g} N exceeds the load cell's capacity "
                                 f"load_cell.capacity_kg {self.load_cell.capacity_kg:g} kg = {full_scale:.4g} N")
        daq = self.daq
        span = daq.force_span() if daq is not None else None
        if daq is None or span is None:
            return
        if span <= 0:
            raise ValueError(f"daq.force_offset_N {daq.force_offset_N:g} N: the load-cell input (±{AIN_FULL_SCALE_V:g} "
                             f"V × daq.force_N_per_V {daq.force_N_per_V:g} N/V) cannot report both tension and "
                             "compression, so the force trip could not fire both ways")
        if f >= span:
            raise ValueError(f"limits.max_force_N {f:g} N is not below the ±{span:.4g} N the load-cell input reads at "
                             f"full scale (±{AIN_FULL_SCALE_V:g} V × daq.force_N_per_V {daq.force_N_per_V:g} N/V, "
                             f"daq.force_offset_N {daq.force_offset_N:g} N): the trip could never fire")
        if daq.force_capacity_N is not None and f > daq.force_capacity_N:
            raise ValueError(f"limits.max_force_N {f:g} N exceeds the load cell's rated capacity "
                             f"daq.force_capacity_N {daq.force_capacity_N:g} N")

    def _field_limit(self) -> None:
        cap, margin = self.limits.max_field_V_per_m, self.limits.breakdown_margin
        if cap is None:
            return
        spec = self.specimen
        if spec.kind == "membrane":
            e_b, source = spec.breakdown_field_V_per_m, "specimen.breakdown_field_V_per_m"
        else:
            e_b, source = max(_highest_breakdown(spec.lozenge(n)) for n in (1, 2, 3)), "the LS-DEA's E_B at any stretch"
        if cap >= e_b / margin:
            raise ValueError(f"limits.max_field_V_per_m {cap:g} V/m is not below the breakdown trip level "
                             f"{e_b / margin:.4g} V/m ({source} {e_b:.4g} V/m / limits.breakdown_margin {margin:g}): "
                             "that trip always fires first, this one never")

    def _travel_tolerance(self, m: MotorConfig) -> None:
        tol = self.limits.travel_tolerance_m
        (lo, hi), (s_lo, s_hi) = m.travel_m, m.stroke_m
        for end, gap in (("lower", lo - s_lo), ("upper", s_hi - hi)):
            if gap > 0 and tol >= gap:
                raise ValueError(f"limits.travel_tolerance_m {tol:g} m reaches the {end} end of motor.stroke_m "
                                 f"[{s_lo:g}, {s_hi:g}] m from travel_m [{lo:g}, {hi:g}] m: the travel trip could "
                                 f"never fire there")

    @property
    def instruments(self) -> list[str]:
        """Roles present on this rig."""
        return [r for r in ("amplifier", "laser", "motor", "load_cell", "daq") if getattr(self, r) is not None]


def _highest_breakdown(q: LozengeParams) -> float:
    """Highest E_B = E0 (λ1λ2)^(r/2) [V/m] of an LS-DEA over the apertures the supervisor's field estimate uses."""
    x = np.linspace(1.0001 * q.xp, 1.999 * q.l, 2001)
    y = np.sqrt(4.0 * q.l**2 - x**2)
    l1, l2 = q.lambda1p * x / q.xp, q.lambda2p * y / q.yp
    return float(np.max(q.material.E0 * (l1 * l2) ** (q.material.r / 2)))


class RigFileError(ValueError):
    """A rig file that cannot be read or is invalid (message: one line, naming file and field)."""

    def __init__(self, message: str) -> None:
        super().__init__(one_line(message))


def _first_error(path: Path, exc: ValidationError) -> str:
    err, suggestion = first_error(exc.errors(), RigConfig)
    loc = ".".join(str(x) for x in err["loc"])
    msg = err["msg"].removeprefix("Value error, ") + type_hint(err) + suggestion
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"rig file {path}: {loc + ': ' if loc else ''}{msg}{more}"  # a whole-rig check names its fields itself


def load_rig(path: str | Path) -> RigConfig:
    """Read and validate a rig file; raise RigFileError with a one-line message."""
    return load_rig_text(path)[0]


def load_rig_text(path: str | Path) -> tuple[RigConfig, str]:
    """(rig, the file's text as written: comments, order, defaults left out) of a rig file; RigFileError with a
    one-line message if it is not one."""
    p = Path(path)
    text, data = read_toml(p, "rig", RigFileError)
    try:
        rig = RigConfig.model_validate(data)
    except ValidationError as exc:
        raise RigFileError(_first_error(p, exc)) from None
    replay = rig.simulation.replay
    if replay is not None and not Path(replay).is_absolute():  # relative to the rig file, as its readers expect
        sim = rig.simulation.model_copy(update={"replay": str((p.parent / replay).resolve())})
        rig = rig.model_copy(update={"simulation": sim})
    return rig, text


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_tables(prefix: str, data: dict[str, Any], out: list[str]) -> None:
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict) and v is not None}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    if prefix and scalars:
        out.append(f"\n[{prefix}]")
    for k, v in scalars.items():
        out.append(f"{k} = {_toml_value(v)}")
    for k, v in tables.items():
        _toml_tables(f"{prefix}.{k}" if prefix else k, v, out)


def rig_from_toml(text: str) -> RigConfig:
    """The rig a run file records (``rig_toml`` attribute, written by :func:`rig_to_toml`)."""
    return RigConfig.model_validate(tomllib.loads(text))


def rig_to_toml(rig: RigConfig) -> str:
    """The rig as TOML text that :func:`load_rig` reads back to the same configuration."""
    lines: list[str] = []
    _toml_tables("", rig.model_dump(), lines)
    return "\n".join(lines) + "\n"


def amplifier_spec(rig: RigConfig) -> AmplifierSpec:
    """The rig's amplifier: its model's datasheet, with the monitor ratios the rig file calibrates."""
    a = rig.amplifier
    base = TREK_DATASHEET[a.model if a else "10/10B-HS"]
    if a is None:
        return base
    return replace(base, vmon_ratio=a.vmon_ratio or base.vmon_ratio, imon_ratio=a.imon_ratio or base.imon_ratio)


def _monitor_chain(rig: RigConfig) -> tuple[AmplifierSpec, DaqInput] | None:
    """The rig's voltage-monitor chain: its amplifier and the DAQ input that converts the monitor (a T7 AIN where
    the DAQ drives the amplifier, else the ADAM-4017+ at the rig's ``ai_bits``); None without an amplifier."""
    a = rig.amplifier
    if a is None:
        return None
    return amplifier_spec(rig), T7_AIN if a.drive == "daq" else adam_4017p(a.ai_bits)


def safe_monitor_v(rig: RigConfig) -> float:
    """|voltage monitor| at or below this [V] is the rig's output verified at 0 V: derived from its monitor chain
    (:func:`bench.core.monitor_chain.safe_threshold_v`); :data:`~bench.core.monitor_chain.SAFE_TOUCH_V` without an
    amplifier. ValueError where the chain cannot verify a safe output."""
    if (chain := _monitor_chain(rig)) is None:
        return SAFE_TOUCH_V
    spec, daq = chain
    return safe_threshold_v(spec.model, spec.max_output, spec.vmon_ratio, daq)


def monitor_band_v(rig: RigConfig) -> float | None:
    """The 0-V band of the rig's voltage-monitor chain [V] (:func:`bench.core.monitor_chain.zero_band_v`): the
    largest |reading| of an output truly at 0 V, so a peak within it is no drive; None without an amplifier."""
    if (chain := _monitor_chain(rig)) is None:
        return None
    spec, daq = chain
    return zero_band_v(spec.model, spec.max_output, spec.vmon_ratio, daq)


def plant_for(rig: RigConfig, clock: Clock, *, temperature_K: float | None = None, prototype: int | None = None,
              hung_mass_kg: float | None = None, membrane_method: Literal["fixed", "rodas"] = "fixed",
              h: float = 1e-4) -> Plant:
    """The one plant of a rig — its specimen (with a protocol's overrides) behind its amplifier's output stage,
    seen through its monitors with the rig's ``[simulation]`` noise and seed — for the simulated rig (twins,
    ``fixed`` step) and the dry run (``rodas`` for the membrane)."""
    spec = rig.specimen
    hv = HVStage.of(amplifier_spec(rig))
    realism = Realism(noise=rig.simulation.noise, seed=rig.simulation.seed)
    if spec.kind == "membrane":
        return Plant(clock, spec.membrane(), temperature=temperature_K or spec.temperature_K, hv=hv, h=h,
                     membrane_method=membrane_method, realism=realism)
    cfg = spec.lsdea
    x0 = cfg.blocked_position_m if cfg.configuration == "blocked" else cfg.x_at_motor_zero_m
    return Plant(clock, spec.lozenge(prototype, hung_mass_kg), configuration=cfg.configuration, x0=x0, hv=hv, h=h,
                 motor_sign=cfg.motor_sign, realism=realism)
