"""LS-DEA identification on a measured voltage (issue 27): the monitor's samples drive the model steps they end,
its calibration (gain, offset) is applied per candidate by the batch kernel and fitted within its datasheet bound.

Expected values: the input corrected by hand, the monitor's samples read from the run file, the monitor error the
twin drew from the rig's seed and the LS-DEA specimen recorded in the file — never the code under test."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.identify.core import FitSettings, fit, to_optimiser, to_physical
from bench.identify.coverage import Subset
from bench.identify.problems import CALIBRATION, LozengeProblem
from bench.models.integrate import OBSERVE_FORCE
from bench.models.lozenge import MODE_HUNG, MODE_IMPOSED, LozengeParams, MaxwellBranch
from bench.models.lozenge_batch import lozenge_batch
from bench.storage.runfile import open_run

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def isotonic_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The short isotonic campaign (hung mass, laser) on its simulated hardware-timed rig: noise on, the voltage
    monitor's gain/offset error drawn from the rig's seed, its samples every 0.1 ms."""
    from bench.runtime.run import execute, plan_run

    out = tmp_path_factory.mktemp("lsdea-isotonic")
    res = execute(plan_run(ROOT / "protocols" / "short" / "lsdea-isotonic-short.toml"), out / "run.h5", virtual=True,
                  operator=lambda _msg: True)
    assert res.state == "completed", res.reason
    return Path(res.path)


@pytest.mark.parametrize("mode", [MODE_IMPOSED, MODE_HUNG])
def test_the_lsdea_kernel_applies_a_per_candidate_voltage_calibration(mode: int) -> None:
    """The specimen sees (U − offset)/(1 + gain) of a monitor reading U: the same outputs (force, or hung
    aperture) as the input corrected by hand, per candidate (two candidates, two calibrations, one batch)."""
    base = LozengeParams.prototype(2, hung_mass=0.15 if mode == MODE_HUNG else 0.0)
    base = replace(base, branches=(MaxwellBranch(2e4, 0.3),))
    P = np.stack([base.pack(mode), base.pack(mode)])
    n, h = 4000, 1e-4
    t = np.arange(1, n + 1) * h
    U = np.zeros((n, 3))
    U[:, 0] = 5000.0 * np.sin(np.pi * t / t[-1]) ** 2
    U[:, 1] = base.xp + 0.01 * np.sin(2 * np.pi * 2.0 * t)  # imposed aperture (hung: unused)
    U[:, 2] = 0.04 * np.pi * np.cos(2 * np.pi * 2.0 * t)
    Y0 = np.stack([base.relaxed_state(base.xp)] * 2)
    channel = OBSERVE_FORCE if mode == MODE_IMPOSED else 0
    calibrations = [(5.0, 1e-3), (-8.0, -2e-3)]
    cal = np.array([[off, 1.0 / (1.0 + gain)] for off, gain in calibrations])
    got = lozenge_batch(P, Y0, U, h, channel, 40, cal)
    for k, (off, gain) in enumerate(calibrations):
        Uk = U.copy()
        Uk[:, 0] = (U[:, 0] - off) / (1.0 + gain)
        want = lozenge_batch(P[k:k + 1], Y0[k:k + 1], Uk, h, channel, 40)
        assert np.isfinite(want).all()
        np.testing.assert_allclose(got[k], want[0], rtol=1e-10, atol=1e-12)
    assert not np.allclose(got[0], got[1], rtol=1e-6, atol=0.0)


