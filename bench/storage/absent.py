"""The one-line reason a path given as a run file is none: not there, or a folder (``bench run --out`` takes a
folder and names the file it writes there; a folder given back to ``bench fit``/``report``/``inspect`` was
"not found", which it plainly was not)."""

from __future__ import annotations

from pathlib import Path

SHOWN = 3  # run files named in the line


def absent_run_file(p: Path) -> str:
    """``run file P: not found``, or for a folder ``…: a folder, not a run file`` and the run files in it."""
    if p.is_dir():
        runs = sorted(x.name for x in p.glob("*.h5") if x.is_file())
        if not runs:
            return f"run file {p}: a folder, not a run file (no .h5 file in it)"
        more = f" and {len(runs) - SHOWN} more" if len(runs) > SHOWN else ""
        return f"run file {p}: a folder, not a run file; the run files in it: {', '.join(runs[:SHOWN])}{more}"
    return f"run file {p}: not found"


def absent_runs_folder(p: Path, why: str = "") -> str:
    """``runs folder P: not found`` (and ``why``), or for a file ``…: a file, not a folder`` (a run file given where
    its folder is asked for: "not found" was wrong)."""
    if p.is_file():
        return f"runs folder {p}: a file, not a folder (give the folder of the run files: {p.parent})"
    return f"runs folder {p}: not found{why}"
