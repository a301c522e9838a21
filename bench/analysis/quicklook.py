"""Quick-look figure of any streams of a run file (``bench plot``): one panel per column, units on every axis.

A record of hours at 10 kHz does not fit on a screen: each column is reduced, chunk by chunk as the file is read
(:mod:`bench.storage.chunks`), to ``columns`` equal spans of the run clock — not of the record count: a pause's or
a recovery's 10-Hz readings and a drive's 10-kHz ones are never pooled into one span drawn at its middle time — and
drawn through each span's first, lowest, highest and last reading at their own times (every extreme kept, the line
ending on the last sample), broken where the record has a hole (a software-timed laser's pause), so memory and
drawing time do not grow with the run.
Step starts are marked, and so is the shutdown's verified 0 V on the amplifier's voltage (a DAQ rig's streams end
on the last scan before the stop: the reading after it is in the ``safe`` event); an incomplete file says so in the
title.
"""

from __future__ import annotations

import os
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.storage import chunks as _chunks
from bench.storage.chunks import StreamChunks, open_source
from bench.storage.outputs import atomic_output, refuse_existing

FLAGS = ("valid", "ok")  # flag columns: not drawn as signals
PIXELS = 2000  # min/max spans per column (about a screen's width)
# the shutdown's own reading (bench/runtime/engine.py ``_verify_safe``): a DAQ rig's streams end on the last scan
# before the stop, so without it the amplifier panel ends at the voltage then, not at the 0 V verified after
VERIFIED = re.compile(r"verified: voltage monitor (-?\d+(?:\.\d+)?) V at (-?\d+(?:\.\d+)?) s")


@dataclass
class Envelope:
    """A column reduced to ``bins`` equal spans of the run clock, from its first recorded time to its last.

    ``lo``/``hi``: each bin's minimum and maximum (NaN: no reading in it); ``t``/``v``: the line drawn — of each bin
    its first, lowest, highest and last reading, in time order, at their own times (so every vertex is a sample of
    the file and the line reaches the last one), NaN between two readings the record has a hole between (a
    software-timed laser's pause, a stream's silence)."""

    stream: str
    column: str
    unit: str
    edges: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    t: np.ndarray
    v: np.ndarray
    samples: int


GAP_RATIO = 4.0  # a hole this many times longer than the intervals either side of it (and over 2 bins) breaks the line


TITLE_CHARS = 120  # a title line's characters at 9 pt on the 10-inch figure (about 140 fit)
PLOT_FORMATS = ("png", "pdf", "svg", "jpg", "jpeg", "tif", "tiff", "webp", "eps", "ps")  # matplotlib's (Agg) writers

def envelopes(run_path: str | Path, streams: list[str] | None = None, columns: int = PIXELS) -> list[Envelope]:
    """Envelopes of every signal column of ``streams`` (all streams if None), read in chunks."""
    with open_source(run_path) as src:
        return _envelopes(src.streams, run_path, streams, columns)


