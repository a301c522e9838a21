"""Release the run file of a crashed or killed run so that every HDF5 tool opens it (``bench recover``).

An SWMR writer marks the file open in its superblock (the *file consistency flags*); a writer that dies
(kill -9, power cut, segfault) leaves them set, and plain ``h5py.File(path)``, h5dump and HDFView refuse the
file until they are cleared (what ``h5clear -s`` does). :func:`recover` clears them, recomputing the
superblock's Jenkins lookup3 checksum, extends a file shorter than its recorded end of allocation (a write
that failed on a full disk), cuts every dataset to the records the writer confirmed (``/status/samples``)
and marks the file: attribute ``recovered_at``, "recovered after crash" in ``/status/reason`` (after the
reason a run killed while stamping its end had already written). The state stays as it was (``running``) and
``complete`` is not set, so readers still report the run incomplete.

Everything is decided on a patched, read-only view of the file (:mod:`bench.storage.repair`) before a byte is
changed; a file it refuses is left as it was. A run file whose root attributes cannot be read (an earlier version's
end stamp failed on a full disk) is identified by its structure (``/status``, ``/events``, ``/program``): its root
attribute messages are dropped and the root rebuilt from ``/status`` (format, end time, exit status and reason;
attribute ``recovered_root`` says what was lost). Any other file is refused in one line.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py

from bench.storage.absent import absent_run_file
from bench.storage.recorder import FORMAT, FORMATS, STATES, STORAGE_FAULT, abandon, cause, ignore_sigxfsz, now_iso
from bench.storage.repair import Patches, open_view, root_attribute_patches, superblock_patches, write_patches
from bench.storage.runfile import open_run, recorded_note, refuse_truncated, state_shown, valid_counts
from bench.storage.superblock import Superblock, open_elsewhere, read_superblock

RECOVERED_REASON = "recovered after crash"
FAULT_REASON = "recovered after the storage fault"  # the writer marked /status/reason "storage fault: …"
REBUILT_REASON = "recovered: end stamp failed, root attributes rebuilt from /status"
LOST = ("root attributes unreadable (the end stamp of an earlier version failed on a full disk): rebuilt from "
        "/status and the attributes that could still be read one by one")
STAMP = ("end_time", "exit_status", "exit_reason", "complete")  # the end stamp: rebuilt from /status, never salvaged
# root attributes a run file holds (bench.runtime.run.execute, the recorder): looked up by name where the header's
# list of names cannot be read
KNOWN = ("format", "Conventions", "NX_class", "default", "software", "start_time", "protocol_name", "protocol_path",
         "protocol_text", "protocol_sha256", "rig_name", "rig_toml", "rig_text", "simulated", "clock", "specimen_kind",
         "specimen", "recording", "sources", "duration_planned", "hv_watchdog", "run_id", "campaign_id", "operator",
         "specimen_id", "notes", "wire_time", "previous_file", "previous_run_id", "resumed_at_step", "replay_of",
         "replay_of_run_id", "fits")
SPACE_MARGIN = 1 << 20  # bytes free beyond the extension: HDF5 writes a little metadata when it trims and marks


@dataclass
class RecoveryReport:
    """What :func:`recover` found and did."""

    path: Path
    actions: list[str] = field(default_factory=list)  # what was changed ([] if the file needed nothing)
    samples: dict[str, int] = field(default_factory=dict)  # valid records per stream after recovery
    recorded_up_to: float = 0.0  # run time to which the writer's last successful flush completed every stream [s]
    stream_ends: list[float] = field(default_factory=list)  # each stream's last sample [s] (whole-chunk writes run
    # ahead of the above)
    state: str = ""
    incomplete_reason: str = ""

    def lines(self) -> list[str]:
        """The report as text, one item a line."""
        out = [f"run file {self.path}: " + ("; ".join(self.actions) if self.actions else "nothing to recover")]
        if self.incomplete_reason:
            out.append(f"state {state_shown(self.state, False, self.incomplete_reason)} — INCOMPLETE: "
                       f"{self.incomplete_reason}")
        else:
            out.append(f"state {self.state} (complete)")
        out.append(f"recorded up to {self.recorded_up_to:.3f} s" + recorded_note(self.recorded_up_to,
                                                                                   self.stream_ends))
        out += [f"{name}: {n:,} samples" for name, n in self.samples.items()]
        return out


def recover(path: str | Path) -> RecoveryReport:
    """Make the file of a crashed or killed run open in every HDF5 tool, and say what it holds.

    Raises ValueError (one line naming the file) if it is not an HDF5 run file, a process still writes it, or
    its disk has too little space (then nothing was changed: free some space and run it again).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(absent_run_file(p))
    with p.open("rb") as fh:
        head = bytearray(fh.read(512 * 2048 + 64))
    sb = read_superblock(head)
    if sb is None:
        raise ValueError(f"run file {p}: not an HDF5 file (no superblock)")
    end = sb.base_address + sb.eoa
    size = p.stat().st_size
    refuse_truncated(p)  # closed by its writer, then cut: nothing to recover (a crashed writer's short file is)
    grow = end - size if sb.version >= 2 and size < end else 0  # a failed write left the file short
    patches = superblock_patches(head, sb)
    fmt, damaged, kept = _identify(p, patches, size + grow)  # as it reads once released: nothing is changed yet
    if damaged:
        patches |= _root_patches(p, head, sb, patches, size + grow)
    writers = open_elsewhere(p)
    if writers:
        raise ValueError(f"run file {p}: still open in process {', '.join(map(str, writers))}: "
                         "a run may be writing it (stop it first)")
    report = RecoveryReport(p)
    free = shutil.disk_usage(p.parent).free
    # damaged root attributes are rebuilt in a copy, which replaces the file only once every step succeeded: HDF5
    # may fail on damage the rebuild cannot see beforehand, and a failure half-way left the file worse than before
    # (its patches written, its open-for-write flag set; an outside tester) — the file is either recovered or as
    # it was. A crash's usual recovery (flags, an extension, the trim) is done in place: no copy of a large file
    need = grow + SPACE_MARGIN + (size if damaged else 0)
    if (patches or grow) and free < need:
        raise ValueError(f"run file {p}: {free:,} bytes free on its disk, recovery needs {need:,}: "
                         "free some space and run it again (nothing was changed)")
    ignore_sigxfsz()
    real = p.resolve()  # a link's target is the file (replaced, not the link)
    if damaged and not os.access(real, os.W_OK):  # as the in-place path, which cannot open it for writing
        raise ValueError(f"run file {p}: not writable (its permissions): recover it where you may write it "
                         "(nothing was changed)")
    work = _copy_beside(real) if damaged else p
    try:
        _repair(p, work, report, patches, grow, size, end, sb, damaged, kept, fmt)
        if work != p:
            with work.open("rb") as fh:  # on disk before it replaces the file: a power cut keeps one whole file
                os.fsync(fh.fileno())
            os.replace(work, real)
    except BaseException as exc:
        if work != p:
            work.unlink(missing_ok=True)
        if work != p and isinstance(exc, OSError):  # the fsync or the replace (a folder that refuses it)
            raise ValueError(f"run file {p}: cannot replace it with its rebuilt copy: {cause(exc)} (nothing was "
                             "changed)") from None
        raise
    run = open_run(p)
    report.samples = {name: len(s) for name, s in run.streams.items()}
    report.stream_ends = [float(s.t[-1]) for s in run.streams.values() if len(s)]
    report.recorded_up_to, report.state, report.incomplete_reason = run.updated, run.state, run.incomplete_reason
    return report



