"""The CPU a benchmark ran on, printed and stored next to its ratios (issue 24: a speed-up measured on one CPU is
that CPU's).

From ``/proc/cpuinfo`` (Linux; elsewhere the platform's processor name and no flags): the model name, the SIMD
flags that decide how wide the compiled kernels' loops run, the logical CPUs this process may use; from numba: its
thread count and the CPU name LLVM compiles for (``znver4``, ``skylake-avx512``, …).
"""

from __future__ import annotations

import os
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

# the flags that set the SIMD width of the compiled kernels (bench/models/membrane_batch.py, vecmath.py)
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512vl", "avx512bw", "asimd", "sve")
CPUINFO = Path("/proc/cpuinfo")


@dataclass(frozen=True)
class Cpu:
    """What a figure was measured on."""

    model: str
    flags: tuple[str, ...]  # of SIMD_FLAGS, those the CPU has, in that order
    logical_cpus: int  # the ones this process may run on
    numba_threads: int
    numba_target: str  # LLVM's name of the host CPU, what numba compiles for

    @property
    def label(self) -> str:
        """One line: model, LLVM target, CPUs and threads, SIMD flags."""
        return (f"{self.model} ({self.numba_target}), {self.logical_cpus} logical CPUs, numba {self.numba_threads} "
                f"threads; {' '.join(self.flags) or 'no SIMD flags read'}")

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {**asdict(self), "flags": list(self.flags)}


def parse_cpuinfo(text: str) -> tuple[str, tuple[str, ...]]:
    """(model name, SIMD flags) of the first processor in a ``/proc/cpuinfo`` text (x86: ``model name`` and
    ``flags``; ARM: ``Features``)."""
    model, flags = "", set[str]()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and not model:
            model = value.strip()
        elif key in ("flags", "Features") and not flags:
            flags = set(value.split())
    return model, tuple(f for f in SIMD_FLAGS if f in flags)


def cpu() -> Cpu:
    """This machine's CPU, as the kernels see it now (numba's current thread count)."""
    import numba
    from llvmlite import binding

    try:
        model, flags = parse_cpuinfo(CPUINFO.read_text(encoding="utf-8", errors="replace"))
    except OSError:
        model, flags = "", ()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return Cpu(model or platform.processor() or platform.machine() or "unknown CPU", flags, usable,
               numba.get_num_threads(), binding.get_host_cpu_name())
