"""Coverage of the stated intervals: fits of records simulated with known parameters and a stated noise model.

A :class:`SyntheticMembrane` problem simulates the thesis membrane model (:mod:`bench.models.membrane`, the
specimen of thesis Table 4.4) under a raised-cosine drive with the same batch kernel the fits use, and adds
Gaussian noise of a stated σ (white, independent per sample: the noise model the fit assumes). Each repeat
draws a new noise realisation, fits from the truth displaced by a random factor (the search is not what is
tested here: the intervals are) with the least-squares polish, and computes the profile-likelihood intervals
(:func:`bench.identify.trust.assess_trust`). :func:`coverage` counts, per parameter, how often the interval
holds the truth. :class:`Subset` fits a few parameters of any problem, the others held (a twin's record checked
against the parameters the twin was configured with).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.identify.core import FitSettings, Problem, fit, sigma_of, to_optimiser
from bench.models.membrane import MembraneParams
from bench.models.membrane_batch import membrane_batch_records

ALL = ["mu0", "J0"] + [f"mu{i}" for i in range(1, 5)] + [f"J{i}" for i in range(1, 5)] + \
    [f"tau{i}" for i in range(1, 5)]


class SyntheticMembrane:
    """The membrane model on a simulated record with noise: ``free`` parameters fitted, the others held at the
    truth (thesis Table 4.4). Drive: 0 → ``volts`` raised cosine at ``frequency`` for ``duration`` s, then a
    rest of ``rest`` s; 296 K; step ``h``; data: ``rate`` Hz window means of u = L_d(λ − λ_pre)."""

    def __init__(self, free: list[str], sigma: float, seed: int, volts: float = 7e3, frequency: float = 0.5,
                 duration: float = 6.0, rest: float = 2.0, h: float = 5e-4, rate: float = 50.0) -> None:
        self.truth_params = MembraneParams()
        t = self.truth_params
        self.full_truth = np.array([t.mu0, t.J0, *t.mu, *t.J, *t.tau])
        self.index = [ALL.index(n) for n in free]
        self.names = list(free)
        units = {"mu": "Pa", "J": "-", "tau": "s"}
        self.units = [units[n.rstrip("0123456789")] for n in free]
        lo = {"mu": 10.0, "J": 100.0, "tau": -5.0}
        hi = {"mu": 500e3, "J": 800.0, "tau": np.log10(20.0)}
        self.lower = np.array([lo[n.rstrip("0123456789")] for n in free])
        self.upper = np.array([hi[n.rstrip("0123456789")] for n in free])
        self.log = np.array([n.startswith("tau") for n in free])
        self.h, self.stride = h, max(1, round(1.0 / (rate * h)))
        n = round((duration + rest) / h)
        n -= n % self.stride
        ts = np.arange(1, n + 1) * h
        U = np.empty((n, 2))
        U[:, 0] = np.where(ts < duration, volts * 0.5 * (1.0 - np.cos(2 * np.pi * frequency * ts)), 0.0)
        U[:, 1] = 296.0
        self.U = U
        self.data_unit = "m"
        self.sigma_true = sigma
        clean = self.predict(self.truth()[None, :])[0]
        self.data = clean + np.random.default_rng(seed).normal(0.0, sigma, clean.size)

    def truth(self) -> np.ndarray:
        """The true values of the free parameters in optimiser coordinates."""
        return to_optimiser(self.log, self.full_truth[self.index])

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """u [m] for each row of Z."""
        Z = np.atleast_2d(Z)
        t = self.truth_params
        P = []
        for z in Z:
            v = self.full_truth.copy()
            v[self.index] = z
            v[np.array(self.index)[self.log]] = 10.0 ** z[self.log]
            mu, J, tau = tuple(v[2:6]), tuple(v[6:10]), tuple(v[10:14])
            P.append(t.with_units(float(v[0]), float(v[1]), mu, J,
                                  tuple(m * s for m, s in zip(mu, tau, strict=True))).pack())
        lam = membrane_batch_records(np.stack(P), t.initial_state()[None, :], [self.U], self.h, self.stride,
                                     self.stride)
        return t.L_d * (lam - t.lambda_pre)


@dataclass
class Coverage:
    """Per parameter: repeats, how often the interval held the truth, how often the parameter was determined,
    and the misses of a parameter not marked determined (must be 0: such a parameter is flagged)."""

    names: list[str]
    repeats: int
    confidence: float
    determined: np.ndarray  # count per parameter
    covered: np.ndarray  # count per parameter, among the determined repeats
    unflagged_misses: int  # truth outside the interval of a parameter not marked determined
    chi2_reduced: float  # mean over the repeats

    def rate(self) -> np.ndarray:
        """Coverage of each parameter over the repeats in which it was determined."""
        rate: np.ndarray = self.covered / np.maximum(self.determined, 1)
        return rate


def coverage(free: list[str], repeats: int, sigma: float = 0.5e-6, seed: int = 0,
             confidence: float = 0.95, spread: float = 0.2) -> Coverage:
    """``repeats`` fits of simulated records (noise σ, seeds seed…seed+repeats−1), each polished from the truth
    displaced by up to ±``spread`` (relative, log-uniform) and given profile-likelihood intervals."""
    D = len(free)
    det, cov = np.zeros(D, int), np.zeros(D, int)
    unflagged, chis = 0, []
    rng = np.random.default_rng(seed + 10_000)
    for k in range(repeats):
        prob = SyntheticMembrane(free, sigma, seed + k)
        truth_phys = prob.full_truth[prob.index]
        start_phys = truth_phys * np.exp(rng.uniform(-1, 1, D) * np.log1p(spread))
        start = np.clip(to_optimiser(prob.log, start_phys), prob.lower, prob.upper)
        # a search of one generation keeps the given start as its best member; the polish and the profile do
        # the work
        settings = FitSettings(population=5, generations=1, cost="lsq", polish_iterations=50, intervals=True,
                               confidence=confidence, seed=seed + k)
        res = fit(prob, settings, start=start)
        tr = res.trust
        assert tr is not None
        chis.append(tr.chi2_reduced)
        for j in range(D):
            inside = tr.lower[j] <= truth_phys[j] <= tr.upper[j]
            if tr.status[j] == "determined":
                det[j] += 1
                cov[j] += inside
            elif not inside:
                unflagged += 1
    return Coverage(list(free), repeats, confidence, det, cov, unflagged, float(np.mean(chis)))


class Subset:
    """A view of a problem with only the parameters ``free`` fitted, the others held at ``held`` (optimiser
    coordinates, all parameters): for checks of a few parameters on a real record in seconds."""

    def __init__(self, problem: Problem, free: list[str], held: np.ndarray) -> None:
        self.problem = problem
        self.index = np.array([problem.names.index(n) for n in free])
        self.held = np.asarray(held, float)
        self.names = list(free)
        self.units = [problem.units[i] for i in self.index]
        self.lower = np.asarray(problem.lower, float)[self.index]
        self.upper = np.asarray(problem.upper, float)[self.index]
        self.log = np.asarray(problem.log, bool)[self.index]
        self.data = problem.data
        self.data_unit = problem.data_unit
        self.sigma = sigma_of(problem)
        self.records = getattr(problem, "records", None)
        self.noise_datasheet = getattr(problem, "noise_datasheet", [])

    def full(self, Z: np.ndarray) -> np.ndarray:
        """Rows of all parameters for rows of the free ones."""
        Z = np.atleast_2d(Z)
        out = np.tile(self.held, (Z.shape[0], 1))
        out[:, self.index] = Z
        return out

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """The problem's prediction with the free parameters set."""
        return self.problem.predict(self.full(Z))
