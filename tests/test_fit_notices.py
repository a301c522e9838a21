"""`bench fit` says, before fitting, what a user may not have meant: run files of different rigs or specimens fitted
as one set of parameters (a warning naming what differs; the fit still goes ahead), and a run that stopped before
its protocol ended (the report's one-line wording).

Expected values come from what each test does to its files (the attributes it changes, the stop it requests) and
from protocols/short/thesis-identification-short.toml (two steps: a 10-s identification drive, a 1-s recovery)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.runtime.engine import Engine
from bench.runtime.run import execute, plan_run
from tests.conftest import ROOT

SHORT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
QUICK = ["--population", "5", "--generations", "1", "--starts", "1", "--no-intervals", "--no-polish"]


def _fit(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["fit", *args, *QUICK], env={"COLUMNS": "400"})
    return res.exit_code, res.output


def _copy(src: Path, dst: Path, **attrs: str) -> Path:
    shutil.copy2(src, dst)
    with h5py.File(dst, "r+") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
    return dst


def _with_specimen(path: Path, change: dict[str, object]) -> None:
    with h5py.File(path, "r+") as f:
        raw = f.attrs["specimen"]
        spec = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
        spec.update(change)
        f.attrs["specimen"] = json.dumps(spec)


def test_runs_of_different_rigs_and_specimens_are_warned_about_before_the_fit(short_run: Path,
                                                                               tmp_path: Path) -> None:
    a = _copy(short_run, tmp_path / "A.h5", specimen_id="VHB-01")
    b = _copy(short_run, tmp_path / "B.h5", rig_name="other-rig", specimen_id="VHB-02", run_id="b" * 32)
    _with_specimen(b, {"breakdown_field_V_per_m": 80e6})
    code, out = _fit(str(a), str(b))
    assert code == 0, out
    warning = next(line for line in out.splitlines() if line.startswith("warning: the runs are not of one"))
    for said in ("specimen_id", "'VHB-01'", "'VHB-02'",
                 "specimen.breakdown_field_V_per_m", "80000000.0", "A.h5", "B.h5"):
        assert said in warning, warning
    assert out.index(warning) < out.index("fitting the membrane model")  # before the fit, which still ran
    assert "stored in" in out
    # a campaign of one specimen at other conditions (its records' own temperature) is not warned about
    from bench.app.fit import specimen_mismatch

    c = _copy(short_run, tmp_path / "C.h5", specimen_id="VHB-01")
    _with_specimen(c, {"temperature_K": 316.0, "overrides": {"temperature_K": 316.0}})
    assert specimen_mismatch([a, c]) == ""
    # nor one specimen on another bench (the LS-DEA campaign's motor and hung-mass rigs)
    d = _copy(short_run, tmp_path / "D.h5", rig_name="other-rig", specimen_id="VHB-01")
    assert specimen_mismatch([a, d]) == ""


def test_a_copy_of_a_run_is_refused_not_fitted_as_a_second_record(short_run: Path, tmp_path: Path) -> None:
    """A copy has its original's run_id: fitted beside it, its record counted twice and the intervals narrowed by √2
    on no new data (the tester's run). One line names both files; a file that is not there is 'not found'."""
    a = _copy(short_run, tmp_path / "A.h5")
    copy = _copy(short_run, tmp_path / "copy.h5")
    code, out = _fit(str(a), str(copy))
    assert code != 0 and "fitting" not in out
    line = next(ln for ln in out.splitlines() if "same run" in ln)
    assert "A.h5" in line and "copy.h5" in line and "Traceback" not in out
    code, out = _fit(str(a), str(a))  # the same path twice: one file, fitted once
    assert code == 0, out
    code, out = _fit(str(tmp_path / "nothere.h5"))
    assert code != 0 and "nothere.h5: not found" in out and "continues" not in out, out


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The short identification run, stopped ("Ctrl-C") 3 s into its drive (its first step)."""
    def ctrl_c(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        def at(_now: float) -> None:
            if engine.snapshot.step == 0 and engine.program_now() > 3.0:
                engine.request_stop("Ctrl-C")
        sim.clock.subscribe(at)

    d = tmp_path_factory.mktemp("stopped")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BENCH_STATE_DIR", str(d / "state"))
        run = execute(plan_run(SHORT), d / "stopped.h5", virtual=True, on_engine=ctrl_c)
    assert run.state == "interrupted", run.reason
    return Path(run.path)


def test_a_stopped_run_is_said_to_have_stopped_before_the_fit(stopped_run: Path) -> None:
    code, out = _fit(str(stopped_run))
    assert code == 0, out
    notes = [line for line in out.splitlines() if line.startswith("note: ")]
    assert len(notes) == 1, out
    note = notes[0]
    assert str(stopped_run) in note and "run interrupted at" in note and "Ctrl-C" in note, note
    # stopped in its first step: neither of the protocol's two steps ran to its end
    assert "in step 1 of 2" in note and "steps 1–2 of 2 not run to their end" in note, note
    assert out.index(note) < out.index("fitting the membrane model")


def test_ctrl_c_to_the_process_group_stops_a_fit_on_workers_in_one_line(short_run: Path, tmp_path: Path) -> None:
    """A terminal's Ctrl-C reaches the whole process group, `--workers`' dask processes too: each died of it with
    dask's tracebacks (104 lines on stderr for two workers, a reviewer's guess confirmed) while the fit stopped. The
    workers are spawned with SIGINT ignored: the fit's own process stops and closes the cluster, one line, exit
    130, nothing stored."""
    import signal

    pytest.importorskip("distributed")
    run = _copy(short_run, tmp_path / "run.h5")
    # the workers up, the search begun; then Ctrl-C as a terminal sends it: to every process of the group
    _out, err, lines = _interrupted_fit(["--workers", "2"], run, "evaluating candidates on the dask cluster", 3.0,
                                        lambda proc: os.killpg(proc.pid, signal.SIGINT))
    assert len(lines) == 1 and lines[0].startswith("fit stopped: Ctrl-C in the "), err
    assert "Traceback" not in err and not (tmp_path / "run.fit.hdf5").exists()


@contextlib.contextmanager
def _read_only_folder(where: Path, files: list[Path]) -> Iterator[Path]:
    """``files`` copied into a folder that cannot be written, even by root: a tmpfs remounted read-only (as the
    tester's, errno 30); without one, mode bits as a non-root user."""
    where.mkdir()
    if os.geteuid() != 0:
        for f in files:
            shutil.copy2(f, where / f.name)
            (where / f.name).chmod(0o444)  # the run file too: --into opens it for writing (a reviewer)
        where.chmod(0o555)
        try:
            yield where
        finally:
            where.chmod(0o755)
        return
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(where)], capture_output=True)
    if res.returncode != 0:
        pytest.skip("cannot mount a tmpfs here: needs root/CAP_SYS_ADMIN")
    try:
        for f in files:
            shutil.copy2(f, where / f.name)
        subprocess.run(["mount", "-o", "remount,ro", str(where)], check=True, capture_output=True)
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def test_an_unwritable_destination_is_refused_in_one_line_before_the_search(short_run: Path, tmp_path: Path) -> None:
    """The tester's run in a read-only folder searched for minutes, then failed in HDF5's words: each destination
    (the fit file beside the run, the run file with --into, the --export rig) is refused before the search, in one
    line naming it; nothing is written anywhere."""
    with _read_only_folder(tmp_path / "ro", [short_run]) as ro:
        run = ro / short_run.name
        code, out = _fit(str(run))
        assert code == 2 and "fitting the" not in out, out
        line = next(ln for ln in out.splitlines() if ln.startswith("error:"))
        assert f"fit file {ro / 'run.fit.hdf5'}: cannot be written" in line and "Traceback" not in out, out
        code, out = _fit(str(run), "--into")
        assert code == 2 and "fitting the" not in out and f"run file {run}: cannot be written" in out, out
        writable = _copy(short_run, tmp_path / "w.h5")  # the fit could be stored, the rig file could not
        code, out = _fit(str(writable), "--export", str(ro / "fitted.toml"))
        assert code == 2 and "fitting the" not in out and f"--export {ro / 'fitted.toml'}: cannot be" in out, out
        assert not (tmp_path / "w.fit.hdf5").exists() and sorted(p.name for p in ro.iterdir()) == ["run.h5"]


