"""LinMot twin: the drive's own cycle, the MC-SW command set and the warn word, against the manuals.

Sources (page numbers of the MC-SW manual 4.3.4 SG5, 23/09/2014, transcribed in Smart-Vision-Works/linmot_client
``linmot_client/reference/LinMot_MotionCtrl.txt``): §3.6 p. 14 ("the servo changes to state 6 without any user
action. The test takes about 300ms"), §3.8–3.17 pp. 15–16, §3.22 control word, §3.23 status word (bit 7
"Warning: one or more bits in the Warn Word are set"), §3.24 warn word (bit 7 "Motor Not Homed"), §4.1.1 header
p. 21, §4.3 commands pp. 28–54, §10 error code list. Telegrams are written out per the LinRS manual 0185-1082-E
p. 11 (``01 ID Len 02 Sub Main data… 04``); expected positions are derived by hand from the trapezoid
kinematics in each test's comment.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator

import pytest
import serial

from bench.core.clock import VirtualClock, WallClock
from bench.rig import load_rig, plant_for
from bench.runtime.sim_rig import SimRig
from sim_devices.linmot_drive import LinMotDriveSim
from tests.conftest import RIGS

RIG = RIGS / "lsdea-motor-sim.toml"
POLL = bytes.fromhex("01 11 03 02 01 00 04")  # Main 00h Sub 01h: default response


def cw(word: int) -> bytes:
    """Write Control Word (LinRS example layout ``01 11 05 02 00 01 <lo> <hi> 04``)."""
    return bytes.fromhex("01 11 05 02 00 01") + struct.pack("<H", word) + b"\x04"


def mci(header: int, params: bytes = b"") -> bytes:
    """Write Motion Command Interface (Main 02h Sub 00h): header word + parameters, little-endian."""
    body = bytes.fromhex("02 00 02") + struct.pack("<H", header) + params
    return bytes([0x01, 0x11, len(body)]) + body + b"\x04"


def decode(reply: bytes) -> tuple[int, int, int, int]:
    """(comm state, status word, state var, position counts) of a default response."""
    assert reply[:6] == bytes.fromhex("01 11 0C 02 00 00") and reply[-1] == 0x04, reply.hex()
    return struct.unpack("<BHHi", reply[6:15])


class Twin:
    """The drive fed telegrams directly, on a virtual clock only the test advances."""

    def __init__(self, **kw: object) -> None:
        self.clock = VirtualClock()
        self.plant = plant_for(load_rig(RIG), self.clock)
        self.drive = LinMotDriveSim(self.plant, self.clock, **kw)  # type: ignore[arg-type]

    def send(self, telegram: bytes) -> tuple[int, int, int, int]:
        return decode(self.drive(telegram))

    def state(self, telegram: bytes = POLL) -> int:
        return self.send(telegram)[2]

    def advance(self, dt: float) -> None:
        self.clock.advance(dt)

    def switch_on(self, word: int = 0x003F) -> None:
        """0 → 1 → 2 → 5 with ``word`` (§3.1–3.3; driver sequence 0000h, 003Eh, then ``word``)."""
        for w in (0x0000, 0x003E, word):
            self.send(cw(w))

    def homed(self) -> None:
        """Switched on, homed (§3.9), back in state 8 with Home released."""
        self.switch_on(0x083F)
        self.advance(2.0)
        assert self.state() == 0x090F
        assert self.state(cw(0x003F)) & 0xFFF0 == 0x08C0  # homed, in target (count: the last one sent)


@pytest.fixture
def twin() -> Iterator[Twin]:
    t = Twin()
    yield t
    t.drive.close()


# ---------------------------------------------------------------- the drive's own cycle (§3.6, §3.9)
def test_home_held_at_switch_on_reports_homing_finished_at_the_first_poll() -> None:
    """The issue's case over the pty: 0x083F, 3 s of silence, one poll → 090Fh (§3.6: to state 6 'without any
    user action' after ~300 ms, then the held control word takes it to 8 and 9; homing finishes on its own)."""
    sim = SimRig(load_rig(RIG), virtual=True, timing="none")
    sim.start()
    try:
        port = serial.Serial(sim.port_map()["motor"], timeout=0.5)
        for word in (0x0000, 0x003E, 0x083F):
            port.write(cw(word))
            assert len(port.read(16)) == 16
        sim.clock.advance(3.0)  # type: ignore[attr-defined]
        port.write(POLL)
        _, status, state, _ = decode(port.read(16))
        # 090Fh "Homing Finished"; status bits 0, 1, 2, 4, 5 (state ≥ 8, cw bits 0/3/1/2) + 11 Homed = 0837h
        assert (status, state) == (0x0837, 0x090F)
        port.close()
    finally:
        sim.stop()


