"""The T7 twin's register set against LabJack's published map (issue 23 item 3).

Expected names, addresses, types, access, defaults and error codes come from ``tests/data/ljm_constants_t7.json``,
a verbatim extract of LabJack's ``ljm_constants.json`` (source and commit in the file), never from the twin.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
import struct
from pathlib import Path

import pytest
from pymodbus.constants import ExcCodes

from bench.core.clock import VirtualClock
from bench.core.plant import HVStage, Plant
from bench.models.membrane import MembraneParams
from sim_devices.labjack_t7 import MODBUS_PORT, STREAM_PORT, LabJackT7Sim
from sim_devices.t7.registers import NOT_IN_MAP, REGISTERS

MAP = json.loads((Path(__file__).parent / "data" / "ljm_constants_t7.json").read_text(encoding="utf-8"))
SIZE = {"UINT16": 1, "UINT32": 2, "INT32": 2, "FLOAT32": 2}


def _expanded() -> dict[int, dict[str, object]]:
    """The map's T7 registers by address, ``NAME#(a:b)SUFFIX`` expanded as LJM does (address + index × size)."""
    out: dict[int, dict[str, object]] = {}
    for r in MAP["registers"]:
        m = re.fullmatch(r"(.*)#\((\d+):(\d+)\)(.*)", r["name"])
        names = [(r["name"], 0)] if m is None else [
            (f"{m[1]}{i}{m[4]}", i - int(m[2])) for i in range(int(m[2]), int(m[3]) + 1)]
        for name, k in names:
            a = r["address"] + SIZE[r["type"]] * k
            out[a] = {"name": name, "type": r["type"], "access": r["readwrite"], "default": r.get("default")}
    return out


EXPANDED = _expanded()
ERRORS = {e["string"]: e["error"] for e in MAP["errors"]}
BY_NAME = {str(v["name"]): a for a, v in EXPANDED.items()}


def _sim() -> LabJackT7Sim:
    """A twin without noise: these tests compare exact register values (the ADC noise: tests/test_t7_noise.py)."""
    clock = VirtualClock()
    return LabJackT7Sim(Plant(clock, MembraneParams(), hv=HVStage()), clock, noise=False)


def _read(sim: LabJackT7Sim, address: int, count: int) -> list[int] | ExcCodes:
    regs = [0] * count
    rc = asyncio.run(sim.action(3, address, address, count, regs, None))
    return rc if rc else regs


def _write(sim: LabJackT7Sim, address: int, words: list[int]) -> ExcCodes | None:
    return asyncio.run(sim.action(16, address, address, len(words), [], words))


def _f32(words: list[int]) -> float:
    return float(struct.unpack(">f", struct.pack(">HH", *words))[0])


def _u32(words: list[int]) -> int:
    return words[0] << 16 | words[1]


def test_every_served_register_has_the_maps_name_type_and_access() -> None:
    served = {a: r for a, r in REGISTERS.items() if a not in NOT_IN_MAP}
    wrong = [(a, r.name, r.kind, r.access, EXPANDED.get(a)) for a, r in served.items()
             if EXPANDED.get(a) is None or (EXPANDED[a]["name"], EXPANDED[a]["type"], EXPANDED[a]["access"])
             != (r.name, r.kind, r.access)]
    assert not wrong, wrong


@pytest.mark.parametrize("name", ["AIN14", "AIN15", "TEST", "TEST_UINT16", "TEST_UINT32", "TEST_INT32",
                                  "TEST_FLOAT32", "BOOTLOADER_VERSION", "AIN_ALL_RANGE", "CORE_TIMER", "FIO_STATE",
                                  "EIO_STATE", "CIO_STATE", "MIO_STATE", "FIO_DIRECTION", "DIO_STATE",
                                  "DIO_DIRECTION", "FIO0", "MIO2", "INTERNAL_FLASH_READ_POINTER"])
def test_the_registers_issue_23_names_are_served(name: str) -> None:
    assert BY_NAME[name] in REGISTERS


