"""The inverted lists of an index in succinct form (docs/method.md, "Storage"), and the numba
functions the query engine reads them with.

Three parts, what a query frame needs to find its list:

- ``occupied``: the sorted occupied addresses, a rank bitmap or Elias–Fano, whichever is
  smaller (a frame's address → its slot, or the numerically nearest occupied one);
- ``starts``: where each slot's list starts among the ids, Elias–Fano (``occupied + 1``
  values, the last one the number of ids);
- ``ids``: the reference ids, grouped by address, bit-packed at ⌈log2 N⌉ bits; inside a
  list the address's single best (least quantisation error, ties to the smaller id) comes
  first and the others follow ascending, so no separate array of bests is kept.

The numba functions take the parts as tuples (:meth:`InvertedLists.args`), so kernels pass
one argument per part whatever the encoding holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from vprscale.core.kernelcache import share_kernels
from vprscale.method.intrinsics import prefetch
from vprscale.method.succinct import (
    SAMPLE_BITS,
    EliasFano,
    RankBitmap,
    ef_nearest,
    ef_pair,
    get_packed,
    occupancy_structure,
    pack,
    rb_nearest,
    unpack,
    width,
)

share_kernels()

SHARED_ABOVE = 1 << 25  # ids (256 MB decoded) beyond which frames share their lists' copies
AHEAD = 8  # frames ahead whose select samples are fetched while a frame is looked up


@numba.njit(cache=True, nogil=True)
def best_first(order: np.ndarray, starts: np.ndarray, best: np.ndarray) -> None:
    """Move each list's single best to its front, in place; the others stay ascending.

    ``order[starts[a]:starts[a + 1]]`` is list ``a`` (ascending ids), ``best[a]`` its best id.
    """
    for a in range(best.shape[0]):
        s = starts[a]
        j = s
        while order[j] != best[a]:
            j += 1
        while j > s:
            order[j] = order[j - 1]
            j -= 1
        order[s] = best[a]


@numba.njit(cache=True, nogil=True)
def ascending_with_best(order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Undo :func:`best_first` in place: each list's front (its single best) moved to its place
    among the others, ascending; returns which ids are their list's best."""
    best = np.zeros(order.shape[0], np.bool_)
    for a in range(starts.shape[0] - 1):
        s, e = starts[a], starts[a + 1]
        if e == s:
            continue
        x = order[s]
        j = s
        while j + 1 < e and order[j + 1] < x:
            order[j] = order[j + 1]
            j += 1
        order[j] = x
        best[j] = True
    return best


