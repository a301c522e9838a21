"""A stream the T7 ends with a status of its own (2942 STREAM_SCAN_OVERLAP, 2943 STREAM_AUTO_RECOVER_END_OVERFLOW,
2945 STREAM_BUFFER_FULL: the T-series register map's stream errors) loses none of the scans measured before it: the
driver's error carries them, the run records them, stops at 0 V and names the status.

The driver tests feed it stream packets written here byte by byte ([E] LabJack's low-level stream example: TransID,
ProtoID 0, Length = 10 + 2·samples, unit 1, function 76, type 16, reserved, backlog, status, AddInfo, samples MSB
first) on a socket pair; the volts expected are the datasheet's nominal ±10-V calibration (code 33523 = 0 V,
0.000315805780 V a code above it), the driver's before it reads a device's constants.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from bench.core.clock import VirtualClock
from bench.core.plant import HVStage, Plant
from bench.models.membrane import MembraneParams
from bench.runtime.engine import Engine
from bench.runtime.sim_rig import SimRig
from drivers.errors import StreamEndedError
from drivers.labjack import LabJackT7, StreamIn, StreamSpec
from drivers.labjack.plan import StreamPlan, StreamState
from sim_devices.labjack_t7 import LabJackT7Sim
from tests.test_interlock import DAQ_RIG, ZERO_V, events, run_with_fault

CENTER, SLOPE = 33523, 0.000315805780  # nominal ±10-V calibration (datasheet; tests/test_labjack.py checks it)
RATE = 10_000.0
SCAN_OVERLAP, RECOVER_OVERFLOW, BUFFER_FULL = 2942, 2943, 2945  # the register map's stream error codes


def packet(tid: int, codes: list[int], status: int = 0) -> bytes:
    """One spontaneous stream packet: 16-byte header, then the samples big-endian."""
    return struct.pack(">HHHBBBBHHH", tid, 0, 10 + 2 * len(codes), 1, 76, 16, 0, 0, status, 0) + \
        struct.pack(f">{len(codes)}H", *codes)


def scans(first: int, n: int) -> list[int]:
    """The codes of ``n`` two-input scans from scan ``first``: input 0 at CENTER + 10·k, input 1 at CENTER + 10·k + 5
    (k the scan number): every scan's codes its own."""
    return [c for k in range(first, first + n) for c in (CENTER + 10 * k, CENTER + 10 * k + 5)]


def volts(first: int, n: int) -> np.ndarray:
    """What ``scans(first, n)`` read, by the nominal calibration."""
    return (np.array(scans(first, n), float).reshape(n, 2) - CENTER) * SLOPE


class Wire:
    """A driver whose stream socket is one end of a socket pair; the test writes the device's packets on the other.
    AIN0 and AIN1 at ±10 V, 4 samples (2 scans) a packet, no stream-out; ``num_scans`` > 0: a burst."""

    def __init__(self, num_scans: int = 0, sleep: Callable[[float], None] | None = None) -> None:
        self.clock = VirtualClock()
        self.daq = LabJackT7("127.0.0.1", clock=self.clock.now, sleep=sleep or self.clock.sleep)
        spec = StreamSpec(RATE, (StreamIn(0), StreamIn(1)), samples_per_packet=4, num_scans=num_scans)
        plan = StreamPlan(RATE, 1 / RATE, ("AIN0", "AIN1"), (0, 2), 4, None, None, 0, np.inf)
        self.device, host = socket.socketpair()
        self.daq._stream = StreamState(plan, spec, 2, (0, 0), sock=host)
        self.daq.streaming = True

    def send(self, *packets: bytes) -> None:
        self.device.sendall(b"".join(packets))

    def close(self) -> None:
        self.device.close()
        self.daq._close_stream_socket()


@pytest.fixture
def wire() -> Iterator[Wire]:
    w = Wire()
    yield w
    w.close()


