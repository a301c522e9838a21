"""Identification problems built from run files (analysis reads files only).

* :class:`MembraneProblem` — thesis model, 14 parameters: μ, J of unit 0 and μ, J, τ of units 1–4. Bounds:
  thesis Tables 4.2–4.3 read as physics.md §1.3 explains (μ 0.01…500 kPa; τ = η/μ 1e-5…20 s, searched on a log
  scale; J0 100…400), except that units 1–4 share one J range, 200…800, the union of the thesis's per-unit
  ranges (200…500, 300…600, 400…700, 500…800): the fit numbers units by relaxation time, the thesis did not
  (its unit 3 is the fastest), so a per-position range would exclude a unit's J once it is renumbered, and the
  search sorts each candidate's units by τ, which needs the same box for all four. Data: the laser displacement
  u(t) of one or more runs; inputs: the voltages (zero-order hold) and temperatures. Where the voltage is the
  amplifier's *measured* monitor (a hardware-timed rig), two more parameters: the monitor's calibration, ``V_gain``
  (relative) and ``V_offset`` [V] — the monitor reads (1 + V_gain)·V + V_offset of the output V —, bounded by
  the monitor's DC accuracy (± accuracy on the gain, ± accuracy × full scale on the offset; a box around the
  datasheet's ``|error| ≤ accuracy × full scale``). The records are precise enough (laser noise ~1e-4 of the
  stroke) that a monitor error within its datasheet shifts the moduli well outside the noise's intervals: it
  is fitted and profiled like the specimen's parameters, so the intervals hold it.
* :class:`LozengeProblem` — LS-DEA material: Gent–Gent μ, Jm, C2, K Maxwell branches (μ_k, τ_k) and the
  lumped damper c. Data: the load-cell force of motor / blocked runs (aperture from the encoder imposed on
  the model) or the laser aperture of hung-mass runs; one record per stretch of constant prototype and mass.
  On a measured voltage, the same two calibration parameters follow the material's.

A measured voltage drives the model step its samples end (:mod:`bench.identify.monitor`); the membrane's is smoothed
over 1 ms.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench.analysis.applied import applied_voltage
from bench.identify import floors
from bench.identify.core import Cost, noise_of, sigma_of, to_optimiser, to_physical
from bench.identify.monitor import CALIBRATION as CALIBRATION  # the problems' parameter names, as before
from bench.identify.monitor import MonitorCalibration, voltage_per_step
from bench.identify.record_costs import record_costs, total
from bench.models.integrate import MODEL_MEMBRANE, OBSERVE_FORCE, run_fixed_batch, run_fixed_batch_calibrated
from bench.models.lozenge import MODE_HUNG, MODE_IMPOSED, PROTOTYPE_LAMBDA2P, LozengeParams, MaxwellBranch
from bench.models.lozenge_batch import lozenge_batch
from bench.models.membrane import MembraneParams
from bench.models.membrane_batch import membrane_batch_records
from bench.storage.runfile import RunFile, open_run, refuse_nonfinite

if TYPE_CHECKING:
    from distributed import Client

    from bench.identify.distributed import DistributedPredict

J_BOUNDS = ((100.0, 400.0), (200.0, 500.0), (300.0, 600.0), (400.0, 700.0), (500.0, 800.0))  # thesis, per unit
# units 1–4 (interchangeable, numbered by τ): one range, the union of the thesis's (module docstring)
UNIT_J_BOUNDS = (min(b[0] for b in J_BOUNDS[1:]), max(b[1] for b in J_BOUNDS[1:]))
SAME_INSTANT_S = 1e-9  # times closer than this are one instant (a model step's end k·h and a stamp, both rounded)


def _sampled(t_grid: np.ndarray, t_data: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The record on the comparison grid: interpolated where a sample lies within a tenth of the grid spacing,
    NaN elsewhere (between sparse samples, e.g. 10-Hz polling during rests, interpolation would invent data)."""
    if t_data.size < 2:
        return np.full(t_grid.size, np.nan)
    out: np.ndarray = np.interp(t_grid, t_data, values, left=np.nan, right=np.nan)
    spacing = float(t_grid[1] - t_grid[0]) if t_grid.size > 1 else np.inf
    j = np.clip(np.searchsorted(t_data, t_grid), 1, t_data.size - 1)
    gap = np.minimum(np.abs(t_grid - t_data[j - 1]), np.abs(t_data[j] - t_grid))
    out[gap > 0.1 * spacing] = np.nan
    return out


