"""SerialLink deadlines and stop requests against a peer on a real pty (a thread writing the master side)."""

from __future__ import annotations

import os
import pathlib
import threading
import time
import tty
from collections.abc import Iterator

import pytest

from drivers.cancel import CancelToken
from drivers.errors import InstrumentTimeoutError, OperationCancelledError
from drivers.serial_link import SerialLink


class PtyPeer:
    """The far end of a pty: a test thread writes bytes to the master; the link opens the slave's name."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.name = os.ttyname(self.slave)
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []

    def run(self, fn: object) -> None:
        t = threading.Thread(target=fn, daemon=True)  # type: ignore[arg-type]
        t.start()
        self.threads.append(t)

    def trickle(self, byte: bytes = b"x", every: float = 0.02) -> None:
        """Send one byte every ``every`` seconds, never a terminator, until stopped."""
        def loop() -> None:
            while not self.stop.wait(every):
                os.write(self.master, byte)
        self.run(loop)

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2.0)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def peer() -> Iterator[PtyPeer]:
    p = PtyPeer()
    yield p
    p.close()


def link_on(peer: PtyPeer, timeout: float, cancel: CancelToken | None = None) -> SerialLink:
    link = SerialLink(peer.name, "probe", timeout=timeout, exclusive=False, cancel=cancel)
    link.open()
    return link


def test_read_until_deadline_counts_total_time_against_a_trickling_peer(peer: PtyPeer) -> None:
    peer.trickle(every=0.02)  # a byte every 20 ms: a "since the last byte" deadline would never expire
    link = link_on(peer, timeout=0.3)
    t0 = time.monotonic()
    with pytest.raises(InstrumentTimeoutError, match=r"probe: no reply within 0\.3 s \(partial reply b'x"):
        link.read_until(b"\r")
    assert 0.29 <= time.monotonic() - t0 < 5.0  # an order: the trickle (forever) does not extend the deadline
    link.close()


def test_read_exact_deadline_counts_total_time_against_a_trickling_peer(peer: PtyPeer) -> None:
    peer.trickle(every=0.02)
    link = link_on(peer, timeout=0.3)
    t0 = time.monotonic()
    with pytest.raises(InstrumentTimeoutError, match=r"probe: no reply within 0\.3 s"):
        link.read_exact(1000)
    assert 0.29 <= time.monotonic() - t0 < 5.0  # an order: the trickle (forever) does not extend the deadline
    link.close()


@pytest.mark.parametrize("trickling", [False, True])
@pytest.mark.parametrize("method", ["read_until", "read_exact"])
def test_a_stop_from_another_thread_ends_a_long_read_within_a_slice(peer: PtyPeer, trickling: bool,
                                                                    method: str) -> None:
    if trickling:
        peer.trickle(every=0.01)
    token = CancelToken()
    link = link_on(peer, timeout=5.0, cancel=token)
    cancelled_at: list[float] = []

    def stop_later() -> None:
        time.sleep(0.2)
        cancelled_at.append(time.monotonic())
        token.cancel("operator pressed Ctrl-C")

    peer.run(stop_later)
    with pytest.raises(OperationCancelledError, match="probe: wait abandoned: operator pressed Ctrl-C"):
        if method == "read_until":
            link.read_until(b"\r")
        else:
            link.read_exact(10_000)
    assert time.monotonic() - cancelled_at[0] < 2.5  # an order: ended by the stop, not the 5-s timeout
    link.close()


def test_cancel_token_is_a_settable_attribute(peer: PtyPeer) -> None:
    link = link_on(peer, timeout=30.0)
    link.cancel = token = CancelToken()
    token.cancel("stop")
    t0 = time.monotonic()
    with pytest.raises(OperationCancelledError):
        link.read_until(b"\r")
    assert time.monotonic() - t0 < 15.0  # an order: the set token ends the read, not the 30-s timeout
    token.clear()  # cleared: traffic flows again
    os.write(peer.master, b"ok\r")
    assert link.read_until(b"\r") == b"ok\r"
    link.close()


def test_a_late_reply_to_an_abandoned_read_is_dropped_before_the_next_request(peer: PtyPeer) -> None:
    link = link_on(peer, timeout=0.1)
    with pytest.raises(InstrumentTimeoutError):
        link.read_until(b"\r")
    os.write(peer.master, b"late reply\r")  # the answer to the timed-out request, arriving afterwards
    time.sleep(0.05)
    link.write(b"next request\r")
    os.read(peer.master, 100)
    os.write(peer.master, b"fresh reply\r")
    assert link.read_until(b"\r") == b"fresh reply\r"
    link.close()


def test_a_pty_gone_from_under_the_link_is_a_lost_link_not_a_termios_error() -> None:
    """pyserial lets termios.error (no OSError) out of reset_input_buffer when the far end of a pty has gone: the
    link says it is lost, one line naming the device, as for any other dead port."""
    from drivers.errors import InstrumentConnectionError

    p = PtyPeer()
    link = SerialLink(p.name, "probe", timeout=0.1, exclusive=False)
    link.open()
    os.close(p.master)
    os.close(p.slave)
    with pytest.raises(InstrumentConnectionError, match=r"probe: link on .* lost"):
        link.discard_input()


class SyscallCount:
    """Counts the port's system calls from here on (``os.read``, ``os.write``, ``select.select``: pyserial's POSIX
    port and the link both call them through the modules)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        import select

        self.calls: list[str] = []
        for module, name in ((os, "read"), (os, "write"), (select, "select")):
            real = getattr(module, name)

            def counted(*args: object, _real: object = real, _name: str = name) -> object:
                self.calls.append(_name)
                return _real(*args)  # type: ignore[operator]

            monkeypatch.setattr(module, name, counted)


