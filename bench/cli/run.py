"""CLI commands for protocols and runs: validate, run, inspect, protocol schema."""

from __future__ import annotations

import contextlib
import logging
import math
import shlex
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from bench.cli.common import JsonOpt, Table, clean_errors, console, escape, fail, json_mode, print_json, progress
from bench.cli.completion import protocol_files, protocol_names, rig_files
from bench.cli.logs import log, run_log
from bench.numbers import mv_per_m

if TYPE_CHECKING:
    from bench.app.runs import Inspection, PreparedRun
    from bench.runtime.engine import Engine, RunResult
    from bench.runtime.run import Plan
    from bench.storage.runfile import RunFile

protocol_app = typer.Typer(help="Protocol files: the shipped ones (list, show, copy) and their schema.",
                            no_args_is_help=True, rich_markup_mode=None)

ProtocolArg = Annotated[Path, typer.Argument(help="Protocol file (TOML), e.g. protocols/thesis-identification.toml.",
                                             autocompletion=protocol_files)]
RigOpt = Annotated[Path | None, typer.Option("--rig", help="Run on this rig file instead of the protocol's.",
                                             autocompletion=rig_files)]
SimOpt = Annotated[bool, typer.Option("--sim", help="Use the simulated twin of the rig (default if it is simulated).")]


def _hms(seconds: float) -> str:
    s = round(seconds)
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _plan(protocol_file: Path, rig: Path | None, sim: bool) -> Plan:
    from bench.app.runs import plan_protocol

    try:
        with progress("validating and dry-running the protocol on the model") as done:
            plan = plan_protocol(protocol_file, rig, sim, progress=done)
    except KeyboardInterrupt:  # typer would exit 130 and say nothing
        raise fail("interrupted by Ctrl-C during the validation and dry run; nothing was connected") from None
    _warn(plan)
    return plan


def _warn(plan: Plan) -> None:
    """The plan's warnings: what a real line would refuse, what a software-timed rig records below the asked rate."""
    for problem in plan.link_problems:  # refused on a real rig; the simulated rig rehearses what it would do
        console.print(f"[yellow]warning[/]: {escape(problem)} — a real line would refuse this protocol; the "
                      "simulated rig will show the consequences in wall-clock runs (set-points skipped, the drive and "
                      "the motor's path sampled more coarsely; beyond about twice the host's time, steps run long); "
                      "a virtual-time run takes no wire time then")
    for short in plan.shortfalls:  # what a software-timed rig records below the asked rate: said, never silent
        console.print(f"[yellow]warning[/]: {escape(short)}")
    for said in plan.prediction.warnings:  # what may trip the run but need not (a polled monitor's current)
        console.print(f"[yellow]warning[/]: {escape(said)}")


def _summary(plan: Plan) -> Table:
    pred, rig, prog = plan.prediction, plan.rig, plan.program
    t = Table(title=f"{plan.protocol.protocol.name} on {rig.name} ({'simulated' if rig.simulated else 'real'} rig)",
              show_header=False)
    t.add_column("", style="bold")
    t.add_column("")
    t.add_row("steps", f"{len(prog.segments)} (after expanding sweeps and repeats)")
    t.add_row("duration", f"{_hms(pred.duration)} ({pred.duration:.1f} s)")
    t.add_row("samples", ", ".join(f"{k} {v:,}" for k, v in pred.samples.items()))
    t.add_row("file size", f"≤ {pred.file_bytes / 1e6:.1f} MB uncompressed")
    if pred.dry_run_budget_s > 0:
        from bench.protocol.predict import budget_rule

        t.add_row("dry run", f"the whole program on the model in {pred.dry_run_s:.1f} s (estimated "
                  f"~{pred.dry_run_estimate_s:.{1 if pred.dry_run_estimate_s < 10 else 0}f} s of one core, kernel "
                  "compilation not counted; budget "
                  f"{pred.dry_run_budget_s:.0f} s: "
                  f"{budget_rule()})")
    lim = rig.limits
    t.add_row("peak voltage", f"{pred.peak_voltage:.0f} V (limit {lim.max_voltage_V:.0f} V)")
    from bench.protocol.staircase import staircase_distortion

    stair = staircase_distortion(prog)
    if stair is not None:
        t.add_row("drive", f"set-point staircase at {stair.setpoint_Hz:g} Hz: up to {stair.max_error_V:.0f} V off the "
                  f"waveform (in {escape(stair.step)}); a hardware-timed rig plays the waveform itself")
    elif rig.amplifier is not None and rig.amplifier.drive == "daq" and rig.daq is not None:
        t.add_row("drive", f"hardware-timed: DAC waveform at {rig.daq.scan_rate_Hz:g} scans/s, every analog channel "
                  "on the same scan clock")
    from bench.protocol.program import recording_rates

    t.add_row("recording", recording_rates(prog))
    margin = pred.min_breakdown_margin
    t.add_row("peak true field", f"{mv_per_m(pred.peak_field)} MV/m; closest to breakdown: "
              f"{mv_per_m(pred.field_at_min_margin)} of {mv_per_m(pred.breakdown_at_min_margin)} MV/m "
              f"(margin {margin:.2f}, required ≥ {lim.breakdown_margin:g})" if math.isfinite(margin) else
              f"{mv_per_m(pred.peak_field)} MV/m")
    if pred.motor_range is not None and rig.motor is not None:
        lo, hi = pred.motor_range
        t.add_row("motor travel", f"{lo * 1e3:.1f} … {hi * 1e3:.1f} mm (limits {rig.motor.travel_m[0] * 1e3:.1f} … "
                  f"{rig.motor.travel_m[1] * 1e3:.1f} mm), aperture {prog.aperture(lo) * 1e3:.1f} … "
                  f"{prog.aperture(hi) * 1e3:.1f} mm")
    d_lo, d_hi = pred.displacement_range
    what = "displacement u" if rig.specimen.kind == "membrane" else "aperture x"
    if math.isfinite(d_lo):
        t.add_row(f"predicted {what}", f"{d_lo * 1e3:.2f} … {d_hi * 1e3:.2f} mm")
    f_lo, f_hi = pred.force_range
    if rig.load_cell is not None and math.isfinite(f_lo):
        t.add_row("predicted force", f"{f_lo:.2f} … {f_hi:.2f} N (limit ±{lim.max_force_N:g} N)")
    relax = sorted({s.ramp_down for s in prog.segments if s.kind == "relax" and s.voltage is not None})
    if relax:
        t.add_row("relax steps", "voltage to 0 V over " + ", ".join(f"{r:g} s" for r in relax) +
                  " (ramp_down_s; default 0.5 s or a tenth of the step, at least 10 set-points and the shutdown "
                  "ramp)")
    ops = [s for s in prog.segments if s.changes]
    if ops:
        t.add_row("specimen changes", f"{len(ops)} ({'applied to the model' if rig.simulated else 'operator actions'})")
    return t


