"""The CPU a benchmark row names (bench/benchmarks/machine.py), read from /proc/cpuinfo texts written here."""

from __future__ import annotations

from bench.benchmarks.machine import parse_cpuinfo

# two processors of a made-up x86 machine without AVX-512 (the format of Linux's /proc/cpuinfo)
X86 = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Example Xeon CPU @ 2.00GHz
flags\t\t: fpu vme sse sse2 ssse3 fma sse4_1 sse4_2 avx f16c avx2 bmi2
bogomips\t: 4000.00

processor\t: 1
model name\t: Example Xeon CPU @ 2.00GHz
flags\t\t: fpu vme sse sse2 ssse3 fma sse4_1 sse4_2 avx f16c avx2 bmi2
"""
ARM = """processor\t: 0
BogoMIPS\t: 50.00
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics sve
CPU implementer\t: 0x41
"""


def test_model_and_the_simd_flags_of_the_first_processor() -> None:
    model, flags = parse_cpuinfo(X86)
    assert model == "Example Xeon CPU @ 2.00GHz"
    assert flags == ("sse4_2", "avx", "avx2", "fma")  # no avx512*
    assert parse_cpuinfo(ARM) == ("", ("asimd", "sve"))  # no model name line on ARM: the caller names the platform
