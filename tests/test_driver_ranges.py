"""Out-of-range readings and absurd identity registers: a named driver error or a not-ok reading, never "ok".

Replies are written out byte by byte (or rewritten on their way from the T7 twin); the expected limits come
from the wire formats and datasheets, not from the drivers:

* LinMot default response: ActualPosition int32 in 0.1 µm (LinRS manual) → the register's ends are
  ±(2^31 − 1) × 0.1 µm = ±214.7483647 m;
* T7: T-Series Datasheet App. A-3 Table A.3-1, typical input range −10.5 … +10.1 V at gain 1 (±10 V range);
  FLOAT32's largest value 3.4028235e38; PRODUCT_ID of a T7 is 7;
* DGT1S: weight as an absolute count of divisions, 32-bit, MSW first (DGT4X/DGT1S manual); a 6-digit display
  shows at most 999 999;
* Keyence AN reply: AN,<storing>,<count>; the storage setting SW,EC carries sign + 6 digits (≤ 999 999).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator

import pytest

from drivers.dini import DiniDGT1S
from drivers.errors import ImplausibleValueError, InstrumentError, InstrumentStateError
from drivers.keyence import KeyenceLKG
from drivers.linmot import LinMotDrive
from drivers.modbus_link import ModbusLink
from drivers.serial_link import SerialLink
from tests.protocol_expect import expected_protocol, rtu
from tests.test_labjack import Rig

POLL = bytes.fromhex("01 11 03 02 01 00 04")  # LinRS default-response request to drive 0x11
F32_MAX = 3.4028234663852886e38  # largest FLOAT32: bytes 7F 7F FF FF


def linmot_response(counts: int, status: int = 0x0C37, state: int = 0x08C0) -> bytes:
    """Default response: 01 11 0C 02 00 00 | comm 00 | status word | state var | position int32 LE | 04."""
    return bytes.fromhex("01 11 0C 02 00 00 00") + struct.pack("<HHi", status, state, counts) + b"\x04"


def linmot(url: str) -> LinMotDrive:
    return LinMotDrive(SerialLink(url, "motor", timeout=0.05), travel=(0.0, 0.095), poll_interval=0.0)


# ---------------------------------------------------------------------------- LinMot position
@pytest.mark.parametrize("counts, metres", [(2**31 - 1, 214.7483647), (-(2**31), -214.7483648),
                                            (12_000_000, 1.2)])  # 1.2 m: 1.1 m past a 95-mm travel
def test_a_linmot_position_no_slider_has_is_a_named_error(counts: int, metres: float) -> None:
    with expected_protocol("far", [(POLL, linmot_response(counts))]) as url:
        d = linmot(url)
        d.link.open()
        with pytest.raises(ImplausibleValueError, match=r"^motor: position .* is not a value it reports") as exc:
            d.read_position()
    assert exc.value.value == pytest.approx(metres) and exc.value.unit == "m"
    lo, hi = exc.value.valid
    assert lo <= 0.0 and 0.095 <= hi and not lo <= metres <= hi
    assert str(exc.value).count("\n") == 0


def test_a_linmot_position_just_past_the_travel_is_still_a_reading() -> None:
    # 100 mm on a 0 … 95 mm travel: an overshoot the supervisor judges, not a garbled register
    with expected_protocol("near", [(POLL, linmot_response(1_000_000))]) as url:
        d = linmot(url)
        d.link.open()
        r = d.read_position()
    assert r.ok and r.value == pytest.approx(0.1)


def test_a_linmot_answering_connect_with_the_register_end_is_refused() -> None:
    with expected_protocol("conn", [(POLL, linmot_response(2**31 - 1))]) as url:
        with pytest.raises(ImplausibleValueError, match=r"^motor: position 214\.748"):
            linmot(url).connect()


def test_linmot_identity_and_status_from_a_garbled_state_are_no_traceback() -> None:
    # main state 0xFF is none of the manual's: named by number, not a KeyError
    script = [(POLL, linmot_response(0, state=0xFF00)), (POLL, linmot_response(0, state=0xFF00))]
    with expected_protocol("ident", script) as url:
        d = linmot(url)
        d.link.open()
        assert d.identify().details["state"] == "255"
        assert d.status().state == "state 255"


# ---------------------------------------------------------------------------- T7 (twin, replies rewritten)
def f32_reply(value: float, skip: int = 0) -> Callable[[bytes], bytes]:
    """Rewrite the data of the (skip+1)-th FC3 reply of two registers to FLOAT32 ``value``; others pass."""
    seen = [0]

    def mutate(reply: bytes) -> bytes:
        if len(reply) == 13 and reply[7] == 3 and reply[8] == 4:  # MBAP(7) | 03 | 04 | 4 data bytes
            seen[0] += 1
            if seen[0] == skip + 1:
                return reply[:9] + struct.pack(">f", value)
        return reply
    return mutate


@pytest.fixture
def t7() -> Iterator[Rig]:
    r = Rig()
    yield r
    r.close()


@pytest.mark.parametrize("value", [F32_MAX, -F32_MAX, -9999.0, math.inf, -math.inf, math.nan, 11.5, -12.0])
def test_a_t7_ain_value_its_converter_cannot_make_is_invalid(t7: Rig, value: float) -> None:
    t7.daq.connect()
    t7.sim.faults.mutate = f32_reply(value)
    r = t7.daq.read_ain(0)
    t7.sim.faults.mutate = None
    assert not r.ok and r.status == "invalid" and math.isnan(r.value)


@pytest.mark.parametrize("value", [-10.5, 10.1, 0.0])  # the datasheet's typical span at gain 1, and 0 V
def test_a_t7_ain_value_within_the_converter_span_is_a_reading(t7: Rig, value: float) -> None:
    t7.daq.connect()
    t7.sim.faults.mutate = f32_reply(value)
    r = t7.daq.read_ain(0)
    t7.sim.faults.mutate = None
    assert r.ok and r.value == pytest.approx(value, rel=1e-6)


def test_a_t7_ain_on_the_1_v_range_is_judged_by_that_range(t7: Rig) -> None:
    t7.daq.connect()
    t7.daq.configure_ain(0, 1.0)
    t7.sim.faults.mutate = f32_reply(5.0)  # fine on ±10 V, five times the ±1 V range
    r = t7.daq.read_ain(0)
    t7.sim.faults.mutate = None
    assert r.status == "invalid"


def test_trek_monitors_through_an_invalid_t7_input_are_invalid_not_huge(t7: Rig) -> None:
    from drivers.trek import TREK_MODELS
    from drivers.trek_daq import TrekOnDaq

    t7.daq.connect()
    amp = TrekOnDaq(t7.daq, TREK_MODELS["10/10B-HS"], max_voltage=8000.0, clock=t7.clock.now)
    t7.sim.faults.mutate = f32_reply(F32_MAX)  # the voltage monitor's read
    v, i = amp.read_monitors()
    t7.sim.faults.mutate = None
    assert (v.status, i.status) == ("invalid", "invalid") and math.isnan(v.value) and math.isnan(i.value)


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, -7.0, 0.0, F32_MAX, 4.0])
def test_an_absurd_t7_product_id_at_connect_is_one_named_line(t7: Rig, value: float) -> None:
    t7.sim.faults.mutate = f32_reply(value)  # the first read of connect: PRODUCT_ID
    with pytest.raises(InstrumentStateError) as exc:
        t7.daq.connect()
    t7.sim.faults.mutate = None
    text = str(exc.value)
    assert text.startswith("daq: PRODUCT_ID (register 60000) reads ") and "expected 7" in text
    assert f"{value:g}" in text and "\n" not in text


def test_a_t7_calibration_that_puts_codes_beyond_the_converter_is_refused_at_connect(t7: Rig) -> None:
    t7.sim.cal[2] = 1.0e6  # HS gain-0 Center: code 0 would read (1e6 − 0)·NSlope ≈ −316 V
    with pytest.raises(ImplausibleValueError, match=r"^daq: calibration: ±10 V range .* \(valid -11 … 11 V"):
        t7.daq.connect()


# ---------------------------------------------------------------------------- DGT1S and Keyence
def cell(url: str) -> DiniDGT1S:
    link = ModbusLink(url, "bus scale", timeout=0.05, retries=0)
    link.open()
    return DiniDGT1S(link, unit=1, division=0.001, clock=lambda: 3.0)


@pytest.mark.parametrize("count", [0xFFFFFFFF, 1_000_000])
def test_a_dgt1s_weight_beyond_its_display_is_a_named_error(count: int) -> None:
    regs = count.to_bytes(4, "big") * 2 + b"\x00\x04"  # gross = net = count, stable
    with expected_protocol("lcx", [(rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, regs))]) as url:
        with pytest.raises(ImplausibleValueError, match=rf"^load_cell: net weight {count} divisions .* 999999"):
            cell(url).read_force()


def test_a_dgt1s_weight_at_its_display_limit_is_a_reading() -> None:
    regs = (999_999).to_bytes(4, "big") * 2 + b"\x00\x04"
    with expected_protocol("lcm", [(rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, regs))]) as url:
        r = cell(url).read_force()
    assert r.ok and r.value == pytest.approx(999.999 * 9.80665)


@pytest.mark.parametrize("count", ["1000000", "99999999", "-5"])
def test_a_keyence_stored_count_beyond_its_storage_is_a_named_error(count: str) -> None:
    with expected_protocol("an", [(b"AN\r", f"AN,1,{count}\r".encode())]) as url:
        k = KeyenceLKG(SerialLink(url, "laser", timeout=0.05), clock=lambda: 0.0)
        k.link.open()
        with pytest.raises(ImplausibleValueError, match=rf"^laser: stored point count {count} points .* 999999"):
            k.buffer_status()


@pytest.mark.parametrize("reply", [b"PR,\xff\xfe\r", b"XX,01\r", b"PR\r"])
def test_a_garbled_keyence_identity_is_a_driver_error_or_a_plain_answer(reply: bytes) -> None:
    with expected_protocol("pr", [(b"PR\r", reply)]) as url:
        k = KeyenceLKG(SerialLink(url, "laser", timeout=0.05), clock=lambda: 0.0)
        k.link.open()
        try:
            ident = k.identify()
        except InstrumentError as exc:
            assert str(exc).startswith("laser: ")
        else:
            assert ident.details["program"] == "?"


@pytest.mark.parametrize("words", [b"\xff\xff\xff\xff", b"\x00\x00\x00\x00", b"\x40\x17\x50\x00"])
def test_a_garbled_adam_module_name_at_connect_is_a_driver_error(words: bytes) -> None:
    from drivers.adam import Adam4024

    with expected_protocol("adam", [(rtu(1, 3, b"\x00\xd2\x00\x02"), rtu(1, 3, 4, words))]) as url:
        link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
        link.open()
        with pytest.raises(InstrumentError, match=r"^ao: unit 1 is ADAM-\w+, expected ADAM-4024$"):
            Adam4024(link, 1).module_name()


def test_a_garbled_dgt1s_identity_is_a_plain_answer() -> None:
    script = [(rtu(1, 4, b"\x00\x04\x00\x02"), rtu(1, 4, 4, b"\xff\xff\xff\xff"))]
    with expected_protocol("dgid", script) as url:
        assert cell(url).identify().details["status"] == "0xffff"
