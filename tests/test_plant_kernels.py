"""The plant's compiled per-block kernels give the very doubles of the numpy array passes they replaced (the
reference formulas are written out here), and a plant fed its amplifier inputs in many chunks, in order or not,
integrates exactly as one fed them at once: the twins' streams stay bit-identical."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.core.amplifier_dynamics import lowpass, monitor_response, step_targets
from bench.core.clock import VirtualClock
from bench.core.motion import MotionProfile, motion_into
from bench.core.plant import HVStage, Plant
from bench.models.lozenge import LozengeParams
from bench.models.lozenge_runs import LozengeStream, _failed_rig, _failure
from bench.models.membrane import MembraneParams, _any_failure, failure_reason


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """The same doubles, bit for bit (−0.0 is not 0.0 here)."""
    a, b = np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(b, dtype=float)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def _targets_reference(t: np.ndarray, v: np.ndarray, first: int, n: int, h: float, gain: float, vmax: float,
                       cap: float | None, prev: float) -> np.ndarray:
    """The plant's former numpy formulation: pieces from searchsorted and floor, clip, copysign, one repeat."""
    m = int(np.searchsorted(t, (first + n + 1 - 1e-6) * h, side="left"))
    starts = np.minimum(np.maximum(0, np.floor(t[:m] / h + 1e-6).astype(np.int64) - first), n)
    ends = np.append(starts[1:], n)
    used = ends > starts
    a, b, v_in = starts[used], ends[used], v[:m][used]
    target = np.clip(gain * v_in, -vmax, vmax)
    if cap is not None:
        target = np.copysign(np.minimum(np.abs(target), cap), target)
    per_step = np.full(n, prev)
    if a.size:
        per_step[a[0]:] = np.repeat(target, b - a)
    return per_step


@pytest.mark.parametrize("cap", [None, 10.0, 0.0])
def test_step_targets_are_the_array_formulas_doubles(cap: float | None) -> None:
    rng = np.random.default_rng(3)
    h = 1e-4
    for first, n in ((0, 1), (0, 500), (1234, 37), (99_000, 2500)):
        t = np.sort(np.concatenate([(first + rng.uniform(-20, n + 40, 300)) * h,
                                    (first + np.arange(0, n + 5, 7)) * h]))  # on and between the step instants
        t[5:9] = t[5]  # equal times
        v = rng.uniform(-14.0, 14.0, t.size)  # beyond ±10 kV through 1000 V/V: clipped
        m = int(np.searchsorted(t, (first + n + 1 - 1e-6) * h, side="left"))
        got = step_targets(t, v, m, first, n, h, 1000.0, 10e3, -1.0 if cap is None else cap, -3.5)
        want = _targets_reference(t, v, first, n, h, 1000.0, 10e3, cap, -3.5)
        assert _same(got, want)


def test_monitor_response_is_lowpass_gain_offset_and_noise() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(0.0, 3e3, 4000)
    x[[3, 100, 2000]] = [np.nan, np.inf, -np.inf]  # a failed specimen's current: counts as 0 in the low-pass
    a, y0, gain_error, offset = math.exp(-2 * math.pi * 20e3 * 1e-4), 12.5, -3.1e-3, 0.7
    noise = rng.normal(0.0, 0.9, x.size)
    for nz in (noise, np.zeros(0)):
        out, y_end = monitor_response(x, a, y0, 1.0 + gain_error, offset, nz)
        y = lowpass(x, a, y0)
        want = (1.0 + gain_error) * np.asarray(y) + offset
        if nz.size:
            want = want + nz
        assert _same(out, want)
        assert y_end == y[-1]


def test_motion_into_is_the_profiles_evaluate() -> None:
    profiles = [MotionProfile.hold(0.3, 0.012),
                MotionProfile.plan(0.1, 0.0, 0.0, 0.02, 0.05, 0.4, 0.3),  # accelerate, cruise, decelerate
                MotionProfile.plan(0.2, 0.01, -0.04, 0.015, 0.05, 0.5, 0.5)]  # starts moving away from the target
    t = np.linspace(0.0, 1.5, 15_001)  # before each start, in every phase, after the end
    for pr in profiles:
        U = np.zeros((t.size, 3))
        motion_into(pr.t_start, pr.p_start, pr.v_start, pr.acc, t, 0, t.size, 0.05, -1.0, U)
        pos, vel = pr.evaluate(t)
        assert _same(U[:, 1], 0.05 + -1.0 * pos)
        assert _same(U[:, 2], -1.0 * vel)
        assert not U[:, 0].any()


