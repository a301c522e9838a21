"""Use case: identify a model's parameters from recorded runs and store the fit with every file (``bench fit``)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from bench.app import Progress
    from bench.identify.campaign import CampaignReport
    from bench.identify.core import FitResult, FitSettings, Problem, RecordedProblem
    from bench.identify.problems import LozengeProblem, MembraneProblem
    from bench.storage.chunks import StreamChunks


# LS-DEA integration steps [s]: the search's (coarse) and the polish's and intervals' (fine). The scheme is first
# order (bench.models.lozenge.lozenge_step), and the intervals are widened by the optimum's shift from the fine to the
# coarse step, which holds the fine step's own error only when the fine step is well below the coarse one (first
# order: that error is h_fine/(h_coarse - h_fine) of the shift). On the short isotonic twin run a 1-ms fine step's
# optimum was 24x that shift away from the exact model's in mu (13x in Jm) and every start's polish ended in a worse
# optimum (mu +10 %, Jm x2.3) whose intervals excluded the truth; at 0.2 ms (two 10-kHz scans: whole monitor samples
# per step) the error is under 0.6 of the shift for every parameter and the intervals hold the truth, for 2-4x the
# fit's time (0.1 ms: 8x). Tests: tests/test_identify_lsdea_monitor.py.
LSDEA_SEARCH_STEP = 2e-3
LSDEA_FINE_STEP = 2e-4


@dataclass
class Fitted:
    """A fit: the result, the (coarse) problem it was searched on (it holds the compared data), the campaign's
    identifiability when several records were fitted, where it was stored, the rig file exported."""

    model: str
    runs: list[Path]
    result: FitResult
    problem: Problem
    campaign: CampaignReport | None = None
    stored: list[tuple[Path, str]] = field(default_factory=list)  # (file, group)
    exported: Path | None = None


def model_of_runs(runs: list[Path], asked: str = "auto") -> str:
    """The model to fit: ``asked`` ("membrane", "lsdea"), or with "auto" the specimen kind the run files share
    (ValueError when they hold different ones)."""
    from bench.storage.runfile import open_run, refuse_manual_session

    files = [open_run(p, streams=False) for p in runs]
    for f in files:  # its readings follow commands typed, not a protocol's drive: nothing to fit them against
        refuse_manual_session(f, "no protocol drive to fit against (fit the files of `bench run`)")
    kinds = {f.specimen()["kind"] for f in files}
    chosen = asked if asked != "auto" else (kinds.pop() if len(kinds) == 1 else "")
    if not chosen:
        raise ValueError("the run files hold different specimens: fit them separately or pass --model")
    return str(chosen)


# what a campaign's records may differ in (bench.identify.campaign: each record keeps its own conditions, the LS-DEA's
# prototype and hung mass among them; the rest of ``lsdea`` is how it is mounted on its rig, which the rig's name
# already tells), and the specimen's starting model (derived from the rest of the attribute): any other difference
# of the ``specimen`` attribute, or of the rig or specimen id, is said
RECORD_CONDITIONS = ("overrides", "temperature_K", "model", "lsdea")


def _flat(value: object, prefix: str = "") -> dict[str, object]:
    """A JSON object's leaves by dotted path."""
    if not isinstance(value, dict):
        return {prefix: value}
    out: dict[str, object] = {}
    for k, v in value.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def specimen_mismatch(runs: list[Path]) -> str:
    """One line naming what differs between the run files' specimens (``specimen_id``, the ``specimen`` attribute
    less the per-record conditions a campaign allows), with the first file's and the first differing file's values;
    '' when they agree. Fitting two specimens as one set of parameters is usually a mistake: said before the fit,
    which still goes ahead. The rig may differ: one specimen measured on two benches (the LS-DEA campaign's motor
    and hung-mass rigs) is one specimen."""
    from bench.storage.runfile import open_run

    if len(runs) < 2:
        return ""
    files = [open_run(p, streams=False) for p in runs]
    keys: dict[str, list[object]] = {}
    for f in files:
        keys.setdefault("specimen_id", []).append(f.attrs.get("specimen_id") or None)
    flats = [_flat(f.specimen()) for f in files]
    for name in sorted(set().union(*flats)):
        if not any(name == c or name.startswith(c + ".") for c in RECORD_CONDITIONS):
            keys["specimen." + name] = [flat.get(name) for flat in flats]
    said = []
    for name, values in keys.items():
        other = next((k for k, v in enumerate(values) if v != values[0]), None)
        if other is not None:
            said.append(f"{name} {values[0]!r} ({runs[0].name}) vs {values[other]!r} ({runs[other].name})")
    if not said:
        return ""
    return ("the runs are not of one specimen: " + "; ".join(said) + " — fitting them as one set of "
            "parameters is usually a mistake (fitting anyway)")


