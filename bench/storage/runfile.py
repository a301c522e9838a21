"""Read a run file (also while it is being written) — the only way analysis sees a run."""

from __future__ import annotations

import errno
import functools
import io
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bench.storage import scan_clock as kickoffs
from bench.storage.absent import absent_run_file
from bench.storage.recorder import EVENT_FIELDS, FORMATS, PROGRAM_FIELDS, STATES, STORAGE_FAULT
from bench.storage.superblock import clear_consistency_flags, open_elsewhere, read_superblock


@dataclass
class Stream:
    """One recorded stream: time base and columns (numpy arrays), their units."""

    name: str
    t: np.ndarray
    columns: dict[str, np.ndarray]
    units: dict[str, str]
    rate: float

    def __len__(self) -> int:
        return int(self.t.size)


KILLED = "no end recorded: the run crashed or was killed"  # a dead writer's file: the start of its incomplete_reason
# a file whose writing failed (the writer abandoned it, its end unstamped): the starts of its incomplete_reason
DISK_FULL = "no end recorded: the disk was full"
WRITE_FAILED = "no end recorded: writing the file failed"
ENDED_SHOWN = {KILLED: "crashed or killed", DISK_FULL: "ended unstamped: disk full",
               WRITE_FAILED: "ended unstamped: write failed"}  # each such start, the state a listing shows
# a run under way that is paused (its last pause event not followed by a resume): the start of its incomplete_reason,
# so the catalogue's row (which keeps that reason) lists it "paused" as inspect does
PAUSED = "no end recorded: the run is paused"
SHOWN = {**ENDED_SHOWN, PAUSED: "paused"}


def state_shown(state: str, complete: bool, incomplete_reason: str) -> str:
    """A run's state as a listing shows it: the file's ``/status/state``, except that a file whose writer is gone
    says so — its state stays ``running`` (nothing stamped its end; ``bench recover`` keeps it), which read as a run
    still going after ``bench recover`` (found by an outside tester), and so did a run that ended on a full disk
    (its writer abandoned the file when a write failed, a second tester): shown as ended, without its stamp."""
    if state == "running" and not complete:
        for start, shown in SHOWN.items():
            if incomplete_reason.startswith(start):
                return shown
    return state


def recorded_note(updated: float, ends: Sequence[float]) -> str:
    """What "recorded up to ``updated`` s" means where a stream runs past it: ``ends``, the time of each stream's last
    sample. Whole-chunk writes carry a stream's samples ahead of ``/status/updated``, the time to which every stream
    and the events are on file; '' where no stream runs past it. Where every stream does, that is said with the
    earliest of their ends (after a full disk, both streams reached 7.750 s while the note said only "some stream"
    went on past 5.491 s: found by an outside tester)."""
    if not ends or max(ends) <= updated + 5e-4:  # the same at the 3 decimals shown
        return ""
    first, last = min(ends), max(ends)
    if first > updated + 5e-4:
        return (f" (the events are on file to here; every stream's samples go on to {first:.3f} s"
                + (f", some to {last:.3f} s)" if last > first + 5e-4 else ")"))
    return f" (every stream and the events complete to here; some stream's samples go on to {last:.3f} s)"