def arriving_velocity(t: np.ndarray, t_samples: np.ndarray, x_samples: np.ndarray) -> np.ndarray:
    """The velocity at each time ``t`` of the path through the position samples (straight between them, as
    ``np.interp`` joins them): the slope of the sample interval (s_{j−1}, s_j] that holds t — at a sample, the
    interval that ends there, the motion up to it; 0 outside the samples (``np.interp`` holds the end values).

    Not ``np.gradient`` of the interpolated path: at a sample that averages the slope after it in, the motion of a
    go-to the host sends at that sample's tick, which the carriage (and the load cell read at the same tick) has
    not yet seen. The LinMot cruises at constant speed between the 100-Hz go-tos (each one's change of speed takes
    ≤ 0.25 ms at the rig's acceleration); on a software-timed rig in virtual time the position and force polls share
    the go-to's tick, so every force sample sat on a change of speed and the damper saw half of the next one —
    ~x″·5 ms, up to 2.5 mm/s (1.4 mm/s rms) on the short isopotential run —, which put c, τb, μb and Jm 2.4–4.1 σ
    off the twin's and their intervals just past it (``tests/test_identify_lsdea_input.py``). Where the speed
    changes between samples (the poll a few ms after the go-to, as on the DAQ rig or in a wall-clock run),
    neither slope is the carriage's near that change; the two agree everywhere else."""
    out = np.zeros(t.size)
    if t_samples.size < 2:
        return out
    at = t - SAME_INSTANT_S  # a step time a rounding off a sample's (k·h against the stamp) is at the sample
    j = np.clip(np.searchsorted(t_samples, at, side="left"), 1, t_samples.size - 1)
    dt = t_samples[j] - t_samples[j - 1]
    inside = (at > t_samples[0]) & (at <= t_samples[-1]) & (dt > 0)
    out[inside] = (x_samples[j] - x_samples[j - 1])[inside] / dt[inside]
    return out


def _window_means(t_grid: np.ndarray, t_data: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Means of the record over (t − Δ, t] for each grid time t (Δ: grid spacing), NaN where the window is not
    densely covered (fewer than 5 samples or spanning less than 80 % of it); the first point is the sample at
    t_grid[0]."""
    out = np.full(t_grid.size, np.nan)
    if t_data.size == 0 or t_grid.size < 2:
        return out
    width = float(t_grid[1] - t_grid[0])
    c = np.concatenate([[0.0], np.cumsum(values)])
    hi = np.searchsorted(t_data, t_grid + 1e-9, side="right")
    lo = np.searchsorted(t_data, t_grid - width + 1e-9, side="right")
    count = hi - lo
    ok = count >= 5
    span = np.zeros(t_grid.size)
    span[ok] = t_data[hi[ok] - 1] - t_data[lo[ok]]
    ok &= span >= 0.8 * width - 1e-9
    out[ok] = (c[hi[ok]] - c[lo[ok]]) / count[ok]
    out[0] = _sampled(t_grid[:2], t_data, values)[0]
    return out


def _record_windows(t_set: np.ndarray, v_set: np.ndarray, t_end: float, split_rest: float,
                    keep_rest: float) -> list[tuple[float, float]]:
    """Time windows (a, b) of a file's records: cut at every rest of ≥ split_rest s (the record before keeps
    keep_rest s of it, the next starts where the drive resumes); the whole file when there is none. A rest is
    a set-point below 1 % of the file's peak (the DAC's zero is a count or two: 2.4 V on the thesis rig)."""
    if split_rest <= 0 or len(v_set) == 0:
        return [(0.0, t_end)]
    quiet = np.abs(np.asarray(v_set)) <= 0.01 * float(np.max(np.abs(v_set)))
    # runs of quiet set-points: from the first quiet one to the next non-quiet one (vectorised: a 10-kHz
    # commanded trace has millions of rows)
    edges = np.diff(np.concatenate([[0], quiet.astype(np.int8), [0]]))
    begins, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    t_arr = np.asarray(t_set, dtype=float)
    rests = [(float(t_arr[b]), float(t_arr[e]) if e < t_arr.size else t_end)
             for b, e in zip(begins.tolist(), ends.tolist(), strict=True)]
    windows, a = [], 0.0
    for r0, r1 in rests:
        if r1 - r0 >= split_rest and r0 > a:
            windows.append((a, min(r0 + keep_rest, r1)))
            a = r1
    if t_end > a:
        windows.append((a, t_end))
    return windows


def _noise_model(records: list[_Record]) -> tuple[np.ndarray, list[float]]:
    """σ per data point — each record's, the larger of its own estimate (:func:`noise_of`, its high-frequency
    content) and its instrument's datasheet floor (:mod:`bench.identify.floors`) — and the floors per record."""
    sigma = np.concatenate([np.full(r.data.size, max(noise_of(r.data), r.floor)) for r in records])
    return sigma, [r.floor for r in records]


