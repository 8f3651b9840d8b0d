"""Window scores over compact codes (docs/protocol.md, "Compact codes"): the sequence match of a
method whose frames retrieve their top-k references from a FAISS index.

A candidate centre ``c`` of the window at ``t`` scores ``Σ_l dist(y_{t+l}, decode(x_{c+l}))``,
the squared L2 distance between a query frame and a reference's decoded code. Two forms
compute it without decoding anything per pair:

- *tables*: ``dist = Σ_m tables[p, m, codes[r, m]]``, one 256-entry table per code byte and
  query frame. Product-quantiser codes (PQ, OPQ + PQ) give their asymmetric distances
  this way, exactly; binary codes give their Hamming distance (a byte's table holds
  ``popcount(q_m xor v)``), the distance their index searches with.
- *residual tables*: IVF-PQ codes encode ``x − c_l``, the residual from the centroid of the
  reference's inverted list ``l = lists_of[r]``. With ``‖y − c_l − ρ‖² = ‖y − c_l‖² +
  (‖ρ‖² + 2⟨c_l, ρ⟩) − 2⟨y, ρ⟩`` the distance is ``coarse[p, l] + ref_terms[r] + Σ_m
  tables[p, m, code]``: the frame's coarse distance to every list (what a flat coarse
  quantiser computes per frame), the reference's query-independent term (computed once, at
  encoding, from FAISS's per-list tables), and one look-up per code byte in the frame's
  table; the three terms FAISS's IVF-PQ scan adds with its precomputed tables
  (``use_precomputed_table``), here for any list rather than the probed ones.
- *vectors*: the references' codes decoded once (``vectors[r]``) against the query frames.

Reference frames outside the map cost the largest distance seen in the window (over every
candidate); the match is the smallest score, ties to the smallest centre, and the next best
follow it.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best


@numba.njit(cache=True, nogil=True, inline="always")
def _table_dist(tables: np.ndarray, p: np.int64, codes: np.ndarray, r: np.int64, width: int) -> np.float64:
    """``Σ_m tables[p, m, codes[r, m]]``, unrolled for the common widths of 3 and 4 bytes."""
    if width == 3:
        return (np.float64(tables[p, 0, codes[r, 0]]) + np.float64(tables[p, 1, codes[r, 1]])
                + np.float64(tables[p, 2, codes[r, 2]]))
    if width == 4:
        return (np.float64(tables[p, 0, codes[r, 0]]) + np.float64(tables[p, 1, codes[r, 1]])
                + np.float64(tables[p, 2, codes[r, 2]]) + np.float64(tables[p, 3, codes[r, 3]]))
    s = np.float64(0.0)
    for m in range(width):
        s += tables[p, m, codes[r, m]]
    return s


@numba.njit(cache=True, nogil=True, inline="always")
def _vector_dist(q: np.ndarray, p: np.int64, x: np.ndarray, r: np.int64) -> np.float64:
    s = np.float64(0.0)
    for j in range(x.shape[1]):
        diff = np.float64(q[p, j]) - np.float64(x[r, j])
        s += diff * diff
    return s


@numba.njit(cache=True, nogil=True)
def _window_sums(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, coarse: np.ndarray,
                 ref_terms: np.ndarray, lists_of: np.ndarray, codes: np.ndarray, q_vectors: np.ndarray,
                 vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.float64]:
    """``(sums, outside, largest)`` of the window centred at query-frame position ``t`` over
    the candidate centres ``cand``: each candidate's sum of terms inside the map, its count
    of reference frames outside it, and the largest term seen.

    The window's frames are the outer loop: each frame's tables (3 KB for 3 code bytes, and
    its coarse row) stay in the first-level cache while every candidate reads its reference
    at that offset, and the candidates' code lines stay there from one frame to the next.
    A frame's coarse row (16 KB at 4,096 lists) is one of thousands held, so it comes from
    memory: read in order into ``row`` it streams; read at each candidate's list it costs a
    miss per candidate (21 against 17 ns a term, 190 candidates, 4,096 lists). With few
    candidates for the row's length, the row is read in place.
    """
    half = L // 2
    form = 0 if coarse.shape[0] > 0 else 1 if tables.shape[0] > 0 else 2  # residual, tables, vectors
    width = codes.shape[1]
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)
    outside = np.zeros(m, np.int64)
    largest = 0.0
    copy_row = form == 0 and 32 * m >= coarse.shape[1]
    row = np.empty(coarse.shape[1] if copy_row else 0, np.float32)
    for i in range(L):
        p = t + i - half
        if copy_row:
            for lst in range(row.shape[0]):
                row[lst] = coarse[p, lst]
        for j in range(m):
            r = cand[j] + i - half
            if r < 0 or r >= n_ref:  # a reference frame outside the map
                outside[j] += 1
                continue
            if form == 2:
                dist = _vector_dist(q_vectors, p, vectors, r)
            else:
                dist = _table_dist(tables, p, codes, r, width)
                if form == 0:
                    coarse_term = row[lists_of[r]] if copy_row else coarse[p, lists_of[r]]
                    dist += np.float64(coarse_term) + np.float64(ref_terms[r])
            sums[j] += dist
            largest = max(largest, dist)
    return sums, outside, largest


@numba.njit(cache=True, nogil=True, parallel=True)
def score_windows(centres_t: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
                  n_ref: int, tables: np.ndarray, coarse: np.ndarray, ref_terms: np.ndarray, lists_of: np.ndarray,
                  codes: np.ndarray, q_vectors: np.ndarray, vectors: np.ndarray,
                  n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(top, scores)``: the ``n_best`` best candidates of every query, best first (−1 where
    fewer), and their scores. Query ``qi``'s candidates are ``cand[first[qi]:first[qi] +
    n_r[qi]]``, for the window centred at query-frame position ``centres_t[qi]``. The form
    follows what is given: residual tables when ``coarse`` has frames, tables when
    ``tables`` has, decoded vectors otherwise.
    """
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    for qi in numba.prange(centres_t.shape[0]):
        mine = cand[first[qi] : first[qi] + n_r[qi]]
        sums, outside, largest = _window_sums(centres_t[qi], L, mine, n_ref, tables, coarse, ref_terms, lists_of,
                                              codes, q_vectors, vectors)
        for j in range(mine.shape[0]):
            keep_best(scores[qi], top[qi], sums[j] + outside[j] * largest, mine[j])
    return finish_best(top), scores
