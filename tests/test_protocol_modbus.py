"""Byte-exact Modbus RTU tests of the TREK/ADAM amplifier driver and the DGT1S load-cell driver."""

from __future__ import annotations

import math

import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime.instruments import build_instruments
from bench.runtime.sim_rig import SimRig
from drivers.adam import Adam4017P, Adam4024, RawScale
from drivers.cancel import CancelToken
from drivers.dini import DiniDGT1S
from drivers.errors import InstrumentStateError, InstrumentTimeoutError, LimitError, OperationCancelledError
from drivers.modbus_link import ModbusLink
from drivers.trek import TrekAmplifier, TrekModel
from tests.conftest import RIGS
from tests.protocol_expect import expected_protocol, rtu


def amplifier(url: str, now: list[float]) -> TrekAmplifier:
    link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
    link.open()
    return TrekAmplifier(Adam4024(link, 1), Adam4017P(link, 2), max_voltage=8000, slew_limit=1e6,
                         clock=lambda: now[0])


def test_raw_scales() -> None:
    ao = RawScale(bits=12)
    assert (ao.to_raw(-10), ao.to_raw(0), ao.to_raw(10)) == (0, 2048, 4095)
    assert ao.to_volts(3071) == pytest.approx(5.0, abs=5e-3)
    ai = RawScale(bits=16, raw_format="twos")
    assert ai.to_raw(-10) == 0x8001 and ai.to_volts(0x7FFF) == pytest.approx(10.0)


