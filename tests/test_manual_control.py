"""bench devices control: manual commands on a simulated rig under the supervisor, every action in the log."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import load_rig
from bench.runtime.manual import ManualSession, Refused

ROOT = Path(__file__).resolve().parent.parent
MOTOR_RIG = ROOT / "rigs" / "lsdea-motor-sim.toml"


def _volts(text: str) -> float:
    return float(re.search(r"voltage (-?\d+) V", text).group(1))  # type: ignore[union-attr]


def test_session_on_the_motor_rig_end_to_end_with_limit_refusals(tmp_path: Path) -> None:
    rig = load_rig(MOTOR_RIG)
    limit_mm = rig.motor.travel_m[1] * 1e3  # type: ignore[union-attr]
    script = "\n".join([
        "# set, move, jog, tare, watch, ramp, refusals, zero",
        "voltage 2kV",
        "move 20",
        "jog -5 mm 10 mm/s",
        "wait 3 s",
        "tare",
        "watch 1 0.25",
        "ramp 1 kV 1 s",
        f"voltage {rig.limits.max_voltage_V + 1000:g} V",
        f"move {limit_mm + 10:g}",
        "read",
        "zero",
        "quit",
        "voltage 1kV",  # after quit: never executed
    ])
    log = tmp_path / "session.log"
    res = CliRunner().invoke(app, ["devices", "control", str(MOTOR_RIG), "--virtual-time", "--log", str(log)],
                             input=script)
    assert res.exit_code == 1, res.output  # two commands were refused
    rows = [line.split("\t") for line in log.read_text(encoding="utf-8").splitlines()]
    commands = [(r[3], r[2]) for r in rows if r[3] not in ("session", "connect", "watch")]
    assert commands == [("voltage 2kV", "ok"), ("move 20", "ok"), ("jog -5 mm 10 mm/s", "ok"), ("wait 3 s", "ok"),
                        ("tare", "ok"), ("watch 1 0.25", "ok"), ("ramp 1 kV 1 s", "ok"),
                        (f"voltage {rig.limits.max_voltage_V + 1000:g} V", "refused"),
                        (f"move {limit_mm + 10:g}", "refused"), ("read", "ok"), ("zero", "ok")]
    by_cmd = {r[3]: r[4] for r in rows}
    assert abs(_volts(by_cmd["voltage 2kV"]) - 2000) < 30  # measured by the monitor, not the set-point
    assert "motor 20.000 mm" in by_cmd["move 20"] and "motor 15.000 mm" in by_cmd["jog -5 mm 10 mm/s"]
    assert abs(float(re.search(r"force (-?[\d.]+) N", by_cmd["tare"]).group(1))) < 0.05  # type: ignore[union-attr]
    assert len([r for r in rows if r[3] == "watch" and r[2] == "read"]) == 4
    assert "beyond the voltage limit" in by_cmd[f"voltage {rig.limits.max_voltage_V + 1000:g} V"]
    assert "outside travel" in by_cmd[f"move {limit_mm + 10:g}"]
    assert abs(_volts(by_cmd["read"]) - 1000) < 30  # the refused set-point never reached the amplifier
    assert rows[0][3] == "session" and rows[-1][3:5] == ["session", "instruments safe and closed"]
    assert "1kV" not in log.read_text(encoding="utf-8").split("quit")[-1]
    assert "2 not done" in res.output


def test_refused_set_point_and_a_breakdown_trip_leave_the_rig_safe(tmp_path: Path) -> None:
    rig = load_rig(ROOT / "rigs" / "thesis-sim.toml")
    seen: list[str] = []
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=seen.append) as s:
        assert s.execute("voltage 5 kV").status == "ok"
        assert s.execute("read").text.count("displacement") == 1
        out = s.execute(f"voltage {rig.limits.max_voltage_V + 1:g}")
        assert out.status == "refused" and "not sent" in out.text
        assert s.execute("nonsense 3").status == "refused"
        s._sim.plant.inject_breakdown()  # the specimen fails: the current monitor trips the supervisor
        trip = s.execute("watch 2 0.5")
        assert trip.status in ("trip", "error"), trip
        assert "output zeroed" in trip.text
        assert s.execute("wait 1").status == "ok"  # fresh monitor conversions (10 S/s)
        after = s.execute("read")
        assert after.status == "ok" and abs(_volts(after.text)) < 100, after
    text = (tmp_path / "s.log").read_text(encoding="utf-8")
    assert "\ttrip\t" in text or "\terror\t" in text
    assert text.rstrip().endswith("instruments safe and closed")


def test_control_refuses_virtual_time_on_a_real_rig(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["devices", "control", str(ROOT / "rigs" / "thesis-lab.toml"), "--virtual-time",
                                   "--log", str(tmp_path / "x.log")], input="read\n")
    assert res.exit_code == 2 and "virtual time needs a simulated rig" in res.output


# ---------------------------------------------------------------- hardening (tester issue: signals, missing
# instruments, driver errors, stale answers, prompt, operator). The output is read from the simulated plant
# (the amplifier's output stage as the twin integrates it), not from the session's own readings.
THESIS_RIG = ROOT / "rigs" / "thesis-sim.toml"
ZERO_V = 5.0  # one code of the 12-bit ADAM-4024 times the TREK gain: 0 V itself has no code (±2.44 V)
SIGNALS = {signal.SIGINT: "interrupted by Ctrl-C", signal.SIGTERM: "terminated by SIGTERM",
           signal.SIGHUP: "hang-up (SIGHUP", signal.SIGQUIT: "quit requested (SIGQUIT)"}


def _rows(log: Path) -> list[list[str]]:
    return [line.split("\t") for line in log.read_text(encoding="utf-8").splitlines()]


def _plant_volts(sim, settle: float = 0.2) -> float:
    """The amplifier output in the plant after ``settle`` more virtual seconds."""
    sim.clock.advance(settle)
    return float(sim.plant.observe().v_out[-1])


def test_commands_of_an_absent_instrument_are_refused_and_nothing_changes(tmp_path: Path) -> None:
    rig = load_rig(THESIS_RIG)  # amplifier and laser: no motor, no load cell
    assert rig.motor is None and rig.load_cell is None
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 3kV").status == "ok"
        for line, what in [("move 5", "motor"), ("move 5 mm 10 mm/s", "motor"), ("jog -1 mm", "motor"),
                           ("stop", "motor"), ("tare", "load cell"), ("zero-cell", "load cell")]:
            out = s.execute(line)
            assert (out.status, out.text) == ("refused", f"this rig has no {what}"), out
        assert abs(_plant_volts(s._sim) - 3000) < 30  # the refusals neither zeroed nor changed the output
        assert s.execute("read").status == "ok"  # the session goes on


def test_commands_of_an_absent_amplifier_are_refused(tmp_path: Path) -> None:
    base = load_rig(MOTOR_RIG)
    rig = type(base).model_validate({**base.model_dump(), "amplifier": None})
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        for line in ("voltage 1kV", "ramp 1kV 1s", "zero"):
            assert (s.execute(line).status, s.outcomes[-1].text) == ("refused", "this rig has no amplifier")
        assert s.execute("move 10").status == "ok"


def test_a_motor_drive_error_during_a_move_is_an_error_line_and_the_output_is_zeroed(tmp_path: Path) -> None:
    from sim_devices.linmot_drive import ERR_MAX_POS_OVERSHOT

    with ManualSession(load_rig(MOTOR_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        motor, twin = s._inst.motor, s._sim.twins["motor"]
        move_to = motor.move_to

        def failing_move(*args, **kwargs) -> None:  # the drive accepts the move, then faults
            move_to(*args, **kwargs)
            twin.inject_error(ERR_MAX_POS_OVERSHOT)
        motor.move_to = failing_move
        out = s.execute("move 30")
        # said by the move's own status loop or by the encoder's poll in between (a run's move step polls it)
        assert out.status == "error" and re.search(r"motor: drive (reports )?error", out.text), out
        assert "output zeroed" in out.text, out
        assert abs(_plant_volts(s._sim)) < ZERO_V
        assert s.execute("read").status == "ok"


def _error_classes() -> list[type[Exception]]:
    import drivers.errors

    found = [c for c in vars(drivers.errors).values() if isinstance(c, type) and issubclass(c, Exception)]
    assert len(found) >= 7 and drivers.errors.InstrumentError in found  # InstrumentError and its subclasses
    return found


@pytest.mark.parametrize("exc_class", [*_error_classes(), AssertionError, TypeError, RuntimeError],
                         ids=lambda c: c.__name__)
def test_any_exception_in_a_command_is_one_line_and_the_session_goes_on(tmp_path: Path, exc_class) -> None:
    from drivers.errors import InstrumentError, LimitError

    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        laser = s._inst.laser
        read = laser.read_displacement

        def fail():
            from drivers.errors import ImplausibleValueError, StreamEndedError
            from drivers.interfaces import StreamBlock

            if exc_class is ImplausibleValueError:
                raise ImplausibleValueError("laser", "displacement", 1e9, (-1.0, 1.0), "m", "first line\nsecond line")
            if exc_class is StreamEndedError:  # with the scans it carries (none here)
                empty = StreamBlock(0, 0.0, 1e-4, ("AIN0",), np.empty((0, 1)), np.empty((0, 1), bool), 0, 0, (2943,),
                                    True)
                raise StreamEndedError("laser", "first line\nsecond line", empty)
            raise exc_class("laser", "first line\nsecond line") if issubclass(exc_class, InstrumentError) \
                else exc_class("first line\nsecond line")
        laser.read_displacement = fail
        out = s.execute("read")
        laser.read_displacement = read
        assert "\n" not in out.text and "second line" in out.text
        if exc_class is LimitError:  # "nothing was sent": a refusal, the output stays
            assert out.status == "refused"
            assert abs(_plant_volts(s._sim) - 2000) < 30
        else:
            assert out.status == "error" and "output zeroed" in out.text, out
            assert abs(_plant_volts(s._sim)) < ZERO_V
        assert s.execute("voltage 1kV").status == "ok"
        assert abs(_plant_volts(s._sim) - 1000) < 30
    assert _rows(tmp_path / "s.log")[-1][2:4] == ["end", "session"]


def test_escape_sequences_and_odd_lines_are_one_line_refusals(tmp_path: Path) -> None:
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        for line in ("\x1b[A", "\x1b[B\x1b[A", "voltage\t3kV\x1b[D", "'unbalanced", "read extra words here"):
            out = s.execute(line)
            assert out.status == "refused" and "\x1b" not in out.text + out.command, out
    for row in _rows(tmp_path / "s.log"):
        assert len(row) == 5, row  # no tab or newline from a command broke the log's columns


def test_a_unit_of_the_wrong_kind_is_named_not_wrong_arguments(tmp_path: Path) -> None:
    """``voltage 77 °F`` said "wrong arguments" (outside tester): a unit that starts with a symbol (°, Ω, %) belongs
    to the number before it as a letter's does, and the refusal names the unit."""
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        for line in ("voltage 77 °F", "voltage 5 Ω", "voltage 3 %"):
            out = s.execute(line)
            assert out.status == "refused" and "wrong arguments" not in out.text, out
            assert line.split()[-1] in out.text, out
        assert abs(_plant_volts(s._sim)) < ZERO_V  # nothing sent


