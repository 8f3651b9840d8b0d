"""The numba kernels of the query engine (docs/method.md): the symmetric code distance δ, the
references' codes (bit planes), and the batched sequence matcher. The lists' look-ups are
:mod:`vprscale.method.invlists`'s.

Sequence distances are computed in fixed point (int64; δ_max is ``DELTA_MAX_UNITS``), so that
sums are exact and associative: the batch kernel, any batching and the online matcher agree
bit for bit. :class:`~vprscale.method.index.Index` hands these kernels their arrays.
"""

from __future__ import annotations

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels
from vprscale.method.intrinsics import funnel_shift_right, popcount, prefetch
from vprscale.method.succinct import get_packed
from vprscale.protocol import NO_MASK

share_kernels()

DELTA_MAX_UNITS = 2**36  # δ_max in fixed point: L · d · δ never overflows int64
N_BEST = 20  # candidates an answer keeps, best first: Recall@N for N up to 20 (docs/protocol.md)
NO_CANDIDATE = np.iinfo(np.int64).max  # an empty place of a best-first list while it fills


@numba.njit(cache=True, nogil=True, inline="always")
def keep_best(best_s: np.ndarray, best_c: np.ndarray, s, c: np.int64) -> None:
    """Insert candidate ``c`` with score ``s`` into the best-first list ``(best_s, best_c)``
    if it belongs there (ordered by score, ties to the smaller candidate; a total order, so
    the list does not depend on the order candidates arrive in)."""
    j = best_s.shape[0] - 1
    if s > best_s[j] or (s == best_s[j] and c >= best_c[j]):
        return
    while j > 0 and (s < best_s[j - 1] or (s == best_s[j - 1] and c < best_c[j - 1])):
        best_s[j] = best_s[j - 1]
        best_c[j] = best_c[j - 1]
        j -= 1
    best_s[j] = s
    best_c[j] = c


@numba.njit(cache=True, nogil=True, inline="always")
def keep_best_at(best_s: np.ndarray, best_c: np.ndarray, base: np.int64, n: int, s, c: np.int64) -> None:
    """:func:`keep_best` on the list at ``base … base + n − 1`` of flat arrays: no array view
    is made per candidate (two views per scored pair cost as much as the score)."""
    j = base + n - 1
    if s > best_s[j] or (s == best_s[j] and c >= best_c[j]):
        return
    while j > base and (s < best_s[j - 1] or (s == best_s[j - 1] and c < best_c[j - 1])):
        best_s[j] = best_s[j - 1]
        best_c[j] = best_c[j - 1]
        j -= 1
    best_s[j] = s
    best_c[j] = c


@numba.njit(cache=True, nogil=True)
def finish_best(best_c: np.ndarray) -> np.ndarray:
    """Places of best-first lists that no candidate filled become −1."""
    flat = best_c.ravel()
    for i in range(flat.shape[0]):
        if flat[i] == NO_CANDIDATE:
            flat[i] = -1
    return best_c


def bit_gaps(w: np.ndarray) -> np.ndarray:
    """For K = 2: the cost of a differing bit ``b`` of two addresses (component ``d − 1 − b``'s gap)."""
    return np.ascontiguousarray(w[::-1, 0, 1])


def byte_tables(w: np.ndarray) -> np.ndarray:
    """For K = 2: δ of each byte of ``h1 xor h2`` as (⌈d/8⌉, 256) int64 tables.

    Bit ``b`` of an address is component ``d − 1 − b``; a differing bit costs that
    component's centre gap. δ is then ⌈d/8⌉ table look-ups (the paper's d/p xor term).
    """
    d = w.shape[0]
    gap = bit_gaps(w)
    n_bytes = (d + 7) // 8
    tables = np.zeros((n_bytes, 256), np.int64)
    values = np.arange(256)
    for i in range(n_bytes):
        for bit in range(8):
            b = 8 * i + bit
            if b < d:
                tables[i] += np.where(values >> bit & 1, gap[b], 0)
    return tables


