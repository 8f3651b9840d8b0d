"""Sliding-window homogenisation of unordered Deep1B rows (docs/dataset.md, step 1).

Row ``i`` becomes the mean of source rows ``[max(0, i − w/2), min(n, i + w/2))``. The window
sum is a running float64 sum restarted at every absolute block, so a row's value depends
only on its position and the source, never on the chunking.
"""

from __future__ import annotations

import dask.array as da
import numba
import numpy as np

from vprscale.core.blocks import block_spans
from vprscale.core.kernelcache import share_kernels
from vprscale.dataset.sources.base import RowSource

share_kernels()


@numba.njit(cache=True, nogil=True)
def _running_window_mean(x: np.ndarray, base: int, lo: int, hi: int, n: int, half: int, centre: np.ndarray,
                         out: np.ndarray) -> None:
    """Means of rows ``lo … hi−1`` less ``centre`` (float32, after the mean's own rounding to
    float32, as numpy subtracts two float32 arrays); ``x`` holds source rows from absolute ``base``."""
    d = x.shape[1]
    acc = np.zeros(d)
    a, b = max(0, lo - half), min(n, lo + half)
    for k in range(a, b):
        for j in range(d):
            acc[j] += x[k - base, j]
    for i in range(lo, hi):
        na, nb = max(0, i - half), min(n, i + half)
        while b < nb:
            for j in range(d):
                acc[j] += x[b - base, j]
            b += 1
        while a < na:
            for j in range(d):
                acc[j] -= x[a - base, j]
            a += 1
        inv = 1.0 / (b - a)
        for j in range(d):
            out[i - lo, j] = np.float32(acc[j] * inv) - centre[j]


def window_mean(source: RowSource, n: int, start: int, stop: int, w: int,
                centre: np.ndarray | None = None) -> np.ndarray:
    """Homogenised rows ``[start, stop)`` of the first ``n`` source rows, window ``w``; less
    ``centre`` (cast to float32) when given: the centred rows a projection takes, in one pass."""
    half = w // 2
    centre = np.zeros(source.dim, np.float32) if centre is None else np.asarray(centre, np.float32)
    out = np.empty((stop - start, source.dim), dtype=np.float32)
    base = max(0, start - half)
    x = source.read(base, min(n, stop + half))  # one read with both halos: rows are drawn once
    for _, lo, hi in block_spans(start, stop):
        _running_window_mean(x, base, lo, hi, n, half, centre, out[lo - start : hi - start])
    return out


def homogenised(source: RowSource, n_read: int, n_kept: int, w: int, chunk_rows: int) -> da.Array:
    """The first ``n_kept`` homogenised rows (window over ``n_read`` rows) as a Dask array."""
    chunks = tuple(min(chunk_rows, n_kept - a) for a in range(0, n_kept, chunk_rows))

    def load(block_info: dict | None = None) -> np.ndarray:
        (a, b), _ = block_info[None]["array-location"]
        return window_mean(source, n_read, a, b, w)

    return da.map_blocks(load, chunks=(chunks, (source.dim,)), dtype=np.float32,
                         meta=np.empty((0, source.dim), np.float32))
