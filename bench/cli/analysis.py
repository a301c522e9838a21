"""CLI commands on recorded runs: fit (identification) and report (figures of merit, plots)."""

from __future__ import annotations

from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from bench.cli.common import JsonOpt, Table, clean_errors, console, err_console, escape, fail, json_mode, print_json

if TYPE_CHECKING:
    from bench.analysis.runs import StepResult
    from bench.app.analysis import Report
    from bench.identify.campaign import CampaignReport
    from bench.identify.core import FitResult, FitSettings, Problem, RecordedProblem
    from bench.identify.problems import MembraneProblem
    from bench.identify.trust import Trust

RunsArg = Annotated[list[Path], typer.Argument(help="Run files (.h5) to fit together.")]
SchedulerOpt = Annotated[str | None, typer.Option(
    help="dask.distributed scheduler to compute on, e.g. tcp://host:8786.")]
WorkersOpt = Annotated[int | None, typer.Option(
    help="Compute on a local dask cluster of this many worker processes (default: in-process).", min=1)]


class ModelChoice(StrEnum):
    auto = "auto"
    membrane = "membrane"
    lsdea = "lsdea"


class CostChoice(StrEnum):
    sae = "sae"
    lsq = "lsq"


def fit_result_table(result: FitResult, title: str) -> Table:
    """Parameters, bounds, sensitivity and flags of a fit; with intervals (``result.trust``): the interval, what
    the data determine, the local ± only where it agrees, and a caption with the method, noise and starts."""
    import numpy as np

    tr = result.trust
    t = Table(title=title)
    if tr is None:
        cols = ("parameter", "value", "unit", "bounds", "± (1σ)", "sensitivity", "flags")
    else:
        cols = ("parameter", "value", "unit", f"{100 * tr.confidence:g} % interval", "data", "± local (1σ)",
                "flags")
    for col in cols:
        t.add_column(col, justify="right" if col in ("value", "± (1σ)", "± local (1σ)", "sensitivity") else "left",
                     no_wrap=col != "flags")
    for j, name in enumerate(result.names):
        flags = "; ".join(f.split(" (")[0].replace("does not change the cost", "insensitive")
                          for f in result.flags_of(name) if tr is None or not f.startswith(
                              ("not determined", "bounded on one side only")))
        local = f"{100 * result.uncertainty[j]:.2g} %" if np.isfinite(result.uncertainty[j]) else "–"
        if tr is None:
            t.add_row(name, f"{result.values[j]:.5g}", result.units[j],
                      f"{result.lower[j]:.3g} … {result.upper[j]:.3g}", local, f"{result.sensitivity[j]:.2e}",
                      f"[yellow]{flags}[/]" if flags else "")
            continue
        status = tr.status[j]
        style = {"determined": "green", "not determined": "red"}.get(status, "yellow")
        t.add_row(name, f"{result.values[j]:.5g}", result.units[j], f"{tr.lower[j]:.4g} … {tr.upper[j]:.4g}",
                  f"[{style}]{status}[/]", local, f"[yellow]{flags}[/]" if flags else "")
    if tr is not None:
        noise = ", ".join(f"{s:.3g}" for s in tr.noise[:4]) + (" …" if len(tr.noise) > 4 else "")
        if any(tr.noise_datasheet):
            noise += "; datasheet " + ", ".join(f"{s:.3g}" for s in tr.noise_datasheet[:4]) + \
                (" …" if len(tr.noise_datasheet) > 4 else "")
        lines = [f"interval: {tr.method} at {100 * tr.confidence:g} % (the values with Δχ² ≤ {tr.threshold:.3g}, "
                 f"the others re-optimised); χ² against each record's noise σ, the max of the record's and the "
                 f"datasheet's ({noise}); "
                 f"reduced χ² {tr.chi2_reduced:.3g}, threshold widened ×{tr.scale:.3g} for the residual above the "
                 "noise / its correlation",
                 "data: determined = both ends inside the search bounds; an open side is shown at its bound",
                 "± local: the Jacobian's estimate, shown only where it agrees with the interval"]
        if tr.starts:
            lines.append(starts_line(tr))
        for td in tr.tradeoffs:
            if td["determined"]:
                lines.append(f"trade-off {' ↔ '.join(td['names'])}: {td['quantity']} = {td['value']:.4g} "
                             f"{td['unit']} ± {100 * td['relative']:.2g} % (local)")
        if tr.order:
            lines.append(tr.order)
        t.caption = "\n".join(lines)
    return t


