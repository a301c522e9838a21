"""The search's cost of each candidate, record by record: where the predictions are made (in-process or on a dask
worker), so that only one number per candidate and record travels.

A record's partial cost of a candidate is the sum over the record's finite data columns of r² (``"lsq"``) or |r|
(``"sae"``), r = (prediction − data)/σ; inf where any such r is not finite (as :func:`bench.identify.core._costs`).
Each row is summed sequentially in column order, so a candidate's partial cost does not depend on how many
candidates were evaluated with it (numpy's axis reductions may change their order with the array's shape), and
:func:`total` adds the records' partial costs in record order: the same bits whichever way a batch was cut.
"""

from __future__ import annotations

import numpy as np

from bench.models.jit import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _partial(pred: np.ndarray, c0: int, data: np.ndarray, sigma: np.ndarray, mask: np.ndarray, sae: bool,
             out: np.ndarray) -> None:
    """out[i]: the partial cost of row i of ``pred`` over the columns c0 … c0 + len(data) (one record's)."""
    for i in range(pred.shape[0]):
        s = 0.0
        for j in range(data.size):
            if mask[j]:
                r = (pred[i, c0 + j] - data[j]) / sigma[j]
                if not np.isfinite(r):
                    s = np.inf
                    break
                s += abs(r) if sae else r * r
        out[i] = s


def record_costs(pred: np.ndarray, c0: int, data: np.ndarray, sigma: np.ndarray, mask: np.ndarray,
                 kind: str) -> np.ndarray:
    """One record's partial cost of each row of ``pred`` (candidates × columns), whose columns c0 … c0 + len(data)
    are the record's; ``mask``: its data columns compared (finite); ``kind``: "sae" or "lsq"."""
    # the compiled loop checks no bounds: a record outside the prediction would read past it
    if not (c0 >= 0 and c0 + data.size <= pred.shape[1] and sigma.size == data.size == mask.size):
        raise ValueError(f"record columns {c0}…{c0 + data.size} of a {pred.shape[1]}-column prediction, "
                         f"σ {sigma.size} and mask {mask.size} for {data.size} data points")
    out = np.empty(pred.shape[0])
    _partial(np.ascontiguousarray(pred, dtype=np.float64), int(c0), np.ascontiguousarray(data, dtype=np.float64),
             np.ascontiguousarray(sigma, dtype=np.float64), np.ascontiguousarray(mask, dtype=np.bool_),
             kind == "sae", out)
    return out


def total(parts: np.ndarray) -> np.ndarray:
    """Each candidate's cost: the records' partial costs (records × candidates) added in record order."""
    out: np.ndarray = np.array(parts[0], dtype=np.float64)
    for p in parts[1:]:
        out += p
    return out
