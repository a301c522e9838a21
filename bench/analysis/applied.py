"""The voltage a run applied to the specimen, as the file holds it, whichever way the rig drove the amplifier.

On a software-timed rig (ADAM-4024 set-point module) every voltage the host sent is a row of ``/setpoints``
(a staircase the amplifier holds between writes). On a hardware-timed rig (``amplifier.drive = "daq"``) the DAQ
plays each step's waveform on its scan clock: ``/amplifier/commanded`` holds the output commanded in every scan
(10 kHz), while ``/setpoints`` keeps only what the host set between streamed steps (0 V, holds) and NaN for
motor-only rows. The applied voltage is the two merged in time order.

The amplifier's measured output (``/amplifier/voltage``) is kept apart: it is what the monitor saw, with its
noise and the amplifier's slew, and the papers' analyses compare the response with the command.

:func:`applied_window` gives the same trace over a time window only, read from the file in chunks (a long record
is never held whole); :func:`applied_voltage` takes a run read whole (the fit problems).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.storage.chunks import StreamChunks
from bench.storage.runfile import RunFile, refuse_nonfinite


@dataclass(frozen=True)
class VoltageTrace:
    """Commanded amplifier output: times [s], volts [V], and where it came from (for legends and reports)."""

    t: np.ndarray
    v: np.ndarray
    source: str

    @property
    def hardware_timed(self) -> bool:
        return self.source != "setpoints"


def applied_voltage(run: RunFile, measured: bool = False) -> VoltageTrace:
    """The amplifier output over the whole run (see the module's docstring): commanded, or with ``measured``
    the voltage monitor wherever the rig sampled it on the DAQ's scan clock (what the specimen saw, slew and
    all), the set-points filling the time between streamed steps. On a software-timed rig the monitor is
    polled a few times a second, too sparse to stand for the drive: the set-points are used either way."""
    sp = run.streams["setpoints"]
    refuse_nonfinite(run.path, "setpoints", "voltage", sp.t, sp.columns["voltage"])  # NaN: a motor-only row
    keep = np.isfinite(sp.columns["voltage"])
    t_sp, v_sp = sp.t[keep], sp.columns["voltage"][keep]
    amp = run.streams.get("amplifier")
    if amp is None or "commanded" not in amp.columns or len(amp) == 0:
        return VoltageTrace(t_sp, v_sp, "setpoints")
    column = "voltage" if measured else "commanded"
    refuse_nonfinite(run.path, "amplifier", column, amp.t, amp.columns[column], nan=False)
    t = np.concatenate([t_sp, amp.t])
    v = np.concatenate([v_sp, amp.columns[column]])
    order = np.argsort(t, kind="stable")
    return VoltageTrace(t[order], v[order], "measured" if measured else "commanded")


def hardware_timed(streams: StreamChunks) -> bool:
    """Whether the run's amplifier stream records the DAQ's output in every scan (a ``commanded`` column, not
    empty): the drive was played on the scan clock, not sent as software set-points."""
    return "commanded" in streams.columns.get("amplifier", []) and streams.length["amplifier"] > 0


def applied_window(streams: StreamChunks, t0: float, t1: float, measured: bool = False) -> VoltageTrace:
    """:func:`applied_voltage` over ``t0 ≤ t ≤ t1`` only, with the sample before and the one after each source's
    window: ``np.interp`` of it at any time of the window gives what it gives on the whole run's trace (the
    bracketing samples are the same), and so does its maximum over the window."""
    sp = streams.window("setpoints", t0, t1, ["voltage"], neighbours=True, finite="voltage")
    if not hardware_timed(streams):
        return VoltageTrace(sp["t"], sp["voltage"], "setpoints")
    column = "voltage" if measured else "commanded"
    amp = streams.window("amplifier", t0, t1, [column], neighbours=True)
    refuse_nonfinite(streams.f.filename, "amplifier", column, amp["t"], amp[column], nan=False)
    t = np.concatenate([sp["t"], amp["t"]])
    v = np.concatenate([sp["voltage"], amp[column]])
    order = np.argsort(t, kind="stable")
    return VoltageTrace(t[order], v[order], "measured" if measured else "commanded")
