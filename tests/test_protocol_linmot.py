"""Byte-exact protocol tests of the LinMot LinRS driver (telegrams from the LinRS manual examples)."""

from __future__ import annotations

import struct

import pytest

from drivers.cancel import CancelToken
from drivers.errors import (
    InstrumentStateError,
    InstrumentTimeoutError,
    LimitError,
    OperationCancelledError,
    ProtocolError,
)
from drivers.linmot import LinMotDrive, crc16_ccitt_reflected, decode_default_response, encode
from drivers.serial_link import SerialLink
from tests.protocol_expect import expected_protocol

POLL = bytes.fromhex("01 11 03 02 01 00 04")


def response(status: int, state: int, pos_counts: int, comm: int = 0, drive: int = 0x11) -> bytes:
    head = bytes([0x01, drive, 0x0C, 0x02, 0x00, 0x00])
    return head + struct.pack("<BHHi", comm, status, state, pos_counts) + b"\x04"


def drive(url: str, **kw: object) -> LinMotDrive:
    d = LinMotDrive(SerialLink(url, "motor", timeout=0.05), travel=(0.0, 0.1), poll_interval=0.0,
                    state_timeout=0.2, **kw)  # type: ignore[arg-type]
    d.link.open()
    return d


def test_manual_examples_encode() -> None:
    # LinRS manual: write control word example, and predefined VAI go to 10 mm (header 0x0201)
    assert encode(0x11, 0x01, 0x00, b"\x00\x00") == bytes.fromhex("01 11 05 02 00 01 00 00 04")
    predef = encode(0x11, 0x02, 0x00, bytes.fromhex("01 02") + struct.pack("<i", 100_000))
    assert predef == bytes.fromhex("01 11 09 02 00 02 01 02 A0 86 01 00 04")
    assert encode(0x11, 0x00, 0x01) == POLL
    with pytest.raises(ValueError, match="exceeds 63"):
        encode(0x11, 0x02, 0x00, bytes(61))


def test_checksum_option() -> None:
    plain = encode(0x11, 0x00, 0x01)
    checked = encode(0x11, 0x00, 0x01, checksum=True)
    assert checked[:6] == plain[:6] and checked[-1] == 0x04 and len(checked) == len(plain) + 2
    assert checked[2] == 3  # Len does not count the checksum
    frame = response(0x0C37, 0x08C0, 42)
    body = frame[3:15]
    from drivers.linmot import crc16_ccitt_reflected

    good = frame[:15] + struct.pack("<H", crc16_ccitt_reflected(body)) + b"\x04"
    assert decode_default_response(good, 0x11, "motor", checksum=True).position_counts == 42
    bad = good[:8] + bytes([good[8] ^ 0x10]) + good[9:]
    with pytest.raises(ProtocolError, match="checksum error"):
        decode_default_response(bad, 0x11, "motor", checksum=True)
    assert crc16_ccitt_reflected(b"123456789") == 0x2189  # CRC-16/KERMIT check value


def test_manual_example_default_response_decodes() -> None:
    frame = bytes.fromhex("01 11 0C 02 00 00 00 37 68 A1 08 8B FC FF FF 04")
    r = decode_default_response(frame, 0x11, "motor")
    assert (r.status_word, r.state_var, r.position_counts) == (0x6837, 0x08A1, -885)
    assert r.main_state == 8 and r.command_count == 1 and r.position == pytest.approx(-88.5e-6)


def test_vai_go_to_position_bytes_and_count_handshake() -> None:
    params = struct.pack("<HiIII", 0x0101, 500_000, 200_000, 500_000, 300_000)
    req = bytes.fromhex("01 11 15 02 00 02") + params + b"\x04"
    assert len(req) == 3 + 0x15 + 1
    with expected_protocol("vai", [(req, response(0x2837, 0x08A1, 0))]) as url:
        drive(url).move_to(0.05, 0.2, 5.0, 3.0)


