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
from bench.runtime.latch import drive_of

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
    rig_latch.latch(rig.name, "interlock: output mismatch", "r.h5", drive_of(rig))
    copy = load_rig(_renamed(LAB, "thesis-lab-copy", tmp_path))
    other = load_rig(_renamed(LAB, "second-amplifier", tmp_path, **{'"/dev/ttyUSB0"': '"/dev/ttyUSB3"'}))
    with pytest.raises(rig_latch.LatchedError) as err:
        rig_latch.refuse_if_latched(copy.name, drive_of(copy))
    line = str(err.value)
    assert "thesis-lab-copy" in line and "latched under rig thesis-lab" in line and "/dev/ttyUSB0" in line
    assert "bench interlock reset thesis-lab " in line  # the reset names the latch's own rig
    rig_latch.refuse_if_latched(other.name, drive_of(other))  # other hardware: not held
    # the operator's reset from the copy (manual control's `reset`, a resumed campaign) clears the hardware's latch
    was = rig_latch.reset(copy.name, "bo", "amplifier checked", drive_of(copy))
    assert was is not None and was["rig"] == "thesis-lab"
    assert rig_latch.latched(rig.name, drive_of(rig)) is None
    history = (rig_latch.state_dir() / "interlock.log").read_text(encoding="utf-8")
    assert "reset\tthesis-lab\tby bo: amplifier checked (latched under rig thesis-lab" in history


def test_simulated_rigs_never_hold_each_other() -> None:
    rig_latch.latch("thesis-sim", "fault", "a.h5", None)
    rig_latch.refuse_if_latched("lsdea-motor-sim", None)


def test_bench_run_of_a_renamed_lab_rig_is_refused_before_any_port_is_opened(tmp_path: Path) -> None:
    rig = load_rig(DAQ_LAB)
    rig_latch.latch(rig.name, "interlock: host stall 1.5 s", "night.h5", drive_of(rig))
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


def test_the_same_port_named_another_way_is_the_same_drive(tmp_path: Path) -> None:
    """A link to the latched port (as /dev/serial/by-id gives one), the path spelt with '..', the T7's host name in
    other letters, or its IPv6 address written out in full: the same hardware, refused."""
    device = tmp_path / "ttyUSB0"  # stands for the adapter's device node
    device.touch()
    link = tmp_path / "usb-FTDI_FT232R_A1B2C3-if00-port0"
    link.symlink_to(device)
    rig = load_rig(_renamed(LAB, "night-rig", tmp_path, **{'"/dev/ttyUSB0"': f'"{device}"'}))
    rig_latch.latch(rig.name, "interlock: output mismatch", "r.h5", drive_of(rig))
    for name, port in (("by-link", str(link)), ("dotted", f"{tmp_path}/../{tmp_path.name}/ttyUSB0")):
        copy = load_rig(_renamed(LAB, name, tmp_path, **{'"/dev/ttyUSB0"': f'"{port}"'}))
        with pytest.raises(rig_latch.LatchedError, match="latched under rig night-rig"):
            rig_latch.refuse_if_latched(copy.name, drive_of(copy))
    daq = load_rig(DAQ_LAB)
    rig_latch.latch(daq.name, "interlock: host stall", "d.h5", drive_of(daq))
    shouted = load_rig(_renamed(DAQ_LAB, "upper", tmp_path, **{'"t7.invalid"': '"T7.INVALID"'}))
    with pytest.raises(rig_latch.LatchedError, match="latched under rig thesis-daq-lab"):
        rig_latch.refuse_if_latched(shouted.name, drive_of(shouted))
    ip = load_rig(_renamed(DAQ_LAB, "by-ip", tmp_path, **{'"t7.invalid"': '"FE80:0000:0000:0000:0000:0000:0000:0A01"'}))
    assert ip.daq is not None
    rig_latch.latch(ip.name, "interlock: host stall", "e.h5", drive_of(ip))
    plain = load_rig(_renamed(DAQ_LAB, "plain-ip", tmp_path, **{'"t7.invalid"': '"fe80::a01"'}))
    with pytest.raises(rig_latch.LatchedError, match="latched under rig by-ip"):
        rig_latch.refuse_if_latched(plain.name, drive_of(plain))


