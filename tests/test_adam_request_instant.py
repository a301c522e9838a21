"""The ADAM-4024 twin acts on a request at the instant it arrived.

On a virtual clock the host can stop waiting for a reply (a dropped link) and move the clock on while the twin's
thread still serves the request. The fault matrix caught it once in about 400 runs beside a CPU hog: the last
set-point write, sent at 2.025 s, reached the plant at 3.225 s — after the module's 1-s communication watchdog
should have zeroed the output at 3.025 s — and high voltage stayed on until the run returned. Here the clock is
moved inside the request on purpose; the expected output comes from the module's documented behaviour (no request
for the watchdog period → 0 V), not from the plant's code.
"""

from __future__ import annotations

import struct

import numpy as np

from bench.core.clock import VirtualClock
from bench.core.plant import HVStage, Plant
from bench.models.membrane import MembraneParams
from sim_devices.modbus_devices import Adam4024Sim
from sim_devices.modbus_host import execute

WATCHDOG_S = 1.0
CODE_5V = 3071  # ±10 V over 12 bits: 3071 ≈ +5 V (ADAM-4024 output code)


def _write_output(module: Adam4024Sim, code: int) -> bytes:
    """FC6 to 40001 (channel 0's output), as the driver sends it."""
    return execute(module, struct.pack(">BHH", 6, 0, code))


def test_a_write_whose_host_moved_the_clock_on_still_lets_the_watchdog_zero_the_output_in_time() -> None:
    clock = VirtualClock()
    plant = Plant(clock, MembraneParams(), hv=HVStage())
    module = Adam4024Sim(1, plant, clock, watchdog_s=WATCHDOG_S)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    plant.listeners.append(lambda b: out.append((b.t.copy(), np.abs(b.v_out.copy()))))

    clock.advance(2.025)
    check = module.check_write

    def slow_thread(address: int, values: list[int]) -> None:
        check(address, values)
        clock.advance(1.2)  # the host gave up on the reply and waited out the watchdog meanwhile

    module.check_write = slow_thread  # type: ignore[method-assign]
    assert _write_output(module, CODE_5V)[0] == 6
    assert clock.now() > 3.2  # the host's wait has ended
    clock.advance(1.3)  # and no request comes again: the link is gone
    plant.advance_to(clock.now())

    t = np.concatenate([b[0] for b in out])
    v = np.concatenate([b[1] for b in out])
    deadline = 2.025 + WATCHDOG_S
    assert v[(t > 2.1) & (t < deadline - 0.01)].min() > 1000.0  # the set-point was on before the deadline
    assert v[t > deadline + 0.05].max() <= 5.0  # and 0 V from it on, through 4.5 s with no request
    assert t[-1] > 4.49 and plant.watchdog_trips == 1
