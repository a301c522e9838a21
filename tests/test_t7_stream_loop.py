"""Stream-out looping on the T7: the twin's loop registers as LabJack documents them, the driver writing a repeating
waveform once, and a periodic protocol on a simulated DAQ rig recording what the refill path records.

Sources of the expected behaviour (not the code under test): the register map (ljm_constants.json)
STREAM_OUT#_LOOP_NUM_VALUES "the number of values, from the end of the array, that will be repeated after reaching
the end of supplied data array", SET_LOOP "1 = use new data immediately"; LabJack's stream-out update example: a set
of values set with SET_LOOP "will not be interrupted until their loop is complete", then the next data plays. The
watchdog's action stopping a loop, and BUFFER_STATUS counting the loop, are the twin's stated choices
(sim_devices/t7/stream_out.py [A]).
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from bench.benchmarks import noise_free_rig
from bench.runtime import hardware_timed
from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from drivers.labjack import StreamIn, StreamOut, StreamSpec
from sim_devices.t7.analog import Conditioning
from sim_devices.t7.stream_out import Tail
from tests.conftest import ROOT
from tests.test_labjack import Rig, _transact

RATE = 10_000.0
TARGET, ALLOC, LOOP, SET_LOOP, STATUS, BUFFER = 4040, 4050, 4060, 4070, 4080, 4420  # STREAM_OUT0_* [register map]


def _mbfb(tid: int, *frames: tuple[int, list[int]]) -> bytes:
    """A Modbus Feedback request (function 76) of write frames: type 1, address, registers, big-endian values."""
    body = b"".join(struct.pack(f">BHB{len(v)}H", 1, a, len(v), *v) for a, v in frames)
    return struct.pack(">HHHBB", tid, 0, 2 + len(body), 1, 76) + body


def _u32(x: int) -> list[int]:
    return [x >> 16, x & 0xFFFF]


def _write(sock: socket.socket, tid: int, *frames: tuple[int, list[int]]) -> None:
    """Send the frames (a buffer's values in frames of at most 255 registers, packets within 1040 bytes) and check
    each reply is the write-only MBFB reply: transaction id, protocol 0, length 2, unit 1, function 76."""
    split = [(a, v[i:i + 255]) for a, v in frames for i in range(0, max(len(v), 1), 255)]
    while split:
        part = []
        while split and 8 + sum(4 + 2 * len(v) for _, v in part + split[:1]) <= 1040:
            part.append(split.pop(0))
        assert _transact(sock, _mbfb(tid, *part)) == struct.pack(">HHHBB", tid, 0, 2, 1, 76)


def _scheduled(rig: Rig, first: int, n: int) -> list[int | None]:
    """The codes stream-out 0 will play at scans first … first + n − 1 (None: nothing there)."""
    got: dict[int, int] = {}
    for p in rig.sim.outs[0].sched:
        got.update((p.first + i, int(c)) for i, c in enumerate(p.codes))
    return [got.get(k) for k in range(first, first + n)]


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(watchdog_s=1)  # the driver loops only with the watchdog armed
    r.daq.connect()
    yield r
    r.close()
    assert not r.sim.errors


def _raw_stream_out(rig: Rig, *frames: tuple[int, list[int]]) -> socket.socket:
    """A stream armed by the driver (AIN0 in, stream-out 0 on DAC0), its buffer then set up again by raw MBFB
    bytes: allocation (empties it), then ``frames``; the caller kicks the stream off."""
    rig.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, np.array([2.5]))))
    sock = socket.create_connection(("127.0.0.1", rig.port), timeout=2)
    _write(sock, 1, (TARGET, _u32(1000)), (ALLOC, _u32(4096)))
    _write(sock, 2, *frames)
    return sock


def test_the_values_a_loop_is_taken_from_are_the_last_written_as_a_bounded_queue_keeps_them() -> None:
    """The twin's ring of the last values written (LOOP_NUM_VALUES counts "from the end of the array") against a
    plain bounded deque, through writes shorter than, equal to and longer than its size, and wrapping."""
    from collections import deque

    rng = np.random.default_rng(3)
    tail, ref = Tail(15), deque(maxlen=15)
    assert tail.last(5).size == 0
    for n in (4, 9, 15, 1, 40, 7, 0, 16, 3):
        values = rng.integers(0, 65536, n)
        tail.extend(values)
        ref.extend(values.tolist())
        assert len(tail) == len(ref)
        for k in (1, 5, 15, 20):  # more than kept: all that is kept
            assert tail.last(k).tolist() == list(ref)[max(len(ref) - k, 0):]


@pytest.mark.parametrize(("loop_num", "after"), [
    (3, [300, 400, 500, 300, 400, 500]),
    (7, [100, 200, 300, 400, 500, 100]),  # [A] more than were written: all of them repeat
])
def test_after_the_data_the_last_loop_num_values_repeat(rig: Rig, loop_num: int, after: list[int]) -> None:
    data = [100, 200, 300, 400, 500]
    with _raw_stream_out(rig, (LOOP, _u32(loop_num)), (BUFFER, data), (SET_LOOP, _u32(1))) as sock:
        rig.daq.kickoff()
        rig.sim.pump()
        assert _scheduled(rig, 0, 11) == data + after
        sock.close()


def test_data_written_while_a_loop_repeats_plays_when_the_repetition_in_progress_is_complete(rig: Rig) -> None:
    loop = list(range(1000, 2000))
    with _raw_stream_out(rig, (LOOP, _u32(1000)), (BUFFER, loop), (SET_LOOP, _u32(1))) as sock:
        rig.daq.kickoff()
        rig.clock.advance(0.25)  # scan 2500 runs: the second repetition (scans 2000–2999)
        rig.sim.pump()
        _write(sock, 3, (BUFFER, [7, 8, 9]))
        # waiting for SET_LOOP: the loop goes on; BUFFER_STATUS counts the loop's values and the new ones
        assert _scheduled(rig, 3000, 2) == [1000, 1001]
        status = _transact(sock, bytes.fromhex("0004 0000 0006 01 03 0ff0 0002"))
        assert int.from_bytes(status[9:13], "big") == 2 * (1000 + 3)
        _write(sock, 5, (LOOP, _u32(1)), (SET_LOOP, _u32(1)))
        assert _scheduled(rig, 2600, 400) == loop[600:]  # the repetition in progress is not interrupted
        assert _scheduled(rig, 3000, 4) == [7, 8, 9, None]  # then the new data; the output holds its last value
        rig.clock.advance(0.1)
        rig.sim.pump()
        assert rig.sim.outs[0].code == 9 and rig.sim.outs[0].underrun_scans == 0


def test_a_loop_not_pumped_for_longer_than_was_queued_plays_on_in_phase() -> None:
    """The device repeats a loop whatever its host does: after 3.05 s in which the twin was not pumped (more than
    the 1–2 s it queues), the output is the loop's phase, not where the queue stopped: scan k (run at (k + 1)/rate
    after the start) plays code 1000 + k mod 1000, so at 3.05 s the last scan run is 30,499 (code 1499) and 30,500
    is next (1500); no scan is an underrun (no watchdog armed here: nothing stops the loop)."""
    r = Rig()
    try:
        r.daq.connect()
        with _raw_stream_out(r, (LOOP, _u32(1000)), (BUFFER, list(range(1000, 2000))), (SET_LOOP, _u32(1))) as sock:
            r.daq.kickoff()
            r.sim.pump()
            r.clock.advance(3.05)
            r.sim.pump()
            o = r.sim.outs[0]
            assert o.code == 1499 and o.underrun_scans == 0
            assert _scheduled(r, 30_500, 3) == [1500, 1501, 1502]
            sock.close()
    finally:
        r.close()


def test_a_loop_is_planned_on_codes_that_repeat_exactly_and_only_where_it_saves_writes() -> None:
    """Expected periods and run lengths read off the made-up codes themselves."""
    from drivers.labjack.looping import Loop, periodic_run, plan_loop

    period = np.array([3, 1, 4, 1, 5, 9, 2, 6])
    codes = np.concatenate([np.tile(period, 10), [7]])  # 10 periods of 8, then an end value
    assert periodic_run(codes, 100) == (8, 80)
    assert periodic_run(np.full(30, 5), 100) == (1, 30)  # a hold: period 1
    assert periodic_run(np.arange(100), 100) == (0, 0)  # a ramp never repeats
    assert periodic_run(codes, 7) == (0, 0)  # the period is longer than allowed
    bumped = codes.copy()
    bumped[50] += 1  # one code off in the 7th period: the run ends there
    assert periodic_run(bumped, 100) == (8, 50)
    # blocks of whole periods, at least min_block long: 8 → 10 blocks; 12 → two periods (16), 5 blocks;
    # 20 → three periods (24), only 3 blocks (< 4: refilling costs as little); a block over max_block: none
    assert plan_loop(codes, 1000, 8, 40) == Loop(1000, 8, 10) and Loop(1000, 8, 10).end == 1080
    assert plan_loop(codes, 1000, 12, 40) == Loop(1000, 16, 5)
    assert plan_loop(codes, 1000, 20, 40) is None
    assert plan_loop(codes, 1000, 20, 20) is None


def test_a_long_run_is_measured_to_its_first_differing_code() -> None:
    """Runs longer than the first stretch the search compares (4,096 codes), ended by one code far in: the run
    length is the index of that code (as for the 7th-period bump above), or every code when none differs."""
    from drivers.labjack.looping import periodic_run

    codes = np.tile(np.array([2, 7, 1, 8, 2, 8, 1]), 3000)  # 21,000 codes of period 7 (the window recurs only there)
    assert periodic_run(codes, 100) == (7, 21_000)
    for at in (4_102, 4_103, 15_000, 20_999):  # k = at − 7: the first stretch's last, the second's first, …
        bumped = codes.copy()
        bumped[at] += 1
        assert periodic_run(bumped, 100) == (7, at)


def _sine(periods: int, period_s: float = 0.5) -> np.ndarray:
    """DAC volts of ``periods`` sine periods at RATE scans/s, ending on the start value."""
    t = np.arange(round(periods * period_s * RATE) + 1) / RATE
    return 2.5 + 0.5 * np.sin(2 * np.pi * t / period_s)


def _play(rig: Rig, volts: np.ndarray, loops: bool, extra_s: float = 0.3) -> np.ndarray:
    """Play ``volts`` with 0.5 s kept ahead (the run time's OUT_AHEAD_S), collected every 0.25 s of rig time as the
    engine collects in virtual time, with its keep-alive request (the watchdog counts silence of the command
    port); returns the V monitor's scans."""
    rig.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, volts), out_ahead_s=0.5,
                           out_loops=loops))
    rig.daq.kickoff()
    blocks = []
    while rig.daq.scans_received < volts.size + extra_s * RATE:
        rig.clock.advance(0.25)
        blocks.append(rig.daq.collect(until=rig.clock.now()).volts[:, 0])
        rig.daq.read_dac(0)
    rig.daq.stop()
    return np.concatenate(blocks)