@pytest.mark.parametrize("asked", [3000, 5000, 1000, 0, 7000, -2000])
def test_a_voltage_answer_names_the_set_point_just_sent(tmp_path: Path, asked: float) -> None:
    """Virtual time: no time passes between commands, so the slew limit cut the first send to a few volts and
    the answer named the previous set-point (tester report: ``voltage 3kV`` answered 2 V)."""
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 4kV").status == "ok"  # a previous set-point
        out = s.execute(f"voltage {asked} V")
        sent = float(re.search(r"set-point (-?\d+) V", out.text).group(1))  # type: ignore[union-attr]
        assert abs(sent - asked) <= ZERO_V, out  # within one code of what was asked
        assert abs(_volts(out.text) - asked) < 30, out  # and the monitor reading in the answer shows it
        assert abs(float(s._sim.plant.observe().v_out[-1]) - asked) < 30


def test_the_operator_is_in_the_log_header(tmp_path: Path) -> None:
    log = tmp_path / "s.log"
    res = CliRunner().invoke(app, ["devices", "control", str(THESIS_RIG), "--virtual-time", "--log", str(log),
                                   "--operator", "Ada Lovelace"], input="read\n")
    assert res.exit_code == 0, res.output
    rows = _rows(log)
    assert rows[0][2:4] == ["start", "session"] and rows[0][4].endswith("operator Ada Lovelace")
    assert rows[1][2:5] == ["operator", "session", "Ada Lovelace"]
    bad = CliRunner().invoke(app, ["devices", "control", str(THESIS_RIG), "--virtual-time", "--log",
                                   str(tmp_path / "b.log"), "--operator", "two\nlines"], input="read\n")
    assert bad.exit_code == 2 and "--operator" in bad.output and not (tmp_path / "b.log").exists()


# ---------------------------------------------------------------- signals (in this process: interactive mode)
def _session_with_signals(tmp_path: Path, lines: list[str], on_watch_line, interactive: bool = True):
    """Run ``lines`` in a session with the stop-signal handlers; ``on_watch_line(n)`` after the n-th watch
    reading. Returns the session, its log rows and the plant's output (after the session) and its history."""
    rig = load_rig(THESIS_RIG)
    seen: list[int] = []
    history: list[tuple[float, float]] = []

    def echo(text: str) -> None:
        if text.startswith("t "):
            seen.append(1)
            on_watch_line(len(seen))

    s = ManualSession(rig, tmp_path / "s.log", virtual=True, echo=echo)
    with s.signal_handlers(interactive=interactive), s:
        sim = s._sim
        sim.plant.listeners.append(lambda b: history.extend(zip(b.t.tolist(), b.v_out.tolist(), strict=True)))
        s.run_lines(lines, stop_on_trip=not interactive)
    return s, _rows(tmp_path / "s.log"), _plant_volts(sim), history


def _kill(*sigs: int):
    def send(n: int) -> None:
        if n == 1:
            for sig in sigs:
                os.kill(os.getpid(), sig)
    return send


def test_ctrl_c_ends_the_command_not_the_session(tmp_path: Path) -> None:
    old = signal.getsignal(signal.SIGINT)
    s, rows, after, _ = _session_with_signals(tmp_path, ["voltage 2kV", "watch 3600 0.5", "read", "wait 2", "read",
                                                         "zero"], _kill(signal.SIGINT))
    assert signal.getsignal(signal.SIGINT) is old  # handlers restored
    assert [o.status for o in s.outcomes] == ["ok", "interrupted", "ok", "ok", "ok", "ok"]
    assert "interrupted by Ctrl-C: command ended" in s.outcomes[1].text
    assert len([r for r in rows if r[3] == "watch"]) == 1  # one reading, not 7200
    assert abs(_volts(s.outcomes[4].text) - 2000) < 30  # output held through the interrupt and the wait
    assert s.end_reason is None and rows[-1][2:5] == ["end", "session", "instruments safe and closed"]
    assert abs(after) < ZERO_V


