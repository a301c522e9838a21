"""Byte-exact protocol tests of the Keyence LK-G driver (request bytes → reply bytes)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from drivers.errors import InstrumentStateError, InstrumentTimeoutError, ProtocolError
from drivers.keyence import KeyenceLKG, format_value, parse_value
from drivers.serial_link import SerialLink
from tests.protocol_expect import expected_protocol


def laser(url: str, model: str = "LK-G3000", **kw: object) -> KeyenceLKG:
    k = KeyenceLKG(SerialLink(url, "laser", timeout=0.05), model=model, clock=lambda: 12.5, **kw)  # type: ignore[arg-type]
    k.link.open()
    return k


@pytest.mark.parametrize("mm, field", [(1.2345, "+01.2345"), (-0.012, "-00.0120"), (0.0, "+00.0000"),
                                       (39.99994, "+39.9999"), (-12.5, "-12.5000")])
def test_value_format_round_trip(mm: float, field: str) -> None:
    assert format_value(mm) == field
    assert parse_value(field, "laser") == (pytest.approx(round(mm, 4)), "ok")


def test_value_format_special_fields() -> None:
    assert format_value(None, "over_range_positive") == "+FFFFFFF"
    assert format_value(None, "over_range_negative") == "-FFFFFFF"
    assert format_value(None, "invalid") == "XXXXXXXX"
    assert format_value(123456.0) == "+FFFFFFF"  # does not fit 7 characters
    assert parse_value("+FFFFFFF", "laser")[1] == "over_range_positive"
    assert parse_value("-FFFFFFF", "laser")[1] == "over_range_negative"
    assert math.isnan(parse_value("XXXXXXXX", "laser")[0])
    assert parse_value("+1234.56", "laser")[0] == 1234.56  # manual p. 5-6 example
    with pytest.raises(ProtocolError, match="8 characters"):
        parse_value("+1.2", "laser")
    with pytest.raises(ProtocolError, match="no sign"):
        parse_value("01.23456", "laser")


def test_single_read_lk_g3000() -> None:
    with expected_protocol("kg3", [(b"M1\r", b"M1,+01.2345\r")]) as url:
        r = laser(url).read_displacement()
    assert r.value == pytest.approx(1.2345e-3) and r.unit == "m" and r.ok
    # stamped at the reply's start: its 12 characters (CR included) at 115,200 Bd, 8N1 (10 bits each), end at 12.5 s
    assert r.timestamp == pytest.approx(12.5 - 12 * 10 / 115200, abs=1e-12)


def test_single_read_stamped_at_the_reply_start_at_the_links_baud() -> None:
    """The same read at 9600 Bd: 12 characters × 10 bits = 12.5 ms of wire before the clock's 12.5 s (the manual's
    8N1, instruments.md §1.2; the line's end-of-reply is when the driver reads its clock)."""
    with expected_protocol("kg9", [(b"M1\r", b"M1,+01.2345\r")]) as url:
        k = KeyenceLKG(SerialLink(url, "laser", baudrate=9600, timeout=0.05), clock=lambda: 12.5)
        k.link.open()
        r = k.read_displacement()
    assert r.timestamp == pytest.approx(12.5 - 0.0125, abs=1e-12)


def test_single_read_lk_g5000() -> None:
    with expected_protocol("kg5", [(b"MS,01\r", b"MS,01,-00.0120\r")]) as url:
        r = laser(url, model="LK-G5000").read_displacement()
    assert r.value == pytest.approx(-12e-6)


def test_over_range_and_invalid_values() -> None:
    with expected_protocol("kor", [(b"M1\r", b"M1,+FFFFFFF\r"), (b"M1\r", b"M1,XXXXXXXX\r")]) as url:
        k = laser(url)
        over = k.read_displacement()
        invalid = k.read_displacement()
    assert over.status == "over_range_positive" and math.isnan(over.value) and not over.ok
    assert invalid.status == "invalid"