def test_a_go_to_at_the_travel_limit_sends_the_nearest_increment_within_it() -> None:
    """LinRS position unit 0.1 µm. Travel [0.03 µm, 95.00007 mm] (ends off the increment grid), by hand:
    95.00007 mm = 950000.7 increments → nearest 950001 = 95.0001 mm, beyond → 950000; 0.04 µm = 0.4 → 0, below
    0.03 µm → 1; a target beyond the travel keeps its nearest increment (refused, not pulled inside)."""
    params = struct.pack("<HiIII", 0x0101, 950_000, 200_000, 500_000, 300_000)
    req = bytes.fromhex("01 11 15 02 00 02") + params + b"\x04"
    with expected_protocol("edge", [(req, response(0x2837, 0x08A1, 0))]) as url:
        d = LinMotDrive(SerialLink(url, "motor", timeout=0.05), travel=(0.03e-6, 0.09500007), poll_interval=0.0,
                        state_timeout=0.2)
        d.link.open()
        edge = d.quantise(0.09500007)
        assert edge == pytest.approx(950_000 * 1e-7, abs=1e-15) and edge <= 0.09500007
        assert d.quantise(0.04e-6) == pytest.approx(1e-7, abs=1e-15)
        assert d.quantise(0.05) == pytest.approx(0.05, abs=1e-15)
        assert d.quantise(0.2) == pytest.approx(0.2, abs=1e-15)
        d.move_to(0.09500007, 0.2, 5.0, 3.0)


def test_enable_runs_the_state_machine_and_homes() -> None:
    script = [
        (POLL, response(0x0040, 0x0000, 0)),  # not ready to switch on, switch-on locked
        (bytes.fromhex("01 11 05 02 00 01 00 00 04"), response(0x0000, 0x0100, 0)),
        (POLL, response(0x0000, 0x0100, 0)),
        (bytes.fromhex("01 11 05 02 00 01 3E 00 04"), response(0x0036, 0x0200, 0)),
        (POLL, response(0x0036, 0x0200, 0)),
        (bytes.fromhex("01 11 05 02 00 01 3F 00 04"), response(0x0037, 0x0500, 0)),
        (POLL, response(0x0037, 0x0500, 0)),
        (POLL, response(0x4037, 0x0840, 0)),  # operation enabled, not homed
        (bytes.fromhex("01 11 05 02 00 01 3F 08 04"), response(0x2036, 0x0901, 0)),
        (POLL, response(0x0836, 0x090F, 0)),  # homing finished
        (bytes.fromhex("01 11 05 02 00 01 3F 00 04"), response(0x0C37, 0x08C0, 0)),
        (POLL, response(0x0C37, 0x08C0, 0)),
        (POLL, response(0x0C37, 0x08C0, 0)),  # read back the command count
    ]
    with expected_protocol("en", script) as url:
        drive(url).enable()


def test_error_acknowledge_is_a_rising_edge_on_bit7() -> None:
    script = [(bytes.fromhex("01 11 05 02 00 01 00 00 04"), response(0x0008, 0x040B, 0)),
              (bytes.fromhex("01 11 05 02 00 01 80 00 04"), response(0x0000, 0x0100, 0)),
              (bytes.fromhex("01 11 05 02 00 01 00 00 04"), response(0x0000, 0x0100, 0))]
    with expected_protocol("ack", script) as url:
        drive(url).acknowledge_error()


def test_refused_motion_reports_the_drive_error() -> None:
    params = struct.pack("<HiIII", 0x0101, 100_000, 100_000, 100_000, 100_000)
    req = bytes.fromhex("01 11 15 02 00 02") + params + b"\x04"
    # LinMot MC-SW drive error codes: 0086h "Motion Cmd In Wrong St" (0020h is "Motor Hot Sensor")
    with expected_protocol("refuse", [(req, response(0x0008, 0x0486, 0))]) as url:
        with pytest.raises(InstrumentStateError, match="code 0x86 motion command in wrong state"):
            drive(url).move_to(0.01, 0.1, 1.0)


