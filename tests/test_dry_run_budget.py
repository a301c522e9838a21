"""The dry run's budget (bench/protocol/predict.py, README "Validation and dry run"): the whole program is dry-run
on the model, at an estimated cost of one core of at most 2 % of the run's own duration, never less than 30 s,
never more than 1800 s. The estimate (:func:`dry_run_cost`): the model at 1/150 of the run time, 20 µs per
set-point update (every segment streaming throughout), 1 ms per step. A fixed cap of 3600 s of run time refused
every protocol over an hour before (found by an outside tester: the thesis voltage sweep with its 60-s relax set
to 1 h, 14,480 s, could not be validated). The expected figures are worked out here from that rule, not asked of
the code; no test here dry-runs hours of model time (only the budget is checked, before any integration)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from bench.protocol.predict import check_budget, predict
from bench.protocol.program import Program, ProtocolLimitError, compile_program
from bench.protocol.schema import load_protocol
from bench.runtime.run import resolve_rig
from tests.conftest import RIGS, ROOT

# the documented rule
FRACTION, FLOOR, CEILING = 0.02, 30.0, 1800.0
MODEL_PER_RUN_S, PER_UPDATE, PER_STEP = 1 / 150, 2e-5, 1e-3


def _sweep_with_relax(tmp_path: Path, relax: str, name: str, rig: str = "thesis-daq-sim") -> Path:
    """The shipped thesis voltage sweep (four 20-s drives, each followed by a relax) with its relax set to
    ``relax``: the tester's copy (on ``rig``: a week on the DAQ rig, every channel at 10 kHz, would exceed the
    format's sample limit first)."""
    text = (ROOT / "protocols" / "thesis-voltage-sweep.toml").read_text()
    text = text.replace('rig = "../rigs/thesis-daq-sim.toml"', f'rig = "{RIGS / (rig + ".toml")}"')
    assert "duration_s = 60.0" in text
    path = tmp_path / f"{name}.toml"
    path.write_text(text.replace("duration_s = 60.0", f'duration_s = "{relax}"'))
    return path


def _program(path: Path) -> Program:
    protocol = load_protocol(path)
    return compile_program(protocol, resolve_rig(protocol))


def _expected(program: Program, run_s: float) -> tuple[float, float]:
    """(estimated cost, budget) by the documented rule, for a program meant to last ``run_s``."""
    assert program.duration == pytest.approx(run_s)
    hz = program.protocol.recording.setpoint_Hz
    updates = sum(max(1, math.ceil(s.duration * hz - 1e-9)) for s in program.segments if s.duration > 0)
    cost = run_s * MODEL_PER_RUN_S + updates * PER_UPDATE + len(program.segments) * PER_STEP
    return cost, min(CEILING, max(FLOOR, FRACTION * run_s))


@pytest.mark.parametrize(("relax", "hours"), [("1 h", 4), ("3 h", 12)])
def test_a_multi_hour_program_is_accepted_with_its_cost_stated(tmp_path: Path, relax: str, hours: int) -> None:
    """Four drives of 20 s and four relaxes of 1 h (3 h): 14,480 s (43,280 s), about 4 h (12 h). The estimate and
    the budget it is held to come back (the summary and --json state both); it is within the budget."""
    relax_s = {"1 h": 3600.0, "3 h": 10800.0}[relax]
    program = _program(_sweep_with_relax(tmp_path, relax, f"sweep-{hours}h"))
    run_s = 4 * (20.0 + relax_s)
    assert round(run_s / 3600) == hours
    cost, budget = _expected(program, run_s)
    assert budget == pytest.approx(FRACTION * run_s) and cost < budget  # 290 s (866 s): 2 % of the run
    assert check_budget(program) == (pytest.approx(cost), pytest.approx(budget))


def test_a_week_is_refused_in_one_line_with_its_estimate_and_what_to_do(tmp_path: Path) -> None:
    """Four relaxes of 41 h: 590,480 s, nearly a week (the format's limit is 7 days). The dry run would take over
    an hour (the model alone 3,937 s),
    beyond the 1800-s ceiling: refused in one line naming the file and the field, with the estimate and the
    longest part that fits (the cost per run second here times the part's length at most the ceiling)."""
    path = _sweep_with_relax(tmp_path, "41 h", "sweep-week", "thesis-sim")
    program = _program(path)
    run_s = 4 * (20.0 + 41 * 3600.0)
    cost, budget = _expected(program, run_s)
    assert budget == CEILING and cost > budget
    with pytest.raises(ProtocolLimitError) as caught:
        check_budget(program)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"protocol file {path}: steps: the dry run would take ~{cost:.0f} s ("), message
    assert f"beyond its budget of {CEILING:.0f} s" in message and "split the protocol" in message, message
    part = re.search(r"files of at most ~([\d.]+) h of run time each", message)
    assert part is not None, message
    assert float(part.group(1)) == pytest.approx(run_s * CEILING / cost / 3600, abs=0.05)


