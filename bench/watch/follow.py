"""A run file followed while it grows: every stream reduced to min/max bins as few as a screen's columns.

Each stream's records are folded into bins of ``size`` consecutive records (the minimum and maximum of every
column, and of the time base, per bin). When the record outgrows ``2 × pixels`` bins, neighbouring bins are merged
in pairs and ``size`` doubles, so a stream holds between ``pixels`` and ``2 × pixels`` bins whatever its length: a
12-hour record at 10 kHz costs the page what a 1-minute one does. Each look reads only the records confirmed
(``/status/samples``) since the last one, through :class:`bench.storage.chunks.StreamChunks`, and at most
``budget`` records per stream, so a long finished file is caught up over a few looks while the page already draws.

A client keeps the bins it was sent with their ``generation``; it is sent again only what changed: the bins from
its last one on (the last bin may have grown), or all of them after a merge (a new generation).
"""

from __future__ import annotations

import errno
import json
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bench.storage.chunks import StreamChunks
from bench.storage.runfile import KILLED, open_h5, read_status, read_table, valid_counts

FLAGS = ("valid", "ok")  # flag columns: not drawn as signals (as bench plot)
PIXELS = 1000  # bins per stream at least (at most twice that): about a screen's width
BUDGET = 2_000_000  # records read per stream per look (a finished long file is caught up over several looks)
MIN_LOOK_S = 0.2  # a look sooner than this after the last one reads nothing (several pages poll one file)
GONE_AFTER_S = 5.0  # a "running" file whose status has not moved this long: is its writer gone? (a /proc scan)
LIMITS = {"V": "max_voltage_V", "A": "max_current_A", "N": "max_force_N"}  # rig limit drawn on panels of a unit
# events drawn on the time axis (the engine's kinds): step starts, operator actions, uploads after a step, how the run
# ended
MARKED = ("start", "pause", "resume", "restart", "drain", "specimen", "request", "stop", "interrupted", "tripped",
          "error", "interlock", "fault", "watchdog", "safe")
FAULTS = ("tripped", "error", "interlock", "fault", "watchdog")  # listed as the run's faults


