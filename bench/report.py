"""Figures of recorded runs, of the papers' types (matplotlib, no display needed).

Each figure is written as PNG at 300 dpi and as PDF and SVG (vector, for publication); the PNG paths are
returned. Legends name what was measured and what was commanded and sit outside the axes (above or to the
right), never on the data; a fitted model is drawn over the record's time span only, with a residual panel
(model − record, its rms in the panel's title) under it; the commanded voltage is drawn dashed on top of the
measured one (solid, another colour), and the right axis is coloured as its curves; hysteresis loops carry
arrows in the direction they are traversed. :func:`table3_figure` draws the Table-3 grid of a campaign.

The run file is opened once (:func:`bench.storage.chunks.open_source`) and read in windows: a figure over the whole
run draws each curve reduced to the minimum and maximum of each of ``PIXELS`` spans (every extreme kept, as
``bench plot``); a step's figure reads that step's records; the loops of a figure share ``LOOP_POINTS`` points.
"""

from __future__ import annotations

import json
import math
import re
import textwrap
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from bench.analysis.applied import VoltageTrace, applied_window, hardware_timed
from bench.analysis.quicklook import PIXELS
from bench.analysis.runs import RunAnalysis, analyse_source, step_records
from bench.identify.store import read_fits
from bench.storage.chunks import RunSource, StreamChunks, open_source
from bench.storage.outputs import atomic_output, claim_folder, write_text
from bench.storage.recorder import cause

DPI = 300  # publication resolution of the PNGs
VECTOR_FORMATS = ("pdf", "svg")
MEASURED_V = "tab:red"  # the amplifier monitor: solid, under the command; the right axis takes its colour
COMMANDED_V = "#4d0000"  # the command: a dark red, dashed, drawn on top (visible where the two coincide)
ARROWS_PER_LOOP = 3
AGG_CHUNK = 500  # vertices of a line rasterised at a time (matplotlib's agg.path.chunksize)
LOOP_POINTS = 200_000  # points of all the loops of one figure together (each loop every k-th sample beyond)


def save_figure(fig: Figure, path: Path, close: bool = True) -> Path:
    """Write ``fig`` as PNG (``path``) and as PDF and SVG beside it, each moved into place whole; the layout is the
    figure's (constrained). Long lines are rasterised ``AGG_CHUNK`` vertices at a time: a whole-run curve reduced
    to min/max pairs zigzags over the axes' height, and Agg would otherwise hold a cell for every pixel it crosses
    at once."""
    try:
        with matplotlib.rc_context({"agg.path.chunksize": AGG_CHUNK}):
            with atomic_output(path, replace=True) as tmp:  # whole or not at all (the format: its suffix)
                fig.savefig(tmp, dpi=DPI)
            for ext in VECTOR_FORMATS:
                with atomic_output(path.with_suffix(f".{ext}"), replace=True) as tmp:
                    fig.savefig(tmp)
    finally:
        if close:
            plt.close(fig)
    return path


def _figure(**kwargs: Any) -> tuple[Figure, Any]:
    fig, axes = plt.subplots(layout="constrained", **kwargs)
    return fig, axes


def _legend_outside(fig: Figure, axes: list[Axes], where: str = "upper", fontsize: float = 8) -> None:
    """One legend for the lines of ``axes`` (twins included), outside the axes: above them or to the right."""
    handles: list[Any] = []
    labels: list[str] = []
    for ax in axes:
        h, lab = ax.get_legend_handles_labels()
        handles, labels = handles + h, labels + lab
    if not handles:
        return
    if where == "upper":
        fig.legend(handles, labels, loc="outside upper center", ncol=2, fontsize=fontsize)
    else:
        fig.legend(handles, labels, loc="outside right upper", fontsize=fontsize)


@contextmanager
def _opened(path: Path, src: RunSource | None) -> Iterator[RunSource]:
    """The run file the report has open, or (a figure drawn on its own) the file opened for it."""
    if src is not None:
        yield src
    else:
        with open_source(path) as own:
            yield own


