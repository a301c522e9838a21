"""Figures of merit of recorded runs — computed from run files only (bench.storage.runfile).

Each waveform step of a run is analysed according to what it drives and what the rig measured:

* thesis membrane, voltage waveform: per-cycle displacement peaks, creep, residual at 0 V, phase lag;
* LS-DEA, aperture waveform (isopotential): hysteresis loss of every cycle (enclosed area / loading work,
  Moretti et al. Table 3) and of the last, stabilised one;
* LS-DEA blocked, voltage waveform (isometric): crest-to-trough force variation of the last cycles;
* LS-DEA hung mass, voltage waveform (isotonic): crest-to-trough displacement of the last cycles with the
  drift removed, stroke as % of the link length, energy density per unit DE mass with and without the
  mechanism's weight; across frequencies, the resonance.

The step parameters (channel, frequency, voltage) come from the protocol text stored in the file. The file is opened
once (:func:`bench.storage.chunks.open_source`) and each step reads only its own time window (or its last cycles),
so memory follows the longest step, never the record's length.
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.analysis.applied import applied_window
from bench.analysis.cycles import crest_to_trough, hysteresis_loss, phase_lag, smooth
from bench.analysis.thesis import NO_DRIVE_V, cycle_figures, no_drive_v_of, undriven, undriven_note
from bench.models.lozenge import LozengeParams
from bench.protocol.schema import Protocol, WaveformStep, load_protocol
from bench.storage.chunks import RunSource, StreamChunks, open_source
from bench.storage.runfile import RunFile, refuse_manual_session, refuse_nonfinite

PAPER_GRAVITY = 9.81  # m/s²: the value behind the paper's loads (3.1 / 4.6 / 4.9 N), not standard gravity
TOL_S = 1e-9  # a window's bounds are widened by this much (step times are sums of floats)
# a waveform step that ended this much after its planned end (the larger of the two) was stretched, not played at
# its frequency: said above its figures (a ramp's end value sent at its end makes a step some ms late: no stretch)
STRETCH_S, STRETCH_FRACTION = 0.05, 0.01
# a step whose end event the file holds ended in it: its window, from its DAQ stream's scan 0, may reach past the
# file's last update by the scan grid's rounding (a scan or so), never by a tail of scans not yet on file (a reviewer)
START_SLACK_S = 1e-3
SKIPPED = re.compile(r"(\d+) of (\d+) set-points skipped")  # the engine's `skipped` event
LATE = re.compile(r"ended (\d+(?:\.\d+)?) s after its scheduled end")  # the engine's `late` event


@dataclass
class StepResult:
    """Figures of one analysed step (SI units; ``kind`` says which figures are present)."""

    index: int
    name: str
    kind: str  # "thesis" | "isopotential" | "isometric" | "isotonic"
    t_start: float
    duration: float
    frequency: float
    voltage: float  # peak |V| commanded during the step [V]
    prototype: int | None = None
    hung_mass: float | None = None
    temperature: float | None = None  # membrane: specimen temperature during the step [K]
    figures: dict[str, float] = field(default_factory=dict)
    series: dict[str, list[float]] = field(default_factory=dict)
    no_drive_v: float = NO_DRIVE_V  # its run's monitor 0-V band [V]: a peak |V| within it is no drive


@dataclass
class RunAnalysis:
    """All analysed steps of one run file."""

    path: Path
    protocol: str
    specimen: str  # "membrane" | "lsdea"
    configuration: str
    steps: list[StepResult]
    run: RunFile  # the file's metadata, events and program as read (no streams)
    notes: list[str] = field(default_factory=list)  # steps not analysed, and why (one line each)
    no_drive_v: float = NO_DRIVE_V  # the run's monitor 0-V band [V] (its rig's chain; the widest where unknown)

    def by_kind(self, kind: str) -> list[StepResult]:
        """Steps of one kind, in run order."""
        return [s for s in self.steps if s.kind == kind]

    def resonance(self) -> dict[float, tuple[float, float]]:
        """Isotonic: per hung mass, (frequency of the largest amplitude [Hz], that amplitude [m]) — the sweep's
        peak: the resonance where the sweep brackets f_n, else an edge or the f_n/2 bump that V²'s 2f content
        excites (physics.md §2.4: 3.25 Hz at m = 0, whose f_n lies above the paper's 1–4 Hz)."""
        out: dict[float, tuple[float, float]] = {}
        for s in self.by_kind("isotonic"):
            amp = s.figures["amplitude"]
            if not np.isfinite(amp):
                continue
            m = s.hung_mass or 0.0
            if m not in out or amp > out[m][1]:
                out[m] = (s.frequency, amp)
        return out


def _vf_lag(streams: StreamChunks, t: np.ndarray, force: np.ndarray, f_out: float) -> float:
    """Time [s] by which the force's troughs lag the voltage's maxima (Fig. 7A: the force falls as V²), measured
    at the output frequency on the recorded voltage; NaN where the monitors were sampled too slowly for it (fewer
    than 20 samples per output period)."""
    if streams.length.get("amplifier", 0) < 2 or t.size < 20:
        return float("nan")
    amp = _window(streams, "amplifier", float(t[0]), float(t[-1]), ["voltage"])
    if amp["t"].size < 20 * f_out * (t[-1] - t[0]):
        return float("nan")
    v = np.interp(t, amp["t"], amp["voltage"])
    return phase_lag(t, v**2, -np.asarray(force, dtype=float), f_out)


def protocol_of(run: RunFile) -> Protocol:
    """The protocol stored in the run file, parsed again (its rig path is not needed)."""
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "protocol.toml"
        p.write_text(run.attrs["protocol_text"], encoding="utf-8")
        return load_protocol(p)


# the unit of each column the analysis reads, as bench records it (README "Run files")
ANALYSED_UNITS = {"displacement": "m", "aperture": "m", "position": "m", "force": "N", "voltage": "V",
                  "current": "A"}


def _window(streams: StreamChunks, stream: str, t0: float, t1: float, columns: list[str],
            neighbours: bool = False) -> dict[str, np.ndarray]:
    """A stream's records over [t0, t1] (bounds widened by ``TOL_S``), read alone from the file. ValueError (one
    line) when the file has no such stream, or no finite value of the columns in the window: nothing to analyse."""
    try:
        out = streams.window(stream, t0 - TOL_S, t1 + TOL_S, columns, neighbours=neighbours)
        units = streams.units(stream)
    except KeyError:
        raise ValueError(f"run file {streams.f.filename}: no {stream!r} stream, which this step's analysis needs "
                         f"({t0:.3f}–{t1:.3f} s)") from None
    for name in columns:  # the figures are computed in SI units: a column in another unit would be misread
        want = ANALYSED_UNITS.get(name)
        if want is not None and units.get(name) != want:
            raise ValueError(f"run file {streams.f.filename}: {stream}/{name} is in {units.get(name)!r}, the "
                             f"analysis reads {want!r}")
    for name in columns:
        refuse_nonfinite(streams.f.filename, stream, name, out["t"], out[name])
        if not np.isfinite(out[name]).any():
            raise ValueError(f"run file {streams.f.filename}: no valid {stream} {name} between {t0:.3f} and {t1:.3f} s "
                             "(the sensor read out of range or invalid throughout): nothing to analyse")
    return out


def _inside(t: np.ndarray, t0: float, t1: float) -> np.ndarray:
    return (t >= t0 - TOL_S) & (t <= t1 + TOL_S)


def _specimen_at(run: RunFile, t: float, spec: dict[str, Any]) -> tuple[int, float]:
    """LS-DEA prototype and hung mass at run time ``t`` (:meth:`RunFile.specimen_at`)."""
    over = spec.get("overrides", {})
    lsdea = spec.get("lsdea", {})
    proto = over.get("prototype") or lsdea.get("prototype", 1)
    mass = over.get("hung_mass_kg")
    mass = lsdea.get("hung_mass_kg", 0.0) if mass is None else mass
    changed = run.specimen_at(t)
    return int(changed.get("prototype", proto)), float(changed.get("hung_mass_kg", mass))


def analyse(path: str | Path, last_cycles: int = 3) -> RunAnalysis:
    """Analyse every waveform step of a run file (opened once, read a step window at a time)."""
    with open_source(path) as src:
        return analyse_source(src, last_cycles)


def analyse_source(src: RunSource, last_cycles: int = 3) -> RunAnalysis:
    """:func:`analyse` on a run file already open."""
    run, streams = src.run, src.streams
    refuse_manual_session(run, "no protocol steps to report")  # its protocol text is an empty program
    protocol = protocol_of(run)
    spec = run.specimen()
    kind_of_specimen = spec["kind"]
    config = spec.get("lsdea", {}).get("configuration", "membrane") if kind_of_specimen == "lsdea" else "membrane"
    results: list[StepResult] = []
    notes: list[str] = []
    band = no_drive_v_of(run.attrs)  # the run's own monitor chain: a T7 rig's 0-V band is narrower than an ADAM's
    done, began = run.completed_steps(), run.step_starts()
    offsets, scheduled = run.step_offset_clocks()  # the DAQ's drive, the host's go-tos
    late = {step: float(m[1]) for _, step, kind, text in run.event_list()
            if kind == "late" and (m := LATE.search(text)) is not None}  # each step's own lateness [s]
    skipped: dict[int, tuple[int, int]] = {}  # each step's set-points (skipped, planned) behind its schedule
    for _, at_step, kind, text in run.event_list():
        if kind == "start":  # a step restarted (after a pause, a drain at 0 V): its last attempt's skips only
            skipped.pop(at_step, None)
        elif kind == "skipped" and (m := SKIPPED.search(text)) is not None:
            was = skipped.get(at_step, (0, 0))
            skipped[at_step] = (was[0] + int(m[1]), was[1] + int(m[2]))
    for row, step in zip(run.program, protocol.steps, strict=True):
        if not isinstance(step, WaveformStep):
            continue
        index = int(row["index"])
        said = f"step {index + 1} of {run.program.shape[0]} (index {index}, {row['name'].decode()})"  # notes' words
        # a voltage step's cycles from where the DAQ began to play it; a position step's from the host's schedule,
        # on which the motor's go-tos go out (a reviewer: the scan clock cut them 50–110 ms late)
        shift = (scheduled if step.channel == "position" else offsets).get(index, 0.0)
        t0, dur = float(row["t_start"]) + shift, float(row["duration"])
        if index not in done or t0 + dur > run.updated + START_SLACK_S:
            continue  # the run stopped (or paused, or resumed later in another file) before this step ended
        behind = late.get(index, 0.0)
        if behind > max(STRETCH_S, STRETCH_FRACTION * dur):  # its actions outran the schedule (its `late` event)
            notes.append(f"{said} ended {behind:.3f} s after its planned end: its waveform was played slower than "
                         f"the protocol's {step.frequency_Hz:g} Hz; its figures below read its planned window at that "
                         "frequency")
        if (n := skipped.get(index, (0, 0)))[0]:
            notes.append(f"{said}: {n[0]} of its {n[1]} set-points skipped behind the schedule, so its drive was "
                         f"sampled at {(n[1] - n[0]) / dur:.3g} set-points/s, not the protocol's {n[1] / dur:.3g}; its "
                         "figures are of that drive")
        sp = applied_window(streams, t0 - TOL_S, t0 + dur + TOL_S, measured=True)
        sel = _inside(sp.t, t0, t0 + dur)
        vpk = float(np.max(np.abs(sp.v[sel]))) if sel.any() else 0.0
        # the specimen as the step found it: the changes logged up to its recorded start (a set step before it
        # logs its change after the program time this step starts at: the program does not wait for it)
        at = max(t0, began.get(index, t0))
        proto, mass = _specimen_at(run, at, spec)
        res = StepResult(int(row["index"]), row["name"].decode(), "", t0, dur, step.frequency_Hz, vpk,
                         proto if kind_of_specimen == "lsdea" else None, mass if config == "hung" else None,
                         no_drive_v=band)
        if kind_of_specimen == "membrane":
            res.temperature = float(run.temperature_at(at))
            _thesis(res, streams, sp.t, sp.v)
            if undriven(vpk, band):
                notes.append(undriven_note(said, vpk, band))
        elif whole_cycles(dur, step.frequency_Hz) == 0:  # the LS-DEA's figures are per whole cycle
            notes.append(f"{said} plays {dur * step.frequency_Hz:g} cycles, less than one whole: no figures")
            continue
        elif step.channel == "position":
            _isopotential(res, streams)
        elif config == "hung":
            _isotonic(res, streams, last_cycles, proto, mass)
        else:
            _isometric(res, streams, last_cycles, 2 * step.frequency_Hz if step.kind == "sine" else step.frequency_Hz)
        results.append(res)
    return RunAnalysis(run.path, run.attrs["protocol_name"], kind_of_specimen, config, results, run, notes, band)


def whole_cycles(duration: float, frequency: float) -> int:
    """Whole periods in a step (a 1.5-cycle waveform has one: the half cycle has no loading branch of its own)."""
    return int(np.floor(duration * frequency + 1e-6))


def _thesis(res: StepResult, streams: StreamChunks, t_v: np.ndarray, v: np.ndarray) -> None:
    """Membrane: per-cycle peaks, creep, lag and residuals of the step's laser record against the voltage seen."""
    t0, dur, f = res.t_start, res.duration, res.frequency
    laser = _window(streams, "laser", t0, t0 + dur, ["displacement"])
    volts = np.interp(laser["t"], t_v, v)
    figs = cycle_figures(laser["t"] - t0, laser["displacement"], volts, f, span=(0.0, dur))
    if not figs.peaks:
        raise ValueError(f"run file {streams.f.filename}: no cycle of step {res.index} ({res.name}) has a laser "
                         f"record to analyse ({t0:.3f}–{t0 + dur:.3f} s)")
    res.kind = "thesis"
    res.figures = {"peak_first": figs.peaks[0], "peak_last": figs.peaks[max(figs.whole, 1) - 1],
                   "creep": figs.creep if figs.whole >= 2 else np.nan, "lag_first": figs.lags[0],
                   "residual_first": figs.residuals[0] if figs.residuals else np.nan,
                   "residual_last": figs.residuals[-1] if figs.residuals else np.nan}
    res.series = {"peaks": list(figs.peaks), "residuals": list(figs.residuals), "lags": list(figs.lags)}
    # no drive: its "peak" is monitor noise, and the response's creep is not to a drive
    if undriven(res.voltage, res.no_drive_v):
        res.figures["lag_first"] = res.figures["creep"] = np.nan
        res.series["lags"] = [np.nan] * len(figs.lags)


def _isopotential(res: StepResult, streams: StreamChunks) -> None:
    """Imposed aperture: hysteresis loss of every cycle, stroke and force extremes of the last one."""
    t0, dur, f = res.t_start, res.duration, res.frequency
    motor = _window(streams, "motor", t0, t0 + dur, ["aperture"])
    lc = _window(streams, "load_cell", t0, t0 + dur, ["force"], neighbours=True)  # interpolated as on the whole
    x, tt = motor["aperture"], motor["t"]
    force = np.interp(tt, lc["t"], lc["force"])
    n_cyc = whole_cycles(dur, f)
    losses = []
    for k in range(n_cyc):
        c = (tt >= t0 + k / f - 1e-9) & (tt <= t0 + (k + 1) / f + 1e-9)
        losses.append(hysteresis_loss(x[c], force[c]))
    res.kind = "isopotential"
    last = (tt >= t0 + (n_cyc - 1) / f - 1e-9)
    fs = smooth(tt[last], force[last], 0.02 / f)  # extremes of the force, not of its noise
    res.figures = {"loss_last": losses[-1], "loss_first": losses[0],
                   "stroke": float(np.ptp(x[last])), "force_max": float(np.max(fs)),
                   "force_min": float(np.min(fs))}
    res.series = {"loss_per_cycle": losses}


def _isotonic(res: StepResult, streams: StreamChunks, last_cycles: int, proto: int, mass: float) -> None:
    """Hung mass: crest-to-trough displacement of the last cycles, stroke, energy density."""
    t0, dur, f = res.t_start, res.duration, res.frequency
    t_tail = t0 + dur - min(last_cycles, whole_cycles(dur, f)) / f
    laser = _window(streams, "laser", t_tail, t0 + dur, ["displacement", "valid"])
    ok = laser["valid"] > 0
    t, u = laser["t"][ok], laser["displacement"][ok]
    res.kind = "isotonic"
    if ok.sum() < 10:  # laser over range or invalid throughout: nothing to measure
        res.figures = {"amplitude": np.nan, "stroke_percent": np.nan, "energy_density": np.nan,
                       "energy_density_with_mechanism": np.nan, "mean_position": np.nan}
        return
    amp = crest_to_trough(t, u, f)
    params = LozengeParams.prototype(proto, hung_mass=mass)
    de_mass = params.membrane_mass
    work = mass * PAPER_GRAVITY * amp
    work_total = (mass + 0.5 * params.mechanism_mass) * PAPER_GRAVITY * amp
    res.figures = {"amplitude": amp, "stroke_percent": 100 * amp / params.l,
                   "energy_density": work / de_mass,  # J/kg = mJ/g
                   "energy_density_with_mechanism": work_total / de_mass,
                   "mean_position": float(np.mean(u))}


def _isometric(res: StepResult, streams: StreamChunks, last_cycles: int, f_out: float) -> None:
    """Blocked: crest-to-trough force of the last cycles at the output frequency, its mean, the V–F lag."""
    t0, dur, f = res.t_start, res.duration, res.frequency
    t_tail = t0 + dur - min(last_cycles, whole_cycles(dur, f)) / f
    lc = _window(streams, "load_cell", t_tail, t0 + dur, ["force"])
    res.kind = "isometric"
    res.figures = {"force_swing": crest_to_trough(lc["t"], lc["force"], f_out),
                   "force_mean": float(np.mean(lc["force"])),
                   "output_frequency": f_out, "vf_lag": _vf_lag(streams, lc["t"], lc["force"], f_out)}


def step_records(a: RunAnalysis) -> list[dict[str, Any]]:
    """The figures of merit of each step as plain records (``figures.json``; NaN as None)."""
    return [{"step": s.name, "kind": s.kind, "prototype": s.prototype, "hung_mass": s.hung_mass,
             "temperature": s.temperature, "frequency": s.frequency, "voltage": s.voltage,
             **{k: (v if np.isfinite(v) else None) for k, v in s.figures.items()}} for s in a.steps]