def test_every_served_address_answers_as_its_access_says() -> None:
    """Readable registers read; a read of a write-only one and a write to a read-only one are illegal-address
    exceptions that leave LJME_MBE2_ILLEGAL_DATA_ADDRESS in LAST_ERR_DETAIL."""
    sim = _sim()
    code = ERRORS["LJME_MBE2_ILLEGAL_DATA_ADDRESS"]
    for a, reg in EXPANDED.items():
        if a not in REGISTERS:
            continue
        n = SIZE[str(reg["type"])]
        got = _read(sim, a, n)
        if "R" in str(reg["access"]):
            assert not isinstance(got, ExcCodes), (reg["name"], got)
        else:
            assert got == ExcCodes.ILLEGAL_ADDRESS, reg["name"]
        if reg["access"] == "R" and reg["name"] != "AIN0":
            assert _write(sim, a, [0] * n) == ExcCodes.ILLEGAL_ADDRESS, reg["name"]
            assert _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1) == [code], reg["name"]


def test_an_address_the_map_lacks_is_an_illegal_address_with_last_err_detail() -> None:
    sim = _sim()
    assert 1500 not in EXPANDED
    assert _read(sim, 1500, 2) == ExcCodes.ILLEGAL_ADDRESS
    assert _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1) == [ERRORS["LJME_MBE2_ILLEGAL_DATA_ADDRESS"]]


def test_stream_out_buffer_status_is_read_only_and_flash_pointer_read_write() -> None:
    sim = _sim()
    assert _write(sim, BY_NAME["STREAM_OUT0_BUFFER_STATUS"], [0, 0]) == ExcCodes.ILLEGAL_ADDRESS
    assert _write(sim, BY_NAME["INTERNAL_FLASH_READ_POINTER"], [0x003C, 0x4000]) is None
    assert _read(sim, BY_NAME["INTERNAL_FLASH_READ_POINTER"], 2) == [0x003C, 0x4000]


def test_test_registers_as_labjacks_test_script_expects() -> None:
    """TEST reads 0x00112233 and one word of it from either address; TEST_* start at the map's defaults and keep
    what is written."""
    sim = _sim()
    t = BY_NAME["TEST"]
    assert _read(sim, t, 2) == [0x0011, 0x2233]
    assert _read(sim, t + 1, 1) == [0x2233]
    assert _read(sim, t, 1) == [0x0011]
    assert _read(sim, BY_NAME["TEST_UINT16"], 1) == [EXPANDED[BY_NAME["TEST_UINT16"]]["default"]]
    assert _u32(_read(sim, BY_NAME["TEST_UINT32"], 2)) == EXPANDED[BY_NAME["TEST_UINT32"]]["default"]  # type: ignore[arg-type]
    i32 = _u32(_read(sim, BY_NAME["TEST_INT32"], 2))  # type: ignore[arg-type]
    assert i32 - (1 << 32) == EXPANDED[BY_NAME["TEST_INT32"]]["default"]
    assert _f32(_read(sim, BY_NAME["TEST_FLOAT32"], 2)) == EXPANDED[BY_NAME["TEST_FLOAT32"]]["default"]  # type: ignore[arg-type]
    assert _write(sim, BY_NAME["TEST_INT32"], [0xFFFF, 0xFFFE]) is None
    assert _read(sim, BY_NAME["TEST_INT32"], 2) == [0xFFFF, 0xFFFE]
    assert _write(sim, BY_NAME["TEST_FLOAT32"], list(struct.unpack(">HH", struct.pack(">f", 1.5)))) is None
    assert _f32(_read(sim, BY_NAME["TEST_FLOAT32"], 2)) == 1.5  # type: ignore[arg-type]
    assert _write(sim, t, [0, 0]) == ExcCodes.ILLEGAL_ADDRESS  # TEST itself is read-only


