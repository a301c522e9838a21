"""LinMot drive (E1100/C1100 class, P01 motors) over LinRS binary telegrams (RS-232/485).

Telegram (LinRS manual 0185-1082-E p. 11; ../shared/instruments.md §2):

    01h | ID | Len | 02h | SubID | MainID | data… | 04h        Len = bytes from 02h to the last data byte

Multi-byte data little-endian. Requests used here:

* ``Main 00h Sub 01h``  poll the default response;
* ``Main 01h Sub 00h``  write control word (2 bytes);
* ``Main 02h Sub 00h``  write motion-command interface: header ``MasterID(8)|SubID(4)|Count(4)`` + parameters;
  VAI go-to-position ``010xh``: target int32 [0.1 µm], max velocity uint32 [1e-6 m/s], acceleration and
  deceleration uint32 [1e-5 m/s²].

Optional checksum (drive parameter UPID 2080h; off by default): two bytes, low first, between the last data
byte and 04h, not counted in Len. The manual offers a byte sum and CRC-16-CCITT variants; this driver
implements CRC-16-CCITT reflected (poly 8408h, init 0000h) over the bytes from 02h to the last data byte —
check the variant configured on the drive. Without it a corrupted data byte cannot be detected.

Every request is answered with the default response ``01 ID 0C 02 00 00 | CommState | StatusWord(2) |
StateVar(2) | ActualPosition int32 [0.1 µm] | 04``. State var = main state (high byte) | sub state (low byte);
in state 8 the sub state carries Homed (bit 7), InTargetPos (6), MotionActive (5) and the echoed motion
command count (bits 0–3), which is the handshake for motion commands.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass

from drivers.cancel import check
from drivers.errors import (
    ImplausibleValueError,
    InstrumentStateError,
    InstrumentTimeoutError,
    LimitError,
    ProtocolError,
)
from drivers.interfaces import (
    CheckResult,
    ClockFn,
    DataKey,
    Identity,
    MotorStatus,
    Reading,
    ReadingMap,
    SleepFn,
    StreamDescription,
)
from drivers.serial_link import SerialLink

START, DATA, END = 0x01, 0x02, 0x04
MAIN_RESPONSE, MAIN_CONTROL_WORD, MAIN_MOTION_COMMAND = 0x00, 0x01, 0x02
SUB_DEFAULT_RESPONSE_REQUEST = 0x01
VAI_GOTO = 0x0100

# control word bits (MC-SW manual §4.3)
CW_SWITCH_ON, CW_VOLTAGE_ENABLE, CW_NOT_QUICK_STOP, CW_ENABLE_OPERATION = 0x0001, 0x0002, 0x0004, 0x0008
CW_NOT_ABORT, CW_NOT_FREEZE, CW_ERROR_ACK, CW_HOME = 0x0010, 0x0020, 0x0080, 0x0800
CW_READY = CW_VOLTAGE_ENABLE | CW_NOT_QUICK_STOP | CW_ENABLE_OPERATION | CW_NOT_ABORT | CW_NOT_FREEZE  # 0x003E
CW_OPERATE = CW_READY | CW_SWITCH_ON  # 0x003F

# status word bits
SW_OPERATION_ENABLED, SW_ERROR, SW_IN_TARGET, SW_HOMED, SW_FATAL, SW_MOTION_ACTIVE = (
    0x0001, 0x0008, 0x0400, 0x0800, 0x1000, 0x2000)

STATE_NAMES = {0: "not ready to switch on", 1: "switch on disabled", 2: "ready to switch on", 3: "setup error",
               4: "error", 5: "hardware tests", 6: "ready to operate", 8: "operation enabled", 9: "homing",
               12: "aborting", 14: "error behaviour quick stop", 15: "going to position"}
# Drive error codes: LinMot "Motion Control SW" user manual 4.3.4, §10 error code list (transcribed in
# Smart-Vision-Works/linmot_client docs/LinMot_MotionCtrl.md). In the error state (main state 4) the state
# var's low byte carries the code.
ERROR_TEXT = {0x01: "X4 logic supply too low", 0x02: "X4 logic supply too high", 0x03: "X1 power voltage too low",
              0x04: "X1 power voltage too high", 0x07: "min position undershot", 0x08: "max position overshot",
              0x0B: "position lag always too big", 0x0C: "position lag standing too big",
              0x20: "motor hot sensor", 0x21: "X3 hall signals missing (fatal)",
              0x22: "motor slider missing (fatal)", 0x23: "motor short time overload",
              0x80: "not homed", 0x81: "unknown motion command", 0x82: "PVT buffer overflow",
              0x83: "PVT buffer underflow", 0x84: "PVT master too fast", 0x85: "PVT master too slow",
              0x86: "motion command in wrong state", 0x87: "limit switch in high", 0x88: "limit switch out high",
              0x8A: "command table entry not defined"}
STATE_ERROR = 4

POS_UNIT = 1e-7  # m per count (0.1 µm)
VEL_UNIT = 1e-6  # m/s per count
ACC_UNIT = 1e-5  # m/s² per count
POS_REGISTER = (-(2**31) * POS_UNIT, (2**31 - 1) * POS_UNIT)  # what the int32 position register holds [m]: ±214.7 m
POSITION_MARGIN_M = 1.0  # default: how far beyond the travel a reported position may lie and still be the slider's


def crc16_ccitt_reflected(data: bytes) -> int:
    """CRC-16-CCITT, reflected (poly 0x8408), init 0x0000."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def encode(drive_id: int, main: int, sub: int, data: bytes = b"", checksum: bool = False) -> bytes:
    """LinRS telegram for one request (with the optional checksum if asked)."""
    body = bytes([DATA, sub, main]) + data
    if len(body) > 63:
        raise ValueError(f"LinRS telegram body of {len(body)} bytes exceeds 63")
    crc = struct.pack("<H", crc16_ccitt_reflected(body)) if checksum else b""
    return bytes([START, drive_id, len(body)]) + body + crc + bytes([END])


