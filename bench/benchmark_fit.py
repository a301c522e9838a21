"""Benchmarks of identification: the thesis fit end to end, and the cost of one candidate evaluation.

The candidate evaluation (the DE's inner loop) is compared with a generic approach: each candidate integrated
on its own by scipy's Radau with a finite-difference Jacobian, over the same record and input.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from bench.benchmark_acquisition import Figure
from bench.identify.core import FitSettings, fit
from bench.identify.problems import MembraneProblem
from bench.models.membrane import membrane_rhs
from bench.run import execute, plan_run

ROOT = Path(__file__).resolve().parent.parent
FIT_TARGET_S = 30.0
SPEEDUP_TARGET = 20.0


def _record(tmp: Path) -> Path:
    result = execute(plan_run(ROOT / "protocols" / "thesis-identification.toml"), tmp / "run.h5", virtual=True)
    if result.state != "completed":
        raise RuntimeError(f"benchmark run ended {result.state}: {result.reason}")
    return Path(result.path)


def _generic_candidate(prob: MembraneProblem, z: np.ndarray) -> np.ndarray:
    """One candidate the generic way: solve_ivp(Radau), no Jacobian, sampled where the data are."""
    rec = prob.records[0]
    p = prob.params_of(z).pack()
    U, h = rec.U, prob.h
    n = U.shape[0]
    dy = np.empty(rec.y0.size)

    def fun(t: float, y: np.ndarray) -> np.ndarray:
        k = min(max(int(t / h), 0), n - 1)
        membrane_rhs(y, U[k, 0], U[k, 1], p, dy)
        return dy.copy()

    t_eval = np.arange(rec.data.size) * rec.stride * h
    sol = solve_ivp(fun, (0.0, float(t_eval[-1])), rec.y0, method="Radau", t_eval=t_eval, rtol=1e-6,
                    atol=np.full(rec.y0.size, 1e-9))
    t = prob.template
    return t.L_d * (sol.y[0] - t.lambda_pre)  # type: ignore[union-attr]


def candidate_speed(prob: MembraneProblem, generic_candidates: int) -> list[Figure]:
    """Per-candidate time: the batched fixed-step kernel (one DE generation of 50) vs generic one-by-one."""
    rng = np.random.default_rng(3)
    Z = prob.lower + (prob.upper - prob.lower) * rng.random((50, len(prob.names)))
    prob.predict(Z[:2])  # JIT warm-up
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        prob.predict(Z)
        best = min(best, time.perf_counter() - t0)
    batch = best / Z.shape[0]
    # the generic path on the specimen's own parameters (thesis Table 4.4): a candidate near the optimum;
    # random candidates with very short relaxation times are stiffer and take it far longer (≈ 50 s measured)
    t0 = time.perf_counter()
    for _ in range(generic_candidates):
        _generic_candidate(prob, prob.start())
    generic = (time.perf_counter() - t0) / generic_candidates
    duration = prob.records[0].U.shape[0] * prob.h
    return [Figure("candidate evaluation, batch of 50 (fixed-step numba kernel, all cores)", batch * 1e3, "ms",
                   f"{duration:.1f} s record at h = {prob.h * 1e3:g} ms"),
            Figure("  same candidate, generic: scipy Radau, FD Jacobian, one by one", generic * 1e3, "ms",
                   "the specimen's parameters (Table 4.4)"),
            Figure("  speed-up of the batched kernel", generic / batch, "×",
                   f"target ≥ {SPEEDUP_TARGET:g}: {'ok' if generic / batch >= SPEEDUP_TARGET else 'BELOW TARGET'}")]


def thesis_fit(path: Path, settings: FitSettings) -> list[Figure]:
    """The demo's fit: thesis DE settings on the coarse step, polish and identifiability on the fine one."""
    coarse, fine = MembraneProblem([path], h=5e-4), MembraneProblem([path], h=1e-4)
    t0 = time.perf_counter()
    result = fit(coarse, settings, fine=fine)
    wall = time.perf_counter() - t0
    target = settings.generations >= 100
    verdict = (f"; target ≤ {FIT_TARGET_S:g} s: {'ok' if wall <= FIT_TARGET_S else 'ABOVE TARGET'}" if target
               else "; quick: fewer generations, no target")
    return [Figure(f"thesis fit, DE {settings.population} × ≤{settings.generations} (F {settings.mutation}, "
                   f"CR {settings.crossover}) + polish", wall, "s",
                   f"{result.generations} generations, {result.evaluations:,} evaluations, "
                   f"rms {result.rms * 1e6:.1f} µm{verdict}")]


def run_all(quick: bool = False) -> list[Figure]:
    """All identification benchmarks (``quick``: 10 generations)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = _record(Path(tmp))
        figs = candidate_speed(MembraneProblem([path], h=5e-4), 1)
        figs += thesis_fit(path, FitSettings(generations=10) if quick else FitSettings())
    return figs
