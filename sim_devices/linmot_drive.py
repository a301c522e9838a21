"""Simulated LinMot drive speaking LinRS on a pty, with the MC-SW state machine and VAI motion.

Written from the manuals, not from :mod:`drivers.linmot` (no constant is shared). Sources:

* LinRS manual 0185-1082-E (E1100/C1100/E1200/E1400 series): telegram layout p. 11, control-word and
  motion-command examples (``01 11 05 02 00 01 00 00 04``; Predef VAI ``01 11 09 02 00 02 01 02 A0 86 01 00
  04``), default response (``01 11 0C 02 00 00 00 37 68 A1 08 8B FC FF FF 04``) — ../shared/instruments.md §2.2;
* LinMot "Motion Control SW" user manual 4.3.4 (A1100/C1100/C1200/E1200/E1400), as transcribed in
  Smart-Vision-Works/linmot_client ``docs/LinMot_MotionCtrl.md``: §3 state machine (§3.1–3.9), §3.22 control
  word, §3.23 status word, §4.1 motion-command header, §4.3 commands, §10 error code list.

Where the manuals are silent the choice is marked ``[assumed]`` beside it.
"""

from __future__ import annotations

import struct
import threading
import time

from bench.core.clock import Clock
from bench.core.motion import MotionProfile
from bench.core.plant import Plant

# ---------------------------------------------------------------- LinRS framing (LinRS manual p. 11)
STX, DATA_START, ETX = 0x01, 0x02, 0x04  # 01h | ID | Len | 02h | SubID | MainID | data… | [CRC lo hi] | 04h
MAIN_RESPONSE = 0x00  # request Sub 01h: "return default response" (manual examples; drivers found)
MAIN_CONTROL_WORD = 0x01  # Sub 00h, 2-byte control word (manual "Write Control Word" example)
MAIN_MOTION_COMMAND = 0x02  # Sub 00h, header + parameters (manual "Write Motion Command Interface" example)
COMM_OK = 0x00
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
CW_ERROR_ACK = 1 << 7  # rising edge acknowledges
CW_HOME = 1 << 11  # level: 1 = Homing, 0 = Stop Homing

# ---------------------------------------------------------------- status word (MC-SW §3.23)
SW_OPERATION_ENABLED = 1 << 0  # state 8 or higher
SW_SWITCH_ON_ACTIVE = 1 << 1  # control word bit 0
SW_ENABLE_OPERATION = 1 << 2  # control word bit 3
SW_ERROR = 1 << 3
SW_VOLTAGE_ENABLE = 1 << 4  # control word bit 1
SW_QUICK_STOP_N = 1 << 5  # control word bit 2
SW_SWITCH_ON_LOCKED = 1 << 6  # released with control word bit 0 = 0
SW_SPECIAL_MOTION = 1 << 9  # special motion (homing, …) runs
SW_IN_TARGET = 1 << 10
SW_HOMED = 1 << 11
SW_FATAL = 1 << 12
SW_MOTION_ACTIVE = 1 << 13

# ---------------------------------------------------------------- main states (MC-SW §3, State Var table)
NOT_READY, SWITCH_ON_DISABLED, READY_TO_SWITCH_ON, ERROR, HW_TESTS, READY_TO_OPERATE = 0, 1, 2, 4, 5, 6
OPERATION_ENABLED, HOMING = 8, 9
SUB_FINISHED = 0x0F  # state 9 sub state "Homing Finished"

# ---------------------------------------------------------------- error codes (MC-SW §10 error code list)
ERR_MIN_POS_UNDERSHOT = 0x0007  # "Err: Min Pos Undershot"
ERR_MAX_POS_OVERSHOT = 0x0008  # "Err: Max Pos Overshot"
ERR_NOT_HOMED = 0x0080  # "User Err: Lin: Not Homed"
ERR_UNKNOWN_MOTION_CMD = 0x0081  # "User Err: Unknown Motion Cmd" (§10 of MC-SW 4.3.4; 0085h there is
#                                   "PVT Master Too Slow" — the 0x85 does not match this list)
ERR_WRONG_STATE = 0x0086  # "User Err: Motion Cmd In Wrong St"