@clean_errors
def validate(protocol_file: ProtocolArg, rig: RigOpt = None, sim: SimOpt = False, json_out: JsonOpt = False) -> None:
    """Validate a protocol against its rig and the specimen model; print what the run will do."""
    with json_mode(json_out):
        plan = _plan(protocol_file, rig, sim)
    if json_out:
        pred = plan.prediction
        print_json({"protocol": plan.protocol.protocol.name, "rig": plan.rig.name, "simulated": plan.rig.simulated,
                    "valid": True, "steps": len(plan.program.segments), "duration_s": pred.duration,
                    "samples": pred.samples, "file_bytes_max": pred.file_bytes, "peak_voltage_V": pred.peak_voltage,
                    "voltage_limit_V": plan.rig.limits.max_voltage_V, "peak_field_V_per_m": pred.peak_field,
                    "min_breakdown_margin": pred.min_breakdown_margin,
                    "motor_range_m": list(pred.motor_range) if pred.motor_range is not None else None,
                    "displacement_range_m": list(pred.displacement_range), "force_range_N": list(pred.force_range),
                    "link_problems": list(plan.link_problems), "recording_shortfalls": list(plan.shortfalls),
                    "prediction_warnings": list(pred.warnings), "dry_run_s": pred.dry_run_s,
                    "dry_run_estimate_s": pred.dry_run_estimate_s, "dry_run_budget_s": pred.dry_run_budget_s})
        return
    console.print(_summary(plan))
    console.print("[green]valid[/]: within the rig's and the specimen's limits")