def test_a_second_ctrl_c_ends_the_session_safely(tmp_path: Path) -> None:
    s, rows, after, history = _session_with_signals(
        tmp_path, ["voltage 3kV", "watch 3600 0.5", "read", "voltage 1kV"], _kill(signal.SIGINT, signal.SIGINT))
    assert [o.command for o in s.outcomes] == ["voltage 3kV", "watch 3600 0.5"]  # nothing after the second
    assert s.outcomes[1].status == "interrupted" and "the session ends" in s.outcomes[1].text
    assert rows[-1][2:5] == ["end", "session", "interrupted by Ctrl-C; instruments safe and closed"]
    assert abs(after) < ZERO_V
    assert max(abs(v) for _, v in history) > 2900  # there was high voltage to remove


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT], ids=lambda s: s.name)
def test_a_stop_signal_ends_an_interactive_session_through_the_exit_ramp(tmp_path: Path, sig: int) -> None:
    s, rows, after, history = _session_with_signals(tmp_path, ["voltage 3kV", "watch 3600 0.5", "read"],
                                                    _kill(sig))
    assert [o.status for o in s.outcomes] == ["ok", "interrupted"]
    # the engine's bounded stop: the ramp, then 0 V verified on the monitor, then the session's end line
    assert rows[-3][2:4] == ["ramp", "session"] and "to 0 V over 0.25 s" in rows[-3][4]
    assert rows[-2][2:4] == ["safe", "session"] and "verified: voltage monitor" in rows[-2][4]
    assert rows[-1][2] == "end" and rows[-1][4].startswith(SIGNALS[sig])
    assert abs(after) < ZERO_V
    # ramped, not dropped: the plant passed through the middle of the range on the way down
    assert any(1000 < v < 2000 for _, v in history)


# ---------------------------------------------------------------- signals to a real `bench devices control`
_OBSERVED_CLI = """
import json, sys
from bench.runtime import sim_rig
from bench.cli import app

trace = []
start, stop = sim_rig.SimRig.start, sim_rig.SimRig.stop

def observed_start(self):
    self.plant.listeners.append(lambda b: trace.extend(zip(b.t.tolist(), b.v_out.tolist())))
    return start(self)

def observed_stop(self):  # the output once the session has made the rig safe, 0.2 s later on the rig clock
    self.clock.advance(0.2)
    self.plant.observe()
    with open(sys.argv[1], "w") as f:
        json.dump(trace[::10] + trace[-1:], f)
    stop(self)

sim_rig.SimRig.start, sim_rig.SimRig.stop = observed_start, observed_stop
app(prog_name="bench", args=sys.argv[2:])
"""