def test_a_reset_on_the_hardware_clears_every_latch_on_it(tmp_path: Path) -> None:
    """Two rig files on one amplifier, both latched: the operator's reset from either clears both (manual control's
    `reset` would otherwise unlatch its session while a run on that hardware stays refused)."""
    a = load_rig(LAB)
    b = load_rig(_renamed(LAB, "thesis-lab-b", tmp_path))
    rig_latch.latch(a.name, "fault a", "a.h5", drive_of(a))
    rig_latch.latch(b.name, "fault b", "b.h5", drive_of(b))
    assert rig_latch.reset(b.name, "bo", "both checked", drive_of(b)) is not None
    assert rig_latch.latched(a.name, drive_of(a)) is None and rig_latch.latched(b.name, drive_of(b)) is None
    history = (rig_latch.state_dir() / "interlock.log").read_text(encoding="utf-8")
    assert "reset\tthesis-lab-b\tby bo: both checked" in history
    assert "reset\tthesis-lab\tby bo: both checked (latched under rig thesis-lab" in history


def test_an_unreadable_older_latch_file_is_not_removed_by_another_rigs_reset() -> None:
    """``interlock-thesis-sim.json`` damaged: it may be thesis-sim's or `thesis sim`'s (both clean up to that name),
    so it latches both and neither reset removes it; the error says to check and remove it by hand."""
    old = rig_latch.state_dir() / "interlock-thesis-sim.json"
    old.parent.mkdir(parents=True, exist_ok=True)
    old.write_text("{damaged")
    rig_latch.latch("thesis sim", "fault", "a.h5")
    with pytest.raises(ValueError, match="unreadable and may be another rig's"):
        rig_latch.reset("thesis sim", "bo", "checked")
    assert old.exists() and rig_latch.latched("thesis-sim") is not None


def test_a_latch_keeps_the_names_its_adapter_had_at_the_start(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The run takes its drive's names at the start, while the adapter is there (bench/runtime/run.py, manual
    control): an "output path dead" latch is written after the adapter is gone, when its by-id link no longer
    resolves to it. Replugged as another device node, the rig file naming the by-id link, or the new node, is
    still refused."""
    links = tmp_path / "by-id"
    links.mkdir()
    monkeypatch.setattr(rig_latch, "SERIAL_LINKS", (links,))
    node0, node1 = tmp_path / "ttyUSB0", tmp_path / "ttyUSB1"
    node0.touch()
    by_id = links / "usb-FTDI_FT232R_A1B2C3-if00-port0"
    by_id.symlink_to(node0)
    rig = load_rig(_renamed(LAB, "night", tmp_path, **{'"/dev/ttyUSB0"': f'"{node0}"'}))
    at_start = drive_of(rig)
    node0.unlink()  # the adapter drops out during the run
    by_id.unlink()
    rig_latch.latch(rig.name, "interlock: output path dead", "n.h5", at_start)
    node1.touch()  # replugged: a new node, udev's by-id link to it
    by_id.symlink_to(node1)
    for name, port in (("by-link", str(by_id)), ("new-node", str(node1))):
        copy = load_rig(_renamed(LAB, name, tmp_path, **{'"/dev/ttyUSB0"': f'"{port}"'}))
        with pytest.raises(rig_latch.LatchedError, match="latched under rig night"):
            rig_latch.refuse_if_latched(copy.name, drive_of(copy))


def test_odd_ports_have_names_and_no_traceback() -> None:
    """A Windows device name in either case is one port; a URL pyserial would refuse is kept as written (no
    ValueError before the driver says what is wrong with it); no name server is asked."""
    assert rig_latch._port_names("com3") == rig_latch._port_names("COM3")
    assert rig_latch._port_names("socket://[::1") == {"socket://[::1"}
    assert rig_latch._port_names("RFC2217://Adapter.lab:2217") == {"rfc2217://adapter.lab:2217"}
