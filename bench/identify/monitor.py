"""The voltage input of an identification problem on a *measured* drive, shared by the membrane and LS-DEA problems.

On a hardware-timed rig the model's voltage input is the amplifier's monitor, sampled on the DAQ's scan clock. Three
things set it apart from a command:

* **alignment** (:func:`step_means`): a monitor sample at t reads the output up to t, so it drives the model step
  that ends at t (a command set at t holds from the step after);
* **noise** (:func:`voltage_per_step`): the monitor's noise, which the specimen never saw, is smoothed by a
  zero-phase Gaussian before it drives the model;
* **calibration** (:class:`MonitorCalibration`): the monitor reads (1 + ``V_gain``)·V + ``V_offset`` of the output
  V; both are fitted within the monitor's datasheet DC accuracy (± accuracy on the gain, ± accuracy × full scale
  on the offset), and the model sees (U − ``V_offset``)/(1 + ``V_gain``) of a reading U.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from bench.analysis.applied import VoltageTrace
from bench.storage.runfile import RunFile

CALIBRATION = ["V_gain", "V_offset"]  # the voltage monitor's calibration (fits on a measured input)


def hold(t_set: np.ndarray, v_set: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Zero-order hold: the value set at or before each time (the step ending at a set time sees the old one)."""
    i = np.searchsorted(t_set, t - 1e-9, side="left") - 1
    held: np.ndarray = np.where(i >= 0, v_set[np.clip(i, 0, None)], 0.0)
    return held


def step_means(t_samples: np.ndarray, values: np.ndarray, t_steps: np.ndarray, h: float) -> np.ndarray:
    """A *sampled* input per model step: the mean of the samples in the step (t − h, t] — a sample at t reads what
    the output was up to t, so it belongs to the step that ends there, not (as a command set at t) to the next
    one —; a step without a sample holds the last sample before it (0 before the first)."""
    c = np.concatenate([[0.0], np.cumsum(values)])
    hi = np.searchsorted(t_samples, t_steps + 1e-9, side="right")
    lo = np.searchsorted(t_samples, t_steps - h + 1e-9, side="right")
    count = hi - lo
    held = np.where(hi > 0, values[np.clip(hi - 1, 0, None)], 0.0)
    means: np.ndarray = np.where(count > 0, (c[hi] - c[lo]) / np.maximum(count, 1), held)
    return means


def voltage_per_step(sp: VoltageTrace, t_steps: np.ndarray, h: float, smoothing_s: float) -> np.ndarray:
    """The voltage input of the model steps ending at ``t_steps``: a command held from when it was set; a measured
    voltage (``sp.source`` "measured") as :func:`step_means`, smoothed by a zero-phase Gaussian of σ
    ``smoothing_s`` (0: as recorded) — the monitor's noise fed to the model drives a response the specimen never
    had (1 ms: −3 dB near 130 Hz, far above the drives' content)."""
    if sp.source != "measured":
        return hold(sp.t, sp.v, t_steps)
    v = step_means(sp.t, sp.v, t_steps, h)
    if smoothing_s > 0:
        from scipy.ndimage import gaussian_filter1d

        v = gaussian_filter1d(v, smoothing_s / h, mode="nearest")
    return v


def monitor_accuracy(run: RunFile) -> tuple[float, float]:
    """(DC accuracy as a fraction of full scale, full scale [V]) of the voltage monitor of the run's amplifier
    (the rig file stored in the run; the model's datasheet figures, :data:`bench.core.noise.TREK_DYNAMICS`)."""
    from bench.core.noise import TREK_DYNAMICS
    from bench.identify.floors import stored_rig
    from bench.rig import amplifier_spec

    rig = stored_rig(run)
    if rig is None:
        raise ValueError(f"run file {run.path}: its recorded rig cannot be read (none stored)")
    spec = amplifier_spec(rig)
    return TREK_DYNAMICS[spec.model].vmon_accuracy, float(spec.max_output)


class _Measured(Protocol):
    measured: bool  # the record's voltage input is the monitor's (its calibration applies)


class Stopped(Exception):  # noqa: N818  # a stop asked for, not an error
    """A fit's evaluation refused because the fit is being stopped (:meth:`MonitorCalibration.check_stop`)."""