# ---------------------------------------------------------------- motion commands (MC-SW §4.1/§4.3)
MC_NOP = 0x000  # "No Operation (000xh)"
MC_VAI_GOTO = 0x010  # "VAI Go To Pos (010xh)": SInt32 pos, UInt32 vel, acc, dec
MC_VAI_INCREMENT = 0x011  # "VAI Increment Dem Pos (011xh)", same parameters, position is an increment
MC_PREDEF_VAI_GOTO = 0x020  # "Predef VAI Go To Pos (020xh)": SInt32 pos; v/a/d from drive parameters
# Every other Master/Sub ID (013xh, 09xxh, streaming, curves, …) is answered with ERR_UNKNOWN_MOTION_CMD:
# [assumed] conservative — the real firmware knows more commands, the twin models only these.


class LinMotDriveSim:
    """Protocol handler + state machine of one simulated drive (feed it bytes; it returns replies)."""

    def __init__(self, plant: Plant, clock: Clock, *, drive_id: int = 0x11, stroke: tuple[float, float] = (0.0, 0.12),
                 home_position: float = 0.0, hw_test_time: float = 0.3, homing_time: float = 1.0,
                 quick_stop_decel: float = 50.0, checksum: bool = False,
                 predef_vai: tuple[float, float, float] = (0.5, 5.0, 5.0)) -> None:
        """``hw_test_time``: state 5 lasts "about 300 ms" (MC-SW §3.6). ``predef_vai``: (velocity, acceleration,
        deceleration) the drive's parameters give Predef VAI commands [assumed values]. ``stroke``: the drive's
        min/max position parameters."""
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
        self.state = NOT_READY
        self.error_code = 0
        self.fatal = False
        self.homed = False
        self.homing_done = False
        self.control_word = 0
        self.count = 0
        self._decel = 1.0
        self._t_state = 0.0  # when the current timed state (5 HW tests, 9 homing) began
        self._buf = b""
        self._rx_at = 0.0  # wall time of the last bytes received
        self._lock = threading.Lock()

    # ------------------------------------------------------------ faults
    def inject_error(self, code: int, fatal: bool = False) -> None:
        """Fault injection: put the drive in its error state (state 4) with ``code``."""
        with self._lock:
            self._error(code, fatal)

    def _error(self, code: int, fatal: bool = False) -> None:
        self._halt(self.quick_stop_decel)
        self.state = ERROR
        self.error_code = code
        self.fatal = self.fatal or fatal

    # ------------------------------------------------------------ state machine (MC-SW §3)
    def _update_timed_states(self) -> None:
        now = self.clock.now()
        if self.state == HW_TESTS and now - self._t_state >= self.hw_test_time:
            self.state = READY_TO_OPERATE  # §3.6: "changes to state 6 without any user action"
            self._evaluate(self.control_word, 0)
        if self.state == HOMING and not self.homing_done and now - self._t_state >= self.homing_time:
            self.homing_done = self.homed = True

    def _apply_control_word(self, cw: int) -> None:
        prev, self.control_word = self.control_word, cw
        self._evaluate(cw, cw & ~prev)

    def _evaluate(self, cw: int, rising: int) -> None:
        """Run the transitions the control word allows, as the drive does cyclically (several per write)."""
        for _ in range(6):
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
        if s == NOT_READY:  # §3.1: wait for the release of bit 0
            if not cw & CW_SWITCH_ON:
                self.state = SWITCH_ON_DISABLED
            return
        if s == SWITCH_ON_DISABLED:  # §3.2 and diagram: control word xxxx x110 → state 2
            if cw & 0x0007 == 0x0006:
                self.state = READY_TO_SWITCH_ON
            return
        if cw & enabled_bits != enabled_bits:  # OFF2 / OFF3 from any powered state: back to state 1
            if s >= HW_TESTS:
                self._halt(self.quick_stop_decel)
            self.state = SWITCH_ON_DISABLED
            return
        if s == READY_TO_SWITCH_ON:  # §3.3: rests while bit 0 is cleared
            if cw & CW_SWITCH_ON:
                self.state, self._t_state = HW_TESTS, self.clock.now()
            return
        if not cw & CW_SWITCH_ON:  # OFF1: power stage off
            if s >= HW_TESTS:
                self._halt(self.quick_stop_decel)
            self.state = READY_TO_SWITCH_ON
            return
        if s == HW_TESTS:
            return
        if s == READY_TO_OPERATE:
            if cw & CW_ENABLE_OPERATION:
                self.state = OPERATION_ENABLED
            return
        if not cw & CW_ENABLE_OPERATION:  # §3.7: clearing bit 3 in state 8 or higher → state 6 at once
            self._halt(self.quick_stop_decel)
            self.state, self.homing_done = READY_TO_OPERATE, False
            return
        if s == OPERATION_ENABLED:
            if not cw & CW_ABORT_N:  # §3.12: quick stop, position controlled, motion command cleared
                self._halt(self.quick_stop_decel)
            elif cw & CW_HOME:  # §3.22 bit 11 is a level: 1 = Homing
                self.state, self.homed, self.homing_done = HOMING, False, False
                self._t_state = self.clock.now()
                home = self.home_position
                self.plant.set_motion(lambda t, p, v: MotionProfile.plan(t, p, v, home, 0.1, 1.0, 1.0))
            return
        if s == HOMING and not cw & CW_HOME:  # 0 = Stop Homing: back to 8 (homed only if it finished)
            if not self.homing_done:
                self._halt(self.quick_stop_decel)
            self.state, self.homing_done = OPERATION_ENABLED, False

    def _halt(self, dec: float) -> None:
        self.plant.set_motion(lambda t, p, v: MotionProfile.hold(t, p) if v == 0 else
                              MotionProfile.plan(t, p, v, p + v * abs(v) / (2 * dec), abs(v) + 1e-9, dec, dec))

    def _motion_command(self, data: bytes) -> None:
        if len(data) < 2:
            return
        header = struct.unpack("<H", data[:2])[0]
        count = header & 0x0F  # §4.1.1.3: executed only when the count changed
        if count == self.count:
            return
        self.count = count
        if self.state == ERROR:
            return  # [assumed] in the error state the pending error stays; the command is dropped
        group = header >> 4
        if group == MC_NOP:
            return  # §4.3.1: "can be sent in any operational state"
        if self.state != OPERATION_ENABLED:
            self._error(ERR_WRONG_STATE)  # §3.7
            return
        if group not in (MC_VAI_GOTO, MC_VAI_INCREMENT, MC_PREDEF_VAI_GOTO):
            self._error(ERR_UNKNOWN_MOTION_CMD)
            return
        if not self.homed:
            self._error(ERR_NOT_HOMED)
            return
        if group == MC_PREDEF_VAI_GOTO:
            if len(data) < 6:
                return
            target = struct.unpack("<i", data[2:6])[0] * POS_UNIT
            vmax, acc, dec = self.predef_vai
        else:
            if len(data) < 18:
                return
            raw, v_raw, a_raw, d_raw = struct.unpack("<iIII", data[2:18])
            target = raw * POS_UNIT
            vmax, acc, dec = v_raw * VEL_UNIT, a_raw * ACC_UNIT, d_raw * ACC_UNIT
            if group == MC_VAI_INCREMENT:
                target += self.plant.motion.target
            if vmax == 0 or acc == 0 or dec == 0:
                return  # [assumed] a zero limit plans no motion
        # [assumed] a target beyond the position limits trips at once (the drive trips when passing them)
        if target > self.stroke[1]:
            self._error(ERR_MAX_POS_OVERSHOT)
            return
        if target < self.stroke[0]:
            self._error(ERR_MIN_POS_UNDERSHOT)
            return
        self._decel = dec
        self.plant.set_motion(lambda t, p, v: MotionProfile.plan(t, p, v, target, vmax, acc, dec))

    # ------------------------------------------------------------ response
    def status(self) -> tuple[int, int, int]:
        """(status word, state var, position counts) now."""
        now = self.clock.now()
        pos, vel = self.plant.motor_state(now)
        moving = abs(vel) > 0 or now < self.plant.motion.t_end
        in_target = not moving and abs(pos - self.plant.motion.target) < 1e-6
        cw, s = self.control_word, self.state
        sw = 0
        sw |= SW_OPERATION_ENABLED if s >= OPERATION_ENABLED else 0
        sw |= SW_SWITCH_ON_ACTIVE if cw & CW_SWITCH_ON else 0
        sw |= SW_ENABLE_OPERATION if cw & CW_ENABLE_OPERATION else 0
        sw |= SW_ERROR if s == ERROR else 0
        sw |= SW_VOLTAGE_ENABLE if cw & CW_VOLTAGE_ENABLE else 0
        sw |= SW_QUICK_STOP_N if cw & CW_QUICK_STOP_N else 0
        sw |= SW_SWITCH_ON_LOCKED if s == NOT_READY else 0
        sw |= SW_SPECIAL_MOTION if s == HOMING and not self.homing_done else 0
        sw |= SW_IN_TARGET if in_target and s == OPERATION_ENABLED else 0
        sw |= SW_HOMED if self.homed else 0
        sw |= SW_FATAL if self.fatal else 0
        sw |= SW_MOTION_ACTIVE if moving and s >= OPERATION_ENABLED else 0
        if s == OPERATION_ENABLED:  # §3.8: Homed | InTarget | MotionActive | EventHandler | count
            sub = (0x80 if self.homed else 0) | (0x40 if in_target else 0) | (0x20 if moving else 0) | self.count
        elif s == HOMING:
            sub = SUB_FINISHED if self.homing_done else 0x01  # [assumed] 01h while homing runs
        elif s == ERROR:
            sub = self.error_code & 0xFF  # "Logged Error Code"
        else:
            sub = 0
        return sw, (s << 8) | sub, round(pos / POS_UNIT)

    def _default_response(self, comm_state: int = COMM_OK) -> bytes:
        sw, sv, pos = self.status()
        body = bytes([DATA_START, 0x00, MAIN_RESPONSE]) + struct.pack("<BHHi", comm_state, sw, sv, pos)
        crc = struct.pack("<H", crc16_ccitt_reflected(body)) if self.checksum else b""
        return bytes([STX, self.drive_id, len(body)]) + body + crc + bytes([ETX])

    def __call__(self, data: bytes) -> bytes:
        """Feed received bytes; returns the responses to all complete telegrams."""
        now = time.monotonic()
        if self._buf and now - self._rx_at > RX_IDLE_RESET_S:
            self._buf = b""  # an incomplete telegram after a pause: noise, discarded
        self._rx_at = now
        self._buf += data
        out = b""
        while True:
            start = self._buf.find(bytes([STX]))
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
            self._update_timed_states()
            if main == MAIN_RESPONSE:
                return self._default_response()
            if main == MAIN_CONTROL_WORD and len(data) == 2:
                self._apply_control_word(struct.unpack("<H", data)[0])
                self._update_timed_states()
                return self._default_response()
            if main == MAIN_MOTION_COMMAND:
                self._motion_command(data)
                return self._default_response()
            return self._default_response(COMM_UNKNOWN_MESSAGE)


def crc16_ccitt_reflected(data: bytes) -> int:
    """LinRS optional checksum (UPID 2080h): CRC-16-CCITT reflected, poly 8408h, init 0000h [assumed variant:
    the manual offers a byte sum and CCITT variants; which one a drive uses is its parameter]."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc
