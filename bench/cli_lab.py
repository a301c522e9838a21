"""CLI commands of a lab's daily work: export of run files, manual control of a rig's instruments."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from bench.cli import app, clean_errors, console


@app.command("export")
@clean_errors
def export(
    run_file: Annotated[Path, typer.Argument(help="Run file (.h5).")],
    csv: Annotated[Path | None, typer.Option("--csv", help="Folder for one CSV per stream (units in the "
                                             "header), events.csv and metadata.json.")] = None,
    mat: Annotated[Path | None, typer.Option("--mat", help="MATLAB file (.mat): one struct per stream.")] = None,
) -> None:
    """Export a run file's streams to CSV files and/or a MATLAB file."""
    from bench.export import to_csv, to_mat

    if csv is None and mat is None:
        raise ValueError("give --csv FOLDER and/or --mat FILE")
    if csv is not None:
        files = to_csv(run_file, csv)
        console.print(f"CSV: {len(files)} files in {escape(str(csv))} ({', '.join(f.name for f in files)})")
    if mat is not None:
        console.print(f"MAT: {escape(str(to_mat(run_file, mat)))}")