def _signal_a_cli_session(tmp_path: Path, sig: int, busy: bool) -> tuple[int, list[list[str]], list[list[float]]]:
    """`bench devices control` in a child process, commands piped in (script mode): 3 kV, then ``sig`` while a
    long watch runs (``busy``) or while it waits for the next command."""
    log, trace = tmp_path / "s.log", tmp_path / "trace.json"
    proc = subprocess.Popen([sys.executable, "-c", _OBSERVED_CLI, str(trace), "devices", "control",
                             str(THESIS_RIG), "--virtual-time", "--log", str(log)], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write("voltage 3kV\n" + ("watch 3600 0.5\n" if busy else ""))
        proc.stdin.flush()
        wanted = "ok: set-point" if not busy else "t 0.80 s:"  # 3 kV answered; or the watch under way
        for line in proc.stdout:
            if wanted in line:
                break
        proc.send_signal(sig)
        proc.communicate(timeout=60)  # stdin stays open: only the signal ends the session
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, _rows(log), json.loads(trace.read_text())


@pytest.mark.parametrize("sig", list(SIGNALS), ids=lambda s: s.name)
def test_a_signal_to_a_scripted_session_during_a_command_zeroes_the_output(tmp_path: Path, sig: int) -> None:
    code, rows, trace = _signal_a_cli_session(tmp_path, sig, busy=True)
    assert code == 1
    assert max(abs(v) for _, v in trace) > 2900 and abs(trace[-1][1]) < ZERO_V
    assert [(r[2], r[3]) for r in rows if r[3] not in ("connect", "watch")] == [
        ("start", "session"), ("operator", "session"),  # who (the login name: no --operator)
        ("ok", "voltage 3kV"), ("interrupted", "watch 3600 0.5"),  # the watch ended,
        ("request", "session"), ("interrupted", "session"),  # the engine's stop: the request, why it stopped,
        ("ramp", "session"), ("safe", "session"), ("end", "session")]  # the exit ramp, 0 V verified, the end
    assert rows[-1][4].startswith(SIGNALS[sig])


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_a_signal_to_a_session_waiting_for_a_command_zeroes_the_output(tmp_path: Path, sig: int) -> None:
    code, rows, trace = _signal_a_cli_session(tmp_path, sig, busy=False)
    assert code == 1
    assert max(abs(v) for _, v in trace) > 2900 and abs(trace[-1][1]) < ZERO_V
    assert rows[-1][2] == "end" and rows[-1][4].startswith(SIGNALS[sig])


# ---------------------------------------------------------------- the interactive prompt, on a pseudo-terminal
def _read_until(fd: int, wanted: str, seen: list[str], timeout: float = 60.0) -> None:
    """Read the terminal until ``wanted`` has appeared once more than it had (``seen`` accumulates the text)."""
    import select

    count = "".join(seen).count(wanted)
    while "".join(seen).count(wanted) <= count:
        ready, _, _ = select.select([fd], [], [], timeout)
        assert ready, f"no {wanted!r} on the terminal; so far: {''.join(seen)[-500:]!r}"
        seen.append(os.read(fd, 4096).decode("utf-8", "replace"))


def _prompts(fd: int, n: int, seen: list[str], timeout: float = 60.0) -> None:
    """Read the terminal until the prompt has been shown ``n`` times in all."""
    import select

    while "".join(seen).count("bench> ") < n:
        ready, _, _ = select.select([fd], [], [], timeout)
        assert ready, f"prompt {n} not shown; so far: {''.join(seen)[-500:]!r}"
        seen.append(os.read(fd, 4096).decode("utf-8", "replace"))


def test_the_prompt_has_line_editing_and_a_history_file_in_home(tmp_path: Path) -> None:
    pytest.importorskip("readline")
    import pty

    home, log = tmp_path / "home", tmp_path / "s.log"
    home.mkdir()
    (home / ".bench_history").write_text("wait 0.5\n", encoding="utf-8")  # an earlier session's last command
    master, slave = pty.openpty()
    env = {**os.environ, "HOME": str(home), "TERM": "xterm", "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "bench", "devices", "control", str(THESIS_RIG),
                             "--virtual-time", "--log", str(log)], cwd=ROOT, env=env,
                            stdin=slave, stdout=slave, stderr=slave)
    os.close(slave)
    seen: list[str] = []
    try:
        # each key sequence only once the prompt is back: keys typed while readline is not reading can be lost
        _read_until(master, "bench> ", seen)
        os.write(master, b"\x1b[A\r")  # ↑: the earlier session's command
        _read_until(master, "waited 0.5 s", seen)
        _prompts(master, 2, seen)
        os.write(master, b"\x1b[A\x1b[D\x1b[D\x1b[D1\r")  # ↑ again, ← three times, "1": "wait 10.5"
        _read_until(master, "waited 10.5 s", seen)
        _prompts(master, 3, seen)
        os.write(master, b"read\r")
        _read_until(master, "ok: t ", seen)
        _prompts(master, 4, seen)
        os.write(master, b"\x04")  # Ctrl-D: end of input
        assert proc.wait(timeout=60) == 0, "".join(seen)[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    commands = [(r[3], r[2]) for r in _rows(log) if r[3] not in ("session", "connect")]
    assert commands == [("wait 0.5", "ok"), ("wait 10.5", "ok"), ("read", "ok")], commands
    assert (home / ".bench_history").read_text(encoding="utf-8").splitlines()[-3:] == \
        ["wait 0.5", "wait 10.5", "read"]


# ---------------------------------------------------------------- latched interlock (bench/runtime/interlock.py)
def _trace(sim) -> list[tuple[float, float]]:
    """Everything the plant's output stage did (rig clock, volts): observed from the plant, not the session."""
    out: list[tuple[float, float]] = []
    sim.plant.listeners.append(lambda b: out.extend(zip(b.t.tolist(), b.v_out.tolist(), strict=True)))
    return out


@pytest.mark.parametrize("where", ["in a command", "at the prompt", "at the exit"])
def test_a_host_stall_longer_than_the_watchdog_latches_and_high_voltage_never_comes_back(
        tmp_path: Path, where: str) -> None:
    """Tester: the host frozen longer than the module's watchdog (SIGSTOP 3 s / SIGCONT) — on resume the session
    wrote 5 kV again. Here the session's threads are frozen while the twins, the plant and the ADAM-4024's 1-s
    watchdog (rig file default) run on: inside a command's keep-alive wait (the keep-alive thread waits for the
    command's lock), at the prompt (the test holds that lock: not even the keep-alive thread runs), or just
    before the session is left (its exit would ramp down from 3 kV)."""
    import time

    rig = load_rig(THESIS_RIG)
    freeze = 2.5  # s, longer than the 1-s watchdog
    seen: list[str] = []
    s = ManualSession(rig, tmp_path / "s.log", echo=seen.append, operator="Ada Lovelace")  # real time
    with s:
        sim = s._sim
        trace = _trace(sim)
        assert s.execute("voltage 3kV").status == "ok"
        t_freeze = sim.clock.now()
        if where == "in a command":
            ctx = s.engine.ctx  # the run context's wait: what the engine's hold waits in
            wait = ctx.wait_until

            def stalled(t: float) -> None:
                ctx.wait_until = wait  # type: ignore[method-assign]
                time.sleep(freeze)
                wait(t)
            ctx.wait_until = stalled  # type: ignore[method-assign]
            out = s.execute("wait 1")
            assert out.status == "trip" and "interlock: host stall" in out.text and "latched" in out.text, out
        elif where == "at the prompt":
            with s._lock:
                time.sleep(freeze)
            deadline = time.monotonic() + 30  # hang guard
            while not any(line.startswith("trip: interlock: host stall") for line in seen):
                assert time.monotonic() < deadline, seen
                time.sleep(0.05)
        else:
            s._lock.acquire()  # held through the exit: the keep-alive thread never gets to write
            time.sleep(freeze)
        if where != "at the exit":
            for line in ("voltage 2kV", "ramp 2kV 1s", "voltage 3kV"):
                out = s.execute(line)
                assert out.status == "refused" and "latched" in out.text and "host stall" in out.text, out
            assert s.execute("wait 0.5").status == "ok"  # nothing that energises is refused
            assert s.execute("reset").status == "refused"  # a reset needs a reason
            sim.plant.observe()
            t_reset = sim.clock.now()
            out = s.execute("reset because the laptop slept; rig checked")
            assert out.status == "ok" and "Ada Lovelace" in out.text and "because the laptop slept" in out.text, out
            assert s.execute("voltage 2kV").status == "ok"
            assert abs(float(sim.plant.observe().v_out[-1]) - 2000) < 30  # accepted, and the plant has it
    if where == "at the exit":
        s._lock.release()
        t_reset = math.inf
    rows = _rows(tmp_path / "s.log")
    (latched,) = [r for r in rows if r[2:4] == ["latched", "interlock"]]
    assert "host stall" in latched[4] and "stays off" in latched[4]
    if where == "at the exit":
        (ramp,) = [r for r in rows if r[2] == "ramp"]
        assert ramp[3] == "session" and "0 V at once, no ramp" in ramp[4]
    else:
        (reset,) = [r for r in rows if r[3].startswith("reset because")]
        assert reset[2] == "ok" and "Ada Lovelace" in reset[4]
    # the plant: high voltage before the freeze; zeroed by the module's watchdog during it; never again until the
    # operator's reset
    held = [(t, v) for t, v in trace if t < t_freeze]
    assert max(abs(v) for _, v in held) > 2900
    after = [(t, v) for t, v in trace if t_freeze <= t < t_reset]
    zeroed = next(t for t, v in after if abs(v) <= ZERO_V)
    assert zeroed < t_freeze + freeze
    assert max(abs(v) for t, v in after if t >= zeroed) <= ZERO_V, "high voltage came back after the stall"


def test_a_monitor_that_disagrees_with_the_set_point_latches_the_output_off(tmp_path: Path) -> None:
    """Verified outputs: the amplifier's gain 25 % off (a calibration outside its tolerance) — the monitor reads
    5 kV where 4 kV is commanded (beyond 100 V + 5 %, README "Interlock"): two readings in a row latch."""
    import dataclasses

    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 4kV").status == "ok"
        hv = s._sim.plant.hv
        s._sim.plant.hv = dataclasses.replace(hv, gain=hv.gain * 1.25)
        out_trip = s.execute("watch 5 0.25")
        assert out_trip.status == "trip" and "interlock: output mismatch" in out_trip.text, out_trip
        assert "latched" in out_trip.text
        assert abs(_plant_volts(s._sim)) < ZERO_V
        out = s.execute("voltage 1kV")
        assert out.status == "refused" and "latched" in out.text and "output mismatch" in out.text
        assert abs(_plant_volts(s._sim)) < ZERO_V
    # one reading out of the band, the second latched (the monitors are polled between the watch's readings too,
    # as in a run's hold: the trip may come before the watch's first): the trip names it
    assert len([r for r in _rows(tmp_path / "s.log") if r[3] == "watch"]) <= 1
    from bench.storage.runfile import open_run

    run = open_run(tmp_path / "s.h5")  # the readings' file: still latched at the end
    assert run.state == "tripped" and "interlock latched" in run.reason
    (latched,) = [text for _, _, kind, text in run.event_list() if kind == "latched"]
    assert "(output mismatch)" in latched and "stays off" in latched
    assert run.streams["amplifier"].columns["voltage"].max() > 4900  # the reading that latched is on file
    assert (run.streams["amplifier"].columns["voltage"] > 4500).sum() == 2  # README: two readings in a row latch
    measured, commanded = map(float, re.search(r"read (-?\d+) V .* where (-?\d+) V was commanded",  # type: ignore[union-attr]
                                               out_trip.text).groups())
    assert abs(commanded - 4000) <= ZERO_V and abs(measured - 1.25 * 4000) < 50, out_trip
    # the latch outlives the session: the next session (and any run) on this rig starts latched
    from bench.runtime.latch import latched

    assert latched(load_rig(THESIS_RIG).name) is not None
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s2.log", virtual=True, echo=lambda _t: None,
                       operator="ada") as s:
        out = s.execute("voltage 1kV")
        assert out.status == "refused" and "latched before this session" in out.text
        assert s.execute("read").status == "ok"  # reading is allowed while latched
        assert s.execute("reset gain recalibrated").status == "ok"
        assert s.execute("voltage 1kV").status == "ok"
        assert abs(_plant_volts(s._sim) - 1000) < 50
    assert latched(load_rig(THESIS_RIG).name) is None


