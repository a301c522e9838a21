"""A silent instrument during high voltage: the run ends as that instrument's fault, not as a host stall.

On the motor bench (rigs/lsdea-motor-sim.toml) the load cell has a bus of its own ("scale") beside the set-point
module's ("io"). Its twin muted over the real transport (sim_devices.transport.Faults ``mute``: the request is
taken, no reply comes), the driver waits its timeout on each of its attempts while the host sends the set-point
module nothing. The run must say that the load cell went silent — a researcher reading "host stall" looks for a
CPU or OS fault — end at 0 V at the plant with the motor stopped, and, when the set-point module's watchdog did
fire while the host waited, latch naming the load cell. A real host stall still latches as one
(tests/test_interlock.py).
"""

from __future__ import annotations

from pathlib import Path

from bench.runtime.engine import Engine
from tests.conftest import ROOT
from tests.test_interlock import ZERO_V, events, run_with_fault

RIG = ROOT / "rigs" / "lsdea-motor-sim.toml"
MUTE_AT = 1.0  # run time [s] of the mute: in the 3-kV hold (the ramp ends at 0.3 s)
PROTOCOL = f"""[protocol]
name = "silent-load-cell"
description = "3 kV held while the load cell is read at 100 Hz"
rig = "{RIG}"

[recording]
setpoint_Hz = 20
force_Hz = 100
position_Hz = 20
monitors_Hz = 5

[[steps]]
type = "ramp"
name = "up"
channel = "voltage"
to = "3 kV"
duration_s = 0.3

[[steps]]
type = "hold"
name = "hold"
duration_s = 2.5

[[steps]]
type = "relax"
name = "end"
duration_s = 0.2
"""


def mute_scale(_engine: Engine, sim) -> None:
    sim.faults["scale"].mute = True


def _run(tmp_path: Path, rig: Path, wire: list[str] | None = None):
    """The protocol on ``rig`` with the load cell muted at :data:`MUTE_AT`; ``wire``: gets, in order, "io" for
    each reply of the amplifier's bus and "scale muted" for each load-cell request left unanswered."""
    protocol = tmp_path / "silent-load-cell.toml"
    protocol.write_text(PROTOCOL.replace(str(RIG), str(rig)), encoding="utf-8")

    def action(engine: Engine, sim) -> None:
        if wire is not None:
            for bus in ("io", "scale"):
                faults = sim.faults[bus]
                process = faults.process

                def logged(reply: bytes, request_len: int = 0, bus: str = bus, faults=faults, process=process):
                    out = process(reply, request_len)
                    if bus == "io" or (reply and out[0] is None and faults.mute):
                        wire.append(bus if bus == "io" else "scale muted")
                    return out
                faults.process = logged
        mute_scale(engine, sim)
    return run_with_fault(rig, tmp_path, MUTE_AT, action, virtual=False, protocol=protocol)


def _ends_safe(result, run, plant) -> None:
    """0 V at the plant at the end (high voltage before the mute), the motor's stop sent, the file's reason set."""
    assert plant.last_high() > plant.t_fault - 1.0  # the output was on when the load cell went silent
    _t, v = plant.arrays()
    assert abs(float(v[-1])) <= ZERO_V
    assert any("stop sent" in text for text in events(run, "motor"))
    assert run.reason.startswith(result.reason)


def test_a_silent_load_cell_ends_the_run_as_the_load_cells_fault(tmp_path: Path) -> None:
    """The shipped bus settings (0.5-s timeout, one retry: 1 s of waiting, longer than the 0.8-s stall bound).
    Between the load cell's two unanswered attempts the set-point module gets a request (its keep-alive is not
    starved by the wait); the run ends as the load cell's timeout."""
    wire: list[str] = []
    result, run, plant = _run(tmp_path, RIG, wire)
    assert "scale muted" in wire, (result.state, result.reason, result.latched)
    if wire.count("scale muted") >= 2:  # both attempts: the module was fed between them
        first = wire.index("scale muted")
        second = wire.index("scale muted", first + 1)
        assert "io" in wire[first + 1:second], wire[first:second + 1]
        assert "no valid reply" in result.reason  # the driver's own words: its timeout, not a refusal
    else:  # a host loaded enough that the module went unheard past the bound already in the first attempt's wait:
        # latched, and named for the load cell the host waited on (not a host stall)
        assert result.latched.startswith("interlock: load cell silent"), result.latched
    assert result.state in ("error", "tripped"), result.reason
    assert "host stall" not in result.reason and "host stall" not in result.latched, (result.reason, result.latched)
    assert not any("host stall" in text for text in events(run, "interlock"))
    assert "load cell" in result.reason, result.reason  # the cause names the instrument that went silent
    _ends_safe(result, run, plant)