@dataclass(frozen=True)
class DefaultResponse:
    """Decoded default response of the drive."""

    comm_state: int
    status_word: int
    state_var: int
    position_counts: int

    @property
    def main_state(self) -> int:
        """Main state (high byte of the state var)."""
        return self.state_var >> 8

    @property
    def sub_state(self) -> int:
        """Sub state (low byte of the state var)."""
        return self.state_var & 0xFF

    @property
    def command_count(self) -> int:
        """Echoed motion-command count (valid in state 8)."""
        return self.state_var & 0x0F

    @property
    def position(self) -> float:
        """Actual position [m]."""
        return self.position_counts * POS_UNIT


_RESPONSE_FIELDS = struct.Struct("<BHHi")  # comm state, status word, state var, actual position: bytes 6–14


def decode_default_response(frame: bytes, drive_id: int, device: str, checksum: bool = False) -> DefaultResponse:
    """Decode and check a default-response telegram."""
    size = 18 if checksum else 16
    if len(frame) != size or frame[0] != START or frame[-1] != END:
        raise ProtocolError(device, f"malformed default response {frame.hex(' ')}")
    if checksum:
        body, crc = frame[3:15], struct.unpack("<H", frame[15:17])[0]
        if crc16_ccitt_reflected(body) != crc:
            raise ProtocolError(device, f"checksum error in default response {frame.hex(' ')}")
    if frame[1] != drive_id:
        raise ProtocolError(device, f"response from drive id {frame[1]:#04x}, expected {drive_id:#04x}")
    if frame[2] != 0x0C or frame[3] != DATA or frame[4] != 0x00 or frame[5] != MAIN_RESPONSE:
        raise ProtocolError(device, f"not a default response: {frame.hex(' ')}")
    return DefaultResponse(*_RESPONSE_FIELDS.unpack_from(frame, 6))


