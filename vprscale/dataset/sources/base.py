"""The interface every descriptor source implements: a 2-D float32 array read by row range.

Readers hold only paths and parameters, so they pickle cheaply to Dask workers and open
their memory maps inside each task; no array data ever sits in a task graph.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator
from typing import Any

import dask.array as da
import numpy as np

from vprscale.core.blocks import BLOCK
from vprscale.core.errors import InputError

_TAKE_RUN = 4096


def check_finite(rows: np.ndarray, start: int, name: str) -> None:
    """Raise naming the first row of ``rows`` (absolute ``start``) that holds NaN or Inf.

    A row's sum is NaN or ±Inf when the row holds either, and one matrix-vector product
    finds that 4–5× faster than ``isfinite`` on every value. A float32 sum can also
    overflow on finite values, so rows flagged by it are confirmed value by value.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        sums = rows @ np.ones(rows.shape[1], dtype=np.float32)
    suspects = np.flatnonzero(~np.isfinite(sums))
    if len(suspects):
        bad = suspects[~np.isfinite(rows[suspects]).all(axis=1)]
        if len(bad):
            raise InputError(f"{name}: row {start + int(bad[0])} holds NaN or Inf")


def part_spans(starts: np.ndarray, start: int, stop: int) -> Iterator[tuple[int, int, int]]:
    """``(part, a, b)`` for each part that rows ``[start, stop)`` reach, of parts laid end to end
    (``starts``: each part's first row, then the total): rows ``a … b − 1`` of that part."""
    first = max(0, int(np.searchsorted(starts, start, side="right")) - 1)
    for i in range(first, len(starts) - 1):
        lo, hi = int(starts[i]), int(starts[i + 1])
        if lo >= stop:
            return
        if min(stop, hi) > max(start, lo):
            yield i, max(start, lo) - lo, min(stop, hi) - lo


class RowSource(abc.ABC):
    """A read-only ``n_rows × dim`` float32 array, read by row range."""

    n_rows: int
    dim: int
    name: str

    @abc.abstractmethod
    def _read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``[start, stop)`` as float32, without validation of their values."""

    @abc.abstractmethod
    def fingerprint(self) -> dict[str, Any]:
        """What identifies this source's content (for provenance and resume checks)."""

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``[start, stop)``; NaN or Inf is an error naming the first bad row."""
        if not 0 <= start <= stop <= self.n_rows:
            raise InputError(f"{self.name}: rows [{start}, {stop}) outside [0, {self.n_rows})")
        rows = np.ascontiguousarray(self._read(start, stop), dtype=np.float32)
        check_finite(rows, start, self.name)
        return rows

    def take(self, rows: np.ndarray) -> np.ndarray:
        """Rows at arbitrary indices, read a run of ``_TAKE_RUN`` rows at a time."""
        rows = np.asarray(rows, dtype=np.int64)
        out = np.empty((len(rows), self.dim), dtype=np.float32)
        runs = rows // _TAKE_RUN
        for r in np.unique(runs):
            sel = np.flatnonzero(runs == r)
            lo, hi = int(rows[sel].min()), int(rows[sel].max()) + 1
            out[sel] = self.read(lo, hi)[rows[sel] - lo]
        return out

    def head(self, n: int) -> RowSource:
        """The first ``n`` rows as a source of its own."""
        if n > self.n_rows:
            raise InputError(f"{self.name}: {n} rows wanted but the source holds {self.n_rows}")
        return HeadSource(self, n)

    def to_dask(self, chunk_rows: int = 4 * BLOCK) -> da.Array:
        """A Dask array whose tasks each read their own rows (nothing in the graph)."""
        chunks = tuple(min(chunk_rows, self.n_rows - a) for a in range(0, self.n_rows, chunk_rows))

        def load(block_info: dict | None = None) -> np.ndarray:
            (a, b), _ = block_info[None]["array-location"]
            return self.read(a, b)

        return da.map_blocks(load, chunks=(chunks, (self.dim,)), dtype=np.float32,
                             meta=np.empty((0, self.dim), np.float32))

    def iter_chunks(self, chunk_rows: int = 2 * BLOCK):
        """Yield ``(start, rows)`` over the whole source, in order."""
        for a in range(0, self.n_rows, chunk_rows):
            b = min(self.n_rows, a + chunk_rows)
            yield a, self.read(a, b)


class HeadSource(RowSource):
    """The first ``n`` rows of another source."""

    def __init__(self, parent: RowSource, n: int) -> None:
        self.parent, self.n_rows, self.dim = parent, n, parent.dim
        self.name = parent.name

    def _read(self, start: int, stop: int) -> np.ndarray:
        return self.parent._read(start, stop)

    def fingerprint(self) -> dict[str, Any]:
        return {**self.parent.fingerprint(), "head": self.n_rows}