# ---------------------------------------------------------------- readings to HDF5 (bench/storage/recorder.py)
_READING = re.compile(r"t (?P<t>[\d.]+) s: voltage (?P<v>-?\d+) V, current (?P<i>-?[\d.]+) µA, motor "
                      r"(?P<m>-?[\d.]+) mm.*, force (?P<f>-?[\d.]+) N")  # the motor rig: no laser


def _nearest(stream, t: float, column: str) -> float:
    k = int(np.argmin(np.abs(stream.t - t)))
    assert abs(stream.t[k] - t) <= 0.01, (stream.name, t, stream.t[k])  # the log prints t to 10 ms
    return float(stream.columns[column][k])


def test_a_scripted_session_records_readings_commands_and_its_end_in_an_hdf5_file(tmp_path: Path) -> None:
    from bench.storage.runfile import open_run

    script, log = tmp_path / "cmds.txt", tmp_path / "session.log"
    script.write_text("voltage 2kV\nmove 20\nread\nwatch 1 0.25\nvoltage 20kV\nramp 1kV 0.5s\n", encoding="utf-8")
    res = CliRunner().invoke(app, ["devices", "control", str(MOTOR_RIG), "--virtual-time", "--log", str(log),
                                   "--script", str(script), "--operator", "Ada Lovelace"])
    assert res.exit_code == 1, res.output  # one refusal
    assert f"readings: {tmp_path / 'session.h5'}" in " ".join(res.output.split())
    run = open_run(tmp_path / "session.h5")
    assert run.complete and run.state == "completed" and "instruments safe and closed" in run.reason
    assert run.attrs["operator"] == "Ada Lovelace" and run.attrs["rig_name"] == "lsdea-motor-sim"
    rows = _rows(log)
    # every reading the log shows is in the streams with the value it shows (to the digits it shows)
    readings = [m for r in rows if (m := _READING.search(r[4]))]
    assert len(readings) == 1 + 1 + 1 + 4 + 1  # voltage, move, read, watch (4), ramp
    amp, motor, cell = (run.streams[k] for k in ("amplifier", "motor", "load_cell"))
    for m in readings:
        t = float(m["t"])
        assert abs(_nearest(amp, t, "voltage") - float(m["v"])) <= 0.5
        assert abs(_nearest(amp, t, "current") * 1e6 - float(m["i"])) <= 0.005
        assert abs(_nearest(motor, t, "position") * 1e3 - float(m["m"])) <= 0.0005
        assert abs(_nearest(cell, t, "force") - float(m["f"])) <= 0.0005
    watch_late = [_nearest(amp, float(m["t"]), "late") for m, r in zip(readings, [r for r in rows if
                                                                                   _READING.search(r[4])],
                                                                        strict=True) if r[3] == "watch"]
    assert all(0.0 <= late < 0.1 for late in watch_late), watch_late  # a watch's readings are scheduled
    # one event per log line but a watch's readings (they are in the streams): commands, refusals, operator, end
    events = [(kind, text.split(": ", 1)[0]) for _, _, kind, text in run.event_list()]
    assert events == [(r[2], r[3]) for r in rows if r[3] != "watch"]
    assert ("refused", "voltage 20kV") in events and ("operator", "session") in events and events[-1] == ("end",
                                                                                                         "session")
    # the set-points: the move's aperture target, and the exit ramp from 1 kV to 0 V in ten steps, then 0 V
    sp = run.streams["setpoints"]
    apertures = sp.columns["aperture"][np.isfinite(sp.columns["aperture"])]
    lsdea = load_rig(MOTOR_RIG).specimen.lsdea
    assert apertures.tolist() == pytest.approx([lsdea.x_at_motor_zero_m + lsdea.motor_sign * 0.020])  # type: ignore[union-attr]
    last = sp.columns["voltage"][-11:]
    assert np.abs(last - [900, 800, 700, 600, 500, 400, 300, 200, 100, 0, 0]).max() <= 2 * ZERO_V, last
    shown = CliRunner().invoke(app, ["inspect", str(tmp_path / "session.h5")], env={"COLUMNS": "200"})
    assert shown.exit_code == 0 and "manual control" in shown.output and "completed" in shown.output, shown.output


class _Turns:
    """The keep-alive thread's wait between set-points (``ManualSession._stop``), made a turn the test gives."""

    def __init__(self) -> None:
        self.go = threading.Event()
        self.ended = False

    def wait(self, _timeout: float) -> bool:
        self.go.wait()
        self.go.clear()
        return self.ended

    def set(self) -> None:  # the session ends
        self.ended = True
        self.go.set()


class _SeenLock:
    """The session's lock; records whether the keep-alive thread got it at once or had to wait."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self.got = threading.Event()
        self.waited = threading.Event()
        self.tried = threading.Event()  # either of the two
        self.stop_waited = threading.Event()  # another thread (the stop) found it held and waited

    def __enter__(self) -> None:
        if threading.current_thread().name != "manual-keepalive":
            if not self._lock.acquire(blocking=False):
                self.stop_waited.set()
                self._lock.acquire()
        elif self._lock.acquire(blocking=False):
            self.got.set()
            self.tried.set()
        else:
            self.waited.set()
            self.tried.set()
            self._lock.acquire()

    def __exit__(self, *_exc: object) -> None:
        self._lock.release()


def test_the_keep_alive_waits_while_a_command_error_is_handled(tmp_path: Path, monkeypatch) -> None:
    """Wall clock (the keep-alive thread runs there only): a command fails and, while its handler makes the rig
    safe, the keep-alive thread is given its turn. It must wait for the lock until the handling is over — between
    an error and its make_safe it could re-send the set-point the error left (here 2 kV)."""
    s = ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=False, echo=lambda _t: None)
    turns, lock = _Turns(), _SeenLock()
    s._stop, s._lock = turns, lock  # type: ignore[assignment]
    with s:
        assert s.execute("voltage 2kV").status == "ok"
        engine = s._engine()
        make_safe = engine.make_safe
        during: list[bool] = []

        def handled() -> str:
            turns.go.set()  # the keep-alive's turn, now, during the error's handling
            assert lock.tried.wait(10)
            during.append(lock.got.is_set())
            return make_safe()

        def fails(_duration: str) -> str:
            raise RuntimeError("a program error in a command")

        monkeypatch.setattr(engine, "make_safe", handled)
        monkeypatch.setattr(s, "_cmd_wait", fails)
        out = s.execute("wait 1")
        assert out.status == "error" and "output zeroed" in out.text, out
        assert during == [False] and lock.waited.is_set()  # it waited for the lock: nothing sent meanwhile


# ADAM-4024 datasheet: 12-bit offset binary over ±10 V, TREK 1000 V/V: 0 V → code 2047.5 → 2048 (0x0800), the
# code the stop's zero sends; every code above it is a positive set-point.
ZERO_CODE = 2048


def _ao_writes(s: ManualSession, monkeypatch) -> list[int]:
    """The codes written to the ADAM-4024's output register from now on (a recording link)."""
    amp = s._amp()
    link, unit, channel = amp.ao.link, amp.ao.unit, amp.ao_channel
    codes: list[int] = []
    write = link.write_register

    def recording(u: int, address: int, value: int, *, always_send: bool = False) -> None:
        write(u, address, value, always_send=always_send)
        if u == unit and address == channel:  # 40001 + channel (App. G p. G-7)
            codes.append(value)
    monkeypatch.setattr(link, "write_register", recording)
    return codes