def test_homing_is_timed_from_the_end_of_the_hw_tests_not_from_a_poll(twin: Twin) -> None:
    twin.switch_on(0x083F)  # at t = 0: state 5
    twin.advance(0.8)  # HW tests end at 0.3 s: homing started then, at least 1 s long here (homing_time)
    assert twin.state() == 0x0901  # the poll at 0.8 s finds homing under way
    twin.advance(0.51)  # 1.31 s: 0.3 + 1.0 passed → finished, though the first poll came at 0.8 s
    assert twin.state() == 0x090F


def test_homing_moves_the_motor_while_the_host_is_silent() -> None:
    t = Twin(home_position=0.02)
    try:
        t.switch_on(0x083F)
        t.advance(3.0)  # no telegram: 20 mm at 0.1 m/s, 1 m/s² take 0.3 s; they start at 0.3 s
        assert t.plant.motor_state()[0] == pytest.approx(0.02, abs=1e-12)
        assert t.send(POLL)[2:] == (0x090F, 200_000)
    finally:
        t.drive.close()


def test_the_cycle_runs_on_the_wall_clock_without_telegrams() -> None:
    clock = WallClock()
    drive = LinMotDriveSim(plant_for(load_rig(RIG), clock), clock, homing_time=0.2)
    try:
        for w in (0x0000, 0x003E, 0x083F):
            drive(cw(w))
        deadline = time.monotonic() + 20.0  # a guard, not a measured duration: the order is what is checked
        while not (drive.state == 9 and drive.special_done) and time.monotonic() < deadline:
            time.sleep(0.02)
        # read from the twin's attributes, no telegram in between: the cycle thread ran 5 → 6 → 8 → 9 → 0Fh
        assert (drive.state, drive.special_done, drive.homed) == (9, True, True)
    finally:
        drive.close()


# ---------------------------------------------------------------- status word bit 7 / warn word (§3.23, §3.24)
def test_warning_bit_follows_the_warn_word_motor_not_homed(twin: Twin) -> None:
    twin.switch_on()
    twin.advance(0.3)
    _, status, state, _ = twin.send(POLL)
    assert state == 0x0840 and twin.drive.warn_word() == 0x0080  # §3.24 bit 7 "Motor Not Homed"
    assert status & 0x0080  # §3.23 bit 7: a warn word bit is set
    twin.send(cw(0x083F))
    twin.advance(1.0)
    assert twin.state(cw(0x003F)) == 0x08C0
    assert twin.drive.warn_word() == 0 and not twin.send(POLL)[1] & 0x0080  # homed: no warning


# ---------------------------------------------------------------- motion commands (§4.3)
def test_predef_vai_go_to_pos_from_act_pos_023xh(twin: Twin) -> None:
    twin.homed()
    # §4.3.28: header 023xh, SInt32 target [0.1 µm]: 10 mm, count 1 → 08A1h (homed, motion active, count 1)
    assert twin.state(mci(0x0231, struct.pack("<i", 100_000))) == 0x08A1
    twin.advance(2.0)
    assert twin.send(POLL)[2:] == (0x08C1, 100_000)


def test_vai_go_to_pos_from_act_pos_and_act_vel_013xh(twin: Twin) -> None:
    twin.homed()
    # §4.3.12: target 5 mm, 0.1 m/s, 1 m/s², 1 m/s² (same layout as 010xh)
    assert twin.state(mci(0x0131, struct.pack("<iIII", 50_000, 100_000, 100_000, 100_000))) == 0x08A1
    twin.advance(1.0)
    assert twin.send(POLL)[2:] == (0x08C1, 50_000)


def test_vai_predef_acc_go_to_pos_from_act_pos_0b3xh_uses_its_velocity(twin: Twin) -> None:
    twin.homed()
    # §4.3.102: target 10 mm, max velocity 0.05 m/s (50 000 µm/s); acceleration from the drive (5 m/s² here)
    twin.send(mci(0x0B31, struct.pack("<iI", 100_000, 50_000)))
    twin.advance(0.1)
    # accelerate 0.05/5 = 0.01 s over 0.5·5·0.01² = 0.25 mm, cruise 0.09 s · 0.05 m/s = 4.5 mm → 4.75 mm
    assert twin.send(POLL)[3] == pytest.approx(47_500, abs=1)
    twin.advance(1.0)
    assert twin.send(POLL)[2:] == (0x08C1, 100_000)


