"""Manual control reads the monitors while high voltage is held (tester's HIGH defect): between commands, during
`wait` and at the prompt, the amplifier's monitors are polled, recorded and verified at the monitor rate, as a
run's hold polls them — an output fault trips and latches without waiting for the operator's next command.

Expected figures come from the README and the datasheets, not from the code under test: the monitors are polled
at 5 S/s (README "Recording": the ADAM-4017+ converts 10 S/s over V and I), a polled output mismatch latches after
two readings in a row out of the band (README "Interlock"), and the output's band opens 0.3 s after a set-point
(the polled lag allowance, README "Interlock"); the ADAM-4024's code nearest 0 V is the datasheet's 12-bit offset
binary over ±10 V (tests/test_limits_as_sent.py's ``adam_out``).
"""

from __future__ import annotations

import dataclasses
import errno
import os
import re
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.rig import load_rig
from bench.runtime.manual import HELP, ManualSession
from bench.storage.runfile import open_run
from tests.conftest import RIGS
from tests.test_limits_as_sent import adam_out

MONITORS_HZ = 5.0  # README: the monitors polled at 5 S/s each
LATCH_READINGS = 2  # README "Interlock": two polled readings in a row out of the band latch
LAG_S = 0.3  # README "Interlock": the polled monitors' lag allowance
ZERO_V = 5.0  # one ADAM-4024 code times the TREK gain


def _gain_off(s: ManualSession) -> float:
    """The amplifier's output stage dead (gain 0: the monitor reads 0 V whatever is commanded); the rig time."""
    s._sim.plant.hv = dataclasses.replace(s._sim.plant.hv, gain=0.0)
    return float(s.engine.now())