def test_a_periodic_drive_is_written_once_and_plays_what_the_refill_path_plays() -> None:
    """Ten periods of 5000 scans: the refill path writes all 50,001 values; looped, the host writes the period
    once (the block: 5000 values, the 0.5 s kept ahead) and, in the last repetitions, what follows it — no more
    than a block and the end value — and the monitor records the same samples."""
    volts = _sine(10)
    got = {}
    written = {}
    for loops in (True, False):
        r = Rig(watchdog_s=1)
        try:
            r.daq.connect()
            got[loops] = _play(r, volts, loops)
            o = r.sim.outs[0]
            written[loops] = (o.values_written, o.loops_set)
            assert r.daq.out_underrun_scans == 0 and o.underrun_scans == 0
        finally:
            r.close()
        assert not r.sim.errors
    assert written[False] == (volts.size, 0)
    assert written[True][1] == 1 and written[True][0] <= 2 * 5000 + 1
    n = min(got[True].size, got[False].size)
    assert n > volts.size and np.array_equal(got[True][:n], got[False][:n])


def test_behind_a_reconstruction_filter_a_looped_drive_reaches_the_amplifier_as_the_refilled_one() -> None:
    """The rig's first-order low-pass (30 Hz, as thesis-daq-sim) filters the scans in order: where the twin cuts a
    loop's queued repetitions, the filter goes on from the value it had after the last repetition played — the
    amplifier input (the V monitor, noise off) is the refilled drive's, bit for bit."""
    got = {}
    for loops in (True, False):
        r = Rig(watchdog_s=1)
        r.sim.conditioning = r.cond = Conditioning(4.0, -10.0, corner_Hz=30.0)
        try:
            r.daq.connect()
            got[loops] = _play(r, np.concatenate([_sine(8), np.full(3000, 2.6)]), loops)
            assert r.sim.outs[0].loops_set == int(loops)
        finally:
            r.close()
        assert not r.sim.errors
    n = min(got[True].size, got[False].size)
    assert np.array_equal(got[True][:n], got[False][:n])


def test_a_loop_the_host_does_not_leave_in_time_is_an_underrun(rig: Rig) -> None:
    """The host stalls past the loop's last repetition: the device has repeated the period where the program has
    something else — reported as an underrun (the run time trips its interlock on it)."""
    volts = np.concatenate([_sine(8), np.full(20_000, 2.0)])
    rig.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, volts), out_ahead_s=0.5,
                           out_loops=True))
    rig.daq.kickoff()
    rig.clock.advance(0.25)
    rig.daq.collect(until=rig.clock.now())
    assert rig.sim.outs[0].loops_set == 1 and rig.daq.out_underrun_scans == 0
    rig.clock.advance(4.5)  # the 8 periods end at 4 s
    rig.daq.collect(until=rig.clock.now(), timeout=5.0)
    assert rig.daq.out_underrun_scans > 0
    rig.daq.stop()


def test_a_lost_host_stops_a_looping_drive_by_the_watchdog() -> None:
    """The T7's watchdog (1 s) with its DAC action (2.5 V: 0 V at the amplifier through the rig's 4·V − 10): a
    host that goes silent while a loop repeats leaves the amplifier input at 0 V once the timeout has passed."""
    r = Rig(watchdog_s=1)
    daq = r.daq
    try:
        daq.connect()
        daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, _sine(40)), out_ahead_s=0.5,
                               out_loops=True))
        daq.kickoff()
        for _ in range(4):
            r.clock.advance(0.25)
            daq.collect(until=r.clock.now())
        assert r.sim.outs[0].loops_set == 1
        last = r.clock.now()  # the host is lost: nothing more
        for _ in range(20):
            r.clock.advance(0.1)
            r.sim.pump()
        r.plant.observe()
        assert r.plant.watchdog_tripped and r.plant.v_in == 0.0 and r.clock.now() > last + 1.0
        assert r.sim.outs[0].loop.size == 0  # the loop no longer plays
    finally:
        daq.close()
        r.sim.stop()
    assert not r.sim.errors


def test_without_the_watchdog_the_driver_refuses_to_loop() -> None:
    """A loop outlives a lost host until something stops it; on a T7 whose watchdog the driver has not armed nothing
    would: arming a looping stream-out is refused, one line naming the device; the refill path stays allowed."""
    r = Rig()  # no watchdog
    try:
        r.daq.connect()
        with pytest.raises(ValueError, match=r"T7.*watchdog"):
            r.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, _sine(8)), out_ahead_s=0.5,
                                 out_loops=True))
        r.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, _sine(8)), out_ahead_s=0.5))
    finally:
        r.close()


# ---------------------------------------------------------------------------- a periodic protocol on a DAQ rig
PERIODIC = """
[protocol]
name = "periodic"
description = "a periodic drive: 2-Hz raised cosine, 6 cycles, then a pause"
rig = "{rig}"

[specimen]
hung_mass_kg = 0.18

[recording]
displacement_Hz = 2000
setpoint_Hz = 100
monitors_Hz = 5

[[steps]]
type = "waveform"
name = "drive"
channel = "voltage"
kind = "raised_cosine"
amplitude = "5 kV"
frequency_Hz = 2.0
cycles = 6

[[steps]]
type = "relax"
name = "pause"
duration_s = 0.5
"""


def _periodic_protocol(tmp: Path) -> Path:
    """The protocol above on a noise-free copy of the isotonic DAQ rig (golden comparison: same bits)."""
    rig = noise_free_rig(ROOT / "rigs" / "lsdea-isotonic-daq-sim.toml", tmp)
    proto = tmp / "periodic.toml"
    proto.write_text(PERIODIC.format(rig=rig))
    return proto


