"""A Modbus bus (RTU on a serial port, or TCP) shared by the modules on it, with named driver errors.

``url``: a serial device or pyserial URL (``/dev/ttyUSB0``, ``/dev/pts/7``, ``socket://host:port``) for RTU,
or ``tcp://host:port`` for Modbus TCP. Uses the pymodbus 3.16 synchronous clients; on TCP an attempt runs
through pymodbus' framer and transaction counter without its transaction manager (:meth:`_TcpClient.exchange`).

Retries are ours, not pymodbus' (its ``retries`` is 0): the optional :class:`~drivers.cancel.CancelToken` is
checked before every attempt (and, on RTU, at every receive poll), so a stop waits out at most one attempt.
Every reply must match its request (function code; FC6 echo of address and value; FC16 echo of address and
count; register count of a read) or it is a :class:`ProtocolError`. Stale replies: on TCP each attempt has a
fresh transaction id and pymodbus skips a reply with another id (checked again here); on RTU, where replies
carry no id, input is discarded before every request, and after a timeout the next reply is held for one
timeout while the line goes quiet — if a second frame follows (the late answer to the earlier attempt came
first), the later one is the answer to the latest request.

Each attempt waits for its reply until a :class:`~drivers.deadline.Deadline` of the link's timer expires: the
attempt's timeout on the wall clock on hardware; in a virtual-time simulation, what the twin did with the request
(:mod:`drivers.deadline`). pymodbus' own receive loop and connect are bounded by the timer's wall-clock ``bound``.

A reading is stamped at the start of its reply (:meth:`ModbusLink.reply_started`): on RTU the arrival of the reply's
last byte less the frame's wire time at the port's baud rate and framing (:func:`drivers.serial_link.wire_time`); on
TCP the arrival itself (a frame's time on Ethernet is microseconds) — unless the TCP peer is a Modbus TCP/RTU gateway
(``gateway_baud``), whose reply follows the RTU frame on its RS-485 line: then that frame's wire time is taken off.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import cast

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from drivers.cancel import CancelToken, check
from drivers.deadline import WALL, Deadline, ReplyTimer
from drivers.errors import (
    InstrumentConnectionError,
    InstrumentStateError,
    InstrumentTimeoutError,
    OperationCancelledError,
    ProtocolError,
)
from drivers.serial_link import (
    POLL_SLICE_S,
    PORT_ERRORS,
    char_bits,
    set_slice_timeout,
    warn_usb_latency,
    wire_time,
)

EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "device failure", 5: "acknowledge", 6: "device busy", 11: "gateway target failed to respond"}

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors are reported by the drivers, one line each


_RTU_SIZE = FramerRTU(DecodePDU(False))  # sizes a reply's RTU frame (on the port, or behind a gateway)


class _TrailingRTUFramer(FramerRTU):
    """RTU framer that keeps the bytes after the frame it decoded (pymodbus' own drops them)."""

    def __init__(self) -> None:
        super().__init__(DecodePDU(False))
        self.trailing = b""

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        used, dev_id, tid, frame = super().decode(data)
        if frame:
            start = data.find(bytes([dev_id]) + frame)
            self.trailing = data[start + len(frame) + 3:]  # id, PDU, 2 CRC bytes
        return used, dev_id, tid, frame


class _SerialClient(ModbusSerialClient):
    """RTU client whose receive waits check the link's cancel token and wake on the first reply byte.

    pymodbus' own ``recv(None)`` sleeps in polls of four character times and waits until the byte count is
    stable over two of them (≈ 4 ms at 19200 Bd after the last byte). Its transaction loop already
    accumulates partial frames until the framer finds a whole one, so this client hands over bytes as soon
    as they arrive: it blocks on the port (pyserial's select) in slices of at most
    ``drivers.serial_link.POLL_SLICE_S`` and returns what has come.
    A reply is then taken the moment its last byte is in.
    """

    def __init__(self, port: str, *, link: ModbusLink, baudrate: int, timeout: float) -> None:
        super().__init__(port, baudrate=baudrate, timeout=timeout, retries=0)
        self.link = link
        self.framer = self.transaction.framer = _TrailingRTUFramer()

    def _wait_for_data(self) -> int:  # pymodbus 3.16 private hook (pinned): same rule, plus the cancel check
        size, more = 0, False
        deadline = time.monotonic() + self.comm_params.timeout_connect
        while time.monotonic() <= deadline:
            self.link._check_cancel()
            available = self._in_waiting()
            if more and available == size:
                break
            if available and available != size:
                more, size = True, available
            time.sleep(self._recv_interval)
        return size

    def recv(self, size: int | None) -> bytes:
        if size is not None or not self.socket:
            return super().recv(size)
        port = self.socket
        deadline = self.link._deadline
        try:
            while not (waiting := port.in_waiting):
                self.link._check_cancel()
                if deadline.expired():
                    return b""
                set_slice_timeout(port, deadline.left())
                if first := port.read(1):  # blocks until a byte arrives or the slice ends
                    return first + port.read(port.in_waiting)
            return port.read(waiting)
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None


class _TcpClient(ModbusTcpClient):
    """TCP client whose receive wait ends when the link's deadline says so (pymodbus' own waits out its timeout
    on the wall clock in one select)."""

    def __init__(self, host: str, *, port: int, link: ModbusLink, timeout: float) -> None:
        super().__init__(host, port=port, timeout=timeout, retries=0)
        self.link = link
        self.connect_error: OSError | None = None  # why the last connection failed

    def connect(self) -> bool:
        """pymodbus' ``connect`` (3.16), keeping why a connection failed (``connect_error``) instead of logging it:
        a refused port, a host name that does not resolve and a silent address each get their own words."""
        if self.socket:
            return True
        params = self.comm_params
        try:
            self.socket = socket.create_connection((params.host, params.port), timeout=params.timeout_connect,
                                                   source_address=params.source_address)
            self.connect_error = None
        except OSError as exc:
            self.connect_error = exc
            self.close()
        return self.socket is not None

    def recv(self, size: int | None) -> bytes:
        sock = self.socket
        if size is not None or sock is None:
            return super().recv(size)
        deadline = self.link._deadline
        if sock.gettimeout() != 0.0:  # non-blocking from the first receive on (each setblocking is a system call)
            sock.setblocking(False)
        while True:
            ready, _, _ = select.select([sock], [], [], min(POLL_SLICE_S, deadline.left()))
            if ready:
                if not (data := sock.recv(4096)):
                    return self._handle_abrupt_socket_close(size, [], 0.0)
                return data
            if deadline.expired():
                return b""

    def exchange(self, request: ModbusPDU) -> ModbusPDU:
        """One attempt of ``request`` as pymodbus' ``sync_execute`` makes it with no retries, without its layers
        (lock, trace hooks, local echo, logging): the frame its framer builds, numbered by its transaction counter,
        sent as its ``send`` does; then bytes received until its framer takes a reply for this unit and id (others
        skipped, as there). The same bytes on the wire and the same exceptions: ModbusIOException when no reply
        came (or one pymodbus cannot decode), ConnectionException when the link is lost. For the requests a device
        sends many of (the T7's stream-out packets: ~20 per second of rig time)."""
        if not self.connect():
            raise ConnectionException(f"Failed to connect[{self!s}]")
        tx = self.transaction
        request.transaction_id = tid = tx.getNextTID()
        dev_id = request.dev_id
        self.send(self.framer.buildFrame(request))
        buffer = b""
        end = time.monotonic() + self.comm_params.timeout_connect
        while True:
            if not (data := self.recv(None)):
                raise ModbusIOException("no reply", function_code=request.function_code, transaction_id=tid,
                                        dev_id=dev_id)
            buffer += data
            if (reply := self._whole_reply(buffer, dev_id, tid, request.function_code)) is not None:
                break
            used, reply = self.framer.handleFrame(buffer, dev_id, tid)
            buffer = buffer[used:]
            if reply is not None:
                break
            if time.monotonic() >= end:
                raise ModbusIOException("no whole reply", function_code=request.function_code, transaction_id=tid,
                                        dev_id=dev_id)
        if reply.dev_id != dev_id or reply.transaction_id != tid:  # a reply numbered 0 passes the framer
            raise ModbusIOException(f"reply from unit {reply.dev_id} with id {reply.transaction_id}",
                                    function_code=request.function_code, transaction_id=tid, dev_id=dev_id)
        return reply


    def _whole_reply(self, buffer: bytes, dev_id: int, tid: int, function_code: int) -> ModbusPDU | None:
        """The reply in ``buffer`` when it is exactly one whole MBAP frame (protocol 0) from this unit with this id
        and the request's function code, decoded as pymodbus' framer would (the decoder's class for that code, no
        sub-function), without its framer's passes and debug formatting; None for anything else (an exception
        reply, a frame cut short or followed by more, another unit or id), which the framer then handles."""
        if len(buffer) < 8 or buffer[2:4] != b"\0\0" or buffer[6] != dev_id or buffer[7] != function_code \
                or len(buffer) != 6 + int.from_bytes(buffer[4:6], "big") or int.from_bytes(buffer[:2], "big") != tid:
            return None
        decoder = self.framer.decoder
        entry = decoder.pdu_table.get(function_code)
        if entry is None or (cls := entry[decoder.pdu_inx]) is None:
            return None
        try:
            pdu = cls()
            pdu.decode(buffer[8:])
        except Exception:  # the framer decides what a frame its decoder refuses is
            return None
        if pdu.sub_function_code >= 0:  # a sub-function's own class: the decoder's lookup
            return None
        pdu.dev_id, pdu.transaction_id = dev_id, tid
        return pdu


def _connect_failure(exc: OSError | None) -> str:
    """Why a TCP connection could not be made, in a few words."""
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused (nothing listening there)"
    if isinstance(exc, socket.gaierror):
        return f"host name not found ({exc.strerror})"
    if isinstance(exc, TimeoutError):
        return "no answer (connection timed out)"
    if exc is None:
        return "connection failed"
    return exc.strerror or str(exc)


class ModbusLink:
    """One Modbus client; serialises requests from every module on the bus."""

    def __init__(self, url: str, device: str, *, baudrate: int = 19200, timeout: float = 0.5,
                 retries: int = 1, poll_interval: float | None = None, cancel: CancelToken | None = None,
                 timer: ReplyTimer = WALL, wire: bool = True, gateway_baud: int | None = None) -> None:
        """``poll_interval``: how often the RTU client polls for reply bytes (pymodbus default: 4 character
        times, at least 1 ms). Twins on a pty answer at once, so simulated rigs use a shorter one.
        ``retries``: further attempts after a timeout (each checks ``cancel`` first).
        ``timer``: how a wait for a reply ends (:mod:`drivers.deadline`).
        ``wire``: whether RTU frames take their wire time at ``baudrate`` (False: a simulated line at pty speed).
        ``gateway_baud``: on TCP, the baud rate of the RS-485 line behind a Modbus TCP/RTU gateway (8N1), whose
        frames' wire time a reply's stamp leaves out (None: a device on Ethernet itself, as the T7).
        ``retrying`` (attribute, None by default): called before each retry of an unanswered request, with this
        link's lock held — work that must not wait out the retry on another link (the engine feeds the set-point
        module's keep-alive there); never a request on this link."""
        self.url = url
        self.device = device
        self.retries = retries
        self.cancel = cancel
        self.timer = timer
        self.retrying: Callable[[], None] | None = None
        self.wire = wire
        self.gateway_baud = gateway_baud
        self._reply_frame = 0  # bytes of the last reply's RTU frame (address, PDU, CRC): on the port or gateway line
        # the clock a reply's arrival is noted on (the drivers' own, set by whoever builds them; None: the caller's
        # time of asking stands for it), and the last reply's arrival on it: a retry's late reply that wins is
        # followed by a wait for the line to go quiet, which must not make the reading look that much later
        self.clock: Callable[[], float] | None = None
        self._arrived: float | None = None
        self._timeout = timeout
        self._deadline: Deadline = timer.start(timeout)  # the present attempt's (set before each request)
        self.lock = threading.RLock()
        self._stale = False  # RTU: an earlier attempt went unanswered, its reply may still come
        self.open_failure = ""  # why the last open() could not connect
        self._cancellable = True  # False during the first attempt of an always_send request
        self._heard: dict[int, float] = {}  # unit → time.monotonic() when its last answered request was sent
        self._gap: dict[int, float] = {}  # unit → longest time between two answered requests since last asked
        self._asked: dict[int, float] = {}  # unit → when longest_silence was last asked (silences count from there)
        self._client: _SerialClient | _TcpClient
        if url.startswith("tcp://"):
            host, _, port = url[len("tcp://"):].rpartition(":")
            if not host or not port.isdigit():
                raise ValueError(f"{device}: Modbus TCP address must be tcp://host:port, got {url!r}")
            self._client = _TcpClient(host, port=int(port), link=self, timeout=timer.bound(timeout))
        else:
            self._client = _SerialClient(url, link=self, baudrate=baudrate, timeout=timer.bound(timeout))
            if poll_interval is not None:
                self._client._recv_interval = poll_interval  # pymodbus 3.16 attribute (pinned)

    @property
    def timeout(self) -> float:
        """Reply timeout of one attempt [s]."""
        return self._timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._timeout = value
        self._client.comm_params.timeout_connect = self.timer.bound(value)  # pymodbus' connect and receive loop

    @property
    def is_open(self) -> bool:
        """Whether the client holds an open connection."""
        return bool(self._client.connected)

    def open(self) -> None:
        """Connect (RTU: open the port; TCP: connect the socket); ``open_failure`` says why it could not."""
        if self._client.connect():
            if isinstance(self._client, _SerialClient):
                warn_usb_latency(self.url, self.device)
            return
        if isinstance(self._client, _TcpClient):
            self.open_failure = _connect_failure(self._client.connect_error)
            raise InstrumentConnectionError(self.device, f"cannot connect to {self.url}: {self.open_failure}")
        self.open_failure = "no such device" if not os.path.exists(self.url) else "connection refused or port busy"
        raise InstrumentConnectionError(self.device, f"cannot open Modbus link {self.url}: {self.open_failure}")

    def close(self) -> None:
        """Close the connection (idempotent)."""
        self._client.close()

    # ------------------------------------------------------------------ transactions
    def _discard_input(self, what: str) -> None:
        client = self._client
        if isinstance(client, _SerialClient) and client.socket is not None:
            try:
                client.socket.reset_input_buffer()
            except PORT_ERRORS:
                client.close()
                raise InstrumentConnectionError(self.device, f"Modbus link {self.url} lost during {what}") \
                    from None
            cast(_TrailingRTUFramer, client.framer).trailing = b""  # the RTU client's framer (set in __init__)
        client.transaction.sent_buffer = b""  # pymodbus' local-echo and receive buffers (3.16)
        client.transaction.recv_buffer = b""

    def _check_cancel(self) -> None:
        if self._cancellable:
            check(self.cancel, self.device)

    def _call(self, what: str, unit: int, request: ModbusPDU, always_send: bool = False,
              retry: bool = True) -> ModbusPDU:
        """Run one request with our retries (none unless ``retry``); returns the checked reply."""
        attempts = self.retries + 1 if retry else 1
        client = self._client
        run = client.exchange if isinstance(client, _TcpClient) else lambda pdu: client.execute(False, pdu)
        with self.lock:
            for attempt in range(attempts):
                if attempt and self.retrying is not None:
                    self.retrying()
                self._cancellable = bool(attempt) or not always_send
                self._check_cancel()
                self._discard_input(what)
                self.timer.sending()
                self._deadline = self.timer.start(self._timeout)
                sent = time.monotonic()
                try:
                    resp = run(request)
                    self._arrived = self.clock() if self.clock is not None else None
                    if isinstance(client, _SerialClient):
                        resp = self._latest_reply(resp, unit, what)
                except ModbusIOException:
                    self._stale = True
                    continue
                except OperationCancelledError:
                    self._stale = True
                    raise
                except (ConnectionException, OSError):  # pymodbus 3.16 lets ECONNRESET through on receive
                    self._client.close()
                    raise InstrumentConnectionError(self.device, f"Modbus link {self.url} lost during {what}") \
                        from None
                except ModbusException as exc:
                    self._stale = True
                    raise ProtocolError(self.device, f"{what} on unit {unit}: {exc}") from None
                if (prev := self._heard.get(unit)) is not None:
                    gap = sent - max(prev, self._asked.get(unit, prev))
                    if gap > self._gap.get(unit, 0.0):
                        self._gap[unit] = gap
                self._heard[unit] = sent  # any reply, an exception reply too: the unit received the request
                try:
                    self._check_reply(what, unit, request, resp)
                except ProtocolError:
                    self._stale = True
                    raise
                self._reply_frame = len(_RTU_SIZE.buildFrame(resp))
                return resp
        tries = f" ({attempts} attempts)" if attempts > 1 else ""
        raise InstrumentTimeoutError(self.device, f"no valid reply from unit {unit} to {what} on {self.url}{tries}"
                                    f"{self._deadline.detail}")

    def _latest_reply(self, resp: ModbusPDU, unit: int, what: str) -> ModbusPDU:
        """RTU: after a timeout, wait one timeout for the line to go quiet; a later whole frame wins."""
        client = self._client
        assert isinstance(client, _SerialClient) and client.socket is not None
        framer = cast(_TrailingRTUFramer, client.framer)  # the RTU client's framer (set in _SerialClient)
        extra, framer.trailing = framer.trailing, b""
        if not self._stale and not extra:
            return resp
        deadline = time.monotonic() + self.timeout
        read_at = self._arrived  # when the bytes in ``extra`` came (the first reply's own, at first)
        while True:
            while extra:
                used, later = framer.handleFrame(extra, unit, 0)
                if later is None:
                    if used >= len(extra):
                        raise ProtocolError(self.device, f"garbled bytes after the reply to {what} "
                                            f"from unit {unit}")
                    break  # incomplete: wait for the rest
                resp, extra, framer.trailing = later, framer.trailing, b""
                self._arrived = read_at  # a later whole frame wins: its arrival, not the end of this wait
            if time.monotonic() >= deadline:
                break
            self._check_cancel()
            waiting = client.socket.in_waiting
            if waiting:
                extra += client.socket.read(waiting)
                read_at = self.clock() if self.clock is not None else None
            else:
                time.sleep(min(0.005, max(deadline - time.monotonic(), 0.0)))
        if extra:
            raise ProtocolError(self.device, f"incomplete frame after the reply to {what} from unit {unit}")
        self._stale = False
        return resp

    def _check_reply(self, what: str, unit: int, request: ModbusPDU, resp: ModbusPDU) -> None:
        """The reply answers this request (function code, device, transaction id, echo) or ProtocolError."""
        fc, rfc = request.function_code, resp.function_code
        if rfc & 0x7F != fc:
            raise ProtocolError(self.device, f"unit {unit} answered {what} (function {fc}) with function {rfc}")
        if resp.dev_id != unit:
            raise ProtocolError(self.device, f"reply to {what} came from unit {resp.dev_id}, asked unit {unit}")
        if resp.transaction_id != request.transaction_id:
            raise ProtocolError(self.device, f"reply to {what} has transaction id {resp.transaction_id}, "
                                f"sent {request.transaction_id}")
        if isinstance(resp, ExceptionResponse) or rfc & 0x80:
            code = getattr(resp, "exception_code", 0)
            raise InstrumentStateError(self.device, f"unit {unit} refused {what}: Modbus exception {code} "
                                       f"({EXCEPTION_TEXT.get(code, 'unknown')})")
        if fc in (3, 4):
            n = len(resp.registers or [])
            if n != request.count:
                kind = "holding" if fc == 3 else "input"
                raise ProtocolError(self.device, f"unit {unit} returned {n} {kind} registers, {request.count} asked")
        elif fc == 6:
            echo = (resp.address, list(resp.registers[:1]))
            if echo != (request.address, list(request.registers)):
                raise ProtocolError(self.device, f"unit {unit} echoed {echo[0]}={echo[1]} to {what}")
        elif fc == 16 and (resp.address, resp.count) != (request.address, request.count):
            raise ProtocolError(self.device, f"unit {unit} echoed {resp.address}+{resp.count} to {what}")

    def reply_wire_s(self) -> float:
        """Wire time [s] of the last reply's RTU frame at the port's baud rate and framing (pymodbus' serial
        settings: 8N1 unless set otherwise), or on a gateway's RS-485 line (``gateway_baud``, 8N1); 0 on TCP to a
        device on Ethernet, and where the link has no wire time (``wire=False``)."""
        client = self._client
        if not self.wire:
            return 0.0
        if isinstance(client, _TcpClient):
            return wire_time(self._reply_frame, self.gateway_baud) if self.gateway_baud else 0.0
        p = client.comm_params
        if not p.baudrate:
            return 0.0
        return wire_time(self._reply_frame, p.baudrate, char_bits(p.bytesize or 8, p.parity or "N", p.stopbits or 1))

    def reply_started(self, arrived: float) -> float:
        """When the last reply started: its arrival less its wire time (:meth:`reply_wire_s`) — when the device put
        its reading on the wire. The arrival is the one the link noted on :attr:`clock` when the reply that
        answered came (after a retry, the late reply's, not the end of the wait for the line to go quiet); without
        a clock, ``arrived`` (the caller's time now). Call it with the link's lock held since the request (another
        module's request on the bus would replace it)."""
        return (self._arrived if self._arrived is not None else arrived) - self.reply_wire_s()

    def heard_at(self, unit: int) -> float | None:
        """``time.monotonic()`` at which the last request that ``unit`` answered was sent (None: none yet).

        A module's communication watchdog counts from the last request it received, which is no earlier than
        this: ``time.monotonic() − heard_at`` bounds from above how long the module has gone unheard."""
        return self._heard.get(unit)

    def longest_silence(self, unit: int) -> float:
        """The longest time [s] ``unit`` went without a request from this link since the last call (the present
        silence included; an upper bound, from send times), and start counting again: a module's watchdog may
        have fired in a silence longer than its period, even if requests have reached it since."""
        with self.lock:
            now = time.monotonic()
            last = self._heard.get(unit)
            ongoing = now - max(last, self._asked.get(unit, last)) if last is not None else 0.0
            self._asked[unit] = now
            return max(self._gap.pop(unit, 0.0), ongoing)

    def register(self, pdu: type[ModbusPDU]) -> None:
        """Teach the client a device's own function code (its reply is decoded by ``pdu``)."""
        self._client.register(pdu)

    def execute(self, unit: int, request: ModbusPDU, *, retry: bool = True, always_send: bool = False) -> ModbusPDU:
        """Run a request of a function taught by :meth:`register`, with the link's reply checks (function code,
        device, transaction id; an exception reply is an :class:`InstrumentStateError`) and its retries — none
        with ``retry=False``, for a request that must not take effect twice (values appended to a device's
        buffer: after a timeout the device may have taken them, and a second attempt would append them again).
        ``always_send``: as for :meth:`write_register`."""
        request.dev_id = unit
        return self._call(f"function {request.function_code}", unit, request, always_send, retry)

    def read_holding(self, unit: int, address: int, count: int = 1) -> list[int]:
        """FC3 read of ``count`` holding registers at 0-based ``address``."""
        req = ReadHoldingRegistersRequest(address=address, count=count, dev_id=unit)
        return list(self._call(f"read holding {address}+{count}", unit, req).registers)

    def read_input(self, unit: int, address: int, count: int = 1) -> list[int]:
        """FC4 read of ``count`` input registers at 0-based ``address``."""
        req = ReadInputRegistersRequest(address=address, count=count, dev_id=unit)
        return list(self._call(f"read input {address}+{count}", unit, req).registers)

    def write_register(self, unit: int, address: int, value: int, *, always_send: bool = False) -> None:
        """FC6 write of one holding register.

        ``always_send``: the first attempt goes out and waits for its echo (one timeout at most) even when a
        stop has been requested — a command that makes the rig safe; retries still check the stop request.
        """
        req = WriteSingleRegisterRequest(address=address, registers=[value], dev_id=unit)
        self._call(f"write register {address}={value}", unit, req, always_send)

    def write_registers(self, unit: int, address: int, values: list[int], *, always_send: bool = False) -> None:
        """FC16 write of consecutive holding registers (``always_send``: as for :meth:`write_register`)."""
        req = WriteMultipleRegistersRequest(address=address, registers=values, dev_id=unit)
        self._call(f"write registers {address}+{len(values)}", unit, req, always_send)
