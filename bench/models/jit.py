"""numba's ``njit`` with the project's compiled-kernel cache: one cache directory per version of the kernels.

numba keys a cached kernel by the contents of its own source file only, yet a kernel carries the machine code of
every kernel it calls (compiled in, often inlined). After a change to ``lozenge.py`` alone, ``run_fixed`` (in
``integrate.py``, unchanged) would load from the cache the *old* LS-DEA step it was compiled with — an edit, a
``git pull`` or a package upgrade that leaves the caller's file as it was would run a model that is no longer in
the sources. So every kernel module takes ``njit`` from here, and the cache lives in a directory named by a
digest of all kernel sources (the files of ``bench`` and ``sim_devices`` that use ``njit``): any change to any of
them starts an empty cache, and identical sources share one (checkouts, dask workers, installed wheels). Within it a
kernel's entry is found by its file's place in the package (``bench/models``), not by the file's absolute folder as
numba's own locator does (it names the entry by a hash of that folder): a checkout elsewhere or the installed wheel
of the same sources loads the kernels another compiled. numba checks each entry against the SHA-256 of the source
file beside the kernel (0.68 on; where an older numba stamps times and sizes, the entries are numba's own).

The directory: ``$NUMBA_CACHE_DIR/<digest>`` where that is set, else ``$XDG_CACHE_HOME/dea-bench/numba/<digest>``
(``~/.cache/…``), else the user's own folder (mode 0700) in the temporary directory; where none can be used the
kernels are compiled in every process and not cached (never numba's per-file cache). Each use marks the folder (its
time stamp); a sibling of another digest unused for :data:`UNUSED_DAYS` is removed (a few MB each: one per version
of the sources a machine has run). The digest covers every file of ``bench/models`` and ``bench/core`` (a kernel
compiles in the constants it reads, such as ``batch_plan.LANES``) and every other file that uses ``njit``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numba
from numba.core import caching

__all__ = ["cache_dir", "njit"]

K = TypeVar("K", bound=Callable[..., Any])
UNUSED_DAYS = 30.0  # a cache of other sources not used this long is removed
_DIGEST = re.compile(r"[0-9a-f]{16}")


def _kernel_roots() -> list[Path]:
    """The packages whose kernels the digest covers: ``bench`` and ``sim_devices`` (where installed)."""
    roots = [Path(__file__).resolve().parents[1]]
    spec = importlib.util.find_spec("sim_devices")
    if spec is not None and spec.origin is not None:
        roots.append(Path(spec.origin).resolve().parent)
    return roots


def _kernel_sources() -> list[tuple[Path, bytes]]:
    """What the compiled kernels are made of, each file with its contents: every ``.py`` file of ``bench/models``
    and ``bench/core``, and the other files of ``bench`` and ``sim_devices`` that use ``njit``."""
    roots = _ROOTS
    bench = roots[0]
    model_dirs = (bench / "models", bench / "core")
    found = ((f, f.read_bytes()) for root in roots for f in sorted(root.rglob("*.py")))
    return [(f, data) for f, data in found if f.parent in model_dirs or b"njit" in data]


def sources_digest() -> str:
    """A digest of every kernel source's path (within its package) and contents."""
    h = hashlib.sha256()
    for f, data in _kernel_sources():
        h.update(f"{f.parent.name}/{f.name}\0".encode())
        h.update(data)
    return h.hexdigest()[:16]


def _usable(path: Path, private: bool = False) -> bool:
    """Whether ``path`` exists or could be made, and can be written; ``private``: its parent is this user's own
    folder that no one else may write (the temporary directory is shared: numba reads its index with pickle; made
    0700, and one of ours that others may only read is fine)."""
    try:
        if private:
            path.parent.mkdir(mode=0o700, exist_ok=True)
            st = path.parent.lstat()
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
                return False
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


def _user_cache() -> Path | None:
    """``$XDG_CACHE_HOME`` or ``~/.cache`` (None where there is no home: a uid without a passwd entry)."""
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"])
    try:
        return Path.home() / ".cache"
    except (RuntimeError, KeyError):
        return None


