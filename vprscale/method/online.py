"""Frame-by-frame sequence matching (docs/method.md): the method applied to a live traverse.

After frame u (u ≥ L − 1) the matcher reports the match of the centre
``t = u − (L − 1 − ⌊L/2⌋)``, exactly as the batch kernel would: the same candidates (the
batch's own candidate collector), the same window scores (its bit-plane and frame-by-frame
scorers) and the same ties. One compiled step per frame does the per-frame work (nearest
occupied address, list retrieval) and the match, so a frame costs about what one batched
query costs, without the batch's sort.

State is O(L + N_r): a ring of the last L frames' addresses and list lengths, their lists
in one sliding buffer, and scratch space for the window and its candidates (nothing allocated
a frame); nothing grows with the length of the stream.

A frame pushed alone costs what a batched query costs only if the call itself is cheap: numba
types and unboxes every argument of every call (about 0.1 µs an array, more for a tuple), and a
step reads some twenty arrays. So the matcher holds them, and the frame's own buffer, in one
struct (:class:`_Engine`, a numba ``StructRef``, unboxed as one pointer), and :func:`_push`
hashes the frame (the batch's own kernel, row by row: the same bits) and steps in a single
compiled call. That call goes straight to the compiled entry point of the struct's type, found
once when the matcher is made: the dispatcher would otherwise work out the struct's type again
on every call, which costs more than a whole L = 50 step's window.
"""

from __future__ import annotations

import numba
import numpy as np
from numba.core import types
from numba.experimental import structref

from vprscale.core.kernelcache import share_kernels
from vprscale.method.hashkernels import hash_one
from vprscale.method.index import Index
from vprscale.method.invlists import list_span, nearest_slot
from vprscale.method.kernels import (
    NO_CANDIDATE,
    delta,
    finish_best,
    keep_best_at,
    score_planes,
    score_window,
    set_bit,
    window_candidates,
    window_masks,
)
from vprscale.method.lent import borrow, lend
from vprscale.method.succinct import get_packed
from vprscale.protocol import MAX_BEST, NO_MASK, check_window

share_kernels()


