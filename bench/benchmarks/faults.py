"""The fault matrix (``bench benchmark faults``): every fault × every phase × both rig kinds, judged at the plant.

Each case runs a 2.7-s protocol (:data:`PROTOCOL`: 0.3 s at 0 V, one 6-kV raised-cosine cycle, a ramp to and a
1-s hold at 5 kV) with ``bench run``'s code (:func:`~bench.runtime.run.execute`) — or a manual-control session
doing much the same (:data:`SCRIPT`, ``bench devices control``'s :class:`~bench.runtime.manual.ManualSession`) —
on a simulated rig, and injects one fault at one phase: set-up (0 V, before high voltage), waveform (at the
6-kV crest), hold (5 kV), shutdown (halfway through the ramp-down that a stop request began). Faults: the twins'
link switches (:class:`sim_devices.transport.Faults`: silence, every reply garbled, a dropped link, replies
later than the driver's timeout, a wire at a tenth of its speed), SIGINT and SIGTERM, a host stall, an
amplifier gain 25 % off, refused and unplayed T7 output writes, a full disk.

The verdict comes from the plant's own output history (the amplifier's output stage as the twins integrate it),
not from the run file: whether |output| was at most :data:`ZERO_V` when the run returned, how long after the
fault the last sample above it was, and whether it came back on after it had reached 0 V once the run was
stopping or once the set-point module's watchdog had zeroed it (re-energised). Faults whose detection rests on
a wall-clock timeout, signals and stalls run in real time; the others in virtual time (the same bytes; the
clock jumps, and a driver's wall-clock timeout would not count).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.resources import rigs_dir
from bench.rig import RigConfig, load_rig
from bench.runtime.latch import STATE_ENV
from bench.runtime.run import Plan, execute, plan_run

ZERO_V = 5.0  # |output| at or below this is 0 V (one ADAM-4024 code × the TREK gain)
STALL_S = 1.5  # a host stall: the run's thread frozen this long (longer than the 1-s module watchdogs)
GAIN_FACTOR = 1.25  # a gain fault: the output is this × what the host sets
SLOW = 4  # a slow wire: a quarter of the link's baud rate (the T7: a quarter of the 1 Mbit/s its stream-out needs)
DISK_SIZE = "4m"  # full disk: the run file on a tmpfs of this size, filled up at the fault
RIGS = {"ADAM": "thesis-sim", "T7": "thesis-daq-sim"}  # software-timed and hardware-timed thesis rigs
PHASES = ("set-up", "waveform", "hold", "shutdown")
AT = {"set-up": 0.15, "waveform": 0.8, "hold": 2.0, "shutdown": 2.0}  # run time [s] of the fault (shutdown: the stop)
QUICK_PHASES = ("waveform",)
# --quick: the waveform phase, the amplifier's link; every virtual-clock fault on both rig kinds (a fraction of a
# second each), each wall-clock fault once (they wait seconds in real time: 1-6 s a case), split between the rig
# kinds so that their two processes take about as long; named by fault kind, or by name for the stop signals
QUICK_WALL = {"ADAM": (("run", "silent link"), ("run", "garbled replies"), ("run", "SIGINT"), ("run", "SIGTERM")),
              "T7": (("run", "replies too late"), ("run", "slow wire"), ("run", "host stall"), ("control", "SIGINT"))}
JOBS = 2  # rig kinds run at once, each in its own process (a wall-clock case takes a sixth to a third of a core)

PROTOCOL = """[protocol]
name = "fault-matrix"
description = "bench benchmark faults: set-up at 0 V, a 6-kV raised cosine, a 5-kV hold"
rig = "{rig}"

[recording]
displacement_Hz = 1000
monitors_Hz = 10
setpoint_Hz = 20

[[steps]]
type = "relax"
name = "set-up"
duration_s = 0.3

[[steps]]
type = "waveform"
name = "waveform"
kind = "raised_cosine"
amplitude = "6 kV"
frequency_Hz = 1.0
duration_s = 1.0

[[steps]]
type = "ramp"
name = "to hold"
to = "5 kV"
duration_s = 0.2

[[steps]]
type = "hold"
name = "hold"
duration_s = 1.0

