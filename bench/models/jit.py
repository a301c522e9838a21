"""numba's ``njit`` with the project's compiled-kernel cache: one cache directory per version of the kernels.

numba keys a cached kernel by the contents of its own source file only, yet a kernel carries the machine code of
every kernel it calls (compiled in, often inlined). After a change to ``lozenge.py`` alone, ``run_fixed`` (in
``integrate.py``, unchanged) would load from the cache the *old* LS-DEA step it was compiled with — an edit, a
``git pull`` or a package upgrade that leaves the caller's file as it was would run a model that is no longer in
the sources. So every kernel module takes ``njit`` from here, and the cache lives in a directory named by a
digest of all kernel sources (the files of ``bench`` and ``sim_devices`` that use ``njit``): any change to any of
them starts an empty cache, and identical sources share one (checkouts, dask workers, installed wheels).

The directory: ``$NUMBA_CACHE_DIR/<digest>`` where that is set, else ``$XDG_CACHE_HOME/dea-bench/numba/<digest>``
(``~/.cache/…``), else a folder in the temporary directory when neither can be written. Each use marks it (its
time stamp); a sibling of another digest unused for :data:`UNUSED_DAYS` is removed (a few MB each: one per version
of the sources a machine has run).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import shutil
import tempfile
import time
from pathlib import Path

import numba
from numba import njit

__all__ = ["cache_dir", "njit"]

UNUSED_DAYS = 30.0  # a cache of other sources not used this long is removed
_DIGEST = re.compile(r"[0-9a-f]{16}")


def _kernel_sources() -> list[Path]:
    """The project's kernel modules: the ``.py`` files of ``bench`` and ``sim_devices`` that use ``njit``."""
    roots = [Path(__file__).resolve().parents[1]]  # bench
    spec = importlib.util.find_spec("sim_devices")
    if spec is not None and spec.origin is not None:
        roots.append(Path(spec.origin).resolve().parent)
    return [f for root in roots for f in sorted(root.rglob("*.py")) if b"njit" in f.read_bytes()]


def sources_digest() -> str:
    """A digest of every kernel module's path (within its package) and contents."""
    h = hashlib.sha256()
    for f in _kernel_sources():
        h.update(f"{f.parent.name}/{f.name}\0".encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        return os.access(path, os.W_OK)
    except OSError:
        return False


def _mark_and_prune(used: Path) -> None:
    """Stamp ``used`` as in use now; remove its siblings of other digests unused for :data:`UNUSED_DAYS`."""
    now = time.time()
    try:
        os.utime(used, (now, now))
        for other in used.parent.iterdir():
            if other != used and _DIGEST.fullmatch(other.name) and other.is_dir() \
                    and now - other.stat().st_mtime > UNUSED_DAYS * 86400.0:
                shutil.rmtree(other, ignore_errors=True)
    except OSError:  # another process pruned first, or a read-only parent: the cache still works
        pass


def cache_dir() -> Path:
    """Where the compiled kernels of these sources are cached (created)."""
    digest = sources_digest()
    base = os.environ.get("NUMBA_CACHE_DIR") or \
        str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "dea-bench" / "numba")
    for candidate in (Path(base) / digest, Path(tempfile.gettempdir()) / f"dea-bench-numba-{os.getuid()}" / digest):
        if _writable(candidate):
            _mark_and_prune(candidate)
            return candidate
    return Path(base) / digest  # numba reports the failure to cache; the kernels still compile and run


numba.config.CACHE_DIR = str(cache_dir())  # type: ignore[attr-defined]  # read as a kernel with cache=True is decorated