@clean_errors
def run(
    protocol_file: Annotated[Path | None, typer.Argument(
        help="Protocol file (TOML), e.g. protocols/thesis-identification.toml (not with --resume).",
        autocompletion=protocol_files)] = None,
    rig: RigOpt = None,
    sim: SimOpt = False,
    virtual_time: Annotated[bool, typer.Option("--virtual-time", help="Simulated rig only: run as fast as the "
                                               "machine allows (same bytes on the wire).")] = False,
    out: Annotated[Path, typer.Option("--out", help="Folder for the run file.")] = Path("runs"),
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Validate and predict only; touch nothing.")] = False,
    yes: Annotated[bool, typer.Option("--yes", help="Confirm operator actions (specimen changes) without asking.")]
    = False,
    live: Annotated[bool, typer.Option(help="Live view (off: one line per step).")] = True,
    allow_no_watchdog: Annotated[bool, typer.Option(
        "--allow-no-watchdog", help="Run although the rig's set-point module has no communication watchdog "
        "(recorded in the file).")] = False,
    operator_name: Annotated[str | None, typer.Option(
        "--operator", help="Who runs it (replaces the protocol's [protocol] operator); recorded in the run file.")]
    = None,
    specimen_id: Annotated[str | None, typer.Option(
        "--specimen-id", help="Specimen identifier (replaces the protocol's specimen_id); recorded in the run file.")]
    = None,
    note: Annotated[list[str] | None, typer.Option(
        "--note", help="A free note recorded in the run file, after the protocol's notes; repeat for more.")]
    = None,
    resume: Annotated[Path | None, typer.Option(
        "--resume", help="Continue the campaign of this run file (crashed, killed, stopped or tripped) at its first "
        "step that did not complete, into a new file linked to it.")] = None,
    why: Annotated[str | None, typer.Option(
        "--why", help="With --resume on a rig whose interlock latched: why it is safe to go on (resets the latch; "
        "recorded with --operator or the login name).")] = None,
    catalog: Annotated[str | None, typer.Option(
        "--catalog", metavar="URL", help="Run catalogue to record the run in (default: $BENCH_CATALOG, else "
        "catalog.sqlite in the --out folder).")] = None,
    web: Annotated[bool, typer.Option("--web", help="Serve live plots of the run to a browser (bench watch, on "
                                      "127.0.0.1; the page can pause or stop the run).")] = False,
    web_port: Annotated[int, typer.Option("--web-port", help="Port of --web (0: a free one).", min=0,
                                          max=65535)] = 8765,
) -> None:
    """Run a protocol on a rig (simulated by default), streaming everything to one HDF5 file.

    Operator, specimen ID and notes come from the protocol's [protocol] table and these options; they are kept in
    the run file as root attributes (`bench inspect` shows them). While it runs, `bench pause RUN.h5` (or SIGUSR1)
    brings the output to 0 V and holds, `bench resume RUN.h5 --why …` (or SIGUSR2) restarts the step it left."""
    from bench.app.runs import check_executable, claim_output, execute_run, prepare_run, release_claim

    with _before_the_run(), progress("recovering if needed, validating and dry-running the stored protocol"
                                     if resume else "validating and dry-running the protocol on the model") as done:
        prepared = prepare_run(protocol_file, rig=rig, sim=sim, out=out, resume=resume, operator=operator_name,
                               specimen_id=specimen_id, notes=note, why=why, dry_run=dry_run, progress=done,
                               on_recovered=lambda line: console.print(f"recovered: {escape(line)}"))
    _show_prepared(prepared, dry_run)
    if dry_run:
        return
    with _before_the_run(lambda: release_claim(prepared)):
        check_executable(prepared, virtual_time=virtual_time, can_confirm=yes or sys.stdin.isatty())
        claim_output(prepared)  # its file and log: a run started in the same second into --out names the next
    operator = _operator(yes)
    with _unstarted(prepared.path), run_log(prepared.path) as log_file:
        _log_plan(prepared, protocol_file, virtual_time)
        from bench.cli.watch import serving

        with serving(prepared.path, web_port) if web else contextlib.nullcontext():
            result = _execute(prepared, live, lambda on_engine: execute_run(
                prepared, virtual_time=virtual_time, operator=operator, allow_no_watchdog=allow_no_watchdog,
                catalog=catalog, on_engine=on_engine))
        _log_result(result)
    _show_result(result, log_file, prepared.plan.rig.name)
    if result.state != "completed":
        raise typer.Exit(1)


@contextlib.contextmanager
def _unstarted(path: Path) -> Iterator[None]:
    """A run that failed before its file was created (an instrument that did not connect): its one error line says
    that nothing was recorded, and where its log is (the only file the run left)."""
    from bench.cli.logs import log_path
    from drivers.errors import InstrumentError, OperationCancelledError

    try:
        yield
    except OperationCancelledError:  # a stop before the engine ran: its line already says what was kept
        raise
    except (ValueError, OSError, InstrumentError) as exc:
        if path.exists():
            raise
        raise fail(f"{' '.join(str(exc).split())} — nothing recorded, no run file {path.name} written (run log: "
                   f"{log_path(path)})") from None


def _operator(yes: bool) -> Callable[[str], bool]:
    """The operator's confirmation of a specimen change: at the terminal, or given by ``--yes``."""
    def operator(message: str) -> bool:
        from rich.prompt import Confirm

        return yes or Confirm.ask(f"[bold]operator:[/] {message} — done?", console=console)

    return operator


class _StopSignal(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGQUIT before the run started, raised as Ctrl-C's KeyboardInterrupt is (nothing that
    catches Exception keeps it), with its account."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text


