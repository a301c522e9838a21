"""LinMot twin: states 3, 14, 18–20, status bits 8, 14, 15 (event handler, range indicators), PV/PVA streams (MC-SW).

Sources (MC-SW manual 4.3.4 SG5, 23/09/2014, transcribed in Smart-Vision-Works/linmot_client
``linmot_client/reference/LinMot_MotionCtrl.txt``): state diagram p. 12 (switch-on pattern ``x110`` from state 1
leads to state 2, or to "Setup Error (3)" which leads to "Error (4)"); State Var table p. 13 (main state 3: sub
state "Error Code which will be logged"; 14: "Quick Stop (Error Behaviour)"); §3.4 p. 14 ("The state machine
rests in this state as long the bits 0 is cleared"); §3.14 p. 16 ("Most of the errors, which can occur during an
active motion, cause a quick stop behavior to stop the motion"); §3.19 ("the phase search is only defined for
three phase EC motors"), §3.20 ("the Special Mode is available only on the B1100 drives"); §3.23 status word bits
8 ("Event Handler Active"), 14/15 ("Defined UPID is in Range 1/2"); §4.3.6 ("As long the event handler is active,
the command to be executed on the event situation will be restarted each time the event condition is fulfilled"),
§4.3.20 (01Bxh); §4.3.39 PV stream 031xh (SInt32 position 0.1 µm, SInt32 velocity 1 µm/s, period 2..5 ms);
§4.3.41/4.3.42 ("The first two streaming commands are used to determine the nominal period length. The setpoints
are [then] delayed 1.5 times the period length"); §4.3.42 PVA stream 034xh (period 0.4 .. 10 ms); §10 0084h/0085h.
Expected positions are derived by hand in each test's comment.
"""

from __future__ import annotations

import struct

from tests.test_conformance_linmot_cycle import POLL, Twin, cw, mci

SW_ERROR, SW_EVENT_HANDLER, SW_MOTION_ACTIVE = 1 << 3, 1 << 8, 1 << 13
SW_RANGE_1, SW_RANGE_2 = 1 << 14, 1 << 15


def test_setup_error_is_state_3_until_switch_on_then_state_4() -> None:
    twin = Twin()
    twin.drive.inject_setup_error(0x0050)  # §10 0050h "Setup Err: HW Not Supported"
    twin.send(cw(0x0000))
    _, sw, state, _ = twin.send(cw(0x003E))  # x110 from state 1: to state 3, sub state = the code to be logged
    assert state == 0x0350 and sw & SW_ERROR
    twin.advance(1.0)
    assert twin.state() == 0x0350  # §3.4: rests while bit 0 is cleared
    assert twin.state(cw(0x003F)) == 0x0450  # bit 0 set: the error state with the logged code
    twin.send(cw(0x00BF))  # acknowledged (§3.5): state 0; the setup still holds the error
    twin.send(cw(0x0000))
    assert twin.state(cw(0x003E)) == 0x0350


def test_an_error_during_motion_is_state_14_until_the_quick_stop_ends() -> None:
    twin = Twin()
    twin.homed()
    # VAI Go To Pos 010xh: 50 mm at 0.1 m/s, 1 m/s²: after 0.2 s the motor cruises at 0.1 m/s
    twin.send(mci(0x0101, struct.pack("<iIII", 500_000, 100_000, 100_000, 100_000)))
    twin.advance(0.2)
    # a target beyond the max position (0.12 m stroke) while moving: §10 0008h with the §3.14 quick stop
    _, sw, state, _ = twin.send(mci(0x0102, struct.pack("<iIII", 2_000_000, 100_000, 100_000, 100_000)))
    assert state == 0x0E00 and sw & SW_ERROR and sw & SW_MOTION_ACTIVE
    twin.advance(0.05)  # 0.1 m/s at the twin's 50 m/s² quick stop: 2 ms
    assert twin.state() == 0x0408


def test_an_error_at_rest_goes_to_state_4_at_once() -> None:
    twin = Twin()
    twin.homed()
    assert twin.state(mci(0x0101, struct.pack("<iIII", 2_000_000, 100_000, 100_000, 100_000))) == 0x0408


def test_phase_search_and_special_mode_bits_leave_an_e1100_with_a_linear_motor_in_state_8() -> None:
    twin = Twin()
    twin.homed()
    for word in (0x803F, 0x043F):  # bit 15 Phase Search (EC motors only), bit 10 Special Mode (B1100 only)
        twin.advance(0.5)
        assert twin.state(cw(word)) >> 8 == 8


