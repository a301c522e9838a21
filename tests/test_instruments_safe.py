"""Making a rig safe tries every instrument, the output's path first and the motor next, whatever one of them
raises — a driver's error or anything else a dead port lets out (e.g. termios.error from a pty gone)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
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
    assert errors == ["daq: RuntimeError: not a driver error", "amplifier: link lost",
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
    with pytest.raises(OperationCancelledError, match="SIGTERM while enabling and homing the motor; nothing recorded; "
                       "rig safe"):
        execute(plan, tmp_path / "run.h5", virtual=True)
    assert closed == [True]
    assert signal.getsignal(signal.SIGTERM) is before  # the handler was the connect phase's only


@pytest.mark.parametrize("sig, said", [(signal.SIGINT, "interrupted by Ctrl-C"),
                                       (signal.SIGTERM, "terminated by SIGTERM"),
                                       (signal.SIGHUP, "hang-up (SIGHUP: terminal closed or connection dropped)")],
                         ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_stop_signal_while_the_motor_homes_says_in_one_line_what_it_stopped_and_that_the_rig_is_safe(
        tmp_path: Path, sig: int, said: str) -> None:
    """`bench run` on a simulated motor rig (wall clock), a stop signal while the LinMot homes: Ctrl-C exited 130
    saying nothing (typer's silent KeyboardInterrupt), with nothing in the run log, where SIGTERM and SIGHUP printed
    one line. Every one of them must print the same one line — what was interrupted, and what was made safe — put
    it in the run log, and no thread's traceback. The signal goes out once the run log says the motor is homing
    (the drive's hardware tests and homing take over a second of wall time from there), never after a fixed wait."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "bench", "run", str(ROOT / "protocols" / "short" / "lsdea-isometric-short.toml"),
         "--out", str(tmp_path), "--no-live"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True, env={**os.environ, "COLUMNS": "300"},
        # a suite started as a background job of a non-interactive shell inherits SIGINT ignored: not this run
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        log = ""
        while "enabling and homing the motor" not in log:
            assert proc.poll() is None and time.monotonic() < deadline, "bench run ended or never homed"
            time.sleep(0.01)
            log = "".join(p.read_text(encoding="utf-8") for p in tmp_path.glob("*.log"))
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    line = (f"error: run: {said} while enabling and homing the motor; nothing recorded; rig safe: every instrument "
            "made safe and closed (output zeroed, motor stopped)")
    assert "Traceback" not in err and "Exception" not in err, err
    assert err.splitlines() == [line], err
    assert proc.returncode == 2
    (log_file,) = tmp_path.glob("*.log")
    assert f"not run: {line.removeprefix('error: run: ')}" in log_file.read_text(encoding="utf-8")
    assert not list(tmp_path.glob("*.h5"))  # nothing recorded, as the line says


def test_closing_errors_name_each_device_once() -> None:
    """A driver's error already names its device ("daq: …"); closing the rig adds the role only where the device
    is named otherwise (it printed "daq: daq: no valid reply …")."""
    from typing import Any, cast

    from bench.runtime.instruments import Instruments
    from drivers.errors import InstrumentTimeoutError

    class Failing:
        def __init__(self, device: str) -> None:
            self.device = device

        def close(self) -> None:
            raise InstrumentTimeoutError(self.device, "no valid reply within 0.5 s")

    inst = Instruments(daq=cast(Any, Failing("daq")), laser=cast(Any, Failing("LK-G5000")))
    assert inst.close() == ["daq: no valid reply within 0.5 s", "laser: LK-G5000: no valid reply within 0.5 s"]
