"""Window scores over compact codes (docs/protocol.md, "Compact codes"): the sequence match of a
method whose frames retrieve their top-k references from a FAISS index.

A candidate centre ``c`` of the window at ``t`` scores ``Σ_l dist(y_{t+l}, decode(x_{c+l}))``,
the squared L2 distance between a query frame and a reference's decoded code. Two forms
compute it without decoding anything per pair:

- *tables*: ``dist = Σ_m tables[p, m, codes[r, m]]``, one 256-entry table per code byte and
  query frame. Product-quantiser codes (PQ, OPQ + PQ) give their asymmetric distances
  this way, exactly; binary codes give their Hamming distance (a byte's table holds
  ``popcount(q_m xor v)``), the distance their index searches with.
- *vectors*: the references' codes decoded once (``vectors[r]``) against the query frames.

Reference frames outside the map cost the largest distance seen in the window (over every
candidate); the match is the smallest score, ties to the smallest centre, and the next best
follow it.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best


@numba.njit(cache=True, nogil=True)
def _table_dist(tables: np.ndarray, p: np.int64, codes: np.ndarray, r: np.int64) -> np.float64:
    s = np.float64(0.0)
    for m in range(codes.shape[1]):
        s += tables[p, m, codes[r, m]]
    return s


@numba.njit(cache=True, nogil=True)
def _vector_dist(q: np.ndarray, p: np.int64, x: np.ndarray, r: np.int64) -> np.float64:
    s = np.float64(0.0)
    for j in range(x.shape[1]):
        diff = np.float64(q[p, j]) - np.float64(x[r, j])
        s += diff * diff
    return s


@numba.njit(cache=True, nogil=True, parallel=True)
def score_windows(centres_t: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
                  n_ref: int, tables: np.ndarray, codes: np.ndarray, q_vectors: np.ndarray,
                  vectors: np.ndarray, n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(top, scores)``: the ``n_best`` best candidates of every query, best first (−1 where
    fewer), and their scores. Query ``qi``'s candidates are ``cand[first[qi]:first[qi] +
    n_r[qi]]``, for the window centred at query-frame position ``centres_t[qi]``; tables
    form when ``tables`` is non-empty.
    """
    half = L // 2
    use_tables = tables.shape[0] > 0
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    for qi in numba.prange(centres_t.shape[0]):
        t = centres_t[qi]
        m = n_r[qi]
        sums = np.empty(m, np.float64)
        outside = np.empty(m, np.int64)
        largest = 0.0
        for j in range(m):
            c = cand[first[qi] + j]
            lo = max(0, half - c)  # window offsets whose reference frame lies inside the map
            hi = min(L, n_ref - c + half)
            s = 0.0
            for i in range(lo, hi):
                p, r = t + i - half, c + i - half
                dist = _table_dist(tables, p, codes, r) if use_tables else _vector_dist(q_vectors, p, vectors, r)
                s += dist
                largest = max(largest, dist)
            sums[j] = s
            outside[j] = lo + L - hi
        for j in range(m):
            keep_best(scores[qi], top[qi], sums[j] + outside[j] * largest, cand[first[qi] + j])
    return finish_best(top), scores