def test_increment_dem_pos_011xh_and_increment_target_pos_012xh(twin: Twin) -> None:
    twin.homed()
    go = struct.pack("<iIII", 200_000, 100_000, 100_000, 100_000)  # 20 mm at 0.1 m/s, 1 m/s²
    inc = struct.pack("<iIII", 50_000, 100_000, 100_000, 100_000)  # + 5 mm
    twin.send(mci(0x0101, go))
    twin.advance(0.1)  # end of the acceleration: demand position 0.5 · 1 · 0.1² = 5 mm, target still 20 mm
    twin.send(mci(0x0122, inc))  # §4.3.11: added to the (former) target → 25 mm
    twin.advance(2.0)
    assert twin.send(POLL)[3] == 250_000
    twin.send(mci(0x0103, struct.pack("<iIII", 0, 100_000, 100_000, 100_000)))  # back to 0
    twin.advance(0.1)  # demand position 25 − 5 = 20 mm
    twin.send(mci(0x0114, inc))  # §4.3.10: added to the demand position → 25 mm, not 0 + 5 mm
    twin.advance(2.0)
    assert twin.send(POLL)[3] == 250_000


@pytest.mark.parametrize(("header", "params", "expected"), [
    (0x0172, struct.pack("<I", 200_000), 125_000),  # §4.3.16 VAI Stop, 2 m/s²: 10 + 0.1²/(2·2) m·1e3 = 12.5 mm
    (0x0272, b"", 101_000),  # §4.3.30 Predef VAI Stop, quick-stop deceleration 50 m/s²: 10 + 0.1 mm
], ids=["017xh", "027xh"])
def test_vai_stop_017xh_and_predef_vai_stop_027xh(twin: Twin, header: int, params: bytes, expected: int) -> None:
    twin.homed()
    twin.send(mci(0x0101, struct.pack("<iIII", 200_000, 100_000, 100_000, 100_000)))  # 20 mm, 0.1 m/s, 1 m/s²
    twin.advance(0.15)  # accelerated 0.1 s over 5 mm, then 0.05 s at 0.1 m/s: at 10 mm, 0.1 m/s
    twin.send(mci(header, params))
    twin.advance(1.0)
    assert twin.send(POLL)[2:] == (0x08C2, expected)


def test_p_stream_030xh_follows_the_points_and_stop_streaming_03fxh(twin: Twin) -> None:
    twin.homed()
    header = 0x0301
    for k in range(1, 11):  # §4.3.38: period 2..5 ms; 3 ms here, 0.1 mm per point
        header ^= 0x0003  # toggle the count (§4.1.1.3)
        twin.send(mci(header, struct.pack("<i", 1_000 * k)))
        twin.advance(0.003)
    _, _, state, pos = twin.send(POLL)
    assert state >> 8 == 8 and 9_000 <= pos <= 10_000  # one period late at most (chosen interpolation)
    twin.send(mci(0x03F3))  # 03Fxh, count 3: leave the streaming mode; no "too slow" error afterwards
    twin.advance(1.0)
    assert twin.send(POLL)[2:] == (0x08C3, 10_000)


def test_p_stream_too_fast_is_0084h_and_too_slow_0085h_by_the_drive_itself(twin: Twin) -> None:
    twin.homed()
    twin.send(mci(0x0301, struct.pack("<i", 1_000)))
    assert twin.state(mci(0x0302, struct.pack("<i", 2_000))) == 0x0484  # §10 0084h: < 2 ms apart
    twin.send(cw(0x00BF))
    twin.send(cw(0x0000))
    twin.homed()
    twin.send(mci(0x0303, struct.pack("<i", 1_000)))
    twin.advance(0.010)  # the host falls silent for 10 ms: the drive raises the error on its own cycle
    assert twin.drive.state == 4 and twin.drive.error_code == 0x85  # §10 0085h "PVT Master Too Slow"
    assert twin.state() == 0x0485


def test_time_curves_are_curve_not_defined_0062h(twin: Twin) -> None:
    twin.homed()
    # §4.3.45 Time Curve With Default Parameters (040xh), curve 1: no curve was downloaded → §10 0062h
    assert twin.state(mci(0x0401, struct.pack("<H", 1))) == 0x0462


def test_write_interface_control_word_001xh_in_any_state(twin: Twin) -> None:
    twin.send(cw(0x0000))
    twin.send(cw(0x003E))
    # §4.3.2 the control word through the motion command interface: 003Fh → state 5 HW tests
    assert twin.state(mci(0x0011, struct.pack("<H", 0x003F))) == 0x0500