def test_ain14_reads_the_internal_temperature_and_ain15_ground() -> None:
    """[E] LabJack's getNominalCalibration: temperature K = −92.379·V + 465.129; the twin's device sits at 25 °C
    (its stated assumption)."""
    sim = _sim()
    volts = _f32(_read(sim, BY_NAME["AIN14"], 2))  # type: ignore[arg-type]
    assert -92.379 * volts + 465.129 == pytest.approx(298.15, abs=1e-3)
    assert _f32(_read(sim, BY_NAME["AIN15"], 2)) == 0.0  # type: ignore[arg-type]


def test_ain_all_range_sets_every_range_and_reads_minus_9999_when_they_differ() -> None:
    sim = _sim()
    one = list(struct.unpack(">HH", struct.pack(">f", 1.0)))
    assert _write(sim, BY_NAME["AIN_ALL_RANGE"], one) is None
    assert all(_f32(_read(sim, BY_NAME[f"AIN{i}_RANGE"], 2)) == 1.0 for i in range(16))  # type: ignore[arg-type]
    assert _f32(_read(sim, BY_NAME["AIN_ALL_RANGE"], 2)) == 1.0  # type: ignore[arg-type]
    assert _write(sim, BY_NAME["AIN3_RANGE"], list(struct.unpack(">HH", struct.pack(">f", 0.1)))) is None
    assert _f32(_read(sim, BY_NAME["AIN_ALL_RANGE"], 2)) == -9999.0  # type: ignore[arg-type]


def test_a_range_or_resolution_the_t7_lacks_is_refused_with_its_error_code() -> None:
    """AIN#_RANGE takes 10, 1, 0.1, 0.01 (map); AIN#_RESOLUTION_INDEX 0–8 on a T7 that is no Pro: otherwise
    LAST_ERR_DETAIL names AIN_RANGE_INVALID / AIN_RESOLUTION_INVALID, and the setting is unchanged."""
    sim = _sim()
    assert _write(sim, BY_NAME["AIN2_RANGE"], list(struct.unpack(">HH", struct.pack(">f", 3.0)))) is not None
    assert _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1) == [ERRORS["AIN_RANGE_INVALID"]]
    assert _f32(_read(sim, BY_NAME["AIN2_RANGE"], 2)) == 10.0  # type: ignore[arg-type]
    assert _write(sim, BY_NAME["AIN2_RESOLUTION_INDEX"], [9]) is not None
    assert _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1) == [ERRORS["AIN_RESOLUTION_INVALID"]]


def test_core_timer_counts_at_half_the_80_mhz_core_clock() -> None:
    clock = VirtualClock()
    sim = LabJackT7Sim(Plant(clock, MembraneParams(), hv=HVStage()), clock)
    t0 = _u32(_read(sim, BY_NAME["CORE_TIMER"], 2))  # type: ignore[arg-type]
    clock.advance(0.05)
    t1 = _u32(_read(sim, BY_NAME["CORE_TIMER"], 2))  # type: ignore[arg-type]
    assert t1 - t0 == pytest.approx(0.05 * 80e6 / 2, abs=1)


def test_dio_lines_state_and_direction_as_the_map_describes() -> None:
    """FIO# write: output at that level; FIO# read: input; _STATE does not configure direction; a port's upper
    byte inhibits. Unconnected inputs read 1 (the twin's stated assumption)."""
    sim = _sim()
    fio_state, fio_dir = BY_NAME["FIO_STATE"], BY_NAME["FIO_DIRECTION"]
    assert _read(sim, fio_dir, 1) == [0] and _read(sim, fio_state, 1) == [0xFF]
    assert _write(sim, BY_NAME["FIO2"], [0]) is None
    assert _read(sim, fio_dir, 1) == [0b100] and _read(sim, fio_state, 1) == [0xFB]
    assert _read(sim, BY_NAME["FIO2"], 1) == [1]  # a read makes it an input again
    assert _read(sim, fio_dir, 1) == [0]
    assert _write(sim, fio_dir, [0x0F]) is None  # FIO0–3 outputs, latches 0
    assert _write(sim, fio_state, [0x0200 | 0x00]) is None  # FIO1 inhibited: its latch unchanged
    assert _read(sim, fio_state, 1) == [0xF0]
    assert _write(sim, fio_state, [0x0F]) is None
    assert _read(sim, fio_state, 1) == [0xFF] and _read(sim, fio_dir, 1) == [0x0F]
    assert _u32(_read(sim, BY_NAME["DIO_STATE"], 2)) == (1 << 23) - 1  # type: ignore[arg-type]
    assert _write(sim, BY_NAME["DIO_DIRECTION"], [0x0070, 0x0000]) is None  # MIO0–2 outputs (DIO 20–22)
    assert _read(sim, BY_NAME["MIO_DIRECTION"], 1) == [0b111] and _read(sim, fio_dir, 1) == [0]


