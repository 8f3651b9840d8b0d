"""The baseline of docs/method.md: modified SeqSLAM on a one-component PCA, same storage budget.

For each query centre it scans all references by ``|x_i − y_t|``, keeps the ``N_r`` nearest
(ties: smaller id) and scores each as a sequence centre with ``Σ_l |x_{c+l} − y_{t+l}|``;
reference frames outside the map cost the full range of ``x``. On a map of many sequences only
centres whose window exists are candidates (:class:`vprscale.protocol.Sequences`).
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels
from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best

share_kernels()


@numba.njit(cache=True, nogil=True)
def _sift_down(hd: np.ndarray, hi: np.ndarray, n: int) -> None:
    """Restore a max-heap on (distance, id) after replacing its root."""
    i = 0
    while True:
        left, right, top = 2 * i + 1, 2 * i + 2, i
        if left < n and (hd[left] > hd[top] or (hd[left] == hd[top] and hi[left] > hi[top])):
            top = left
        if right < n and (hd[right] > hd[top] or (hd[right] == hd[top] and hi[right] > hi[top])):
            top = right
        if top == i:
            return
        hd[i], hd[top] = hd[top], hd[i]
        hi[i], hi[top] = hi[top], hi[i]
        i = top


@numba.njit(cache=True, nogil=True)
def nearest(x: np.ndarray, y: float, n_r: int, valid: np.ndarray) -> np.ndarray:
    """Ids of the ``n_r`` references nearest to ``y`` by a full scan (ties: smaller id), of those
    ``valid`` allows (one byte a reference, or empty: all); fewer where fewer are allowed."""
    hd = np.full(n_r, np.inf)
    hi = np.full(n_r, np.iinfo(np.int64).max)
    for i in range(x.shape[0]):
        if valid.shape[0] > 0 and valid[i] == 0:
            continue
        dist = abs(x[i] - y)
        if dist < hd[0]:  # ids arrive ascending: an equal distance never displaces a smaller id
            hd[0], hi[0] = dist, i
            _sift_down(hd, hi, n_r)
    found = np.sort(hi)
    return found[found < np.iinfo(np.int64).max]


@numba.njit(cache=True, nogil=True, parallel=True)
def baseline_batch(centres_t: np.ndarray, L: int, n_r: int, x: np.ndarray, y: np.ndarray,
                   x_range: float, valid: np.ndarray, n_best: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(top, scores, n_r)`` of every query centre (``y`` indexed by query frame): its
    ``n_best`` best candidates, best first (−1 where fewer), their scores, and the number
    of candidates, never a centre whose window ``valid`` rules out (many sequences)."""
    half = L // 2
    n_ref = x.shape[0]
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    counts = np.empty(centres_t.shape[0], np.int64)
    for qi in numba.prange(centres_t.shape[0]):
        t = centres_t[qi]
        cand = nearest(x, y[t], min(n_r, n_ref), valid)
        for c in cand:  # ascending
            s = 0.0
            bound = scores[qi, n_best - 1]
            for i in range(L):
                r = c + i - half
                s += x_range if (r < 0 or r >= n_ref) else abs(x[r] - y[t + i - half])
                if s > bound:  # terms are ≥ 0: this candidate can no longer enter the list
                    break
            keep_best(scores[qi], top[qi], s, c)
        counts[qi] = cand.shape[0]
    return finish_best(top), scores, counts