def test_set_voltage_writes_the_ao_register() -> None:
    now = [0.0]
    script = [(rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x00")),  # zero: raw 2048
              (rtu(1, 6, b"\x00\x00\x0b\xff"), rtu(1, 6, b"\x00\x00\x0b\xff"))]  # 5 kV → 5 V → raw 3071
    with expected_protocol("ao", script) as url:
        amp = amplifier(url, now)
        amp.zero()
        now[0] = 1.0
        assert amp.set_voltage(5000.0) == pytest.approx(-10e3 + 3071 / 4095 * 20e3)  # the code's voltage


def test_limits_refuse_and_slew_clamps() -> None:
    now = [0.0]
    # zero = code 2048 = +2.44 V out; 1e6 V/s over 1 ms allows 1000 V more: 1002.44 V → 1.00244 V → code 2253
    script = [(rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x00")),
              (rtu(1, 6, b"\x00\x00\x08\xcd"), rtu(1, 6, b"\x00\x00\x08\xcd"))]
    with expected_protocol("slew", script) as url:
        amp = amplifier(url, now)
        amp.zero()
        with pytest.raises(LimitError, match="9000 V beyond the software limit ±8000 V"):
            amp.set_voltage(9000.0)
        now[0] = 1e-3
        assert amp.set_voltage(5000.0) == pytest.approx(1000.0, abs=5.0)  # 1 kV, to the nearest code


def adam_out(code: int) -> float:
    """ADAM-4024 datasheet: 12-bit offset binary over ±10 V, times the TREK's 1000 V/V."""
    return (-10.0 + code * 20.0 / 4095.0) * 1000.0


def test_a_set_point_at_the_limit_sends_the_nearest_code_within_it() -> None:
    """By hand, code = round((V/1000 + 10)/20 · 4095): 8 kV → 3685.5 → 3686 (8002.4 V, beyond 8 kV) → one code toward
    zero: 3685 (0x0E65); −8 kV → 409.5 → 410 (0x019A, −7997.6 V, within); 7 kV within ±7 kV → 3480.75 → 3481
    (7001.2 V, beyond) → 3480 (0x0D98)."""
    now = [0.0]
    script = [(rtu(1, 6, b"\x00\x00\x0e\x65"), rtu(1, 6, b"\x00\x00\x0e\x65")),
              (rtu(1, 6, b"\x00\x00\x01\x9a"), rtu(1, 6, b"\x00\x00\x01\x9a")),
              (rtu(1, 6, b"\x00\x00\x0d\x98"), rtu(1, 6, b"\x00\x00\x0d\x98"))]
    with expected_protocol("edge", script) as url:
        amp = amplifier(url, now)  # max_voltage 8000 V
        assert amp.quantise(8000.0) == pytest.approx(adam_out(3685), abs=1e-9)
        assert amp.quantise(7000.0) == pytest.approx(adam_out(3481), abs=1e-9)  # within ±8 kV: the nearest
        assert amp.quantise(7000.0, within=7000.0) == pytest.approx(adam_out(3480), abs=1e-9)
        assert amp.quantise(7000.0, within=9000.0) == pytest.approx(adam_out(3481), abs=1e-9)  # max_voltage caps
        assert amp.set_voltage(8000.0) == pytest.approx(adam_out(3685), abs=1e-9) and amp.commanded <= 8000.0
        now[0] = 1.0
        assert amp.set_voltage(-8000.0) == pytest.approx(adam_out(410), abs=1e-9)
        now[0] = 2.0
        assert amp.set_voltage(7000.0, within=7000.0) == pytest.approx(adam_out(3480), abs=1e-9)
        with pytest.raises(LimitError, match="no code of the analog output lies within ±1 V"):
            amp.quantise(0.0, within=1.0)  # 0 V has no code: ±2.44 V
        with pytest.raises(LimitError, match="8001 V beyond the software limit"):
            amp.quantise(8001.0)


def test_neighbouring_codes_of_both_raw_formats() -> None:
    off, twos = RawScale(bits=12), RawScale(bits=12, raw_format="twos")
    assert off.neighbours(0) == [0, 1] and off.neighbours(4095) == [4095, 4094] and off.neighbours(7) == [7, 6, 8]
    assert twos.neighbours(0) == [0, 0xFFFF, 1] and twos.neighbours(2047) == [2047, 2046]
    assert twos.neighbours(0xF801) == [0xF801, 0xF802]  # −2047, the range's end


def test_monitors_read_both_channels_in_one_request() -> None:
    # vmon 5 V (raw offset 16-bit) → 5 kV; imon −0.25 V → −0.25 mA
    v_raw = round((5.0 + 10) / 20 * 65535)
    i_raw = round((-0.25 + 10) / 20 * 65535)
    reply = rtu(2, 3, 4, v_raw.to_bytes(2, "big") + i_raw.to_bytes(2, "big"))
    with expected_protocol("ai", [(rtu(2, 3, b"\x00\x00\x00\x02"), reply)]) as url:
        v, i = amplifier(url, [0.0]).read_monitors()
    assert v.value == pytest.approx(5000.0, abs=0.2) and v.unit == "V"
    assert i.value == pytest.approx(-0.25e-3, abs=1e-7) and i.unit == "A"
    # both stamped at the reply's start: 1 + 1 + 1 + 4 + 2 = 9 characters × 10 bits at 19,200 Bd before 0 s
    assert v.timestamp == i.timestamp == pytest.approx(-9 * 10 / 19200, abs=1e-12)


def test_rtu_reply_stamp_follows_the_links_baud_and_parity() -> None:
    """An 8E1 link (11 bits a character: the Modbus serial default, Serial Line v1.02 §2.5.1) at 9600 Bd: the
    monitors' 9-character reply started 9 × 11 / 9600 s before the clock's 5 s."""
    v_raw = i_raw = 32768
    reply = rtu(2, 3, 4, v_raw.to_bytes(2, "big") + i_raw.to_bytes(2, "big"))
    with expected_protocol("ai8e1", [(rtu(2, 3, b"\x00\x00\x00\x02"), reply)]) as url:
        link = ModbusLink(url, "bus io", baudrate=9600, timeout=0.05, retries=0)
        link._client.comm_params.parity = "E"  # as a port opened 8E1 (pymodbus' own setting)
        link.open()
        amp = TrekAmplifier(Adam4024(link, 1), Adam4017P(link, 2), max_voltage=8000, clock=lambda: 5.0)
        v, i = amp.read_monitors()
    assert v.timestamp == i.timestamp == pytest.approx(5.0 - 9 * 11 / 9600, abs=1e-12)


def test_module_identity_and_exception_replies() -> None:
    script = [(rtu(1, 3, b"\x00\xd2\x00\x02"), rtu(1, 3, 4, b"\x40\x24\x00\x00")),
              (rtu(2, 3, b"\x00\xd2\x00\x02"), rtu(2, 3, 4, b"\x40\x17\x50\x00")),
              (rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 0x86, 4))]
    with expected_protocol("ident", script) as url:
        amp = amplifier(url, [0.0])
        ident = amp.identify()
        with pytest.raises(InstrumentStateError, match=r"unit 1 refused .* exception 4 \(device failure\)"):
            amp.zero()
    assert "ADAM-4024 unit 1" in str(ident) and "ADAM-4017P unit 2" in str(ident)


def test_wrong_module_and_bad_crc() -> None:
    with expected_protocol("wrong", [(rtu(1, 3, b"\x00\xd2\x00\x02"), rtu(1, 3, 4, b"\x40\x17\x50\x00"))]) as url:
        link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
        link.open()
        with pytest.raises(Exception, match="unit 1 is ADAM-4017P, expected ADAM-4024"):
            Adam4024(link, 1).module_name()
    good = rtu(2, 3, 4, b"\x80\x00\x80\x00")
    garbled = good[:-1] + bytes([good[-1] ^ 0xFF])
    with expected_protocol("crc", [(rtu(2, 3, b"\x00\x00\x00\x02"), garbled)]) as url:
        with pytest.raises(InstrumentTimeoutError, match="no valid reply from unit 2"):
            amplifier(url, [0.0]).read_monitors()


def cell(url: str) -> DiniDGT1S:
    link = ModbusLink(url, "bus scale", timeout=0.05, retries=0)
    link.open()
    return DiniDGT1S(link, unit=1, division=0.001, clock=lambda: 3.0, command_timeout=0.2)


def test_load_cell_read_signed_net_weight() -> None:
    # gross 350 g, net 125 g negative (bit0), stable (bit2), tare active (bit5)
    regs = b"\x00\x00\x01\x5e" + b"\x00\x00\x00\x7d" + b"\x00\x25"
    with expected_protocol("lc", [(rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, regs))]) as url:
        r = cell(url).read_force()
    assert r.value == pytest.approx(-0.125 * 9.80665) and r.unit == "N" and r.ok
    # stamped at the reply's start: address, function, byte count, 10 data bytes, CRC = 15 characters of 10 bits
    # (8N1) at pymodbus' default 19,200 Bd before the clock's 3.0 s (Modbus over Serial Line v1.02 §2.5.1)
    assert r.timestamp == pytest.approx(3.0 - 15 * 10 / 19200, abs=1e-12)


