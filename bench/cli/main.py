"""The main options and the commands of no other group: simulate, sim, devices check, benchmark."""

from __future__ import annotations

import math
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from bench.app.simulate import SIMULATE_MAX_S
from bench.cli.common import JsonOpt, Table, _version, clean_errors, console, fail, json_mode, print_json
from bench.cli.completion import rig_files
from bench.numbers import mv_per_m
from bench.units import option_si

if TYPE_CHECKING:
    from collections.abc import Callable

    from bench.benchmarks.acquisition import Figure
    from bench.runtime.sim_rig import Endpoint


def main(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version and exit.")] = False,
         verbose: Annotated[int, typer.Option("--verbose", "-v", count=True,
                                              help="More detail on stderr (-v: info, -vv: debug).")] = 0,
         quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print only errors and results that are "
                                             "data (--json, file paths).")] = False) -> None:
    """dea-bench: DEA test-bench control, simulation and data acquisition."""
    from bench.cli.logs import configure_console

    console.quiet = quiet
    configure_console(verbose, quiet)


def _qopt(help_text: str) -> Any:
    """A typer option taking a quantity (``7kV``, ``9 cm``, ``25 °C``: any unit of the option's dimension) or a plain
    number in the unit its help names."""
    return typer.Option(metavar="<quantity>", help=help_text)


class WaveKindOption(StrEnum):
    raised_cosine = "raised_cosine"
    sine = "sine"
    triangle = "triangle"
    square = "square"


class Electrostriction(StrEnum):
    corrected = "corrected"
    thesis = "thesis"


@clean_errors
def simulate_thesis(
    voltage: Annotated[str, _qopt("Peak voltage Vmax [V]. 0–12 kV; or with a unit: 7kV.")] = "7000",
    frequency: Annotated[str | None, _qopt("Drive frequency [Hz]. 0.0001–1000 Hz (default 1/9 Hz, the thesis's); "
                                           "or with a unit: '0.5 Hz'.")] = None,
    temperature: Annotated[str, _qopt("Temperature [K]. 150–450 K; or with a unit: '23 °C'.")] = "296",
    duration: Annotated[str, _qopt(f"Simulated time [s]. Up to {SIMULATE_MAX_S:g} s; or with a unit: "
                                   "'2 min'.")] = "20",
    waveform: Annotated[WaveKindOption, typer.Option(help="Voltage waveform.")] = WaveKindOption.raised_cosine,
    electrostriction: Annotated[Electrostriction, typer.Option(
        help="Electrostatic stress: corrected (κ = 1/2) or as printed in the thesis (κ = 2).")]
    = Electrostriction.corrected,
    method: Annotated[str, typer.Option(
        help="Integrator: rodas (compiled Rosenbrock, offline), radau (scipy, the reference) or fixed (streaming "
             "scheme).")]
    = "rodas",
) -> None:
    """Thesis membrane (Model A) under a periodic voltage: per-cycle peaks, creep, residual, lag, field."""
    from bench.analysis.thesis import undriven, undriven_note
    from bench.app.simulate import simulate_thesis as simulate

    voltage_V = option_si(voltage, "V", "--voltage", 0, 12_000)
    frequency_Hz = 1 / 9 if frequency is None else option_si(frequency, "Hz", "--frequency", 1e-4, 1000)
    temperature_K = option_si(temperature, "K", "--temperature", 150, 450)
    duration_s = option_si(duration, "s", "--duration", 1e-3, SIMULATE_MAX_S)
    with console.status("simulating the thesis membrane…"):
        sim = simulate(voltage_V, frequency_Hz, temperature_K, duration_s, waveform.value, electrostriction.value,
                       method)
    figs = sim.figures
    table = Table(title=f"Thesis membrane: {voltage_V / 1e3:g} kV {waveform.value}, {frequency_Hz:.4g} Hz, "
                        f"{temperature_K:g} K, {duration_s:g} s")
    for col in ("cycle", "peak u [mm]", "at t [s]", "lag [s]", "u at cycle end [mm]"):
        table.add_column(col, justify="right")
    driven = not undriven(voltage_V)  # at 0 V the "voltage peak" is any sample: no lag or creep to the drive
    for k, (pk, tk, lag) in enumerate(zip(figs.peaks, figs.peak_times, figs.lags, strict=True)):
        res = f"{figs.residuals[k] * 1e3:.3f}" if k < len(figs.residuals) else "–"
        table.add_row(str(k + 1), f"{pk * 1e3:.3f}", f"{tk:.3f}", f"{lag:.3f}" if driven else "–", res)
    console.print(table)
    if not driven:
        console.print(undriven_note(f"--voltage {voltage_V:g} V", voltage_V), soft_wrap=True)
    creep = f"{sim.creep:+.1f} %" if driven and math.isfinite(sim.creep) else "–"
    console.print(f"max displacement {sim.max_displacement * 1e3:.3f} mm (L_d = {sim.params.L_d * 1e3:g} mm), "
                  f"max stretch {sim.max_stretch:.4f}, creep {creep}, "
                  f"peak true field {mv_per_m(sim.peak_field)} MV/m, peak current {sim.peak_current * 1e6:.2f} µA")
    if sim.trace.failed:
        raise fail(f"specimen failed: {sim.trace.failure}", code=1)


