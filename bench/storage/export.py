"""Run files out to the formats other tools read: CSV (one file per stream) and MATLAB ``.mat``, in bounded memory.

CSV: ``<stream>.csv`` with a header naming each column and its unit (``t [s],voltage [V],…``), plus
``events.csv`` (t [s], step, kind, text) and ``metadata.json`` (the run file's attributes, and under
``export_files`` the names of the files the export wrote). Numbers are written
with the precision the instruments have, not every bit of a float: time with 12 significant digits (0.1 µs
over a week of run time), measured and commanded values with 9 (a 24-bit converter has about 7), flags and
counts as integers.

A CSV folder holds one run: an export into a folder that holds another run's export (its ``metadata.json`` names
another run), or CSV files of no export this module recognises, is refused before anything is written. An export
of the same run again (the same ``run_id``) replaces its own files and removes those of its earlier export it no
longer writes (listed in that export's ``export_files``); any other file in the folder is left alone.

MAT: a new file (an existing one is refused, :func:`bench.storage.outputs.refuse_existing`), written to a
temporary file beside it and moved into place once whole; one struct per stream (``t`` and the columns as column
vectors, ``units`` a struct of unit strings),
``events`` and ``metadata`` (MATLAB: ``s = load('run.mat'); plot(s.laser.t, s.laser.displacement)``). Two
versions: v5 (scipy.io; events' kind and text as cell arrays of strings), and v7.3 — the HDF5-based format
MATLAB uses for variables beyond v5's 2 GB — written here with h5py chunk by chunk (events' kind and text as
cell arrays of strings too). ``auto`` picks v7.3 when a stream holds more than
``MAT5_MAX_STREAM_BYTES``: v5 has to hold a whole variable in memory to write it.

Every stream is read from the run file in chunks (:mod:`bench.storage.chunks`), so the memory an export needs does
not grow with the length of the run (``bench benchmark export`` prints it).
"""

from __future__ import annotations

import contextlib
import csv
import json
import re
import stat
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

from bench.storage.chunks import StreamChunks
from bench.storage.outputs import atomic_output, claim_folder, refuse_existing
from bench.storage.recorder import cause
from bench.storage.runfile import RunFile, open_h5, open_run

MAT5_MAX_STREAM_BYTES = 256 * 2**20  # auto: above this a stream goes to MAT v7.3, written in chunks
MatVersion = Literal["auto", "5", "7.3"]


def _header(name: str, unit: str) -> str:
    return f"{name} [{unit}]" if unit else name


def run_metadata(run: RunFile) -> dict[str, Any]:
    def plain(v: Any) -> Any:
        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, np.ndarray):
            return v.tolist()
        return v

    return {k: plain(v) for k, v in run.attrs.items()} | {  # (a killed run's state is "running": state_shown)
        "state": run.state, "state_shown": run.state_shown, "reason": run.reason, "complete": run.complete,
        "incomplete_reason": None if run.complete else run.incomplete_reason}


def _formats(streams: StreamChunks, stream: str) -> list[str]:
    """printf formats per column: integers and flags as integers, time with 12 digits, values with 9."""
    out = []
    for c in streams.columns[stream]:
        kind = streams.dtype(stream, c).kind
        out.append("%d" if kind in "iub" else "%.12g" if c == "t" else "%.9g")
    return out


Progress = Callable[[float], None]  # fraction of the run's records written, 0 … 1


@contextlib.contextmanager
def _into(target: Path) -> Iterator[None]:
    """A failure to write the export's ``target`` (no such folder, not writable, a folder, disk full) as one line
    naming it: the OSError of a write names no file (``No space left on device``), scipy's failed open says
    ``Reader needs file name``, HDF5's a paragraph."""
    try:
        yield
    except OSError as exc:
        raise OSError(f"{target}: cannot write the export: {cause(exc)}") from None