def _copy_beside(real: Path) -> Path:
    """A copy of ``real`` in its folder under a name of its own (``NAME.h5.<random>.recovering``), its permission
    bits kept (:func:`shutil.copy2`); nothing is left behind if the copy fails or is interrupted. ValueError (one
    line) if it cannot be made."""
    import tempfile

    fd, name = tempfile.mkstemp(prefix=real.name + ".", suffix=".recovering", dir=real.parent)
    os.close(fd)
    work = Path(name)
    try:
        shutil.copy2(real, work)
    except BaseException as exc:
        work.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise ValueError(f"run file {real}: cannot copy it to rebuild its root attributes: {cause(exc)} "
                             "(nothing was changed)") from None
        raise
    return work


def _repair(p: Path, work: Path, report: RecoveryReport, patches: Patches, grow: int, size: int, end: int,
            sb: Superblock, damaged: bool, kept: dict[str, Any] | None, fmt: str) -> None:
    """The writes of :func:`recover`, on ``work`` (the file itself, or the copy that replaces it on success)."""
    unchanged = " (nothing was changed: the damage is beyond what recover rebuilds)" if work != p else ""
    if grow:
        try:
            os.truncate(work, end)  # zeros up to what HDF5 allocated; readers never count them (/status/samples)
        except OSError as exc:
            raise ValueError(f"run file {p}: cannot extend it to {end:,} bytes: {cause(exc)} (nothing was changed)"
                             ) from None
        report.actions.append(f"extended the file from {size:,} to {end:,} bytes (a write had failed)")
    if patches:
        write_patches(work, patches)
    if sb.flags and sb.version >= 2:
        report.actions.append(f"cleared the file consistency flags (0x{sb.flags:02x}) left by the writer")
    if damaged and kept is not None:
        report.actions.append("dropped the root attributes (the end stamp of an earlier version failed; "
                              f"{len(kept)} of them read one by one first, to be written back)")
    try:
        f = h5py.File(work, "r+")
    except OSError as exc:
        raise ValueError(f"run file {p}: HDF5 cannot open it even now ({' '.join(str(exc).split())})"
                         + unchanged) from None
    try:
        if kept is not None:
            report.actions += _rebuild_root(f, fmt, kept)
        if not f.attrs.get("complete", False):
            report.actions += _trim(f)
            if report.actions:
                f.attrs["recovered_at"] = now_iso()
                before = f["status/reason"][0].decode(errors="replace")  # a run killed while stamping its end
                note = (REBUILT_REASON if kept is not None else FAULT_REASON if before.startswith(STORAGE_FAULT)
                        else RECOVERED_REASON)
                tail = f" | {note}" if before else note  # such a run keeps its reason
                head_of = before.encode()[:400 - len(tail)].decode(errors="ignore")  # whole characters only
                f["status/reason"][0] = (head_of + tail).encode()
                report.actions.append("marked it recovered (attribute recovered_at)")
        f.close()
    except Exception as exc:  # e.g. the disk filled meanwhile: release the file without crashing
        abandon(f)
        raise ValueError(f"run file {p}: cannot write the recovery marks: {cause(exc)}" + unchanged) from None