# ---------------------------------------------------------------- states 10–13, 15–17 (§3.10–3.17)
def test_abort_is_state_12_and_freeze_13_resumes_the_motion(twin: Twin) -> None:
    twin.homed()
    twin.send(mci(0x0101, struct.pack("<iIII", 200_000, 100_000, 100_000, 100_000)))
    twin.advance(0.15)
    assert twin.state(cw(0x001F)) == 0x0D00  # /Freeze cleared → 13 Freezing, quick stop
    twin.advance(0.5)
    frozen = twin.send(POLL)[3]
    assert 0 < frozen < 200_000
    assert twin.state(cw(0x003F)) >> 8 == 8  # /Freeze set: "the drive will finish the frozen motion"
    twin.advance(2.0)
    assert twin.send(POLL)[2:] == (0x08C1, 200_000)
    twin.send(mci(0x0102, struct.pack("<iIII", 0, 100_000, 100_000, 100_000)))
    twin.advance(0.15)
    assert twin.state(cw(0x002F)) == 0x0C00  # /Abort cleared → 12 Aborting
    twin.advance(0.5)
    stopped = twin.send(POLL)[3]
    assert twin.state(cw(0x003F)) == 0x08C2  # set again: rests in position (in target), count 2
    twin.advance(1.0)
    assert twin.send(POLL)[3] == stopped


def test_jog_plus_16_moves_to_the_max_position_and_stops_when_released() -> None:
    t = Twin(stroke=(0.0, 0.02), jog_velocity=0.01)
    try:
        t.homed()
        assert t.state(cw(0x013F)) == 0x1001  # bit 8 Jog Move + → 16, sub 01h "Moving positive"
        t.advance(0.5)
        assert t.state(cw(0x003F)) >> 8 == 8  # released: the motion stops (§3.16)
        t.advance(1.0)
        stopped = t.send(POLL)[3]
        assert 0 < stopped < 200_000
        t.send(cw(0x013F))
        t.advance(3.0)  # 20 mm at 0.01 m/s: done within 2.1 s
        assert t.send(POLL)[2:] == (0x100F, 200_000)  # 0Fh "Jogging + Finished" at the max position
        t.send(cw(0x003F))
        assert t.state(cw(0x023F)) == 0x1101  # bit 9 Jog Move - → 17
    finally:
        t.drive.close()


def test_go_to_position_15_initial_position_11_and_clearance_check_10() -> None:
    t = Twin(go_to_position=0.01, initial_position=0.005, clearance_positions=(0.03, 0.015))
    try:
        t.homed()
        assert t.state(cw(0x007F)) == 0x0F01  # bit 6 → 15 Going To Position
        t.advance(2.0)
        assert t.send(POLL)[2:] == (0x0F0F, 100_000)
        t.send(cw(0x003F))
        assert t.state(cw(0x203F)) == 0x0B01  # bit 13 → 11 Going To Initial Position
        t.advance(2.0)
        assert t.send(POLL)[2:] == (0x0B0F, 50_000)
        t.send(cw(0x003F))
        assert t.state(cw(0x103F)) == 0x0A01  # bit 12 → 10 Clearance Check: two positions, in turn
        t.advance(3.0)
        assert t.send(POLL)[2:] == (0x0A0F, 150_000)
    finally:
        t.drive.close()


def test_special_motions_need_a_homed_motor_0080h(twin: Twin) -> None:
    twin.switch_on()
    twin.advance(0.3)
    assert twin.state(cw(0x007F)) == 0x0480  # §10 0080h: "an action that requires the motor … homed"


# ---------------------------------------------------------------- LinRS requests beyond the default response
def test_warn_word_request_main_00h_sub_03h(twin: Twin) -> None:
    """Layout as public drivers read it ([C] Aurele-Le-Borgne/LinmotPY C1100.py ``getWarning``: request
    ``01 ID 03 02 03 00 04``, a 20-byte reply, warn word at bytes 15–16); value per §3.24 bit 7."""
    twin.switch_on()
    twin.advance(0.3)
    r = twin.drive(bytes.fromhex("01 11 03 02 03 00 04"))
    assert len(r) == 20 and r[2] == 0x10 and r[-1] == 0x04
    assert struct.unpack("<HH", r[9:11] + r[15:17]) == (0x0840, 0x0080)  # state 8, "Motor Not Homed"
    twin.send(cw(0x083F))
    twin.advance(1.0)
    r = twin.drive(bytes.fromhex("01 11 03 02 03 00 04"))
    assert struct.unpack("<HH", r[9:11] + r[15:17]) == (0x090F, 0x0000)  # homed: no warning


def test_read_upid_main_03h_motion_command_count(twin: Twin) -> None:
    """[C] LinmotPY ``getNibble``: ``01 ID 05 02 00 03 B0 1D 04`` → 20 bytes, the count in byte 15's low nibble
    (the same count the state var echoes in state 8, §3.8)."""
    twin.homed()
    twin.send(mci(0x0235, struct.pack("<i", 10_000)))  # count 5
    r = twin.drive(bytes.fromhex("01 11 05 02 00 03 B0 1D 04"))
    assert len(r) == 20 and r[15] & 0x0F == 5 and r[9] & 0x0F == 5
