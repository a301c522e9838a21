"""Acquisition-rate benchmarks: each instrument through its driver and its simulated twin on real ports.

Polled figures are request/response rates over a pty (or pty bridge for Modbus RTU) on the wall-clock
simulated rig: they measure the driver + protocol + twin + plant, not a real wire, since a pty has no baud
rate. The buffered laser figure runs the LK-G data storage at 10 kHz in virtual time and checks that every
stored sample arrives exactly once; a second figure emulates the wire time of a 115200 Bd RS-232 link.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.instruments import Instruments, build_instruments
from bench.rig import RigConfig, load_rig
from sim_devices.rig import SimRig

RIGS = Path(__file__).resolve().parent.parent / "rigs"


@dataclass(frozen=True)
class Figure:
    """One measured figure."""

    name: str
    value: float
    unit: str
    note: str = ""


def _rig(name: str, virtual: bool, modbus: str | None = None) -> tuple[SimRig, Instruments]:
    rig = load_rig(RIGS / f"{name}.toml")
    if modbus is not None:
        rig = RigConfig.model_validate({**rig.model_dump(),
                                        "simulation": {**rig.simulation.model_dump(), "modbus_transport": modbus}})
    sim = SimRig(rig, virtual=virtual)
    sim.start()
    inst = build_instruments(rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep)
    for _, drv in inst.items():
        drv.connect()
    return sim, inst


def _rate(fn: Callable[[], object], seconds: float) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        fn()
        n += 1
    return n / elapsed


def polled(seconds: float = 1.0) -> list[Figure]:
    """Sustained polled rates of every instrument on the wall-clock simulated rigs."""
    out: list[Figure] = []
    for modbus, label in (("rtu", "Modbus RTU on a pty"), ("tcp", "Modbus TCP on loopback")):
        sim, inst = _rig("thesis-sim", virtual=False, modbus=modbus)
        try:
            if modbus == "rtu":
                out.append(Figure("laser single read (M1 / MS)", _rate(inst.laser.read, seconds), "reads/s", "pty"))
            out.append(Figure("amplifier set-point (FC6 on ADAM-4024)",
                              _rate(lambda i=inst: i.amplifier.set_voltage(100.0), seconds), "writes/s", label))
            out.append(Figure("amplifier monitors (FC3 on ADAM-4017+)", _rate(inst.amplifier.read_monitors, seconds),
                              "reads/s", f"{label}; module converts at 10 S/s"))
        finally:
            inst.close()
            sim.stop()
    sim, inst = _rig("lsdea-motor-sim", virtual=False, modbus="rtu")
    try:
        out.append(Figure("motor position (LinRS default response)", _rate(inst.motor.read_position, seconds),
                          "reads/s", "pty"))
        out.append(Figure("load cell (FC4 on DGT1S)", _rate(inst.load_cell.read, seconds), "reads/s",
                          "Modbus RTU on a pty; transmitter converts at 100 S/s"))
    finally:
        inst.close()
        sim.stop()
    return out


def buffered_laser(duration: float = 20.0, fetch_every: float = 0.5) -> list[Figure]:
    """LK-G storage at 10 kHz for ``duration`` virtual seconds, fetched in blocks while it runs."""
    sim, inst = _rig("thesis-sim", virtual=True)
    laser, clock = inst.laser, sim.clock
    try:
        clock.advance(1.0)  # type: ignore[attr-defined]
        inst.amplifier.set_voltage(7000.0)
        t0 = time.perf_counter()
        laser.start_buffer(1e-4)
        indices, steps = [], round(duration / fetch_every)
        for _ in range(steps):
            clock.advance(fetch_every)  # type: ignore[attr-defined]
            block = laser.fetch_buffer()
            indices.append(block.first_index + np.arange(block.values.size))
        laser.stop_buffer()
        wall = time.perf_counter() - t0
    finally:
        inst.close()
        sim.stop()
    idx = np.concatenate(indices)
    expected = round(duration * 1e4) + 1
    lost = expected - np.unique(idx).size
    dup = idx.size - np.unique(idx).size
    contiguous = bool(np.array_equal(idx, np.arange(expected)))
    note = f"{idx.size} samples in {duration:g} s, lost {lost}, duplicated {dup}, contiguous {contiguous}"
    return [Figure("laser storage at 10 kHz, fetched while storing", idx.size / wall, "samples/s (wall)", note),
            Figure("  same, as a multiple of real time", duration / wall, "× real time", "virtual clock")]


def laser_upload_at_baud(baud: float = 115200.0, points: int = 2000) -> Figure:
    """Upload throughput of stored points with the wire time of ``baud`` emulated on the pty."""
    sim, inst = _rig("thesis-sim", virtual=True)
    try:
        inst.laser.start_buffer(1e-4)
        sim.clock.advance(points * 1e-4)  # type: ignore[attr-defined]
        inst.laser.stop_buffer()
        sim.faults["laser"].wire_baud = baud
        t0 = time.perf_counter()
        n = inst.laser.fetch_buffer().values.size
        wall = time.perf_counter() - t0
    finally:
        inst.close()
        sim.stop()
    return Figure(f"laser storage upload at {baud:g} Bd (wire time emulated)", n / wall, "samples/s",
                  "9 bytes per value on the wire")


def run_all(quick: bool = False) -> list[Figure]:
    """All acquisition figures (``quick``: shorter runs)."""
    figs = polled(0.3 if quick else 1.0)
    figs += buffered_laser(2.0 if quick else 20.0)
    figs.append(laser_upload_at_baud(points=500 if quick else 2000))
    return figs
