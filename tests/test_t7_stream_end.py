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
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from bench.core.clock import VirtualClock
from drivers.errors import StreamEndedError
from drivers.labjack import LabJackT7, StreamIn, StreamSpec
from drivers.labjack.plan import StreamPlan, StreamState

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