class LinMotDrive:
    """Driver of one LinMot drive on a LinRS link (implements LinearMotor).

    Software travel limits [m] are checked before any motion command is sent. A reported position more than
    ``position_margin`` [m] beyond the travel is an :class:`ImplausibleValueError`, never a reading: the int32
    register's ends (±214.7 m) and anything near them are no slider's position. An overshoot, a slider pushed past
    a limit or an unhomed drive counting from where it was switched on stays within the motor's stroke; the
    default (1 m, about ten times the rigs’ 95-mm travel) leaves room for that, and a rig with a longer stator may set
    it wider (it must keep the register's ends outside). ``poll_interval``: pause between
    status polls while waiting for a drive state (enabling, homing, in-target). 10 ms keeps the RS-232 line mostly
    free (a poll and its default response are 23 bytes, 2.0 ms at 115,200 baud) and adds at most 10 ms to a wait
    that lasts 0.3 s (switch-on test) to seconds (homing).
    """

    def __init__(self, link: SerialLink, *, name: str = "motor", drive_id: int = 0x11,
                 travel: tuple[float, float] = (0.0, 0.12), max_velocity: float = 1.0,
                 max_acceleration: float = 20.0, clock: ClockFn = time.monotonic, sleep: SleepFn = time.sleep,
                 state_timeout: float = 5.0, poll_interval: float = 0.01, checksum: bool = False,
                 position_margin: float = POSITION_MARGIN_M) -> None:
        if not travel[0] < travel[1]:
            raise ValueError(f"{name}: travel limits must be increasing, got {travel}")
        plausible = (travel[0] - position_margin, travel[1] + position_margin)
        if not (position_margin >= 0 and POS_REGISTER[0] < plausible[0] and plausible[1] < POS_REGISTER[1]):
            raise ValueError(f"{name}: travel {travel} m ± position margin {position_margin} m must lie inside "
                             f"the position register's {POS_REGISTER[0]:.4f} … {POS_REGISTER[1]:.4f} m")
        self.plausible = plausible
        self.link = link
        self.name = name
        self.drive_id = drive_id
        self.travel = travel
        self.max_velocity = max_velocity
        self.max_acceleration = max_acceleration
        self.clock = clock
        self.sleep = sleep
        self.state_timeout = state_timeout
        self.poll_interval = poll_interval
        self.checksum = checksum
        self._count = 0
        self._control_word = 0
        self._poll_telegram: tuple[tuple[int, bool], bytes] | None = None  # (drive id, checksum), telegram

    # ----------------------------------------------------------- protocol
    def transact(self, main: int, sub: int, data: bytes = b"") -> DefaultResponse:
        """Send one telegram and read the default response."""
        return self._exchange(encode(self.drive_id, main, sub, data, self.checksum))

    def _exchange(self, telegram: bytes) -> DefaultResponse:
        """Send ``telegram`` and read the default response."""
        with self.link.lock:
            self.link.write(telegram)
            head = self.link.read_exact(3)
            if head[0] != START:
                self.link.discard_input()
                raise ProtocolError(self.name, f"reply does not start with 01h: {head.hex(' ')}")
            rest = self.link.read_exact(head[2] + (3 if self.checksum else 1))
        resp = decode_default_response(head + rest, self.drive_id, self.name, self.checksum)
        if resp.comm_state != 0:
            raise ProtocolError(self.name, f"drive reports communication state {resp.comm_state:#04x}")
        return resp

    def poll(self) -> DefaultResponse:
        """Request the default response (the telegram encoded once for this drive id and checksum setting)."""
        key = (self.drive_id, self.checksum)
        cached = self._poll_telegram
        if cached is None or cached[0] != key:  # encode() checks the id: a bad one raises as on every telegram
            cached = self._poll_telegram = key, encode(self.drive_id, MAIN_RESPONSE, SUB_DEFAULT_RESPONSE_REQUEST,
                                                       checksum=self.checksum)
        return self._exchange(cached[1])

    def write_control_word(self, word: int) -> DefaultResponse:
        """Write the control word."""
        self._control_word = word
        return self.transact(MAIN_CONTROL_WORD, 0x00, struct.pack("<H", word))

    def _wait(self, predicate: Callable[[DefaultResponse], bool], what: str,
              timeout: float | None = None) -> DefaultResponse:
        deadline = self.clock() + (self.state_timeout if timeout is None else timeout)
        while True:
            check(self.link.cancel, self.name)
            resp = self.poll()
            if self.in_error(resp):
                raise InstrumentStateError(self.name, f"drive error while waiting for {what}: "
                                           f"{self._error_text(resp)}")
            if predicate(resp):
                return resp
            if self.clock() > deadline:
                raise InstrumentTimeoutError(self.name, f"{what} not reached; drive in state "
                                             f"{STATE_NAMES.get(resp.main_state, resp.main_state)}")
            self.sleep(self.poll_interval)

    @staticmethod
    def in_error(resp: DefaultResponse) -> bool:
        """Error state (main state 4) or the Error / Fatal Error flag of the status word."""
        return resp.main_state == STATE_ERROR or bool(resp.status_word & (SW_ERROR | SW_FATAL))

    @staticmethod
    def error_code(resp: DefaultResponse) -> int:
        """The drive error code (state var low byte in the error state; 0 otherwise)."""
        return resp.sub_state if resp.main_state == STATE_ERROR else 0

    @classmethod
    def _error_text(cls, resp: DefaultResponse) -> str:
        code = cls.error_code(resp)
        fatal = " (fatal)" if resp.status_word & SW_FATAL else ""
        return f"code {code:#04x} {ERROR_TEXT.get(code, 'unknown error')}{fatal}"

    def checked_position(self, resp: DefaultResponse) -> float:
        """The position a default response reports [m]; an :class:`ImplausibleValueError` if it lies more than
        the position margin beyond the travel (see the class docstring)."""
        x = resp.position
        if not self.plausible[0] <= x <= self.plausible[1]:
            raise ImplausibleValueError(self.name, "position", x, self.plausible, "m",
                                        f"travel {self.travel[0]:g} … {self.travel[1]:g} m ± "
                                        f"{self.plausible[1] - self.travel[1]:g} m; register {resp.position_counts} "
                                        "counts of 0.1 µm")
        return x

    def _check_count(self, resp: DefaultResponse, *allowed: int) -> None:
        """In state 8 the echoed motion-command count must be one we sent, else the reply is not ours."""
        if resp.main_state == 8 and resp.command_count not in allowed:
            raise ProtocolError(self.name, f"drive echoes motion command count {resp.command_count}, "
                                f"last sent {self._count}")

    # ----------------------------------------------------------- Instrument
    def connect(self) -> None:
        """Open the link and check that the drive answers with a position it can have."""
        self.link.open()
        self.link.discard_input()
        self.checked_position(self.poll())

    def close(self) -> None:
        """Stop any motion and release the link."""
        try:
            if self.link.is_open:
                self.safe_state()
        finally:
            self.link.close()

    def describe(self) -> StreamDescription:
        """The stream it records: columns, units, source."""
        return StreamDescription(self.name, (DataKey("position", "m", "motor encoder position"),), "LinMot LinRS")

    def check(self) -> CheckResult:
        """The drive's main state and flags; its position."""
        s = self.status()
        flags = ", ".join(f for f, on in (("homed", s.homed), ("moving", s.moving), ("error", s.error)) if on)
        position = Reading(s.position, "m", self.clock(), "error" if s.error else "ok")
        return CheckResult(s.state + (f" ({flags})" if flags else ""), (("position", position),))

    def identify(self) -> Identity:
        """LinRS has no identification telegram in the default profile: report state and position."""
        resp = self.poll()
        return Identity("LinMot", "LinRS drive", {"id": f"{self.drive_id:#04x}",
                                                  "state": STATE_NAMES.get(resp.main_state, str(resp.main_state))})

    def safe_state(self) -> None:
        """Abort whatever the drive is doing — a go-to, homing, a jog, its own special motions — with a controlled
        stop, position held (MC-SW §3.12 /Abort; §3.22: Home and the other special-motion bits are levels, and the
        abort word clears them). Where this driver switched the drive on, the abort goes out first, before any
        reply is waited for: a stop request cancels waits, and a serial write always goes out. Otherwise one poll
        decides: a drive not operating (main state below 8) is left as it is — nothing here switches it on."""
        if not self._control_word & CW_SWITCH_ON and self.poll().main_state < 8:
            return
        self.stop()

    # ----------------------------------------------------------- LinearMotor
    def enable(self, home: bool = True) -> None:
        """Run the state machine to Operation Enabled (0 → 2 → 8), acknowledge a pending error, home."""
        resp = self.poll()
        if resp.status_word & SW_FATAL:
            raise InstrumentStateError(self.name, f"fatal drive error: {self._error_text(resp)}")
        if resp.status_word & SW_ERROR:
            self.acknowledge_error()
        if resp.main_state != 8:
            self.write_control_word(0x0000)
            self._wait(lambda r: r.main_state in (1, 2), "switch-on disabled state")
            self.write_control_word(CW_READY)
            self._wait(lambda r: r.main_state == 2, "ready to switch on")
            self.write_control_word(CW_OPERATE)
            resp = self._wait(lambda r: r.main_state == 8, "operation enabled")
        if home and not resp.status_word & SW_HOMED:
            self.home()
        self._count = self.poll().command_count

    def home(self) -> None:
        """Home the motor (control word bit 11) and return to Operation Enabled."""
        self.write_control_word(CW_OPERATE | CW_HOME)
        self._wait(lambda r: r.state_var == 0x090F, "homing finished", timeout=max(self.state_timeout, 20.0))
        self.write_control_word(CW_OPERATE)
        self._wait(lambda r: r.main_state == 8 and bool(r.status_word & SW_HOMED), "homed and operation enabled")

    def acknowledge_error(self) -> None:
        """Rising edge on control-word bit 7 (not possible for fatal errors)."""
        self.write_control_word(self._control_word & ~CW_ERROR_ACK)
        self.write_control_word(self._control_word | CW_ERROR_ACK)
        resp = self.write_control_word(self._control_word & ~CW_ERROR_ACK)
        if resp.status_word & SW_FATAL:
            raise InstrumentStateError(self.name, f"fatal error cannot be acknowledged: {self._error_text(resp)}")

    def check_move(self, position: float, velocity: float, acceleration: float, deceleration: float) -> None:
        """Raise LimitError if a move would leave the software limits."""
        lo, hi = self.travel
        if not lo <= position <= hi:
            raise LimitError(self.name, f"target {position * 1e3:.3f} mm outside travel "
                             f"[{lo * 1e3:.3f}, {hi * 1e3:.3f}] mm")
        if not 0 < velocity <= self.max_velocity:
            raise LimitError(self.name, f"velocity {velocity:g} m/s outside (0, {self.max_velocity:g}] m/s")
        for label, acc in (("acceleration", acceleration), ("deceleration", deceleration)):
            if not 0 < acc <= self.max_acceleration:
                raise LimitError(self.name, f"{label} {acc:g} m/s² outside (0, {self.max_acceleration:g}] m/s²")

    def _counts(self, position: float) -> int:
        """The go-to target in drive increments: the nearest; where that lies beyond the travel and ``position``
        does not, the next one toward the inside."""
        lo, hi = self.travel
        n = round(position / POS_UNIT)
        if lo <= position <= hi:
            if n * POS_UNIT > hi:
                n -= 1
            elif n * POS_UNIT < lo:
                n += 1
        return n

    def quantise(self, position: float) -> float:
        """The target [m] :meth:`move_to` really sends for ``position``, sending nothing: the nearest drive
        increment (0.1 µm), one increment toward the inside where that lies just beyond the travel (a target at a
        travel limit stays within it). A value that is not finite is returned as it is (move_to refuses it)."""
        return self._counts(position) * POS_UNIT if math.isfinite(position) else position

    def move_to(self, position: float, velocity: float, acceleration: float,
                deceleration: float | None = None) -> None:
        """VAI go-to-position on the increment :meth:`quantise` chooses; returns when the drive has echoed the new
        command count."""
        dec = acceleration if deceleration is None else deceleration
        self.check_move(position, velocity, acceleration, dec)
        previous = self._count
        self._count = (self._count + 1) & 0x0F
        header = VAI_GOTO | self._count
        params = struct.pack("<HiIII", header, self._counts(position), round(velocity / VEL_UNIT),
                             round(acceleration / ACC_UNIT), round(dec / ACC_UNIT))
        resp = self.transact(MAIN_MOTION_COMMAND, 0x00, params)
        if self.in_error(resp):
            raise InstrumentStateError(self.name, f"motion command refused: {self._error_text(resp)}")
        self._check_count(resp, previous, self._count)
        if resp.main_state != 8 or resp.command_count != self._count:
            def acknowledged(r: DefaultResponse) -> bool:
                self._check_count(r, previous, self._count)
                return r.main_state == 8 and r.command_count == self._count
            self._wait(acknowledged, "motion command acknowledged", timeout=1.0)

    def wait_in_target(self, timeout: float = 10.0) -> Reading:
        """Block until the drive reports In Target Position; returns the position reached."""
        def reached(r: DefaultResponse) -> bool:
            self._check_count(r, self._count)
            return bool(r.status_word & SW_IN_TARGET) and not r.status_word & SW_MOTION_ACTIVE

        resp = self._wait(reached, "in-target position", timeout=timeout)
        return Reading(self.checked_position(resp), "m", self.clock())

    def read(self) -> ReadingMap:
        """One :meth:`read_position` keyed as :meth:`describe`: ``position`` [m]."""
        return {"position": self.read_position()}

    def read_position(self) -> Reading:
        """Actual position [m]; status "error" whenever the drive is in its error state or flags an error; an
        :class:`ImplausibleValueError` for a position far outside the travel (see the class docstring).

        Stamped at the start of the drive's reply (:meth:`SerialLink.reply_started`): the position was taken
        then, and the 16-byte default response's wire time (1.4 ms at 115,200 baud) came after."""
        with self.link.lock:
            resp = self.poll()
            t = self.link.reply_started(self.clock())
        return Reading(self.checked_position(resp), "m", t, "error" if self.in_error(resp) else "ok")

    def status(self) -> MotorStatus:
        """Decoded drive state."""
        r = self.poll()
        sw = r.status_word
        return MotorStatus(state=STATE_NAMES.get(r.main_state, f"state {r.main_state}"),
                           enabled=bool(sw & SW_OPERATION_ENABLED), homed=bool(sw & SW_HOMED),
                           moving=bool(sw & SW_MOTION_ACTIVE), in_target=bool(sw & SW_IN_TARGET),
                           error=self.in_error(r), error_code=self.error_code(r), position=self.checked_position(r),
                           error_text=self._error_text(r) if self.in_error(r) else "")

    def stop(self) -> None:
        """Abort the motion (clear /Abort), then re-arm; the drive decelerates and holds position."""
        self.write_control_word(CW_OPERATE & ~CW_NOT_ABORT)
        self.write_control_word(CW_OPERATE)

    def hurry(self, reply_timeout: float) -> None:
        """Shorter reply waits on the LinRS link (see the LinearMotor contract); a telegram is sent once anyway."""
        self.link.timeout = min(self.link.timeout, reply_timeout)

    def quick_stop(self) -> None:
        """Quick stop (clear /Quick Stop): maximum deceleration, then the drive leaves Operation Enabled."""
        self.write_control_word(CW_OPERATE & ~CW_NOT_QUICK_STOP)
