"""Run files out to the formats other tools read: CSV (one file per stream) and MATLAB ``.mat`` (scipy.io).

CSV: ``<stream>.csv`` with a header naming each column and its unit (``t [s],voltage [V],…``), plus
``events.csv`` (t [s], step, kind, text) and ``metadata.json`` (the run file's attributes). MAT: one struct
per stream (``t`` and the columns as column vectors, ``units`` a struct of unit strings), ``events`` and
``metadata`` (MATLAB: ``s = load('run.mat'); plot(s.laser.t, s.laser.displacement)``).
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from bench.storage.runfile import RunFile, open_run


def _header(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def _columns(run: RunFile, stream: str) -> list[tuple[str, str, np.ndarray]]:
    """(name, unit, values) of a stream, time first."""
    s = run.streams[stream]
    return [("t", s.units.get("t", "s"), s.t)] + [(k, s.units.get(k, ""), v) for k, v in s.columns.items()]


def _metadata(run: RunFile) -> dict[str, Any]:
    def plain(v: Any) -> Any:
        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, np.ndarray):
            return v.tolist()
        return v

    return {k: plain(v) for k, v in run.attrs.items()} | {"state": run.state, "reason": run.reason,
                                                          "complete": run.complete}


def to_csv(run_path: str | Path, folder: str | Path) -> list[Path]:
    """Write one CSV per stream, ``events.csv`` and ``metadata.json`` into ``folder``; returns the files."""
    run = open_run(run_path)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for stream in run.streams:
        cols = _columns(run, stream)
        path = out / f"{stream}.csv"
        with path.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow([_header(n, u) for n, u, _ in cols])
            # shortest text that reads back to the same float; integer and flag columns as integers
            text = [np.asarray(v).astype(int).astype(str) if np.asarray(v).dtype.kind in "iub"
                    else [repr(float(x)) for x in v] for _, _, v in cols]
            w.writerows(zip(*text, strict=True))
        written.append(path)
    path = out / "events.csv"
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["t [s]", "step", "kind", "text"])
        w.writerows([repr(t), step, kind, text] for t, step, kind, text in run.event_list())
    written.append(path)
    path = out / "metadata.json"
    path.write_text(json.dumps(_metadata(run), indent=1, ensure_ascii=False, default=str), encoding="utf-8")
    written.append(path)
    return written


def _mat_name(name: str) -> str:
    """A valid MATLAB field name (letters, digits, underscore; starts with a letter)."""
    clean = re.sub(r"\W", "_", name)
    return clean if clean[:1].isalpha() else f"x_{clean}"


def to_mat(run_path: str | Path, path: str | Path) -> Path:
    """Write the run as a MATLAB file (see module docstring); returns its path."""
    from scipy.io import savemat

    run = open_run(run_path)
    data: dict[str, Any] = {}
    for stream in run.streams:
        cols = _columns(run, stream)
        struct: dict[str, Any] = {_mat_name(n): np.asarray(v, dtype=float).reshape(-1, 1) for n, _, v in cols}
        struct["units"] = {_mat_name(n): u for n, u, _ in cols}
        data[_mat_name(stream)] = struct
    events = run.event_list()
    data["events"] = {"t": np.array([e[0] for e in events], dtype=float).reshape(-1, 1),
                      "step": np.array([e[1] for e in events], dtype=float).reshape(-1, 1),
                      "kind": np.array([e[2] for e in events], dtype=object).reshape(-1, 1),
                      "text": np.array([e[3] for e in events], dtype=object).reshape(-1, 1)}
    data["metadata"] = {_mat_name(k): (json.dumps(v) if isinstance(v, dict | list) else
                                       ("" if v is None else v)) for k, v in _metadata(run).items()}
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    savemat(target, data, do_compression=True, oned_as="column")
    return target