def test_the_compiled_failure_checks_find_what_the_messages_report() -> None:
    p = MembraneParams()
    rng = np.random.default_rng(1)
    for case in range(4):
        Y = np.full((50, 3), p.lambda_pre)
        obs = np.zeros((50, 4))
        obs[:, 0] = rng.uniform(0.0, 0.9 * p.breakdown_field, 50)
        if case == 1:
            Y[20, 0] = p.runaway_stretch * 1.01
        elif case == 2:
            obs[30, 0] = -1.1 * p.breakdown_field
        elif case == 3:
            Y[40, 0] = np.nan
        found = _any_failure(Y, obs, float(p.runaway_stretch), float(p.breakdown_field))
        assert found == bool(failure_reason(p, Y[:, 0], obs[:, 0])) == (case > 0)
    for case in range(4):
        Y = np.full((50, 4), 0.05)
        obs = np.ones((50, 5))
        obs[:, 3] = 2.0
        if case == 1:
            Y[7, 0] = np.inf
        elif case == 2:
            obs[8, 4] = 0.0  # the Gent margin gone
        elif case == 3:
            obs[9, 2] = -2.5  # |E| above the breakdown field
        found = _failed_rig(Y, obs)
        assert found == bool(_failure(float, Y[:, 0], obs[:, 4], obs[:, 2], obs[:, 3])) == (case > 0)


def _lsdea_plant(clock: VirtualClock) -> Plant:
    plant = Plant(clock, LozengeParams(), configuration="motor", hv=HVStage())
    plant.warm_up()
    return plant


@pytest.mark.parametrize("specimen", ["membrane", "lozenge"])
def test_inputs_in_chunks_integrate_as_inputs_given_at_once(specimen: str) -> None:
    """Chunks in time order (the fast path: not merged at each block), a chunk out of order (merged and sorted) and
    a watchdog input: the plant's blocks equal those of a plant given every input at once, sorted."""
    t = np.arange(1, 20_001) / 10_000.0
    volts = 5.0 * np.sin(2 * np.pi * 7.0 * t) + 1.0
    order = np.r_[0:3000, 5000:6000, 3000:5000, 6000:20_000]  # one chunk scheduled before the inputs it follows
    records = []
    for chunks in ([(0, 20_000)], [(0, 3000), (3000, 4000), (4000, 6000), (6000, 13_000), (13_000, 20_000)]):
        clock = VirtualClock()
        plant = (Plant(clock, MembraneParams(), hv=HVStage()) if specimen == "membrane" else _lsdea_plant(clock))
        if specimen == "lozenge":
            plant.set_motion(lambda t0, p, v: MotionProfile.plan(t0, p, v, 0.004, 0.05, 0.5, 0.5))
        got: list[np.ndarray] = []
        plant.listeners.append(lambda b, got=got: got.append(np.stack([b.t, b.voltage, b.current, b.displacement,
                                                                       b.force])))
        for k, (a, b) in enumerate(chunks):
            idx = order[a:b] if len(chunks) > 1 else np.arange(20_000)
            plant.schedule_amplifier_input(t[idx], volts[idx])
            clock.advance(0.013 * (k + 1))
            plant.advance_to(clock.now())
        clock.advance_to(2.0)
        plant.advance_to(clock.now())
        records.append((np.concatenate(got, axis=1), plant.v_in))
    (whole, v_whole), (chunked, v_chunked) = records
    assert whole.shape == chunked.shape == (5, 20_000)
    assert _same(whole, chunked)
    assert v_whole == v_chunked == volts[-1]


def test_watchdog_zero_follows_the_last_input_in_time_order() -> None:
    """A watchdog trip appends 0 V after the last input in time order, whether or not the pending inputs were
    merged: the output decays to 0 after the deadline either way."""
    for split in (False, True):
        clock = VirtualClock()
        plant = Plant(clock, MembraneParams(), hv=HVStage())
        plant.input_watchdog = 0.05
        if split:
            plant.schedule_amplifier_input([0.01, 0.02], [2.0, 3.0])
            plant.schedule_amplifier_input([0.03], [4.0])
        else:
            plant.schedule_amplifier_input([0.01, 0.02, 0.03], [2.0, 3.0, 4.0])
        clock.advance_to(0.2)
        plant.advance_to(clock.now())
        assert plant.watchdog_trips == 1
        assert plant.v_in == 0.0
        assert abs(plant.v_out) < 1.0


