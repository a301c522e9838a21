"""Replay: a recorded run's measured signals served through the simulated instruments.

:class:`ReplayPlant` takes the place of the rig's :class:`~bench.core.plant.Plant` behind the twins: it has the
plant's interface (the twins call ``advance_to``/``observe``, listen to its blocks and read the motor state), but its
blocks carry the record's values instead of the model's — the laser's displacement, the amplifier's monitors, the
load cell's force, the motor's position — so every twin serves real data over its own wire protocol, with its own
conversions and quantisation (and no noise of its own: the record has its own).

Time base: record time 0 is plant time :attr:`ReplayPlant.origin` — the start of the run recorded against the
replay (:meth:`ReplayPlant.anchor`, called just before the engine starts), or the moment the twins start serving
(``bench sim serve --replay``). Until then, and before the record's first sample, the first is served (so what
the twins saw while the host connected is the record's state at its time 0); after its last sample, the last.

Between samples, *next-sample hold*: the value recorded at t_i is served over (t_{i−1}, t_i]. A recorded sample is
the instrument's reading as of its time stamp — the latest conversion a poll returned, an integrating converter's
mean over the time before it — so an instrument that samples, or integrates over less than one record period, at
t_i reads exactly v_i: a run re-recorded on the same time stamps reproduces the record within the instruments'
quantisation. Interpolation would invent values between samples (and blur a polled stream's steps); a hold that
starts at t_i would give an integrating converter (ADAM-4017+) a mix of v_{i−1} and v_i.

What the host commands is ignored: the amplifier input and the motor's motion profiles are accepted (the twins'
registers, watchdogs and the drive's state machine behave as commanded, so the host's waits end) but move nothing;
the motor's position is the recorded one. The record is read a chunk at a time
(:class:`~bench.storage.chunks.StreamChunks`), forward as the clock goes, so memory does not grow with its length.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bench.core.clock import Clock
from bench.core.plant import PLANT_FIELDS, Plant, PlantBlock
from bench.rig import RigConfig, rig_from_toml
from bench.storage import scan_clock
from bench.storage.chunks import StreamChunks
from bench.storage.runfile import open_h5, read_table, valid_counts

TIME_TOL = 1e-9  # s: a record time this close before a plant step counts as at it (float sums of the time base)
# plant observable ← (stream, column) of the record
SOURCES = {"displacement": ("laser", "displacement"), "voltage": ("amplifier", "voltage"),
           "current": ("amplifier", "current"), "force": ("load_cell", "force")}
MOTOR = ("motor", "position")


class ReplayError(ValueError):
    """A replay file that cannot be served (one line)."""


class _Track:
    """One recorded column read forward a chunk at a time: value at any time by next-sample hold."""

    def __init__(self, chunks: StreamChunks, stream: str, column: str, rows: int) -> None:
        self.chunks, self.stream, self.column, self.rows = chunks, stream, column, rows
        self.n = chunks.length[stream]
        self.lock = threading.Lock()
        self._start = 0  # record index of self._t[0]
        self._t = np.zeros(0)
        self._v = np.zeros(0)

    def _load(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        ts, vs = [], []
        for c in self.chunks.chunks(self.stream, self.rows, start, stop):
            ts.append(c["t"].astype(float))
            vs.append(c[self.column].astype(float))
        return (np.concatenate(ts), np.concatenate(vs)) if ts else (np.zeros(0), np.zeros(0))

    def at(self, times: np.ndarray) -> np.ndarray:
        """Values at ``times`` (increasing): the first sample at or after each time (the last after the end)."""
        with self.lock:
            if times.size == 0 or self.n == 0:
                return np.full(times.size, np.nan)
            lo, hi = float(times[0]) - TIME_TOL, float(times[-1]) - TIME_TOL
            if self._start > 0 and (not self._t.size or self._t[0] >= lo):
                self._start, self._t, self._v = 0, np.zeros(0), np.zeros(0)  # asked further back: from the start
            end = self._start + self._t.size
            while end < self.n and (not self._t.size or self._t[-1] < hi):
                t, v = self._load(end, min(end + self.rows, self.n))
                self._t, self._v = np.concatenate([self._t, t]), np.concatenate([self._v, v])
                end += t.size
            idx = np.minimum(np.searchsorted(self._t, times - TIME_TOL, side="left"), self._t.size - 1)
            out = self._v[idx]
            drop = max(int(idx[0]) - 1, 0)  # keep the sample before the first one used (the next call's start)
            self._start += drop
            self._t, self._v = self._t[drop:], self._v[drop:]
            return out


class Recording:
    """A run file opened for replay: its measured streams as tracks."""

    def __init__(self, path: str | Path, rows: int = 65_536) -> None:
        p = Path(path)
        if not p.is_file():
            raise ReplayError(f"replay file {p}: not found")
        self.path = p
        try:
            self.file = open_h5(p)
        except ValueError:
            raise ReplayError(f"replay file {p}: not an HDF5 run file") from None
        try:
            if "status" not in self.file or "format" not in self.file.attrs:
                raise ReplayError(f"replay file {p}: not a dea-bench run file")
            self.attrs: dict[str, Any] = dict(self.file.attrs)
            self.chunks = StreamChunks(self.file)
        except ReplayError:
            self.file.close()
            raise
        self.kickoffs = _kickoffs(self.file)
        self.tracks: dict[tuple[str, str], _Track] = {}
        for stream, column in (*SOURCES.values(), MOTOR):
            if column in self.chunks.columns.get(stream, []) and self.chunks.length[stream] > 0:
                self.tracks[stream, column] = _Track(self.chunks, stream, column, rows)

    @property
    def run_id(self) -> str:
        """The recorded run's id ('' in files without one)."""
        v = self.attrs.get("run_id", "")
        return v.decode() if isinstance(v, bytes) else str(v)

    def has(self, stream: str) -> bool:
        """Whether the record has this stream with samples."""
        return any(s == stream for s, _ in self.tracks)

    def close(self) -> None:
        """Close the file."""
        self.file.close()