@dataclass
class RunFile:
    """Contents of a run file."""

    path: Path
    attrs: dict[str, Any]
    state: str
    reason: str
    end_time: str
    updated: float
    complete: bool
    streams: dict[str, Stream] = field(default_factory=dict)
    events: np.ndarray = field(default_factory=lambda: np.zeros(0))  # records t, step, kind, text (UTF-8 bytes)
    program: np.ndarray = field(default_factory=lambda: np.zeros(0))  # index, label, name, kind, t_start, duration
    orphaned: bool = False  # 'running', marked open by a writer, and no process on this machine has it open

    @property
    def recovered_at(self) -> str:
        """When ``bench recover`` released the file of a crashed run ('' if it never had to)."""
        return str(self.attrs.get("recovered_at", ""))

    @property
    def state_shown(self) -> str:
        """:func:`state_shown` of this file; "paused" for a run under way that is paused (:attr:`paused`): its file
        says ``running`` all the while, and `bench inspect` showed it so (found by an outside tester)."""
        return state_shown(self.state, self.complete, self.incomplete_reason)

    @property
    def paused(self) -> bool:
        """Whether its last ``pause`` event is not yet followed by a ``resume`` (as ``bench pause`` and the watch
        page read it)."""
        held = [kind for _, _, kind, _ in self.event_list() if kind in ("pause", "resume")]
        return bool(held) and held[-1] == "pause"

    @property
    def paused_s(self) -> float:
        """Time spent paused: the sum of each ``pause``→``resume`` span, and a pause still open runs to
        :attr:`updated`. The file's clock runs on through a pause, the protocol's does not (a file killed while paused
        read "18.250 s of 14.0 s planned": an outside tester)."""
        held, since = 0.0, None
        for t, _, kind, _ in self.event_list():
            if kind == "pause" and since is None:
                since = t
            elif kind == "resume" and since is not None:
                held, since = held + t - since, None
        return held + (max(self.updated - since, 0.0) if since is not None else 0.0)

    @property
    def storage_fault(self) -> str:
        """Why writing the file failed, as its writer marked ``/status/reason`` then ('' if it did not)."""
        if self.state == "running" and self.reason.startswith(STORAGE_FAULT):
            return self.reason[len(STORAGE_FAULT):].split(" | ")[0]
        return ""

    @property
    def incomplete_reason(self) -> str:
        """Why the file is not a complete record ('' if it is)."""
        if self.complete:
            return ""
        if self.storage_fault:
            full = any(f"(errno {e})" in self.storage_fault for e in (errno.ENOSPC, errno.EDQUOT))
            why = f"{DISK_FULL}: " if full else "no end recorded: "
            return (f"{why}writing the file failed ({self.storage_fault})"
                    + (f"; file recovered at {self.recovered_at}" if self.recovered_at else ""))
        if self.recovered_at and self.state != "running":  # its end is in /status: the stamp of the root failed
            return f"finished ({self.state}) but not finalised (file recovered at {self.recovered_at})"
        if self.recovered_at:
            return f"{KILLED} (file recovered at {self.recovered_at})"
        if self.orphaned:
            return (f"{KILLED} (no process on this machine has the file open; `bench recover` releases it for other "
                    "HDF5 tools)")
        if self.state == "running" and self.paused:
            return f"{PAUSED} (`bench resume {self.path} --why …` continues it), or it crashed / was killed"
        if self.state == "running":
            return "no end recorded: the run is still going, or it crashed / was killed"
        return "finished but not finalised (writer stopped before stamping the file)"

    def specimen(self, model: bool = False) -> dict[str, Any]:
        """The ``specimen`` attribute: the specimen the run was made on, with its ``model`` if asked (a fit needs
        it); :func:`specimen_of`."""
        return specimen_of(self.attrs, self.path, model)

    def event_list(self) -> list[tuple[float, int, str, str]]:
        """Events as (t, step, kind, text)."""
        return [(float(e["t"]), int(e["step"]), e["kind"].decode(), e["text"].decode()) for e in self.events]

    def completed_steps(self) -> set[int]:
        """Indices of the steps whose end the file recorded (a step's last start followed by its end): a step cut
        by a crash, a stop or a pause (and not restarted to its end) is not among them. (A manual session's own
        ``end``, at step −1, is no step: its listing read "steps 1/0".)"""
        done: set[int] = set()
        for _, step, kind, _ in self.event_list():
            if kind == "start":
                done.discard(step)
            elif kind == "end" and step >= 0:
                done.add(step)
        return done

    def step_offsets(self, scan_clock: bool = True) -> dict[int, float]:
        """Run time − program time of each step's last start [s]: a resumed file and a pause shift the program
        (``offset`` events, "run time = program time + X s"); steps absent here ran with none (0).

        ``scan_clock``: a step a DAQ played on a stream it started is where that stream's scan 0 is (its ``timing``
        event, :mod:`bench.storage.scan_clock`: the waveform's first value plays there), and a step appended to that
        stream is on the same scan clock: a wall-clock stream starts some 50–110 ms after the step's ``start`` event
        (arming it), and the cycles were cut that far off the waveform's (an outside tester). A stream of the
        engine's own (a ramp), an ``offset`` event and a step of no duration end that clock. Without it (``False``):
        the host's schedule, on which the motor's go-tos are sent (an isopotential step's cycles). Both at once, in
        one pass over the events: :meth:`step_offset_clocks`."""
        scan, host = self.step_offset_clocks()
        return scan if scan_clock else host

    def step_offset_clocks(self) -> tuple[dict[int, float], dict[int, float]]:
        """(:meth:`step_offsets` on the scan clock, on the host's schedule), from one pass over the events."""
        rows = zip(self.program["index"], self.program["t_start"], self.program["duration"], strict=True) \
            if self.program.size else ()
        starts = {int(i): (float(t), float(d)) for i, t, d in rows}
        offset, clock, scan, host = 0.0, None, {}, {}
        for _, step, kind, text in self.event_list():
            if kind == "offset":
                offset, clock = float(text.rsplit("+", 1)[1].split()[0]), None
            elif kind == "start":
                if starts.get(step, (0.0, 0.0))[1] <= 0:
                    clock = None
                scan[step] = offset if clock is None else clock
                host[step] = offset
            elif kind == kickoffs.KIND and (k := kickoffs.parse_kickoff(text)) is not None:
                if k[1] and step in starts:  # a step's own stream: its scan 0 plays t_start
                    clock = scan[step] = k[0] - starts[step][0]
                else:
                    clock = None
        return scan, host

    def specimen_changes(self) -> list[tuple[float, dict[str, float]]]:
        """Specimen changes during the run (``specimen`` events "key=value, …") as (t, {key: value})."""
        out = []
        for t, _, kind, text in self.event_list():
            if kind == "specimen":
                out.append((t, {k.strip(): float(v) for k, _, v in (p.partition("=") for p in text.split(","))}))
        return out

    def step_starts(self) -> dict[int, float]:
        """Run time of each step's last ``start`` event [s]: when the step began as recorded (a step of the program
        begins when the one before it has ended, a little after its program time on any clock)."""
        return {step: t for t, step, kind, _ in self.event_list() if kind == "start"}

    def specimen_at(self, t: float) -> dict[str, float]:
        """The specimen changes in effect at run time ``t`` [s]: each change (``specimen`` event) holds from the
        time it was logged on, the latest of each key kept (keys never changed are absent)."""
        out: dict[str, float] = {}
        for te, values in self.specimen_changes():
            if te <= t + 1e-9:
                out.update(values)
        return out

    def temperature_at(self, t: np.ndarray | float) -> np.ndarray:
        """The specimen temperature [K] at run time(s) ``t``: the specimen's (its override, else 296 K) until a
        ``temperature_K`` change is logged, that change's from its time on (as :meth:`specimen_at`). The one
        reading of the temperature history: the fit's inputs and the report's steps both come from it."""
        spec = self.specimen()
        T0 = spec.get("overrides", {}).get("temperature_K") or spec.get("temperature_K", 296.0)
        tt = np.asarray(t, dtype=float)
        out = np.full(tt.shape, float(T0))
        for te, values in self.specimen_changes():
            if "temperature_K" in values:
                out[tt + 1e-9 >= te] = float(values["temperature_K"])
        return out


