"""Stream a run to one HDF5 file while it goes on (SWMR), and never leave it unmarked.

Layout (``format = "dea-bench run 2"``; readers also read format 1, which kept ``/program`` and ``/events`` as
compound datasets that netCDF readers cannot read):

* root attributes — software version, protocol (name, path, full text, SHA-256), rig (name, TOML of the
  effective rig), specimen (JSON), recording settings (JSON), clock kind, simulated flag, start time;
  the end stamp — ``end_time``, ``exit_status``, ``exit_reason`` (fixed-length UTF-8, empty while the run goes on)
  and ``complete`` (False) — is created with the file and overwritten in place by a clean finish (``complete =
  True``), so a full disk cannot strike there (files of earlier versions add these attributes at the finish);
* ``/status`` — datasets ``state`` (running / completed / tripped / error / interrupted), ``reason``,
  ``end_time``, ``updated`` (rig time of the last flush), ``samples`` (valid records per stream and of
  ``/events``, in the order of its ``names`` attribute, written only once the data of a flush is on disk):
  written during the run, so a file from a crashed run still says ``running`` and is recognised as
  incomplete, and a reader trims every dataset to ``samples`` (beyond it a failed write can leave
  zero-filled records);
* ``/program`` — the compiled steps, one dataset per field (``index``, the dimension scale; ``label``, ``name``,
  ``kind`` as variable-length UTF-8 strings; ``t_start``, ``duration``);
* ``/events`` — step starts and ends, trips, operator actions, one dataset per field (``t``, the dimension scale;
  ``step``; ``kind`` and ``text`` as fixed-length UTF-8 strings: SWMR cannot append variable-length data);
* one group per stream (``setpoints``, ``amplifier``, ``laser``, ``motor``, ``load_cell``) with a time base
  ``t`` [s on the run clock] and one dataset per column, chunked, gzip-compressed.

Every time base (and ``/program/index``) is an HDF5 dimension scale attached to the datasets of its group, so
netCDF readers (xarray, netCDF4, h5netcdf) see it as the group's dimension and coordinate; every numeric
dataset has a ``units`` attribute ("1": dimensionless); every string is declared UTF-8.

Datasets, dimension scales and attributes are created before SWMR mode starts (HDF5 allows no attribute change under
SWMR); the datasets are then appended in blocks and flushed at least every ``flush_interval`` seconds of wall time,
so another process can read the file during the run: every ``append``/``event`` checks the interval itself (a caller
busy elsewhere, e.g. uploading stored laser data for 30 s, still has its data on disk within the interval), and
``maybe_flush`` covers stretches without data. A stream with :data:`FLUSH_CHUNKS` chunks queued, or whose queue
spans :data:`QUEUED_MAX_S` of the run clock, is written sooner, its whole chunks only (data faster than real time: a
virtual-time run; the second rule bounds what a storage fault leaves unwritten); so is every stream's at a step's
end from :data:`STEP_END_CHUNKS` chunks and at the run's end from one (:meth:`Recorder.write_ahead`), which leaves
the finish only the tails. Those flushes take the queued data on the caller's thread and write it on a background
thread (h5py releases the GIL while HDF5 compresses and writes, so the run goes on meanwhile); one write at a time,
in order. A failure there is raised on the caller's thread by its next recorder call. :meth:`Recorder.flush`,
``set_state`` and ``finish`` first wait for a write under way, then write on the caller's thread.

A failed write (disk full, file-size limit, unwritable directory, any HDF5 error) raises one
:class:`StorageError` naming the file and the cause; the recorder is then *failed*: further calls are no-ops,
and the HDF5 handle is closed with its descriptor pointed at ``/dev/null`` — HDF5 cannot write the rest of
its metadata to a file whose last write failed, and closing it there (or at exit) crashed the interpreter.
The file keeps everything up to the last successful flush, and its ``/status/reason`` says why it stops there:
"storage fault: <the error>" (:data:`STORAGE_FAULT`), written straight into the bytes the reason has held since the
file was created — an overwrite in place, which needs no new space on a disk that has just filled — while the
state stays ``running`` (the run's end is not on file). Readers and ``bench recover`` name the cause (a full
disk) rather than a crash.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bench.storage.hv_stats import HvAccumulator, HvStats
from drivers.errors import OperationCancelledError
from drivers.interfaces import DataKey

log = logging.getLogger(__name__)
event_log = logging.getLogger("bench.run")  # every event, as it is recorded (the run log beside the file follows it)

FORMAT = "dea-bench run 2"
FORMATS = ("dea-bench run 1", FORMAT)  # what the readers read (1: /program and /events as compound datasets)
EVENT_FIELDS = ("t", "step", "kind", "text")
EVENT_DTYPE = np.dtype(list(zip(EVENT_FIELDS, ("f8", "i4", "S16", "S200"), strict=True)))  # strings: UTF-8 bytes
EVENT_UNITS = {"t": "s", "step": "1"}
PROGRAM_FIELDS = ("index", "label", "name", "kind", "t_start", "duration")
PROGRAM_UNITS = {"index": "1", "t_start": "s", "duration": "s"}
TEXT = h5py.string_dtype("utf-8")  # variable-length UTF-8 (for data written before SWMR mode only)
STORAGE_FAULT = "storage fault: "  # /status/reason of a file whose writing failed: the failure follows
STATUS_TEXT = {"state": 16, "reason": 400, "end_time": 40}  # fixed-length UTF-8 fields of /status [bytes]
STATES = ("running", "completed", "tripped", "error", "interrupted")
# the end-of-run stamp: root attributes created with the file (text: fixed-length UTF-8 of the /status limit plus a
# terminator), so that finish() overwrites them in place and needs no new space in the file
STAMP_TEXT = {"end_time": STATUS_TEXT["end_time"] + 1, "exit_status": STATUS_TEXT["state"] + 1,
              "exit_reason": STATUS_TEXT["reason"] + 1}
FLUSH_INTERVAL_S = 0.2  # wall time between flushes: a kill -9 loses at most this plus one flush (goal ≤ 0.5 s)
CHUNK_S = 0.25  # chunk length [s of a stream]: about one flush, so a compressed chunk is rewritten once or twice
# (a flush rewrites the partial last chunk elsewhere in the file: 2-s chunks made files 2-3x larger)
FLUSH_CHUNKS = 16  # a stream with this many chunks queued is written at once (its whole chunks), whatever the
# interval: faster than real time (virtual time) the interval alone left a short run's whole file to be written after
# its last step; a write costs about two chunks' compression besides its data, which 16 keep to an eighth of it (real
# time: the interval comes first)
QUEUED_MAX_S = 4 * CHUNK_S  # a stream whose queued samples span this much of the run clock (rig time) is written
# at once, its whole chunks: faster than real time FLUSH_CHUNKS chunks (4 s of a stream) could wait in memory, and a
# storage fault was only found at their write — a virtual run drove on for 3.25 s of rig time with nothing recorded
# after a disk filled (real time: the interval comes first). A second costs half a chunk's compression per chunk.
STEP_END_CHUNKS = FLUSH_CHUNKS // 4  # a step's end starts a write of the whole chunks queued once a stream has this
# many (a second of it) and would not reach FLUSH_CHUNKS before the program ends: its data then compresses during the
# next steps, not after the last one on the run's thread; earlier steps' chunks, and those of steps of less, are left
# to the rules above, so that the steps' ends do not multiply the writes and their own cost


def chunk_length(rate: float) -> int:
    """Samples per chunk of a stream recorded at ``rate`` [Hz]: :data:`CHUNK_S` of it, 256 to 65,536."""
    return int(min(65536, max(256, rate * CHUNK_S)))


# what one flush writes: per stream with data (its index, name, columns, sample count), the events, the rig time
# of the last sample
_Work = tuple[list[tuple[int, str, dict[str, np.ndarray], int]], np.ndarray | None, float]


class StorageError(OSError):
    """Writing the run file failed (disk full, file-size limit, unwritable directory, HDF5 error); one line.

    An :class:`OSError`, so command-line error handling and the engine's storage-fault path both see it.
    """


class UnlinkedError(OSError):
    """The run file is no longer in any folder (deleted, or its folder removed, while the run writes it)."""


def cause(exc: BaseException) -> str:
    """One line on why an HDF5/OS call failed: the errno text if there is one, else the first line.

    h5py's OSError carries the errno but HDF5's multi-line driver message as ``strerror``: the errno decides.
    """
    if isinstance(exc, UnlinkedError):
        return str(exc)
    if isinstance(exc, OSError) and exc.errno and not isinstance(exc, StorageError):
        return f"{os.strerror(exc.errno)} (errno {exc.errno})"
    m = re.search(r"errno = (\d+)", str(exc))
    if m:
        return f"{os.strerror(int(m.group(1)))} (errno {m.group(1)})"
    first = " ".join(str(exc).split())[:200]
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def abandon(f: h5py.File, fd: int | None = None) -> None:
    """Close ``f`` after a failed write without touching the file again and without crashing.

    HDF5 keeps the metadata it could not write and retries at close; that fails again and (at close or at
    interpreter exit) ends in a segfault. Pointing the descriptor at /dev/null lets the close succeed while
    the file on disk stays as the last successful flush left it. ``fd``: the descriptor, taken when the file was
    opened — after a close that failed half-way, asking the handle for it crashes the interpreter.
    """
    try:
        fd = f.id.get_vfd_handle() if fd is None else fd
        null = os.open(os.devnull, os.O_RDWR)
        try:
            os.dup2(null, int(fd))
        finally:
            os.close(null)
    except Exception:  # best effort: no descriptor (already closed) or another driver
        pass
    with contextlib.suppress(Exception):  # the close of an abandoned file may report the failure again
        f.close()


def ignore_sigxfsz() -> None:
    """A write beyond RLIMIT_FSIZE must fail with EFBIG (reported) rather than kill the process (SIGXFSZ)."""
    if hasattr(signal, "SIGXFSZ") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


Column = DataKey  # one recorded quantity of a stream: name, unit, description, dtype (the drivers' describe())


def utf8(text: str, size: int) -> bytes:
    """``text`` as UTF-8 in at most ``size`` bytes, cut at a character boundary (fixed-length UTF-8 fields)."""
    return text.encode()[:size].decode(errors="ignore").encode()


def fixed_text(size: int) -> np.dtype:
    """Fixed-length UTF-8 string type of ``size`` bytes (appendable under SWMR, declared UTF-8 in the file)."""
    dtype: np.dtype = h5py.string_dtype("utf-8", size)
    return dtype


def stamp_text(size: int) -> h5py.h5t.TypeID:
    """Fixed-length, NUL-terminated UTF-8 string of ``size`` bytes (the stamp; HDF5 tools print no padding)."""
    t = h5py.h5t.C_S1.copy()
    t.set_size(size)
    t.set_strpad(h5py.h5t.STR_NULLTERM)
    t.set_cset(h5py.h5t.CSET_UTF8)
    return t


def stamp(f: h5py.File, end: str, state: str, reason: str) -> None:
    """Overwrite the end-of-run placeholders of ``f`` in place (no new space in the file: a full disk cannot
    move the root object header); texts cut to their fields at a character boundary."""
    for name, text in (("end_time", end), ("exit_status", state), ("exit_reason", reason)):
        size = STAMP_TEXT[name]
        a = h5py.h5a.open(f.id, name.encode())
        a.write(np.array(utf8(text, size - 1), dtype=f"S{size}"), mtype=a.get_type())
    f.attrs.modify("complete", True)


def reopen_for_stamp(path: Path) -> h5py.File:
    """The just-closed run file opened again to write its end stamp (mode ``r+``).

    A reader that has the file open — ``bench watch`` (``bench run --web``), ``h5py`` with ``swmr=True`` —
    holds HDF5's advisory lock (a shared ``flock`` kept while open), which refuses this writer with EAGAIN, and the
    run ended unstamped (CI, 2026-11-27). This process created the file and has just closed it, so no other writer
    can hold it; on that refusal only, the file is opened without the lock. The stamp overwrites placeholders in
    place (:func:`stamp`), in a header HDF5 checksums: an SWMR reader that reads it at that instant reads it again;
    a reader that keeps its handle sees the stamp once it opens the file anew (``/status`` at its next refresh).
    """
    try:
        return h5py.File(path, "r+")
    except OSError as exc:
        if exc.errno != errno.EAGAIN and f"errno = {errno.EAGAIN}," not in str(exc):
            raise
    log.info("run file %s: held open by a reader; the end stamp is written without HDF5's file lock", path)
    return h5py.File(path, "r+", locking=False)


_VLEN = h5py.string_dtype()  # a Python str as h5py stores it: variable-length UTF-8, NUL-terminated, scalar
_VLEN_FILE, _VLEN_MEMORY = h5py.h5t.py_create(_VLEN, logical=True), h5py.h5t.py_create(_VLEN)
_SCALAR = h5py.h5s.create(h5py.h5s.SCALAR)


def set_attrs(obj: h5py.HLObject, values: dict[str, Any]) -> None:
    """``obj.attrs[name] = value`` for each item, in order. A text (ASCII name, no NUL: what h5py refuses takes its
    path) goes through h5py's low-level calls with the type and space h5py's ``attrs`` would make for it, made once:
    the same attribute at a sixth of the cost (~100 µs each through ``attrs``, most of a new run file's creation)."""
    for name, value in values.items():
        if type(value) is str and name.isascii() and "\0" not in value:
            key = name.encode()
            if h5py.h5a.exists(obj.id, key):
                h5py.h5a.delete(obj.id, key)
            h5py.h5a.create(obj.id, key, _VLEN_FILE, _SCALAR).write(np.asarray(value, dtype=_VLEN), mtype=_VLEN_MEMORY)
        else:
            obj.attrs[name] = value


def dimension_scale(g: h5py.Group, name: str, data: np.ndarray | None = None, **kwargs: Any) -> h5py.Dataset:
    """Create ``g[name]`` as the group's dimension scale (a netCDF dimension and coordinate of that name)."""
    d = g.create_dataset(name, data=data, **kwargs)
    d.make_scale(name)
    return d


def attach(d: h5py.Dataset, scale: h5py.Dataset, units: str | None = None) -> h5py.Dataset:
    """Attach ``scale`` as the dimension of the 1-D dataset ``d`` (and set its units, if given)."""
    d.dims[0].attach_scale(scale)
    if units is not None:
        set_attrs(d, {"units": units})
    return d


def seconds_since(start: object) -> str:
    """CF units of a time base that starts at ``start`` (ISO 8601): ``seconds since <start>``; "s" without one."""
    if isinstance(start, str):
        try:
            datetime.fromisoformat(start)
        except ValueError:
            return "s"
        return f"seconds since {start}"
    return "s"


def _time_axis(t: h5py.Dataset, units: str) -> None:
    set_attrs(t, {"units": units, "standard_name": "time", "long_name": "time on the run clock", "axis": "T"})


def now_iso() -> str:
    """UTC time stamp, ISO 8601."""
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def stored_text(text: str, size: int) -> str:
    """``text`` as a reader reads it back from a fixed-length UTF-8 field of ``size`` bytes (cut at a character
    boundary; NUL padding, and so trailing NULs, dropped)."""
    return utf8(text, size).rstrip(b"\0").decode()


@dataclass(frozen=True)
class Written:
    """What a finished run file holds, as :func:`bench.storage.runfile.open_run` reads it back: the root
    attributes given at its creation, its end (state, reason, end time; ``complete``), its steps completed and in
    all, and the file's size and modification time [ns] when the recorder closed it (a change since: not this
    account's file). The run's end catalogues it instead of reading the file again."""

    attrs: dict[str, Any]
    state: str
    reason: str
    end_time: str
    steps_completed: int
    steps_total: int
    file_stat: tuple[int, int]


def _samples(values: np.ndarray | float, dtype: type | None = None) -> np.ndarray:
    """``values`` as a 1-d array (of ``dtype``, if given): ``np.atleast_1d(np.asarray(values, dtype))``, without
    numpy's conversion machinery for a Python float (a poll's value: the same float64 array of one sample) or for a
    1-d array already of ``dtype`` (a DAQ block's column: the array itself, as asarray and atleast_1d return it)."""
    if type(values) is np.ndarray:
        if values.ndim == 1 and (dtype is None or values.dtype == dtype):
            return values
    elif type(values) is float:
        return np.array((values,))
    return np.atleast_1d(np.asarray(values, dtype=dtype))


def _same_row(a: list[Any], b: list[Any] | None) -> bool:
    """Whether two single-sample rows hold the same values (NaN equal to NaN: a column not set in either)."""
    return b is not None and all(x == y or (x != x and y != y) for x, y in zip(a, b, strict=True))


class Recorder:
    """Appends blocks of samples to an HDF5 file in SWMR mode; see the module docstring for the layout."""

    def __init__(self, path: Path, attrs: dict[str, Any], streams: dict[str, list[Column]],
                 program: Sequence[tuple[int, str, str, str, float, float]], rates: dict[str, float],
                 flush_interval: float = FLUSH_INTERVAL_S, virtual: bool = False) -> None:
        self.path = Path(path)
        self.flush_interval = flush_interval
        # a virtual clock waits for the writer (maybe_flush); a real-time run never does: its thread would stall,
        # and a set-point module's watchdog bound (the host's stall bound) is shorter than a slow disk's write
        self.virtual = virtual
        self.streams = streams
        self._last_row: dict[str, list[Any]] = {}  # each stream's last single-sample row (append)
        self._buffers: dict[str, dict[str, list[np.ndarray]]] = {s: {c.name: [] for c in [Column("t", "s", ""), *cols]}
                                                                 for s, cols in streams.items()}
        self._events: list[tuple[float, int, bytes, bytes]] = []
        # per stream: samples queued, taken for writing so far, its chunk length; a stream is due for writing at
        # FLUSH_CHUNKS chunks queued
        self._queued = dict.fromkeys(streams, 0)
        self._taken = dict.fromkeys(streams, 0)
        self._rates = {s: rates.get(s, 100.0) for s in streams}
        self._chunks = {s: chunk_length(r) for s, r in self._rates.items()}
        self._due = False
        self._taken_t = 0.0  # rig time up to which every stream's samples and the events are taken for writing
        self._ahead_t = 0.0  # rig time of the last sample taken for writing (whole-chunk writes run ahead of it)
        self._events_ds: dict[str, h5py.Dataset] = {}
        self._last_flush = time.monotonic()
        self.samples_written = 0
        self.write_seconds = 0.0  # wall time spent writing
        self._cpu_queue = 0.0  # CPU time of the caller's thread spent queueing (append)
        self._cpu_write = 0.0  # CPU time of the writing thread (one write at a time)
        self.failure = ""  # the StorageError message once a write has failed ('' while healthy)
        self._writing: threading.Thread | None = None  # the background write under way (maybe_flush)
        self._write_error: Exception | None = None  # its failure, raised by the caller's next call
        self._f: h5py.File | None = None
        self._fd: int | None = None  # its descriptor, taken at open (abandon)
        self._reason_at: tuple[int, int, int] | None = None  # /status/reason: file offset; the file's device, inode
        self._state_written = False  # an end state and its reason flushed to the file (_mark_fault leaves them)
        self._links_counted = False  # set at open (see _unlinked)
        self._names = [*streams, "events"]
        self._counts = np.zeros(len(self._names), dtype=np.int64)  # valid records on disk, per stream and events
        # the catalogue's high-voltage statistics of the measured amplifier voltage, over what is written
        self._hv = HvAccumulator() if any(c.name == "voltage" for c in streams.get("amplifier", [])) else None
        # what the file holds once finished, followed as it is written (the catalogue's end row: Written)
        self._attrs = {k: v if not isinstance(v, dict | list) else json.dumps(v) for k, v in attrs.items()}
        self._steps_total = len(program)
        self._steps_done: set[int] = set()  # steps whose end is queued after their last start
        self._written: Written | None = None
        ignore_sigxfsz()
        if self.path.exists():  # said plainly; the "w-" of _create keeps a file made meanwhile as well
            self.failure = f"run file {self.path}: exists: a run file is never overwritten"
            raise StorageError(self.failure)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._create(attrs, streams, program, rates)
        except Exception as exc:  # whatever stopped the file being made, said in one line
            if self._f is not None:
                abandon(self._f, self._fd)
                self._f = None
                # made here ("w-"), half made and holding nothing: removed, not left for readers to call damaged
                with contextlib.suppress(OSError):
                    self.path.unlink()
            self.failure = f"run file {self.path}: cannot create: {cause(exc)}"
            raise StorageError(self.failure) from None

    def _create(self, attrs: dict[str, Any], streams: dict[str, list[Column]],
                program: Sequence[tuple[int, str, str, str, float, float]], rates: dict[str, float]) -> None:
        # w-: create, never truncate (another run's file); SWMR needs the 1.10 format, newer breaks 1.10 tools
        f = h5py.File(self.path, "w-", libver=("v110", "v110"))
        self._f = f
        self._fd = int(f.id.get_vfd_handle())  # for abandon(): a handle whose close failed cannot say
        self._links_counted = os.fstat(self._fd).st_nlink >= 1  # a filesystem that counts links (see _unlinked)
        set_attrs(f, {"format": FORMAT, **self._attrs})
        time_units = seconds_since(attrs.get("start_time"))
        self._create_stamp(f)
        self._updated, self._samples = self._create_status(f)
        self._create_program(f, program)
        # the appended datasets, kept as created: group look-ups cost more than the writes
        self._events_ds = self._create_events(f, time_units)
        self._datasets = {name: self._create_stream(f, name, cols, rates.get(name, 100.0), time_units)
                          for name, cols in streams.items()}
        self._create_entry(f, list(streams))
        f.swmr_mode = True
        f.flush()
        offset = f["status/reason"].id.get_offset()  # contiguous, written at creation: its bytes stay where they are
        st = os.fstat(self._fd)
        self._reason_at = (int(offset), st.st_dev, st.st_ino) if offset is not None else None

    @staticmethod
    def _create_stamp(f: h5py.File) -> None:
        """The end-of-run stamp as placeholders (empty texts, ``complete = False``), overwritten by :func:`stamp`."""
        space = h5py.h5s.create(h5py.h5s.SCALAR)
        for name, size in STAMP_TEXT.items():
            if name in f.attrs:
                del f.attrs[name]
            kind = stamp_text(size)
            h5py.h5a.create(f.id, name.encode(), kind, space).write(np.array(b"", dtype=f"S{size}"), mtype=kind)
        f.attrs["complete"] = False

    def _create_status(self, f: h5py.File) -> tuple[h5py.Dataset, h5py.Dataset]:
        """``/status``: the run's state and the valid-record counts, rewritten in place during the run; returns
        ``updated`` and ``samples``."""
        status = f.create_group("status")
        for name, size in STATUS_TEXT.items():
            initial = b"running" if name == "state" else b""
            status.create_dataset(name, data=np.array([initial], dtype=fixed_text(size)))
        updated = status.create_dataset("updated", data=np.array([0.0]))
        set_attrs(updated, {"units": "s"})
        samples = status.create_dataset("samples", data=self._counts)
        set_attrs(samples, {"names": json.dumps(self._names), "units": "1",
                            "description": "valid records per stream (and of /events) at the last successful flush"})
        return updated, samples

    @staticmethod
    def _create_program(f: h5py.File, program: Sequence[tuple[int, str, str, str, float, float]]) -> None:
        """``/program``: one dataset per field of the compiled steps, along the dimension scale ``index``."""
        g = f.create_group("program")
        rows = list(zip(*program, strict=True)) if program else [()] * len(PROGRAM_FIELDS)
        columns = dict(zip(PROGRAM_FIELDS, rows, strict=True))
        index = dimension_scale(g, "index", np.array(columns["index"], dtype="i4"))
        set_attrs(index, {"units": PROGRAM_UNITS["index"]})
        for field in ("label", "name", "kind"):
            attach(g.create_dataset(field, data=np.array(columns[field], dtype=object), dtype=TEXT), index)
        for field in ("t_start", "duration"):
            attach(g.create_dataset(field, data=np.array(columns[field], dtype="f8")), index, PROGRAM_UNITS[field])

    @staticmethod
    def _create_events(f: h5py.File, time_units: str) -> dict[str, h5py.Dataset]:
        """``/events``: one appendable dataset per event field, along the dimension scale ``t``; returns them by
        field."""
        g = f.create_group("events")
        t = dimension_scale(g, "t", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
        _time_axis(t, time_units)
        out = {"t": t}
        for field in EVENT_FIELDS[1:]:
            kind, size = EVENT_DTYPE[field].kind, EVENT_DTYPE[field].itemsize
            dtype = fixed_text(size) if kind == "S" else EVENT_DTYPE[field]
            d = g.create_dataset(field, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(256,))
            out[field] = attach(d, t, EVENT_UNITS.get(field))
        return out

    @staticmethod
    def _create_stream(f: h5py.File, name: str, cols: list[Column], rate: float,
                       time_units: str) -> dict[str, h5py.Dataset]:
        """One group per stream (a NeXus NXdata): the time base ``t`` (dimension scale, the NXdata's axis) and one
        dataset per column (the first is the group's signal); returns them by name, ``t`` first."""
        g = f.create_group(name)
        set_attrs(g, {"rate_Hz": rate, "NX_class": "NXdata", **({"signal": cols[0].name} if cols else {}), "axes": "t"})
        chunk = chunk_length(rate)
        layout: dict[str, Any] = {"shape": (0,), "maxshape": (None,), "chunks": (chunk,), "compression": "gzip",
                                  "compression_opts": 1, "shuffle": True}
        t = dimension_scale(g, "t", dtype="f8", **layout)
        _time_axis(t, time_units)
        set_attrs(t, {"description": "time on the run clock"})
        out = {"t": t}
        for col in cols:
            d = out[col.name] = attach(g.create_dataset(col.name, dtype=col.dtype, **layout), t, col.unit)
            flags = ({"flag_values": np.array([0, 1], dtype=col.dtype), "flag_meanings": "invalid valid"}
                     if col.name == "valid" and np.dtype(col.dtype).kind in "ub" else {})
            set_attrs(d, {"description": col.description, "long_name": col.description or col.name, **flags})
        return out

    @staticmethod
    def _create_entry(f: h5py.File, streams: list[str]) -> None:
        """NeXus and CF conventions at the root: ``/entry`` (NXentry) links every stream group and names the one
        a viewer plots by default (the displacement where there is one)."""
        set_attrs(f, {"Conventions": "CF-1.10", "NX_class": "NXroot"})
        entry = f.create_group("entry")
        set_attrs(entry, {"NX_class": "NXentry"})
        for name in streams:
            entry[name] = h5py.SoftLink(f"/{name}")
        preferred = [s for s in ("laser", "amplifier", "load_cell", "motor", "setpoints") if s in streams]
        if preferred:
            set_attrs(entry, {"default": preferred[0]})
            set_attrs(f, {"default": "entry"})

    @property
    def cpu_seconds(self) -> float:
        """CPU time the recorder used [s]: queueing on the caller's thread and writing (on whichever thread)."""
        return self._cpu_queue + self._cpu_write

    @property
    def failed(self) -> bool:
        """Whether a write has failed (the recorder then ignores further calls)."""
        return bool(self.failure)

    def _fail(self, what: str, exc: BaseException) -> StorageError:
        """Enter the failed state: drop queued data, release the file safely; the error to raise."""
        self.failure = f"run file {self.path}: {what}: {cause(exc)}"
        if self._f is not None:  # first: releasing a dataset flushes its chunk cache, which must not reach the file
            self._mark_fault()  # while the descriptor is still the file's
            abandon(self._f, self._fd)
            self._f = None
        for buf in self._buffers.values():
            for parts in buf.values():
                parts.clear()
        self._events.clear()
        self._datasets, self._events_ds, self._updated, self._samples = {}, {}, None, None
        return StorageError(self.failure)

    def _mark_fault(self) -> None:
        """Write "storage fault: <failure>" into ``/status/reason`` through the file's descriptor, past HDF5 (whose
        handle is abandoned next): the reason's bytes were written when the file was created, so overwriting them
        needs no new space. Best effort: nothing when the descriptor is no longer this file's, or the write fails."""
        if self._fd is None or self._reason_at is None or self._state_written:
            return  # a state already on disk keeps its reason (a trip's cause), as readers show it (review finding)
        offset, dev, ino = self._reason_at
        size = STATUS_TEXT["reason"]
        text = utf8(STORAGE_FAULT + self.failure, size).ljust(size, b"\0")
        with contextlib.suppress(OSError):
            st = os.fstat(self._fd)
            if (st.st_dev, st.st_ino) == (dev, ino):  # the descriptor is still this file's
                os.pwrite(self._fd, text, offset)

    # -------------------------------------------------------------- writing
    def append(self, stream: str, t: np.ndarray | float, **columns: np.ndarray | float) -> None:
        """Queue samples of ``stream``: the time base and every column, as many of each (ValueError, with nothing
        queued, otherwise); flushes if the flush interval has passed (may raise :class:`StorageError`)."""
        if self.failure:
            return
        c0 = time.thread_time()
        buf = self._buffers[stream]
        times = _samples(t, float)
        n = times.size
        block = {"t": times}
        sized = True
        for name, values in columns.items():
            a = block[name] = _samples(values)
            sized = sized and a.size == n
        if not sized or block.keys() != buf.keys():
            got = ", ".join(f"{k} ({a.size})" for k, a in block.items())
            raise ValueError(f"stream {stream}: a block needs t and every column ({', '.join(buf)}), one value per "
                             f"time; got {got} (nothing of it queued)")
        if n == 1:  # a polled row: the same row again (same time, same values) is the same sample, recorded once
            row = [float(a[0]) if a.dtype.kind == "f" else a[0] for a in block.values()]
            if _same_row(row, self._last_row.get(stream)):
                self._cpu_queue += time.thread_time() - c0
                return
            self._last_row[stream] = row
        elif n:
            self._last_row.pop(stream, None)
        for name, values in block.items():  # all or nothing: the columns of a stream stay equally long
            buf[name].append(values)
        self._queued[stream] += n
        chunk, taken = self._chunks[stream], self._taken[stream]
        self._due = (self._due or self._queued[stream] >= FLUSH_CHUNKS * chunk
                     or (n > 0 and (taken + self._queued[stream]) // chunk > taken // chunk  # a whole chunk queued
                         and float(times[-1]) - float(buf["t"][0][0]) >= QUEUED_MAX_S))
        self._cpu_queue += time.thread_time() - c0
        self.maybe_flush()

    def event(self, t: float, step: int, kind: str, text: str) -> None:
        """Log the event at once (logger ``bench.run``, info: the run log gets one line with the wall-clock time
        of this call and the run time ``t``), then queue it for the file; flushes if the flush interval has
        passed (may raise :class:`StorageError`). Logged even once the file has failed: the log is the account
        that survives it."""
        event_log.info("event t=%.3f s step %d %s: %s", t, step, kind, " | ".join(text.splitlines()))
        if self.failure:
            return
        stored = utf8(kind, 16)
        self._events.append((t, step, stored, utf8(text, 200)))
        if stored == b"start":  # as RunFile.completed_steps counts them
            self._steps_done.discard(step)
        elif stored == b"end":
            self._steps_done.add(step)
        self.maybe_flush()

    def maybe_flush(self) -> None:
        """Flush if the flush interval has passed (call it often), or only the whole chunks queued if a stream has
        :data:`FLUSH_CHUNKS` of them: the data is taken here and written on a background thread, unless the last
        such write is still under way (then at a later call) — unless the run's clock is virtual and a stream's
        queue already spans :data:`QUEUED_MAX_S` of it: then the caller waits for it (a run ahead of its writer by
        that much would leave more than the stated bound unwritten at a storage fault; the virtual clock waits with
        it). A real-time run never waits here: its thread would stall the rig's supervision and its set-point
        module's watchdog (a reviewer: 2-s writes tripped a host stall and latched the rig). Raises the
        :class:`StorageError` of a background write that failed."""
        if self.failure:
            return
        writing = self._writing
        if writing is not None:
            if writing.is_alive() and not (self.virtual and self._queued_span_s() >= QUEUED_MAX_S):
                return
            self._await_write()
        interval = time.monotonic() - self._last_flush >= self.flush_interval
        if interval or self._due:
            if interval:  # (a write of whole chunks leaves the rest queued: the interval still runs for it)
                self._last_flush = time.monotonic()
            self._start_write(self._take(whole_chunks=not interval))

    def _queued_span_s(self) -> float:
        """The longest stretch of the run clock any stream's queued samples span (0 with nothing queued)."""
        span = 0.0
        for buf in self._buffers.values():
            parts = [p for p in buf["t"] if p.size]
            if parts:
                span = max(span, float(parts[-1][-1]) - float(parts[0][0]))
        return span

    def _start_write(self, work: _Work) -> None:
        """Write ``work`` on a background thread (none under way), or here where no thread can be started."""
        # not a daemon: the interpreter finishes a write under way before h5py's exit handler closes the file
        writing = threading.Thread(target=self._write_in_background, args=(work,), name="recorder-flush")
        try:
            writing.start()
        except RuntimeError:  # no thread to be had (process or memory limits): write the data here instead
            try:
                self._write(work)
            except Exception as exc:
                raise self._fail("write failed", exc) from None
            return
        self._writing = writing

    def write_ahead(self, min_chunks: int = 1, remaining_s: float = 0.0) -> None:
        """Write the whole chunks queued on the background thread now (or, with a write under way, as soon as it
        has finished) if some stream has ``min_chunks`` of them and would not reach :data:`FLUSH_CHUNKS` in the
        ``remaining_s`` of the run still to come: at a step's end and at the run's end, so that what the run does
        meanwhile overlaps their compression instead of :meth:`finish` doing it all on the caller's thread after
        the last step (a stream that reaches FLUSH_CHUNKS before then is written then, at no extra write). Raises
        the :class:`StorageError` of a background write that failed."""
        if self.failure:
            return
        if any((self._taken[s] + q) // self._chunks[s] - self._taken[s] // self._chunks[s] >= min_chunks
               and q + self._rates[s] * remaining_s < FLUSH_CHUNKS * self._chunks[s]
               for s, q in self._queued.items()):  # whole chunks, as _take counts them
            self._due = True
        self.maybe_flush()

    def flush(self) -> None:
        """Write every queued sample and event, and make them visible to readers (after a background write under
        way has finished).

        Two steps: the data (then an HDF5 flush), and only once that succeeded the valid-record counts and the
        time of the flush (then a second, small flush) — so a reader never counts records a failed or
        interrupted write left zero-filled. Raises :class:`StorageError` on the first failure.
        """
        self._await_write()
        if self.failure:
            return
        self._last_flush = time.monotonic()
        try:
            self._write(self._take())
        except Exception as exc:  # any failure of the file (OS or HDF5) is a storage fault
            raise self._fail("write failed", exc) from None

    def _await_write(self) -> None:
        """Wait for the background write under way; raise its failure (once) as a :class:`StorageError`."""
        writing, self._writing = self._writing, None
        if writing is None:
            return
        writing.join()
        exc, self._write_error = self._write_error, None
        if exc is not None and not self.failure:
            raise self._fail("write failed", exc) from None

    def _take(self, whole_chunks: bool = False) -> _Work:
        """The queued samples per stream, the queued events and the rig time of the last sample; the queues are
        left empty (caller's thread: appends go on into new lists). ``whole_chunks``: of each stream only the samples
        up to its dataset's last chunk boundary, the rest left queued — a write that compresses every chunk once,
        complete, and rewrites no partial one; the events and the valid-up-to time then stay queued with the tails, so
        that nothing reaches the file ahead of samples that precede it."""
        blocks: list[tuple[int, str, dict[str, np.ndarray], int]] = []
        for k, (stream, buf) in enumerate(self._buffers.items()):
            if not buf["t"]:
                continue
            queued = self._queued[stream]
            n_new = queued
            if whole_chunks:
                chunk = self._chunks[stream]
                n_new = (self._taken[stream] + queued) // chunk * chunk - self._taken[stream]
                if n_new <= 0:
                    continue
            data = {}
            for name, parts in buf.items():
                whole = np.concatenate(parts) if len(parts) > 1 else parts[0]
                if whole.size != queued:
                    raise ValueError(f"stream {stream}: column {name} has {whole.size} samples queued, {queued} "
                                     "expected")
                data[name] = whole[:n_new]
                parts[:] = [whole[n_new:]] if n_new < queued else []
            blocks.append((k, stream, data, n_new))
            self._queued[stream] = queued - n_new
            self._taken[stream] += n_new
            if n_new:
                self._ahead_t = max(self._ahead_t, float(np.max(data["t"])))
        self._due = False
        if whole_chunks:  # other streams' tails stay queued: no event (a step's end) and no valid-up-to time may
            return blocks, None, self._taken_t  # reach the file before the samples that precede them
        self._taken_t = self._ahead_t
        events = np.array(self._events, dtype=EVENT_DTYPE) if self._events else None
        self._events.clear()
        return blocks, events, self._taken_t

    def _write_in_background(self, work: _Work) -> None:
        try:
            self._write(work)
        except Exception as exc:  # raised on the caller's thread by its next call (_await_write)
            self._write_error = exc

    def _write(self, work: _Work) -> None:
        """The file side of a flush (one at a time: the caller's thread or the background thread). A file no longer
        linked in any folder (deleted, or its folder removed, while the run writes it) fails the write: its data
        could never be read, and the run must stop rather than drive the rig with nothing recorded (a file moved
        away is treated alike: the end stamp could not find it)."""
        if self._fd is not None and self._unlinked():
            raise UnlinkedError("the file (or its folder) was deleted or moved while the run was writing it: "
                                "nothing more can be recorded")
        blocks, events, last_t = work
        t0, c0 = time.perf_counter(), time.thread_time()
        counts = self._counts.copy()
        for k, stream, data, n_new in blocks:
            datasets = self._datasets[stream]
            n = int(counts[k])
            written = {}
            for name, values in data.items():
                d = datasets[name]
                d.resize((n + n_new,))
                written[name] = np.ascontiguousarray(values, dtype=d.dtype)
                d.write_direct(written[name], dest_sel=np.s_[n:n + n_new])
            if stream == "amplifier" and self._hv is not None:
                self._hv.add(written["t"], written["voltage"])
            counts[k] = n + n_new
        if events is not None:
            n = int(counts[-1])
            for field, d in self._events_ds.items():
                d.resize((n + events.size,))
                d[n:] = events[field].astype(d.dtype)  # S16 → the dataset's UTF-8 type (no HDF5 conversion)
            counts[-1] = n + events.size
        f = self._f
        assert f is not None
        f.flush()  # the data first …
        self._samples[:] = counts
        self._updated[0] = last_t
        f.flush()  # … then what a reader may count as valid
        self.samples_written += int((counts[:-1] - self._counts[:-1]).sum())
        self._counts = counts
        self.write_seconds += time.perf_counter() - t0
        self._cpu_write += time.thread_time() - c0

    def _unlinked(self) -> bool:
        """Whether the open file is no longer the one at its path: its last link gone (where the filesystem counts
        links: some FUSE mounts say 0 throughout), or its path now missing or another file (NFS renames a deleted
        open file to ``.nfsXXXX`` and keeps it linked)."""
        assert self._fd is not None
        st = os.fstat(self._fd)
        if self._links_counted and st.st_nlink == 0:
            return True
        try:
            at = os.stat(self.path)
        except FileNotFoundError:
            return True
        except OSError:  # the folder unreadable for a moment: not a reason to stop a run
            return False
        return (at.st_dev, at.st_ino) != (st.st_dev, st.st_ino)

    def hv_stats(self) -> HvStats | None:
        """The catalogue's high-voltage statistics of what was written (those :func:`~bench.storage.catalog.
        hv_statistics` reads from the file, bit for bit), once the file is finished; None while it is open, after a
        failed write, or without a measured amplifier voltage."""
        if self._f is not None or self.failure or self._hv is None:
            return None
        return self._hv.stats()

    def set_state(self, state: str, reason: str = "") -> None:
        """Record the run's state (visible to readers at once); a no-op once the recorder has failed."""
        if state not in STATES:
            raise ValueError(f"unknown run state {state!r}")
        self.flush()  # the data first: a state must never be on disk without the records before it
        if self.failure or self._f is None:
            return
        try:
            self._f["status/state"][0] = state.encode()
            self._f["status/reason"][0] = utf8(reason, STATUS_TEXT["reason"])
            self._f.flush()
            self._state_written = state != "running"
        except Exception as exc:
            raise self._fail("write failed", exc) from None

    def end_unstarted(self, exc: BaseException) -> None:
        """Record the end of a run stopped before it started (``exc``: Ctrl-C, a stop signal or an exit — interrupted
        —, any other error — error), so its file never stays "running"; quiet (the caller raises ``exc``), a no-op
        once finished or failed."""
        state = "interrupted" if isinstance(exc, KeyboardInterrupt | SystemExit | OperationCancelledError) else "error"
        why = " ".join(str(exc).split())
        reason = f"stopped before the run started: {type(exc).__name__}" + (f": {why}" if why else "")
        with contextlib.suppress(Exception):
            self.finish(state, reason)

    def finish(self, state: str, reason: str) -> None:
        """Final flush, close, and stamp the root attributes (the file is complete after this).

        Once the recorder has failed this only makes sure the file is released, and does not raise again;
        the file then keeps ``state = running`` and ``complete`` False (or absent): a reader reports it incomplete.
        """
        if self.failure or self._f is None:
            return
        end = now_iso()
        self.set_state(state, reason)
        f = self._f
        if f is None:  # set_state failed (and raised); the guard is for type checkers
            return
        try:
            f["status/end_time"][0] = end.encode()
            f.flush()
            f.close()
        except Exception as exc:
            raise self._fail("cannot close", exc) from None
        self._f = None
        g: h5py.File | None = None
        fd: int | None = None
        try:
            g = reopen_for_stamp(self.path)
            fd = int(g.id.get_vfd_handle())  # now: once a close has failed, asking for it crashes the interpreter
            stamp(g, end, state, reason)
            g.close()
        except Exception as exc:
            if g is not None:
                abandon(g, fd)
            self.failure = f"run file {self.path}: cannot stamp the end of the run: {cause(exc)}"
            raise StorageError(self.failure) from None
        try:  # the file is complete and closed: a failing stat only means the end row reads the file back
            st = os.stat(self.path)
        except OSError:
            return
        self._written = Written(dict(self._attrs), state, stored_text(reason, STATUS_TEXT["reason"]), end,
                                len(self._steps_done), self._steps_total, (st.st_size, st.st_mtime_ns))

    def written(self) -> Written | None:
        """What the finished file holds (:class:`Written`); None unless :meth:`finish` completed (a failed write, a
        file not yet finished)."""
        return self._written