def _is_run(f: h5py.File) -> bool:
    """Whether ``f`` has the structure of a dea-bench run file (what identifies one whose root attributes are lost):
    ``/status`` with its texts, a state the recorder writes and a floating-point ``updated``, ``/events``, and a
    ``/program`` with its start times and durations (columns of a group, or fields of format 1's compound)."""
    try:
        status, program = f.get("status"), f.get("program")
        if not (isinstance(status, h5py.Group) and "events" in f and program is not None
                and all(isinstance(status.get(k), h5py.Dataset) for k in ("state", "reason", "end_time", "updated"))):
            return False
        state = status["state"][0]
        columns = set(program) if isinstance(program, h5py.Group) else set(program.dtype.names or ())
        return (isinstance(state, bytes) and state.rstrip(b"\0").decode("utf-8", "replace") in STATES
                and status["updated"].dtype.kind == "f" and {"t_start", "duration"} <= columns)
    except Exception:  # anything unreadable in that structure: not one to rebuild
        return False


def _identify(p: Path, patches: Patches, size: int) -> tuple[str, bool, dict[str, Any] | None]:
    """The run file's format as it reads once released; whether its root attributes are unreadable (then its
    structure identifies it); and the root attributes to write back (None: the root is as it should be). A root
    with no attributes at all on a run's structure is one a recover stopped half-way left (its attributes dropped,
    not yet rebuilt). ValueError (one line) for anything else."""
    try:
        with open_view(p, patches, size) as f:
            try:
                attrs = dict(f.attrs)
            except Exception:  # the root object header points at attribute storage that never reached the disk
                if _is_run(f):
                    return _format_of(f), True, _salvage(f)
                attrs = {}
            else:
                if not attrs and _is_run(f):
                    return _format_of(f), False, {}
            fmt = attrs.get("format")
    except (OSError, ValueError) as exc:
        raise ValueError(f"run file {p}: not a readable HDF5 file ({' '.join(str(exc).split())})") from None
    if fmt not in FORMATS:
        raise ValueError(f"run file {p}: not a dea-bench run file (format {fmt!r})")
    return str(fmt), False, None


