"""Arguments of the compiled kernels in one form: C-contiguous, writable float64.

numba compiles (and caches) one machine-code variant per argument type, and an array's type includes its layout
(C, F, any) and whether it is read-only (a ``np.broadcast_to`` view, an array a dask worker received). The batch
kernels take 10–20 s each to compile on a 2-core machine, so every call site hands them arrays of one form: a
caller's own C float64 array passes through uncopied; a view of another form is copied once.
"""

from __future__ import annotations

import numpy as np


def kernel_array(x: np.ndarray | float, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``x`` as a C-contiguous, writable float64 array (broadcast to ``shape`` first where it has another shape):
    ``x`` itself where it already is one, else a copy."""
    a = np.asarray(x, dtype=np.float64)
    if shape is not None and a.shape != shape:
        a = np.broadcast_to(a, shape)
    return np.require(a, np.float64, ("C_CONTIGUOUS", "WRITEABLE"))
