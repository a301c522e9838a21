"""Speed benchmarks of the physics integrators (``bench benchmark``).

Each figure is simulated time divided by wall time ("× real time"), best of ``repeats`` runs, one core
(numba threads are limited to 1 for the single-core figures).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from bench.benchmarks import best_of
from bench.models.lozenge import LozengeParams
from bench.models.lozenge_runs import LozengeStream, simulate_lozenge
from bench.models.membrane import MembraneParams
from bench.models.membrane_runs import MembraneStream, integrate_membrane, simulate_membrane
from bench.waveforms import Waveform

OFFLINE_RATIO_TARGET = 5.0  # issue 13: compiled offline path ≥ 5× scipy Radau at max|Δλ| ≤ 1e-6


@dataclass(frozen=True)
class BenchResult:
    """One benchmark figure: name, simulated seconds, best wall seconds, target multiple (0 = none)."""

    name: str
    simulated: float
    wall: float
    target: float = 0.0

    @property
    def speed(self) -> float:
        """Multiple of real time."""
        return self.simulated / self.wall

    @property
    def passed(self) -> bool:
        """Whether the target (if any) is met."""
        return self.speed >= self.target


def thesis_offline(repeats: int = 5) -> list[BenchResult]:
    """Thesis base case (7 kV, 1/9 Hz, 296 K, 20 s), states at 10 kHz: the compiled Rosenbrock integrator
    (default of ``simulate_membrane``) against the reference-style scipy Radau with analytic Jacobian, in the
    same run, each with its max|Δλ| against a tight reference (Radau, rtol 1e-10); then the whole
    ``simulate_membrane`` (integration plus the observables both paths share)."""
    p, w = MembraneParams(), Waveform("raised_cosine", 7000.0, 1 / 9)
    t = np.arange(200_001) / 10_000.0
    ref = integrate_membrane(p, w, t, method="radau", rtol=1e-10)[0][:, 0]
    err_new = float(np.max(np.abs(integrate_membrane(p, w, t)[0][:, 0] - ref)))
    err_old = float(np.max(np.abs(integrate_membrane(p, w, t, method="radau")[0][:, 0] - ref)))
    wall_new = best_of(lambda: integrate_membrane(p, w, t), repeats)
    wall_old = best_of(lambda: integrate_membrane(p, w, t, method="radau"), repeats)
    ratio = wall_old / wall_new
    verdict = "ok" if ratio >= OFFLINE_RATIO_TARGET and err_new <= 1e-6 else "BELOW TARGET"
    sim_new = best_of(lambda: simulate_membrane(p, w, 20.0, fs=10_000.0), repeats)
    sim_old = best_of(lambda: simulate_membrane(p, w, 20.0, fs=10_000.0, method="radau"), repeats)
    return [BenchResult(f"thesis base case, offline integrator: compiled Rodas3, states at 10 kHz, max|Δλ| "
                        f"{err_new:.1e}; {ratio:.1f}× the Radau path (target ≥ {OFFLINE_RATIO_TARGET:g}× at "
                        f"≤ 1e-6: {verdict})", 20.0, wall_new),
            BenchResult(f"  same, scipy Radau + analytic Jacobian (rtol 1e-6), max|Δλ| {err_old:.1e}", 20.0, wall_old),
            BenchResult(f"thesis base case, simulate_membrane with all observables (Rodas3; {sim_old / sim_new:.1f}× "
                        "the same with Radau)", 20.0, sim_new, 500.0),
            BenchResult("  same with Radau", 20.0, sim_old)]


def thesis_streaming(repeats: int = 3) -> BenchResult:
    """Same run stepped one sample at a time from Python (the simulated rig's path), h = 1e-4 s."""
    p = MembraneParams()
    phi = Waveform("raised_cosine", 7000.0, 1 / 9)(np.arange(1, 200_001) * 1e-4).tolist()

    def run(n: int | None = None) -> None:  # n: the first n samples only (the warm-up)
        s = MembraneStream(p, h=1e-4)
        step = s.step
        for v in phi if n is None else phi[:n]:
            step(v)

    return BenchResult("thesis base case, streaming (one call per 100 µs sample)", 20.0,
                       best_of(run, repeats, lambda: run(10)), 100.0)


def thesis_streaming_block(repeats: int = 5) -> BenchResult:
    """Same run advanced in blocks of 1000 samples (0.1 s) with full observables per block."""
    p = MembraneParams()
    phi = Waveform("raised_cosine", 7000.0, 1 / 9)(np.arange(1, 200_001) * 1e-4).reshape(-1, 1000)

    def run(n: int | None = None) -> None:  # n: the first n blocks only (the warm-up)
        s = MembraneStream(p, h=1e-4)
        for block in phi[:n]:  # a view
            s.advance(block)

    return BenchResult("thesis base case, streaming in 0.1-s blocks", 20.0, best_of(run, repeats, lambda: run(1)))


def lsdea_isotonic_streaming(repeats: int = 3) -> BenchResult:
    """LS-DEA #1, 180 g, 5 kV raised cosine at 2.75 Hz, 15 s stepped one sample at a time (h = 1e-4 s)."""
    p = LozengeParams(hung_mass=0.18)
    V = Waveform("raised_cosine", 5000.0, 2.75)(np.arange(1, 150_001) * 1e-4).tolist()

    def run(n: int | None = None) -> None:  # n: the first n samples only (the warm-up)
        s = LozengeStream(p, "hung")
        step = s.step
        for v in V if n is None else V[:n]:
            step(v)

    return BenchResult("LS-DEA isotonic, streaming (one call per 100 µs sample)", 15.0,
                       best_of(run, repeats, lambda: run(10)), 100.0)


def lsdea_isopotential_offline(repeats: int = 3) -> BenchResult:
    """LS-DEA #1, 7 kV, 50↔140 mm at 0.5 Hz, 10 cycles (20 s), compiled fixed-step loop, 10 kHz output."""
    p = LozengeParams.prototype(1)

    def pos(t: np.ndarray) -> np.ndarray:
        return 0.095 - 0.045 * np.cos(np.pi * t)

    def vel(t: np.ndarray) -> np.ndarray:
        return 0.045 * np.pi * np.sin(np.pi * t)

    def volts(t: np.ndarray) -> np.ndarray:
        return np.full_like(t, 7000.0)

    def run(seconds: float) -> None:
        simulate_lozenge(p, "imposed", volts, seconds, position=pos, velocity=vel)

    wall = best_of(lambda: run(20.0), repeats, lambda: run(0.1))
    return BenchResult("LS-DEA isopotential 20 s, fixed-step block (10 kHz output)", 20.0, wall)


ALL: tuple[Callable[..., BenchResult | list[BenchResult]], ...] = (
    thesis_offline, thesis_streaming, thesis_streaming_block, lsdea_isotonic_streaming, lsdea_isopotential_offline)


def run_all(quick: bool = False) -> list[BenchResult]:
    """Run every benchmark on one thread (``quick``: one repeat each)."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        out: list[BenchResult] = []
        for fn in ALL:
            r = fn(1) if quick else fn()
            out += r if isinstance(r, list) else [r]
        return out
    finally:
        numba.set_num_threads(threads)
