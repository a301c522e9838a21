"""RUN.log beside RUN.h5 follows the run: one line per event as it happens, flushed at once (``tail -f``).

Expected run times come from the protocol file (thesis-sweeps-short: a 0-s chamber step, a 5-s drive, a 2-s
recovery, twice), not from the engine; the completed run's events are checked against the run file's /events.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest

from bench.storage.runfile import open_run
from tests.conftest import ROOT

SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"
THESIS = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
EVENT = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) INFO +\S+: event t=(-?[\d.]+) s step (-?\d+) "
                   r"(\w+): (.*)$")


def events(log: str) -> list[tuple[datetime, float, int, str, str]]:
    """The event lines of a run log: (wall-clock stamp, run time, step, kind, text)."""
    out = []
    for line in log.splitlines():
        m = EVENT.match(line)
        if m:
            out.append((datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f"), float(m[2]), int(m[3]), m[4], m[5]))
    return out


def _killed_at_the_second_chamber_step(folder: Path) -> str | None:
    """A real-time run of the sweeps killed (SIGKILL) once its log shows the second chamber step's start; its stderr
    where it ended by itself before (a loaded host: a stall or a starved twin's missing reply), else None."""
    folder.mkdir()
    env = {**os.environ, "BENCH_STATE_DIR": str(folder / "state")}  # (a run that ends so latches its rig)
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(SWEEPS), "--out", str(folder), "--no-live"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            stdin=subprocess.DEVNULL, env=env)
    try:
        deadline = time.monotonic() + 120  # a guard against a hung run, not a timing claim
        seen: list[tuple[datetime, float, int, str, str]] = []
        while time.monotonic() < deadline and proc.poll() is None:
            logs = list(folder.glob("*.log"))
            seen = events(logs[0].read_text(encoding="utf-8")) if logs else []
            if any(step == 3 and kind == "start" for _, _, step, kind, _ in seen):  # the second chamber step
                break
            time.sleep(0.05)
        if proc.poll() is not None:
            return proc.communicate()[1]
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)
    return None


def test_a_killed_run_s_log_already_holds_its_step_starts_each_at_its_own_time(tmp_path: Path) -> None:
    ended = _killed_at_the_second_chamber_step(tmp_path / "try0")
    folder = tmp_path / "try0"
    if ended is not None:  # once more on a loaded host; a second run that ends by itself fails the test
        print(f"the run ended before it was killed (a loaded machine): {ended}")
        folder = tmp_path / "try1"
        ended = _killed_at_the_second_chamber_step(folder)
    assert ended is None, f"the run ended before it was killed: {ended}"
    (log_file,) = folder.glob("*.log")
    log = log_file.read_text(encoding="utf-8")
    assert "completed" not in log and "high voltage:" not in log  # killed: no end-of-run lines
    starts = {step: (wall, t) for wall, t, step, kind, _ in events(log) if kind == "start"}
    kinds = [kind for _, _, _, kind, _ in events(log)]
    assert "stop" not in kinds and "safe" not in kinds
    # each step start once, in order, up to the one the kill came in (step 4, the drive, starts with step 3)
    assert sorted(starts) == list(range(len(starts))) and 4 <= len(starts) <= 5 and kinds.count("start") == len(starts)
    # run times from the protocol: drive (step 1) at 0 s, recovery (2) after the 5-s drive, the next chamber (3)
    # after the 2-s recovery (a streamed step ends when its last scans are collected: late by a collect period or
    # more on a loaded machine, never early)
    # the drive's program time is 0 s: never early; late by the 0-s chamber step's work on a loaded machine
    assert -1e-3 <= starts[1][1] < 1.0
    assert 5.0 - 1e-3 <= starts[2][1] < starts[3][1] and 7.0 - 1e-3 <= starts[3][1] < 8.0
    walls = [starts[k][0] for k in (1, 2, 3)]
    assert walls[0] < walls[1] < walls[2]  # each written when it happened (a real-time run: seconds apart)