class ManualSessionError(ValueError):
    """The readings of a manual-control session (``bench devices control``: attribute ``session_log``) where the
    record of a protocol's run was needed: it has no program of steps to analyse or fit against."""


def refuse_manual_session(run: RunFile, what: str) -> None:
    """ManualSessionError (one line naming the file, then ``what`` cannot be done) for a manual session's file."""
    if run.attrs.get("session_log"):
        raise ManualSessionError(f"run file {run.path}: a manual-control session: {what}")


def specimen_of(attrs: Mapping[str, Any], p: Path, model: bool = False) -> dict[str, Any]:
    """The run file ``p``'s ``specimen`` attribute (JSON: the rig's specimen, its ``kind`` and ``model``, and a
    protocol's ``overrides``) from its root attributes ``attrs``. ValueError (one line naming the file and the
    attribute) when it is missing, not JSON, not an object with a ``kind``, or — with ``model`` (a fit) — without a
    ``model`` object: every reader of the specimen goes through here, so a damaged or hand-edited attribute is
    refused alike wherever it is read."""
    where = f"run file {p}: attribute 'specimen'"
    if "specimen" not in attrs:
        raise ValueError(f"{where} is missing")
    text = _decode(attrs["specimen"])
    try:
        spec = json.loads(text)
    except (ValueError, TypeError) as exc:  # JSONDecodeError, bad UTF-8, or not text at all
        raise ValueError(f"{where} is not valid JSON ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{where} is not a JSON object (a {type(spec).__name__})")
    if not isinstance(spec.get("kind"), str):
        raise ValueError(f"{where} has no 'kind' (text): the kind of specimen")
    if model and not isinstance(spec.get("model"), dict):
        raise ValueError(f"{where} has no 'model' (an object): the specimen's model, which the fit starts from")
    return spec