def test_travel_limits_are_checked_before_sending() -> None:
    with expected_protocol("limits", []) as url:
        d = drive(url)
        with pytest.raises(LimitError, match=r"target 150\.000 mm outside travel"):
            d.move_to(0.15, 0.1, 1.0)
        with pytest.raises(LimitError, match="velocity"):
            d.move_to(0.05, 5.0, 1.0)
        with pytest.raises(LimitError, match="deceleration"):
            d.move_to(0.05, 0.1, 1.0, 100.0)


def test_malformed_replies() -> None:
    with expected_protocol("bad-start", [(POLL, b"\x05\x11\x0c" + bytes(13))]) as url:
        with pytest.raises(ProtocolError, match="does not start with 01h"):
            drive(url).poll()
    with expected_protocol("bad-end", [(POLL, response(0, 0, 0)[:-1] + b"\x05")]) as url:
        with pytest.raises(ProtocolError, match="malformed default response"):
            drive(url).poll()
    with expected_protocol("other-id", [(POLL, response(0, 0, 0, drive=0x12))]) as url:
        with pytest.raises(ProtocolError, match="drive id 0x12"):
            drive(url).poll()
    with expected_protocol("comm", [(POLL, response(0, 0, 0, comm=1))]) as url:
        with pytest.raises(ProtocolError, match="communication state 0x01"):
            drive(url).poll()
    with expected_protocol("short", [(POLL, response(0, 0, 0)[:9])]) as url:
        with pytest.raises(InstrumentTimeoutError, match="motor: no reply"):
            drive(url).poll()


def test_status_decoding_and_stop() -> None:
    script = [(POLL, response(0x6C37, 0x08E3, 123_456)),
              (bytes.fromhex("01 11 05 02 00 01 2F 00 04"), response(0x4C37, 0x08C3, 123_456)),
              (bytes.fromhex("01 11 05 02 00 01 3F 00 04"), response(0x4C37, 0x08C3, 123_456))]
    with expected_protocol("status", script) as url:
        d = drive(url)
        s = d.status()
        d.stop()
    assert s.state == "operation enabled" and s.homed and s.moving and not s.error
    assert s.position == pytest.approx(12.3456e-3)


@pytest.mark.parametrize("code, text", [(0x80, "not homed"), (0x81, "unknown motion command"),
                                        (0x85, "PVT master too slow"), (0x86, "motion command in wrong state"),
                                        (0x20, "motor hot sensor"), (0x21, "X3 hall signals missing"),
                                        (0x08, "max position overshot")])
def test_error_codes_follow_the_mc_sw_error_list(code: int, text: str) -> None:
    # MC-SW 4.3.4 §10 error code list; error state: main state 4, code in the state var's low byte
    with expected_protocol("errcode", [(POLL, response(0x0008, 0x0400 | code, 5000))]) as url:
        s = drive(url).status()
    assert s.error and s.error_code == code and text in s.error_text and s.state == "error"


@pytest.mark.parametrize("status, state", [(0x0008, 0x0480), (0x0000, 0x0480), (0x1008, 0x0422), (0x0C3F, 0x08C0 | 0)])
def test_position_is_not_ok_when_the_drive_is_in_error(status: int, state: int) -> None:
    flagged = status & 0x1008 or state >> 8 == 4
    with expected_protocol("poserr", [(POLL, response(status, state, 123_456))]) as url:
        r = drive(url).read_position()
    assert r.status == ("error" if flagged else "ok") and r.ok is (not flagged)
    assert r.value == pytest.approx(12.3456e-3)