def test_error_reply_names_the_code() -> None:
    with expected_protocol("ker", [(b"M1\r", b"ER,M1,01\r")]) as url:
        with pytest.raises(InstrumentStateError, match=r"laser: 'M1' refused: ER 01 \(status error"):
            laser(url).read_displacement()
    with expected_protocol("ker5", [(b"MS,01\r", b"ER,MS,62\r")]) as url:
        with pytest.raises(InstrumentStateError, match="parameter range error"):
            laser(url, model="LK-G5000").read_displacement()


def test_garbled_and_missing_replies() -> None:
    with expected_protocol("kgb", [(b"M1\r", b"N1,+01.2345\r")]) as url:
        with pytest.raises(ProtocolError, match="does not echo"):
            laser(url).read_displacement()
    with expected_protocol("kna", [(b"M1\r", b"M1,+01.2\xff45\r")]) as url:
        with pytest.raises(ProtocolError, match="not ASCII"):
            laser(url).read_displacement()
    with expected_protocol("kto", [(b"M1\r", None)]) as url:
        with pytest.raises(InstrumentTimeoutError, match="laser: no reply"):
            laser(url).read_displacement()
    with expected_protocol("kpart", [(b"M1\r", b"M1,+01.23")]) as url:
        with pytest.raises(InstrumentTimeoutError, match="partial reply"):
            laser(url).read_displacement()


def test_connect_leaves_communication_mode_and_probes() -> None:
    with expected_protocol("kcon", [(b"R0\r", b"ER,R0,01\r"), (b"M1\r", b"M1,+00.0000\r")]) as url:
        k = KeyenceLKG(SerialLink(url, "laser", timeout=0.05))
        k.connect()


def test_sampling_setting_enters_and_leaves_communication_mode() -> None:
    with expected_protocol("ksam", [(b"Q0\r", b"Q0\r"), (b"SW,CA,3\r", b"SW,CA\r"), (b"R0\r", b"R0\r")]) as url:
        laser(url).set_sampling(200)
    with pytest.raises(ValueError, match="sampling cycle"):
        KeyenceLKG(SerialLink("expect://none", "laser")).set_sampling(300)


def test_storage_start_fetch_stop() -> None:
    start = [(b"Q0\r", b"Q0\r"), (b"SW,CA,2\r", b"SW,CA\r"), (b"SW,EB,0\r", b"SW,EB\r"),
             (b"SW,EC,+065536\r", b"SW,EC\r"), (b"R0\r", b"R0\r"), (b"AQ\r", b"AQ\r"), (b"AS\r", b"AS\r")]
    fetch = [(b"AN\r", b"AN,1,3\r"), (b"AO,1,0,3\r", b"AO,+01.0000,+01.0001,XXXXXXXX\r"),
             (b"AN\r", b"AN,1,4\r"), (b"AO,1,3,1\r", b"AO,-00.5000\r"), (b"AP\r", b"AP\r")]
    with expected_protocol("kst", start + fetch) as url:
        k = laser(url)
        assert k.start_buffer(1e-4) == pytest.approx(1e-4)
        b1 = k.fetch_buffer()
        b2 = k.fetch_buffer()
        k.stop_buffer()
    assert b1.first_index == 0 and b2.first_index == 3
    assert np.allclose(b1.values[:2], [1e-3, 1.0001e-3]) and list(b1.valid) == [True, True, False]
    assert b2.values[0] == pytest.approx(-0.5e-3)
    # the storage's time base starts at the AS reply's start: 3 characters (A, S, CR) of 10 bits at the link's
    # 115,200 Bd (8N1, instruments.md §1.2) before the clock's 12.5 s; the fourth point 3 intervals later
    assert np.allclose(b2.times(), [12.5 - 3 * 10 / 115200 + 3e-4], rtol=0, atol=1e-12)


def test_storage_interval_choice() -> None:
    assert KeyenceLKG.storage_setting(1e-4) == (100, 1)
    assert KeyenceLKG.storage_setting(1e-3) == (1000, 1)
    assert KeyenceLKG.storage_setting(5e-3) == (1000, 5)
    assert KeyenceLKG.storage_setting(2e-5) == (20, 1)


