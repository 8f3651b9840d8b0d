"""A task's positives counted on a grid, never by a query × database matrix.

MSLS's positive of a query window is a database window holding a frame within the threshold of
one of the query's frames (:mod:`vprscale.evaluation.tasks`). The database frames are binned
in square cells as wide as the threshold, so a frame's neighbours lie in the 3 × 3 cells around
its own; each query window gathers the frames within the threshold there, and the kept windows
holding any of them are counted from prefix sums over the kept centres (the windows holding a
frame are the kept centres within half a window of it). At 10M database frames and 2M query
windows the whole count is one parallel pass; the positives themselves are never listed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels

share_kernels()


@dataclass
class Grid:
    """A city's database frames binned in cells of ``cell`` metres: ``members[starts[i]:starts[i + 1]]``
    are the rows in the cell numbered ``keys[i]`` (``x · ny + y``, from ``origin``)."""

    keys: np.ndarray
    starts: np.ndarray
    members: np.ndarray
    origin: np.ndarray
    ny: int
    nx: int
    cell: float


def grid(pos: np.ndarray, rows: np.ndarray, cell: float) -> Grid:
    """The grid of database ``rows`` (their positions ``pos[rows]``)."""
    p = pos[rows]
    origin = p.min(axis=0) if len(p) else np.zeros(2)
    ix = np.floor((p - origin) / cell).astype(np.int64)
    nx, ny = (int(ix[:, 0].max()) + 1, int(ix[:, 1].max()) + 1) if len(p) else (1, 1)
    key = ix[:, 0] * ny + ix[:, 1]
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    return Grid(keys, np.append(starts, len(order)).astype(np.int64), rows[order].astype(np.int64),
                origin.astype(np.float64), ny, nx, float(cell))


@numba.njit(cache=True, nogil=True)
def _cell(g_keys: np.ndarray, key: np.int64) -> np.int64:
    i = np.searchsorted(g_keys, key)
    return i if i < g_keys.shape[0] and g_keys[i] == key else -1


@numba.njit(cache=True, nogil=True, parallel=True)
def window_counts(q_pos: np.ndarray, first: np.ndarray, q_len: int, g_keys: np.ndarray, g_starts: np.ndarray,
                  g_members: np.ndarray, origin: np.ndarray, nx: int, ny: int, cell: float, db_pos: np.ndarray,
                  kept_before: np.ndarray, half: int, threshold: float) -> np.ndarray:
    """For each query window (frames ``first[i] … first[i] + q_len − 1``), the kept database
    windows holding a frame within ``threshold`` of one of its frames: kept centres within
    ``half`` of such a frame, counted from ``kept_before`` (kept centres before each row)."""
    n_db = kept_before.shape[0] - 1
    counts = np.zeros(first.shape[0], np.int64)
    t2 = threshold * threshold
    for i in numba.prange(first.shape[0]):
        bound = 0
        for j in range(q_len):
            cx = np.int64(np.floor((q_pos[first[i] + j, 0] - origin[0]) / cell))
            cy = np.int64(np.floor((q_pos[first[i] + j, 1] - origin[1]) / cell))
            for x in range(cx - 1, cx + 2):
                for y in range(cy - 1, cy + 2):
                    if 0 <= x < nx and 0 <= y < ny:
                        c = _cell(g_keys, x * ny + y)
                        if c >= 0:
                            bound += g_starts[c + 1] - g_starts[c]
        if bound == 0:
            continue
        found = np.empty(bound, np.int64)
        m = 0
        for j in range(q_len):
            qx, qy = q_pos[first[i] + j, 0], q_pos[first[i] + j, 1]
            cx = np.int64(np.floor((qx - origin[0]) / cell))
            cy = np.int64(np.floor((qy - origin[1]) / cell))
            for x in range(cx - 1, cx + 2):
                for y in range(cy - 1, cy + 2):
                    if 0 <= x < nx and 0 <= y < ny:
                        c = _cell(g_keys, x * ny + y)
                        if c >= 0:
                            for k in range(g_starts[c], g_starts[c + 1]):
                                r = g_members[k]
                                dx, dy = db_pos[r, 0] - qx, db_pos[r, 1] - qy
                                if dx * dx + dy * dy <= t2:
                                    found[m] = r
                                    m += 1
        if m == 0:
            continue
        found = np.sort(found[:m])
        lo, hi = found[0] - half, found[0] + half + 1  # the span of centres whose windows hold the frames so far
        total = 0
        for k in range(1, m):
            f = found[k]
            if f - half > hi:  # a gap: the span so far is counted
                total += kept_before[min(max(hi, 0), n_db)] - kept_before[min(max(lo, 0), n_db)]
                lo = f - half
            hi = f + half + 1
        total += kept_before[min(max(hi, 0), n_db)] - kept_before[min(max(lo, 0), n_db)]
        counts[i] = total
    return counts