def _format_of(f: h5py.File) -> str:
    """A run file's format from its structure (events a group of columns: the current format)."""
    return FORMAT if isinstance(f["events"], h5py.Group) else FORMATS[0]


def _salvage(f: h5py.File) -> dict[str, Any]:
    """The root attributes of ``f`` that can still be read one by one (the end stamp left out), by the names the
    header lists where it can, else by the names a run file has."""
    names: list[str] = []
    try:
        for i in range(h5py.h5a.get_num_attrs(f.id)):
            with contextlib.suppress(Exception):
                names.append(h5py.h5a.open(f.id, index=i).get_name().decode("utf-8", "replace"))
    except Exception:  # the count itself is unreadable
        pass
    out: dict[str, Any] = {}
    for name in dict.fromkeys([*names, *KNOWN]):
        if name not in STAMP:
            with contextlib.suppress(Exception):
                out[name] = f.attrs[name]
    return out


def _root_patches(p: Path, head: bytearray, sb: Superblock, patches: Patches, size: int) -> Patches:
    """The patches that drop the root attributes, checked to leave a readable run file (ValueError if not)."""
    root = root_attribute_patches(p, head, sb, size)
    try:
        with open_view(p, patches | root, size) as f:
            if root and not dict(f.attrs) and _is_run(f):
                return root
    except Exception:  # said below, in one line
        pass
    raise ValueError(f"run file {p}: its root attributes are unreadable and its root object header cannot be "
                     "repaired (nothing was changed)")


def _rebuild_root(f: h5py.File, fmt: str, kept: dict[str, Any]) -> list[str]:
    """Root attributes of a run file whose own were lost: ``kept`` (those read one by one before), the format from
    its structure, the end from ``/status``."""
    for name, value in kept.items():
        f.attrs[name] = value
    f.attrs["format"] = fmt
    f.attrs["recovered_root"] = LOST
    if "entry" in f:
        f.attrs["Conventions"] = "CF-1.10"
        f.attrs["NX_class"] = "NXroot"
        f.attrs["default"] = "entry"
    state = f["status/state"][0].decode(errors="replace")
    if state != "running":
        f.attrs["end_time"] = f["status/end_time"][0].decode(errors="replace")
        f.attrs["exit_status"] = state
        f.attrs["exit_reason"] = f["status/reason"][0].decode(errors="replace")
    return [f"rebuilt the root attributes from /status (format {fmt!r}, state {state}) and wrote back the {len(kept)} "
            "read one by one"]


def _trim(f: h5py.File) -> list[str]:
    """Cut every dataset to the records the writer confirmed, so no tool shows zero-filled records."""
    if "samples" in f["status"]:
        valid = valid_counts(f)  # a negative count would cut records the writer confirmed: refused
    else:
        valid = {name: min(d.shape[0] for d in f[name].values()) for name in f
                 if isinstance(f[name], h5py.Group) and "t" in f[name]}
    cut = []
    for name, n in valid.items():
        obj = f.get(name)  # a group of datasets (a stream; events in format 2) or a dataset (events in format 1)
        datasets = [obj] if isinstance(obj, h5py.Dataset) else list(obj.values()) if obj is not None else []
        extra = max((d.shape[0] - n for d in datasets), default=0)
        if extra > 0:
            for d in datasets:
                if d.shape[0] > n:
                    d.resize((n,))
            cut.append(f"{name}: {extra:,} unconfirmed record{'s' * (extra != 1)} cut")
    return cut
