"""Rig files (validation, one-line errors) and the commands `bench sim serve` / `bench devices check`."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import RigFileError, load_rig
from bench.runtime.devices import check_instruments, served_rig, write_rig
from tests.conftest import RIGS, ROOT

runner = CliRunner()
ALL_RIGS = sorted(RIGS.glob("*.toml"))


@pytest.mark.parametrize("path", ALL_RIGS, ids=lambda p: p.stem)
def test_every_example_rig_file_validates(path: Path) -> None:
    rig = load_rig(path)
    assert rig.simulated == path.stem.endswith("-sim")
    assert rig.amplifier is not None and rig.amplifier.max_voltage_V <= 10_000


@pytest.mark.parametrize("text, message", [
    ("name = 'x'\n[laser]\nmodel = 'LK-X'\n", "laser.model: Input should be 'LK-G3000' or 'LK-G5000'"),
    ("name = 'x'\n[amplifier]\nbus = 'io'\n", "amplifier.bus 'io' is not defined under [buses]"),
    ("name = 'x'\n[buses.io]\n[amplifier]\nbus = ''\n", "amplifier.bus: String should have at least 1 character"),
    ("name = 'x'\n[buses.io]\n[load_cell]\nbus = ''\n", "load_cell.bus: String should have at least 1 character"),
    ("name = 'x'\ncolour = 'red'\n", "colour: Extra inputs are not permitted"),
    ("name = 'x'\n[motor]\ntravel_m = [0.1, 0.0]\n", "travel_m must be increasing"),
    ("name = 'x'\n[limits]\nmax_voltage_V = 20000\n", "limits.max_voltage_V: Input should be less than or equal"),
    # pydantic read true as 1 (an outside tester: a 1-s ramp, a 1-A limit); a true/false field still takes one
    ("name = 'x'\n[limits]\nshutdown_ramp_s = true\n", "limits.shutdown_ramp_s: true is not a number"),
    ("name = 'x'\n[limits]\nmax_current_A = false\n", "limits.max_current_A: false is not a number"),
    ("name = 'x'\nsimulated = 1.5\n", "simulated: Input should be a valid boolean"),
    # two load cells: the bridge on the DAQ sampled by the stream, the transmitter never supervised (a reviewer)
    ((ROOT / "rigs" / "lsdea-motor-daq-sim.toml").read_text(encoding="utf-8")
     + "\n[buses.scale]\nport = 'sim'\n[load_cell]\nbus = 'scale'\n", "both name the rig's load cell"),
    ("name = \n", "not valid TOML"),
    # a NUL in the name ended a manual session with "embedded null byte" (an outside tester)
    ('name = "a\\u0000b"\n', "name: one line of printable text"),
    ("name = ' '\n", "name: empty: give the rig a name"),
    (f"name = '{'x' * 101}'\n", "name: String should have at most 100 characters"),
    ("description = 'no name'\n", "name: Field required"),
])
def test_malformed_rig_files_get_one_line_errors(tmp_path: Path, text: str, message: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(RigFileError) as err:
        load_rig(f)
    assert message in str(err.value) and str(f) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("old, new, message", [
    ("laser_ain = 2", "laser_ain = 0", "daq: analog inputs must differ (vmon 0, imon 1, force None, laser 0)"),
    ("drive_offset_V = -10.0", "drive_offset_V = 10.0", "daq: the conditioning stage cannot produce 0 V"),
])
def test_a_daq_section_s_own_checks_name_the_section_once(tmp_path: Path, old: str, new: str, message: str) -> None:
    """Two of its analog inputs on one pin read "daq: daq: analog inputs must differ" (an outside tester): the
    section's name comes from where the error is, once."""
    text = (ROOT / "rigs" / "thesis-daq-sim.toml").read_text(encoding="utf-8")
    assert old in text
    f = tmp_path / "bad.toml"
    f.write_text(text.replace(old, new), encoding="utf-8")
    with pytest.raises(RigFileError) as err:
        load_rig(f)
    assert f"{f}: {message}" in str(err.value), str(err.value)