[[steps]]
type = "relax"
name = "end"
duration_s = 0.2
"""
# manual control: 0 V, a ramp to 5 kV (the "waveform" phase, mid-ramp), a hold; the shutdown phase ends the
# script at the hold's fault time, and the fault comes during the session's exit ramp
SCRIPT = ["wait 0.3", "ramp 5kV 1.0", "wait 1.2"]
SCRIPT_TO_EXIT = ["wait 0.3", "ramp 5kV 1.0", "wait 0.7"]


@dataclass
class Target:
    """What a fault acts on: the simulated rig, the run's engine (None in manual control), the run's thread and
    the folder of its file."""

    sim: Any
    engine: Any
    thread: int
    folder: Path


@dataclass(frozen=True)
class Fault:
    """One fault: its name in the table, its class (the summary's worst times are per class), the clock its
    cases run on, what injects it, and which modes (``run``, ``control``) it is tried in."""

    name: str
    kind: str
    clock: str  # "virtual" or "wall"
    inject: Callable[[Target], None]
    modes: tuple[str, ...] = ("run",)


@dataclass(frozen=True)
class Spec:
    """One case of the matrix."""

    mode: str  # "run" (bench run) or "control" (bench devices control)
    rig: str  # a key of RIGS
    fault: Fault
    phase: str

    @property
    def key(self) -> tuple[str, str, str, str]:
        """What names the case across processes: mode, rig, fault name, phase."""
        return self.mode, self.rig, self.fault.name, self.phase


@dataclass
class Case:
    """What one case did. Times on the rig clock, from the fault."""

    mode: str
    rig: str
    fault: str
    kind: str
    phase: str
    clock: str
    injected: bool = False
    zero_at_return: bool = False  # |output| ≤ ZERO_V at the plant when the run (session) returned
    to_zero_s: float | None = None  # fault → last plant sample above ZERO_V (0: none after the fault)
    ramp_s: float | None = None  # fault → the first ramp-down (or 0 V at once) event after it
    returned_s: float | None = None  # fault → the run returned
    peak_after_V: float = 0.0  # largest |output| from the fault on
    reenergised_V: float = 0.0  # largest |output| back on after 0 V, once stopping or a watchdog zeroed it
    state: str = ""
    reason: str = ""
    wall_s: float = 0.0

    @property
    def stopped(self) -> bool:
        """Whether the run ended early: a stop (the shutdown phase), or an end state other than a completed run or a
        session whose commands all passed (the fault did not stop those)."""
        return self.phase == "shutdown" or self.state not in ("completed", "ok")


# ---------------------------------------------------------------- the faults
def _switch(link: str, **switches: object) -> Callable[[Target], None]:
    def inject(t: Target) -> None:
        for k, v in switches.items():
            setattr(t.sim.faults[link], k, v)
    return inject


def _signal(sig: int) -> Callable[[Target], None]:
    return lambda _t: os.kill(os.getpid(), sig)


def _stall(t: Target) -> None:
    """Freeze the run's thread at its next recorder call (a point between two actions), as SIGSTOP does to a
    process: the twins, the plant and the module's watchdog run on."""
    rec = t.engine.rec
    frozen: list[bool] = []
    for name in ("maybe_flush", "append"):
        original = getattr(rec, name)

        def stalled(*args: Any, _original: Callable[..., Any] = original, **kwargs: Any) -> Any:
            if not frozen and threading.get_ident() == t.thread:
                frozen.append(True)
                time.sleep(STALL_S)
            return _original(*args, **kwargs)
        setattr(rec, name, stalled)


def _gain(t: Target) -> None:
    """The amplifier's gain drifts 25 %, at once (the T7 twin's conditioning stage would act only on the stream-out
    values it has not yet handed to the plant, up to 0.8 s later)."""
    t.sim.plant.hv = dataclasses.replace(t.sim.plant.hv, gain=t.sim.plant.hv.gain * GAIN_FACTOR)


def _refuse_writes(t: Target) -> None:
    """The T7 refuses every DAC and stream-out buffer write (exception 4, device failure) from now on."""
    from pymodbus.constants import ExcCodes

    from sim_devices.labjack_t7 import R_DAC, R_O_U16

    twin = t.sim.twins["daq"]
    write = twin._write_regs

    def refused(address: int, words: list[int]) -> Any:
        if address in (R_DAC, R_DAC + 2) or R_O_U16 <= address < R_O_U16 + 4:
            return ExcCodes.DEVICE_FAILURE
        return write(address, words)
    twin._write_regs = refused


def _unplayed(t: Target) -> None:
    """The T7 acknowledges stream-out buffer writes but plays none of them."""
    from sim_devices.labjack_t7 import R_O_U16

    twin = t.sim.twins["daq"]
    write = twin._write_regs
    twin._write_regs = lambda address, words: None if R_O_U16 <= address < R_O_U16 + 4 else write(address, words)


def _fill_disk(t: Target) -> None:
    """Fill the run file's disk (a small tmpfs) to the last byte."""
    chunk = bytes(1 << 16)
    with contextlib.suppress(OSError), (t.folder / "filler").open("wb", buffering=0) as f:
        while True:
            f.write(chunk)


def links(rig: RigConfig) -> list[tuple[str, float, float]]:
    """The rig's instrument links a run uses: (name in ``SimRig.faults``, how long the driver waits for a reply
    in all [s], the wire's baud rate — for the DAQ's Ethernet, a rate its stream-out needs)."""
    out = []
    amp = rig.amplifier
    if amp is not None and amp.drive == "daq" and rig.daq is not None:
        out.append(("daq", rig.daq.timeout_s, 1e6))
    elif amp is not None:
        bus = rig.buses[amp.bus]
        out.append((amp.bus, bus.timeout_s * (1 + bus.retries), float(bus.baudrate)))
    if rig.laser is not None and not (rig.daq is not None and rig.daq.laser_ain is not None):
        out.append(("laser", rig.laser.timeout_s, float(rig.laser.baudrate)))  # the T7 rig samples its analog out
    return out


def faults_for(rig: RigConfig) -> list[Fault]:
    """Every fault that makes sense on ``rig``."""
    out = []
    for link, timeout, baud in links(rig):
        out += [Fault(f"{link}: silent", "silent link", "wall", _switch(link, mute=True)),
                Fault(f"{link}: garbled", "garbled replies", "wall", _switch(link, garble_next=1 << 30)),
                Fault(f"{link}: dropped", "dropped link", "virtual", _switch(link, drop=True)),
                Fault(f"{link}: late {timeout + 0.25:g} s", "replies too late", "wall",
                      _switch(link, latency=timeout + 0.25)),
                Fault(f"{link}: slow wire {baud / SLOW:g} Bd", "slow wire", "wall",
                      _switch(link, wire_baud=baud / SLOW))]
    out += [Fault("SIGINT", "stop signal", "wall", _signal(signal.SIGINT), ("run", "control")),
            Fault("SIGTERM", "stop signal", "wall", _signal(signal.SIGTERM), ("run", "control")),
            Fault(f"host stall {STALL_S:g} s", "host stall", "wall", _stall),
            Fault(f"gain ×{GAIN_FACTOR:g}", "gain off", "virtual", _gain)]
    if rig.daq is not None:
        out += [Fault("T7 writes refused", "refused writes", "virtual", _refuse_writes),
                Fault("stream-out not played", "unplayed stream-out", "virtual", _unplayed)]
    out.append(Fault("disk full", "full disk", "virtual", _fill_disk))
    return out


def matrix(quick: bool = False) -> list[Spec]:
    """Every case (``quick``: a subset of the waveform phase that has every fault kind, both rig kinds and both
    modes: the virtual-clock faults on both rigs, each wall-clock one once, :data:`QUICK_WALL`)."""
    specs = []
    for label, name in RIGS.items():
        rig = load_rig(rigs_dir() / f"{name}.toml")
        amp_link = links(rig)[0][0]
        for fault in faults_for(rig):
            if quick and ":" in fault.name and not fault.name.startswith(f"{amp_link}:"):
                continue
            for mode in fault.modes:
                if quick and not _in_quick(label, mode, fault):
                    continue
                specs += [Spec(mode, label, fault, phase) for phase in (QUICK_PHASES if quick else PHASES)]
    return specs


def _in_quick(rig: str, mode: str, fault: Fault) -> bool:
    """Whether ``--quick`` runs this fault in this mode on this rig kind."""
    if fault.clock == "virtual":
        return mode == "run"
    return any(m == mode and what in (fault.kind, fault.name) for m, what in QUICK_WALL[rig])


# ---------------------------------------------------------------- one case
class Injector:
    """Does a fault at its phase: at run time ``at``; in the shutdown phase, a stop request at ``at`` and the
    fault halfway through the ramp-down that follows. Polled from the clock (virtual) or a watcher thread."""

    def __init__(self, spec: Spec, ramp_s: float) -> None:
        self.spec, self.ramp_s = spec, ramp_s
        self.at = AT[spec.phase]
        self.t_fault = float("nan")  # rig clock
        self.done = False
        self._stop_sent = False
        self._stopping_at: float | None = None
        self._target: Target | None = None
        self._now: Callable[[], float] = lambda: 0.0
        self._state: Callable[[], str] = lambda: "starting"
        self._stop: Callable[[], None] = lambda: None
        self._quit = threading.Event()

    def bind(self, target: Target, now: Callable[[], float], state: Callable[[], str],
             stop: Callable[[], None]) -> None:
        """What to act on, the run's time and state ("starting", "running", anything else: shutting down), and
        how to request a stop."""
        self._target, self._now, self._state, self._stop = target, now, state, stop

    def poll(self, _t: float = 0.0) -> None:
        """Act if the moment has come."""
        if self.done or self._target is None:
            return
        state = self._state()
        if state == "starting":
            return
        now = self._now()
        if self.spec.phase != "shutdown":
            if now >= self.at:
                self._fire()
        elif not self._stop_sent:
            if now >= self.at:
                self._stop_sent = True
                self._stop()
        elif self._stopping_at is None:
            if state != "running":
                self._stopping_at = now
        elif now >= self._stopping_at + self.ramp_s / 2:
            self._fire()

    def _fire(self) -> None:
        self.done = True
        assert self._target is not None
        self.t_fault = self._target.sim.clock.now()
        self.spec.fault.inject(self._target)

    def watch(self) -> None:
        """Start polling from a thread every 2 ms (wall clock) until the fault is done or :meth:`quit`."""
        def loop() -> None:
            while not self.done and not self._quit.wait(0.002):
                self.poll()
        threading.Thread(target=loop, name="fault-injector", daemon=True).start()

    def quit(self) -> None:
        self._quit.set()


@contextlib.contextmanager
def _folder(spec: Spec, tmp: Path) -> Iterator[Path]:
    """Where the case's file goes: a small tmpfs for the full-disk fault (mounting needs root), else ``tmp``."""
    folder = Path(tempfile.mkdtemp(dir=tmp))
    if spec.fault.kind != "full disk":
        yield folder
        return
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK_SIZE}", "tmpfs", str(folder)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise PermissionError(f"cannot mount a tmpfs ({res.stderr.strip() or 'mount failed'}): needs root")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


