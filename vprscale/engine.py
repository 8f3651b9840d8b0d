"""The query engine (docs/method.md): a loaded index, query hashing and sequence matching.

An index is held as compact arrays: the sorted occupied addresses, CSR offsets into the
reference ids, the single best per address, and every reference's own address. Sequence
distances are computed in fixed point (int64; δ_max is ``DELTA_MAX_UNITS``), so that sums are exact and
associative: the batch kernel and the online matcher agree bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numba
import numpy as np

from vprscale.coarsehash import hash_descriptors
from vprscale.index import load_index_meta
from vprscale.intrinsics import funnel_shift_right, popcount, prefetch

DELTA_MAX_UNITS = 2**36  # δ_max in fixed point: L · d · δ never overflows int64


COPIED_LISTS = 1 << 25  # ids (256 MB) up to which query frames get their own copy of their lists


@dataclass
class QueryFrames:
    """The per-frame work on query frames, done once per frame as it arrives (docs/method.md).

    A frame is hashed, given the nearest occupied address, and has that address's list
    retrieved (the paper's O(1) list look-up per new frame); for K = 2 its address also
    goes into bit planes like the references' (:func:`bit_planes`). Every window that
    contains the frame then reads these, so a query's sequence match never goes back to
    the index's lists: its L lists are adjacent here, in frame order. (Unless the frames'
    lists hold more than ``COPIED_LISTS`` ids together, as a coarse index's do: then
    ``ids`` is the index's own and the bounds point into it.)

    Only the frames worked on are held, ascending; arrays are indexed by position among
    them, and a window's frames, consecutive in the sequence, are consecutive here too.
    """

    frames: np.ndarray  # the frames held (ascending), positions 0 … n − 1
    hashes: np.ndarray  # own address of every frame (uint64)
    addr: np.ndarray  # index of the occupied address used
    start: np.ndarray  # the list of the frame at position i is ids[start[i]:stop[i]]
    stop: np.ndarray
    ids: np.ndarray
    planes: np.ndarray  # K = 2: bit b of positions 64·i … 64·i + 63 as word i·d + b

    def positions(self, t: np.ndarray, L: int = 1) -> np.ndarray:
        """Positions of frames ``t``, each with the whole window of ``L`` centred on it held."""
        t = np.asarray(t, np.int64)
        pos = np.searchsorted(self.frames, t)
        first, last = pos - L // 2, pos - L // 2 + L - 1
        ok = (first >= 0) & (last < len(self.frames))
        ok[ok] &= (self.frames[first[ok]] == t[ok] - L // 2) & (self.frames[last[ok]] == t[ok] - L // 2 + L - 1)
        if not ok.all():
            raise ValueError(f"frame {t[~ok][0]}: its window of {L} is not among the query frames held")
        return pos

    def kernel_args(self) -> tuple:
        """``(hashes, planes, start, stop, ids)``: the query frames' arguments of :func:`match_batch`."""
        return self.hashes, self.planes, self.start, self.stop, self.ids


@numba.njit(cache=True, nogil=True)
def _retrieve_lists(offsets: np.ndarray, ids: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start, stop, lists)``: the lists of addresses ``a`` copied one after another."""
    start = np.empty(a.shape[0], np.int64)
    stop = np.empty(a.shape[0], np.int64)
    total = 0
    for i in range(a.shape[0]):
        total += offsets[a[i] + 1] - offsets[a[i]]
    out = np.empty(total, np.int64)
    m = 0
    for i in range(a.shape[0]):
        start[i] = m
        for q in range(offsets[a[i]], offsets[a[i] + 1]):
            out[m] = ids[q]
            m += 1
        stop[i] = m
    return start, stop, out


@dataclass
class Index:
    """A CoarseHash index in memory."""

    d: int
    k: int
    mean: np.ndarray
    components: np.ndarray
    centres: np.ndarray
    addresses: np.ndarray  # sorted occupied addresses (uint64)
    offsets: np.ndarray  # CSR: ids of address a are ids[offsets[a]:offsets[a+1]]
    ids: np.ndarray  # int64 ref ids, grouped by address, ascending inside
    best: np.ndarray  # single best ref id per address
    ref_hash: np.ndarray  # the address of every reference (uint64)
    meta: dict

    @classmethod
    def load(cls, path: str | Path) -> Index:
        """Open an index directory; the lists and the map are memory-mapped, not read."""
        path = Path(path)
        meta = load_index_meta(path)
        m = {k: np.load(path / "model" / f"{k}.npy") for k in ("mean", "components", "centres")}
        arrays = {k: np.load(path / f"{k}.npy", mmap_mode="r")
                  for k in ("addresses", "offsets", "ids", "best", "ref_hash")}
        return cls(meta["d"], meta["k"], m["mean"], m["components"], m["centres"], arrays["addresses"],
                   arrays["offsets"], arrays["ids"], arrays["best"], arrays["ref_hash"], meta)

    @classmethod
    def from_addresses(cls, ref_hash: np.ndarray, centres: np.ndarray, errors: np.ndarray | None = None,
                       mean: np.ndarray | None = None, components: np.ndarray | None = None) -> Index:
        """An index over given reference addresses (for hand-built cases and tests)."""
        from vprscale.lists import inverted_lists

        ref_hash = np.asarray(ref_hash, np.uint64)
        d, k = centres.shape
        lists = inverted_lists(ref_hash, np.zeros(len(ref_hash)) if errors is None else errors)
        offsets = np.r_[lists["offsets"], len(ref_hash)].astype(np.int64)
        return cls(d, k, np.zeros(d) if mean is None else mean, np.eye(d) if components is None else components,
                   centres, lists["addresses"], offsets, lists["order"].astype(np.int64),
                   lists["best"].astype(np.int64), ref_hash, {"n_ref": len(ref_hash), "d": d, "k": k})

    @property
    def n_ref(self) -> int:
        return len(self.ref_hash)

    def weights(self) -> np.ndarray:
        """Fixed-point ``|c_ja − c_jb|`` as a (d, K, K) int64 table."""
        diff = np.abs(self.centres[:, :, None] - self.centres[:, None, :])
        span = (self.centres[:, -1] - self.centres[:, 0]).sum()
        return np.rint(diff * (DELTA_MAX_UNITS / span)).astype(np.int64)

    @cached_property
    def planes(self) -> np.ndarray:
        """For K = 2 the references' addresses as bit planes (:func:`bit_planes`); else empty.

        ``d / 8`` bytes per place, built once per loaded index (0.1 s per 10M places).
        """
        return bit_planes(self.ref_hash, self.d) if self.k == 2 else np.zeros(0, np.uint64)

    def kernel_args(self) -> tuple:
        """``(ref_hash, planes, gaps, w, tables, d, k, δ_max)``: the index's arguments of :func:`match_batch`.

        ``gaps[b]`` is the cost of a differing bit ``b`` (K = 2), ``tables`` the per-byte δ.
        """
        w, tables, dmax = self.delta_tables()
        return self.ref_hash, self.planes, bit_gaps(w), w, tables, self.d, self.k, dmax

    def delta_tables(self) -> tuple[np.ndarray, np.ndarray, np.int64]:
        """``(w, tables, δ_max)``: what :func:`delta` needs, frame by frame."""
        w = self.weights()
        tables = byte_tables(w) if self.k == 2 else np.zeros((1, 256), np.int64)
        return w, tables, np.int64(w[:, 0, -1].sum())

    def hash_queries(self, x: np.ndarray) -> np.ndarray:
        """Own addresses of query rows (docs/method.md)."""
        return hash_descriptors(x, self.mean, self.components, self.centres)[1]

    @cached_property
    def _prefix(self) -> tuple[np.ndarray, int]:
        """``(first, shift)``: the occupied addresses whose top bits are ``p`` are ``first[p] … first[p+1]``.

        About 2^16 prefixes, so a search touches two table entries and one short run
        instead of ~log2(occupied) scattered cache lines of the whole array.
        """
        bits = int(np.ceil(self.d * np.log2(self.k)))
        shift = max(0, bits - 16)
        prefixes = np.arange((1 << (bits - shift)) + 1, dtype=np.uint64)
        first = np.searchsorted(self.addresses >> np.uint64(shift), prefixes)
        return first.astype(np.int64), shift

    def query_frames(self, h: np.ndarray, frames: np.ndarray | None = None) -> QueryFrames:
        """The per-frame work on query frames with own addresses ``h`` (docs/method.md).

        ``frames`` (ascending; default ``0 … len(h) − 1``) number them in their sequence.
        See :class:`QueryFrames`.
        """
        h = np.asarray(h, np.uint64)
        frames = np.arange(len(h)) if frames is None else np.asarray(frames, np.int64)
        a = self.nearest_occupied(h)
        start, stop = self.offsets[a], self.offsets[a + 1]
        if (stop - start).sum() <= COPIED_LISTS:
            start, stop, ids = _retrieve_lists(self.offsets, self.ids, a)
        else:  # long lists (a coarse index): read in place
            ids = self.ids
        planes = bit_planes(h, self.d) if self.k == 2 else np.zeros(0, np.uint64)
        return QueryFrames(frames, h, a, start, stop, ids, planes)

    def nearest_occupied(self, h: np.ndarray) -> np.ndarray:
        """Index of ``h`` among the occupied addresses, else of the numerically nearest (ties: smaller)."""
        first, shift = self._prefix
        return _nearest_occupied(self.addresses, first, shift, np.asarray(h, np.uint64))


@numba.njit(cache=True, nogil=True)
def _nearest_occupied(a: np.ndarray, first: np.ndarray, shift: int, h: np.ndarray) -> np.ndarray:
    out = np.empty(h.shape[0], np.int64)
    for i in range(h.shape[0]):
        x = h[i]
        p = np.int64(x >> np.uint64(shift))
        lo, hi = first[p], first[p + 1]  # the first address ≥ x is in [lo, hi], hi meaning "a later prefix"
        while lo < hi:
            mid = (lo + hi) >> 1
            if a[mid] < x:
                lo = mid + 1
            else:
                hi = mid
        if lo < a.shape[0] and a[lo] == x:
            out[i] = lo
        elif lo == 0:
            out[i] = 0
        elif lo == a.shape[0] or x - a[lo - 1] <= a[lo] - x:  # ties go to the smaller address
            out[i] = lo - 1
        else:
            out[i] = lo
    return out


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


@numba.njit(cache=True, nogil=True)
def _score(c: np.int64, t: np.int64, L: int, half: int, ref_hash: np.ndarray, q_hash: np.ndarray,
           w: np.ndarray, tables: np.ndarray, d: int, k: int, dmax: np.int64, bound: np.int64) -> np.int64:
    """Score of centre ``c`` for the window at ``t``, abandoned once it reaches ``bound``.

    Reference frames outside the map cost δ_max each; the in-range offsets form one
    contiguous run, scanned without a branch per frame. δ ≥ 0, so a partial sum that has
    reached ``bound`` can only end at or above it: returning early changes no decision.
    """
    n_ref = ref_hash.shape[0]
    lo = max(0, half - c)  # first window offset whose reference frame is inside [0, n_ref)
    hi = min(L, n_ref - c + half)
    s = np.int64(lo + (L - hi)) * dmax
    for i in range(lo, hi):
        s += delta(ref_hash[c + i - half], q_hash[t + i - half], w, tables, d, k)
        if s >= bound:
            return s
    return s


PREFETCH = 8  # pairs whose reference window is fetched ahead of the one being scored
QUERY_BLOCK = 1 << 14  # queries matched together at most (a pair holds its query in 20 bits)
PAIR_BUDGET = 1 << 22  # proposals matched together at most: 32 MB per pair array
SORT_BLOCKS = 16  # blocks of queries whose candidates are counted and scattered in parallel by the pair sort
SCORE_CHUNKS = 16  # runs of sorted pairs scored in parallel, each keeping its own best per query
BUCKET_BITS = 12  # pairs are sorted by their window's position, 4096 places (12 KB of planes) at a time
MAX_BUCKETS = 1 << 16
CACHED_PLANES = 1 << 23  # bytes of bit planes that stay in cache: smaller maps keep pairs in query order


@numba.njit(cache=True, nogil=True, parallel=True)
def bit_planes(h: np.ndarray, d: int) -> np.ndarray:
    """For K = 2: bit ``b`` of the addresses of places ``64·i … 64·i + 63`` as word ``i·d + b``.

    Flat (rows of ``d`` words), so that the short scoring kernel slices it directly: a
    reshape on every call cost twice the arithmetic. Two zero rows pad the end so that any
    window inside the map reads whole rows.
    """
    n = h.shape[0]
    out = np.zeros((n // 64 + 2) * d, np.uint64)
    for blk in numba.prange((n + 63) // 64):
        row = out[blk * d:]
        for p in range(64 * blk, min(n, 64 * blk + 64)):
            _set_bit(row, h[p], p & 63, d)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _set_bit(row: np.ndarray, x: np.uint64, bit: int, d: int) -> None:
    """Bit ``bit`` of word ``b`` of a plane row becomes bit ``b`` of address ``x``, for every plane."""
    for b in range(d):
        row[b] |= ((x >> np.uint64(b)) & np.uint64(1)) << np.uint64(bit)


@numba.njit(cache=True, nogil=True, inline="always")
def _window_words(planes: np.ndarray, d: int, p: np.int64, e: int) -> np.uint64:
    """Word ``e`` (flat over word, plane) of the window of places starting at ``p``: 64 frames of one plane."""
    row = (p >> 6) * d
    return funnel_shift_right(planes[row + d + e], planes[row + e], np.uint64(p & 63))


@numba.njit(cache=True, nogil=True, inline="always")
def _score_planes(p: np.int64, planes: np.ndarray, d: int, q_words: np.ndarray, masks: np.ndarray,
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
def _candidates(t: np.int64, L: int, half: int, aligned: bool, q_start: np.ndarray, q_stop: np.ndarray,
                ids: np.ndarray, n_ref: int, cand: np.ndarray, slots: np.ndarray, bits: int) -> int:
    """Distinct candidate centres of the window at ``t`` into ``cand``, in first-seen order.

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
        if c < 0 or c >= n_ref:
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
def _proposals(centres_t: np.ndarray, L: int, q_start: np.ndarray, q_stop: np.ndarray) -> np.ndarray:
    """Number of ids in the lists of each query's window (its candidates before repeats are dropped)."""
    proposals = np.empty(centres_t.shape[0], np.int64)
    for qi in numba.prange(centres_t.shape[0]):
        total = 0
        for i in range(L):
            total += q_stop[centres_t[qi] + i - L // 2] - q_start[centres_t[qi] + i - L // 2]
        proposals[qi] = total
    return proposals


@numba.njit(cache=True, nogil=True, parallel=True)
def _propose(centres_t: np.ndarray, L: int, aligned: bool, q_start: np.ndarray, q_stop: np.ndarray,
             ids: np.ndarray, n_ref: int, proposals: np.ndarray, shift: int
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
            n_r[qi] = _candidates(centres_t[qi], L, half, aligned, q_start, q_stop, ids, n_ref, cand[first[qi]:],
                                  slots[: 1 << bits], bits)
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

    A counting sort (the counts from :func:`_propose`), its scatter split over the same
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


@numba.njit(cache=True, nogil=True, parallel=True, fastmath={"reassoc", "contract"})
def _score_pairs(pairs: np.ndarray, centres_t: np.ndarray, L: int, q_hash: np.ndarray, q_words: np.ndarray,
                 ref_hash: np.ndarray, planes: np.ndarray, bit_gap: np.ndarray, w: np.ndarray, tables: np.ndarray,
                 d: int, k: int, dmax: np.int64, fast: bool) -> np.ndarray:
    """The centre of each query's best pair, ties to the smaller centre.

    Runs of the sorted pairs are scored in parallel, each run keeping its own best per
    query; the runs' bests are then merged. The minimum does not depend on the order, so
    the answer does not depend on the thread count.
    """
    n = centres_t.shape[0]
    half = L // 2
    n_ref = ref_hash.shape[0]
    n_words = (L + 63) // 64
    masks = np.full(n_words * d, np.uint64(0xFFFFFFFFFFFFFFFF))  # flat over (word, plane), as q_words
    if L % 64:
        masks[-d:] = (np.uint64(1) << np.uint64(L % 64)) - np.uint64(1)
    gaps = np.empty(n_words * d, np.float64)
    for e in range(n_words * d):
        gaps[e] = bit_gap[e % d]
    m = pairs.shape[0]
    run_s = np.full((SCORE_CHUNKS, n), np.int64(2**62))
    run_c = np.full((SCORE_CHUNKS, n), np.int64(-1))
    for run in numba.prange(SCORE_CHUNKS):
        stop = m * (run + 1) // SCORE_CHUNKS
        for j in range(m * run // SCORE_CHUNKS, stop):
            c = pairs[j] >> 20
            qi = pairs[j] & 0xFFFFF
            if fast and j + PREFETCH < stop:
                _prefetch_window(planes, d, (pairs[j + PREFETCH] >> 20) - half, L)
            if fast and c >= half and c - half + L <= n_ref:
                s = _score_planes(c - half, planes, d, q_words[qi], masks, gaps)
            else:
                s = _score(c, centres_t[qi], L, half, ref_hash, q_hash, w, tables, d, k, dmax, run_s[run, qi] + 1)
            if s < run_s[run, qi] or (s == run_s[run, qi] and c < run_c[run, qi]):
                run_s[run, qi] = s
                run_c[run, qi] = c
    best_s = run_s[0].copy()
    best = run_c[0].copy()
    for qi in numba.prange(n):
        for run in range(1, SCORE_CHUNKS):
            s, c = run_s[run, qi], run_c[run, qi]
            if s < best_s[qi] or (s == best_s[qi] and c < best[qi]):
                best_s[qi], best[qi] = s, c
    return best


@numba.njit(cache=True, nogil=True)
def match_batch(centres_t: np.ndarray, L: int, aligned: bool, q_hash: np.ndarray, q_planes: np.ndarray,
                q_start: np.ndarray, q_stop: np.ndarray, q_ids: np.ndarray, ref_hash: np.ndarray,
                planes: np.ndarray, gaps: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int, k: int,
                dmax: np.int64) -> tuple[np.ndarray, np.ndarray]:
    """Sequence match of every query centre; returns ``(match, number of candidates)``.

    The query-frame arrays are those of :class:`QueryFrames` (the own address of the frame
    at position ``i``, its list ``q_ids[q_start[i]:q_stop[i]]``, the frames' bit planes),
    and ``centres_t`` are positions there (:meth:`QueryFrames.positions`). Paper mode scores
    every id of every window frame's list as a centre; aligned mode scores ``r − l`` for an
    id ``r`` in the list of frame ``t + l``. Ties go to the smallest centre.

    Queries are matched in blocks: each query's distinct candidates are collected (a small
    hash set per query), all (candidate, query) pairs of the block are sorted by where
    their reference window lies (:func:`_pairs_by_window`), and scored in that order, so
    that the bit planes of the map stream through the caches instead of being fetched
    window by window. For K = 2 a window inside the map is scored on bit planes
    (:func:`_score_planes`); other windows, and K > 2, frame by frame (:func:`_score`).
    """
    n = centres_t.shape[0]
    n_ref = ref_hash.shape[0]
    # the bit-plane score sums in float64: exact while L·δ_max < 2^53
    fast = k == 2 and planes.shape[0] > 0 and np.float64(L) * np.float64(dmax) < 2.0**53
    match = np.empty(n, np.int64)
    n_r = np.empty(n, np.int64)
    shift = _bucket_shift(n_ref, planes.shape[0] * 8)
    proposals = _proposals(centres_t, L, q_start, q_stop)
    upto = np.cumsum(proposals)  # proposals of the queries up to each, inclusive
    lo = 0
    while lo < n:  # blocks of at most QUERY_BLOCK queries and PAIR_BUDGET proposals (at least one query)
        hi = min(n, lo + QUERY_BLOCK,
                 max(lo + 1, np.searchsorted(upto, upto[lo] - proposals[lo] + PAIR_BUDGET, "right")))
        t = centres_t[lo:hi]
        cand, first, block_n_r, counts = _propose(t, L, aligned, q_start, q_stop, q_ids, n_ref, proposals[lo:hi],
                                                  shift)
        pairs = _pairs_by_window(cand, first, block_n_r, counts, shift)
        q_words = _query_words(t, L, q_planes, d) if fast else np.zeros((t.shape[0], 0), np.uint64)
        match[lo:hi] = _score_pairs(pairs, t, L, q_hash, q_words, ref_hash, planes, gaps, w, tables, d, k, dmax, fast)
        n_r[lo:hi] = block_n_r
        lo = hi
    return match, n_r


@numba.njit(cache=True, nogil=True)
def in_list_distance(addr: np.ndarray, gt: np.ndarray, offsets: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """For single frames: the smallest ``|id − gt|`` over the address's whole list."""
    out = np.empty(addr.shape[0], np.int64)
    for i in range(addr.shape[0]):
        best = np.int64(2**62)
        for p in range(offsets[addr[i]], offsets[addr[i] + 1]):
            dist = abs(ids[p] - gt[i])
            if dist < best:
                best = dist
        out[i] = best
    return out


class OnlineMatcher:
    """Frame-by-frame sequence matching with incrementally updated scores.

    Each new frame extends the window that ends at it; the match reported is the centre of
    that window, as the batch form would compute for centre ``t − (L − 1 − ⌊L/2⌋)``. Scores
    of diagonals already tracked are updated by adding the new pair and removing the pair
    that left the window (the paper's ~3·N_r operations per frame); new diagonals are
    scored in full once.
    """

    def __init__(self, index: Index, L: int, aligned: bool = False) -> None:
        self.index, self.L, self.aligned = index, L, aligned
        self.half = L // 2
        self._w, self._tables, self._dmax = index.delta_tables()
        self._hashes: list[int] = []
        self._addrs: list[int] = []
        self._scores: dict[int, int] = {}  # diagonal (ref centre − query centre) → score

    def _delta_at(self, ref: int, frame: int) -> int:
        if ref < 0 or ref >= self.index.n_ref:
            return int(self._dmax)
        return int(delta(self.index.ref_hash[ref], np.uint64(self._hashes[frame]), self._w, self._tables,
                         self.index.d, self.index.k))

    def push(self, descriptor: np.ndarray) -> int | None:
        """Add one query frame; the match of the window it completes (None until L frames)."""
        h = self.index.hash_queries(np.asarray(descriptor, np.float32)[None, :])
        return self.push_address(int(h[0]))

    def push_address(self, h: int) -> int | None:
        """Add one query frame given its own address (already hashed)."""
        self._hashes.append(int(h))
        self._addrs.append(int(self.index.nearest_occupied(np.array([h], np.uint64))[0]))
        u = len(self._hashes) - 1
        if u + 1 < self.L:
            return None
        t = u - (self.L - 1 - self.half)  # centre of the window ending at u
        first = t - self.half
        if self._scores:  # slide: add the newest pair, drop the pair that left
            for diag in list(self._scores):
                s = self._scores[diag] + self._delta_at(t + diag + self.L - 1 - self.half, u)
                s -= self._delta_at(t + diag - self.half - 1, first - 1)
                self._scores[diag] = s
        idx = self.index
        candidates = set()
        for i in range(self.L):
            a = self._addrs[first + i]
            for r in idx.ids[idx.offsets[a] : idx.offsets[a + 1]]:
                c = int(r) - (i - self.half) if self.aligned else int(r)
                if 0 <= c < idx.n_ref:
                    candidates.add(c)
        kept = {}
        for c in candidates:
            diag = c - t
            if diag not in self._scores:
                self._scores[diag] = sum(self._delta_at(c + i - self.half, first + i) for i in range(self.L))
            kept[diag] = self._scores[diag]
        self._scores = kept
        best = min(kept.items(), key=lambda kv: (kv[1], kv[0]))
        return t + best[0]