@pytest.mark.parametrize("status", [SCAN_OVERLAP, RECOVER_OVERFLOW, BUFFER_FULL])
def test_the_error_of_a_status_that_ends_the_stream_carries_every_scan_before_it(wire: Wire, status: int) -> None:
    """Scans 0–1 collected; then scans 2–7 in three packets and a header-only packet with the status: the error
    names the device and the status in one line and its block holds scans 2–7, values and numbers."""
    wire.send(packet(0, scans(0, 2)))
    assert wire.daq.collect(timeout=0.0).n == 2
    wire.send(packet(1, scans(2, 2)), packet(2, scans(4, 2)), packet(3, scans(6, 2)), packet(4, [], status))
    with pytest.raises(StreamEndedError) as err:
        wire.daq.collect(timeout=0.0)
    assert str(err.value).startswith("daq: ") and str(status) in str(err.value) and "\n" not in str(err.value)
    block = err.value.block
    assert (block.first_scan, block.n) == (2, 6) and status in block.statuses and block.done
    np.testing.assert_allclose(block.volts, volts(2, 6), rtol=0, atol=1e-12)
    assert block.valid.all()
    assert not wire.daq.streaming  # the device sends no more


def test_the_fatal_packets_own_scans_are_in_the_block_too(wire: Wire) -> None:
    """A packet that carries the status and samples: its scans are measured data as well."""
    wire.send(packet(0, scans(0, 2)), packet(1, scans(2, 2), RECOVER_OVERFLOW))
    with pytest.raises(StreamEndedError) as err:
        wire.daq.collect(timeout=0.0)
    assert (err.value.block.first_scan, err.value.block.n) == (0, 4)
    np.testing.assert_allclose(err.value.block.volts, volts(0, 4), rtol=0, atol=1e-12)


def test_complete_of_a_burst_the_device_ends_carries_the_blocks_collected_before_it_too() -> None:
    """A burst of 100 scans; between the complete's collects (its poll sleeps) the device sends two packets, then
    a packet with 2945: the error's block holds every scan since the complete began (0–3), in order."""
    due = iter([[packet(1, scans(2, 2))], [packet(2, [], BUFFER_FULL)]])
    w: Wire

    def sleep(_s: float) -> None:
        w.send(*next(due))

    w = Wire(num_scans=100, sleep=sleep)
    try:
        w.send(packet(0, scans(0, 2)))
        with pytest.raises(StreamEndedError) as err:
            w.daq.complete(poll=0.01)
        assert (err.value.block.first_scan, err.value.block.n) == (0, 4)
        np.testing.assert_allclose(err.value.block.volts, volts(0, 4), rtol=0, atol=1e-12)
        assert BUFFER_FULL in err.value.block.statuses
    finally:
        w.close()


