"""Shared fixtures: simulated rigs on real ports (virtual clock) with their connected drivers."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from bench.rig import RigConfig, load_rig
from bench.runtime.instruments import Instruments, build_instruments
from bench.runtime.sim_rig import SimRig, Timing

ROOT = Path(__file__).resolve().parent.parent
RIGS = ROOT / "rigs"

# fixtures of a wider scope (module, session) run before the per-test folder below exists: they, too, get a folder
# of this test process, never the user's ~/.local/state/dea-bench (a latch there would refuse other sessions' runs)
os.environ["BENCH_STATE_DIR"] = tempfile.mkdtemp(prefix="dea-bench-test-state-")

if os.environ.get("PYTEST_XDIST_WORKER"):  # pytest-xdist's workers (execnet) set an 80 x 24 terminal that is not
    os.environ.pop("COLUMNS", None)        # there: the CLI tests check output as a redirected run prints it
    os.environ.pop("LINES", None)


def session_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of this test session that all its pytest-xdist workers share (their base folders' parent, the
    session's own pytest-N); without xdist, the base folder itself (its parent holds other sessions' folders)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def run_once_per_session(tmp_path_factory: pytest.TempPathFactory, protocol: str, name: str,
                         **options: object) -> Path:
    """A completed virtual-time run of ``protocols/<protocol>`` on its rig, made once per test session: the first
    pytest-xdist worker to ask runs it under a lock file, the others wait for it and copy its run file, so that
    each worker reads its own copy as before (a test of one worker never sees what a test of another did beside
    it). ``options``: for :func:`bench.runtime.run.execute`."""
    import fcntl
    import shutil

    from bench.runtime.run import execute, plan_run

    shared = session_folder(tmp_path_factory) / f"{name}-shared"
    shared.mkdir(exist_ok=True)
    done = shared / "run"
    with open(shared / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
        if not done.is_dir():
            work = Path(tempfile.mkdtemp(prefix="work-", dir=shared))
            with pytest.MonkeyPatch.context() as mp:
                mp.setenv("BENCH_STATE_DIR", str(work / "state"))
                result = execute(plan_run(ROOT / "protocols" / protocol), work / "run" / "run.h5", virtual=True,
                                 **options)  # type: ignore[arg-type]
            assert result.state == "completed", result.reason
            assert Path(result.path) == work / "run" / "run.h5", result.path
            (work / "run").rename(done)  # whole or not there: a failed run is run again by the next worker
    out = tmp_path_factory.mktemp(name)
    # the run catalogue beside it names the shared path, not this copy: left out (no test reads that folder's
    # catalogue; a folder without one is reconciled from its files)
    shutil.copytree(done, out, dirs_exist_ok=True, ignore=shutil.ignore_patterns("catalog.sqlite"))
    return out / "run.h5"


@pytest.fixture(scope="session")
def short_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed virtual-time run of protocols/short/thesis-identification-short.toml on its rig (read only),
    made once per session (:func:`run_once_per_session`)."""
    return run_once_per_session(tmp_path_factory, "short/thesis-identification-short.toml", "short-run")


@pytest.fixture(scope="session")
def isopotential_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed virtual-time run of the short isopotential campaign on the protocol's own rig (the DAQ motor
    bench), the operator's prompts answered yes (read only: copy it to change it), made once per session
    (:func:`run_once_per_session`)."""
    return run_once_per_session(tmp_path_factory, "short/lsdea-isopotential-short.toml", "isopotential",
                                operator=lambda _msg: True)


@pytest.fixture(autouse=True, scope="module")
def _module_interlock_state(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The same for a module's own fixtures (a module-scoped run starts before any test's folder is set): without
    it they used the user's default folder, where a latch any other run left refused them."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BENCH_STATE_DIR", str(tmp_path_factory.mktemp("module-state")))
        yield


@pytest.fixture(autouse=True)
def _own_interlock_state(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test has its own interlock latch folder (bench.runtime.latch), also for the processes it starts: a
    latch one test leaves (on purpose) never refuses another test's run."""
    monkeypatch.setenv("BENCH_STATE_DIR", str(tmp_path_factory.mktemp("state")))


@dataclass
class RunningRig:
    """A started simulated rig and the drivers connected to it."""

    rig: RigConfig
    sim: SimRig
    inst: Instruments

    def advance(self, seconds: float) -> None:
        """Let virtual time pass (the plant advances lazily when instruments are read)."""
        self.sim.clock.advance(seconds)  # type: ignore[attr-defined]


def start_rig(name: str, virtual: bool = True, watchdog: bool = False, timing: Timing = "none",
              **overrides: object) -> RunningRig:
    """Start the simulated rig ``rigs/<name>.toml`` and connect every driver to it.

    The analog module's communication watchdog is off unless ``watchdog``: these tests hold voltages over
    virtual seconds without talking to the module (the engine feeds it; see test_engine). ``timing``: these
    fixtures test behaviour at pty speed (``"none"``); wire-time tests ask for ``"real"`` (SimRig's default).
    On a virtual clock the links wait for replies as in a virtual-time run (``SimRig.reply_timers``): a muted twin
    times out at once, a slow one is waited for.
    """
    rig = load_rig(RIGS / f"{name}.toml")
    data = {**rig.model_dump(), **overrides}
    if not watchdog and data.get("amplifier"):
        data["amplifier"] = {**data["amplifier"], "comm_watchdog_s": None}
    rig = RigConfig.model_validate(data)
    sim = SimRig(rig, virtual=virtual, timing=timing)
    sim.start()
    inst = build_instruments(rig, sim.port_map(), clock=sim.clock.now, sleep=sim.clock.sleep,
                             timers=sim.reply_timers(), wire_time=sim.wire_time)
    for link in inst.links.values():
        link.timeout = 0.3
    try:
        for _, drv in inst.items():
            drv.connect()
    except Exception:
        sim.stop()
        raise
    running = RunningRig(rig, sim, inst)
    if virtual:
        running.advance(1.0)  # settle; the amplifier's slew limit allows a full step after this
    return running


def _running(name: str, **overrides: object) -> Iterator[RunningRig]:
    r = start_rig(name, **overrides)
    yield r
    r.inst.close()
    r.sim.stop()


@pytest.fixture
def thesis() -> Iterator[RunningRig]:
    yield from _running("thesis-sim")


@pytest.fixture
def lsdea_motor() -> Iterator[RunningRig]:
    yield from _running("lsdea-motor-sim")


@pytest.fixture
def lsdea_isotonic() -> Iterator[RunningRig]:
    yield from _running("lsdea-isotonic-sim")


RTU_ON_PTY = {"simulation": {"seed": 1, "modbus_transport": "rtu"}}


@pytest.fixture
def thesis_rtu() -> Iterator[RunningRig]:
    """The thesis rig with its Modbus twins on a pty (RTU, through the fault-injecting bridge)."""
    yield from _running("thesis-sim", **RTU_ON_PTY)


@pytest.fixture
def thesis_rtu_watchdog() -> Iterator[RunningRig]:
    """As thesis_rtu, with the ADAM-4024 communication watchdog of the rig file (1 s) active."""
    yield from _running("thesis-sim", watchdog=True, **RTU_ON_PTY)


@pytest.fixture
def lsdea_motor_rtu() -> Iterator[RunningRig]:
    """The LS-DEA motor bench with its Modbus twins on ptys (RTU)."""
    yield from _running("lsdea-motor-sim", **RTU_ON_PTY)