@contextlib.contextmanager
def _before_the_run(release: Callable[[], None] | None = None) -> Iterator[None]:
    """Ctrl-C — or SIGTERM, SIGHUP, SIGQUIT — before the run starts (recovering a resumed file, validating,
    dry-running on the model): nothing is connected yet, and typer would end the command with exit 130 (the other
    signals: killed, 143, outside tester) and not a word. One line, and exit 2 as a stop signal while the rig is set
    up (:func:`execute_run`, which says what it was doing): `bench run`'s statuses are 0 (completed), 1 (started,
    did not complete) and 2 (not started), whatever stopped it. No run log: no run has claimed its name yet."""
    import signal
    import threading

    from bench.runtime.engine import STOP_SIGNALS

    def stop(sig: int, _frame: object) -> None:
        raise _StopSignal(STOP_SIGNALS[signal.Signals(sig)])

    old = [(sig, signal.signal(sig, stop)) for sig in STOP_SIGNALS
           if sig != signal.SIGINT and threading.current_thread() is threading.main_thread()]
    try:
        yield
    except KeyboardInterrupt as exc:
        said = exc.text if isinstance(exc, _StopSignal) else "interrupted by Ctrl-C"
        if release is not None:  # a claim made just before the signal (its log, empty) is taken back
            release()
        raise fail(f"{said} before the run started; nothing was connected, no run file or log written") from None
    finally:
        for sig, handler in old:
            signal.signal(sig, handler)


def _show_prepared(prepared: PreparedRun, dry_run: bool = False) -> None:
    """What was done to get the run ready (a reset latch, warnings), the plan's summary, where a campaign resumes;
    that nothing was touched, on a ``dry_run``."""
    from bench.storage.chain import resumed_text

    plan, link = prepared.plan, prepared.link
    if prepared.reset is not None:
        who, why = prepared.reset
        console.print(f"interlock of {escape(plan.rig.name)}: to be reset by {escape(who)} ({escape(why)}) once "
                      "the rig has connected (a start that fails keeps the latch)")
    if link is None:
        _warn(plan)
    console.print(_summary(plan))
    if link is not None:
        seg = plan.program.segments[link.step]
        console.print(f"resuming the campaign of {escape(str(link.previous))} at "
                      f"{resumed_text(link.step, link.steps)}: {escape(seg.name)}; {link.step} step(s) completed there")
    if dry_run:
        console.print("[green]dry run[/]: nothing was touched")


def _log_plan(prepared: PreparedRun, protocol_file: Path | None, virtual_time: bool) -> None:
    """The run's plan, its warnings and metadata, into the run log."""
    plan = prepared.plan
    what = protocol_file if protocol_file is not None else (  # a resume names no protocol file ("bench run None")
        f"--resume {prepared.link.previous}" if prepared.link is not None else plan.protocol.path)
    log.info("bench run %s on rig %s (%s), %s clock → %s", what, plan.rig.name,
             "simulated" if plan.rig.simulated else "real", "virtual" if virtual_time else "wall", prepared.path)
    log.info("planned: %d steps, %.1f s, peak %.0f V", len(plan.program.segments), plan.prediction.duration,
             plan.prediction.peak_voltage)
    for problem in plan.link_problems:
        log.info("link budget warning: %s", problem)
    for short in plan.shortfalls:
        log.info("recording warning: %s", short)
    for key, value in prepared.metadata.items():
        log.info("%s: %s", key.replace("_", " "), value.replace("\n", " | "))


def _show_result(result: RunResult, log_file: Path, rig_name: str) -> None:
    with contextlib.suppress(OSError):  # the terminal went away (SIGHUP): the file holds the whole account
        _print_result(result, rig_name)
        console.print(f"run log: {escape(str(log_file))}")
        if console.quiet:  # -q: the run file's path alone, for scripts (f=$(bench -q run …)), whatever the outcome
            sys.stdout.write(f"{result.path}\n")
            sys.stdout.flush()


def _log_result(result: RunResult) -> None:
    """How the run ended, into the run log (its events are already there: the recorder logs each as it happens)."""
    log.log(logging.INFO if result.state == "completed" else logging.ERROR, "%s: %s; high voltage: %s; %d samples",
            result.state, result.reason, result.safe_path, result.samples)


def _execute(prepared: PreparedRun, live: bool,
             execute: Callable[[Callable[[Engine, object], None] | None], RunResult]) -> RunResult:
    """Execute the run (``execute``, given what to call with the engine), with the live view on a terminal."""
    from rich.live import Live

    from bench.runtime.live import Keys, LiveView, units_of

    plan = prepared.plan
    engines: list[Engine] = []
    title = f"{plan.protocol.protocol.name} → {prepared.path}"
    if plan.rig.simulated and plan.rig.simulation.replay:  # said before the run, and kept in the file (replay_of)
        console.print(f"replay: the twins serve the measured signals of {escape(plan.rig.simulation.replay)} "
                      "(noise off; the commands move nothing; the output verifier checks the recorded monitors)")
    if live and console.is_terminal:
        holder: dict[str, LiveView] = {}
        # keys only where no operator prompt reads the terminal (a real rig's specimen changes ask for Enter)
        keyed = plan.rig.simulated or not any(s.changes for s in plan.program.segments)
        hint = "p: pause (output to 0 V)   r: resume (restarts the step)   Ctrl-C: stop" if keyed else ""

        def attach(engine: Engine, _sim: object) -> None:
            engines.append(engine)
            holder["view"] = LiveView(title, engine.snapshot, units_of(engine.rec.streams), hint)
            live_ctx.update(holder["view"])

        def on_engine(name: str) -> None:
            if engines:
                (engines[0].request_pause if name == "p" else engines[0].request_resume)(
                    f"the operator at the live view (key {name})")

        keys = Keys({"p": lambda: on_engine("p"), "r": lambda: on_engine("r")}) if keyed else contextlib.nullcontext()
        with keys, Live(console=console, refresh_per_second=4, transient=False) as live_ctx:
            return execute(attach)
    # said once the run file exists (the instruments connected): a rig that fails to connect leaves none
    return execute(lambda _engine, _sim: console.print(f"running {escape(title)}"))