class MonitorCalibration:
    """The voltage monitor's calibration as two more parameters of a problem (mixed into the problem classes).

    The problem reads its runs through :meth:`_note_run` (the rig, and the monitor's accuracy on a measured
    input), then, with its own parameters named, calls :meth:`_add_calibration`: ``n_model`` counts the specimen's
    parameters, the calibration's follow where a record's input is measured."""

    names: list[str]
    units: list[str]
    lower: np.ndarray
    upper: np.ndarray
    log: np.ndarray
    n_model: int
    records: Sequence[_Measured]
    accuracy: tuple[float, float] | None = None  # the voltage monitor's (accuracy, full scale)
    rig_toml: str = ""  # the rig file stored in the first run
    stop: threading.Event | None = None  # set: the fit is being stopped (Ctrl-C); the next evaluation raises Stopped

    def check_stop(self) -> None:
        """Raise :class:`Stopped` once :attr:`stop` is set: called before each batch of evaluations, so every stage
        of a fit (search, polish, intervals), in whichever thread it runs, ends within one batch."""
        if self.stop is not None and self.stop.is_set():
            raise Stopped("the fit was stopped")

    def _note_run(self, run: RunFile, source: str, measured: bool) -> None:
        """Note a run's rig; on a measured input its monitor's accuracy, which every file fitted together shares."""
        self.rig_toml = self.rig_toml or str(run.attrs.get("rig_toml", ""))  # older files and replays: none
        if not measured:
            return
        acc = monitor_accuracy(run)
        if self.accuracy is not None and self.accuracy != acc:
            raise ValueError(f"run file {source}: its amplifier's voltage monitor differs from the other "
                             "files' (one calibration is fitted): fit them separately")
        self.accuracy = acc

    def _add_calibration(self) -> None:
        """Count the specimen's parameters; append the calibration's where an input is measured."""
        self.n_model = len(self.names)
        if self.accuracy is None:
            return
        acc, full = self.accuracy
        self.names = [*self.names, *CALIBRATION]
        self.units = [*self.units, "-", "V"]
        self.lower = np.concatenate([self.lower, [-acc, -acc * full]])
        self.upper = np.concatenate([self.upper, [acc, acc * full]])
        self.log = np.concatenate([self.log, [False, False]])

    def calibration(self, Z: np.ndarray) -> np.ndarray | None:
        """(records, rows of Z, 2): each record's voltage input correction per row, offset [V] and inverse gain
        (the identity on a set-point input, or where Z has no calibration columns); None: none anywhere."""
        Z = np.atleast_2d(Z)
        measured = [r.measured for r in self.records]
        if Z.shape[1] <= self.n_model or not any(measured):
            return None
        cal = np.empty((len(measured), Z.shape[0], 2))
        cal[:] = (0.0, 1.0)
        for i, m in enumerate(measured):
            if m:
                cal[i, :, 0] = Z[:, self.n_model + 1]
                cal[i, :, 1] = 1.0 / (1.0 + Z[:, self.n_model])
        return cal

    def simulated_calibration(self) -> dict[str, float]:
        """On a simulated rig with noise, the voltage monitor's errors its twin drew from the rig's seed
        (:func:`bench.core.amplifier_dynamics.monitors`), by parameter name; empty on a real rig, without noise or
        without the calibration parameters."""
        from bench.core.amplifier_dynamics import monitors
        from bench.core.noise import TREK_DYNAMICS, Realism
        from bench.rig import amplifier_spec, rig_from_toml

        if not self.rig_toml or CALIBRATION[0] not in self.names:
            return {}
        rig = rig_from_toml(self.rig_toml)
        if not rig.simulated or not rig.simulation.noise or CALIBRATION[0] not in self.names:
            return {}
        spec = amplifier_spec(rig)
        vm, _ = monitors(TREK_DYNAMICS[spec.model], spec.max_output, spec.max_current,
                         Realism(noise=True, seed=rig.simulation.seed))
        return {CALIBRATION[0]: vm.gain_error, CALIBRATION[1]: vm.offset}

    def _with_nominal_calibration(self, model: np.ndarray) -> np.ndarray:
        """An optimiser vector of the specimen's parameters, the monitor's calibration at its nominal (no error)."""
        return np.concatenate([model, np.zeros(len(self.names) - self.n_model)])
