"""Injected link faults reach the real drivers on every transport the simulated rigs serve.

Each case starts a shipped simulated rig (``rigs/thesis-sim.toml``, ``rigs/lsdea-motor-sim.toml``: Modbus over
TCP), injects one fault on one link, drives the real driver over it and checks both sides: the driver raised the
error class that ``drivers/errors.py`` promises, and ``Faults.counts`` shows the simulator really acted.

Which error a garbled reply must give is decided by what the protocol can detect:

* Modbus RTU (pty, RTU over TCP): every byte is covered by the CRC-16, which detects any single flipped byte.
  A frame that fails its CRC is discarded, as the Modbus serial-line spec requires, so the master never gets a
  valid reply: ``InstrumentTimeoutError``, whichever byte was flipped.
* Modbus TCP has no checksum (TCP's own covers a real wire). A flipped MBAP byte (transaction, protocol,
  length, unit id) makes a frame that does not answer the request; the master drops it and times out:
  ``InstrumentTimeoutError``. A flipped function code gives a frame that does not decode: a ``ProtocolError``
  under the error contract, though a driver that reports the client library's decode failure as "no valid reply"
  gives ``InstrumentTimeoutError``, so both are accepted. A flipped register byte is undetectable and reads as
  a wrong value (pinned below, so nobody mistakes a TCP garble test on data bytes for a link test).
* Keyence ASCII: a flipped echo byte fails the echo check (``ProtocolError``); a flipped CR leaves no
  terminator (``InstrumentTimeoutError``).
* LinMot LinRS: flipped start or end byte: ``ProtocolError`` (data bytes need the optional checksum).

Retries are the driver's business: garble and mute stay on for every attempt, and are cleared before the
recovery check.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from bench.core.clock import VirtualClock
from bench.runtime.run import execute, plan_run
from drivers.errors import InstrumentConnectionError, InstrumentError, InstrumentTimeoutError, ProtocolError
from sim_devices.transport import Faults
from tests.conftest import ROOT, RunningRig, start_rig

LATENCY = 0.06  # s; well below every link timeout (0.3 s in the fixtures), even on a loaded machine
MANY = 1000  # garble every attempt the driver makes


@dataclass(frozen=True)
class Link:
    """One link of a shipped simulated rig and a driver call that goes over it."""

    rig: str
    name: str  # role (serial twin) or bus name
    kind: str  # "serial" or "modbus"
    call: Callable[[RunningRig], object]

    def __str__(self) -> str:
        return f"{self.rig}:{self.name}"


def _amp(r: RunningRig) -> object:
    return r.inst.amplifier.read_voltage()


def _cell(r: RunningRig) -> object:
    return r.inst.load_cell.read_force()


def _laser(r: RunningRig) -> object:
    return r.inst.laser.read_displacement()


def _motor(r: RunningRig) -> object:
    return r.inst.motor.poll()


LINKS = [Link("thesis-sim", "io", "modbus", _amp), Link("thesis-sim", "laser", "serial", _laser),
         Link("lsdea-motor-sim", "io", "modbus", _amp), Link("lsdea-motor-sim", "scale", "modbus", _cell),
         Link("lsdea-motor-sim", "motor", "serial", _motor)]
GARBLE_INDEX = {"laser": 0, "motor": 0, "io": 6, "scale": 6}  # echo / start byte; MBAP unit id
GARBLE_ERROR: dict[str, tuple[type[InstrumentError], ...]] = {
    "laser": (ProtocolError,), "motor": (ProtocolError,),
    "io": (InstrumentTimeoutError,), "scale": (InstrumentTimeoutError,)}


def _rig(name: str, **overrides: object) -> Iterator[RunningRig]:
    r = start_rig(name, **overrides)
    try:
        yield r
    finally:
        with contextlib.suppress(Exception):  # closing over a dropped link is not what these tests check
            r.inst.close()
        r.sim.stop()


@pytest.fixture(params=LINKS, ids=str)
def link(request: pytest.FixtureRequest) -> Iterator[tuple[Link, RunningRig, Faults]]:
    lk: Link = request.param
    for r in _rig(lk.rig):
        yield lk, r, r.sim.faults_of(lk.name)


def _recovered(lk: Link, r: RunningRig) -> None:
    """After the fault is cleared the driver works again (serial: after discarding stale bytes)."""
    if lk.kind == "serial":
        getattr(r.inst, lk.name).link.discard_input()
    lk.call(r)


def test_shipped_sim_rigs_serve_modbus_tcp_through_the_fault_relay() -> None:
    for name in ("thesis-sim", "lsdea-motor-sim"):
        for r in _rig(name):
            for bus in r.sim._modbus.buses:  # type: ignore[union-attr]
                assert bus.transport == "tcp" and bus.relay is not None
                assert bus.endpoint == f"tcp://127.0.0.1:{bus.relay.port}" == r.sim.port_map()[bus.name]


def test_latency(link: tuple[Link, RunningRig, Faults]) -> None:
    lk, r, faults = link
    faults.latency = LATENCY
    t0 = time.perf_counter()
    lk.call(r)
    assert time.perf_counter() - t0 >= LATENCY
    assert faults.counts["latency"] >= 1 and faults.injected >= 1


def test_mute_times_out(link: tuple[Link, RunningRig, Faults]) -> None:
    lk, r, faults = link
    faults.mute = True
    with pytest.raises(InstrumentTimeoutError):
        lk.call(r)
    assert faults.counts["mute"] >= 1 and faults.injected >= 1
    faults.mute = False
    _recovered(lk, r)


def test_garble(link: tuple[Link, RunningRig, Faults]) -> None:
    lk, r, faults = link
    faults.garble_next, faults.garble_index = MANY, GARBLE_INDEX[lk.name]
    with pytest.raises(GARBLE_ERROR[lk.name]):
        lk.call(r)
    assert faults.counts["garble"] >= 1 and faults.injected >= 1
    faults.garble_next = 0
    _recovered(lk, r)


def _dropped(faults: Faults) -> None:
    """Wait until the transport has acted on ``drop`` (its poll is 5-10 ms; the deadline is a hang guard, not a
    timing claim: a loaded machine may hold the poll far longer)."""
    deadline = time.monotonic() + 30.0
    while faults.counts["drop"] == 0:
        assert time.monotonic() < deadline, "the transport never dropped the link"
        time.sleep(0.005)


def test_drop_is_a_lost_link(link: tuple[Link, RunningRig, Faults]) -> None:
    lk, r, faults = link
    faults.drop = True
    _dropped(faults)
    with pytest.raises(InstrumentConnectionError):
        lk.call(r)
    with pytest.raises(InstrumentConnectionError):  # and stays lost: no reconnection while dropped
        lk.call(r)
    assert faults.counts["drop"] == 1 and faults.injected >= 1
    if lk.kind == "modbus":  # the relay listens again once the link is back (a pty is gone for good)
        faults.drop = False
        deadline = time.monotonic() + 2.0
        while True:
            try:
                lk.call(r)
                break
            except InstrumentConnectionError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.02)


def test_modbus_tcp_server_dies_during_a_request(thesis: RunningRig) -> None:
    """The relay closes (FIN) as the reply arrives: the driver, waiting for it, sees a lost link."""
    faults = thesis.sim.faults_of("amplifier")
    faults.schedule(after_replies=1, drop=True)
    _amp(thesis)
    with pytest.raises(InstrumentConnectionError):
        _amp(thesis)
    assert faults.counts["drop"] == 1


def test_modbus_tcp_reset_during_a_request(thesis: RunningRig) -> None:
    """As above with a TCP reset (a rebooted gateway): still a lost link under the error contract."""
    faults = thesis.sim.faults_of("amplifier")
    faults.drop_reset = True
    faults.schedule(after_replies=1, drop=True)
    _amp(thesis)
    with pytest.raises(InstrumentConnectionError):
        _amp(thesis)
    assert faults.counts["drop"] == 1


# ------------------------------------------------------------------ every Modbus transport, not just TCP


@pytest.fixture(params=["tcp", "rtu-socket", "rtu"])
def thesis_on(request: pytest.FixtureRequest) -> Iterator[RunningRig]:
    yield from _rig("thesis-sim", simulation={"seed": 1, "modbus_transport": request.param})


def test_every_modbus_transport_applies_every_fault(thesis_on: RunningRig) -> None:
    r, faults = thesis_on, thesis_on.sim.faults_of("amplifier")
    faults.latency = LATENCY
    t0 = time.perf_counter()
    _amp(r)
    assert time.perf_counter() - t0 >= LATENCY
    faults.latency = 0.0
    faults.mute = True
    with pytest.raises(InstrumentTimeoutError):
        _amp(r)
    faults.mute = False
    _amp(r)
    faults.garble_next, faults.garble_index = MANY, 6 if r.rig.simulation.modbus_transport == "tcp" else None
    with pytest.raises(InstrumentTimeoutError):  # CRC (RTU) or MBAP unit id (TCP): the frame is discarded
        _amp(r)
    faults.garble_next = 0
    _amp(r)
    assert all(faults.counts[k] >= 1 for k in ("latency", "mute", "garble"))


@pytest.mark.parametrize("transport", [
    "tcp", "rtu-socket",
    "rtu"])
def test_every_modbus_transport_drops(transport: str) -> None:
    for r in _rig("thesis-sim", simulation={"seed": 1, "modbus_transport": transport}):
        faults = r.sim.faults_of("amplifier")
        _amp(r)
        faults.drop = True
        _dropped(faults)
        with pytest.raises(InstrumentConnectionError):
            _amp(r)
        assert faults.counts["drop"] == 1


def test_modbus_tcp_garbled_function_code_is_never_a_valid_reply(thesis: RunningRig) -> None:
    """MBAP is bytes 0–6, byte 7 the function code: 03h ^ 5Ah = 59h is no Modbus function, so the reply
    cannot be decoded, every attempt fails and the read ends as 'no valid reply' (never as data)."""
    faults = thesis.sim.faults_of("io")
    faults.garble_next, faults.garble_index = MANY, 7
    with pytest.raises(InstrumentTimeoutError, match="no valid reply"):
        _amp(thesis)
    assert faults.counts["garble"] >= 1


def test_modbus_tcp_cannot_detect_a_garbled_register(thesis: RunningRig) -> None:
    """No checksum in Modbus TCP: a flipped high byte of the first register reads back as a wrong voltage."""
    faults = thesis.sim.faults_of("io")
    clean = thesis.inst.amplifier.read_voltage().value
    faults.garble_next, faults.garble_index = 1, 9
    assert abs(thesis.inst.amplifier.read_voltage().value - clean) > 1000.0
    assert faults.counts["garble"] == 1


# ------------------------------------------------------------------ schedules


def test_amplifier_bus_goes_silent_two_seconds_into_the_run(thesis: RunningRig) -> None:
    faults = thesis.sim.faults_of("amplifier")
    t0 = thesis.sim.clock.now()
    faults.schedule(at_time=t0 + 2.0, mute=True)
    thesis.advance(1.5)
    _amp(thesis)
    assert faults.pending == 1 and faults.injected == 0
    thesis.advance(1.0)
    with pytest.raises(InstrumentTimeoutError):
        _amp(thesis)
    assert faults.pending == 0 and faults.counts["mute"] >= 1


def test_garble_after_n_replies(thesis: RunningRig) -> None:
    laser, faults = thesis.inst.laser, thesis.sim.faults_of("laser")
    faults.schedule(after_replies=2, garble_next=1, garble_index=0)
    laser.read_displacement()
    laser.read_displacement()
    with pytest.raises(ProtocolError):
        laser.read_displacement()
    assert laser.read_displacement().ok and faults.counts["garble"] == 1 and faults.pending == 0


def test_scheduled_drop_fires_without_traffic(lsdea_motor: RunningRig) -> None:
    """A time schedule is checked by the transport while idle, so a link drops on time even if nobody talks."""
    faults = lsdea_motor.sim.faults_of("load_cell")
    faults.schedule(at_time=lsdea_motor.sim.clock.now() + 1.0, drop=True)
    lsdea_motor.advance(1.0)
    deadline = time.monotonic() + 2.0
    while faults.counts["drop"] == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert faults.drop and faults.counts["drop"] == 1
    with pytest.raises(InstrumentConnectionError):
        _cell(lsdea_motor)


def test_schedule_rejects_what_it_cannot_do() -> None:
    faults = Faults()
    with pytest.raises(ValueError, match="exactly one"):
        faults.schedule(mute=True)
    with pytest.raises(ValueError, match="exactly one"):
        faults.schedule(at_time=1.0, after_replies=1, mute=True)
    with pytest.raises(ValueError, match="needs a clock"):
        faults.schedule(at_time=1.0, mute=True)
    with pytest.raises(TypeError, match="unknown fault switch"):
        faults.schedule(after_replies=1, silent=True)
    clock = VirtualClock()
    faults = Faults(clock=clock.now)
    faults.schedule(at_time=1.0, drop=True)
    faults.schedule(after_replies=0, mute=True)
    assert faults.process(b"reply") == (None, 0.0) and faults.mute and faults.pending == 1
    faults.reset()
    assert faults.pending == 0 and not faults.mute and faults.replies == 1 and faults.counts["mute"] == 1
    clock.advance(2.0)
    faults.tick()
    assert not faults.drop


def test_faults_by_role_or_bus_name(lsdea_motor: RunningRig) -> None:
    sim = lsdea_motor.sim
    assert sim.faults_of("amplifier") is sim.faults["io"] is sim.faults_of("io")
    assert sim.faults_of("load_cell") is sim.faults["scale"]
    assert sim.faults_of("motor") is sim.faults["motor"]
    with pytest.raises(KeyError, match="known: io, motor, scale"):
        sim.faults_of("laser")


def test_scheduled_fault_stops_a_protocol_run_without_touching_the_engine(tmp_path: Path) -> None:
    """The laser link is lost 3 s into a virtual-time run (a schedule, no patched engine): a lost-link stop."""
    sims: list = []

    def arm(_engine: object, sim: object) -> None:
        sims.append(sim)
        sim.faults_of("laser").schedule(at_time=3.0, drop=True)  # type: ignore[attr-defined]

    plan = plan_run(ROOT / "protocols" / "short" / "thesis-identification-short.toml",
                    ROOT / "rigs" / "thesis-sim.toml")  # the laser on its serial line (the DAQ rig reads it on an AIN)
    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=arm)
    assert result.state == "error" and result.reason.startswith("lost link: laser")
    assert sims[0].faults_of("laser").counts["drop"] == 1


def test_scheduled_loss_of_the_daq_stops_a_hardware_timed_run(tmp_path: Path) -> None:
    """The DAQ's link (Modbus TCP and its stream socket) is lost 3 s into a virtual-time run on the default,
    hardware-timed rig: the run stops as a lost link, and the output is made safe by the T7's watchdog."""
    sims: list = []

    def arm(_engine: object, sim: object) -> None:
        sims.append(sim)
        sim.faults_of("amplifier").schedule(at_time=3.0, drop=True)  # type: ignore[attr-defined]  # the DAQ

    plan = plan_run(ROOT / "protocols" / "short" / "thesis-identification-short.toml")
    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=arm)
    assert result.state == "error" and "daq" in result.reason, result.reason
    assert sims[0].faults_of("daq").counts["drop"] == 1
    assert "watchdog" in result.safe_path, result.safe_path