def test_the_watchdog_s_zero_lands_after_the_last_input_of_inputs_given_out_of_order() -> None:
    """5 V at 10 and 30 ms, then 0 V at 20 ms given after them: in time order the last input is 5 V at 30 ms, so
    with no request for 50 ms (watchdog 0.05 s, last feed at 0) the module outputs 0 V from 50 ms on — the
    input at 20 ms does not make the last one 0 V (review: a last-input look-up that ignored the order lost the
    zero and held 5 kV): one trip, and the output near 0 V well after 50 ms."""
    clock = VirtualClock()
    plant = Plant(clock, MembraneParams(), hv=HVStage())
    plant.input_watchdog = 0.05
    plant.schedule_amplifier_input([0.01, 0.03], [5.0, 5.0])
    plant.schedule_amplifier_input([0.02], [0.0])
    clock.advance_to(0.2)  # in one block: the chunks are still apart when the watchdog looks for the last input
    plant.advance_to(clock.now())
    assert plant.watchdog_trips == 1 and plant.v_in == 0.0
    assert abs(plant.v_out) < 1.0


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_scheduled_input_at_a_time_that_is_not_finite_is_refused(bad: float) -> None:
    """A chunk starting at NaN would stop every later chunk from playing (NaN < t is False): refused whole, and
    the inputs before it still play."""
    clock = VirtualClock()
    plant = Plant(clock, MembraneParams(), hv=HVStage())
    plant.schedule_amplifier_input([0.01], [2.0])
    with pytest.raises(ValueError, match="finite"):
        plant.schedule_amplifier_input([bad, 0.02], [4.0, 0.0])
    plant.schedule_amplifier_input([0.03], [0.0])
    clock.advance_to(0.02)
    plant.advance_to(clock.now())
    assert plant.v_out > 1500.0  # 2 V in at 1 kV/V, settled
    clock.advance_to(0.1)
    plant.advance_to(clock.now())
    assert abs(plant.v_out) < 1.0


def test_a_lozenge_stream_checks_one_sample_blocks() -> None:
    s = LozengeStream(LozengeParams(), "imposed", 0.05)
    tr = s.advance_rig(np.array([[0.0, 0.05, 0.0]]))
    assert not tr.failed and tr.position.shape == (1,)


def test_warm_up_compiles_what_advancing_calls() -> None:
    """Plant.warm_up compiles the kernels for the very types a block gives them: advancing (one-step blocks
    included) adds no signature, so no compile happens inside a twin's reply."""
    from bench.core.amplifier_dynamics import output_response
    from bench.models.integrate import run_fixed
    from bench.models.lozenge import lozenge_observe_rig

    kernels = [step_targets, monitor_response, motion_into, _failed_rig, _any_failure, output_response, run_fixed,
               lozenge_observe_rig]
    for specimen in ("membrane", "lozenge"):
        clock = VirtualClock()
        plant = (Plant(clock, MembraneParams(), hv=HVStage()) if specimen == "membrane" else _lsdea_plant(clock))
        plant.warm_up()
        before = [len(k.signatures) for k in kernels]
        if specimen == "lozenge":
            plant.set_motion(lambda t0, p, v: MotionProfile.plan(t0, p, v, 0.004, 0.05, 0.5, 0.5))
        plant.schedule_amplifier_input(np.arange(1, 3001) / 1e4, np.linspace(0.0, 3.0, 3000))
        for dt in (1e-4, 0.0123, 1e-4, 0.2):
            clock.advance(dt)
            plant.advance_to(clock.now())
        assert plant._n == 2125
        assert [len(k.signatures) for k in kernels] == before


def _lozenge_step_reference(y: np.ndarray, V: float, x_in: float, v_in: float, h: float, p: np.ndarray) -> bool:
    """The LS-DEA fixed step as first written (physics.md §2.3-2.4): branches by exponential Euler, then the hung
    mass by symplectic Euler under the full :func:`lozenge_force` (stiffness and gradient computed and dropped),
    the Gent margin from :func:`gentgent`; in Python around the compiled model functions."""
    from bench.models import lozenge as lz

    K = int(p[lz.Q_K])
    hung = int(p[lz.Q_MODE]) == lz.MODE_HUNG
    if not hung:
        y[0], y[1] = x_in, v_in
    x, v = float(y[0]), float(y[1])
    if not 0.0 < x < 2.0 * p[lz.Q_L]:
        return False
    l1, l2, _, _, _, _ = lz.kinematics(x, p)
    ll1, ll2 = math.log(l1), math.log(l2)
    for i in range(K):
        tau = p[lz.Q_BRANCHES + K + i]
        p1, p2 = ll1 - y[2 + i], ll2 - y[2 + K + i]
        fa, fb, _, _, _, _ = lz.branch_flow(p1, p2, tau)
        decay = math.exp(-h / tau)
        y[2 + i] = ll1 - (p1 * decay - (1.0 - decay) * (tau * fa - p1))
        y[2 + K + i] = ll2 - (p2 * decay - (1.0 - decay) * (tau * fb - p2))
    if hung:
        F = lz.lozenge_force(y, x, v, V, p, np.empty(y.size))
        me, dme, _ = lz.effective_mass(x, p)
        R = (p[lz.Q_MHUNG] + 0.5 * p[lz.Q_M]) * p[lz.Q_G] - F - 0.5 * dme * v * v
        v = v + h * R / me
        x = x + h * v
        y[0], y[1] = x, v
    G = lz.gentgent(l1, l2, p)[6]
    return bool(G > 0.0 and math.isfinite(x) and math.isfinite(v))


