"""bench devices control: manual commands on a simulated rig under the supervisor, every action in the log."""

from __future__ import annotations

import re
from pathlib import Path

from typer.testing import CliRunner

from bench.cli import app
from bench.rig import load_rig
from bench.runtime.manual import ManualSession

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
