"""Release the run file of a crashed or killed run so that every HDF5 tool opens it (``bench recover``).

An SWMR writer marks the file open in its superblock (the *file consistency flags*); a writer that dies
(kill -9, power cut, segfault) leaves them set, and plain ``h5py.File(path)``, h5dump and HDFView refuse the
file until they are cleared (what ``h5clear -s`` does). :func:`recover` clears them, recomputing the
superblock's Jenkins lookup3 checksum, extends a file shorter than its recorded end of allocation (a write
that failed on a full disk), cuts every dataset to the records the writer confirmed (``/status/samples``)
and marks the file: attribute ``recovered_at``, "recovered after crash" in ``/status/reason`` (after the
reason a run killed while stamping its end had already written). The state stays as it was (``running``) and
there is no ``complete`` attribute, so readers still report the run incomplete.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from bench.storage.recorder import FORMATS, abandon, cause, ignore_sigxfsz, now_iso
from bench.storage.runfile import open_h5, open_run
from bench.storage.superblock import clear_consistency_flags, open_elsewhere, read_superblock

RECOVERED_REASON = "recovered after crash"
SPACE_MARGIN = 1 << 20  # bytes free beyond the extension: HDF5 writes a little metadata when it trims and marks


@dataclass
class RecoveryReport:
    """What :func:`recover` found and did."""

    path: Path
    actions: list[str] = field(default_factory=list)  # what was changed ([] if the file needed nothing)
    samples: dict[str, int] = field(default_factory=dict)  # valid records per stream after recovery
    recorded_up_to: float = 0.0  # run time of the writer's last successful flush [s]
    state: str = ""
    incomplete_reason: str = ""

    def lines(self) -> list[str]:
        """The report as text, one item a line."""
        out = [f"run file {self.path}: " + ("; ".join(self.actions) if self.actions else "nothing to recover")]
        out.append(f"state {self.state}" + (f" — INCOMPLETE: {self.incomplete_reason}" if self.incomplete_reason
                                            else " (complete)"))
        out.append(f"recorded up to {self.recorded_up_to:.3f} s")
        out += [f"{name}: {n:,} samples" for name, n in self.samples.items()]
        return out


def recover(path: str | Path) -> RecoveryReport:
    """Make the file of a crashed or killed run open in every HDF5 tool, and say what it holds.

    Raises ValueError (one line naming the file) if it is not an HDF5 run file, a process still writes it, or
    its disk has too little space (then nothing was changed: free some space and run it again).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"run file {p}: not found")
    with p.open("rb") as fh:
        head = bytearray(fh.read(512 * 2048 + 64))
    sb = read_superblock(head)
    if sb is None:
        raise ValueError(f"run file {p}: not an HDF5 file (no superblock)")
    try:
        with open_h5(p) as f:
            fmt = f.attrs.get("format")
    except (OSError, ValueError) as exc:
        raise ValueError(f"run file {p}: not a readable HDF5 file ({' '.join(str(exc).split())})") from None
    if fmt not in FORMATS:
        raise ValueError(f"run file {p}: not a dea-bench run file (format {fmt!r})")
    writers = open_elsewhere(p)
    if writers:
        raise ValueError(f"run file {p}: still open in process {', '.join(map(str, writers))}: "
                         "a run may be writing it (stop it first)")
    report = RecoveryReport(p)
    end = sb.base_address + sb.eoa
    size = p.stat().st_size
    grow = end - size if sb.version >= 2 and size < end else 0  # a failed write left the file short
    free = shutil.disk_usage(p.parent).free
    if (sb.flags or grow) and free < grow + SPACE_MARGIN:
        raise ValueError(f"run file {p}: {free:,} bytes free on its disk, recovery needs {grow + SPACE_MARGIN:,}: "
                         "free some space and run it again (nothing was changed)")
    ignore_sigxfsz()
    if grow:
        try:
            os.truncate(p, end)  # zeros up to what HDF5 allocated; readers never count them (/status/samples)
        except OSError as exc:
            raise ValueError(f"run file {p}: cannot extend it to {end:,} bytes: {cause(exc)} (nothing was changed)"
                             ) from None
        report.actions.append(f"extended the file from {size:,} to {end:,} bytes (a write had failed)")
    if clear_consistency_flags(head):
        with p.open("r+b") as fh:
            fh.seek(sb.offset + 11)
            fh.write(head[sb.offset + 11:sb.offset + 12])
            fh.seek(sb.checksum_at)
            fh.write(head[sb.checksum_at:sb.checksum_at + 4])
            fh.flush()
            os.fsync(fh.fileno())
        report.actions.append(f"cleared the file consistency flags (0x{sb.flags:02x}) left by the writer")
    try:
        f = h5py.File(p, "r+")
    except OSError as exc:
        raise ValueError(f"run file {p}: HDF5 cannot open it even now ({' '.join(str(exc).split())})") from None
    try:
        if not f.attrs.get("complete", False):
            report.actions += _trim(f)
            if report.actions:
                f.attrs["recovered_at"] = now_iso()
                before = f["status/reason"][0].decode(errors="replace")  # a run killed while stamping its end
                tail = f" | {RECOVERED_REASON}" if before else RECOVERED_REASON  # such a run keeps its reason
                kept = before.encode()[:400 - len(tail)].decode(errors="ignore")  # whole characters only
                f["status/reason"][0] = (kept + tail).encode()
                report.actions.append("marked it recovered (attribute recovered_at)")
        f.close()
    except Exception as exc:  # e.g. the disk filled meanwhile: release the file without crashing
        abandon(f)
        raise ValueError(f"run file {p}: cannot write the recovery marks: {cause(exc)}") from None
    run = open_run(p)
    report.samples = {name: len(s) for name, s in run.streams.items()}
    report.recorded_up_to, report.state, report.incomplete_reason = run.updated, run.state, run.incomplete_reason
    return report


def _trim(f: h5py.File) -> list[str]:
    """Cut every dataset to the records the writer confirmed, so no tool shows zero-filled records."""
    if "samples" in f["status"]:
        d = f["status/samples"]
        valid = dict(zip(json.loads(d.attrs["names"]), (int(n) for n in d[:]), strict=True))
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