def cache_dir() -> Path | None:
    """Where the compiled kernels of these sources are cached (created); None: nowhere usable."""
    digest = sources_digest()
    user = _user_cache()
    candidates = [(Path(os.environ["NUMBA_CACHE_DIR"]) / digest, False)] if os.environ.get("NUMBA_CACHE_DIR") else \
        ([(user / "dea-bench" / "numba" / digest, False)] if user is not None else [])
    candidates.append((Path(tempfile.gettempdir()) / f"dea-bench-numba-{os.getuid()}" / digest, True))
    for relative, private in candidates:
        candidate = Path(os.path.abspath(relative))  # numba resolves a relative folder anew at every decoration
        if _usable(candidate, private):
            _mark_and_prune(candidate)
            return candidate
    return None


_ROOTS = _kernel_roots()  # found once: the digest's sources and the files whose kernels share entries
_CACHE = cache_dir()


def njit(**options: Any) -> Callable[[K], K]:
    """numba's ``njit(**options)`` (always with its options: ``@njit(cache=True)``), caching in :func:`cache_dir`'s
    folder, or not at all where there is none. numba picks a kernel's cache folder as it decorates it, from its
    config, which it re-reads from the environment when a ``NUMBA_*`` variable changed: so the folder is set again
    at every decoration."""
    if options.get("cache"):
        if _CACHE is None:
            options["cache"] = False
        else:
            numba.config.CACHE_DIR = str(_CACHE)  # type: ignore[attr-defined]
    decorate: Callable[[K], K] = numba.njit(**options)
    if not options.get("cache") or _PackageCache is None:
        return decorate
    uncached: Callable[[K], K] = numba.njit(**{**options, "cache": False})

    def cached(func: K) -> K:
        """numba's dispatcher with the cache found by the file's place in its package, for the files the digest
        covers (numba's own cache for any other file: only the digest makes a shared entry safe); compiled in
        this process, not cached, where the folder cannot be made or written (never numba's per-file cache)."""
        source = Path(inspect.getfile(func)).resolve()
        if not any(source.is_relative_to(root) for root in _ROOTS):
            return decorate(func)
        try:
            cache = _PackageCache(func)
        except RuntimeError:  # no locator: the folder went away or cannot be written since the import
            return uncached(func)
        dispatcher = uncached(func)
        dispatcher._cache = cache  # type: ignore[attr-defined]  # what numba's enable_caching() sets
        return dispatcher

    return cached


def _package_folder(py_file: str) -> Path | None:
    """``py_file``'s folder relative to the folder that holds its top-level package (``bench/models``); None
    where the file is not in a package."""
    folder = Path(py_file).resolve().parent
    top = folder
    while (top.parent / "__init__.py").is_file():
        top = top.parent
    return folder.relative_to(top.parent) if (top / "__init__.py").is_file() else None


# numba's content-stamped cache (0.68 on: an entry is used only where its source file hashes the same) with the
# locator class numba then has; with an older numba the kernels keep numba's own locator
_Locator = getattr(caching, "UserProvidedCacheLocator", None)
_CONTENT_STAMPED = hasattr(caching, "_hash_source_file")

if _Locator is not None and _CONTENT_STAMPED:
    class _PackageLocator(_Locator):  # type: ignore[misc, valid-type]
        """numba's locator for ``config.CACHE_DIR``, the entry named by the file's place in its package."""

        def __init__(self, py_func: Any, py_file: str) -> None:
            super().__init__(py_func, py_file)
            folder = _package_folder(py_file)
            assert folder is not None  # from_function returns None first
            self._cache_path = os.path.join(numba.config.CACHE_DIR, *folder.parts)  # type: ignore[attr-defined]

        @classmethod
        def from_function(cls, py_func: Any, py_file: str) -> Any:
            if not numba.config.CACHE_DIR or _package_folder(py_file) is None:  # type: ignore[attr-defined]
                return None
            return super().from_function(py_func, py_file)

    class _PackageCacheImpl(caching.CompileResultCacheImpl):
        _locator_classes = [_PackageLocator]  # noqa: RUF012  (numba's own class attribute)

    class _PackageFunctionCache(caching.FunctionCache):
        _impl_class = _PackageCacheImpl

    _PackageCache: Any = _PackageFunctionCache
else:
    _PackageCache = None
