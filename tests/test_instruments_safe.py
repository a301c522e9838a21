"""Making a rig safe tries every instrument, the output's path first and the motor next, whatever one of them
raises — a driver's error or anything else a dead port lets out (e.g. termios.error from a pty gone)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import pytest

from bench.runtime import engine as engine_mod
from bench.runtime.instruments import Instruments
from bench.runtime.interlock import InterlockTrip
from bench.runtime.latch import LatchedError, latched, refuse_if_latched
from bench.runtime.run import execute, plan_run
from drivers.errors import InstrumentConnectionError
from tests.conftest import ROOT


class _Fake:
    def __init__(self, role: str, calls: list[str], error: BaseException | None = None) -> None:
        self.role, self.calls, self.error = role, calls, error

    def safe_state(self) -> None:
        self.calls.append(self.role)
        if self.error is not None:
            raise self.error


def test_every_instrument_is_made_safe_in_order_whatever_one_raises() -> None:
    calls: list[str] = []
    inst = Instruments(
        laser=cast(Any, _Fake("laser", calls, OSError(5, "Input/output error"))),
        daq=cast(Any, _Fake("daq", calls, RuntimeError("not a driver error"))),
        amplifier=cast(Any, _Fake("amplifier", calls, InstrumentConnectionError("amplifier", "link lost"))),
        motor=cast(Any, _Fake("motor", calls)),
        load_cell=cast(Any, _Fake("load_cell", calls)))
    errors = inst.safe_state()
    assert calls == ["daq", "amplifier", "motor", "laser", "load_cell"]  # output path, motor, then the rest
    assert errors == ["daq: RuntimeError: not a driver error", "amplifier: amplifier: link lost",
                      "laser: OSError: [Errno 5] Input/output error"]


def test_a_latched_fault_is_kept_when_the_run_ends_by_an_exception(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The engine latched a fault, then something it did not catch ended the run: the latch file is still written,
    and the next run on the rig is refused until an operator resets it."""
    monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / "state"))

    def run(self: Any) -> Any:
        self.latched = InterlockTrip("host stall", "test: latched, then an uncaught error")
        raise RuntimeError("uncaught after the latch")

    monkeypatch.setattr(engine_mod.Engine, "run", run)
    plan = plan_run(ROOT / "protocols" / "short" / "thesis-identification-short.toml",
                    ROOT / "rigs" / "thesis-sim.toml")
    with pytest.raises(RuntimeError, match="uncaught"):
        execute(plan, tmp_path / "run.h5", virtual=True)
    assert latched(plan.rig.name) is not None
    with pytest.raises(LatchedError):
        refuse_if_latched(plan.rig.name)


def test_sigterm_while_the_motor_homes_closes_the_instruments_instead_of_killing_the_process(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before the engine installs its handlers, SIGTERM (as Ctrl-C already did) ends the run by an exception that
    names it, so the instruments are closed — the LinMot's safe state aborts the homing — rather than the process
    dying with the motor moving."""
    import os
    import signal

    from drivers.errors import OperationCancelledError
    from drivers.linmot import LinMotDrive

    home, closed = LinMotDrive.home, []

    def homing(self: LinMotDrive) -> None:
        os.kill(os.getpid(), signal.SIGTERM)  # arrives while the drive homes
        home(self)

    close = Instruments.close

    def spy(self: Instruments) -> list[str]:
        closed.append(True)
        return close(self)

    monkeypatch.setattr(LinMotDrive, "home", homing)
    monkeypatch.setattr(Instruments, "close", spy)
    plan = plan_run(ROOT / "protocols" / "short" / "lsdea-isometric-short.toml",
                    ROOT / "rigs" / "lsdea-motor-sim.toml")
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(OperationCancelledError, match="SIGTERM while connecting the instruments"):
        execute(plan, tmp_path / "run.h5", virtual=True)
    assert closed == [True]
    assert signal.getsignal(signal.SIGTERM) is before  # the handler was the connect phase's only
