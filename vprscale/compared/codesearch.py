"""A flat code's exact top-k without scanning its places (docs/protocol.md, "Compact codes").

A flat FAISS index (PQ, OPQ + PQ, binary LSH and ITQ codes) answers a frame by scanning every
place: 25-35 ms a frame for 3-byte product-quantiser codes at 10M places, so 1,000 centres of
100 frames cost 20 minutes per code and noise level. Its answer depends on the code *values*
only: places with one code are at one distance. So a map's distinct values are listed once
(:func:`code_lists`: each value's places, ascending) and a frame visits values in increasing
distance until its k nearest places are certain:

- product-quantiser codes: the multi-sequence algorithm of the inverted multi-index (Babenko
  and Lempitsky, 2012) over each sub-quantiser's table sorted ascending, a heap of index
  tuples whose sums only grow (each tuple has one parent: itself less one in its last
  non-zero place), so values leave the heap in order of distance;
- binary codes: Hamming balls of growing radius around the frame's own code.

Both give the ``k`` smallest (distance, id) pairs, what FAISS's scan keeps (its heap takes a
place only at a strictly smaller distance, and scans places in id order). Distances here are
float64 sums of float64 tables; FAISS sums float32 ones, so the two can order places
differently only where their distances tie to float32 rounding (:func:`agree` checks that
nothing else differs). A frame whose nearest values are empty for more than ``budget`` visits
(a sparse code space far from the frame) is answered by a pass over the distinct values
instead: the same pairs, at a scan's cost.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels

share_kernels()

NO_PLACE = -1
MAX_KEY_BITS = 62  # a code value is one int64 key: Σ index_m << (bits · m)
# A visit (a heap pop and its pushes, a value's look-up) costs about as much as 32–40 values of a pass
# (runs29: 0.2 µs against 5 ns), so a frame visits at most 1/32 of the distinct values before a pass:
# a frame that needs the pass pays at most twice its cost, as in ski rental
BUDGET_SHARE = 32
MIN_BUDGET = 64


def code_keys(codes: np.ndarray, bits: int | None = None) -> np.ndarray:
    """Each place's code as one int64 key. ``codes`` are packed little-endian bytes (FAISS's
    own layout: index ``m`` at bits ``[bits·m, bits·(m+1))``) when ``bits`` is None, else one
    ``bits``-wide index per byte."""
    keys = np.zeros(len(codes), np.int64)
    step = 8 if bits is None else bits
    for b in range(codes.shape[1]):
        keys |= codes[:, b].astype(np.int64) << (step * b)
    return keys


def code_lists(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(values, starts, ids)``: the distinct keys ascending, and the places of ``values[j]``
    at ``ids[starts[j]:starts[j + 1]]``, ascending."""
    ids = np.argsort(keys, kind="stable")
    ordered = keys[ids]
    first = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]]) if len(ordered) else np.zeros(0, np.int64)
    return ordered[first], np.append(first, len(ordered)).astype(np.int64), ids.astype(np.int64, copy=False)


