"""Virtual time never fails from host load: a wait for a twin's reply ends on what the twin did, not on the wall clock.

A twin thread starved of CPU answers late and must be waited for; a twin that withholds its reply (``Faults.mute``)
must still time out — at once on the wall clock, after its timeout on the rig clock. The campaigns run beside one
busy loop per core with the rigs' link timeouts cut to 5 ms: on the wall clock (the old waits) that fails within
seconds on a loaded host (``motor: write to /dev/pts/N timed out``, ``no valid reply``).
"""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.rig import RigConfig, load_rig, rig_to_toml
from bench.runtime.run import execute, plan_run
from drivers.deadline import WALL
from drivers.errors import InstrumentTimeoutError
from tests.conftest import ROOT, RunningRig

SHORT = ROOT / "protocols" / "short"
RIGS = ROOT / "rigs"
TIGHT_S = 0.005  # link timeouts far below what a starved host takes to answer


@pytest.fixture
def cpu_hogs() -> Iterator[list[subprocess.Popen[bytes]]]:
    """One busy loop per core (2) for the length of the test."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        yield hogs
    finally:
        for p in hogs:
            p.kill()
        for p in hogs:
            p.wait()


def tight_rig(name: str, folder: Path) -> Path:
    """``rigs/<name>.toml`` with every link timeout cut to TIGHT_S, written to ``folder``."""
    rig = load_rig(RIGS / f"{name}.toml")
    data = rig.model_dump()
    for section in ("motor", "laser", "daq"):
        if data.get(section):
            data[section]["timeout_s"] = TIGHT_S
    for bus in data["buses"].values():
        bus["timeout_s"] = TIGHT_S
    path = folder / f"{name}-tight.toml"
    path.write_text(rig_to_toml(RigConfig.model_validate(data)))
    return path


# ------------------------------------------------------------------ one link


def test_a_starved_twin_is_waited_for_where_the_wall_clock_gives_up(lsdea_motor: RunningRig) -> None:
    """The motor twin cannot answer while its state lock is held, as when its thread gets no CPU. With a 50-ms
    timeout a virtual-time link waits until the twin is free; the wall-clock wait gives up on the same twin."""
    motor, twin = lsdea_motor.inst.motor, lsdea_motor.sim.twins["motor"]
    motor.link.timeout = 0.05
    twin_timer = motor.link.timer
    order: list[str] = []
    release = threading.Event()

    def starve(hold: float | None) -> None:
        with twin._lock:  # type: ignore[attr-defined]
            held.set()
            release.wait(hold)
            order.append("twin free")

    held = threading.Event()
    starver = threading.Thread(target=starve, args=(0.3,))  # six timeouts
    starver.start()
    held.wait()
    motor.poll()
    order.append("replied")
    starver.join()

    motor.link.timer = WALL
    held = threading.Event()
    starver = threading.Thread(target=starve, args=(None,))  # until the wall clock has given up
    starver.start()
    held.wait()
    with pytest.raises(InstrumentTimeoutError):
        motor.poll()
    order.append("wall clock gave up")
    release.set()
    starver.join()
    motor.link.timer = twin_timer
    assert len(motor.link.read_exact(16)) == 16  # the late reply, so that it is not taken for the next one
    assert order == ["twin free", "replied", "wall clock gave up", "twin free"]


@pytest.mark.parametrize(("role", "attempts"), [("motor", 1), ("amplifier", 2)])
def test_a_muted_twin_times_out_at_once_after_its_timeout_in_rig_time(lsdea_motor: RunningRig, role: str,
                                                                         attempts: int) -> None:
    """Muted: no wait on the wall clock; the rig clock moves on by the timeout of every attempt (the io bus retries
    once), as the run would on hardware."""
    inst, clock = lsdea_motor.inst, lsdea_motor.sim.clock
    faults = lsdea_motor.sim.faults_of(role)
    faults.mute = True
    timeout = inst.motor.link.timeout if role == "motor" else inst.links["io"].timeout
    t0 = clock.now()
    with pytest.raises(InstrumentTimeoutError):
        if role == "motor":
            inst.motor.poll()  # type: ignore[union-attr]
        else:
            inst.amplifier.read_voltage()  # type: ignore[union-attr]
    assert clock.now() == pytest.approx(t0 + attempts * timeout, abs=1e-9)
    assert faults.counts["mute"] == attempts


# ------------------------------------------------------------------ whole runs beside a CPU hog on each core

CAMPAIGNS = [("lsdea-isopotential-short", "lsdea-motor-sim"), ("thesis-identification-short", "thesis-daq-sim")]


@pytest.mark.slow
@pytest.mark.parametrize(("protocol", "rig"), CAMPAIGNS)
def test_a_virtual_campaign_completes_beside_cpu_hogs(cpu_hogs: list[subprocess.Popen[bytes]], tmp_path: Path,
                                                      protocol: str, rig: str) -> None:
    plan = plan_run(SHORT / f"{protocol}.toml", tight_rig(rig, tmp_path))
    result = execute(plan, tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    assert all(p.poll() is None for p in cpu_hogs)  # the hogs ran throughout


@pytest.mark.slow
@pytest.mark.parametrize(("protocol", "rig", "role"), [(*CAMPAIGNS[0], "motor"), (*CAMPAIGNS[1], "daq")])
def test_a_muted_twin_still_ends_a_virtual_run_beside_cpu_hogs(cpu_hogs: list[subprocess.Popen[bytes]],
                                                               tmp_path: Path, protocol: str, rig: str,
                                                               role: str) -> None:
    """The twin goes silent 3 s into the run: the run stops on that link's timeout (its own timeouts, 0.5 s)."""
    sims: list = []

    def arm(_engine: object, sim: object) -> None:
        sims.append(sim)
        sim.faults_of(role).schedule(at_time=3.0, mute=True)  # type: ignore[attr-defined]

    plan = plan_run(SHORT / f"{protocol}.toml", RIGS / f"{rig}.toml")
    result = execute(plan, tmp_path / "run.h5", virtual=True, on_engine=arm)
    assert result.state == "error" and result.reason.startswith(f"instrument error: {role}: "), result.reason
    assert "no reply" in result.reason or "no valid reply" in result.reason, result.reason
    assert sims[0].faults_of(role).counts["mute"] >= 1
    assert all(p.poll() is None for p in cpu_hogs)
