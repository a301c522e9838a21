"""Every run file holds the measured safe state: the shutdown's verifying monitor read(s) as ``/safe_state``.

Before, the read that verified 0 V was in the ``safe`` event's words only, and on a DAQ rig nowhere else (its
streams end on the last scan; README "Hardware-timed"). Now ``/safe_state`` holds time [s], voltage [V], current
[A] and, on a rig with a motor, the carriage's position [m] once at rest, on every rig kind, whatever ended the run
(its end, an instrument error, a stop signal).

Expected figures from the README ("Safety", step 5): the safe state is the voltage monitor within the rig's
threshold (at most 50 V on every rig, the safe touch limit; tests/test_monitor_chain.py derives each), read 0.5 s
after 0 V was commanded; the file conventions from README "Run files" (a ``units`` attribute on every numeric
dataset, ``t`` a dimension scale of its group).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from bench.rig import load_rig
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from drivers.errors import InstrumentError
from tests.conftest import RIGS
from tests.test_protocols import SAFE_HEAD

SAFE_V = 50.0  # README "Safety" 5: every rig's verified-safe threshold is at most this (the safe touch limit)
SETTLE_S = 0.5  # README "Safety" 5: the verifying read comes 0.5 s after 0 V was commanded
SIM_RIGS = sorted(p.stem for p in RIGS.glob("*-sim.toml"))
BODY = ('[[steps]]\ntype = "ramp"\nchannel = "voltage"\nto = "1 kV"\nduration_s = 1.0\n\n'
        '[[steps]]\ntype = "hold"\nduration_s = 1.0\n\n'
        '[[steps]]\ntype = "relax"\nduration_s = 1.0\n')
END_AT = 1.5  # run time of the stop or the fault: in the hold, 1 kV on


def _run(tmp: Path, rig: str, how: str) -> Any:
    f = tmp / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=RIGS / f"{rig}.toml") + BODY)

    def hook(engine: Engine, sim: Any) -> None:
        if how == "signal":  # what the SIGTERM handler does (Engine._on_signal → request_stop)
            sim.clock.subscribe(lambda _now: engine.request_stop("terminated by SIGTERM")
                                if engine.now() >= END_AT and engine._stop_reason is None else None)
        elif how == "error":  # an instrument that fails in the hold
            wait = engine.ctx.wait_until

            def failing(t: float) -> None:
                if engine.now() >= END_AT and not engine._stopping:
                    raise InstrumentError("laser", "no answer (injected)")
                wait(t)
            engine.ctx.wait_until = failing  # type: ignore[method-assign]

    return execute(plan_run(f), tmp / "run.h5", virtual=True, on_engine=hook)


@pytest.mark.parametrize("how", ["end", "error", "signal"])
@pytest.mark.parametrize("rig", SIM_RIGS)
def test_the_file_holds_the_measured_safe_state(tmp_path: Path, rig: str, how: str) -> None:
    result = _run(tmp_path, rig, how)
    assert result.state == {"end": "completed", "error": "error", "signal": "interrupted"}[how], result.reason
    motor = load_rig(RIGS / f"{rig}.toml").motor is not None
    with h5py.File(result.path, "r") as f:
        g = f["safe_state"]
        n = int(g["t"].shape[0])
        assert n >= 1
        t, v, i = g["t"][:], g["voltage"][:], g["current"][:]
        assert g["voltage"].attrs["units"] == "V" and g["current"].attrs["units"] == "A"
        assert g["t"].attrs["units"].startswith("seconds since ") and g["t"].is_scale
        assert g["voltage"].dims[0][0].name == g["t"].name  # t is the voltage's dimension (netCDF coordinate)
        assert abs(v[-1]) <= SAFE_V and np.isfinite(i[-1]), (v, i)
        assert ("position" in g) == motor
        assert g.attrs["rate_Hz"] == pytest.approx(10.0)  # README "Safety" 5: re-read every 0.1 s (not a default)
        if motor:
            assert g["position"].attrs["units"] == "m" and np.all(np.isfinite(g["position"][:]))
        zero = [float(e.split("0 V commanded by the host at ")[1].split(" s")[0])
                for e in (x.decode() for x in f["events/text"][:]) if e.startswith("0 V commanded by the host at ")]
    assert zero and t[0] >= zero[0] + SETTLE_S - 1e-9  # read after the settle that follows the zero
    assert t[-1] <= result.run_time + 1e-9


def test_an_output_nothing_could_zero_is_still_measured_into_the_file(tmp_path: Path) -> None:
    """A reviewer: where 0 V could not be commanded and the set-point module has no watchdog (a rig allowed to run
    without one), the shutdown said UNSAFE without reading the monitor, and /safe_state stayed empty — the case
    that most needs a measurement. The module refusing every request from the stop on: the file holds the monitor's
    reading of the output left on (1 kV, the hold's), and the result says it."""
    from bench.rig import RigConfig

    f = tmp_path / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=RIGS / "thesis-sim.toml") + BODY)
    plan = plan_run(f)
    rig = RigConfig.model_validate({**plan.rig.model_dump(),
                                    "amplifier": {**plan.rig.amplifier.model_dump(), "comm_watchdog_s": None}})
    plan.rig = plan.program.rig = rig

    def hook(engine: Engine, sim: Any) -> None:
        amp = engine.inst.amplifier
        set_voltage = amp.set_voltage

        def refused(*args: Any, **kwargs: Any) -> float:
            if engine._stopping:
                raise InstrumentError("amplifier", "no answer (injected)")
            return float(set_voltage(*args, **kwargs))

        def zero() -> None:
            raise InstrumentError("amplifier", "no answer (injected)")
        amp.set_voltage, amp.zero = refused, zero
        sim.clock.subscribe(lambda _now: engine.request_stop("terminated by SIGTERM")
                            if engine.now() >= END_AT and engine._stop_reason is None else None)

    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook, allow_no_watchdog=True)
    assert result.safe_path.startswith("UNSAFE") and "voltage monitor" in result.safe_path, result.safe_path
    with h5py.File(result.path, "r") as fh:
        v = fh["safe_state"]["voltage"][:]
    assert v.size >= 1 and abs(v[-1]) > 500, v  # the hold's 1 kV, measured