def refuse_nonfinite(p: str | Path, stream: str, column: str, t: np.ndarray, values: np.ndarray,
                     nan: bool = True) -> None:
    """ValueError (one line naming the file and ``stream/column``) when ``values`` (at times ``t``) hold an
    infinity — no instrument reads one: a damaged or edited record — or, with ``nan`` False, a NaN where the reader
    needs a number at every record (the applied voltage). NaN is otherwise what a sensor out of range records."""
    bad = ~np.isfinite(values) if not nan else np.isinf(values)
    if bad.any():
        i = int(np.argmax(bad))
        when = f" at t = {float(t[i]):.6g} s" if i < len(t) else ""
        raise ValueError(f"run file {p}: {stream}/{column} holds {int(bad.sum()):,} "
                         f"{'non-finite' if not nan else 'infinite'} value(s), the first {float(values[i])}{when}: "
                         "a damaged record, not a measurement")


def _decode(v: Any) -> Any:
    return v.decode() if isinstance(v, bytes) else v


def unit_of(v: Any) -> str:
    """A dataset's unit as bench shows it: a CF time base ("seconds since <start>") is in seconds, "s"."""
    text = str(_decode(v))
    return "s" if text.startswith("seconds since ") else text


def open_h5(p: Path) -> h5py.File:
    """Open for reading: as an SWMR reader (also while a run writes, or after a crash), else — a writer that
    died before SWMR mode left the file marked open — from an in-memory copy with those marks cleared. A file its
    writer closed that is shorter than its superblock says is refused at once: an SWMR reader does not check the
    length (a live file grows) and retried its reads past the end for minutes, deaf to Ctrl-C."""
    if p.is_dir():
        raise ValueError(absent_run_file(p))
    refuse_truncated(p)
    try:
        return _open_swmr(p)
    except OSError as exc:
        first = exc
    try:
        image = bytearray(p.read_bytes())
        if not clear_consistency_flags(image):
            raise first
        return h5py.File(io.BytesIO(bytes(image)), "r")
    except (OSError, ValueError):
        raise ValueError(f"run file {p}: not a readable HDF5 file ({' '.join(str(first).split())})") from None


# HDF5's SWMR reader retries a metadata read that fails its checksum (a writer mid-update) 100 times, waiting longer
# each time: on a damaged file, minutes per object, deaf to Ctrl-C (an exploratory test's copy with 200 kB of noise
# written into it hung `bench inspect` for ten minutes). A live writer's update needs a few; these last about 2 s.
SWMR_READ_ATTEMPTS = 12


@functools.cache
def _read_attempts_setter() -> Callable[[int, int], int] | None:
    """``H5Pset_metadata_read_attempts`` of the HDF5 library h5py runs on (h5py does not expose it), found among the
    libraries this process has loaded (Linux); None where it cannot be found (then HDF5's default holds)."""
    import ctypes

    try:
        maps = Path("/proc/self/maps").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    paths = {line.split(None, 5)[-1] for line in maps.splitlines() if "libhdf5" in line and "_hl" not in line
             and len(line.split(None, 5)) == 6}
    for path in sorted(paths):
        try:
            fn = ctypes.CDLL(path).H5Pset_metadata_read_attempts
        except (OSError, AttributeError):
            continue
        fn.argtypes, fn.restype = [ctypes.c_int64, ctypes.c_uint], ctypes.c_int
        return lambda fapl, n: int(fn(fapl, n))
    return None


