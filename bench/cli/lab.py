"""CLI commands of a lab's daily work: export of run files, manual control of a rig's instruments."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Annotated

import typer

from bench.cli.common import clean_errors, console, escape, progress
from bench.cli.completion import rig_files


@clean_errors
def export(
    run_file: Annotated[Path, typer.Argument(help="Run file (.h5).")],
    csv: Annotated[Path | None, typer.Option("--csv", help="Folder for one CSV per stream (units in the "
                                             "header), events.csv and metadata.json: new, empty, or an earlier "
                                             "export of the same run (replaced; another run's is refused).")]
    = None,
    mat: Annotated[Path | None, typer.Option("--mat", help="MATLAB file (.mat): one struct per stream; a new file "
                                             "(an existing one is refused).")] = None,
    mat_version: Annotated[str, typer.Option(help="MAT version: 5 (scipy; whole streams in memory), 7.3 (HDF5, "
                                             "written in chunks: any length), or auto: 7.3 when a stream exceeds "
                                             "256 MB.")] = "auto",
) -> None:
    """Export a run file's streams to CSV files and/or a MATLAB file, reading the run in chunks (memory does not
    grow with its length). CSV numbers carry the instruments' precision: time 12 digits, values 9."""
    from bench.storage.export import to_csv, to_mat
    from bench.storage.outputs import refuse_existing

    if mat_version not in ("auto", "5", "7.3"):
        raise ValueError(f"--mat-version {mat_version!r}: give 5, 7.3 or auto")
    if csv is None and mat is None:
        raise ValueError("give --csv FOLDER and/or --mat FILE")
    if mat is not None:  # before the CSV files are written
        refuse_existing(mat, "export", example="run.mat")
        if mat.suffix.lower() != ".mat":  # a MAT file named x.csv (an outside tester) passes for what it is not
            raise ValueError(f"--mat {mat}: a MATLAB file's name ends in .mat (e.g. {mat.with_suffix('.mat')})")
    _say_incomplete(run_file)
    if csv is not None:
        with progress("CSV export") as done:
            files = to_csv(run_file, csv, progress=done, said=lambda text: console.print(escape(text)))
        console.print(f"CSV: {len(files)} files in {escape(str(csv))} ({', '.join(f.name for f in files)})")
    if mat is not None:
        with progress("MAT export") as done:
            target = to_mat(run_file, mat, mat_version, progress=done)  # type: ignore[arg-type]  # checked above
        console.print(f"MAT: {escape(str(target))}")


def _say_incomplete(run_file: Path) -> None:
    """One line before an export of a run that is not a complete record (killed, under way, ended unstamped): the
    export held what was recorded and said nothing, exit 0 (outside tester)."""
    from bench.storage.runfile import open_run

    try:
        run = open_run(run_file, streams=False)
    except (OSError, ValueError):  # not a run file: the export's own refusal says it
        return
    if not run.complete:
        console.print(f"[yellow]note:[/] {escape(str(run_file))} is not a complete record ({run.state_shown}: "
                      f"{escape(run.incomplete_reason)}); the export holds what was recorded up to "
                      f"{run.updated:.3f} s", highlight=False, soft_wrap=True)


@clean_errors
def devices_control(
    rig_file: Annotated[Path, typer.Argument(help="Rig file (TOML), e.g. rigs/lsdea-motor-sim.toml.",
                                             autocompletion=rig_files)],
    script: Annotated[Path | None, typer.Option(help="Read commands from this file (default: stdin; a prompt "
                                                "on a terminal).")] = None,
    log: Annotated[Path | None, typer.Option(help="Session log file (default: runs/manual-<rig>-<time>.log); the "
                                             "readings go to an HDF5 file beside it (<log>.h5).")] = None,
    virtual_time: Annotated[bool, typer.Option("--virtual-time", help="Simulated rig only: waits and ramps take "
                                               "no wall time.")] = False,
    operator_name: Annotated[str | None, typer.Option(
        "--operator", help="Who runs the session; recorded in the session log's header.")] = None,
    specimen_id: Annotated[str | None, typer.Option(
        "--specimen-id", help="The specimen on the rig; recorded in the session's file, so that `bench specimen "
        "show` counts the session.")] = None,
) -> None:
    """Manual control under the safety supervisor and the latched interlock: set or ramp the voltage, jog or
    move the motor, tare the load cell, watch every channel; every action is logged, every reading recorded to
    an HDF5 file beside the log (`bench inspect` reads it). Commands: see `help` in the session.

    A host stall longer than the set-point module's watchdog allows, or an output that is not what was
    commanded, zeroes the output at once and latches: high voltage is refused until `reset WHY...`. A script
    (--script, or piped commands) stops at a trip: the commands after it are not run.

    SIGUSR1 pauses (as for a run): output ramped to 0 V and held, motor stopped; at a prompt `resume` lets high
    voltage on again. A script stops at such a pause too (an operator's pause outranks its lines): the session ends
    through its safe exit, recorded as interrupted.

    On a terminal the prompt has line editing and a history (~/.bench_history). Ctrl-C ends the command under
    way; a second Ctrl-C, Ctrl-C at the prompt, SIGTERM, SIGHUP or SIGQUIT end the session: output ramped to
    0 V, motor stopped, instruments safe.

    While the output is on, the monitors are polled and verified between commands too (a fault trips with nothing
    typed); `voltage` and `ramp` say whether the monitor shows the set-point (status unsettled where it does not).

    Exit status 0 if every command passed, 1 if one was refused, not verified, tripped a limit or failed, or a
    signal ended the session.
    """
    from bench.app.manual import manual_session

    def echo(text: str) -> None:
        with contextlib.suppress(OSError):  # the terminal went away (SIGHUP): the log holds the whole account
            console.print(escape(text), highlight=False)

    done = manual_session(rig_file, script=script, log=log, virtual_time=virtual_time, operator=operator_name,
                          specimen_id=specimen_id, echo=echo,
                          show_help=lambda text: console.print(text, markup=False, highlight=False))
    bad = done.not_done
    with contextlib.suppress(OSError):
        if done.safe_path:  # as `bench run` says it: how the end made the output safe, the 0 V verified
            console.print(f"high voltage: {escape(done.safe_path)}", highlight=False)
        console.print((f"session ended: {done.end_reason}; " if done.end_reason else "")
                      + f"session log: {escape(str(done.log))} ({len(done.outcomes)} commands"
                      + (f", {len(bad)} not done" if bad else "") + ")"
                      + (f"; readings: {escape(str(done.data_file))}"
                         if done.data_file is not None and done.data_file.exists() else ""))
    if not done.ok:
        raise typer.Exit(1)


def register(app: typer.Typer, devices: typer.Typer) -> None:
    """Put export on ``app`` and control on the ``devices`` group."""
    app.command("export")(export)
    devices.command("control")(devices_control)
