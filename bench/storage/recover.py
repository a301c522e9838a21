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
import struct
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from bench.storage.recorder import FORMATS, abandon, cause, ignore_sigxfsz, now_iso

SIGNATURE = b"\x89HDF\r\n\x1a\n"
RECOVERED_REASON = "recovered after crash"
SPACE_MARGIN = 1 << 20  # bytes free beyond the extension: HDF5 writes a little metadata when it trims and marks


def hashlittle(data: bytes | bytearray | memoryview, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle`` (byte-wise, little-endian), the checksum of HDF5 metadata."""
    m = 0xFFFFFFFF

    def rot(x: int, k: int) -> int:
        return ((x << k) | (x >> (32 - k))) & m

    length = len(data)
    a = b = c = (0xDEADBEEF + length + initval) & m
    k = bytes(data)
    i = 0
    while length > 12:
        a = (a + int.from_bytes(k[i:i + 4], "little")) & m
        b = (b + int.from_bytes(k[i + 4:i + 8], "little")) & m
        c = (c + int.from_bytes(k[i + 8:i + 12], "little")) & m
        a = (a - c) & m; a ^= rot(c, 4); c = (c + b) & m  # noqa: E702 — the reference's mix(), line by line
        b = (b - a) & m; b ^= rot(a, 6); a = (a + c) & m  # noqa: E702
        c = (c - b) & m; c ^= rot(b, 8); b = (b + a) & m  # noqa: E702
        a = (a - c) & m; a ^= rot(c, 16); c = (c + b) & m  # noqa: E702
        b = (b - a) & m; b ^= rot(a, 19); a = (a + c) & m  # noqa: E702
        c = (c - b) & m; c ^= rot(b, 4); b = (b + a) & m  # noqa: E702
        length -= 12
        i += 12
    if length == 0:
        return c
    tail = k[i:i + length] + bytes(12 - length)
    a = (a + int.from_bytes(tail[0:4], "little")) & m
    b = (b + int.from_bytes(tail[4:8], "little")) & m
    c = (c + int.from_bytes(tail[8:12], "little")) & m
    c ^= b; c = (c - rot(b, 14)) & m  # noqa: E702 — final()
    a ^= c; a = (a - rot(c, 11)) & m  # noqa: E702
    b ^= a; b = (b - rot(a, 25)) & m  # noqa: E702
    c ^= b; c = (c - rot(b, 16)) & m  # noqa: E702
    a ^= c; a = (a - rot(c, 4)) & m  # noqa: E702
    b ^= a; b = (b - rot(a, 14)) & m  # noqa: E702
    c ^= b; c = (c - rot(b, 24)) & m  # noqa: E702
    return c


@dataclass(frozen=True)
class Superblock:
    """Where the superblock (version 2 or 3) sits and what it says."""

    offset: int  # of the signature in the file (0, or after a user block: 512, 1024, …)
    version: int
    size_of_offsets: int
    flags: int  # file consistency flags: 0 when the file was closed properly
    base_address: int
    eoa: int  # end-of-file address (relative to the base address): end of the space HDF5 allocated

    @property
    def checksum_at(self) -> int:
        """Offset (in the file) of the 4-byte checksum; it covers everything from the signature to here."""
        return self.offset + 12 + 4 * self.size_of_offsets


def _find_superblock(head: bytes | bytearray) -> Superblock | None:
    for off in (0, *(512 << k for k in range(12))):
        if head[off:off + 8] == SIGNATURE:
            version = head[off + 8]
            if version < 2:
                return Superblock(off, version, 0, 0, 0, 0)
            so = head[off + 9]
            fmt = {4: "<I", 8: "<Q"}.get(so)
            if fmt is None:
                return None
            base = struct.unpack_from(fmt, head, off + 12)[0]
            eoa = struct.unpack_from(fmt, head, off + 12 + 2 * so)[0]
            return Superblock(off, version, so, head[off + 11], base, eoa)
    return None


def read_superblock(image: bytes | bytearray) -> Superblock | None:
    """The superblock of an HDF5 file image (its first bytes suffice), or None if there is none."""
    return _find_superblock(image)


def clear_consistency_flags(image: bytearray) -> bool:
    """Clear the file consistency flags in ``image`` (a version 2/3 superblock; checksum recomputed).

    Returns whether anything changed. Works on the first bytes of the file or on a whole in-memory copy.
    """
    sb = _find_superblock(image)
    if sb is None or sb.version < 2 or sb.flags == 0:
        return False
    image[sb.offset + 11] = 0
    struct.pack_into("<I", image, sb.checksum_at, hashlittle(image[sb.offset:sb.checksum_at]))
    return True


def open_elsewhere(path: Path) -> list[int]:
    """Processes (other than this one) holding ``path`` open — a writer still at work (Linux /proc)."""
    target = os.path.realpath(path)
    pids = []
    proc = Path("/proc")
    if not proc.is_dir():
        return []
    for d in proc.iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if any(os.path.realpath(fd) == target for fd in (d / "fd").iterdir()):
                pids.append(int(d.name))
        except OSError:
            continue
    return pids


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
    from bench.storage.runfile import open_h5, open_run

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"run file {p}: not found")
    with p.open("rb") as fh:
        head = bytearray(fh.read(512 * 2048 + 64))
    sb = _find_superblock(head)
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