def starts_line(tr: Trust) -> str:
    """The caption's line on the starts: how many reached the best χ², the failed searches, where they disagree."""
    n = len(tr.starts)
    line = (f"{n} independent starts (seeds {tr.starts[0]['seed']}…{tr.starts[-1]['seed']}): {len(tr.arrived)} of "
            f"{n} reached the best optimum (χ² within the threshold)")
    if tr.failed:
        line += "; " + ", ".join(f"seed {f['seed']} ended Δχ² {f['above']:,.0f} above it" for f in tr.failed) + \
            (": failed searches" if len(tr.failed) > 1 else ": a failed search")
        line += " (ignored: two starts confirm the best)" if len(tr.arrived) >= 2 else \
            " and nothing confirms the best: the parameters they put elsewhere are not determined (more --generations)"
    if tr.disagree:
        line += "; the starts that reached it end apart on " + ", ".join(tr.disagree)
    return line


def campaign_table(report: CampaignReport) -> Table:
    """Parameters × records: which records determine which parameter alone (✓), and the campaign."""
    t = Table(title="what each record determines alone, at the campaign's optimum (✓ determined, · not)")
    t.add_column("record")
    t.add_column("conditions")
    for name in report.names:
        t.add_column(name, justify="center")
    for src, cond, und in zip(report.records, report.conditions, report.undetermined, strict=True):
        t.add_row(escape(Path(src.split(" [")[0]).name + (" [" + src.split(" [")[1] if " [" in src else "")),
                  cond, *("·" if n in und else "✓" for n in report.names))
    t.add_row("[bold]campaign[/]", f"{len(report.records)} records",
              *("·" if n in report.campaign_undetermined else
                ("[green bold]✓[/]" if n in report.gained else "✓") for n in report.names))
    return t


# least-squares polish iterations of the commands (the library's FitSettings keeps the thesis-era 20): the search
# runs at the coarse step, whose optima are not the fine model's, so the polish does most of the work; on the demo's
# record (DE 50 x 100, units sorted by tau) 2 of 8 seeds reached the best chi2 with 20, 5 of 8 with 60, and 150
# brought two of the others from chi2 3,971 and 3,762 to 2,629 and 2,607 (best 2,590). The polish stops where it
# converges: the cap costs time only where it is needed (issue 27)
POLISH_ITERATIONS = 150
PolishOpt = Annotated[int, typer.Option(help="Least-squares polish iterations at most (it stops where it converges).",
                                        min=1)]


@clean_errors
def fit_command(
    runs: RunsArg,
    model: Annotated[ModelChoice, typer.Option(help="Model to identify (auto: from the run files).")]
    = ModelChoice.auto,
    population: Annotated[int, typer.Option(help="DE population (thesis: 50).", min=5)] = 50,
    generations: Annotated[int, typer.Option(help="DE generations (thesis: 100).", min=1)] = 100,
    mutation: Annotated[float, typer.Option(help="DE mutation factor F (thesis: 0.6).", min=0.0, max=2.0)] = 0.6,
    crossover: Annotated[float, typer.Option(help="DE crossover rate (thesis: 0.9).", min=0.0, max=1.0)] = 0.9,
    cost: Annotated[CostChoice, typer.Option(help="sae: the thesis's sum of absolute errors; lsq: least squares.")]
    = CostChoice.sae,
    branches: Annotated[int, typer.Option(help="LS-DEA: number of Maxwell branches.", min=0, max=4)] = 1,
    seed: Annotated[int, typer.Option(help="Random seed of the search.")] = 1,
    polish: Annotated[bool, typer.Option(help="Least-squares polish after the search.")] = True,
    polish_iterations: PolishOpt = POLISH_ITERATIONS,
    export: Annotated[Path | None, typer.Option(help="Write a rig file with the fitted parameters.")] = None,
    into: Annotated[bool, typer.Option("--into", help="Store the fit inside the run file(s) instead of a fit file "
                                       "beside each.")] = False,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    json_out: JsonOpt = False,
    starts: Annotated[int, typer.Option(help="Searches from independent seeds (seed, seed + 1, …); the table says "
                                        "whether they agree.", min=1)] = 3,
    intervals: Annotated[bool, typer.Option(help="95 % profile-likelihood intervals against each record's noise "
                                            "(--no-intervals: the plain fit, local ± only).")] = True,
) -> None:
    """Identify model parameters from recorded runs (differential evolution, as in the thesis) and store them.

    The fit is stored in a fit file beside each run, RUN.fit.hdf5 for RUN.h5 (HDF5, the same /fit groups a run
    file holds; the run file is not modified), or with --into inside the run file. `bench report` and `bench
    inspect` find fits in either place; keep a fit file with its run (rename both).

    Several files make a campaign: one specimen model is fitted to all of them (shared material, each record
    with its own voltage, temperature, prototype and hung mass), and the table says which parameters only the
    campaign determines. The campaign's fit is stored with every one of its files (in each fit file, or with
    --into in each run file), so the report of any of them finds it. Fit files given among the runs (a glob such
    as runs/*) are skipped."""
    from bench.app.fit import model_of_runs
    from bench.identify.core import FitSettings

    with json_mode(json_out):
        runs = runs_only(runs, writing="fitting")
    chosen = model_of_runs(runs, model.value)
    mismatch, stopped = fit_notices(runs, json_out)
    settings = FitSettings(population, generations, mutation, crossover, cost.value, polish, polish_iterations,
                           seed=seed, starts=starts, intervals=intervals)
    with json_mode(json_out):
        result, problem = run_fit(runs, chosen, settings, branches, export, scheduler, workers, into=into)
    if json_out:
        print_json({"model": chosen, "runs": [str(p) for p in runs], "cost": result.cost,
                    "cost_kind": result.cost_kind, "rms": result.rms, "rms_unit": problem.data_unit,
                    "rms_by_unit": result.rms_by_unit or None,
                    "lack_of_fit": result.lack_of_fit, "specimen_mismatch": mismatch or None, "stopped": stopped,
                    **({"intervals": result.trust.as_dict(result.names)} if result.trust is not None else {}),
                    "parameters": [{"name": n, "value": result.values[j], "unit": result.units[j],
                                    "lower": result.lower[j], "upper": result.upper[j],
                                    "relative_uncertainty": result.uncertainty[j],
                                    **({"interval": [result.trust.lower[j], result.trust.upper[j]],
                                        "interval_method": result.trust.method,
                                        "confidence": result.trust.confidence,
                                        "status": result.trust.status[j]} if result.trust is not None else {}),
                                    "sensitivity": result.sensitivity[j], "flags": result.flags_of(n)}
                                   for j, n in enumerate(result.names)]})