@pytest.mark.parametrize("name", ["thesis-sim", "thesis-daq-sim"])
def test_a_held_voltage_is_read_at_the_monitor_rate_during_a_wait(tmp_path: Path, name: str) -> None:
    """2 kV held for 20 s of `wait`: the readings' file has the monitors at 5 S/s over the wait (before: none)."""
    with ManualSession(load_rig(RIGS / f"{name}.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        t0 = s.engine.now()
        assert s.execute("wait 20").status == "ok"
        t1 = s.engine.now()
    amp = open_run(tmp_path / "s.h5").streams["amplifier"]
    inside = (amp.t > t0) & (amp.t <= t1)
    assert abs(int(inside.sum()) - 20 * MONITORS_HZ) <= 2, int(inside.sum())
    assert np.all(np.abs(amp.columns["voltage"][inside] - 2000) < 100)  # what was held, as read


@pytest.mark.parametrize("name", ["thesis-sim", "thesis-daq-sim"])
def test_an_output_fault_during_a_wait_latches_within_two_readings(tmp_path: Path, name: str) -> None:
    """The output dies while 3 kV is held in a 4-s `wait`: the wait ends in a trip that latches, at most two
    readings after the fault — not when the operator next types `read` (the tester's 4073.8 ms)."""
    with ManualSession(load_rig(RIGS / f"{name}.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        assert s.execute("voltage 3kV").status == "ok"
        assert s.execute("wait 1").status == "ok"  # settled, read all along
        t_fault = _gain_off(s)
        out = s.execute("wait 4")
        assert out.status == "trip" and "output mismatch" in out.text and "latched" in out.text, out
        assert s.engine.latched is not None
        t_latch = s.engine.latched_at
        assert s.execute("voltage 1kV").status == "refused"
    amp = open_run(tmp_path / "s.h5").streams["amplifier"]
    after = int(((amp.t > t_fault) & (amp.t <= t_latch + 1e-9)).sum())
    assert 1 <= after <= LATCH_READINGS, after
    lasted = float(re.search(r"out of the commanded band for ([\d.]+) ms", out.text).group(1))  # type: ignore[union-attr]
    assert lasted <= 1e3 * LATCH_READINGS / MONITORS_HZ + 1, out.text


def test_an_output_fault_at_the_prompt_latches_without_a_command(tmp_path: Path) -> None:
    """Wall clock, nothing typed: 3 kV held at the prompt, the output dies — the keep-alive thread's polls trip
    and latch within two readings, told at the prompt and in the log; the plant's output goes to 0 V."""
    seen: list[str] = []
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", echo=seen.append) as s:
        assert s.execute("voltage 3kV").status == "ok"
        time.sleep(1.0)  # at the prompt: held and read
        with s._lock:  # not between two reads of the keep-alive thread
            t_fault = _gain_off(s)
        deadline = time.monotonic() + 30  # hang guard only; the bound is counted in readings below
        while not any(line.startswith("trip: interlock: output mismatch") for line in seen):
            assert time.monotonic() < deadline, seen
            time.sleep(0.05)
        assert s.engine.latched is not None
        t_latch = s.engine.latched_at
        assert s.execute("voltage 1kV").status == "refused"
    rows = [line.split("\t") for line in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert any(r[2:4] == ["trip", "(at the prompt)"] and "latched" in r[4] for r in rows), rows
    run = open_run(tmp_path / "s.h5")
    amp = run.streams["amplifier"]
    held = (amp.t > t_fault - 1.0) & (amp.t <= t_fault)
    assert int(held.sum()) >= MONITORS_HZ * 1.0 - 2  # read at the prompt before the fault
    after = int(((amp.t > t_fault) & (amp.t <= t_latch + 1e-9)).sum())
    assert 1 <= after <= LATCH_READINGS + 1, after  # +1: the reading already on the wire when the gain went


def test_a_monitor_link_lost_at_the_prompt_zeroes_the_output_and_is_said_once(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Wall clock: the monitors' reads fail while 3 kV is held at the prompt — one `error` line, the output zeroed
    (the plant), and not one more line every keep-alive while nothing is typed; the next command reads again."""
    from drivers.errors import InstrumentError

    seen: list[str] = []
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", echo=seen.append) as s:
        assert s.execute("voltage 3kV").status == "ok"

        def lost(*_a: object, **_k: object) -> None:
            raise InstrumentError("amplifier", "bus io: no answer from the monitors' module")

        with s._lock:
            monkeypatch.setattr(s._inst.amplifier, "read", lost)
        deadline = time.monotonic() + 30  # hang guard
        while not any(line.startswith("error:") for line in seen):
            assert time.monotonic() < deadline, seen
            time.sleep(0.05)
        time.sleep(1.5)  # six keep-alive periods at the prompt
        assert len([line for line in seen if line.startswith("error:")]) == 1, seen
        assert "output zeroed" in next(line for line in seen if line.startswith("error:"))
        s._sim.plant.observe()
        assert abs(float(s._sim.plant.observe().v_out[-1])) < ZERO_V
        assert s.execute("read").status == "error"  # the next command reads again (and fails, said)


def test_a_script_stops_at_a_trip_between_its_commands(tmp_path: Path) -> None:
    """Piped commands (wall clock): the output dies while the script waits for its next line — the trip at the
    prompt stops the script as a command's trip does; the commands after it are not run."""
    seen: list[str] = []
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", echo=seen.append) as s:
        def lines():  # type: ignore[no-untyped-def]
            yield "voltage 3kV"
            _gain_off(s)
            deadline = time.monotonic() + 30  # hang guard: the next line comes once the trip is seen
            while not any(line.startswith("trip:") for line in seen):
                assert time.monotonic() < deadline, seen
                time.sleep(0.05)
            yield "voltage 2kV"
        s.run_lines(lines(), stop_on_trip=True)
    commands = [r.split("\t")[3] for r in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert "voltage 3kV" in commands and "voltage 2kV" not in commands, commands
    assert any(line.startswith("stopped: the script stops at the trip of '(at the prompt)'") for line in seen), seen


@pytest.mark.parametrize("name", ["thesis-sim", "thesis-daq-sim"])
def test_a_set_point_the_monitor_does_not_show_is_not_ok(tmp_path: Path, name: str) -> None:
    """`voltage 1kV` on a dead output: never "ok: … voltage 0 V" — the verifier's judgement is said (or the
    interlock has latched already); the next wait latches."""
    with ManualSession(load_rig(RIGS / f"{name}.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        _gain_off(s)
        out = s.execute("voltage 1kV")
        assert out.status in ("unsettled", "trip"), out
        if out.status == "unsettled":
            assert "not verified" in out.text and "outside" in out.text, out
            out = s.execute("wait 1")
        assert out.status == "trip" and "latched" in out.text, out
        assert s.execute("voltage 1kV").status == "refused"


def test_a_verified_set_point_says_so(tmp_path: Path) -> None:
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        out = s.execute("voltage 2kV")
        assert out.status == "ok" and "verified on the voltage monitor" in out.text, out


def test_zero_prints_the_set_point_it_records(tmp_path: Path) -> None:
    """`zero` sends the ADAM-4024's code nearest 0 V (2048: +2.4 V after the TREK): said as recorded."""
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", virtual=True,
                       echo=lambda _t: None) as s:
        assert s.execute("voltage 2kV").status == "ok"
        out = s.execute("zero")
        t_zero = s.engine.now()
        assert out.status == "ok" and f"{adam_out(2048):.1f} V" in out.text, out
    sp = open_run(tmp_path / "s.h5").streams["setpoints"]
    v = sp.columns["voltage"][(sp.t <= t_zero) & np.isfinite(sp.columns["voltage"])]
    assert v[-1] == pytest.approx(adam_out(2048), abs=1e-3)  # the zero's row (the exit ramp's come after)


def test_help_has_no_markup() -> None:
    assert "``" not in HELP and "voltage 3kV" in HELP


def _slow_prompt_polls(s: ManualSession, monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """The keep-alive thread's monitor reads wait 2 s on the bus (cancellable, as the drivers' waits are); set once
    one is in flight."""
    inst: Any = s._inst
    amp = inst.amplifier
    read, in_flight = amp.read, threading.Event()

    def slow(*a: object, **k: object) -> object:
        if threading.current_thread() is s._keepalive:
            in_flight.set()
            for _ in range(200):
                inst.cancel.check("amplifier")
                time.sleep(0.01)
        return read(*a, **k)

    with s._lock:
        monkeypatch.setattr(amp, "read", slow)
    return in_flight


def test_a_stop_signal_during_a_poll_at_the_prompt_ramps_the_output_down(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM while the keep-alive thread's poll waits on the bus (3 kV held at the prompt): the session ends
    through the exit ramp (README: the output ramped to 0 V over ``shutdown_ramp_s``), not a one-step drop, and no
    false `error` line (before: "wait abandoned: SIGTERM; output zeroed", then "ramp from 2 V")."""
    rig = load_rig(RIGS / "thesis-sim.toml")
    ramp_s = rig.limits.shutdown_ramp_s
    seen: list[str] = []
    history: list[tuple[float, float]] = []
    s = ManualSession(rig, tmp_path / "s.log", echo=seen.append)
    with s.signal_handlers(), s:
        s._sim.plant.listeners.append(lambda b: history.extend(zip(b.t.tolist(), b.v_out.tolist(), strict=True)))
        assert s.execute("voltage 3kV").status == "ok"
        in_flight = _slow_prompt_polls(s, monkeypatch)
        assert in_flight.wait(10)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)  # the poll in flight is cancelled before the session's exit
    assert not [line for line in seen if line.startswith("error")], seen
    rows = [line.split("\t") for line in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert not [r for r in rows if r[2] == "error"], rows
    ramp = next(r for r in rows if r[2] == "ramp")
    assert float(re.search(r"ramp from (-?\d+) V", ramp[4]).group(1)) > 2900, ramp  # type: ignore[union-attr]
    t, v = np.array(history).T
    high = t[np.abs(v) > 2900].max()  # the output leaves 3 kV …
    low = t[(t > high) & (np.abs(v) < 100)].min()  # … and reaches 0 V over the ramp, not in one step
    assert low - high > 0.5 * ramp_s, (low - high, ramp_s)
    assert rows[-1][2] == "end" and "SIGTERM" in rows[-1][4]


def test_a_storage_fault_at_the_prompt_is_said_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The readings' file fails (disk full) under the keep-alive thread's polls at the prompt: one `error` line, as
    after a command (README: a storage fault later is one error line, the session goes on with the log alone);
    the held output stays supervised (before: the fault was suppressed without a word)."""
    seen: list[str] = []
    with ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", echo=seen.append) as s:
        assert s.execute("voltage 3kV").status == "ok"
        rec: Any = s._rec
        engine: Any = s.engine
        append = rec.append

        def full(stream: str, *a: Any, **k: Any) -> None:
            if threading.current_thread() is s._keepalive and stream == "amplifier" and not rec.failure:
                rec.failure = "disk full"  # as the recorder: failed once, silent after (recorder.py)
                raise OSError(errno.ENOSPC, "No space left on device")
            append(stream, *a, **k)

        with s._lock:
            monkeypatch.setattr(rec, "append", full)
            t_fail = float(engine.now())
        deadline = time.monotonic() + 10  # hang guard: the monitors are polled at 5 S/s
        while not any(line.startswith("error:") for line in seen):
            assert time.monotonic() < deadline, seen
            time.sleep(0.05)
        time.sleep(1.5)  # six keep-alive periods at the prompt
        errors = [line for line in seen if line.startswith("error:")]
        assert len(errors) == 1 and "No space left on device" in errors[0] and "log" in errors[0], seen
        with s._lock:
            last = engine.verifier.last
            assert last is not None and last.t > t_fail + 1.0, (last, t_fail)  # still read and verified
        assert s.execute("read").status == "ok"  # the session goes on
    rows = [line.split("\t") for line in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert len([r for r in rows if r[2] == "error"]) == 1, rows


@pytest.mark.parametrize("passes", [False, True], ids=["trips", "passes"])
def test_a_reading_whose_record_fails_is_still_checked(passes: bool) -> None:
    """A polled reading the file could not record (disk full) is still checked (a run's polls and a manual
    session's): a trip it shows is raised; where it passes, the storage fault is (the run ends on it)."""
    from types import SimpleNamespace

    from bench.runtime.polls import Polled, poll_once
    from bench.runtime.safety import SafetyTrip

    def no_room(*_a: object, **_k: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    checked: list[dict[str, float]] = []

    def check(_e: object, _r: object, row: dict[str, float]) -> None:
        checked.append(row)
        if not passes:
            raise SafetyTrip("current 6 mA beyond the 5-mA limit")

    e: Any = SimpleNamespace(rec=SimpleNamespace(append=no_room), t0=0.0, late_columns=lambda _s, _l: {},
                             lateness=lambda _due: 0.0)
    drv: Any = SimpleNamespace(read=lambda: {"current": SimpleNamespace(value=6e-3, timestamp=1.0)})
    d: Any = SimpleNamespace(stream="amplifier", columns=[SimpleNamespace(name="current")])
    with pytest.raises(OSError if passes else SafetyTrip):
        poll_once(e, drv, Polled("monitors", lambda _e, _s: None, check=check), 1.0, d)
    assert checked == [{"current": 6e-3}]


def _pause_ramp_then_sigterm(folder: Path, ramp_s: float) -> tuple[list[str], list[list[str]], np.ndarray, float]:
    """A manual session at 3 kV, SIGUSR1 (a pause: the keep-alive thread ramps down over ``ramp_s``), SIGTERM once
    the output is under 2 kV: what it echoed, its log's rows, the plant's (t, v_out) and the SIGTERM's plant time."""
    rig = load_rig(RIGS / "thesis-sim.toml")
    rig = rig.model_copy(update={"limits": rig.limits.model_copy(update={"shutdown_ramp_s": ramp_s})})
    seen: list[str] = []
    history: list[tuple[float, float]] = []
    folder.mkdir()
    s = ManualSession(rig, folder / "s.log", echo=seen.append)
    with s.signal_handlers(), s:
        sim = s._sim
        sim.plant.listeners.append(lambda b: history.extend(zip(b.t.tolist(), b.v_out.tolist(), strict=True)))
        assert s.execute("voltage 3kV").status == "ok"
        os.kill(os.getpid(), signal.SIGUSR1)
        deadline = time.monotonic() + 10  # hang guard: the pause's ramp takes 3 s
        while True:
            assert time.monotonic() < deadline, seen
            sim.plant.observe()
            if history and history[-1][1] < 2000:
                break
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGTERM)
        t_stop = history[-1][0]
    rows = [line.split("\t") for line in (folder / "s.log").read_text(encoding="utf-8").splitlines()]
    return seen, rows, np.array(history).T, t_stop


def test_a_stop_signal_during_a_pause_ramp_at_the_prompt_ramps_on(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A pause asked for at the prompt (SIGUSR1: the keep-alive thread ramps 3 kV down over ``shutdown_ramp_s``),
    then SIGTERM in that ramp: the session's stop ramps on from where the pause's ramp was (README: the exit ramps
    the output to 0 V over ``shutdown_ramp_s``) — no one-step drop, no `error` line (before: "pause: …; output
    zeroed"). A wall-clock session: on a loaded host the keep-alive thread can go past the stall bound, and the
    rig latches (host stall) and goes to 0 V at once, as it must — the premise lost, tried again (its own latch
    folder), as the browser test does."""
    ramp_s = 3.0  # long enough to signal within the pause's ramp
    for attempt in range(3):
        monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path / f"state{attempt}"))
        seen, rows, (t, v), t_stop = _pause_ramp_then_sigterm(tmp_path / f"try{attempt}", ramp_s)
        if not any(r[2] == "latched" and "host stall" in r[4] for r in rows):
            break
    assert not [line for line in seen if line.startswith("error")], seen
    assert not [r for r in rows if r[2] == "error"], rows
    after = t >= t_stop
    low = t[after & (np.abs(v) < 100)].min()
    assert low - t_stop > 0.5 * ramp_s, low - t_stop  # from 2 kV to 0 V over the exit ramp, not one step
    assert rows[-1][2] == "end" and "SIGTERM" in rows[-1][4]


def test_quit_during_a_stuck_poll_at_the_prompt_is_the_stop_alone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Quit while the keep-alive thread's poll is stuck on the bus past the session's 2-s join (a wait that does not
    look at the cancel), then fails: the stop waits for that tick and then runs alone — no `error` line from the
    thread after the stop began, its make_safe not interleaved with the stop (before: the stop ran beside it)."""
    from drivers.errors import InstrumentError

    s = ManualSession(load_rig(RIGS / "thesis-sim.toml"), tmp_path / "s.log", echo=lambda _t: None)
    s.__enter__()
    try:
        assert s.execute("voltage 3kV").status == "ok"
        inst: Any = s._inst
        in_flight, ended = threading.Event(), []

        def stuck(*_a: object, **_k: object) -> None:
            if threading.current_thread() is s._keepalive:
                in_flight.set()
                time.sleep(2.5)
                ended.append(s._now())  # the log's run time
                raise InstrumentError("amplifier", "bus io: no answer (dead link)")
            raise AssertionError("read from the main thread")

        with s._lock:
            monkeypatch.setattr(inst.amplifier, "read", stuck)
        assert in_flight.wait(10)
    finally:
        s.__exit__(None, None, None)
    time.sleep(1.0)  # a thread left behind would say its error now
    rows = [line.split("\t") for line in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert not [r for r in rows if r[2] == "error"], rows
    assert rows[-1][2:4] == ["end", "session"], rows
    stop = next(r for r in rows if r[2] == "stop")
    assert float(stop[1].split("=")[1].split()[0]) >= ended[0] - 1e-3, (stop, ended)  # after the tick (ms)


def test_a_limit_trip_at_the_prompt_latches_the_rig(tmp_path: Path) -> None:
    """Wall clock, nothing typed: the film breaks down under 5 kV held at the prompt — the keep-alive thread's
    polls trip on it, and the trip latches the rig as one after a command does (README "Interlock": a limit trip
    latches; a reviewer found the prompt's trip made safe but not latched, the next `voltage 1 kV` accepted)."""
    from bench.runtime import latch as rig_latch

    seen: list[str] = []
    rig = load_rig(RIGS / "thesis-sim.toml")
    with ManualSession(rig, tmp_path / "s.log", echo=seen.append) as s:
        assert s.execute("voltage 5kV").status == "ok"
        with s._lock:  # not between two reads of the keep-alive thread
            s._sim.plant.inject_breakdown()
        deadline = time.monotonic() + 30  # hang guard only
        while not any(line.startswith("trip:") for line in seen):
            assert time.monotonic() < deadline, seen
            time.sleep(0.05)
        assert s.engine.latched is not None
        assert s.execute("voltage 1kV").status == "refused"
    assert rig_latch.latched(rig.name) is not None


def test_a_limit_trip_in_a_session_s_exit_ramp_latches_the_rig_and_ends_it_tripped(tmp_path: Path) -> None:
    """The film breaks down as the session ends at 5 kV (the ADAM rig's exit ramp reads the monitors): the current
    beyond the rig's 5-mA limit is a trip — the session's file says `tripped` and the rig latches, as a limit trip
    at a command or at the prompt does (a reviewer: the file said `completed` and no latch was written, the log
    saying "latched")."""
    from bench.runtime import latch as rig_latch

    rig = load_rig(RIGS / "thesis-sim.toml")
    rig = rig.model_copy(update={"limits": rig.limits.model_copy(update={"shutdown_ramp_s": 1.0})})
    with ManualSession(rig, tmp_path / "s.log", virtual=True, echo=lambda _t: None) as s:
        assert s.execute("voltage 5kV").status == "ok"
        s._sim.plant.inject_breakdown()  # as the operator quits
    run = open_run(tmp_path / "s.h5")
    assert [e for e in run.event_list() if e[2] == "tripped" and "during the ramp to 0 V" in e[3]], run.event_list()
    assert run.state == "tripped", (run.state, run.reason)
    assert rig_latch.latched(rig.name) is not None
    rows = [line.split("\t") for line in (tmp_path / "s.log").read_text(encoding="utf-8").splitlines()]
    assert [r for r in rows if r[2] == "latched"], rows