class OnlineMatcher:
    """Localise query frames one at a time against an :class:`~vprscale.method.index.Index`.

    Parameters
    ----------
    index : the index to match against.
    L : sequence length (frames per window).
    mode : ``"paper"`` or ``"aligned"`` (see docs/method.md).
    n_best : how many best candidates each window keeps (``top``); 1 keeps the match alone.
    valid : for a map of many sequences, a byte a place, 1 where a window of ``L`` centred
        there exists (:func:`vprscale.protocol.window_mask`): no other place is a candidate.

    ``push(descriptor)`` returns the match of the window the frame completes (None for the
    first L − 1 frames); ``n_r`` is then that window's number of candidates and ``top`` its
    ``n_best`` best candidates, best first (−1 where there were fewer): the batch's
    ``Matches.top``, by the same window scores and ties. With L = 1 the match is the single best
    of the frame's address, as in the batch evaluation. With ``return_score=True`` each match
    comes with its score, the batch's ``Matches.score`` (the matched window's score in δ_max
    units; lower is more confident), so a live user can threshold it.
    """

    def __init__(self, index: Index, L: int, mode: str = "paper", n_best: int = 1,
                 valid: np.ndarray | None = None) -> None:
        check_window(L, mode)
        if not 1 <= int(n_best) <= MAX_BEST:
            raise ValueError(f"n_best {n_best}: keep 1 to {MAX_BEST} candidates a window")
        valid = NO_MASK if valid is None else np.ascontiguousarray(valid, np.uint8)
        if len(valid) not in (0, index.n_ref):
            raise ValueError(f"valid: {len(valid):,} places, the index has {index.n_ref:,}")
        self.index, self.L, self.mode, self.n_best = index, int(L), mode, int(n_best)
        self._top_s = np.full(self.n_best, 2**62, np.int64)  # the window's best-first list, as the batch keeps it
        self._top_c = np.full(self.n_best, NO_CANDIDATE, np.int64)
        codes, code_bits, n_ref, planes, bit_gap, w, tables, d, k, dmax = index.kernel_args()
        capacity = 2 * self.L * max(1, index.lists.longest)
        masks, gaps = window_masks(self.L, d, bit_gap)
        self._state = np.zeros(4, np.int64)  # frames seen, buffer start, buffer end, ring slot of the oldest
        self._ring_h = np.zeros(self.L, np.uint64)
        self._ring_n = np.zeros(self.L, np.int64)
        self._buf = np.empty(capacity, np.int64)
        self._scratch = np.empty(capacity, np.int64)
        slots = 16
        while slots < 2 * capacity:
            slots *= 2
        self._slots = np.empty(slots, np.int64)
        # The window's addresses, list bounds and bit planes, rebuilt on each frame in place.
        self._win_h = np.empty(self.L, np.uint64)
        self._win_bounds = np.empty((2, self.L), np.int64)
        self._win_planes = np.empty(((self.L + 63) // 64 + 2) * d, np.uint64)
        lists = index.lists
        self._args = _plain((lists.occupied_args(), lists.starts_args(), lists.ids, lists.id_bits, codes, code_bits,
                             n_ref, planes, gaps, masks, valid, w, tables, d, k, dmax))
        self._fast = bool(k == 2 and planes.shape[0] > 0 and float(self.L) * float(dmax) < 2.0**53)
        centres = np.ascontiguousarray(index.centres, np.float64)
        self._dim = int(index.components.shape[1])
        self._frame = np.zeros((1, self._dim), np.float32)  # push copies each frame here: one type, one call
        self._row = self._frame[0]  # ``row[...] = x`` is numpy's shortest copy path, half of ``frame[0] = x``
        self._last = np.full(1, -1, np.int64)  # the last match's N_r (−1 before the first)
        self._score = np.full(1, np.nan)  # and its score
        model = (np.ascontiguousarray(index.mean, np.float64), np.ascontiguousarray(index.components.T, np.float64),
                 centres, np.empty(d), np.empty(d, np.uint8))
        self._lent = model  # the engine holds the arrays by address only: these, the index's and the matcher's
        self._engine = _engine(self._frame, self._last, self._score, self._top_s, self._top_c, *model,
                               float((centres[:, -1] - centres[:, 0]).sum()), self._state, self._ring_h,
                               self._ring_n, self._buf, self._scratch, self._slots, self._win_h, self._win_bounds,
                               self._win_planes, self.L, self.mode == "aligned", self._fast, *self._args)
        self._push = _push.compile((numba.typeof(self._engine),))  # compiled, or loaded from numba's cache

    def push(self, descriptor: np.ndarray, return_score: bool = False) -> int | tuple[int, float] | None:
        """Add one query frame; the match of the window it completes (None until L frames), and
        its score with ``return_score``."""
        try:
            self._row[...] = descriptor  # cast to float32 as the batch reads frames
        except (ValueError, TypeError):
            raise ValueError(f"a query frame of {np.size(descriptor)} features; this index hashes frames of "
                             f"{self._dim}") from None
        match = self._push(self._engine)  # one Python int back: N_r and the score stay in the engine
        if match < 0:
            return None
        return (match, float(self._score[0])) if return_score else match

    @property
    def n_r(self) -> int | None:
        """The last window matched's number of candidates (None before the first match)."""
        n = int(self._last[0])
        return None if n < 0 else n

    @property
    def top(self) -> np.ndarray:
        """The ``n_best`` best candidates of the last window matched, best first (−1 where there
        were fewer)."""
        return np.where(self._top_c == NO_CANDIDATE, -1, self._top_c)

    def push_address(self, h: int) -> int | None:
        """Add one query frame given its own address (already hashed)."""
        match, _ = self.push_addresses(np.array([h], np.uint64))
        return None if match[0] < 0 else int(match[0])

    def push_many(self, descriptors: np.ndarray, return_score: bool = False,
                  return_top: bool = False) -> tuple[np.ndarray, ...]:
        """Add consecutive query frames (rows); ``(match, n_r)`` of the window each completes
        (−1 and 0 for the first L − 1 frames), then ``score`` (NaN there) with ``return_score``
        and ``top`` (rows of ``n_best``, −1 there) with ``return_top``: what :meth:`push`
        answers frame by frame, with the hashing and the Python call done once for the block."""
        h, err = self.index.hash_frames(np.asarray(descriptors, np.float32))
        return self._advance(h, err, return_score, return_top)

    def push_addresses(self, h: np.ndarray, return_score: bool = False,
                       return_top: bool = False) -> tuple[np.ndarray, ...]:
        """:meth:`push_many` for frames given by their own addresses (already hashed; an L = 1
        score then counts no quantisation error, as the batch's without errors)."""
        return self._advance(np.asarray(h, np.uint64), None, return_score, return_top)

    def _advance(self, h: np.ndarray, errors: np.ndarray | None, scores: bool, tops: bool) -> tuple[np.ndarray, ...]:
        """The frames in; ``(match, n_r)``, then the scores in δ_max units, as the batch's (at L = 1
        computed only when asked for; for sequences the step finds them anyway) and the best-first
        lists, as asked for."""
        h = np.asarray(h, np.uint64)
        if self.L == 1:  # a single frame: the single best of its address, as the batch reports it
            lists = self.index.lists
            slots, taken = lists.nearest(h)
            match, n_r, top = _heads(lists.starts_args(), lists.ids, lists.id_bits, slots, self.n_best)
            score = self.index.single_scores(h, taken, errors) if scores else None
        else:
            match, n_r, units, top = _steps(h, self._state, self._ring_h, self._ring_n, self._buf, self._scratch,
                                            self._slots, self._win_h, self._win_bounds, self._win_planes, self.L,
                                            self.mode == "aligned", self._fast, self._top_s, self._top_c, *self._args)
            score = np.where(match >= 0, units / float(self._args[-1]), np.nan)
        if len(h) and match[-1] >= 0:  # the last frame's window, as push leaves it
            self._top_c[:] = np.where(top[-1] < 0, NO_CANDIDATE, top[-1])
            self._last[0] = n_r[-1]
            self._score[0] = np.nan if score is None else score[-1]
        return (match, n_r, *((score,) if scores else ()), *((top,) if tops else ()))

    @property
    def state_bytes(self) -> int:
        """Bytes held between frames: fixed at construction, whatever the length of the stream."""
        return sum(a.nbytes for a in (self._state, self._ring_h, self._ring_n, self._buf, self._scratch, self._slots,
                                      self._win_h, self._win_bounds, self._win_planes, self._top_s, self._top_c))


@structref.register
class _EngineType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(typ)) for name, typ in fields)


