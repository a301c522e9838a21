"""Parameter identification: differential evolution (as in the thesis), least-squares polish, identifiability.

A :class:`Problem` gives parameter names, bounds in optimiser coordinates (linear or log10 per parameter),
a *batched* predictor (many parameter sets at once, on all cores) and the measured data; a problem may compute the
search's costs itself (:class:`Costs`: where its predictions are made, on a cluster one number per candidate back
instead of its prediction). Differential evolution (scipy, ``vectorized=True``: one batch per generation) searches
the bounded space with the thesis's settings (Table 4.1: population 50, F = 0.6, CR = 0.9, 100 generations);
where the problem has interchangeable units of equal bounds, the same scheme with each candidate's units sorted by
τ (:func:`canonical`).
A bounded least-squares step (scipy ``least_squares``, finite-difference Jacobian evaluated as one batch) polishes
the best member.
The same Jacobian gives each parameter's sensitivity and the correlation matrix; parameters on a bound, with
no influence on the cost, or almost perfectly correlated with another are flagged.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np
from scipy.optimize import OptimizeResult, differential_evolution, least_squares

if TYPE_CHECKING:
    from bench.identify.trust import Trust

Cost = Literal["sae", "lsq"]


class Problem(Protocol):
    """What the fitter needs from a model and its records."""

    names: list[str]
    units: list[str]
    lower: np.ndarray  # optimiser coordinates
    upper: np.ndarray
    log: np.ndarray  # bool per parameter: optimiser coordinate is log10 of the physical value
    data: np.ndarray  # measured values, concatenated over records (NaN: ignore)
    data_unit: str  # unit of the data (and of the residual)

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """Model predictions for each row of Z (S × D) → S × len(data); NaN where a model failed."""


@runtime_checkable
class Costs(Protocol):
    """A problem that computes the search's costs itself (e.g. where its predictions are made, on a cluster): the
    values of :func:`_costs` on its prediction, up to the order of the sums."""

    def costs(self, Z: np.ndarray, kind: Cost) -> np.ndarray:
        """The cost of each row of Z (S × D) → S; inf where a compared residual is not finite."""


class Record(Protocol):
    """One record of a problem: its inputs per step, packed template, compared data and where it came from."""

    U: np.ndarray
    template: np.ndarray
    data: np.ndarray
    source: str


class RecordedProblem(Problem, Protocol):
    """A problem made of records whose data are concatenated in ``data`` (campaign analysis reads them)."""

    @property
    def records(self) -> Sequence[Record]:
        """The records, in the order of their data."""


@dataclass(frozen=True)
class FitSettings:
    """Differential evolution and polish settings (defaults: thesis Table 4.1)."""

    population: int = 50
    generations: int = 100
    mutation: float = 0.6
    crossover: float = 0.9
    cost: Cost = "sae"  # the thesis's sum of absolute errors, or least squares
    polish: bool = True
    polish_iterations: int = 20
    seed: int = 1
    tol: float = 0.01  # scipy's relative convergence tolerance of the population's costs
    # stop on convergence of the best cost: when it improved by less than stall_tol (relative) over the last
    # stall_generations generations, the search ends and the polish takes over (0: run to scipy's criterion)
    stall_generations: int = 10
    stall_tol: float = 1e-3
    # trust (:mod:`bench.identify.trust`): the search repeated from ``starts`` seeds (seed, seed + 1, …) and, with
    # ``intervals``, profile-likelihood intervals at ``confidence`` against each record's noise
    starts: int = 1
    intervals: bool = False
    confidence: float = 0.95
    # simultaneous: the intervals hold *together* at ``confidence`` (each the projection of the joint region, Δχ²
    # up to the χ²(p) quantile, p the fitted parameters) — for checking a whole table against a known truth;
    # otherwise each on its own (χ²(1))
    simultaneous: bool = False


@dataclass
class FitResult:
    """Outcome of a fit: physical parameter values, bounds, cost, identifiability."""

    names: list[str]
    units: list[str]
    values: np.ndarray
    lower: np.ndarray  # physical units
    upper: np.ndarray
    cost: float
    cost_kind: str
    rms: float
    n_data: int
    evaluations: int
    generations: int
    wall_time: float
    sensitivity: np.ndarray  # change of the model output (rms) per 1 % change of the parameter, relative to data rms
    correlation: np.ndarray
    uncertainty: np.ndarray  # relative standard error from the residual and the Jacobian (NaN: not estimable)
    flags: list[str] = field(default_factory=list)
    settings: FitSettings = field(default_factory=FitSettings)
    jacobian: np.ndarray | None = None  # ∂prediction/∂(optimiser coordinate) at the result, compared points only
    residual: np.ndarray | None = None  # prediction − data at the compared points
    z: np.ndarray | None = None  # the result in optimiser coordinates
    search_time: float = 0.0  # s of the wall time spent in the differential evolution (the rest: polish, analysis)
    lack_of_fit: str = ""  # why the model does not follow the data ('' when it does): see :func:`lack_of_fit`
    trust: Trust | None = None  # intervals, identifiability, noise, multi-start agreement (settings.intervals)
    rms_by_unit: dict[str, float] = field(default_factory=dict)  # a campaign of force and laser records: each's rms

    def flags_of(self, name: str) -> list[str]:
        """Flags of one parameter."""
        return [f.split(": ", 1)[1] for f in self.flags if f.startswith(name + ": ")]


def rms_by_unit(problem: Any, residual: np.ndarray) -> dict[str, float]:
    """The residual's rms over each unit's compared points, where ``problem`` holds records of more than one unit
    (``point_units``: the unit of each data point; an rms over newtons and metres together means nothing); {}
    otherwise."""
    units_of = getattr(problem, "point_units", None)
    if units_of is None:
        return {}
    units = np.asarray(units_of())[np.isfinite(problem.data)]
    if units.size != residual.size or len(set(units.tolist())) < 2:
        return {}
    return {str(u): float(np.sqrt(np.mean(residual[units == u] ** 2))) for u in dict.fromkeys(units.tolist())}


def to_physical(log: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Optimiser coordinates → physical values (10**z where ``log``)."""
    V = np.array(Z, dtype=float)
    V[..., log] = 10.0 ** V[..., log]
    return V