def test_a_request_is_one_write_and_a_reply_read_as_header_then_body_one_wait_and_one_read(
        peer: PtyPeer, monkeypatch: pytest.MonkeyPatch) -> None:
    """A LinRS exchange as the LinMot driver makes it: the request written whole, the 16-byte default response
    (LinRS manual p. 11) read as its 3-byte header, then the 13 bytes its length byte announces. On a POSIX port the
    write is one system call (no wait for writability after it) and the reply, there whole, one wait and one read:
    the body comes from what the header's read already took."""
    link = link_on(peer, timeout=1.0)
    request = bytes.fromhex("01 11 03 02 01 00 04")
    reply = bytes.fromhex("01 11 0C 02 00 00 00 37 68 A1 08 8B FC FF FF 04")
    count = SyscallCount(monkeypatch)
    link.write(request)
    assert count.calls == ["write"]
    monkeypatch.undo()
    assert os.read(peer.master, 100) == request
    os.write(peer.master, reply)
    count = SyscallCount(monkeypatch)
    head = link.read_exact(3)
    body = link.read_exact(head[2] + 1)
    assert head + body == reply
    assert count.calls == ["select", "read"]
    monkeypatch.undo()
    link.close()


def test_bytes_read_beyond_a_count_go_to_the_next_read_and_are_dropped_with_the_input(peer: PtyPeer) -> None:
    link = link_on(peer, timeout=1.0)
    os.write(peer.master, b"abcdef\r")
    time.sleep(0.05)  # all of it has arrived: the first read takes it all from the port
    assert link.read_exact(2) == b"ab"
    assert link.read_exact(3) == b"cde"
    assert link.read_until(b"\r") == b"f\r"
    os.write(peer.master, b"stale")
    time.sleep(0.05)
    assert link.read_exact(1) == b"s"
    link.discard_input()  # "tale" is in the link now, not in the port: dropped all the same
    os.write(peer.master, b"new")
    assert link.read_exact(3) == b"new"
    link.close()


def test_a_count_longer_than_what_the_link_holds_takes_that_first_then_waits_for_the_rest(peer: PtyPeer) -> None:
    link = link_on(peer, timeout=1.0)
    os.write(peer.master, b"abcd")
    time.sleep(0.05)
    assert link.read_exact(1) == b"a"  # "bcd" stays in the link
    os.write(peer.master, b"efg")
    assert link.read_exact(5) == b"bcdef"
    assert link.read_exact(1) == b"g"
    link.close()


