"""Exact 1-D k-means of weighted points (the per-component quantiser of docs/method.md).

In one dimension the optimal clusters are contiguous runs of the sorted points, so the
global optimum is a dynamic programme over split points (Wang & Song 2011); the
divide-and-conquer form costs O(K · B · log B) for B points. Streamed columns are reduced
to a histogram of B bins first: the result is then the exact optimum of the data with
every value moved to its bin's midpoint, i.e. by at most half a bin width.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels

share_kernels()


@numba.njit(cache=True)
def _segment_cost(cw: np.ndarray, cx: np.ndarray, cxx: np.ndarray, i: int, j: int) -> float:
    """Weighted sum of squared deviations of points ``i … j−1`` from their mean."""
    w = cw[j] - cw[i]
    if w <= 0:
        return 0.0
    s = cx[j] - cx[i]
    return max(0.0, (cxx[j] - cxx[i]) - s * s / w)


@numba.njit(cache=True)
def _dp(x: np.ndarray, w: np.ndarray, k: int) -> np.ndarray:
    """Split points of the optimal ``k`` contiguous clusters of sorted points ``x``."""
    n = x.shape[0]
    cw = np.zeros(n + 1)
    cx = np.zeros(n + 1)
    cxx = np.zeros(n + 1)
    for t in range(n):
        cw[t + 1] = cw[t] + w[t]
        cx[t + 1] = cx[t] + w[t] * x[t]
        cxx[t + 1] = cxx[t] + w[t] * x[t] * x[t]
    inf = np.inf
    prev = np.full(n + 1, inf)
    for j in range(n + 1):
        prev[j] = _segment_cost(cw, cx, cxx, 0, j)
    arg = np.zeros((k + 1, n + 1), dtype=np.int64)
    for level in range(2, k + 1):
        cur = np.full(n + 1, inf)
        # Divide and conquer over j: the optimal split opt(j) is monotone in j.
        stack = [(0, n, 0, n)]
        while len(stack) > 0:
            jlo, jhi, olo, ohi = stack.pop()
            if jlo > jhi:
                continue
            j = (jlo + jhi) // 2
            best, best_i = inf, olo
            for i in range(olo, min(j, ohi) + 1):
                v = prev[i] + _segment_cost(cw, cx, cxx, i, j)
                if v < best:
                    best, best_i = v, i
            cur[j] = best
            arg[level, j] = best_i
            stack.append((jlo, j - 1, olo, best_i))
            stack.append((j + 1, jhi, best_i, ohi))
        prev = cur
    splits = np.zeros(k + 1, dtype=np.int64)
    splits[k] = n
    j = n
    for level in range(k, 1, -1):
        j = arg[level, j]
        splits[level - 1] = j
    return splits


def kmeans_1d(values: np.ndarray, weights: np.ndarray, k: int) -> np.ndarray:
    """Centres (ascending) of the globally optimal weighted 1-D k-means.

    ``values`` must be sorted ascending; zero-weight points are ignored. With fewer than
    ``k`` distinct values the missing centres repeat the largest one.
    """
    keep = weights > 0
    x, w = np.asarray(values, np.float64)[keep], np.asarray(weights, np.float64)[keep]
    if len(x) == 0:
        raise ValueError("k-means of an empty column")
    splits = _dp(x, w, min(k, len(x)))
    centres = [np.average(x[a:b], weights=w[a:b]) for a, b in zip(splits[:-1], splits[1:], strict=True) if b > a]
    centres += [centres[-1]] * (k - len(centres))
    return np.asarray(centres)
