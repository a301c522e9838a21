"""The main options and the commands of no other group: simulate, sim, devices check, benchmark."""

from __future__ import annotations

import contextlib
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from bench.cli.common import JsonOpt, Table, _version, clean_errors, console, fail, json_mode, print_json
from bench.cli.completion import rig_files
from bench.units import option_si


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


SIMULATE_MAX_S = 600.0  # `bench simulate`: simulated time (the offline solver keeps 10 kHz output in memory)
SIMULATE_MAX_CYCLES = 200  # `bench simulate thesis`: drive cycles (the solver's cost grows with them: ~20 ms each)
SIMULATE_MAX_SQUARE_CYCLES = 5  # the offline solver resolves every square-wave edge: 0.2–1.4 s per cycle


def _simulation_size(duration: float) -> None:
    """Refuse, in one line, a simulation beyond the documented size (it would take minutes and gigabytes)."""
    if not duration <= SIMULATE_MAX_S:
        raise ValueError(f"simulated time {duration:g} s exceeds {SIMULATE_MAX_S:g} s: fewer --cycles or a "
                         "higher --frequency")


def _qopt(help_text: str) -> Any:
    """A typer option taking a quantity (``7kV``) or a plain number in the unit its help names."""
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
    temperature: Annotated[str, _qopt("Temperature [K]. 150–450 K; or with a unit: '296 K'.")] = "296",
    duration: Annotated[str, _qopt(f"Simulated time [s]. Up to {SIMULATE_MAX_S:g} s; or with a unit: "
                                   "'20 s'.")] = "20",
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
    import numpy as np

    from bench.analysis.thesis import cycle_figures
    from bench.models.membrane import MembraneParams
    from bench.models.membrane_runs import simulate_membrane
    from bench.waveforms import Waveform

    voltage_V = option_si(voltage, "V", "--voltage", 0, 12_000)
    frequency_Hz = 1 / 9 if frequency is None else option_si(frequency, "Hz", "--frequency", 1e-4, 1000)
    temperature_K = option_si(temperature, "K", "--temperature", 150, 450)
    duration_s = option_si(duration, "s", "--duration", 1e-3, SIMULATE_MAX_S)
    if method not in ("rodas", "radau", "fixed"):
        raise ValueError(f"--method must be 'rodas', 'radau' or 'fixed', got {method!r}")
    max_cycles = SIMULATE_MAX_SQUARE_CYCLES if waveform is WaveKindOption.square and method != "fixed" \
        else SIMULATE_MAX_CYCLES
    if frequency_Hz * duration_s > max_cycles:
        raise ValueError(f"--frequency {frequency_Hz:g} Hz × --duration {duration_s:g} s = "
                         f"{frequency_Hz * duration_s:g} cycles exceed {max_cycles} for this waveform and method: "
                         "shorten the run")
    params = MembraneParams(electrostriction=electrostriction.value)
    wave = Waveform(waveform.value, voltage_V, frequency_Hz)
    with console.status("simulating the thesis membrane…"):
        tr = simulate_membrane(params, wave, duration_s, T=temperature_K, method=method)  # type: ignore[arg-type]
    figs = cycle_figures(tr.t, tr.displacement, tr.voltage, frequency_Hz)
    table = Table(title=f"Thesis membrane: {voltage_V / 1e3:g} kV {waveform.value}, {frequency_Hz:.4g} Hz, "
                        f"{temperature_K:g} K, {duration_s:g} s")
    table.add_column("cycle", justify="right")
    table.add_column("peak u [mm]", justify="right")
    table.add_column("at t [s]", justify="right")
    table.add_column("lag [s]", justify="right")
    table.add_column("u at cycle end [mm]", justify="right")
    for k, (pk, tk, lag) in enumerate(zip(figs.peaks, figs.peak_times, figs.lags, strict=True)):
        res = f"{figs.residuals[k] * 1e3:.3f}" if k < len(figs.residuals) else "–"
        table.add_row(str(k + 1), f"{pk * 1e3:.3f}", f"{tk:.3f}", f"{lag:.3f}", res)
    console.print(table)
    valid = np.isfinite(tr.stretch)
    creep = figs.creep * 100 if figs.whole > 1 and figs.peaks[0] != 0 else 0.0  # no drive, no creep
    console.print(f"max displacement {np.nanmax(tr.displacement) * 1e3:.3f} mm (L_d = {params.L_d * 1e3:g} mm), "
                  f"max stretch {np.nanmax(tr.stretch):.4f}, creep {creep:+.1f} %, "
                  f"peak true field {np.nanmax(np.abs(tr.field[valid])) / 1e6:.1f} MV/m, "
                  f"peak current {np.nanmax(np.abs(tr.current[valid])) * 1e6:.2f} µA")
    if tr.failed:
        raise fail(f"specimen failed: {tr.failure}", code=1)


