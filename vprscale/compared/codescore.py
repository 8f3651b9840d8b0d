"""Window scores over compact codes (docs/protocol.md, "Compact codes"): the sequence match of a
method whose frames retrieve their top-k references from a FAISS index.

A candidate centre ``c`` of the window at ``t`` scores ``Σ_l dist(y_{t+l}, decode(x_{c+l}))``,
the squared L2 distance between a query frame and a reference's decoded code. Three forms
compute it:

- *tables*: ``dist = Σ_m tables[p, m, codes[r, m]]``, one 256-entry table per code byte and
  query frame. Product-quantiser codes (PQ, OPQ + PQ) give their asymmetric distances
  this way, exactly; binary codes give their Hamming distance (a byte's table holds
  ``popcount(q_m xor v)``), the distance their index searches with.
- *residual tables*: IVF-PQ codes encode ``x − c_l``, the residual from the centroid of the
  reference's inverted list ``l = lists_of[r]``. With ``‖y − c_l − ρ‖² = ‖y − c_l‖² +
  (‖ρ‖² + 2⟨c_l, ρ⟩) − 2⟨y, ρ⟩`` the distance is the frame's coarse distance to the list,
  the reference's query-independent term ``ref_terms[r]`` (computed once, at encoding, from
  FAISS's per-list tables) and one look-up per code byte in the frame's table: the three
  terms FAISS's IVF-PQ scan adds with its precomputed tables (``use_precomputed_table``),
  here for any list rather than the probed ones. The coarse distance is read as one of a
  frame's 8-bit ``levels`` to bound every candidate, and computed exactly for the few the
  bounds leave (:func:`_residual_best`).
- *vectors*: the references' codes decoded once (``vectors[r]``) against the query frames.

Reference frames outside the map cost the largest distance seen in the window (over every
candidate); the match is the smallest score, ties to the smallest centre, and the next best
follow it.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best

# Relative rounding allowed between a window's sum of bounded terms and its exact sum (float64
# sums of terms of float32 parts differ by far less), so that the bounds stay bounds.
SLACK = 1e-6
# Relative error allowed in a coarse distance computed as ‖y‖² + ‖c‖² − 2⟨y, c⟩ in float32 (what
# FAISS's coarse step does), relative to ‖y‖² + ‖c‖²: about 100 roundings of 2^-24 at 96-d, doubled.
COARSE_ROUNDING = 1e-5


def coarse_levels(coarse: np.ndarray, y: np.ndarray, centroid_norm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(levels, scale)`` of frames ``y``'s coarse distances to the centroids (frames, lists;
    float32, as FAISS computes them; ``centroid_norm`` the largest squared norm of a centroid):
    each frame's distances as one of 256 even steps
    between its smallest and largest, and per frame ``(base, step, err)`` with ``base + step ·
    level`` within ``err`` of the exact distance (half a step, plus the coarse distances' own
    rounding), the bounds :func:`score_windows` rules candidates out with."""
    rows = np.asarray(coarse, np.float64)
    if rows.shape[1] == 0:
        return np.zeros(rows.shape, np.uint8), np.zeros((len(rows), 3))
    low, high = rows.min(axis=1), rows.max(axis=1)
    step = (high - low) / 256
    levels = np.minimum(np.floor((rows - low[:, None]) / np.where(step > 0, step, 1)[:, None]), 255).astype(np.uint8)
    norms = (np.asarray(y, np.float64) ** 2).sum(axis=1) + centroid_norm
    err = 0.5 * step + COARSE_ROUNDING * norms + SLACK * np.maximum(np.abs(low), np.abs(high))
    return levels, np.stack([low + 0.5 * step, step, err], axis=1)


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
def _window_sums(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, codes: np.ndarray,
                 q_vectors: np.ndarray, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.float64]:
    """``(sums, outside, largest)`` of the window centred at query-frame position ``t`` over
    the candidate centres ``cand`` (tables or vectors form): each candidate's sum of terms
    inside the map, its count of reference frames outside it, and the largest term seen.

    The window's frames are the outer loop: each frame's tables (3 KB for 3 code bytes) stay
    in the first-level cache while every candidate reads its reference at that offset, and
    the candidates' code lines stay there from one frame to the next.
    """
    half = L // 2
    by_tables = tables.shape[0] > 0
    width = codes.shape[1]
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)
    outside = np.zeros(m, np.int64)
    largest = 0.0
    for i in range(L):
        p = t + i - half
        for j in range(m):
            r = cand[j] + i - half
            if r < 0 or r >= n_ref:  # a reference frame outside the map
                outside[j] += 1
                continue
            dist = _table_dist(tables, p, codes, r, width) if by_tables else _vector_dist(q_vectors, p, vectors, r)
            sums[j] += dist
            largest = max(largest, dist)
    return sums, outside, largest