@pytest.mark.parametrize("baud, checksum", [(115200, False), (9600, False), (115200, True)])
def test_position_is_stamped_at_the_start_of_the_default_response(baud: int, checksum: bool) -> None:
    """The drive puts its actual position into the default response as it starts sending it; the 16 bytes (18
    with the checksum: LinRS manual p. 11, instruments.md §2.2) then take 10 bits each (8N1) at the drive's baud
    rate. The clock reads 7.0 s when the reply is in: the reading is stamped 16 × 10 / baud before that."""
    frame = response(0x0C37, 0x08C0, 42)
    if checksum:
        frame = frame[:15] + struct.pack("<H", crc16_ccitt_reflected(frame[3:15])) + b"\x04"
    poll = encode(0x11, 0x00, 0x01, checksum=checksum)
    with expected_protocol("posstamp", [(poll, frame)]) as url:
        d = LinMotDrive(SerialLink(url, "motor", baudrate=baud, timeout=0.05), travel=(0.0, 0.1),
                        clock=lambda: 7.0, checksum=checksum)
        d.link.open()
        r = d.read_position()
    assert len(frame) == (18 if checksum else 16)
    assert r.timestamp == pytest.approx(7.0 - len(frame) * 10 / baud, abs=1e-12)


def test_a_count_echo_we_never_sent_is_a_protocol_error() -> None:
    params = struct.pack("<HiIII", 0x0101, 100_000, 100_000, 100_000, 100_000)
    req = bytes.fromhex("01 11 15 02 00 02") + params + b"\x04"
    with expected_protocol("badcount", [(req, response(0x0837, 0x08C5, 0))]) as url:  # echoes count 5, sent 1
        with pytest.raises(ProtocolError, match="motor: drive echoes motion command count 5, last sent 1"):
            drive(url).move_to(0.01, 0.1, 1.0)
    script = [(POLL, response(0x2837, 0x08A3, 0))]  # moving, echoing count 3 while we sent 0
    with expected_protocol("badcount2", script) as url:
        with pytest.raises(ProtocolError, match="echoes motion command count 3"):
            drive(url).wait_in_target(timeout=0.2)


def test_a_stop_request_ends_every_drive_wait() -> None:
    token = CancelToken()
    token.cancel("SIGTERM")
    with expected_protocol("cancel", []) as url:  # nothing is polled once the stop is requested
        d = drive(url)
        d.link.cancel = token
        with pytest.raises(OperationCancelledError, match="motor: wait abandoned: SIGTERM"):
            d.wait_in_target(timeout=5.0)
        with pytest.raises(OperationCancelledError):
            d._wait(lambda r: True, "anything")
    script = [(bytes.fromhex("01 11 05 02 00 01 3F 08 04"), response(0x2036, 0x0901, 0)),
              (POLL, response(0x2036, 0x0901, 0))]  # homing under way
    with expected_protocol("cancel-home", script) as url:
        d = drive(url)
        d.sleep = lambda s: token.cancel("Ctrl-C")  # the stop arrives while homing is polled
        token.clear()
        d.link.cancel = token
        with pytest.raises(OperationCancelledError, match="Ctrl-C"):
            d.home()


def test_a_state_wait_polls_every_10_ms_by_default() -> None:
    # The default keeps the RS-232 line mostly free while a drive switches on (~0.3 s) or homes (seconds): a poll
    # and its default response are 7 + 16 bytes, 2.0 ms at 115,200 Bd 8N1, so polls 10 ms apart load the line
    # ~17 %; a pause of 2 ms (the former default) kept it busy half the time for no gain in reaction time a
    # human-scale homing could use.
    script = [(POLL, response(0x0037, 0x0500, 0)),  # state 5: switch-on test still running
              (POLL, response(0x0037, 0x0500, 0)),
              (POLL, response(0x4037, 0x0840, 0))]  # operation enabled
    pauses: list[float] = []
    with expected_protocol("pace", script) as url:
        d = LinMotDrive(SerialLink(url, "motor", timeout=0.05), travel=(0.0, 0.1), sleep=pauses.append)
        d.link.open()
        d._wait(lambda r: r.main_state == 8, "operation enabled")
    assert pauses == [0.01, 0.01]