def test_load_cell_overload_and_unstable() -> None:
    over = b"\x00\x00\x13\x88" + b"\x00\x00\x13\x88" + b"\x00\x10"
    moving = b"\x00\x00\x00\x10" + b"\x00\x00\x00\x10" + b"\x00\x00"
    script = [(rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, over)),
              (rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, moving))]
    with expected_protocol("lco", script) as url:
        c = cell(url)
        assert c.read_force().status == "overload"
        r = c.read_force()
    assert r.status == "unstable" and r.value == pytest.approx(0.016 * 9.80665)


def test_tare_waits_for_the_processed_command_counter() -> None:
    script = [(rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x01\x03")),  # last cmd 1, counter 3
              (rtu(1, 6, b"\x00\x00\x00\x02"), rtu(1, 6, b"\x00\x00\x00\x02")),
              (rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x01\x03")),  # not yet processed
              (rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x02\x04"))]  # tare done, result 0
    with expected_protocol("tare", script) as url:
        cell(url).tare()


def test_zero_refused_reports_the_result() -> None:
    script = [(rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x00\x00")),
              (rtu(1, 6, b"\x00\x00\x00\x01"), rtu(1, 6, b"\x00\x00\x00\x01")),
              (rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x01\x21"))]  # result 2, counter 1
    with expected_protocol("zero", script) as url:
        with pytest.raises(InstrumentStateError, match="zero not executed: outside the zero range"):
            cell(url).zero()


def test_zero_and_safe_state_go_out_after_a_stop_request_but_set_points_do_not() -> None:
    token = CancelToken()
    script = [(rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x00")),  # safe_state: raw 2048
              (rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x00"))]  # zero
    with expected_protocol("zero-stop", script) as url:
        amp = amplifier(url, [0.0])
        amp.ao.link.cancel = token
        token.cancel("Ctrl-C")
        with pytest.raises(OperationCancelledError):
            amp.set_voltage(1000.0)  # nothing written
        amp.safe_state()
        amp.zero()
    assert amp.commanded == pytest.approx(20e3 * 2048 / 4095 - 10e3)


def test_non_finite_monitor_values_are_invalid(monkeypatch: pytest.MonkeyPatch) -> None:
    with expected_protocol("nf", []) as url:
        amp = amplifier(url, [0.0])
        monkeypatch.setattr(amp.ai, "read_volts", lambda first, n: [math.nan, math.inf])
        v, i = amp.read_monitors()
    assert (v.status, i.status) == ("invalid", "invalid") and not v.ok and not i.ok
    with pytest.raises(ValueError, match="vmon_ratio must be finite"):
        TrekAmplifier(amp.ao, amp.ai, trek=TrekModel("x", 10e3, 1e-3, vmon_ratio=math.inf))


def test_non_finite_force_is_invalid() -> None:
    regs = b"\x00\x00\x01\x5e" + b"\x00\x00\x00\x7d" + b"\x00\x04"
    with expected_protocol("lcnf", [(rtu(1, 4, b"\x00\x00\x00\x05"), rtu(1, 4, 10, regs))]) as url:
        c = cell(url)
        c.g = math.inf  # a calibration that went wrong after construction
        r = c.read_force()
    assert r.status == "invalid" and not r.ok
    with pytest.raises(ValueError, match="g must be > 0"):
        DiniDGT1S(c.link, g=math.nan)


def test_a_stop_ends_the_tare_handshake_wait() -> None:
    token = CancelToken()
    script = [(rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x01\x03")),
              (rtu(1, 6, b"\x00\x00\x00\x02"), rtu(1, 6, b"\x00\x00\x00\x02")),
              (rtu(1, 4, b"\x00\x05\x00\x01"), rtu(1, 4, 2, b"\x01\x03"))]  # not yet processed
    with expected_protocol("tare-stop", script) as url:
        c = cell(url)
        c.link.cancel = token
        c.sleep = lambda s: token.cancel("SIGHUP")
        with pytest.raises(OperationCancelledError, match="SIGHUP"):
            c.tare()


def test_the_watchdog_flag_is_40216_read_and_cleared() -> None:
    """ADAM-4000 manual, appendix G: 40216 is the communication-safety flag (protocol address 215 = 0x00D7). The
    driver reads it with FC3 and clears it by writing 0 with FC6."""
    script = [(rtu(1, 3, b"\x00\xd7\x00\x01"), rtu(1, 3, 2, b"\x00\x01")),
              (rtu(1, 6, b"\x00\xd7\x00\x00"), rtu(1, 6, b"\x00\xd7\x00\x00")),
              (rtu(1, 3, b"\x00\xd7\x00\x01"), rtu(1, 3, 2, b"\x00\x00"))]
    with expected_protocol("flag", script) as url:
        amp = amplifier(url, [0.0])
        assert amp.watchdog_fired() is True
        amp.ao.clear_safety_flag()
        assert amp.watchdog_fired() is False


# ADAM-4000 manual, appendix G p. G-7: 40215 is the communication-safety (WDT) enable, 1 = on; protocol address
# 40215 − 40001 = 214 = 0x00D6. Connect reads both module names (40211, 0x00D2), the flag (40216, 0x00D7), sends
# 0 V (ADAM-4024 datasheet: 12-bit offset binary over ±10 V, 0 V → code 2047.5 → 2048 = 0x0800), then the enable.
def _connect_script(enable: bytes) -> list[tuple[bytes, bytes | None]]:
    return [(rtu(1, 3, b"\x00\xd2\x00\x02"), rtu(1, 3, 4, b"\x40\x24\x00\x00")),
            (rtu(2, 3, b"\x00\xd2\x00\x02"), rtu(2, 3, 4, b"\x40\x17\x50\x00")),
            (rtu(1, 3, b"\x00\xd7\x00\x01"), rtu(1, 3, 2, b"\x00\x00")),
            (rtu(1, 6, b"\x00\x00\x08\x00"), rtu(1, 6, b"\x00\x00\x08\x00")),
            # ADAM-4017+ 40221 channel enable (read as register 220): V and I, channels 0 and 1
            (rtu(2, 3, b"\x00\xdc\x00\x01"), rtu(2, 3, 2, b"\x00\x03")),
            (rtu(1, 3, b"\x00\xd6\x00\x01"), rtu(1, 3, 2, enable))]


def _expecting_watchdog(url: str) -> TrekAmplifier:
    link = ModbusLink(url, "bus io", timeout=0.05, retries=0)
    return TrekAmplifier(Adam4024(link, 1, "amplifier AO"), Adam4017P(link, 2), max_voltage=8000,
                         clock=lambda: 0.0, comm_watchdog_s=1.0)


def test_connect_refuses_an_adam_4024_whose_watchdog_is_off_when_the_rig_expects_one() -> None:
    with expected_protocol("wdt-off", _connect_script(b"\x00\x00")) as url:
        amp = _expecting_watchdog(url)
        with pytest.raises(InstrumentStateError) as err:
            amp.connect()
    text = str(err.value)
    assert "\n" not in text and text.startswith("amplifier AO: ADAM-4024 unit 1")
    assert "register 40215 reads 0" in text and "comm_watchdog_s = 1 s" in text
    assert amp.commanded == pytest.approx(20e3 * 2048 / 4095 - 10e3)  # refused after the 0 V, not before


def test_connect_accepts_an_adam_4024_whose_watchdog_is_on() -> None:
    with expected_protocol("wdt-on", _connect_script(b"\x00\x01")) as url:
        _expecting_watchdog(url).connect()


def _twin_amplifier(watchdog_on: bool) -> None:
    """thesis-sim's twins (the rig expects a 1-s watchdog), the ADAM-4024 twin's 40215 written as the module's
    configuration would leave it, then the rig's amplifier driver connected."""
    data = load_rig(RIGS / "thesis-sim.toml").model_dump()
    data["amplifier"] = {**data["amplifier"], "comm_watchdog_s": 1.0}
    rig = RigConfig.model_validate(data)
    sim = SimRig(rig, virtual=True, timing="none")
    sim.start()
    try:
        sim.twins["amplifier AO"].write(6, 214, [int(watchdog_on)])  # FC6 to 40215 (address 214)
        inst = build_instruments(rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep,
                                 timers=sim.reply_timers(), wire_time=sim.wire_time)
        assert inst.amplifier is not None
        try:
            inst.amplifier.connect()
        finally:
            inst.close()
    finally:
        sim.stop()


def test_the_twin_with_its_watchdog_off_is_refused_at_connect() -> None:
    with pytest.raises(InstrumentStateError, match=r"^amplifier AO: ADAM-4024 unit 1: communication watchdog "
                       r"reported off \(register 40215 reads 0"):
        _twin_amplifier(watchdog_on=False)


def test_the_twin_with_its_watchdog_on_connects() -> None:
    _twin_amplifier(watchdog_on=True)
