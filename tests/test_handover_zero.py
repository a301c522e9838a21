"""Before the rig goes to a person (a `set` step: the operator's prompt), the output is *measured* at 0 V.

A relax shorter than its ramp rule ramps over its whole length, so 0 V is commanded at its last instant and the
specimen change follows at once. The engine now reads the voltage monitor before the prompt, as the shutdown
verifies 0 V, and an output that stays up trips and latches instead of prompting.

Expected figures from the README ("Safety", step 5): the safe state is the voltage monitor within the rig's
threshold (23.3 V on the ADAM rig, 15.3 V on the T7 rig: tests/test_monitor_chain.py), read after
0.5 s of fresh conversions and again for up to 2 s otherwise; from the schema (tests/test_relax_ramp.py): a relax's
ramp is at least 10 set-point periods (0.5 s at 20 set-points/s), at most the step — so a 0.3-s relax ramps over
all of it. The TREK's gain is 1000 V/V (datasheet): an input stuck at 3 V holds 3 kV, within the supervisor's
8-kV limit, so only a check of the output against 0 V can see it. A campaign continued (``bench run --resume``) from
its set step checks the same before that step's change, at the continuation's start.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.rig import load_rig
from bench.runtime.engine import Engine
from bench.runtime.latch import latched
from bench.runtime.run import execute, plan_resume, plan_run
from bench.storage.runfile import open_run
from tests.conftest import RIGS
from tests.test_monitor_chain import ADAM_BAND, T7_BAND
from tests.test_protocols import SAFE_HEAD

# README "Safety" 5: the voltage monitor at or below the rig's threshold is the output at 0 V (worked out from the
# monitor chain's manual figures in tests/test_monitor_chain.py: TREK monitor into an ADAM-4017+ or a T7 AIN)
SAFE_V = {"thesis-sim": ADAM_BAND, "thesis-daq-sim": T7_BAND}
SETTLE_S = 0.5  # README "Safety" 5: fresh monitor conversions after the zero
REREAD_S = 2.0  # README "Safety" 5: read again for up to 2 s
STUCK_IN_V = 3.0  # amplifier input held: 3 kV out at the TREK's 1000 V/V
RISE_S = 0.2  # the stuck input's rise
DT = 1 / 20  # SAFE_HEAD's recording.setpoint_Hz
BODY = ('[[steps]]\ntype = "ramp"\nchannel = "voltage"\nto = "2 kV"\nduration_s = 1.0\n\n'
        '[[steps]]\ntype = "relax"\nname = "short-relax"\nduration_s = 0.3\n\n'  # ramp rule 0.5 s > 0.3 s
        '[[steps]]\ntype = "set"\nname = "swap"\ntemperature_K = 310.0\n\n'
        '[[steps]]\ntype = "hold"\nname = "after"\nduration_s = 1.0\n')
SET_INDEX = 2


def _plan(tmp: Path, rig: str) -> Any:
    f = tmp / "p.toml"
    f.write_text(SAFE_HEAD.format(rig=RIGS / f"{rig}.toml") + BODY)
    return plan_run(f)


def _stick(plant: Any, volts_in: float) -> None:
    """The twin's amplifier input taken to ``volts_in`` over ``RISE_S`` from now on and held there, whatever the host
    or a stream writes (a rise slow enough that the specimen's charging current stays far below the 5-mA trip:
    only the output's voltage is wrong)."""
    at = plant.clock.now()

    def level(t: np.ndarray) -> np.ndarray:
        return volts_in * np.clip((t - at) / RISE_S, 0.0, 1.0)

    with plant.lock:
        plant._v_chunks = [(t, np.where(t >= at, level(t), v)) for t, v in plant._v_chunks]
    add = plant._add_input
    plant._add_input = lambda t, v, ordered: add(t, np.where(t >= at, level(t), v), ordered)
    ramp = at + np.linspace(0.0, RISE_S, 201)
    plant.schedule_amplifier_input(ramp, level(ramp))


def _run(tmp: Path, rig: str, stuck: bool) -> tuple[Any, list[float]]:
    """The plan run in virtual time with a person at the prompt (the twin's specimen change replaced by the
    operator's, as on a lab rig): returns the result and the run times at which the prompt was shown."""
    prompts: list[float] = []

    def hook(engine: Engine, sim: Any) -> None:
        def operator(_text: str) -> bool:
            prompts.append(engine.now())
            return True

        engine.apply_specimen, engine.operator = None, operator
        if stuck:
            relax_end = engine.program.segments[SET_INDEX - 1].t_end

            def at(_now: float) -> None:  # from the relax's last instant on (its last set-point is 0 V)
                if engine.now() >= relax_end - 1e-9 and not getattr(sim.plant, "_stuck", False):
                    sim.plant._stuck = True
                    _stick(sim.plant, STUCK_IN_V)
            sim.clock.subscribe(at)

    return execute(_plan(tmp, rig), tmp / "run.h5", virtual=True, on_engine=hook), prompts


@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_the_monitor_reads_zero_before_the_prompt(tmp_path: Path, rig: str) -> None:
    result, prompts = _run(tmp_path, rig, stuck=False)
    assert result.state == "completed", result.reason
    assert len(prompts) == 1
    run = open_run(result.path)
    steps = run.program
    relax_end = float(steps["t_start"][1] + steps["duration"][1])  # program time; no offset before the set step
    amp = run.streams["amplifier"]
    t, v = amp.t, amp.columns["voltage"]
    between = (t >= relax_end - 1e-9) & (t <= prompts[0] + 1e-9)
    assert between.any(), "no monitor reading between the relax's 0 V and the prompt"
    last = int(np.flatnonzero(between)[-1])
    assert abs(v[last]) <= SAFE_V[rig], v[between]
    # a fresh conversion of the zeroed output, not a stale one: 0.5 s after the output was last commanded above
    # the safe level, which the ramp (20 set-points/s; played at the scan rate on a DAQ rig) passes in its last period
    assert t[last] >= relax_end - DT + SETTLE_S - 1e-6
    hand = [e for e in run.event_list() if e[2] == "handover"]
    assert len(hand) == 1 and hand[0][1] == SET_INDEX and hand[0][0] <= prompts[0] + 1e-9, hand
    assert "0 V verified" in hand[0][3]


@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_an_output_that_stays_up_trips_and_latches_without_a_prompt(tmp_path: Path, rig: str) -> None:
    result, prompts = _run(tmp_path, rig, stuck=True)
    assert prompts == []  # nobody was asked to touch the specimen
    assert result.state == "tripped" and "interlock: output not verified" in result.reason, result.reason
    assert result.latched and "output not verified" in result.latched
    assert latched(load_rig(RIGS / f"{rig}.toml").name) is not None  # the next start is refused
    run = open_run(result.path)
    kinds = [(e[1], e[2]) for e in run.event_list()]
    assert (SET_INDEX, "specimen") not in kinds and (SET_INDEX, "handover") not in kinds, kinds
    amp = run.streams["amplifier"]
    t0 = float(run.program["t_start"][SET_INDEX])
    # what the monitor said once fresh conversions of the output commanded to 0 V were due, until the trip
    read = (amp.t >= t0 + SETTLE_S - 1e-6) & (amp.t <= t0 + SETTLE_S + REREAD_S + 0.1)
    assert read.sum() >= 2 and np.all(np.abs(amp.columns["voltage"][read]) > SAFE_V[rig]), amp.columns["voltage"][read]


def test_a_stop_during_the_check_is_taken_within_the_stop_poll(tmp_path: Path) -> None:
    """A stop request while the check waits for fresh conversions ends the run at once (README "Stop bound": the
    engine checks the request between waits of at most 0.1 s), without a prompt."""
    prompts: list[float] = []
    asked: list[float] = []

    def hook(engine: Engine, sim: Any) -> None:
        def operator(_text: str) -> bool:
            prompts.append(engine.now())
            return True

        engine.apply_specimen, engine.operator = None, operator
        relax_end = engine.program.segments[SET_INDEX - 1].t_end

        def at(_now: float) -> None:
            if engine.now() >= relax_end + 0.1 and not asked:
                asked.append(engine.now())
                engine.request_stop("terminated by SIGTERM")
        sim.clock.subscribe(at)

    result = execute(_plan(tmp_path, "thesis-sim"), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "interrupted" and prompts == [], result.reason
    (t_stop,) = [e[0] for e in open_run(result.path).event_list() if e[2] == "interrupted"]
    assert asked and t_stop - asked[0] <= 0.1 + 1e-6


def test_a_stop_that_cancels_a_check_read_is_a_stop_not_a_latch(tmp_path: Path) -> None:
    """A reviewer: a signal during the check's monitor read cancels the link's wait (OperationCancelledError, an
    InstrumentError), which the check took for an unreadable monitor: "output not verified", tripped, the rig
    latched. A cancelled read is the stop: the run is interrupted, nothing latched, nobody prompted."""
    from drivers.errors import OperationCancelledError

    prompts: list[float] = []

    def hook(engine: Engine, sim: Any) -> None:
        engine.apply_specimen = None
        engine.operator = lambda _text: bool(prompts.append(engine.now())) or True
        relax_end = engine.program.segments[SET_INDEX - 1].t_end
        amp = engine.inst.amplifier
        read, cancelled = amp.read_monitors, []

        def reading() -> Any:
            if engine.now() >= relax_end + 0.4 and not cancelled:
                cancelled.append(engine.now())
                engine.request_stop("terminated by SIGTERM")  # the signal arrives while the read waits on the link
                raise OperationCancelledError("amplifier", "wait abandoned: terminated by SIGTERM")
            return read()
        amp.read_monitors = reading

    result = execute(_plan(tmp_path, "thesis-sim"), tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert prompts == []
    assert result.state == "interrupted" and not result.latched, (result.state, result.reason, result.latched)


# ---------------------------------------------------------------- a resumed campaign that starts at the set step
def _interrupted_before_the_set_step(tmp: Path, rig: str) -> tuple[Any, Any]:
    """The campaign stopped at its set step (the operator declines the change): the first step that did not
    complete is the set step, so its continuation (``bench run --resume``) starts there. Returns the plan and link."""
    first = execute(_plan(tmp, rig), tmp / "first.h5", virtual=True, operator=lambda _text: False,
                    on_engine=lambda engine, _sim: setattr(engine, "apply_specimen", None))
    assert first.state == "interrupted" and "did not confirm 'swap'" in first.reason, first.reason
    plan, link, _ = plan_resume(first.path)
    assert link.step == SET_INDEX and plan.program.segments[link.step].changes, (link.step, first.reason)
    return plan, link


def _resume(tmp: Path, rig: str, who: str, residual: bool, volts_in: float = STUCK_IN_V) -> tuple[Any, list[float]]:
    """The continuation in virtual time; the set step's change made by ``who`` ("operator": the prompt, as on a lab
    rig; "twin": the simulated rig's own change). ``residual``: the amplifier's input held at ``volts_in`` from
    before the continuation starts (the output still up when the campaign is taken up again). Returns the result and
    the run times at which the change was asked for."""
    plan, link = _interrupted_before_the_set_step(tmp, rig)
    changes: list[float] = []

    def hook(engine: Engine, sim: Any) -> None:
        if who == "operator":
            engine.apply_specimen = None
            engine.operator = lambda _text: bool(changes.append(engine.now())) or True
        else:
            apply = engine.apply_specimen
            assert apply is not None
            engine.apply_specimen = lambda c: (changes.append(engine.now()), apply(c))[1]
        if residual:
            _stick(sim.plant, volts_in)
            sim.clock.advance(RISE_S + SETTLE_S)  # the output is up before the continuation's first read

    return execute(plan, tmp / "second.h5", virtual=True, resume=link, on_engine=hook), changes


@pytest.mark.parametrize("who", ["operator", "twin"])
@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_a_resumed_campaign_that_starts_at_a_set_step_verifies_zero_first(tmp_path: Path, rig: str,
                                                                           who: str) -> None:
    result, changes = _resume(tmp_path, rig, who, residual=False)
    assert result.state == "completed", result.reason
    assert len(changes) == 1
    run = open_run(result.path)
    assert run.attrs["previous_file"] == "first.h5"
    events = run.event_list()
    hand = [e for e in events if e[2] == "handover"]
    (spec,) = [e for e in events if e[2] == "specimen"]
    assert len(hand) == 1 and hand[0][1] == SET_INDEX == spec[1], hand
    assert "0 V verified" in hand[0][3] and "specimen change of step" in hand[0][3]
    # recorded before the change: earlier in the file's event list and in run time
    assert events.index(hand[0]) < events.index(spec) and hand[0][0] <= changes[0] + 1e-9
    amp = run.streams["amplifier"]
    read = amp.t <= changes[0] + 1e-9
    assert read.any() and abs(amp.columns["voltage"][read][-1]) <= SAFE_V[rig]


@pytest.mark.parametrize("who", ["operator", "twin"])
@pytest.mark.parametrize("rig", ["thesis-sim", "thesis-daq-sim"])
def test_a_resumed_campaign_whose_output_is_still_up_trips_at_its_set_step(tmp_path: Path, rig: str,
                                                                             who: str) -> None:
    result, changes = _resume(tmp_path, rig, who, residual=True)
    assert changes == []  # neither prompted nor changed
    assert result.state == "tripped" and "interlock: output not verified" in result.reason, result.reason
    assert result.latched and "output not verified" in result.latched
    assert latched(load_rig(RIGS / f"{rig}.toml").name) is not None
    run = open_run(result.path)
    kinds = [e[2] for e in run.event_list()]
    assert "specimen" not in kinds and "handover" not in kinds, kinds
    amp = run.streams["amplifier"]
    read = amp.t <= REREAD_S + 0.1  # the check's readings, from the continuation's start to the trip
    assert read.sum() >= 2 and np.all(np.abs(amp.columns["voltage"][read]) > SAFE_V[rig]), amp.columns["voltage"][read]
