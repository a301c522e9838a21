"""Stream a run to one HDF5 file while it goes on (SWMR), and never leave it unmarked.

Layout (``format = "dea-bench run 1"``):

* root attributes — software version, protocol (name, path, full text, SHA-256), rig (name, TOML of the
  effective rig), specimen (JSON), recording settings (JSON), clock kind, simulated flag, start time;
  after a clean finish also end time, exit status and reason, ``complete = True``;
* ``/status`` — datasets ``state`` (running / completed / tripped / error / interrupted), ``reason``,
  ``end_time``, ``updated`` (rig time of the last flush): written during the run, so a file from a crashed
  run still says ``running`` and is recognised as incomplete;
* ``/program`` — the compiled steps (index, label, kind, start, duration);
* ``/events`` — step starts and ends, trips, operator actions (t, step, kind, text);
* one group per stream (``setpoints``, ``amplifier``, ``laser``, ``motor``, ``load_cell``) with a time base
  ``t`` [s on the run clock] and one dataset per column, chunked, gzip-compressed, with ``units`` attributes.

Datasets are created before SWMR mode starts, appended in blocks and flushed at least every
``flush_interval`` seconds of wall time, so another process can read the file during the run.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

FORMAT = "dea-bench run 1"
EVENT_DTYPE = np.dtype([("t", "f8"), ("step", "i4"), ("kind", "S16"), ("text", "S200")])
PROGRAM_DTYPE = np.dtype([("index", "i4"), ("label", "S240"), ("name", "S120"), ("kind", "S16"),
                          ("t_start", "f8"), ("duration", "f8")])
STATES = ("running", "completed", "tripped", "error", "interrupted")


@dataclass(frozen=True)
class Column:
    """One recorded quantity of a stream."""

    name: str
    units: str
    description: str
    dtype: str = "f8"


def now_iso() -> str:
    """UTC time stamp, ISO 8601."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class Recorder:
    """Appends blocks of samples to an HDF5 file in SWMR mode; see the module docstring for the layout."""

    def __init__(self, path: Path, attrs: dict[str, Any], streams: dict[str, list[Column]],
                 program: list[tuple[int, str, str, str, float, float]], rates: dict[str, float],
                 flush_interval: float = 0.45) -> None:
        self.path = Path(path)
        self.flush_interval = flush_interval
        self.streams = streams
        self._buffers: dict[str, dict[str, list[np.ndarray]]] = {s: {c.name: [] for c in [Column("t", "s", ""), *cols]}
                                                                 for s, cols in streams.items()}
        self._events: list[tuple[float, int, bytes, bytes]] = []
        self._last_flush = time.monotonic()
        self._last_t = 0.0
        self.samples_written = 0
        self.write_seconds = 0.0  # wall time spent writing
        self.cpu_seconds = 0.0  # CPU time of the calling thread spent in append and flush
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.path, "w", libver=("v110", "v110"))  # SWMR needs the 1.10 format; newer breaks 1.10 tools
        self._f = f
        f.attrs["format"] = FORMAT
        for key, value in attrs.items():
            f.attrs[key] = value if not isinstance(value, dict | list) else json.dumps(value)
        status = f.create_group("status")
        status.create_dataset("state", data=np.array([b"running"], dtype="S16"))
        status.create_dataset("reason", data=np.array([b""], dtype="S400"))
        status.create_dataset("end_time", data=np.array([b""], dtype="S40"))
        status.create_dataset("updated", data=np.array([0.0]))
        status["updated"].attrs["units"] = "s"
        prog = np.array([(i, lab.encode()[:240], name.encode()[:120], kind.encode(), t0, dur)
                         for i, lab, name, kind, t0, dur in program], dtype=PROGRAM_DTYPE)
        f.create_dataset("program", data=prog)
        f["program"].attrs["units"] = json.dumps({"t_start": "s", "duration": "s"})
        ev = f.create_dataset("events", shape=(0,), maxshape=(None,), dtype=EVENT_DTYPE, chunks=(256,))
        ev.attrs["units"] = json.dumps({"t": "s"})
        for name, cols in streams.items():
            g = f.create_group(name)
            rate = rates.get(name, 100.0)
            g.attrs["rate_Hz"] = rate
            chunk = int(min(65536, max(1024, rate * 2)))
            for col in [Column("t", "s", "time on the run clock"), *cols]:
                d = g.create_dataset(col.name, shape=(0,), maxshape=(None,), dtype=col.dtype, chunks=(chunk,),
                                     compression="gzip", compression_opts=1, shuffle=True)
                d.attrs["units"] = col.units
                d.attrs["description"] = col.description
        self._datasets = {s: {c.name: f[s][c.name] for c in [Column("t", "s", ""), *cols]}
                          for s, cols in streams.items()}  # cached: group look-ups cost more than the writes
        self._events_ds = f["events"]
        self._updated = f["status/updated"]
        f.swmr_mode = True
        f.flush()

    # -------------------------------------------------------------- writing
    def append(self, stream: str, t: np.ndarray | float, **columns: np.ndarray | float) -> None:
        """Queue samples of ``stream`` (flushed by :meth:`maybe_flush` / :meth:`flush`)."""
        c0 = time.thread_time()
        buf = self._buffers[stream]
        buf["t"].append(np.atleast_1d(np.asarray(t, dtype=float)))
        for name, values in columns.items():
            buf[name].append(np.atleast_1d(np.asarray(values)))
        self._last_t = max(self._last_t, float(np.max(buf["t"][-1])) if buf["t"][-1].size else self._last_t)
        self.cpu_seconds += time.thread_time() - c0

    def event(self, t: float, step: int, kind: str, text: str) -> None:
        """Queue an event."""
        self._events.append((t, step, kind.encode()[:16], text.encode()[:200]))

    def maybe_flush(self) -> None:
        """Flush if the flush interval has passed (call it often)."""
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        """Write every queued sample and event, and make them visible to readers."""
        t0, c0 = time.perf_counter(), time.thread_time()
        f = self._f
        for stream, buf in self._buffers.items():
            if not buf["t"]:
                continue
            datasets = self._datasets[stream]
            n_new = sum(a.size for a in buf["t"])
            for name, parts in buf.items():
                data = np.concatenate(parts) if len(parts) > 1 else parts[0]
                if data.size != n_new:
                    raise ValueError(f"stream {stream}: column {name} has {data.size} samples, t has {n_new}")
                d = datasets[name]
                n = d.shape[0]
                d.resize((n + n_new,))
                d.write_direct(np.ascontiguousarray(data, dtype=d.dtype), dest_sel=np.s_[n:n + n_new])
                parts.clear()
            self.samples_written += n_new
        if self._events:
            ev = self._events_ds
            n = ev.shape[0]
            ev.resize((n + len(self._events),))
            ev[n:] = np.array(self._events, dtype=EVENT_DTYPE)
            self._events.clear()
        self._updated[0] = self._last_t
        f.flush()
        self._last_flush = time.monotonic()
        self.write_seconds += time.perf_counter() - t0
        self.cpu_seconds += time.thread_time() - c0

    def set_state(self, state: str, reason: str = "") -> None:
        """Record the run's state (visible to readers at once)."""
        if state not in STATES:
            raise ValueError(f"unknown run state {state!r}")
        self._f["status/state"][0] = state.encode()
        self._f["status/reason"][0] = reason.encode()[:400]
        self.flush()

    def finish(self, state: str, reason: str) -> None:
        """Final flush, close, and stamp the root attributes (the file is complete after this)."""
        end = now_iso()
        self.set_state(state, reason)
        self._f["status/end_time"][0] = end.encode()
        self._f.flush()
        self._f.close()
        with h5py.File(self.path, "r+") as f:
            f.attrs["end_time"] = end
            f.attrs["exit_status"] = state
            f.attrs["exit_reason"] = reason
            f.attrs["complete"] = True