def stopped_notices(runs: list[Path]) -> list[str]:
    """One line per run file that stopped before its protocol ended (interrupted, tripped, error): the report's
    wording (:func:`bench.app.analysis.stopped_line`), naming the file among ``runs`` that continued it."""
    from bench.app.analysis import continued_in, stopped_line
    from bench.storage.runfile import open_run

    out = []
    for k, p in enumerate(runs):
        run = open_run(p, streams=False)
        later = continued_in(run, runs[:k] + runs[k + 1:]) if run.state != "completed" else None
        line = stopped_line(run, later) if run.state != "completed" else ""
        if run.state == "running" and not run.complete:  # killed or crashed (a tester: fitted as whole, unsaid)
            line = (f"run {run.state_shown}: recorded up to {run.updated:.2f} s"
                    + (f"; the campaign goes on in {later.name}" if later is not None else ""))
        if line:
            out.append(f"{p}: {line}; fitting what was recorded")
    return out


def check_fittable(runs: list[Path], into: bool = False) -> None:
    """Refuse, before any work, a file the fit cannot be stored with: not finalised (a crashed file that a resumed
    campaign continued is fine), or crashed with ``into`` (fits go inside finished files only)."""
    from bench.storage.runfile import open_run

    for p in runs:
        f = open_run(p, streams=False)
        crashed = f.state == "running" and bool(f.orphaned or f.recovered_at)  # a resumed campaign's earlier part
        if not (f.complete or crashed):
            raise ValueError(f"run file {p}: not finalised ({f.incomplete_reason}); fit it when it has ended")
        if into and not f.complete:
            raise ValueError(f"run file {p}: not finalised (crashed); --into stores fits in finished files only — "
                             "leave out --into to store the fit in its fit file beside it")


def check_driven(runs: list[Path]) -> None:
    """Refuse, before any work, membrane runs none of which drove the amplifier beyond the voltage monitor's 0-V
    band (each file's own: the chain of the rig it records, :func:`bench.analysis.thesis.no_drive_v_of`; the widest,
    :data:`bench.analysis.thesis.NO_DRIVE_V`, where unknown): the membrane moves only under voltage, so its record at
    rest holds no information on any parameter (the search would run to the end and find every one insensitive).
    One undriven file among driven ones is a record at rest of the campaign, and is fitted with them."""
    from bench.analysis.thesis import no_drive_v_of, undriven
    from bench.storage.chunks import open_source

    peaks, bands = [], []
    for p in runs:
        with open_source(p) as src:
            peaks.append(_peak_voltage(src.streams))
            bands.append(no_drive_v_of(src.run.attrs))
    if all(undriven(v, b) for v, b in zip(peaks, bands, strict=True)):
        names = ", ".join(str(p) for p in runs)
        raise ValueError(f"run file{'s' if len(runs) > 1 else ''} {names}: the amplifier was never driven above "
                         f"{max(bands):.3g} V (the voltage monitor's 0-V band; peak {max(peaks):.3g} V): no model "
                         "parameter is identifiable without a drive")


MIN_POINTS_PER_PARAMETER = 10  # measured points a fit needs per free parameter (see check_enough_data)


