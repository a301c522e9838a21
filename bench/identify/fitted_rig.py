"""The fitted rig file (``bench fit --export``): the rig the run was recorded on, edited with tomlkit so that its
comments, its order and the values it leaves at their defaults stay as written, and only what the fit sets
changes: the specimen model table (``[specimen.membrane_model]`` with the relaxation times ``tau`` the fit reports,
or ``[specimen.lsdea_model]``), the name (``<name>-fitted``) and ``simulated = true`` (a fitted rig is a model to
simulate); a header line says which run it was fitted from.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import tomlkit
from tomlkit.items import Table

from bench.rig import RigConfig, rig_from_toml
from bench.storage.outputs import write_text

HEADER = "# fitted by `bench fit` from "
# a DAQ rig's fit also sets the voltage monitor's calibration (bench/identify/monitor.py), which no rig table holds:
# the specimen is the one seen through it, and the file says so under its header
CALIBRATION_NOTE = "# the same fit set the voltage monitor's calibration, which a rig file does not hold: "


def fitted_model(model: str, names: list[str], values: np.ndarray) -> tuple[str, dict[str, Any]]:
    """(the specimen table the fit sets, its values) for ``model`` "membrane" or "lsdea"."""
    v = dict(zip(names, (float(x) for x in values), strict=True))
    if model == "membrane":
        units = range(1, 1 + sum(1 for n in names if n.startswith("tau")))
        return "membrane_model", {"mu0": v["mu0"], "J0": v["J0"], "mu": [v[f"mu{i}"] for i in units],
                                  "J": [v[f"J{i}"] for i in units], "tau": [v[f"tau{i}"] for i in units]}
    branches = range(1, 1 + sum(1 for n in names if n.startswith("mu_b")))
    return "lsdea_model", {"mu": v["mu"], "Jm": v["Jm"], "C2": v["C2"],
                           "branch_mu": [v[f"mu_b{k}"] for k in branches],
                           "branch_tau": [v[f"tau_b{k}"] for k in branches], "damping": v["c"]}


def fitted_rig_text(source: str, model: str, names: list[str], values: np.ndarray, run: str) -> str:
    """``source`` (a rig file's TOML text) with the fitted values set; every other line as in ``source``."""
    lines = source.splitlines(keepends=True)
    while lines and lines[0].startswith((HEADER, CALIBRATION_NOTE)):  # a fitted rig fitted again: the newest only
        lines = lines[1:]
    doc = tomlkit.parse("".join(lines))
    name = str(doc.get("name", "rig")).removesuffix("-fitted")
    doc["name"] = f"{name}-fitted"  # an existing item keeps its place and its comment
    if doc.get("simulated") is False:  # absent means true
        doc["simulated"] = True
    sim = doc.get("simulation")
    if sim is not None and "replay" in sim:  # a recorded run served instead of the model: the fitted rig is the model
        del sim["replay"]
    if "specimen" not in doc:
        doc["specimen"] = tomlkit.table()
    specimen = doc["specimen"]
    key, fitted = fitted_model(model, names, values)
    table = specimen.get(key)
    if table is None:
        table = tomlkit.table()
        specimen[key] = table
    for k, value in fitted.items():
        table[k] = value
    if key == "membrane_model" and "eta" in table:  # the fit's dashpots are relaxation times
        del table["eta"]
    if isinstance(table, Table) and not tomlkit.dumps(table).endswith("\n\n"):
        table.add(tomlkit.nl())  # a blank line before the next table, as rig files are written
    v = dict(zip(names, (float(x) for x in values), strict=True))
    note = "" if "V_gain" not in v else (
        f"{CALIBRATION_NOTE}V_gain = {v['V_gain']:.6g}, V_offset = {v.get('V_offset', 0.0):.6g} V (the monitor read "
        "(1 + V_gain)·V + V_offset of the output V); the specimen below is the one seen through it, so a run on "
        "this rig reproduces the record only as well as the fit determined that calibration (see its flags)\n")
    return f"{HEADER}{run}\n{note}" + tomlkit.dumps(doc)


def export_rig(source: str, model: str, names: list[str], values: np.ndarray, path: str | Path,
               run: str) -> RigConfig:
    """Write the fitted rig file (:func:`fitted_rig_text`) once it validates as a rig, a new file only (an existing
    ``path``: FileExistsError); return that rig."""
    text = fitted_rig_text(source, model, names, values, run)
    rig = rig_from_toml(text)
    write_text(Path(path), text)  # whole or not at all; never replaces a file (FileExistsError)
    return rig
