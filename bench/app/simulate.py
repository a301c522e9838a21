"""Use cases of the offline models: the thesis membrane under a periodic voltage, the LS-DEA in one of the paper's
three test configurations (``bench simulate thesis|lsdea``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, TypeVar

if TYPE_CHECKING:
    from bench.analysis.thesis import CycleFigures
    from bench.models.lozenge_runs import LozengeTrace
    from bench.models.membrane import MembraneParams, MembraneTrace

SIMULATE_MAX_S = 600.0  # simulated time (the offline solver keeps 10 kHz output in memory)
SIMULATE_MAX_CYCLES = 200  # thesis: drive cycles (the solver's cost grows with them: ~20 ms each)
SIMULATE_MAX_SQUARE_CYCLES = 5  # the offline solver resolves every square-wave edge: 0.2–1.4 s per cycle
Method = Literal["rodas", "radau", "fixed"]
METHODS: tuple[Method, ...] = ("rodas", "radau", "fixed")
Choice = TypeVar("Choice", bound=str)


def one_of(value: str, options: tuple[Choice, ...], what: str) -> Choice:
    """``value`` as the one of ``options`` it equals; ValueError (one line) naming ``what`` otherwise."""
    for option in options:
        if value == option:
            return option
    raise ValueError(f"{what} must be one of {', '.join(options)}, got {value!r}")


def check_simulation_size(duration: float) -> None:
    """Refuse, in one line, a simulation beyond the documented size (it would take minutes and gigabytes)."""
    if not duration <= SIMULATE_MAX_S:
        raise ValueError(f"simulated time {duration:g} s exceeds {SIMULATE_MAX_S:g} s: fewer --cycles or a "
                         "higher --frequency")


@dataclass
class ThesisSimulation:
    """The thesis membrane's trace, its per-cycle figures and the headline numbers."""

    params: MembraneParams
    trace: MembraneTrace
    figures: CycleFigures
    creep: float  # [%] (NaN without drive or with under two whole cycles)
    max_displacement: float  # [m]
    max_stretch: float
    peak_field: float  # [V/m], over the valid samples
    peak_current: float  # [A]


def simulate_thesis(voltage: float, frequency: float, temperature: float, duration: float,
                    waveform: str = "raised_cosine", electrostriction: str = "corrected",
                    method: str = "rodas") -> ThesisSimulation:
    """Thesis membrane (Model A) under a periodic voltage [V] at ``frequency`` [Hz], ``temperature`` [K], for
    ``duration`` [s]. ValueError (one line) for an unknown method, waveform or form of electrostriction, or too
    many cycles."""
    solver = one_of(method, METHODS, "--method")
    max_cycles = SIMULATE_MAX_SQUARE_CYCLES if waveform == "square" and method != "fixed" else SIMULATE_MAX_CYCLES
    if frequency * duration > max_cycles:
        raise ValueError(f"--frequency {frequency:g} Hz × --duration {duration:g} s = {frequency * duration:g} cycles "
                         f"exceed {max_cycles} for this waveform and method: shorten the run")
    import numpy as np

    from bench.analysis.thesis import cycle_figures
    from bench.models.membrane import ELECTROSTRICTIONS, MembraneParams
    from bench.models.membrane_runs import simulate_membrane
    from bench.waveforms import WAVE_KINDS, Waveform

    params = MembraneParams(electrostriction=one_of(electrostriction, ELECTROSTRICTIONS, "electrostriction"))
    tr = simulate_membrane(params, Waveform(one_of(waveform, WAVE_KINDS, "waveform"), voltage, frequency), duration,
                           T=temperature, method=solver)
    figs = cycle_figures(tr.t, tr.displacement, tr.voltage, frequency)
    valid = np.isfinite(tr.stretch)
    # one whole cycle (or none driven) has no creep: NaN, shown "–" as the report shows it (it printed "+0.0 %")
    creep = figs.creep * 100 if figs.whole > 1 and figs.peaks[0] != 0 else math.nan
    return ThesisSimulation(params, tr, figs, float(creep), float(np.nanmax(tr.displacement)),
                            float(np.nanmax(tr.stretch)), float(np.nanmax(np.abs(tr.field[valid]))),
                            float(np.nanmax(np.abs(tr.current[valid]))))


LsdeaTest = Literal["isopotential", "isometric", "isotonic"]
LSDEA_TESTS: tuple[LsdeaTest, ...] = ("isopotential", "isometric", "isotonic")


@dataclass
class LsdeaSimulation:
    """The LS-DEA's trace, its figure of merit (by test) and the headline numbers."""

    test: str
    trace: LozengeTrace
    figure: dict[str, float]  # isopotential: loss; isometric: force_swing [N]; isotonic: swing, mean_position [m]
    force_range: tuple[float, float]  # [N]
    peak_field: float  # [V/m]
    margin: float  # the smallest breakdown margin E_B/E
    tension_lost: float  # fraction of samples


def simulate_lsdea(test: str, prototype: int, voltage: float, *, frequency: float | None = None,
                   mass: float = 0.18, position: float = 0.1, stroke: float = 0.09,
                   cycles: int = 10) -> LsdeaSimulation:
    """LS-DEA (Model B) prototype ``prototype`` in one test configuration: ``voltage`` [V] constant
    (isopotential), sine amplitude (isometric) or raised-cosine peak (isotonic); ``mass`` [kg] hung (isotonic),
    ``position`` [m] blocked (isometric), ``stroke`` [m] imposed from 50 mm (isopotential)."""
    import numpy as np

    from bench.analysis.cycles import crest_to_trough, hysteresis_loss, last_cycles
    from bench.models.lozenge import LozengeParams
    from bench.models.lozenge_runs import simulate_lozenge
    from bench.waveforms import Waveform

    test = one_of(test, LSDEA_TESTS, "test")
    params = LozengeParams.prototype(prototype, hung_mass=mass if test == "isotonic" else 0.0)
    f = (0.5 if test == "isopotential" else 1.0) if frequency is None else frequency
    duration = cycles / f
    check_simulation_size(duration)
    if test == "isopotential":
        dx, w = stroke, 2 * np.pi * f
        tr = simulate_lozenge(params, "imposed", lambda t: np.full_like(t, voltage), duration,
                              position=lambda t: 0.05 + dx / 2 * (1 - np.cos(w * t)),
                              velocity=lambda t: dx / 2 * w * np.sin(w * t))
        m = last_cycles(tr.t, f, 1)
        figure = {"loss": float(hysteresis_loss(tr.position[m], tr.force[m]))}
    elif test == "isometric":
        tr = simulate_lozenge(params, "blocked", Waveform("sine", voltage, f), duration, position=position)
        m = last_cycles(tr.t, f, 1)
        figure = {"force_swing": float(crest_to_trough(tr.t[m], tr.force[m]))}
    else:
        tr = simulate_lozenge(params, "hung", Waveform("raised_cosine", voltage, f), duration)
        m = last_cycles(tr.t, f, min(3, cycles))
        figure = {"swing": float(crest_to_trough(tr.t[m], tr.position[m], f)),
                  "mean_position": float(np.mean(tr.position[m]))}
    with np.errstate(divide="ignore"):
        margin = float(np.nanmin(tr.breakdown_field / np.abs(tr.field)))
    return LsdeaSimulation(test, tr, figure, (float(np.nanmin(tr.force)), float(np.nanmax(tr.force))),
                           float(np.nanmax(np.abs(tr.field))), margin, float(np.mean(tr.tension_lost)))
