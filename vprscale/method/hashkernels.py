"""Fused numba kernels of CoarseHash: projection, quantisation, hashing and the fit statistics.

Each kernel works row by row from the float32 rows, with no (rows × d) float64 temporaries
beyond its output, so two threads run at full speed instead of contending for memory
bandwidth. Every projected value is a sum over the input columns in a fixed order, so a
row's bits depend on nothing but the row (not on the chunk or the number of rows).
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels

share_kernels()

_TILE = 1024  # rows projected at a time before they are binned column by column


@numba.njit(cache=True, nogil=True, inline="always")
def _project_row(x: np.ndarray, i: int, mean: np.ndarray, w: np.ndarray, acc: np.ndarray) -> None:
    acc[:] = 0.0
    for c in range(w.shape[0]):
        v = np.float64(x[i, c]) - mean[c]
        for j in range(w.shape[1]):  # independent lanes: vectorised without reassociation
            acc[j] += v * w[c, j]


@numba.njit(cache=True, nogil=True, inline="always")
def _project_block(x: np.ndarray, start: int, rows: int, mean: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:
    """Rows ``start … start + rows − 1`` of ``(x − mean) @ w`` into ``out[:rows]``.

    Four rows at a time: one row's sums form a chain through memory (add, store, load,
    add) that leaves the vector units idle; four independent chains keep them busy, 1.6×
    faster. Every value is still summed over the input columns in order, so the bits
    equal :func:`_project_row`'s.
    """
    r = 0
    while r + 4 <= rows:
        a0, a1, a2, a3 = out[r], out[r + 1], out[r + 2], out[r + 3]
        a0[:] = 0.0
        a1[:] = 0.0
        a2[:] = 0.0
        a3[:] = 0.0
        for c in range(w.shape[0]):
            m = mean[c]
            v0 = np.float64(x[start + r, c]) - m
            v1 = np.float64(x[start + r + 1, c]) - m
            v2 = np.float64(x[start + r + 2, c]) - m
            v3 = np.float64(x[start + r + 3, c]) - m
            wc = w[c]
            for j in range(w.shape[1]):
                a0[j] += v0 * wc[j]
                a1[j] += v1 * wc[j]
                a2[j] += v2 * wc[j]
                a3[j] += v3 * wc[j]
        r += 4
    for i in range(r, rows):
        _project_row(x, start + i, mean, w, out[i])


@numba.njit(cache=True, nogil=True)
def project_rows(x: np.ndarray, mean: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(x − mean) @ w`` in float64; ``w`` is the (D × d) transposed component matrix."""
    y = np.empty((x.shape[0], w.shape[1]))
    _project_block(x, 0, x.shape[0], mean, w, y)
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
    tile = np.empty((_TILE, d))
    outliers = np.empty(_TILE)
    for start in range(0, x.shape[0], _TILE):
        rows = min(_TILE, x.shape[0] - start)
        _project_block(x, start, rows, mean, w, tile)
        for j in range(d):  # column by column: one histogram row stays in cache
            low, high, base, top = ranges[0, j], ranges[1, j], lo[j], lo[j] + bins * width[j]
            inv = 1.0 / width[j]
            row = counts[j]
            m = 0
            for i in range(rows):
                v = tile[i, j]
                low = min(low, v)
                high = max(high, v)
                if base <= v < top:
                    row[min(int((v - base) * inv), bins - 1)] += 1
                else:
                    outliers[m] = v
                    m += 1
            ranges[0, j], ranges[1, j] = low, high
            if n_out + m > out_col.shape[0]:  # grown outside the loop above, which then stays tight
                out_col = np.concatenate((out_col, np.empty(n_out + m, np.int64)))
                out_val = np.concatenate((out_val, np.empty(n_out + m)))
            out_col[n_out:n_out + m] = j
            out_val[n_out:n_out + m] = outliers[:m]
            n_out += m
    return counts, ranges, out_col[:n_out], out_val[:n_out]


@numba.njit(cache=True, nogil=True)
def hash_rows(x: np.ndarray, mean: np.ndarray, w: np.ndarray, centres: np.ndarray, k: int,
              first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Codes, addresses, quantisation errors and per-component level counts of rows; into
    ``first`` (when it holds a value per row) each row's first projected component as float32.

    Code ``argmin_k |y_j − c_jk|`` (ties: the smaller k); address ``Σ_j K^(d−j) q_j`` with
    the first component as the top digit; error ``Σ_j min_k |y_j − c_jk|``. The first
    component is summed as :func:`project_rows` sums it with one component alone (each
    component is its own sum, in the same order): a compact build's baseline map comes free.
    """
    n, d = x.shape[0], w.shape[1]
    codes = np.empty((n, d), np.uint8)
    h = np.empty(n, np.uint64)
    err = np.empty(n)
    counts = np.zeros((d, k), np.int64)
    tile = np.empty((_TILE, d))
    base = np.uint64(k)
    for start in range(0, n, _TILE):
        rows = min(_TILE, n - start)
        _project_block(x, start, rows, mean, w, tile)
        for r in range(rows):
            i = start + r
            h[i], err[i] = _quantise(tile[r], centres, k, base, codes[i])
            if len(first):
                first[i] = np.float32(tile[r, 0])
            for j in range(d):
                counts[j, codes[i, j]] += 1
    return codes, h, err, counts


@numba.njit(cache=True, nogil=True, inline="always")
def _quantise(acc: np.ndarray, centres: np.ndarray, k: int, base: np.uint64,
              codes: np.ndarray) -> tuple[np.uint64, float]:
    """One projected row's codes (into ``codes``), address and quantisation error."""
    addr = np.uint64(0)
    e = 0.0
    for j in range(acc.shape[0]):
        best = abs(acc[j] - centres[j, 0])
        code = 0
        for level in range(1, k):
            dist = abs(acc[j] - centres[j, level])
            if dist < best:  # strict: a tie keeps the smaller level
                best, code = dist, level
        codes[j] = code
        addr = addr * base + np.uint64(code)
        e += best
    return addr, e


@numba.njit(cache=True, nogil=True, inline="always")
def hash_one(x: np.ndarray, i: int, mean: np.ndarray, w: np.ndarray, centres: np.ndarray, acc: np.ndarray,
             codes: np.ndarray) -> tuple[np.uint64, float]:
    """Row ``i``'s address and quantisation error, the bits :func:`hash_rows` gives it (the same
    projection, column by column, and the same quantisation), with no array made: what a live
    frame costs. ``acc`` and ``codes`` are scratch of d values."""
    _project_row(x, i, mean, w, acc)
    return _quantise(acc, centres, centres.shape[1], np.uint64(centres.shape[1]), codes)
