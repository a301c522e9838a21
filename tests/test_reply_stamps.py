"""A polled encoder position is stamped when the drive took it, on the run's clock, on a real run in virtual time.

The outside tester's finding: on ``lsdea-motor-daq-sim`` the LinMot position (polled over LinRS) was stamped after
its reply had arrived, 2.4 ms after the drive took it (1 ms turnaround, then the 16-byte default response's 1.4 ms
at 115,200 Bd), against the T7's scan clock that samples force and voltage; the fit's damping came out 10 % high.
Now a reading is stamped at the start of its reply (the arrival less the reply's wire time) and the twin reads the
plant as its reply starts, so the recorded positions lie on the plant's own trajectory.

Expected values come from the plant itself: its output history (``sim.plant.listeners``, the aperture at every
model step of 0.1 ms) against the run file's ``motor/position``, never from the drivers' or the engine's account of
themselves. The offset is the least-squares time shift of the recorded positions onto that trajectory, over the
samples taken while the motor moves. Virtual time: deterministic in rig time, ~1 s of wall time per run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.runtime.run import execute, plan_run
from bench.storage.runfile import open_run
from tests.conftest import RIGS

PROTOCOL = """[protocol]
name = "stamp-check"
rig = "{rig}"

[recording]
setpoint_Hz = {setpoint_Hz}
position_Hz = {position_Hz}
force_Hz = 10
monitors_Hz = 5

[[steps]]
type = "move"
name = "to start"
position = "50 mm"
velocity = "0.2 m/s"

[[steps]]
type = "waveform"
name = "cycle"
channel = "position"
kind = "raised_cosine"
offset = "50 mm"
amplitude = "40 mm"
frequency_Hz = {frequency_Hz}
cycles = 1
"""
X_AT_MOTOR_ZERO = 0.045  # both rigs' [specimen.lsdea] x_at_motor_zero_m (motor_sign 1): aperture = 45 mm + position


def recorded_offset(tmp_path: Path, rig: str, *, setpoint_Hz: int, position_Hz: int, frequency_Hz: float,
                    wire: bool) -> tuple[float, int, str]:
    """(time offset [s] of the recorded motor positions behind the plant's trajectory, samples while moving, the
    run file's wire_time) of one virtual-time run; ``wire``: whether the twins keep their wire time."""
    proto = tmp_path / "p.toml"
    proto.write_text(PROTOCOL.format(rig=RIGS / f"{rig}.toml", setpoint_Hz=setpoint_Hz, position_Hz=position_Hz,
                                     frequency_Hz=frequency_Hz))
    plan = plan_run(proto)
    assert bool(plan.link_problems) is not wire  # the link budget decides the twins' timing (run._start_sim)
    seen: dict[str, Any] = {}
    blocks: list[tuple[np.ndarray, np.ndarray]] = []

    def hook(engine: Any, sim: Any) -> None:
        sim.plant.listeners.append(lambda b: blocks.append((b.t.copy(), b.displacement.copy())))

        def at(_now: float) -> None:
            if "t0" not in seen and engine.snapshot.state == "running":
                seen["t0"] = sim.clock.now() - engine.now()  # the plant's time of the run's zero
        sim.clock.subscribe(at)

    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=hook)
    assert result.state == "completed", result.reason
    run = open_run(result.path)
    motor = run.streams["motor"]
    t, x = np.asarray(motor.t), X_AT_MOTOR_ZERO + np.asarray(motor.columns["position"])
    tp = np.concatenate([b[0] for b in blocks]) - seen["t0"]
    xp = np.concatenate([b[1] for b in blocks])
    order = np.argsort(tp, kind="stable")
    tp, xp = tp[order], xp[order]
    inside = (t > tp[0] + 0.01) & (t < tp[-1] - 0.01)
    v = np.interp(t, tp, np.gradient(xp, tp))
    moving = inside & (np.abs(v) > 0.02)  # the raised cosine's peak speed is ~0.06 m/s at 0.5 Hz, 0.13 at 1 Hz
    r = x[moving] - np.interp(t[moving], tp, xp)  # a reading stamped δ late lies at x(t − δ) ≈ x(t) − v δ
    delay = float(-np.sum(r * v[moving]) / np.sum(v[moving] ** 2))
    # the shift fits: what is left is the encoder's 0.1-µm counts, not a trajectory the stamps do not follow
    assert np.max(np.abs(x[moving] - np.interp(t[moving] - delay, tp, xp))) < 1e-6
    return delay, int(moving.sum()), str(run.attrs["wire_time"])


@pytest.mark.parametrize("rig, setpoint_Hz, position_Hz, frequency_Hz", [
    ("lsdea-motor-daq-sim", 50, 50, 1.0),  # hardware-timed: the T7 plays the voltage, the motor is polled
    ("lsdea-motor-sim", 10, 20, 0.5),  # software-timed, slow enough for its lines (wire time on)
])
def test_the_recorded_motor_position_follows_the_plants_trajectory_without_delay(
        tmp_path: Path, rig: str, setpoint_Hz: int, position_Hz: int, frequency_Hz: float) -> None:
    """Before: 2.39 ms behind on both rigs (the turnaround and the reply's wire time); after: under 0.1 ms."""
    delay, n, wire_time = recorded_offset(tmp_path, rig, setpoint_Hz=setpoint_Hz, position_Hz=position_Hz,
                                          frequency_Hz=frequency_Hz, wire=True)
    assert wire_time == "real"
    assert n >= 25
    assert abs(delay) < 0.1e-3, f"motor position {delay * 1e3:.3f} ms behind the plant"


