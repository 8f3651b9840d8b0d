"""Fused numba kernels of CoarseHash: projection, quantisation, hashing and the fit statistics.

Each kernel works row by row from the float32 rows, with no (rows × d) float64 temporaries
beyond its output, so two threads run at full speed instead of contending for memory
bandwidth. Every projected value is a sum over the input columns in a fixed order, so a
row's bits depend on nothing but the row (not on the chunk or the number of rows).
"""

from __future__ import annotations

import numba
import numpy as np

_TILE = 1024  # rows projected at a time before they are binned column by column


@numba.njit(cache=True, nogil=True, inline="always")
def _project_row(x: np.ndarray, i: int, mean: np.ndarray, w: np.ndarray, acc: np.ndarray) -> None:
    acc[:] = 0.0
    for c in range(w.shape[0]):
        v = np.float64(x[i, c]) - mean[c]
        for j in range(w.shape[1]):  # independent lanes: vectorised without reassociation
            acc[j] += v * w[c, j]


@numba.njit(cache=True, nogil=True)
def project_rows(x: np.ndarray, mean: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(x − mean) @ w`` in float64; ``w`` is the (D × d) transposed component matrix."""
    y = np.empty((x.shape[0], w.shape[1]))
    acc = np.empty(w.shape[1])
    for i in range(x.shape[0]):
        _project_row(x, i, mean, w, acc)
        y[i] = acc
    return y


@numba.njit(cache=True, nogil=True)
def column_histogram(x: np.ndarray, mean: np.ndarray, w: np.ndarray, lo: np.ndarray, width: np.ndarray,
                     bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Histograms of every projected column over ``[lo, lo + bins · width)``, in one pass.

    Returns ``(counts (d × bins), ranges (2 × d), outlier columns, outlier values)``: values
    outside the histogram's range are returned exactly rather than binned.
    """
    d = w.shape[1]
    counts = np.zeros((d, bins), np.int64)
    ranges = np.empty((2, d))
    ranges[0] = np.inf
    ranges[1] = -np.inf
    out_col = np.empty(256, np.int64)
    out_val = np.empty(256)
    n_out = 0
    acc = np.empty(d)
    tile = np.empty((_TILE, d))
    for start in range(0, x.shape[0], _TILE):
        rows = min(_TILE, x.shape[0] - start)
        for i in range(rows):
            _project_row(x, start + i, mean, w, acc)
            tile[i] = acc
        for j in range(d):  # column by column: one histogram row stays in cache
            low, high, base, top = ranges[0, j], ranges[1, j], lo[j], lo[j] + bins * width[j]
            inv = 1.0 / width[j]
            for i in range(rows):
                v = tile[i, j]
                low = min(low, v)
                high = max(high, v)
                if base <= v < top:
                    counts[j, min(int((v - base) * inv), bins - 1)] += 1
                else:
                    if n_out == out_col.shape[0]:
                        out_col = np.concatenate((out_col, np.empty(n_out, np.int64)))
                        out_val = np.concatenate((out_val, np.empty(n_out)))
                    out_col[n_out] = j
                    out_val[n_out] = v
                    n_out += 1
            ranges[0, j], ranges[1, j] = low, high
    return counts, ranges, out_col[:n_out], out_val[:n_out]


@numba.njit(cache=True, nogil=True)
def hash_rows(x: np.ndarray, mean: np.ndarray, w: np.ndarray, centres: np.ndarray,
              k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Codes, addresses, quantisation errors and per-component level counts of rows.

    Code ``argmin_k |y_j − c_jk|`` (ties: the smaller k); address ``Σ_j K^(d−j) q_j`` with
    the first component as the top digit; error ``Σ_j min_k |y_j − c_jk|``.
    """
    n, d = x.shape[0], w.shape[1]
    codes = np.empty((n, d), np.uint8)
    h = np.empty(n, np.uint64)
    err = np.empty(n)
    counts = np.zeros((d, k), np.int64)
    acc = np.empty(d)
    base = np.uint64(k)
    for i in range(n):
        _project_row(x, i, mean, w, acc)
        addr = np.uint64(0)
        e = 0.0
        for j in range(d):
            best = abs(acc[j] - centres[j, 0])
            code = 0
            for level in range(1, k):
                dist = abs(acc[j] - centres[j, level])
                if dist < best:  # strict: a tie keeps the smaller level
                    best, code = dist, level
            codes[i, j] = code
            counts[j, code] += 1
            addr = addr * base + np.uint64(code)
            e += best
        h[i] = addr
        err[i] = e
    return codes, h, err, counts