def fit_notices(runs: list[Path], json_out: bool) -> tuple[str, list[str]]:
    """What a user may not have meant, said before the minutes of fitting (when the command can still be stopped):
    files of more than one specimen, runs that stopped early; returned for ``--json``."""
    from bench.app.fit import specimen_mismatch, stopped_notices

    mismatch, stopped = specimen_mismatch(runs), stopped_notices(runs)
    with json_mode(json_out):
        if mismatch:
            console.print(f"[yellow]warning: {escape(mismatch)}[/]")
        for line in stopped:
            console.print(f"note: {escape(line)}")
    return mismatch, stopped


def runs_only(paths: list[Path], writing: str = "") -> list[Path]:
    """``paths`` without fit files (``*.fit.hdf5``, which a glob such as ``runs/*`` picks up), saying so, with their
    campaigns' other files (:func:`campaign_files`, ``writing`` as there)."""
    from bench.identify.store import is_sidecar

    skipped = [p for p in paths if is_sidecar(p)]
    if skipped:
        console.print(f"skipping {len(skipped)} fit file(s) among the runs: "
                      + ", ".join(escape(str(p)) for p in skipped))
    runs = [p for p in paths if not is_sidecar(p)]
    if not runs:
        raise ValueError("no run files: only fit files (*.fit.hdf5) were given; name the runs (.h5)")
    return campaign_files(runs, writing)


def campaign_files(runs: list[Path], writing: str = "") -> list[Path]:
    """``runs`` with the earlier files of each resumed campaign (``bench run --resume``), saying so: a chain of
    linked files is one campaign (each step counted from the file in which it completed). ``writing``: what the
    caller does (e.g. "fitting"): a file that continued a named one and is still being written (its state
    ``running``, no dead writer seen) is then left out, said in one line — a fit of the first file of a campaign
    under way took the part of its last file written so far, and stored its result in it. Named, it is
    taken."""
    from bench.storage.chain import campaign, describe, with_chains

    out = with_chains(runs)
    said: set[str] = set()
    named = {p.resolve() for p in runs}
    going: list[Path] = []
    for p in runs:
        links = campaign(p)  # also the files that continued it: its first file reads as the whole campaign
        if len(links) > 1 and (line := describe(links)) not in said:
            said.add(line)
            console.print(f"campaign of {len(links)} linked files: {escape(line)}")
        going += [link.path for link in links if writing and link.shown == "running" and not link.complete
                  and link.path.resolve() not in named and link.path not in going]
    for p in going:
        console.print(f"leaving out {escape(str(p))}: still being written (the campaign goes on); {writing} what "
                      "has ended — name the file to take what it holds so far")
    return [p for p in out if p not in going]