@dataclass
class Bins:
    """Min/max bins of one stream's columns; bin ``k`` holds records ``k·size`` … ``(k+1)·size − 1``."""

    columns: list[str]
    pixels: int = PIXELS
    size: int = 1
    records: int = 0
    generation: int = 0
    t_lo: np.ndarray = field(default_factory=lambda: np.zeros(0))
    t_hi: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lo: dict[str, np.ndarray] = field(default_factory=dict)
    hi: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for c in self.columns:
            self.lo[c], self.hi[c] = np.zeros(0), np.zeros(0)

    def _merge(self) -> None:
        """Pairs of bins into one; ``size`` doubles (an odd last bin stays alone, still partial)."""
        n = self.t_lo.size
        starts = np.arange(0, n, 2)
        self.t_lo = np.minimum.reduceat(self.t_lo, starts) if n else self.t_lo
        self.t_hi = np.maximum.reduceat(self.t_hi, starts) if n else self.t_hi
        for c in self.columns:
            if n:
                self.lo[c] = np.fmin.reduceat(self.lo[c], starts)
                self.hi[c] = np.fmax.reduceat(self.hi[c], starts)
        self.size *= 2
        self.generation += 1

    def add(self, chunk: dict[str, np.ndarray]) -> int:
        """Fold the next records in; returns the index of the first bin that changed."""
        m = chunk["t"].size
        if m == 0:
            return self.t_lo.size
        while -(-(self.records + m) // self.size) > 2 * self.pixels:
            self._merge()
        k = np.arange(self.records, self.records + m) // self.size  # bin of each record
        starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        first = int(k[0])
        t = chunk["t"].astype(np.float64)
        parts = {"t_lo": np.minimum.reduceat(t, starts), "t_hi": np.maximum.reduceat(t, starts)}
        lo = {c: np.fmin.reduceat(chunk[c].astype(np.float64), starts) for c in self.columns}
        hi = {c: np.fmax.reduceat(chunk[c].astype(np.float64), starts) for c in self.columns}
        if first < self.t_lo.size:  # the last bin was partial: it takes the chunk's first part
            parts["t_lo"][0] = min(parts["t_lo"][0], self.t_lo[first])
            parts["t_hi"][0] = max(parts["t_hi"][0], self.t_hi[first])
            for c in self.columns:
                lo[c][0] = np.fmin(lo[c][0], self.lo[c][first])
                hi[c][0] = np.fmax(hi[c][0], self.hi[c][first])
        self.t_lo = np.concatenate([self.t_lo[:first], parts["t_lo"]])
        self.t_hi = np.concatenate([self.t_hi[:first], parts["t_hi"]])
        for c in self.columns:
            self.lo[c] = np.concatenate([self.lo[c][:first], lo[c]])
            self.hi[c] = np.concatenate([self.hi[c][:first], hi[c]])
        self.records += m
        return first

    def since(self, generation: int, have: int) -> dict[str, Any]:
        """What a client holding ``have`` bins of ``generation`` lacks: ``from`` (first bin sent) and the bins."""
        start = max(0, min(have - 1, self.t_lo.size)) if generation == self.generation else 0
        return {"generation": self.generation, "size": self.size, "records": self.records, "from": start,
                "t_lo": _json(self.t_lo[start:]), "t_hi": _json(self.t_hi[start:]),
                "lo": {c: _json(self.lo[c][start:]) for c in self.columns},
                "hi": {c: _json(self.hi[c][start:]) for c in self.columns}}


def _json(a: np.ndarray) -> list[float | None]:
    """Floats for JSON: NaN and ±inf (a bin with no finite value) as null."""
    out: list[float | None] = a.tolist()
    if not np.isfinite(a).all():
        out = [v if v is not None and np.isfinite(v) else None for v in out]
    return out


class Follower:
    """One run file followed: its streams' bins, state, events, limits; one look at a time (thread-safe)."""

    def __init__(self, path: Path, pixels: int = PIXELS, budget: int = BUDGET) -> None:
        self.path = path
        self.pixels = pixels
        self.budget = budget
        self.f: h5py.File | None = None
        self.bins: dict[str, Bins] = {}
        self.units: dict[str, dict[str, str]] = {}
        self.info: dict[str, Any] = {"state": "waiting", "reason": f"waiting for {path.name}"}
        self.static: dict[str, Any] = {"name": path.name, "limits": {}, "steps": []}
        self._lock = threading.Lock()
        self._looked = -1e9
        self.read_records = 0  # records read in all (the benchmark's count)
        self._updated, self._moved, self._scanned, self._gone = float("nan"), 0.0, -1e9, False  # _writer_gone's

    def close(self) -> None:
        with self._lock:
            if self.f is not None:
                self.f.close()
                self.f = None

    def look(self) -> None:
        """Read what the writer confirmed since the last look (at most ``budget`` records a stream)."""
        with self._lock:
            if time.monotonic() - self._looked < MIN_LOOK_S:
                return
            self._looked = time.monotonic()
            if self.f is None:
                if not self.path.exists():
                    return
                try:
                    self.f = open_h5(self.path)
                except ValueError as exc:  # being created (before SWMR mode): looked at again next time
                    self.info = {"state": "waiting", "reason": str(exc)}
                    return
                self._static()
            f = self.f
            self._status(f)
            reader = StreamChunks(f, self.path)
            for name in reader.length:
                if name not in self.bins:
                    self.units[name] = reader.units(name)
                    cols = [c for c in reader.columns[name] if c != "t" and c not in FLAGS]
                    self.bins[name] = Bins(cols, self.pixels)
                b = self.bins[name]
                for chunk in reader.chunks(name, start=b.records, stop=b.records + self.budget):
                    b.add(chunk)
                    self.read_records += chunk["t"].size
            self.info["behind"] = {k: reader.length[k] - b.records for k, b in self.bins.items()}

    def _static(self) -> None:
        """What the file holds from its start: the rig's limits, the program, the run's identity."""
        if self.f is None:
            return
        a = self.f.attrs

        def text(k: str) -> str:
            return (a[k].decode() if isinstance(a[k], bytes) else str(a[k])) if k in a else ""

        limits: dict[str, float] = {}
        try:
            rig = tomllib.loads(text("rig_toml")) if text("rig_toml") else {}
            limits = {unit: float(rig["limits"][key]) for unit, key in LIMITS.items() if key in rig.get("limits", {})}
        except (tomllib.TOMLDecodeError, TypeError, ValueError):
            limits = {}
        program: Any = read_table(self.f["program"]) if "program" in self.f else []
        self.static = {"name": self.path.name, "protocol": text("protocol_name"), "rig": text("rig_name"),
                       "simulated": text("simulated"), "start_time": text("start_time"), "limits": limits,
                       "steps": [{"index": int(p["index"]), "name": p["name"].decode(), "t_start": float(p["t_start"]),
                                  "duration": float(p["duration"])} for p in program]}

    def _status(self, f: h5py.File) -> None:
        state, reason, _, updated = read_status(f, self.path)  # checked: one line naming the field, on the page
        valid = valid_counts(f, self.path)
        events = read_table(f["events"], valid.get("events"))
        marks = [{"t": float(e["t"]), "step": int(e["step"]), "kind": e["kind"].decode(errors="replace"),
                  "text": e["text"].decode(errors="replace")} for e in events]
        held = [m["kind"] for m in marks if m["kind"] in ("pause", "resume")]
        if state == "running" and held and held[-1] == "pause":  # the file says running; its events, paused
            state = "paused"
        if state in ("running", "paused"):  # the file says so, but its writer may be gone: ended, not stamped
            state, reason = self._writer_gone(state, reason, updated)
        from bench.runtime.latch import latched

        latch = latched(self.static["rig"]) if self.static.get("rig") else None
        faults = [m for m in marks if m["kind"] in FAULTS]
        self.info = {"state": state, "reason": reason, "updated": updated,
                     "events": [m for m in marks if m["kind"] in MARKED], "faults": faults,
                     "latched": json.dumps(latch) if latch else ""}

    def _writer_gone(self, state: str, reason: str, updated: float) -> tuple[str, str]:
        """(state, reason) of a file that says it is running (or paused) whose writer is gone, as a listing shows it
        (:func:`~bench.storage.runfile.state_shown`): its write failed (``/status/reason``, at once), or, once its
        status has not moved for :data:`GONE_AFTER_S`, no process here holds it open (a killed run; the page showed
        it running for good). The /proc scan runs at most every :data:`GONE_AFTER_S`, and only then."""
        from bench.storage.recorder import STORAGE_FAULT
        from bench.storage.runfile import DISK_FULL, WRITE_FAILED, orphaned_file, state_shown

        if reason.startswith(STORAGE_FAULT):
            full = any(f"(errno {e})" in reason for e in (errno.ENOSPC, errno.EDQUOT))
            return state_shown("running", False, DISK_FULL if full else WRITE_FAILED), reason
        now = time.monotonic()
        if updated != self._updated:
            self._updated, self._moved = updated, now
        elif now - self._moved >= GONE_AFTER_S and now - self._scanned >= GONE_AFTER_S:
            self._scanned = now
            self._gone = orphaned_file(self.path)
        if self._gone and updated == self._updated:
            return state_shown("running", False, KILLED), f"{KILLED}: no process holds the file open"
        return state, reason

    def payload(self, have: dict[str, tuple[int, int]]) -> dict[str, Any]:
        """State, marks, limits and each stream's bins a client lacks (``have``: stream → (generation, bins))."""
        with self._lock:
            streams = {name: {"units": self.units[name], **b.since(*have.get(name, (-1, 0)))}
                       for name, b in self.bins.items()}
            return {**self.static, **self.info, "streams": streams}