def test_the_t7s_own_ports_are_502_and_702() -> None:
    """STREAM_AUTO_TARGET bit 0 in the map: "Send to Ethernet 702 sockets"; Modbus TCP: 502."""
    target = next(r for r in MAP["registers"] if r["name"] == "STREAM_AUTO_TARGET")
    assert "702" in target["description"]
    assert (MODBUS_PORT, STREAM_PORT) == (502, 702)


def test_the_twin_serves_on_the_ports_it_is_given() -> None:
    """The option's wiring, on ports an unprivileged test can bind (502/702 need root or CAP_NET_BIND_SERVICE)."""
    with socket.socket() as a, socket.socket() as b:
        a.bind(("127.0.0.1", 0))
        b.bind(("127.0.0.1", 0))
        free = a.getsockname()[1], b.getsockname()[1]
    sim = _sim()
    try:
        assert sim.start(port=free[0], stream_port=free[1]) == free
        with socket.create_connection(("127.0.0.1", free[0]), timeout=2) as s:
            s.sendall(bytes.fromhex("0001 0000 0006 01 03 d73c 0002"))  # FC3, TEST (55100), 2 registers
            reply = s.recv(64)
        assert reply[7] == 3 and reply[9:13] == bytes.fromhex("00112233")
        socket.create_connection(("127.0.0.1", free[1]), timeout=2).close()
    finally:
        sim.stop()


def test_a_port_the_twin_cannot_bind_is_a_one_line_error() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        sim = _sim()
        try:
            with pytest.raises(RuntimeError, match=f"Modbus port {taken}"):
                sim.start(port=taken)
        finally:
            sim.stop()


def _u32w(v: int) -> list[int]:
    return [v >> 16 & 0xFFFF, v & 0xFFFF]


def _f32w(v: float) -> list[int]:
    return list(struct.unpack(">HH", struct.pack(">f", v)))


def _start(sim: LabJackT7Sim, *, rate: float, scanlist: list[int], res: int = 0, settle: float = 0.0) -> int:
    """Configure a spontaneous stream and enable it: 0, or the LAST_ERR_DETAIL of the refusal."""
    for name, words in (("STREAM_SCANRATE_HZ", _f32w(rate)), ("STREAM_NUM_ADDRESSES", _u32w(len(scanlist))),
                        ("STREAM_SAMPLES_PER_PACKET", _u32w(8)), ("STREAM_AUTO_TARGET", _u32w(1)),
                        ("STREAM_RESOLUTION_INDEX", _u32w(res)), ("STREAM_SETTLING_US", _f32w(settle))):
        assert _write(sim, BY_NAME[name], words) is None, name
    for i, a in enumerate(scanlist):
        assert _write(sim, BY_NAME[f"STREAM_SCANLIST_ADDRESS{i}"], _u32w(a)) is None
    rc = _write(sim, BY_NAME["STREAM_ENABLE"], _u32w(1))
    if rc is None:
        assert _write(sim, BY_NAME["STREAM_ENABLE"], _u32w(0)) is None
        return 0
    assert rc == ExcCodes.DEVICE_FAILURE
    got = _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1)
    assert isinstance(got, list)
    return got[0]


