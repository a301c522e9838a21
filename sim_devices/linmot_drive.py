"""Simulated LinMot drive speaking LinRS on a pty, with the MC-SW state machine and VAI motion.

State machine (MC-SW manual §4.3; ../shared/instruments.md §2.3): 0 Not Ready (switch-on locked) → control
word with bit 0 clear → 1 Switch On Disabled → 0x003E → 2 Ready To Switch On → 0x003F → 5 HW tests
(``hw_test_time``) → 8 Operation Enabled. Homing (bit 11) → 9, sub state 0x0F when done. Errors → 4 with
the error code as sub state; acknowledged by a rising edge of bit 7 (not if fatal). Motion commands are
executed when the command count changes, only in state 8 (otherwise error 0x86 "Motion Cmd In Wrong St") and
homed (otherwise 0x80 "Not Homed"), only inside the drive's stroke (otherwise 0x87, see ERR_OUTSIDE_STROKE).
The motor position drives the plant (LS-DEA motor coupling).
Malformed telegrams are ignored (the master times out); unknown message groups are answered with a
non-zero communication state.
"""

from __future__ import annotations

import struct
import threading

from drivers.linmot import (
    CW_ENABLE_OPERATION,
    CW_ERROR_ACK,
    CW_HOME,
    CW_NOT_ABORT,
    CW_NOT_QUICK_STOP,
    CW_READY,
    CW_SWITCH_ON,
    CW_VOLTAGE_ENABLE,
    DATA,
    END,
    MAIN_CONTROL_WORD,
    MAIN_MOTION_COMMAND,
    MAIN_RESPONSE,
    POS_UNIT,
    START,
    SW_ERROR,
    SW_FATAL,
    SW_HOMED,
    SW_IN_TARGET,
    SW_MOTION_ACTIVE,
    SW_OPERATION_ENABLED,
    VAI_GOTO,
    crc16_ccitt_reflected,
)
from sim_devices.clock import Clock
from sim_devices.motion import MotionProfile
from sim_devices.plant import Plant

# Drive error codes (LinMot MC-SW drive error list; ../shared/instruments.md §2.3).
ERR_NOT_HOMED = 0x80  # "Not Homed"
ERR_WRONG_STATE = 0x86  # "Motion Cmd In Wrong St"
ERR_OUTSIDE_STROKE = 0x87  # [assumed] a target beyond the configured position range; the code was not verified
ERR_MOTOR_MISSING = 0x22
COMM_UNKNOWN_MESSAGE = 0x01