def _print_result(result: RunResult, rig_name: str) -> None:
    speed = result.run_time / result.wall_time if result.wall_time > 0 else float("nan")
    colour = "green" if result.state == "completed" else "red"
    console.print(f"[{colour}]{result.state}[/]: {escape(result.reason)}")
    console.print(f"run {result.run_time:.1f} s in {result.wall_time:.1f} s of wall time ({speed:.1f}× real time), "
                  f"{result.samples:,} samples" + (f", {result.overruns} late actions" if result.overruns else "")
                  + (f", [yellow]{result.skipped} set-points skipped[/] (behind the schedule: the skipped events say "
                     "where; validate's link budget says why)" if result.skipped else ""))
    console.print(f"high voltage: {escape(result.safe_path)}")
    if result.latched:
        console.print(f"[red]rig {escape(rig_name)} latched[/]: {escape(result.latched)}; nothing energises it until "
                      f"an operator resets it: bench interlock reset {escape(shlex.quote(rig_name))} --why '…'")
    console.print(f"run file: {escape(str(result.path))}")


@clean_errors
def inspect(run_files: Annotated[list[Path], typer.Argument(help="Run files (.h5), finished or being written.")],
            json_out: JsonOpt = False) -> None:
    """Summarise run files: metadata, state, streams, events (works while a run is being written). Exit 1 when a
    file is incomplete (killed, crashed, recovered or still running); --json of several files is a list."""
    results = [_inspect(p, json_out) for p in run_files]
    if json_out:
        print_json(results[0][0] if len(results) == 1 else [r for r, _ in results])
    if not all(complete for _, complete in results):
        raise typer.Exit(1)


def _inspect(run_file: Path, json_out: bool) -> tuple[dict[str, object] | None, bool]:
    """One file of ``inspect``: its JSON object (``json_out``) or its tables printed; and whether it is complete."""
    from bench.app.runs import inspect_run

    found = inspect_run(run_file)
    if json_out:
        return found.record(), found.complete
    _inspect_tables(found)
    return None, found.complete


def _planned(r: RunFile) -> str:
    """" of X s planned": the file's own part of its protocol — a resumed file runs the steps from where its campaign
    resumed, on a clock from 0 (a completed resumed file read "recorded up to 40.511 s of 60.0 s planned", as if
    incomplete: an outside tester)."""
    from bench.storage.chain import resumed_text

    total = float(r.attrs.get("duration_planned", 0))
    first = int(r.attrs.get("resumed_at_step") or 0)
    held = r.paused_s  # the file's clock runs on through a pause, the plan's does not
    paused = f", plus {held:.1f} s paused" if held >= 0.05 else ""
    if not 0 < first < len(r.program):
        return f" of {total:.1f} s planned{paused}"
    return (f" of {total - float(r.program['t_start'][first]):.1f} s planned{paused} (resumed at "
            f"{resumed_text(first, len(r.program))}; the campaign's {total:.1f} s)")


def _inspect_tables(found: Inspection) -> None:
    """``bench inspect`` on a terminal: the run file's metadata, its streams, its last events and its fits."""
    from bench.storage.runfile import recorded_note

    r, a, run_file, manual = found.run, found.run.attrs, found.file, found.manual
    meta = Table(title="run file", show_header=False)
    meta.add_column("", style="bold")
    meta.add_column("")
    meta.add_row("file", escape(str(run_file)))  # a row, not the title: a title wraps at the table's width
    if found.campaign_text is not None:
        text, broken = found.campaign_text
        meta.add_row("campaign", f"[red]{escape(text)}[/]" if broken else escape(text))
    if found.continued_in is not None:
        meta.add_row("continued", f"continued in {escape(str(found.continued_in))}")
    sha = str(a.get("protocol_sha256", ""))[:12]
    if manual:  # the readings of a manual-control session (bench devices control)
        meta.add_row("session", f"manual control (log {escape(str(a['session_log']))})")
    else:
        meta.add_row("protocol", f"{a.get('protocol_name')} ({a.get('protocol_path')}, sha256 {sha}…)")
    kind = "simulated" if a.get("simulated") else "real"
    wire = str(a.get("wire_time", "real"))
    meta.add_row("rig", f"{a.get('rig_name')} ({kind}, {a.get('clock')} clock"
                 + ("" if wire == "real" else f", wire time {escape(wire)}") + ")")
    meta.add_row("software", str(a.get("software")))
    for key, label in (("operator", "operator"), ("specimen_id", "specimen ID")):
        if a.get(key):
            meta.add_row(label, escape(str(a[key])))
    for k, text in enumerate(found.notes):
        meta.add_row("notes" if k == 0 else "", escape(text))
    meta.add_row("started", str(a.get("start_time")))
    state = r.state if r.complete else f"[red]{r.state_shown} — INCOMPLETE: {r.incomplete_reason}[/]"
    meta.add_row("state", state)
    if r.reason:
        meta.add_row("reason", r.reason)
    if r.end_time:
        meta.add_row("ended", r.end_time)
    meta.add_row("recorded up to", f"{r.updated:.3f} s" + ("" if manual else _planned(r)) + recorded_note(
        r.updated, found.stream_ends))
    console.print(meta)
    streams = Table(title="streams")
    for col in ("stream", "samples", "from [s]", "to [s]", "columns (units): last value"):
        streams.add_column(col)
    for name, s in found.streams.items():
        last = ", ".join(f"{k} ({s.units.get(k, '')}): {v:.6g}" if v is not None else f"{k} ({s.units.get(k, '')})"
                         for k, v in s.last.items())
        streams.add_row(name, f"{s.samples:,}", f"{s.first:.3f}" if s.samples else "–",
                        f"{s.last_t:.3f}" if s.samples else "–", last)
    console.print(streams)
    events = r.event_list()
    console.print(f"{len(events)} events; last: " + "; ".join(f"{t:.2f} s {kind} {escape(text)}"
                                                             for t, _, kind, text in events[-3:]), soft_wrap=True)
    if found.fits_error:
        console.print(f"[yellow]fits not read[/]: {escape(found.fits_error)}", soft_wrap=True)
    for f in found.fits:
        where = "in the run file" if Path(f["file"]) == Path(run_file) else f"in {f['file']}"
        console.print(f"fit {escape(f['group'])} ({escape(where)}): {f.get('model')} model, rms "
                      f"{f.get('rms', float('nan')):.4g}, {len(f.get('records', []))} record(s), {f.get('created')}",
                      soft_wrap=True)


@clean_errors
def recover(run_file: Annotated[Path, typer.Argument(help="Run file (.h5) of a crashed or killed run.")]) -> None:
    """Release the file of a crashed or killed run so that h5py, h5dump and HDFView open it; print what it holds."""
    from bench.storage.recover import recover as recover_file

    for line in recover_file(run_file).lines():
        console.print(escape(line))


RunArg = Annotated[Path, typer.Argument(help="Run file (.h5) of a run under way.")]
WhyOpt = Annotated[str, typer.Option("--why", help="Why (recorded in the run file's events).")]
ResumeWhyOpt = Annotated[str, typer.Option("--why", help="Why it is safe to go on: required (recorded in the run "
                                           "file's events).")]
ByOpt = Annotated[str | None, typer.Option("--operator", help="Who (default: the login name).")]


CONTROL_SETTLE_S = 0.5  # a control word this fresh may not be in the run file yet (looked at every 0.1 s, flushed
# every 0.2 s): bench pause / resume wait until it is this old before reading whether the run is paused


def _running(run_file: Path, asked: str = "pause or resume") -> RunFile:
    """The run file of a protocol run under way; ValueError (one line: nothing to ``asked``) otherwise — suggesting
    `bench run --resume` only where it can continue the campaign."""
    from bench.runtime.run import resume_refusal
    from bench.storage.runfile import open_run

    if not run_file.is_file():
        from bench.storage.absent import absent_run_file

        raise ValueError(absent_run_file(run_file))
    f = open_run(run_file, streams=False)
    if f.attrs.get("session_log"):
        raise ValueError(f"run file {run_file}: a manual-control session, not a protocol run: pause and resume it at "
                         "its prompt (pause, resume WHY...)")
    if f.state != "running" or f.orphaned or f.state_shown not in ("running", "paused"):  # a recovered file's
        # writer is gone too (it is no longer marked open: `pause` said "asked…" to no process, outside tester)
        refusal = resume_refusal(run_file, f)  # (its "…: nothing to resume" is the campaign's, not this command's)
        raise ValueError(f"run file {run_file}: no run is writing it ({f.state_shown}): nothing to {asked}; "
                         + ("to continue its campaign: bench run --resume " + shlex.quote(str(run_file))
                            if refusal is None else refusal.split(": nothing to resume")[0]))
    return f


def _paused(run_file: Path, asked: str) -> tuple[RunFile, str | None]:
    """The run under way in ``run_file`` (:func:`_running`) and the pause it is in (who, from its ``pause`` event),
    or None if it is not paused; read once the last control word has had time to reach the file."""
    from bench.runtime.control import control_path

    with contextlib.suppress(OSError):
        age = time.time() - control_path(run_file).stat().st_mtime
        if 0.0 <= age < CONTROL_SETTLE_S:
            time.sleep(CONTROL_SETTLE_S - age)
    f = _running(run_file, asked)
    held = [(kind, text) for _t, _step, kind, text in f.event_list() if kind in ("pause", "resume")]
    if not held or held[-1][0] != "pause":
        return f, None
    return f, held[-1][1].split(": output", 1)[0]