def test_a_completed_run_s_log_has_each_event_of_the_file_once_and_q_prints_only_its_path(tmp_path: Path) -> None:
    # as a script runs it: f=$(bench -q run …) — stdout is the run file's path, one line, nothing else
    proc = subprocess.run([sys.executable, "-m", "bench", "-q", "run", str(THESIS), "--virtual-time", "--out",
                           str(tmp_path)], capture_output=True, text=True, cwd=ROOT, stdin=subprocess.DEVNULL,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    (run_file,) = tmp_path.glob("*.h5")
    assert proc.stdout == f"{run_file}\n"
    logged = events(run_file.with_suffix(".log").read_text(encoding="utf-8"))
    stored = open_run(run_file, streams=False).event_list()
    assert len(stored) >= 6  # run start, 2 × (step start, end), stop, safe
    assert [(f"{t:.3f}", step, kind) for _, t, step, kind, _ in logged] == \
        [(f"{t:.3f}", step, kind) for t, step, kind, _ in stored]
    for (_, _, _, _, text), (_, _, _, stored_text) in zip(logged, stored, strict=True):
        assert text.startswith(stored_text)  # the file keeps at most 200 bytes of a text
    walls = [w for w, *_ in logged]
    assert walls == sorted(walls)


def test_what_ended_the_command_is_the_log_s_last_line(tmp_path: Path) -> None:
    """A failure that ends `bench run` inside its log (a dead port while connecting) is the log's last line: before,
    the log ended at 'connecting the instruments' and the reason was on the terminal only (found from outside)."""
    from bench.cli.logs import run_log

    run = tmp_path / "r.h5"
    with pytest.raises(OSError), run_log(run) as log_file:
        raise OSError("laser at /dev/ttyUSB9: cannot open the port\n(no such device)")
    last = log_file.read_text(encoding="utf-8").splitlines()[-1]
    assert "not completed: laser at /dev/ttyUSB9: cannot open the port (no such device)" in last


def test_a_stop_signal_raised_while_the_log_is_written_reaches_the_run(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A stop signal's handler raises where the main thread is (bench.runtime.engine.termination_raises); landing in
    the run log's flush, logging printed it as a "Logging error" traceback and swallowed it, and the run went on
    homing the motor (seen in the suite's signal-while-homing test). It must go on to the run."""
    import logging

    from bench.cli.logs import run_log
    from drivers.errors import OperationCancelledError

    def stopped() -> None:
        raise OperationCancelledError("run", "interrupted by Ctrl-C while enabling and homing the motor")

    with run_log(tmp_path / "run.h5"):
        handler = next(h for h in logging.getLogger("bench").handlers if isinstance(h, logging.FileHandler))
        assert handler.stream is not None
        handler.stream.flush = stopped  # type: ignore[method-assign]  # the signal arrives inside the flush
        with pytest.raises(OperationCancelledError, match="interrupted by Ctrl-C"):
            logging.getLogger("bench.runtime.run").info("enabling and homing the motor")
        handler.stream.flush = lambda: None  # type: ignore[method-assign]
    assert "Logging error" not in capsys.readouterr().err


def test_a_stop_raised_in_the_console_write_leaves_the_run_log_its_line(tmp_path: Path) -> None:
    """The run log's handler comes before the console's: a stop signal landing in the console's write (re-raised,
    see above) no longer keeps the line from the run's log file (review finding)."""
    import logging

    from bench.cli.logs import _stderr, run_log
    from drivers.errors import OperationCancelledError

    def stopped(_record: logging.LogRecord) -> None:
        raise OperationCancelledError("run", "interrupted by Ctrl-C while connecting")

    with run_log(tmp_path / "run.h5") as log_file, pytest.MonkeyPatch.context() as mp:
        mp.setattr(_stderr, "emit", stopped)
        mp.setattr(_stderr, "level", logging.DEBUG)
        with pytest.raises(OperationCancelledError):
            logging.getLogger("bench.runtime.run").warning("connecting the instruments")
    assert "connecting the instruments" in log_file.read_text(encoding="utf-8")
