"""Acquisition-rate benchmarks: each instrument through its driver and its simulated twin on real ports.

Polled figures are sustained request/response rates on the wall-clock simulated rig with real timing (the
twins take each transaction's wire time at the rig's baud rate, the inter-frame silences and the device
turnaround), each beside its analytic limit from :mod:`bench.protocol.link_budget` — the rate the line
allows if the host wasted no time. The buffered laser figure runs the LK-G data storage at 10 kHz in
virtual time at pty speed and checks that every stored sample arrives exactly once.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

import numpy as np

from bench.core.clock import VirtualClock
from bench.protocol.link_budget import (
    TURNAROUND_LINRS_S,
    TURNAROUND_LKG_S,
    char_time,
    laser_upload_rate,
    rtu_transaction,
)
from bench.resources import rigs_dir
from bench.rig import RigConfig, load_rig
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.sim_rig import SimRig, Timing

RIGS = rigs_dir()
T = TypeVar("T")


@dataclass(frozen=True)
class Figure:
    """One measured figure."""

    name: str
    value: float
    unit: str
    note: str = ""


def _rig(name: str, virtual: bool, modbus: str | None = None, timing: Timing = "real") -> tuple[SimRig, Instruments]:
    rig = load_rig(RIGS / f"{name}.toml")
    if modbus is not None:
        rig = RigConfig.model_validate({**rig.model_dump(),
                                        "simulation": {**rig.simulation.model_dump(), "modbus_transport": modbus}})
    sim = SimRig(rig, virtual=virtual, timing=timing)
    sim.start()
    inst = build_instruments(rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep, wire_time=sim.wire_time)
    for _, drv in inst.items():
        drv.connect()
    return sim, inst


def _need(driver: T | None, what: str, sim: SimRig) -> T:
    """The rig's ``what`` driver; a one-line error if the rig file has none (the shipped rigs all do)."""
    if driver is None:
        raise ValueError(f"rig {sim.rig.name} has no {what}: this benchmark needs one")
    return driver


def _rate(fn: Callable[[], object], seconds: float) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        fn()
        n += 1
    return n / elapsed


def _vs(rate: float, limit: float) -> str:
    return f"analytic limit {limit:,.0f}/s: {rate / limit:.0%}"


def polled(seconds: float = 1.0) -> list[Figure]:
    """Sustained polled rates through the drivers with real timing, beside each link's analytic limit."""
    out: list[Figure] = []
    fc6, fc3, fc4 = rtu_transaction(19200, 8, 8), rtu_transaction(19200, 8, 9), rtu_transaction(19200, 8, 15)
    for modbus, label in (("rtu", "RTU, 19200 Bd, pty"), ("tcp", "Modbus TCP gateway, RS-485 at 19200 Bd")):
        sim, inst = _rig("thesis-sim", virtual=False, modbus=modbus)
        try:
            amp = _need(inst.amplifier, "amplifier", sim)
            if modbus == "rtu":
                limit = 1 / ((6 + 15) * char_time(115200) + TURNAROUND_LKG_S)
                rate = _rate(_need(inst.laser, "laser", sim).read, seconds)
                out.append(Figure("laser single read (MS,01), 115200 Bd", rate, "reads/s", _vs(rate, limit)))
            rate = _rate(partial(amp.set_voltage, 100.0), seconds)
            out.append(Figure(f"amplifier set-point (FC6 on ADAM-4024), {label}", rate, "writes/s",
                              _vs(rate, 1 / fc6)))
            rate = _rate(amp.read_monitors, seconds)
            out.append(Figure(f"amplifier monitors (FC3 on ADAM-4017+), {label}", rate, "reads/s",
                              _vs(rate, 1 / fc3)))
        finally:
            inst.close()
            sim.stop()
    sim, inst = _rig("lsdea-motor-sim", virtual=False, modbus="tcp")
    try:
        rate = _rate(_need(inst.motor, "motor", sim).read_position, seconds)
        limit = 1 / ((7 + 16) * char_time(115200) + TURNAROUND_LINRS_S)
        out.append(Figure("motor position (LinRS default response), 115200 Bd", rate, "reads/s", _vs(rate, limit)))
        rate = _rate(_need(inst.load_cell, "load cell", sim).read, seconds)
        out.append(Figure("load cell (FC4 on DGT1S), gateway, RS-485 at 19200 Bd", rate, "reads/s",
                          _vs(rate, 1 / fc4)))
    finally:
        inst.close()
        sim.stop()
    return out


def buffered_laser(duration: float = 20.0, fetch_every: float = 0.5) -> list[Figure]:
    """LK-G storage at 10 kHz for ``duration`` virtual seconds, fetched in blocks while it runs."""
    sim, inst = _rig("thesis-sim", virtual=True, timing="none")
    clock = sim.clock
    try:
        laser, amp = _need(inst.laser, "laser", sim), _need(inst.amplifier, "amplifier", sim)
        if not isinstance(clock, VirtualClock):  # SimRig(virtual=True) makes one
            raise TypeError(f"a virtual simulated rig has a VirtualClock, not a {type(clock).__name__}")
        clock.advance(1.0)
        amp.set_voltage(7000.0)
        t0 = time.perf_counter()
        laser.start_buffer(1e-4)
        indices, steps = [], round(duration / fetch_every)
        for _ in range(steps):
            clock.advance(fetch_every)
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


def laser_upload(points: int = 2000) -> Figure:
    """Upload throughput of stored points through the driver on the wall clock with real timing (115200 Bd)."""
    sim, inst = _rig("thesis-sim", virtual=False)
    try:
        laser = _need(inst.laser, "laser", sim)
        laser.start_buffer(1e-4)
        time.sleep(points * 1e-4 + 0.05)
        laser.stop_buffer()
        n, t0 = 0, time.perf_counter()
        while laser.pending or n == 0:
            n += laser.fetch_buffer().values.size
        wall = time.perf_counter() - t0
    finally:
        inst.close()
        sim.stop()
    rate = n / wall
    return Figure("laser storage upload (AO), 115200 Bd", rate, "samples/s",
                  f"{_vs(rate, laser_upload_rate(115200))}; 9 bytes a value")


def run_all(quick: bool = False) -> list[Figure]:
    """All acquisition figures (``quick``: shorter runs)."""
    figs = polled(0.3 if quick else 1.0)
    figs += buffered_laser(2.0 if quick else 20.0)
    figs.append(laser_upload(points=500 if quick else 4000))
    return figs