@pytest.mark.parametrize("mode", ["imposed", "hung"])
def test_lozenge_step_and_rig_observables_are_the_full_forces_doubles(mode: str) -> None:
    """The step's and the rig's force computed without stiffness, gradient or the energy's logarithms
    (:func:`bench.models.lozenge.rig_force`, ``gent_stress``) give the doubles of the full formulas, per step over
    a moving, driven history, for one and four Maxwell branches."""
    from bench.models import lozenge as lz

    rng = np.random.default_rng(5 if mode == "hung" else 6)
    for params in (LozengeParams.prototype(2), LozengeParams.prototype(3, branches=lz.VE_B)):
        p = params.pack(lz.MODE_HUNG if mode == "hung" else lz.MODE_IMPOSED)
        n = 400
        x0 = params.xp * rng.uniform(1.05, 1.35)
        xs = x0 * (1.0 + 0.2 * np.sin(np.arange(n) * 0.02))
        U = np.column_stack([rng.uniform(0.0, 6000.0, n), xs, np.gradient(xs) / 1e-4])
        ref, new = params.relaxed_state(x0), params.relaxed_state(x0)
        hist = np.empty((n, ref.size))
        for k in range(n):
            assert _lozenge_step_reference(ref, *U[k], 1e-4, p) == lz.lozenge_step(new, *U[k], 1e-4, p)
            assert _same(ref, new), (mode, k)
            hist[k] = new
        full = np.empty((n, 12))
        rig = np.empty((n, 5))
        lz.lozenge_observe(hist, U[:, 0].copy(), p, full)
        lz.lozenge_observe_rig(hist, U[:, 0].copy(), p, rig)
        assert _same(rig[:, 0], full[:, 0]) and _same(rig[:, 1], full[:, 4]) and _same(rig[:, 4], full[:, 11])
        if mode == "hung":
            assert np.ptp(hist[:, 0]) > 1e-6  # the hung end moved under the drive: the force path ran


def _membrane_step_reference(y: np.ndarray, phi: float, T: float, h: float, p: np.ndarray) -> bool:
    """The membrane's fixed step as first written (physics.md §1.5): every Gent unit through the full
    :func:`gent_h_e2` (dh/du computed and dropped); in Python around the compiled model functions."""
    from bench.models import membrane as mb
    from bench.models.gent import gent_h_e2, relaxation_rate

    lam, v = float(y[0]), float(y[1])
    n = int(p[mb.P_N])
    h0, _, G0 = gent_h_e2(lam * lam, p[mb.P_J0])
    M, dM = mb.inertia(lam, p)
    force = -0.5 * dM * v * v - p[mb.P_MU0] * h0 / lam
    ok = G0 > 0.0
    for i in range(n):
        mu, J, eta = p[mb.P_BRANCHES + i], p[mb.P_BRANCHES + n + i], p[mb.P_BRANCHES + 2 * n + i]
        e = lam / y[2 + i]
        u = math.log(e)
        hu, _, _ = gent_h_e2(e * e, J)
        u *= math.exp(-h * relaxation_rate(u, hu, mu, eta))
        e2 = math.exp(2.0 * u)
        y[2 + i] = lam / math.sqrt(e2)
        hu, _, G = gent_h_e2(e2, J)
        ok = ok and G > 0.0
        force -= mu * hu / lam
    s_es, _ = mb.es_stress(lam, phi, T, p)
    force += p[mb.P_SPRE] - p[mb.P_KF] * (lam - p[mb.P_LPRE]) + s_es
    v = v + h * force / M
    lam = lam + h * v
    y[0], y[1] = lam, v
    return bool(ok and lam > 0.0 and math.isfinite(lam))


def test_membrane_step_is_the_full_gent_units_doubles() -> None:
    """The membrane step's Gent units without dh/du (``gent_h_G``) give the doubles of the full unit, step after
    step under a driven voltage, through a relaxed start and a large stretch."""
    from bench.models.membrane import membrane_step

    params = MembraneParams()
    p = params.pack()
    rng = np.random.default_rng(8)
    ref, new = params.initial_state(), params.initial_state()
    phi = 7000.0 * (1.0 - np.cos(np.linspace(0.0, 2.0 * np.pi, 600))) / 2.0 + rng.normal(0.0, 50.0, 600)
    for k, f in enumerate(phi):
        assert _membrane_step_reference(ref, float(f), 296.0, 1e-4, p) == membrane_step(new, float(f), 296.0, 1e-4, p)
        assert _same(ref, new), k
    assert new[0] > params.lambda_pre * 1.0001  # the drive stretched the membrane: the force path ran
