"""Fuzzing the wire: frames to each simulated instrument, replies to each driver.

* **Frames to the twins.** Random bytes and mutated valid requests (the manuals' own examples, bit-flipped,
  truncated, repeated, spliced) go to every twin of the simulated rigs on its real port (pty or Modbus TCP).
  A twin must answer or ignore them, never die: afterwards no twin has raised, and — once the host has done
  what it would do after line noise (a CR on an ASCII line, silence on RS-485, a new TCP connection) — every
  driver connects and reads a finite value again.
* **Replies to the drivers.** Each reply a twin sends is rewritten on its way (bytes flipped, cut, repeated,
  inserted, replaced, or dropped) while the drivers read. A driver must return a reading that is finite when it
  says "ok", or raise one of the named driver errors (:mod:`drivers.errors`); anything else is a traceback.

``python -m tests.fuzzing.wire --frames N --replies N --seed S`` prints the counts per instrument.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import serial

from bench.resources import rigs_dir
from bench.rig import RigConfig, load_rig
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.sim_rig import SimRig
from drivers.errors import InstrumentError
from drivers.interfaces import Reading

RIGS = ("thesis-sim", "lsdea-motor-sim", "thesis-daq-sim")
FUZZ_TIMEOUT_S = 0.05  # driver reply timeout while fuzzing (a dropped reply costs this, not 0.5 s)

# valid requests from the manuals (as the conformance tests use them), mutated into near-valid frames
SEEDS: dict[str, tuple[bytes, ...]] = {
    "laser": (b"MS,01\r", b"M1\r", b"SR,00,00\r", b"AO,1\r", b"R0\r", b"Q0\r"),
    "motor": (bytes.fromhex("01 11 09 02 00 02 01 02 A0 86 01 00 04"), bytes.fromhex("01 11 02 01 00 04")),
    "rtu": (bytes.fromhex("01 03 00 00 00 01 84 0A"), bytes.fromhex("02 03 00 00 00 02 C4 38"),
            bytes.fromhex("01 06 00 00 08 00 8F DB")),
    "tcp": (bytes.fromhex("00 01 00 00 00 06 01 03 00 00 00 01"),
            bytes.fromhex("00 02 00 00 00 06 01 10 00 00 00 00"),
            # LabJack MBFB (function 76): write DAC0 ← 2.0 V, read it back, read PRODUCT_ID
            bytes.fromhex("00 03 00 00 00 12 01 4c 01 03 e8 02 40 00 00 00 00 03 e8 02 00 ea 60 02")),
}


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One random rewrite of ``data``: flip, cut, repeat, insert, replace, splice random bytes, or drop."""
    n = len(data)
    kind = int(rng.integers(0, 7))
    if kind == 0 and n:  # flip bits of one to three bytes
        buf = bytearray(data)
        for i in rng.integers(0, n, int(rng.integers(1, 4))):
            buf[int(i)] ^= int(rng.integers(1, 256))
        return bytes(buf)
    if kind == 1:  # cut
        return data[:int(rng.integers(0, n + 1))]
    if kind == 2:  # repeat
        return data * int(rng.integers(2, 4))
    if kind == 3:  # insert random bytes
        i = int(rng.integers(0, n + 1))
        return data[:i] + rng.bytes(int(rng.integers(1, 9))) + data[i:]
    if kind == 4:  # random bytes of random length
        return rng.bytes(int(rng.integers(1, 65)))
    if kind == 5:  # drop the tail and append another copy's head
        return data[:int(rng.integers(0, n + 1))] + data[int(rng.integers(0, n + 1)):]
    return b""  # nothing at all


@dataclass
class Tally:
    """Outcomes per instrument: ``ok`` (a valid reading), ``refused`` (a driver error), ``traceback`` (any other
    exception), ``bad value`` (an 'ok' reading that is not finite), ``twin died``, ``no recovery``."""

    counts: dict[str, Counter[str]] = field(default_factory=dict)
    examples: list[str] = field(default_factory=list)

    def add(self, who: str, kind: str, detail: str = "") -> None:
        self.counts.setdefault(who, Counter())[kind] += 1
        if kind not in ("ok", "refused") and len(self.examples) < 20:
            self.examples.append(f"{who}: {kind}: {detail}")

    def failures(self) -> int:
        return sum(c[k] for c in self.counts.values() for k in ("traceback", "bad value", "twin died", "no recovery"))


def _start(name: str, transport: str | None = None) -> tuple[SimRig, RigConfig]:
    rig = load_rig(rigs_dir() / f"{name}.toml")
    data = rig.model_dump()
    if data.get("amplifier"):  # the fuzz holds no voltage: the module's watchdog would only add noise
        data["amplifier"] = {**data["amplifier"], "comm_watchdog_s": None}
    if transport is not None:
        data["simulation"] = {**data["simulation"], "modbus_transport": transport}
    rig = RigConfig.model_validate(data)
    sim = SimRig(rig, virtual=True, timing="none")
    sim.start()
    return sim, rig


def _connect(rig: RigConfig, sim: SimRig) -> Instruments:
    inst = build_instruments(rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep, wire_time=sim.wire_time)
    for _, drv in inst.items():
        drv.connect()
    return inst


def _reads(inst: Instruments) -> dict[str, Callable[[], object]]:
    """One read per role (the calls a run makes most)."""
    out: dict[str, Callable[[], object]] = {}
    if inst.amplifier is not None:
        out["amplifier"] = inst.amplifier.read_monitors
    if inst.laser is not None:
        out["laser"] = inst.laser.read_displacement
    if inst.motor is not None:
        out["motor"] = inst.motor.read_position
    if inst.load_cell is not None:
        out["load_cell"] = inst.load_cell.read_force
    if inst.daq is not None:
        daq = inst.daq
        out["daq"] = lambda: daq.read_ain(0)
    return out


