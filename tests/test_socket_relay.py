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