@numba.njit(cache=True, nogil=True, inline="always")
def delta(h1: np.uint64, h2: np.uint64, w: np.ndarray, tables: np.ndarray, d: int, k: int) -> np.int64:
    """Fixed-point symmetric distance between the codes of two addresses."""
    s = np.int64(0)
    if k == 2:
        x = np.int64(h1 ^ h2)  # signed shifts: numba mixes uint64 with int64 through float64
        for i in range(tables.shape[0]):
            s += tables[i, (x >> (8 * i)) & 255]
        return s
    base = np.uint64(k)
    for j in range(d - 1, -1, -1):
        s += w[j, np.int64(h1 % base), np.int64(h2 % base)]
        h1 //= base
        h2 //= base
    return s


@numba.njit(cache=True, nogil=True, inline="always")
def code_at(codes: np.ndarray, code_bits: int, d: int, k: int, p: np.int64) -> np.uint64:
    """The address of reference ``p``: gathered from its bit in each of the ``d`` planes (K = 2),
    else read from the packed codes."""
    if k == 2:
        row = (p >> 6) * d
        bit = np.uint64(p & 63)
        v = np.uint64(0)
        for b in range(d):
            v |= ((codes[row + b] >> bit) & np.uint64(1)) << np.uint64(b)
        return v
    return get_packed(codes, code_bits, p)


@numba.njit(cache=True, nogil=True)
def decode_codes(codes: np.ndarray, code_bits: int, d: int, k: int, a: np.int64, b: np.int64) -> np.ndarray:
    """Addresses of references ``a … b − 1`` (uint64)."""
    out = np.empty(max(0, b - a), np.uint64)
    for p in range(a, b):
        out[p - a] = code_at(codes, code_bits, d, k, p)
    return out


@numba.njit(cache=True, nogil=True)
def score_window(c: np.int64, t: np.int64, L: int, half: int, codes: np.ndarray, code_bits: int, n_ref: int,
                 q_hash: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int, k: int, dmax: np.int64,
                 bound: np.int64) -> np.int64:
    """Score of centre ``c`` for the window at ``t``, abandoned once it reaches ``bound``.

    Reference frames outside the map cost δ_max each; the in-range offsets form one
    contiguous run, scanned without a branch per frame. δ ≥ 0, so a partial sum that has
    reached ``bound`` can only end at or above it: returning early changes no decision.
    """
    lo = max(0, half - c)  # first window offset whose reference frame is inside [0, n_ref)
    hi = min(L, n_ref - c + half)
    s = np.int64(lo + (L - hi)) * dmax
    for i in range(lo, hi):
        s += delta(code_at(codes, code_bits, d, k, c + i - half), q_hash[t + i - half], w, tables, d, k)
        if s >= bound:
            return s
    return s


@numba.njit(cache=True, nogil=True, parallel=True)
def score_centres(cand: np.ndarray, positions: np.ndarray, L: int, q_hash: np.ndarray, codes: np.ndarray,
                  code_bits: int, n_ref: int, w: np.ndarray, tables: np.ndarray, d: int, k: int,
                  dmax: np.int64) -> np.ndarray:
    """Window scores of given candidate centres: ``cand[i, j]`` for the window centred at query
    frame ``positions[i]`` (``NO_CANDIDATE`` where ``cand`` is negative). What re-ranks another
    method's proposals by CoarseHash's own score (a pooled sequence descriptor's, say)."""
    out = np.full(cand.shape, NO_CANDIDATE, np.int64)
    half = L // 2
    for i in numba.prange(cand.shape[0]):
        for j in range(cand.shape[1]):
            if cand[i, j] >= 0:
                out[i, j] = score_window(cand[i, j], positions[i], L, half, codes, code_bits, n_ref, q_hash, w,
                                         tables, d, k, dmax, NO_CANDIDATE)
    return out


