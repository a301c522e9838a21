"""Use cases on models and recorded runs: the LS-DEA design map, the report of run files (figures of merit,
plots, the Table-3 grid of a campaign)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from bench.analysis.runs import RunAnalysis
    from bench.app import Progress
    from bench.design_map import DesignCurves, DesignMap, MapSettings
    from bench.storage.runfile import RunFile

PROTOTYPES = ((1, 2.5), (2, 2.75), (3, 3.0))  # Moretti's prototypes: number, pre-stretch λ2p (all at xp 40 mm)
PROTOTYPE_XP = 0.040


@dataclass
class DesignMapResult:
    """The map, its smallest stiffness and region per (λ2p, xp), the prototypes on it, the figures written."""

    settings: MapSettings
    map: DesignMap
    min_stiffness: np.ndarray  # [N/m], [i_λ2p, i_xp]
    regions: np.ndarray  # "stiff", "near-zero", "negative"
    prototypes: list[tuple[int, float, DesignCurves, str]]  # (number, its λ2p, its curves, its region)
    figures: list[Path]


def design_map(out: Path = Path("runs/design-map"), voltages: tuple[float, ...] = (0.0, 3e3, 5e3, 7e3),
               scheduler: str | None = None, workers: int | None = None,
               progress: Progress | None = None) -> DesignMapResult:
    """Compute the design map at ``voltages`` [V] (on a dask cluster if asked) and plot it into ``out``;
    ``progress`` gets the fraction of the map's rows computed."""
    from bench.app.cluster import cluster_client
    from bench.design_map import MapSettings, compute_map, plot_map

    settings = MapSettings(voltages=voltages)
    with cluster_client(scheduler, workers) as client:
        dmap = compute_map(settings, client=client, progress=progress)
    regions = dmap.regions()
    protos = []
    for num, l2p in PROTOTYPES:
        d = dmap.design(l2p, PROTOTYPE_XP)
        protos.append((num, l2p, d, str(regions[settings.lambda2p.index(d.lambda2p), settings.xp.index(d.xp)])))
    return DesignMapResult(settings, dmap, dmap.min_stiffness(), regions, protos, plot_map(dmap, out))


@dataclass
class RunReport:
    """One run file's report: whether it is complete, its analysis, its figures."""

    path: Path
    state: str
    complete: bool
    incomplete_reason: str
    recovered_at: str
    steps_completed: int
    steps_total: int
    analysis: RunAnalysis
    figures: list[Path]
    reason: str = ""  # the file's /status/reason: why the run ended, then how the output was made safe
    stopped: str = ""  # a run that ended before its protocol did: one line saying so (:func:`stopped_line`)
    state_shown: str = ""  # the state as listings show it (RunFile.state_shown: a dead writer's file, a pause)

    def flags(self) -> dict[str, object]:
        """The file's state for ``--json``: ``state`` and ``reason`` say how the run ended (``completed`` or
        interrupted, tripped, error; running when no end was recorded), ``complete`` only that the file was
        finalised (a stopped run's file is complete: it holds all that was run); ``state_shown`` the state as
        listings show it ("paused", "crashed or killed", "ended unstamped: …" for a file that says running)."""
        return {"state": self.state, "state_shown": self.state_shown or self.state, "reason": self.reason or None,
                "stopped": self.stopped or None,
                "complete": self.complete, "incomplete_reason": self.incomplete_reason or None,
                "recovered_at": self.recovered_at or None}


def _steps(first: int, last: int, total: int) -> str:
    """Steps ``first``–``last`` (indices) as the CLI counts them: 1-based, of ``total``."""
    if first == last:
        return f"step {first + 1} of {total}"
    return f"steps {first + 1}–{last + 1} of {total}"


def stopped_line(run: RunFile, continued_in: Path | None = None) -> str:
    """One line on a run that ended before its protocol did ('' for a completed run, or one with no end recorded:
    that is the INCOMPLETE line's): how it ended and when, why, and the steps it did not run to their end
    (numbered from 1, as ``bench run --resume`` counts them; the file's step indices are 0-based)."""
    if run.state in ("completed", "running"):
        return ""
    events = run.event_list()
    t, step = run.updated, None
    for te, st, kind, _ in events:
        if kind == run.state:  # the engine's event of the stop: its time and the step it stopped in
            t, step = te, st
    why = run.reason.split(" | ")[0] or "no reason recorded"
    total = int(run.program.shape[0])
    first = int(run.attrs.get("resumed_at_step") or 0)  # steps before ran in the earlier file of the campaign
    done = run.completed_steps()
    left = [i for i in range(first, total) if i not in done]
    line = f"run {run.state} at {t:.2f} s: {why}"
    if step is not None and 0 <= step < total:
        name = run.program[step]["name"]
        line += f" — in step {step + 1} of {total} (index {step}, {name.decode() if isinstance(name, bytes) else name})"
    if left:
        line += "; " + _steps(left[0], left[-1], total) + (" not run to their end" if len(left) > 1 else
                                                          " not run to its end")
    if continued_in is not None:
        line += f"; the campaign goes on in {continued_in.name}"
    return line


