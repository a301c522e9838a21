"""A run file's streams read a chunk at a time, so a reader's memory does not grow with the run's length.

Used by the export, the quick-look plot, the analysis and the report; each dataset is cut to the records the writer
confirmed (``/status/samples``), as :func:`bench.storage.runfile.open_run` does. A time window of a stream (a step,
its last cycles) is found from a coarse index — each chunk's last time, built by one chunked pass — and read
alone (the time base must not go back: the recorder writes it in order); :func:`open_source` opens a run once for
all of a command's reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import h5py
import numpy as np

from bench.storage.absent import absent_run_file
from bench.storage.runfile import (
    RunFile,
    damaged,
    open_h5,
    read_run,
    refuse_nonfinite,
    stream_names,
    unit_of,
    valid_counts,
)

CHUNK_ROWS = 262_144  # records per stream read at a time (a few MB per column)


class StreamChunks:
    """The run file's streams, read a chunk at a time: names, units, lengths trimmed to the confirmed records."""

    def __init__(self, f: h5py.File, path: str | Path | None = None) -> None:
        self.f = f
        self.path = Path(path if path is not None else f.filename)  # for messages (an in-memory copy has no name)
        valid = valid_counts(f, self.path)
        self.length: dict[str, int] = {}
        self.columns: dict[str, list[str]] = {}
        for name in stream_names(f):
            g = f[name]
            for d in g.values():
                d.refresh()
            n = min(d.shape[0] for d in g.values())
            self.length[name] = min(n, valid.get(name, n))
            self.columns[name] = ["t", *(k for k in g if k != "t")]
        self._index: dict[str, tuple[int, np.ndarray]] = {}

    def units(self, stream: str) -> dict[str, str]:
        """Unit per column (time in s)."""
        g = self.f[stream]
        return {k: unit_of(g[k].attrs.get("units", "s" if k == "t" else "")) for k in self.columns[stream]}

    def dtype(self, stream: str, column: str) -> np.dtype:
        """The stored type of a column."""
        dtype: np.dtype = self.f[stream][column].dtype
        return dtype

    def nbytes(self, stream: str) -> int:
        """Bytes of the stream's confirmed records, all columns."""
        return sum(self.dtype(stream, c).itemsize for c in self.columns[stream]) * self.length[stream]

    def chunks(self, stream: str, rows: int | None = None, start: int = 0,
               stop: int | None = None) -> Iterator[dict[str, np.ndarray]]:
        """The stream's columns from record ``start`` to ``stop`` (default: the confirmed end), ``rows`` (default
        ``CHUNK_ROWS``) records at a time (``bench watch`` reads only the records added since its last look)."""
        step = rows or CHUNK_ROWS
        n = self.length[stream] if stop is None else min(stop, self.length[stream])
        for a in range(start, n, step):
            b = min(a + step, n)
            yield {c: self.read(stream, c, a, b) for c in self.columns[stream]}

    def read(self, stream: str, column: str, a: int, b: int) -> np.ndarray:
        """Records ``a`` … ``b``−1 of one column: every read of a stream goes through here (a damaged file: one line
        naming it and the records)."""
        try:
            data: np.ndarray = self.f[stream][column][a:b]
        except OSError as exc:  # HDF5 could not read them (a checksum, a compression filter)
            raise ValueError(f"run file {self.f.filename}: damaged, HDF5 cannot read {stream}/{column} records "
                             f"{a}–{b - 1} ({' '.join(str(exc).split())[:200]})") from None
        return data

    def _blocks(self, stream: str) -> tuple[int, np.ndarray]:
        """(records per block, last time of each block), built once per stream by a chunked pass; a time base
        that goes back anywhere is refused (every reader of a window assumes it, as ``np.interp`` does)."""
        if stream not in self._index:
            rows, lasts, prev = CHUNK_ROWS, [], -np.inf
            for a in range(0, self.length[stream], rows):
                t = self.read(stream, "t", a, min(a + rows, self.length[stream]))
                if t[0] < prev or (t.size > 1 and bool(np.any(np.diff(t) < 0))):
                    raise ValueError(f"run file {self.f.filename}: stream {stream}: time goes back near record {a}")
                lasts.append(t[-1])
                prev = t[-1]
            self._index[stream] = (rows, np.array(lasts, dtype=float))
        return self._index[stream]

    def _position(self, stream: str, t: float, side: Literal["left", "right"]) -> int:
        """The record where ``t`` would be inserted (``np.searchsorted`` on the whole time base, ``side``)."""
        rows, lasts = self._blocks(stream)
        k = int(np.searchsorted(lasts, t, side=side))  # the first block that can hold it
        if k >= lasts.size:
            return self.length[stream]
        a = k * rows
        block = self.read(stream, "t", a, min(a + rows, self.length[stream]))
        return a + int(np.searchsorted(block, t, side=side))

    def span(self, stream: str, t0: float, t1: float) -> tuple[int, int]:
        """Records ``a`` … ``b``−1: those with ``t0 ≤ t ≤ t1``."""
        a = self._position(stream, t0, "left")
        return a, max(a, self._position(stream, t1, "right"))

    def window(self, stream: str, t0: float, t1: float, columns: list[str] | None = None,
               neighbours: bool = False, finite: str | None = None) -> dict[str, np.ndarray]:
        """The records with ``t0 ≤ t ≤ t1`` (``columns``, default all; ``t`` always). ``finite``: records where that
        column is NaN left out. ``neighbours``: also the last record before and the first after the window (those
        with a finite ``finite``), so that ``np.interp`` inside the window gives what it gives on the whole
        stream."""
        cols = list(dict.fromkeys(["t", *(columns or self.columns[stream][1:])]))
        if finite is not None and finite not in cols:
            cols.append(finite)
        a, b = self.span(stream, t0, t1)
        parts = [self._rows(stream, cols, a, b, finite)]
        if neighbours:
            parts = [self._nearest(stream, cols, a, -1, finite), *parts, self._nearest(stream, cols, b, 1, finite)]
        return {c: np.concatenate([p[c] for p in parts]) for c in cols}

    def _rows(self, stream: str, cols: list[str], a: int, b: int, finite: str | None) -> dict[str, np.ndarray]:
        out = {c: self.read(stream, c, a, b) for c in cols}
        if finite is not None:  # NaN: a row that does not set the column (a motor-only set-point); inf: damaged
            refuse_nonfinite(self.path, stream, finite, out["t"] if "t" in out else np.empty(0), out[finite])
            keep = np.isfinite(out[finite])
            out = {c: v[keep] for c, v in out.items()}
        return out

    def _nearest(self, stream: str, cols: list[str], at: int, direction: int,
                 finite: str | None) -> dict[str, np.ndarray]:
        """The nearest record before ``at`` (``direction`` −1) or from ``at`` on (+1) with a finite ``finite``
        (any record without), read a chunk at a time; empty columns if there is none."""
        n, rows = self.length[stream], CHUNK_ROWS
        while 0 <= at <= n:
            a, b = (max(at - rows, 0), at) if direction < 0 else (at, min(at + rows, n))
            if a == b:
                break
            got = self._rows(stream, cols, a, b, finite)
            if got["t"].size:
                i = -1 if direction < 0 else 0
                return {c: v[[i]] for c, v in got.items()}
            at = a if direction < 0 else b
        return {c: np.zeros(0, dtype=self.dtype(stream, c)) for c in cols}

    def first_last(self, stream: str, flag: str) -> tuple[float, float] | None:
        """Times of the first and the last record whose ``flag`` column is > 0 (None if none is)."""
        first = last = None
        for chunk in self.chunks(stream):
            ok = np.flatnonzero(chunk[flag] > 0)
            if ok.size:
                first = float(chunk["t"][ok[0]]) if first is None else first
                last = float(chunk["t"][ok[-1]])
        return None if first is None or last is None else (first, last)

    def decimate(self, stream: str, column: str, t0: float, t1: float, spans: int, flag: str | None = None,
                 drop_nan: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(t, values) of ``column`` over ``t0 ≤ t ≤ t1`` (where ``flag`` > 0; NaN values left out if
        ``drop_nan``) for a line on a screen: every record when there are at most 2 × ``spans``; else the time they
        span cut into ``spans`` equal intervals and of each its minimum and its maximum, in time order — the line a
        screen of that width draws, every extreme kept (memory: a chunk and 2 × ``spans`` points). Intervals of
        time, not of record count: a stream whose rate changes (a pause's slow readings after a drive's) kept few
        points over the slow part, each span of records then covering much of the run (as `bench plot` did)."""
        a, b = self.span(stream, t0, t1)
        cols = ["t", column, *([flag] if flag else [])]

        def kept(chunk: dict[str, np.ndarray]) -> np.ndarray:
            ok = np.isfinite(chunk[column].astype(float)) if drop_nan else np.ones(chunk["t"].size, bool)
            return ok & (chunk[flag] > 0) if flag else ok

        if b - a <= 2 * spans:
            rows = self._rows(stream, cols, a, b, None)
            ok = kept(rows)
            return rows["t"][ok].astype(float), rows[column][ok].astype(float)
        t_first, t_last = (float(self._rows(stream, ["t"], i, i + 1, None)["t"][0]) for i in (a, b - 1))
        edges = np.linspace(t_first, t_last, spans + 1)
        best = {"lo": np.full(spans, np.inf), "hi": np.full(spans, -np.inf)}
        where = {"lo": np.full(spans, -1, np.int64), "hi": np.full(spans, -1, np.int64)}
        times = {"lo": np.zeros(spans), "hi": np.zeros(spans)}
        for start in range(a, b, CHUNK_ROWS):
            stop = min(start + CHUNK_ROWS, b)
            chunk = self._rows(stream, cols, start, stop, None)
            ok = np.flatnonzero(kept(chunk))
            if not ok.size:
                continue
            idx, v, t = start + ok, chunk[column][ok].astype(float), chunk["t"][ok].astype(float)
            k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, spans - 1)  # (the last record: the last span)
            for side, sign in (("lo", 1.0), ("hi", -1.0)):
                order = np.lexsort((sign * v, k))  # by span, then by value: each span's extreme first
                firsts = order[np.r_[True, k[order][1:] != k[order][:-1]]]
                ks = k[firsts]
                better = sign * v[firsts] < sign * best[side][ks]
                best[side][ks[better]] = v[firsts][better]
                where[side][ks[better]] = idx[firsts][better]
                times[side][ks[better]] = t[firsts][better]
        idx = np.concatenate([where["lo"], where["hi"]])
        t = np.concatenate([times["lo"], times["hi"]])
        v = np.concatenate([best["lo"], best["hi"]])
        idx, first = np.unique(idx, return_index=True)  # in record order; a span's min and max may be one record
        keep = idx >= 0
        return t[first][keep], v[first][keep]


@dataclass
class RunSource:
    """A run file opened once: its metadata, events and program (``run``, no streams) and its streams read in
    chunks and windows (``streams``)."""

    run: RunFile
    streams: StreamChunks


@contextmanager
def open_source(path: str | Path) -> Iterator[RunSource]:
    """Open a run file once for all the reads of a command (analysis, report, inspect)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(absent_run_file(p))
    with open_h5(p) as f:
        try:
            run = read_run(f, p)
        except (OSError, UnicodeDecodeError) as exc:  # as open_run says it
            raise damaged(p, exc) from None
        yield RunSource(run, StreamChunks(f, p))