class LsdeaTest(StrEnum):
    isopotential = "isopotential"
    isometric = "isometric"
    isotonic = "isotonic"
    map = "map"  # the design map over λ2p × xp (bench/design_map.py; options: bench design-map)


@clean_errors
def simulate_lsdea(
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
        from bench.cli.analysis import run_design_map

        run_design_map()
        return
    import numpy as np

    from bench.analysis.cycles import crest_to_trough, hysteresis_loss, last_cycles
    from bench.models.lozenge import LozengeParams
    from bench.models.lozenge_runs import simulate_lozenge
    from bench.waveforms import Waveform

    voltage_V = option_si(voltage, "V", "--voltage", 0, 10_000)
    mass_kg = option_si(mass, "kg", "--mass", 0, 2)
    position_m = option_si(position, "mm", "--position", 45, 200)
    stroke_m = option_si(stroke, "mm", "--stroke", 1, 120)
    params = LozengeParams.prototype(prototype, hung_mass=mass_kg if test is LsdeaTest.isotonic else 0.0)
    frequency_Hz = (0.5 if test is LsdeaTest.isopotential else 1.0) if frequency is None else \
        option_si(frequency, "Hz", "--frequency", 0.01, 100)
    duration = cycles / frequency_Hz
    _simulation_size(duration)
    with console.status(f"simulating LS-DEA #{prototype} ({test.value})…"):
        if test is LsdeaTest.isopotential:
            dx, w = stroke_m, 2 * np.pi * frequency_Hz
            tr = simulate_lozenge(params, "imposed", lambda t: np.full_like(t, voltage_V), duration,
                                  position=lambda t: 0.05 + dx / 2 * (1 - np.cos(w * t)),
                                  velocity=lambda t: dx / 2 * w * np.sin(w * t))
            m = last_cycles(tr.t, frequency_Hz, 1)
            figure = f"hysteresis loss of the last cycle {100 * hysteresis_loss(tr.position[m], tr.force[m]):.1f} %"
        elif test is LsdeaTest.isometric:
            tr = simulate_lozenge(params, "blocked", Waveform("sine", voltage_V, frequency_Hz), duration,
                                  position=position_m)
            m = last_cycles(tr.t, frequency_Hz, 1)
            figure = f"force crest-to-trough {crest_to_trough(tr.t[m], tr.force[m]):.4f} N"
        else:
            tr = simulate_lozenge(params, "hung", Waveform("raised_cosine", voltage_V, frequency_Hz), duration)
            m = last_cycles(tr.t, frequency_Hz, min(3, cycles))
            swing = crest_to_trough(tr.t[m], tr.position[m], frequency_Hz)
            figure = (f"detrended crest-to-trough displacement {swing * 1e3:.3f}"
                      f" mm, mean position {np.mean(tr.position[m]) * 1e3:.2f} mm")
    console.print(f"LS-DEA #{prototype} {test.value}: {figure}")
    with np.errstate(divide="ignore"):
        margin = np.nanmin(tr.breakdown_field / np.abs(tr.field))
    console.print(f"force {np.nanmin(tr.force):.3f} … {np.nanmax(tr.force):.3f} N, peak true field "
                  f"{np.nanmax(np.abs(tr.field)) / 1e6:.1f} MV/m, smallest breakdown margin E_B/E = {margin:.2f}×, "
                  f"tension lost in {100 * np.mean(tr.tension_lost):.1f} % of samples")
    if tr.failed:
        raise fail(f"specimen failed: {tr.failure}", code=1)


RigArg = Annotated[Path, typer.Argument(help="Rig file (TOML), e.g. rigs/thesis-sim.toml.", autocompletion=rig_files)]


def _endpoint_table(title: str, endpoints: dict) -> Table:
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
    import math
    import signal
    import threading
    import time

    from bench.rig import load_rig
    from bench.runtime.devices import served_rig
    from bench.runtime.devices import write_rig as write_rig_file
    from bench.runtime.replay import replay_rig
    from bench.runtime.sim_rig import T7_PORTS, SimRig

    duration_s = None if duration is None else option_si(duration, "s", "--duration", 0.1)
    if rig_file is not None:
        rig = load_rig(rig_file)
        if not rig.simulated:
            raise ValueError(f"rig file {rig_file}: simulated = false; `bench sim serve` needs a simulated rig")
    elif replay is not None:
        rig = replay_rig(replay)
    else:
        raise ValueError("bench sim serve: give a rig file, or --replay RUN.h5 (its own rig)")
    if replay is not None:
        rig = rig.model_copy(update={"simulation": rig.simulation.model_copy(update={"replay": str(replay)})})
    stop = threading.Event()
    # both set explicitly: a process started with SIGINT ignored (a background job of a non-interactive shell)
    # inherits the ignore, and Python then installs no KeyboardInterrupt handler of its own
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    sim = SimRig(rig, timing="real" if wire_time else "none", daq_ports=T7_PORTS if t7_ports else (0, 0))
    try:
        endpoints = sim.start()
        if sim.replay is not None:  # record time 0: now
            sim.replay.anchor(sim.clock.now())
            console.print(f"replaying {replay} (noise off; what the host commands moves nothing)")
        console.print(_endpoint_table(f"simulated rig {rig.name} ({rig.specimen.kind})", endpoints))
        if write_rig is not None:
            # the clients' rig is real instruments: the replay is this process's business, not theirs
            plain = rig.model_copy(update={"simulation": rig.simulation.model_copy(update={"replay": None})})
            write_rig_file(served_rig(plain, sim.port_map()), write_rig)
            console.print(f"rig file for clients: {write_rig}")
        console.print("wire time: " + ("real (the rig file's baud rates, RTU gaps and device turnarounds)"
                                       if wire_time else "off (pty speed: faster than any real line)"))
        console.print("serving; Ctrl-C to stop" + (f" (or after {duration_s:g} s)" if duration_s else ""))
        with contextlib.suppress(KeyboardInterrupt):
            # short waits: a Ctrl-C the kernel hands to one of the twins' threads only sets Python's flag, and a
            # main thread blocked in one long wait would not run the handler until the wait ends (never, without
            # --duration)
            end = math.inf if duration_s is None else time.monotonic() + duration_s
            while not stop.wait(min(0.1, max(end - time.monotonic(), 0.0))) and time.monotonic() < end:
                pass
    finally:
        sim.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    console.print("simulated rig stopped")


@clean_errors
def devices_check(rig_file: RigArg) -> None:
    """Connect to every instrument of a rig, identify it, print its state and a first reading."""
    from bench.rig import load_rig
    from bench.runtime.devices import check_instruments
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
            table.add_row(r.role, "[red]FAIL[/]", "", r.error, "")
    console.print(table)
    failed = [r for r in rows if not r.ok]
    if failed:
        raise fail(f"{len(failed)} of {len(rows)} instruments failed: " + "; ".join(r.error for r in failed), code=1)


class BenchmarkSet(StrEnum):
    physics = "physics"
    acquisition = "acquisition"
    run = "run"
    fit = "fit"
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
    json_out: JsonOpt = False,
) -> None:
    """Measure the integrators, the acquisition rates through the drivers, whole runs, the fitter and the command
    line's start-up; run the fault matrix (every fault × every phase × both rig kinds: is the plant's output at 0 V
    when the run returns?)."""
    with json_mode(json_out):
        collected = _benchmark(which, quick)
    if json_out:
        print_json(collected)