def check_enough_data(problem: RecordedProblem, runs: list[Path]) -> None:
    """Refuse, before the search, records that hold fewer than :data:`MIN_POINTS_PER_PARAMETER` measured points per
    free parameter: with hardly more points than parameters the search fits the noise, its intervals span orders of
    magnitude and nothing it finds is a property of the specimen — a run stopped within its first second gave 114
    points for 16 parameters, and the fit was stored, exit 0 (an outside tester). The choice of ten is ours (no
    source gives one): a whole short identification record holds over 1,000 points, 70 per parameter."""
    # all the files' points together: a campaign's last, resumed part may be short
    n, k = int(np.isfinite(problem.data).sum()), int(np.asarray(problem.lower).size)
    names = ", ".join(str(p) for p in runs)
    if n <= k:  # none to speak of: the sensor's record, not the run's length (the fit's own words)
        raise ValueError(f"run file{'s' if len(runs) > 1 else ''} {names}: {n} valid data points for {k} parameters: "
                         "nothing to fit (the sensor read out of range or invalid through the whole record?)")
    if n < MIN_POINTS_PER_PARAMETER * k:
        raise ValueError(f"run file{'s' if len(runs) > 1 else ''} {names}: {n} measured points for {k} parameters "
                         f"(a fit needs {MIN_POINTS_PER_PARAMETER} per parameter, {MIN_POINTS_PER_PARAMETER * k}): "
                         "too short a record to fit (a run stopped early?); nothing fitted or stored")


def _peak_voltage(streams: StreamChunks) -> float:
    """The largest |V| a run applied (the set-points; on a hardware-timed rig also the measured output, as
    :func:`bench.analysis.applied.applied_window` reads it), read a chunk at a time: a long 10-kHz record is
    never held whole."""
    import numpy as np

    from bench.analysis.applied import hardware_timed

    sources = [("setpoints", "voltage")] + ([("amplifier", "voltage")] if hardware_timed(streams) else [])
    peak = 0.0
    for stream, column in sources:
        if stream not in streams.columns:
            continue
        for chunk in streams.chunks(stream):
            v = np.abs(chunk[column])
            if bool(np.isnan(v).all()):
                continue
            peak = max(peak, float(np.nanmax(v)))
    return peak


def fit_runs(runs: list[Path], model: str, settings: FitSettings, *, branches: int = 1, export: Path | None = None,
             scheduler: str | None = None, workers: int | None = None, into: bool = False,
             on_read: Callable[[RecordedProblem], None] | None = None, on_cluster: Callable[[str], None] | None = None,
             progress: Progress | None = None, stage: Callable[[str, float], None] | None = None) -> Fitted:
    """Fit ``model`` ("membrane" or "lsdea") to the records of ``runs`` (differential evolution on a coarse
    integration step, polish and identifiability on a fine one); store the result with every file (in its fit
    file, or with ``into`` in the run file) and optionally export a rig file. On a dask cluster when
    ``scheduler`` (address) or ``workers`` (LocalCluster) is given (membrane model: ``on_cluster`` gets its
    address). ``on_read`` gets the problem once the records are read; ``progress`` the fraction of generations,
    ``stage`` the stage after the search ("polish", "intervals") and the share of it done, never going back."""
    from bench.identify.problems import LozengeProblem, MembraneProblem

    check_fittable(runs, into)
    if model == "membrane":
        check_driven(runs)
    if export is not None:
        check_export(export)
    check_writable(runs, into, export)
    files: list[str | Path] = list(runs)
    coarse: RecordedProblem
    fine: RecordedProblem
    if model == "membrane":
        coarse, fine = MembraneProblem(files, h=5e-4), MembraneProblem(files, h=1e-4)
    else:
        coarse = LozengeProblem(files, branches=branches, h=LSDEA_SEARCH_STEP)
        fine = LozengeProblem(files, branches=branches, h=LSDEA_FINE_STEP)
    check_enough_data(coarse, runs)
    if on_read is not None:
        on_read(coarse)
    total = settings.generations * max(settings.starts, 1)  # progress is called at each generation of each start
    done = [0]

    counting = threading.Lock()  # the starts search in threads of their own

    def generation() -> None:
        with counting:
            done[0] += 1
            share = done[0] / total
        if progress is not None:
            progress(share)

    try:
        return _search_and_store(coarse, fine, model, runs, settings, scheduler, workers, into, export, on_cluster,
                                 generation, done, total, stage)
    except KeyboardInterrupt:  # before the search's own stop took over: the cluster starting, the records spread
        raise FitStopped("Ctrl-C before the search began (starting the cluster); nothing stored") from None