class _Engine(structref.StructRefProxy):
    """What :func:`_push` reads, in one object: the hashing model and scratch, the matcher's state
    (the same arrays ``push_many`` steps, so both kinds of push share one stream) and the index,
    every array lent by address (:mod:`vprscale.method.lent`)."""


structref.define_proxy(_Engine, _EngineType, [
    "frame", "last", "score", "top_s", "top_c", "mean", "w", "centres", "acc", "code_row", "span",
    "state", "ring_h", "ring_n", "buf", "cand", "slots", "win_h", "win_bounds", "win_planes", "L", "aligned", "fast",
    "occ", "starts", "ids", "id_bits", "codes", "code_bits", "n_ref", "planes", "gaps", "masks", "valid", "dw",
    "tables", "d", "k", "dmax"])


@numba.njit(cache=True)
def _engine(frame, last, score, top_s, top_c, mean, w, centres, acc, code_row, span, state, ring_h, ring_n, buf, cand,
            slots, win_h, win_bounds, win_planes, L, aligned, fast, occ, starts, ids, id_bits, codes, code_bits, n_ref,
            planes, gaps, masks, valid, dw, tables, d, k, dmax) -> _Engine:
    """The engine of these arrays (lent: their owner keeps them) and values."""
    kind, high, low, lb, ones, zeros, n, size = occ
    s_high, s_low, s_lb, s_ones = starts
    return _Engine(lend(frame), lend(last), lend(score), lend(top_s), lend(top_c), lend(mean), lend(w), lend(centres),
                   lend(acc), lend(code_row), span, lend(state), lend(ring_h), lend(ring_n), lend(buf), lend(cand),
                   lend(slots), lend(win_h), lend(win_bounds), lend(win_planes), L, aligned, fast,
                   (kind, lend(high), lend(low), lb, lend(ones), lend(zeros), n, size),
                   (lend(s_high), lend(s_low), s_lb, lend(s_ones)), lend(ids), id_bits, lend(codes), code_bits,
                   n_ref, lend(planes), lend(gaps), lend(masks), lend(valid), lend(dw), lend(tables), d, k, dmax)


