"""The T7 twin pumping on demand in virtual time: packets leave when the host waits on the twin (or after a step of
rig time without a host), not at every move of the clock — the same packets, only fewer pumps.

Expected values come from the datasheet's stream layout and timing (T-Series Datasheet §3.2, LabJack's low-level
stream example: TransID +1 per packet, Length 10 + 2·n, backlog = bytes still buffered after the packet, scan k at
t_enable + (k + 1) / rate, a burst's last packet short with status 2944) and from a run of the same protocol with
the twin pumping at every move of the clock (today's mode), not from the code under test.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import drivers.labjack.stream_in as driver_stream_in
from bench.core.clock import VirtualClock
from bench.runtime.run import execute, plan_run
from bench.runtime.sim_rig import SimRig
from bench.storage.runfile import open_run
from drivers.errors import InstrumentTimeoutError
from drivers.labjack import LabJackT7, StreamIn, StreamOut, StreamSpec
from drivers.labjack.packets import StreamBatch
from sim_devices.labjack_t7 import LabJackT7Sim
from sim_devices.transport import Faults, TwinTimer
from tests.conftest import ROOT
from tests.test_labjack import STREAM_WAIT_S, Rig, _transact, _wait_for

# 1 kHz, AIN0/1, 4 samples a packet, spontaneous stream, enable (hand-written Modbus TCP frames, as test_labjack)
CONFIG = ["0010 0000 000b 01 10 0fa2 0002 04 447a 0000", "0011 0000 000b 01 10 0fa4 0002 04 0000 0002",
          "0012 0000 000b 01 10 0fa6 0002 04 0000 0004", "0013 0000 000b 01 10 0fb0 0002 04 0000 0001",
          "0014 0000 000f 01 10 1004 0004 08 0000 0000 0000 0002", "0015 0000 000b 01 10 137e 0002 04 0000 0001"]
PRODUCT_ID = bytes.fromhex("0020 0000 0006 01 03 ea60 0002")  # FC3 PRODUCT_ID (60000): a round trip, nothing else
RATE = 10_000.0


def _configure(s: socket.socket) -> None:
    for f in CONFIG:
        assert _transact(s, bytes.fromhex(f))[7] == 0x10


def _round_trip(s: socket.socket) -> None:
    """A request answered: a wake the clock queued on the twin's thread before it has run by then."""
    assert _transact(s, PRODUCT_ID)[-4:] == bytes.fromhex("40e0 0000")


def test_a_twin_timer_tells_the_twin_before_each_blocking_read_not_for_a_look_or_a_withheld_reply() -> None:
    """``waiting`` is called each time the driver is about to block (``left`` > 0), never for a look (timeout 0) or
    once the twin has withheld the reply (the wait ends at once)."""
    clock = VirtualClock()
    faults = Faults(clock=clock.now)
    calls: list[float] = []
    timer = TwinTimer(faults, clock, waiting=lambda: calls.append(clock.now()))
    timer.sending()
    wait = timer.start(1.0)
    assert wait.left() > 0 and wait.left() > 0 and len(calls) == 2
    assert timer.start(0.0).left() == 0.0 and len(calls) == 2
    faults.withheld += 1  # the twin swallowed the reply
    assert wait.left() == 0.0 and len(calls) == 2


@pytest.fixture
def raw_twin() -> Iterator[Rig]:
    r = Rig()
    r.sim.poll = 3600.0  # the wall-clock poll never comes: only the clock and the host's waits pump
    r.sim.on_demand()
    yield r
    r.sim.stop()


def _demand_rig(watchdog_s: int | None = None) -> Rig:
    """The driver on the twin as a virtual-time run wires them: its waits tell the twin (poll: never)."""
    r = Rig(watchdog_s=watchdog_s)
    r.sim.poll = 3600.0
    r.daq = LabJackT7("127.0.0.1", port=r.port, stream_port=r.stream_port, clock=r.clock.now, sleep=r.clock.sleep,
                      safe_dac=(2.5, 0.0), timeout=1.0, watchdog_s=watchdog_s,
                      timer=TwinTimer(r.sim.faults, r.clock, waiting=r.sim.on_demand()))
    r.daq.connect()
    return r


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = _demand_rig()
    yield r
    r.close()
    assert not r.sim.errors


def test_small_clock_steps_send_nothing_and_a_host_wait_sends_every_packet_due(raw_twin: Rig) -> None:
    """Three packets come due in 13 steps of 0.5 ms (scans 0…5 at 1…6 ms: 12 samples) — nothing leaves; the host's
    wait then sends all three at once: TransID 0, 1, 2, backlog 16, 8, 0 bytes."""
    with socket.create_connection(("127.0.0.1", raw_twin.port), timeout=2) as s, \
            socket.create_connection(("127.0.0.1", raw_twin.stream_port), timeout=STREAM_WAIT_S) as data:
        _configure(s)
        for _ in range(13):
            raw_twin.clock.advance(0.0005)
        _round_trip(s)
        assert raw_twin.sim.packets_sent == 0
        raw_twin.sim.host_waits()
        got = data.recv(3 * 28, socket.MSG_WAITALL)
    samples = "82f3 82f3 82f3 82f3"  # the plant at rest: 0 V on both monitors (nominal centre 33523)
    assert got == bytes.fromhex(f"0000 0000 0012 01 4c 10 00 0010 0000 0000 {samples}"
                                f"0001 0000 0012 01 4c 10 00 0008 0000 0000 {samples}"
                                f"0002 0000 0012 01 4c 10 00 0000 0000 0000 {samples}")


def test_with_no_host_the_twin_still_pumps_once_a_step_of_rig_time_has_passed(raw_twin: Rig) -> None:
    """No host waits: nothing leaves within 0.45 s of the enable; at 0.55 s (past the 0.5-s step) the 550 scans
    due (275 packets of 2 scans) do — the device streams on without a host."""
    with socket.create_connection(("127.0.0.1", raw_twin.port), timeout=2) as s:
        _configure(s)
        for _ in range(9):
            raw_twin.clock.advance(0.05)
        _round_trip(s)
        assert raw_twin.sim.packets_sent == 0
        raw_twin.clock.advance(0.1)
        _wait_for(lambda: raw_twin.sim.packets_sent == 275)


def test_a_bursts_short_last_packet_leaves_at_its_last_scan_without_the_poll(rig: Rig) -> None:
    """1000 scans of 4 inputs, 128 scans a packet: 7 whole packets (scan 895 at 89.6 ms), then a short one of 104
    scans with status 2944 at scan 999 (0.1 s) — before an eighth whole packet could fill (102.4 ms). The host
    waits for it and gets it then; the poll (an hour) plays no part."""
    rig.daq.arm(StreamSpec(RATE, tuple(StreamIn(i) for i in range(4)), num_scans=1000, samples_per_packet=512))
    rig.daq.kickoff()
    rig.clock.advance(0.095)
    first = rig.daq.collect(until=rig.clock.now(), timeout=2.0)
    assert (first.n, first.done, rig.sim.packets_sent) == (7 * 128, False, 7)
    rig.clock.advance(0.0051)
    last = rig.daq.collect(until=rig.clock.now(), timeout=2.0)
    assert (last.first_scan, last.n, last.done, last.statuses) == (7 * 128, 104, True, (2944,))
    assert rig.sim.packets_sent == 8 and not rig.daq.streaming


def test_stream_enable_0_sends_the_whole_packets_filled_by_then_and_discards_the_partial_one(raw_twin: Rig) -> None:
    """No host wait, no pump for 7.5 ms (below the step): scans 0…6 are due (14 samples). STREAM_ENABLE ← 0 (a raw
    write: nothing else pumps) sends the three whole packets first — backlog 20, 12, 4 bytes: the partial packet's
    2 samples still buffered after the last — then stops; those 2 samples are not sent."""
    with socket.create_connection(("127.0.0.1", raw_twin.port), timeout=2) as s, \
            socket.create_connection(("127.0.0.1", raw_twin.stream_port), timeout=STREAM_WAIT_S) as data:
        _configure(s)
        for _ in range(15):
            raw_twin.clock.advance(0.0005)
        _round_trip(s)
        assert raw_twin.sim.packets_sent == 0
        # FC16 STREAM_ENABLE (4990 = 0x137E) ← UINT32 0
        assert _transact(s, bytes.fromhex("0016 0000 000b 01 10 137e 0002 04 0000 0000"))[7] == 0x10
        got = data.recv(3 * 28, socket.MSG_WAITALL)
        raw_twin.clock.advance(0.01)
        _round_trip(s)
    assert raw_twin.sim.packets_sent == 3 and not raw_twin.sim.streaming
    samples = "82f3 82f3 82f3 82f3"  # the plant at rest, as above
    assert got == bytes.fromhex(f"0000 0000 0012 01 4c 10 00 0014 0000 0000 {samples}"
                                f"0001 0000 0012 01 4c 10 00 000c 0000 0000 {samples}"
                                f"0002 0000 0012 01 4c 10 00 0004 0000 0000 {samples}")