def test_nothing_follows_the_zero_once_the_stop_has_begun(tmp_path: Path, monkeypatch) -> None:
    """A keep-alive tick (or a set-point) that lands after the session's stop has zeroed the output sends nothing:
    before, the keep-alive re-sent the held set-point (2 kV) after the zero. Checked on the codes written."""
    after: list[object] = []
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        engine, amp = s._engine(), s._amp()
        codes = _ao_writes(s, monkeypatch)
        safe_state = amp.safe_state

        def then_a_tick() -> None:  # the stop's 0 V, then the keep-alive thread's turn
            safe_state()
            after.append(len(codes))
            engine.keep_alive()
            try:
                engine.voltage(2000.0)
            except Refused as exc:
                after.append(str(exc))
        monkeypatch.setattr(amp, "safe_state", then_a_tick)
    zeroed = after[0]
    assert isinstance(zeroed, int) and codes[zeroed - 1] == ZERO_CODE, codes  # the tick came after the stop's zero
    assert set(codes[zeroed:]) <= {ZERO_CODE}, codes  # after it, 0 V alone (closing zeroes again)
    assert len(after) == 2 and isinstance(after[1], str), after  # the set-point was refused
    assert "\n" not in after[1] and "session is ending" in after[1] and "not sent" in after[1], after


def test_the_stop_waits_for_a_set_point_in_flight(tmp_path: Path, monkeypatch) -> None:
    """A keep-alive set-point already on the wire when the stop begins is sent before the stop's ramp and zero,
    never after them: the stop takes the engine's set-point lock (here it finds it held, waits, and the set-point
    in flight is released only then)."""
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        engine, amp = s._engine(), s._amp()
        codes = _ao_writes(s, monkeypatch)
        seen = _SeenLock()
        engine._setpoint_lock = seen  # type: ignore[assignment]
        in_flight, release = threading.Event(), threading.Event()
        set_voltage = amp.set_voltage

        def held(volts: float, within: float | None = None) -> float:
            in_flight.set()
            assert release.wait(10)
            return set_voltage(volts, within)
        monkeypatch.setattr(amp, "set_voltage", held)
        tick = threading.Thread(target=engine.keep_alive, name="manual-keepalive")
        tick.start()
        assert in_flight.wait(10)
        monkeypatch.setattr(amp, "set_voltage", set_voltage)  # the stop's own ramp goes straight out
        releaser = threading.Thread(target=lambda: (seen.stop_waited.wait(10), release.set()))
        releaser.start()
    tick.join(10)
    releaser.join(10)
    assert seen.stop_waited.is_set() and not tick.is_alive()
    first_zero = codes.index(ZERO_CODE)
    assert codes[0] > ZERO_CODE and set(codes[first_zero:]) == {ZERO_CODE}, codes  # the tick's code, then the stop


def test_a_zero_that_could_not_be_commanded_latches_the_session(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The amplifier's link lost under a set-point, and lost for the safe state too: 0 V was not commanded, the
    output is the set-point module's watchdog's to zero. Found from outside: the line said "output zeroed, motor
    stopped" (on a rig without a motor), nothing latched, and the next `voltage` energised the rig again once the
    link was back. Now: said as it is, latched as a run latches ("output path dead"), refused until a reset."""
    from bench.runtime.latch import latched
    from drivers.errors import InstrumentError

    monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / "state"))
    rig = load_rig(THESIS_RIG)
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 3kV").status == "ok"
        amp = s._inst.amplifier

        def lost(*_a: object, **_k: object) -> None:
            raise InstrumentError("amplifier", "bus io: connection lost during write register 0")

        monkeypatch.setattr(amp, "set_voltage", lost)
        monkeypatch.setattr(amp, "safe_state", lost)
        out = s.execute("voltage 2kV")
        assert out.status == "error" and "0 V NOT commanded" in out.text and "latched" in out.text, out
        assert "output zeroed" not in out.text and "motor" not in out.text.split("(")[0]  # no motor on this rig
        monkeypatch.undo()  # the link is back
        monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / "state"))
        again = s.execute("voltage 2kV")
        assert again.status == "refused" and "latched" in again.text, again
        assert latched(rig.name) is not None  # the rig's latch: runs are refused too
        assert "output path dead" in str(latched(rig.name))


def test_a_speed_beyond_the_rig_limit_is_refused_not_capped(tmp_path: Path) -> None:
    """As a protocol's move step is refused ("beyond the rig's 1 m/s"), a manual move faster than the rig file's
    motor.max_velocity_m_per_s is refused in one line, nothing sent, and the session goes on."""
    rig_text = MOTOR_RIG.read_text(encoding="utf-8")
    limit = float(re.search(r"^max_velocity_m_per_s = ([\d.]+)", rig_text, re.M).group(1))  # type: ignore[union-attr]
    assert limit == 1.0
    with ManualSession(load_rig(MOTOR_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        for line in ("move 90 mm 5 m/s", "jog 10 mm 50 m/s", "move 30 mm 1001 mm/s"):
            out = s.execute(line)
            assert out.status == "refused" and "beyond the rig's 1 m/s" in out.text and "not sent" in out.text, out
            assert "motor 0.000 mm" in s.execute("read").text  # nothing was sent: the motor stands at home
        assert s.execute("move 30 mm 1 m/s").status == "ok"  # the limit itself is allowed; the session went on
    rows = _rows(tmp_path / "s.log")
    assert [r[2] for r in rows if r[3] == "move 90 mm 5 m/s"] == ["refused"]


def test_move_says_motor_position_and_aperture_and_takes_an_aperture(tmp_path: Path) -> None:
    """``move X`` is the motor's position, a protocol's move step the aperture: the answer names both, and
    ``move aperture X`` goes where the aperture is X. Expected values from the rig file's own mapping (aperture =
    x_at_motor_zero_m + motor_sign × motor position)."""
    rig_text = MOTOR_RIG.read_text(encoding="utf-8")
    x0_mm = float(re.search(r"^x_at_motor_zero_m = ([\d.]+)", rig_text, re.M).group(1)) * 1e3  # type: ignore[union-attr]
    sign = int(re.search(r"^motor_sign = (-?1)", rig_text, re.M).group(1))  # type: ignore[union-attr]
    assert (x0_mm, sign) == (45.0, 1)
    with ManualSession(load_rig(MOTOR_RIG), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        out = s.execute("move 50 mm")
        assert out.status == "ok" and out.text.startswith(
            f"motor position 50.000 mm = aperture {x0_mm + sign * 50:.3f} mm"), out
        out = s.execute("move aperture 60 mm 10 mm/s")
        assert out.status == "ok" and out.text.startswith(
            f"motor position {(60 - x0_mm) / sign:.3f} mm = aperture 60.000 mm"), out
        assert f"motor {(60 - x0_mm) / sign:.3f} mm" in s.execute("read").text
        assert s.execute("move motor 20").text.startswith("motor position 20.000 mm = aperture")
        low = s.execute(f"move aperture {x0_mm - 10:g} mm")  # motor position -10 mm: outside the travel
        assert low.status == "refused" and "outside travel" in low.text, low
        for bad in ("move aperture", "move", "move aperture 1 mm 2 mm/s 3"):
            assert s.execute(bad).status == "refused" and "move [motor|aperture] POSITION" in s.outcomes[-1].text
        assert "move aperture X [SPEED]" in s.execute("help").text
    base = load_rig(MOTOR_RIG)  # the same motor, the LS-DEA blocked: the motor sets no aperture
    dump = base.model_dump()
    dump["specimen"]["lsdea"]["configuration"] = "blocked"
    with ManualSession(type(base).model_validate(dump), tmp_path / "b.log", virtual=True, echo=lambda _t: None) as s:
        out = s.execute("move aperture 60 mm")
        assert out.status == "refused" and "does not set an LS-DEA aperture" in out.text, out
        out = s.execute("move 10 mm")
        assert out.status == "ok" and out.text.startswith("motor position 10.000 mm (target"), out


def test_a_script_stops_at_a_trip_and_says_the_rest_is_not_run(tmp_path: Path) -> None:
    """A scripted session (stop_on_trip, as ``--script`` and piped input run it) does not go on after a trip — the
    README's account — and the log and the terminal say that the commands after it were not run."""
    import dataclasses

    seen: list[str] = []
    with ManualSession(load_rig(THESIS_RIG), tmp_path / "s.log", virtual=True, echo=seen.append) as s:
        def script():
            yield "voltage 4kV"
            hv = s._sim.plant.hv  # the amplifier's gain 25 % off: the output verifier latches on the watch
            s._sim.plant.hv = dataclasses.replace(hv, gain=hv.gain * 1.25)
            yield "watch 5 0.25"
            yield "read"  # never run
            yield "voltage 1kV"  # never run
        s.run_lines(script(), stop_on_trip=True)
    assert [(o.command, o.status) for o in s.outcomes] == [("voltage 4kV", "ok"), ("watch 5 0.25", "trip")]
    rows = _rows(tmp_path / "s.log")
    (stopped,) = [r for r in rows if r[2:4] == ["stopped", "session"]]
    assert "'watch 5 0.25'" in stopped[4] and "not run" in stopped[4]
    assert any(line.startswith("stopped: ") and "not run" in line for line in seen), seen
    assert not any(r[3] in ("read", "voltage 1kV") for r in rows)


