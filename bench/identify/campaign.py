"""Campaign fits: one specimen model fitted jointly to all records of a campaign, and what the campaign adds.

The joint fit itself is :func:`bench.identify.core.fit` on a problem holding every record (shared material
parameters; each record keeps its own conditions — voltage history, temperature, prototype, hung mass — read
from its file). This module asks, at the campaign's optimum, which parameters each record determines on its
own: the identifiability analysis of :func:`bench.identify.core.assess` applied to that record's rows of the
campaign's Jacobian. A parameter the campaign determines but no single record does is what fitting the
campaign together gains (e.g. a fast Maxwell unit only the combination of frequencies pins down).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.identify.core import FitResult, RecordedProblem, assess, to_optimiser

# flags that say a parameter is not determined (a bound is a property of the estimate, not of the data): the local
# analysis's, and the profile intervals' of a trusted fit (:mod:`bench.identify.trust`, which drops "poorly
# determined" for its own verdicts: without them the campaign listed as determined by it a parameter its own row
# called "not determined", outside tester). One side bounded is not determined either.
UNDETERMINED = ("does not change the cost", "poorly determined", "correlated with", "not determined",
                "bounded on one side only")


@dataclass
class CampaignReport:
    """Per-record identifiability at the campaign's optimum."""

    names: list[str]
    records: list[str]
    conditions: list[str]  # per record: its conditions, e.g. "7 kV, 296 K"
    undetermined: list[list[str]]  # per record: parameter names the record alone leaves undetermined
    campaign_undetermined: list[str]  # parameter names the whole campaign leaves undetermined

    @property
    def gained(self) -> list[str]:
        """Parameters the campaign determines that no single record does."""
        return [n for n in self.names if n not in self.campaign_undetermined
                and all(n in u for u in self.undetermined)]

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (stored beside the fit)."""
        return {"records": self.records, "conditions": self.conditions,
                "undetermined_per_record": self.undetermined, "undetermined": self.campaign_undetermined,
                "determined_only_by_the_campaign": self.gained}


def _undetermined(flags: list[str]) -> list[str]:
    return sorted({f.split(": ", 1)[0] for f in flags if any(k in f for k in UNDETERMINED)})


def _levels(temps: np.ndarray, gap: float = 2.0) -> list[np.ndarray]:
    """Masks of a record's temperature levels in the order they come: values within ``gap`` K of each other are one
    level (a thermometer's noise does not split one)."""
    finite = np.isfinite(temps)
    values = np.unique(temps[finite])
    if values.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(values) > gap)
    bounds = zip(np.concatenate([[values[0]], values[cuts + 1]]), np.concatenate([values[cuts], [values[-1]]]),
                 strict=True)
    masks = [finite & (temps >= lo) & (temps <= hi) for lo, hi in bounds]
    return sorted(masks, key=lambda m: int(np.argmax(m)))


def record_conditions(problem: RecordedProblem) -> list[str]:
    """A short description of each record's conditions, from its inputs and packed template."""
    out = []
    for rec in problem.records:
        U = rec.U
        if U.shape[1] == 2:  # membrane: (Φ, T); a sweep's record holds several (a 5 kV, 266 K then 7 kV, 316 K
            # record read "7 kV, 266 K": the highest voltage and the median temperature, a second tester)
            parts = [f"{np.max(np.abs(U[m, 0])) / 1e3:.3g} kV, {np.median(U[m, 1]):.0f} K" for m in _levels(U[:, 1])]
            out.append("; ".join(parts) if parts else "—")
        else:  # LS-DEA: (V, x, ẋ); template holds λ2p and the hung mass
            out.append(f"λ2p {rec.template[10]:.3g}, {rec.template[13] * 1e3:.0f} g, {_voltage_span(U[:, 0])}")
    return out


def _voltage_span(volts: np.ndarray) -> str:
    """The |voltage| a record spans, in kV: "0–7 kV", or its median where it stays within 5 % of its peak. An
    isopotential prototype's record holds 0, 3, 5 and 7 kV in turn and read "7 kV" (its peak), as if all at 7 kV (an
    outside tester)."""
    v = np.abs(np.asarray(volts, dtype=float))
    v = v[np.isfinite(v)]
    if v.size == 0:
        return "—"
    lo, hi = float(v.min()), float(v.max())
    if hi - lo <= 0.05 * hi:
        return f"{float(np.median(v)) / 1e3:.3g} kV"
    return f"{round(lo / 1e3, 2):g}–{round(hi / 1e3, 2):g} kV"


def campaign_identifiability(problem: RecordedProblem, result: FitResult) -> CampaignReport:
    """Which parameters each record determines alone, at the campaign fit's optimum (``problem``: the one the
    fit's Jacobian was computed on — the fine problem when the fit had one)."""
    if result.jacobian is None or result.residual is None or result.z is None:
        raise ValueError("the fit result carries no Jacobian: campaign identifiability needs a fresh fit")
    records = problem.records
    mask = np.isfinite(problem.data)
    pos = np.cumsum(mask) - 1  # index of each compared point among the compared points
    log = np.asarray(problem.log, bool)
    # the result's bounds: its units are numbered by relaxation time, each with the bounds it was searched in
    lo, hi = to_optimiser(log, result.lower), to_optimiser(log, result.upper)
    undetermined, start = [], 0
    for rec in records:
        seg = slice(start, start + rec.data.size)
        start += rec.data.size
        rows = pos[seg][mask[seg]]
        data = problem.data[seg][mask[seg]]
        if rows.size <= len(problem.names):
            undetermined.append(list(problem.names))
            continue
        scale = max(float(np.sqrt(np.mean(data * data))), 1e-30)
        _, _, _, flags = assess(list(problem.names), log, lo, hi, result.z, result.jacobian[rows],
                                result.residual[rows], scale)
        undetermined.append(_undetermined(flags))
    joint = _undetermined(result.flags)
    # what the whole campaign leaves undetermined no part of it determines (its data are a subset): the records'
    # local analysis could tick a parameter whose profile interval over all records is open (the table read J0 ✓ for a
    # record and · for the campaign, outside tester)
    undetermined = [sorted(set(u) | set(joint), key=list(problem.names).index) for u in undetermined]
    return CampaignReport(list(problem.names), [r.source for r in records], record_conditions(problem),
                          undetermined, joint)
