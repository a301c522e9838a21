"""Look at a damaged run file without changing it, and the byte patches that make it readable (``bench recover``).

A writer that died with the file open leaves its superblock marked (the file consistency flags) and, where a write
failed on a full disk, the file shorter than the space HDF5 allocated. Earlier versions also added the end-of-run
stamp as new root attributes after the run: a full disk there left the root object header pointing at attribute
storage that never reached the disk, so no root attribute could be read. :func:`open_view` opens such a file as
it would read once patched (flags cleared, extended with zeros, root attribute messages dropped) while the file on
disk stays untouched; :func:`root_attribute_patches` are the patches of the root object header: every attribute
message and the attribute-info message become NIL messages of the same size, checksums recomputed (HDF5 file
format specification, version 2 object headers, sections IV.A.1.b and IV.A.2.a/m).
"""

from __future__ import annotations

import io
import os
import struct
from pathlib import Path

import h5py

from bench.storage.superblock import Superblock, hashlittle

ATTRIBUTE, ATTRIBUTE_INFO, CONTINUATION = 0x0C, 0x15, 0x10  # object header message types
Patches = dict[int, bytes]  # file offset: bytes to read there instead


class View(io.RawIOBase):
    """A file read through ``patches`` and extended with zeros to ``size`` bytes; read-only, the file untouched."""

    def __init__(self, path: Path, patches: Patches, size: int) -> None:
        super().__init__()
        self._fh = path.open("rb")
        self._patches = patches
        self._size = size
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self._pos = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence] + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        n = max(0, min(len(buffer), self._size - self._pos))
        self._fh.seek(self._pos)
        data = bytearray(self._fh.read(n).ljust(n, b"\0"))
        for at, patch in self._patches.items():
            lo, hi = max(at, self._pos), min(at + len(patch), self._pos + n)
            if lo < hi:
                data[lo - self._pos:hi - self._pos] = patch[lo - at:hi - at]
        buffer[:n] = data
        self._pos += n
        return n

    def close(self) -> None:
        self._fh.close()
        super().close()


def open_view(path: Path, patches: Patches, size: int) -> h5py.File:
    """``path`` opened read-only as it reads with ``patches`` applied and extended to ``size`` bytes."""
    return h5py.File(View(path, patches, size), "r")


def superblock_patches(head: bytes | bytearray, sb: Superblock) -> Patches:
    """The superblock with its file consistency flags cleared (and its checksum recomputed); {} if none are set."""
    if sb.version < 2 or sb.flags == 0:
        return {}
    block = bytearray(head[sb.offset:sb.checksum_at])
    block[11] = 0
    return {sb.offset: bytes(block) + struct.pack("<I", hashlittle(block))}


def _root_address(head: bytes | bytearray, sb: Superblock) -> int:
    fmt = {4: "<I", 8: "<Q"}[sb.size_of_offsets]
    return int(struct.unpack_from(fmt, head, sb.offset + 12 + 3 * sb.size_of_offsets)[0]) + sb.base_address


def _drop_attributes(chunk: bytearray, start: int, flags: int, sb: Superblock, sl: int,
                     eoa: int) -> list[tuple[int, int]]:
    """NIL every attribute and attribute-info message of one header chunk (messages from ``start``, a checksum at
    the end); the continuation chunks it names inside the file, as (address, length); ``sl``: the superblock's
    size of lengths (a continuation's length field; its address field is the size of offsets)."""
    header = 6 if flags & 0x04 else 4  # type, size, flags (and the creation order where tracked)
    so = sb.size_of_offsets
    chunks, pos, end = [], start, len(chunk) - 4
    while pos + header <= end:
        kind, size = chunk[pos], struct.unpack_from("<H", chunk, pos + 1)[0]
        body = pos + header
        if kind in (ATTRIBUTE, ATTRIBUTE_INFO):
            chunk[pos] = 0
            chunk[pos + 3] = 0
        elif kind == CONTINUATION:
            addr = int.from_bytes(chunk[body:body + so], "little") + sb.base_address
            length = int.from_bytes(chunk[body + so:body + so + sl], "little")
            if addr + length <= eoa:
                chunks.append((addr, length))
        pos = body + size
    struct.pack_into("<I", chunk, end, hashlittle(chunk[:end]))
    return chunks


def root_attribute_patches(path: Path, head: bytes | bytearray, sb: Superblock, eoa: int) -> Patches:
    """Patches that drop every root attribute (the root object header and its continuation chunks); {} if the
    root object header is not a version 2 header (or the superblock older than version 2)."""
    patches: Patches = {}
    if sb.version < 2:
        return patches
    sl = head[sb.offset + 10]  # size of lengths: the byte after the size of offsets (superblock version 2/3)
    with path.open("rb") as fh:
        addr = _root_address(head, sb)
        fh.seek(addr)
        prefix = fh.read(6 + 16 + 4 + 8)
        if len(prefix) < 7 or prefix[:4] != b"OHDR" or prefix[4] != 2:
            return {}
        flags = prefix[5]
        at = 6 + (16 if flags & 0x20 else 0) + (4 if flags & 0x10 else 0)
        width = 1 << (flags & 0x03)
        size = int.from_bytes(prefix[at:at + width], "little")
        start = at + width
        fh.seek(addr)
        chunk = bytearray(fh.read(start + size + 4))
        todo = _drop_attributes(chunk, start, flags, sb, sl, eoa)
        patches[addr] = bytes(chunk)
        while todo:
            addr, length = todo.pop()
            fh.seek(addr)
            chunk = bytearray(fh.read(length))
            if chunk[:4] != b"OCHK" or len(chunk) != length:
                continue
            todo += _drop_attributes(chunk, 4, flags, sb, sl, eoa)
            patches[addr] = bytes(chunk)
    return patches


def write_patches(path: Path, patches: Patches) -> None:
    """Write ``patches`` into the file and make them durable."""

    with path.open("r+b") as fh:
        for at, data in sorted(patches.items()):
            fh.seek(at)
            fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