def test_at_pty_speed_no_wire_time_is_taken_off_the_stamps(tmp_path: Path) -> None:
    """A protocol that outruns the rig's lines runs its twins at pty speed ("none" timing): a reply arrives the
    moment the twin makes it, so the stamp is the arrival — taking the 1.4-ms wire time of a reply that never took it
    off would put every position 1.4 ms ahead of the plant."""
    delay, n, wire_time = recorded_offset(tmp_path, "lsdea-motor-sim", setpoint_Hz=50, position_Hz=50,
                                          frequency_Hz=1.0, wire=False)
    assert wire_time.startswith("off")
    assert n >= 25
    assert abs(delay) < 0.1e-3, f"motor position {delay * 1e3:.3f} ms behind the plant"


def _sampled_at(twin: Any, method: str, clock: Any) -> list[float]:
    """Record the rig-clock instant at which ``twin`` calls its own ``method`` (where it reads its instrument)."""
    seen: list[float] = []
    original = getattr(twin, method)

    def recording(*args: Any, **kwargs: Any) -> Any:
        seen.append(clock.now())
        return original(*args, **kwargs)
    setattr(twin, method, recording)
    return seen


@pytest.mark.parametrize("rig", ["lsdea-motor-sim", "thesis-sim"])
def test_every_polled_reading_is_stamped_when_its_twin_read_its_instrument(rig: str) -> None:
    """Wire time on, virtual clock, nothing else moving it: each driver's stamp is the instant its twin read the
    plant — the LinMot drive its status (115,200 Bd), the DGT1S and the ADAM-4017+ their registers (behind the
    twins' Modbus TCP gateway, on its 19,200-Bd RS-485 line), the LK-G its measured value (115,200 Bd). Before,
    each was late by its turnaround and its reply's wire time (LinMot 2.4 ms, LK-G 1.5 ms, DGT1S 8.8 ms)."""
    from tests.conftest import start_rig

    r = start_rig(rig, timing="real")
    try:
        clock, twins, inst = r.sim.clock, r.sim.twins, r.inst
        reads: list[tuple[str, Any, list[float]]] = [
            ("amplifier monitors", lambda: inst.amplifier.read_monitors()[0],  # type: ignore[union-attr]
             _sampled_at(twins["amplifier AI"], "read", clock))]
        if rig == "lsdea-motor-sim":
            reads += [("motor position", inst.motor.read_position,  # type: ignore[union-attr]
                       _sampled_at(twins["motor"], "status", clock)),
                      ("load cell", inst.load_cell.read_force,  # type: ignore[union-attr]
                       _sampled_at(twins["load_cell"], "read", clock))]
        else:
            reads.append(("laser", inst.laser.read_displacement,  # type: ignore[union-attr]
                          _sampled_at(twins["laser"], "reply", clock)))
        for name, read, sampled in reads:
            before = clock.now()
            reading = read()
            assert sampled and sampled[-1] > before, name  # the twin read its instrument for this request
            assert clock.now() > sampled[-1]  # and its reply took wire time after that
            assert reading.timestamp == pytest.approx(sampled[-1], abs=1e-9), \
                f"{name}: stamped {(reading.timestamp - sampled[-1]) * 1e3:.3f} ms after its twin read it"
    finally:
        r.inst.close()
        r.sim.stop()


@pytest.mark.parametrize("gateway, endpoint, expected", [
    (None, False, None),  # a Modbus TCP device itself: nothing taken off
    (9600, False, 9600),  # the rig file says a TCP/RTU gateway's RS-485 line runs at 9600 Bd
    (None, True, 19200),  # a twin's endpoint: its transport serves the bus as a gateway at the bus's baud rate
])
def test_a_tcp_bus_takes_a_gateways_line_time_off_only_where_there_is_one(tmp_path: Path, gateway: int | None,
                                                                          endpoint: bool, expected: int | None) -> None:
    """A reviewer's finding: every tcp:// bus was taken for a gateway at ``baudrate`` (19,200 Bd by default), so a
    real Modbus TCP device's readings were stamped up to 7.8 ms early. The rig file now says so (gateway_baudrate)."""
    from bench.rig import load_rig
    from bench.runtime.instruments import build_instruments
    from tests.test_validation import _set

    text = (RIGS / "lsdea-motor-sim.toml").read_text()
    bus = next(line.split(".", 1)[1].rstrip("]") for line in text.splitlines() if line.startswith("[buses."))
    text = _set(text, f"buses.{bus}", "port", '"tcp://192.0.2.1:502"')
    if gateway is not None:
        text = _set(text, f"buses.{bus}", "gateway_baudrate", str(gateway))
    (tmp_path / "rig.toml").write_text(text)
    rig = load_rig(tmp_path / "rig.toml")
    inst = build_instruments(rig, {bus: "tcp://127.0.0.1:5020"} if endpoint else {})
    assert inst.links[bus].gateway_baud == expected


def test_a_rig_file_of_twins_served_without_wire_time_takes_none_off_the_stamps(tmp_path: Path) -> None:
    """`bench sim serve --no-wire-time --write-rig` wrote a rig that connected as real hardware, wire time on: every
    stamp early by its reply's wire time (a reviewer's finding). The written rig now says that its lines take none."""
    from bench.rig import load_rig
    from bench.runtime.devices import served_rig, write_rig
    from bench.runtime.instruments import build_instruments

    rig = load_rig(RIGS / "lsdea-motor-sim.toml")
    ports = {name: f"tcp://127.0.0.1:{5020 + k}" for k, name in enumerate(rig.buses)}
    for wire in (False, True):
        write_rig(served_rig(rig, ports, wire_time=wire), tmp_path / "served.toml")
        inst = build_instruments(load_rig(tmp_path / "served.toml"))
        assert inst.links and all(link.wire is wire for link in inst.links.values())
        assert inst.motor is not None and inst.motor.link.wire is wire  # type: ignore[attr-defined]
