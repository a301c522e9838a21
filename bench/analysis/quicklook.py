"""Quick-look figure of any streams of a run file (``bench plot``): one panel per column, units on every axis.

A record of hours at 10 kHz does not fit on a screen: each column is reduced, chunk by chunk as the file is read
(:mod:`bench.storage.chunks`), to its minimum and maximum in each of ``columns`` equal spans of the record — the
envelope a screen of that width shows, every extreme kept — so memory and drawing time do not grow with the run.
Step starts are marked, and so is the shutdown's verified 0 V on the amplifier's voltage (a DAQ rig's streams end
on the last scan before the stop: the reading after it is in the ``safe`` event); an incomplete file says so in the
title.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.storage.chunks import StreamChunks, open_source
from bench.storage.outputs import atomic_output, refuse_existing

FLAGS = ("valid", "ok")  # flag columns: not drawn as signals
PIXELS = 2000  # min/max spans per column (about a screen's width)
# the shutdown's own reading (bench/runtime/engine.py ``_verify_safe``): a DAQ rig's streams end on the last scan
# before the stop, so without it the amplifier panel ends at the voltage then, not at the 0 V verified after
VERIFIED = re.compile(r"verified: voltage monitor (-?\d+(?:\.\d+)?) V at (-?\d+(?:\.\d+)?) s")


@dataclass
class Envelope:
    """A column reduced to spans: the time at each span's middle, its minimum and its maximum."""

    stream: str
    column: str
    unit: str
    t: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    samples: int


def envelopes(run_path: str | Path, streams: list[str] | None = None, columns: int = PIXELS) -> list[Envelope]:
    """Min/max envelopes of every signal column of ``streams`` (all streams if None), read in chunks."""
    with open_source(run_path) as src:
        return _envelopes(src.streams, run_path, streams, columns)


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
        spans = min(columns, n)
        edges = np.linspace(0, n, spans + 1).astype(np.int64)  # span k holds records edges[k] … edges[k+1]-1
        lo = {c: np.full(spans, np.inf) for c in cols}
        hi = {c: np.full(spans, -np.inf) for c in cols}
        t_lo, t_hi = np.full(spans, np.inf), np.full(spans, -np.inf)
        a = 0
        for chunk in reader.chunks(stream):
            b = a + chunk["t"].size
            k = np.searchsorted(edges, np.arange(a, b), side="right") - 1  # span of each record
            starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
            which = k[starts]
            np.minimum.at(t_lo, which, np.minimum.reduceat(chunk["t"], starts))
            np.maximum.at(t_hi, which, np.maximum.reduceat(chunk["t"], starts))
            for c in cols:
                v = chunk[c].astype(np.float64)
                with np.errstate(invalid="ignore"):  # a pixel of only NaN (no valid reading) stays NaN: not drawn
                    np.minimum.at(lo[c], which, np.fmin.reduceat(v, starts))
                    np.maximum.at(hi[c], which, np.fmax.reduceat(v, starts))
            a = b
        mid = (t_lo + t_hi) / 2
        for c in cols:
            out.append(Envelope(stream, c, units.get(c, ""), mid, lo[c], hi[c], n))
    return out


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
    folder = out is not None and (Path(out).is_dir() or not Path(out).suffix or str(out).endswith(("/", os.sep)))
    target = Path(run_path).with_name(default) if out is None else Path(out) / default if folder else Path(out)
    named = out is not None and not folder  # a file the user named is a new file; the default name is the run's own
    if named and not show:  # before the drawing
        refuse_existing(target, "plot", "--out")
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
        finite = np.isfinite(e.lo) & np.isfinite(e.hi)
        ax.fill_between(e.t[finite], e.lo[finite], e.hi[finite], color="tab:blue", linewidth=0.6, step="mid")
        ax.plot(e.t[finite], e.hi[finite], color="tab:blue", linewidth=0.5)
        ax.set_ylabel(f"{e.stream}/{e.column}\n[{e.unit or '1'}]", fontsize=8)
        for t, _name in starts:
            ax.axvline(t, color="0.6", linewidth=0.6, linestyle=":")
        ax.grid(True, linewidth=0.3)
    axes[-1, 0].set_xlabel("t [s] (run clock)")
    state = run.state if run.complete else f"{run.state}, INCOMPLETE: {run.incomplete_reason}"
    fig.suptitle(f"{Path(run_path).name} — {run.attrs.get('protocol_name', '?')} ({state})", fontsize=9)
    fig.tight_layout()
    if show:
        plt.show()
        plt.close(fig)
        return None
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_output(target, replace=not named) as tmp:  # whole or not at all
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
    return target
