"""Link budget: every shipped protocol on every lab template and simulated rig; refused where the line
cannot carry it, accepted where the rates fit. Expected figures are derived here from the wire, not taken
from the module: 8N1 = 10 bits a character; Modbus RTU FC6 = 8 + 8 characters, FC4 of 5 registers = 8 + 15,
two 3.5-character silences (Modbus over Serial Line v1.02 §2.5.1.1), 1 ms module turnaround [assumed];
an LK-G stored value = 9 characters (8 and a comma, manual p. 5-6)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.protocol.link_budget import check_links, laser_upload_rate
from bench.protocol.program import Program, compile_program
from bench.protocol.schema import Protocol, load_protocol
from bench.rig import load_rig
from tests.conftest import RIGS, ROOT

PROTOCOLS = sorted((ROOT / "protocols").glob("*.toml")) + sorted((ROOT / "protocols" / "short").glob("*.toml"))
FC6_19200 = 16 * 10 / 19200 + 2 * 3.5 * 10 / 19200 + 1e-3  # 12.98 ms: at most 77 set-points/s
FC4_19200 = 23 * 10 / 19200 + 2 * 3.5 * 10 / 19200 + 1e-3  # 16.6 ms: at most 60 load-cell reads/s
FC3_2REG_19200 = (8 + 9) * 10 / 19200 + 2 * 3.5 * 10 / 19200 + 1e-3  # 13.5 ms: V and I monitors
# LinRS at 115,200 Bd (LinMot LinRS manual): a VAI go-to telegram 25 bytes, a default-response request 7 bytes,
# the default response 16 bytes; 1 ms drive turnaround [assumed]
GOTO_115200 = (25 + 16) * 10 / 115200 + 1e-3  # 4.56 ms
POLL_115200 = (7 + 16) * 10 / 115200 + 1e-3  # 3.00 ms


def compiled(path: Path, kind: str, **recording: float) -> tuple[Protocol, Program]:
    """The protocol compiled (no model dry run) for the software-timed lab template or simulated rig of its bench
    (the low-cost ADAM/DGT1S variant: the protocols' default rigs are hardware-timed, with no serial budget)."""
    protocol = load_protocol(path)
    name = load_rig(protocol.rig_path()).name.rsplit("-", 1)[0].removesuffix("-daq")
    if recording:
        protocol = protocol.model_copy(update={"recording": protocol.recording.model_copy(update=recording)})
    return protocol, compile_program(protocol, load_rig(RIGS / f"{name}-{kind}.toml"))


@pytest.mark.parametrize("kind", ["lab", "sim"])
@pytest.mark.parametrize("protocol", PROTOCOLS, ids=lambda p: p.stem)
def test_shipped_protocols_are_refused_where_a_real_line_cannot_carry_them(protocol: Path, kind: str) -> None:
    proto, plan = compiled(protocol, kind)
    rec, problems = proto.recording, check_links(plan)
    text = "\n".join(problems)
    if plan.rig.laser is not None and rec.displacement_Hz * 9 * 10 > 115200:  # storage outruns the upload
        assert f"laser at 115200 Bd: storage fills at {rec.displacement_Hz:,.0f} S/s" in text
    if plan.rig.amplifier is not None and rec.setpoint_Hz * FC6_19200 > 1:
        assert f"bus io at 19200 Bd: busy {rec.setpoint_Hz * FC6_19200 + 5 * (FC6_19200 + 2 * 10 / 19200):.0%}" \
            in text and "lower recording.setpoint_Hz to ≤" in text
    if plan.rig.load_cell is not None and rec.force_Hz * FC4_19200 > 1:
        assert f"bus scale at 19200 Bd: busy {rec.force_Hz * FC4_19200:.0%}" in text
    assert problems  # every shipped protocol outruns one of its lines (the finding of issue 10)
    assert all("\n" not in p and len(p) < 400 for p in problems)


@pytest.mark.parametrize("kind", ["lab", "sim"])
def test_what_fits_is_accepted(kind: str) -> None:
    # thesis-identification stores the laser at 200 S/s: each 0.25-s fetch uploads 50 values, 43 ms on the wire
    # ((50·9 + 38)·10/115200 s + 2 × 0.5 ms), within the 50-ms set-point period (at 500 S/s: 102 ms, two set-points
    # fall in one fetch), and the upload holds the host 16 % of the time beside the io bus's set-points and monitors
    for name, changes in [("thesis-identification", {"displacement_Hz": 200.0, "setpoint_Hz": 20.0}),
                          # at 60 set-points/s the io bus alone is busy 85 %: the laser stores at 50 S/s (4 %;
                          # a fetch of 13 values, 14.5 ms, within the 16.7-ms period: 100 S/s takes 23.8 ms)
                          ("lsdea-isotonic-short", {"displacement_Hz": 50.0, "setpoint_Hz": 60.0,
                                                    "points_per_cycle": 20}),
                          ("lsdea-isopotential", {"setpoint_Hz": 20.0, "force_Hz": 20.0, "position_Hz": 20.0})]:
        path = next(p for p in PROTOCOLS if p.stem == name)
        _, program = compiled(path, kind, **changes)
        assert check_links(program) == [], name


def test_laser_upload_rate_is_the_wire_rate_less_the_request_overhead() -> None:
    wire = 115200 / 10 / 9  # 1280 values/s if the link carried nothing else
    assert 0.95 * wire < laser_upload_rate(115200) < wire


def test_conversion_rates_bound_the_polling_rates() -> None:
    _, program = compiled(ROOT / "protocols" / "thesis-identification.toml", "lab", monitors_Hz=20.0,
                          displacement_Hz=200.0)
    problems = check_links(program)
    assert problems == ["amplifier monitors: polled at 20/s but the ADAM-4017+ converts 10 S/s over 2 channels "
                        "(5 S/s each): most reads repeat a value; lower recording.monitors_Hz to ≤ 5"]


P2 = """[protocol]
name = "p2"
rig = "{rig}"

[recording]
setpoint_Hz = {hz}
monitors_Hz = 5
force_Hz = 20
position_Hz = 20

[[steps]]
type = "move"
position = "9 cm"
velocity = "100 mm/s"

[[steps]]
type = "waveform"
name = "pos"
channel = "position"
kind = "triangle"
offset = "90 mm"
amplitude = "-40 mm"
frequency_Hz = 0.5
cycles = 1.5

[[steps]]
type = "ramp"
channel = "voltage"
to = "4 kV"
duration_s = 1

[[steps]]
type = "hold"
duration_s = 2

[[steps]]
type = "relax"
duration_s = 1
"""


@pytest.mark.parametrize("kind", ["lab", "sim"])
def test_links_that_each_fit_but_together_outrun_the_host_are_refused(tmp_path: Path, kind: str) -> None:
    """A triangle on the motor at 50 set-points/s on the software-timed LS-DEA motor bench: the io bus (FC6 at
    50/s + monitors), the scale bus (load cell at 20/s) and the LinRS link (go-tos at 50/s + polls at 20/s) are each
    below 100 %, but the engine waits on one link at a time, so together they need more than the host's second —
    the outside tester's run played the 0.5-Hz triangle at ~0.41 Hz. One line names the step, the sum and the rate
    that fits in 90 % of the host's time."""
    io = 50 * FC6_19200 + 5 * FC3_2REG_19200
    scale = 20 * FC4_19200
    motor = 50 * GOTO_115200 + 20 * POLL_115200
    assert max(io, scale, motor) < 1 < io + scale + motor  # each wire fits; the host does not
    fits = int((0.9 - 5 * FC3_2REG_19200 - scale - 20 * POLL_115200) / (FC6_19200 + GOTO_115200))  # 25
    path = tmp_path / "p2.toml"
    path.write_text(P2.format(rig=RIGS / f"lsdea-motor-{kind}.toml", hz=50))
    problems = check_links(compile_program(load_protocol(path), load_rig(RIGS / f"lsdea-motor-{kind}.toml")))
    assert len(problems) == 1, problems
    (line,) = problems
    assert "recording.setpoint_Hz = 50" in line and "steps[1](pos)" in line
    assert f"{io + scale + motor:.0%} of the time" in line
    assert f"lower recording.setpoint_Hz to ≤ {fits}" in line and "\n" not in line
    # at 20 set-points/s (the tester's run kept time there) nothing is said
    path.write_text(P2.format(rig=RIGS / f"lsdea-motor-{kind}.toml", hz=20))
    assert check_links(compile_program(load_protocol(path), load_rig(RIGS / f"lsdea-motor-{kind}.toml"))) == []


def test_the_laser_upload_counts_in_the_host_s_time() -> None:
    """A 2-s waveform on thesis-sim storing the laser at 1,000 S/s, set-points at 20/s and monitors at 5/s: each
    link fits, but the engine fetches the stored values in the step, one link at a time. The upload alone holds the
    host 1000 / laser_upload_rate(115200) ≈ 80 % of the time (the wire: 9 characters a value at 11,520 characters/s),
    the io bus's FC6 and monitor reads about a third more: more than the host has (a virtual run of it ended its step
    0.56 s late before the warning lifted the twins' wire time)."""
    _, program = compiled(ROOT / "protocols" / "thesis-identification.toml", "sim", displacement_Hz=1000.0,
                          setpoint_Hz=20.0)
    (host,) = [p for p in check_links(program) if p.startswith("host")]
    assert "laser storage upload 80%" in host and "displacement_Hz" in host


@pytest.mark.parametrize("kind", ["lab", "sim"])
def test_a_laser_upload_longer_than_a_set_point_period_is_said(kind: str) -> None:
    """A tester's protocol (500 S/s stored, 20 set-points/s) validated and then skipped 15 set-points: the engine
    fetches the storage every 0.25 s, 125 values, and sends nothing while it waits on the upload —
    (125·9 + 16 + 3 + 3 + 16) characters × 10/115200 s + 2 × 0.5 ms (LK-G turnaround, assumed) = 102 ms, two
    50-ms set-point periods. At most 0.05 s of upload fits a period: 58 values (232 S/s: 48.7 + 3.3 + 1 = 49.6 ms)."""
    path = ROOT / "protocols" / "thesis-identification.toml"
    hold = (125 * 9 + 38) * 10 / 115200 + 1e-3
    fit = max(n for n in range(1, 500) if (-(-n // 4) * 9 + 38) * 10 / 115200 + 1e-3 <= 0.05)  # ceil(0.25·n)
    assert fit == 232
    _, program = compiled(path, kind, displacement_Hz=500.0, setpoint_Hz=20.0)
    (line,) = [p for p in check_links(program) if p.startswith("laser storage upload")]
    assert f"holds the host ~{hold * 1e3:.0f} ms" in line and "set-point period (50 ms)" in line
    assert f"displacement_Hz to ≤ {fit}" in line and f"setpoint_Hz to ≤ {int(1 / hold)}" in line
    _, program = compiled(path, kind, displacement_Hz=float(fit), setpoint_Hz=20.0)
    assert not [p for p in check_links(program) if p.startswith("laser storage upload")]
    _, program = compiled(path, kind, displacement_Hz=500.0, setpoint_Hz=float(int(1 / hold)))
    assert not [p for p in check_links(program) if p.startswith("laser storage upload")]


def test_the_upload_hold_is_one_ao_request_at_most() -> None:
    """The driver uploads at most one AO request's worth of wire per fetch (0.2 s: 256 values at 115,200 Bd, the rest
    on the next call): at 2,000 S/s a fetch holds the host (256·9 + 38)·10/115200 s + 1 ms = 204 ms, not the
    500 values' 0.4 s (a reviewer: the line said 1,996 ms at 10 kS/s)."""
    _, program = compiled(ROOT / "protocols" / "thesis-identification.toml", "lab", displacement_Hz=2000.0,
                          setpoint_Hz=20.0)
    (line,) = [p for p in check_links(program) if p.startswith("laser storage upload")]
    assert f"~{((256 * 9 + 38) * 10 / 115200 + 1e-3) * 1e3:.0f} ms" in line