STAGES = {"polish": "least-squares polish", "intervals": "profile-likelihood intervals"}  # the bars' titles


def run_fit(runs: list[Path], chosen: str, settings: FitSettings, branches: int = 1,
            export: Path | None = None, scheduler: str | None = None,
            workers: int | None = None, *, into: bool = False) -> tuple[FitResult, Problem]:
    """Fit (:func:`bench.app.fit.fit_runs`: stored with every file, optionally exported as a rig) and print it: a
    spinner while the records are read, a progress bar over the generations, one over the polish, one over the
    intervals, then the table, the campaign's identifiability, where it was stored. Returns the result and the
    (coarse) problem it was searched on."""
    import contextlib
    import threading

    import numpy as np

    from bench.app.fit import FitStopped, fit_runs
    from bench.cli.common import progress

    s = settings
    with contextlib.ExitStack() as stack:
        reading = stack.enter_context(console.status("reading the records…"))
        advance: list[Callable[[float], None]] = []

        def read(coarse: RecordedProblem) -> None:
            reading.stop()
            console.print(f"fitting the {chosen} model ({len(coarse.names)} parameters) to "
                          f"{len(coarse.records)} records, {int(np.isfinite(coarse.data).sum()):,} points; "
                          f"DE population {s.population}, up to {s.generations} generations, F {s.mutation}, "
                          f"CR {s.crossover}, cost {s.cost}")
            open_bar("differential evolution")

        bar = stack.enter_context(contextlib.ExitStack())  # the bar shown: one live display at a time on a console
        lock = threading.Lock()  # the starts polish in threads of their own
        stages: list[str] = []

        def open_bar(title: str) -> None:
            bar.close()  # the bar before ends
            advance.append(bar.enter_context(progress(title)))

        # the search's bar takes the generations alone (a start still searching while another polishes updates a
        # closed bar: nothing is drawn), each later stage its own
        def stage(name: str, fraction: float) -> None:  # a bar of its own for each stage after the search
            with lock:
                if not stages or stages[-1] != name:
                    stages.append(name)
                    open_bar(STAGES.get(name, name))
                advance[-1](fraction)

        try:
            done = fit_runs(runs, chosen, s, branches=branches, export=export, scheduler=scheduler,
                            workers=workers, into=into, on_read=read, progress=lambda fraction: advance[0](fraction),
                            stage=stage, on_cluster=lambda address: console.print(
                                f"evaluating candidates on the dask cluster {address}"))
        except FitStopped as exc:  # Ctrl-C (bench fit, bench demo): a user's stop, not an error; 130 as for SIGINT
            stack.close()  # the bar first, then the line under it
            err_console.print(f"fit stopped: {escape(str(exc))}", highlight=False, soft_wrap=True)
            raise typer.Exit(130) from None
    result, coarse = done.result, done.problem
    console.print(fit_result_table(result, f"{chosen} model fitted to {len(runs)} run(s)"))
    rms = ", ".join(f"{v:.4g} {u}" for u, v in result.rms_by_unit.items()) or f"{result.rms:.4g} {coarse.data_unit}"
    console.print(f"cost ({result.cost_kind}) {result.cost:.4g}, residual rms {rms}, "
                  f"{result.evaluations:,} model evaluations, {result.generations} generations, "
                  f"{result.wall_time:.1f} s (search {result.search_time:.1f} s)")
    if result.lack_of_fit:
        console.print(f"[yellow]warning: {result.lack_of_fit}: check the model choice and the record[/]")
    if done.campaign is not None:
        console.print(campaign_table(done.campaign))
        gained = done.campaign.gained
        console.print("determined by the campaign but by no single record: "
                      + (", ".join(gained) if gained else "none"))
    for file, group in done.stored:
        console.print(f"stored in {escape(str(file))}:{group}")
    if done.exported is not None:
        console.print(f"fitted rig file: {export} (bench run PROTOCOL --rig {export})")
    return result, coarse


