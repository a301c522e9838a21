"""ModbusLink against small fake peers written here: RTU on a pty, TCP on a loopback socket.

Frames are built by hand from the Modbus application protocol (function 3: address, count → byte count,
registers; MBAP header: transaction id, protocol 0, length, unit) — not by the code under test.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import threading
import time
import tty
from collections.abc import Callable, Iterator

import pytest

from drivers.cancel import CancelToken
from drivers.errors import InstrumentStateError, InstrumentTimeoutError, OperationCancelledError, ProtocolError
from drivers.modbus_link import ModbusLink
from tests.protocol_expect import expected_protocol, rtu

# handler(request PDU without unit/CRC, request number from 1) → [(delay before sending [s], reply PDU)]
Handler = Callable[[bytes, int], list[tuple[float, bytes]]]


def fc3_reply(value: int) -> bytes:
    return bytes([3, 2]) + struct.pack(">H", value)


class RtuPeer:
    """Unit 1 on the master side of a pty; the link opens the slave's name. Replies are sent in order."""

    def __init__(self, handler: Handler) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.name = os.ttyname(self.slave)
        self.handler = handler
        self.requests = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        buf = b""
        while not self.stop.is_set():
            try:
                if not select.select([self.master], [], [], 0.02)[0]:
                    continue
                buf += os.read(self.master, 256)
            except (OSError, ValueError):
                return
            while len(buf) >= 8:  # FC3/4/6 requests are 8 bytes: unit, fc, 4 bytes, CRC
                frame, buf = buf[:8], buf[8:]
                self.requests += 1
                for delay, pdu in self.handler(frame[1:6], self.requests):
                    if self.stop.wait(delay):
                        return
                    os.write(self.master, rtu(1, pdu))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)
        os.close(self.slave)
        os.close(self.master)


class TcpPeer:
    """Unit 1 behind a loopback socket: one connection, MBAP-framed replies echoing the request's tid."""

    def __init__(self, handler: Handler) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.02)
        self.port = self.server.getsockname()[1]
        self.handler = handler
        self.requests = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.server.accept()
                break
            except TimeoutError:
                continue
        else:
            return
        conn.settimeout(0.02)
        buf = b""
        with conn:
            while not self.stop.is_set():
                try:
                    data = conn.recv(256)
                except TimeoutError:
                    continue
                if not data:
                    return
                buf += data
                while len(buf) >= 6 and len(buf) >= 6 + struct.unpack(">H", buf[4:6])[0]:
                    size = 6 + struct.unpack(">H", buf[4:6])[0]
                    frame, buf = buf[:size], buf[size:]
                    self.requests += 1
                    for delay, pdu in self.handler(frame[7:], self.requests):
                        if self.stop.wait(delay):
                            return
                        conn.sendall(frame[:2] + struct.pack(">HHB", 0, len(pdu) + 1, 1) + pdu)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.server.close()


@pytest.fixture
def peers() -> Iterator[list[RtuPeer | TcpPeer]]:
    started: list[RtuPeer | TcpPeer] = []
    yield started
    for p in started:
        p.close()


def open_link(peers: list[RtuPeer | TcpPeer], kind: str, handler: Handler, **kw: object) -> ModbusLink:
    peer: RtuPeer | TcpPeer = RtuPeer(handler) if kind.startswith("rtu") else TcpPeer(handler)
    peers.append(peer)
    url = peer.name if isinstance(peer, RtuPeer) else f"tcp://127.0.0.1:{peer.port}"
    poll = 0.001 if kind == "rtu-prompt" else None
    link = ModbusLink(url, "bus io", poll_interval=poll, **kw)  # type: ignore[arg-type]
    link.open()
    return link


KINDS = ["rtu", "rtu-prompt", "tcp"]


@pytest.mark.parametrize("kind", KINDS)
def test_the_late_reply_to_the_first_attempt_is_never_taken_for_the_retry(peers: list, kind: str) -> None:
    # request n is answered with register value n; the first answer comes after the client's timeout
    def handler(req: bytes, n: int) -> list[tuple[float, bytes]]:
        return [(0.3 if n == 1 else 0.0, fc3_reply(n))]

    link = open_link(peers, kind, handler, timeout=0.2, retries=2)
    assert link.read_holding(1, 0, 1) == [2]  # the reply to the retry, not the stale reply to attempt 1


@pytest.mark.parametrize("kind", KINDS)
def test_a_reply_arriving_after_the_request_was_given_up_is_not_the_next_answer(peers: list, kind: str) -> None:
    def handler(req: bytes, n: int) -> list[tuple[float, bytes]]:
        return [(0.3 if n == 1 else 0.0, fc3_reply(n))]

    link = open_link(peers, kind, handler, timeout=0.2, retries=0)
    with pytest.raises(Exception, match="no valid reply from unit 1"):
        link.read_holding(1, 0, 1)
    assert link.read_holding(1, 0, 1) == [2]