class LsdeaTest(StrEnum):
    isopotential = "isopotential"
    isometric = "isometric"
    isotonic = "isotonic"
    map = "map"  # the design map over λ2p × xp (bench/design_map.py; options: bench design-map)


@clean_errors
def simulate_lsdea(
    ctx: typer.Context,
    test: Annotated[LsdeaTest, typer.Argument(help="Test configuration.")] = LsdeaTest.isotonic,
    prototype: Annotated[int, typer.Option(help="Prototype #1–#3 (Table 2).", min=1, max=3)] = 1,
    voltage: Annotated[str, _qopt("Voltage [V]: constant (isopotential), sine amplitude (isometric) or "
                                  "raised-cosine peak (isotonic). 0–10 kV; or with a unit: 5kV.")] = "5000",
    frequency: Annotated[str | None, _qopt("Drive frequency [Hz] (default 0.5 isopotential, 1 otherwise). "
                                           "0.01–100 Hz; or with a unit: '2 Hz'.")] = None,
    mass: Annotated[str, _qopt("Hung mass [kg] (isotonic). 0–2 kg; or with a unit: '180 g'.")] = "0.18",
    position: Annotated[str, _qopt("Blocked aperture [mm] (isometric). 45–200 mm; or with a unit: "
                                   "'0.1 m'.")] = "100",
    stroke: Annotated[str, _qopt("Crest-to-trough Δx from 50 mm [mm] (isopotential). 1–120 mm; or with a "
                                 "unit: '9 cm'.")] = "90",
    cycles: Annotated[int, typer.Option(help="Number of cycles.", min=2, max=1000)] = 10,
) -> None:
    """LS-DEA (Model B) in one of the paper's three test configurations, with its figure of merit; or `map`,
    the design map (Moretti Fig. 2) with the prototypes on it."""
    if test is LsdeaTest.map:
        from bench.cli.analysis import show_design_map

        _map_takes_no_options(ctx)
        show_design_map()
        return
    from bench.app.simulate import simulate_lsdea as simulate

    voltage_V = option_si(voltage, "V", "--voltage", 0, 10_000)
    mass_kg = option_si(mass, "kg", "--mass", 0, 2)
    position_m = option_si(position, "mm", "--position", 45, 200)
    stroke_m = option_si(stroke, "mm", "--stroke", 1, 120)
    frequency_Hz = None if frequency is None else option_si(frequency, "Hz", "--frequency", 0.01, 100)
    with console.status(f"simulating LS-DEA #{prototype} ({test.value})…"):
        sim = simulate(test.value, prototype, voltage_V, frequency=frequency_Hz, mass=mass_kg,
                       position=position_m, stroke=stroke_m, cycles=cycles)
    fig = sim.figure
    figure = (f"hysteresis loss of the last cycle {100 * fig['loss']:.1f} %" if "loss" in fig else
              f"force crest-to-trough {fig['force_swing']:.4f} N" if "force_swing" in fig else
              f"detrended crest-to-trough displacement {fig['swing'] * 1e3:.3f} mm, mean position "
              f"{fig['mean_position'] * 1e3:.2f} mm")
    console.print(f"LS-DEA #{prototype} {test.value}: {figure}")
    console.print(f"force {sim.force_range[0]:.3f} … {sim.force_range[1]:.3f} N, peak true field "
                  f"{mv_per_m(sim.peak_field)} MV/m, smallest breakdown margin E_B/E = "
                  + (f"{sim.margin:.2f}×, " if math.isfinite(sim.margin) else "– (no field), ")
                  + f"tension lost in {100 * sim.tension_lost:.1f} % of samples")
    if sim.trace.failed:
        raise fail(f"specimen failed: {sim.trace.failure}", code=1)