ABORT = bytes.fromhex("01 11 05 02 00 01 2F 00 04")  # 003Fh with bit 4 /Abort clear (§3.12) and Home (bit 11) clear
REARM = bytes.fromhex("01 11 05 02 00 01 3F 00 04")


def test_the_safe_state_aborts_homing_first_without_waiting_for_a_poll() -> None:
    """Homing is a motion too: the safe state clears /Abort with Home released (both levels, §3.22) as its first
    telegram — no poll before it — then re-arms; the drive rests in position (§3.12)."""
    script = [(bytes.fromhex("01 11 05 02 00 01 3F 08 04"), response(0x2036, 0x0901, 0)),  # homing under way
              (ABORT, response(0x4C37, 0x0C00, 0)), (REARM, response(0x4C37, 0x0800, 0))]
    with expected_protocol("safe-homing", script) as url:
        d = drive(url)
        d.write_control_word(0x083F)
        d.safe_state()


def test_the_safe_state_s_abort_goes_out_after_a_stop_request() -> None:
    """With the stop request's token set, the abort still goes out (a serial write always does); only the wait
    for its reply is abandoned — the drive stays stopped, /Abort clear."""
    token = CancelToken()
    script = [(bytes.fromhex("01 11 05 02 00 01 3F 00 04"), response(0x6C37, 0x08E3, 0)),  # a go-to under way
              (ABORT, response(0x4C37, 0x0C00, 0))]
    with expected_protocol("safe-cancelled", script) as url:
        d = drive(url)
        d.write_control_word(0x003F)
        d.link.cancel = token
        token.cancel("Ctrl-C")
        with pytest.raises(OperationCancelledError, match="Ctrl-C"):
            d.safe_state()


def test_the_safe_state_leaves_a_drive_it_did_not_switch_on_as_it_is() -> None:
    """A drive this driver never switched on, found ready to switch on (main state 2): one poll, nothing that
    could switch it on."""
    with expected_protocol("safe-off", [(POLL, response(0x0036, 0x0200, 0))]) as url:
        drive(url).safe_state()


def test_each_poll_sends_the_default_response_request_of_the_drive_id_and_checksum_set_now() -> None:
    """The poll telegram (LinRS manual p. 11: 01h | ID | Len 03h | 02h | Sub 01h | Main 00h | 04h) is the same bytes at
    every poll, and follows a drive id or checksum setting changed after the first: 01 12 03 02 01 00 04 for drive
    12h; with the checksum, its two bytes before the 04h (the CRC checked against CRC-16/KERMIT above)."""
    other = bytes.fromhex("01 12 03 02 01 00 04")
    checked = encode(0x12, 0x00, 0x01, checksum=True)
    assert checked[:6] == other[:6] and len(checked) == 9
    reply = response(0x0837, 0x0800, 13, drive=0x12)
    script = [(POLL, response(0x0837, 0x0800, 10)), (POLL, response(0x0837, 0x0800, 11)),
              (other, response(0x0837, 0x0800, 12, drive=0x12)),
              (checked, reply[:15] + struct.pack("<H", crc16_ccitt_reflected(reply[3:15])) + b"\x04")]
    with expected_protocol("poll-ids", script) as url:
        d = drive(url)
        assert [d.poll().position_counts for _ in range(2)] == [10, 11]
        d.drive_id = 0x12
        assert d.poll().position_counts == 12
        d.checksum = True
        assert d.poll().position_counts == 13


def test_a_poll_for_a_drive_id_outside_a_byte_is_refused_before_anything_is_sent() -> None:
    """The LinRS ID field is one byte (LinRS manual p. 11): a drive id of −1 or 256 cannot be sent, and the poll says
    so at once (as every other telegram does) instead of sending nothing and waiting out a timeout."""
    for bad in (-1, 256):
        with expected_protocol(f"bad-id-{bad}", []) as url:
            d = drive(url)
            d.drive_id = bad
            with pytest.raises(ValueError):
                d.poll()