@pytest.mark.parametrize("kind", KINDS)
def test_an_answer_with_another_function_code_is_a_protocol_error(peers: list, kind: str) -> None:
    def handler(req: bytes, n: int) -> list[tuple[float, bytes]]:
        return [(0.0, bytes([4, 2, 0, 7]))]  # an FC4 answer to whatever was asked

    link = open_link(peers, kind, handler, timeout=0.2, retries=0)
    with pytest.raises(ProtocolError, match=r"unit 1 answered read holding 0\+1 \(function 3\) with function 4"):
        link.read_holding(1, 0, 1)
    with pytest.raises(ProtocolError, match=r"answered write register 0=5 \(function 6\) with function 4"):
        link.write_register(1, 0, 5)


@pytest.mark.parametrize("kind", ["rtu", "rtu-prompt"])
def test_a_stop_ends_a_modbus_wait_within_a_poll(peers: list, kind: str) -> None:
    token = CancelToken()
    link = open_link(peers, kind, lambda req, n: [], timeout=10.0, retries=5, cancel=token)  # silent unit
    threading.Timer(0.2, token.cancel, ("SIGTERM",)).start()
    t0 = time.monotonic()
    with pytest.raises(OperationCancelledError, match="bus io: wait abandoned: SIGTERM"):
        link.read_holding(1, 0, 1)
    assert time.monotonic() - t0 < 10.0  # an order: within the first attempt's wait, not six attempts of 10 s


def test_a_stop_on_tcp_waits_out_at_most_one_attempt(peers: list) -> None:
    token = CancelToken()
    link = open_link(peers, "tcp", lambda req, n: [], timeout=3.0, retries=10, cancel=token)
    threading.Timer(0.1, token.cancel, ("SIGINT",)).start()
    t0 = time.monotonic()
    with pytest.raises(OperationCancelledError):
        link.read_holding(1, 0, 1)
    assert time.monotonic() - t0 < 2 * 3.0  # an order: at most the one attempt under way, not eleven of 3 s


def test_a_safety_write_goes_out_despite_a_stop_but_is_not_retried(peers: list) -> None:
    token = CancelToken()
    token.cancel("stop")
    link = open_link(peers, "rtu-prompt", lambda req, n: [(0.0, req)], timeout=0.2, retries=3, cancel=token)
    with pytest.raises(OperationCancelledError):
        link.write_register(1, 0, 2048)
    assert peers[0].requests == 0
    link.write_register(1, 0, 2048, always_send=True)  # FC6 echo
    assert peers[0].requests == 1


def test_write_echo_and_register_count_must_match_the_request() -> None:
    script = [(rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x01")),  # echoes another value
              (rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x01\x08\x00")),  # echoes another address
              (rtu(1, 16, b"\x00\x02\x00\x02\x04\x00\x01\x00\x02"), rtu(1, 16, b"\x00\x02\x00\x01")),  # count 1
              (rtu(1, 3, b"\x00\x00\x00\x02"), rtu(1, 3, 2, b"\x00\x01")),  # one register for two
              (rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 0x83, 2))]  # exception for another function
    with expected_protocol("echo", script) as url:
        link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
        link.open()
        with pytest.raises(ProtocolError, match=r"unit 1 echoed 0=\[2049\] to write register 0=2048"):
            link.write_register(1, 0, 2048)
        with pytest.raises(ProtocolError, match=r"unit 1 echoed 1=\[2048\]"):
            link.write_register(1, 0, 2048)
        with pytest.raises(ProtocolError, match=r"unit 1 echoed 2\+1 to write registers 2\+2"):
            link.write_registers(1, 2, [1, 2])
        with pytest.raises(ProtocolError, match="unit 1 returned 1 holding registers, 2 asked"):
            link.read_holding(1, 0, 2)
        with pytest.raises(ProtocolError, match=r"\(function 6\) with function 131"):
            link.write_register(1, 0, 2048)


def test_an_exception_reply_to_the_request_is_a_refusal() -> None:
    with expected_protocol("exc", [(rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 0x86, 2))]) as url:
        link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
        link.open()
        with pytest.raises(InstrumentStateError, match=r"exception 2 \(illegal data address\)"):
            link.write_register(1, 0, 2048)


def _scripted_tcp_peer(replies: Callable[[bytes], list[bytes]]) -> tuple[int, threading.Thread]:
    """A one-connection MBAP peer: for each request ADU read, the whole ADUs ``replies(request)`` gives, sent in one
    write."""
    server = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        conn, _ = server.accept()
        server.close()
        with conn:
            buf = b""
            while data := conn.recv(1024):
                buf += data
                while len(buf) >= 6 and len(buf) >= 6 + struct.unpack(">H", buf[4:6])[0]:
                    size = 6 + struct.unpack(">H", buf[4:6])[0]
                    frame, buf = buf[:size], buf[size:]
                    conn.sendall(b"".join(replies(frame)))

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return server.getsockname()[1], thread


