"""Dry run: the compiled program on the physical model alone, before any instrument is touched.

The plant of the simulated rig (same model, same amplifier stage, same motor profiles, same set-point
ticks as the engine) is advanced through the whole program in virtual time, so the dry run states what the
specimen will see: peak voltage, peak true electric field against the stretch-dependent breakdown field,
aperture and motor travel, force, and whether the model predicts a failure (pull-in, breakdown).

The dry run covers the whole program, never only its beginning, so its cost is bounded and stated before it
starts (:func:`check_budget`): the estimated cost (model at 10 kHz, set-point updates, steps; see
:func:`dry_run_cost`) on one core may be at most a fixed fraction of the run's own duration
(``DRY_RUN_FRACTION``: 2 %, 72 s per hour of run), never less than ``DRY_RUN_BUDGET_S`` (30 s) and never more
than ``DRY_RUN_CEILING_S`` (30 min, :func:`dry_run_budget`). An overnight run is dry-run whole (12 h at 20
set-points/s: ~5 min); a protocol beyond the ceiling (a week: ~70 min) is refused in one line that says the
estimate and how long its parts may be (split it into several files) rather than run with a prediction of only
its beginning. Before, a fixed cap of 3600 s of run time refused every protocol over one hour, however cheap its
dry run; the proportional budget keeps the wait before a run a small part of the run itself, and the ceiling
keeps an operator from waiting more than half an hour before anything starts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from bench.core.clock import VirtualClock
from bench.core.monitor_chain import SAFE_TOUCH_V
from bench.core.motion_chain import chain
from bench.core.one_pole import one_pole
from bench.core.plant import Plant, PlantBlock
from bench.numbers import against, mv_per_m
from bench.protocol.link_budget import upload_hold
from bench.protocol.program import Program, ProtocolLimitError, Segment, change_specimen, sample_counts
from bench.protocol.tick_arrays import tick_arrays
from bench.rig import plant_for

STREAM_COLUMNS = {"setpoints": 2, "amplifier": 3, "laser": 2, "motor": 2, "load_cell": 1}
# the dry run's budget (:func:`dry_run_budget`), in estimated seconds of one core: this fraction of the run's own
# duration, at least the floor (the longest shipped campaign: ~17 s estimated, 14 s measured), at most the ceiling
DRY_RUN_FRACTION = 0.02
DRY_RUN_BUDGET_S = 30.0
DRY_RUN_CEILING_S = 1800.0
# costs measured on the reference machine (2 cores, numba kernels): the slowest specimen model (LS-DEA, hung mass)
# advances ~150× faster than real time; one set-point update ~20 µs; one step (segment) 0.2–1 ms (kernel calls)
# ADAM-4017+ (the polled monitors of a software-timed rig): an integrating ADC with 50/60-Hz rejection, each
# conversion the mean of its input over 20 ms (one 50-Hz period: the twin's assumption, sim_devices/modbus_devices.py,
# where the manual gives no window): a charging pulse of well under a ms reads as its charge over 20 ms there, while
# a DAQ's scan reads the monitor's own output
MONITOR_INTEGRATION_S = 0.02
COST_PER_RUN_S = 1 / 150
COST_PER_TICK = 2e-5
COST_PER_SEGMENT = 1e-3
FILTER_SHORTFALL = 0.02  # a DAQ rig's filtered drive reaching less than this share below a step's peak is refused
SNAP_V = 1e-6  # a filtered drive this close to the wanted value [V] is scheduled as that value (_Filter.follow)
SCAN_CHUNK = 1 << 20  # scans of a DAQ-played segment evaluated at once (8 MB per array)


@dataclass
class Prediction:
    """What the dry run predicts for a program."""

    duration: float
    samples: dict[str, int]
    file_bytes: int
    peak_voltage: float = 0.0
    peak_field: float = 0.0
    field_at_min_margin: float = 0.0
    breakdown_at_min_margin: float = np.inf
    min_breakdown_margin: float = np.inf  # min over time of E_B / |E|
    displacement_range: tuple[float, float] = (np.inf, -np.inf)
    force_range: tuple[float, float] = (np.inf, -np.inf)
    motor_range: tuple[float, float] | None = None
    peak_current: float = 0.0  # |current| as the amplifier's current monitor reports it [A]
    peak_current_step: str = ""  # the step in which it came
    failure: str = ""
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # what may trip the run but need not (said, not refused)
    dry_run_estimate_s: float = 0.0  # the dry run's estimated cost on one core (:func:`check_budget`)
    dry_run_budget_s: float = 0.0  # and its budget (:func:`dry_run_budget`)
    dry_run_s: float = 0.0  # what it took here (wall clock)

    @property
    def ok(self) -> bool:
        """No predicted failure and no limit exceeded."""
        return not self.failure and not self.problems


def build_plant(program: Program, clock: VirtualClock, h: float = 1e-4) -> Plant:
    """The rig's plant (the simulated rig's factory) with the protocol's specimen overrides; the membrane
    advances by the error-controlled offline integrator."""
    over = program.protocol.specimen
    return plant_for(program.rig, clock, temperature_K=over.temperature_K, prototype=over.prototype,
                     hung_mass_kg=over.hung_mass_kg, membrane_method="rodas", h=h)


def update_bound(program: Program) -> int:
    """At most this many set-point updates over the whole program (every segment streaming throughout)."""
    dt = 1.0 / program.protocol.recording.setpoint_Hz
    return sum(max(1, math.ceil(s.duration / dt - 1e-9)) for s in program.segments if s.duration > 0)


def dry_run_cost(program: Program) -> tuple[float, float, float]:
    """Estimated seconds of one core the dry run spends on (the model, set-point updates, steps)."""
    return (program.duration * COST_PER_RUN_S, update_bound(program) * COST_PER_TICK,
            len(program.segments) * COST_PER_SEGMENT)


def dry_run_budget(duration: float) -> float:
    """The dry run's budget for a run of ``duration`` seconds: ``DRY_RUN_FRACTION`` of it, at least
    ``DRY_RUN_BUDGET_S``, at most ``DRY_RUN_CEILING_S`` (estimated seconds of one core)."""
    return min(DRY_RUN_CEILING_S, max(DRY_RUN_BUDGET_S, DRY_RUN_FRACTION * duration))


def budget_rule() -> str:
    """The budget rule in words (the summary's and the refusal's)."""
    return (f"{DRY_RUN_FRACTION:.0%} of the run's duration, at least {DRY_RUN_BUDGET_S:.0f} s, at most "
            f"{DRY_RUN_CEILING_S:.0f} s")


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def check_budget(program: Program) -> tuple[float, float]:
    """The dry run's estimated cost and its budget (seconds of one core, :func:`dry_run_budget`); refuse, in one
    line, a program whose estimate is beyond the budget, saying the estimate and how long its parts may be."""
    model, updates, steps = dry_run_cost(program)
    cost, budget = model + updates + steps, dry_run_budget(program.duration)
    if cost > budget:
        field = "recording.setpoint_Hz" if updates >= max(model, steps) else "steps"
        rate = cost / program.duration if program.duration > 0 else math.inf  # about the same in any part
        part = (DRY_RUN_CEILING_S if rate <= DRY_RUN_FRACTION else DRY_RUN_BUDGET_S) / rate  # the longest that fits
        split = f"split the protocol into files of at most ~{_hours(part)} of run time each"
        raise ProtocolLimitError(
            f"protocol file {program.protocol.path}: {field}: the dry run would take ~{cost:.0f} s "
            f"({_hours(cost)}; {program.duration:.0f} s of run time, {update_bound(program):,} set-point updates, "
            f"{len(program.segments):,} steps), beyond its budget of {budget:.0f} s ({budget_rule()}): "
            + (f"lower recording.setpoint_Hz or {split}" if field == "recording.setpoint_Hz" else split))
    return cost, budget


def _apply_ticks(program: Program, seg: Segment, plant: Plant, clock: VirtualClock, gain: float,
                 pred: Prediction | None) -> tuple[float, float]:
    """The set-points of a segment's ticks on the plant, at once: the voltages (unless ``pred`` is None: the DAQ
    plays them) and the go-tos, each planned from the motion in force at its tick — what sending them one by one
    at the clock's time does, the plant advancing (and failing) only at the segment's end. Returns the lowest and
    highest motor target (inf, −inf: none); notes the peak voltage in ``pred``."""
    tab = tick_arrays(program, seg)
    act = np.zeros(tab.t.size, dtype=bool)  # the ticks that change an input (the rest: keep-alives)
    act[tab.motor] = True
    if pred is not None and tab.voltage is not None:
        act[:] = True
    now = np.maximum.accumulate(np.concatenate(([clock.now()], tab.t[act])))[1:]  # the clock at each of them
    at = np.full(tab.t.size, np.nan)
    at[act] = now
    if act.any():
        clock.advance_to(float(now[-1]))
    if pred is not None and tab.voltage is not None and tab.voltage.size:
        pred.peak_voltage = max(pred.peak_voltage, float(np.max(np.abs(tab.voltage))))
        plant.schedule_amplifier_input(now, tab.voltage / gain)
    if not tab.motor.size:
        return np.inf, -np.inf
    times = at[tab.motor]
    plant.add_motions(list(zip(times.tolist(),
                               chain(plant.motion, times, tab.target, tab.velocity, tab.acceleration), strict=True)))
    lo, hi = tab.target[int(np.argmin(tab.target))], tab.target[int(np.argmax(tab.target))]  # the first of equals
    return float(lo), float(hi)


@dataclass
class _Filter:
    """The DAQ rig's reconstruction filter as the engine drives it: its ``alpha`` per scan, the pre-compensation's
    bound [V] (the voltage limit: the engine's may be lower where the field limit binds, which only leaves the
    output further short), the last wanted value and the filter's output at the last scan [V], and the most the
    output reached in the segment under way [V]."""

    alpha: float
    bound: float
    w: float = 0.0
    y: float = 0.0
    peak: float = 0.0

    def follow(self, wanted: np.ndarray) -> np.ndarray:
        """The filter's output on ``wanted``'s pre-compensation as the engine computes it
        (:meth:`~bench.runtime.hardware_timed.HardwareTimed._precompensate`: each input from the previous *wanted*
        value, clipped to ±bound), through the filter (:func:`~bench.core.one_pole.one_pole`): what the amplifier
        is driven with. Where the output is within ``SNAP_V`` of the wanted value it is that value, bit for bit
        (the recursion itself runs on unsnapped): a hold is then one input again, not a geometric tail that differs
        at every scan (:func:`_play_scans` leaves out the scans that repeat the one before)."""
        prev = np.concatenate(([self.w], wanted[:-1]))
        x = np.clip(prev + (wanted - prev) / self.alpha, -self.bound, self.bound)
        out = one_pole(np.ascontiguousarray(x), self.alpha, self.y)
        self.w, self.y, self.peak = float(wanted[-1]), float(out[-1]), max(self.peak, float(np.max(np.abs(out))))
        return np.where(np.abs(out - wanted) <= SNAP_V, wanted, out)


def _play_scans(seg: Segment, plant: Plant, scan_rate: float, gain: float, drive: _Filter | None = None) -> float:
    """Schedule a DAQ-played segment's scans on the plant (its waveform at every scan of the DAQ's clock, ending
    on its target), ``SCAN_CHUNK`` scans at a time, each scan that repeats the one before it (bit for bit) left
    out: the plant holds an input until the next one (:func:`~bench.core.amplifier_dynamics.step_targets`), so
    the model gets the same targets at every step, while a long hold no longer holds every scan in memory (a 1-h
    relax at 10 kHz: 36 M scans, ~1.9 GB before). Returns the peak |voltage|."""
    assert seg.voltage is not None
    n = max(1, round(seg.duration * scan_rate)) + 1
    peak, last = 0.0, None  # the bits of the last input scheduled
    for a in range(0, n, SCAN_CHUNK):
        ts = seg.t_start + np.arange(a, min(a + SCAN_CHUNK, n)) / scan_rate
        vs = np.asarray(seg.voltage(ts), dtype=float)
        if a + ts.size == n:  # the last scan plays the step's end value, as the engine's does (on the scan grid,
            vs[-1] = float(seg.voltage(np.array([seg.t_end]))[0])  # n / scan_rate need not be its duration)
        peak = max(peak, float(np.max(np.abs(vs))))
        inputs = (vs if drive is None else drive.follow(vs)) / gain  # a DAQ's drive filter: what it passes on
        bits = inputs.view(np.int64)
        new = np.empty(bits.size, dtype=bool)
        new[0] = last is None or bits[0] != last
        new[1:] = bits[1:] != bits[:-1]
        last = int(bits[-1])
        if new.any():
            plant.schedule_amplifier_input(ts[new], inputs[new])
    return peak


def _current_remedy(program: Program, label: str, scanned: bool, drive_filter_Hz: float | None) -> str:
    """What takes the charging current of the step ``label`` below the limit, in the protocol's and the rig's own
    words (``scanned``: a DAQ plays the drive): "a slower ramp" was said of a square wave too, which has no ramp to
    set (an outside tester)."""
    seg = next((s for s in program.segments if s.label == label), None)
    kind = seg.kind if seg is not None else ""
    if kind == "waveform":
        slows = ("; or daq.drive_filter_Hz: a reconstruction filter that slows the edges, the engine pre-compensating "
                 f"its lag (this rig's: {drive_filter_Hz:g} Hz)" if drive_filter_Hz is not None else
                 "; or daq.drive_filter_Hz: a reconstruction filter that slows the edges (this rig has none)") \
            if scanned else ""
        return f"a smoother waveform kind (raised_cosine), a lower frequency or a smaller amplitude{slows}"
    if kind == "relax":
        return "a longer ramp_down_s"
    return "a slower ramp"


def predict(program: Program, progress: Callable[[float], None] | None = None) -> Prediction:
    """Run the program on the model; collect peaks, margins and predicted failures. ``progress`` is told the
    fraction of the program's run time simulated so far (0 … 1) after each block the model advances (every 2 s of
    run time at most: a long hold moves the bar too) and after each step.

    Raises ProtocolLimitError (one line) if the program is beyond the dry run's budget (:func:`check_budget`).
    """
    estimate, budget = check_budget(program)
    started = time.perf_counter()
    counts = sample_counts(program)
    nbytes = sum(n * 8 * (1 + STREAM_COLUMNS[k]) for k, n in counts.items())
    pred = Prediction(program.duration, counts, nbytes, dry_run_estimate_s=estimate, dry_run_budget_s=budget)
    clock = VirtualClock()
    plant = build_plant(program, clock)
    gain = plant.hv.gain
    motor_lo, motor_hi = np.inf, -np.inf

    def watch(block: PlantBlock) -> None:
        nonlocal pred
        if progress is not None and program.duration > 0 and block.t.size:
            progress(min(float(block.t[-1]) / program.duration, 1.0))
        if not np.isfinite(block.displacement).any():
            return  # the model stopped (runaway) before this block's first sample: nothing to observe
        e = np.abs(block.field)
        pred.peak_field = max(pred.peak_field, float(np.nanmax(e)))
        if (i_peak := read_current(block)) > pred.peak_current:
            pred.peak_current, pred.peak_current_step = i_peak, label
        with np.errstate(all="ignore"):  # E → 0 or tiny: an infinite margin
            margin = np.where(e > 0, block.breakdown / e, np.inf)
        i = int(np.nanargmin(margin))
        if margin[i] < pred.min_breakdown_margin:
            pred.min_breakdown_margin = float(margin[i])
            pred.field_at_min_margin, pred.breakdown_at_min_margin = float(e[i]), float(block.breakdown[i])
        d, f = block.displacement, block.force
        pred.displacement_range = (min(pred.displacement_range[0], float(np.nanmin(d))),
                                   max(pred.displacement_range[1], float(np.nanmax(d))))
        pred.force_range = (min(pred.force_range[0], float(np.nanmin(f))),
                            max(pred.force_range[1], float(np.nanmax(f))))

    rig = program.rig
    scan_rate = rig.daq.scan_rate_Hz if rig.daq is not None and rig.amplifier is not None \
        and rig.amplifier.drive == "daq" else None
    scanned = scan_rate is not None  # the DAQ plays the amplifier and scans its monitors
    tail: list[np.ndarray] = [np.zeros(0)]  # the last conversion window's current samples (a polled rig)

    def read_current(block: PlantBlock) -> float:
        """The largest |current| the supervisor could read in ``block``: the monitor's own on a DAQ's scan, its
        mean over a conversion window (:data:`MONITOR_INTEGRATION_S`, sliding) on a polled ADAM-4017+."""
        i = np.nan_to_num(np.asarray(block.current, dtype=float))
        if scanned or i.size < 2:
            return float(np.max(np.abs(i))) if i.size else 0.0
        n = max(1, round(MONITOR_INTEGRATION_S / float(block.t[1] - block.t[0])))
        both = np.concatenate([tail[0], i])
        tail[0] = both[-(n - 1):] if n > 1 else np.zeros(0)
        if both.size < n:
            return 0.0
        c = np.concatenate([[0.0], np.cumsum(both)])
        return float(np.max(np.abs(c[n:] - c[:-n]))) / n

    plant.listeners.append(watch)
    fc = rig.daq.drive_filter_Hz if scanned and rig.daq is not None else None
    drive = None if fc is None or scan_rate is None else \
        _Filter(1.0 - math.exp(-2.0 * math.pi * fc / scan_rate),
                min(rig.limits.max_voltage_V, rig.amplifier.max_voltage_V if rig.amplifier else math.inf))
    # the step the peaks name: the one the plant is advanced through, or where that step changes neither the voltage nor
    # the aperture (a hold), the last one that did — a 1-ms ramp's charging current runs on into the hold after it,
    # and the hold was named (an outside tester)
    label = ""
    for seg in program.segments:
        if not label or seg.voltage is not None or seg.move is not None or seg.position is not None or seg.changes:
            label = seg.label
        if seg.changes:
            change_specimen(plant, seg.changes)
        played = scan_rate is not None and seg.voltage is not None and seg.duration > 0
        if played:  # hardware-timed: the waveform at every scan of the DAQ's clock, ending on its target
            assert scan_rate is not None
            if drive is not None:
                drive.peak = 0.0
            wanted = _play_scans(seg, plant, scan_rate, gain, drive)
            pred.peak_voltage = max(pred.peak_voltage, wanted)
            if drive is not None and wanted > SAFE_TOUCH_V and drive.peak < (1 - FILTER_SHORTFALL) * wanted:
                pred.problems.append(  # a rig whose filter could not follow ran "completed" at a third of the
                    # voltage (an outside tester)
                    f"{seg.label}: the amplifier would reach {drive.peak:.0f} V where the waveform asks {wanted:.0f} "
                    f"V: daq.drive_filter_Hz {fc:g} Hz is too slow for it (the engine's pre-compensation is held "
                    f"to ±{drive.bound:.0f} V)")
        if not (played and not program.has_motor_axis):
            lo, hi = _apply_ticks(program, seg, plant, clock, gain, None if played else pred)
            motor_lo, motor_hi = min(motor_lo, lo), max(motor_hi, hi)
        clock.advance_to(seg.t_end)
        plant.advance_to(seg.t_end)
        if progress is not None:
            progress(seg.t_end / program.duration if program.duration > 0 else 1.0)
        if plant.broken:
            pred.failure = f"{seg.label}: model predicts {plant.failure}"
            break
    pred.dry_run_s = time.perf_counter() - started
    if program.has_motor_axis:
        pred.motor_range = (float(motor_lo), float(motor_hi)) if motor_lo <= motor_hi else None
    limits = program.rig.limits
    if limits.max_field_V_per_m is not None and pred.peak_field > limits.max_field_V_per_m:
        field_text, limit_text = against(pred.peak_field, limits.max_field_V_per_m, 1e-6)
        pred.problems.append(f"peak true field {field_text} MV/m exceeds limits.max_field_V_per_m {limit_text} MV/m")
    if pred.min_breakdown_margin < limits.breakdown_margin:
        pred.problems.append(f"true field {mv_per_m(pred.field_at_min_margin)} MV/m against a breakdown field of "
                             f"{mv_per_m(pred.breakdown_at_min_margin)} MV/m: margin {pred.min_breakdown_margin:.2f} "
                             f"below limits.breakdown_margin {limits.breakdown_margin:g}")
    if program.rig.amplifier is not None and pred.peak_current > limits.max_current_A:
        # the supervisor trips on the monitor's reading: a set-point step charges (or discharges) the film at the
        # amplifier's current limit for well under a ms; a DAQ rig's scan sees every such pulse (refused), a polled
        # monitor only as its charge over a 20-ms conversion, and only when a conversion's window holds it (said)
        current_text, limit_text = against(pred.peak_current, limits.max_current_A, 1e3)
        text = (f"{pred.peak_current_step}: current {current_text} mA (as the current monitor "
                f"{'reports it' if scanned else 'reads over a 20-ms conversion'}) beyond limits.max_current_A "
                f"{limit_text} mA, a voltage step too steep for the film's capacitance")
        remedy = _current_remedy(program, pred.peak_current_step, scanned, fc)
        if scanned:
            pred.problems.append(text + f" (the DAQ's monitor scan would trip the run: {remedy})")
        else:
            pred.warnings.append(text + f": a monitor poll that lands on the pulse trips the run ({remedy}, or "
                                 "more set-points, avoid it)")
    if (held := upload_hold(program, SAFE_TOUCH_V)) is not None:
        pred.warnings.append(held)
    peak_force = max(abs(pred.force_range[0]), abs(pred.force_range[1]))
    if np.isfinite(peak_force) and peak_force > limits.max_force_N:
        force_text, limit_text = against(peak_force, limits.max_force_N)
        pred.problems.append(f"force {force_text} N exceeds limits.max_force_N {limit_text} N")
    return pred
