"""Peak memory of ``bench export`` and ``bench report`` against the length of the run (``bench benchmark export``).

A run file with four analog channels at 10 kHz (voltage, current, displacement, force: the papers' rig) is
written through the recorder for two lengths; each export runs in a fresh process whose peak resident memory
(``VmHWM``) is read at its end, next to the same process's peak after the imports alone. Bounded memory means
the two lengths give the same peak: the figure to read is the peak, and the ratio long/short.

The report is measured the same way on a membrane run of 10-s raised-cosine steps at 10 kHz (commanded and
measured voltage, current, displacement): the long file has ten times the steps of the short one. The report reads
a step's window at a time and draws whole-run curves reduced to a screen's width, so its memory follows the
longest step, not the number of steps.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.benchmarks.acquisition import Figure
from bench.storage.recorder import Column, Recorder

RATE_HZ = 10_000.0
BLOCK = 50_000  # samples per append (5 s at 10 kHz)

# VmHWM (the peak resident set of this process image): ru_maxrss on Linux keeps the parent's peak across exec
_HWM = """
import re, sys, time
def hwm():
    with open("/proc/self/status") as fh:
        return int(re.search(r"VmHWM:\\s+(\\d+) kB", fh.read()).group(1))
"""  # each child below: its peak after imports, then after the work, and the work's time
_CHILD = _HWM + """
from bench.storage import export
base = hwm()
t0 = time.perf_counter()
if sys.argv[1] == "csv":
    export.to_csv(sys.argv[2], sys.argv[3])
else:
    export.to_mat(sys.argv[2], sys.argv[3], "7.3")