def _open_swmr(p: Path) -> h5py.File:
    """``h5py.File(p, "r", libver="latest", swmr=True)`` with :data:`SWMR_READ_ATTEMPTS` metadata read attempts."""
    setter = _read_attempts_setter()
    if setter is None:
        return h5py.File(p, "r", libver="latest", swmr=True)
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    fapl.set_libver_bounds(h5py.h5f.LIBVER_LATEST, h5py.h5f.LIBVER_LATEST)
    if setter(fapl.id, SWMR_READ_ATTEMPTS) < 0:
        return h5py.File(p, "r", libver="latest", swmr=True)
    fid = h5py.h5f.open(os.fsencode(p), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
    return h5py.File(fid)


def damaged(p: Path, exc: BaseException) -> ValueError:
    """The one-line error for a run file HDF5 opened but could not read a part of (``exc``: what failed)."""
    return ValueError(f"run file {p}: damaged, a part cannot be read ({type(exc).__name__}: "
                      f"{' '.join(str(exc).split())[:200]})")


def refuse_truncated(p: Path) -> None:
    """ValueError (one line) when ``p`` was closed by its writer (no consistency flags) and is shorter than the end
    of the space its superblock allocated: a copy cut short, a partial download."""
    try:
        with p.open("rb") as fh:
            head = fh.read(1 << 16)
            size = os.fstat(fh.fileno()).st_size
    except OSError:
        return  # the open below says why, as before
    sb = read_superblock(head)
    if sb is not None and sb.version >= 2 and sb.flags == 0 and size < sb.base_address + sb.eoa:
        raise ValueError(f"run file {p}: truncated: {size:,} bytes where its HDF5 superblock ends the file at "
                         f"{sb.base_address + sb.eoa:,} (a copy cut short? copy it again from the "
                         "original)")


def read_table(obj: h5py.Dataset | h5py.Group, n: int | None = None) -> np.ndarray:
    """A table (``/events``, ``/program``) as one structured array of its first ``n`` records (all if None).

    Format 2 stores a group of 1-D datasets, one per field; format 1 a compound dataset. Strings come back as
    UTF-8 bytes either way. While a writer appends, the fields may differ in length: the shortest counts.
    """
    if isinstance(obj, h5py.Dataset):
        obj.refresh()
        return np.asarray(obj[:n])
    order = PROGRAM_FIELDS if "index" in obj else EVENT_FIELDS  # the fields in the order format 1 stored them
    fields = sorted(obj, key=lambda k: order.index(k) if k in order else len(order))
    for d in obj.values():
        d.refresh()
    size = min((obj[k].shape[0] for k in fields), default=0)
    rows = size if n is None else min(n, size)
    cols = {k: obj[k][:rows] for k in fields}
    cols = {k: c.astype(bytes) if c.dtype.kind in "OS" else c for k, c in cols.items()}
    table = np.zeros(rows, dtype=[(k, c.dtype) for k, c in cols.items()])
    for k, c in cols.items():
        table[k] = c
    return table


def valid_counts(f: h5py.File, p: str | Path | None = None) -> dict[str, int]:
    """Valid records per stream and of ``events`` at the writer's last successful flush ({} in older files) of the
    open run file ``f`` (path ``p``, default its name). ValueError (one line naming the file and the field) when
    ``/status/samples`` is not a count per name in its ``names`` attribute, or a count is negative: a reader would
    cut the stream from its end (``t[:-5]``) and show, export or fit the wrong records."""
    if "samples" not in f["status"]:
        return {}
    d = f["status/samples"]
    d.refresh()
    where = f"run file {p if p is not None else f.filename}: /status/samples"
    try:
        names = json.loads(_decode(d.attrs["names"]))
    except (KeyError, ValueError, TypeError):
        raise ValueError(f"{where}: its 'names' attribute is missing or not JSON") from None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{where}: its 'names' attribute is not a list of stream names")
    if d.ndim != 1 or d.dtype.kind not in "iu":
        raise ValueError(f"{where}: not a list of record counts (shape {d.shape}, type {d.dtype})")
    counts = [int(n) for n in d[:]]
    if len(counts) != len(names):
        raise ValueError(f"{where}: {len(counts)} counts for the {len(names)} names of its 'names' attribute")
    negative = [f"{n} {c}" for n, c in zip(names, counts, strict=True) if c < 0]
    if negative:
        raise ValueError(f"{where}: negative record counts ({', '.join(negative)})")
    return dict(zip(names, counts, strict=True))


def _status_value(st: h5py.Group, name: str, p: Path) -> Any:
    """The one value of ``/status/<name>`` (KeyError where it is missing: a part every run file has)."""
    d = st[name]
    d.refresh()
    if d.shape != (1,):
        raise ValueError(f"run file {p}: /status/{name} holds {d.size} values of shape {d.shape}, not one")
    return d[0]


def read_status(f: h5py.File, p: Path) -> tuple[str, str, str, float]:
    """``/status``: the run's state, reason, end time and the run time of the writer's last flush [s]. ValueError
    (one line naming the file and the field) for a state bench does not write, text that is not UTF-8 text, or a
    time that is not a finite number ≥ 0."""
    st = f["status"]
    text: dict[str, str] = {}
    for name in ("state", "reason", "end_time"):
        v = _status_value(st, name, p)
        try:
            decoded = v.decode() if isinstance(v, bytes) else v
        except UnicodeDecodeError:
            decoded = None
        if not isinstance(decoded, str):
            raise ValueError(f"run file {p}: /status/{name} is not UTF-8 text ({v!r:.60})")
        text[name] = decoded
    if text["state"] not in STATES:
        raise ValueError(f"run file {p}: /status/state is {text['state']!r:.60}, not one of {', '.join(STATES)}")
    v = _status_value(st, "updated", p)
    try:
        updated = float(v)
        shown = str(updated)
    except (TypeError, ValueError):
        updated, shown = math.nan, f"{v!r:.60}"
    if not math.isfinite(updated) or updated < 0:
        raise ValueError(f"run file {p}: /status/updated is {shown}, not a run time ≥ 0 s")
    return text["state"], text["reason"], text["end_time"], updated


KNOWN_STREAMS = ("setpoints", "amplifier", "laser", "motor", "load_cell")


def stream_names(f: h5py.File) -> list[str]:
    """The streams a file records: the known ones present, then any other instrument's that ``/entry`` links (a
    rig's extra sensors: each records to a stream of its own)."""
    known = [n for n in KNOWN_STREAMS if n in f]
    return known + (sorted(n for n in f["entry"] if n not in KNOWN_STREAMS and n in f) if "entry" in f else [])


def open_run(path: str | Path, streams: bool = True) -> RunFile:
    """Read a run file; works on a file another process is writing (SWMR reader) and on the file of a
    crashed or killed run (``incomplete_reason`` says so). Every dataset is cut to the records the writer
    confirmed (``/status/samples``): a failed or interrupted write can leave zero-filled records beyond.
    ``streams=False`` reads the metadata, events and program only (:mod:`bench.storage.chunks` reads the streams
    a chunk at a time)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"run file {p}: not found")
    with open_h5(p) as f:
        try:
            return read_run(f, p, streams)
        except (OSError, UnicodeDecodeError) as exc:  # a part HDF5 cannot read (a checksum, a filter) or text that is
            raise damaged(p, exc) from None  # no longer UTF-8: damaged, said in one line


def read_run(f: h5py.File, p: Path, streams: bool = False) -> RunFile:
    """The run in the open file ``f`` (of path ``p``): as :func:`open_run`, without opening the file again."""
    try:
        attrs = {k: _decode(v) for k, v in f.attrs.items()}
    except Exception as exc:  # e.g. an earlier version's end stamp failed on a full disk
        raise ValueError(f"run file {p}: its root attributes are unreadable ({' '.join(str(exc).split())}): "
                         "`bench recover` rebuilds them") from None
    if not attrs and isinstance(f.get("status"), h5py.Group):  # a recover stopped between dropping and rebuilding
        raise ValueError(f"run file {p}: its root attributes are missing: `bench recover` rebuilds them")
    if attrs.get("format") not in FORMATS:
        raise ValueError(f"run file {p}: not a dea-bench run file (format {attrs.get('format')!r})")
    try:
        return _read_body(f, p, attrs, streams)
    except KeyError as exc:  # a group or dataset every run file has is gone: said in one line, not a traceback
        raise ValueError(f"run file {p}: damaged, a part every run file has is missing "
                         f"({' '.join(str(exc).split())})") from None


def _read_body(f: h5py.File, p: Path, attrs: dict[str, Any], streams: bool) -> RunFile:
    """:func:`read_run` past the root attributes (KeyError where a required group or dataset is missing)."""
    run = RunFile(p, attrs, *read_status(f, p), bool(attrs.get("complete", False)))
    valid = valid_counts(f, p)
    run.events = read_table(f["events"], valid.get("events"))
    run.program = read_table(f["program"])
    if streams:
        for name in stream_names(f):
            g = f[name]
            for d in g.values():
                d.refresh()
            n = min(d.shape[0] for d in g.values())  # a reader may see columns mid-append
            n = min(n, valid.get(name, n))
            cols = {k: d[:n] for k, d in g.items() if k != "t"}
            run.streams[name] = Stream(name, g["t"][:n], cols, {k: unit_of(d.attrs["units"]) for k, d in g.items()},
                                       float(g.attrs.get("rate_Hz", 0.0)))
    if run.state == "running" and not run.complete:
        run.orphaned = orphaned_file(p)
    return run


def orphaned_file(p: Path) -> bool:
    """Whether the file is still marked open by an SWMR writer that no longer exists (here)."""
    try:
        with p.open("rb") as fh:
            sb = read_superblock(fh.read(4096))
    except OSError:
        return False
    return sb is not None and sb.flags != 0 and not open_elsewhere(p)
