"""The loopback relay in front of Modbus TCP twins: a device's own (``local``) answers keep the requests' order."""

from __future__ import annotations

import asyncio
import struct

from sim_devices.transport import Faults, SocketRelay


def _adu(tid: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, 1 + len(pdu), 1) + pdu


async def _exchange(requests: list[bytes], faults: Faults | None = None) -> list[bytes]:
    """Send ``requests`` back to back (no waiting) through a relay whose server answers FC3 after 0.2 s and
    whose local handler answers function 76 at once; returns the replies in the order they arrived."""

    async def slow_server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while True:
            head = await reader.readexactly(6)
            body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
            await asyncio.sleep(0.2)
            writer.write(_adu(int.from_bytes(head[:2], "big"), bytes([body[1], 2, 0x12, 0x34])))
            await writer.drain()

    def local(adu: bytes) -> bytes | None:
        return _adu(int.from_bytes(adu[:2], "big"), bytes([76])) if adu[7] == 76 else None

    server = await asyncio.start_server(slow_server, "127.0.0.1", 0)
    relay = await SocketRelay("test", server.sockets[0].getsockname()[:2], faults, framing="mbap",
                              local=local).start()
    reader, writer = await asyncio.open_connection(*relay.address)
    try:
        for r in requests:
            writer.write(r)
            await writer.drain()
            await asyncio.sleep(0.02)  # separate reads at the relay
        out = []
        for _ in requests:
            head = await asyncio.wait_for(reader.readexactly(6), 2.0)
            out.append(head + await reader.readexactly(int.from_bytes(head[4:6], "big")))
        return out
    finally:
        writer.close()
        await relay.close()
        server.close()


def test_a_local_answer_waits_its_turn_behind_a_request_the_server_has_not_answered() -> None:
    fc3, mbfb = _adu(1, bytes.fromhex("03 ea60 0002")), _adu(2, bytes.fromhex("4c 00 ea60 02"))
    replies = asyncio.run(_exchange([fc3, mbfb]))
    # in the requests' order: the MBFB packet went on to the server, which answered it after the FC3
    assert replies == [_adu(1, bytes.fromhex("03 02 1234")), _adu(2, bytes.fromhex("4c 02 1234"))]
    assert asyncio.run(_exchange([mbfb])) == [_adu(2, bytes([76]))]  # alone, the relay answers it itself


def test_a_local_answer_goes_through_the_links_faults() -> None:
    faults = Faults()
    faults.garble_next, faults.garble_index = 1, 7  # the function code of the next reply
    reply = asyncio.run(_exchange([_adu(3, bytes.fromhex("4c 00 ea60 02"))], faults))[0]
    assert reply[7] == 76 ^ 0x5A and faults.counts["garble"] == 1


class _Writer:
    """A client's writer as :meth:`SocketRelay._answer_now` uses it: what it was given, nothing buffered."""

    def __init__(self) -> None:
        self.written: list[bytes] = []
        self.transport = self

    def get_write_buffer_size(self) -> int:
        return 0

    def write(self, data: bytes) -> None:
        self.written.append(data)


def test_a_latency_switched_on_while_a_local_reply_is_made_holds_that_reply_back() -> None:
    """Another thread switching on a latency between the relay's look at the faults and the reply's passage through
    them (here: inside ``local``, which runs between the two) counted the reply as delayed but wrote it at once —
    a virtual-time driver's timer then gives up on a reply already on the wire (found in review). Now the faults
    decide once, and the reply they delay is written by a task after its delay."""
    from sim_devices.transport import _Conn

    faults = Faults()
    mbfb = _adu(5, bytes.fromhex("4c 00 ea60 02"))
    reply = _adu(5, bytes([76]))

    def local(adu: bytes) -> bytes:
        faults.latency = 0.01  # as another thread would, while the reply is made
        return reply

    async def answer() -> tuple[bool, list[bytes], list[bytes]]:
        relay = SocketRelay("test", ("127.0.0.1", 1), faults, framing="mbap", local=local)
        writer, conn = _Writer(), _Conn()
        answered = relay._answer_now(writer, conn, mbfb)  # type: ignore[arg-type]  # the writer's two methods
        at_once = list(writer.written)
        await asyncio.gather(*asyncio.all_tasks() - {asyncio.current_task()})  # what the relay left to do
        return answered, at_once, writer.written

    answered, at_once, written = asyncio.run(answer())
    assert answered and faults.delayed == 1 and faults.last_latency == 0.01
    assert at_once == []  # held back, as counted
    assert written == [reply]  # and sent once its delay was over

    # and it keeps its place: the next request, answered once the latency is off again, does not overtake it
    assert asyncio.run(_held_then_next()) == [_adu(1, bytes([76])), _adu(2, bytes([76]))]


async def _held_then_next() -> list[bytes]:
    """Two MBFB requests through a relay whose ``local`` switches a latency on while it makes the first reply and
    off while it makes the second (the second sent once the first was made); the replies in their order."""
    faults = Faults()
    calls: list[int] = []

    def local(adu: bytes) -> bytes:
        calls.append(int.from_bytes(adu[:2], "big"))
        faults.latency = 0.5 if len(calls) == 1 else 0.0
        return _adu(calls[-1], bytes([76]))

    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read()  # a server that answers nothing: a request passed on to it would never be answered

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    relay = await SocketRelay("test", server.sockets[0].getsockname()[:2], faults, framing="mbap",
                              local=local).start()
    reader, writer = await asyncio.open_connection(*relay.address)
    try:
        while not relay._conns:  # the relay has its upstream: from now on a request is offered to _answer_now
            await asyncio.sleep(0.001)
        writer.write(_adu(1, bytes.fromhex("4c 00 ea60 02")))
        await writer.drain()
        while not calls:  # the first reply made (and held back): then the second request
            await asyncio.sleep(0.001)
        writer.write(_adu(2, bytes.fromhex("4c 00 ea60 02")))
        await writer.drain()
        out = []
        for _ in range(2):
            head = await asyncio.wait_for(reader.readexactly(6), 30.0)
            out.append(head + await reader.readexactly(int.from_bytes(head[4:6], "big")))
        assert calls == [1, 2] and faults.delayed == 1
        return out
    finally:
        writer.close()
        await relay.close()
        server.close()