def test_a_monitor_sample_drives_the_lsdea_step_it_ends(isotonic_run: Path) -> None:
    """A monitor sample at t reads the output up to t: the model step (t − h, t] gets it (h = the scan period,
    0.1 ms) or the mean of the two it holds (h = 0.2 ms) — not, as a command set at t, the step after. The
    samples are the file's own; the record starts at 0 and its step k ends at (k + 1)·h."""
    amp = open_run(isotonic_run).streams["amplifier"]
    v, ts = amp.columns["voltage"], amp.t
    assert ts[:3] == pytest.approx([1e-4, 2e-4, 3e-4])  # one sample per scan from the first scan's end
    for h, per_step in ((1e-4, 1), (2e-4, 2)):
        prob = LozengeProblem([isotonic_run], h=h)
        assert prob.names[-2:] == CALIBRATION and prob.records[0].measured
        m = len(v) // per_step - 1
        want = v[:m * per_step].reshape(m, per_step).mean(axis=1)
        # to 1 µV (running sums of 1e5 kV-samples round at 1e-8 V); neighbouring samples differ by ~1 V (noise)
        np.testing.assert_allclose(prob.records[0].U[:m, 0], want, rtol=0.0, atol=1e-6)


def test_the_isotonic_twin_run_s_intervals_hold_the_monitor_error_it_drew(isotonic_run: Path) -> None:
    """The short isotonic run on the simulated DAQ rig: μ, the damper c and the monitor's calibration fitted (the
    rest held at the specimen recorded in the file), simultaneous 95 % intervals. Each interval holds the twin's
    value — the monitor's gain and offset errors drawn from the rig's seed among them —, the offset is
    determined, and the truth with the monitor taken at its word sits far above the optimum (what the calibration
    is fitted for: the laser resolves the 3-V offset of a 10-kV monitor)."""
    prob = LozengeProblem([isotonic_run], h=1e-4)  # the twin's step: no discretisation error in the comparison
    model = json.loads(open_run(isotonic_run, streams=False).attrs["specimen"])["model"]
    m, br = model["material"], model["branches"][0]
    drawn = prob.simulated_calibration()
    assert set(drawn) == set(CALIBRATION) and drawn["V_offset"] != 0.0
    truth = {"mu": m["mu"], "Jm": m["Jm"], "C2": m["C2"], "mu_b1": br["mu"], "tau_b1": br["tau"],
             "c": model["damping"], **drawn}
    z = to_optimiser(prob.log, np.array([truth[n] for n in prob.names]))
    free = ["mu", "c", *CALIBRATION]
    sub = Subset(prob, free, z)
    zt = z[sub.index]
    start = np.clip(zt + 0.05 * (sub.upper - sub.lower) * np.array([1, -1, 1, -1]), sub.lower, sub.upper)
    res = fit(sub, FitSettings(population=5, generations=1, cost="lsq", polish_iterations=30, intervals=True,
                               simultaneous=True), start=start)
    tr = res.trust
    assert tr is not None and "simultaneous" in tr.method
    t = to_physical(sub.log, zt)
    assert tr.status[free.index("V_offset")] == "determined"
    for j, name in enumerate(free):
        tol = 1e-9 * abs(t[j])
        assert tr.lower[j] - tol <= t[j] <= tr.upper[j] + tol, (name, t[j], tr.lower[j], tr.upper[j])
    ok = np.isfinite(prob.data)
    nominal = z.copy()
    nominal[-2:] = 0.0
    chi_nominal = float(np.sum(((prob.predict(nominal)[0] - prob.data)[ok] / sub.sigma[ok]) ** 2))
    chi_min = float(np.sum((res.residual / sub.sigma[ok]) ** 2))
    assert chi_nominal - chi_min > 10 * tr.threshold