def _kickoffs(f: h5py.File) -> list[float]:
    """The record's hardware-timed streams' scan 0 times [s, record time], in order: its ``timing`` events
    (:meth:`bench.runtime.hardware_timed.HardwareTimed.start` writes them); none on a software-timed rig."""
    if "events" not in f:
        return []
    events = read_table(f["events"], valid_counts(f).get("events"))
    return [k[0] for e in events if e["kind"] == scan_clock.KIND.encode()
            and (k := scan_clock.parse_kickoff(bytes(e["text"]).decode("utf-8", "replace"))) is not None]


def replay_rig(path: str | Path) -> RigConfig:
    """The rig a run file was recorded on (its ``rig_toml``), as a simulated rig that replays the file."""
    recording = Recording(path)
    try:
        text = recording.attrs.get("rig_toml")
        if not text:
            raise ReplayError(f"replay file {path}: records no rig (rig_toml); give a rig file")
        rig = rig_from_toml(text.decode() if isinstance(text, bytes) else str(text))
    finally:
        recording.close()
    sim = rig.simulation.model_copy(update={"replay": str(path)})
    return rig.model_copy(update={"simulated": True, "simulation": sim})


def check_fits(recording: Recording, needs: dict[str, str]) -> None:
    """Refuse a record that lacks a stream a twin of the rig serves: ``needs`` maps stream → the twin's name."""
    missing = [f"{stream} (for the {twin})" for stream, twin in needs.items() if not recording.has(stream)]
    if missing:
        raise ReplayError(f"replay file {recording.path}: records no {', no '.join(missing)} stream; the rig's "
                          "twins need it")