@numba.njit(cache=True, nogil=True, inline="always")
def _coarse_dist(q: np.ndarray, p: np.int64, centroids: np.ndarray, lst: np.int64) -> np.float64:
    """``‖q[p] − centroids[lst]‖²`` in float64 over four running sums: one sum waits for its
    last addition at every term; four, in a fixed order, overlap and give the same bits
    everywhere."""
    s0 = s1 = s2 = s3 = np.float64(0.0)
    d = centroids.shape[1]
    whole = d - d % 4
    for j in range(0, whole, 4):
        a0 = np.float64(q[p, j]) - np.float64(centroids[lst, j])
        a1 = np.float64(q[p, j + 1]) - np.float64(centroids[lst, j + 1])
        a2 = np.float64(q[p, j + 2]) - np.float64(centroids[lst, j + 2])
        a3 = np.float64(q[p, j + 3]) - np.float64(centroids[lst, j + 3])
        s0 += a0 * a0
        s1 += a1 * a1
        s2 += a2 * a2
        s3 += a3 * a3
    for j in range(whole, d):
        a0 = np.float64(q[p, j]) - np.float64(centroids[lst, j])
        s0 += a0 * a0
    return (s0 + s1) + (s2 + s3)


@numba.njit(cache=True, nogil=True, inline="always")
def _residual_dist(tables: np.ndarray, q_vectors: np.ndarray, centroids: np.ndarray, ref_terms: np.ndarray,
                   lists_of: np.ndarray, codes: np.ndarray, p: np.int64, r: np.int64, width: int) -> np.float64:
    """The exact residual term of query frame ``p`` and reference ``r`` (its coarse distance
    from the frame and the list's centroid)."""
    dist = _table_dist(tables, p, codes, r, width)
    return dist + (_coarse_dist(q_vectors, p, centroids, np.int64(lists_of[r])) + np.float64(ref_terms[r]))


