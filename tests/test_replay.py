"""Replay (bench.runtime.replay): a recorded run served through the twins, re-recorded, reproduces the record.

Tolerances are the instruments' quantisation, from the manuals, not from the code: the LK-G outputs millimetres
with 4 decimals (LK-G5000 manual p. 5-6: ``+01.2345``) → 1e-7 m; the ADAM-4017+ and the T7's stream give 16-bit
codes over ±10 V (ADAM-4017+ datasheet, 16-bit; LabJack T-Series datasheet: stream data are 16-bit) → 20/65536 V
at the input, times the rig's monitor ratio (1000 V/V, 1 mA/V) or the laser's analog scale (4 mm/V); the LinMot
reports positions in 0.1 µm (LinRS ActualPosition, int32 × 0.1 µm); the DGT1S in divisions of the rig file's
``division_kg`` (× standard gravity, the driver's N). The replay rigs have another seed than the recording: had
the twins served the model (noise off in a replay), the record's own noise (LK-G, monitors, load cell) could not
be reproduced.

Not compared: ``late`` (the host's own poll timing) and the DGT1S's ``ok`` — its stability judgement over its
own window of conversions, which a record at the polling rate does not hold (the held samples move the window's
changes by up to one record period).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.rig import load_rig
from bench.runtime.instruments import build_instruments
from bench.runtime.replay import ReplayError
from bench.runtime.run import execute, plan_run
from bench.runtime.sim_rig import SimRig
from tests.conftest import RIGS, ROOT

PROTOCOL = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
CODE_V = 20.0 / 65536  # one 16-bit code over ±10 V [V]
LKG_M = 1e-7  # 0.0001 mm
QUANTUM = {  # per (rig kind, stream, column): one step of what the instrument reports
    ("serial", "laser", "displacement"): LKG_M,
    ("serial", "amplifier", "voltage"): CODE_V * 1000.0, ("serial", "amplifier", "current"): CODE_V * 1e-3,
    ("daq", "laser", "displacement"): CODE_V * 0.004,
    ("daq", "amplifier", "voltage"): CODE_V * 1000.0, ("daq", "amplifier", "current"): CODE_V * 1e-3,
    ("motor", "amplifier", "voltage"): CODE_V * 1000.0, ("motor", "amplifier", "current"): CODE_V * 1e-3,
    ("motor", "motor", "position"): 1e-7, ("motor", "motor", "aperture"): 1e-7,
    ("motor", "load_cell", "force"): 0.001 * 9.80665,  # rigs/lsdea-motor-sim.toml: division_kg = 0.001
}
NOT_COMPARED = {"t", "late", "ok"}
RUNS = {"serial": ("thesis-sim.toml", PROTOCOL), "daq": ("thesis-daq-sim.toml", PROTOCOL),
        "motor": ("lsdea-motor-sim.toml", ROOT / "protocols" / "short" / "lsdea-isometric-short.toml")}


def replay_rig(rig: Path, record: Path, dest: Path) -> Path:
    """``rig`` with ``[simulation] replay = record`` and another seed."""
    text = rig.read_text(encoding="utf-8").replace("seed = 1", f'seed = 7\nreplay = "{record}"')
    assert "replay =" in text
    dest.write_text(text, encoding="utf-8")
    return dest


def record(rig: Path, out: Path, protocol: Path = PROTOCOL) -> Path:
    result = execute(plan_run(protocol, rig), out, virtual=True)
    assert result.state == "completed", result.reason
    return Path(result.path)


def assert_reproduces(original: Path, replayed: Path, kind: str) -> None:
    """Every stream of ``original`` is in ``replayed``, equal within one quantum on matching time stamps."""
    with h5py.File(original, "r") as a, h5py.File(replayed, "r") as b:
        assert b.attrs["replay_of"] == str(original)
        streams = [s for s in ("setpoints", "amplifier", "laser", "motor", "load_cell") if s in a]
        assert ({"motor", "load_cell"} if kind == "motor" else {"laser"}) | {"amplifier"} <= set(streams)
        for s in streams:
            ta, tb = np.round(a[s]["t"][:], 9), np.round(b[s]["t"][:], 9)
            _, ia, ib = np.intersect1d(ta, tb, return_indices=True)
            assert ia.size >= 0.99 * np.unique(ta).size, f"{s}: {ia.size} of {ta.size} time stamps match"
            for c in a[s]:
                if c in NOT_COMPARED:
                    continue
                x, y = a[s][c][:][ia].astype(float), b[s][c][:][ib].astype(float)
                same_nan = np.isnan(x) & np.isnan(y)
                q = QUANTUM.get((kind, s, c), 0.0)
                worst = float(np.max(np.where(same_nan, 0.0, np.abs(x - y)), initial=0.0))
                assert worst <= q * (1 + 1e-9), f"{s}/{c}: off by {worst:g} (quantum {q:g})"


@pytest.mark.parametrize("kind", list(RUNS))
def test_a_replayed_record_re_recorded_equals_the_original(kind: str, tmp_path: Path, short_run: Path) -> None:
    """Software-timed rig (LK-G storage, ADAM modules), hardware-timed rig (T7 stream), LS-DEA on the motor with
    the load cell (LinMot position, DGT1S force)."""
    name, protocol = RUNS[kind]
    rig = RIGS / name
    original = short_run if kind == "daq" else record(rig, tmp_path / "original.h5", protocol)
    again = record(replay_rig(rig, original, tmp_path / "replay.toml"), tmp_path / "again.h5", protocol)
    assert_reproduces(original, again, kind)


def test_replay_serves_the_record_not_the_model(tmp_path: Path, short_run: Path) -> None:
    """A record edited to a constant the model never gives is what the laser twin reports (read over the wire)."""
    edited = tmp_path / "edited.h5"
    shutil.copy(short_run, edited)
    with h5py.File(edited, "r+") as f:
        f["laser/displacement"][:] = 1.2345e-3
    sim = SimRig(load_rig(replay_rig(RIGS / "thesis-sim.toml", edited, tmp_path / "r.toml")), virtual=True)
    sim.start()
    try:
        inst = build_instruments(sim.rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep,
                                 timers=sim.reply_timers(), wire_time=sim.wire_time)
        assert inst.laser is not None
        inst.laser.connect()
        assert sim.replay is not None
        sim.replay.anchor(sim.clock.now())
        sim.clock.advance(2.0)  # type: ignore[attr-defined]
        assert inst.laser.read_displacement().value == pytest.approx(1.2345e-3, abs=LKG_M / 2)
        inst.close()
    finally:
        sim.stop()


def test_sim_serve_replay_serves_another_process(tmp_path: Path, short_run: Path) -> None:
    """`bench sim serve --replay RUN.h5 --write-rig x.toml` (the record's own rig): a client process reads the
    replayed laser value."""
    edited = tmp_path / "edited.h5"
    shutil.copy(short_run, edited)
    with h5py.File(edited, "r+") as f:
        f["laser/displacement"][:] = -0.4321e-3
    served = tmp_path / "served.toml"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    server = subprocess.Popen([sys.executable, "-m", "bench", "sim", "serve", "--replay", str(edited), "--write-rig",
                               str(served), "--no-wire-time", "--duration", "60"], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        rig = None
        for _ in range(600):  # until the rig file is there and whole (written while we look)
            if server.poll() is not None:
                break
            try:
                rig = load_rig(served)
                break
            except ValueError:
                time.sleep(0.1)
        assert rig is not None, server.communicate(timeout=5)[0] if server.poll() is not None else "no rig file"
        assert rig.simulation.replay is None  # the client's rig is real instruments
        client = ("from bench.rig import load_rig\nfrom bench.runtime.instruments import build_instruments\n"
                  f"inst = build_instruments(load_rig({str(served)!r}))\ninst.laser.connect()\n"
                  "print(inst.laser.read_displacement().value)\ninst.close()\n")
        out = subprocess.run([sys.executable, "-c", client], cwd=ROOT, env=env, capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr
        assert float(out.stdout.split()[-1]) == pytest.approx(-0.4321e-3, abs=LKG_M / 2)
    finally:
        server.terminate()
        server.wait(timeout=10)


def test_replay_errors_are_one_line(tmp_path: Path, short_run: Path) -> None:
    runner = CliRunner()
    not_run = tmp_path / "other.h5"
    with h5py.File(not_run, "w") as f:
        f["x"] = np.zeros(3)
    text = tmp_path / "notes.h5"
    text.write_text("not HDF5\n", encoding="utf-8")
    cases = [([str(tmp_path / "missing.h5")], "not found"), ([str(not_run)], "not a dea-bench run file"),
             ([str(text)], "not an HDF5 run file"),
             ([str(short_run), str(RIGS / "lsdea-motor-sim.toml")], "records no load_cell")]
    for args, words in cases:
        rig = args[1:] if len(args) > 1 else []
        res = runner.invoke(app, ["sim", "serve", *rig, "--replay", args[0], "--duration", "0.1"])
        assert res.exit_code != 0, res.output
        lines = [x for x in res.output.splitlines() if x.strip()]
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in res.output, res.output


def test_a_rig_replay_without_a_stream_its_twins_serve_is_refused(tmp_path: Path, short_run: Path) -> None:
    """No laser stream in the record, a laser twin in the rig: refused before anything serves."""
    stripped = tmp_path / "no-laser.h5"
    shutil.copy(short_run, stripped)
    with h5py.File(stripped, "r+") as f:
        del f["laser"]
    with pytest.raises(ReplayError, match="records no laser"):
        SimRig(load_rig(replay_rig(RIGS / "thesis-sim.toml", stripped, tmp_path / "r.toml")), virtual=True)


def test_commands_unlike_the_record_trip_the_output_verifier(tmp_path: Path, short_run: Path) -> None:
    """The verifier stays on in a replay and compares the host's commands with the recorded monitors: a protocol
    other than the one recorded (a sweep against a 7-kV raised cosine) is an output mismatch, never silent."""
    rig = replay_rig(RIGS / "thesis-daq-sim.toml", short_run, tmp_path / "replay.toml")
    result = execute(plan_run(ROOT / "protocols" / "short" / "thesis-sweeps-short.toml", rig), tmp_path / "x.h5",
                     virtual=True)
    assert result.state == "tripped" and "output mismatch" in result.reason, result.reason
    with h5py.File(result.path, "r") as f:
        assert f.attrs["replay_of"] == str(short_run)


def test_a_record_read_in_small_chunks_gives_the_next_sample_hold(short_run: Path, tmp_path: Path) -> None:
    """The track read forward 7 records at a time (chunk edges everywhere) gives, at any time, the first sample at
    or after it (the last after the end): computed here on the whole column at once. The record is the short
    run's laser cut to its first 2.6 s (26,000 records, some 3,700 chunks; a copy): forward within a chunk's
    reach, a jump of 1.7 s over thousands of chunks, the last samples, past the end and back to the start are
    the same cases as on the whole 11-s record, which took four times as many 7-record reads."""
    from bench.runtime.replay import Recording

    cut = tmp_path / "cut.h5"
    shutil.copy(short_run, cut)
    with h5py.File(cut, "r+") as f:
        for d in f["laser"].values():
            d.resize((26_000, *d.shape[1:]))
        t_all, v_all = f["laser/t"][:], f["laser/displacement"][:]
    assert t_all[-1] == pytest.approx(2.6)
    rec = Recording(cut, rows=7)
    try:
        track = rec.tracks["laser", "displacement"]
        rng = np.random.default_rng(3)
        for start in (-0.5, 0.0, 0.3, 2.00005, 2.5, 3.0):  # forward, then back to the start (re-read)
            times = start + np.sort(rng.uniform(0.0, 0.01, 40))
            expected = v_all[np.minimum(np.searchsorted(t_all, times - 1e-9), t_all.size - 1)]
            np.testing.assert_array_equal(track.at(times), expected)
        times = t_all[[1, 2]]  # back to the record's second and third samples after reading to the end
        np.testing.assert_array_equal(track.at(times), v_all[[1, 2]])
    finally:
        rec.close()


def test_a_record_whose_stream_started_late_replays_aligned_on_its_kickoff(tmp_path: Path, short_run: Path) -> None:
    """A record made on the wall clock starts its DAQ stream some 0.1 s into the run (connects, arming); a run
    replaying it in virtual time starts at once. Aligned on the run's start alone, the replayed monitors lagged the
    drive and the output verifier tripped on the recorded protocol (found from outside: 'read 760 V where 428 V was
    commanded'). Here the record's every time is moved 83.3 ms later, as such a record's are; the replay of the
    recorded protocol completes and serves scan k of the record at its own scan k."""
    late = 0.0833
    shifted = tmp_path / "late.h5"
    shutil.copy2(short_run, shifted)
    with h5py.File(shifted, "r+") as f:
        for s in ("setpoints", "amplifier", "laser"):
            f[s]["t"][...] = f[s]["t"][:] + late
        ev = f["events"]
        ev["t"][...] = ev["t"][:] + late
        texts = list(ev["text"][:])
        for k, text in enumerate(texts):
            if text.startswith(b"DAQ scan clock: scan 0 at "):
                was = float(text.split(b" at ")[1].split(b" s ")[0])
                ev["text"][k] = text.replace(f"{was:.6f}".encode(), f"{was + late:.6f}".encode(), 1)
        assert b"scan 0 at 0.0834" in b" ".join(ev["text"][:])
    again = execute(plan_run(PROTOCOL, replay_rig(RIGS / "thesis-daq-sim.toml", shifted, tmp_path / "replay.toml")),
                    tmp_path / "again.h5", virtual=True)
    assert again.state == "completed", again.reason
    with h5py.File(shifted, "r") as a, h5py.File(again.path, "r") as b:
        n = min(a["amplifier"]["t"].size, b["amplifier"]["t"].size)
        assert n > 0.99 * a["amplifier"]["t"].size
        worst = np.max(np.abs(a["amplifier"]["voltage"][:n] - b["amplifier"]["voltage"][:n]))
        assert worst <= QUANTUM["daq", "amplifier", "voltage"] * (1 + 1e-9)