def test_stream_resolution_index_above_8_is_refused_as_the_map_says() -> None:
    """STREAM_RESOLUTION_INDEX: "Valid values: 0-8"; error 2606 "Stream resolution can not be greater than 8"."""
    sim = _sim()
    ain0, ain1 = BY_NAME["AIN0"], BY_NAME["AIN1"]
    assert _start(sim, rate=100, scanlist=[ain0, ain1], res=8) == 0  # 200 S/s: within index 8's rate
    assert _start(sim, rate=100, scanlist=[ain0, ain1], res=9) == ERRORS["STREAM_CONFIG_INVALID"]


def test_stream_settling_beyond_4400_us_or_beyond_the_scan_period_is_refused() -> None:
    """STREAM_SETTLING_US: "Max is 4400" (2621 STREAM_SETTLING_INVALID); it applies between a scan's channels, not
    before the first: 3 channels at 1000 scans/s leave 1000 µs for 2 settlings (the twin's stated rule)."""
    sim = _sim()
    three = [BY_NAME["AIN0"], BY_NAME["AIN1"], BY_NAME["AIN2"]]
    assert _start(sim, rate=10, scanlist=three, settle=4401) == ERRORS["STREAM_SETTLING_INVALID"]
    assert _start(sim, rate=10, scanlist=three, settle=4400) == 0
    assert _start(sim, rate=1000, scanlist=three, settle=499) == 0
    assert _start(sim, rate=1000, scanlist=three, settle=500) == ERRORS["STREAM_SCAN_RATE_INVALID"]
    assert _start(sim, rate=1000, scanlist=three, settle=0) == 0  # automatic settling


def test_the_temperature_sensor_streams_at_most_250_hz() -> None:
    """Error 2631: "Temperature sensor do not work properly when sampled above 250Hz"."""
    sim = _sim()
    assert _start(sim, rate=250, scanlist=[BY_NAME["AIN14"]]) == 0
    assert _start(sim, rate=500, scanlist=[BY_NAME["AIN14"]]) == ERRORS["STREAM_RATE_INVALID_FOR_TEMPERATURE_SENSOR"]


def test_a_watchdog_write_while_enabled_is_refused_with_swdt_enabled() -> None:
    """WATCHDOG_ENABLE_DEFAULT: "The watchdog must be disabled before writing any of the other watchdog registers";
    error 2671 SWDT_ENABLED."""
    sim = _sim()
    assert _write(sim, BY_NAME["WATCHDOG_ENABLE_DEFAULT"], _u32w(1)) is None
    assert _write(sim, BY_NAME["WATCHDOG_TIMEOUT_S_DEFAULT"], _u32w(5)) == ExcCodes.DEVICE_FAILURE
    assert _read(sim, BY_NAME["LAST_ERR_DETAIL"], 1) == [ERRORS["SWDT_ENABLED"]]


def test_input_noise_is_seeded_and_a_twin_built_without_noise_reads_exact_values() -> None:
    """A wired input with noise: the same seed gives the same samples; ``noise=False`` (the rig's [sim] noise
    option) gives the noiseless gain·observable + offset."""
    from sim_devices.labjack_t7 import Signal

    def reads(noise: bool, seed: int) -> list[float]:
        clock = VirtualClock()
        sim = LabJackT7Sim(Plant(clock, MembraneParams(), hv=HVStage()), clock, seed=seed, noise=noise,
                           signals={0: Signal("voltage", 1.0, 0.5, noise=0.01)})
        return [_f32(_read(sim, BY_NAME["AIN0"], 2)) for _ in range(20)]  # type: ignore[arg-type]

    assert reads(False, 1) == [0.5] * 20  # the plant at rest: 0 V at the amplifier output
    noisy = reads(True, 1)
    assert noisy == reads(True, 1) and noisy != reads(True, 2)
    assert len(set(noisy)) > 1
