"""A run file's streams read a chunk at a time, so a reader's memory does not grow with the run's length.

Used by the export and the quick-look plot; each dataset is cut to the records the writer confirmed
(``/status/samples``), as :func:`bench.storage.runfile.open_run` does.
"""

from __future__ import annotations

from collections.abc import Iterator

import h5py
import numpy as np

from bench.storage.runfile import stream_names, unit_of, valid_counts

CHUNK_ROWS = 262_144  # records per stream read at a time (a few MB per column)


class StreamChunks:
    """The run file's streams, read a chunk at a time: names, units, lengths trimmed to the confirmed records."""

    def __init__(self, f: h5py.File) -> None:
        self.f = f
        valid = valid_counts(f)
        self.length: dict[str, int] = {}
        self.columns: dict[str, list[str]] = {}
        for name in stream_names(f):
            g = f[name]
            for d in g.values():
                d.refresh()
            n = min(d.shape[0] for d in g.values())
            self.length[name] = min(n, valid.get(name, n))
            self.columns[name] = ["t", *(k for k in g if k != "t")]

    def units(self, stream: str) -> dict[str, str]:
        """Unit per column (time in s)."""
        g = self.f[stream]
        return {k: unit_of(g[k].attrs.get("units", "s" if k == "t" else "")) for k in self.columns[stream]}

    def dtype(self, stream: str, column: str) -> np.dtype:
        """The stored type of a column."""
        dtype: np.dtype = self.f[stream][column].dtype
        return dtype

    def nbytes(self, stream: str) -> int:
        """Bytes of the stream's confirmed records, all columns."""
        return sum(self.dtype(stream, c).itemsize for c in self.columns[stream]) * self.length[stream]

    def chunks(self, stream: str, rows: int | None = None, start: int = 0,
               stop: int | None = None) -> Iterator[dict[str, np.ndarray]]:
        """The stream's columns from record ``start`` to ``stop`` (default: the confirmed end), ``rows`` (default
        ``CHUNK_ROWS``) records at a time (``bench watch`` reads only the records added since its last look)."""
        g, step = self.f[stream], rows or CHUNK_ROWS
        n = self.length[stream] if stop is None else min(stop, self.length[stream])
        for a in range(start, n, step):
            b = min(a + step, n)
            yield {c: g[c][a:b] for c in self.columns[stream]}