@numba.njit(cache=True)  # the GIL kept: releasing and taking it back would cost a third of an L = 1 frame
def _push(e: _Engine) -> np.int64:
    """One frame (``e.frame``): hashed as the batch hashes it, then the step; the match (−1
    before L frames), its N_r and its score (in δ_max units, as the batch reports it) left in
    ``e.last`` and ``e.score``: one value boxed for Python, not three. L = 1: the single best of
    the frame's address, scored by its quantisation error and its move to the occupied address it
    took (:meth:`Index.single_scores`)."""
    kind, high, low, lb, ones, zeros, n, size = e.occ
    occ = (kind, borrow(high), borrow(low), lb, borrow(ones), borrow(zeros), n, size)
    s_high, s_low, s_lb, s_ones = e.starts
    starts = (borrow(s_high), borrow(s_low), s_lb, borrow(s_ones))
    ids, top_c, dw, tables, last_n, score = borrow(e.ids), borrow(e.top_c), borrow(e.dw), borrow(e.tables), \
        borrow(e.last), borrow(e.score)
    h, err = hash_one(borrow(e.frame), 0, borrow(e.mean), borrow(e.w), borrow(e.centres), borrow(e.acc),
                      borrow(e.code_row))
    if e.L == 1:
        slot, taken = nearest_slot(occ, h)
        first, last = list_span(starts, slot)
        _list_head(ids, e.id_bits, first, last, top_c)
        moved = delta(h, taken, dw, tables, e.d, e.k)
        last_n[0], score[0] = last - first, err / e.span + moved / float(e.dmax)
        return np.int64(get_packed(ids, e.id_bits, first))
    best, n_r, units = _step(h, borrow(e.state), borrow(e.ring_h), borrow(e.ring_n), borrow(e.buf), borrow(e.cand),
                             borrow(e.slots), borrow(e.win_h), borrow(e.win_bounds), borrow(e.win_planes), e.L,
                             e.aligned, e.fast, borrow(e.top_s), top_c, occ, starts, ids, e.id_bits, borrow(e.codes),
                             e.code_bits, e.n_ref, borrow(e.planes), borrow(e.gaps), borrow(e.masks),
                             borrow(e.valid), dw, tables, e.d, e.k, e.dmax)
    if best >= 0:
        last_n[0], score[0] = n_r, units / float(e.dmax)
    return best


@numba.njit(cache=True, nogil=True, inline="always")
def _list_head(ids: np.ndarray, id_bits: int, first: np.int64, last: np.int64, top_c: np.ndarray) -> None:
    """L = 1's best-first list: the list's first ``n_best`` ids (its single best, then the rest by
    id, as the batch's ``frame_top``), empty places ``NO_CANDIDATE``."""
    for j in range(top_c.shape[0]):
        top_c[j] = np.int64(get_packed(ids, id_bits, first + j)) if first + j < last else NO_CANDIDATE


