"""A plant with many pending motion events splits its blocks in numpy passes: the very pieces, and the same
history kept, as the plant's former Python loop (written out here), in time order or not."""

from __future__ import annotations

import math

import numpy as np

from bench.core.clock import VirtualClock
from bench.core.motion import MotionProfile
from bench.core.plant import PIECES_NUMPY, Plant
from bench.models.lozenge import LozengeParams

Events = list[tuple[float, MotionProfile]]


def _reference(events: Events, first_step: int, h: float, n: int) -> list[tuple[int, int, MotionProfile]]:
    starts = [max(0, math.floor(te / h + 1e-6) - first_step) for te, _ in events]
    out = []
    for i, (_, value) in enumerate(events):
        a = min(starts[i], n)
        b = min(starts[i + 1], n) if i + 1 < len(events) else n
        if b > a or (i == len(events) - 1 and a < n):
            out.append((a, b, value))
    keep = max(i for i, st in enumerate(starts) if st <= n)
    del events[:keep]
    return out


def test_many_pending_events_split_a_block_as_the_python_loop() -> None:
    rng = np.random.default_rng(3)
    plant = Plant(VirtualClock(), LozengeParams(), configuration="motor")
    for trial in range(200):
        plant._n = int(rng.integers(0, 10_000))
        k = int(rng.integers(1, 4 * PIECES_NUMPY))
        t0 = plant._n * plant.h
        times = t0 + np.sort(rng.uniform(-0.01, 0.5, k)) if trial % 4 else t0 + rng.uniform(0.0, 0.5, k)
        times[0] = min(times[0], t0)
        times[rng.random(k) < 0.2] = t0 + 0.01  # events at one time, and at a step boundary
        events: Events = [(float(te), MotionProfile.hold(float(te), float(j))) for j, te in enumerate(times)]
        mine, ref = list(events), list(events)
        n = int(rng.integers(1, 6000))
        got, want = plant._pieces(mine, n), _reference(ref, plant._n, plant.h, n)
        assert [(a, b, id(p)) for a, b, p in got] == [(a, b, id(p)) for a, b, p in want]
        assert all(type(a) is int and type(b) is int for a, b, _ in got)
        assert [id(p) for _, p in mine] == [id(p) for _, p in ref]


def test_many_pieces_fill_the_motor_inputs_as_each_profile_evaluates() -> None:
    """Past ``PIECES_NUMPY`` pieces the block's motor inputs come from one compiled call over the joined phases:
    each piece is still its profile's :meth:`MotionProfile.evaluate` (x0 + sign·position, sign·velocity)."""
    rng = np.random.default_rng(5)
    clock = VirtualClock()
    plant = Plant(clock, LozengeParams(), configuration="motor", x0=0.05, motor_sign=-1.0)
    for _ in range(3 * PIECES_NUMPY):
        clock.advance(float(rng.uniform(0.0, 0.012)))
        target, vmax = float(rng.uniform(-0.02, 0.02)), float(rng.choice([0.01, 0.05, 0.3]))

        def plan(t0: float, p: float, v: float, g: float = target, vm: float = vmax) -> MotionProfile:
            return MotionProfile.plan(t0, p, v, g, vm, 1.0, 1.0)

        plant.set_motion(plan)
    n = int(clock.now() / plant.h) + 7
    t = (np.arange(1, n + 1) + plant._n) * plant.h
    pieces = _reference(list(plant._motions), plant._n, plant.h, n)
    assert len(pieces) > PIECES_NUMPY
    U = np.zeros((n, 3))
    plant._motor_into(t, U)
    want = np.zeros((n, 3))
    for a, b, pr in pieces:
        pos, vel = pr.evaluate(t[a:b])
        want[a:b, 1], want[a:b, 2] = 0.05 + -1.0 * pos, -1.0 * vel
    assert np.array_equal(U.view(np.uint64), want.view(np.uint64))


def test_an_input_set_at_a_stopped_streams_end_follows_its_last_scan_in_time_order() -> None:
    """A stream's scans on its clock (t0 + k / rate, the sum a rounding off the host's clock), then the stream stops
    at the instant its last scan played and the host sets 0 V there: the plant must end at 0 V. Before, the first
    pending scan (kept as the value in force) kept its time, a rounding later than the stop, and the 0-V input set
    at the stop sorted before it: the stale scan stayed in force for good (2026-11-28)."""
    clock = VirtualClock()
    plant = Plant(clock, LozengeParams(), configuration="motor")
    rate, t0, first = 10_000.0, 1.5163437499999999, 10_938  # a twin's enable time and packet (its run's)
    times = (first + 1 + np.arange(1_000)) / rate + t0  # the T7 twin's scan instants [D]
    plant.schedule_amplifier_scans(times, np.full(times.size, 2.0))
    stop = float(np.nextafter(times[0], -np.inf))  # the host's clock at the stop: the scan's time one rounding later
    clock.advance(stop - clock.now())
    plant.advance_to(stop)  # integrated to the step the scan falls in: the scan is the first pending input
    plant.unschedule_amplifier_input(stop)
    plant.set_amplifier_input(0.0, at=stop)
    clock.advance(0.1)
    plant.advance_to(clock.now())
    assert plant.v_in == 0.0
    assert abs(plant.v_out) < 1.0  # V: settled at 0 (the stage's corner ~20 kHz; 0.1 s is thousands of its τ)