def test_a_rig_file_takes_quantities_with_units_as_a_protocol_file_does(tmp_path: Path) -> None:
    """Rig files took plain numbers only where protocol files take units (last note): a field whose name ends in
    its unit takes a quantity of that dimension in any unit, converted to the unit the name gives (500 ms = 0.5 s,
    4 mA = 0.004 A, 4 cm = 40 mm, 25 °C = 298.15 K, 8 kV = 8000 V); a plain number is that unit, as before; a
    quantity of another dimension is refused in one line naming the field."""
    f = tmp_path / "units.toml"
    f.write_text("name = 'x'\n[specimen]\ntemperature_K = '25 °C'\n[limits]\nmax_voltage_V = '8 kV'\n"
                 "max_current_A = '4 mA'\nshutdown_ramp_s = '500 ms'\ntravel_tolerance_m = 0.002\n"
                 "[laser]\nrange_mm = '4 cm'\n[motor]\ntravel_m = ['0 mm', '10 cm']\n"
                 "max_velocity_m_per_s = '500 mm/s'\n")
    rig = load_rig(f)
    assert rig.specimen.temperature_K == pytest.approx(298.15)
    assert rig.limits.max_voltage_V == 8000.0 and rig.limits.max_current_A == pytest.approx(4e-3)
    assert rig.limits.shutdown_ramp_s == pytest.approx(0.5) and rig.limits.travel_tolerance_m == 0.002
    assert rig.laser is not None and rig.laser.range_mm == pytest.approx(40.0)
    assert rig.motor is not None and rig.motor.travel_m == pytest.approx((0.0, 0.1))
    assert rig.motor.max_velocity_m_per_s == pytest.approx(0.5)
    for text, message in (("[limits]\nmax_current_A = '5 kV'", "limits.max_current_A: '5 kV' is a voltage, "
                                                                 "expected a current"),
                          ("[limits]\nshutdown_ramp_s = '2 min'", "limits.shutdown_ramp_s: Input should be less "
                                                                   "than or equal to 10 s (got 120 s)"),
                          ("[limits]\nmax_force_N = 'much'", "limits.max_force_N: 'much' is not a number with a "
                                                              "unit")):
        f.write_text(f"name = 'x'\n{text}\n")
        with pytest.raises(RigFileError) as err:
            load_rig(f)
        assert message in str(err.value) and str(f) in str(err.value) and "\n" not in str(err.value), err.value


def test_devices_check_cli_on_the_simulated_rigs() -> None:
    for name in ("thesis-sim", "lsdea-motor-sim"):
        res = runner.invoke(app, ["devices", "check", str(RIGS / f"{name}.toml")], env={"COLUMNS": "200"})
        assert res.exit_code == 0, res.output
        assert res.output.count(" ok ") == len(load_rig(RIGS / f"{name}.toml").instruments)


def test_devices_check_cli_on_missing_hardware_fails_cleanly() -> None:
    proc = subprocess.run([sys.executable, "-m", "bench", "devices", "check", str(RIGS / "thesis-lab.toml")],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "200"})
    assert proc.returncode == 1 and "Traceback" not in proc.stderr + proc.stdout
    assert proc.stderr.strip().count("\n") == 0
    assert "2 of 2 instruments failed" in proc.stderr and "/dev/ttyUSB0" in proc.stderr