def _who(operator: str | None) -> str:
    from bench.app.runs import login_name

    return login_name(operator)


def _reason(why: str, needed: str | None = None) -> str:
    from bench.app.runs import reason_given

    return reason_given(why, needed)


@clean_errors
def pause(run_file: RunArg, why: WhyOpt = "", operator: ByOpt = None) -> None:
    """Pause a run from another terminal: output ramped to 0 V, motor held, recording goes on (`bench resume`
    restarts the step it left). The same as SIGUSR1 to the run's process."""
    from bench.runtime.control import write_control

    why, who = _reason(why), _who(operator)  # (what was given, checked before the run file is looked at)
    _f, paused = _paused(run_file, "pause")
    # never refused: the file may not show a resume already on its way (asked meanwhile, or taken after an upload
    # the pause waits on), which this pause then withdraws; the run records what it did with it (found in review)
    path = write_control(run_file, True, who, why)
    if paused is not None:
        console.print(f"run file {escape(str(run_file))}: already paused ({escape(paused)}); the pause is sent anyway "
                      f"({escape(str(path))}): it withdraws a resume on its way, and the run records it")
        return
    console.print(f"pause asked ({escape(str(path))}); the run takes it within 0.1 s and records it")


@clean_errors
def resume_run(run_file: RunArg, why: ResumeWhyOpt = "", operator: ByOpt = None) -> None:
    """Resume a paused run: the step it left restarts from its start (motor back, voltage ramped up). For a run that
    ended (crashed, stopped, tripped), use `bench run --resume RUN.h5`. The same as SIGUSR2 to the run's process."""
    from bench.runtime.control import write_control

    why, who = _reason(why, "say why it is safe to go on (recorded in the run file)"), _who(operator)
    _f, paused = _paused(run_file, "resume")
    if paused is None:
        raise ValueError(f"run file {run_file}: not paused: nothing to resume")
    path = write_control(run_file, False, who, why)
    console.print(f"resume asked ({escape(str(path))}); the run takes it within 0.1 s and records it")


interlock_app = typer.Typer(help="The interlock latch: after a latched fault nothing energises the rig until an "
                             "operator resets it.", no_args_is_help=True, rich_markup_mode=None)


@clean_errors
def interlock_status(json_out: JsonOpt = False) -> None:
    """Every latched rig: the fault, when, and in which run file or session; and every bench armed on a rig now
    (judged running: it may energise its rig)."""
    from bench.runtime.latch import all_latched, armed, state_dir

    found = all_latched()
    live = armed()
    if json_out:
        print_json({"state_dir": str(state_dir()), "latched": found, "armed": live})
        return
    if not found:
        console.print(f"no rig latched ({escape(str(state_dir()))})")
    for rig_name, was in found.items():
        console.print(f"[red]latched[/] {escape(_latch_line(rig_name, was))}", soft_wrap=True)
    for was in live:
        line = (f"rig {was.get('rig')}: armed by pid {was.get('pid')} on {was.get('host') or '?'} since "
                f"{was.get('at')}, in {was.get('where')} (running: {was.get('alive')})")
        console.print(f"[yellow]armed[/] {escape(' '.join(line.split()))}", soft_wrap=True)


def _latch_line(rig_name: str, was: dict[str, object]) -> str:
    """One latch, readable on one line: ``RIG: FAULT; at WHEN; in WHERE[; drive DRIVE]``."""

    def flat(key: str) -> str:
        return " ".join(str(was.get(key) or "?").split())

    drive = f"; drive {flat('drive')}" if was.get("drive") else ""
    return f"{' '.join(rig_name.split())}: {flat('fault')}; at {flat('at')}; in {flat('where')}{drive}"


@clean_errors
def interlock_reset(rig_name: Annotated[str, typer.Argument(help="Rig name (the rig file's name field).")],
                    why: WhyOpt = "", operator: ByOpt = None) -> None:
    """Reset a rig's latched interlock (who and why go to the interlock history); the exact rig name, and an
    error if that rig is not latched."""
    from bench.runtime.latch import latched, reset

    if latched(rig_name) is None:  # said first: a reason is asked only for a latch to reset (outside tester)
        _not_latched(rig_name)
    why = _reason(why, "say why it is safe to energise the rig again")
    was = reset(rig_name, _who(operator), why)
    if was is None:  # reset meanwhile by another operator
        _not_latched(rig_name)
    console.print(f"rig {escape(rig_name)}: reset (was: {escape(str(was.get('fault')))})")


