"""One process at a time per instrument (bench/runtime/rig_lock.py): a second run, manual session or device check
on a rig another process drives is refused before it touches any instrument."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime.devices import check_instruments, served_rig, write_rig
from bench.runtime.rig_lock import LOCK_DIR_ENV, RigInUseError, addresses, claimed
from bench.runtime.run import execute, plan_run
from tests.conftest import RIGS, ROOT

SHORT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"


@pytest.fixture(autouse=True)
def _own_lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    (tmp_path / "locks").mkdir()


@pytest.fixture
def served(tmp_path: Path) -> Iterator[RigConfig]:
    """The T7 thesis rig's twins, started here and seen as a real rig (as `bench sim serve --write-rig` writes it)."""
    from bench.runtime.sim_rig import SimRig

    sim = SimRig(load_rig(RIGS / "thesis-daq-sim.toml"), timing="none")
    sim.start()
    try:
        write_rig(served_rig(sim.rig, sim.port_map()), tmp_path / "served.toml")
        yield load_rig(tmp_path / "served.toml")
    finally:
        sim.stop()


def test_the_addresses_are_the_rig_file_s_instruments() -> None:
    """Each instrument of the lab rig files once, by the address its file gives (a serial device by its real path)."""
    def serial(port: str) -> str:
        return port.lower() if port.startswith("tcp://") else f"serial:{os.path.realpath(port)}"

    rig = load_rig(RIGS / "lsdea-motor-lab.toml")
    assert rig.motor is not None and rig.load_cell is not None
    assert addresses(rig) == {"motor": serial(rig.motor.port),
                              f"bus {rig.load_cell.bus}": serial(rig.buses[rig.load_cell.bus].port),
                              **({f"bus {rig.amplifier.bus}": serial(rig.buses[rig.amplifier.bus].port)}
                                 if rig.amplifier is not None and rig.amplifier.drive != "daq" else {}),
                              **({"laser": serial(rig.laser.port)} if rig.laser is not None else {})}
    daq = load_rig(RIGS / "thesis-daq-lab.toml")
    assert daq.daq is not None
    assert addresses(daq)["daq"] == f"tcp://{daq.daq.host.lower()}:{daq.daq.port}"


def test_a_rig_held_elsewhere_refuses_a_run_and_a_check_before_touching_them(served: RigConfig,
                                                                          tmp_path: Path) -> None:
    with claimed(served):  # another holder (a second open file description: flock refuses it as another process's)
        with pytest.raises(RigInUseError, match=rf"^rig {served.name}: the (daq|laser) at \S+ is in use by "
                                                rf"process {os.getpid()} "):
            check_instruments(served)
        with pytest.raises(RigInUseError, match="one process at a time"):
            execute(plan_run(SHORT, tmp_path / "served.toml"), tmp_path / "second.h5")
        assert not (tmp_path / "second.h5").exists()
    rows = check_instruments(served)  # released: the check runs
    assert rows and all(r.ok for r in rows), rows


def test_a_simulated_rig_claims_nothing(tmp_path: Path) -> None:
    rig = load_rig(RIGS / "thesis-daq-sim.toml")
    with claimed(rig), claimed(rig):  # each process starts its own twins
        pass
    assert not list((tmp_path / "locks").iterdir())


HOLD = """
import sys, time
from bench.rig import load_rig
from bench.runtime.rig_lock import claimed
with claimed(load_rig(sys.argv[1])):
    print("held", flush=True)
    time.sleep(60)
"""


def test_a_second_process_is_refused_in_one_line_naming_the_holder(served: RigConfig, tmp_path: Path) -> None:
    env = {**os.environ, "COLUMNS": "300"}
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path / "served.toml")], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        res = subprocess.run([sys.executable, "-m", "bench", "devices", "check", str(tmp_path / "served.toml")],
                             cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    finally:
        holder.kill()
        holder.wait()
    assert res.returncode == 2, res.stdout + res.stderr
    (line,) = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert f"is in use by process {holder.pid}" in line and "Traceback" not in res.stderr, res.stderr
    # the holder gone (however it ended), the kernel released its claims
    again = subprocess.run([sys.executable, "-m", "bench", "devices", "check", str(tmp_path / "served.toml")],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr


def test_a_missing_lock_folder_is_made_and_one_that_cannot_be_is_named(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """$BENCH_LOCK_DIR naming a folder not made yet: made (before, every claim failed with 'No such file or
    directory', the variable unnamed; found from outside); one that cannot be made: one line naming the variable."""
    rig = load_rig(RIGS / "lsdea-motor-lab.toml")  # a real rig's serial ports: claims, nothing opened
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "new" / "locks"))
    with claimed(rig):
        assert any((tmp_path / "new" / "locks").glob("dea-bench-instrument-*.lock"))
    (tmp_path / "file").write_text("")
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "file" / "locks"))
    with pytest.raises(ValueError, match=rf"^{LOCK_DIR_ENV}=.*file/locks: cannot make the folder"), claimed(rig):
        pass
