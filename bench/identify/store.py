"""Fit results written back beside the data (the fitted rig file: :mod:`bench.identify.fitted_rig`).

Where: by default in a *fit file* beside the run, ``<run>.fit.hdf5`` for ``<run>.h5`` (:func:`fit_sidecar`), so the
run file itself is never modified after its run (and a ``runs/*.h5`` glob does not pick up fit files); or, on
request, in the run file itself. A fit file is HDF5 with root attributes ``format = "dea-bench fits 1"``,
``run_file`` (the run's file name), ``run_start_time`` and ``protocol_sha256`` (copied from the run, to tell a fit
file from one left over by another run of the same name) and the same ``/fit`` groups as a run file.
:func:`read_fits` reads both places. A fit over several files (a campaign) is stored with each of them.

In either file: group ``/fit/<model>-<n>`` with datasets ``names``, ``units``, ``values``, ``lower``,
``upper``, ``sensitivity``, ``correlation``, ``uncertainty`` (each with a ``units`` attribute: per parameter
for ``values``, ``lower``, ``upper``; "1" for the relative others) and attributes ``cost``, ``cost_kind``, ``rms``,
``n_data``, ``records`` (the files and windows used), DE settings, ``software``, ``wall_time``, ``flags``,
``lack_of_fit`` ('' when the model follows the data), ``created`` and, for a fit over several records,
``campaign`` (JSON: what each record determines alone and what only the campaign determines).

A fit with intervals (:mod:`bench.identify.trust`) adds datasets ``interval_lower`` and ``interval_upper`` (physical
units, per parameter; the search bound where the data leave that side open) and ``status`` ("determined", "bounded
on one side only", "not determined"), and attributes ``interval_method`` ("profile likelihood"), ``confidence``
(0.95), ``chi2_reduced`` and ``trust`` (JSON: noise σ per record, variance scale and Δχ² threshold, trade-offs,
the starts and whether they agree, the spread per parameter, the unit-order rule). ``uncertainty`` then holds the
local (Jacobian) relative 1σ only where it agrees with the profile, NaN elsewhere.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bench import __version__
from bench.identify.core import FitResult
from bench.storage.recorder import now_iso
from bench.storage.runfile import open_h5, open_run

SIDECAR_FORMAT = "dea-bench fits 1"
SIDECAR_SUFFIX = ".fit.hdf5"


def fit_sidecar(run_path: str | Path) -> Path:
    """The fit file beside a run file: ``runs/x.h5`` → ``runs/x.fit.hdf5``."""
    p = Path(run_path)
    return p.with_name(p.stem + SIDECAR_SUFFIX)


def is_sidecar(path: str | Path) -> bool:
    """Whether ``path`` names a fit file (by its name: ``*.fit.hdf5``)."""
    return Path(path).name.endswith(SIDECAR_SUFFIX)


def _run_identity(run_path: str | Path, ended: bool = False) -> dict[str, str]:
    """The run file's identity a fit file records (and is checked against); ValueError while a run still writes
    it. A crashed file (a resumed campaign's earlier part) takes a fit file like a finished one: its data are
    what was measured up to the crash. ``ended``: the caller found it ended before the fit (`bench fit`'s check):
    not looked at again — a crashed file another process happens to hold open now (a reader) would read as being
    written, and the fit's minutes were lost at the end (a second tester: refused after 32 s of fitting)."""
    run = open_run(run_path, streams=False)
    crashed = run.state == "running" and bool(run.orphaned or run.recovered_at)
    if not (ended or run.complete or crashed):
        raise ValueError(f"run file {run_path}: not finalised ({run.incomplete_reason}); fit results go with ended "
                         "runs only")
    return _run_identity_any(run_path)


def _check_sidecar(f: h5py.File, side: Path, run_path: str | Path, identity: dict[str, str]) -> None:
    if f.attrs.get("format") != SIDECAR_FORMAT:
        raise ValueError(f"fit file {side}: not a dea-bench fit file (format {f.attrs.get('format')!r})")
    for key in ("run_start_time", "protocol_sha256"):
        if str(f.attrs.get(key, "")) != identity[key]:
            raise ValueError(f"fit file {side}: belongs to another run of the name {f.attrs.get('run_file')!r} "
                             f"({key} differs from {run_path}'s): move it away or delete it")


def write_fit(run_path: str | Path, model: str, result: FitResult, records: list[str],
              campaign: dict[str, object] | None = None, *, sidecar: bool = False, ended: bool = False,
              mixed: str = "") -> str:
    """Append the fit to a finished run file, or with ``sidecar`` to its fit file (:func:`fit_sidecar`, created if
    absent); returns the group name. ``campaign``: the campaign report (which parameters the records determine
    alone and together), stored as JSON in attribute ``campaign``; ``ended``: :func:`_run_identity`'s; ``mixed``:
    why the records are not of one specimen (attribute ``mixed_specimens``: a specimen's history leaves it out)."""
    if sidecar:
        identity = _run_identity(run_path, ended)
        side = fit_sidecar(run_path)
        with h5py.File(side, "a") as f:
            if not f.attrs.get("format"):
                f.attrs.update({"format": SIDECAR_FORMAT, **identity})
            _check_sidecar(f, side, run_path, identity)
            return _write_group(f, model, result, records, campaign, mixed)
    with h5py.File(run_path, "r+") as f:
        if not f.attrs.get("complete", False):
            raise ValueError(f"run file {run_path}: incomplete run; fit results go into finished files only")
        return _write_group(f, model, result, records, campaign, mixed)


def _write_group(f: h5py.File, model: str, result: FitResult, records: list[str],
                 campaign: dict[str, object] | None, mixed: str = "") -> str:
    g0 = f.require_group("fit")
    k = 1
    while f"{model}-{k}" in g0:
        k += 1
    g = g0.create_group(f"{model}-{k}")
    text = h5py.string_dtype("utf-8")
    g.create_dataset("names", data=np.array(result.names, dtype=object), dtype=text)
    g.create_dataset("units", data=np.array(result.units, dtype=object), dtype=text)
    for key in ("values", "lower", "upper", "sensitivity", "correlation", "uncertainty"):
        g.create_dataset(key, data=np.asarray(getattr(result, key), dtype=float))
    for key in ("values", "lower", "upper"):  # one unit per parameter: an array, element i for parameter i
        g[key].attrs.create("units", np.array(result.units, dtype=object), dtype=text)
    for key in ("sensitivity", "correlation", "uncertainty"):  # relative quantities
        g[key].attrs["units"] = "1"
    g.attrs.update({"model": model, "cost": result.cost, "cost_kind": result.cost_kind, "rms": result.rms,
                    "n_data": result.n_data, "evaluations": result.evaluations,
                    "generations": result.generations, "wall_time": result.wall_time,
                    "settings": json.dumps(asdict(result.settings)), "records": json.dumps(records),
                    "flags": json.dumps(result.flags), "lack_of_fit": result.lack_of_fit,
                    "software": f"dea-bench {__version__}",
                    "created": now_iso()})
    if campaign is not None:
        g.attrs["campaign"] = json.dumps(campaign)
    if mixed:
        g.attrs["mixed_specimens"] = mixed
    tr = result.trust
    if tr is not None:
        for key, arr in (("interval_lower", tr.lower), ("interval_upper", tr.upper)):
            g.create_dataset(key, data=np.asarray(arr, dtype=float))
            g[key].attrs.create("units", np.array(result.units, dtype=object), dtype=text)
        g.create_dataset("status", data=np.array(tr.status, dtype=object), dtype=text)
        g.attrs.update({"interval_method": tr.method, "confidence": tr.confidence, "chi2_reduced": tr.chi2_reduced,
                        "trust": json.dumps(tr.as_dict(result.names))})
    return str(g.name)


def read_fits(run_path: str | Path) -> list[dict[str, Any]]:
    """Fits stored in a run file and in its fit file (newest last): dicts with ``file`` (where it is stored),
    group, names, values, bounds, cost, flags, …; ValueError if the fit file belongs to another run."""
    out = _read_groups(run_path)
    side = fit_sidecar(run_path)
    if side.exists():
        identity = _run_identity_any(run_path)
        with h5py.File(side, "r") as f:
            _check_sidecar(f, side, run_path, identity)
        out += _read_groups(side, run_file=False)
    return sorted(out, key=lambda d: str(d.get("created", "")))


def _run_identity_any(run_path: str | Path) -> dict[str, str]:
    with open_h5(Path(run_path)) as f:  # as every reader opens a run file: also one a crash left marked open
        return {"run_file": Path(run_path).name, "run_start_time": str(f.attrs.get("start_time", "")),
                "protocol_sha256": str(f.attrs.get("protocol_sha256", ""))}


def _read_groups(path: str | Path, run_file: bool = True) -> list[dict[str, Any]]:
    """The fit groups of a run file (opened as readers open one: :func:`open_h5`) or of a fit file."""
    out: list[dict[str, Any]] = []
    with open_h5(Path(path)) if run_file else h5py.File(path, "r") as f:
        if "fit" not in f:
            return out
        for name in sorted(f["fit"], key=lambda n: f["fit"][n].attrs["created"]):
            g = f["fit"][name]
            out.append({"file": str(path), "group": g.name, "names": list(g["names"].asstr()[:]),
                        "units": list(g["units"].asstr()[:]), "values": g["values"][:],
                        "lower": g["lower"][:], "upper": g["upper"][:], "sensitivity": g["sensitivity"][:],
                        "uncertainty": g["uncertainty"][:] if "uncertainty" in g else None,
                        **{k: g[k][:] for k in ("interval_lower", "interval_upper") if k in g},
                        **({"status": list(g["status"].asstr()[:])} if "status" in g else {}),
                        **{k: (json.loads(v) if k in ("settings", "records", "flags", "campaign", "trust") else v)
                           for k, v in g.attrs.items()}})
    return out