def test_storage_upload_count_mismatch_is_a_protocol_error() -> None:
    with expected_protocol("kcnt", [(b"AN\r", b"AN,0,2\r"), (b"AO,1,0,2\r", b"AO,+01.0000\r")]) as url:
        with pytest.raises(ProtocolError, match="AO returned 1 values, 2 requested"):
            laser(url).fetch_buffer()


@pytest.mark.parametrize("field", ["+nan    ", "-INF    ", "+inf.000", "+1e999  ", "+1.2e+03", "+ 1.2345", "+12F4.56",
                                   "+1.2.345", "+0012345"])
def test_non_manual_value_fields_are_protocol_errors(field: str) -> None:
    # manual p. 5-6: sign + 7 characters with one decimal point; only ±FFFFFFF and XXXXXXXX are special
    with pytest.raises(ProtocolError, match="laser: measured value"):
        parse_value(field, "laser")
    with expected_protocol("knan", [(b"M1\r", b"M1," + field.encode() + b"\r")]) as url:
        with pytest.raises(ProtocolError, match=re.escape(repr(field))):
            laser(url).read_displacement()


@pytest.mark.parametrize("reply, bad", [
    (b"AO,+01.0000,+nan    ,+01.0002\r", r"'\+nan    ' is not a number .*field 2 of 3"),
    (b"AO,+01.0000,+01.0001,+1.0\r", r"'\+1.0' is not 8 characters .*field 3 of 3"),
    (b"AO,+01.0000,-INF    ,+01.0002\r", "field 2 of 3")])
def test_bulk_values_that_are_not_manual_fields_are_named(reply: bytes, bad: str) -> None:
    with expected_protocol("kbulk", [(b"AN\r", b"AN,1,3\r"), (b"AO,1,0,3\r", reply)]) as url:
        k = laser(url)
        with pytest.raises(ProtocolError, match=bad):
            k.fetch_buffer()
    assert k._fetched == 0  # nothing consumed: the next fetch asks for the same points again


def test_fetch_is_bounded_per_call_and_indices_stay_contiguous() -> None:
    script = [(b"AN\r", b"AN,1,5\r"), (b"AO,1,0,2\r", b"AO,+01.0000,+01.0001\r"),
              (b"AN\r", b"AN,1,6\r"), (b"AO,1,2,2\r", b"AO,+01.0002,XXXXXXXX\r"),
              (b"AN\r", b"AN,0,6\r"), (b"AO,1,4,2\r", b"AO,+01.0004,+01.0005\r"),
              (b"AN\r", b"AN,0,6\r")]
    with expected_protocol("kpart2", script) as url:
        k = laser(url, max_fetch_points=2)
        k._t0, k._dt = 12.5, 1e-4
        blocks = []
        for pending in (3, 2, 0, 0):
            blocks.append(k.fetch_buffer())
            assert k.pending == pending
    assert [b.first_index for b in blocks] == [0, 2, 4, 6]
    assert [b.values.size for b in blocks] == [2, 2, 2, 0]
    times = np.concatenate([b.times() for b in blocks])
    assert np.allclose(times, 12.5 + 1e-4 * np.arange(6))
    values = np.concatenate([b.values for b in blocks])
    valid = np.concatenate([b.valid for b in blocks])
    assert list(valid) == [True, True, True, False, True, True]
    assert np.allclose(values[valid], 1e-3 * np.array([1.0, 1.0001, 1.0002, 1.0004, 1.0005]))


def test_upload_requests_fit_the_wire_budget_at_the_baud_rate() -> None:
    k = KeyenceLKG(SerialLink("expect://none", "laser", baudrate=115200))
    assert k.upload_chunk() == 256  # 0.2 s × 11520 bytes/s / 9 bytes per value
    assert KeyenceLKG(SerialLink("expect://none", "laser", baudrate=9600)).upload_chunk() == 21
    assert KeyenceLKG(SerialLink("expect://none", "laser", baudrate=10_000_000)).upload_chunk() == 1000