class Trace:
    """The plant's output history (a listener on the plant), when the run began to stop, and when the set-point
    module's communication watchdog zeroed the amplifier's input (the plant models both modules' watchdogs)."""

    def __init__(self) -> None:
        self.blocks: list[tuple[np.ndarray, np.ndarray]] = []
        self.t_stop: float | None = None  # rig clock: first block integrated once the run was stopping
        self.trips: list[float] = []  # rig clock: the watchdog's deadlines that zeroed the input

    def listen(self, plant: Any, stopping: Callable[[], bool]) -> None:
        """Record ``plant``'s output from now on; ``stopping()`` says whether the run is shutting down."""
        def block(b: Any) -> None:
            self.blocks.append((b.t.copy(), b.v_out.copy()))
            if self.t_stop is None and stopping():
                self.t_stop = float(b.t[0])
        plant.listeners.append(block)
        check = plant._check_watchdog

        def checked(t_end: float) -> None:
            trips, deadline = plant.watchdog_trips, plant._last_feed + (plant.input_watchdog or 0.0)
            check(t_end)
            if plant.watchdog_trips > trips:
                self.trips.append(deadline)
        plant._check_watchdog = checked

    def judge(self, case: Case, plant: Any, t_fault: float, t_return: float) -> None:
        """Fill ``case`` from the history up to ``t_return`` (rig clock)."""
        plant.observe()  # up to now
        if not self.blocks:
            return
        t = np.concatenate([b[0] for b in self.blocks])
        v = np.abs(np.concatenate([b[1] for b in self.blocks]))
        keep = t <= t_return
        t, v = t[keep], v[keep]
        case.zero_at_return = bool(v.size and v[-1] <= ZERO_V)
        after = t >= t_fault
        high = after & (v > ZERO_V)
        case.to_zero_s = float(t[high][-1] - t_fault) if high.any() else 0.0
        case.peak_after_V = float(v[after].max()) if after.any() else 0.0
        # watchdog trips that zeroed a high output (one at 0 V, a set-up stall, changes nothing)
        zeroed = [d for d in self.trips if v[max(int(np.searchsorted(t, d)) - 1, 0)] > ZERO_V]
        starts = ([self.t_stop] if self.t_stop is not None else []) + zeroed
        case.reenergised_V = max((_back_on(t, v, s) for s in starts), default=0.0)
        case.returned_s = t_return - t_fault


