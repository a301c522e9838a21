"""Figures of recorded runs, of the papers' types (matplotlib, no display needed).

Each figure is written as PNG at 300 dpi and as PDF and SVG (vector, for publication); the PNG paths are
returned. Legends name what was measured and what was commanded.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from bench.analysis.applied import VoltageTrace, applied_voltage, measured_voltage
from bench.analysis.runs import RunAnalysis, analyse
from bench.identify.store import read_fits
from bench.storage.runfile import RunFile, open_run

DPI = 300  # publication resolution of the PNGs
VECTOR_FORMATS = ("pdf", "svg")


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    for ext in VECTOR_FORMATS:
        fig.savefig(path.with_suffix(f".{ext}"))
    plt.close(fig)
    return path


def _legend(ax: plt.Axes, *others: plt.Axes, **kwargs: object) -> None:
    """One legend on ``ax`` for the lines of ``ax`` and of its twin axes."""
    handles, labels = ax.get_legend_handles_labels()
    for other in others:
        h, lab = other.get_legend_handles_labels()
        handles, labels = handles + h, labels + lab
    ax.legend(handles, labels, **kwargs)  # type: ignore[arg-type]


def _fitted_membrane(run_path: Path) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """(t, u, fit) of the newest membrane fit, or None."""
    fits = [f for f in read_fits(run_path) if f["model"] == "membrane"]
    if not fits:
        return None
    from bench.identify.core import to_optimiser
    from bench.identify.problems import MembraneProblem

    prob = MembraneProblem([run_path], h=1e-4)
    fit = fits[-1]
    u = prob.predict(to_optimiser(prob.log, fit["values"])[None, :])[0]
    t = np.arange(u.size) * prob.records[0].stride * prob.h
    return t, u, fit


def _commanded_label(sp: VoltageTrace) -> str:
    if sp.hardware_timed:
        return "commanded voltage (DAQ output, every scan)"
    return "commanded voltage (software set-points)"


def _plot_measured_voltage(ax: plt.Axes, run: RunFile, t0: float | None = None, t1: float | None = None) -> None:
    """The amplifier's voltage monitor on the voltage axis (time from t0 when a window is given)."""
    got = measured_voltage(run)
    if got is None:
        return
    t, v = got
    if t0 is not None and t1 is not None:
        w = (t >= t0) & (t <= t1)
        t, v = t[w] - t0, v[w]
    dense = t.size > 2 and float(np.median(np.diff(t))) < 1e-2
    style = {"lw": 0.6} if dense else {"marker": ".", "ls": "none", "ms": 2}
    ax.plot(t, v / 1e3, color="tab:purple", label="measured voltage (amplifier monitor)", **style)


def thesis_figures(a: RunAnalysis, out: Path) -> list[Path]:
    """Displacement vs time and vs voltage (the thesis's Figs 4.15–4.22), with the fitted model if any."""
    run = open_run(a.path)
    laser, sp = run.streams["laser"], applied_voltage(run)
    ok = laser.columns["valid"] > 0
    t, u = laser.t[ok], laser.columns["displacement"][ok] * 1e3
    v = np.interp(t, sp.t, sp.v) / 1e3
    seen = applied_voltage(run, measured=True)  # the loop against what the specimen saw (as the analysis)
    v_loop = np.interp(t, seen.t, seen.v) / 1e3
    fitted = _fitted_membrane(a.path)
    paths = []
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, u, lw=0.8, label="measured displacement (laser)")
    if fitted is not None:
        ax.plot(fitted[0], fitted[1] * 1e3, "--", lw=1.0, label=f"fitted model (rms {fitted[2]['rms'] * 1e6:.1f} µm)")
    ax2 = ax.twinx()
    ax2.plot(t, v, color="tab:red", lw=0.6, alpha=0.6, label=_commanded_label(sp))
    _plot_measured_voltage(ax2, run)
    ax2.set_ylabel("voltage [kV]", color="tab:red")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("displacement u [mm]")
    ax.set_title(f"{a.protocol}: displacement vs time")
    _legend(ax, ax2, loc="upper left", fontsize=8)
    paths.append(_save(fig, out / "displacement_vs_time.png"))
    fig, ax = plt.subplots(figsize=(6, 5))
    for s in a.by_kind("thesis"):
        w = (t >= s.t_start) & (t <= s.t_start + s.duration)
        ax.plot(v_loop[w], u[w], lw=0.8, label=f"{s.voltage / 1e3:.0f} kV, {s.frequency:.3g} Hz, {s.temperature:g} K")
    ax.set_xlabel("measured voltage [kV]" if seen.source == "measured" else "commanded voltage [kV]")
    ax.set_ylabel("displacement u [mm]")
    ax.set_title("displacement vs voltage")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out / "displacement_vs_voltage.png"))
    return paths


