"""A manual-control session that ends at high voltage tells the terminal how the output was made safe (outside
tester: it printed only "session ended …", the "0 V … verified" line was in its log and file alone). README
("Manual control"): whatever ended it, the terminal gets the `safe` line's words as `bench run` says them,
`high voltage: 0 V commanded by the host at … s; verified: voltage monitor … V at … s`."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from bench.cli import app
from tests.conftest import ROOT

THESIS_RIG = ROOT / "rigs" / "thesis-sim.toml"
SAID = re.compile(r"high voltage: (0 V commanded by the host at \d+\.\d+ s; verified: voltage monitor -?\d+ V at "
                  r"\d+\.\d+ s)$")


def _safe_line(log: Path) -> str:
    """The `safe` line of the session log (tab-separated: wall time, run time, kind, command, text)."""
    (text,) = [r[4] for r in (ln.split("\t") for ln in log.read_text(encoding="utf-8").splitlines())
               if r[2] == "safe" and r[3] == "session"]
    return text


def test_a_script_that_ends_at_high_voltage_prints_the_verified_zero(tmp_path: Path) -> None:
    script, log = tmp_path / "s.txt", tmp_path / "s.log"
    script.write_text("voltage 1000\nwait 1\n", encoding="utf-8")
    res = CliRunner().invoke(app, ["devices", "control", str(THESIS_RIG), "--script", str(script), "--virtual-time",
                                   "--log", str(log)], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    said = [m.group(1) for ln in res.output.splitlines() if (m := SAID.search(ln.strip()))]
    assert said == [_safe_line(log)], res.output


def test_a_session_ended_by_ctrl_c_prints_the_verified_zero(tmp_path: Path) -> None:
    script, log = tmp_path / "s.txt", tmp_path / "s.log"
    script.write_text("voltage 1000\nwait 60\n", encoding="utf-8")
    proc = subprocess.Popen([sys.executable, "-m", "bench", "devices", "control", str(THESIS_RIG), "--script",
                             str(script), "--log", str(log)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "COLUMNS": "300"})
    try:
        assert proc.stdout is not None
        seen = []
        for line in proc.stdout:  # the set-point is on: Ctrl-C during the wait
            seen.append(line)
            if line.startswith("ok: set-point"):
                proc.send_signal(signal.SIGINT)
                break
        rest, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    out = "".join(seen) + rest
    assert proc.returncode == 1, out  # a signal ended the session (README)
    said = [m.group(1) for ln in out.splitlines() if (m := SAID.search(ln.strip()))]
    assert said == [_safe_line(log)], out