def _back_on(t: np.ndarray, v: np.ndarray, since: float) -> float:
    """Largest |output| ``v`` after it first reached 0 V from ``since`` on (0 if it stayed there)."""
    rest = np.flatnonzero((t >= since) & (v <= ZERO_V))
    if not rest.size:
        return 0.0
    later = v[rest[0]:]
    return float(later.max()) if later.max() > ZERO_V else 0.0


def _short(text: str, n: int = 90) -> str:
    text = " ".join(text.split())
    return text if len(text) <= n else text[: n - 1] + "…"


def _plan(rig: str, tmp: Path) -> Plan:
    path = rigs_dir() / f"{RIGS[rig]}.toml"
    protocol = tmp / f"fault-matrix-{rig}.toml"
    protocol.write_text(PROTOCOL.format(rig=path.as_posix()), encoding="utf-8")
    return plan_run(protocol, path)


def run_case(spec: Spec, plan: Plan, tmp: Path) -> Case:
    """One ``bench run`` case."""
    f = spec.fault
    case = Case("run", spec.rig, f.name, f.kind, spec.phase, f.clock)
    virtual = f.clock == "virtual"
    inj = Injector(spec, plan.rig.limits.shutdown_ramp_s)
    trace = Trace()
    seen: dict[str, Any] = {}

    def hook(engine: Any, sim: Any) -> None:
        seen.update(engine=engine, sim=sim)
        trace.listen(sim.plant, lambda: engine.snapshot.state not in ("starting", "running"))
        inj.bind(Target(sim, engine, threading.get_ident(), out.parent), engine.now, lambda: engine.snapshot.state,
                 lambda: engine.request_stop("fault matrix: stop, to reach the shutdown ramp"))
        if virtual:
            sim.clock.subscribe(inj.poll)
        else:
            inj.watch()

    with _folder(spec, tmp) as folder:
        out = folder / "run.h5"
        w0 = time.perf_counter()
        try:
            result = execute(plan, out, virtual=virtual, on_engine=hook)
            case.state, case.reason = result.state, _short(result.reason)
        except Exception as exc:  # execute must return whatever failed: that it raised is itself a finding
            result = None
            case.state, case.reason = "raised", _short(f"{type(exc).__name__}: {exc}")
        finally:
            inj.quit()
        case.wall_s = time.perf_counter() - w0
        if "sim" not in seen:  # it raised before the run began
            return case
        t_return = seen["sim"].clock.now()
        events = _events(result.path) if result is not None else []
    _finish(case, inj, trace, seen["sim"], t_return)
    if case.injected:
        t_fault_run = inj.t_fault - seen["engine"].ctx.t0
        ramps = [t for t, kind, _ in events if kind == "ramp" and t >= t_fault_run - 1e-6]
        case.ramp_s = ramps[0] - t_fault_run if ramps else None
    return case