class LinMotDriveSim:
    """Protocol handler + state machine of one simulated drive (feed it bytes; it returns replies)."""

    def __init__(self, plant: Plant, clock: Clock, *, drive_id: int = 0x11, stroke: tuple[float, float] = (0.0, 0.12),
                 home_position: float = 0.0, hw_test_time: float = 0.3, homing_time: float = 1.0,
                 quick_stop_decel: float = 50.0, checksum: bool = False) -> None:
        self.plant = plant
        self.clock = clock
        self.drive_id = drive_id
        self.stroke = stroke
        self.home_position = home_position
        self.hw_test_time = hw_test_time
        self.homing_time = homing_time
        self.quick_stop_decel = quick_stop_decel
        self.checksum = checksum
        self.state = 0
        self.error_code = 0
        self.fatal = False
        self.homed = False
        self.control_word = 0
        self.count = 0
        self._decel = 1.0
        self._t_state = 0.0  # when the current timed state (5 HW tests, 9 homing) began
        self._buf = b""
        self._lock = threading.Lock()

    # ------------------------------------------------------------ faults
    def inject_error(self, code: int, fatal: bool = False) -> None:
        """Fault injection: put the drive in its error state (state 4) with ``code``."""
        with self._lock:
            self._error(code, fatal)

    def _error(self, code: int, fatal: bool = False) -> None:
        self._halt(self.quick_stop_decel)
        self.state = 4
        self.error_code = code
        self.fatal = self.fatal or fatal

    # ------------------------------------------------------------ state machine
    def _update_timed_states(self) -> None:
        now = self.clock.now()
        if self.state == 5 and now - self._t_state >= self.hw_test_time:
            self.state = 8 if self.control_word & CW_ENABLE_OPERATION else 6
        if self.state == 9 and now - self._t_state >= self.homing_time:
            self.homed = True

    def _apply_control_word(self, cw: int) -> None:
        prev, self.control_word = self.control_word, cw
        rising, falling = cw & ~prev, prev & ~cw
        ready = cw & CW_READY == CW_READY  # bits 1-5: voltage enable, /quick stop, enable op, /abort, /freeze
        if self.state == 4:
            if rising & CW_ERROR_ACK and not self.fatal:
                self.state, self.error_code = 1, 0
            return
        if self.state in (5, 6, 8, 9) and (not cw & CW_SWITCH_ON or not cw & CW_VOLTAGE_ENABLE):
            self._halt(self.quick_stop_decel)  # power stage off
            self.state = 2 if ready and not cw & CW_SWITCH_ON else 1
            return
        if self.state in (0, 1):
            if not cw & CW_SWITCH_ON:
                self.state = 2 if ready else 1
            return
        if self.state == 2:
            if not ready:
                self.state = 1
            elif cw & CW_SWITCH_ON:
                self.state, self._t_state = 5, self.clock.now()
            return
        if self.state in (6, 8) and not cw & CW_NOT_QUICK_STOP:
            self._halt(self.quick_stop_decel)
            self.state = 6
            return
        if self.state == 6 and cw & CW_ENABLE_OPERATION:
            self.state = 8
        if self.state == 8:
            if not cw & CW_ENABLE_OPERATION:
                self._halt(self.quick_stop_decel)
                self.state = 6
            elif falling & CW_NOT_ABORT:
                self._halt(self._decel)
            elif rising & CW_HOME:
                self.state, self.homed, self._t_state = 9, False, self.clock.now()
                home, speed = self.home_position, 0.1
                self.plant.set_motion(lambda t, p, v: MotionProfile.plan(t, p, v, home, speed, 1.0, 1.0))
        elif self.state == 9 and not cw & CW_HOME and self.homed:
            self.state = 8

    def _halt(self, dec: float) -> None:
        self.plant.set_motion(lambda t, p, v: MotionProfile.hold(t, p) if v == 0 else
                              MotionProfile.plan(t, p, v, p + v * abs(v) / (2 * dec), abs(v) + 1e-9, dec, dec))

    def _motion_command(self, data: bytes) -> None:
        if len(data) < 2:
            return
        header = struct.unpack("<H", data[:2])[0]
        count = header & 0x0F
        if count == self.count:
            return  # not a new command
        self.count = count
        if self.state == 4:
            return  # in the error state motion commands are ignored; the original error stays
        if self.state != 8:
            self._error(ERR_WRONG_STATE)
            return
        if not self.homed:
            self._error(ERR_NOT_HOMED)
            return
        if header & 0xFFF0 == VAI_GOTO and len(data) >= 18:
            target, vmax, acc, dec = struct.unpack("<iIII", data[2:18])
            pos = target * POS_UNIT
            if not self.stroke[0] <= pos <= self.stroke[1] or vmax == 0 or acc == 0 or dec == 0:
                self._error(ERR_OUTSIDE_STROKE)
                return
            self._decel = dec * 1e-5
            self.plant.set_motion(lambda t, p, v: MotionProfile.plan(t, p, v, pos, vmax * 1e-6, acc * 1e-5, dec * 1e-5))

    # ------------------------------------------------------------ response
    def status(self) -> tuple[int, int, int]:
        """(status word, state var, position counts) now."""
        now = self.clock.now()
        pos, vel = self.plant.motor_state(now)
        moving = abs(vel) > 0 or now < self.plant.motion.t_end
        in_target = not moving and abs(pos - self.plant.motion.target) < 1e-6
        cw = self.control_word
        sw = 0
        if self.state == 8:
            sw |= SW_OPERATION_ENABLED
        if cw & CW_SWITCH_ON and self.state in (5, 6, 8, 9):
            sw |= 0x0002
        if cw & CW_ENABLE_OPERATION:
            sw |= 0x0004
        if self.state == 4:
            sw |= SW_ERROR
        if cw & CW_VOLTAGE_ENABLE:
            sw |= 0x0010
        if cw & CW_NOT_QUICK_STOP:
            sw |= 0x0020
        if self.state == 0:
            sw |= 0x0040
        if in_target and self.state == 8:
            sw |= SW_IN_TARGET
        if self.homed:
            sw |= SW_HOMED
        if self.fatal:
            sw |= SW_FATAL
        if moving and self.state in (8, 9):
            sw |= SW_MOTION_ACTIVE
        if self.state == 8:
            sub = (0x80 if self.homed else 0) | (0x40 if in_target else 0) | (0x20 if moving else 0) | self.count
        elif self.state == 9:
            sub = 0x0F if self.homed else 0x01
        elif self.state == 4:
            sub = self.error_code
        else:
            sub = 0
        return sw, (self.state << 8) | sub, round(pos / POS_UNIT)

    def _default_response(self, comm_state: int = 0) -> bytes:
        sw, sv, pos = self.status()
        body = bytes([DATA, 0x00, MAIN_RESPONSE]) + struct.pack("<BHHi", comm_state, sw, sv, pos)
        crc = struct.pack("<H", crc16_ccitt_reflected(body)) if self.checksum else b""
        return bytes([START, self.drive_id, len(body)]) + body + crc + bytes([END])

    def __call__(self, data: bytes) -> bytes:
        """Feed received bytes; returns the responses to all complete telegrams."""
        self._buf += data
        out = b""
        while True:
            start = self._buf.find(bytes([START]))
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
            if frame[-1] != END or frame[3] != DATA:
                continue  # framing error: a real drive discards it, the master times out
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