def test_a_dac_read_during_stream_out_gives_the_value_played_by_now(rig: Rig) -> None:
    """A ramp played at 10 kHz, read back (a raw FC3 read of DAC0: no host wait pumps) 0.3 s after the enable
    without a pump: the value of the last scan that ran — scan k at t_enable + (k + 1) / rate."""
    ramp = np.linspace(2.5, 4.0, 20_000)
    plan = rig.daq.arm(StreamSpec(RATE, (StreamIn(0),), StreamOut(0, ramp)))
    t0 = rig.daq.kickoff()
    for _ in range(6):
        rig.clock.advance(0.05)
    with socket.create_connection(("127.0.0.1", rig.port), timeout=2) as s:
        reply = _transact(s, bytes.fromhex("0021 0000 0006 01 03 03e8 0002"))  # FC3 DAC0 (1000), FLOAT32
    volts = struct.unpack(">f", reply[-4:])[0]
    played = int((rig.clock.now() - (t0 - plan.dt)) * plan.scan_rate + 1e-6) - 1
    assert plan.out_volts is not None and played > 2000
    assert volts == pytest.approx(plan.out_volts[played], abs=1e-6)
    rig.daq.stop()


def _looping_with_watchdog() -> Rig:
    """A demand rig with a 1-s watchdog playing a looped sine for 1 s, a DAC keep-alive after each collect (as a
    run's engine sends): the watchdog counts from the last."""
    from tests.test_t7_stream_loop import _sine

    r = _demand_rig(watchdog_s=1)
    try:
        r.daq.arm(StreamSpec(RATE, (StreamIn(0, name="vmon"),), StreamOut(0, _sine(40)), out_ahead_s=0.5,
                             out_loops=True))
        r.daq.kickoff()
        for _ in range(4):
            r.clock.advance(0.25)
            r.daq.collect(until=r.clock.now())
            r.daq.read_dac(0)
    except BaseException:
        r.close()
        raise
    return r


def test_a_lost_host_in_demand_mode_is_still_stopped_by_the_t7_watchdog() -> None:
    """As tests/test_t7_stream_loop.py's lost host, with nobody pumping the twin by hand: the host goes silent
    while a loop repeats, just after a keepalive; the clock alone (steps of 0.1 s for 2 s) makes the twin act — the
    watchdog (1 s) stops the loop and the amplifier input is at 0 V."""
    r = _looping_with_watchdog()
    try:
        assert r.sim.outs[0].loops_set == 1
        with socket.create_connection(("127.0.0.1", r.port), timeout=2) as s:
            _round_trip(s)  # at the same rig time: a wake the host's waits asked for has run by its reply
        last = r.clock.now()  # the host is lost: nothing more
        assert r.sim.outs[0].loop.size > 1  # the loop still plays
        for _ in range(20):
            r.clock.advance(0.1)
        _wait_for(lambda: r.sim.outs[0].loop.size == 0)  # the loop no longer plays
        r.plant.observe()
        assert r.plant.watchdog_tripped and r.plant.v_in == 0.0 and r.clock.now() > last + 1.0
    finally:
        r.close()
    assert not r.sim.errors


def test_a_request_after_the_watchdogs_timeout_cannot_restart_the_loop_it_stopped() -> None:
    """The host goes silent while a loop repeats; the clock passes the 1-s watchdog timeout in steps below the
    twin's 0.5-s pump step (nothing has played up to there); a DAC read then arrives 0.05 s after the timeout. On a T7
    the timeout acted when it ended (datasheet, Watchdog: "if the timeout is reached, the T7 performs the
    configured actions"), so the read finds the loop stopped and the amplifier input at 0 V — it must not play on."""
    r = _looping_with_watchdog()
    try:
        with socket.create_connection(("127.0.0.1", r.port), timeout=2) as s:
            _round_trip(s)  # the last request: the watchdog counts from here
            last = r.clock.now()
            r.clock.advance_to(last + 0.3)  # below the twin's 0.5-s pump step: no pump
            r.clock.advance_to(last + 0.6)  # a step: the twin pumps (plays up to here) on its own thread
            _wait_for(lambda: r.sim._worked_at == last + 0.6)
            r.clock.advance_to(last + 0.9)
            r.clock.advance_to(last + 1.05)  # 0.45 s since that pump: nothing has played past 0.6 s
            _transact(s, bytes.fromhex("0021 0000 0006 01 03 03e8 0002"))  # FC3 DAC0, 0.05 s after the timeout
        assert r.sim.outs[0].loop.size == 0 and not r.sim.outs[0].loop_active
        r.clock.advance(0.5)
        _wait_for(lambda: r.sim.outs[0].loop.size == 0)
        r.plant.observe()
        assert r.plant.watchdog_tripped and r.plant.v_in == 0.0
    finally:
        r.close()
    assert not r.sim.errors


