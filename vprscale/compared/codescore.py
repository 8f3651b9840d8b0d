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
  bounds every candidate from 8-bit levels of the first two terms (the frame's,
  :func:`coarse_levels`; the place's, :func:`ref_scale`) and computes the terms
  exactly for the few the bounds leave (:func:`_residual_best`).
- *factors* (RaBitQ, :mod:`vprscale.compared.rabitq`): ``dist = max(0, F_r + ‖y − c‖² −
  2 D_r Σ_b tables[p, b, signs[r, b]])``, the code's estimator of the distance, with the
  place's two factors from its record and the frame's distance to the code's centre: one
  per frame for a flat index (``scale[p, 0]``), to the place's list's centroid over an
  inverted file (computed, D operations; the centroids stay in cache).
- *vectors*: the references' codes decoded once (``vectors[r]``) against the query frames.

Reference frames outside the map cost the largest distance seen in the window (over every
candidate); the match is the smallest score, ties to the smallest centre, and the next best
follow it.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from vprscale.core.kernelcache import share_kernels
from vprscale.method.kernels import NO_CANDIDATE, finish_best, keep_best

share_kernels()

# Relative rounding allowed between a window's sum of bounded terms and its exact sum (float64
# sums of terms of float32 parts differ by far less), so that the bounds stay bounds.
SLACK = 1e-6
# Relative error allowed in a coarse distance computed as ‖y‖² + ‖c‖² − 2⟨y, c⟩ in float32 (what
# FAISS's coarse step does), relative to ‖y‖² + ‖c‖²: about 100 roundings of 2^-24 at 96-d, doubled.
COARSE_ROUNDING = 1e-5
# A residual place's record (:func:`place_records`) keeps its term's level in one byte.
REF_LEVEL_BYTES = 1


def place_records(sub: np.ndarray, list_bytes: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Residual IVF-PQ places' window records, the one layout :func:`score_windows` reads: per
    place its sub-quantiser indices (``sub``), its list number's little-endian bytes
    (``list_bytes``, as FAISS's standalone code holds them) and its term's level (``level``,
    :func:`ref_scale`). One record, not three arrays: a window reads a place's bytes from
    wherever it lies, and one line per place costs less than three."""
    return np.concatenate([sub, list_bytes, level[:, None].astype(np.uint8)], axis=1)


def list_numbers(codes: np.ndarray, list_bytes: int) -> np.ndarray:
    """The list numbers of standalone IVF codes: their first ``list_bytes`` bytes, little-endian
    (FAISS's ``coarse_code_size``; none for a flat index: list 0)."""
    return (codes[:, :list_bytes].astype(np.int64) << (8 * np.arange(list_bytes, dtype=np.int64))).sum(axis=1)


def record_width(code_width: int, list_bytes: int) -> int:
    """Bytes of a :func:`place_records` record."""
    return code_width + list_bytes + REF_LEVEL_BYTES


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


def coarse_levels(coarse: np.ndarray, ref_base: np.ndarray, y: np.ndarray, centroid_norm: float, ref_step: float,
                  ref_err: float) -> tuple[np.ndarray, np.ndarray]:
    """``(levels, scale)``: what the window scores keep of frames ``y``'s coarse distances to the
    centroids (frames, lists; float32, as FAISS computes them; ``centroid_norm`` the largest
    squared norm of a centroid), for the bounds :func:`score_windows` rules candidates out with.

    Each list's distance plus its places' smallest term (``ref_base``, :func:`ref_scale`) is
    ``g``; a frame keeps its ``g`` as one of 256 even steps between its smallest and largest
    (4 KB at 4,096 lists, a quarter of the float32 row), and per frame ``(base, step, err,
    ref_step)``: a list's ``g`` plus a place's term is ``base + step · level + ref_step ·
    place_level`` within ``err`` (half of each step, plus the coarse distances' own rounding).
    """
    if coarse.shape[1] == 0:
        return np.zeros(coarse.shape, np.uint8), np.zeros((len(coarse), 4))
    levels, low, high = _levels(np.ascontiguousarray(coarse, np.float32), np.ascontiguousarray(ref_base, np.float64))
    step = (high - low) / 256
    norms = (np.asarray(y, np.float64) ** 2).sum(axis=1) + centroid_norm
    err = 0.5 * step + COARSE_ROUNDING * norms + SLACK * np.maximum(np.abs(low), np.abs(high)) + ref_err
    return levels, np.stack([low + 0.5 * step + 0.5 * ref_step, step, err, np.full(len(low), ref_step)], axis=1)


@numba.njit(cache=True, nogil=True)
def _levels(coarse: np.ndarray, ref_base: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's ``g = coarse + ref_base`` (float64) as levels ``min(⌊(g − low) / step⌋, 255)``
    with ``step = (high − low) / 256`` (1 where 0), and its ``low`` and ``high``: a row at a time,
    the same operations as numpy's on the whole (frames × lists) float64 array, without it."""
    n, m = coarse.shape
    levels = np.empty((n, m), np.uint8)
    low = np.empty(n)
    high = np.empty(n)
    for f in range(n):
        lo = hi = np.float64(coarse[f, 0]) + ref_base[0]
        for j in range(1, m):
            g = np.float64(coarse[f, j]) + ref_base[j]
            lo = min(lo, g)
            hi = max(hi, g)
        step = (hi - lo) / 256
        if not step > 0:
            step = 1.0
        for j in range(m):
            levels[f, j] = np.uint8(min(np.floor((np.float64(coarse[f, j]) + ref_base[j] - lo) / step), 255.0))
        low[f], high[f] = lo, hi
    return levels, low, high


CACHE_LINE = 64  # bytes


@intrinsic
def _prefetch(typingctx: object, arr: types.Array, i: types.Integer) -> tuple:
    """Ask the processor to bring the cache line of ``arr[i]`` (a 1-d array) in, without
    waiting for it (LLVM's ``prefetch``: a read, kept in every cache level)."""
    if not (isinstance(arr, types.Array) and arr.ndim == 1 and isinstance(i, types.Integer)):
        return None

    def codegen(context, builder, sig, args):  # numba lowers a call to this
        array = context.make_array(sig.args[0])(context, builder, args[0])
        index = context.cast(builder, args[1], sig.args[1], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, sig.args[0], array, [index], wraparound=False)
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0i8")
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(arr, i), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _prefetch_row(rows: np.ndarray, p: np.int64) -> None:
    """Prefetch every line of row ``p`` of ``rows`` (a frame's tables or levels).

    A window reads each of its frames' rows at as many places as it has candidates; an
    evaluation's frames are too many for their rows to stay cached (7 KB a frame for IVF-PQ at
    4,096 lists), so each frame's lines come from memory, one miss after another as the
    candidates reach them. Asked for while the frame before is scored, they arrive together:
    on 200 windows spread over 1,200 (the evaluation's timed sample), IVF4096,PQ3's term cost
    17–19 ns without, 9–10 with (runs27/h15.py)."""
    row = rows[p].ravel()
    step = max(1, CACHE_LINE // row.itemsize)
    for q in range(0, row.shape[0], step):
        _prefetch(row, q)


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
def _squared_distance(q: np.ndarray, p: np.int64, x: np.ndarray, r: np.int64) -> np.float64:
    """``‖q[p] − x[r]‖²`` in float64 over eight running sums: one sum waits for its last addition
    at every term (96 dimensions: a chain of 96 additions); eight, in a fixed order, overlap (the
    vector units take them together: 2× at 10M) and give the same bits everywhere."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float64(0.0)
    d = x.shape[1]
    whole = d - d % 8
    for j in range(0, whole, 8):
        a0 = np.float64(q[p, j]) - np.float64(x[r, j])
        a1 = np.float64(q[p, j + 1]) - np.float64(x[r, j + 1])
        a2 = np.float64(q[p, j + 2]) - np.float64(x[r, j + 2])
        a3 = np.float64(q[p, j + 3]) - np.float64(x[r, j + 3])
        a4 = np.float64(q[p, j + 4]) - np.float64(x[r, j + 4])
        a5 = np.float64(q[p, j + 5]) - np.float64(x[r, j + 5])
        a6 = np.float64(q[p, j + 6]) - np.float64(x[r, j + 6])
        a7 = np.float64(q[p, j + 7]) - np.float64(x[r, j + 7])
        s0 += a0 * a0
        s1 += a1 * a1
        s2 += a2 * a2
        s3 += a3 * a3
        s4 += a4 * a4
        s5 += a5 * a5
        s6 += a6 * a6
        s7 += a7 * a7
    for j in range(whole, d):
        a0 = np.float64(q[p, j]) - np.float64(x[r, j])
        s0 += a0 * a0
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@numba.njit(cache=True, nogil=True, inline="always")
def _factors_dist(tables: np.ndarray, records: np.ndarray, factors: np.ndarray, p: np.int64, r: np.int64,
                  width: int, centre_dist: np.float64) -> np.float64:
    """A RaBitQ term: the place's factors ``F, D`` (the last two of its record's float32
    view), its signs' look-ups and the frame's distance to the code's centre (``centre_dist``)."""
    f = factors.shape[1]
    dot = _table_dist(tables, p, records, r, width)
    return max(0.0, np.float64(factors[r, f - 2]) + centre_dist - 2.0 * np.float64(factors[r, f - 1]) * dot)


@numba.njit(cache=True, nogil=True)
def _window_sums(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, codes: np.ndarray,
                 q_vectors: np.ndarray, vectors: np.ndarray, scale: np.ndarray,
                 centroids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.float64]:
    """``(sums, outside, largest)`` of the window centred at query-frame position ``t`` over
    the candidate centres ``cand`` (tables, factors or vectors form): each candidate's sum of
    terms inside the map, its count of reference frames outside it, and the largest term seen.

    Decoded rows are summed candidate by candidate (:func:`_vector_window_sums`); codes frame by
    frame, the window's frames the outer loop: each frame's tables (3 KB for 3 code bytes) stay
    in the first-level cache while every candidate reads its reference at that offset, and
    the candidates' code lines stay there from one frame to the next.
    """
    half = L // 2
    by_tables = tables.shape[0] > 0
    by_factors = by_tables and vectors.shape[0] > 0
    width = tables.shape[1] if by_factors else codes.shape[1]
    list_bytes = 0  # as FAISS's coarse_code_size: the bytes of the largest list number
    lists = centroids.shape[0] - 1
    while lists > 0:
        list_bytes += 1
        lists >>= 8
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)
    outside = np.zeros(m, np.int64)
    largest = 0.0
    if not by_tables:
        return _vector_window_sums(t, L, cand, n_ref, q_vectors, vectors, sums, outside)
    for i in range(L):
        p = t + i - half
        if by_tables and i + 1 < L:
            _prefetch_row(tables, p + 1)
        # RaBitQ: the frame's distance to the code's centre, one per frame (flat) or per list, kept
        # for the next candidate (half of a traverse's consecutive places share their list)
        centre_list, centre_dist = -1, scale[p, 0] if by_factors else 0.0
        for j in range(m):
            r = cand[j] + i - half
            if r < 0 or r >= n_ref:  # a reference frame outside the map
                outside[j] += 1
                continue
            if by_factors:
                if list_bytes > 0:
                    lst = _list_at(codes, r, width, list_bytes)
                    if lst != centre_list:
                        centre_list, centre_dist = lst, _squared_distance(q_vectors, p, centroids, lst)
                dist = _factors_dist(tables, codes, vectors, p, r, width, centre_dist)
            else:
                dist = _table_dist(tables, p, codes, r, width)
            sums[j] += dist
            largest = max(largest, dist)
    return sums, outside, largest


@numba.njit(cache=True, nogil=True, inline="always")
def _vector_window_sums(t: np.int64, L: int, cand: np.ndarray, n_ref: int, q_vectors: np.ndarray,
                        vectors: np.ndarray, sums: np.ndarray,
                        outside: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.float64]:
    """:func:`_window_sums` over decoded rows (a graph's own rows: 384 bytes a place at 96-d),
    candidate by candidate: a candidate's ``L`` consecutive rows are one run of memory the
    processor streams in, where frame by frame every term was a miss of its own (each sum
    still adds its terms in frame order: the same bits). The frames' rows, a few tens of KB,
    stay cached across candidates."""
    half = L // 2
    largest = 0.0
    for j in range(cand.shape[0]):
        for i in range(L):
            r = cand[j] + i - half
            if r < 0 or r >= n_ref:  # a reference frame outside the map
                outside[j] += 1
                continue
            dist = _squared_distance(q_vectors, t + i - half, vectors, r)
            sums[j] += dist
            largest = max(largest, dist)
    return sums, outside, largest


@numba.njit(cache=True, nogil=True, inline="always")
def _list_at(records: np.ndarray, r: np.int64, width: int, list_bytes: int) -> np.int64:
    """The list number of residual place ``r``: the ``list_bytes`` little-endian bytes of its
    record (:func:`place_records`) after its ``width`` code bytes."""
    lst = np.int64(0)
    for b in range(list_bytes):
        lst |= np.int64(records[r, width + b]) << (8 * b)
    return lst


@numba.njit(cache=True, nogil=True, inline="always")
def _bound_sums(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, levels: np.ndarray,
                scale: np.ndarray, records: np.ndarray, width: int, list_bytes: int, edge: bool,
                sums: np.ndarray, ref_levels: np.ndarray, frame_max: np.ndarray) -> None:
    """The first pass of :func:`_residual_best`, for records of ``width`` code bytes and
    ``list_bytes`` bytes of list number: into ``sums`` each candidate's sum of its terms' code
    look-ups and coarse levels (times their frames' steps), into ``ref_levels`` the sum of its
    places' term levels; the terms' bases are the caller's to add, per frame and not per term.

    Called with the common layouts' widths as constants, the record's offsets are constants
    too and the inner loop has no loop of its own: 11–13 against 16–19 ns a term on real 10M
    windows (runs27/h13.py). A window whose candidates all lie inside the map (``edge``
    false, nearly every one) checks no reference's position and keeps no frame's largest
    term (``frame_max``, only the cost of references outside the map needs it).
    """
    half = L // 2
    level_at = width + list_bytes  # the record's last byte (place_records)
    m = cand.shape[0]
    for i in range(L):
        p = t + i - half
        step = scale[p, 1]
        if i + 1 < L:  # the next frame's levels and tables, while this one is scored
            _prefetch_row(levels, p + 1)
            _prefetch_row(tables, p + 1)
        if edge:
            base, ref_step = scale[p, 0], scale[p, 3]
            top = -np.inf
            for j in range(m):
                r = cand[j] + i - half
                if 0 <= r < n_ref:
                    lst = _list_at(records, r, width, list_bytes)
                    dist = _table_dist(tables, p, records, r, width) + step * levels[p, lst]
                    sums[j] += dist
                    ref_levels[j] += records[r, level_at]
                    top = max(top, dist + (base + ref_step * records[r, level_at]))
            frame_max[i] = top
        else:
            for j in range(m):
                r = cand[j] + i - half
                lst = _list_at(records, r, width, list_bytes)
                sums[j] += _table_dist(tables, p, records, r, width) + step * levels[p, lst]
                ref_levels[j] += records[r, level_at]


@numba.njit(cache=True, nogil=True, inline="always")
def _smallest(values: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` smallest of ``values`` (``n`` at most their number), smallest first,
    ties to the smaller index: :func:`~vprscale.method.kernels.keep_best` over them, its empty
    places holding an index past every one (so any value, an infinite one too, takes them). A
    window keeps one or a few; numba's ``partition`` and ``argpartition`` copy and sort, about
    1 ns a term of the window."""
    keep_v = np.full(n, np.inf)
    keep_i = np.full(n, values.shape[0], np.int64)
    for j in range(values.shape[0]):
        keep_best(keep_v, keep_i, values[j], j)
    return keep_i


@numba.njit(cache=True, nogil=True, inline="always")
def _residual_dist(tables: np.ndarray, q_vectors: np.ndarray, centroids: np.ndarray, per_list: np.ndarray,
                   records: np.ndarray, p: np.int64, r: np.int64, width: int, list_bytes: int) -> np.float64:
    """The exact residual term of query frame ``p`` and reference ``r``: its coarse distance from
    the frame and the list's centroid, the place's term summed in float32 from the list's
    tables as FAISS sums it (and its level was taken from), and its code's look-ups."""
    lst = _list_at(records, r, width, list_bytes)
    term = np.float32(0.0)
    for m in range(width):
        term += per_list[lst, m, records[r, m]]
    dist = _table_dist(tables, p, records, r, width)
    return dist + (_squared_distance(q_vectors, p, centroids, lst) + np.float64(term))


@numba.njit(cache=True, nogil=True)
def _residual_best(t: np.int64, L: int, cand: np.ndarray, n_ref: int, tables: np.ndarray, levels: np.ndarray,
                   scale: np.ndarray, q_vectors: np.ndarray, centroids: np.ndarray, per_list: np.ndarray,
                   records: np.ndarray, best_s: np.ndarray, best_c: np.ndarray) -> None:
    """The ``len(best_s)`` best candidates of the window centred at ``t`` by their exact
    residual scores, into ``(best_s, best_c)``, in two passes.

    A frame's coarse distances to every list are 16 KB of float32 at 4,096 lists; held for
    every frame of an evaluation they took 6 GB at 10M and more than 24 GB at 1M. So the first
    pass reads each frame's 8-bit levels (:func:`coarse_levels`, a quarter of the bytes) and
    each place's record (code, list number and the level of its term: one line where three
    arrays took three), and bounds every candidate's exact score from them; the second scores
    exactly only the candidates whose bounds do not rule them out of the best (one or two at
    n_best = 1), and finds the exact largest term (the cost of reference frames outside the
    map) among the frames that could hold it. The answer is what exact scores of every
    candidate give, score for score.

    A frame's levels are read in place, where each list number points: copying the frame's
    4 KB row first, to read it in order, cost more than every look-up it saved (numba's
    element-wise copy: about 10 ns a term at 178 candidates a window).
    """
    half = L // 2
    width = tables.shape[1]
    list_bytes = records.shape[1] - REF_LEVEL_BYTES - width
    m = cand.shape[0]
    sums = np.zeros(m, np.float64)
    ref_levels = np.zeros(m, np.int64)
    frame_max = np.full(L, -np.inf)
    outside = np.empty(m, np.int64)
    firsts = np.empty(m, np.int64)
    lasts = np.empty(m, np.int64)
    for j in range(m):  # a candidate's references lie in the map for window frames first … last − 1
        firsts[j] = min(L, max(0, half - cand[j]))
        lasts[j] = max(firsts[j], min(L, n_ref - cand[j] + half))
        outside[j] = L - (lasts[j] - firsts[j])
    edge = (outside > 0).any()
    # the bounds: sums of terms whose coarse distances and place terms are read as levels
    if width == 3 and list_bytes == 2 and not edge:  # up to 65,536 lists, 3 sub-quantisers (IVF4096,PQ3)
        _bound_sums(t, L, cand, n_ref, tables, levels, scale, records, 3, 2, False, sums, ref_levels, frame_max)
    elif width == 4 and list_bytes == 2 and not edge:
        _bound_sums(t, L, cand, n_ref, tables, levels, scale, records, 4, 2, False, sums, ref_levels, frame_max)
    else:
        _bound_sums(t, L, cand, n_ref, tables, levels, scale, records, width, list_bytes, edge, sums, ref_levels,
                    frame_max)
    errs = np.zeros(L + 1)  # the frames' errors and bases, summed from the window's first frame
    bases = np.zeros(L + 1)
    err_max = 0.0
    for i in range(L):
        errs[i + 1] = errs[i] + scale[t + i - half, 2]
        bases[i + 1] = bases[i] + scale[t + i - half, 0]
        if frame_max[i] > -np.inf:
            err_max = max(err_max, scale[t + i - half, 2])
    largest = max(0.0, frame_max.max())
    ref_step = scale[t, 3]  # one step for every frame (coarse_levels)
    low = np.empty(m, np.float64)
    high = np.empty(m, np.float64)
    for j in range(m):
        sums[j] += ref_step * ref_levels[j] + (bases[lasts[j]] - bases[firsts[j]])
        margin = (errs[lasts[j]] - errs[firsts[j]] + outside[j] * err_max
                  + SLACK * (abs(sums[j]) + outside[j] * abs(largest)))
        low[j] = sums[j] + outside[j] * largest - margin
        high[j] = sums[j] + outside[j] * largest + margin
    exact_largest = 0.0
    if (outside > 0).any():  # the exact largest term, from the frames that could hold it
        for i in range(L):
            p = t + i - half
            if frame_max[i] + scale[p, 2] >= largest - err_max - SLACK * abs(largest):
                for j in range(m):
                    r = cand[j] + i - half
                    if 0 <= r < n_ref:
                        exact_largest = max(exact_largest, _residual_dist(tables, q_vectors, centroids, per_list,
                                                                          records, p, r, width, list_bytes))
    if m == 0:
        return
    # The bar: the n-th best upper bound, or the worst exact score of the n candidates of best
    # lower bounds if that is lower (exact scores are their own bounds; where candidates score
    # alike, noisy queries say, it rules more out). Every candidate of a lower bound above it
    # is out of the best.
    n = min(m, best_s.shape[0])
    bar = high[_smallest(high, n)[n - 1]]
    scored = np.zeros(m, np.bool_)
    for j in _smallest(low, n):
        s = _residual_score(t, L, cand[j], n_ref, tables, q_vectors, centroids, per_list, records, list_bytes,
                            outside[j] * exact_largest)
        scored[j] = True
        keep_best(best_s, best_c, s, cand[j])
    bar = min(bar, best_s[n - 1])
    for j in range(m):
        if not scored[j] and low[j] <= bar:
            keep_best(best_s, best_c, _residual_score(t, L, cand[j], n_ref, tables, q_vectors, centroids,
                                                      per_list, records, list_bytes, outside[j] * exact_largest),
                      cand[j])


@numba.njit(cache=True, nogil=True, inline="always")
def _residual_score(t: np.int64, L: int, c: np.int64, n_ref: int, tables: np.ndarray, q_vectors: np.ndarray,
                    centroids: np.ndarray, per_list: np.ndarray, records: np.ndarray, list_bytes: int,
                    outside_cost: float) -> np.float64:
    """The exact residual score of candidate centre ``c`` in the window centred at ``t``
    (records of ``list_bytes`` bytes of list number), its references outside the map costing
    ``outside_cost`` together.

    Its places' terms (12 MB of per-list tables at 4,096 lists) and centroids are read where
    its records point, one miss after another unless asked for first: a window's one or two
    exact scores cost as much as a third of its bound pass without (runs29/h19_run.py)."""
    half = L // 2
    width = tables.shape[1]
    terms = per_list.reshape(-1)
    for i in range(L):  # the lines of its places' terms and lists' centroids, asked for together
        r = c + i - half
        if 0 <= r < n_ref:
            lst = _list_at(records, r, width, list_bytes)
            for m in range(width):
                _prefetch(terms, (lst * width + m) * per_list.shape[2] + records[r, m])
            _prefetch_row(centroids, lst)
    s = np.float64(0.0)
    for i in range(L):
        r = c + i - half
        if 0 <= r < n_ref:
            s += _residual_dist(tables, q_vectors, centroids, per_list, records, t + i - half, r, width, list_bytes)
    return s + outside_cost


@numba.njit(cache=True, nogil=True, parallel=True)
def score_windows(centres_t: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
                  n_ref: int, tables: np.ndarray, levels: np.ndarray, scale: np.ndarray, per_list: np.ndarray,
                  codes: np.ndarray, q_vectors: np.ndarray, vectors: np.ndarray, centroids: np.ndarray,
                  n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(top, scores)``: the ``n_best`` best candidates of every query, best first (−1 where
    fewer), and their scores. Query ``qi``'s candidates are ``cand[first[qi]:first[qi] +
    n_r[qi]]``, for the window centred at query-frame position ``centres_t[qi]``. The form
    follows what is given: residual tables when ``levels`` has frames (:func:`coarse_levels`;
    ``q_vectors`` the frames and ``centroids`` the lists'
    centroids, in the space the codes are in; ``codes`` the places' records and
    ``per_list`` their lists' tables), factors when ``tables`` and ``vectors`` have (RaBitQ:
    ``codes`` the places' records, ``vectors`` their float32 view, ``centroids`` the lists'
    centroids of an inverted file, none for a flat index, whose frames' distances to its centre
    are ``scale[:, 0]``), tables when ``tables`` has, decoded vectors otherwise.
    """
    top = np.full((centres_t.shape[0], n_best), NO_CANDIDATE)
    scores = np.full((centres_t.shape[0], n_best), np.inf)
    for qi in numba.prange(centres_t.shape[0]):
        mine = cand[first[qi] : first[qi] + n_r[qi]]
        if levels.shape[0] > 0:
            _residual_best(centres_t[qi], L, mine, n_ref, tables, levels, scale, q_vectors, centroids, per_list,
                           codes, scores[qi], top[qi])
            continue
        sums, outside, largest = _window_sums(centres_t[qi], L, mine, n_ref, tables, codes, q_vectors, vectors, scale,
                                              centroids)
        for j in range(mine.shape[0]):
            keep_best(scores[qi], top[qi], sums[j] + outside[j] * largest, mine[j])
    return finish_best(top), scores
