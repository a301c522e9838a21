"""A step that falls behind its schedule on a software-timed rig: it keeps its times, and so do the later steps.

The outside tester's protocol: on ``lsdea-motor-sim`` at 50 set-points/s, a 1.5-cycle triangle on the motor
(3 s), a ramp to 4 kV over 1 s, a 2-s hold and a 1-s relax. The host sends the ADAM-4024's FC6 and the LinMot
go-to at every tick and polls the load cell and the encoder at 20/s, all in turn, so the triangle step needs more
rig time than its 3 s (the link budget warns; here the plan's warning is lifted so that the twins keep the wire
time, as a real line would). First the triangle ended ~0.6 s late and the hold lasted ~1.3 s; then the schedule
shifted after it, which kept the hold whole but played the triangle at ~0.41 Hz. Now a set-point whose successor
is already due is skipped (and a poll's missed slots), so the triangle keeps its 0.5 Hz, sampled more coarsely.

Expected values come from the protocol (the triangle's offset, amplitude and frequency, 50 set-points/s, 2-s
hold, 1-s relax, 4 kV) and the plant's own output history, never from the engine's account of itself. Virtual
time: deterministic in rig time.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import RIGS
from tests.test_protocol_link_budget import P2

PROTOCOL = P2.replace("{hz}", "50")  # the tester's protocol, as the link-budget test holds it (steps by index)
V_HOLD = 4000.0  # the ramp's target, held by the hold step
HOLD_S, RELAX_S, RAMP_S = 2.0, 1.0, 1.0
TRIANGLE_S = 1.5 / 0.5  # cycles / frequency


def test_a_step_behind_its_schedule_skips_superseded_set_points_and_every_step_keeps_its_times(tmp_path: Path) -> None:
    proto = tmp_path / "p2.toml"
    proto.write_text(PROTOCOL.format(rig=RIGS / "lsdea-motor-sim.toml"))
    plan = plan_run(proto)
    assert plan.link_problems  # the link budget warns about this protocol (tests/test_protocol_link_budget.py)
    plan = dataclasses.replace(plan, link_problems=[])  # wire time on: the twins take a real line's time
    seen: dict[str, Any] = {}
    blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def hook(engine: Any, sim: Any) -> None:
        seen["sim"] = sim
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.v_out.copy(), b.displacement.copy())))

        def at(_now: float) -> None:
            if "t0" not in seen and engine.snapshot.state == "running":
                seen["t0"] = sim.clock.now() - engine.now()
        sim.clock.subscribe(at)

    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    events = run.event_list()
    starts = {step: t for t, step, kind, _ in events if kind == "start"}
    ends = {step: t for t, step, kind, _ in events if kind == "end"}
    # the triangle played its planned 3 s (before: 3.6 s, its waveform stretched to ~0.41 Hz)
    assert ends[1] - starts[1] == pytest.approx(TRIANGLE_S, abs=2e-3)
    # every later step runs its planned duration (the events)
    assert ends[2] - starts[2] >= RAMP_S - 1e-6
    assert ends[3] - starts[3] == pytest.approx(HOLD_S, abs=1e-3)
    assert ends[4] - starts[4] == pytest.approx(RELAX_S, abs=1e-3)
    # the plant's output: at 4 kV for the hold's 2 s (from the ramp's top to the relax's ramp down)
    seen["sim"].plant.observe()
    t = np.concatenate([b[0] for b in blocks]) - seen["t0"]
    v = np.concatenate([b[1] for b in blocks])
    top = np.flatnonzero(v >= 0.99 * V_HOLD)
    assert top.size
    held = t[top[-1]] - t[top[0]]
    # never shorter; longer by the relax's first staircase set-point (1/50 s after its start, the ramp down's first
    # value still 4 kV) and the amplifier's fall from 4 kV
    assert HOLD_S - 0.01 <= held <= HOLD_S + 0.1, held
    # every go-to the triangle sent is the protocol's triangle at its recorded time (LinRS go-tos aim two ticks
    # ahead, the driver's streaming scheme: bench/protocol/program.py motor_command); fewer than its 3 s x 50/s,
    # and the file says how many were skipped
    sp = run.streams["setpoints"]
    sp_t = np.asarray(sp.t)
    aperture = np.asarray(sp.columns["aperture"])
    go_to = np.isfinite(aperture)  # the triangle's rows (the ramp's carry no aperture)
    mine = (sp_t >= starts[1] - 1e-9) & (sp_t < ends[1] - 1e-9) & go_to
    tau = sp_t[mine] - starts[1] + 2 / 50
    phase = (tau * 0.5) % 1.0
    tri = np.where(phase < 0.5, 2 * phase, 2 * (1 - phase))
    tri = np.where(tau >= TRIANGLE_S, 1.0, tri)  # past the end: the go-to aims at the step's end value (50 mm)
    assert np.max(np.abs(aperture[mine] - (0.090 - 0.040 * tri))) < 1e-6
    assert 50 < mine.sum() < TRIANGLE_S * 50
    skipped = [text for _, step, kind, text in events if kind == "skipped" and step == 1]
    assert len(skipped) == 1 and f"{int(TRIANGLE_S * 50 - mine.sum())} of {int(TRIANGLE_S * 50)} set-points" \
        in skipped[0], skipped
    assert np.all(np.diff(sp_t) >= 0)  # in time order
    # the run's summary counts them (every step's), and so does its timing event
    n_skipped = sum(int(re.search(r"(\d+) of \d+ set-points", text)[1])  # type: ignore[index, misc]
                    for _, _, kind, text in events if kind == "skipped")
    assert result.skipped == n_skipped >= TRIANGLE_S * 50 - mine.sum()
    assert any(kind == "timing" and f"{n_skipped} set-points skipped" in text for _, _, kind, text in events)
    # the carriage itself (the plant's aperture) reaches the triangle's turns, 50 mm and back at 90 mm: a skip never
    # drops a turn's set-point, and a go-to after a skip catches up (before: 89.0 mm, the turn cut by a skipped one)
    x = np.concatenate([b[2] for b in blocks])
    first_turn = (t >= starts[1] + 0.5) & (t <= starts[1] + 1.5)  # at 1 s (not the step's last trough at 3 s)
    second_turn = (t >= starts[1] + 1.5) & (t <= starts[1] + 2.5)  # back at 90 mm at 2 s
    assert abs(x[first_turn].min() - 0.050) < 3e-4
    assert abs(x[second_turn].max() - 0.090) < 3e-4
    assert not [step for _, step, kind, _ in events if kind == "late" and step == 1]
    # a poll behind its slots reads once at the latest: its lateness (counted on the virtual clock, in rig time)
    # stays within about one period (20/s), where it grew to 0.6 s in the stretched triangle
    late = np.asarray(run.streams["load_cell"].columns["late"])
    assert 0.005 < np.nanmax(late) < 2 / 20
    # the analysis reads the triangle at its 0.5 Hz: over its one whole cycle (a half cycle has no loading branch
    # of its own), its stroke the protocol's 40 mm less what the encoder's 20/s misses of the corners
    from bench.analysis.runs import analyse

    a = analyse(result.path)
    assert [n for n in a.notes if "index 1" in n and f"{int(TRIANGLE_S * 50 - mine.sum())} of its 150 set-points "
            "skipped" in n and f"sampled at {mine.sum() / TRIANGLE_S:.3g} set-points/s" in n] == a.notes, a.notes
    (tri_step,) = a.steps
    assert tri_step.kind == "isopotential" and len(tri_step.series["loss_per_cycle"]) == 1
    assert 0.035 < tri_step.figures["stroke"] <= 0.040 + 1e-6
    # a step that still ended late (one exchange longer than the tolerance, an upload inside it) is said to have
    # played slower than its frequency: the same file with a `late` event for the triangle, as the engine words it
    stretched = tmp_path / "stretched.h5"
    shutil.copy(result.path, stretched)
    with h5py.File(stretched, "r+") as f:
        ev = f["events"]
        for name, value in (("t", ends[1]), ("step", 1), ("kind", "late"),
                            ("text", "step 1 (pos) ended 0.600 s after its scheduled end: the program's schedule "
                                     "shifted by 0.600 s so that the next step runs whole")):
            ev[name].resize((ev[name].shape[0] + 1,))
            ev[name][-1] = value
        counts = f["status/samples"]  # the rows the writer confirmed, per name (its `names` attribute)
        counts[json.loads(counts.attrs["names"]).index("events")] += 1
    notes = analyse(stretched).notes
    assert any("index 1" in n and "0.5 Hz" in n and "played slower" in n for n in notes), notes

    # a step restarted (a pause, a drain at 0 V) is analysed from its last attempt: the note counts that attempt's
    # skips alone (a tester's report after a pause and resume added both attempts and gave a rate the protocol never
    # asked for); an earlier attempt inserted before the step's start, as the engine would have written it
    restarted = tmp_path / "restarted.h5"
    shutil.copy(result.path, restarted)
    with h5py.File(restarted, "r+") as f:
        ev = f["events"]
        rows = list(zip(*(ev[name][:] for name in ("t", "step", "kind", "text")), strict=True))
        at = next(k for k, r in enumerate(rows) if r[1] == 1 and r[2] == b"start")
        earlier = [(rows[at][0], 1, b"start", rows[at][3]),
                   (rows[at][0], 1, b"skipped", b"99 of 100 set-points skipped; behind the schedule")]
        rows[at:at] = earlier
        for j, name in enumerate(("t", "step", "kind", "text")):
            ev[name].resize((len(rows),))
            ev[name][:] = [r[j] for r in rows]
        f["status/samples"][json.loads(f["status/samples"].attrs["names"]).index("events")] += 2
    notes = [n for n in analyse(restarted).notes if "set-points skipped" in n]
    assert len(notes) == 1 and f"{int(TRIANGLE_S * 50 - mine.sum())} of its 150 set-points" in notes[0], notes

SINE = """[protocol]
name = "sine-behind"
rig = "{rig}"