def to_optimiser(log: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Physical values → optimiser coordinates (log10 where ``log``); the inverse of :func:`to_physical`."""
    V = np.asarray(V, dtype=float)
    return np.where(log, np.log10(np.where(log, V, 1.0)), V)


def physical(problem: Problem, Z: np.ndarray) -> np.ndarray:
    """Optimiser coordinates → physical values."""
    return to_physical(np.asarray(problem.log, bool), Z)


def noise_of(data: np.ndarray) -> float:
    """Noise σ of a record estimated from itself: 1.4826 × the median absolute deviation of its fourth
    differences over √70 (white noise of σ gives k-th differences of variance C(2k, k) σ²: 70 σ² for k = 4; a
    signal smooth at the sampling rate adds (ωΔt)⁴ of its amplitude, and the median ignores its few steep
    points). NaN points are skipped; the floor is 1e-9 of the record's rms (a quantised, noiseless record)."""
    d = np.asarray(data, float)
    d4 = d[4:] - 4 * d[3:-1] + 6 * d[2:-2] - 4 * d[1:-3] + d[:-4]
    d4 = d4[np.isfinite(d4)]
    rms = float(np.sqrt(np.nanmean(d * d))) if np.isfinite(d).any() else 0.0
    floor = max(1e-9 * rms, 1e-300)
    if d4.size < 3:
        return floor
    return max(1.4826 * float(np.median(np.abs(d4 - np.median(d4)))) / float(np.sqrt(70.0)), floor)


def sigma_of(problem: Problem) -> np.ndarray:
    """Noise σ per data point: the problem's ``sigma`` (per record) when it has one, else one σ of all data."""
    s = getattr(problem, "sigma", None)
    if s is not None:
        return np.asarray(s, float)
    return np.full(problem.data.shape, noise_of(problem.data))


def _costs(problem: Problem, pred: np.ndarray, kind: Cost) -> np.ndarray:
    mask = np.isfinite(problem.data)
    r = ((pred - problem.data) / sigma_of(problem))[:, mask]
    c: np.ndarray = np.sum(np.abs(r), axis=1) if kind == "sae" else np.sum(r * r, axis=1)
    c[~np.all(np.isfinite(r), axis=1)] = np.inf
    return c


Stage = Callable[[str, float], None]  # (stage after the search: "polish" or "intervals", fraction of it done)


def fit(problem: Problem, settings: FitSettings = FitSettings(), start: np.ndarray | None = None,
        fine: Problem | None = None, progress: Callable[[], None] | None = None,
        stage: Stage | None = None) -> FitResult:
    """Identify the problem's parameters; returns values, cost and identifiability.

    ``fine``: the same problem at a finer integration step, used for the polish and the identifiability
    (the search runs on the coarse, fast one). ``progress`` is called once per generation, ``stage`` with the
    share done of the polish (its evaluations against the iteration limit, all starts together) and of the
    intervals (the profiles' walks finished). With
    ``settings.starts`` > 1 the search and polish run from that many seeds and the best is kept; with
    ``settings.intervals`` the result carries profile-likelihood intervals (:mod:`bench.identify.trust`).
    """
    t0 = time.perf_counter()
    n_data = int(np.isfinite(problem.data).sum())
    if n_data <= len(problem.names):  # no fit to be had: a cost of 0 over no points would be stored as one
        raise ValueError(f"{n_data} valid data points for {len(problem.names)} parameters: nothing to fit (the "
                         "sensor read out of range or invalid through the whole record?)")
    runs = searches(problem, settings, start, fine, progress, stage)
    best = min(runs, key=lambda r: r.cost)
    target = fine or problem
    mask = np.isfinite(target.data)
    data = target.data[mask]
    scale = max(float(np.sqrt(np.mean(data * data))), 1e-30)
    z, J, r = best.z, best.J, best.pred - data
    log = np.asarray(target.log, bool)
    sens, corr, uncertainty, flags = assess(list(target.names), log, best.lo, best.hi, z, J, r, scale)
    result = FitResult(list(target.names), list(target.units), physical(target, z), physical(target, best.lo),
                       physical(target, best.hi), best.cost, settings.cost, float(np.sqrt(np.mean(r * r))),
                       int(data.size), sum(x.evaluations for x in runs), best.generations,
                       time.perf_counter() - t0, sens, corr, uncertainty, flags, settings, J, r, z,
                       sum(x.search_time for x in runs), lack_of_fit(r, data), rms_by_unit=rms_by_unit(target, r))
    if settings.intervals:
        from bench.identify.trust import assess_trust

        assess_trust(target, result, [(x.seed, x.z, x.lo, x.hi) for x in runs], best.lo, best.hi,
                     coarse=problem if fine is not None else None,
                     on_profile=None if stage is None else lambda fraction: stage("intervals", fraction))
        result.wall_time = time.perf_counter() - t0
    return result


def searches(problem: Problem, settings: FitSettings, start: np.ndarray | None = None, fine: Problem | None = None,
             progress: Callable[[], None] | None = None, stage: Stage | None = None) -> list[_Run]:
    """The search and polish from ``settings.starts`` seeds (seed, seed + 1, …), concurrently: one thread per start
    (the model kernels release the GIL), each given its share of the kernel's threads (numba's thread count is
    per thread); on a dask cluster (a distributed problem) the starts' evaluations are tasks side by side. Each
    start depends on its seed only (its own generator and counters), not on the others or on the timing."""
    n = max(1, settings.starts)
    shares = [0.0] * n  # each start's share of its polish done: the stage reports their mean

    def polished(k: int) -> Callable[[float], None] | None:
        if stage is None:
            return None

        def one(fraction: float) -> None:
            shares[k] = fraction
            stage("polish", sum(shares) / n)
        return one

    if n == 1 or not _kernels_thread_safe():
        return [_search(problem, replace(settings, seed=settings.seed + k), start if k == 0 else None, fine,
                        progress, polished(k)) for k in range(n)]
    from concurrent.futures import ThreadPoolExecutor

    import numba

    share = max(1, numba.get_num_threads() // n)

    def one(k: int) -> _Run:
        numba.set_num_threads(share)
        return _search(problem, replace(settings, seed=settings.seed + k), start if k == 0 else None, fine, progress,
                       polished(k))

    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="fit-start") as pool:
        return list(pool.map(one, range(n)))


def _kernels_thread_safe() -> bool:
    """Whether numba's threading layer lets several threads call the parallel kernels at once: TBB and OpenMP do,
    the ``workqueue`` fallback (where neither is installed) aborts the process on concurrent use, so the starts
    then run one after another."""
    import importlib

    import numba

    try:
        return bool(numba.threading_layer() != "workqueue")  # type: ignore[attr-defined]  # exported untyped
    except ValueError:  # no parallel kernel ran yet: the layer numba will choose
        pass
    if numba.config.THREADING_LAYER == "workqueue":  # type: ignore[attr-defined]  # set by numba.config at import
        return False
    for layer in ("numba.np.ufunc.tbbpool", "numba.np.ufunc.omppool"):
        try:
            importlib.import_module(layer)
            return True
        except ImportError:
            continue
    return False


@dataclass
class _Run:
    seed: int
    z: np.ndarray
    pred: np.ndarray
    J: np.ndarray
    cost: float
    lo: np.ndarray  # bounds in optimiser coordinates, in the order of z (units ordered by relaxation time)
    hi: np.ndarray
    evaluations: int
    generations: int
    search_time: float


def unit_order(problem: Problem, z: np.ndarray) -> np.ndarray:
    """Permutation of the parameters that numbers interchangeable units by increasing relaxation time: the
    problem's ``unit_groups`` (index lists of each unit's parameters, its relaxation time last); identity when
    it has none."""
    perm = np.arange(z.size)
    groups = getattr(problem, "unit_groups", None)
    if not groups:
        return perm
    g = np.asarray(groups, dtype=np.intp)
    perm[g] = g[_slots(z[None, :], g)[0]]
    return perm


def _slots(Z: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """For each row of Z, the unit that goes into each slot: the units by increasing relaxation time (the last
    index of each group), ties kept in order."""
    order: np.ndarray = np.argsort(Z[:, groups[:, -1]], axis=1, kind="stable")
    return order


def sorts_units(problem: Problem) -> bool:
    """Whether the search sorts the problem's interchangeable units (:func:`canonical`): two groups or more, all
    with the same bounds."""
    groups = np.asarray(getattr(problem, "unit_groups", None) or [], int)
    if groups.ndim != 2 or groups.shape[0] < 2:
        return False
    lo, hi = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    return bool(np.all(lo[groups] == lo[groups[:1]]) and np.all(hi[groups] == hi[groups[:1]]))


def canonical(problem: Problem, Z: np.ndarray) -> np.ndarray:
    """Each row of Z (S × D, optimiser coordinates) with its interchangeable units sorted by relaxation time (the
    problem's ``unit_groups``, τ last): the one representative of the row's copies under exchanging units, which
    the model cannot tell apart. Z unchanged where the problem has fewer than two groups, or where the groups'
    bounds differ (a sorted row could leave the box)."""
    Z = np.atleast_2d(np.asarray(Z, float))
    if not sorts_units(problem):
        return Z
    groups = np.array(getattr(problem, "unit_groups", None), dtype=np.intp)  # sorts_units: it has them
    out = Z.copy()
    out[:, groups] = Z[np.arange(Z.shape[0])[:, None, None], groups[_slots(Z, groups)]]
    return out


def _evolve(cost: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray, init: np.ndarray,
            settings: FitSettings, rng: np.random.Generator, canon: Callable[[np.ndarray], np.ndarray],
            generation: Callable[[float], None]) -> tuple[np.ndarray, np.ndarray, int]:
    """Differential evolution (best/1/bin, one batch per generation, as scipy's ``updating="deferred"``) whose
    population is kept canonical (``canon``: units sorted by τ) so that its differences compare like units; a
    component driven out of the box is redrawn uniformly in it (scipy's rule). Ends after ``settings.generations``,
    when the population's costs agree within ``settings.tol`` (scipy's criterion) or when ``generation`` (called
    with the best cost after each) raises StopIteration. Returns the population, its costs and the generations
    run."""
    pop = canon(init)
    S, D = pop.shape
    if S < 5:  # scipy's rule: best/1/bin draws two members other than the target
        raise ValueError(f"differential evolution needs a population of at least 5, got {S}")
    E = cost(pop)
    nit = 0
    while nit < settings.generations:
        nit += 1
        b = int(np.argmin(E))
        r = np.argsort(rng.random((S, S)) + np.eye(S), axis=1)[:, :2]  # two other members each, distinct
        mutant = pop[b] + settings.mutation * (pop[r[:, 0]] - pop[r[:, 1]])
        cross = rng.random((S, D)) < settings.crossover
        cross[np.arange(S), rng.integers(D, size=S)] = True
        trial = np.where(cross, mutant, pop)
        trial = canon(np.where((trial < lo) | (trial > hi), lo + (hi - lo) * rng.random((S, D)), trial))
        Et = cost(trial)
        better = Et <= E
        pop[better], E[better] = trial[better], Et[better]
        try:
            generation(float(np.min(E)))
        except StopIteration:
            break
        if np.all(np.isfinite(E)) and np.std(E) <= settings.tol * abs(float(np.mean(E))):
            break
    return pop, E, nit


def _search(problem: Problem, settings: FitSettings, start: np.ndarray | None, fine: Problem | None,
            progress: Callable[[], None] | None, polished: Callable[[float], None] | None = None) -> _Run:
    """One differential evolution from ``settings.seed`` and its polish (``polished``: the share of the polish's
    evaluation limit used, as it goes; 1 when it ends)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(settings.seed)
    D = len(problem.names)
    lo, hi = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    init = lo + (hi - lo) * rng.random((settings.population, D))
    if start is not None:
        init[0] = np.clip(start, lo, hi)
    evaluations = 0
    own = problem.costs if isinstance(problem, Costs) else None  # its own costs (one number per candidate back)

    def batch_cost(Zt: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        Z = np.atleast_2d(Zt.T) if Zt.ndim == 2 else Zt[None, :]
        evaluations += Z.shape[0]
        if own is not None:
            return own(Z, settings.cost)
        return _costs(problem, problem.predict(Z), settings.cost)

    best: list[float] = []

    def generation(fun: float) -> None:
        if progress:
            progress()
        best.append(fun)
        n = settings.stall_generations
        if n and len(best) > n and best[-1 - n] - best[-1] <= settings.stall_tol * abs(best[-1 - n]):
            raise StopIteration  # converged: the best cost no longer moves

    def scipy_generation(intermediate_result: OptimizeResult) -> None:  # scipy passes the result by this name
        generation(float(intermediate_result.fun))

    if not sorts_units(problem):  # no interchangeable units: scipy's differential evolution
        de = differential_evolution(batch_cost, list(zip(lo, hi, strict=True)), init=init,
                                    maxiter=settings.generations, mutation=settings.mutation,
                                    recombination=settings.crossover, tol=settings.tol, polish=False,
                                    vectorized=True, updating="deferred", seed=settings.seed,
                                    callback=scipy_generation)
        pop, E, nit = np.asarray(de.population, float), np.asarray(de.population_energies, float), int(de.nit)
    else:  # the same, with each candidate's units sorted by τ (:func:`canonical`)
        pop, E, nit = _evolve(lambda Z: batch_cost(Z.T), lo, hi, init, settings, rng,
                              lambda Z: canonical(problem, Z), generation)
    search_time = time.perf_counter() - t0
    problem = fine or problem
    mask = np.isfinite(problem.data)
    data = problem.data[mask]
    sigma = sigma_of(problem)[mask]
    step = 1e-3 * (hi - lo)

    def jac_batch(zc: np.ndarray, cols: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        nonlocal evaluations
        cols = np.arange(D) if cols is None else cols
        dz = np.where(zc + step > hi, -step, step)[cols]
        Z = np.tile(zc, (cols.size + 1, 1))
        Z[np.arange(1, cols.size + 1), cols] += dz
        evaluations += Z.shape[0]
        pred = problem.predict(Z)[:, mask]
        return pred[0], (pred[1:] - pred[0]).T / dz

    def cost_of(r: np.ndarray) -> float:
        if not np.all(np.isfinite(r)):
            return np.inf
        return float(np.sum(np.abs(r)) if settings.cost == "sae" else np.sum(r * r))

    points = [0]  # points the polish evaluated (each with its Jacobian): its limit is max_nfev
    limit = max(settings.polish_iterations, 1)

    def polish(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The polish of one candidate: (z, prediction, Jacobian) after it."""
        pred, J = jac_batch(z)
        if not settings.polish:
            return z, pred, J
        # polish the parameters that influence the cost (a move across the span changes χ²: √Δχ² ≥ 0.1), at the
        # fine step: the others only hurt conditioning
        from bench.identify.trust import influence

        free = np.flatnonzero(influence(J, sigma, hi - lo) >= 0.1)
        z_fixed = z.copy()

        def full(zf: np.ndarray) -> np.ndarray:
            zz = z_fixed.copy()
            zz[free] = zf
            return zz

        cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

        def both(zf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            key = zf.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = jac_batch(full(zf), free)
                if polished is not None:
                    points[0] += 1
                    polished(min(points[0] / limit, 1.0))
            return cache[key]

        def res(zc: np.ndarray) -> np.ndarray:
            r = (both(zc)[0] - data) / sigma  # each stream against its noise
            return np.where(np.isfinite(r), r, 1e6)

        def jac(zc: np.ndarray) -> np.ndarray:
            J = both(zc)[1] / sigma[:, None]
            return np.where(np.isfinite(J), J, 0.0)

        ls = least_squares(res, z[free], jac=jac, bounds=(lo[free], hi[free]), x_scale=(hi - lo)[free],
                           max_nfev=settings.polish_iterations)
        after = cost_of((both(ls.x)[0] - data) / sigma)
        if np.isfinite(after) and after <= cost_of((pred - data) / sigma):
            z = full(ls.x)
            pred, J = jac_batch(z)
        return z, pred, J

    z, pred, J = polish(pop[int(np.argmin(E))])
    if polished is not None:
        polished(1.0)
    perm = unit_order(problem, z)  # the model is symmetric under exchanging units: number them by τ
    return _Run(settings.seed, z[perm], pred, J[:, perm], cost_of(pred - data), lo[perm], hi[perm], evaluations,
                nit, search_time)


LACK_OF_FIT_SHARE = 0.02  # residual rms above this share of the data's spread ...
LACK_OF_FIT_CORRELATION = 0.5  # ... and residuals this correlated from point to point: a systematic misfit


def lack_of_fit(r: np.ndarray, data: np.ndarray) -> str:
    """Why the best fit does not describe the data, or '' when it does.

    A model that cannot follow the data leaves a residual that is both large against the data's spread (its
    standard deviation) and systematic: neighbouring residuals share their sign (lag-1 autocorrelation near
    1), whereas measurement noise averages out (near 0). Either alone is no verdict: a small systematic
    residual (quantisation, integrator) and a large noisy one (a noisy sensor) are both fits."""
    r, data = np.asarray(r, float).ravel(), np.asarray(data, float).ravel()
    spread = float(np.std(data))
    if r.size < 3 or spread == 0.0:
        return ""
    share = float(np.sqrt(np.mean(r * r))) / spread
    rc = r - r.mean()
    denom = float(np.dot(rc, rc))
    lag1 = float(np.dot(rc[:-1], rc[1:]) / denom) if denom > 0 else 0.0
    if share > LACK_OF_FIT_SHARE and lag1 > LACK_OF_FIT_CORRELATION:
        return (f"the model does not follow the data: residual rms {100 * share:.1f} % of the data's spread, "
                f"systematic (lag-1 autocorrelation {lag1:.2f})")
    return ""


def assess(names: list[str], log: np.ndarray, lo: np.ndarray, hi: np.ndarray, z: np.ndarray, J: np.ndarray,
           r: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Identifiability at ``z`` from the Jacobian J (points × parameters, optimiser coordinates) and residual r:
    sensitivity, correlation, relative standard errors and flags (bound, no effect, correlated, poorly
    determined). ``scale`` is the data's rms (sensitivities are relative to it)."""
    values = to_physical(log, z)
    # sensitivity: output change (rms, relative to the data rms) for a 1 % change of the physical value
    dphys = np.where(log, values * np.log(10.0), 1.0)  # dθ/dz
    Jphys = J / dphys  # ∂pred/∂θ
    sens = np.sqrt(np.mean((Jphys * (0.01 * values)) ** 2, axis=0)) / scale
    active = sens >= 1e-3 * max(float(np.max(sens)), 1e-300)  # correlations among parameters that matter
    corr = np.full((len(values), len(values)), np.nan)
    Ja = Jphys[:, active] * values[active]  # relative parameters: the scales do not condition the inverse
    cov = np.linalg.pinv(Ja.T @ Ja)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr[np.ix_(active, active)] = cov / np.outer(d, d)
    # relative standard errors: residual variance × (JᵀJ)⁻¹ in relative parameters (a lower bound when the
    # residual is systematic rather than noise)
    s2 = float(np.sum(r * r)) / max(r.size - int(active.sum()), 1)
    uncertainty = np.full(len(values), np.nan)
    uncertainty[active] = np.sqrt(s2) * d
    flags = []
    for j, name in enumerate(names):
        span = hi[j] - lo[j]
        if z[j] - lo[j] < 0.01 * span:
            flags.append(f"{name}: at its lower bound")
        if hi[j] - z[j] < 0.01 * span:
            flags.append(f"{name}: at its upper bound")
        if sens[j] < 1e-3 * max(float(np.max(sens)), 1e-300):
            flags.append(f"{name}: does not change the cost (sensitivity {sens[j]:.1e})")
        if np.isfinite(uncertainty[j]) and uncertainty[j] > 0.05:
            flags.append(f"{name}: poorly determined (±{100 * uncertainty[j]:.0f} %)")
        others = [k for k in range(len(names)) if k != j and np.isfinite(corr[j, k]) and abs(corr[j, k]) > 0.98]
        if others:
            flags.append(f"{name}: correlated with " + ", ".join(names[k] for k in others))
    return sens, corr, uncertainty, flags