def nothing_to_report(a: RunAnalysis) -> str:
    """One line on a run file none of whose steps could be analysed (outside tester: `bench report` on a run
    interrupted at once exited 0): the file, and why — how the run ended (:func:`stopped_line`), an incomplete
    file's reason, the analysis's notes, or a protocol with no drive step to analyse."""
    run = a.run
    why = [stopped_line(run) or ("" if run.complete else f"incomplete file: {run.incomplete_reason}"), *a.notes]
    why = [" ".join(w.split()) for w in why if w]
    return (f"run file {a.path}: nothing to report: no step of it could be analysed ("
            + ("; ".join(why) or "its protocol has no drive step, the steps the report analyses") + ")")


@dataclass
class Report:
    """The report of run files: each one's, and the Table-3 grid of their isopotential steps (None without)."""

    runs: list[RunReport] = field(default_factory=list)
    grid: dict[str, Any] | None = None
    grid_figure: Path | None = None  # the grid drawn (table3.png beside table3.csv)
    notes: list[str] = field(default_factory=list)  # what the caller should say (a folder renamed for a collision)
    skipped: list[tuple[Path, str]] = field(default_factory=list)  # (file, why): a manual session's readings

    @property
    def figures(self) -> list[Path]:
        return [p for r in self.runs for p in r.figures] + ([self.grid_figure] if self.grid_figure else [])


def report_runs(runs: list[Path], out: Path | None = None, progress: Progress | None = None) -> Report:
    """Analyse run files and write their figures (into ``out``, a folder per file when there are several: its name,
    another for a name that collides, said in ``notes``; default beside each file); the Table-3 grid of the
    isopotential steps, also written as CSV (its path in ``grid``) and drawn beside it.
    ``progress`` gets the fraction of the files done."""
    from bench.report import NothingToReportError, report, save_figure, table3_figure

    done = Report()
    analyses = _analyse_first(runs, done) if len(runs) > 1 else {}
    folders = report_folders(runs) if len(runs) > 1 else {}
    for k, p in enumerate(runs):
        if len(runs) > 1 and k not in analyses:
            continue  # a manual session's: skipped, said
        where = out / folders[k] if out is not None and folders else out
        try:  # several: each file analysed once above; alone: opened once for analysis and figures
            a, paths = report(p, where, empty=len(runs) > 1, analysis=analyses.get(k))
        except NothingToReportError as exc:  # alone: refused in one line, nothing written
            raise ValueError(nothing_to_report(exc.analysis)) from None
        if where is not None and where.name != p.stem and folders:
            done.notes.append(f"{p}: figures in {where} (another run file is named {p.name})")
        run = a.run  # the file's state as the analysis read it
        later = continued_in(run, runs[k + 1:]) if run.state not in ("completed", "running") else None
        done.runs.append(RunReport(p, run.state, run.complete, run.incomplete_reason, run.recovered_at,
                                   len(run.completed_steps()), run.program.shape[0], a, paths, run.reason,
                                   stopped_line(run, later), run.state_shown))
        if progress is not None:
            progress((k + 1) / len(runs))
    grid = table3([s for r in done.runs for s in r.analysis.steps])
    if grid is not None:
        csv_path = (out if out is not None else runs[-1].with_name(runs[-1].stem + "-report")) / "table3.csv"
        _claim_table3(csv_path, [r.analysis.run.attrs.get("run_id") or str(r.path.resolve()) for r in done.runs])
        write_table3_csv(grid, csv_path)
        grid["csv"] = str(csv_path)
        done.grid_figure = save_figure(table3_figure(grid), csv_path.with_suffix(".png"))
    done.grid = grid
    return done


def _analyse_first(runs: list[Path], done: Report) -> dict[int, Any]:
    """Each of several run files analysed (by index) before any report is written: manual sessions' files skipped
    (said in ``done.skipped``); none left, or none with a step analysed, is refused in one line with nothing
    written (a campaign report that can hold nothing makes no folders)."""
    from bench.analysis.runs import analyse
    from bench.storage.runfile import ManualSessionError

    analyses: dict[int, Any] = {}
    for k, p in enumerate(runs):
        try:
            analyses[k] = analyse(p)
        except ManualSessionError as exc:  # among run files (a glob of runs/): skipped, said
            done.skipped.append((p, str(exc)))
    if not analyses:  # every file given was a manual session's
        raise ValueError(f"no run file to report: {len(runs)} manual-control session files "
                         "(bench devices control), which hold no protocol steps")
    if not any(a.steps for a in analyses.values()):
        raise ValueError(f"no step of {', '.join(str(runs[k]) for k in analyses)} could be analysed: "
                         "nothing to report")
    return analyses