def test_range_indicators_on_the_actual_position() -> None:
    twin = Twin(range_indicators=((-0.001, 0.001), (0.02, 0.03)))
    twin.homed()  # at the home position 0 m: in range 1
    sw = twin.send(POLL)[1]
    assert sw & (SW_RANGE_1 | SW_RANGE_2) == SW_RANGE_1
    twin.send(mci(0x0101, struct.pack("<iIII", 250_000, 100_000, 100_000, 100_000)))  # to 25 mm
    twin.advance(1.0)
    sw = twin.send(POLL)[1]
    assert sw & (SW_RANGE_1 | SW_RANGE_2) == SW_RANGE_2


def test_pv_stream_031xh_keeps_the_velocity_and_a_silent_host_ends_in_14_then_0085h() -> None:
    twin = Twin()
    twin.homed()
    header = 0x0311
    for k in range(1, 11):  # a ramp at 0.05 m/s, one point every 3 ms: p_k = 0.05 · 0.003 · k = 150 µm · k
        header ^= 0x0003
        twin.send(mci(header, struct.pack("<ii", 1_500 * k, 50_000)))
        twin.advance(0.003)
    # §4.3.39/4.3.41: the first two points give the nominal period (3 ms); each point is reached 1.5 periods after
    # its receipt: point 9 (received at 24 ms) at 28.5 ms, point 10 (27 ms) at 31.5 ms. At 30 ms the drive is
    # 1.5 ms past point 9 on the ramp: 1.35 mm + 0.05 m/s · 1.5 ms = 1.425 mm, still moving
    _, sw, state, pos = twin.send(POLL)
    assert state >> 8 == 8 and abs(pos - 14_250) <= 1 and sw & SW_MOTION_ACTIVE
    twin.advance(0.0025)  # 32.5 ms: no point for 5.5 ms (> 5 ms) while moving: quick stop (state 14)
    assert twin.state() == 0x0E00
    twin.advance(0.01)
    assert twin.state() == 0x0485  # §10 0085h "PVT Master Too Slow"


def test_pva_stream_034xh_takes_1_ms_periods_the_pv_stream_does_not() -> None:
    twin = Twin()
    twin.homed()
    twin.send(mci(0x0341, struct.pack("<iii", 100, 0, 0)))
    twin.advance(0.001)  # §4.3.42: 0.4 .. 10 ms
    assert twin.state(mci(0x0342, struct.pack("<iii", 200, 0, 0))) >> 8 == 8
    twin.send(mci(0x03F3))  # 03Fxh: leave the streaming mode (the last point is reached 2 ms later)
    twin.advance(0.01)  # at rest again: the error below is not raised during motion (that would be state 14)
    twin.send(mci(0x0311, struct.pack("<ii", 300, 0)))
    twin.advance(0.001)  # §4.3.39: 2..5 ms
    assert twin.state(mci(0x0312, struct.pack("<ii", 400, 0))) == 0x0484


def test_trigger_event_command_sets_up_the_event_handler_until_clear_event_008xh() -> None:
    twin = Twin()
    twin.homed()
    # §4.3.20 VAI Increment Target Pos On Rising Trigger Event (01Bxh): +5 mm at 0.1 m/s, 1 m/s², 1 m/s²
    _, sw, state, _ = twin.send(mci(0x01B1, struct.pack("<iIII", 50_000, 100_000, 100_000, 100_000)))
    assert sw & SW_EVENT_HANDLER and state & 0x10  # §3.8: state var bit 4 "Event Handler Active"
    twin.advance(0.5)
    assert twin.send(POLL)[3] == 0  # waits for its event
    for edge in (1, 2):  # §4.3.6: "restarted each time the event condition is fulfilled"
        twin.drive.set_trigger(True)
        twin.advance(1.0)
        assert twin.send(POLL)[3] == 50_000 * edge
        twin.drive.set_trigger(False)  # a falling edge does not start a rising-edge command
        twin.advance(1.0)
        assert twin.send(POLL)[3] == 50_000 * edge
    assert not twin.send(mci(0x0082))[1] & SW_EVENT_HANDLER  # §4.3.6 Clear Event Evaluation
    twin.drive.set_trigger(True)
    twin.advance(1.0)
    assert twin.send(POLL)[3] == 100_000
