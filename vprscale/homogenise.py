"""Sliding-window homogenisation of unordered Deep1B rows (SPEC §2 step 1).

Row ``i`` becomes the mean of source rows ``[max(0, i − w/2), min(n, i + w/2))``. Sums are
running sums in float64 restarted at every absolute block, so a row's value depends only on
its position and the source, never on the chunking.
"""

from __future__ import annotations

import dask.array as da
import numpy as np

from vprscale.blocks import block_spans
from vprscale.sources.base import RowSource


def window_mean(source: RowSource, n: int, start: int, stop: int, w: int) -> np.ndarray:
    """Homogenised rows ``[start, stop)`` of the first ``n`` source rows, window ``w``."""
    half = w // 2
    out = np.empty((stop - start, source.dim), dtype=np.float32)
    for _, lo, hi in block_spans(start, stop):
        base, top = max(0, lo - half), min(n, hi + half)
        csum = np.zeros((top - base + 1, source.dim))
        np.cumsum(source.read(base, top), axis=0, dtype=np.float64, out=csum[1:])
        rows = np.arange(lo, hi)
        a, b = np.maximum(0, rows - half), np.minimum(n, rows + half)
        sums = csum[b - base] - csum[a - base]
        out[lo - start : hi - start] = sums / (b - a)[:, None]
    return out


def homogenised(source: RowSource, n_read: int, n_kept: int, w: int, chunk_rows: int) -> da.Array:
    """The first ``n_kept`` homogenised rows (window over ``n_read`` rows) as a Dask array."""
    chunks = tuple(min(chunk_rows, n_kept - a) for a in range(0, n_kept, chunk_rows))

    def load(block_info: dict | None = None) -> np.ndarray:
        (a, b), _ = block_info[None]["array-location"]
        return window_mean(source, n_read, a, b, w)

    return da.map_blocks(load, chunks=(chunks, (source.dim,)), dtype=np.float32,
                         meta=np.empty((0, source.dim), np.float32))