def _map_takes_no_options(ctx: typer.Context) -> None:
    """`simulate lsdea map` covers every design at the map's voltages: a design option given with it is refused,
    never ignored without a word."""
    given = [f"--{name}" for name in ("prototype", "voltage", "frequency", "mass", "position", "stroke", "cycles")
             if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"]
    if given:
        raise fail(f"simulate lsdea map takes no {', '.join(given)}: the map covers every design (prototypes "
                   "#1–#3 marked on it); its voltages: bench design-map --voltages 0,3,5,7")


RigArg = Annotated[Path, typer.Argument(help="Rig file (TOML), e.g. rigs/thesis-sim.toml.", autocompletion=rig_files)]


def _endpoint_table(title: str, endpoints: dict[str, Endpoint]) -> Table:
    table = Table(title=title)
    for col in ("name", "protocol", "endpoint", "units / details"):
        table.add_column(col)
    for ep in endpoints.values():
        table.add_row(ep.name, ep.protocol, ep.address, ep.details)
    return table


@clean_errors
def sim_serve(
    rig_file: Annotated[Path | None, typer.Argument(
        help="Rig file (TOML), e.g. rigs/thesis-sim.toml (with --replay: default the record's own rig).",
        autocompletion=rig_files)] = None,
    replay: Annotated[Path | None, typer.Option(
        help="Serve this run file's measured signals (laser, monitors, load cell, motor position) through the "
             "twins, on the record's time base from the moment they start, noise off.")] = None,
    write_rig: Annotated[Path | None, typer.Option(
        help="Also write a rig file pointing at the running twins (for other processes).")] = None,
    duration: Annotated[str | None, _qopt("Stop after this time [s], at least 0.1 s (default: Ctrl-C); "
                                                 "or with a unit: '30 s'.")] = None,
    wire_time: Annotated[bool, typer.Option(
        "--wire-time/--no-wire-time",
        help="Serve at the rig file's baud rates with the devices' turnarounds (as the real lines), or at pty "
             "speed (faster than any real bench: for a quick look only).")] = True,
    t7_ports: Annotated[bool, typer.Option(
        "--t7-ports", help="Serve the T7 twin on the T7's own ports, 502 (Modbus TCP) and 702 (stream), for "
                           "clients that assume them; where ports below 1024 need privileges this process lacks, "
                           "on 10502/10702.")] = False,
) -> None:
    """Start every simulated instrument of a rig (wall clock) and print where to connect; Ctrl-C stops."""
    from bench.app.sim import Serving, serve_rig

    def started(served: Serving) -> None:
        if served.replay is not None:
            console.print(f"replaying {served.replay} (noise off; what the host commands moves nothing)")
        console.print(_endpoint_table(f"simulated rig {served.rig.name} ({served.rig.specimen.kind})",
                                      served.endpoints))
        if served.client_rig is not None:
            console.print(f"rig file for clients: {served.client_rig}")
        console.print("wire time: " + ("real (the rig file's baud rates, RTU gaps and device turnarounds)"
                                       if served.wire_time else "off (pty speed: faster than any real line)"))
        console.print("serving; Ctrl-C to stop" + (f" (or after {served.duration:g} s)" if served.duration else ""))

    duration_s = None if duration is None else option_si(duration, "s", "--duration", 0.1)
    serve_rig(rig_file, write_rig=write_rig, duration=duration_s, wire_time=wire_time, t7_ports=t7_ports,
              replay=replay, on_started=started)
    console.print("simulated rig stopped")


@clean_errors
def devices_check(rig_file: RigArg) -> None:
    """Connect to every instrument of a rig, identify it, print its state and a first reading."""
    from bench.rig import load_rig
    from bench.runtime.devices import check_instruments, failures
    from bench.runtime.sim_rig import SimRig

    rig = load_rig(rig_file)
    sim = SimRig(rig) if rig.simulated else None
    try:
        if sim is not None:
            sim.start()
        with console.status(f"checking the instruments of {rig.name}…"):
            rows = check_instruments(rig, sim.port_map() if sim else None)
    finally:
        if sim is not None:
            sim.stop()
    table = Table(title=f"{rig.name}: {'simulated' if rig.simulated else 'real'} instruments")
    for col in ("instrument", "", "identity", "state", "first reading"):
        table.add_column(col)
    for r in rows:
        if r.ok:
            table.add_row(r.role, "[green]ok[/]", r.identity, r.state, r.reading)
        else:
            table.add_row(r.role if r.instrument else "(closing)", "[red]FAIL[/]", "", r.error, "")
    console.print(table)
    if said := failures(rows):
        raise fail(said, code=1)


class BenchmarkSet(StrEnum):
    physics = "physics"
    acquisition = "acquisition"
    run = "run"
    fit = "fit"
    kernels = "kernels"
    cluster = "cluster"
    daq = "daq"
    faults = "faults"
    startup = "startup"
    export = "export"
    watch = "watch"
    all = "all"


@clean_errors
def benchmark(
    which: Annotated[BenchmarkSet, typer.Argument(help="Which figures.")] = BenchmarkSet.all,
    quick: Annotated[bool, typer.Option(help="One repeat / short runs; the slow reference timings (the generic "
                                        "scipy candidate) only in the full run.")] = False,
    sizes: Annotated[str, typer.Option(help="The cluster set's worker counts, each against the in-process fit on as "
                                       "many numba threads (1 is always measured), e.g. 1,2,4,8,16 on a 16-core "
                                       "machine.")] = "1,2",
    copies: Annotated[int, typer.Option(min=1, max=16, help="The cluster set's campaign: its records this many "
                                        "times over (2: 24 records), to show scale-out where there are more "
                                        "records than workers.")] = 1,
    json_out: JsonOpt = False,
) -> None:
    """Measure the integrators, the acquisition rates through the drivers, whole runs, the fitter and the command
    line's start-up; run the fault matrix (every fault × every phase × both rig kinds: is the plant's output at 0 V
    when the run returns?)."""
    from bench.benchmarks.cluster import parse_sizes

    try:
        scale = parse_sizes(sizes)
    except ValueError as e:
        raise fail(str(e)) from None
    with json_mode(json_out):
        collected = _benchmark(which, quick, scale, copies)
    if json_out:
        print_json(collected)


# the sets of figures in the order they run: (set, what the progress line says, title of the table)
BENCHMARK_SETS = (
    (BenchmarkSet.physics, "the integrators (includes JIT warm-up)", "physics integrators (one core, best of repeats)"),
    (BenchmarkSet.acquisition, "acquisition through the drivers",
     "acquisition through the drivers (simulated rigs on ptys)"),
    (BenchmarkSet.run, "whole runs", "whole runs: engine, recorder"),
    (BenchmarkSet.fit, "identification", "identification (thesis record, all numba threads unless a row says one)"),
    (BenchmarkSet.kernels, "the kernels and the thesis fit against their reference paths",
     "identification kernels and thesis fit against their reference paths (all numba threads unless a row says one)"),
    (BenchmarkSet.cluster, "the distributed fit (--workers N against in-process on N threads)",
     "distributed fit: the campaign search in-process on N numba threads against dask --workers N"),
    (BenchmarkSet.daq, "the hardware-timed rigs", "hardware-timed rigs (LabJack T7 twin)"),
    (BenchmarkSet.startup, "the command line's start-up",
     'start-up of the command line against python -c "import typer, rich"'),
    (BenchmarkSet.export, "the export's and the report's memory",
     "export and report: peak memory against the run's length"),
    (BenchmarkSet.watch, "bench watch", "bench watch: server CPU and lag during a run, page data"),
    (BenchmarkSet.faults, "the fault matrix (faults that a wall-clock timeout, a signal or a stall detects run in "
     "real time)", "fault matrix"),
)


# sets that `bench benchmark --quick` leaves out unless named: the cluster's worker start-up and runs take a third of
# the quick run's 60 s
FULL_ONLY = (BenchmarkSet.cluster,)
# sets that run only when named: the kernels' rows are the fit set's too (named alone, a second machine's CPU figures
# in minutes, without the fit set's generic scipy candidate, campaign, trusted fit and coverage)
NAMED_ONLY = (BenchmarkSet.kernels,)


def _benchmark(which: BenchmarkSet, quick: bool, sizes: tuple[int, ...] = (1, 2), copies: int = 1) -> dict[str, object]:
    """Run and print the chosen benchmark sets, with a progress line (set k of n, elapsed); returns their figures
    by set."""
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    chosen = [entry for entry in BENCHMARK_SETS if which is entry[0]
              or (which is BenchmarkSet.all and entry[0] not in NAMED_ONLY and not (quick and entry[0] in FULL_ONLY))]
    collected: dict[str, object] = {}
    t0 = time.perf_counter()
    took: list[str] = []
    with Progress(TextColumn("[{task.completed}/{task.total}] benchmarking {task.description}…"), BarColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task("", total=len(chosen))
        for kind, doing, title in chosen:
            bar.update(task, description=doing)
            t_set = time.perf_counter()
            if kind is BenchmarkSet.physics:
                collected["physics"] = _physics(quick)
            elif kind is BenchmarkSet.faults:
                collected["faults"] = _fault_matrix(quick)
            else:
                collected[title] = _figures(kind, title, quick, sizes, copies)
            took.append(f"{kind.value} {time.perf_counter() - t_set:.1f}")
            bar.advance(task)
    console.print(f"benchmark {which.value}{' --quick' if quick else ''}: {len(chosen)} set(s) in "
                  f"{time.perf_counter() - t0:.1f} s ({', '.join(took)} s)")
    return collected


def _physics(quick: bool) -> list[dict[str, object]]:
    """Run and print the integrators' figures; returns them."""
    from bench.benchmarks.machine import cpu
    from bench.benchmarks.main import run_all

    results = run_all(quick=quick)
    machine = cpu()
    table = Table(title="physics integrators (one core, best of repeats)", caption=f"on {machine.label}")
    for col in ("case", "simulated [s]", "wall [s]", "× real time", "target", ""):
        table.add_column(col, justify="left" if col == "case" else "right")
    for r in results:
        mark = "" if not r.target else ("[green]ok[/]" if r.passed else "[red]below target[/]")
        table.add_row(r.name, f"{r.simulated:g}", f"{r.wall:.4f}", f"{r.speed:.0f}",
                      f"≥ {r.target:g}" if r.target else "–", mark)
    console.print(table)
    return [{"case": r.name, "simulated_s": r.simulated, "wall_s": r.wall, "speed_x": r.speed,
             "target_x": r.target or None, "passed": r.passed if r.target else None, "cpu": machine.as_dict()}
            for r in results]


def _figures(kind: BenchmarkSet, title: str, quick: bool, sizes: tuple[int, ...],
             copies: int = 1) -> list[dict[str, object]]:
    """Run and print one set of figures (acquisition, run, fit, kernels, cluster, daq, export, watch, startup);
    returns them."""
    run_all: Callable[..., list[Figure]]
    if kind is BenchmarkSet.acquisition:
        from bench.benchmarks.acquisition import run_all
    elif kind is BenchmarkSet.run:
        from bench.benchmarks.run import run_all
    elif kind is BenchmarkSet.fit:
        from bench.benchmarks.fit import run_all
    elif kind is BenchmarkSet.kernels:
        from bench.benchmarks.fit import kernels as run_all
    elif kind is BenchmarkSet.cluster:
        from bench.benchmarks import cluster

        def run_all(quick: bool) -> list[Figure]:
            return cluster.run_all(quick, sizes, copies)
    elif kind is BenchmarkSet.daq:
        from bench.benchmarks.daq import run_all
    elif kind is BenchmarkSet.export:
        from bench.benchmarks.export import run_all
    elif kind is BenchmarkSet.watch:
        from bench.benchmarks.watch import run_all
    else:
        from bench.benchmarks.startup import run_all
    from bench.benchmarks.machine import cpu

    figures = run_all(quick=quick)
    machine = cpu()
    ratios = [f.unit in RATIO_UNITS for f in figures]
    table = Table(title=title, caption=f"on {machine.label}" if any(ratios) else None)
    for col in ("path", "value", "unit", "notes"):
        table.add_column(col, justify="right" if col == "value" else "left")
    for f in figures:
        table.add_row(f.name, f"{f.value:,.1f}" if f.value < 100 else f"{f.value:,.0f}", f.unit, f.note)
    console.print(table)
    where = {"cpu": machine.as_dict()}
    return [{"name": f.name, "value": f.value, "unit": f.unit, "note": f.note, **(where if r else {})}
            for f, r in zip(figures, ratios, strict=True)]


RATIO_UNITS = ("×", "× real time")  # a figure in these is a ratio: its JSON row names the CPU it was measured on


def _seconds(x: float | None) -> str:
    return "–" if x is None else f"{x:.3f}"


def _fault_matrix(quick: bool) -> dict[str, object]:
    """Run and print the fault matrix: one row per case, then the summary; returns cases and summary."""
    from dataclasses import asdict

    from bench.benchmarks import faults

    cases = faults.run_all(quick=quick)
    table = Table(title=f"fault matrix: |output| at the plant (0 V: ≤ {faults.ZERO_V:g} V); times from the fault, "
                  "rig clock")
    for col in ("mode", "rig", "fault", "phase", "clock", "0 V at return", "→ 0 V [s]", "→ ramp [s]",
                "returned [s]", "peak after [V]", "back on [V]", "end"):
        table.add_column(col, justify="right" if "[" in col else "left")
    for c in cases:
        zero = "[green]yes[/]" if c.zero_at_return else ("–" if not c.injected else "[red]NO[/]")
        back = f"[red]{c.reenergised_V:.0f}[/]" if c.reenergised_V > faults.ZERO_V else "–"
        table.add_row(c.mode, c.rig, c.fault, c.phase, c.clock, zero, _seconds(c.to_zero_s), _seconds(c.ramp_s),
                      _seconds(c.returned_s), f"{c.peak_after_V:.0f}", back, f"{c.state}: {c.reason}")
    console.print(table)
    s = faults.summarise(cases)
    for line in faults.summary_lines(s):
        console.print(line, markup=False, highlight=False)
    return {"cases": [asdict(c) for c in cases], "summary": {**asdict(s), "all_safe": s.all_safe}}


def register(app: typer.Typer) -> dict[str, typer.Typer]:
    """Put the callback (--version …), the simulate, sim and devices groups and ``benchmark`` on ``app``.

    Returns the groups by name: other modules add their commands to ``devices``.
    """
    # rich_markup_mode=None: help texts are plain text ("Simulated time [s]." keeps its unit)
    simulate_app = typer.Typer(help="Simulate the papers' specimens with the physical models (no instruments).",
                               no_args_is_help=True)
    sim_app = typer.Typer(help="Simulated rigs: twins of every instrument on real ports.", no_args_is_help=True)
    devices_app = typer.Typer(help="The instruments of a rig (real or simulated).", no_args_is_help=True)
    for sub in (simulate_app, sim_app, devices_app):
        sub.rich_markup_mode = None  # plain help text, as for the main app
    app.add_typer(simulate_app, name="simulate")
    app.add_typer(sim_app, name="sim")
    app.add_typer(devices_app, name="devices")
    app.callback()(main)
    simulate_app.command("thesis")(simulate_thesis)
    simulate_app.command("lsdea")(simulate_lsdea)
    sim_app.command("serve")(sim_serve)
    devices_app.command("check")(devices_check)
    app.command()(benchmark)
    return {"simulate": simulate_app, "sim": sim_app, "devices": devices_app}