@dataclass
class _Record:
    U: np.ndarray  # inputs per step
    y0: np.ndarray
    template: np.ndarray  # packed parameters of the record (geometry, mode) before the fitted values
    stride: int
    data: np.ndarray
    source: str
    measured: bool = False  # the voltage input is the amplifier's monitor (its calibration applies)
    floor: float = 0.0  # the datasheet's noise σ of a data point (bench.identify.floors); 0: no figure


class MembraneProblem(MonitorCalibration):
    """Thesis membrane identification from laser records."""

    def __init__(self, paths: list[str | Path], h: float = 5e-4, data_rate: float = 100.0,
                 average: bool = True, reference_kernel: bool = False, split_rest: float = 30.0,
                 keep_rest: float = 20.0, input_smoothing_s: float = 1e-3) -> None:
        """``average``: compare 1/data_rate window means of record and model (removes the aliasing of
        fast ringing); otherwise point values at the record's sample times. ``reference_kernel``: predict
        through the scalar per-candidate kernel (the benchmark's old path) instead of the vectorised one.

        A file is cut into records at every rest (0 V) of at least ``split_rest`` s: each record starts from
        the rest state where the drive resumes (the protocols' long rests are there for the specimen to
        recover) and keeps the first ``keep_rest`` s of the rest that ends it (``split_rest`` 0: whole files).

        A *measured* voltage (the monitor) carries the monitor's noise, which the specimen never saw: fed to the
        model as it is, it drives a pressure noise (∝ 2VδV) that the fit then damps with a spurious fast unit. It
        is smoothed by a zero-phase Gaussian of σ ``input_smoothing_s`` (1 ms: −3 dB near 130 Hz, far above the
        drives' content; the white noise's power / 35); 0 leaves it as recorded.
        """
        self.h, self.data_rate, self.average = h, data_rate, average
        self.records: list[_Record] = []
        self.reference_kernel = reference_kernel
        self.split_rest, self.keep_rest = split_rest, keep_rest
        self.input_smoothing_s = input_smoothing_s
        self.remote: DistributedPredict | None = None
        self.data_unit = "m"
        self.names = ["mu0", "J0"] + [f"mu{i}" for i in range(1, 5)] + [f"J{i}" for i in range(1, 5)] + \
            [f"tau{i}" for i in range(1, 5)]
        self.units = ["Pa", "-"] + ["Pa"] * 4 + ["-"] * 4 + ["s"] * 4
        self.lower = np.array([10.0, J_BOUNDS[0][0]] + [10.0] * 4 + [UNIT_J_BOUNDS[0]] * 4 + [-5.0] * 4)
        self.upper = np.array([500e3, J_BOUNDS[0][1]] + [500e3] * 4 + [UNIT_J_BOUNDS[1]] * 4 + [np.log10(20.0)] * 4)
        self.log = np.array([False] * 10 + [True] * 4)
        self.template: MembraneParams | None = None
        for path in paths:
            self._add(open_run(path), str(path))
        if not self.records:
            raise ValueError("no membrane records with laser data in the given run files")
        self._add_calibration()
        self.data = np.concatenate([r.data for r in self.records])
        self.sigma, self.noise_datasheet = _noise_model(self.records)
        # Maxwell units 1–4 are interchangeable (μ_i, J_i, τ_i; τ last): the fit numbers them by τ
        self.unit_groups = [[1 + i, 5 + i, 9 + i] for i in range(1, 5)]

    def _add(self, run: RunFile, source: str) -> None:
        spec = run.specimen(model=True)
        if spec["kind"] != "membrane" or "laser" not in run.streams:
            raise ValueError(f"run file {source}: not a membrane run with laser data")
        model = spec["model"]
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in model.items()}  # JSON
        params = MembraneParams(**fields)
        self.template = self.template or params
        stride = max(1, round(1.0 / (self.data_rate * self.h)))
        sp = applied_voltage(run, measured=True)
        laser = run.streams["laser"]
        ok = laser.columns["valid"] > 0
        refuse_nonfinite(run.path, "laser", "displacement", laser.t[ok], laser.columns["displacement"][ok])
        sample = _window_means if self.average else _sampled
        head = floors.laser_noise_m(floors.stored_rig(run))
        windows = _record_windows(sp.t, sp.v, run.updated, self.split_rest, self.keep_rest)
        measured = sp.source == "measured"
        self._note_run(run, source, measured)
        for a, b in windows:
            n = int(np.floor((b - a) / self.h + 1e-9))
            n -= n % stride
            if n < 10 * stride:
                continue
            t_steps = a + np.arange(1, n + 1) * self.h
            U = np.empty((n, 2))
            U[:, 0] = voltage_per_step(sp, t_steps, self.h, self.input_smoothing_s)
            U[:, 1] = run.temperature_at(t_steps)  # as the report reads a step's temperature
            t_data = a + np.arange(0, n // stride + 1) * stride * self.h
            data = sample(t_data, laser.t[ok], laser.columns["displacement"][ok])
            floor = (floors.of_window_means if self.average else floors.of_points)(head, t_data, laser.t[ok])
            where = source if len(windows) == 1 else f"{source} [{a:.1f}, {b:.1f}] s"
            self.records.append(_Record(U, params.initial_state(), params.pack(), stride, data, where, measured,
                                        floor))

    @property
    def recorded(self) -> MembraneParams:
        """The specimen model recorded in the first run file read."""
        if self.template is None:
            raise ValueError("no membrane record read: no specimen model")
        return self.template

    def params_of(self, z: np.ndarray) -> MembraneParams:
        """Physical MembraneParams for one optimiser vector."""
        v = to_physical(self.log, z)
        mu, J, tau = tuple(v[2:6]), tuple(v[6:10]), tuple(v[10:14])
        return self.recorded.with_units(float(v[0]), float(v[1]), mu, J,
                                        tuple(m * t for m, t in zip(mu, tau, strict=True)))

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """Displacements u [m] for each row of Z, all records concatenated (one parallel batch per record). Rows of
        the specimen's parameters only (a fit stored before the calibration was fitted) take the input as
        recorded."""
        self.check_stop()
        if self.reference_kernel:
            return self.predict_reference(Z)
        Z = np.atleast_2d(Z)
        P = np.stack([self.params_of(z).pack() for z in Z])
        cal = self.calibration(Z)
        t = self.recorded
        if self.remote is not None:
            return t.L_d * (self.remote(P, cal) - t.lambda_pre)
        lam = membrane_batch_records(P, np.stack([r.y0 for r in self.records]), [r.U for r in self.records],
                                     self.h, self.records[0].stride, self.records[0].stride if self.average else 0,
                                     cal)
        return t.L_d * (lam - t.lambda_pre)

    def distribute(self, client: Client | None) -> None:
        """Evaluate candidates on a dask cluster from now on (None: in-process again)."""
        if client is None:
            self.remote = None
            return
        from bench.identify.distributed import DistributedPredict

        stride = self.records[0].stride
        data, sigma = zip(*self._targets(), strict=True)
        self.remote = DistributedPredict(client, [r.U for r in self.records], np.stack([r.y0 for r in self.records]),
                                         self.h, stride, stride if self.average else 0, self.recorded.pack(),
                                         list(data), list(sigma))

    def _targets(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each record's data and σ (slices of ``data`` and ``sigma``)."""
        bounds = np.cumsum([0] + [r.data.size for r in self.records])
        sigma = sigma_of(self)
        return [(self.data[a:b], sigma[a:b]) for a, b in itertools.pairwise(bounds.tolist())]

    def costs(self, Z: np.ndarray, kind: Cost) -> np.ndarray:
        """The search's cost of each row of Z (:func:`bench.identify.core._costs`' sum over the compared points of
        |r| or r², r the residual over σ; inf where one is not finite), summed record by record where the
        predictions are made (:mod:`bench.identify.record_costs`): on a cluster, the workers return one number per
        candidate and record. The same bits in-process and distributed, however the batch is cut. The data and σ
        are those when :meth:`distribute` was called."""
        self.check_stop()
        Z = np.atleast_2d(Z)
        if self.remote is not None and not self.reference_kernel:
            P = np.stack([self.params_of(z).pack() for z in Z])
            t = self.recorded
            return total(self.remote.costs(P, self.calibration(Z), t.L_d, t.lambda_pre, kind))
        pred = self.predict(Z)
        parts = np.empty((len(self.records), Z.shape[0]))
        c0 = 0
        for k, (data, sigma) in enumerate(self._targets()):
            parts[k] = record_costs(pred, c0, data, sigma, np.isfinite(data), kind)
            c0 += data.size
        return total(parts)

    def predict_reference(self, Z: np.ndarray) -> np.ndarray:
        """:meth:`predict` through the scalar per-candidate kernel (``run_fixed_batch``): the benchmark's
        reference."""
        Z = np.atleast_2d(Z)
        out = []
        P = np.stack([self.params_of(z).pack() for z in Z])
        cal = self.calibration(Z)
        t = self.recorded
        for i, rec in enumerate(self.records):
            window = rec.stride if self.average else 0
            if cal is None or not rec.measured:
                lam = run_fixed_batch(MODEL_MEMBRANE, np.tile(rec.y0, (Z.shape[0], 1)), rec.U, self.h, P, 0,
                                      rec.stride, window)
            else:  # the calibration changes the input per candidate, still in parallel over the candidates
                lam = run_fixed_batch_calibrated(MODEL_MEMBRANE, np.tile(rec.y0, (Z.shape[0], 1)), rec.U, self.h, P,
                                                 np.ascontiguousarray(cal[i]), 0, rec.stride, window)
            out.append(t.L_d * (lam - t.lambda_pre))
        return np.concatenate(out, axis=1)

    def reference(self) -> dict[str, float]:
        """Physical values of the specimen model recorded in the (first) run file, by parameter name."""
        t = self.recorded
        return dict(zip(self.names[:self.n_model], (float(x) for x in (t.mu0, t.J0, *t.mu, *t.J, *t.tau)),
                        strict=True))

    def start(self) -> np.ndarray:
        """Optimiser vector of the recorded specimen's parameters (thesis Table 4.4 unless the run says otherwise),
        the monitor's calibration at its nominal (no error)."""
        model = to_optimiser(self.log[:self.n_model], np.array(list(self.reference().values())))
        start: np.ndarray = np.clip(self._with_nominal_calibration(model), self.lower, self.upper)
        return start


class LozengeProblem(MonitorCalibration):
    """LS-DEA material identification from load-cell or laser records."""

    def __init__(self, paths: list[str | Path], branches: int = 1, h: float = 1e-3, data_rate: float = 50.0,
                 input_smoothing_s: float = 0.0) -> None:
        """``input_smoothing_s``: σ of a zero-phase Gaussian over a measured voltage
        (:func:`bench.identify.monitor.voltage_per_step`); 0, the default: as recorded. Unlike the membrane's, the
        LS-DEA's response hardly sees the monitor's noise (the force goes through the mass and the load cell),
        while a Gaussian of σ attenuates a drive of frequency f by (2πfσ)²/2 — 1.5e-4 at 2.75 Hz for 1 ms, 2e-3
        at 10 Hz, twice that in the force ∝ V² —, a bias the laser of a hung-mass record resolves."""
        self.h, self.data_rate, self.K = h, data_rate, branches
        self.input_smoothing_s = input_smoothing_s
        self.names = ["mu", "Jm", "C2"] + [f"mu_b{k + 1}" for k in range(branches)] + \
            [f"tau_b{k + 1}" for k in range(branches)] + ["c"]
        self.units = ["Pa", "-", "Pa"] + ["Pa"] * branches + ["s"] * branches + ["N·s/m"]
        self.lower = np.array([50e3, 5.0, 0.0] + [3.0] * branches + [-2.0] * branches + [0.0])
        self.upper = np.array([1e6, 100.0, 500e3] + [6.0] * branches + [2.0] * branches + [5.0])
        self.log = np.array([False] * 3 + [True] * (2 * branches) + [False])
        self.records: list[_Record] = []
        self.base: LozengeParams | None = None
        for path in paths:
            self._add(open_run(path), str(path))
        if not self.records:
            raise ValueError("no LS-DEA records in the given run files")
        self._add_calibration()
        self.data = np.concatenate([r.data for r in self.records])
        self.sigma, self.noise_datasheet = _noise_model(self.records)
        # the Maxwell branches are interchangeable (μ_b, τ_b; τ last): the fit numbers them by τ
        self.unit_groups = [[3 + k, 3 + branches + k] for k in range(branches)]
        hung = {int(r.template[16]) == MODE_HUNG for r in self.records}  # Q_MODE
        self.data_unit = "m" if hung == {True} else "N" if hung == {False} else "N and m"

    def point_units(self) -> np.ndarray:
        """The unit of each data point: a hung-mass record's laser in m, a motor record's force in N."""
        return np.concatenate([np.full(r.data.size, "m" if int(r.template[16]) == MODE_HUNG else "N")
                               for r in self.records])

    def _add(self, run: RunFile, source: str) -> None:
        spec = run.specimen(model=True)
        if spec["kind"] != "lsdea":
            raise ValueError(f"run file {source}: not an LS-DEA run")
        lsdea, over = spec["lsdea"], spec.get("overrides", {})
        config = lsdea["configuration"]
        model = spec["model"]
        base = LozengeParams.prototype(int(over.get("prototype") or lsdea["prototype"]),
                                       hung_mass=over.get("hung_mass_kg") if over.get("hung_mass_kg") is not None
                                       else lsdea.get("hung_mass_kg", 0.0))
        base = replace(base, mechanism_mass=model.get("mechanism_mass", base.mechanism_mass))
        self.base = self.base or base
        changes = run.specimen_changes()
        cuts = sorted({0.0, *[t for t, _ in changes], run.updated})
        sp = applied_voltage(run, measured=True)
        measured = sp.source == "measured"
        for stream, column in (("laser", "displacement"), ("motor", "aperture"), ("load_cell", "force")):
            if stream in run.streams:
                got = run.streams[stream]
                refuse_nonfinite(run.path, stream, column, got.t, got.columns[column])
        self._note_run(run, source, measured)
        rig = floors.stored_rig(run)
        stride = max(1, round(1.0 / (self.data_rate * self.h)))
        proto, mass = base.lambda2p, base.hung_mass
        for a, b in itertools.pairwise(cuts):
            for te, values in changes:
                if te <= a + 1e-9:
                    proto = PROTOTYPE_LAMBDA2P[int(values["prototype"])] if "prototype" in values else proto
                    mass = values.get("hung_mass_kg", mass)
            n = int(np.floor((b - a) / self.h))
            n -= n % stride
            if n < 10 * stride:
                continue
            t_steps = a + np.arange(0, n + 1) * self.h
            U = np.zeros((n + 1, 3))
            U[:, 0] = voltage_per_step(sp, t_steps, self.h, self.input_smoothing_s)
            params = replace(base, lambda2p=proto, hung_mass=mass)
            if config == "hung":
                laser = run.streams["laser"]
                ok = laser.columns["valid"] > 0
                x_start = float(np.interp(a, laser.t[ok], laser.columns["displacement"][ok]))
                mode, y0 = MODE_HUNG, params.relaxed_state(x_start)
                data = _sampled(t_steps[::stride], laser.t[ok], laser.columns["displacement"][ok])
                floor = floors.of_points(floors.laser_noise_m(rig), t_steps[::stride], laser.t[ok])
            else:
                motor, lc = run.streams["motor"], run.streams["load_cell"]
                U[:, 1] = np.interp(t_steps, motor.t, motor.columns["aperture"])
                U[:, 2] = arriving_velocity(t_steps, motor.t, motor.columns["aperture"])
                mode, y0 = MODE_IMPOSED, params.relaxed_state(float(U[0, 1]))
                data = _sampled(t_steps[::stride], lc.t, lc.columns["force"])  # "ok" means stable, not valid
                floor = floors.of_points(floors.force_noise_N(rig), t_steps[::stride], lc.t)
            self.records.append(_Record(U[1:], y0, params.pack(mode), stride, data, f"{source} [{a:.1f}, {b:.1f}] s",
                                        measured, floor))
        self._mode_channel = 0 if config == "hung" else OBSERVE_FORCE

    def params_of(self, z: np.ndarray, template: LozengeParams | None = None) -> LozengeParams:
        """Physical LozengeParams for one optimiser vector."""
        v = to_physical(self.log, z)
        K = self.K
        base = template or self.base
        if base is None:
            raise ValueError("no LS-DEA record read: no specimen model")
        material = replace(base.material, mu=float(v[0]), Jm=float(v[1]), C2=float(v[2]))
        branches = tuple(MaxwellBranch(float(v[3 + k]), float(v[3 + K + k])) for k in range(K))
        return replace(base, material=material, branches=branches, damping=float(v[3 + 2 * K]))

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """Forces [N] (motor / blocked) or apertures [m] (hung) for each row of Z, records concatenated. Rows of the
        specimen's parameters only (a fit stored before the calibration was fitted) take the input as recorded."""
        self.check_stop()
        Z = np.atleast_2d(Z)
        cal = self.calibration(Z)
        out = []
        for i, rec in enumerate(self.records):
            mode = int(rec.template[16])  # Q_MODE
            lam2p = float(rec.template[10])  # Q_L2P
            mass = float(rec.template[13])  # Q_MHUNG
            P = np.stack([replace(self.params_of(z), lambda2p=lam2p, hung_mass=mass).pack(mode) for z in Z])
            Y0 = np.tile(rec.y0, (Z.shape[0], 1))
            channel = 0 if mode == MODE_HUNG else OBSERVE_FORCE
            out.append(lozenge_batch(P, Y0, rec.U, self.h, channel, rec.stride, None if cal is None else cal[i]))
        return np.concatenate(out, axis=1)

    def start(self) -> np.ndarray:
        """Optimiser vector of Table 1 + VE-A (the defaults), the monitor's calibration at its nominal (no error)."""
        b = LozengeParams()
        m = b.material
        z = [m.mu, m.Jm, m.C2] + [np.log10(b.branches[0].mu)] * self.K + [np.log10(b.branches[0].tau)] * self.K + \
            [b.damping]
        start: np.ndarray = np.clip(self._with_nominal_calibration(np.array(z, float)), self.lower, self.upper)
        return start


def match_membrane_units(fitted: dict[str, float], reference: dict[str, float]) -> dict[int, int]:
    """Fitted Maxwell unit → reference unit, paired in order of relaxation time τ.

    The membrane model is symmetric under exchanging its Maxwell units, and the fit numbers them by τ while a
    reference (the thesis's Table 4.4) may not; compare units by τ rank, not by number.
    """
    units = range(1, 5)
    by_tau_fit = sorted(units, key=lambda i: fitted[f"tau{i}"])
    by_tau_ref = sorted(units, key=lambda i: reference[f"tau{i}"])
    return dict(zip(by_tau_fit, by_tau_ref, strict=True))