def _search_and_store(coarse: MembraneProblem | LozengeProblem, fine: MembraneProblem | LozengeProblem, model: str,
                      runs: list[Path],
                      settings: FitSettings, scheduler: str | None, workers: int | None, into: bool,
                      export: Path | None, on_cluster: Callable[[str], None] | None, generation: Callable[[], None],
                      done: list[int], total: int, stage: Callable[[str, float], None] | None) -> Fitted:
    """:func:`fit_runs` from the cluster on: the search, polish and identifiability (Ctrl-C: one line, nothing
    stored), then the stores (not cut short)."""
    from bench.app.cluster import cluster_client
    from bench.identify.campaign import campaign_identifiability
    from bench.identify.core import fit
    from bench.identify.monitor import Stopped
    from bench.identify.problems import MembraneProblem

    with cluster_client(scheduler, workers) as client:
        if client is not None:
            if not isinstance(coarse, MembraneProblem) or not isinstance(fine, MembraneProblem):
                raise ValueError("--scheduler/--workers: distributed fits are implemented for the membrane "
                                 "model only; fit LS-DEA records in-process")
            coarse.distribute(client)
            fine.distribute(client)
            if on_cluster is not None:
                on_cluster(str(client.scheduler.address if client.scheduler is not None else scheduler))
        stop = threading.Event()
        coarse.stop = fine.stop = stop
        stages = ["differential evolution"]

        def staged(name: str, fraction: float) -> None:
            if stages[-1] != name:
                stages.append(name)
            if stage is not None:
                stage(name, fraction)
        try:
            with _stopped_by_ctrl_c(stop):
                result = fit(coarse, settings, start=None, fine=fine, progress=generation,
                             stage=_forward_only(staged))
                out = Fitted(model, runs, result, coarse)
                records = [r.source for r in coarse.records]
                campaign = None
                if len(records) > 1:
                    out.campaign = campaign_identifiability(fine, result)
                    campaign = out.campaign.as_dict()
        except (KeyboardInterrupt, Stopped):
            raise FitStopped(f"Ctrl-C in the {STAGES.get(stages[-1], stages[-1])}, after {done[0]} of {total} "
                             "generations (all starts); nothing stored") from None
        finally:
            for prob in (coarse, fine):
                if isinstance(prob, MembraneProblem):
                    prob.distribute(None)
    with _ctrl_c_deferred() as late:  # the stores are not cut short: each file gets the whole fit or none
        _store(out, runs, model, records, campaign, into, export)
    if late:
        raise FitStopped("Ctrl-C while the fit was stored: the stores were finished first ("
                         + ", ".join(f"{f}:{g}" for f, g in out.stored)
                         + (f", rig file {out.exported}" if out.exported else "") + ")")
    return out


def _store(out: Fitted, runs: list[Path], model: str, records: list[str], campaign: dict[str, object] | None,
           into: bool, export: Path | None) -> None:
    """Write the fit with every run file (or its fit file) and the ``--export`` rig file; fills ``out``."""
    from bench.identify.fitted_rig import export_rig
    from bench.identify.store import fit_sidecar, write_fit
    from bench.storage.runfile import open_run

    result, mixed = out.result, specimen_mismatch(runs)
    for p in runs:
        group = write_fit(p, model, result, records, campaign, sidecar=not into, ended=True,  # (check_fittable)
                          mixed=mixed)
        out.stored.append((p if into else fit_sidecar(p), group))
    if export is not None:
        attrs = open_run(runs[0], streams=False).attrs  # the rig file as written, else (older runs) as parsed
        try:
            export_rig(str(attrs.get("rig_text") or attrs["rig_toml"]), model, result.names, result.values, export,
                       str(runs[0]))
        except FileExistsError:  # made while the fit ran
            raise FileExistsError(f"--export {export}: exists; bench fit does not overwrite files: choose another "
                                  "name (the fit is stored)") from None
        except OSError as exc:
            raise OSError(f"--export {export}: cannot write the rig file: {exc.strerror or exc} (the fit is "
                          "stored)") from None
        out.exported = export