def test_bench_validate_refuses_a_week_in_one_line(tmp_path: Path) -> None:
    """The CLI's word for it: one line on stderr, exit 2, no traceback."""
    from typer.testing import CliRunner

    from bench.cli import app

    path = _sweep_with_relax(tmp_path, "41 h", "sweep-week", "thesis-sim")
    out = CliRunner().invoke(app, ["validate", str(path)], env={"COLUMNS": "400"})
    assert out.exit_code == 2, out.output
    lines = [ln for ln in out.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: protocol file ") and "Traceback" not in out.output
    assert "steps: the dry run would take ~" in lines[0] and "split the protocol" in lines[0]


def test_a_short_program_keeps_the_30_s_floor(tmp_path: Path) -> None:
    """Ten minutes of relax in all (four of 150 s): 2 % would be 12.8 s; the budget stays 30 s."""
    program = _program(_sweep_with_relax(tmp_path, "150 s", "sweep-short"))
    cost, budget = _expected(program, 4 * 170.0)
    assert budget == FLOOR
    assert check_budget(program) == (pytest.approx(cost), pytest.approx(FLOOR))


def test_the_progress_moves_within_a_long_step(tmp_path: Path) -> None:
    """The progress callback is told the fraction done as the model advances through a step (each block of the
    plant), not only at its end: a long hold does not freeze the bar. Four relaxes of 12 s (a short dry run)."""
    program = _program(_sweep_with_relax(tmp_path, "12 s", "sweep-12s"))
    seen: list[float] = []
    pred = predict(program, seen.append)
    assert pred.ok
    assert seen == sorted(seen) and seen[-1] == 1.0
    assert len(set(seen)) > len(program.segments)  # within steps too
    assert pred.dry_run_estimate_s == pytest.approx(_expected(program, 4 * 32.0)[0])


def test_ctrl_c_in_validate_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C during `bench validate` (a long dry run): one line, exit 2 (typer said nothing and exited 130)."""
    from typer.testing import CliRunner

    import bench.app.runs
    from bench.cli import app

    def interrupted(*_args: object, **_kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(bench.app.runs, "plan_protocol", interrupted)
    out = CliRunner().invoke(app, ["validate", str(ROOT / "protocols" / "thesis-voltage-sweep.toml")],
                             env={"COLUMNS": "400"})
    assert out.exit_code == 2, out.output
    lines = [ln for ln in out.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "interrupted by Ctrl-C" in lines[0], out.output


def test_a_daq_played_hold_is_scheduled_in_chunks_and_the_model_sees_the_same(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """On a DAQ rig the dry run plays every 10-kHz scan: a 1-h relax held 36 M scans at once (~1.9 GB). They are
    now scheduled a chunk at a time, a scan that repeats the one before left out (the plant holds an input until
    the next): every block the model gives is the same, bit for bit, as with every scan scheduled at once (the
    former code, here), with far fewer inputs. Chunks of 1000 scans here, so that runs cross their ends. The scans
    go through the rig's drive filter (its output is what the amplifier follows): where that output is within
    SNAP_V of the wanted value it is that value, so a hold after a ramp is one input again, not a decaying tail."""
    import numpy as np

    import bench.protocol.predict as dry
    from bench.core.plant import Plant, PlantBlock

    def every_scan(seg: object, plant: Plant, scan_rate: float, gain: float,  # the former code: every scan at once,
                   drive: dry._Filter | None = None) -> float:  # through the drive filter at once
        assert seg.voltage is not None  # type: ignore[attr-defined]
        ts = seg.t_start + np.arange(max(1, round(seg.duration * scan_rate)) + 1) / scan_rate  # type: ignore[attr-defined]
        vs = np.asarray(seg.voltage(ts), dtype=float)  # type: ignore[attr-defined]
        plant.schedule_amplifier_input(ts, (vs if drive is None else drive.follow(vs)) / gain)
        return float(np.max(np.abs(vs)))

    program = _program(_sweep_with_relax(tmp_path, "12 s", "sweep-12s"))
    built = dry.build_plant

    def run(play: object) -> tuple[list[PlantBlock], int, dry.Prediction]:
        blocks: list[PlantBlock] = []
        inputs = [0]

        def build(*args: object, **kwargs: object) -> Plant:
            plant = built(*args, **kwargs)  # type: ignore[arg-type]
            plant.listeners.append(blocks.append)
            schedule = plant.schedule_amplifier_input

            def counted(t: np.ndarray, v: np.ndarray) -> None:
                inputs[0] += len(t)
                schedule(t, v)

            plant.schedule_amplifier_input = counted  # type: ignore[method-assign]
            return plant

        monkeypatch.setattr(dry, "build_plant", build)
        monkeypatch.setattr(dry, "_play_scans", play)
        pred = dry.predict(program)
        return blocks, inputs[0], pred

    monkeypatch.setattr(dry, "SCAN_CHUNK", 1000)
    new_blocks, new_inputs, new = run(dry._play_scans)
    old_blocks, old_inputs, old = run(every_scan)
    assert len(new_blocks) == len(old_blocks) > 0
    for a, b in zip(new_blocks, old_blocks, strict=True):
        for name in ("t", "voltage", "current", "displacement", "force", "field", "breakdown"):
            assert np.asarray(getattr(a, name)).tobytes() == np.asarray(getattr(b, name)).tobytes(), name
    assert (new.peak_voltage, new.peak_field, new.min_breakdown_margin) == \
        (old.peak_voltage, old.peak_field, old.min_breakdown_margin)
    assert old_inputs == sum(round(s.duration * 10000) + 1 for s in program.segments if s.voltage is not None
                             and s.duration > 0)
    assert old_inputs - new_inputs > 4 * 11 * 10000  # each relax's 0 V after its 0.5-s ramp: one input, not 11 s