def _mbap(tid: bytes, unit: int, pdu: bytes) -> bytes:
    return tid + struct.pack(">HHB", 0, len(pdu) + 1, unit) + pdu


def test_tcp_a_reply_from_another_unit_is_skipped_and_one_numbered_0_is_no_answer() -> None:
    """MBAP: the answer carries the request's transaction id and unit. A reply from another unit before it is passed
    over; a reply numbered 0 answers no request (the attempt fails); the answer that followed it, late, is not taken
    for the next request's."""
    def replies(req: bytes) -> list[bytes]:
        if req[:2] == b"\x00\x01":
            return [_mbap(req[:2], 2, fc3_reply(7)), _mbap(req[:2], 1, fc3_reply(8))]
        if req[:2] == b"\x00\x02":
            return [_mbap(b"\x00\x00", 1, fc3_reply(9)), _mbap(req[:2], 1, fc3_reply(10))]
        return [_mbap(req[:2], 1, fc3_reply(11))]

    port, thread = _scripted_tcp_peer(replies)
    link = ModbusLink(f"tcp://127.0.0.1:{port}", "bus io", timeout=0.2, retries=0)
    link.open()
    try:
        assert link.read_holding(1, 0, 1) == [8]
        with pytest.raises(InstrumentTimeoutError, match="no valid reply from unit 1"):
            link.read_holding(1, 0, 1)
        assert link.read_holding(1, 0, 1) == [11]
    finally:
        link.close()
        thread.join(2.0)


@pytest.mark.parametrize("gateway_baud", [None, 9600])
def test_tcp_reply_stamp_is_the_arrival_unless_a_gateways_rs485_line_carried_it(gateway_baud: int | None) -> None:
    """A device on Ethernet: a frame's time on the wire is microseconds, nothing is taken off. Behind a Modbus
    TCP/RTU gateway the reply first crossed the RS-485 line as an RTU frame — address, function, byte count, one
    register, CRC: 7 characters of 10 bits (8N1) — and started that long before the TCP reply arrived."""
    port, thread = _scripted_tcp_peer(lambda req: [_mbap(req[:2], 1, fc3_reply(5))])
    link = ModbusLink(f"tcp://127.0.0.1:{port}", "bus io", timeout=0.2, retries=0, gateway_baud=gateway_baud)
    link.open()
    try:
        assert link.read_holding(1, 0, 1) == [5]
        assert link.reply_started(4.0) == pytest.approx(4.0 - (7 * 10 / 9600 if gateway_baud else 0.0), abs=1e-12)
    finally:
        link.close()
        thread.join(2.0)


def test_rtu_reply_stamp_counts_the_whole_frame_at_the_ports_baud() -> None:
    """On the port itself: the FC3 reply of one register is 7 characters (address, function, byte count, 2 data
    bytes, CRC), 10 bits each at pymodbus' 8N1, here at 9600 Bd; without wire time (a line at pty speed) none."""
    for wire, expected in ((True, 4.0 - 7 * 10 / 9600), (False, 4.0)):
        peer = RtuPeer(lambda _pdu, _n: [(0.0, fc3_reply(5))])
        link = ModbusLink(peer.name, "bus io", baudrate=9600, timeout=0.2, retries=0, wire=wire)
        link.open()
        try:
            assert link.read_holding(1, 0, 1) == [5]
            assert link.reply_started(4.0) == pytest.approx(expected, abs=1e-12)
        finally:
            link.close()
            peer.close()


def test_a_reply_after_a_retry_is_stamped_at_its_arrival_not_after_the_wait_for_a_quiet_line() -> None:
    """The first request goes unanswered; the retry's reply comes, and the link then waits one more timeout for
    the line to go quiet (a late reply to the first request would win). The reading was taken when that reply
    came, so its stamp lies a whole timeout before the wait ended — it read 0.297 s later in a reviewer's run
    (the caller's time of asking stood for the arrival). An order, not a duration: a loaded host only widens it."""
    peer = RtuPeer(lambda _pdu, n: [] if n == 1 else [(0.0, fc3_reply(5))])
    link = ModbusLink(peer.name, "bus io", baudrate=19200, timeout=0.3, retries=1)
    link.clock = time.monotonic
    link.open()
    try:
        with link.lock:
            asked = time.monotonic()
            assert link.read_holding(1, 0, 1) == [5]
            done = time.monotonic()
            stamp = link.reply_started(done)
        assert asked < stamp and done - stamp >= link.timeout
    finally:
        link.close()
        peer.close()