PREFETCH = 8  # pairs whose reference window is fetched ahead of the one being scored
QUERY_BLOCK = 1 << 14  # queries matched together at most (a pair holds its query in 20 bits)
PAIR_BUDGET = 1 << 22  # proposals matched together at most: 32 MB per pair array
SORT_BLOCKS = 16  # blocks of queries whose candidates are counted and scattered in parallel by the pair sort
SCORE_CHUNKS = 16  # runs of sorted pairs scored in parallel, each keeping its own best per query
BUCKET_BITS = 12  # pairs are sorted by their window's position, 4096 places (12 KB of planes) at a time
MAX_BUCKETS = 1 << 16
CACHED_PLANES = 1 << 23  # bytes of bit planes that stay in cache: smaller maps keep pairs in query order


def plane_words(n: int, d: int) -> int:
    """Words of the bit planes of ``n`` places: rows of ``d`` words per 64 places, two zero rows after."""
    return (n // 64 + 2) * d


def bit_planes(h: np.ndarray, d: int) -> np.ndarray:
    """For K = 2: bit ``b`` of the addresses of places ``64·i … 64·i + 63`` as word ``i·d + b``.

    Flat (rows of ``d`` words), so that the short scoring kernel slices it directly: a
    reshape on every call cost twice the arithmetic. Two zero rows pad the end so that any
    window inside the map reads whole rows. This is also how an index stores its
    references' codes (P1, d bits per place): the engine maps the file and scores on it.
    """
    out = np.zeros(plane_words(len(h), d), np.uint64)
    planes_into(out, np.asarray(h, np.uint64), 0, d)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def planes_into(out: np.ndarray, h: np.ndarray, start: np.int64, d: int) -> None:
    """Set the plane bits of places ``start … start + len(h) − 1`` (their bits still zero), so a
    streamed job writes the planes chunk by chunk."""
    n = h.shape[0]
    if n == 0:
        return
    first, last = start >> 6, (start + n - 1) >> 6
    for blk in numba.prange(first, last + 1):
        row = out[blk * d:]
        for p in range(max(start, 64 * blk), min(start + n, 64 * blk + 64)):
            set_bit(row, h[p - start], p & 63, d)


@numba.njit(cache=True, nogil=True, inline="always")
def set_bit(row: np.ndarray, x: np.uint64, bit: int, d: int) -> None:
    """Bit ``bit`` of word ``b`` of a plane row becomes bit ``b`` of address ``x``, for every plane."""
    for b in range(d):
        row[b] |= ((x >> np.uint64(b)) & np.uint64(1)) << np.uint64(bit)


@numba.njit(cache=True, nogil=True, inline="always")
def _window_words(planes: np.ndarray, d: int, p: np.int64, e: int) -> np.uint64:
    """Word ``e`` (flat over word, plane) of the window of places starting at ``p``: 64 frames of one plane."""
    row = (p >> 6) * d
    return funnel_shift_right(planes[row + d + e], planes[row + e], np.uint64(p & 63))


@numba.njit(cache=True, nogil=True, inline="always")
def score_planes(p: np.int64, planes: np.ndarray, d: int, q_words: np.ndarray, masks: np.ndarray,
                  gaps: np.ndarray) -> np.int64:
    """K = 2 score of the window of references starting at ``p`` (all inside the map).

    Per plane, a popcount of the xor of 64 reference bits with 64 query bits counts the
    frames whose code differs in that component: ⌈L/64⌉·d words instead of L·⌈d/8⌉ table
    look-ups. ``q_words``, ``masks`` and ``gaps`` are flat over (word, plane), so one
    short loop runs over all of them and vectorises; the slices start at 0 so that numba adds
    no negative-index checks (which cost half the time).

    The sum is taken in float64, whose multiply-add is one instruction where an int64
    multiply is three: every product and partial sum is an integer below L·δ_max < 2^53
    (the caller checks), so it is exact in any order and the result equals the int64 sum.
    """
    lo = planes[(p >> 6) * d:]
    hi = planes[(p >> 6) * d + d:]
    sh = np.uint64(p & 63)
    s = 0.0
    for e in range(q_words.shape[0]):  # word e // d of plane e % d
        s += gaps[e] * np.float64(popcount((funnel_shift_right(hi[e], lo[e], sh) ^ q_words[e]) & masks[e]))
    return np.int64(s)


@numba.njit(cache=True, nogil=True, inline="always")
def _prefetch_window(planes: np.ndarray, d: int, p: np.int64, L: int) -> None:
    """Ask for the plane rows a window of ``L`` starting at ``p`` reads (one hint per 64-byte line)."""
    if p < 0:
        return
    first = (p >> 6) * d
    for e in range(first, min(first + ((L + 63) // 64 + 1) * d, planes.shape[0]), 8):
        prefetch(planes, e)


@numba.njit(cache=True, nogil=True)
def window_candidates(t: np.int64, L: int, half: int, aligned: bool, q_start: np.ndarray, q_stop: np.ndarray,
                ids: np.ndarray, n_ref: int, cand: np.ndarray, slots: np.ndarray, bits: int,
                valid: np.ndarray) -> int:
    """Distinct candidate centres of the window at ``t`` into ``cand``, in first-seen order.

    ``valid`` (one byte a reference, or empty: all) leaves out a centre whose window does not
    exist, one that would cross a sequence's end or a gap (:class:`vprscale.protocol.Sequences`).

    The proposals are first copied out of the lists, which lie next to each other
    (:class:`QueryFrames`); then an open-addressing set in ``slots`` (``2**bits`` entries,
    at least twice the proposals) removes repeats in O(1) each. (Sorting the proposals
    cost more than scoring them.)
    """
    m = 0
    for i in range(L):
        shift = i - half if aligned else 0
        for q in range(q_start[t + i - half], q_stop[t + i - half]):
            cand[m] = ids[q] - shift
            m += 1
    size = slots.shape[0]
    slots[:] = -1
    hash_shift = np.uint64(64 - bits)
    u = 0
    for j in range(m):
        c = cand[j]
        if c < 0 or c >= n_ref or (valid.shape[0] > 0 and valid[c] == 0):
            continue
        pos = np.int64((np.uint64(c) * np.uint64(0x9E3779B97F4A7C15)) >> hash_shift)
        while slots[pos] != -1 and slots[pos] != c:
            pos = (pos + 1) & (size - 1)
        if slots[pos] == -1:
            slots[pos] = c
            cand[u] = c
            u += 1
    return u


@numba.njit(cache=True, nogil=True, parallel=True)
def count_proposals(centres_t: np.ndarray, L: int, q_start: np.ndarray, q_stop: np.ndarray) -> np.ndarray:
    """Number of ids in the lists of each query's window (its candidates before repeats are dropped)."""
    proposals = np.empty(centres_t.shape[0], np.int64)
    for qi in numba.prange(centres_t.shape[0]):
        total = 0
        for i in range(L):
            total += q_stop[centres_t[qi] + i - L // 2] - q_start[centres_t[qi] + i - L // 2]
        proposals[qi] = total
    return proposals


@numba.njit(cache=True, nogil=True, parallel=True)
def propose(centres_t: np.ndarray, L: int, aligned: bool, q_start: np.ndarray, q_stop: np.ndarray,
             ids: np.ndarray, n_ref: int, proposals: np.ndarray, shift: int, valid: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(cand, first, n_r, counts)``: query ``qi``'s distinct candidates are ``cand[first[qi]:first[qi] + n_r[qi]]``.

    ``counts[block, bucket]`` counts each block of queries' candidates per bucket
    (``centre >> shift``) for :func:`_pairs_by_window`, while they are still in cache.
    """
    n = centres_t.shape[0]
    half = L // 2
    first = np.zeros(n + 1, np.int64)
    first[1:] = np.cumsum(proposals)
    cand = np.empty(first[n], np.int64)
    n_r = np.empty(n, np.int64)
    counts = np.zeros((SORT_BLOCKS, (n_ref >> shift) + 1), np.int64)
    for blk in numba.prange(SORT_BLOCKS):
        slots = np.empty(0, np.int64)
        for qi in range(n * blk // SORT_BLOCKS, n * (blk + 1) // SORT_BLOCKS):
            bits = 4
            while (1 << bits) < 2 * proposals[qi]:
                bits += 1
            if (1 << bits) > slots.shape[0]:
                slots = np.empty(1 << bits, np.int64)
            n_r[qi] = window_candidates(centres_t[qi], L, half, aligned, q_start, q_stop, ids, n_ref, cand[first[qi]:],
                                  slots[: 1 << bits], bits, valid)
            for j in range(first[qi], first[qi] + n_r[qi]):
                counts[blk, cand[j] >> shift] += 1
    return cand, first, n_r, counts


@numba.njit(cache=True, nogil=True)
def _bucket_shift(n_ref: int, map_bytes: int) -> int:
    """Bits of a centre below its sort bucket: 4096-place buckets, or one bucket for a cached map.

    Sorting pairs pays where windows would come from memory: a map of at most
    ``CACHED_PLANES`` bytes of planes stays in the caches, and there query order was
    faster (1M places, 2.5 MB: 15.7 µs per query against 18.8 sorted).
    """
    shift = BUCKET_BITS if map_bytes > CACHED_PLANES else 62
    while (n_ref >> shift) >= MAX_BUCKETS:
        shift += 1
    return shift


@numba.njit(cache=True, nogil=True, parallel=True)
def _pairs_by_window(cand: np.ndarray, first: np.ndarray, n_r: np.ndarray, counts: np.ndarray,
                     shift: int) -> np.ndarray:
    """Every (candidate, query) pair as ``centre << 20 | query``, ordered by ``centre >> shift``.

    A counting sort (the counts from :func:`propose`), its scatter split over the same
    blocks of queries, stable: inside a bucket pairs keep query order. Scoring pairs in
    this order reads the reference planes almost sequentially, once per batch, instead
    of one scattered window per pair: at 10M places and a thousand queries of L = 100
    the windows cover the map about three times over.
    """
    n = n_r.shape[0]
    total = 0
    for b in range(counts.shape[1]):
        for blk in range(SORT_BLOCKS):
            c = counts[blk, b]
            counts[blk, b] = total
            total += c
    pairs = np.empty(total, np.int64)
    for blk in numba.prange(SORT_BLOCKS):
        cursor = counts[blk]
        for qi in range(n * blk // SORT_BLOCKS, n * (blk + 1) // SORT_BLOCKS):
            for j in range(first[qi], first[qi] + n_r[qi]):
                b = cand[j] >> shift
                pairs[cursor[b]] = (cand[j] << 20) | qi
                cursor[b] += 1
    return pairs


@numba.njit(cache=True, nogil=True, parallel=True)
def _query_words(centres_t: np.ndarray, L: int, q_planes: np.ndarray, d: int) -> np.ndarray:
    """Every query window's bit planes, (query, word·plane), read out of the query frames' planes."""
    out = np.empty((centres_t.shape[0], (L + 63) // 64 * d), np.uint64)
    for qi in numba.prange(centres_t.shape[0]):
        for e in range(out.shape[1]):
            out[qi, e] = _window_words(q_planes, d, centres_t[qi] - L // 2, e)
    return out


@numba.njit(cache=True, nogil=True)
def window_masks(L: int, d: int, bit_gap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(masks, gaps)`` of a window of ``L`` frames, flat over (word, plane) as its query words:
    the frames each 64-bit word holds, and the cost of a differing bit of each plane."""
    n_words = (L + 63) // 64
    masks = np.full(n_words * d, np.uint64(0xFFFFFFFFFFFFFFFF))
    if L % 64:
        masks[-d:] = (np.uint64(1) << np.uint64(L % 64)) - np.uint64(1)
    gaps = np.empty(n_words * d, np.float64)
    for e in range(n_words * d):
        gaps[e] = bit_gap[e % d]
    return masks, gaps


@numba.njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract"})
def _score_pairs(pairs: np.ndarray, centres_t: np.ndarray, L: int, q_hash: np.ndarray, q_words: np.ndarray,
                 codes: np.ndarray, code_bits: int, n_ref: int, planes: np.ndarray, bit_gap: np.ndarray,
                 w: np.ndarray, tables: np.ndarray, d: int, k: int, dmax: np.int64, fast: bool, n_best: int,
                 runs: int) -> tuple[np.ndarray, np.ndarray]:
    """``(centres, scores)``: each query's ``n_best`` best pairs, best first (ties to the smaller centre).

    Runs of the sorted pairs are scored in parallel, each run keeping its own best-first
    list per query; the runs' lists are then merged. The order is total, so the lists do
    not depend on the number of runs or threads; there are two runs per thread (at most
    ``SCORE_CHUNKS``), so that a single-threaded call does not fill sixteen lists per query.
    """
    n = centres_t.shape[0]
    half = L // 2
    masks, gaps = window_masks(L, d, bit_gap)
    m = pairs.shape[0]
    run_s = np.full(runs * n * n_best, np.int64(2**62))  # flat: (run, query, place)
    run_c = np.full(runs * n * n_best, NO_CANDIDATE)
    for run in numba.prange(runs):
        stop = m * (run + 1) // runs
        for j in range(m * run // runs, stop):
            c = pairs[j] >> 20
            qi = pairs[j] & 0xFFFFF
            if fast and j + PREFETCH < stop:
                _prefetch_window(planes, d, (pairs[j + PREFETCH] >> 20) - half, L)
            base = (run * n + qi) * n_best
            if fast and c >= half and c - half + L <= n_ref:
                s = score_planes(c - half, planes, d, q_words[qi], masks, gaps)
            else:
                s = score_window(c, centres_t[qi], L, half, codes, code_bits, n_ref, q_hash, w, tables, d, k, dmax,
                                 run_s[base + n_best - 1] + 1)
            keep_best_at(run_s, run_c, base, n_best, s, c)
    for qi in numba.prange(n):  # every run's list merged into the first run's
        for run in range(1, runs):
            other = (run * n + qi) * n_best
            for j in range(other, other + n_best):
                if run_c[j] == NO_CANDIDATE:
                    break
                keep_best_at(run_s, run_c, qi * n_best, n_best, run_s[j], run_c[j])
    return finish_best(run_c[: n * n_best].reshape(n, n_best)), run_s[: n * n_best].reshape(n, n_best)


@numba.njit(cache=True, nogil=True)
def match_batch(centres_t: np.ndarray, L: int, aligned: bool, q_hash: np.ndarray, q_planes: np.ndarray,
                q_start: np.ndarray, q_stop: np.ndarray, q_ids: np.ndarray, codes: np.ndarray, code_bits: int,
                n_ref: int, planes: np.ndarray, gaps: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int,
                k: int, dmax: np.int64, valid: np.ndarray, n_best: int = 1, threads: int = SCORE_CHUNKS // 2
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sequence match of every query centre: ``(top, scores, n_r)``, its ``n_best`` best
    candidates best first (``top[:, 0]`` is the match; −1 where there were fewer), their
    fixed-point scores (``DELTA_MAX_UNITS`` per δ_max) and the number of candidates.
    ``threads`` (numba's, from the caller: reading it here would keep numba from caching
    the kernel) sets how many runs score pairs side by side; the answer does not depend on it.

    The query-frame arrays are those of :class:`QueryFrames` (the own address of the frame
    at position ``i``, its list ``q_ids[q_start[i]:q_stop[i]]``, the frames' bit planes),
    and ``centres_t`` are positions there (:meth:`QueryFrames.positions`). Paper mode scores
    every id of every window frame's list as a centre; aligned mode scores ``r − l`` for an
    id ``r`` in the list of frame ``t + l``. Ties go to the smallest centre.

    Queries are matched in blocks: each query's distinct candidates are collected (a small
    hash set per query), all (candidate, query) pairs of the block are sorted by where
    their reference window lies (:func:`_pairs_by_window`), and scored in that order, so
    that the bit planes of the map stream through the caches instead of being fetched
    window by window. ``valid`` (one byte a reference, or empty) leaves out the centres whose
    window does not exist (many sequences: :func:`window_candidates`). For K = 2 a window
    inside the map is scored on bit planes (:func:`score_planes`); other windows, and K > 2,
    frame by frame (:func:`score_window`).
    """
    n = centres_t.shape[0]
    # the bit-plane score sums in float64: exact while L·δ_max < 2^53
    fast = k == 2 and planes.shape[0] > 0 and np.float64(L) * np.float64(dmax) < 2.0**53
    top = np.empty((n, n_best), np.int64)
    scores = np.empty((n, n_best), np.int64)
    n_r = np.empty(n, np.int64)
    shift = _bucket_shift(n_ref, planes.shape[0] * 8)
    proposals = count_proposals(centres_t, L, q_start, q_stop)
    upto = np.cumsum(proposals)  # proposals of the queries up to each, inclusive
    lo = 0
    while lo < n:  # blocks of at most QUERY_BLOCK queries and PAIR_BUDGET proposals (at least one query)
        hi = min(n, lo + QUERY_BLOCK,
                 max(lo + 1, np.searchsorted(upto, upto[lo] - proposals[lo] + PAIR_BUDGET, "right")))
        t = centres_t[lo:hi]
        cand, first, block_n_r, counts = propose(t, L, aligned, q_start, q_stop, q_ids, n_ref, proposals[lo:hi],
                                                  shift, valid)
        pairs = _pairs_by_window(cand, first, block_n_r, counts, shift)
        q_words = _query_words(t, L, q_planes, d) if fast else np.zeros((t.shape[0], 0), np.uint64)
        top[lo:hi], scores[lo:hi] = _score_pairs(pairs, t, L, q_hash, q_words, codes, code_bits, n_ref, planes,
                                                 gaps, w, tables, d, k, dmax, fast, n_best,
                                                 min(SCORE_CHUNKS, max(1, 2 * threads)))
        n_r[lo:hi] = block_n_r
        lo = hi
    return top, scores, n_r


@numba.njit(cache=True, nogil=True)
def address_delta(h1: np.ndarray, h2: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int, k: int) -> np.ndarray:
    """Fixed-point δ between the codes of each pair of addresses ``h1[i]``, ``h2[i]``."""
    out = np.empty(h1.shape[0], np.int64)
    for i in range(h1.shape[0]):
        out[i] = delta(h1[i], h2[i], w, tables, d, k)
    return out


def ranked_lists(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start, stop, flat)``: top-k rows of a search (−1 padded) as lists one after another,
    frame ``i``'s found ids ``flat[start[i]:stop[i]]`` in rank order, what :func:`propose`
    reads. Built once per frame, with the per-frame work, not per window."""
    found = np.asarray(ids) >= 0
    stop = np.cumsum(found.sum(axis=1))
    return stop - found.sum(axis=1), stop, np.asarray(ids)[found].astype(np.int64)


def window_proposals(positions: np.ndarray, L: int, aligned: bool, lists: tuple, n_ref: int,
                     valid: np.ndarray = NO_MASK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(cand, first, n_r)`` of the windows centred at ``positions`` from per-frame
    :func:`ranked_lists`: the union of their lists (paper) or the centres their members imply
    (aligned), as CoarseHash's windows take theirs, never a centre ``valid`` rules out."""
    start, stop, flat = lists
    positions = np.asarray(positions, np.int64)
    cand, first, n_r, _ = propose(positions, L, aligned, start, stop, flat, n_ref,
                                  count_proposals(positions, L, start, stop), 62, valid)
    return cand, first, n_r
