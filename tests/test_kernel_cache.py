"""The compiled-kernel cache is keyed by all kernel sources (bench.models.jit): numba keys a cached kernel by its own
file only, so a caller whose callee changed in another file would load the old callee's machine code. Here a copy
of the packages is edited the way a `git pull` or an upgrade edits it, and the cache a fresh interpreter uses is
read back from numba itself."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT

PROBE = """
import numba, numpy as np
from bench.core.one_pole import one_pole
one_pole(np.zeros(3), 0.5, 0.0)
print(numba.config.CACHE_DIR)
print(one_pole._cache._cache_path)
"""


def _cache_of(tree: Path, base: Path) -> tuple[Path, Path]:
    res = subprocess.run([sys.executable, "-c", PROBE], cwd=tree, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(base)})
    assert res.returncode == 0, res.stderr
    cache_dir, kernel_dir = res.stdout.split()
    return Path(cache_dir), Path(kernel_dir)


def test_a_change_to_any_kernel_source_starts_a_new_cache_and_nothing_else_does(tmp_path: Path) -> None:
    tree = tmp_path / "tree"
    for package in ("bench", "sim_devices", "drivers"):
        shutil.copytree(ROOT / package, tree / package, ignore=shutil.ignore_patterns("__pycache__"))
    base = tmp_path / "cache"
    first, kernel = _cache_of(tree, base)
    assert first.parent == base and kernel.is_relative_to(first)  # numba caches the kernel there
    assert any(kernel.glob("*.nbi")) and any(kernel.glob("*.nbc"))
    assert _cache_of(tree, base)[0] == first  # same sources: the same cache, loaded again

    cli = tree / "bench" / "cli" / "main.py"  # no kernel in it
    cli.write_text(cli.read_text() + "\n# edited\n")
    assert _cache_of(tree, base)[0] == first

    callee = tree / "bench" / "models" / "lozenge.py"  # kernels of integrate.py call its step
    callee.write_text(callee.read_text().replace("return G > 0.0 and", "return 0.0 < G and"))
    second = _cache_of(tree, base)[0]
    assert second != first and second.parent == base

    twin = tree / "sim_devices" / "t7" / "analog.py"
    twin.write_text(twin.read_text() + "\n# edited\n")
    assert _cache_of(tree, base)[0] not in (first, second)


def test_a_copy_of_the_same_sources_elsewhere_loads_the_kernels_another_compiled(tmp_path: Path) -> None:
    """A checkout at another path (or the installed wheel) of identical sources finds the kernels by their place in
    the package: numba's own locator names an entry by a hash of the source's absolute folder and would compile
    them all again. The copy's kernel is a cache hit, read from numba's dispatcher statistics."""
    probe = PROBE + "print(sum(one_pole.stats.cache_hits.values()), sum(one_pole.stats.cache_misses.values()))\n"
    base = tmp_path / "cache"
    seen = []
    for name in ("first", "second"):
        tree = tmp_path / name / "checkout"
        for package in ("bench", "sim_devices", "drivers"):
            shutil.copytree(ROOT / package, tree / package, ignore=shutil.ignore_patterns("__pycache__"))
        res = subprocess.run([sys.executable, "-c", probe], cwd=tree, capture_output=True, text=True, timeout=120,
                             env={**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(base)})
        assert res.returncode == 0, res.stderr
        seen.append(res.stdout.split())
    (_, first_dir, hits, misses), (_, second_dir, hits2, misses2) = seen
    assert (hits, misses) == ("0", "1")  # compiled and saved
    assert first_dir == second_dir and Path(first_dir).parts[-2:] == ("bench", "core")
    assert (hits2, misses2) == ("1", "0")  # loaded, not compiled


def test_caches_of_other_sources_unused_for_30_days_are_removed_and_the_one_in_use_is_marked(tmp_path: Path) -> None:
    base = tmp_path / "cache"
    old, recent, other = base / ("a" * 16), base / ("b" * 16), base / "not-a-digest"
    for d in (old, recent, other):
        (d / "x").mkdir(parents=True)
    month = 31 * 86400
    for d in (old, other):
        os.utime(d, (d.stat().st_atime - month, d.stat().st_mtime - month))
    os.utime(recent, (recent.stat().st_atime - 20 * 86400, recent.stat().st_mtime - 20 * 86400))
    res = subprocess.run([sys.executable, "-c", "import bench.models.jit as jit; print(jit._CACHE)"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "NUMBA_CACHE_DIR": str(base)})
    assert res.returncode == 0, res.stderr
    used = Path(res.stdout.strip())
    assert used.parent == base and used.is_dir()
    assert not old.exists() and recent.exists() and other.exists()  # only digest-named folders are the bench's
    assert used.stat().st_mtime > recent.stat().st_mtime  # marked as used now


NO_HOME = """
import pwd, sys
def refuse(uid):
    raise KeyError(uid)