def _events(path: str) -> list[tuple[float, str, str]]:
    """The run file's events as (run time, kind, text); none if the file cannot be read (a full disk)."""
    from bench.storage.runfile import open_run

    try:
        return [(t, kind, text) for t, _, kind, text in open_run(path).event_list()]
    except Exception:
        return []


def _finish(case: Case, inj: Injector, trace: Trace, sim: Any, t_return: float) -> None:
    case.injected = inj.done
    if inj.done:
        trace.judge(case, sim.plant, inj.t_fault, t_return)
    else:
        case.reason = _short(f"fault not injected (the run ended first): {case.reason}")


def run_control_case(spec: Spec, tmp: Path) -> Case:
    """One ``bench devices control`` case (a script of commands, wall clock)."""
    from bench.runtime.manual import ManualSession

    f = spec.fault
    case = Case("control", spec.rig, f.name, f.kind, spec.phase, "wall")
    rig = load_rig(rigs_dir() / f"{RIGS[spec.rig]}.toml")
    inj = Injector(spec, rig.limits.shutdown_ramp_s)
    trace = Trace()
    folder = Path(tempfile.mkdtemp(dir=tmp))
    session = ManualSession(rig, folder / "session.log", echo=lambda _text: None)
    script = SCRIPT_TO_EXIT if spec.phase == "shutdown" else SCRIPT
    w0 = time.perf_counter()
    with session.signal_handlers(interactive=False):
        try:
            with session:
                sim = session._sim
                trace.listen(sim.plant, lambda: session._ending or session.end_reason is not None)
                inj.bind(Target(sim, None, threading.get_ident(), folder), session._now,
                         lambda: "stopping" if session._ending else "running", lambda: None)
                inj.watch()
                session.run_lines(script)
        finally:
            inj.quit()
    t_return = sim.clock.now()
    case.wall_s = time.perf_counter() - w0
    bad = [o for o in session.outcomes if o.status != "ok"]
    case.state = bad[0].status if bad else "ok"
    case.reason = _short(session.end_reason or (bad[0].text if bad else "script completed"))
    _finish(case, inj, trace, sim, t_return)
    if case.injected:
        t0 = session._t0 or 0.0
        ramps = [t for t in _log_ramps(folder / "session.log") if t + t0 >= inj.t_fault - 1e-3]
        case.ramp_s = ramps[0] + t0 - inj.t_fault if ramps else None
    return case