def _not_latched(rig_name: str) -> NoReturn:
    """ValueError (one line): rig ``rig_name`` is not latched, naming the rigs that are."""
    from bench.runtime.latch import all_latched

    others = sorted(all_latched())
    if rig_name.endswith(".toml"):  # a rig file where the rig's name goes (an outside tester)
        raise ValueError(f"{rig_name}: give the rig's name, not its file" + (f" (latched: {', '.join(others)})"
                                                                          if others else " (none is latched)"))
    raise ValueError(f"rig {rig_name}: not latched: nothing to reset"
                     + (f" (latched: {', '.join(others)})" if others else ""))


def protocol_schema(
    out: Annotated[Path | None, typer.Option(help="Write to this file instead of stdout.")] = None,
) -> None:
    """JSON schema of the protocol file format, for editors (TOML language servers read JSON schemas)."""
    from bench.protocol.schema import json_schema

    text = json_schema()
    if out is None:
        sys.stdout.write(text + "\n")
    else:
        out.write_text(text + "\n", encoding="utf-8")
        console.print(f"wrote {out}")



@clean_errors
def protocols_list(json_out: JsonOpt = False) -> None:
    """The protocol files shipped with dea-bench: name, rig, description."""
    from bench.cli.lab_folder import protocol_infos

    infos = protocol_infos()
    if json_out:
        print_json([{"name": i.name, "rig": i.rig, "description": i.description, "path": str(i.path)}
                    for i in infos])
        return
    table = Table(title="shipped protocols (bench protocols show NAME · bench protocols copy NAME DEST)")
    for col in ("name", "rig", "description"):
        table.add_column(col, no_wrap=col != "description")
    for i in infos:
        table.add_row(escape(i.name), escape(i.rig), escape(i.description))
    console.print(table)


@clean_errors
def protocols_show(name: Annotated[str, typer.Argument(help="Protocol name (bench protocols list).",
                                                       autocompletion=protocol_names)]) -> None:
    """Print a shipped protocol file as it is (comments included)."""
    from bench.resources import protocol

    sys.stdout.write(protocol(name).read_text(encoding="utf-8"))


@clean_errors
def protocols_copy(
    name: Annotated[str, typer.Argument(help="Protocol name (bench protocols list).", autocompletion=protocol_names)],
    dest: Annotated[Path, typer.Argument(help="File or existing folder to copy to.")] = Path("."),
    rig: Annotated[Path | None, typer.Option(help="Rig file the copy runs on (default: the lab folder's "
                                             "rigs/<rig>.toml beside it if present, else the shipped rig).",
                                             autocompletion=rig_files)]
    = None,
) -> None:
    """Copy a shipped protocol to edit it (comments kept); its rig reference is rewritten to stay valid."""
    from bench.cli.lab_folder import copy_protocol
    from bench.resources import protocol

    target = copy_protocol(protocol(name), dest, rig)
    console.print(f"wrote {escape(str(target))}")
    _say_if_shipped_rig(target)


def _say_if_shipped_rig(copy: Path) -> None:
    """A copy outside a lab folder names the shipped rig by its name (found inside the installed package wherever
    it is): said, with where an editable one comes from, since that file is not the user's to edit (outside
    tester: it was an absolute site-packages path, written without a word)."""
    import tomllib

    from bench.protocol.schema import resolve_rig_ref
    from bench.resources import rigs_dir

    ref = str(tomllib.loads(copy.read_text(encoding="utf-8"))["protocol"]["rig"])
    if resolve_rig_ref(copy.parent, ref).is_relative_to(rigs_dir().resolve()):
        console.print(f"note: its rig = {escape(ref)} is the rig of that name shipped with bench (not for editing): "
                      "for one of your own, copy into a lab folder (bench init LAB) or pass --rig RIG.toml")


@clean_errors
def init(folder: Annotated[Path, typer.Argument(help="Lab folder to create (new or empty).")]) -> None:
    """Create a lab folder: editable copies of the rig templates and protocols, a runs/ folder, a README."""
    from bench.cli.lab_folder import init_lab

    written = init_lab(folder)
    console.print(f"lab folder {escape(str(folder))}: {len(written)} files (rigs/, protocols/, README.md), runs/")
    console.print(f"next: cd {escape(str(folder))} && bench run protocols/thesis-identification.toml --virtual-time")

def register(app: typer.Typer) -> None:
    """Put validate, run, inspect, recover, init and the protocols group on ``app``."""
    app.add_typer(protocol_app, name="protocols")
    app.add_typer(protocol_app, name="protocol", hidden=True)  # the earlier name (`bench protocol schema`)
    app.command()(validate)
    app.command()(run)
    app.command()(inspect)
    app.command()(recover)
    app.command()(pause)
    app.command("resume")(resume_run)
    app.add_typer(interlock_app, name="interlock")
    interlock_app.command("status")(interlock_status)
    interlock_app.command("reset")(interlock_reset)
    protocol_app.command("schema")(protocol_schema)
    protocol_app.command("list")(protocols_list)
    protocol_app.command("show")(protocols_show)
    protocol_app.command("copy")(protocols_copy)
    app.command("init")(init)