@numba.njit(cache=True, nogil=True)
def _heads(starts: tuple, ids: np.ndarray, id_bits: int, slots: np.ndarray,
           n_best: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(best, size, top)`` of each slot's list: the single best, the length, the best-first list."""
    best = np.empty(slots.shape[0], np.int64)
    size = np.empty(slots.shape[0], np.int64)
    top = np.empty((slots.shape[0], n_best), np.int64)
    for i in range(slots.shape[0]):
        first, last = list_span(starts, slots[i])
        best[i], size[i] = np.int64(get_packed(ids, id_bits, first)), last - first
        _list_head(ids, id_bits, first, last, top[i])
    return best, size, finish_best(top)


def _plain(value):
    """Memory-mapped arrays as plain ndarray views of the same pages (nothing copied): numba types
    an ndarray subclass on its slow path, and a push pays that on every call."""
    if isinstance(value, np.ndarray):
        return value.view(np.ndarray)
    if isinstance(value, tuple):
        return tuple(_plain(v) for v in value)
    return value


@numba.njit(cache=True, nogil=True)
def _steps(hs: np.ndarray, st: np.ndarray, ring_h: np.ndarray, ring_n: np.ndarray, buf: np.ndarray,
           cand: np.ndarray, slots: np.ndarray, win_h: np.ndarray, win_bounds: np.ndarray, win_planes: np.ndarray,
           L: int, aligned: bool, fast: bool, top_s: np.ndarray, top_c: np.ndarray, occ: tuple, starts: tuple,
           ids: np.ndarray, id_bits: int, codes: np.ndarray, code_bits: int, n_ref: int, planes: np.ndarray,
           gaps: np.ndarray, masks: np.ndarray, valid: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int, k: int,
           dmax: np.int64) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_step` for each address of ``hs`` in turn: match, N_r, the match's score in
    fixed-point units and the best-first list (−1 before L frames)."""
    match = np.empty(hs.shape[0], np.int64)
    n_r = np.empty(hs.shape[0], np.int64)
    units = np.empty(hs.shape[0], np.int64)
    top = np.full((hs.shape[0], top_c.shape[0]), NO_CANDIDATE, np.int64)
    for i in range(hs.shape[0]):
        match[i], n_r[i], units[i] = _step(hs[i], st, ring_h, ring_n, buf, cand, slots, win_h, win_bounds,
                                           win_planes, L, aligned, fast, top_s, top_c, occ, starts, ids, id_bits,
                                           codes, code_bits, n_ref, planes, gaps, masks, valid, w, tables, d, k, dmax)
        if match[i] >= 0:
            top[i] = top_c
    return match, n_r, units, finish_best(top)


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _step(h: np.uint64, st: np.ndarray, ring_h: np.ndarray, ring_n: np.ndarray, buf: np.ndarray,
          cand: np.ndarray, slots: np.ndarray, win_h: np.ndarray, win_bounds: np.ndarray, win_planes: np.ndarray,
          L: int, aligned: bool, fast: bool, top_s: np.ndarray, top_c: np.ndarray, occ: tuple, starts: tuple,
          ids: np.ndarray, id_bits: int, codes: np.ndarray, code_bits: int, n_ref: int, planes: np.ndarray,
          gaps: np.ndarray, masks: np.ndarray, valid: np.ndarray, w: np.ndarray, tables: np.ndarray, d: int, k: int,
          dmax: np.int64) -> tuple[np.int64, np.int64, np.int64]:
    """One frame: its list into the window, then the window's match (−1 until L frames), its N_r
    and its score (fixed point); ``(top_s, top_c)`` then hold the window's best-first list
    (scores and candidates, ``NO_CANDIDATE`` where there were fewer), as the batch's
    ``_score_pairs`` keeps it: ordered by score, ties to the smaller candidate, each score
    bounded by the list's last."""
    a, _ = nearest_slot(occ, h)
    slot = st[3]
    if st[0] >= L:  # the oldest frame leaves the window
        st[1] += ring_n[slot]
    first, last = list_span(starts, a)
    n = last - first
    if st[2] + n > buf.shape[0]:  # slide the window's lists back to the start of the buffer
        live = st[2] - st[1]
        for i in range(live):
            buf[i] = buf[st[1] + i]
        st[1], st[2] = 0, live
    for q in range(n):
        buf[st[2] + q] = np.int64(get_packed(ids, id_bits, first + q))
    ring_h[slot], ring_n[slot] = h, n
    st[2] += n
    st[3] = (slot + 1) % L
    st[0] += 1
    if st[0] < L:
        return np.int64(-1), np.int64(0), np.int64(0)
    # The window, oldest frame first: its addresses, list bounds and bit planes.
    half = L // 2
    q_hash, q_start, q_stop, q_planes = win_h, win_bounds[0], win_bounds[1], win_planes
    q_planes[:] = 0
    pos = st[1]
    for i in range(L):
        j = (st[3] + i) % L
        q_hash[i] = ring_h[j]
        q_start[i] = pos
        pos += ring_n[j]
        q_stop[i] = pos
        if fast:
            set_bit(q_planes[(i >> 6) * d:], ring_h[j], i & 63, d)
    total = st[2] - st[1]
    bits = 4
    while (1 << bits) < 2 * total:
        bits += 1
    q_words = q_planes[: masks.shape[0]]  # the window starts at frame 0: its words are the plane rows as they are
    n_r = window_candidates(np.int64(half), L, half, aligned, q_start, q_stop, buf, n_ref, cand, slots[: 1 << bits],
                            bits, valid)
    n_best = top_c.shape[0]
    top_s[:] = np.int64(2**62)
    top_c[:] = NO_CANDIDATE
    for m in range(n_r):
        c = cand[m]
        if fast and c >= half and c - half + L <= n_ref:
            s = score_planes(c - half, planes, d, q_words, masks, gaps)
        else:
            s = score_window(c, np.int64(half), L, half, codes, code_bits, n_ref, q_hash, w, tables, d, k, dmax,
                             top_s[n_best - 1] + 1)
        keep_best_at(top_s, top_c, np.int64(0), n_best, s, c)
    best = top_c[0] if top_c[0] != NO_CANDIDATE else np.int64(-1)
    return best, np.int64(n_r), np.int64(top_s[0])