def _interrupted_fit(args: list[str], run: Path, begun: str, after_s: float,
                     interrupt: Callable[[subprocess.Popen[str]], None]) -> tuple[str, str, list[str]]:
    """`bench fit RUN *args` (40 generations, no intervals) in a process of its own session, interrupted
    (``interrupt``) ``after_s`` after its output says ``begun``: (stdout, stderr, stderr's non-blank lines); the
    exit status checked to be SIGINT's (130)."""
    import sys
    import time

    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", "COLUMNS": "400"}
    proc = subprocess.Popen([sys.executable, "-m", "bench", "fit", str(run), *args, "--generations", "40",
                             "--no-intervals"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=_sigint_default)
    assert proc.stdout is not None and proc.stderr is not None
    seen = ""
    while begun not in seen:
        line = proc.stdout.readline()
        assert line, proc.stderr.read()
        seen += line
    time.sleep(after_s)
    interrupt(proc)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    return out, err, [ln for ln in err.splitlines() if ln.strip()]


def _sigint_default() -> None:
    """In the child before exec: SIGINT to its default, as a terminal's process has it. A suite started in the
    background (a non-interactive shell's ``&``) inherits SIGINT ignored, which the fit then rightly keeps: a
    process started ignoring Ctrl-C is meant to."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_stops_a_fit_within_a_batch_in_one_line_storing_nothing(short_run: Path, tmp_path: Path) -> None:
    """Ctrl-C on `bench fit` (the default three starts, searching in threads of their own) was taken by the main
    thread only, which then waited for every start to finish its search (2 min 20 s for the tester) and exited 130
    without a word. Now it stops at the starts' next batch: one line saying where, exit 130 (SIGINT's), no fit file.
    Stopped before the search's end: fewer generations done than asked (the line's count, all starts)."""
    import re
    import signal

    run = _copy(short_run, tmp_path / "run.h5")
    # the records read, the search begun, a few generations into it
    out, err, lines = _interrupted_fit([], run, "fitting the membrane model", 4.0,
                                       lambda proc: proc.send_signal(signal.SIGINT))
    assert len(lines) == 1, err
    m = re.fullmatch(r"fit stopped: Ctrl-C in the differential evolution, after (\d+) of 120 generations \(all "
                     r"starts\); nothing stored", lines[0])
    assert m is not None and int(m.group(1)) < 120, err
    assert "stored in" not in out and not (tmp_path / "run.fit.hdf5").exists()


def test_a_record_too_short_to_fit_is_refused_before_the_search(tmp_path: Path) -> None:
    """A run stopped 0.2 s into its drive (an outside tester's Ctrl-C): about a second of record, some hundred
    points for the membrane model's 16 parameters (physics.md Model A: μ0, J0 and four Maxwell units' μ, J, η — 14 —
    and the voltage monitor's gain and offset). The fit ran, printed intervals of ±9e+08 %, stored the result and
    exited 0; it is refused in one line (a fit needs ten points per parameter: 160), nothing stored."""
    def ctrl_c(engine: Engine, sim) -> None:  # type: ignore[no-untyped-def]
        def at(_now: float) -> None:
            if engine.snapshot.step == 0 and engine.program_now() > 0.2:
                engine.request_stop("Ctrl-C")
        sim.clock.subscribe(at)

    run = execute(plan_run(SHORT), tmp_path / "early.h5", virtual=True, on_engine=ctrl_c)
    assert run.state == "interrupted", run.reason
    code, out = _fit(str(run.path))
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and out.splitlines()[-1] == errors[0], out  # (after the stop's note)
    assert errors[0].startswith(f"error: run file {run.path}: ") and " measured points for 16 parameters (a fit " \
        "needs 10 per parameter, 160): too short a record to fit" in errors[0], out
    assert not Path(run.path).with_name("early.fit.hdf5").exists()


def test_a_killed_run_is_said_to_be_killed_before_the_fit(short_run: Path, tmp_path: Path) -> None:
    """A run killed (SIGKILL) and recovered was fitted as if it were whole: no note, `"stopped": []` in --json, where
    a Ctrl-C'd run gets its line (an outside tester). The file as `bench recover` leaves a killed run's: state
    running, not complete, `recovered_at` stamped."""
    killed = _copy(short_run, tmp_path / "killed.h5", recovered_at="2026-11-28T07:00:00+00:00")
    with h5py.File(killed, "r+") as f:
        f["status/state"][0] = b"running"
        f.attrs["complete"] = False
    code, out = _fit(str(killed), "--json")
    assert code == 0, out
    (note,) = json.loads(out)["stopped"]
    assert note.startswith(f"{killed}: run crashed or killed: recorded up to ") and note.endswith(
        "; fitting what was recorded"), note