def _peak_voltage(streams: StreamChunks) -> float:
    """max |V| of the voltage the specimen saw (:func:`bench.analysis.applied.applied_voltage`, measured) over the
    whole run, a chunk at a time (NaN propagates, as ``np.max`` does)."""
    peaks = [float(np.max(np.abs(c["voltage"][np.isfinite(c["voltage"])]), initial=-np.inf))
             for c in streams.chunks("setpoints")]
    if hardware_timed(streams):
        peaks += [float(np.max(np.abs(c["voltage"]))) for c in streams.chunks("amplifier")]
    return float(np.max(peaks)) if peaks else float("nan")


def _record_starts(prob: Any, streams: StreamChunks) -> list[float]:
    """Start time [s] of each record of a membrane problem: 0 for a whole file; for a file cut at its rests, the
    window named in the record's source (to 0.1 s), snapped to the set-point where the drive resumes there (the
    problem's rule: a rest is a set-point below 1 % of the peak). Only the 0.05 s around each start is read."""
    if len(prob.records) == 1:
        return [0.0]
    peak = _peak_voltage(streams)
    starts = []
    for r in prob.records:
        m = re.search(r"\[([-+0-9.e]+), [-+0-9.e]+\] s$", r.source)
        a = float(m.group(1)) if m else 0.0
        if a > 0:
            sp = applied_window(streams, a - 0.052, a + 0.052, measured=True)  # with the sample before
            quiet = np.abs(sp.v) <= 0.01 * peak
            resumes = sp.t[1:][quiet[:-1] & ~quiet[1:]]
            if resumes.size:
                near = resumes[np.argmin(np.abs(resumes - a))]
                a = float(near) if abs(near - a) <= 0.051 else a
        starts.append(a)
    return starts


def fitted_membrane(run_path: Path, src: RunSource | None = None) -> dict[str, Any] | None:
    """The newest membrane fit of a run on the record's sample grid: ``t`` [s], ``model`` and ``record`` [m]
    (window means, NaN where the laser has no valid samples), the stored ``fit``; None without a fit. Points
    outside the laser record are left out (the model is not drawn past the record)."""
    fits = [f for f in read_fits(run_path) if f["model"] == "membrane"]
    if not fits:
        return None
    from bench.identify.core import to_optimiser
    from bench.identify.problems import MembraneProblem

    prob = MembraneProblem([run_path], h=1e-4)  # the fine problem of `bench fit`: its rms is the fit's
    fit = fits[-1]
    # by name: a fit stored before the monitor's calibration was fitted lacks V_gain/V_offset (nominal: 0), and a
    # campaign's fit may carry them for a record that has no measured voltage
    given = dict(zip(fit["names"], (float(v) for v in fit["values"]), strict=True))
    lacking = [n for n in prob.names[:prob.n_model] if n not in given]
    if lacking:
        raise ValueError(f"run file {run_path}: its stored membrane fit lacks {', '.join(lacking)}")
    values = np.array([given.get(n, 0.0) for n in prob.names])
    u = prob.predict(to_optimiser(prob.log, values)[None, :])[0]
    with _opened(run_path, src) as s:
        ts = [a + np.arange(r.data.size) * r.stride * prob.h
              for a, r in zip(_record_starts(prob, s.streams), prob.records, strict=True)]
        valid = s.streams.first_last("laser", "valid")
    t, data = np.concatenate(ts), prob.data
    inside = (t >= valid[0]) & (t <= valid[1]) if valid is not None else np.zeros(t.size, bool)
    return {"t": t[inside], "model": u[inside], "record": data[inside], "fit": fit}


def _commanded_label(sp: VoltageTrace) -> str:
    if sp.hardware_timed:
        return "commanded voltage (DAQ output, every scan)"
    return "commanded voltage (software set-points)"