class _Column:
    """One column's envelope as its chunks come: per bin the (key, time, value) of its first, lowest, highest and
    last reading, and the holes of the record longer than two bins (with the intervals either side of them)."""

    def __init__(self, spans: int, t0: float, width: float) -> None:
        self.spans, self.t0, self.width = spans, t0, width
        self.key = {s: np.full(spans, np.inf) for s in ("first", "lo", "hi", "last")}
        self.at = {s: np.full(spans, np.nan) for s in self.key}
        self.val = {s: np.full(spans, np.nan) for s in self.key}
        self.prev_t, self.prev_dt = np.nan, np.nan  # the last reading so far and the interval before it
        self.holes: list[list[float]] = []  # [t before, t after, interval before, interval after]

    def add(self, t: np.ndarray, v: np.ndarray) -> None:
        ok = np.isfinite(t) & np.isfinite(v)
        t, v = t[ok], v[ok]
        if not t.size:
            return
        k = np.clip(((t - self.t0) / self.width).astype(np.int64) if self.width > 0 else np.zeros(t.size, np.int64),
                    0, self.spans - 1)
        for side, key in (("first", t), ("lo", v), ("hi", -v), ("last", -t)):
            bins, idx = _argmin_by_bin(k, key)
            better = key[idx] < self.key[side][bins]
            b, i = bins[better], idx[better]
            self.key[side][b], self.at[side][b], self.val[side][b] = key[i], t[i], v[i]
        self._holes(t)

    def _holes(self, t: np.ndarray) -> None:
        if self.holes and np.isnan(self.holes[-1][3]):  # the interval after the last hole: this chunk's first
            self.holes[-1][3] = float(t[0] - self.prev_t)
        tt = np.r_[self.prev_t, t] if np.isfinite(self.prev_t) else t
        dt = np.diff(tt)
        before = np.r_[self.prev_dt, dt[:-1]] if dt.size else dt
        after = np.r_[dt[1:], np.nan] if dt.size else dt
        for i in np.flatnonzero(np.abs(dt) > 2 * self.width):
            self.holes.append([float(tt[i]), float(tt[i + 1]), float(before[i]), float(after[i])])
        if dt.size:
            self.prev_dt = float(dt[-1])
        self.prev_t = float(t[-1])

    def line(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices (time order), NaN at each hole that is a gap."""
        t = np.concatenate([self.at[s] for s in self.at])
        v = np.concatenate([self.val[s] for s in self.val])
        keep = np.isfinite(t)
        t, v = t[keep], v[keep]
        order = np.lexsort((v, t))
        t, v = t[order], v[order]
        once = np.r_[True, (t[1:] != t[:-1]) | (v[1:] != v[:-1])][:t.size]  # a reading that is two vertices: once
        t, v = t[once], v[once]
        cuts = [h[1] for h in self.holes
                if abs(h[1] - h[0]) > GAP_RATIO * np.nanmax([abs(h[2]), abs(h[3]), 0.0])]
        at = np.searchsorted(t, cuts, side="left")
        return np.insert(t, at, np.nan), np.insert(v, at, np.nan)


def _argmin_by_bin(k: np.ndarray, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bins, index of the smallest ``key`` in each): one entry per bin present in ``k``, the first of equal keys.
    Readings in time order (the recorder writes them so) take the linear path; any other order is sorted."""
    if k.size > 1 and bool(np.any(k[1:] < k[:-1])):
        order = np.lexsort((key, k))  # by bin, then by key
        first = order[np.r_[True, k[order][1:] != k[order][:-1]]]
        return k[first], first
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    group = np.repeat(np.arange(starts.size), np.diff(np.r_[starts, k.size]))
    hit = np.flatnonzero(key == np.minimum.reduceat(key, starts)[group])
    first = hit[np.r_[True, group[hit][1:] != group[hit][:-1]]]
    return k[starts], first


def _envelopes(reader: StreamChunks, run_path: str | Path, streams: list[str] | None,
               columns: int) -> list[Envelope]:
    out: list[Envelope] = []
    names = streams if streams else list(reader.length)
    unknown = [s for s in names if s not in reader.length]
    if unknown:
        raise ValueError(f"run file {run_path}: no stream {', '.join(unknown)} (it has "
                         f"{', '.join(reader.length) or 'none'})")
    for stream in names:
        n = reader.length[stream]
        if n == 0:
            continue
        units = reader.units(stream)
        cols = [c for c in reader.columns[stream] if c != "t" and c not in FLAGS]
        t_first, t_last = np.inf, -np.inf  # the run clock's span of the stream (in any order the file has it)
        rows = _chunks.CHUNK_ROWS
        for a in range(0, n, rows):
            t = reader.read(stream, "t", a, min(a + rows, n)).astype(np.float64)
            t = t[np.isfinite(t)]
            if t.size:
                t_first, t_last = min(t_first, float(t.min())), max(t_last, float(t.max()))
        if not np.isfinite(t_first):
            continue
        spans = max(1, min(columns, n))
        width = (t_last - t_first) / spans
        acc = {c: _Column(spans, t_first, width) for c in cols}
        for chunk in reader.chunks(stream):
            t = chunk["t"].astype(np.float64)
            for c in cols:
                acc[c].add(t, chunk[c].astype(np.float64))
        edges = t_first + width * np.arange(spans + 1)
        edges[-1] = t_last
        for c in cols:
            lt, lv = acc[c].line()
            out.append(Envelope(stream, c, units.get(c, ""), edges, acc[c].val["lo"], acc[c].val["hi"], lt, lv, n))
    return out


def _alone(t: np.ndarray) -> np.ndarray:
    """Indices of the vertices with a break (NaN) or an end on both sides."""
    gap = np.r_[True, np.isnan(t), True]
    return np.flatnonzero(~gap[1:-1] & gap[:-2] & gap[2:])


def plot_name(run_path: str | Path, streams: list[str] | None = None) -> str:
    """The default name of a quick look: ``RUN-plot.png`` of all streams, ``RUN-plot-laser-amplifier.png`` of those
    chosen (in their order), so that plots of different streams of a run do not replace each other."""
    chosen = list(dict.fromkeys(streams or []))  # each once, in the order given
    return "-".join([f"{Path(run_path).stem}-plot", *(re.sub(r"[^\w.]", "_", s) for s in chosen)]) + ".png"


def verified_zero(events: list[tuple[float, int, str, str]]) -> list[tuple[float, float]]:
    """(run time [s], monitor voltage [V]) of each shutdown's verified reading, from the run's ``safe`` events."""
    return [(float(m[2]), float(m[1])) for _t, _step, kind, text in events
            if kind == "safe" and (m := VERIFIED.search(text)) is not None]


def quicklook(run_path: str | Path, streams: list[str] | None = None, out: str | Path | None = None,
              show: bool = False) -> Path | None:
    """Draw the envelopes of ``streams``; save a PNG (``out``: a new file — an existing one is refused — or a folder
    to hold :func:`plot_name`, one that exists or a name without a file type; default that name beside the run,
    replaced) or show a window. The PNG is written beside its target and moved into place whole."""
    import matplotlib

    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    default = plot_name(run_path, streams)
    # a folder: one that exists, or a name without a file type (``--out figs``, ``--out figs/``), which matplotlib
    # would have written as figs.png while the plot said "figure: figs"
    if out is not None and Path(out).exists() and not Path(out).is_dir():  # an existing file named with no type
        refuse_existing(Path(out), "plot", "--out")  # (/dev/null, "afile"): not a folder to write into ([Errno 17])
    folder = out is not None and (Path(out).is_dir() or not Path(out).suffix or str(out).endswith(("/", os.sep)))
    target = Path(run_path).with_name(default) if out is None else Path(out) / default if folder else Path(out)
    named = out is not None and not folder  # a file the user named is a new file; the default name is the run's own
    if named and not show:  # before the drawing
        refuse_existing(target, "plot", "--out")
        if target.suffix.lower().lstrip(".") not in PLOT_FORMATS:  # matplotlib's own words named no option
            raise ValueError(f"--out {target}: '{target.suffix}' is not a figure format the plot writes (one of "
                             f"{', '.join('.' + f for f in PLOT_FORMATS)}, or a folder)")
    with open_source(run_path) as src:  # opened once: metadata and streams
        run, env = src.run, _envelopes(src.streams, run_path, streams, PIXELS)
    if not env:
        raise ValueError(f"run file {run_path}: no recorded samples to plot")
    fig, axes = plt.subplots(len(env), 1, sharex=True, figsize=(10, 1.9 * len(env) + 0.8), squeeze=False)
    events = run.event_list()
    starts = [(t, text.split(" | ")[0]) for t, _, kind, text in events if kind == "start"]
    zero = verified_zero(events)
    for ax, e in zip(axes[:, 0], env, strict=True):
        if (e.stream, e.column) == ("amplifier", "voltage") and zero:
            ax.plot([t for t, _ in zero], [v for _, v in zero], "o", color="tab:red", markersize=4,
                    label="0 V verified at the stop")
            ax.legend(loc="upper right", fontsize=7)
        ax.plot(e.t, e.v, color="tab:blue", linewidth=0.5, label="_envelope")
        alone = _alone(e.t)  # a reading with a gap either side: a dot, not an invisible line
        if alone.size:
            ax.plot(e.t[alone], e.v[alone], ".", color="tab:blue", markersize=2, label="_alone")
        ax.set_ylabel(f"{e.stream}/{e.column}\n[{e.unit or '1'}]", fontsize=8)
        for t, _name in starts:
            ax.axvline(t, color="0.6", linewidth=0.6, linestyle=":")
        ax.grid(True, linewidth=0.3)
    axes[-1, 0].set_xlabel("t [s] (run clock)")
    state = run.state if run.complete else f"{run.state_shown}, INCOMPLETE: {run.incomplete_reason}"
    # wrapped to the figure's width (a killed or paused file's long state was cut off at both edges: outside tester),
    # the axes kept below it
    lines = textwrap.wrap(f"{Path(run_path).name} — {run.attrs.get('protocol_name', '?')} ({state})", TITLE_CHARS)
    fig.suptitle("\n".join(lines), fontsize=9)
    height = 1.9 * len(env) + 0.8
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - (0.1 + 0.16 * len(lines)) / height))
    if show:
        plt.show()
        plt.close(fig)
        return None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(target, replace=not named) as tmp:  # whole or not at all
            fig.savefig(tmp, dpi=110)
    except OSError as exc:
        if exc.errno is None:  # already one line naming the file (atomic_output's own refusal)
            raise
        # the OS's words alone ("[Errno 20] Not a directory: 'afile/sub'", an outside tester): the figure named
        raise OSError(f"{target}: cannot write the plot: {exc.strerror or exc} (errno {exc.errno})") from None
    finally:
        plt.close(fig)
    return target