@contextlib.contextmanager
def _no_partial(target: Path) -> Iterator[None]:
    """Remove ``target``, written by the export, if writing it fails: a cut-off file would pass for an export.
    Only a plain file: a device (``/dev/full``) or a pipe given as the target stays."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(OSError):
            if stat.S_ISREG(target.lstat().st_mode):
                target.unlink()
        raise


def _records(streams: StreamChunks) -> int:
    return max(sum(streams.length.values()), 1)


EXPORT_FILES = "export_files"  # metadata.json: the files the export wrote (a later export of the run removes stale)


def _csv_folder(out: Path, run: dict[str, Any], names: list[str]) -> tuple[bool, list[Path]]:
    """Check that ``out`` may take the CSV export of ``run`` (its metadata) writing the files ``names``
    (:func:`bench.storage.outputs.claim_folder`: new or empty, or holding an earlier export of the same run). Returns
    whether it holds one, and that export's files this one no longer writes (to remove)."""
    loose = sorted(p.name for p in out.glob("*.csv")) if out.is_dir() else []
    meta = claim_folder(out, "metadata.json", run, "export", "export", loose)
    if meta is None:
        return False, []  # none yet (or not a folder: said when it is created)
    listed = meta.get(EXPORT_FILES, [])
    earlier = [n for n in listed if isinstance(n, str)] if isinstance(listed, list) else []
    # only plain names of export files (a hand-edited list naming ../x or a folder removes nothing)
    stale = [out / n for n in earlier if n not in names and Path(n).name == n and n.endswith(".csv")
             and (out / n).is_file()]
    return True, stale


def to_csv(run_path: str | Path, folder: str | Path, progress: Progress | None = None,
           said: Callable[[str], None] | None = None) -> list[Path]:
    """Write one CSV per stream, ``events.csv`` and ``metadata.json`` into ``folder``; returns the files.
    ``progress`` is told the fraction of the records written after every chunk; ``said`` that an earlier export of
    the same run is replaced (and which of its files were removed). A folder holding another run's export is
    refused (see the module docstring)."""
    run = open_run(run_path, streams=False)
    out = Path(folder)
    written = []
    with open_h5(Path(run_path)) as f:
        streams = StreamChunks(f, run_path)
        names = [f"{stream}.csv" for stream in streams.length] + ["events.csv", "metadata.json"]
        meta = run_metadata(run)
        again, stale = _csv_folder(out, meta, names)
        with _into(out):
            out.mkdir(parents=True, exist_ok=True)
        for p in stale:
            with _into(p):
                p.unlink()
        if again and said is not None:
            said(f"{out}: replaced the earlier export of this run"
                 + (f"; removed its {', '.join(p.name for p in stale)}" if stale else ""))
        # metadata.json first: a cut-off export still says whose it is (a second try of the run may replace it)
        meta_path = out / "metadata.json"
        text = json.dumps(meta | {EXPORT_FILES: names}, indent=1, ensure_ascii=False, default=str)
        with _into(meta_path):
            fh = meta_path.open("w", encoding="utf-8")
        with _into(meta_path), _no_partial(meta_path), fh:
            fh.write(text)
        total, done = _records(streams), 0
        for stream in streams.length:
            units = streams.units(stream)
            row = ",".join(_formats(streams, stream)) + "\n"
            path = out / f"{stream}.csv"
            with _into(path):
                fh = path.open("w", newline="", encoding="utf-8")
            with _no_partial(path), fh:
                with _into(path):
                    fh.write(",".join(_header(c, units[c]) for c in streams.columns[stream]) + "\n")
                for chunk in streams.chunks(stream):  # reads: the run file's own errors
                    table = np.column_stack([chunk[c] for c in streams.columns[stream]]).astype(np.float64)
                    with _into(path):
                        fh.write((row * table.shape[0]) % tuple(table.ravel().tolist()))  # one format call a chunk
                    done += table.shape[0]
                    if progress is not None:
                        progress(done / total)
                with _into(path):
                    fh.flush()
            written.append(path)
    path = out / "events.csv"
    with _into(path):
        fh = path.open("w", newline="", encoding="utf-8")
    with _into(path), _no_partial(path), fh:
        w = csv.writer(fh)
        w.writerow(["t [s]", "step", "kind", "text"])
        w.writerows([f"{t:.12g}", step, kind, text] for t, step, kind, text in run.event_list())
    written.append(path)
    written.append(meta_path)
    return written


def _mat_name(name: str) -> str:
    """A valid MATLAB field name (letters, digits, underscore; starts with a letter)."""
    clean = re.sub(r"\W", "_", name)
    return clean if clean[:1].isalpha() else f"x_{clean}"


