"""Simulated LinMot drive speaking LinRS on a pty: the MC-SW state machine on its own cycle, and VAI motion.

Written from the manuals, not from :mod:`drivers.linmot` (no constant is shared). Sources:

* LinRS manual 0185-1082-E (E1100/C1100/E1200/E1400 series): telegram layout p. 11, control-word and
  motion-command examples (``01 11 05 02 00 01 00 00 04``; Predef VAI ``01 11 09 02 00 02 01 02 A0 86 01 00
  04``), default response (``01 11 0C 02 00 00 00 37 68 A1 08 8B FC FF FF 04``) — ../shared/instruments.md §2.2;
* LinMot "Motion Control SW" user manual 4.3.4 (A1100/C1100/C1200/E1200/E1400), SG5 23/09/2014, as transcribed
  in Smart-Vision-Works/linmot_client ``docs/LinMot_MotionCtrl.md`` and ``linmot_client/reference/
  LinMot_MotionCtrl.txt`` (page numbers below are the manual's): §3 state machine pp. 12–16 (§3.1–3.20), §3.22
  control word, §3.23 status word, §3.24 warn word, §4.1 motion-command header p. 21, §4.2 command overview
  pp. 22–27, §4.3 commands pp. 28–54, §10 error code list.

**The drive runs its own cycle.** Every timed transition happens at its time on the rig clock, whether or not a
telegram arrives: the hardware tests end ~300 ms after switch-on and the drive "changes to state 6 without any user
action" (§3.6), then follows the control word it holds (to 8, and on to 9 with Home held); homing, special motions
and motion commands progress on the plant's clock and finish while the host is silent. On a virtual clock the
drive is told each advance (:meth:`VirtualClock.subscribe`); on the wall clock a thread wakes at its next due time.
Each transition is applied at its own time (a homing started by the cycle plans its motion from the instant the
hardware tests ended), so what a poll reads never depends on when, or how often, the host polled.

Modelled: main states 0, 1, 2, 3 (setup error, after :meth:`LinMotDriveSim.inject_setup_error`), 4, 5, 6, 8, 9
(homing), 10 (clearance check: two positions), 11 (going to initial position), 12 (aborting), 13 (freezing,
resumed on /Freeze), 14 (error behaviour quick stop: an error raised while the motor moves), 15 (going to
position), 16/17 (jogging to the stroke ends); status word bits 0–15 (§3.23, bit 7 = warn word ≠ 0; bit 8 the
event handler; bits 14/15 on the actual position, ``range_indicators``); warn word bit 7 "Motor Not Homed" (§3.24);
motion commands 000xh, 001xh, 008xh, 010xh–017xh, 01Axh–01Dxh, 020xh–024xh, 027xh, 02Axh–02Dxh, 030xh–035xh (P,
PV, PVA streams, §4.3.38–4.3.43), 03Fxh, 0B0xh–0B4xh; time curves 040xh–04Fxh answer 0062h "Curve Not Defined"
(§10: no curve is ever downloaded to the twin).

States 18–20 (§3.18–3.20 p. 16) are never entered, as on the drive the twin stands for: "the phase search is only
defined for three phase EC motors with hall switches and ABZ-sensors" (§3.19: a LinMot P01 linear motor is not
one, so control word bit 15 "Phase Search" has no effect); "the Special Mode is available only on the B1100
drives" (§3.20: the twin is an E1100/C1100, so bit 10 has no effect); linearizing (§3.18) has no control-word bit
in §3.22 [chosen: it is started from LinMot-Talk, not over LinRS]. Status bit 8 "Event Handler Active" is set by
the trigger-event commands 01Axh–01Dxh and 02Axh–02Dxh (§4.3.19–4.3.22, §4.3.32–4.3.35) and cleared by 008xh
(§4.3.6); the command runs again at each edge of the X4.6 trigger input, which nothing on the rig drives
(:meth:`LinMotDriveSim.set_trigger` does in tests).

Not modelled (stated choices): state 7 (not used, §3 table p. 13); warn bits other than 7; following error (the
actual position is the demand position, so the "From Act Pos" commands behave as their demand-position
counterparts); every other command of the §4.2 list (other trigger events, analog position, 16-bit VAI, encoder CAM,
indexing, command table, Sin/Bestehorn, force control, …) is answered 0081h "Unknown Motion Cmd", as by a
firmware without it [chosen: accepting a command whose motion the twin cannot produce would let a host believe it
ran]. LinRS messages (the LinRS pages read, p. 11 and the
examples, describe Main 00h Sub 01h, 01h and 02h only; the rest follows the public drivers, marked [C]): Main 00h
Sub 01h, 02h, 04h return the default response ([C] jbaboval/Test-tool-for-LinMot-drives reads the default
response's fields from Sub 02h and 04h replies; what else they carry is not known here); Sub 03h the default
response followed by the warn word and a zero word ([C] LinmotPY reads a 20-byte reply, warn word at bytes 15–16);
Main 01h writes the control word, 02h the motion command interface; Main 03h with UPID 1DB0h returns the default
response followed by the motion command count as SInt32 ([C] LinmotPY); any other UPID or Main ID (04h curves,
05h parameters, 06h program handling, 08h command table) is answered with the default response and communication
state 01h [chosen: a reply keeps a host's framing in step; the non-zero comm state tells it the message was not
served].

Where the manuals are silent the choice is marked ``[assumed]`` or ``[chosen]`` beside it.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bench.core.clock import Clock
from bench.core.motion import MotionProfile
from bench.core.plant import Plant

# ---------------------------------------------------------------- LinRS framing (LinRS manual p. 11)
STX, DATA_START, ETX = 0x01, 0x02, 0x04  # 01h | ID | Len | 02h | SubID | MainID | data… | [CRC lo hi] | 04h
STX_BYTE, ETX_BYTE = bytes([STX]), bytes([ETX])
MAIN_RESPONSE = 0x00  # request Sub 01h: "return default response" (manual examples; drivers found)
MAIN_CONTROL_WORD = 0x01  # Sub 00h, 2-byte control word (manual "Write Control Word" example)
MAIN_MOTION_COMMAND = 0x02  # Sub 00h, header + parameters (manual "Write Motion Command Interface" example)
# [C] Aurele-Le-Borgne/LinmotPY C1100.py (read, not copied): Main 00h Sub 03h is answered with 20 bytes, the warn
# word at bytes 15–16 after the default response's fields; Main 03h with a 2-byte UPID with 20 bytes, the UPID's
# value (SInt32) at bytes 15–18 — UPID 1DB0h read as the motion command count (low nibble)
SUB_WARN_WORD = 0x03
MAIN_READ_UPID = 0x03
UPID_MOTION_COMMAND_COUNT = 0x1DB0
COMM_OK = 0x00
_RESPONSE_IDS = bytes([DATA_START, 0x00, MAIN_RESPONSE])  # a response's 02h, Sub ID 00h, Main ID 00h
# A telegram left incomplete for this long (wall time) is discarded before new bytes are taken. [chosen: the
# LinRS pages read do not say how the drive resynchronises after line noise; a receive timeout is what a UART
# protocol without a length-independent delimiter needs, and a host writes a telegram in one go, so a pause
# inside one only follows noise]
RX_IDLE_RESET_S = 0.02
COMM_UNKNOWN_MESSAGE = 0x01  # [assumed] the manual pages read do not list communication-state codes
POS_UNIT = 1e-7  # m per count: positions SInt32 in 0.1 µm (MC-SW §4.3.9)
VEL_UNIT = 1e-6  # m/s per count (MC-SW §4.3.9)
ACC_UNIT = 1e-5  # m/s² per count (MC-SW §4.3.9)

# ---------------------------------------------------------------- control word (MC-SW §3.22)
CW_SWITCH_ON = 1 << 0
CW_VOLTAGE_ENABLE = 1 << 1
CW_QUICK_STOP_N = 1 << 2  # /Quick Stop: 0 = OFF3
CW_ENABLE_OPERATION = 1 << 3
CW_ABORT_N = 1 << 4  # /Abort
CW_FREEZE_N = 1 << 5  # /Freeze
CW_GO_TO_POSITION = 1 << 6
CW_ERROR_ACK = 1 << 7  # rising edge acknowledges
CW_JOG_PLUS = 1 << 8
CW_JOG_MINUS = 1 << 9
CW_HOME = 1 << 11  # level: 1 = Homing, 0 = Stop Homing
CW_CLEARANCE_CHECK = 1 << 12
CW_GO_TO_INITIAL = 1 << 13

# ---------------------------------------------------------------- status word (MC-SW §3.23)
SW_OPERATION_ENABLED = 1 << 0  # state 8 or higher
SW_SWITCH_ON_ACTIVE = 1 << 1  # control word bit 0
SW_ENABLE_OPERATION = 1 << 2  # control word bit 3
SW_ERROR = 1 << 3
SW_VOLTAGE_ENABLE = 1 << 4  # control word bit 1
SW_QUICK_STOP_N = 1 << 5  # control word bit 2
SW_SWITCH_ON_LOCKED = 1 << 6  # released with control word bit 0 = 0
SW_WARNING = 1 << 7  # "one or more bits in the Warn Word are set"
SW_EVENT_HANDLER = 1 << 8  # "Event Handler setup" (a trigger-event command), until 008xh clears it
SW_SPECIAL_MOTION = 1 << 9  # special motion (homing, …) runs
SW_IN_TARGET = 1 << 10
SW_HOMED = 1 << 11
SW_FATAL = 1 << 12
SW_MOTION_ACTIVE = 1 << 13
SW_RANGE_1 = 1 << 14  # "Defined UPID is in Range 1" [chosen UPID: the actual position]
SW_RANGE_2 = 1 << 15  # "Defined UPID is in Range 2"

# ---------------------------------------------------------------- warn word (MC-SW §3.24)
WW_MOTOR_NOT_HOMED = 1 << 7  # "Warning Motor Not Homed Yet"

# ---------------------------------------------------------------- main states (MC-SW §3, State Var table p. 13)
NOT_READY, SWITCH_ON_DISABLED, READY_TO_SWITCH_ON, SETUP_ERROR, ERROR, HW_TESTS = 0, 1, 2, 3, 4, 5
READY_TO_OPERATE, OPERATION_ENABLED, HOMING, CLEARANCE_CHECK, GOING_TO_INITIAL = 6, 8, 9, 10, 11
ABORTING, FREEZING, ERROR_QUICK_STOP, GOING_TO_POSITION, JOGGING_PLUS, JOGGING_MINUS = 12, 13, 14, 15, 16, 17
SUB_FINISHED = 0x0F  # "Homing Finished", "Clearance Check Finished", …, "Jogging + Finished"
SUB_RUNNING = 0x01  # states 16/17: "Moving positive/negative"; [assumed] the same in 9, 10, 11, 15 while running
# The special states a control-word level starts from state 8, in the order tried [chosen: the manual gives no
# priority between bits set together], and leaves when it is released (§3.9–3.11, §3.15–3.17, §3.22).
SPECIAL_BITS = {HOMING: CW_HOME, CLEARANCE_CHECK: CW_CLEARANCE_CHECK, GOING_TO_INITIAL: CW_GO_TO_INITIAL,
                GOING_TO_POSITION: CW_GO_TO_POSITION, JOGGING_PLUS: CW_JOG_PLUS, JOGGING_MINUS: CW_JOG_MINUS}

# ---------------------------------------------------------------- error codes (MC-SW §10 error code list)
ERR_MIN_POS_UNDERSHOT = 0x0007  # "Err: Min Pos Undershot"
ERR_MAX_POS_OVERSHOT = 0x0008  # "Err: Max Pos Overshot"
ERR_CURVE_NOT_DEFINED = 0x0062  # "Cfg Err: Curve Not Defined"
ERR_NOT_HOMED = 0x0080  # "User Err: Lin: Not Homed"
ERR_UNKNOWN_MOTION_CMD = 0x0081  # "User Err: Unknown Motion Cmd" (§10 of MC-SW 4.3.4; 0085h there is
#                                   "PVT Master Too Slow" — the 0x85 does not match this list)
ERR_PVT_MASTER_TOO_FAST = 0x0084  # "User Err: PVT Master Too Fast": streaming commands closer than 2 ms
ERR_PVT_MASTER_TOO_SLOW = 0x0085  # "User Err: PVT Master Too Slow": more than 5 ms between them
ERR_WRONG_STATE = 0x0086  # "User Err: Motion Cmd In Wrong St"

# ---------------------------------------------------------------- motion commands (MC-SW §4.2/§4.3)
# header = Master ID (bits 15–8) | Sub ID (7–4) | count (3–0); the twin keys on header >> 4 (e.g. 010h)
MC_NOP = 0x000  # §4.3.1 "No Operation": "can be sent in any operational state"
MC_WRITE_CONTROL_WORD = 0x001  # §4.3.2 UInt16 control word
MC_CLEAR_EVENT = 0x008  # §4.3.6 "resets the event handler"
MC_VAI_GOTO = 0x010  # §4.3.9  SInt32 pos, UInt32 vel, acc, dec
MC_VAI_INC_DEM = 0x011  # §4.3.10 increment added to the demand position
MC_VAI_INC_TARGET = 0x012  # §4.3.11 increment added to the (former) target position
MC_VAI_GOTO_ACT = 0x013  # §4.3.12 from actual position and actual velocity
MC_VAI_GOTO_ACT_V0 = 0x014  # §4.3.13 from actual position, start velocity forced to zero
MC_VAI_INC_ACT = 0x015  # §4.3.14 increment added to the actual position
MC_VAI_INC_ACT_V0 = 0x016  # §4.3.15 the same, start velocity forced to zero
MC_VAI_STOP = 0x017  # §4.3.16 UInt32 deceleration
MC_PREDEF_GOTO = 0x020  # §4.3.25 SInt32 pos; v/a/d from the drive's parameters
MC_PREDEF_INC_DEM = 0x021  # §4.3.26
MC_PREDEF_INC_TARGET = 0x022  # §4.3.27
MC_PREDEF_GOTO_ACT = 0x023  # §4.3.28 "from the actual position"
MC_PREDEF_GOTO_ACT_V0 = 0x024  # §4.3.29
MC_PREDEF_STOP = 0x027  # §4.3.30 "Predef VAI Stop With Quick Stop Deceleration"
MC_P_STREAM = 0x030  # §4.3.38 SInt32 position; slave time stamp; period 2..5 ms
MC_PV_STREAM = 0x031  # §4.3.39 SInt32 position, SInt32 velocity (1 µm/s); period 2..5 ms
MC_P_STREAM_CFG = 0x032  # §4.3.40 as 030xh, derivation with the configured period (UPID 14E6h)
MC_PV_STREAM_CFG = 0x033  # §4.3.41 position, velocity; "period length must be in the time range of 0.4ms .. 10ms"
MC_PVA_STREAM = 0x034  # §4.3.42 position, velocity, acceleration (1E-5 m/s²); 0.4 .. 10 ms
MC_PVA_STREAM_CFG = 0x035  # §4.3.43 as 034xh with the configured period
MC_STOP_STREAMING = 0x03F  # §4.3.44 "used to leave the streaming mode"
MC_PREDEF_ACC_GOTO = 0x0B0  # §4.3.99  SInt32 pos, UInt32 vel; acc/dec from the drive's parameters
MC_PREDEF_ACC_INC_DEM = 0x0B1  # §4.3.100
MC_PREDEF_ACC_INC_TARGET = 0x0B2  # §4.3.101
MC_PREDEF_ACC_GOTO_ACT = 0x0B3  # §4.3.102 "from the actual position and with actual velocity"
MC_PREDEF_ACC_GOTO_ACT_V0 = 0x0B4  # §4.3.103
# §4.3.19–4.3.22, §4.3.32–4.3.35: VAI / Predef VAI on a trigger edge of X4.6: (rising edge, increment target,
# parameters). They set up the event handler (status bit 8); "as long the event handler is active, the command to
# be executed on the event situation will be restarted each time the event condition is fulfilled" (§4.3.6).
# 02Dxh: the overview p. 22 names it "Predef VAI Increment Target Pos On Falling Trigger Event"; §4.3.35's heading
# repeats 02Cxh's name [chosen: the overview, which follows the 01Dxh pattern].
_TRIGGERED: dict[int, tuple[bool, bool, str]] = {
    0x01A: (True, False, "full"), 0x01B: (True, True, "full"), 0x01C: (False, False, "full"),
    0x01D: (False, True, "full"), 0x02A: (True, False, "predef"), 0x02B: (True, True, "predef"),
    0x02C: (False, False, "predef"), 0x02D: (False, True, "predef"),
}
TIME_CURVES = frozenset({0x040, 0x041, 0x042, 0x043, 0x044, 0x045, 0x046, 0x047, 0x04A, 0x04C, 0x04E, 0x04F})
STREAM_PERIOD_S = (0.002, 0.005)  # §4.3.38: "the streaming period has to be in the time range 2..5ms"
# Streams: (parameters carrying velocity, period range [s]) per §4.3.38–4.3.43. The "configured period" variants
# derive velocity and acceleration with UPID 14E6h; the twin's configured period is the host's measured one
# [chosen: the twin has no parameter store]. The PVA acceleration is read and not used to shape the motion (the
# segment matches position and velocity) [chosen].
_STREAMS: dict[int, tuple[bool, tuple[float, float]]] = {
    MC_P_STREAM: (False, STREAM_PERIOD_S), MC_PV_STREAM: (True, STREAM_PERIOD_S),
    MC_P_STREAM_CFG: (False, STREAM_PERIOD_S), MC_PV_STREAM_CFG: (True, (0.0004, 0.010)),
    MC_PVA_STREAM: (True, (0.0004, 0.010)), MC_PVA_STREAM_CFG: (True, (0.0004, 0.010)),
}

# VAI families: (kind of target, start velocity forced to 0, parameters: "full" v/a/d, "predef", "predef acc")
_VAI: dict[int, tuple[str, bool, str]] = {
    MC_VAI_GOTO: ("abs", False, "full"), MC_VAI_INC_DEM: ("dem", False, "full"),
    MC_VAI_INC_TARGET: ("target", False, "full"), MC_VAI_GOTO_ACT: ("abs", False, "full"),
    MC_VAI_GOTO_ACT_V0: ("abs", True, "full"), MC_VAI_INC_ACT: ("act", False, "full"),
    MC_VAI_INC_ACT_V0: ("act", True, "full"),
    MC_PREDEF_GOTO: ("abs", False, "predef"), MC_PREDEF_INC_DEM: ("dem", False, "predef"),
    MC_PREDEF_INC_TARGET: ("target", False, "predef"), MC_PREDEF_GOTO_ACT: ("abs", False, "predef"),
    MC_PREDEF_GOTO_ACT_V0: ("abs", True, "predef"),
    MC_PREDEF_ACC_GOTO: ("abs", False, "acc"), MC_PREDEF_ACC_INC_DEM: ("dem", False, "acc"),
    MC_PREDEF_ACC_INC_TARGET: ("target", False, "acc"), MC_PREDEF_ACC_GOTO_ACT: ("abs", False, "acc"),
    MC_PREDEF_ACC_GOTO_ACT_V0: ("abs", True, "acc"),
}
_PARAM_BYTES = {"full": 16, "predef": 4, "acc": 8}  # §4.3.9 / §4.3.25 / §4.3.99 parameter layouts
WALL_IDLE_WAKE_S = 0.05  # wall clock: the cycle thread's longest sleep when nothing is due [chosen]


@dataclass
class _Stream:
    """The streaming mode under way: its kind, its longest period, the last point and the nominal period."""

    with_velocity: bool
    longest: float
    t_last: float
    p_last: float
    v_last: float
    nominal: float | None = None


class LinMotDriveSim:
    """Protocol handler + state machine of one simulated drive (feed it bytes; it returns replies)."""

    def __init__(self, plant: Plant, clock: Clock, *, drive_id: int = 0x11, stroke: tuple[float, float] = (0.0, 0.12),
                 home_position: float = 0.0, hw_test_time: float = 0.3, homing_time: float = 1.0,
                 quick_stop_decel: float = 50.0, checksum: bool = False,
                 predef_vai: tuple[float, float, float] = (0.5, 5.0, 5.0),
                 special_vai: tuple[float, float, float] = (0.1, 1.0, 1.0), jog_velocity: float = 0.01,
                 initial_position: float | None = None, go_to_position: float | None = None,
                 clearance_positions: tuple[float, float] | None = None,
                 range_indicators: tuple[tuple[float, float] | None, tuple[float, float] | None] = (None, None),
                 ) -> None:
        """``hw_test_time``: state 5 lasts "about 300 ms" (MC-SW §3.6). ``homing_time``: shortest homing [assumed].
        ``predef_vai``: (velocity, acceleration, deceleration) the drive's parameters give Predef VAI commands
        (Predef Acc commands take acceleration and deceleration from it) [assumed values]. ``special_vai``: the
        same for homing, clearance check, going to initial position and going to position; ``jog_velocity`` the
        jog speed [assumed]. ``initial_position``, ``go_to_position`` (default: the home position) and
        ``clearance_positions`` (default: the stroke ends) are the drive's parameters for states 11, 15 and 10.
        ``stroke``: the drive's min/max position parameters. ``range_indicators``: (min, max) of the actual
        position [m] for status bits 14 and 15, None for a range not set up (the bit reads 0)."""
        self.plant = plant
        self.clock = clock
        self.drive_id = drive_id
        self.stroke = stroke
        self.home_position = home_position
        self.hw_test_time = hw_test_time
        self.homing_time = homing_time
        self.quick_stop_decel = quick_stop_decel
        self.checksum = checksum
        self.predef_vai = predef_vai
        self.special_vai = special_vai
        self.jog_velocity = jog_velocity
        self.initial_position = home_position if initial_position is None else initial_position
        self.go_to_position = home_position if go_to_position is None else go_to_position
        self.clearance_positions = stroke if clearance_positions is None else clearance_positions
        self.range_indicators = range_indicators
        self.state = NOT_READY
        self.error_code = 0
        self.fatal = False
        self.setup_error = 0  # a setup error the drive's configuration holds (inject_setup_error): state 3
        self._pending: tuple[int, bool] = (0, False)  # the error state 14 logs when its quick stop ends
        self.homed = False
        self.special_done = False  # the special motion of states 9–11, 15–17 has finished (sub state 0Fh)
        self.control_word = 0
        self.count = 0
        self._now = clock.now()  # how far the drive's cycle has run
        self._t_state = self._now  # when the current timed state (5 HW tests) began
        self._special_end = math.inf  # when the special motion under way finishes
        self._phase = 0  # clearance check: 0 going to the first position, 1 to the second
        self._vai: tuple[float, float, float, float] | None = None  # last VAI (target, v, a, d): resumes a freeze
        self._stream: _Stream | None = None  # the streaming mode under way
        # the event handler's command: (rising edge, increment target, raw position, v, a, d); None: not set up
        self._event: tuple[bool, bool, float, float, float, float] | None = None
        self.trigger_level = False  # X4.6 trigger input [chosen: configured as trigger input, low, not wired]
        self._due = math.inf  # the next timed transition
        self._buf = b""
        self._rx_at = 0.0  # wall time of the last bytes received
        self._lock = threading.RLock()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        subscribe = getattr(clock, "subscribe", None)
        if clock.virtual and subscribe is not None:
            subscribe(self._on_clock)
        else:
            self._thread = threading.Thread(target=self._cycle, name="linmot-cycle", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------ the drive's own cycle
    def close(self) -> None:
        """Stop the drive's cycle (wall clock: its thread; virtual clock: its subscription)."""
        self._closed.set()
        unsubscribe = getattr(self.clock, "unsubscribe", None)
        if unsubscribe is not None:
            unsubscribe(self._on_clock)
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None

    def _on_clock(self, t: float) -> None:
        if t >= self._due:  # cheap when nothing is due: the clock tells every advance
            self.advance(t)

    def _cycle(self) -> None:
        while not self._closed.wait(min(max(self._due - self.clock.now(), 0.0), WALL_IDLE_WAKE_S)):
            self.advance(self.clock.now())

    def advance(self, t: float) -> None:
        """Run the drive's cycle up to rig time ``t``: each timed transition at its own time."""
        with self._lock:
            self._run_until(t)

    def _run_until(self, t: float) -> None:
        while self._due <= t:
            self._now = max(self._now, self._due)
            self._timed_transition()
            self._evaluate(self.control_word, 0)  # the cycle follows the control word it holds
            self._reschedule()
        self._now = max(self._now, t)

    def _reschedule(self) -> None:
        due = math.inf
        if self.state == HW_TESTS:
            due = self._t_state + self.hw_test_time
        elif self.state in SPECIAL_BITS and not self.special_done:
            due = self._special_end
        elif self.state == OPERATION_ENABLED and self._stream is not None:
            due = self._stream.t_last + self._stream.longest
        elif self.state == ERROR_QUICK_STOP:
            due = self.plant.motion.t_end
        self._due = due

    def _timed_transition(self) -> None:
        s, now = self.state, self._now
        if s == HW_TESTS:
            self.state = READY_TO_OPERATE  # §3.6: "changes to state 6 without any user action"
        elif s == CLEARANCE_CHECK and self._phase == 0:  # §3.10: "two positions are moved to"
            self._phase = 1
            self._special_end = self._goto(now, self.clearance_positions[1], *self.special_vai).t_end
        elif s in SPECIAL_BITS:
            self.special_done = True
            self.homed = self.homed or s == HOMING
        elif s == OPERATION_ENABLED and self._stream is not None:
            self._error(ERR_PVT_MASTER_TOO_SLOW)  # §10 0085h: "the drive expects … every 2ms to 5ms"
        elif s == ERROR_QUICK_STOP:  # §3.14: "after the quick stop is finished" → the error state
            self.state, (self.error_code, fatal) = ERROR, self._pending
            self.fatal = self.fatal or fatal

    # ------------------------------------------------------------ faults
    def inject_error(self, code: int, fatal: bool = False) -> None:
        """Fault injection: the drive raises error ``code`` now (state 4, through state 14 if the motor moves)."""
        with self._lock:
            self._run_until(self.clock.now())
            self._error(code, fatal)
            self._reschedule()

    def inject_setup_error(self, code: int) -> None:
        """Fault injection: the drive's setup holds error ``code`` (e.g. 0050h "Setup Err: HW Not Supported"):
        from state 1 the switch-on pattern leads to state 3 instead of 2 (§3 diagram p. 12); 0 clears it."""
        with self._lock:
            self.setup_error = code

    def set_trigger(self, level: bool) -> None:
        """Drive the X4.6 trigger input (the rig wires nothing to it; tests and fault scripts do): an edge of the
        event handler's kind starts its command again, in state 8 (§4.3.6, §4.3.19–4.3.22)."""
        with self._lock:
            self._run_until(self.clock.now())
            rising = level and not self.trigger_level
            falling = self.trigger_level and not level
            self.trigger_level = level
            if self._event is None or self.state != OPERATION_ENABLED:
                return
            on_rising, increment, raw, vmax, acc, dec = self._event
            if (rising and on_rising) or (falling and not on_rising):
                target = raw + (self.plant.motion.target if increment else 0.0)
                if vmax > 0 and acc > 0 and dec > 0 and not self._out_of_stroke(target):
                    self._stream, self._vai = None, (target, vmax, acc, dec)
                    self._goto(self._now, target, vmax, acc, dec)
            self._reschedule()

    def _error(self, code: int, fatal: bool = False) -> None:
        """§3.14: "most of the errors, which can occur during an active motion, cause a quick stop behavior to
        stop the motion": in state 8 or higher with the motor moving the drive goes to state 14 and on to 4 when
        the quick stop has ended; at rest, or below state 8, to state 4 at once [chosen: "most" is not a list,
        the twin treats every error alike]."""
        moving = self.state >= OPERATION_ENABLED and self._moving(self._now)
        self._halt(self.quick_stop_decel)
        self._stream = None
        if moving and self.state != ERROR_QUICK_STOP:
            self.state, self._pending = ERROR_QUICK_STOP, (code, fatal)
            return
        self.state = ERROR
        self.error_code = code
        self.fatal = self.fatal or fatal

    def _moving(self, t: float) -> bool:
        _, vel = self.plant.motor_state(t)
        return bool(abs(vel) > 0 or t < self.plant.motion.t_end)

    # ------------------------------------------------------------ state machine (MC-SW §3)
    def _apply_control_word(self, cw: int) -> None:
        prev, self.control_word = self.control_word, cw
        self._evaluate(cw, cw & ~prev)

    def _evaluate(self, cw: int, rising: int) -> None:
        """Run the transitions the control word allows, as the drive does cyclically (several per write)."""
        for _ in range(8):
            before = self.state
            self._step(cw, rising)
            rising = 0  # an edge acts once
            if self.state == before:
                return

    def _step(self, cw: int, rising: int) -> None:
        s = self.state
        enabled_bits = CW_VOLTAGE_ENABLE | CW_QUICK_STOP_N
        if s == ERROR:  # §3.5: rising edge of bit 7 acknowledges, not for a fatal error
            if rising & CW_ERROR_ACK and not self.fatal:
                self.state, self.error_code = NOT_READY, 0  # diagram: error → (bit 7) → state 0
            return
        if s == ERROR_QUICK_STOP:
            return  # §3.14: the quick stop runs to its end whatever the control word [chosen]
        if s == SETUP_ERROR:  # §3.4: "rests in this state as long the bits 0 is cleared"; diagram: 3 → 4
            if cw & CW_SWITCH_ON:
                self.state, self.error_code = ERROR, self.setup_error
            return
        if s == NOT_READY:  # §3.1: wait for the release of bit 0
            if not cw & CW_SWITCH_ON:
                self.state = SWITCH_ON_DISABLED
            return
        if s == SWITCH_ON_DISABLED:  # §3.2 and diagram: control word xxxx x110 → state 2
            if cw & 0x0007 == 0x0006:
                self.state = SETUP_ERROR if self.setup_error else READY_TO_SWITCH_ON
            return
        if cw & enabled_bits != enabled_bits:  # OFF2 / OFF3 from any powered state: back to state 1
            if s >= HW_TESTS:
                self._halt(self.quick_stop_decel)
            self.state = SWITCH_ON_DISABLED
            self._stream = None
            return
        if s == READY_TO_SWITCH_ON:  # §3.3: rests while bit 0 is cleared
            if cw & CW_SWITCH_ON:
                self.state, self._t_state = HW_TESTS, self._now
            return
        if not cw & CW_SWITCH_ON:  # OFF1: power stage off
            if s >= HW_TESTS:
                self._halt(self.quick_stop_decel)
            self.state = READY_TO_SWITCH_ON
            self._stream = None
            return
        if s == HW_TESTS:
            return  # §3.6: left by the cycle when the tests are done
        if s == READY_TO_OPERATE:
            if cw & CW_ENABLE_OPERATION:
                self.state = OPERATION_ENABLED
            return
        if not cw & CW_ENABLE_OPERATION:  # §3.7: clearing bit 3 in state 8 or higher → state 6 at once
            self._halt(self.quick_stop_decel)
            self.state, self.special_done, self._stream = READY_TO_OPERATE, False, None
            return
        if s == OPERATION_ENABLED:
            if not cw & CW_ABORT_N:  # §3.12: quick stop, rests position controlled, motion command cleared
                self._halt(self.quick_stop_decel)
                self.state, self._vai, self._stream = ABORTING, None, None
            elif not cw & CW_FREEZE_N:  # §3.13: quick stop, the target is kept
                self._halt(self.quick_stop_decel)
                self.state, self._stream = FREEZING, None
            else:
                for state, bit in SPECIAL_BITS.items():
                    if cw & bit:
                        self._start_special(state)
                        return
            return
        if s == ABORTING:  # §3.12: "setting the bit again the drive rests in position"
            if cw & CW_ABORT_N:
                self.state = OPERATION_ENABLED
            return
        if s == FREEZING:  # §3.13: "setting the bit again the drive will finish the frozen motion"
            if cw & CW_FREEZE_N:
                self.state = OPERATION_ENABLED
                if self._vai is not None:
                    self._goto(self._now, *self._vai)
            return
        if s in SPECIAL_BITS and not cw & SPECIAL_BITS[s]:  # released: back to 8 (homed only if it finished)
            if not self.special_done:
                self._halt(self.quick_stop_decel)  # §3.16/3.17: "releasing the bit will stop the motion"
            self.state, self.special_done = OPERATION_ENABLED, False

    def _start_special(self, state: int) -> None:
        """Enter state 9, 10, 11, 15, 16 or 17 from state 8 and start its motion."""
        if state != HOMING and not self.homed:
            self._error(ERR_NOT_HOMED)  # §10 0080h: "an action that requires the motor to be already homed"
            return
        now = self._now
        self.state, self.special_done, self._phase, self._vai = state, False, 0, None
        vmax, acc, dec = self.special_vai
        target = {HOMING: self.home_position, CLEARANCE_CHECK: self.clearance_positions[0],
                  GOING_TO_INITIAL: self.initial_position, GOING_TO_POSITION: self.go_to_position,
                  JOGGING_PLUS: self.stroke[1], JOGGING_MINUS: self.stroke[0]}[state]
        if state in (JOGGING_PLUS, JOGGING_MINUS):
            vmax = self.jog_velocity
        end = self._goto(now, target, vmax, acc, dec).t_end
        if state == HOMING:  # the reference search takes at least homing_time [assumed]
            self.homed = False
            end = max(end, now + self.homing_time)
        self._special_end = end

    # ------------------------------------------------------------ motion on the plant
    def _set_profile(self, make: Callable[[float, float], MotionProfile]) -> MotionProfile:
        """Replace the motion from the cycle's time: ``make(position, velocity)`` at that time."""
        p, v = self.plant.motion.at(self._now)
        profile = make(p, v)
        self.plant.set_motion(lambda _t, _p, _v: profile)  # planned from self._now, however late applied
        return profile

    def _goto(self, t: float, target: float, vmax: float, acc: float, dec: float,
              from_rest: bool = False) -> MotionProfile:
        return self._set_profile(lambda p, v: MotionProfile.plan(t, p, 0.0 if from_rest else v, target, vmax, acc,
                                                                 dec))

    def _halt(self, dec: float) -> None:
        t = self._now
        self._set_profile(lambda p, v: MotionProfile.hold(t, p) if v == 0 else
                          MotionProfile.plan(t, p, v, p + v * abs(v) / (2 * dec), abs(v) + 1e-9, dec, dec))

    def _motion_command(self, data: bytes) -> None:
        if len(data) < 2:
            return
        header = struct.unpack("<H", data[:2])[0]
        count = header & 0x0F  # §4.1.1.3: executed only when the count changed
        if count == self.count:
            return
        self.count = count
        if self.state in (ERROR, ERROR_QUICK_STOP):
            return  # [assumed] in the error state the pending error stays; the command is dropped
        group, params = header >> 4, data[2:]
        if group == MC_NOP:
            return  # §4.3.1: "can be sent in any operational state"
        if group == MC_WRITE_CONTROL_WORD:  # §4.3.2: the control word through the motion command interface
            if len(params) >= 2:
                self._apply_control_word(struct.unpack("<H", params[:2])[0])
            return
        if self.state != OPERATION_ENABLED:
            self._error(ERR_WRONG_STATE)  # §3.7, §10 0086h
            return
        if group == MC_CLEAR_EVENT:
            self._event = None  # §4.3.6: "resets the event handler"
            return
        if group in TIME_CURVES:
            self._error(ERR_CURVE_NOT_DEFINED)  # §10 0062h: no curve is defined in the twin
            return
        if group not in _VAI and group not in _STREAMS and group not in _TRIGGERED and group not in (
                MC_VAI_STOP, MC_PREDEF_STOP, MC_STOP_STREAMING):
            self._error(ERR_UNKNOWN_MOTION_CMD)
            return
        if not self.homed:
            self._error(ERR_NOT_HOMED)
            return
        params = params.ljust(16, b"\0")  # [chosen] parameters a short telegram leaves out read as 0
        if group in _TRIGGERED:
            rising, increment, layout = _TRIGGERED[group]
            raw = struct.unpack("<i", params[:4])[0] * POS_UNIT
            if layout == "full":
                v_raw, a_raw, d_raw = struct.unpack("<III", params[4:16])
                self._event = (rising, increment, raw, v_raw * VEL_UNIT, a_raw * ACC_UNIT, d_raw * ACC_UNIT)
            else:
                self._event = (rising, increment, raw, *self.predef_vai)
            return  # waits for its edge; the streaming mode is not left [chosen]
        if group in _STREAMS:
            with_velocity, periods = _STREAMS[group]
            raw_p, raw_v = struct.unpack("<ii", params[:8])
            self._stream_point(raw_p * POS_UNIT, raw_v * VEL_UNIT if with_velocity else None, periods)
            return
        last_stream, self._stream = self._stream, None  # any other command leaves the streaming mode [chosen]
        if group == MC_STOP_STREAMING:
            if last_stream is not None:  # the last point is still reached, then the drive rests [chosen]
                self._leave_stream(last_stream)
            return
        if group in (MC_VAI_STOP, MC_PREDEF_STOP):  # §4.3.16 deceleration parameter; §4.3.30 quick stop dec.
            dec = struct.unpack("<I", params[:4])[0] * ACC_UNIT if group == MC_VAI_STOP else self.quick_stop_decel
            if dec > 0:
                self._halt(dec)
                self._vai = None
            return
        kind, from_rest, layout = _VAI[group]
        raw = struct.unpack("<i", params[:4])[0] * POS_UNIT
        if layout == "full":
            v_raw, a_raw, d_raw = struct.unpack("<III", params[4:16])
            vmax, acc, dec = v_raw * VEL_UNIT, a_raw * ACC_UNIT, d_raw * ACC_UNIT
        elif layout == "acc":
            vmax = struct.unpack("<I", params[4:8])[0] * VEL_UNIT
            acc, dec = self.predef_vai[1:]
        else:
            vmax, acc, dec = self.predef_vai
        if vmax == 0 or acc == 0 or dec == 0:
            return  # [assumed] a zero limit plans no motion
        pos, _ = self.plant.motor_state(self._now)  # actual = demand position: no following error in the twin
        target = raw + {"abs": 0.0, "dem": pos, "act": pos, "target": self.plant.motion.target}[kind]
        if self._out_of_stroke(target):
            return
        self._vai = (target, vmax, acc, dec)
        self._goto(self._now, target, vmax, acc, dec, from_rest=from_rest)

    def _out_of_stroke(self, target: float) -> bool:
        # [assumed] a target beyond the position limits trips at once (the drive trips when passing them)
        if target > self.stroke[1]:
            self._error(ERR_MAX_POS_OVERSHOT)
            return True
        if target < self.stroke[0]:
            self._error(ERR_MIN_POS_UNDERSHOT)
            return True
        return False

    def _stream_point(self, position: float, velocity: float | None, periods: tuple[float, float]) -> None:
        """§4.3.38–4.3.43 streams: the interface time-stamps each point on receipt, ``periods`` (shortest,
        longest) apart. PV/PVA (§4.3.41–4.3.43): "The first two streaming commands are used to determine the
        nominal period length. The setpoints are [then] delayed 1.5 times the period length. Between the setpoints,
        the slave performs a fine interpolation" — each point is reached with its velocity 1.5 nominal periods after
        its receipt, the drive moving between points in two constant-acceleration halves that match position and
        velocity [chosen interpolation]. P (§4.3.38/4.3.40, delay not given): when a point arrives the drive moves
        to the previous one over the period just measured, at a constant pace, to rest there [assumed]."""
        if self._out_of_stroke(position):
            return
        now, st = self._now, self._stream
        self._vai = None
        if st is not None and now - st.t_last < periods[0]:
            self._error(ERR_PVT_MASTER_TOO_FAST)  # §10 0084h
            return
        if st is None or st.with_velocity != (velocity is not None):
            st = self._stream = _Stream(velocity is not None, periods[1], now, position, velocity or 0.0)
            return
        if velocity is None:
            self._p_segment(st.p_last, now - st.t_last)
        else:
            if st.nominal is None:
                st.nominal = now - st.t_last  # "the first two streaming commands"
            delay = 1.5 * st.nominal
            self._pv_segments([(st.t_last + delay, st.p_last, st.v_last), (now + delay, position, velocity)])
        st.t_last, st.p_last, st.v_last = now, position, velocity or 0.0

    def _leave_stream(self, st: _Stream) -> None:
        """03Fxh: the last point is still reached (a P stream's at the shortest period, a PV/PVA stream's when
        planned), and the drive comes to rest there [chosen: §4.3.44 says only that the command leaves the mode]."""
        if not st.with_velocity:
            self._p_segment(st.p_last, STREAM_PERIOD_S[0])
            return
        end = max(self.plant.motion.t_end, self._now + (st.nominal or STREAM_PERIOD_S[0]))
        self._pv_segments([(end, st.p_last, 0.0)])

    def _p_segment(self, to: float, period: float) -> None:
        t = self._now

        def segment(p: float, _v: float) -> MotionProfile:
            rate = (to - p) / period
            return MotionProfile(np.array([t, t + period]), np.array([p, to]), np.array([rate, 0.0]),
                                 np.zeros(2), t + period, to)
        self._set_profile(segment)

    def _pv_segments(self, points: list[tuple[float, float, float]]) -> None:
        """From the drive's state now through (time, position, velocity) ``points`` still ahead, each segment in two
        equal halves of constant acceleration: a1 + a2 = 2 (v1 − v0) / T, 3 a1 + a2 = 8 (p1 − p0 − v0 T) / T²; after
        the last point the motion goes on at its velocity (the next point or a timeout changes it)."""
        t0 = self._now

        def plan(p: float, v: float) -> MotionProfile:
            ts, ps, vs, accs = [], [], [], []
            t = t0
            for t1, p1, v1 in points:
                if t1 <= t:
                    continue  # already due: the next point takes over [chosen]
                span = t1 - t
                a1 = (8 * (p1 - p - v * span) / span ** 2 - 2 * (v1 - v) / span) / 2
                a2 = 2 * (v1 - v) / span - a1
                half = span / 2
                ts += [t, t + half]
                ps += [p, p + v * half + 0.5 * a1 * half ** 2]
                vs += [v, v + a1 * half]
                accs += [a1, a2]
                t, p, v = t1, p1, v1
            ts.append(t)
            ps.append(p)
            vs.append(v)
            accs.append(0.0)
            return MotionProfile(np.array(ts), np.array(ps), np.array(vs), np.array(accs), t, p)
        self._set_profile(plan)

    # ------------------------------------------------------------ response
    def warn_word(self) -> int:
        """Warn word now (§3.24): bit 7 "Motor Not Homed" while operation is enabled and the motor is not homed
        [chosen: the manual ties the warning to no state; before state 8 there is no motion to warn about]."""
        with self._lock:
            self._run_until(self.clock.now())
            return WW_MOTOR_NOT_HOMED if self.state >= OPERATION_ENABLED and not self.homed else 0

    def status(self) -> tuple[int, int, int]:
        """(status word, state var, position counts) now."""
        now = self.clock.now()
        with self._lock:
            self._run_until(now)
            pos, vel = self.plant.motor_state(now)
            moving = abs(vel) > 0 or now < self.plant.motion.t_end
            in_target = not moving and abs(pos - self.plant.motion.target) < 1e-6
            cw, s = self.control_word, self.state
            special = s in SPECIAL_BITS
            sw = 0
            sw |= SW_OPERATION_ENABLED if s >= OPERATION_ENABLED else 0
            sw |= SW_SWITCH_ON_ACTIVE if cw & CW_SWITCH_ON else 0
            sw |= SW_ENABLE_OPERATION if cw & CW_ENABLE_OPERATION else 0
            sw |= SW_ERROR if s in (SETUP_ERROR, ERROR, ERROR_QUICK_STOP) else 0  # [chosen] an error is pending
            sw |= SW_VOLTAGE_ENABLE if cw & CW_VOLTAGE_ENABLE else 0
            sw |= SW_QUICK_STOP_N if cw & CW_QUICK_STOP_N else 0
            sw |= SW_SWITCH_ON_LOCKED if s == NOT_READY else 0
            sw |= SW_WARNING if s >= OPERATION_ENABLED and not self.homed else 0  # warn word ≠ 0 (warn_word)
            sw |= SW_EVENT_HANDLER if self._event is not None else 0
            sw |= SW_SPECIAL_MOTION if special and not self.special_done else 0
            sw |= SW_IN_TARGET if in_target and s == OPERATION_ENABLED else 0
            sw |= SW_HOMED if self.homed else 0
            sw |= SW_FATAL if self.fatal else 0
            sw |= SW_MOTION_ACTIVE if moving and s >= OPERATION_ENABLED else 0
            for bit, window in zip((SW_RANGE_1, SW_RANGE_2), self.range_indicators, strict=True):
                sw |= bit if window is not None and window[0] <= pos <= window[1] else 0
            if s == OPERATION_ENABLED:  # §3.8: Homed | InTarget | MotionActive | EventHandler | count
                sub = ((0x80 if self.homed else 0) | (0x40 if in_target else 0) | (0x20 if moving else 0)
                       | (0x10 if self._event is not None else 0) | self.count)
            elif special:
                sub = SUB_FINISHED if self.special_done else SUB_RUNNING
            elif s == ERROR:
                sub = self.error_code & 0xFF  # "Logged Error Code"
            elif s == SETUP_ERROR:
                sub = self.setup_error & 0xFF  # "Error Code which will be logged"
            else:
                sub = 0  # states 0–2, 5, 6: 0; 12–14: "not yet defined"
            return sw, (s << 8) | sub, round(pos / POS_UNIT)

    def _default_response(self, comm_state: int = COMM_OK, extra: bytes = b"") -> bytes:
        """The default response, ``extra`` appended after the position [assumed: the response IDs stay 00h 00h
        for the extended replies too; the drivers found do not read them]."""
        sw, sv, pos = self.status()
        body = _RESPONSE_IDS + struct.pack("<BHHi", comm_state, sw, sv, pos) + extra
        crc = struct.pack("<H", crc16_ccitt_reflected(body)) if self.checksum else b""
        return bytes((STX, self.drive_id, len(body))) + body + crc + ETX_BYTE

    def __call__(self, data: bytes) -> bytes:
        """Feed received bytes; returns the responses to all complete telegrams."""
        now = time.monotonic()
        if self._buf and now - self._rx_at > RX_IDLE_RESET_S:
            self._buf = b""  # an incomplete telegram after a pause: noise, discarded
        self._rx_at = now
        self._buf += data
        out = b""
        while True:
            start = self._buf.find(STX_BYTE)
            if start < 0:
                self._buf = b""
                break
            self._buf = self._buf[start:]
            if len(self._buf) < 3:
                break
            length = self._buf[2]
            total = 3 + length + (3 if self.checksum else 1)
            if length < 3 or length > 63:
                self._buf = self._buf[1:]  # not a telegram start: resynchronise
                continue
            if len(self._buf) < total:
                break
            frame, self._buf = self._buf[:total], self._buf[total:]
            if frame[-1] != ETX or frame[3] != DATA_START:
                self._buf = frame[1:] + self._buf  # framing error: not a telegram start, look for the next one
                continue
            if self.checksum:
                body_end = 3 + length
                if crc16_ccitt_reflected(frame[3:body_end]) != struct.unpack("<H", frame[body_end:body_end + 2])[0]:
                    continue  # checksum error: discarded
            if frame[1] != self.drive_id:
                continue  # another drive's telegram
            out += self._handle(frame[5], frame[4], frame[6:3 + length])
        return out

    def _handle(self, main: int, sub: int, data: bytes) -> bytes:
        with self._lock:
            self._run_until(self.clock.now())
            if main == MAIN_CONTROL_WORD and len(data) == 2:
                self._apply_control_word(struct.unpack("<H", data)[0])
            elif main == MAIN_MOTION_COMMAND:
                self._motion_command(data)
            elif main == MAIN_RESPONSE and sub == SUB_WARN_WORD:
                return self._default_response(extra=struct.pack("<HH", self.warn_word(), 0))  # [assumed] 2nd word 0
            elif main == MAIN_READ_UPID and data == struct.pack("<H", UPID_MOTION_COMMAND_COUNT):
                return self._default_response(extra=struct.pack("<i", self.count))
            elif main != MAIN_RESPONSE:
                return self._default_response(COMM_UNKNOWN_MESSAGE)
            self._reschedule()
            return self._default_response()


def crc16_ccitt_reflected(data: bytes) -> int:
    """LinRS optional checksum (UPID 2080h): CRC-16-CCITT reflected, poly 8408h, init 0000h [assumed variant:
    the manual offers a byte sum and CCITT variants; which one a drive uses is its parameter]."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc
