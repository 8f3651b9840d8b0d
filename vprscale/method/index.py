"""The index container of the query engine (docs/method.md): a loaded index,
query hashing, the per-frame work on query frames, and matching through the kernels of
:mod:`vprscale.method.kernels`. The frame-by-frame matcher is :mod:`vprscale.method.online`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import dask.array as da
import numba
import numpy as np

from vprscale.core.publish import PartialOutput
from vprscale.method.coarsehash import CoarseHasher, hash_descriptors
from vprscale.method.engine import code_bits
from vprscale.method.indexfile import read_arrays, write_arrays
from vprscale.method.invlists import InvertedLists, best_first, frame_top
from vprscale.method.kernels import (
    DELTA_MAX_UNITS,
    N_BEST,
    address_delta,
    bit_gaps,
    bit_planes,
    byte_tables,
    decode_codes,
    match_batch,
    score_centres,
)
from vprscale.method.lists import inverted_lists
from vprscale.method.succinct import pack
from vprscale.protocol import NO_MASK, centre_lag, check_window, window_positions, window_start


@dataclass
class QueryFrames:
    """The per-frame work on query frames, done once per frame as it arrives (docs/method.md).

    A frame is hashed, given the nearest occupied address, and has that address's list
    decoded (the paper's O(1) list look-up per new frame); for K = 2 its address also
    goes into bit planes like the references' (:func:`bit_planes`). Every window that
    contains the frame then reads these, so a query's sequence match never goes back to
    the index's lists. The lists lie in frame order; past ``SHARED_ABOVE`` ids together (a
    coarse index, whose frames share a few long lists) each distinct list is decoded once
    and shared (:func:`~vprscale.method.invlists.gather`).

    Only the frames worked on are held, ascending; arrays are indexed by position among
    them, and a window's frames, consecutive in the sequence, are consecutive here too.
    """

    frames: np.ndarray  # the frames held (ascending), positions 0 … n − 1
    hashes: np.ndarray  # own address of every frame (uint64)
    slot: np.ndarray  # position of the occupied address used, among the occupied addresses
    taken: np.ndarray  # that occupied address (uint64)
    start: np.ndarray  # the list of the frame at position i is ids[start[i]:stop[i]]
    stop: np.ndarray
    ids: np.ndarray  # the frames' lists, decoded (int64)
    planes: np.ndarray  # K = 2: bit b of positions 64·i … 64·i + 63 as word i·d + b
    errors: np.ndarray | None = None  # each frame's quantisation error Σ_j min_k |y_j − c_kj| (None: unknown)

    def positions(self, t: np.ndarray, L: int = 1) -> np.ndarray:
        """Positions of frames ``t``, each with the whole window of ``L`` centred on it held."""
        return window_positions(self.frames, t, L)

    def kernel_args(self) -> tuple:
        """``(hashes, planes, start, stop, ids)``: the query frames' arguments of :func:`match_batch`."""
        return self.hashes, self.planes, self.start, self.stop, self.ids


@dataclass
class Matches:
    """What :meth:`Index.match` answers for each centre (docs/method.md, "Scores").

    ``score`` is the matched window's score in units of δ_max (the most two codes can
    differ), lower meaning more confident: the sum of the window's frame distances for
    L > 1; for L = 1 the frame's own quantisation error plus the distance from its own
    address to the occupied one it took, both in the same units. ``top`` holds the
    ``n_best`` best candidates, best first (−1 where there were fewer); ``top[:, 0]`` is
    ``match``. For L = 1 it is the single best, then the rest of its list by id.
    """

    centres: np.ndarray  # frame index of each window's centre (default: L // 2 onwards)
    match: np.ndarray
    score: np.ndarray
    n_r: np.ndarray  # candidates scored (L = 1: the length of the frame's list)
    top: np.ndarray

    def __repr__(self) -> str:
        return f"Matches({len(self.centres):,} centres, top {self.top.shape[1]})"


@dataclass(repr=False)
class Index:
    """A CoarseHash index: a fitted :class:`~vprscale.method.coarsehash.CoarseHasher`, its
    references' codes and their inverted lists (docs/method.md), shaped like a FAISS index.

    ``Index.build(ref, d=…, k=…)`` fits and adds in one call (or ``Index.build(ref,
    hasher=fitted)``), :meth:`match` localises a traverse, :meth:`save` / :meth:`load` (and
    the module's :func:`write_index` / :func:`read_index`) write and open the directory
    format of :mod:`vprscale.method.indexfile` that every command reads. A loaded index
    holds its codes and lists as the engine's arrays, decoded from the directory's Parquet
    tables in memory or, for a large index, once into a local cache that later loads
    memory-map (:mod:`vprscale.method.engine`).

    Everything is held succinctly (docs/method.md, "Storage"): ``codes`` is P1, each
    place's address in ⌈d·log2 K⌉ bits (for K = 2 the bit planes the windows are scored
    on), and ``lists`` the ids bit-packed with an Elias–Fano directory
    (:class:`~vprscale.method.invlists.InvertedLists`).
    """

    hasher: CoarseHasher
    codes: np.ndarray  # P1: K = 2 bit planes (kernels.bit_planes), else packed addresses
    lists: InvertedLists
    n_ref: int
    meta: dict = field(default_factory=dict)

    @classmethod
    def build(cls, ref: np.ndarray | da.Array, d: int | None = None, k: int = 2,
              hasher: CoarseHasher | None = None) -> Index:
        """Fit CoarseHash on reference rows ``ref`` (numpy or Dask; or take a fitted ``hasher``)
        and add every row: the index of ``ref`` in memory, ids ``0 … len(ref) − 1``.

        For stores of any size the ``vprscale index`` job does the same in bounded memory.
        """
        if hasher is None:
            hasher = CoarseHasher(d=d, k=k).fit(ref)
        elif d is not None and d != hasher.d_ or k != hasher.k:
            raise ValueError(f"d = {d}, k = {k}: give either d and k or a fitted hasher "
                             f"(its d = {hasher.d_}, k = {hasher.k}), not both")
        x = ref.compute() if isinstance(ref, da.Array) else np.asarray(ref)
        _, h, err, _ = hash_descriptors(hasher._rows(x), hasher.mean_, hasher.components_, hasher.centres_)
        return cls.from_addresses(h, hasher, err.astype(np.float32))

    @classmethod
    def from_addresses(cls, ref_hash: np.ndarray, hasher: CoarseHasher, errors: np.ndarray) -> Index:
        """The index of references with given addresses and quantisation errors (the single best
        of an address is its least error, ties to the smaller id)."""
        ref_hash = np.asarray(ref_hash, np.uint64)
        errors = np.asarray(errors)
        if errors.shape != ref_hash.shape:
            raise ValueError(f"errors: shape {errors.shape}, one per address {ref_hash.shape} expected")
        lists = inverted_lists(ref_hash, errors)
        offsets = np.r_[lists["offsets"], len(ref_hash)].astype(np.int64)
        order = lists["order"].astype(np.int64)
        best_first(order, offsets, lists["best"].astype(np.int64))
        d, k = int(hasher.d_), int(hasher.k)
        codes = bit_planes(ref_hash, d) if k == 2 else pack(ref_hash, code_bits(d, k))
        return cls(hasher, codes, InvertedLists.build(lists["addresses"], offsets, order, len(ref_hash), k**d),
                   len(ref_hash), {"n_ref": len(ref_hash)})

    @classmethod
    def load(cls, path: str | Path) -> Index:
        """Open an index directory (:func:`read_index`)."""
        return read_index(path)

    def save(self, path: str | Path) -> Path:
        """Write the index directory (:func:`write_index`)."""
        return write_index(self, path)

    def __repr__(self) -> str:
        return (f"Index(d={self.d}, k={self.k}, n_ref={self.n_ref:,}, occupied={self.occupied:,}, "
                f"features={self.components.shape[1]})")

    @property
    def d(self) -> int:
        return int(self.hasher.d_)

    @property
    def k(self) -> int:
        return int(self.hasher.k)

    @property
    def mean(self) -> np.ndarray:
        return self.hasher.mean_

    @property
    def components(self) -> np.ndarray:
        return self.hasher.components_

    @property
    def centres(self) -> np.ndarray:
        return self.hasher.centres_

    @property
    def occupied(self) -> int:
        """Number of occupied addresses (lists)."""
        return self.lists.n_lists

    @property
    def code_bits(self) -> int:
        return code_bits(self.d, self.k)

    @property
    def planes(self) -> np.ndarray:
        """For K = 2 the references' addresses as bit planes (:func:`bit_planes`), which are the
        codes themselves; else empty."""
        return self.codes if self.k == 2 else np.zeros(0, np.uint64)

    def ref_addresses(self, a: int = 0, b: int | None = None) -> np.ndarray:
        """The addresses of references ``a … b − 1`` (default: all), decoded from the codes (uint64)."""
        b = self.n_ref if b is None else min(b, self.n_ref)
        return decode_codes(self.codes, self.code_bits, self.d, self.k, np.int64(a), np.int64(max(a, b)))

    def weights(self) -> np.ndarray:
        """Fixed-point ``|c_ja − c_jb|`` as a (d, K, K) int64 table."""
        diff = np.abs(self.centres[:, :, None] - self.centres[:, None, :])
        span = (self.centres[:, -1] - self.centres[:, 0]).sum()
        return np.rint(diff * (DELTA_MAX_UNITS / span)).astype(np.int64)

    def kernel_args(self) -> tuple:
        """``(codes, code_bits, n_ref, planes, gaps, w, tables, d, k, δ_max)``: the index's
        arguments of :func:`match_batch`.

        ``gaps[b]`` is the cost of a differing bit ``b`` (K = 2), ``tables`` the per-byte δ.
        """
        w, tables, dmax = self.delta_tables()
        return (self.codes, self.code_bits, self.n_ref, self.planes, bit_gaps(w), w, tables, self.d, self.k,
                dmax)

    def delta_tables(self) -> tuple[np.ndarray, np.ndarray, np.int64]:
        """``(w, tables, δ_max)``: what :func:`delta` needs, frame by frame (built once)."""
        return self._delta

    @cached_property
    def _delta(self) -> tuple[np.ndarray, np.ndarray, np.int64]:
        w = self.weights()
        tables = byte_tables(w) if self.k == 2 else np.zeros((1, 256), np.int64)
        return w, tables, np.int64(w[:, 0, -1].sum())

    def hash_queries(self, x: np.ndarray) -> np.ndarray:
        """Own addresses of query rows (docs/method.md)."""
        return self.hash_frames(x)[0]

    def hash_frames(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(addresses, quantisation errors)`` of query rows: what :meth:`query_frames` takes."""
        x = np.asarray(x)
        if x.ndim != 2 or x.shape[1] != self.components.shape[1]:
            raise ValueError(f"query rows have shape {x.shape}; this index hashes rows of "
                             f"{self.components.shape[1]} features")
        _, h, err, _ = hash_descriptors(x, self.mean, self.components, self.centres)
        return h, err

    def match(self, frames: np.ndarray, L: int, mode: str = "paper", centres: np.ndarray | None = None,
              n_best: int = N_BEST) -> Matches:
        """Localise a traverse by sequences of ``L`` frames (:class:`Matches`).

        ``frames`` are query descriptors in traverse order (rows); ``centres`` index them
        (default: every centre whose whole window lies inside ``frames``, that is
        ``L // 2 … len(frames) − 1 − (L − 1 − L // 2)``). ``mode`` is ``"paper"``
        (candidates: the union of the window's lists) or ``"aligned"`` (each list member
        proposes the centre it implies). L = 1 gives each frame's single best, with its
        list's length as N_r.
        """
        check_window(L, mode)
        h, err = self.hash_frames(frames)
        if L > len(h):
            raise ValueError(f"L = {L}: longer than the {len(h)} frames given")
        t = np.arange(L // 2, len(h) - centre_lag(L)) if centres is None else np.asarray(centres, np.int64)
        if len(t) and (window_start(t.min(), L) < 0 or window_start(t.max(), L) + L > len(h)):
            raise ValueError(f"centres: each window of {L} frames must lie inside the {len(h)} frames given")
        qf = self.query_frames(h, errors=err)
        top, score, n_r = self.answer(qf, qf.positions(t, L), L, mode, n_best)
        return Matches(t, top[:, 0].copy(), score, n_r, top)

    def answer(self, qf: QueryFrames, pos: np.ndarray, L: int, mode: str | None,
               n_best: int = N_BEST, valid: np.ndarray = NO_MASK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(top, score, n_r)`` of the centres at positions ``pos`` of the query frames (see
        :class:`Matches`; ``score`` of the best, in δ_max units); ``valid`` (a byte a place,
        :func:`vprscale.protocol.window_mask`) leaves out the centres whose window does not exist."""
        pos = np.ascontiguousarray(pos, np.int64)  # a slice too: one compiled signature of match_batch
        if L == 1:  # the frame's own list, decoded with the per-frame work: its best first
            err = None if qf.errors is None else np.asarray(qf.errors)[pos]
            score = self.single_scores(qf.hashes[pos], qf.taken[pos], err)
            return frame_top(qf.start, qf.stop, qf.ids, pos, n_best), score, qf.stop[pos] - qf.start[pos]
        args = self.kernel_args()  # (…, δ_max) last
        top, scores, n_r = match_batch(pos, L, mode == "aligned", *qf.kernel_args(), *args, valid, n_best,
                                       numba.get_num_threads())
        return top, scores[:, 0] / float(args[-1]), n_r

    def window_scores(self, qf: QueryFrames, pos: np.ndarray, cand: np.ndarray, L: int) -> np.ndarray:
        """Fixed-point scores (δ_max = ``DELTA_MAX_UNITS``) of candidate centres ``cand[i, j]``
        (−1: none, scored ``NO_CANDIDATE``) for the windows centred at positions ``pos`` of the
        query frames: another method's proposals, scored as this index scores its own."""
        w, tables, dmax = self.delta_tables()
        return score_centres(np.ascontiguousarray(cand, np.int64), np.asarray(pos, np.int64), L, qf.hashes,
                             self.codes, self.code_bits, self.n_ref, w, tables, self.d, self.k, dmax)

    def single_scores(self, h: np.ndarray, taken: np.ndarray, errors: np.ndarray | None) -> np.ndarray:
        """L = 1 scores, in δ_max units: the frame's quantisation error (over the centres' span;
        0 where unknown) plus the distance from its own address to the occupied one it took."""
        w, tables, dmax = self.delta_tables()
        span = float((self.centres[:, -1] - self.centres[:, 0]).sum())
        err = np.zeros(len(h)) if errors is None else np.asarray(errors, np.float64)
        return err / span + address_delta(h, taken, w, tables, self.d, self.k) / float(dmax)

    def warm(self) -> Index:
        """Hold the directory (occupied addresses, list starts: well under a byte per place) and
        the codes in memory, read in order.

        A batch then times look-ups, not first touches of a memory-mapped file: on this VM a
        page's first touch costs 5–35 µs even from the page cache, and at 1B places each
        query frame touches several. The ids stay memory-mapped (a frame reads one list).
        """
        self.lists = self.lists.in_memory()
        self.codes = np.array(self.codes)
        return self

    def query_frames(self, h: np.ndarray, frames: np.ndarray | None = None,
                     errors: np.ndarray | None = None) -> QueryFrames:
        """The per-frame work on query frames with own addresses ``h`` (docs/method.md).

        ``frames`` (ascending; default ``0 … len(h) − 1``) number them in their sequence;
        ``errors`` are their quantisation errors (:meth:`hash_frames`), for L = 1 scores.
        See :class:`QueryFrames`.
        """
        h = np.asarray(h, np.uint64)
        frames = np.arange(len(h)) if frames is None else np.asarray(frames, np.int64)
        a, taken = self.lists.nearest(h)
        start, stop, ids = self.lists.gather(a)
        planes = bit_planes(h, self.d) if self.k == 2 else np.zeros(0, np.uint64)
        return QueryFrames(frames, h, a, taken, start, stop, ids, planes, errors)

    def nearest_occupied(self, h: np.ndarray) -> np.ndarray:
        """Slot of ``h`` among the occupied addresses, else of the numerically nearest (ties: smaller)."""
        return self.lists.nearest(np.asarray(h, np.uint64))[0]


def read_index(path: str | Path) -> Index:
    """Open an index directory (:mod:`vprscale.method.indexfile`); the codes and the lists are
    the engine's arrays (:func:`~vprscale.method.indexfile.read_lists`)."""
    hasher, codes, lists, meta = read_arrays(path)
    return Index(hasher, codes, lists, int(meta["n_ref"]), meta)


def write_index(index: Index, path: str | Path) -> Path:
    """Write ``index`` as the directory that :func:`read_index` and every command open.

    Written whole into a hidden work copy beside ``path`` and published by renames; an
    existing index at ``path`` is replaced only then, anything else there is refused.
    """
    path = Path(path)
    if path.exists() and not (path / "index.json").is_file():
        raise ValueError(f"{path}: exists and is not an index directory; not replaced")
    publish = PartialOutput(path, {"save": index.n_ref})
    publish.recover()
    publish.open()
    write_arrays(publish.path, index.hasher, index.ref_addresses(), index.lists, index.meta)
    publish.publish()
    return path