def mat_version(run_path: str | Path, asked: MatVersion = "auto") -> Literal["5", "7.3"]:
    """The MAT version an export writes: ``asked``, or for ``auto`` v7.3 when a stream exceeds v5's budget."""
    if asked != "auto":
        return asked
    with open_h5(Path(run_path)) as f:
        streams = StreamChunks(f, run_path)
        big = any(streams.nbytes(s) > MAT5_MAX_STREAM_BYTES for s in streams.length)
    return "7.3" if big else "5"


def to_mat(run_path: str | Path, path: str | Path, version: MatVersion = "auto",
           progress: Progress | None = None) -> Path:
    """Write the run as a MATLAB file (see the module docstring), a new file (an existing ``path`` is refused),
    moved into place only once whole; returns its path. ``progress``: the fraction of the records written, after
    every chunk (v7.3) or once at the end (v5, written in one call)."""
    target = Path(path)
    refuse_existing(target, "export", example="run.mat")
    version = mat_version(run_path, version)
    with _into(target):
        target.parent.mkdir(parents=True, exist_ok=True)
    stack = contextlib.ExitStack()
    with _into(target):  # a folder no file can be made in
        tmp = stack.enter_context(atomic_output(target))
    with stack:  # written whole into place, or not at all (the temporary removed)
        if version == "7.3":
            _to_mat73(run_path, tmp, target, progress)
        else:
            _to_mat5(run_path, tmp, target)
            if progress is not None:
                progress(1.0)
    return target


def _to_mat5(run_path: str | Path, tmp: Path, target: Path) -> None:
    """The v5 file into ``tmp``; errors name ``target``."""
    from scipy.io import savemat

    run = open_run(run_path)
    data: dict[str, Any] = {}
    for stream, s in run.streams.items():
        cols = [("t", s.units.get("t", "s"), s.t)] + [(k, s.units.get(k, ""), v) for k, v in s.columns.items()]
        struct: dict[str, Any] = {_mat_name(n): np.asarray(v, dtype=float).reshape(-1, 1) for n, _, v in cols}
        struct["units"] = {_mat_name(n): u for n, u, _ in cols}
        data[_mat_name(stream)] = struct
    events = run.event_list()
    data["events"] = {"t": np.array([e[0] for e in events], dtype=float).reshape(-1, 1),
                      "step": np.array([e[1] for e in events], dtype=float).reshape(-1, 1),
                      "kind": np.array([e[2] for e in events], dtype=object).reshape(-1, 1),
                      "text": np.array([e[3] for e in events], dtype=object).reshape(-1, 1)}
    data["metadata"] = _mat_metadata(run)
    with _into(target):
        fh = tmp.open("wb")
    with _into(target), fh:
        savemat(fh, data, do_compression=True, oned_as="column")


def _mat_metadata(run: RunFile) -> dict[str, Any]:
    return {_mat_name(k): (json.dumps(v) if isinstance(v, dict | list) else ("" if v is None else v))
            for k, v in run_metadata(run).items()}


# ---------------------------------------------------------------- MAT v7.3: HDF5 with MATLAB's conventions
# MATLAB stores an m×n array as an HDF5 dataset of shape (n, m) (column-major), names its class in the
# MATLAB_class attribute, char arrays as uint16 code units with MATLAB_int_decode = 2, structs as groups with
# MATLAB_class "struct" and MATLAB_fields listing the field names, and reads the file only after a 512-byte
# user block that holds the MAT header text, the version 0x0200 and the endian indicator "IM".


def _mat_class(obj: h5py.Dataset | h5py.Group, name: str) -> None:
    obj.attrs.create("MATLAB_class", np.bytes_(name))


def _struct(parent: h5py.Group, name: str, fields: list[str]) -> h5py.Group:
    g = parent.create_group(name)
    _mat_class(g, "struct")
    names = np.empty(len(fields), dtype=h5py.vlen_dtype(np.dtype("S1")))
    for i, f in enumerate(fields):
        names[i] = np.frombuffer(f.encode(), dtype="S1")
    g.attrs.create("MATLAB_fields", names, dtype=h5py.vlen_dtype(np.dtype("S1")))
    return g