[recording]
displacement_Hz = 1000
monitors_Hz = 40
setpoint_Hz = 50

[[steps]]
type = "waveform"
name = "sine"
channel = "voltage"
kind = "sine"
amplitude = "3 kV"
offset = "3 kV"
frequency_Hz = 0.5
cycles = 2

[[steps]]
type = "relax"
duration_s = 1
"""


def test_a_skip_never_moves_the_voltage_further_than_twice_the_waveforms_own_step(tmp_path: Path) -> None:
    """thesis-sim with set-points at 50/s and monitor reads at 40/s, more than its io bus carries (once it was the
    laser's storage upload inside the step; the engine now ends each fetch before the next set-point): skipping
    every set-point already superseded jumped the output by 2 kV in one write (the reviewer's run), a step load
    the dry run never saw. A skip now stops within twice the sine's largest change between two set-points,
    2π f A / setpoint_Hz (the protocol's numbers)."""
    v = _first_step_behind(tmp_path, SINE)
    own = 2 * np.pi * 0.5 * 3000.0 / 50  # the sine's largest change between two set-points [V]
    assert np.max(np.abs(np.diff(v))) <= 2 * own + 1e-6  # as recorded: no code of slack (the test below)


def _first_step_behind(tmp_path: Path, text: str) -> np.ndarray:
    """The recorded voltage set-points of the first step of protocol ``text`` on thesis-sim, run in virtual time
    with wire time though its links cannot carry it (the link budget's problems cleared: the step falls behind);
    checks that it completed and skipped set-points in that step."""
    proto = tmp_path / "p.toml"
    proto.write_text(text.format(rig=RIGS / "thesis-sim.toml"))
    plan = plan_run(proto)
    assert plan.link_problems
    result = execute(dataclasses.replace(plan, link_problems=[]), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    events = run.event_list()
    # the step's own set-points, to its planned end (its end value included): not the drain's ramp to 0 V after it
    # (a step's whole storage, uploaded after it, outlasts the 1-s hold), which is no skip
    end = plan.program.segments[0].t_end + 1e-6
    sp = run.streams["setpoints"]
    assert result.skipped > 0 and any(kind == "skipped" and step == 0 for _, step, kind, _ in events)
    return np.asarray(sp.columns["voltage"])[np.asarray(sp.t) <= end]



SLOW_RAMP = """[protocol]
name = "slow-ramp-behind"
rig = "{rig}"

[recording]
displacement_Hz = 1000
monitors_Hz = 40
setpoint_Hz = 50

[[steps]]
type = "ramp"
name = "slow"
channel = "voltage"
to = "600 V"
duration_s = 4

[[steps]]
type = "relax"
duration_s = 1
"""


def test_a_skip_bound_holds_on_the_values_recorded_not_only_on_those_requested(tmp_path: Path) -> None:
    """The skip bound compared the requested voltages, but the file records the module's codes: a tester saw a
    recorded jump of 83.0 V against 2 × 40 V. A ramp whose own change per set-point (600 V / 4 s / 50 = 3 V, the
    protocol's numbers) is below the ADAM-4024's code (the TREK's ±10 kV over 12 bits, ≈ 4.9 V) makes it plain:
    a requested 6-V skip recorded two codes (9.8 V). Behind its schedule (the io bus overloaded, as above), no
    recorded change in the ramp may exceed 2 × 3 V — no code of slack."""
    v = _first_step_behind(tmp_path, SLOW_RAMP)
    own = 600.0 / 4.0 / 50  # the ramp's change between two set-points [V]
    d = np.abs(np.diff(v))
    assert np.max(d) <= 2 * own + 1e-6, np.sort(d)[-5:]
    assert v[-1] == pytest.approx(600.0, abs=5.0)  # the ramp still reaches its target (within a code)


def test_a_skip_of_one_code_is_allowed_where_twice_the_steps_own_change_is_under_a_code(tmp_path: Path) -> None:
    """The same ramp over 10 s changes 600 V / 10 s / 50 = 1.2 V a set-point, twice that under the ADAM-4024's code
    (±10 kV over 12 bits: 20 kV / 4095 ≈ 4.88 V). With the host held 0.1 s every 0.25 s (as the laser's storage
    upload held it before it was bounded; a reply's retry does the same), a skip bound of 2.4 V refused every skip
    that changed the code, so the step fell behind and ended 5.2 s late. One code is the least any change moves
    the output, so a skip may move it by one: no recorded change beyond one code, and the step keeps its times
    (well under a second late)."""
    proto = tmp_path / "p.toml"
    proto.write_text(SLOW_RAMP.replace("duration_s = 4", "duration_s = 10")
                     .replace("monitors_Hz = 40", "monitors_Hz = 5").format(rig=RIGS / "thesis-sim.toml"))

    def held(engine: Any, sim: Any) -> None:
        flush, mark = engine.rec.maybe_flush, [0.25]

        def holding() -> None:
            if engine.snapshot.step == 0 and engine.program_now() >= mark[0]:
                mark[0] += 0.25
                sim.clock.sleep(0.1)
            flush()
        engine.rec.maybe_flush = holding

    result = execute(plan_run(proto), tmp_path / "run.h5", virtual=True, on_engine=held)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    events = run.event_list()
    assert any(kind == "skipped" and step == 0 for _, step, kind, _ in events)
    sp = run.streams["setpoints"]
    v = np.asarray(sp.columns["voltage"])[np.asarray(sp.t) <= 10.0 + 1e-6]
    code = 20_000.0 / 4095
    assert np.max(np.abs(np.diff(v))) <= code * (1 + 1e-9)
    late = [float(re.search(r"ended ([0-9.]+) s after", text).group(1))  # type: ignore[union-attr]
            for _, step, kind, text in events if kind == "late" and step == 0]
    assert all(s < 0.5 for s in late), late


def test_the_one_code_allowance_needs_both_values_inside_the_bound() -> None:
    """A reviewer: with the last value sent outside the supervisor's bound (4998.8 V sent, the bound lowered to
    4000 V), a skip to 4500 V quantises to the bound's code and so does the midpoint, so the adjacency test passed a
    ~1-kV jump. Codes of 10 V here (a stand-in module): inside the bound one code passes, two do not; from outside
    it nothing passes but the step's own bound."""
    from types import SimpleNamespace

    from bench.protocol.program import Tick
    from bench.runtime.engine import Engine

    class Module:
        def quantise(self, volts: float, within: float | None = None) -> float:
            top = (within // 10) * 10 if within is not None else 10_000.0
            return min(max(round(volts / 10) * 10, -top), top)

    def skips(v_cmd: float, later: float, jump: float) -> bool:
        engine = Engine.__new__(Engine)
        engine.ctx = SimpleNamespace(amp=Module(), v_cmd=v_cmd)  # type: ignore[assignment]
        engine.sup = SimpleNamespace(setpoint_bound=lambda: 4000.0)  # type: ignore[assignment]
        return engine._skip_within(Tick(0.0, later, None), jump)

    assert skips(1000.0, 1010.0, 2.0) and not skips(1000.0, 1020.0, 2.0)  # one code inside, not two
    assert skips(-1000.0, -1010.0, 2.0) and skips(1000.0, 1020.0, 25.0)
    assert not skips(4990.0, 4500.0, 2.0)  # from outside the bound: clamped to 4000, a 990-V jump


def test_inspect_says_when_a_virtual_run_took_no_wire_time(tmp_path: Path) -> None:
    """A virtual run of a protocol that outruns its lines runs at pty speed (no skips, nothing late: the run can
    not show what a real line would do); a tester found that only the file's attribute said so. `bench inspect`
    now says it beside the rig, in text and in --json."""
    from typer.testing import CliRunner

    from bench.cli import app

    proto = tmp_path / "p2.toml"
    proto.write_text(PROTOCOL.format(rig=RIGS / "lsdea-motor-sim.toml"))
    plan = plan_run(proto)
    assert plan.link_problems
    result = execute(plan, tmp_path / "run.h5", virtual=True)
    out = CliRunner().invoke(app, ["inspect", result.path], env={"COLUMNS": "300"})
    assert out.exit_code == 0, out.output
    assert "wire time off (the protocol outruns the rig's lines)" in " ".join(out.output.split())
    out = CliRunner().invoke(app, ["inspect", result.path, "--json"])
    assert json.loads(out.output)["wire_time"].startswith("off")