def _log_ramps(log: Path) -> list[float]:
    """Session times [s] of the exit-ramp lines of a session log (``…\\tt=1.234 s\\tramp\\tsession\\t…``)."""
    out = []
    for line in log.read_text(encoding="utf-8").splitlines():
        parts = line.split("\t")
        if len(parts) >= 4 and parts[2] == "ramp":
            out.append(float(parts[1].removeprefix("t=").removesuffix(" s")))
    return out


# ---------------------------------------------------------------- the matrix
@dataclass
class Summary:
    """The matrix in figures: cases, how many were injected and ended at 0 V, the worst fault → 0 V per class."""

    cases: int
    injected: int
    safe: int
    skipped: int = 0  # cases this machine cannot run (a full disk needs root to mount a tmpfs)
    findings: list[str] = field(default_factory=list)
    worst: dict[str, float] = field(default_factory=dict)  # class → worst fault → 0 V [s], runs the fault ended
    ran_on: dict[str, int] = field(default_factory=dict)  # class → cases the fault did not end
    stop_bound: dict[str, dict[str, float]] = field(default_factory=dict)  # mode → signal → ramp / 0 V [s]

    @property
    def all_safe(self) -> bool:
        """Every case run was injected and ended at 0 V, and none re-energised the output."""
        return not self.findings and self.safe == self.injected == self.cases - self.skipped


def summarise(cases: list[Case]) -> Summary:
    """The summary of ``cases``."""
    injected = [c for c in cases if c.injected]
    s = Summary(len(cases), len(injected), sum(c.zero_at_return for c in injected))
    for c in cases:
        where = f"{c.mode} {c.rig} {c.fault} {c.phase}"
        if c.state == "skipped":
            s.skipped += 1
        elif not c.injected:
            s.findings.append(f"{where}: fault not injected")
        elif not c.zero_at_return:
            s.findings.append(f"{where}: output NOT at 0 V when the run returned ({c.state}: {c.reason})")
        if c.state == "raised":
            s.findings.append(f"{where}: the run raised instead of returning ({c.reason})")
        if c.reenergised_V > ZERO_V:
            s.findings.append(f"{where}: output back at {c.reenergised_V:.0f} V after it had reached 0 V (the run "
                              "stopping, or the module's watchdog) — re-energised")
    for c in injected:
        if c.stopped and c.to_zero_s is not None:
            s.worst[c.kind] = max(s.worst.get(c.kind, 0.0), c.to_zero_s)
        elif not c.stopped:
            s.ran_on[c.kind] = s.ran_on.get(c.kind, 0) + 1
    for mode in ("run", "control"):
        sig = [c for c in injected if c.mode == mode and c.kind == "stop signal"]
        first = [c for c in sig if c.phase != "shutdown"]
        second = [c for c in sig if c.phase == "shutdown"]
        if first:
            s.stop_bound[mode] = {
                "signals": len(first),
                "ramp_s": max((c.ramp_s for c in first if c.ramp_s is not None), default=float("nan")),
                "zero_s": max(c.to_zero_s or 0.0 for c in first),
                "second_zero_s": max((c.to_zero_s or 0.0 for c in second), default=float("nan"))}
    return s