def test_a_stop_written_after_a_burst_ended_is_refused_and_the_burst_ends_whole(rig: Rig) -> None:
    """A burst of 1000 scans ends at 0.1 s (scan 999); no host wait and no pump step until the host writes
    STREAM_ENABLE ← 0 at 0.12 s. A T7 stopped streaming when the burst ended: the write is refused (exception 4,
    2620 STREAM_NOT_RUNNING) and every scan arrives, the last packet with status 2944."""
    rig.daq.arm(StreamSpec(RATE, tuple(StreamIn(i) for i in range(4)), num_scans=1000, samples_per_packet=512))
    rig.daq.kickoff()
    rig.clock.advance(0.12)
    with socket.create_connection(("127.0.0.1", rig.port), timeout=2) as s:
        reply = _transact(s, bytes.fromhex("0016 0000 000b 01 10 137e 0002 04 0000 0000"))
    assert reply[7] == 0x90
    block = rig.daq.collect(until=rig.clock.now(), timeout=2.0)
    assert (block.n, block.done, block.statuses) == (1000, True, (2944,))


def test_a_reply_the_twin_withheld_does_not_stop_the_stream_from_arriving(rig: Rig) -> None:
    """The Modbus link is muted for one request (it times out, as a T7 that does not answer); the stream socket is
    another connection, and its packets still come: after the mute is lifted, the next 0.1 s of scans (1000 at 10
    kHz) is collected whole."""
    rig.daq.arm(StreamSpec(RATE, (StreamIn(0),), samples_per_packet=100))
    rig.daq.kickoff()
    rig.clock.advance(0.1)
    assert rig.daq.collect(until=rig.clock.now()).n == 1000
    rig.sim.faults.mute = True
    with pytest.raises(InstrumentTimeoutError):
        rig.daq.read_dac(0)
    rig.sim.faults.mute = False
    seen = rig.daq.scans_received
    rig.clock.advance(0.1)
    block = rig.daq.collect(until=rig.clock.now())
    assert rig.daq.scans_received - seen == block.n >= 1000
    rig.daq.stop()


@pytest.mark.parametrize("virtual", [False, True])
def test_only_a_virtual_time_rig_pumps_its_t7_on_demand_and_only_its_daq_link_tells_it(virtual: bool) -> None:
    """Real time: no reply timers, the twin pumps on its poll and at every clock move as a T7 streams; virtual
    time: the "daq" link's timer tells the twin when the host waits, the other links' timers do not."""
    from bench.rig import load_rig

    sim = SimRig(load_rig(ROOT / "rigs" / "lsdea-motor-daq-sim.toml"), virtual=virtual)
    sim.start()
    try:
        timers = sim.reply_timers()
        daq = sim.twins["daq"]
        assert isinstance(daq, LabJackT7Sim) and daq.demand is virtual
        assert sorted(timers) == ([] if not virtual else sorted(sim.faults))
        assert [n for n, t in timers.items() if t.waiting is not None] == (["daq"] if virtual else [])
        if virtual:
            assert timers["daq"].waiting == daq.host_waits
    finally:
        sim.stop()


def _run_isometric(tmp: Path, demand: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[StreamBatch]]:
    """lsdea-isometric-short on its motor + DAQ rig in virtual time; the stream packets the driver received."""
    with monkeypatch.context() as m:
        got: list[StreamBatch] = []
        parse = driver_stream_in.parse_stream_batch

        def keep(frames: bytes, spans: list[tuple[int, int]], device: str = "T7") -> StreamBatch:
            got.append(batch := parse(frames, spans, device))
            return batch

        m.setattr(driver_stream_in, "parse_stream_batch", keep)
        if not demand:  # today's mode: the host's waits tell the twin nothing, it pumps at every clock move
            m.setattr(LabJackT7Sim, "on_demand", lambda self: lambda: None)
        plan = plan_run(ROOT / "protocols" / "short" / "lsdea-isometric-short.toml",
                        ROOT / "rigs" / "lsdea-motor-daq-sim.toml")
        twins: list[object] = []
        result = execute(plan, tmp / f"{'demand' if demand else 'clock'}.h5", virtual=True,
                         on_engine=lambda engine, sim: twins.append(sim.twins["daq"]))
        assert result.state == "completed"
        assert [getattr(t, "demand", None) for t in twins] == [demand]  # the mode each run was meant to test
        return result.path, got


