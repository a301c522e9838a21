"""Every driver against its simulated twin over a real pty / loopback socket, including injected faults."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import (
    InstrumentConnectionError,
    InstrumentStateError,
    InstrumentTimeoutError,
    LimitError,
    ProtocolError,
)
from tests.conftest import RunningRig

# ------------------------------------------------------------------ laser (Keyence LK-G over a pty)


def test_laser_single_reads_follow_the_plant(thesis: RunningRig) -> None:
    laser, amp = thesis.inst.laser, thesis.inst.amplifier
    assert abs(laser.read_displacement().value) < 20e-6  # at rest: noise only (LK-G152 at averaging 64: 4 µm rms, 5σ)
    amp.set_voltage(6000.0)
    thesis.advance(3.0)
    r = laser.read_displacement()
    plant_u = float(thesis.sim.plant.last.displacement[0])
    assert r.timestamp == pytest.approx(4.0)
    assert r.value == pytest.approx(plant_u, abs=20e-6)  # LK-G152 at averaging 64: 4 µm rms (5σ)
    assert plant_u > 3e-3  # 6 kV moves the membrane by millimetres


def test_laser_buffer_is_complete_at_10_kHz(thesis: RunningRig) -> None:
    laser, amp = thesis.inst.laser, thesis.inst.amplifier
    history_t: list[np.ndarray] = []
    history_u: list[np.ndarray] = []
    thesis.sim.plant.listeners.append(lambda b: (history_t.append(b.t), history_u.append(b.displacement)))
    amp.set_voltage(5000.0)
    assert laser.start_buffer(1e-4) == pytest.approx(1e-4)
    blocks = []
    for _ in range(10):
        thesis.advance(0.25)
        blocks.append(laser.fetch_buffer())
    laser.stop_buffer()
    index = np.concatenate([b.first_index + np.arange(b.values.size) for b in blocks])
    assert np.array_equal(index, np.arange(index.size))  # no sample lost or duplicated
    assert index.size == 25_001  # 2.5 s at 10 kHz, both ends included
    t = np.concatenate([b.times() for b in blocks])
    values = np.concatenate([b.values for b in blocks])
    truth = np.interp(t, np.concatenate(history_t), np.concatenate(history_u))
    assert np.all(np.concatenate([b.valid for b in blocks]))
    # noise: Keyence LK-G152 repeatability 0.5 µm at averaging 4096 (catalogue), √(4096/64) = 8× at the rig's 64
    assert np.sqrt(np.mean((values - truth) ** 2)) == pytest.approx(4e-6, rel=0.1)


def test_laser_storage_capacity_stops_storage(thesis: RunningRig) -> None:
    laser = thesis.inst.laser
    laser.storage_points = 1000
    laser.start_buffer(1e-4)
    thesis.advance(0.5)
    block = laser.fetch_buffer()
    assert block.values.size == 1000
    assert laser.buffer_status() == (False, 1000)
    with pytest.raises(InstrumentStateError, match="data storage full"):
        laser.fetch_buffer()


def test_laser_mode_errors_and_injected_faults(thesis: RunningRig) -> None:
    laser, twin, faults = thesis.inst.laser, thesis.sim.twins["laser"], thesis.sim.faults["laser"]
    with pytest.raises(InstrumentStateError, match="status error"):
        laser.query("SW,CA,2")  # settings need communication mode
    with pytest.raises(InstrumentStateError, match="command error"):
        laser.query("ZZ")
    with pytest.raises(InstrumentStateError, match="parameter count error"):
        laser.query("AO,1")
    twin.fault_error_code = "99"
    with pytest.raises(InstrumentStateError, match="ER 99"):
        laser.read_displacement()
    twin.fault_error_code = None
    faults.mute = True
    with pytest.raises(InstrumentTimeoutError, match="laser: no reply"):
        laser.read_displacement()
    faults.mute = False
    laser.link.discard_input()
    faults.garble_next, faults.garble_index = 1, 0  # the echoed command garbled: a wrong reply
    with pytest.raises(ProtocolError):
        laser.read_displacement()
    laser.link.discard_input()
    assert laser.read_displacement().ok  # the link recovers after a garbled reply
    faults.garble_next, faults.garble_index = 1, -1  # the CR garbled: the reply never ends
    with pytest.raises(InstrumentTimeoutError):
        laser.read_displacement()
    laser.link.discard_input()
    faults.garble_index = None
    assert laser.read_displacement().ok
    faults.drop = True
    with pytest.raises(InstrumentConnectionError, match="laser: link on /dev/pts/"):
        for _ in range(50):
            laser.read_displacement()


def test_laser_over_range(lsdea_isotonic: RunningRig) -> None:
    laser = lsdea_isotonic.inst.laser
    assert laser.read_displacement().ok  # x ≈ 66 mm reads ≈ −1 mm within ±40 mm
    lsdea_isotonic.sim.twins["laser"].head.offset_mm = -140.0
    r = laser.read_displacement()
    assert r.status == "over_range_negative" and np.isnan(r.value)


# ------------------------------------------------------------------ motor (LinMot LinRS over a pty)


def test_motor_state_machine_homing_and_motion(lsdea_motor: RunningRig) -> None:
    motor = lsdea_motor.inst.motor
    assert motor.status().state == "not ready to switch on"
    motor.enable()
    s = motor.status()
    assert s.state == "operation enabled" and s.homed and s.enabled and not s.error
    motor.move_to(0.055, 0.5, 5.0)
    assert motor.status().moving
    reached = motor.wait_in_target()
    assert reached.value == pytest.approx(0.055, abs=1e-7)
    x = lsdea_motor.sim.plant.observe().displacement[0]
    assert x == pytest.approx(0.045 + 0.055)  # aperture = x at motor zero + motor position


def test_motor_refuses_and_recovers_from_errors(lsdea_motor: RunningRig) -> None:
    motor, twin = lsdea_motor.inst.motor, lsdea_motor.sim.twins["motor"]
    with pytest.raises(InstrumentStateError, match="code 0x86 motion command in wrong state"):
        motor.move_to(0.01, 0.1, 1.0)  # not switched on
    motor.enable()  # acknowledges the error and runs the state machine again
    with pytest.raises(LimitError, match="outside travel"):
        motor.move_to(0.2, 0.1, 1.0)
    motor.move_to(0.05, 0.5, 5.0)
    lsdea_motor.advance(0.05)
    twin.inject_error(0x0B)
    assert motor.status().state == "error behaviour quick stop"  # MC-SW §3.14: an error while moving
    lsdea_motor.advance(0.05)  # the quick stop (0.25 m/s at the twin's 50 m/s²: 5 ms) has ended: state 4
    s = motor.status()
    assert (s.error and s.error_code == 0x0B and not s.moving) or s.state == "error"
    with pytest.raises(InstrumentStateError, match="position lag"):
        motor.wait_in_target()
    motor.enable()
    assert motor.status().state == "operation enabled"
    twin.inject_error(0x22, fatal=True)
    with pytest.raises(InstrumentStateError, match="fatal"):
        motor.enable()


def test_motor_stop_holds_position(lsdea_motor: RunningRig) -> None:
    motor = lsdea_motor.inst.motor
    motor.enable()
    motor.move_to(0.09, 0.2, 2.0)
    lsdea_motor.advance(0.2)
    motor.stop()
    lsdea_motor.advance(1.0)
    s = motor.status()
    assert not s.moving and 0.02 < s.position < 0.09
    lsdea_motor.advance(1.0)
    assert motor.status().position == s.position


def test_motor_link_faults(lsdea_motor: RunningRig) -> None:
    motor, faults = lsdea_motor.inst.motor, lsdea_motor.sim.faults["motor"]
    faults.mute = True
    with pytest.raises(InstrumentTimeoutError, match="motor: no reply"):
        motor.poll()
    faults.mute = False
    faults.garble_next, faults.garble_index = 1, -1  # END byte corrupted: framing error
    with pytest.raises(ProtocolError, match="malformed default response"):
        motor.poll()
    faults.garble_next, faults.garble_index = 1, 0  # start byte corrupted
    with pytest.raises(ProtocolError, match="does not start with 01h"):
        motor.poll()
    motor.link.discard_input()
    assert motor.poll().comm_state == 0  # back in step


def test_motor_checksum_detects_corrupted_data_bytes() -> None:
    from tests.conftest import start_rig

    r = start_rig("lsdea-motor-sim", motor={**start_rig_motor(), "checksum": True})
    try:
        motor, faults = r.inst.motor, r.sim.faults["motor"]
        motor.enable()
        faults.garble_next, faults.garble_index = 1, 8  # a status-word byte: undetectable without checksum
        with pytest.raises(ProtocolError, match="checksum error"):
            motor.poll()
        assert motor.status().state == "operation enabled"
    finally:
        r.inst.close()
        r.sim.stop()


def start_rig_motor() -> dict:
    from bench.rig import load_rig
    from tests.conftest import RIGS

    return load_rig(RIGS / "lsdea-motor-sim.toml").motor.model_dump()


# ------------------------------------------------------------------ amplifier and load cell (Modbus RTU on ptys)


def test_amplifier_monitors_follow_the_set_point(thesis: RunningRig) -> None:
    amp = thesis.inst.amplifier
    amp.set_voltage(4000.0)
    thesis.advance(0.5)  # the ADAM-4017+ converts 10 S/s over the enabled channels
    v, i = amp.read_monitors()
    # 12-bit AO step 4.9 V; TREK monitors [assumed, bench/core/noise.py]: ±0.1 % of 10 kV (10 V) and 1 V rms
    # noise; current monitor ±1 % of 10 mA (100 µA)
    assert v.value == pytest.approx(4000.0, abs=4.9 + 10.0 + 5.0)
    assert abs(i.value) < 100e-6 + 5e-6
    assert v.timestamp == pytest.approx(1.5)


def test_amplifier_device_failure_bus_faults_and_breakdown(thesis_rtu: RunningRig) -> None:
    thesis = thesis_rtu
    amp, sim = thesis.inst.amplifier, thesis.sim
    sim.twins["amplifier AO"].failed = True
    with pytest.raises(InstrumentStateError, match=r"unit 1 refused .* exception 4 \(device failure\)"):
        amp.set_voltage(100.0)
    sim.twins["amplifier AO"].failed = False
    sim.faults["io"].mute = True
    with pytest.raises(InstrumentTimeoutError, match="bus io: no valid reply from unit 2"):
        amp.read_voltage()
    sim.faults["io"].mute = False
    amp.set_voltage(5000.0)
    thesis.advance(2.0)
    before = thesis.inst.laser.read_displacement().value
    sim.plant.inject_breakdown()
    thesis.advance(2.0)
    v, i = amp.read_monitors()
    assert i.value == pytest.approx(10e-3, rel=0.02)  # current limit of the 10/10B-HS into the short
    assert v.value < 50.0  # output collapses: I_max × R_short = 10 V
    assert thesis.inst.laser.read_displacement().value < 0.5 * before  # the membrane relaxes without field
    assert "breakdown" in sim.plant.failure


def test_load_cell_zero_tare_and_failure(lsdea_motor: RunningRig) -> None:
    cell, twin = lsdea_motor.inst.load_cell, lsdea_motor.sim.twins["load_cell"]
    lsdea_motor.advance(1.0)
    f0 = cell.read_force()
    assert f0.ok and f0.value == pytest.approx(float(lsdea_motor.sim.plant.last.force[0]), abs=0.02)
    with pytest.raises(InstrumentStateError, match="outside the zero range"):
        cell.zero()  # 1.1 N ≈ 113 g is beyond the ±2 % (100 g) zero band of a 5-kg cell
    cell.tare()
    assert cell.read_force().value == pytest.approx(0.0, abs=0.02)
    twin.failed = True
    with pytest.raises(InstrumentStateError, match="device failure"):
        cell.read_force()


@pytest.mark.parametrize("transport, prefix", [("tcp", "tcp://127.0.0.1:"), ("rtu", "/dev/pts/"),
                                               ("rtu-socket", "socket://127.0.0.1:")])
def test_modbus_transports(transport: str, prefix: str) -> None:
    from tests.conftest import start_rig

    r = start_rig("lsdea-motor-sim", simulation={"seed": 1, "modbus_transport": transport})
    try:
        assert all(ep.address.startswith(prefix) for ep in r.sim.endpoints().values()
                   if ep.protocol.startswith("Modbus"))
        r.inst.amplifier.set_voltage(3000.0)
        r.advance(0.5)
        assert r.inst.amplifier.read_voltage().value == pytest.approx(3000.0, abs=4.9 + 10.0 + 5.0)
        assert r.inst.load_cell.read_force().ok
    finally:
        r.inst.close()
        r.sim.stop()


def test_motor_quick_stop_and_malformed_telegrams(lsdea_motor: RunningRig) -> None:
    motor = lsdea_motor.inst.motor
    motor.enable()
    motor.move_to(0.09, 0.5, 5.0)
    lsdea_motor.advance(0.05)
    motor.quick_stop()
    lsdea_motor.advance(0.5)
    s = motor.status()
    # MC-SW §3.22 bit 2 = 0 is OFF3 (quick stop, bridges off) and §3.2: state 1 while bit 1 or 2 is cleared
    assert s.state == "switch on disabled" and not s.moving and not s.enabled
    with motor.link.lock:  # framing error (no 04h): the drive discards it, the master times out
        motor.link.write(bytes.fromhex("01 11 03 02 01 00 05"))
        with pytest.raises(InstrumentTimeoutError):
            motor.link.read_exact(16, timeout=0.2)
    with pytest.raises(ProtocolError, match="communication state 0x01"):
        motor.transact(0x07, 0x00)  # an unsupported message group is answered with a comm error


def test_modbus_bus_dropped_and_reply_latency(thesis_rtu: RunningRig) -> None:
    thesis = thesis_rtu
    import time

    amp, faults = thesis.inst.amplifier, thesis.sim.faults["io"]
    faults.latency = 0.15
    t0 = time.perf_counter()
    amp.read_voltage()
    assert time.perf_counter() - t0 >= 0.15
    faults.latency = 0.0
    faults.drop = True
    time.sleep(0.2)
    with pytest.raises(InstrumentConnectionError, match=r"bus io: Modbus link .* lost"):
        amp.read_voltage()


def test_analog_module_watchdog_zeroes_the_amplifier_when_the_host_goes_silent(
        thesis_rtu_watchdog: RunningRig) -> None:
    thesis_rtu = thesis_rtu_watchdog
    amp, sim = thesis_rtu.inst.amplifier, thesis_rtu.sim
    amp.set_voltage(5000.0)
    thesis_rtu.advance(0.5)
    assert amp.read_voltage().value == pytest.approx(5000.0, abs=4.9 + 10.0 + 5.0)
    sim.faults["io"].drop = True  # the host can no longer reach the module
    thesis_rtu.advance(2.0)  # longer than the 1-s communication safety of the rig file
    assert sim.plant.observe().v_out[0] == 0.0 and sim.plant.watchdog_tripped


# ------------------------------------------------------------------ wall clock: the plant keeps up in the background


def test_first_reply_after_idle_is_wire_time_not_integration_time() -> None:
    """Issue 10: the first reply after 3 minutes idle within 5 ms + wire time. Three minutes of idle are
    emulated by moving the wall clock's origin back 180 s (the background thread then has to catch up, as it
    would have done during the idle time); the reply after it costs no more than after 1 s of idle."""
    import time

    from tests.conftest import start_rig

    r = start_rig("thesis-sim", virtual=False, timing="real")
    try:
        laser, sim = r.inst.laser, r.sim
        wire = (6 + 15) * 10 / 115200 + 0.5e-3  # "MS,01\r" + "MS,01,+dd.dddd\r" at 115200 Bd, turnaround
        time.sleep(1.0)
        t0 = time.perf_counter()
        laser.read_displacement()
        after_1s = time.perf_counter() - t0
        moved = time.perf_counter()
        sim.clock._t0 -= 180.0  # type: ignore[attr-defined]  # three minutes have passed
        deadline = time.monotonic() + 20.0
        while sim.plant.t < sim.clock.now() - 0.1 and time.monotonic() < deadline:
            time.sleep(0.05)
        catch_up = time.perf_counter() - moved  # the background thread integrating 180 s of plant
        t0 = time.perf_counter()
        reading = laser.read_displacement()
        after_3min = time.perf_counter() - t0
        assert reading.timestamp > 180.0 and sim.plant.t > 180.0
        # ratios in the same run, not durations a loaded machine can exceed: the reply after idle is one reply
        # (the same order as after 1 s), a small part of the integration it would cost if it integrated
        assert after_3min < max(10 * after_1s, 10 * wire) and after_3min < catch_up / 4, \
            (after_1s, after_3min, catch_up)
    finally:
        r.inst.close()
        r.sim.stop()


def test_the_twins_processing_time_is_part_of_the_device_turnaround_not_added_to_it() -> None:
    """A reply's first byte leaves the device's turnaround after the request's end-of-frame silence; time the
    simulator spends computing the reply (here 0.3 ms of a 1-ms turnaround) does not delay it, while
    processing longer than the turnaround does (the simulator cannot answer before it has the reply)."""
    from bench.core.clock import VirtualClock
    from sim_devices.transport import Line

    clock = VirtualClock()
    char = 10 / 19200
    line = Line(clock, 19200, gap_chars=3.5)
    end_req = line.request(8)
    assert end_req == pytest.approx(8 * char + 3.5 * char)
    clock.advance(0.3e-3)  # the twin computes the reply
    line.reply(7, turnaround=1e-3)
    assert clock.now() == pytest.approx(end_req + 1e-3 + 7 * char, abs=1e-12)
    clock.advance(3.5 * char)  # the reply's own end-of-frame silence
    end_req = line.request(8)
    clock.advance(1.5e-3)  # slower than the turnaround
    line.reply(7, turnaround=1e-3)
    assert clock.now() == pytest.approx(end_req + 1.5e-3 + 7 * char, abs=1e-12)


def test_the_pty_hop_is_taken_out_of_the_emulated_wire_time_not_added_to_it() -> None:
    """On the wall clock a request reaches the twin one pty hop after the host wrote it, and the reply reaches
    the host one hop after the twin writes it; the wire model starts the request a hop back and writes the
    reply a hop early, so the host sees the exchange take the wire's time. The hop used is the minimum of
    measured hops (a lower bound: never faster than the wire)."""
    from bench.core.clock import VirtualClock
    from sim_devices.transport import Line, pty_hop_latency

    hop = pty_hop_latency()
    assert 0.0 < hop < 5e-3
    clock = VirtualClock(1.0)
    char = 10 / 115200
    line = Line(clock, 115200, turnaround=0.5e-3)
    line.hop = 1e-4
    end_req = line.request(6)
    assert end_req == pytest.approx(1.0 - 1e-4 + 6 * char)
    line.reply(15)
    assert clock.now() == pytest.approx(end_req + 0.5e-3 + 15 * char - 1e-4)


def test_a_stop_while_the_pty_hop_is_measured_leaves_no_thread_to_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    """The hop is measured when a rig's first serial twin starts; a stop signal raised there (Ctrl-C in the first
    second of `bench run`) closed the pty under the measuring thread, which then printed its own traceback
    (``Exception in thread … OSError: [Errno 9] Bad file descriptor``) after the run's one line."""
    import threading
    import time
    from types import SimpleNamespace

    from sim_devices import transport

    class StopSignalError(Exception):
        pass

    sleeps = [0]

    def sleep(dt: float) -> None:  # the signal's exception, raised in the main thread mid-measurement
        sleeps[0] += 1
        if sleeps[0] == 5:
            raise StopSignalError
        time.sleep(dt)

    monkeypatch.setattr(transport, "time", SimpleNamespace(sleep=sleep, perf_counter=time.perf_counter))
    failed: list[object] = []
    monkeypatch.setattr(threading, "excepthook", failed.append)
    before = set(threading.enumerate())
    with pytest.raises(StopSignalError):
        transport.pty_hop_latency.__wrapped__()
    for thread in set(threading.enumerate()) - before:  # the measuring thread, if it outlived the call
        thread.join(2.0)
    assert failed == []