def test_a_watchdog_that_fires_while_the_host_waits_on_the_load_cell_latches_naming_it(tmp_path: Path) -> None:
    """One attempt longer than the set-point module's 1-s watchdog (``timeout_s = 1.5``, no retry): no keep-alive
    can go out during that wait, so the watchdog fires; the latch names the load cell, not a host stall."""
    text = RIG.read_text(encoding="utf-8")
    assert "[buses.scale]\nport = \"sim\"\n" in text
    rig = tmp_path / "lsdea-motor-sim-slow-scale.toml"
    rig.write_text(text.replace("[buses.scale]\nport = \"sim\"\n",
                                "[buses.scale]\nport = \"sim\"\ntimeout_s = 1.5\nretries = 0\n"), encoding="utf-8")
    result, run, plant = _run(tmp_path, rig)
    assert result.latched.startswith("interlock: load cell silent"), result.latched
    assert result.state in ("error", "tripped") and "load cell" in result.reason, result.reason
    assert "host stall" not in result.reason and "host stall" not in result.latched
    assert "its watchdog fired" in result.latched  # the ADAM-4024's own flag (40216, ADAM-4000 manual app. G)
    assert any("load cell silent" in text for text in events(run, "interlock"))
    _ends_safe(result, run, plant)



# ---------------------------------------------------------------- which silence is the instrument's (review)
def _context(monkeypatch, now: float, wait: tuple[float, float]):  # type: ignore[no-untyped-def]
    """A run context's view of the last unanswered wait (``wait``: its start and end on time.monotonic) at
    ``now``: only what :meth:`RunContext._waited_on` reads."""
    import types

    from bench.rig import load_rig
    from bench.runtime import context

    monkeypatch.setattr(context.time, "monotonic", lambda: now)
    ctx = object.__new__(context.RunContext)
    ctx._silent = context.Wait("load_cell", wait[0], end=wait[1], unanswered=True)
    ctx.program = types.SimpleNamespace(rig=load_rig(RIG))
    return ctx


def test_a_silence_the_wait_covers_is_the_instruments_one_left_after_it_is_a_host_stall(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """lsdea-motor-sim: 1-s watchdog, stall bound 0.8 s (0.8 × the watchdog, README "Interlock"). A 1.0-s wait on
    the load cell inside a 1.05-s silence leaves 0.05 s uncovered: the load cell's. A wait whose keep-alive fed
    the module at 100.5 s and a 1.0-s freeze after it: the silence (100.5…101.55 s) is covered by the wait for
    0.03 s only, so it is the host's (it was laid to the load cell: the wait was long enough, but not in it)."""
    ctx = _context(monkeypatch, 101.05, (100.0, 101.0))
    blamed = ctx._waited_on(1.05)
    assert blamed is not None and blamed.role == "load_cell"
    ctx = _context(monkeypatch, 101.55, (100.0, 100.53))
    assert ctx._waited_on(1.05) is None
    ctx = _context(monkeypatch, 100.5, (100.0, 100.5))  # a 1.0-s freeze before the read, then its 0.5-s wait
    assert ctx._waited_on(1.5) is None


def test_a_keep_alive_between_attempts_is_recorded_after_the_last_set_point() -> None:
    """A set-point recorded at a ramp's time (5.0 s) and then a read scheduled for 4.9 s whose request went
    unanswered: the keep-alive sent before its retry is recorded at 5.0 s, not 4.9 s (the stream stays in time
    order; the windowed readers rely on it)."""
    import types

    sent: list[float] = []
    engine = object.__new__(Engine)
    engine._setpoint_t = 5.0
    engine._stream, engine._stopping = None, False
    engine.inst = types.SimpleNamespace(amplifier=object())
    engine.ctx = types.SimpleNamespace(unanswered=lambda: 4.9, unheard_for=lambda: 1.0, v_req=300.0)
    engine._set_voltage = lambda v, t, x=float("nan"): sent.append(t)  # type: ignore[method-assign]
    engine._between_attempts()
    assert sent == [5.0]