def _finite_if_ok(result: object) -> bool:
    readings = result if isinstance(result, tuple) else (result,)
    return all(math.isfinite(r.value) for r in readings if isinstance(r, Reading) and r.ok)


def _short_timeouts(inst: Instruments) -> None:
    links = list(inst.links.values())
    daq_link = getattr(inst.daq, "link", None)
    if daq_link is not None:
        links.append(daq_link)
    for link in links:
        link.timeout, link.retries = FUZZ_TIMEOUT_S, 0
    for drv in (inst.laser, inst.motor):
        link = getattr(drv, "link", None)
        if link is not None:
            link.timeout = FUZZ_TIMEOUT_S


def fuzz_replies(n: int, seed: int, tally: Tally) -> None:
    """``n`` mutated replies to every driver of every fuzzed rig."""
    for k, name in enumerate(RIGS):
        sim, rig = _start(name)
        rng = np.random.default_rng(seed + k)
        try:
            inst = _connect(rig, sim)
            _short_timeouts(inst)
            for role, read in _reads(inst).items():
                faults = sim.faults_of(role)
                faults.mutate = lambda data, r=rng: mutate(data, r)
                for _ in range(n):
                    try:
                        result = read()
                    except InstrumentError:
                        tally.add(role, "refused")
                    except Exception as exc:  # what the fuzz is looking for
                        tally.add(role, "traceback", f"{type(exc).__name__}: {exc}"[:300])
                    else:
                        tally.add(role, "ok" if _finite_if_ok(result) else "bad value", repr(result)[:200])
                faults.mutate = None
                if not _recovers(read):
                    tally.add(role, "no recovery", "no valid reading in 20 tries after the fuzz")
            inst.close()
        finally:
            for err in sim.twin_errors():
                tally.add(name, "twin died", err)
            sim.stop()


def _recovers(read: Callable[[], object], tries: int = 20) -> bool:
    for _ in range(tries):
        try:
            if _finite_if_ok(read()):
                return True
        except InstrumentError:
            time.sleep(FUZZ_TIMEOUT_S)
        except Exception:  # counted as a failure by the caller (no recovery), not a crash of the fuzz run
            return False
    return False


def _frames_to(address: str, frames: list[bytes], line_noise_end: bytes) -> None:
    """Send ``frames`` to a twin's port, draining what comes back; then what a host does after line noise."""
    if address.startswith("tcp://") or address.count(":") == 2:  # Modbus TCP (the T7: host:modbus:stream)
        host, port = address.removeprefix("tcp://").split(":")[:2]
        with socket.create_connection((host, int(port)), timeout=1.0) as sock:
            sock.settimeout(0.002)
            for frame in frames:
                if frame:
                    sock.sendall(frame)
                with contextlib.suppress(TimeoutError, OSError):
                    sock.recv(65536)
        return  # the next driver opens a fresh connection (a TCP stream out of step cannot be resynchronised)
    with serial.serial_for_url(address, timeout=0.002) as port:
        for frame in frames:
            if frame:
                port.write(frame)
            port.read(4096)
        port.write(line_noise_end)
        time.sleep(0.03)  # silence: the end of any RTU frame, a LinRS receive timeout
        port.read(4096)


def fuzz_frames(n: int, seed: int, tally: Tally) -> None:
    """``n`` random or mutated frames to every twin of every fuzzed rig (Modbus on RTU and on TCP)."""
    runs = [("thesis-sim", "rtu"), ("thesis-sim", "tcp"), ("lsdea-motor-sim", None), ("thesis-daq-sim", None)]
    for k, (name, transport) in enumerate(runs):
        sim, rig = _start(name, transport)
        rng = np.random.default_rng(seed + 100 + k)
        try:
            ports = sim.port_map()
            for target, address in ports.items():
                kind = target if target in ("laser", "motor") else \
                    ("rtu" if address.startswith("/") or address.startswith("socket://") else "tcp")
                seeds = SEEDS[kind]
                frames = [mutate(seeds[int(rng.integers(0, len(seeds)))], rng) if rng.random() < 0.7
                          else rng.bytes(int(rng.integers(1, 65))) for _ in range(n)]
                _frames_to(address, frames, b"\r" if kind == "laser" else b"")
                tally.counts.setdefault(f"{target} frames", Counter())["sent"] += n
            errors = sim.twin_errors()
            for err in errors:
                tally.add(name, "twin died", err)
            try:  # every driver connects and reads again
                inst = _connect(rig, sim)
                for role, read in _reads(inst).items():
                    if not _recovers(read):
                        tally.add(role, "no recovery", f"{name}: no valid reading after the frames")
                inst.close()
            except InstrumentError as exc:
                tally.add(name, "no recovery", f"connect after the frames: {exc}")
        finally:
            sim.stop()


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.fuzzing.wire``: print the counts per instrument and the first failures."""
    ap = argparse.ArgumentParser(prog="python -m tests.fuzzing.wire", description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=500, help="frames to each twin")
    ap.add_argument("--replies", type=int, default=500, help="mutated replies to each driver")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    tally = Tally()
    fuzz_frames(args.frames, args.seed, tally)
    fuzz_replies(args.replies, args.seed, tally)
    for who, c in sorted(tally.counts.items()):
        print(f"{who:18s} " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    print(f"failures {tally.failures()} ({time.monotonic() - t0:.0f} s, seed {args.seed})")
    for line in tally.examples[:10]:
        print("---", line)
    return 1 if tally.failures() else 0


if __name__ == "__main__":
    raise SystemExit(main())
