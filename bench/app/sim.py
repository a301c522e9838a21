"""Use case: serve the simulated instruments of a rig (``bench sim serve``) until stopped."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from bench.rig import RigConfig
    from bench.runtime.sim_rig import Endpoint


@dataclass
class Serving:
    """What is served: the rig, each twin's endpoint (by name), the client rig file written (if asked)."""

    rig: RigConfig
    endpoints: dict[str, Endpoint]  # name → where a twin (or bus) listens
    client_rig: Path | None
    wire_time: bool
    duration: float | None
    replay: Path | None = None  # the run file whose measured signals the twins serve


def serve_rig(rig_file: Path | None, *, write_rig: Path | None = None, duration: float | None = None,
              wire_time: bool = True, t7_ports: bool = False, replay: Path | None = None,
              on_started: Callable[[Serving], None] | None = None) -> Serving:
    """Start every twin of a simulated rig on the wall clock (at the rig file's baud rates with the devices'
    turnarounds, or with ``wire_time`` off at pty speed; a T7 twin with ``t7_ports`` on the T7's own ports, else on
    ephemeral ones; with ``replay`` the twins serve that run file's measured signals from now on, on the rig file
    or else the record's own rig); ``on_started`` gets where to connect. Serves until
    SIGINT/SIGTERM or ``duration`` [s]; the twins are stopped and the signal handlers restored on the way out."""
    import math
    import signal
    import threading
    import time

    from bench.rig import load_rig
    from bench.runtime.devices import served_rig
    from bench.runtime.devices import write_rig as write_rig_file
    from bench.runtime.replay import replay_rig
    from bench.runtime.sim_rig import T7_PORTS, SimRig

    if rig_file is not None:
        rig = load_rig(rig_file)
        if not rig.simulated:
            raise ValueError(f"rig file {rig_file}: simulated = false; `bench sim serve` needs a simulated rig")
    elif replay is not None:
        rig = replay_rig(replay)
    else:
        raise ValueError("bench sim serve: give a rig file, or --replay RUN.h5 (its own rig)")
    if replay is not None:
        rig = rig.model_copy(update={"simulation": rig.simulation.model_copy(update={"replay": str(replay)})})
    stop = threading.Event()
    # both set explicitly: a process started with SIGINT ignored (a background job of a non-interactive shell)
    # inherits the ignore, and Python then installs no KeyboardInterrupt handler of its own
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    sim = SimRig(rig, timing="real" if wire_time else "none", daq_ports=T7_PORTS if t7_ports else (0, 0))
    try:
        try:
            ports = sim.start()
        except RuntimeError as exc:  # a port in use or needing privileges: one line naming it, no traceback
            raise ValueError(f"bench sim serve {rig.name}: {' '.join(str(exc).split())}") from None
        served = Serving(rig, ports, write_rig, wire_time, duration, replay)
        if sim.replay is not None:  # record time 0: now
            sim.replay.anchor(sim.clock.now())
        if write_rig is not None:
            # the clients' rig is real instruments: the replay is this process's business, not theirs
            plain = rig.model_copy(update={"simulation": rig.simulation.model_copy(update={"replay": None})})
            write_rig_file(served_rig(plain, sim.port_map(), wire_time=wire_time), write_rig)
        if on_started is not None:
            on_started(served)
        with contextlib.suppress(KeyboardInterrupt):
            # short waits: a Ctrl-C the kernel hands to one of the twins' threads only sets Python's flag, and a
            # main thread blocked in one long wait would not run the handler until the wait ends (never, without
            # a duration)
            end = math.inf if duration is None else time.monotonic() + duration
            while not stop.wait(min(0.1, max(end - time.monotonic(), 0.0))) and time.monotonic() < end:
                pass
    finally:
        sim.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return served