def budget(n_values: int) -> int:
    """Values a frame may visit before its exhaustive pass (which costs about as much as
    ``n_values / BUDGET_SHARE`` visits)."""
    return max(MIN_BUDGET, n_values // BUDGET_SHARE)


@numba.njit(cache=True, nogil=True)
def _keep(best_d: np.ndarray, best_i: np.ndarray, n: int, d: float, i: int) -> int:
    """Insert ``(d, i)`` into the first ``n`` pairs, sorted by (distance, id), of at most
    ``len(best_d)``; returns the new count."""
    k = best_d.shape[0]
    if n == k and (d > best_d[k - 1] or (d == best_d[k - 1] and i > best_i[k - 1])):
        return n
    j = min(n, k - 1)
    while j > 0 and (best_d[j - 1] > d or (best_d[j - 1] == d and best_i[j - 1] > i)):
        best_d[j], best_i[j] = best_d[j - 1], best_i[j - 1]
        j -= 1
    best_d[j], best_i[j] = d, i
    return min(n + 1, k)


@numba.njit(cache=True, nogil=True)
def _keep_value(values: np.ndarray, starts: np.ndarray, ids: np.ndarray, key: np.int64, d: float,
                best_d: np.ndarray, best_i: np.ndarray, n: int) -> int:
    """Insert the places of code value ``key`` (if any place has it) at distance ``d``."""
    j = np.searchsorted(values, key)
    if j == values.shape[0] or values[j] != key:
        return n
    return _keep_places(starts, ids, j, d, best_d, best_i, n)


@numba.njit(cache=True, nogil=True, inline="always")
def _keep_places(starts: np.ndarray, ids: np.ndarray, j: int, d: float, best_d: np.ndarray, best_i: np.ndarray,
                 n: int) -> int:
    """Insert the places of the ``j``-th distinct value at distance ``d`` (a pass knows ``j``:
    looking its value up again cost a binary search per value)."""
    for r in range(starts[j], starts[j + 1]):
        if n == best_d.shape[0] and (d > best_d[n - 1] or (d == best_d[n - 1] and ids[r] > best_i[n - 1])):
            break  # neither this place nor the rest of the value's (later ids) enters
        n = _keep(best_d, best_i, n, d, ids[r])
    return n


@numba.njit(cache=True, nogil=True, inline="always")
def _pq_value_distance(tables: np.ndarray, key: np.int64, bits: int) -> float:
    mask = (1 << bits) - 1
    s = 0.0
    for m in range(tables.shape[0]):
        s += tables[m, (key >> (bits * m)) & mask]
    return s


@numba.njit(cache=True, nogil=True)
def _pq_frame(tables: np.ndarray, bits: int, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
              best_d: np.ndarray, best_i: np.ndarray, limit: int) -> int:
    """One frame's k nearest places of a product-quantiser code (``tables``: float64, (M, ksub))
    by the multi-sequence algorithm; a pass over the values past ``limit`` visits. Returns
    how many were found."""
    M, ksub = tables.shape
    order = np.empty((M, ksub), np.int64)
    ranked = np.empty((M, ksub))
    for m in range(M):
        order[m] = np.argsort(tables[m], kind="mergesort")
        ranked[m] = tables[m][order[m]]
    tuples = np.empty((1 + M * (limit + 1), M), np.int64)  # every tuple pushed, by push order
    tuples[0] = 0
    s0 = 0.0
    for m in range(M):
        s0 += ranked[m, 0]
    heap = [(s0, 0)]
    pushed, n, visits = 1, 0, 0
    while len(heap) > 0:
        s, t = heapq.heappop(heap)
        if n == best_d.shape[0] and s > best_d[n - 1]:
            return n
        visits += 1
        if visits > limit:
            return _pq_pass(tables, bits, values, starts, ids, best_d, best_i)
        key = np.int64(0)
        last = 0
        for m in range(M):
            key |= order[m, tuples[t, m]] << (bits * m)
            if tuples[t, m] > 0:
                last = m
        n = _keep_value(values, starts, ids, key, s, best_d, best_i, n)
        for j in range(last, M):  # the children: one more in place ``last`` or after it
            if tuples[t, j] + 1 < ksub:
                tuples[pushed] = tuples[t]
                tuples[pushed, j] += 1
                sj = 0.0
                for m in range(M):
                    sj += ranked[m, tuples[pushed, m]]
                heapq.heappush(heap, (sj, pushed))
                pushed += 1
    return n


@numba.njit(cache=True, nogil=True)
def _pq_pass(tables: np.ndarray, bits: int, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
             best_d: np.ndarray, best_i: np.ndarray) -> int:
    """A frame's k nearest places by a pass over every distinct value."""
    best_d[:], best_i[:] = np.inf, NO_PLACE
    k, n = best_d.shape[0], 0
    for j in range(values.shape[0]):
        d = _pq_value_distance(tables, values[j], bits)
        # most values are farther than the k-th: tested here, not only in _keep_places (whose loop
        # says the same), or the pass costs 63 ns a value instead of 5 (runs29/probe4.py)
        if n < k or d <= best_d[k - 1]:
            n = _keep_places(starts, ids, j, d, best_d, best_i, n)
    return n


@numba.njit(cache=True, nogil=True)
def _hamming_frame(q: np.int64, bits: int, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
                   best_d: np.ndarray, best_i: np.ndarray, limit: int) -> int:
    """One frame's k nearest places of a binary code (``q``: the frame's code) by balls of
    growing radius; a pass over the values past ``limit`` visits. Returns how many were found."""
    n, visits = 0, 0
    for r in range(bits + 1):
        flips = np.arange(r)  # the bits flipped, ascending; every r-subset in turn
        while True:
            visits += 1
            if visits > limit:
                return _hamming_pass(q, values, starts, ids, best_d, best_i)
            mask = np.int64(0)
            for f in flips:
                mask |= np.int64(1) << f
            n = _keep_value(values, starts, ids, q ^ mask, float(r), best_d, best_i, n)
            i = r - 1
            while i >= 0 and flips[i] == bits - r + i:
                i -= 1
            if i < 0:
                break
            flips[i] += 1
            for j in range(i + 1, r):
                flips[j] = flips[j - 1] + 1
        if n == best_d.shape[0]:
            return n  # every place within radius r is in; the rest are farther
    return n


@numba.njit(cache=True, nogil=True)
def _hamming_pass(q: np.int64, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
                  best_d: np.ndarray, best_i: np.ndarray) -> int:
    """A frame's k nearest places of a binary code by a pass over every distinct value."""
    best_d[:], best_i[:] = np.inf, NO_PLACE
    k, n = best_d.shape[0], 0
    for j in range(values.shape[0]):
        d = 0
        x = values[j] ^ q
        while x:
            x &= x - 1
            d += 1
        if n < k or d <= best_d[k - 1]:
            n = _keep_places(starts, ids, j, float(d), best_d, best_i, n)
    return n


@numba.njit(cache=True, nogil=True)
def pq_topk(tables: np.ndarray, bits: int, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
            k: int, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """``(distances, ids)`` of each frame's ``k`` nearest places (ids −1, distances inf where
    fewer), for product-quantiser ``tables`` (frames, M, ksub) of squared distances, float64."""
    dist = np.full((tables.shape[0], k), np.inf)
    best = np.full((tables.shape[0], k), NO_PLACE, np.int64)
    for p in range(tables.shape[0]):
        _pq_frame(tables[p], bits, values, starts, ids, dist[p], best[p], limit)
    return dist, best


@numba.njit(cache=True, nogil=True)
def hamming_topk(queries: np.ndarray, bits: int, values: np.ndarray, starts: np.ndarray, ids: np.ndarray,
                 k: int, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """``(distances, ids)`` of each frame's ``k`` nearest places by Hamming distance (ids −1,
    distances inf where fewer), for the frames' codes as keys (``queries``)."""
    dist = np.full((queries.shape[0], k), np.inf)
    best = np.full((queries.shape[0], k), NO_PLACE, np.int64)
    for p in range(queries.shape[0]):
        _hamming_frame(queries[p], bits, values, starts, ids, dist[p], best[p], limit)
    return dist, best


def pq_distances(tables: np.ndarray, bits: int, keys: np.ndarray) -> np.ndarray:
    """Each frame's distance to code values ``keys`` (frames, j), from its float64 ``tables``,
    summed in the enumeration's order (a check independent of it)."""
    s = np.zeros(keys.shape)
    for m in range(tables.shape[1]):
        s += np.take_along_axis(tables[:, m, :], (keys >> (bits * m)) & ((1 << bits) - 1), axis=1)
    return s


def hamming_distances(queries: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Hamming distances between each frame's code ``queries`` (frames,) and code values ``keys`` (frames, j)."""
    x = (keys ^ queries[:, None]).view(np.uint64)
    return np.unpackbits(x.view(np.uint8), axis=-1).reshape(*x.shape, 64).sum(axis=-1).astype(np.float64)


def agree(faiss_dist: np.ndarray, faiss_ids: np.ndarray, dist: np.ndarray, ids: np.ndarray,
          scale: np.ndarray, rounding: float) -> np.ndarray:
    """Per frame, whether FAISS's top-k and the exact one agree: the same ids, or distances
    equal rank by rank within ``rounding`` of the frame's ``scale`` (places tied to rounding,
    which FAISS's float32 sums may order either way)."""
    same_ids = (faiss_ids == ids).all(axis=1)
    found = ids >= 0
    close = np.where(found, np.abs(faiss_dist.astype(np.float64) - dist) <= rounding * scale[:, None],
                     faiss_ids < 0)
    return same_ids | ((found == (faiss_ids >= 0)) & close).all(axis=1)
