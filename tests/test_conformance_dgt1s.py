"""Dini Argeo DGT1S twin against the manuals: RTU frames written out literally.

Sources: DGT4X/DGT1S manuals — input registers 30001–30002 gross, 30003–30004 net (absolute, in divisions,
MSW first), 30005 status (bit 1 gross negative, bit 2 stable, bit 5 tare active), 30006 command status
(high byte last command, low nibble processed-command counter), 30111–30114 µV per channel; holding 40001
command (01h zero, 02h tare, 03h preset tare), 40002–40003 parameter 1 (example: preset tare 1000 =
00 00 03 E8); Modbus Application Protocol v1.1b3 §6.4 (FC4), §6.12 (FC16), §7 (exception 03).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.test_conformance_adam import Bus, h

G = 9.80665


@pytest.fixture
def scale() -> Iterator[Bus]:
    b = Bus("lsdea-motor-sim.toml")  # DGT1S unit 1 on bus "scale"
    b.sim.clock.advance(0.5)  # type: ignore[attr-defined]
    yield b
    b.close()


def regs(reply: bytes) -> list[int]:
    n = reply[2] // 2
    return [int.from_bytes(reply[3 + 2 * i:5 + 2 * i], "big") for i in range(n)]


def test_weight_block_and_microvolts_follow_the_load(scale: Bus) -> None:
    r = scale.xfer("01 04 00 00 00 07 B1 C8", 19, bus="scale")
    assert r[:3] == h("01 04 0E")
    gross_hi, gross_lo, net_hi, net_lo, status, _, _ = regs(r)
    kg = scale.sim.twins["load_cell"].raw_kg  # type: ignore[attr-defined]
    assert (gross_hi << 16 | gross_lo) == round(abs(kg) / 0.001)  # 1-g divisions of the rig file
    assert (net_hi << 16 | net_lo) == (gross_hi << 16 | gross_lo)  # no tare yet
    assert bool(status & 0x02) == (kg < 0)
    uv = scale.xfer("01 04 00 6E 00 01 50 17", 7, bus="scale")
    signed = int.from_bytes(uv[3:5], "big", signed=True)
    # 30111 = load / capacity × 2 mV/V × 5 V [assumed cell]; capacity 5 kg in the rig file
    assert signed == round(kg / 5.0 * 10_000)
    assert abs(kg) > 0.01  # a loaded cell (the LS-DEA pulls on it): the µV register is not 0


def test_zero_command_bumps_the_processed_counter(scale: Bus) -> None:
    before = regs(scale.xfer("01 04 00 05 00 01 21 CB", 7, bus="scale"))[0]
    assert scale.xfer("01 06 00 00 00 02 08 0B", 8, bus="scale") == h("01 06 00 00 00 02 08 0B")  # tare
    after = regs(scale.xfer("01 04 00 05 00 01 21 CB", 7, bus="scale"))[0]
    assert after >> 8 == 0x02 and after & 0x0F == (before + 1) & 0x0F
    status = regs(scale.xfer("01 04 00 00 00 07 B1 C8", 19, bus="scale"))[4]
    assert status & 0x20  # tare active


def test_preset_tare_with_the_manual_example_parameter(scale: Bus) -> None:
    # parameter 1 = 1000 → 00 00 03 E8 (manual example), then command 03h
    assert scale.xfer("01 10 00 01 00 02 04 00 00 03 E8 32 DD", 8, bus="scale") == h("01 10 00 01 00 02 10 08")
    assert scale.xfer("01 06 00 00 00 03 C9 CB", 8, bus="scale") == h("01 06 00 00 00 03 C9 CB")
    _, _, net_hi, net_lo, *_ = regs(scale.xfer("01 04 00 00 00 07 B1 C8", 19, bus="scale"))
    kg = scale.sim.twins["load_cell"].gross()  # type: ignore[attr-defined]
    assert (net_hi << 16 | net_lo) == round(abs(kg - 1.0) / 0.001)  # net = gross − 1000 divisions


def test_unknown_command_and_absent_unit(scale: Bus) -> None:
    assert scale.xfer("01 06 00 00 00 63 C9 E3", 5, bus="scale") == h("01 86 03 02 61")
    assert scale.xfer("07 03 00 00 00 01 84 6C", bus="scale") == b""