# the sets of figures in the order they run: (set, what the progress line says, title of the table)
BENCHMARK_SETS = (
    (BenchmarkSet.physics, "the integrators (includes JIT warm-up)", "physics integrators (one core, best of repeats)"),
    (BenchmarkSet.acquisition, "acquisition through the drivers",
     "acquisition through the drivers (simulated rigs on ptys)"),
    (BenchmarkSet.run, "whole runs", "whole runs: engine, recorder"),
    (BenchmarkSet.fit, "identification", "identification (thesis record, 2 cores)"),
    (BenchmarkSet.daq, "the hardware-timed rigs", "hardware-timed rigs (LabJack T7 twin)"),
    (BenchmarkSet.startup, "the command line's start-up",
     'start-up of the command line against python -c "import typer, rich"'),
    (BenchmarkSet.export, "the export's memory", "export: peak memory against the run's length"),
    (BenchmarkSet.watch, "bench watch", "bench watch: server CPU and lag during a run, page data"),
    (BenchmarkSet.faults, "the fault matrix (faults that a wall-clock timeout, a signal or a stall detects run in "
     "real time)", "fault matrix"),
)


def _benchmark(which: BenchmarkSet, quick: bool) -> dict[str, object]:
    """Run and print the chosen benchmark sets, with a progress line (set k of n, elapsed); returns their figures
    by set."""
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    chosen = [entry for entry in BENCHMARK_SETS if which in (entry[0], BenchmarkSet.all)]
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
                collected[title] = _figures(kind, title, quick)
            took.append(f"{kind.value} {time.perf_counter() - t_set:.1f}")
            bar.advance(task)
    console.print(f"benchmark {which.value}{' --quick' if quick else ''}: {len(chosen)} set(s) in "
                  f"{time.perf_counter() - t0:.1f} s ({', '.join(took)} s)")
    return collected