def _claim_table3(csv_path: Path, runs: list[Any]) -> None:
    """The Table 3 of ``runs`` (their run ids) may go to ``csv_path``: none there yet, or the same runs' (replaced;
    ``table3.json`` beside it names them). Another set of runs' Table 3 is refused in one line, as a report folder
    refuses another run's report (bench/storage/outputs.py)."""
    import json

    from bench.storage.outputs import write_text

    marker = csv_path.with_name("table3.json")
    ids = sorted(str(r) for r in runs)
    if marker.exists() or csv_path.exists():
        try:
            held = json.loads(marker.read_text(encoding="utf-8")).get("runs")
        except (OSError, ValueError, AttributeError):
            held = None
        if held != ids:
            raise FileExistsError(f"{csv_path.parent}: holds the Table 3 of other runs ({csv_path.name}); bench "
                                  "report does not replace another campaign's: choose another --out")
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    write_text(marker, json.dumps({"runs": ids}, indent=1) + "\n", replace=True)


def report_folders(runs: list[Path]) -> dict[int, str]:
    """The folder of each run's figures in a report of several: its name (``x`` for ``A/x.h5``), or for a name
    another file took before it ``x-2``, ``x-3`` … (one no run's name takes), so that no file's figures replace
    another's."""
    stems = {p.stem for p in runs}
    taken: set[str] = set()
    out: dict[int, str] = {}
    for i, p in enumerate(runs):
        name, k = p.stem, 2
        while name in taken or (name != p.stem and name in stems):
            name, k = f"{p.stem}-{k}", k + 1
        taken.add(name)
        out[i] = name
    return out


def continued_in(run: RunFile, later: list[Path]) -> Path | None:
    """The file among ``later`` (reported with it) that resumed ``run``'s campaign (``previous_run_id``)."""
    from bench.storage.runfile import open_run

    rid = run.attrs.get("run_id")
    for q in later:
        if rid and open_run(q, streams=False).attrs.get("previous_run_id") == rid:
            return q
    return None


def table3(steps: list[Any]) -> dict[str, Any] | None:
    """The Table-3 grid of isopotential steps: per prototype, the hysteresis loss of the stabilised cycle at each
    voltage for its largest stroke Δx. Conditions that differ between cells (Δx between rows, the frequency within
    a row or a cell, several steps in one cell) are listed in ``warnings``, never mixed silently."""
    iso = [s for s in steps if s.kind == "isopotential"]
    if not iso:
        return None
    volts = sorted({round(s.voltage / 1e3) for s in iso})
    rows, warnings = [], []
    for proto in sorted({s.prototype for s in iso}):
        ss = [s for s in iso if s.prototype == proto]
        dx = max(round(s.figures["stroke"] * 1e3) for s in ss)  # mm: the imposed stroke
        cells: dict[str, list[Any]] = {}
        for s in ss:
            if round(s.figures["stroke"] * 1e3) == dx:
                cells.setdefault(str(round(s.voltage / 1e3)), []).append(s)
        freqs = sorted({round(s.frequency, 6) for c in cells.values() for s in c})
        for v, c in cells.items():
            if len(c) > 1:
                warnings.append(f"#{proto} at {v} kV, Δx {dx} mm: {len(c)} steps ({', '.join(s.name for s in c)}); "
                                "the last one is shown")
        if len(freqs) > 1:
            warnings.append(f"#{proto}: cells at different frequencies ({', '.join(f'{f:g}' for f in freqs)} Hz)")
        rows.append({"prototype": proto, "stroke_m": dx / 1e3, "frequencies_Hz": freqs,
                     "loss": {v: c[-1].figures["loss_last"] for v, c in cells.items()},
                     "steps": {v: [s.name for s in c] for v, c in cells.items()}})
    strokes = sorted({r["stroke_m"] for r in rows})
    if len(strokes) > 1:
        warnings.append("rows at different strokes Δx: " + ", ".join(
            f"#{r['prototype']} {r['stroke_m'] * 1e3:.0f} mm" for r in rows) + " (an incomplete campaign?)")
    return {"quantity": "hysteresis loss of the stabilised cycle", "unit": "1", "voltages_kV": volts, "rows": rows,
            "warnings": warnings}


def write_table3_csv(grid: dict[str, Any], path: Path) -> None:
    """The Table-3 grid as CSV: prototype, Δx [mm], frequencies [Hz], then the loss [%] at each voltage."""
    import csv

    from bench.storage.outputs import atomic_output

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, replace=True) as tmp, tmp.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["prototype", "stroke_mm", "frequency_Hz", *(f"loss_{v}kV_percent" for v in grid["voltages_kV"])])
        for row in grid["rows"]:
            w.writerow([row["prototype"], f"{row['stroke_m'] * 1e3:.0f}",
                        " ".join(f"{f:g}" for f in row["frequencies_Hz"]),
                        *(f"{100 * row['loss'][str(v)]:.4g}" if str(v) in row["loss"] else ""
                          for v in grid["voltages_kV"])])
