"""ADAM-4024 / ADAM-4017+ twins on an RS-485 line against the manuals: RTU frames written out literally.

Sources: ADAM-4000 manual appendix G, ADAM-4024 Modbus table p. G-7 (40001–40004 output, 40211/40212 module
name, 40215 comm-safety enable, 40216 comm-safety flag) and the ADAM-4017+ table (40211/40212 = 4017h, 5000h);
Modbus Application Protocol v1.1b3 §6.3/§6.6 (FC3/FC6 frames), §7 (exceptions 01/02/03); Modbus over Serial
Line v1.02 §2.1 (broadcast: no reply), §2.4.1/§2.5.1.2 (other address or CRC error: the slave stays silent),
§2.5.1.1 (3.5-character silence). CRCs are part of the literal frames (checked once against the spec's CRC).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import serial

from bench.rig import RigConfig, load_rig
from bench.runtime.sim_rig import SimRig
from tests.conftest import RIGS


def crc_ok(frame: bytes) -> bool:
    """Serial Line v1.02 §6.2.2 CRC (A001h), to guard the literal frames against typing errors."""
    crc = 0xFFFF
    for b in frame[:-2]:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return frame[-2:] == crc.to_bytes(2, "little")


class Bus:
    def __init__(self, name: str, timing: str = "none", watchdog: float | None = 1.0) -> None:
        rig = load_rig(RIGS / name)
        data = rig.model_dump()
        data["simulation"] = {**data["simulation"], "modbus_transport": "rtu"}
        if data.get("amplifier"):
            data["amplifier"] = {**data["amplifier"], "comm_watchdog_s": watchdog}
        self.sim = SimRig(RigConfig.model_validate(data), virtual=True, timing=timing)  # type: ignore[arg-type]
        self.sim.start()
        self.ports = {k: serial.Serial(v, timeout=0.15) for k, v in self.sim.port_map().items()
                      if k in ("io", "scale")}

    def xfer(self, frame: str, expect: int = 256, bus: str = "io") -> bytes:
        raw = bytes.fromhex(frame)
        assert crc_ok(raw), f"typing error in {frame}"
        port = self.ports[bus]
        port.reset_input_buffer()
        port.write(raw)
        return port.read(expect)

    def close(self) -> None:
        for p in self.ports.values():
            p.close()
        self.sim.stop()


@pytest.fixture
def bus() -> Iterator[Bus]:
    b = Bus("thesis-sim.toml")  # ADAM-4024 unit 1, ADAM-4017+ unit 2 on bus "io", watchdog 1 s
    yield b
    b.close()


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def test_module_names(bus: Bus) -> None:
    assert bus.xfer("01 03 00 D2 00 02 64 32", 9) == h("01 03 04 40 24 00 00 AF F8")  # 40211/40212 ADAM-4024
    assert bus.xfer("02 03 00 D2 00 02 64 01", 9) == h("02 03 04 40 17 50 00 50 F7")  # ADAM-4017+ ("P")


def test_output_write_echo_and_read_back(bus: Bus) -> None:
    assert bus.xfer("01 06 00 00 0C 00 8C CA", 8) == h("01 06 00 00 0C 00 8C CA")  # FC6 echo
    assert bus.xfer("01 03 00 00 00 01 84 0A", 7) == h("01 03 02 0C 00 BD 44")


def test_comm_safety_registers_reflect_the_watchdog(bus: Bus) -> None:
    assert bus.xfer("01 03 00 D6 00 02 25 F3", 9) == h("01 03 04 00 01 00 00 AB F3")  # enabled, not fired
    bus.xfer("01 06 00 00 0C 00 8C CA", 8)
    bus.sim.clock.advance(1.5)  # type: ignore[attr-defined]  # silence longer than the 1-s period
    assert bus.xfer("01 03 00 D6 00 02 25 F3", 9) == h("01 03 04 00 01 00 01 6A 33")  # flag 40216 = 1
    # 40001 reads back the safe value: 0 V = 0800h in the 12-bit offset-binary format [assumed format]
    assert bus.xfer("01 03 00 00 00 01 84 0A", 7) == h("01 03 02 08 00 BF 84")
    assert bus.sim.plant.observe().v_out[0] == 0.0  # the true output (the monitor reads it with its offset)
    assert bus.xfer("01 06 00 D7 00 00 39 F2", 8) == h("01 06 00 D7 00 00 39 F2")  # clear the flag [assumed]
    assert bus.xfer("01 03 00 D6 00 02 25 F3", 9) == h("01 03 04 00 01 00 00 AB F3")


def test_watchdog_off_reads_zero_in_40215() -> None:
    b = Bus("thesis-sim.toml", watchdog=None)
    try:
        assert b.xfer("01 03 00 D6 00 02 25 F3", 9)[3:7] == h("00 00 00 00")
    finally:
        b.close()


def test_exception_replies(bus: Bus) -> None:
    assert bus.xfer("01 07 41 E2", 5) == h("01 87 01 82 30")  # FC7 not supported: illegal function
    assert bus.xfer("01 03 00 63 00 01 74 14", 5) == h("01 83 02 C0 F1")  # 40100 not mapped: illegal address
    assert bus.xfer("01 06 00 00 10 00 84 0A", 5) == h("01 86 03 02 61")  # 1000h > 12-bit code: illegal value
    assert bus.xfer("01 06 00 D2 12 34 24 84", 5) == h("01 86 02 C3 A1")  # module name is read-only
    assert bus.xfer("01 05 00 00 FF 00 8C 3A", 5) == h("01 85 02 C3 51")  # emergency-DI flags read-only


def test_absent_unit_bad_crc_and_broadcast_are_silent(bus: Bus) -> None:
    assert bus.xfer("07 03 00 00 00 01 84 6C") == b""  # no unit 7 on the line: silence, not exception 04
    bad = bytes.fromhex("01 03 00 00 00 01 84 0B")
    bus.ports["io"].write(bad)
    assert bus.ports["io"].read(7) == b""  # CRC error: ignored
    assert bus.xfer("00 06 00 00 08 00 8F DB") == b""  # broadcast write: executed, no reply
    assert bus.xfer("01 03 00 00 00 01 84 0A", 7) == h("01 03 02 08 00 BF 84")  # …and it was executed


def test_a_transaction_takes_its_wire_time_at_19200_bd() -> None:
    b = Bus("thesis-sim.toml", timing="real")
    try:
        clock = b.sim.clock
        t0 = clock.now()
        assert b.xfer("01 03 00 D2 00 02 64 32", 9) == h("01 03 04 40 24 00 00 AF F8")
        char = 10 / 19200  # 8N1
        # request 8 + reply 9 characters, the 3.5-character silence that ends the request, 1 ms turnaround
        # [assumed]; the reply's own end-of-frame silence delays the next request
        once = 17 * char + 3.5 * char + 1e-3
        assert clock.now() - t0 == pytest.approx(once, abs=1e-9)
        b.xfer("01 03 00 D2 00 02 64 32", 9)
        assert clock.now() - t0 == pytest.approx(2 * once + 3.5 * char, abs=1e-9)
    finally:
        b.close()