class FitStopped(Exception):  # noqa: N818  # a user's stop, not an error
    """``bench fit`` stopped by Ctrl-C (the message says where; the CLI exits 130)."""


STAGES = {"polish": "least-squares polish", "intervals": "profile-likelihood intervals"}


@contextlib.contextmanager
def _stopped_by_ctrl_c(stop: threading.Event) -> Iterator[None]:
    """Ctrl-C (SIGINT) sets ``stop`` before the KeyboardInterrupt: the starts searching in threads of their own
    (:func:`bench.identify.core.searches`) then end at their next batch of evaluations, instead of the main
    thread's interrupt waiting on them, unstopped, to the end of the fit (2 min 20 s for the defaults). Only in the
    main thread, and not where SIGINT is ignored (a background job)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        stop.set()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _ctrl_c_deferred() -> Iterator[list[bool]]:
    """Ctrl-C held back while the body runs (a list that is true afterwards when one came), so that writes are
    not cut short halfway; as :func:`_stopped_by_ctrl_c`, only where Python's own handler is installed."""
    late: list[bool] = []
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield late
        return
    previous = signal.signal(signal.SIGINT, lambda *_: late.append(True))
    try:
        yield late
    finally:
        signal.signal(signal.SIGINT, previous)


def check_export(export: Path) -> None:
    """Refuse an ``--export`` target before minutes of fitting, not after the store, in one line naming it: an
    existing file (never replaced, as ``bench protocols copy`` and ``bench init`` do not), a folder, a missing
    folder."""
    from bench.storage.outputs import refuse_existing

    refuse_existing(export, "fit", "--export", "fitted.toml")
    if not export.parent.is_dir():
        raise ValueError(f"--export {export}: folder {export.parent} not found")


def check_writable(runs: list[Path], into: bool = False, export: Path | None = None) -> None:
    """Refuse, before minutes of fitting, a destination the fit could not be written to (a read-only folder or file
    system, a file without write permission), in one line naming it: each run's fit file (or with ``into`` the run
    file itself) and the ``--export`` rig file. Probed by opening for writing (an existing file, not changed) or by
    creating and removing a temporary file in the folder: mode bits alone say nothing for root or a read-only
    mount."""
    from bench.identify.store import fit_sidecar

    for p in runs:
        if into:
            _probe(p, f"run file {p}", "--into stores the fit inside it: leave out --into to write a fit file beside "
                   "it, or copy the run to a writable folder")
        else:
            _probe(fit_sidecar(p), f"fit file {fit_sidecar(p)}", "the fit is stored beside its run: copy the run "
                   "(with any fit file of it) to a writable folder and fit it there")
    if export is not None:
        _probe(export, f"--export {export}", "choose a writable folder for the rig file")


def _probe(path: Path, what: str, hint: str) -> None:
    import os
    import tempfile

    try:
        if path.exists():
            os.close(os.open(path, os.O_RDWR))
        else:
            with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".bench-write-check-"):
                pass
    except OSError as exc:
        raise ValueError(f"{what}: cannot be written ({exc.strerror or exc}); {hint}") from None


def _forward_only(stage: Callable[[str, float], None]) -> Callable[[str, float], None]:
    """``stage`` told only of progress: a profile re-centred (its walks start again) keeps its share shown."""
    most: dict[str, float] = {}
    lock = threading.Lock()  # the starts polish in threads of their own

    def tell(name: str, fraction: float) -> None:
        with lock:
            if fraction > most.get(name, -1.0):
                most[name] = fraction
                stage(name, fraction)
    return tell