@numba.njit(cache=True, nogil=True)
def _residual_best(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, levels: np.ndarray,
                   scale: np.ndarray, q_vectors: np.ndarray, centroids: np.ndarray, ref_terms: np.ndarray,
                   lists_of: np.ndarray, codes: np.ndarray, best_s: np.ndarray, best_c: np.ndarray) -> None:
    """The ``len(best_s)`` best candidates of the window centred at ``t`` by their exact
    residual scores, into ``(best_s, best_c)``, in two passes.

    A frame's coarse distances to every list are 16 KB of float32 at 4,096 lists; held for
    every frame of an evaluation they took 6 GB at 10M and more than 24 GB at 1M. So the
    first pass reads each frame's 8-bit levels (:func:`coarse_levels`, a quarter of the
    bytes) and bounds every candidate's exact score from them; the second scores exactly
    only the candidates whose bounds do not rule them out of the best (about one at n_best
    = 1; their coarse distances from the frame and the centroid, in float64), and finds the
    exact largest term (the cost of reference frames outside the map) among the frames that
    could hold it. The answer is what exact scores of every candidate give, score for
    score; a term costs what it did with float32 rows (a frame's row comes from memory
    either way, docs/protocol.md).
    """
    half = L // 2
    width = codes.shape[1]
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)
    frame_max = np.full(L, -np.inf)
    copy_row = 32 * m >= levels.shape[1]  # many candidates for the row's length: copied, it is read in order
    row = np.empty(levels.shape[1] if copy_row else 0, np.uint8)
    for i in range(L):  # the bounds: sums of terms whose coarse distances are read as levels
        p = t + i - half
        if copy_row:
            row[:] = levels[p]
        base, step = scale[p, 0], scale[p, 1]
        top = -np.inf
        for j in range(m):
            r = cand[j] + i - half
            if 0 <= r < n_ref:
                level = row[lists_of[r]] if copy_row else levels[p, lists_of[r]]
                dist = _table_dist(tables, p, codes, r, width) + (base + step * level + np.float64(ref_terms[r]))
                sums[j] += dist
                top = max(top, dist)
        frame_max[i] = top
    errs = np.zeros(L + 1)  # the frames' errors, summed from the window's first frame
    err_max = 0.0
    for i in range(L):
        errs[i + 1] = errs[i] + scale[t + i - half, 2]
        if frame_max[i] > -np.inf:
            err_max = max(err_max, scale[t + i - half, 2])
    largest = max(0.0, frame_max.max())
    outside = np.empty(m, np.int64)
    margin = np.empty(m, np.float64)
    for j in range(m):  # a candidate's references lie in the map for window frames first … last − 1
        first = min(L, max(0, half - cand[j]))
        last = max(first, min(L, n_ref - cand[j] + half))
        outside[j] = L - (last - first)
        margin[j] = errs[last] - errs[first] + outside[j] * err_max + SLACK * (abs(sums[j]) + outside[j] * abs(largest))
        sums[j] += outside[j] * largest
    n = min(m, best_s.shape[0])
    bar = np.partition(sums + margin, n - 1)[n - 1] if m > 0 else 0.0  # the n-th best upper bound
    chosen = np.flatnonzero(sums - margin <= bar)
    exact = np.zeros(chosen.shape[0], np.float64)
    need_largest = (outside[chosen] > 0).any()
    exact_largest = 0.0
    for i in range(L):  # the chosen candidates' exact sums; the exact largest where it could lie
        p = t + i - half
        for c in range(chosen.shape[0]):
            r = cand[chosen[c]] + i - half
            if 0 <= r < n_ref:
                exact[c] += _residual_dist(tables, q_vectors, centroids, ref_terms, lists_of, codes, p, r, width)
        if need_largest and frame_max[i] + scale[p, 2] >= largest - err_max - SLACK * abs(largest):
            for j in range(m):
                r = cand[j] + i - half
                if 0 <= r < n_ref:
                    exact_largest = max(exact_largest, _residual_dist(tables, q_vectors, centroids, ref_terms,
                                                                      lists_of, codes, p, r, width))
    for c in range(chosen.shape[0]):
        j = chosen[c]
        keep_best(best_s, best_c, exact[c] + outside[j] * exact_largest, cand[j])


@numba.njit(cache=True, nogil=True, parallel=True)
def score_windows(centres_t: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
                  n_ref: int, tables: np.ndarray, levels: np.ndarray, scale: np.ndarray, ref_terms: np.ndarray,
                  lists_of: np.ndarray, codes: np.ndarray, q_vectors: np.ndarray, vectors: np.ndarray,
                  centroids: np.ndarray, n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(top, scores)``: the ``n_best`` best candidates of every query, best first (−1 where
    fewer), and their scores. Query ``qi``'s candidates are ``cand[first[qi]:first[qi] +
    n_r[qi]]``, for the window centred at query-frame position ``centres_t[qi]``. The form
    follows what is given: residual tables when ``levels`` has frames (:func:`coarse_levels`;
    ``q_vectors`` the frames and ``centroids`` the lists' centroids, in the space the
    codes are in), tables when ``tables`` has, decoded vectors otherwise.
    """
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    for qi in numba.prange(centres_t.shape[0]):
        mine = cand[first[qi] : first[qi] + n_r[qi]]
        if levels.shape[0] > 0:
            _residual_best(centres_t[qi], L, mine, n_ref, tables, levels, scale, q_vectors, centroids, ref_terms,
                           lists_of, codes, scores[qi], top[qi])
            continue
        sums, outside, largest = _window_sums(centres_t[qi], L, mine, n_ref, tables, codes, q_vectors, vectors)
        for j in range(mine.shape[0]):
            keep_best(scores[qi], top[qi], sums[j] + outside[j] * largest, mine[j])
    return finish_best(top), scores