def isopotential_figures(a: RunAnalysis, out: Path) -> list[Path]:
    """Force–displacement loops of the last (stabilised) cycle at each voltage, per prototype and stroke."""
    run = open_run(a.path)
    motor, lc = run.streams["motor"], run.streams["load_cell"]
    paths = []
    groups: dict[tuple, list] = {}
    for s in a.by_kind("isopotential"):
        groups.setdefault((s.prototype, round(s.figures["stroke"] * 1e3)), []).append(s)
    for (proto, stroke), steps in sorted(groups.items()):
        fig, ax = plt.subplots(figsize=(6, 5))
        for s in steps:
            t0 = s.t_start + s.duration - 1 / s.frequency
            w = (motor.t >= t0) & (motor.t <= s.t_start + s.duration)
            f = np.interp(motor.t[w], lc.t, lc.columns["force"])
            ax.plot(motor.columns["aperture"][w] * 1e3, f, lw=1.0,
                    label=f"{s.voltage / 1e3:.0f} kV: loss {100 * s.figures['loss_last']:.1f} %")
        ax.set_xlabel("aperture x [mm]")
        ax.set_ylabel("force F [N]")
        ax.set_title(f"LS-DEA #{proto}, Δx {stroke} mm, stabilised cycle")
        ax.legend(fontsize=8)
        paths.append(_save(fig, out / f"isopotential_p{proto}_dx{stroke}.png"))
    return paths


def isometric_figures(a: RunAnalysis, out: Path) -> list[Path]:
    """Force vs time at the highest frequency, and force variation vs output frequency (Fig. 7)."""
    run = open_run(a.path)
    lc, sp = run.streams["load_cell"], applied_voltage(run)
    steps = a.by_kind("isometric")
    paths = []
    top = max(steps, key=lambda s: s.frequency)
    w = (lc.t >= top.t_start) & (lc.t <= top.t_start + top.duration)
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(lc.t[w] - top.t_start, lc.columns["force"][w], lw=0.8, label="measured force (load cell)")
    ax2 = ax.twinx()
    ws = (sp.t >= top.t_start) & (sp.t <= top.t_start + top.duration)
    ax2.plot(sp.t[ws] - top.t_start, sp.v[ws] / 1e3, color="tab:red", lw=0.6, alpha=0.6,
             label=_commanded_label(sp))
    _plot_measured_voltage(ax2, run, top.t_start, top.t_start + top.duration)
    _legend(ax, ax2, loc="upper right", fontsize=8)
    ax2.set_ylabel("voltage [kV]", color="tab:red")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("force [N]")
    ax.set_title(f"isometric, LS-DEA #{top.prototype}: {top.name}")
    paths.append(_save(fig, out / "isometric_time_series.png"))
    fig, ax = plt.subplots(figsize=(6, 4))
    series: dict[tuple, list] = {}
    for s in steps:
        series.setdefault((s.prototype, round(s.figures["force_mean"], 1)), []).append(s)
    for (proto, _), ss in series.items():
        ax.plot([s.figures["output_frequency"] for s in ss], [s.figures["force_swing"] for s in ss], "o-",
                label=f"#{proto}, mean force {np.mean([s.figures['force_mean'] for s in ss]):.2f} N")
    ax.set_xlabel("force frequency [Hz]")
    ax.set_ylabel("crest-to-trough force [N]")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    ax.set_title("electrically induced force variation")
    paths.append(_save(fig, out / "isometric_force_vs_frequency.png"))
    return paths


def isotonic_figures(a: RunAnalysis, out: Path) -> list[Path]:
    """Crest-to-trough displacement vs frequency for each hung mass (Fig. 10), resonances marked."""
    fig, ax = plt.subplots(figsize=(6, 4))
    masses = sorted({s.hung_mass for s in a.by_kind("isotonic")})
    for m in masses:
        ss = [s for s in a.by_kind("isotonic") if s.hung_mass == m]
        ax.plot([s.frequency for s in ss], [s.figures["amplitude"] * 1e3 for s in ss], "o-",
                label=f"{m * 1e3:.0f} g")
    for f, amp in a.resonance().values():
        ax.annotate(f"{f:g} Hz", (f, amp * 1e3), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("voltage frequency [Hz]")
    ax.set_ylabel("crest-to-trough displacement [mm]")
    ax.set_title("isotonic response, LS-DEA #1")
    ax.legend(title="hung mass")
    return [_save(fig, out / "isotonic_amplitude_vs_frequency.png")]


def report(run_path: str | Path, out: str | Path | None = None) -> tuple[RunAnalysis, list[Path]]:
    """Analyse a run file and write its figures; returns the analysis and the PNG paths."""
    run_path = Path(run_path)
    out = Path(out) if out is not None else run_path.with_suffix("").with_name(run_path.stem + "-report")
    out.mkdir(parents=True, exist_ok=True)
    a = analyse(run_path)
    paths: list[Path] = []
    kinds = {s.kind for s in a.steps}
    if "thesis" in kinds:
        paths += thesis_figures(a, out)
    if "isopotential" in kinds:
        paths += isopotential_figures(a, out)
    if "isometric" in kinds:
        paths += isometric_figures(a, out)
    if "isotonic" in kinds:
        paths += isotonic_figures(a, out)
    (out / "figures.json").write_text(json.dumps(
        [{"step": s.name, "kind": s.kind, "prototype": s.prototype, "hung_mass": s.hung_mass,
          "temperature": s.temperature,
          "frequency": s.frequency, "voltage": s.voltage,
          **{k: (v if np.isfinite(v) else None) for k, v in s.figures.items()}} for s in a.steps], indent=1))
    return a, paths
