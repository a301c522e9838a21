"""Keyence LK-G twin against the manual: ASCII commands written out literally, replies checked.

Sources: LK-G user manual LK-G-M-NO5-E p. 5-5 (command ``MAIN[,ID…]<CR>``, reply headed by the received
main command/identifiers, ``ER,<main>,<code>`` with 00 command, 01 status, 20 length, 21 parameter count,
22 invalid parameter; upper or lower case accepted), p. 5-6 (value = sign + 7 characters with one point,
``±FFFFFFF`` over range, ``XXXXXXXX`` no value). [C]: public drivers written against real units (DESY
cmstkmodlab: M0/M1/M2, KL, VR, PW, PR, Q0/R0; theion firm_keyence_rs232: MS/MM/MA and the LK-G5000
codes 50/51/60/61/62).
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
import serial

from bench.rig import RigConfig, load_rig
from bench.runtime.sim_rig import SimRig
from tests.conftest import RIGS

VALUE = r"[+-](?=[0-9.]{7})[0-9]*\.[0-9]*"  # p. 5-6: sign + 7 characters, one of them the point


class Controller:
    def __init__(self, rig: RigConfig, timing: str = "none") -> None:
        self.sim = SimRig(rig, virtual=True, timing=timing)  # type: ignore[arg-type]
        self.sim.start()
        self.port = serial.Serial(self.sim.port_map()["laser"], timeout=0.3)

    def ask(self, command: bytes) -> bytes:
        self.port.write(command)
        return self.port.read_until(b"\r")

    def close(self) -> None:
        self.port.close()
        self.sim.stop()


@pytest.fixture
def g3000() -> Iterator[Controller]:
    c = Controller(load_rig(RIGS / "lsdea-isotonic-sim.toml"))  # LK-G3000
    yield c
    c.close()


@pytest.fixture
def g5000() -> Iterator[Controller]:
    c = Controller(load_rig(RIGS / "thesis-sim.toml"))  # LK-G5000
    yield c
    c.close()


def test_measured_values_lk_g3000(g3000: Controller) -> None:
    assert re.fullmatch(rf"M1,{VALUE}\r", g3000.ask(b"M1\r").decode())
    assert re.fullmatch(rf"M0,{VALUE},XXXXXXXX\r", g3000.ask(b"M0\r").decode())  # no head on OUT2
    assert g3000.ask(b"M2\r") == b"M2,XXXXXXXX\r"
    assert re.fullmatch(rf"M1,{VALUE}\r", g3000.ask(b"m1\r").decode(), re.IGNORECASE)  # lower case accepted


def test_over_range_is_plus_or_minus_ffffffff(g3000: Controller) -> None:
    g3000.sim.twins["laser"].head.offset_mm = 140.0  # type: ignore[attr-defined]
    assert g3000.ask(b"M1\r") == b"M1,+FFFFFFF\r"
    g3000.sim.twins["laser"].head.offset_mm = -140.0  # type: ignore[attr-defined]
    assert g3000.ask(b"M1\r") == b"M1,-FFFFFFF\r"


def test_error_replies_lk_g3000(g3000: Controller) -> None:
    assert g3000.ask(b"ZZ\r") == b"ER,ZZ,00\r"  # command error
    assert g3000.ask(b"M1,1\r") == b"ER,M1,21\r"  # parameter count error
    assert g3000.ask(b"KL,5\r") == b"ER,KL,22\r"  # invalid parameter
    assert g3000.ask(b"MS,01\r") == b"ER,MS,00\r"  # an LK-G5000 command on the LK-G3000


def test_panel_lock_reset_and_program_lk_g3000(g3000: Controller) -> None:
    assert g3000.ask(b"KL,1\r") == b"KL\r"
    assert g3000.ask(b"KL,0\r") == b"KL\r"
    assert g3000.ask(b"VR,1\r") == b"VR\r"
    assert g3000.ask(b"PW,2\r") == b"PW\r"
    assert g3000.ask(b"PR\r") == b"PR,2\r"


def test_modes_q0_r0(g3000: Controller) -> None:
    assert g3000.ask(b"R0\r") == b"R0\r"  # already in general mode: echoed ([C] drivers send it at start-up)
    assert g3000.ask(b"Q0\r") == b"Q0\r"
    assert g3000.ask(b"M1\r") == b"ER,M1,01\r"  # measurement in communication mode: status error
    assert g3000.ask(b"PW,1\r") == b"ER,PW,01\r"
    assert g3000.ask(b"SW,CA,2\r") == b"SW,CA\r"
    assert g3000.ask(b"R0\r") == b"R0\r"
    assert g3000.ask(b"SW,CA,2\r") == b"ER,SW,01\r"  # settings in general mode: status error


def test_measured_values_lk_g5000(g5000: Controller) -> None:
    assert re.fullmatch(rf"MS,01,{VALUE}\r", g5000.ask(b"MS,01\r").decode())
    assert g5000.ask(b"MS,02\r") == b"MS,02,XXXXXXXX\r"  # no head on OUT2
    assert re.fullmatch(rf"MA,{VALUE}\r", g5000.ask(b"MA\r").decode())  # every OUT with a head
    assert re.fullmatch(rf"MM,100000000000,{VALUE}\r", g5000.ask(b"MM,100000000000\r").decode())
    assert re.fullmatch(rf"MM,110000000000,{VALUE},XXXXXXXX\r", g5000.ask(b"MM,110000000000\r").decode())


def test_error_replies_lk_g5000(g5000: Controller) -> None:
    assert g5000.ask(b"ZZ\r") == b"ER,ZZ,50\r"
    assert g5000.ask(b"MS\r") == b"ER,MS,61\r"
    assert g5000.ask(b"MS,13\r") == b"ER,MS,62\r"
    assert g5000.ask(b"MM,12\r") == b"ER,MM,62\r"
    assert g5000.ask(b"M1\r") == b"ER,M1,50\r"  # an LK-G3000 command on the LK-G5000
    assert g5000.ask(b"Q0\r") == b"Q0\r"
    assert g5000.ask(b"MA\r") == b"ER,MA,51\r"


def test_reply_time_is_the_wire_time_at_115200_bd() -> None:
    c = Controller(load_rig(RIGS / "lsdea-isotonic-sim.toml"), timing="real")
    try:
        t0 = c.sim.clock.now()
        assert len(c.ask(b"M1\r")) == 12  # "M1,+dd.dddd\r"
        # (3 + 12) characters × 10 bits / 115200 Bd + 0.5 ms turnaround [assumed figure]
        assert c.sim.clock.now() - t0 == pytest.approx(15 * 10 / 115200 + 0.5e-3, abs=1e-9)
    finally:
        c.close()