def _line(streams: StreamChunks, stream: str, column: str, t0: float, t1: float, flag: str | None = None,
          drop_nan: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A curve over [t0, t1] as a screen draws it (:meth:`bench.storage.chunks.StreamChunks.decimate`)."""
    if streams.length.get(stream, 0) == 0:
        return np.zeros(0), np.zeros(0)
    return streams.decimate(stream, column, t0, t1, PIXELS, flag=flag, drop_nan=drop_nan)


def _dense(streams: StreamChunks, stream: str, t0: float, t1: float) -> bool:
    """Whether the stream is sampled faster than every 10 ms over [t0, t1] (median of its first 1000 intervals)."""
    a, b = streams.span(stream, t0, t1)
    t = streams.read(stream, "t", a, min(b, a + 1001))
    return t.size > 2 and float(np.median(np.diff(t))) < 1e-2


def _plot_voltages(ax: Axes, streams: StreamChunks, t0: float, t1: float) -> None:
    """Measured (solid, under) and commanded (dashed, on top) voltage over [t0, t1], time from t0; the axis
    label and ticks in the curve's colour."""
    hardware = hardware_timed(streams)
    if streams.length.get("amplifier", 0) > 0:
        t, v = _line(streams, "amplifier", "voltage", t0, t1)
        style: dict[str, Any] = {"lw": 1.4} if _dense(streams, "amplifier", t0, t1) else \
            {"marker": ".", "ls": "none", "ms": 3}
        ax.plot(t - t0, v / 1e3, color=MEASURED_V, alpha=0.7, zorder=2, label="measured voltage (amplifier monitor)",
                **style)
    t, v = _line(streams, "setpoints", "voltage", t0, t1, drop_nan=True)
    if hardware:  # the set-points between streamed steps and the DAQ's output, merged in time order
        ta, va = _line(streams, "amplifier", "commanded", t0, t1)
        order = np.argsort(np.concatenate([t, ta]), kind="stable")
        t, v = np.concatenate([t, ta])[order], np.concatenate([v, va])[order]
    sp = VoltageTrace(t, v, "commanded" if hardware else "setpoints")
    ax.plot(sp.t - t0, sp.v / 1e3, color=COMMANDED_V, ls="--", lw=0.9, zorder=3,
            drawstyle="default" if sp.hardware_timed else "steps-post", label=_commanded_label(sp))
    ax.set_ylabel("voltage [kV]", color=MEASURED_V)
    ax.tick_params(axis="y", colors=MEASURED_V)
    ax.spines["right"].set_color(MEASURED_V)


def _arrows(ax: Axes, x: np.ndarray, y: np.ndarray, color: Any, n: int = ARROWS_PER_LOOP) -> None:
    """Arrows along a loop (x, y) in the direction its samples run, at n evenly spaced points of its length."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 8:
        return
    sx = np.ptp(x) or 1.0
    sy = np.ptp(y) or 1.0
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x) / sx, np.diff(y) / sy))])
    if s[-1] <= 0:
        return
    step = max(1, x.size // 100)
    for k in range(n):
        i = int(np.searchsorted(s, (k + 0.5) / n * s[-1]))
        i, j = min(i, x.size - 1 - step), min(i, x.size - 1 - step) + step
        ax.annotate("", xy=(x[j], y[j]), xytext=(x[i], y[i]),
                    arrowprops={"arrowstyle": "-|>", "color": color, "lw": 1.0, "mutation_scale": 12})


def thesis_time_figure(a: RunAnalysis, src: RunSource | None = None) -> Figure:
    """Displacement and voltage vs time; with a fitted model, the model over the record and a residual panel."""
    with _opened(a.path, src) as s:
        t, u = _line(s.streams, "laser", "displacement", -np.inf, np.inf, flag="valid")
        u = u * 1e3
        unread = ""
        try:
            fitted = fitted_membrane(a.path, s)
        except (ValueError, OSError) as exc:  # a fit file that is not this run's: the record is drawn all the same
            fitted, unread = None, " ".join(str(exc).split())  # (it stopped the whole report, a second tester)
        if fitted is None:
            fig, ax = _figure(figsize=(8, 4.4))
            ax.set_xlabel("time [s]")
        else:
            fig, (ax, ax_r) = _figure(nrows=2, figsize=(8, 5.6), sharex=True,
                                      gridspec_kw={"height_ratios": [3, 1]})
        ax.plot(t, u, lw=0.8, color="tab:blue", label="measured displacement (laser)")
        if fitted is not None:
            rms_fit, records = float(fitted["fit"]["rms"]), len(fitted["fit"].get("records") or [1])
            over = f"over its {records} records" if records > 1 else "over this record"
            ax.plot(fitted["t"], fitted["model"] * 1e3, "--", lw=1.0, color="black", zorder=4,
                    label=f"fitted model (fit {str(fitted['fit']['group']).rsplit('/', 1)[-1]}, rms "
                          f"{rms_fit * 1e6:.1f} µm {over})")  # (the legend's rms and the residual's differed unsaid)
            res = (fitted["model"] - fitted["record"]) * 1e6
            fin = np.isfinite(res)
            rms = float(np.sqrt(np.mean(res[fin] ** 2))) if fin.any() else float("nan")
            ax_r.plot(fitted["t"], res, lw=0.8, color="black")
            ax_r.axhline(0.0, color="0.6", lw=0.6, zorder=0)
            ax_r.set_title(f"residual on this record: model − record, rms {rms:.1f} µm", fontsize=9, loc="left")
            ax_r.set_ylabel("residual [µm]")
            ax_r.set_xlabel("time [s]")
        ax2 = ax.twinx()
        _plot_voltages(ax2, s.streams, 0.0, float(s.run.updated) if s.run.updated else float(t[-1]))
    ax.set_ylabel("displacement u [mm]")
    unread = "\n" + textwrap.fill(f"(stored fit not read: {unread})", 90) if unread else ""
    ax.set_title(f"{a.protocol}: displacement vs time{unread}", fontsize=10)
    _legend_outside(fig, [ax, ax2])
    return fig


def _loop_stride(streams: StreamChunks, stream: str, windows: list[tuple[float, float]]) -> int:
    """Every how many samples the loops over ``windows`` are drawn so that together they hold ``LOOP_POINTS``."""
    total = sum(b - a for a, b in (streams.span(stream, t0, t1) for t0, t1 in windows))
    return max(1, math.ceil(total / LOOP_POINTS))


def thesis_loop_figure(a: RunAnalysis, src: RunSource | None = None) -> Figure:
    """Displacement vs (measured) voltage per step, with arrows in the direction of the loop."""
    fig, ax = _figure(figsize=(7.5, 5))
    steps = a.by_kind("thesis")
    with _opened(a.path, src) as s:
        stride = _loop_stride(s.streams, "laser", [(st.t_start, st.t_start + st.duration) for st in steps])
        for st in steps:
            t1 = st.t_start + st.duration
            laser = s.streams.window("laser", st.t_start, t1, ["displacement", "valid"])
            ok = laser["valid"] > 0
            t, u = laser["t"][ok][::stride], laser["displacement"][ok][::stride] * 1e3
            seen = applied_window(s.streams, st.t_start, t1, measured=True)  # what the specimen saw (as the analysis)
            v_loop = np.interp(t, seen.t, seen.v) / 1e3
            (line,) = ax.plot(v_loop, u, lw=0.8,
                              label=f"{st.voltage / 1e3:.0f} kV, {st.frequency:.3g} Hz, {st.temperature:g} K")
            _arrows(ax, v_loop, u, line.get_color())
        measured = hardware_timed(s.streams)
    ax.set_xlabel("measured voltage [kV]" if measured else "commanded voltage [kV]")
    ax.set_ylabel("displacement u [mm]")
    ax.set_title("displacement vs voltage (arrows: direction of the loop)", fontsize=10)
    _legend_outside(fig, [ax], "right")
    return fig


def thesis_figures(a: RunAnalysis, out: Path, src: RunSource | None = None) -> list[Path]:
    """Displacement vs time and vs voltage (the thesis's Figs 4.15–4.22), with the fitted model if any."""
    return [save_figure(thesis_time_figure(a, src), out / "displacement_vs_time.png"),
            save_figure(thesis_loop_figure(a, src), out / "displacement_vs_voltage.png")]


def isopotential_loop_figures(a: RunAnalysis, src: RunSource | None = None) -> dict[str, Figure]:
    """Force–displacement loops of the last (stabilised) cycle at each voltage, per prototype and stroke, with
    arrows in the direction of the cycle; keyed by file name."""
    groups: dict[tuple[int | None, int], list[Any]] = {}
    for st in a.by_kind("isopotential"):
        groups.setdefault((st.prototype, round(st.figures["stroke"] * 1e3)), []).append(st)
    figs = {}
    with _opened(a.path, src) as s:
        for (proto, stroke), steps in sorted(groups.items()):
            fig, ax = _figure(figsize=(7.5, 5))
            for st in steps:
                t0, t1 = st.t_start + st.duration - 1 / st.frequency, st.t_start + st.duration
                motor = s.streams.window("motor", t0, t1, ["aperture"])
                lc = s.streams.window("load_cell", t0, t1, ["force"], neighbours=True)  # interpolated as on the whole
                f = np.interp(motor["t"], lc["t"], lc["force"])
                x = motor["aperture"] * 1e3
                label = f"{st.voltage / 1e3:.0f} kV: loss {100 * st.figures['loss_last']:.1f} %"
                (line,) = ax.plot(x, f, lw=1.0, label=label)
                _arrows(ax, x, f, line.get_color())
            ax.set_xlabel("aperture x [mm]")
            ax.set_ylabel("force F [N]")
            ax.set_title(f"LS-DEA #{proto}, Δx {stroke} mm, stabilised cycle", fontsize=10)
            _legend_outside(fig, [ax], "right")
            figs[f"isopotential_p{proto}_dx{stroke}.png"] = fig
    return figs


def isopotential_figures(a: RunAnalysis, out: Path, src: RunSource | None = None) -> list[Path]:
    """The stabilised loops of :func:`isopotential_loop_figures`, saved."""
    return [save_figure(fig, out / name) for name, fig in isopotential_loop_figures(a, src).items()]


def isometric_time_figure(a: RunAnalysis, src: RunSource | None = None) -> Figure:
    """Force and voltage vs time in the step of the highest frequency."""
    top = max(a.by_kind("isometric"), key=lambda s: s.frequency)
    fig, ax = _figure(figsize=(8, 4.4))
    with _opened(a.path, src) as s:
        t, force = _line(s.streams, "load_cell", "force", top.t_start, top.t_start + top.duration)
        ax.plot(t - top.t_start, force, lw=0.8, label="measured force (load cell)")
        ax2 = ax.twinx()
        _plot_voltages(ax2, s.streams, top.t_start, top.t_start + top.duration)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("force [N]")
    ax.set_title(f"isometric, LS-DEA #{top.prototype}: {top.name}", fontsize=10)
    _legend_outside(fig, [ax, ax2])
    return fig


def isometric_figures(a: RunAnalysis, out: Path, src: RunSource | None = None) -> list[Path]:
    """Force vs time at the highest frequency, and force variation vs output frequency (Fig. 7)."""
    steps = a.by_kind("isometric")
    paths = [save_figure(isometric_time_figure(a, src), out / "isometric_time_series.png")]
    fig, ax = _figure(figsize=(7.5, 4))
    series: dict[tuple[int | None, float], list[Any]] = {}
    for s in steps:
        series.setdefault((s.prototype, round(s.figures["force_mean"], 1)), []).append(s)
    for (proto, _), ss in series.items():
        ax.plot([s.figures["output_frequency"] for s in ss], [s.figures["force_swing"] for s in ss], "o-",
                label=f"#{proto}, mean force {np.mean([s.figures['force_mean'] for s in ss]):.2f} N")
    ax.set_xlabel("force frequency [Hz]")
    ax.set_ylabel("crest-to-trough force [N]")
    ax.set_ylim(bottom=0)
    ax.set_title("electrically induced force variation", fontsize=10)
    _legend_outside(fig, [ax], "right", fontsize=7)
    paths.append(save_figure(fig, out / "isometric_force_vs_frequency.png"))
    return paths


def isotonic_figures(a: RunAnalysis, out: Path) -> list[Path]:
    """Crest-to-trough displacement vs frequency for each hung mass (Fig. 10), resonances marked."""
    fig, ax = _figure(figsize=(7, 4))
    masses = sorted({s.hung_mass or 0.0 for s in a.by_kind("isotonic")})
    for m in masses:
        ss = [s for s in a.by_kind("isotonic") if (s.hung_mass or 0.0) == m]
        ax.plot([s.frequency for s in ss], [s.figures["amplitude"] * 1e3 for s in ss], "o-",
                label=f"hung mass {m * 1e3:.0f} g")
    for f, amp in a.resonance().values():
        ax.annotate(f"{f:g} Hz", (f, amp * 1e3), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("voltage frequency [Hz]")
    ax.set_ylabel("crest-to-trough displacement [mm]")
    ax.set_title("isotonic response, LS-DEA #1", fontsize=10)
    _legend_outside(fig, [ax], "right")
    return [save_figure(fig, out / "isotonic_amplitude_vs_frequency.png")]


def table3_figure(grid: dict[str, Any]) -> Figure:
    """The Table-3 grid of a campaign (``bench report`` of several files: prototype × voltage, the hysteresis
    loss of the stabilised cycle at each row's largest stroke) as a coloured table with the loss [%] in each
    cell; an empty cell (no step) is left blank and marked "–"."""
    volts, rows = grid["voltages_kV"], grid["rows"]
    loss = np.full((len(rows), len(volts)), np.nan)
    for i, row in enumerate(rows):
        for j, v in enumerate(volts):
            if str(v) in row["loss"]:
                loss[i, j] = 100 * row["loss"][str(v)]
    fig, ax = _figure(figsize=(1.6 + 1.1 * len(volts), 1.4 + 0.6 * len(rows)))
    image = ax.imshow(np.ma.masked_invalid(loss), cmap="viridis", aspect="auto")
    for i in range(len(rows)):
        for j in range(len(volts)):
            value = loss[i, j]
            dark = np.isfinite(value) and value < np.nanmean(loss)
            ax.text(j, i, f"{value:.1f}" if np.isfinite(value) else "–", ha="center", va="center", fontsize=9,
                    color="white" if dark else "black")
    ax.set_xticks(range(len(volts)), [f"{v:g} kV" for v in volts])
    ax.set_yticks(range(len(rows)), [f"#{r['prototype']}, Δx {r['stroke_m'] * 1e3:.0f} mm" for r in rows])
    ax.set_xlabel("voltage")
    ax.set_ylabel("prototype, stroke")
    ax.set_title("hysteresis loss of the stabilised cycle [%]", fontsize=10)
    fig.colorbar(image, ax=ax, label="loss [%]")
    return fig


REPORT_MARKER = "report.json"  # a report folder's: the metadata of the run whose report it holds


class NothingToReportError(ValueError):
    """A run file none of whose steps could be analysed (its ``analysis`` says why: the run's state, its notes);
    raised by :func:`report` (``empty=False``) before anything is written."""

    def __init__(self, analysis: RunAnalysis) -> None:
        super().__init__(f"run file {analysis.path}: no step of it could be analysed: nothing to report")
        self.analysis = analysis


def report(run_path: str | Path, out: str | Path | None = None, empty: bool = True,
           analysis: RunAnalysis | None = None) -> tuple[RunAnalysis, list[Path]]:
    """Analyse a run file and write its figures; returns the analysis and the PNG paths. The file is opened once
    and read a window at a time (see the module's docstring). A folder holds one run's report (``report.json``
    names it): an earlier report of the same run is replaced; another run's, or (in ``out``) a ``figures.json``
    of no marked report, is refused in one line before anything is written. ``empty=False``: a file with no step
    analysed is refused (:class:`NothingToReportError`), nothing written. ``analysis``: the file's analysis already
    made (:func:`bench.analysis.runs.analyse`), not repeated."""
    from bench.storage.export import run_metadata

    run_path = Path(run_path)
    default = out is None  # beside the run, named by it: its own (an older report there has no marker)
    out = Path(out) if out is not None else run_path.with_suffix("").with_name(run_path.stem + "-report")
    paths: list[Path] = []
    with open_source(run_path) as src:
        a = analysis if analysis is not None else analyse_source(src)
        if not empty and not a.steps:
            raise NothingToReportError(a)
        meta = run_metadata(a.run)
        loose = ["figures.json"] if not default and (out / "figures.json").exists() else []
        claim_folder(out, REPORT_MARKER, meta, "report", "report", loose)
        try:
            out.mkdir(parents=True, exist_ok=True)  # (not for a file refused: a manual session's)
        except OSError as exc:  # (/proc/x, a read-only medium): one line naming the folder, not "[Errno 2] …"
            raise OSError(f"report folder {out}: cannot be made ({cause(exc)})") from None
        # the marker first: a report cut off still says whose it is
        write_text(out / REPORT_MARKER, json.dumps(meta, indent=1, ensure_ascii=False, default=str), replace=True)
        kinds = {s.kind for s in a.steps}
        if "thesis" in kinds:
            paths += thesis_figures(a, out, src)
        if "isopotential" in kinds:
            paths += isopotential_figures(a, out, src)
        if "isometric" in kinds:
            paths += isometric_figures(a, out, src)
        if "isotonic" in kinds:
            paths += isotonic_figures(a, out)
    write_text(out / "figures.json", json.dumps(step_records(a), indent=1), replace=True)
    return a, paths