def _char(parent: h5py.Group, name: str, rows: list[str]) -> None:
    """A char array: one row per string, padded with blanks (a 1×N row vector for one string)."""
    units = [np.frombuffer(r.encode("utf-16-le"), dtype=np.uint16) for r in rows]
    width = max((u.size for u in units), default=0)
    if width == 0:  # MATLAB's empty array: its dimensions as data, flagged empty
        d = parent.create_dataset(name, data=np.array([len(rows), 0], dtype=np.uint64))
        d.attrs.create("MATLAB_empty", np.uint8(1))
    else:
        codes = np.full((width, len(rows)), ord(" "), dtype=np.uint16)
        for j, u in enumerate(units):
            codes[: u.size, j] = u
        d = parent.create_dataset(name, data=codes)
        d.attrs.create("MATLAB_int_decode", np.int32(2))
    _mat_class(d, "char")


def _cellstr(parent: h5py.Group, name: str, rows: list[str]) -> None:
    """A column cell array of strings: references to char arrays kept in the file's ``#refs#`` group."""
    refs = parent.file.require_group("#refs#")
    targets = []
    for i, r in enumerate(rows):
        key = f"{parent.name.strip('/').replace('/', '_')}_{name}_{i}"
        _char(refs, key, [r])
        targets.append(refs[key].ref)
    d = parent.create_dataset(name, data=np.array(targets, dtype=h5py.ref_dtype).reshape(1, -1))
    _mat_class(d, "cell")


def _double(parent: h5py.Group, name: str, values: np.ndarray) -> None:
    d = parent.create_dataset(name, data=np.asarray(values, dtype=np.float64).reshape(1, -1))
    _mat_class(d, "double")


def _mat73_header() -> bytes:
    stamp = datetime.now(UTC).strftime("%a %b %d %H:%M:%S %Y")
    text = f"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: {stamp} HDF5 schema 1.00 .".encode()
    return text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"


def _to_mat73(run_path: str | Path, tmp: Path, target: Path, progress: Progress | None = None) -> None:
    """The v7.3 file into ``tmp``; errors name ``target``."""
    run = open_run(run_path, streams=False)
    events = run.event_list()
    meta = _mat_metadata(run)
    with open_h5(Path(run_path)) as src:
        streams = StreamChunks(src, run_path)
        total, done = _records(streams), 0
        with _into(target):
            out = h5py.File(tmp, "w", userblock_size=512)
        try:
            for stream, n in streams.length.items():
                cols = streams.columns[stream]
                units = streams.units(stream)
                with _into(target):
                    g = _struct(out, _mat_name(stream), [*map(_mat_name, cols), "units"])
                    sets = {}
                    for c in cols:
                        d = g.create_dataset(_mat_name(c), shape=(1, n), dtype=np.float64,
                                             chunks=(1, min(max(n, 1), 65_536)), compression="gzip",
                                             compression_opts=1)
                        _mat_class(d, "double")
                        sets[c] = d
                a = 0
                for chunk in streams.chunks(stream):  # reads: the run file's own errors
                    b = a + chunk["t"].size
                    with _into(target):
                        for c in cols:
                            sets[c][0, a:b] = chunk[c].astype(np.float64)
                    a = b
                    done += chunk["t"].size
                    if progress is not None:
                        progress(done / total)
                with _into(target):
                    u = _struct(g, "units", [_mat_name(c) for c in cols])
                    for c in cols:
                        _char(u, _mat_name(c), [units[c]])
            with _into(target):
                ev = _struct(out, "events", ["t", "step", "kind", "text"])
                _double(ev, "t", np.array([e[0] for e in events], dtype=float))
                _double(ev, "step", np.array([e[1] for e in events], dtype=float))
                _cellstr(ev, "kind", [e[2] for e in events])
                _cellstr(ev, "text", [e[3] for e in events])
                m = _struct(out, "metadata", list(meta))
                for k, v in meta.items():
                    if isinstance(v, bool | int | float | np.integer | np.floating):
                        _double(m, k, np.array([float(v)]))
                    else:
                        _char(m, k, [str(v)])
        finally:
            with _into(target):
                out.close()
        with _into(target), tmp.open("r+b") as fh:
            fh.write(_mat73_header())