@clean_errors
def design_map_command(
    out: Annotated[Path, typer.Option(help="Folder for the PNGs.")] = Path("runs/design-map"),
    voltages: Annotated[str, typer.Option(help="Voltages [kV], comma-separated, 0–10 kV; each may carry a unit: "
                                          "'0,3kV,5000V'.")] = "0,3,5,7",
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """LS-DEA design map (Moretti Fig. 2): F–x over pre-stretch λ2p × aperture xp, breakdown, loss of tension."""
    from bench.units import option_si

    show_design_map(out, tuple(option_si(v.strip(), "kV", "--voltages", 0, 10) for v in voltages.split(",")),
                    scheduler, workers)


def show_design_map(out: Path = Path("runs/design-map"), voltages: tuple[float, ...] = (0.0, 3e3, 5e3, 7e3),
                    scheduler: str | None = None, workers: int | None = None) -> list[Path]:
    """Compute the design map and print it: the stiffness table, the prototypes, the figures (``bench
    design-map``, ``bench simulate lsdea map``)."""
    from bench.app.analysis import design_map
    from bench.cli.common import progress

    before = set(out.glob("*.png")) if out.is_dir() else set()
    with progress("computing the design map") as advance:
        done = design_map(out, voltages, scheduler, workers, progress=advance)
    settings, k, regions = done.settings, done.min_stiffness, done.regions
    t = Table(title=f"smallest elastic stiffness over the {settings.stroke[0] * 1e3:g}–{settings.stroke[1] * 1e3:g} "
                    f"mm stroke [N/m] (stiff > {settings.flat:g}, near-zero, negative < −{settings.flat:g})")
    t.add_column("λ2p \\ xp [mm]")
    for xp in settings.xp:
        t.add_column(f"{xp * 1e3:g}", justify="right")
    colour = {"stiff": "red", "near-zero": "white", "negative": "blue"}
    for i, lam in enumerate(settings.lambda2p):
        t.add_row(f"{lam:g}", *(f"[{colour[regions[i, j]]}]{k[i, j]:.0f}[/]" for j in range(len(settings.xp))))
    console.print(t)
    for num, l2p, d, region in done.prototypes:
        lost = d.tension_lost[-1]
        console.print(f"prototype #{num} (λ2p {l2p:g}, xp 40 mm): {region}, k_min "
                      f"{d.min_stiffness:.1f} N/m, V_B {d.breakdown_voltage.min() / 1e3:.2f}–"
                      f"{d.breakdown_voltage.max() / 1e3:.2f} kV, tension lost at {voltages[-1] / 1e3:g} kV in "
                      f"{100 * lost.mean():.0f} % of the stroke")
    console.print("figures: " + ", ".join(str(p) for p in done.figures))
    if replaced := [p.name for p in done.figures if p in before]:
        console.print(f"[yellow]replaced[/] the earlier map's {', '.join(replaced)} in {escape(str(out))} (the map's "
                      "own folder; --out another folder keeps them)")
    return done.figures


@clean_errors
def report_command(
    runs: Annotated[list[Path], typer.Argument(help="Run files (.h5); several make a campaign report.")],
    out: Annotated[Path | None, typer.Option(help="Folder for the figures (default: beside the run file).")] = None,
    json_out: JsonOpt = False,
) -> None:
    """Figures of merit and plots (PNG, PDF, SVG) of recorded runs; several files add a campaign table (Table 3
    layout, also written as CSV). An incomplete, killed or recovered file is flagged; a run that stopped before
    its protocol ended (interrupted, tripped, error) says so in one line (--json: state, reason; complete means the
    file was finalised, as for a stopped run). A manual-control session's file among the runs is skipped, said; a
    file alone of which no step could be analysed is refused, saying why."""
    with json_mode(json_out):
        done = print_report(runs_only(runs), out)
    if json_out:
        print_json({"units": FIGURE_UNITS, "figures": [str(p) for p in done.figures], "table3": done.grid, "runs": [
            {"file": str(r.path), **r.flags(), "protocol": r.analysis.protocol,
             "steps": [{"step": s.name, "kind": s.kind, "prototype": s.prototype, "hung_mass_kg": s.hung_mass,
                        "temperature_K": s.temperature, "frequency_Hz": s.frequency, "voltage_V": s.voltage,
                        "figures": s.figures} for s in r.analysis.steps]} for r in done.runs],
            "skipped": [{"file": str(p), "why": why} for p, why in done.skipped]})


def figures_table(steps: list[StepResult], title: str) -> Table:
    """Figures of merit of analysed steps: one row per step, or one column per step when there are few."""
    keys = sorted({k for s in steps for k in s.figures})
    keys = [k for k in FIGURE_COLUMNS if k in keys] + [k for k in keys if k not in FIGURE_COLUMNS]
    has_where = any(s.prototype or s.hung_mass for s in steps)
    has_T = any(s.temperature for s in steps)
    conditions: dict[str, Callable[[StepResult], str]] = {
        "#": lambda s: f"{s.prototype or ''}" + (f" {s.hung_mass * 1e3:.0f} g" if s.hung_mass else ""),
        "T [K]": lambda s: f"{s.temperature:g}", "V [kV]": _peak_kV,
        "f [Hz]": lambda s: f"{s.frequency:.3g}"}
    if not has_where:
        del conditions["#"]
    if not has_T:
        del conditions["T [K]"]

    def figure(k: str) -> Callable[[StepResult], str]:
        return lambda s: _fmt(k, s.figures.get(k))

    rows = [(label, fn) for label, fn in conditions.items()] + \
        [(FIGURE_COLUMNS.get(k, (k, 1.0))[0], figure(k)) for k in keys]
    t = Table(title=title)
    if len(steps) <= 3:  # few steps: figures down, steps across (fits a narrow terminal)
        t.add_column("")
        for s in steps:
            t.add_column(escape(s.name), justify="right")
        for label, fn in rows:
            t.add_row(escape(label), *(fn(s) for s in steps))
        return t
    t.add_column("step", overflow="fold", min_width=14)
    for label, _ in rows:
        t.add_column(escape(label), justify="right")
    for s in steps:
        t.add_row(s.name, *(fn(s) for _, fn in rows))
    return t


def print_report(runs: list[Path], out: Path | None = None) -> Report:
    """Report run files (:func:`bench.app.analysis.report_runs`) and print it: each file's figures of merit (an
    incomplete file flagged), resonances, figures; the Table-3 grid of the isopotential steps, its CSV and figure."""
    from bench.app.analysis import report_runs
    from bench.cli.common import progress

    with progress(f"analysing and plotting {len(runs)} run file(s)") as advance:
        done = report_runs(runs, out, advance)
    for _, why in done.skipped:
        console.print(f"[yellow]skipping[/] {escape(why)}", soft_wrap=True)
    for note in done.notes:
        console.print(escape(note), soft_wrap=True)
    names = [r.path.name for r in done.runs]
    for r in done.runs:
        a, p = r.analysis, r.path
        shown = p.name if names.count(p.name) == 1 else str(p)  # files of one name in two folders: told apart
        if not r.complete:
            console.print(f"[red]INCOMPLETE[/] {escape(shown)} ({r.state_shown or r.state}): "
                          f"{escape(r.incomplete_reason)}; {r.steps_completed} of {r.steps_total} steps completed",
                          soft_wrap=True)
        if r.stopped:
            console.print(f"[yellow]{escape(r.stopped)}[/]", soft_wrap=True)
        for note in a.notes:
            console.print(f"[yellow]{escape(note)}[/]", soft_wrap=True)
        if a.steps:
            console.print(figures_table(a.steps, f"{a.protocol} ({shown})"
                                        + ("" if r.complete else " — INCOMPLETE FILE")
                                        + (f" — {r.state.upper()}" if r.stopped else "")))
        else:  # (an empty table's title wraps to its narrow width)
            console.print(f"no step of {escape(shown)} could be analysed")
        if a.by_kind("isotonic"):
            console.print("largest crest-to-trough per hung mass: " + ", ".join(
                f"{m * 1e3:.0f} g at {f:g} Hz ({amp * 1e3:.1f} mm)" for m, (f, amp) in a.resonance().items())
                + " (a resonance only where the sweep brackets it; V²'s 2f content also peaks at half of it)")
        # a file with nothing to plot (killed in its first step) showed an empty "figures: " line
        console.print("figures: " + (", ".join(str(x) for x in r.figures) if r.figures else "none (nothing to plot)"))
    grid = done.grid
    if grid is None:
        return done
    volts = grid["voltages_kV"]
    t = Table(title="hysteresis loss of the stabilised cycle [%] (Table 3 layout: prototype × voltage, largest Δx)")
    for col in ("prototype", "Δx [mm]", "f [Hz]", *(f"{v:g} kV" for v in volts)):
        t.add_column(col, justify="left" if col == "prototype" else "right")
    for row in grid["rows"]:
        t.add_row(f"#{row['prototype']}", f"{row['stroke_m'] * 1e3:.0f}",
                  ", ".join(f"{f:.3g}" for f in row["frequencies_Hz"]),
                  *(f"{100 * row['loss'][str(v)]:.1f}" if str(v) in row["loss"] else "–" for v in volts))
    console.print(t)
    for w in grid["warnings"]:
        console.print(f"[yellow]grid warning[/]: {escape(w)}", soft_wrap=True)
    console.print(f"grid as CSV: {escape(grid['csv'])}, as a figure: {escape(str(done.grid_figure))}")
    return done


# figure of merit → (column header, scale to the shown unit)
FIGURE_COLUMNS: dict[str, tuple[str, float]] = {
    "peak_first": ("u peak 1 [mm]", 1e3), "peak_last": ("u peak N [mm]", 1e3), "creep": ("creep [%]", 100.0),
    "lag_first": ("lag 1 [s]", 1.0), "residual_first": ("u end 1 [mm]", 1e3), "residual_last": ("u end N [mm]", 1e3),
    "loss_first": ("loss 1 [%]", 100.0), "loss_last": ("loss N [%]", 100.0), "stroke": ("Δx [mm]", 1e3),
    "force_max": ("F max [N]", 1.0), "force_min": ("F min [N]", 1.0), "amplitude": ("ampl. [mm]", 1e3),
    "stroke_percent": ("stroke [%]", 1.0), "energy_density": ("w [mJ/g]", 1.0),
    "energy_density_with_mechanism": ("w+mech [mJ/g]", 1.0), "mean_position": ("x mean [mm]", 1e3),
    "force_swing": ("ΔF [N]", 1.0), "force_mean": ("F mean [N]", 1.0), "output_frequency": ("f out [Hz]", 1.0),
    "vf_lag": ("V–F lag [ms]", 1e3),
}


# figure of merit → SI unit of the value stored in figures.json and printed by --json ("1": a fraction)
FIGURE_UNITS: dict[str, str] = {
    "peak_first": "m", "peak_last": "m", "creep": "1", "lag_first": "s", "residual_first": "m", "residual_last": "m",
    "loss_first": "1", "loss_last": "1", "stroke": "m", "force_max": "N", "force_min": "N", "amplitude": "m",
    "stroke_percent": "%", "energy_density": "mJ/g", "energy_density_with_mechanism": "mJ/g", "mean_position": "m",
    "force_swing": "N", "force_mean": "N", "output_frequency": "Hz", "vf_lag": "s",
}


RESOLUTION = {"vf_lag": 1e-4}  # [s]: the V–F lag read on a 10-kHz record, one sample (a finer digit is noise)


def _fmt(key: str, value: float | None) -> str:
    import numpy as np

    if value is None or not np.isfinite(value):
        return "–"
    scale = FIGURE_COLUMNS.get(key, ('', 1.0))[1]
    if key in RESOLUTION:  # as many decimals as one step of its resolution shows
        return f"{value * scale:.{max(0, -int(np.floor(np.log10(RESOLUTION[key] * scale))))}f}"
    return f"{value * scale:.4g}"


def _peak_kV(s: StepResult) -> str:
    """The step's measured peak voltage [kV]; "0" within the monitor's 0-V band (an undriven step's noise)."""
    from bench.analysis.thesis import undriven

    return "0" if undriven(s.voltage, s.no_drive_v) else f"{s.voltage / 1e3:.3g}"


@clean_errors
def demo(
    out: Annotated[Path, typer.Option(help="Folder for the run file and the report.")] = Path("runs/demo"),
    generations: Annotated[int, typer.Option(help="DE generations (thesis: 100).", min=1)] = 100,
    population: Annotated[int, typer.Option(help="DE population (thesis: 50).", min=5)] = 50,
    starts: Annotated[int, typer.Option(help="Searches from independent seeds; the table says whether they agree.",
                                        min=1)] = 3,
    intervals: Annotated[bool, typer.Option(help="95 % profile-likelihood intervals against the record's noise, "
                                            "simultaneous (they hold together, as the table is checked against "
                                            "the twin as a whole; --no-intervals: the plain fit).")] = True,
    polish_iterations: PolishOpt = POLISH_ITERATIONS,
) -> None:
    """The main job on the simulated rig: a paper protocol run, recorded, fitted and reported from the file.

    Runs the thesis identification protocol (7 kV raised cosine at 1/9 Hz, 296 K, laser at 10 kHz) in virtual
    time through the real wire protocols, identifies the membrane model from the HDF5 file by differential
    evolution (thesis settings), compares it with the specimen the twin simulated, and writes the report.
    """
    import numpy as np

    from bench.app.demo import plan_demo, run_demo
    from bench.identify.core import FitSettings

    with console.status("validating and dry-running the thesis identification protocol…"):
        plan = plan_demo()
    console.print(f"[bold]1. run[/] {plan.protocol.protocol.name}: {plan.protocol.protocol.description}")
    with console.status("running it on the simulated rig in virtual time (same bytes on the wire)…"):
        result = run_demo(plan, out)
    console.print(f"[{'green' if result.state == 'completed' else 'red'}]{result.state}[/]: {result.reason}; "
                  f"{result.run_time:.0f} s of run in {result.wall_time:.2f} s, {result.samples:,} samples "
                  f"→ {result.path}")
    if result.state != "completed":
        raise fail(f"run ended {result.state}: {result.reason}", code=1)
    console.print("[bold]2. fit[/] the membrane model to the recorded file")
    path = Path(result.path)
    # the table is checked against the truth as a whole: intervals that hold together (simultaneous)
    fitted, problem = run_fit([path], "membrane", FitSettings(population=population, generations=generations,
                                                                       polish_iterations=polish_iterations,
                                                                       starts=starts, intervals=intervals,
                                                                       simultaneous=True))
    console.print(twin_comparison(problem, fitted))  # type: ignore[arg-type]  # a "membrane" fit's problem is one
    peak = float(np.nanmax(np.abs(problem.data)))
    console.print(f"the fitted model reproduces the record to rms {fitted.rms * 1e6:.1f} µm "
                  f"({100 * fitted.rms / peak:.2f} % of the {peak * 1e3:.2f} mm peak)")
    console.print("[bold]3. report[/]")
    print_report([path], path.with_name(path.stem + "-report"))
    console.print(f"next: bench inspect {path} · bench fit --help · bench protocols list · "
                  "bench run thesis-voltage-sweep --virtual-time")


def twin_comparison(problem: MembraneProblem, fitted: FitResult) -> Table:
    """Fitted parameters next to the ones the simulated specimen used (recorded in the run file)."""
    import numpy as np

    from bench.identify.problems import match_membrane_units

    true = problem.reference()
    values = dict(zip(fitted.names, fitted.values, strict=True))
    pairing = match_membrane_units(values, true)
    true.update(problem.simulated_calibration())  # the voltage monitor's error the twin drew from the rig's seed
    t = Table(title="identified vs the simulated specimen (the twin's model, recorded in the file; the voltage "
                    "monitor's error drawn from the rig's seed)")
    tr = fitted.trust
    cols = ("parameter", "simulated", "identified", "error") + \
        ((f"{100 * tr.confidence:g} % interval", "holds it") if tr is not None else ()) + ("note",)
    for col in cols:
        t.add_column(col, justify="left" if col in ("parameter", "note", "holds it") else "right")
    for j, name in enumerate(fitted.names):
        ref = name
        if name[-1] in "1234" and name[:-1] in ("mu", "J", "tau"):
            ref = f"{name[:-1]}{pairing[int(name[-1])]}"
        if ref not in true:  # a parameter the twin has no value of (the calibration of a noiseless rig)
            continue
        err = fitted.values[j] / true[ref] - 1.0 if true[ref] != 0 else np.nan
        note = "; ".join(f.split(" (")[0].replace("does not change the cost", "insensitive: not identifiable")
                         for f in fitted.flags_of(name))
        style = "dim" if note else ""
        if ref != name:
            name = f"{name} (≙ {ref})"
        cells = [name, f"{true[ref]:.4g}", f"{fitted.values[j]:.4g}", f"{100 * err:+.1f} %"]
        if tr is not None:
            tol = 1e-9 * abs(true[ref])  # a value on a search bound is on the interval's open end
            inside = tr.lower[j] - tol <= true[ref] <= tr.upper[j] + tol
            cells += [f"{tr.lower[j]:.4g} … {tr.upper[j]:.4g}", "yes" if inside else "[red]no[/]"]
        t.add_row(*cells, note, style=style)
    t.caption = ("Maxwell units are interchangeable in the model and are paired by relaxation time (≙); flagged "
                 "parameters are not determined by this record (they trade off against others at equal cost)")
    return t

@clean_errors
def plot_command(
    run: Annotated[Path, typer.Argument(help="Run file (.h5).")],
    streams: Annotated[list[str] | None, typer.Argument(help="Streams to draw (default: all), e.g. laser amplifier.")]
    = None,
    out: Annotated[Path | None, typer.Option(help="PNG file (a new one: an existing file is refused), or folder for "
                                          "it (one that exists or a name without a file type; default: beside the "
                                          "run file), the figure named RUN-plot.png for all streams, "
                                          "RUN-plot-laser.png for laser.")] = None,
    show: Annotated[bool, typer.Option("--show", help="Open a window instead of writing a file.")] = False,
) -> None:
    """Quick look at a run file: every column of the chosen streams on the run clock, units on each axis, step
    starts marked; long records drawn as their min/max envelope (read in chunks: any length)."""
    from bench.analysis.quicklook import quicklook

    if not run.is_file():
        from bench.storage.absent import absent_run_file

        raise ValueError(absent_run_file(run))
    target = quicklook(run, streams or None, out, show)
    if target is not None:
        console.print(f"figure: {escape(str(target))}")


def register(app: typer.Typer) -> None:
    """Put fit, design-map, report, plot and demo on ``app``."""
    app.command("fit")(fit_command)
    app.command("design-map")(design_map_command)
    app.command("report")(report_command)
    app.command("plot")(plot_command)
    app.command()(demo)