def test_bad_rig_file_on_the_command_line(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("name = 'x'\n[laser]\nbaudrate = -5\n")
    proc = subprocess.run([sys.executable, "-m", "bench", "devices", "check", str(f)], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: rig file {f}: laser.baudrate: Input should be greater than 0"


def test_served_rig_file_round_trips(tmp_path: Path) -> None:
    rig = load_rig(RIGS / "lsdea-motor-sim.toml")
    served = served_rig(rig, {"motor": "/dev/pts/99", "io": "/dev/pts/98", "scale": "tcp://127.0.0.1:5020"})
    write_rig(served, tmp_path / "served.toml")
    again = load_rig(tmp_path / "served.toml")
    assert again == served and not again.simulated
    assert again.motor.port == "/dev/pts/99" and again.buses["scale"].port == "tcp://127.0.0.1:5020"


@pytest.mark.parametrize("path", [p for p in ALL_RIGS if p.stem.endswith("-sim")], ids=lambda p: p.stem)
def test_every_shipped_sim_rig_can_be_served_to_another_process(path: Path, tmp_path: Path) -> None:
    """Issue 23 item 5: the rig `sim serve --write-rig` writes validates and a client connects to every instrument
    through it alone (a DAQ rig's endpoint is two sockets: daq.host, daq.port, daq.stream_port)."""
    from bench.runtime.sim_rig import SimRig

    rig = load_rig(path)
    sim = SimRig(rig, timing="none")
    try:
        sim.start()
        write_rig(served_rig(rig, sim.port_map()), tmp_path / "served.toml")
        served = load_rig(tmp_path / "served.toml")  # validates
        assert not served.simulated
        if served.daq is not None:
            host, port, stream = sim.port_map()["daq"].rsplit(":", 2)
            assert (served.daq.host, served.daq.port, served.daq.stream_port) == (host, int(port), int(stream))
        rows = check_instruments(served)  # no endpoints passed: the written file alone says where to connect
    finally:
        sim.stop()
    wired = ["load_cell"] if rig.daq is not None and rig.daq.force_ain is not None else []  # its bridge on an AIN
    assert sorted(r.role for r in rows if r.ok) == sorted({*rig.instruments, *wired}), rows


SERVE_AND_CTRL_C_IN_ANOTHER_THREAD = """
import signal, sys, threading, time
from pathlib import Path
served = Path(sys.argv[2])

def ctrl_c_lands_in_this_thread():  # the kernel may hand a process's SIGINT to any thread
    while not served.exists():
        time.sleep(0.02)
    time.sleep(0.5)  # serving now
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)

threading.Thread(target=ctrl_c_lands_in_this_thread, daemon=True).start()
from bench.cli import app
app(prog_name="bench", args=["sim", "serve", sys.argv[1], "--write-rig", str(served)])
"""


def test_sim_serve_stops_on_a_ctrl_c_that_lands_in_another_thread(tmp_path: Path) -> None:
    """With a twin's thread (not the main one) taking the signal, the main thread must still notice it."""
    res = subprocess.run([sys.executable, "-c", SERVE_AND_CTRL_C_IN_ANOTHER_THREAD, str(RIGS / "thesis-sim.toml"),
                          str(tmp_path / "served.toml")], capture_output=True, text=True, timeout=30, cwd=ROOT,
                         env={**os.environ, "COLUMNS": "200"})
    assert "simulated rig stopped" in res.stdout, res.stdout + res.stderr


def _serving(rig: str, served: Path, preexec: Callable[[], object] | None = None) -> subprocess.Popen[str]:
    """`bench sim serve RIG --write-rig SERVED` in another process, returned once its twins are up."""
    proc = subprocess.Popen([sys.executable, "-m", "bench", "sim", "serve", str(RIGS / rig), "--write-rig",
                             str(served)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "COLUMNS": "200"}, preexec_fn=preexec)
    deadline = time.monotonic() + 60
    while not served.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    if not served.exists():
        proc.kill()
        raise AssertionError(proc.stderr.read() if proc.poll() is not None else "timeout")
    time.sleep(0.2)
    return proc


def test_sim_serve_stops_on_sigint_even_when_started_with_sigint_ignored(tmp_path: Path) -> None:
    """A background job of a non-interactive shell starts with SIGINT ignored; a SIGINT sent to it must still stop
    the twins (Python installs no KeyboardInterrupt handler then, so `sim serve` sets its own)."""
    proc = _serving("thesis-sim.toml", tmp_path / "served.toml",
                    lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and "simulated rig stopped" in out, out + err


def test_sim_serve_for_another_process_and_ctrl_c(tmp_path: Path) -> None:
    served = tmp_path / "served.toml"
    proc = _serving("lsdea-motor-sim.toml", served)
    try:
        rows = check_instruments(load_rig(served))  # a client in this process, the twins in the other
        assert [r.role for r in rows if r.ok] == ["amplifier", "motor", "load_cell"], rows
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "LinMot LinRS" in out and "Modbus TCP" in out and "/dev/pts/" in out and "tcp://127.0.0.1:" in out
    assert "simulated rig stopped" in out and "Traceback" not in err


def test_sim_serve_stops_on_sigterm_and_refuses_real_rigs(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "bench", "sim", "serve", str(RIGS / "thesis-sim.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    line = ""
    while "serving" not in line and time.monotonic() < deadline:
        line = proc.stdout.readline()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "simulated rig stopped" in out, err
    res = runner.invoke(app, ["sim", "serve", str(RIGS / "thesis-lab.toml")])
    assert res.exit_code == 2 and "needs a simulated rig" in res.output


@pytest.mark.parametrize("flag, timing, said", [([], "real", "wire time: real"),
                                                (["--no-wire-time"], "none", "wire time: off")])
def test_sim_serve_serves_with_wire_time_unless_told_otherwise(flag: list[str], timing: str, said: str,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 10: `sim serve` serves the rig with its real timing unless told otherwise."""
    import bench.runtime.sim_rig as simrig

    seen: list[str | None] = []
    real_start = simrig.SimRig.start

    def start(self: simrig.SimRig) -> object:
        seen.append(self.timing)
        return real_start(self)

    monkeypatch.setattr(simrig.SimRig, "start", start)
    res = runner.invoke(app, ["sim", "serve", str(RIGS / "thesis-sim.toml"), "--duration", "0.2", *flag])
    assert res.exit_code == 0, res.output
    assert seen == [timing] and said in res.output


@pytest.mark.parametrize("flag, ports", [([], (0, 0)), (["--t7-ports"], (502, 702))])
def test_sim_serve_t7_ports_asks_for_the_t7s_own_ports(flag: list[str], ports: tuple[int, int],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 23: `sim serve --t7-ports` serves the T7 twin on 502 (Modbus TCP) and 702 (stream), the ports the T7
    datasheet gives; without it, ephemeral ports. (The wiring only: binding 502 needs root, which tests do not.)"""
    import bench.runtime.sim_rig as simrig

    seen: list[tuple[int, int]] = []
    monkeypatch.setattr(simrig.SimRig, "start", lambda self: seen.append(self.daq_ports) or {})
    res = runner.invoke(app, ["sim", "serve", str(RIGS / "thesis-daq-sim.toml"), "--duration", "0.1", *flag])
    assert res.exit_code == 0, res.output
    assert seen == [ports]


def _free_ports() -> tuple[int, int]:
    import socket

    with socket.socket() as a, socket.socket() as b:
        a.bind(("127.0.0.1", 0))
        b.bind(("127.0.0.1", 0))
        return a.getsockname()[1], b.getsockname()[1]


def test_a_daq_rig_serves_its_t7_on_the_ports_asked_and_a_client_connects_there() -> None:
    from bench.runtime.sim_rig import SimRig

    ports = _free_ports()
    sim = SimRig(load_rig(RIGS / "thesis-daq-sim.toml"), timing="none", daq_ports=ports)
    try:
        sim.start()
        assert sim.port_map()["daq"] == f"127.0.0.1:{ports[0]}:{ports[1]}"
        rows = check_instruments(sim.rig, sim.port_map())
    finally:
        sim.stop()
    assert [r.role for r in rows if r.role == "daq" and r.ok] == ["daq"], rows


def test_t7_ports_below_1024_move_up_where_binding_them_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """Unprivileged fallback: where the kernel refuses 502/702 (no root, no CAP_NET_BIND_SERVICE) the twin serves
    on 10502/10702. The refusal is simulated (a test must not need root, and this one may run as root)."""
    import bench.runtime.sim_rig as simrig
    from sim_devices.labjack_t7 import LabJackT7Sim

    real_start = LabJackT7Sim.start
    asked: list[tuple[int, int]] = []
    free = _free_ports()

    def start(self: LabJackT7Sim, timeout: float = 10.0, *, host: str = "127.0.0.1", port: int = 0,
              stream_port: int = 0) -> tuple[int, int]:
        asked.append((port, stream_port))
        if port < 1024:
            raise RuntimeError("simulated T7 did not start") from PermissionError(13, "Permission denied")
        return real_start(self, timeout, host=host, port=free[0], stream_port=free[1])  # the test's free ports

    monkeypatch.setattr(LabJackT7Sim, "start", start)
    sim = simrig.SimRig(load_rig(RIGS / "thesis-daq-sim.toml"), timing="none", daq_ports=simrig.T7_PORTS)
    try:
        sim.start()
    finally:
        sim.stop()
    assert asked == [(502, 702), (10502, 10702)]


def test_sim_serve_on_t7_ports_in_use_is_one_line(tmp_path: Path) -> None:
    """The T7's own ports taken by another program: one line naming them, no traceback (it printed 65 lines)."""
    import socket

    from bench.runtime.sim_rig import T7_PORTS

    held = []
    try:
        for port in T7_PORTS:
            s = socket.socket()
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                s.close()
                pytest.skip(f"port {port} cannot be bound here")
            s.listen()
            held.append(s)
        res = subprocess.run([sys.executable, "-m", "bench", "sim", "serve", str(RIGS / "thesis-daq-sim.toml"),
                              "--t7-ports", "--duration", "1"], capture_output=True, text=True, timeout=120, cwd=ROOT,
                             env={**os.environ, "COLUMNS": "300"})
    finally:
        for s in held:
            s.close()
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert "did not start" in line and "address already in use" in line, line


@pytest.mark.parametrize("args", [["watch", "x.h5", "--port", "99999"], ["watch", "x.h5", "--port", "-5"],
                                  ["run", "x.toml", "--web", "--web-port", "70000"]])
def test_a_port_out_of_range_is_refused_by_the_option(args: list[str]) -> None:
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "Invalid value for '--" in res.output and "port" in res.output, res.output


def test_devices_check_counts_only_instruments_when_closing_fails(tmp_path: Path) -> None:
    """A T7 address where something accepts the connection and never answers: the check's close step fails too,
    and its row was counted as an instrument ("4 of 4 instruments failed" on a rig of three; found by an outside
    tester). Now the summary counts the rig's instruments and names the closing error apart."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:  # hold every connection open, read nothing back
        server.settimeout(0.05)
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                held.append(server.accept()[0])

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    rig = tmp_path / "silent-t7.toml"
    port = server.getsockname()[1]
    rig.write_text((RIGS / "thesis-daq-lab.toml").read_text().replace(
        'host = "t7.invalid"', f'host = "127.0.0.1"\nport = {port}\ntimeout_s = 0.1'))
    try:
        res = runner.invoke(app, ["devices", "check", str(rig)], env={"COLUMNS": "200"})
    finally:
        stop.set()
        thread.join()
        for s in held:
            s.close()
        server.close()
    n = len(load_rig(rig).instruments)
    assert n == 3  # daq, amplifier, laser
    assert res.exit_code == 1, res.output
    assert f"3 of {n} instruments failed" in res.output and "closing the instruments: daq:" in res.output
    assert "Traceback" not in res.output


def test_a_rig_named_without_its_file_suggests_the_file_meant(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--rig thesis-sim` (a rig's name, not a file) said only "not found" (outside tester): a shipped rig's name is
    that rig; a misspelt one is suggested; a lab folder's rigs/NAME.toml is suggested, not chosen silently."""
    import shutil

    from bench.resources import rigs_dir

    protocol = str(ROOT / "protocols" / "short" / "thesis-identification-short.toml")

    def said(rig: str) -> str:
        res = CliRunner().invoke(app, ["validate", protocol, "--rig", rig], env={"COLUMNS": "300"})
        assert res.exit_code == 2 and "Traceback" not in res.output, res.output
        return res.output.strip().splitlines()[-1]

    monkeypatch.chdir(tmp_path)
    # a shipped rig's name is that rig (as a protocol's rig = "thesis-sim"; outside tester: refused with a hint)
    res = CliRunner().invoke(app, ["validate", protocol, "--rig", "thesis-sim", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["rig"] == "thesis-sim", res.output
    takes = "(--rig takes a rig file or a shipped rig's name)"
    here = Path.cwd().resolve()
    assert said("thesis-sm") == f"error: rig file {here / 'thesis-sm'}: not found; did you mean thesis-sim? {takes}"
    assert said("no-such-rig") == f"error: rig file {here / 'no-such-rig'}: not found {takes}"
    assert rigs_dir().is_dir()
    (tmp_path / "rigs").mkdir()  # a lab folder's own copy of that name: not chosen silently, suggested
    shutil.copy2(ROOT / "rigs" / "thesis-sim.toml", tmp_path / "rigs" / "thesis-sim.toml")
    assert said("thesis-sim") == "error: rig file thesis-sim: not found; did you mean rigs/thesis-sim.toml?"
