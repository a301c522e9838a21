"""The HDF5 superblock of a run file: where it sits, its file consistency flags and their checksum.

Read by :mod:`bench.storage.runfile` (a reader opens the file of a crashed writer from an in-memory copy with its
flags cleared; whether a writer still holds it) and by :mod:`bench.storage.recover` (clears them on disk).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

SIGNATURE = b"\x89HDF\r\n\x1a\n"


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
    """Processes (other than this one) holding ``path`` open for writing — a writer still at work (Linux /proc). A
    reader does not count: a crashed run's file read as "still going" while a viewer (HDFView, `bench watch`, h5py
    in a notebook) had it open (found by an outside tester)."""
    target = os.path.realpath(path)
    pids = []
    proc = Path("/proc")
    if not proc.is_dir():
        return []
    for d in proc.iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if any(os.path.realpath(fd) == target and _for_writing(d / "fdinfo" / fd.name)
                   for fd in (d / "fd").iterdir()):
                pids.append(int(d.name))
        except OSError:
            continue
    return pids


def _for_writing(fdinfo: Path) -> bool:
    """Whether the descriptor whose /proc/PID/fdinfo/FD this is was opened for writing (its ``flags``, octal: the
    access mode O_WRONLY or O_RDWR); True where that cannot be read (counted as a writer: the safe side)."""
    try:
        for line in fdinfo.read_text().splitlines():
            if line.startswith("flags:"):
                return int(line.split()[1], 8) & os.O_ACCMODE != os.O_RDONLY
    except (OSError, ValueError, IndexError):
        pass
    return True