def _run_keys(keys: list[tuple[str, str, str, str]]) -> list[Case]:
    """Run the cases named by ``keys`` (:attr:`Spec.key`) one after the other, in this process's main thread
    (where signal handlers can be installed); one plan per rig."""
    specs = {spec.key: spec for spec in matrix(quick=False)}
    specs.update({spec.key: spec for spec in matrix(quick=True)})
    with tempfile.TemporaryDirectory() as tmp:
        # the interlock latch outlives a run (bench/runtime/latch.py): the matrix keeps its own, and each case starts
        # unlatched, as after an operator's reset
        state = Path(tmp) / "state"
        saved = os.environ.get(STATE_ENV)
        os.environ[STATE_ENV] = str(state)
        try:
            cases = _run_specs([specs[k] for k in keys], state, Path(tmp))
        finally:
            if saved is None:
                os.environ.pop(STATE_ENV, None)
            else:
                os.environ[STATE_ENV] = saved
    return cases


def _run_specs(specs: list[Spec], state: Path, tmp: Path) -> list[Case]:
    """The cases of ``specs`` in order, each from an unlatched rig (``state``: the matrix's latch folder)."""
    cases: list[Case] = []
    plans: dict[str, Plan] = {}
    for spec in specs:
        for latch_file in state.glob("interlock-*.json"):
            latch_file.unlink()
        if spec.mode == "control":
            cases.append(run_control_case(spec, tmp))
            continue
        if spec.rig not in plans:
            plans[spec.rig] = _plan(spec.rig, tmp)
        try:
            cases.append(run_case(spec, plans[spec.rig], tmp))
        except PermissionError as exc:  # the full disk needs a tmpfs
            f = spec.fault
            cases.append(Case("run", spec.rig, f.name, f.kind, spec.phase, f.clock, state="skipped",
                              reason=_short(str(exc))))
    return cases


MODE_COMMAND = {"run": "bench run", "control": "bench devices control"}


def summary_lines(s: Summary) -> list[str]:
    """The summary as printed: counts and verdict, worst fault → 0 V per class, the stop bounds, the findings."""
    skipped = f", {s.skipped} skipped" if s.skipped else ""
    lines = [f"{s.cases} cases ({s.injected} injected{skipped}): {s.safe} at 0 V when the run returned, "
             f"{len(s.findings)} findings; all safe: {'yes' if s.all_safe else 'NO'}",
             "worst fault → 0 V, runs the fault ended: " + ", ".join(f"{k} {v:.3f} s" for k, v in s.worst.items())]
    if s.ran_on:
        lines.append("ran on (the fault did not end the run; 0 V at its end): "
                     + ", ".join(f"{k} {n}" for k, n in s.ran_on.items()))
    for mode, b in s.stop_bound.items():
        second = b["second_zero_s"]
        lines.append(f"{MODE_COMMAND[mode]} stop bound ({b['signals']:.0f} SIGINT/SIGTERM cases): ramp-down within "
                     f"{b['ramp_s']:.3f} s, 0 V at the plant within {b['zero_s']:.3f} s of the signal"
                     + (f"; a second signal during the ramp: 0 V within {second:.3f} s" if second == second else ""))
    return lines + [f"FINDING: {f}" for f in s.findings]


def run_all(quick: bool = False, jobs: int | None = None) -> list[Case]:
    """Run the matrix (``quick``: a subset): each rig kind's cases in order, up to ``jobs`` (default :data:`JOBS`)
    rig kinds at once — the last in this process (its imports are done, and its main thread takes the signals),
    the others each in a process of its own."""
    by_rig: dict[str, list[tuple[str, str, str, str]]] = {}
    for spec in matrix(quick):
        by_rig.setdefault(spec.rig, []).append(spec.key)
    jobs = JOBS if jobs is None else jobs
    groups = list(by_rig.values())
    if jobs <= 1 or len(groups) <= 1:
        return [case for keys in groups for case in _run_keys(keys)]
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    *others, here = groups[: jobs]
    with ProcessPoolExecutor(len(others), mp_context=get_context("spawn")) as pool:
        futures = [pool.submit(_run_keys, keys) for keys in others]
        mine = _run_keys(here)
        cases = [case for future in futures for case in future.result()] + mine
    return cases + [case for keys in groups[jobs:] for case in _run_keys(keys)]
