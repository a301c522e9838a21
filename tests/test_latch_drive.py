"""A real rig's latch holds its hardware, not only its name: the amplifier's drive path (the set-point module's
port, unit and channel, or the T7's address and DAC) is recorded with the latch, and every rig file driving the same
hardware is refused until an operator resets it — renaming the rig, or copying its file under another name, does
not get round a latch. A latch is also written in the older file form, so a bench from before the hashed names sees
it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.rig import load_rig
from bench.runtime import latch as rig_latch

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "rigs" / "thesis-lab.toml"
DAQ_LAB = ROOT / "rigs" / "thesis-daq-lab.toml"


def _renamed(src: Path, name: str, tmp_path: Path, **replace: str) -> Path:
    text = src.read_text(encoding="utf-8")
    old = load_rig(src).name
    text = text.replace(f'name = "{old}"', f'name = "{name}"', 1)
    for a, b in replace.items():
        text = text.replace(a, b, 1)
    out = tmp_path / f"{name}.toml"
    out.write_text(text, encoding="utf-8")
    return out


def test_the_drive_path_names_the_hardware_as_the_rig_file_gives_it() -> None:
    # rigs/thesis-lab.toml: [buses.io] port "/dev/ttyUSB0", ao_unit 1, ao_channel 0
    assert load_rig(LAB).drive_path() == "/dev/ttyUSB0 unit 1 channel 0"
    # rigs/thesis-daq-lab.toml: [daq] host "t7.invalid", Modbus port 502 (the T7's default), DAC0
    assert load_rig(DAQ_LAB).drive_path() == "T7 t7.invalid:502 DAC0"
    assert load_rig(ROOT / "rigs" / "thesis-sim.toml").drive_path() is None  # its twins are its own


def test_a_renamed_copy_of_a_latched_rig_is_refused_until_the_reset(tmp_path: Path) -> None:
    rig = load_rig(LAB)
    rig_latch.latch(rig.name, "interlock: output mismatch", "r.h5", rig.drive_path())
    copy = load_rig(_renamed(LAB, "thesis-lab-copy", tmp_path))
    other = load_rig(_renamed(LAB, "second-amplifier", tmp_path, **{'"/dev/ttyUSB0"': '"/dev/ttyUSB3"'}))
    with pytest.raises(rig_latch.LatchedError) as err:
        rig_latch.refuse_if_latched(copy.name, copy.drive_path())
    line = str(err.value)
    assert "thesis-lab-copy" in line and "latched under rig thesis-lab" in line and "/dev/ttyUSB0" in line
    assert "bench interlock reset thesis-lab " in line  # the reset names the latch's own rig
    rig_latch.refuse_if_latched(other.name, other.drive_path())  # other hardware: not held
    # the operator's reset from the copy (manual control's `reset`, a resumed campaign) clears the hardware's latch
    was = rig_latch.reset(copy.name, "bo", "amplifier checked", copy.drive_path())
    assert was is not None and was["rig"] == "thesis-lab"
    assert rig_latch.latched(rig.name, rig.drive_path()) is None
    history = (rig_latch.state_dir() / "interlock.log").read_text(encoding="utf-8")
    assert "reset\tthesis-lab\tby bo: amplifier checked (latched under rig thesis-lab" in history


def test_simulated_rigs_never_hold_each_other() -> None:
    rig_latch.latch("thesis-sim", "fault", "a.h5", None)
    rig_latch.refuse_if_latched("lsdea-motor-sim", None)


def test_bench_run_of_a_renamed_lab_rig_is_refused_before_any_port_is_opened(tmp_path: Path) -> None:
    rig = load_rig(DAQ_LAB)
    rig_latch.latch(rig.name, "interlock: host stall 1.5 s", "night.h5", rig.drive_path())
    copy = _renamed(DAQ_LAB, "renamed", tmp_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    protocol = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    cli = subprocess.run([sys.executable, "-m", "bench", "run", str(protocol), "--rig", str(copy), "--yes",
                          "--no-live", "--out", str(tmp_path / "out")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert cli.returncode == 2, cli.stdout + cli.stderr
    text = " ".join(cli.stderr.split())
    assert "latched under rig thesis-daq-lab" in text and "Traceback" not in cli.stderr, cli.stderr
    assert not (tmp_path / "out").exists()


def test_a_latch_is_written_in_the_older_form_too_unless_another_rig_holds_it() -> None:
    rig_latch.latch("thesis-sim", "fault a", "a.h5")
    old = rig_latch.state_dir() / "interlock-thesis-sim.json"  # the form a bench before the hashed names reads
    assert json.loads(old.read_text(encoding="utf-8"))["rig"] == "thesis-sim"
    rig_latch.latch("thesis sim", "fault b", "b.h5")  # cleans up alike: the older file stays thesis-sim's
    assert json.loads(old.read_text(encoding="utf-8"))["fault"] == "fault a"
    assert rig_latch.reset("thesis sim", "bo", "x") is not None and old.exists()
    assert rig_latch.reset("thesis-sim", "bo", "x") is not None and not old.exists()
    old.write_text("{not json")  # an unreadable older latch is never replaced: it may be another rig's
    rig_latch.latch("thesis sim", "fault c", "c.h5")
    assert old.read_text() == "{not json"