def test_a_periodic_protocol_on_a_daq_rig_writes_its_period_once_and_records_the_refill_paths_samples(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    proto = _periodic_protocol(tmp_path)
    records, out = {}, {}
    twins: list = []
    for loops in (True, False):
        monkeypatch.setattr(hardware_timed, "OUT_LOOPS", loops)
        result = execute(plan_run(proto), tmp_path / f"run-{loops}.h5", virtual=True,
                         on_engine=lambda _e, sim: twins.append(sim.twins["daq"]))
        assert result.state == "completed"
        f = open_run(result.path)
        records[loops] = {(s, c): np.asarray(v) for s, stream in f.streams.items()
                          for c, v in [("t", stream.t), *stream.columns.items()]}
        o = twins[-1].outs[0]
        out[loops] = (o.loops_set, o.values_written)
    assert out[False][0] == 0 and out[True][0] == 1  # one loop: the 2-Hz period (5000 scans) written once
    # 6 periods + the pause: refilled, every value; looped, at most the block and what follows its last repetitions
    assert out[True][1] <= out[False][1] - 3 * 5000
    assert records[True].keys() == records[False].keys()
    for key, values in records[True].items():
        assert np.array_equal(values, records[False][key], equal_nan=True), key
    assert records[True][("amplifier", "voltage")].max() > 4000.0  # the drive was played


def test_a_stop_during_a_looping_step_brings_the_output_to_zero_and_keeps_it_there(tmp_path: Path) -> None:
    """A stop requested while the T7 repeats the 2-Hz period: the stream stops (its loop with it), the host zeroes
    the output, and two seconds later nothing has played the loop again."""
    proto = _periodic_protocol(tmp_path)
    sims, twins = [], []

    def hook(engine, sim) -> None:
        sims.append(sim)
        twins.append(sim.twins["daq"])

        def stop() -> None:
            for _ in range(50_000):  # ≤ 100 s of wall clock; the run reaches 1.5 s of rig time long before
                if engine.snapshot.state != "starting" and engine.now() >= 1.5:
                    break
                threading.Event().wait(0.002)
            engine.request_stop("stopped by the test")
        threading.Thread(target=stop, daemon=True).start()

    result = execute(plan_run(proto), tmp_path / "stopped.h5", virtual=True, on_engine=hook)
    assert result.state == "interrupted" and "stopped by the test" in result.reason, (result.state, result.reason)
    assert twins[0].outs[0].loops_set == 1  # stopped while the loop played
    sim = sims[0]
    sim.clock.advance(2.0)  # long after the stop: nothing plays the loop any more
    assert np.all(np.abs(sim.plant.observe().v_out) < 5.0)
    assert [t for t, _, k, _ in open_run(result.path).event_list() if k == "safe"]


class _ToppedUpDaq:
    """A DAQ whose every collect tops up its stream-out (a request the T7 answers) and whose reads are counted."""

    timeout = 0.5
    out_underrun_scans = 0

    def __init__(self, clock) -> None:
        self.clock, self.reads, self.answered_at, self.tops_up = clock, 0, -np.inf, True

    def collect(self, until: float | None = None, timeout: float = 1.0):
        from drivers.interfaces import StreamBlock

        if self.tops_up:
            self.answered_at = self.clock.now()
        return StreamBlock(0, 0.0, 1e-4, ("vmon",), np.empty((0, 1)), np.empty((0, 1), bool))

    def read_dac(self, dac: int) -> float:
        self.reads += 1
        return 0.0


def test_a_collect_that_topped_up_the_stream_out_needs_no_keepalive_request() -> None:
    """Any request clears the T7's watchdog timer (register map, WATCHDOG_*): a collect whose stream-out top-up the
    T7 answered has fed it, so no separate command-response read is sent; one that wrote nothing still sends it."""
    import types

    from bench.core.clock import VirtualClock
    from bench.rig import load_rig
    from bench.runtime.hardware_timed import HardwareTimed
    from bench.runtime.polls import COLLECT_PERIOD_VIRTUAL_S

    clock = VirtualClock(100.0)
    daq = _ToppedUpDaq(clock)
    ctx = types.SimpleNamespace(clock=clock, guard=lambda streaming=False: None)
    hw = HardwareTimed(load_rig(ROOT / "rigs" / "thesis-daq-sim.toml"), daq, object(), ctx)  # type: ignore[arg-type]
    hw._keepalive = clock.now()
    for _ in range(8):
        clock.advance(COLLECT_PERIOD_VIRTUAL_S)
        hw.collect()
    assert daq.reads == 0
    daq.tops_up = False  # nothing to write (a loop plays): the keep-alive goes out every period
    for _ in range(4):
        clock.advance(COLLECT_PERIOD_VIRTUAL_S)
        hw.collect()
    assert daq.reads == 4


@pytest.mark.parametrize(("simulated", "virtual", "watchdog_s", "loops"), [
    (True, True, 1.0, True),  # the one case: a simulated rig in virtual time with its watchdog configured
    (True, False, 1.0, False),  # a wall-clock rehearsal takes the lab rig's path
    (False, True, 1.0, False),  # a lab rig: not until the watchdog's action on a loop is checked on hardware
    (True, True, None, False),  # no watchdog (--allow-no-watchdog): nothing would stop a loop
])
def test_a_run_loops_its_stream_out_only_in_virtual_time_on_a_simulated_rig_with_a_watchdog(
        simulated: bool, virtual: bool, watchdog_s: float | None, loops: bool) -> None:
    from types import SimpleNamespace

    side = SimpleNamespace(simulated=simulated, ctx=SimpleNamespace(clock=SimpleNamespace(virtual=virtual)),
                           cfg=SimpleNamespace(watchdog_s=watchdog_s))
    assert hardware_timed.HardwareTimed._loops(side) is loops  # type: ignore[arg-type]


def test_a_buffer_emptied_after_a_cut_loop_takes_a_whole_buffer_again() -> None:
    """A loop of 4000 values at 1 kHz, cut (LOOP_NUM 0 + SET_LOOP 1) mid-repetition, leaves scans without data
    before that repetition's end; once played out, BUFFER_STATUS reads 0 and the buffer takes alloc/2 − 1 = 8191
    values again, as the datasheet's buffer rule says. The faster append path took the empty scans for data and
    refused packets as full (exception 4) while the status read 0 (found in review)."""
    r = Rig()
    r.daq.connect()
    try:
        r.daq.arm(StreamSpec(1000.0, (StreamIn(0, name="vmon"),), StreamOut(0, np.array([2.5]))))
        sock = socket.create_connection(("127.0.0.1", r.port), timeout=2)
        _write(sock, 1, (TARGET, _u32(1000)), (ALLOC, _u32(16384)))
        _write(sock, 2, (LOOP, _u32(4000)))
        _write(sock, 3, (BUFFER, list(range(1000, 5000))))
        _write(sock, 4, (SET_LOOP, _u32(1)))
        r.daq.kickoff()
        r.sim.pump()
        for t in (3.5, 4.6):
            r.clock.advance(t - r.clock.now() + r.sim.t_enable)
            r.sim.pump()
        _write(sock, 5, (LOOP, _u32(0)), (SET_LOOP, _u32(1)))
        r.clock.advance(6.7 - r.clock.now() + r.sim.t_enable)
        r.sim.pump()
        status = _transact(sock, struct.pack(">HHHBBHH", 6, 0, 6, 1, 3, STATUS, 2))
        assert int.from_bytes(status[9:13], "big") == 0  # nothing left to play
        _write(sock, 7, (BUFFER, list(range(20000, 20000 + 8191))))  # every packet answered as written
        sock.close()
    finally:
        r.close()


def test_a_stream_armed_after_one_stopped_mid_loop_plays_its_data_and_is_topped_up(rig: Rig) -> None:
    """A pause stops a stream while its loop repeats; the next stream's values then play as data. [D] every buffer
    update is LOOP_NUM_VALUES, the values, SET_LOOP (T-series datasheet, "Performing Stream-Out"), LOOP_NUM_VALUES
    "the number of values, from the end of the array, that will be repeated"; nothing there says allocating the
    buffer resets it (the twin keeps it, as a register keeps what was written). An arm that did not write it left
    the stopped stream's loop size in force: the preload's last 5000 values repeated in the device, and with the
    loop counted in the buffer ([A], module docstring) the first top-up (2500 values, half the preload still
    unplayed) no longer fit its alloc/2 − 1 = 8191 values: refused, STREAM_OUT_BUFF_FULL (2613) — the error a
    pause in a looping relax ended a run with."""
    spec = StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, _sine(8)), out_ahead_s=0.5, out_loops=True)
    rig.daq.arm(spec)
    rig.daq.kickoff()
    for _ in range(4):  # into the loop's repetitions (its block is ≥ the 0.5 s kept ahead: 5000 values)
        rig.clock.advance(0.25)
        rig.daq.collect(until=rig.clock.now())
        rig.daq.read_dac(0)  # the run time's keep-alive: the watchdog does not stop the loop
    assert rig.sim.outs[0].loop_active and rig.sim.outs[0].loop.size >= 5000  # stopped while it repeats
    rig.daq.stop()
    # the next stream: a 2-s ramp, kept 0.5 s ahead, no loops of its own (every update is data)
    ramp = np.linspace(1.0, 3.0, 20_001)
    rig.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, ramp), out_ahead_s=0.5))
    rig.daq.kickoff()
    got: dict[int, int] = {}
    for _ in range(10):  # every top-up is taken
        rig.clock.advance(0.25)
        rig.daq.collect(until=rig.clock.now())
        rig.daq.read_dac(0)
        got.update((p.first + i, int(c)) for p in rig.sim.outs[0].sched if not p.loop
                   for i, c in enumerate(p.codes))
    assert rig.sim.outs[0].loop.size <= 1  # no loop set on the new stream's data
    assert rig.daq.out_underrun_scans == 0
    codes = rig.daq.cal.dac_codes(ramp, 0, None, rig.daq.dac_bits)
    assert [got.get(k) for k in range(5000, 5010)] == [int(c) for c in codes[5000:5010]]  # the data, in order
    rig.daq.stop()