def test_a_pty_whose_far_end_closes_during_a_read_is_a_lost_link() -> None:
    from drivers.errors import InstrumentConnectionError

    p = PtyPeer()
    link = SerialLink(p.name, "probe", timeout=5.0, exclusive=False)
    link.open()
    threading.Timer(0.1, os.close, (p.master,)).start()
    t0 = time.monotonic()
    with pytest.raises(InstrumentConnectionError, match=r"probe: link on .* lost"):
        link.read_exact(16)
    assert time.monotonic() - t0 < 4.0  # an order: the closed line ends the read, not the 5-s timeout
    assert not link.is_open
    os.close(p.slave)


def test_the_reply_start_is_its_arrival_less_the_wire_time_of_every_byte_read_since_the_request(
        peer: PtyPeer) -> None:
    """A reply read in parts (header, then body) counts whole; bytes read beyond it wait for the next read and are not
    counted; the next request starts a new count. 8N1: 10 bits a character (start, 8 data, stop)."""
    link = SerialLink(peer.name, "probe", baudrate=9600, timeout=1.0, exclusive=False)
    link.open()
    link.write(b"?")
    os.write(peer.master, b"0123456789ABCDEF\rnext")
    assert link.read_exact(3) == b"012"
    assert link.reply_started(10.0) == pytest.approx(10.0 - 3 * 10 / 9600, abs=1e-12)
    assert link.read_until(b"\r") == b"3456789ABCDEF\r"
    assert link.reply_started(10.0) == pytest.approx(10.0 - 17 * 10 / 9600, abs=1e-12)  # 17 characters: 17.7 ms
    link.write(b"?")
    assert link.reply_started(2.0) == 2.0  # nothing read since the request
    assert link.read_exact(4) == b"next"
    assert link.reply_started(2.0) == pytest.approx(2.0 - 4 * 10 / 9600, abs=1e-12)
    link.close()


def test_a_link_without_wire_time_stamps_a_reply_at_its_arrival(peer: PtyPeer) -> None:
    """A simulated line at pty speed (``wire=False``): the reply arrived the moment it was made."""
    link = SerialLink(peer.name, "probe", baudrate=9600, timeout=1.0, exclusive=False, wire=False)
    link.open()
    link.write(b"?")
    os.write(peer.master, b"0123456789\r")
    assert link.read_until(b"\r") == b"0123456789\r"
    assert link.reply_started(3.0) == 3.0
    link.close()


def test_a_usb_serial_adapter_holding_replies_longer_than_1_ms_is_warned_about(
        tmp_path: pathlib.Path, caplog: pytest.LogCaptureFixture) -> None:
    """An FTDI-type adapter holds a short reply up to its latency timer (16 ms by default) before the host sees it:
    no stamp can take that off, so opening such a port says so, naming the device, the tty and the fix. A tty
    without a latency timer (a pty, a twin's port) or one at 1 ms says nothing. The sysfs tree is a stand-in."""
    from drivers.serial_link import usb_latency_ms, warn_usb_latency

    sysfs = tmp_path / "sysfs"
    for name, ms in (("ttyUSB0", "16\n"), ("ttyUSB1", "1\n")):
        (sysfs / name).mkdir(parents=True)
        (sysfs / name / "latency_timer").write_text(ms)
    (tmp_path / "by-id").mkdir()
    link = tmp_path / "by-id" / "usb-FTDI_FT232R-if00-port0"
    link.symlink_to(tmp_path / "ttyUSB0")  # a /dev/serial/by-id link resolves to the tty
    assert usb_latency_ms(str(link), sysfs) == 16
    with caplog.at_level("WARNING", logger="drivers.serial_link"):
        text = warn_usb_latency(str(link), "laser", sysfs)
    assert text is not None and "laser" in text and "ttyUSB0" in text and "16 ms" in text and "echo 1 >" in text
    assert any("ttyUSB0" in r.getMessage() for r in caplog.records)
    assert warn_usb_latency(str(tmp_path / "ttyUSB1"), "motor", sysfs) is None
    assert warn_usb_latency("/dev/pts/7", "motor", sysfs) is None