@numba.njit(cache=True, nogil=True)
def nearest_slots(occ: tuple, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(slots, taken)``: the slot of each address ``h`` among the occupied ones, else of the
    numerically nearest (ties: smaller), and the occupied address it took.

    ``occ`` is the occupied addresses' ``args()``: a rank bitmap (kind 1: bits, ranks, select
    samples) or Elias–Fano (kind 0). The words a later frame reads are fetched ahead.
    """
    kind, high, low, lb, ones, zeros, n, size = occ
    slots = np.empty(h.shape[0], np.int64)
    taken = np.empty(h.shape[0], np.uint64)
    for i in range(h.shape[0]):
        if kind == 1:
            if i + AHEAD < h.shape[0] and np.int64(h[i + AHEAD]) < size:
                x = np.int64(h[i + AHEAD])
                prefetch(zeros, x >> 9)
                prefetch(high, x >> 6)
            slots[i], taken[i] = rb_nearest(high, zeros, ones, n, size, h[i])
            continue
        if i + AHEAD < h.shape[0]:  # the select sample a later frame will read, then the words it points to
            hx = np.int64(h[i + AHEAD] >> np.uint64(lb)) - 1
            if 0 <= hx < size:
                prefetch(zeros, hx >> SAMPLE_BITS)
        if i + AHEAD // 2 < h.shape[0]:
            hx = np.int64(h[i + AHEAD // 2] >> np.uint64(lb)) - 1
            if 0 <= hx < size:
                prefetch(high, zeros[hx >> SAMPLE_BITS] >> 6)
        slots[i], taken[i] = ef_nearest(high, low, lb, ones, zeros, n, size, h[i])
    return slots, taken


@numba.njit(cache=True, nogil=True, inline="always")
def nearest_slot(occ: tuple, h: np.uint64) -> tuple[np.int64, np.uint64]:
    """:func:`nearest_slots` of one address, with no array made (a live frame's look-up)."""
    kind, high, low, lb, ones, zeros, n, size = occ
    if kind == 1:
        slot, taken = rb_nearest(high, zeros, ones, n, size, h)
    else:
        slot, taken = ef_nearest(high, low, lb, ones, zeros, n, size, h)
    return np.int64(slot), np.uint64(taken)


@numba.njit(cache=True, nogil=True, inline="always")
def list_span(starts: tuple, slot: np.int64) -> tuple[np.int64, np.int64]:
    """``(start, stop)`` of a slot's list among the ids."""
    high, low, lb, ones = starts
    return ef_pair(high, low, lb, ones, slot)


@numba.njit(cache=True, nogil=True)
def spans(starts: tuple, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    start = np.empty(slots.shape[0], np.int64)
    stop = np.empty(slots.shape[0], np.int64)
    for i in range(slots.shape[0]):
        start[i], stop[i] = list_span(starts, slots[i])
    return start, stop


@numba.njit(cache=True, nogil=True)
def gather(starts: tuple, ids: np.ndarray, id_bits: int, slots: np.ndarray, limit: np.int64
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start, stop, flat)``: the list of slot ``slots[i]`` is ``flat[start[i]:stop[i]]``.

    The lists are decoded one after another in frame order, so the lists of a window's
    frames lie together. Where that would exceed ``limit`` ids (a coarse index, whose frames
    share a few long lists), each distinct slot's list is decoded once instead and shared.
    """
    n = slots.shape[0]
    start = np.empty(n, np.int64)
    stop = np.empty(n, np.int64)
    total = 0
    for i in range(n):
        if i + AHEAD < n:  # the select sample a later frame will read, then the word it points to
            prefetch(starts[3], slots[i + AHEAD] >> SAMPLE_BITS)
        if i + AHEAD // 2 < n:
            prefetch(starts[0], starts[3][slots[i + AHEAD // 2] >> SAMPLE_BITS] >> 6)
        start[i], stop[i] = list_span(starts, slots[i])
        total += stop[i] - start[i]
    if total > limit:
        return _gather_shared(starts, ids, id_bits, slots)
    flat = np.empty(total, np.int64)
    m = 0
    for i in range(n):
        if i + AHEAD < n:
            prefetch(ids, (start[i + AHEAD] * id_bits) >> 6)
        s, e = start[i], stop[i]
        start[i] = m
        for q in range(s, e):
            flat[m] = np.int64(get_packed(ids, id_bits, q))
            m += 1
        stop[i] = m
    return start, stop, flat


@numba.njit(cache=True, nogil=True)
def _gather_shared(starts: tuple, ids: np.ndarray, id_bits: int, slots: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`gather` with each distinct slot's list decoded once."""
    uniq = np.unique(slots)
    u_start = np.empty(uniq.shape[0], np.int64)
    u_stop = np.empty(uniq.shape[0], np.int64)
    total = 0
    for j in range(uniq.shape[0]):
        u_start[j], u_stop[j] = list_span(starts, uniq[j])
        total += u_stop[j] - u_start[j]
    flat = np.empty(total, np.int64)
    first = np.empty(uniq.shape[0], np.int64)
    m = 0
    for j in range(uniq.shape[0]):
        first[j] = m
        for q in range(u_start[j], u_stop[j]):
            flat[m] = np.int64(get_packed(ids, id_bits, q))
            m += 1
    where = np.searchsorted(uniq, slots)
    start = np.empty(slots.shape[0], np.int64)
    stop = np.empty(slots.shape[0], np.int64)
    for i in range(slots.shape[0]):
        start[i] = first[where[i]]
        stop[i] = start[i] + u_stop[where[i]] - u_start[where[i]]
    return start, stop, flat


@numba.njit(cache=True, nogil=True)
def heads(starts: tuple, ids: np.ndarray, id_bits: int, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(best, size)`` of each slot's list: its first id (the single best) and its length."""
    best = np.empty(slots.shape[0], np.int64)
    size = np.empty(slots.shape[0], np.int64)
    for i in range(slots.shape[0]):
        s, e = list_span(starts, slots[i])
        best[i], size[i] = np.int64(get_packed(ids, id_bits, s)), e - s
    return best, size


@numba.njit(cache=True, nogil=True)
def frame_top(start: np.ndarray, stop: np.ndarray, flat: np.ndarray, pos: np.ndarray, n_best: int) -> np.ndarray:
    """L = 1's best-first candidates of the frames at ``pos`` from their decoded lists
    (:func:`gather`): each list's first ``n_best`` ids, its single best then the rest by id
    (−1 where the list is shorter)."""
    out = np.full((pos.shape[0], n_best), -1, np.int64)
    for i in range(pos.shape[0]):
        s = start[pos[i]]
        for j in range(min(n_best, stop[pos[i]] - s)):
            out[i, j] = flat[s + j]
    return out


@numba.njit(cache=True, nogil=True)
def in_list_distance(start: np.ndarray, stop: np.ndarray, flat: np.ndarray, pos: np.ndarray,
                     gt: np.ndarray) -> np.ndarray:
    """For single frames: the smallest ``|id − gt|`` over the frame's whole list."""
    out = np.empty(pos.shape[0], np.int64)
    for i in range(pos.shape[0]):
        best = np.int64(2**62)
        for q in range(start[pos[i]], stop[pos[i]]):
            dist = abs(flat[q] - gt[i])
            if dist < best:
                best = dist
        out[i] = best
    return out


@dataclass
class InvertedLists:
    """Occupied addresses, list starts and packed ids (see the module's docstring)."""

    occupied: EliasFano | RankBitmap
    starts: EliasFano
    ids: np.ndarray  # packed words
    id_bits: int
    longest: int  # the longest list's length (what a matcher's buffers must hold)

    @classmethod
    def build(cls, addresses: np.ndarray, offsets: np.ndarray, order: np.ndarray, n_ref: int,
              universe: int) -> InvertedLists:
        """From lists in memory: sorted occupied ``addresses`` (below ``universe``, K^d), CSR
        ``offsets`` (one more than the addresses) and the ids in list order (each list's
        single best first)."""
        bits = width(max(0, n_ref - 1))
        words = pack(order, bits)
        offsets = np.asarray(offsets, np.int64)
        return cls(occupancy_structure(np.asarray(addresses, np.uint64), universe), EliasFano.build(offsets), words,
                   bits, int(np.diff(offsets).max(initial=0)))

    @property
    def n_lists(self) -> int:
        return self.occupied.n

    @property
    def n_ids(self) -> int:
        return int(self.starts.get(self.starts.n - 1)[0]) if self.starts.n else 0

    def occupied_args(self) -> tuple:
        return self.occupied.args()

    def starts_args(self) -> tuple:
        s = self.starts
        return s.high, s.low, s.lb, s.ones

    def nearest(self, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(slots, taken)``: the slot of each address, or of the numerically nearest occupied
        one (ties: smaller), and the address it took."""
        return nearest_slots(self.occupied_args(), np.asarray(h, np.uint64))

    def addresses(self, slots: np.ndarray) -> np.ndarray:
        """The occupied addresses at ``slots`` (uint64)."""
        return self.occupied.get(slots).astype(np.uint64)

    def spans(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(start, stop)`` of each slot's list among the ids."""
        return spans(self.starts_args(), np.atleast_1d(np.asarray(slots, np.int64)))

    def sizes(self, a: int = 0, b: int | None = None) -> np.ndarray:
        """Lengths of the lists of slots ``a … b − 1`` (default: all), decoded in one pass."""
        b = self.n_lists if b is None else min(b, self.n_lists)
        return np.diff(self.starts.decode(a, b + 1))

    def ids_range(self, a: int, b: int) -> np.ndarray:
        """Ids ``a … b − 1`` in list order (int64)."""
        return unpack(self.ids, self.id_bits, np.int64(a), np.int64(b))

    def list_ids(self, slot: int) -> np.ndarray:
        """The ids of one slot's list, its single best first."""
        s, e = self.spans(np.array([slot]))
        return self.ids_range(s[0], e[0])

    def best(self, slots: np.ndarray) -> np.ndarray:
        """Each slot's single best id (its list's first)."""
        return heads(self.starts_args(), self.ids, self.id_bits, np.atleast_1d(np.asarray(slots, np.int64)))[0]

    def gather(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(start, stop, flat)``: the lists of ``slots`` decoded (:func:`gather`)."""
        return gather(self.starts_args(), self.ids, self.id_bits, np.asarray(slots, np.int64),
                      np.int64(SHARED_ABOVE))

    def in_memory(self) -> InvertedLists:
        """The directory (occupied addresses, starts) held in memory; the ids stay where they are."""
        return InvertedLists(self.occupied.in_memory(), self.starts.in_memory(), self.ids, self.id_bits, self.longest)

    def nbytes(self) -> dict[str, int]:
        return {"ids": int(self.ids.nbytes), "occupied": self.occupied.nbytes, "starts": self.starts.nbytes}