def test_without_operator_the_login_name_is_recorded_as_a_run_records_it(tmp_path: Path) -> None:
    """No --operator: the session is the login name's, as a run's is (outside tester: a manual reset recorded
    "an operator not named" while runs recorded the login name)."""
    import getpass

    log = tmp_path / "s.log"
    res = CliRunner().invoke(app, ["devices", "control", str(THESIS_RIG), "--virtual-time", "--log", str(log)],
                             input="read\n")
    assert res.exit_code == 0, res.output
    rows = _rows(log)
    assert rows[0][4].endswith(f"operator {getpass.getuser()}"), rows[0]


def test_a_daq_rigs_load_cell_is_read_and_supervised_in_manual_control(tmp_path: Path) -> None:
    """On a DAQ rig the load cell's bridge amplifier is an analog input of the T7, which a run samples on its scan
    clock; manual control plays no stream, and the force was never read: the session's header printed the rig's
    ±2 N and `move 95 50` went to 140 mm with exit 0, `tare` said "this rig has no load cell" (outside tester). Now
    the input is read on request: `read` gives the force the plant exerts, the session records it, the move trips
    the force limit and latches, and `tare` is refused (a bridge amplifier has no command)."""
    from bench.storage.runfile import open_run

    text = (ROOT / "rigs" / "lsdea-motor-daq-sim.toml").read_text(encoding="utf-8")
    assert "max_force_N = 9.5 " in text
    low = tmp_path / "low-force.toml"
    low.write_text(text.replace("max_force_N = 9.5 ", "max_force_N = 2.0 "), encoding="utf-8")
    with ManualSession(load_rig(low), tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        out = s.execute("read")
        force = float(re.search(r"force (-?[\d.]+) N", out.text).group(1))  # type: ignore[union-attr]
        plant = float(s._sim.plant.observe().force[-1])
        # (the plant a little later than the read: the specimen relaxes; the cell's noise is mN)
        assert out.status == "ok" and force == pytest.approx(plant, rel=0.1), (out, plant)
        tare = s.execute("tare")
        assert tare.status == "refused" and "bridge amplifier" in tare.text, tare
        zero = s.execute("zero-cell")  # refused in the driver's words, nothing sent
        assert zero.status == "refused" and "no zero command" in zero.text and "daq.force_offset_N" in zero.text, zero
        move = s.execute("move 95 50")
        assert move.status == "trip" and "force" in move.text and "2 N" in move.text, move
        assert s.execute("voltage 1 kV").status == "refused"  # latched
    cell = open_run(tmp_path / "s.h5").streams["load_cell"]
    forces = cell.columns["force"]
    assert len(forces) >= 2 and np.nanmax(np.abs(forces)) > 2.0  # recorded, the reading that tripped among them
    # and once more after the trip, the rig made safe (the file ended at the tripping reading: a second tester)
    assert len(forces) - 1 > int(np.nanargmax(np.abs(forces))), (cell.t, forces)
    # the premise, on the rig as shipped (±9.5 N): the same move meets a force beyond 2 N, read at rest
    with ManualSession(load_rig(ROOT / "rigs" / "lsdea-motor-daq-sim.toml"), tmp_path / "t.log", virtual=True,
                       echo=lambda _t: None) as s:
        assert s.execute("move 95 50").status == "ok"
        at_rest = s.execute("read").text
        assert float(re.search(r"force (-?[\d.]+) N", at_rest).group(1)) > 2.0, at_rest  # type: ignore[union-attr]


def test_a_script_stops_at_the_latch_and_cannot_reset_it(tmp_path: Path) -> None:
    """A script on a rig a run had latched went on past "refused: interlock latched…", and its own `reset` line
    cleared the latch and the next line energised the rig (outside tester). The README: a script stops at a
    latched fault; a reset is an operator's, at a prompt. The script stops at the first refusal the latch causes;
    a scripted `reset` is refused and stops it too; the rig stays latched and at 0 V."""
    from bench.runtime.latch import latch, latched

    rig = load_rig(THESIS_RIG)
    for script, stops_at in ((["read", "voltage 1kV", "read", "voltage 2kV"], "voltage 1kV"),
                             (["read", "reset the script says so", "voltage 1kV"], "reset the script says so")):
        latch(rig.name, "interlock: safety trip (a run, the test)", str(tmp_path / "run.h5"))
        log = tmp_path / f"{len(script)}-{stops_at.split()[0]}.log"
        with ManualSession(rig, log, virtual=True, echo=lambda _t: None, operator="carol") as s:
            outcomes = s.run_lines(script, stop_on_trip=True)
            assert [o.command for o in outcomes][-1] == stops_at, outcomes
            assert outcomes[-1].status == "refused", outcomes[-1]
            assert abs(_plant_volts(s._sim)) < ZERO_V
        assert any(r[3] == "session" and r[2] == "stopped" for r in _rows(log)), _rows(log)
        assert latched(rig.name) is not None  # nothing reset it
    # at a prompt (no script) the operator's reset stands, as before
    with ManualSession(rig, tmp_path / "prompt.log", virtual=True, echo=lambda _t: None, operator="carol") as s:
        assert s.execute("reset looked at the rig").status == "ok"
    assert latched(rig.name) is None


def test_an_operators_pause_stops_a_script_and_its_resume_is_refused(tmp_path: Path) -> None:
    """SIGUSR1 during a script's `watch` paused the session, and the script's own `resume` line turned high voltage
    back on 0.35 s later (outside tester). An operator's pause stops the script, as a trip does; and a `resume`
    a script reads while the session is paused from outside it is refused (the script stops there too). The
    session then ends "interrupted", not "completed": its script did not run to its end."""
    rig = load_rig(THESIS_RIG)
    with ManualSession(rig, tmp_path / "a.log", virtual=True, echo=lambda _t: None) as s:
        asked: list[float] = []

        def pause_once(_now: float) -> None:
            if s.engine is not None and not asked and s.engine.now() >= 1.0:
                asked.append(s.engine.now())
                s.engine.request_pause("signal SIGUSR1")
        s._sim.clock.subscribe(pause_once)
        outcomes = s.run_lines(["voltage 2kV", "wait 3", "resume", "voltage 3kV"], stop_on_trip=True)
        assert asked and [o.command for o in outcomes] == ["voltage 2kV", "wait 3"], outcomes
        assert outcomes[-1].status == "paused", outcomes[-1]
        assert abs(_plant_volts(s._sim)) < ZERO_V  # stayed paused: nothing after the pause ran
    assert any(r[3] == "session" and r[2] == "stopped" and "pause" in r[4] for r in _rows(tmp_path / "a.log"))
    # the session's file says the script did not run to its end (it read "completed": a second outside tester)
    from bench.storage.runfile import open_run

    run = open_run(tmp_path / "a.h5")
    assert run.state == "interrupted", run.reason
    assert "stopped at the pause of 'wait 3' (signal SIGUSR1 paused the session)" in run.reason, run.reason
    # paused from outside between a script's lines (by the keep-alive thread, no command under way): the script
    # stops before its next line — it had gone on, each `voltage` refused, to "completed" (a reviewer); a script's
    # `resume` is refused while an operator's pause holds; the output stays off
    with ManualSession(rig, tmp_path / "b.log", virtual=True, echo=lambda _t: None) as s:
        def lines() -> Iterator[str]:
            yield "voltage 2kV"
            assert s.engine is not None
            s.engine.request_pause("signal SIGUSR1")  # at the prompt: what the keep-alive thread does on it (a
            with s._lock:  # virtual session's thread waits on the virtual clock, which stands still at a prompt)
                s._paused("(SIGUSR1 at the prompt)", s.engine, s.engine.pause_asked_by())
            assert s.engine.paused
            yield from ("voltage 2.5kV", "voltage 3kV")
        outcomes = s.run_lines(lines(), stop_on_trip=True)
        assert outcomes and outcomes[0].status == "ok", outcomes
        assert all(o.command != "voltage 3kV" for o in outcomes), outcomes  # stopped at the pause, not run out
        assert abs(_plant_volts(s._sim)) < ZERO_V
        s._scripted = True  # a script's own `resume` under an operator's pause (the script stops before one, too)
        refused = s.execute("resume")
        assert refused.status == "refused" and "paused by signal SIGUSR1" in refused.text, refused
    assert open_run(tmp_path / "b.h5").state == "interrupted"


@pytest.mark.parametrize("rig", ["thesis-daq-sim", "thesis-sim"])
def test_a_held_voltage_that_creeps_the_membrane_out_of_the_laser_s_range_trips_before_it_fails(
        tmp_path: Path, rig: str) -> None:
    """8 kV held on the thesis membrane creeps it on to runaway in about 7 s (the dry run refuses such a protocol;
    physics.md's model). In manual control the laser was read once, so the supervisor's field check used the stretch
    of that one reading, and the specimen failed with nothing said but "monitors read nan" (an outside tester). Now
    the laser is read while the output is held, and once it reads no displacement (past its range) at high voltage
    the session trips: the true field is not known. The plant has not failed when it does."""
    from bench.storage.runfile import open_run

    with ManualSession(load_rig(ROOT / "rigs" / f"{rig}.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        first = s.execute("voltage 7999")
        assert first.status == "ok" and "displacement n/a" not in first.text, first  # read just after a poll
        held = s.execute("wait 30")
        plant = s._sim.plant
        assert held.status == "trip" and "laser reads no displacement" in held.text, held
        assert "true field" in held.text and not plant.failure, (held, plant.failure)
    run = open_run(s.data_file)
    laser = run.streams["laser"]
    assert len(laser) > 30  # read through the hold (10 per second), not once
    assert not np.isfinite(laser.columns["displacement"][-1])  # the reading that tripped it is recorded


def test_a_manual_ramp_reads_the_laser_as_it_goes(tmp_path: Path) -> None:
    """A ramp checked only the monitors after each set-point: through a ramp (up to an hour) the field check kept
    the stretch from before it (a reviewer). The rig's due polls run after each set-point too: the laser's 10 per
    second (bench/protocol/program.py PASSIVE_LASER_HZ)."""
    from bench.storage.runfile import open_run

    with ManualSession(load_rig(ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        t0 = s.engine.now() if s.engine is not None else 0.0
        assert s.execute("ramp 3000 4").status == "ok"
        t1 = s.engine.now() if s.engine is not None else 0.0
    laser = open_run(s.data_file).streams["laser"]
    during = (laser.t > t0 + 0.2) & (laser.t < t1 - 0.2)
    assert during.sum() >= 0.8 * 10 * (t1 - t0 - 0.4), (during.sum(), t0, t1)


def test_a_ramp_to_the_voltage_limit_ends_at_it(tmp_path: Path) -> None:
    """`ramp 8kV 2` on the 8-kV thesis rig ran its 2 s, then was refused "8000 V beyond the software limit ±8000 V",
    the output left at 7.8 kV (an outside tester): its last set-point, computed from a start one code off 0 V, came
    out a rounding above 8000 V. A ramp ends on its target: the limit's own code (within ±8000 V)."""
    with ManualSession(load_rig(ROOT / "rigs" / "thesis-sim.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        out = s.execute("ramp 8kV 2")
        assert out.status == "ok", out
        assert s.engine is not None and 7990 < s.engine.ctx.v_cmd <= 8000.0, s.engine.ctx.v_cmd


def test_a_manual_pause_says_the_output_it_reads_not_the_set_point(tmp_path: Path) -> None:
    """`voltage 6kV`, `wait 2`, `pause` answered "output 2 V" (the set-point) while the next `read` showed 4223 V on
    the still discharging output (an outside tester). The pause reads the monitor until it is at 0 V (the rig's safe
    threshold) and says so; the next read agrees."""
    from bench.rig import safe_monitor_v

    rig = load_rig(ROOT / "rigs" / "thesis-sim.toml")
    safe = safe_monitor_v(rig)
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        s.execute("voltage 6kV")
        s.execute("wait 2")
        paused = s.execute("pause")
        m = re.search(r"output at 0 V \(0 V commanded: the voltage monitor reads (-?\d+) V", paused.text)
        assert paused.status == "ok" and m is not None and abs(int(m.group(1))) <= safe, paused
        after = s.execute("read")
        v = float(re.search(r"voltage (-?\d+) V", after.text).group(1))  # type: ignore[union-attr]
        assert abs(v) <= safe, after


def test_control_help_says_what_sigusr1_does() -> None:
    """`devices control --help` named every stop signal but not SIGUSR1, which pauses, and in a script stops it (an
    outside tester saw a piped session end on it)."""
    out = " ".join(CliRunner().invoke(app, ["devices", "control", "--help"], env={"COLUMNS": "200"}).output.split())
    assert "SIGUSR1 pauses" in out and "A script stops at such a pause too" in out, out
