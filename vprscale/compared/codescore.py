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
  reference's inverted list ``l``. With ``‖y − c_l − ρ‖² = ‖y − c_l‖² + (‖ρ‖² + 2⟨c_l, ρ⟩)
  − 2⟨y, ρ⟩`` the distance is the frame's coarse distance to the list, the reference's
  query-independent term (a sum of FAISS's per-list tables) and one look-up per code byte in
  the frame's table: the three terms FAISS's IVF-PQ scan adds with its precomputed tables
  (``use_precomputed_table``), here for any list rather than the probed ones. A window
  bounds every candidate from 8-bit levels of the first two terms (the frame's nearest
  lists', :func:`near_levels`; the place's, :func:`ref_scale`) and computes the terms
  exactly for the few the bounds leave (:func:`_residual_best`).
- *vectors*: the references' codes decoded once (``vectors[r]``) against the query frames.

Reference frames outside the map cost the largest distance seen in the window (over every
candidate); the match is the smallest score, ties to the smallest centre, and the next best
follow it.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.method.intrinsics import popcount
from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best

# Relative rounding allowed between a window's sum of bounded terms and its exact sum (float64
# sums of terms of float32 parts differ by far less), so that the bounds stay bounds.
SLACK = 1e-6
# Relative error allowed in a coarse distance computed as ‖y‖² + ‖c‖² − 2⟨y, c⟩ in float32 (what
# FAISS's coarse step does), relative to ‖y‖² + ‖c‖²: about 100 roundings of 2^-24 at 96-d, doubled.
COARSE_ROUNDING = 1e-5


def ref_scale(per_list: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``(base, step, err)`` of residual places' query-independent terms ``‖ρ‖² + 2⟨c_l, ρ⟩``
    from FAISS's per-list tables (lists, sub-quantisers, codes): per list the smallest term
    its codes can give, and one step for 256 levels above it that spans the widest list's
    range; a term's level (:meth:`~vprscale.compared.faisscodes.FaissCodes.window_records`)
    gives it to within ``err`` (half a step, plus its float32 sum's rounding)."""
    tables = per_list.astype(np.float64)
    base = tables.min(axis=2).sum(axis=1)
    step = float((tables.max(axis=2).sum(axis=1) - base).max()) / 256 if len(tables) else 0.0
    err = 0.5 * step + SLACK * float(np.abs(tables).max(axis=2).sum(axis=1).max(initial=0.0))
    return base, step, err


def near_levels(coarse: np.ndarray, ref_base: np.ndarray, y: np.ndarray, centroid_norm: float, near: int,
                ref_step: float, ref_err: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the window scores keep of frames ``y``'s coarse distances to the centroids
    (frames, lists; float32, as FAISS computes them; ``centroid_norm`` the largest squared norm
    of a centroid), for the bounds :func:`score_windows` rules candidates out with.

    Each list's distance plus its places' smallest term (``ref_base``, :func:`ref_scale`) is
    ``g``; a frame keeps its ``near`` lists of smallest ``g`` (a bit per list, ``bits``, and
    per 64-bit word the count of near lists before it, ``ranks``) and their ``g`` as 256 even
    steps between the smallest and largest (``levels``, in list order); a list not kept is
    bounded below by the smallest ``g`` not kept and above by the largest. Returns
    ``(levels, scale, bits, ranks)``, ``scale`` per frame ``(base, step, err, far, gap,
    ref_step)``: a near list's ``g`` plus a place's term is ``base + step · level + ref_step ·
    place_level`` within ``err``; a far one's is at least ``far + ref_step · place_level − err``
    and at most that plus ``gap + 2 · err``.
    """
    g = np.asarray(coarse, np.float64) + ref_base[None, :]
    n, lists = g.shape
    if near < lists:
        order = np.argpartition(g, near, axis=1)
        kept = np.sort(order[:, :near], axis=1)
        far = np.take_along_axis(g, order[:, near : near + 1], axis=1)[:, 0]
    else:
        kept, far = np.broadcast_to(np.arange(lists), (n, lists)), np.full(n, np.inf)
    rows = np.take_along_axis(g, kept, axis=1)
    low, high = rows.min(axis=1, initial=np.inf), rows.max(axis=1, initial=-np.inf)
    step = np.where(high > low, (high - low) / 256, 0.0)
    levels = np.minimum(np.floor((rows - low[:, None]) / np.where(step > 0, step, 1)[:, None]), 255).astype(np.uint8)
    words = -(-lists // 64)
    marks = np.zeros((n, words * 64), bool)
    np.put_along_axis(marks, kept, True, axis=1)
    bits = np.packbits(marks.reshape(n, words, 64), axis=2, bitorder="little").view(np.uint64).reshape(n, words)
    counts = marks.reshape(n, words, 64).sum(axis=2)
    ranks = (np.cumsum(counts, axis=1) - counts).astype(np.uint16)
    norms = (np.asarray(y, np.float64) ** 2).sum(axis=1) + centroid_norm
    top = np.abs(g).max(axis=1, initial=0.0)
    err = 0.5 * step + COARSE_ROUNDING * norms + SLACK * top + ref_err
    half = 0.5 * ref_step
    gap = np.where(np.isfinite(far), g.max(axis=1, initial=0.0) - np.where(np.isfinite(far), far, 0.0), 0.0)
    scale = np.stack([low + 0.5 * step + half, step, err, far + half, gap, np.full(n, ref_step)], axis=1)
    return levels, scale, bits, ranks


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
def _record_list(records: np.ndarray, r: np.int64, width: int) -> np.int64:
    """The list number of residual place ``r``: the little-endian bytes of its record between
    its ``width`` code bytes and its term's level."""
    lst = np.int64(0)
    for b in range(records.shape[1] - 1 - width):
        lst |= np.int64(records[r, width + b]) << (8 * b)
    return lst


@numba.njit(cache=True, nogil=True, inline="always")
def _residual_dist(tables: np.ndarray, q_vectors: np.ndarray, centroids: np.ndarray, per_list: np.ndarray,
                   records: np.ndarray, p: np.int64, r: np.int64, width: int) -> np.float64:
    """The exact residual term of query frame ``p`` and reference ``r``: its coarse distance from
    the frame and the list's centroid, the place's term summed in float32 from the list's
    tables as FAISS sums it (and its level was taken from), and its code's look-ups."""
    lst = _record_list(records, r, width)
    term = np.float32(0.0)
    for m in range(width):
        term += per_list[lst, m, records[r, m]]
    dist = _table_dist(tables, p, records, r, width)
    return dist + (_coarse_dist(q_vectors, p, centroids, lst) + np.float64(term))


@numba.njit(cache=True, nogil=True)
def _residual_best(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, levels: np.ndarray,
                   scale: np.ndarray, bits: np.ndarray, ranks: np.ndarray, q_vectors: np.ndarray,
                   centroids: np.ndarray, per_list: np.ndarray, records: np.ndarray, best_s: np.ndarray,
                   best_c: np.ndarray) -> None:
    """The ``len(best_s)`` best candidates of the window centred at ``t`` by their exact
    residual scores, into ``(best_s, best_c)``, in two passes.

    A frame's distances to all 4,096 lists, read at random by a window's candidates, came
    from memory frame after frame (16 KB of float32, or 4 KB of 8-bit levels: 9 ns a term
    either way, docs/protocol.md). So the first pass reads less of a frame: which lists are
    among its nearest (a bit per list, and per word the rank of its first near list), their
    levels (:func:`near_levels`; 1.7 KB a frame at 1,024 of 4,096 lists), and per place one
    record (code, list, term level); it bounds every candidate's exact score from them (a
    far list's from the nearest not kept and the farthest). The second scores exactly only
    the candidates whose bounds do not rule them out of the best (about two at n_best = 1),
    and finds the exact largest term (the cost of reference frames outside the map) among
    the frames that could hold it. The answer is what exact scores of every candidate give,
    score for score.
    """
    half = L // 2
    width = tables.shape[1]
    level_at = records.shape[1] - 1
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)  # estimates of the in-map terms
    gaps = np.zeros(m, np.float64)  # what far lists add to the upper bounds
    frame_lo = np.full(L, -np.inf)  # per frame, the largest estimate, and the largest upper estimate
    frame_hi = np.full(L, -np.inf)
    one = np.uint64(1)
    for i in range(L):  # the bounds
        p = t + i - half
        base, step, far, gap, ref_step = scale[p, 0], scale[p, 1], scale[p, 3], scale[p, 4], scale[p, 5]
        lo_top, hi_top = -np.inf, -np.inf
        for j in range(m):
            r = cand[j] + i - half
            if 0 <= r < n_ref:
                lst = _record_list(records, r, width)
                word = bits[p, lst >> 6]
                shift = np.uint64(lst & 63)
                if (word >> shift) & one:
                    rank = np.int64(ranks[p, lst >> 6]) + popcount(word & ((one << shift) - one))
                    g, extra = base + step * levels[p, rank], 0.0
                else:
                    g, extra = far, gap
                dist = _table_dist(tables, p, records, r, width) + (g + ref_step * records[r, level_at])
                sums[j] += dist
                gaps[j] += extra
                lo_top = max(lo_top, dist)
                hi_top = max(hi_top, dist + extra)
        frame_lo[i], frame_hi[i] = lo_top, hi_top
    errs = np.zeros(L + 1)  # the frames' errors, summed from the window's first frame
    largest_lo, largest_hi = 0.0, 0.0  # bounds of the largest term
    for i in range(L):
        e = scale[t + i - half, 2]
        errs[i + 1] = errs[i] + e
        if frame_hi[i] > -np.inf:
            largest_lo = max(largest_lo, frame_lo[i] - e)
            largest_hi = max(largest_hi, frame_hi[i] + e)
    outside = np.empty(m, np.int64)
    low = np.empty(m, np.float64)
    high = np.empty(m, np.float64)
    for j in range(m):  # a candidate's references lie in the map for window frames first … last − 1
        first = min(L, max(0, half - cand[j]))
        last = max(first, min(L, n_ref - cand[j] + half))
        outside[j] = L - (last - first)
        slack = SLACK * (abs(sums[j]) + gaps[j] + outside[j] * largest_hi)
        err = errs[last] - errs[first] + slack
        low[j] = sums[j] - err + outside[j] * largest_lo
        high[j] = sums[j] + gaps[j] + err + outside[j] * largest_hi
    n = min(m, best_s.shape[0])
    bar = np.partition(high, n - 1)[n - 1] if m > 0 else 0.0  # the n-th best upper bound
    chosen = np.flatnonzero(low <= bar)
    exact = np.zeros(chosen.shape[0], np.float64)
    need_largest = (outside[chosen] > 0).any()
    exact_largest = 0.0
    for i in range(L):  # the chosen candidates' exact sums; the exact largest where it could lie
        p = t + i - half
        for c in range(chosen.shape[0]):
            r = cand[chosen[c]] + i - half
            if 0 <= r < n_ref:
                exact[c] += _residual_dist(tables, q_vectors, centroids, per_list, records, p, r, width)
        if need_largest and frame_hi[i] + scale[p, 2] >= largest_lo - SLACK * largest_hi:
            for j in range(m):
                r = cand[j] + i - half
                if 0 <= r < n_ref:
                    exact_largest = max(exact_largest, _residual_dist(tables, q_vectors, centroids, per_list,
                                                                      records, p, r, width))
    for c in range(chosen.shape[0]):
        j = chosen[c]
        keep_best(best_s, best_c, exact[c] + outside[j] * exact_largest, cand[j])


@numba.njit(cache=True, nogil=True, parallel=True)
def score_windows(centres_t: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
                  n_ref: int, tables: np.ndarray, levels: np.ndarray, scale: np.ndarray, bits: np.ndarray,
                  ranks: np.ndarray, per_list: np.ndarray, codes: np.ndarray, q_vectors: np.ndarray,
                  vectors: np.ndarray, centroids: np.ndarray, n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(top, scores)``: the ``n_best`` best candidates of every query, best first (−1 where
    fewer), and their scores. Query ``qi``'s candidates are ``cand[first[qi]:first[qi] +
    n_r[qi]]``, for the window centred at query-frame position ``centres_t[qi]``. The form
    follows what is given: residual tables when ``levels`` has frames (the frames' near
    lists, :func:`near_levels`; ``q_vectors`` the frames and ``centroids`` the lists'
    centroids, in the space the codes are in; ``codes`` the places' records and
    ``per_list`` their lists' tables), tables when ``tables`` has, decoded vectors otherwise.
    """
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    for qi in numba.prange(centres_t.shape[0]):
        mine = cand[first[qi] : first[qi] + n_r[qi]]
        if levels.shape[0] > 0:
            _residual_best(centres_t[qi], L, mine, n_ref, tables, levels, scale, bits, ranks, q_vectors, centroids,
                           per_list, codes, scores[qi], top[qi])
            continue
        sums, outside, largest = _window_sums(centres_t[qi], L, mine, n_ref, tables, codes, q_vectors, vectors)
        for j in range(mine.shape[0]):
            keep_best(scores[qi], top[qi], sums[j] + outside[j] * largest, mine[j])
    return finish_best(top), scores