class ReplayPlant(Plant):
    """A :class:`Plant` whose blocks are a record's values (see the module's docstring)."""

    def __init__(self, clock: Clock, recording: Recording, base: Plant) -> None:
        """``base``: the rig's own plant (specimen, output stage, configuration: what the engine and the twins ask
        of it); its model is not advanced."""
        self.recording = recording
        self.origin = math.inf  # not anchored yet: the record's first sample (its state at record time 0)
        self._kickoffs = 0  # hardware-timed streams started so far (stream_started)
        self.__dict__.update({k: v for k, v in base.__dict__.items() if k not in ("lock", "listeners")})
        self.lock = threading.RLock()
        self.listeners = []
        self.clock = clock
        self._refresh_last_at_rest()

    def anchor(self, t: float) -> None:
        """Record time 0 is plant time ``t`` from now on (the run recorded against the replay starts)."""
        with self.lock:
            self.origin = float(t)

    def stream_started(self, t: float) -> None:
        """The k-th hardware-timed stream's scan 0 is at plant time ``t``: the record's k-th kickoff (its scan 0, from
        its ``timing`` event) is served from then on. A record made on the wall clock started its stream some
        0.1 s after the run (connects, arming), a run in virtual time at once: aligned on the run's start alone, the
        replayed monitors lagged the drive by that much and the output verifier tripped (found from outside)."""
        with self.lock:
            k, self._kickoffs = self._kickoffs, self._kickoffs + 1
            if math.isfinite(self.origin) and k < len(self.recording.kickoffs):
                self.origin = float(t) - self.recording.kickoffs[k]

    def warm_up(self) -> None:
        """Nothing to compile: no model runs."""

    def _values(self, t: np.ndarray) -> dict[str, np.ndarray]:
        rt = t - self.origin
        out = {}
        for name, key in SOURCES.items():
            track = self.recording.tracks.get(key)
            out[name] = track.at(rt) if track is not None else np.zeros(t.size)
        return out

    def _advance(self, n: int) -> None:
        t = (self._n + np.arange(1, n + 1, dtype=float)) * self.h
        self._check_watchdog(float(t[-1]))  # the module's safety behaviour, as commanded
        self._input_pieces(n)  # the host's amplifier input: accepted, ignored
        self._pieces(self._motions, n)  # the motion profiles used up: dropped, as the plant does
        self._n += n
        self.t = self._n * self.h
        self._emit(t)

    def _emit(self, t: np.ndarray) -> None:
        v = self._values(t)
        breakdown = float(getattr(self.specimen, "breakdown_field", np.inf))
        field = np.full(t.size, np.nan)  # not in a record
        block = PlantBlock(t, v["voltage"], v["current"], v["displacement"], v["force"], field,
                           np.full(t.size, breakdown), v["voltage"], v["current"])
        self.v_out = float(v["voltage"][-1])
        self.last = PlantBlock(*(getattr(block, f)[-1:] for f in PLANT_FIELDS))
        for listener in self.listeners:
            listener(block)

    def _refresh_last_at_rest(self) -> None:
        t = np.array([self.t])
        v = self._values(t)
        field = np.full(1, np.nan)
        breakdown = np.full(1, float(getattr(self.specimen, "breakdown_field", np.inf)))
        self.last = PlantBlock(t, v["voltage"], v["current"], v["displacement"], v["force"], field, breakdown,
                               v["voltage"], v["current"])

    def motor_state(self, t: float | None = None) -> tuple[float, float]:
        """The recorded motor position at t (default: now) and the commanded profile's velocity (the drive's
        state machine runs as commanded; only the position is the record's)."""
        when = self.clock.now() if t is None else t
        _, vel = self.motion.at(when)
        track = self.recording.tracks.get(MOTOR)
        if track is None:
            return super().motor_state(when)
        return float(track.at(np.array([when - self.origin]))[0]), float(vel)

    def change_specimen(self, temperature_K: float | None = None, hung_mass_kg: float | None = None,
                        prototype: int | None = None) -> None:
        """The record's specimen is what it is: a change between tests only advances to now."""
        with self.lock:
            self.advance_to(self.clock.now())

    def inject_breakdown(self) -> None:
        """Faults of the specimen are the record's: an injected breakdown is refused."""
        raise ValueError("replay: the specimen is a record; a breakdown cannot be injected")