def _packets(batches: list[StreamBatch]) -> dict[str, np.ndarray]:
    return {"tid": np.concatenate([b.transaction_ids for b in batches]),
            "status": np.concatenate([b.statuses for b in batches]),
            "additional": np.concatenate([b.additional for b in batches]),
            "size": np.concatenate([np.diff(b.ends, prepend=0) for b in batches]),
            "samples": np.concatenate([b.samples for b in batches])}


def test_on_demand_the_isometric_run_records_what_pumping_at_every_clock_move_records(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same run with the twin pumping at every clock move and on demand: the same packets (TransIDs, statuses,
    AddInfo, sizes, samples — only the backlog words may differ) and the same recorded streams and events."""
    clock_path, clock_batches = _run_isometric(tmp_path, False, monkeypatch)
    demand_path, demand_batches = _run_isometric(tmp_path, True, monkeypatch)
    a, b = _packets(clock_batches), _packets(demand_batches)
    assert a["tid"].size > 100  # the stream ran (the run records ~9 s of 10 kHz scans)
    for key in a:
        assert np.array_equal(a[key], b[key]), key
    assert len(demand_batches) < len(clock_batches)  # fewer pumps: more packets in each receive
    fa, fb = open_run(clock_path), open_run(demand_path)
    assert sorted(fa.streams) == sorted(fb.streams)
    for name in fa.streams:
        sa, sb = fa.streams[name], fb.streams[name]
        assert np.array_equal(sa.t, sb.t), name
        assert sorted(sa.columns) == sorted(sb.columns)
        for col in sa.columns:
            assert np.array_equal(sa.columns[col], sb.columns[col], equal_nan=True), (name, col)
    assert fa.event_list() == fb.event_list()


def test_a_refill_never_writes_more_than_the_buffer_surely_holds_whatever_the_clock_says(rig: Rig) -> None:
    """The host tops the stream-out up to out_ahead_s beyond where the scan clock may be (t0 + its uncertainty).
    A device that played less than that — one that started later than t0 says, or a twin whose thread lags a loaded
    host (a CI run beside a CPU hog) — had no room for it: the write was refused, STREAM_OUT_BUFF_FULL (2613), and
    the run ended in an error. Here the host's clock says 1 s has passed while the twin, never pumped, played
    nothing: the refill stays within the buffer's capacity less what is unplayed for sure (datasheet §3.2.3: the
    device refuses a write beyond its buffer)."""
    plan = rig.daq.arm(StreamSpec(RATE, (StreamIn(0),), StreamOut(0, np.full(40_000, 2.5)), out_ahead_s=0.2))
    rig.daq.kickoff()
    s = rig.daq._stream
    assert s is not None and plan.out_ahead is not None and plan.out_capacity > plan.out_ahead
    now = rig.clock.now()
    rig.daq.clock = lambda: now + 1.0  # the host's clock far ahead of what the device played
    for _ in range(8):  # every collect tops up again: before, each wrote out_ahead more until the twin refused
        rig.daq._feed_out()
    assert s.out_written - s.scans <= plan.out_capacity
    assert s.out_written >= plan.out_ahead  # what fits still went in
    rig.daq.clock = rig.clock.now
    rig.daq.stop()


def test_a_host_wait_a_rounding_short_of_a_packet_s_scan_time_sends_the_packet(raw_twin: Rig) -> None:
    """Scan k is taken at t_enable + (k + 1) / rate [D]; a clock a rounding short of the scan that fills a packet
    (a sum of run times, as the host's own scan count reads it, to a millionth of a scan) takes it, so the host's
    wait there sends the packet. Before, the twin's wake compared the exact instant: the host's wait sent nothing and
    the host waited out its timeout (a second Ctrl-C's settle stream, 30 s of wall time per run in virtual time)."""
    with socket.create_connection(("127.0.0.1", raw_twin.port), timeout=2) as s, \
            socket.create_connection(("127.0.0.1", raw_twin.stream_port), timeout=STREAM_WAIT_S) as data:
        _configure(s)  # 1 kHz, two channels, 4 samples a packet: scans 0 and 1 fill packet 0, scan 1 at 2 ms
        full = raw_twin.sim.t_enable + 2 / 1000.0
        raw_twin.clock.advance(float(np.nextafter(full, -np.inf)) - raw_twin.clock.now())
        assert raw_twin.clock.now() < full
        _round_trip(s)
        raw_twin.sim.host_waits()
        got = data.recv(28, socket.MSG_WAITALL)
    assert raw_twin.sim.packets_sent == 1 and got[:2] == bytes.fromhex("0000")  # TransID 0: the first packet