def test_the_lsdea_fit_s_model_step_widening_holds_its_fine_step_s_error(isotonic_run: Path) -> None:
    """The fit's fine LS-DEA step keeps its discretisation error within what the intervals are widened by: per
    parameter, the fine step's least-squares optimum (from the twin's specimen) lies no farther from the optimum at
    the twin's own step (the monitor's scan period, at which the run was simulated: no discretisation error) than
    the search step's optimum lies from it (the shift :func:`bench.identify.trust.assess_trust` widens each interval
    by). At the former 1-ms fine step μ, Jm and C2 were 24, 13 and 3 times that shift away (ad-hoc script, see the
    commit) and their intervals excluded the truth. Optimised here by scipy, not by the code under test."""
    from scipy.optimize import least_squares

    from bench.app.fit import LSDEA_FINE_STEP, LSDEA_SEARCH_STEP

    ts = open_run(isotonic_run).streams["amplifier"].t
    twin_step = float(ts[1] - ts[0])
    model = json.loads(open_run(isotonic_run, streams=False).attrs["specimen"])["model"]
    m, br = model["material"], model["branches"][0]

    def optimum(h: float, start: np.ndarray | None = None) -> np.ndarray:
        prob = LozengeProblem([isotonic_run], h=h)
        if start is None:
            truth = {"mu": m["mu"], "Jm": m["Jm"], "C2": m["C2"], "mu_b1": br["mu"], "tau_b1": br["tau"],
                     "c": model["damping"], **prob.simulated_calibration()}
            start = to_optimiser(prob.log, np.array([truth[n] for n in prob.names]))
        ok = np.isfinite(prob.data)

        def weighted(Z: np.ndarray) -> np.ndarray:
            R: np.ndarray = (prob.predict(Z)[:, ok] - prob.data[ok]) / prob.sigma[ok]
            return R

        def residual(z: np.ndarray) -> np.ndarray:
            r: np.ndarray = weighted(z[None, :])[0]
            return r

        def jacobian(z: np.ndarray) -> np.ndarray:  # forward differences, all columns in one model batch
            dz = 1e-6 * np.maximum(np.abs(z), 1.0)
            dz = np.where(z + dz > prob.upper, -dz, dz)
            R = weighted(np.vstack([z, z + np.diag(dz)]))
            J: np.ndarray = ((R[1:] - R[0]) / dz[:, None]).T
            return J

        res = least_squares(residual, start, jac=jacobian, bounds=(prob.lower, prob.upper), x_scale="jac")
        z: np.ndarray = res.x
        return z

    exact = optimum(twin_step)
    fine = optimum(LSDEA_FINE_STEP)
    coarse = optimum(LSDEA_SEARCH_STEP, fine)
    bias, shift = np.abs(fine - exact), np.abs(coarse - fine)
    names = LozengeProblem([isotonic_run], h=LSDEA_SEARCH_STEP).names
    assert all(bias <= shift), [(n, b, d) for n, b, d in zip(names, bias, shift, strict=True) if b > d]


def test_a_file_without_a_stored_rig_fits_on_its_set_points(tmp_path: Path) -> None:
    """A run file that stores no rig (older files, replays) and whose voltage is the set-points (a software-timed
    rig: monitors polled, not sampled at the scan rate) builds its LS-DEA problem as before the monitor calibration:
    no calibration parameters, no twin's drawn error — not a KeyError on the missing attribute."""
    import shutil

    import h5py

    from bench.runtime.run import execute, plan_run

    res = execute(plan_run(ROOT / "protocols" / "short" / "lsdea-isotonic-short.toml",
                           ROOT / "rigs" / "lsdea-isotonic-sim.toml"), tmp_path / "run.h5", virtual=True,
                  operator=lambda _msg: True)
    assert res.state == "completed", res.reason
    bare = tmp_path / "bare.h5"
    shutil.copy(res.path, bare)
    with h5py.File(bare, "a") as f:
        del f.attrs["rig_toml"]
    prob = LozengeProblem([bare], h=2e-3)
    assert not set(CALIBRATION) & set(prob.names)
    assert prob.simulated_calibration() == {}
    # a stored rig that today's schema refuses (an unknown field): one line naming the file, not pydantic's report
    stale = tmp_path / "stale.h5"
    shutil.copy(res.path, stale)
    with h5py.File(stale, "a") as f:
        f.attrs["rig_toml"] = str(f.attrs["rig_toml"]) + "\nbogus_field = 1\n"
    with pytest.raises(ValueError, match=r"stale\.h5: its recorded rig cannot be read") as err:
        LozengeProblem([stale], h=2e-3)
    assert "\n" not in str(err.value)