def _physics(quick: bool) -> list[dict[str, object]]:
    """Run and print the integrators' figures; returns them."""
    from bench.benchmarks.main import run_all

    results = run_all(quick=quick)
    table = Table(title="physics integrators (one core, best of repeats)")
    for col in ("case", "simulated [s]", "wall [s]", "× real time", "target", ""):
        table.add_column(col, justify="left" if col == "case" else "right")
    for r in results:
        mark = "" if not r.target else ("[green]ok[/]" if r.passed else "[red]below target[/]")
        table.add_row(r.name, f"{r.simulated:g}", f"{r.wall:.4f}", f"{r.speed:.0f}",
                      f"≥ {r.target:g}" if r.target else "–", mark)
    console.print(table)
    return [{"case": r.name, "simulated_s": r.simulated, "wall_s": r.wall, "speed_x": r.speed,
             "target_x": r.target or None, "passed": r.passed if r.target else None} for r in results]


def _figures(kind: BenchmarkSet, title: str, quick: bool) -> list[dict[str, object]]:
    """Run and print one set of figures (acquisition, run, fit, daq, export, watch, startup); returns them."""
    if kind is BenchmarkSet.acquisition:
        from bench.benchmarks.acquisition import run_all
    elif kind is BenchmarkSet.run:
        from bench.benchmarks.run import run_all
    elif kind is BenchmarkSet.fit:
        from bench.benchmarks.fit import run_all
    elif kind is BenchmarkSet.daq:
        from bench.benchmarks.daq import run_all
    elif kind is BenchmarkSet.export:
        from bench.benchmarks.export import run_all
    elif kind is BenchmarkSet.watch:
        from bench.benchmarks.watch import run_all
    else:
        from bench.benchmarks.startup import run_all
    figures = run_all(quick=quick)
    table = Table(title=title)
    for col in ("path", "value", "unit", "notes"):
        table.add_column(col, justify="right" if col == "value" else "left")
    for f in figures:
        table.add_row(f.name, f"{f.value:,.1f}" if f.value < 100 else f"{f.value:,.0f}", f.unit, f.note)
    console.print(table)
    return [{"name": f.name, "value": f.value, "unit": f.unit, "note": f.note} for f in figures]


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