pwd.getpwuid = refuse  # a uid without a passwd entry (containers, services): Path.home() fails
import numba, numpy as np
from bench.core.one_pole import one_pole
one_pole(np.zeros(3), 0.5, 0.0)
print(type(one_pole._cache).__name__, getattr(one_pole._cache, "_cache_path", ""))
"""


def _no_home(tmp_path: Path) -> tuple[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("HOME", "XDG_CACHE_HOME", "NUMBA_CACHE_DIR")}
    res = subprocess.run([sys.executable, "-c", NO_HOME], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**env, "TMPDIR": str(tmp_path)})
    assert res.returncode == 0, res.stderr
    kind, _, path = res.stdout.strip().partition(" ")
    return kind, path


def test_without_a_home_the_cache_is_the_users_own_folder_in_the_temporary_directory(tmp_path: Path) -> None:
    kind, path = _no_home(tmp_path)
    own = tmp_path / f"dea-bench-numba-{os.getuid()}"
    assert kind.endswith("FunctionCache") and Path(path).is_relative_to(own)
    assert own.stat().st_mode & 0o777 == 0o700


def test_a_temporary_folder_others_may_write_is_not_used_and_nothing_is_cached(tmp_path: Path) -> None:
    shared = tmp_path / f"dea-bench-numba-{os.getuid()}"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)  # planted, or made by a careless umask: numba would unpickle what others put there
    kind, _ = _no_home(tmp_path)
    assert kind == "NullCache"  # compiled in this process, not cached (and not in the sources' __pycache__)
    assert list(shared.iterdir()) == []


def test_a_changed_numba_variable_does_not_move_the_kernels_cache(tmp_path: Path) -> None:
    """numba re-reads its config from the environment at a compile after any NUMBA_* variable changed; a kernel
    module imported after that still caches in the digest's folder."""
    probe = ("import os, numba, bench.models.jit as jit\n"
             "os.environ['NUMBA_DISABLE_PERFORMANCE_WARNINGS'] = '1'\n"
             "numba.njit(lambda x: x + 1)(1)\n"
             "from bench.identify.record_costs import _partial\n"
             "print(jit.cache_dir())\nprint(_partial._cache._cache_path)\n")
    res = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    assert res.returncode == 0, res.stderr
    folder, kernel = res.stdout.split()
    assert Path(folder).parent == tmp_path and Path(kernel).is_relative_to(folder)


def test_a_temporary_folder_of_ours_that_others_may_only_read_is_used(tmp_path: Path) -> None:
    own = tmp_path / f"dea-bench-numba-{os.getuid()}"
    own.mkdir(mode=0o755)
    own.chmod(0o755)  # as an earlier version made it
    kind, path = _no_home(tmp_path)
    assert kind.endswith("FunctionCache") and Path(path).is_relative_to(own)


def test_a_relative_cache_folder_stays_where_it_was_when_the_process_changes_directory(tmp_path: Path) -> None:
    probe = ("import os, sys, numpy as np, bench.models.jit\n"
             "os.chdir(sys.argv[1])\n"
             "from bench.core.one_pole import one_pole\n"
             "one_pole(np.zeros(2), 0.5, 0.0)\n"
             "print(one_pole._cache._cache_path)\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "NUMBA_CACHE_DIR": "relnc", "PYTHONPATH": str(ROOT)}  # run from another folder
    res = subprocess.run([sys.executable, "-c", probe, str(elsewhere)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, env=env)
    assert res.returncode == 0, res.stderr
    assert Path(res.stdout.strip()).is_relative_to(tmp_path / "relnc")
    assert not (elsewhere / "relnc").exists()