print(base, hwm(), time.perf_counter() - t0)
"""
_REPORT_CHILD = _HWM + """
from bench.report import report
base = hwm()
t0 = time.perf_counter()
a, paths = report(sys.argv[1], sys.argv[2])
print(base, hwm(), time.perf_counter() - t0, len(a.steps))
"""
STEP_S = 10.0  # length of each step of the report's run [s]


def write_run(path: Path, seconds: float) -> int:
    """A run file of ``seconds`` at 4 × 10 kHz (smooth signals with converter-like noise); returns its scans."""
    streams = {"amplifier": [Column("voltage", "V", ""), Column("current", "A", ""), Column("commanded", "V", "")],
               "laser": [Column("displacement", "m", ""), Column("valid", "1", "", "u1")],
               "load_cell": [Column("force", "N", ""), Column("valid", "1", "", "u1")]}
    rng = np.random.default_rng(0)
    n = int(seconds * RATE_HZ)
    rec = Recorder(path, {"protocol_name": "benchmark-export"}, streams, [], dict.fromkeys(streams, RATE_HZ))
    for a in range(0, n, BLOCK):
        k = np.arange(a, min(a + BLOCK, n))
        t = k / RATE_HZ
        v = 3500.0 * (1 - np.cos(2 * np.pi * t / 9))
        noise = rng.normal(0.0, 1.0, k.size)
        ones = np.ones(k.size, "u1")
        rec.append("amplifier", t, voltage=v + 0.5 * noise, current=1e-4 * np.sin(2 * np.pi * t / 9) + 1e-7 * noise,
                   commanded=v)
        rec.append("laser", t, displacement=1e-3 * v / 7000 + 1e-8 * noise, valid=ones)
        rec.append("load_cell", t, force=0.1 * v / 7000 + 1e-4 * noise, valid=ones)
        rec.maybe_flush()
    rec.finish("completed", "benchmark")
    return n


def _step_toml(k: int) -> str:
    return (f'[[steps]]\ntype = "waveform"\nname = "cycles {k}"\nchannel = "voltage"\nkind = "raised_cosine"\n'
            f'amplitude = "7 kV"\nfrequency_Hz = 1.0\nduration_s = {STEP_S}\n')


def write_report_run(path: Path, steps: int) -> int:
    """A membrane run of ``steps`` raised-cosine steps (1 Hz, 7 kV, ``STEP_S`` each) recorded at 10 kHz as a
    hardware-timed rig records it (the DAQ's command and monitors, the laser), the protocol stored with it and a
    start and end event per step, so that ``bench report`` analyses every step; returns its scans."""
    text = ('[protocol]\nname = "benchmark-report"\nrig = "rigs/thesis-daq-sim.toml"\n\n[specimen]\n'
            'temperature_K = 296.0\n\n' + "\n".join(_step_toml(k) for k in range(steps)))
    program = [(k, f"steps[{k}](cycles {k})", f"cycles {k}", "waveform", k * STEP_S, STEP_S) for k in range(steps)]
    streams = {"setpoints": [Column("voltage", "V", ""), Column("aperture", "m", "")],
               "amplifier": [Column("voltage", "V", ""), Column("current", "A", ""), Column("commanded", "V", "")],
               "laser": [Column("displacement", "m", ""), Column("valid", "1", "", "u1")]}
    attrs = {"protocol_name": "benchmark-report", "protocol_text": text,
             "specimen": {"kind": "membrane", "temperature_K": 296.0}}
    rng = np.random.default_rng(0)
    per_step = int(STEP_S * RATE_HZ)
    rec = Recorder(path, attrs, streams, program, dict.fromkeys(streams, RATE_HZ))
    rec.event(0.0, -1, "run", "start")
    for k in range(steps):
        rec.event(k * STEP_S, k, "start", f"cycles {k} | steps[{k}](cycles {k})")
        for a in range(0, per_step, BLOCK):
            t = (k * per_step + np.arange(a, min(a + BLOCK, per_step))) / RATE_HZ
            v = 3500.0 * (1 - np.cos(2 * np.pi * t))
            noise = rng.normal(0.0, 1.0, t.size)
            rec.append("amplifier", t, voltage=v + 0.5 * noise, current=1e-7 * noise, commanded=v)
            rec.append("laser", t, displacement=1e-3 * (v / 7000) ** 2 + 1e-8 * noise, valid=np.ones(t.size, "u1"))
            rec.maybe_flush()
        rec.event((k + 1) * STEP_S, k, "end", f"cycles {k}")
    rec.append("setpoints", steps * STEP_S, voltage=0.0, aperture=np.nan)  # the host's 0 V at the end
    rec.finish("completed", "benchmark")
    return steps * per_step


def _report(run: Path, out: Path) -> tuple[float, float, float, int]:
    """(MB after imports, peak MB, seconds, steps analysed) of ``bench report`` in a fresh process."""
    proc = subprocess.run([sys.executable, "-c", _REPORT_CHILD, str(run), str(out)], capture_output=True, text=True,
                          check=True)
    base, peak, took, steps = proc.stdout.split()
    return int(base) / 1024, int(peak) / 1024, float(took), int(steps)


def report_figures() -> list[Figure]:
    """Peak memory of ``bench report`` on a membrane run of 6 minutes and on one ten times longer (ten times the
    steps). Full run only: the report's imports and figures take seconds in each process whatever the run's
    length, more than the quick run can spend."""
    counts = (36, 360)
    figures, peaks = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for steps in counts:
            run = Path(tmp) / f"report-{steps}.h5"
            scans = write_report_run(run, steps)
            size = run.stat().st_size / 1e6
            base, peak, took, analysed = _report(run, Path(tmp) / f"report-{steps}")
            peaks.append(peak)
            figures.append(Figure(f"report, {steps * STEP_S / 60:g}-min membrane run ({steps} steps, 4 × 10 kHz), "
                                  "peak memory", peak, "MB",
                                  f"{base:.0f} MB after imports; {scans:,} scans, run file {size:.0f} MB, "
                                  f"{analysed} steps analysed and drawn in {took:.1f} s"))
            run.unlink()
    figures.append(Figure(f"  report peak, {counts[1] * STEP_S / 60:g} min / {counts[0] * STEP_S / 60:g} min",
                          peaks[1] / peaks[0], "×", f"{counts[1] / counts[0]:g}× the data; 1.0: memory independent "
                          "of the length"))
    return figures


def _export(kind: str, run: Path, out: Path) -> tuple[float, float, float]:
    """(MB after imports, peak MB, seconds) of one export in a fresh process."""
    proc = subprocess.run([sys.executable, "-c", _CHILD, kind, str(run), str(out)], capture_output=True, text=True,
                          check=True)
    base, peak, took = proc.stdout.split()
    return int(base) / 1024, int(peak) / 1024, float(took)


def run_all(quick: bool = False) -> list[Figure]:
    """Peak memory of CSV and MAT v7.3 export for a short and a long run file (--quick: 5 and 15 seconds; full:
    10 and 60 minutes), then the report's (full run only)."""
    lengths = (5.0, 15.0) if quick else (600.0, 3600.0)
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        peaks: dict[str, list[float]] = {"csv": [], "mat": []}
        for seconds in lengths:
            run = Path(tmp) / f"run-{seconds:g}.h5"
            t0 = time.perf_counter()
            scans = write_run(run, seconds)
            written = time.perf_counter() - t0
            size = run.stat().st_size / 1e6
            for kind in ("csv", "mat"):
                out = Path(tmp) / (f"csv-{seconds:g}" if kind == "csv" else f"run-{seconds:g}.mat")
                base, peak, took = _export(kind, run, out)
                out_mb = (sum(p.stat().st_size for p in out.iterdir()) if out.is_dir() else out.stat().st_size) / 1e6
                peaks[kind].append(peak)
                figures.append(Figure(f"{'CSV' if kind == 'csv' else 'MAT v7.3'} export, {seconds / 60:g}-min run "
                                      "(4 × 10 kHz), peak memory", peak, "MB",
                                      f"{base:.0f} MB after imports; {scans:,} scans, run file {size:.0f} MB "
                                      f"(written in {written:.0f} s), output {out_mb:.0f} MB in {took:.1f} s"))
                out.unlink() if out.is_file() else None
            run.unlink()
        for kind, (short, long) in peaks.items():
            figures.append(Figure(f"  {'CSV' if kind == 'csv' else 'MAT v7.3'} peak, {lengths[1] / 60:g} min / "
                                  f"{lengths[0] / 60:g} min", long / short, "×",
                                  f"{lengths[1] / lengths[0]:g}× the data; 1.0: memory independent of the length"))
    return figures if quick else figures + report_figures()