def test_a_stop_returns_the_scans_of_a_stream_the_device_had_ended(wire: Wire) -> None:
    """The fatal packet arrives while the host stops the stream (it had not collected it yet): the stop returns
    the scans before it; its STREAM_ENABLE = 0 is not sent to a stream the driver knows has ended."""
    wire.send(packet(0, scans(0, 2)))
    assert wire.daq.collect(timeout=0.0).n == 2
    wire.send(packet(1, scans(2, 2)), packet(2, [], SCAN_OVERLAP))
    wire.daq.streaming = False  # (no Modbus link here: the stop's write is not what this checks)
    block = wire.daq.stop()
    assert block is not None and (block.first_scan, block.n) == (2, 2) and SCAN_OVERLAP in block.statuses
    np.testing.assert_allclose(block.volts, volts(2, 2), rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------- the twin
def _transact(sock: socket.socket, request: bytes) -> bytes:
    sock.sendall(request)
    head = sock.recv(6, socket.MSG_WAITALL)
    return head + sock.recv(struct.unpack(">H", head[4:6])[0], socket.MSG_WAITALL)


def _wait_for(done: Callable[[], bool]) -> None:
    """Until ``done()`` (the twin acts on a clock move on its own thread): a condition, the limit only a guard."""
    end = time.monotonic() + 60.0
    while not done():
        assert time.monotonic() < end, "the twin did not get there"
        time.sleep(0.001)


def test_twin_ends_the_stream_with_2943_when_its_skipped_scan_counter_overflows() -> None:
    """[E] (LabJack's low-level stream example) the skipped-scan counter of auto-recovery is 16 bits (AddInfo):
    ([A]) the 65,535th skipped scan still counts, the 65,536th overflows it, and the device ends the stream with
    2943 (STREAM_AUTO_RECOVER_END_OVERFLOW). 1 kHz, AIN0/1, 4 samples (2 scans) a packet of 24 bytes, the default
    4096-byte buffer, no client reading: scans 0–499 fill 250 packets (6000 bytes unsent), scans from 500 on are
    skipped. Scan k is due at (k + 1) ms: at 66.0355 s scans 500–66034 (65,535) are skipped, at 66.0365 s one more.
    A client then gets the 250 kept packets and, numbered next, one with status 2943; STREAM_ENABLE reads 0."""
    clock = VirtualClock()
    sim = LabJackT7Sim(Plant(clock, MembraneParams(), hv=HVStage()), clock, noise=False)
    port, stream_port = sim.start()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
            for f in ["0010 0000 000b 01 10 0fa2 0002 04 447a 0000", "0011 0000 000b 01 10 0fa4 0002 04 0000 0002",
                      "0012 0000 000b 01 10 0fa6 0002 04 0000 0004", "0013 0000 000b 01 10 0fb0 0002 04 0000 0001",
                      "0014 0000 000f 01 10 1004 0004 08 0000 0000 0000 0002",
                      "0015 0000 000b 01 10 137e 0002 04 0000 0001"]:  # 1 kHz, AIN0/1, 4 samples, enable
                assert _transact(s, bytes.fromhex(f))[7] == 0x10
            clock.advance(0.5005)
            _wait_for(lambda: sim.packets_sent == 250)
            clock.advance(66.0355 - 0.5005)
            _wait_for(lambda: sim.skipped == 65_535)
            assert sim.streaming
            clock.advance(0.001)
            _wait_for(lambda: not sim.streaming)
            enable = _transact(s, bytes.fromhex("0016 0000 0006 01 03 137e 0002"))  # FC3 STREAM_ENABLE (4990)
            assert enable[7] == 0x03 and struct.unpack(">I", enable[9:13])[0] == 0
        with socket.create_connection(("127.0.0.1", stream_port), timeout=60.0) as data:
            kept = data.recv(250 * 24, socket.MSG_WAITALL)
            assert [struct.unpack(">H", kept[k:k + 2])[0] for k in range(0, len(kept), 24)] == list(range(250))
            tid, proto, length, unit, fn, typ, _, _, status, _ = struct.unpack(">HHHBBBBHHH",
                                                                                data.recv(16, socket.MSG_WAITALL))
        # the scans before the overflow were all in the 250 packets: the last packet carries none
        assert (tid, proto, length, unit, fn, typ, status) == (250, 0, 10, 1, 0x4C, 16, RECOVER_OVERFLOW)
    finally:
        sim.stop()
    assert not sim.errors


# ---------------------------------------------------------------------------- a run on the simulated DAQ rig
def test_a_run_whose_stream_the_t7_ends_records_every_scan_up_to_the_fatal_packet_and_stops_at_0_v(
        tmp_path: Path) -> None:
    """At run time 3 s (7-kV waveform, virtual time) the T7 twin ends the stream with 2943: its last packet follows
    the scans it took by then. The run ends in error naming the status, the output at 0 V; the amplifier stream
    of the run file holds that stream's scans up to the last the device sent — scan number ``produced − 1``, the
    twin's count (scan k at t_scan0 + k/rate on the run clock, ``t_scan0`` from the stream's timing event)."""
    ended: dict[str, float] = {}

    def end(_engine: Engine, sim: SimRig) -> None:
        twin = sim.twins["daq"]
        twin.end_stream(RECOVER_OVERFLOW)
        ended["produced"], ended["rate"] = twin.produced, twin.rate

    result, run, plant = run_with_fault(DAQ_RIG, tmp_path, 3.0, end, virtual=True)
    assert result.state == "error" and str(RECOVER_OVERFLOW) in result.reason, result.reason
    assert run.state == "error" and f"device status {RECOVER_OVERFLOW}" in run.reason, run.reason
    assert "STREAM_AUTO_RECOVER_END_OVERFLOW" in run.reason
    assert abs(plant.sim.plant.observe().v_out[-1]) <= ZERO_V  # type: ignore[attr-defined]
    assert plant.high_after(plant.t_fault) > ZERO_V  # high voltage when the stream ended: the trial tests something
    # scan 0 of each stream on the run clock; the ended stream's is the last before the fault, the ramp's follows
    t_fault = 3.0
    starts = [float(text.split("scan 0 at ")[1].split(" s")[0]) for text in events(run, "timing")
              if "scan 0 at" in text]
    scan0 = max(t for t in starts if t <= t_fault)
    ramp0 = min(t for t in starts if t > t_fault)
    rate = ended["rate"]
    t = run.streams["amplifier"].t
    ours = t[(t >= scan0 - 0.5 / rate) & (t < ramp0 - 0.5 / rate)]
    last = round((float(ours[-1]) - scan0) * rate)
    assert last == ended["produced"] - 1
