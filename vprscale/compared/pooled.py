"""Pooled sequence descriptors as a compared method (docs/protocol.md, "Sequence descriptors").

Since 2022 the sequence-VPR field pools the ``L`` frames of a window into one descriptor and
retrieves it (SeqVLAD's and JIST's untrained baselines: the mean, and GeM). Here the window of
every reference centre and of every query centre is pooled alike, the references' pooled rows
are held in any FAISS code (``seq:PQ3``, ``seq:IVF4096,PQ3``, ``seq:Flat``), and a query
window's pooled row is searched in it: its nearest pooled reference is the match. With
``+rerank`` the code only proposes: CoarseHash's own window score ranks its ``N`` best, as
CaseVPR refines a sequence descriptor's proposals by frame-to-frame matching.

Reference windows depend on ``L``, so each ``L`` has its own encoding. A window's sum is made
the same way whatever rows arrive together (:class:`WindowPooler`): the same bytes for any
chunking of the references.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import dask.array as da
import numba
import numpy as np
from threadpoolctl import threadpool_limits

from vprscale.compared.faisscodes import FaissCodes, training_rows
from vprscale.core.errors import InputError
from vprscale.core.kernelcache import share_kernels
from vprscale.core.progress import ChunkProgress, Timings
from vprscale.protocol import WindowMask

share_kernels()

POOLINGS = {"seq": "mean", "seq-gem3": "gem"}  # prefix of a --compare string → how its windows are pooled
GEM_P = 3.0  # GeM's exponent (JIST's SeqGeM and GeM's usual starting value)
DEFAULT_RERANK = 20  # candidates the pooled code proposes to CoarseHash's window score
POOL_ROWS = 1 << 16  # reference rows pooled at a time (three float64 copies of them are held)
_SPEC = re.compile(r"^(seq|seq-gem3):(.+?)(\+rerank(\d*))?$")


def is_pooled(spec: str) -> bool:
    """Whether a ``--compare`` string names a pooled sequence descriptor (``seq:…``, ``seq-gem3:…``);
    a prefix that looks like one but is not (``seq-gem:``, ``seq-mean:``) is an error saying which are."""
    prefix, colon, _ = spec.partition(":")
    if colon and prefix not in POOLINGS and prefix.lower().startswith("seq"):
        raise InputError(f"--compare {spec}: {prefix}: is no pooling; a pooled sequence descriptor is seq:FACTORY "
                         "(the window's mean) or seq-gem3:FACTORY (GeM, p = 3), e.g. seq:PQ3, seq-gem3:PQ3")
    return prefix in POOLINGS


@dataclass(frozen=True)
class PooledSpec:
    """A ``--compare`` string of a pooled descriptor: its pooling, FAISS factory and re-ranking."""

    prefix: str  # "seq" (mean) or "seq-gem3" (GeM, p = 3)
    factory: str
    rerank: int | None = None  # candidates CoarseHash's window score re-ranks (None: no re-ranking)

    @property
    def pooling(self) -> str:
        return POOLINGS[self.prefix]

    @property
    def name(self) -> str:
        """The ``method`` column: the string as given, with the re-ranking's N when not the default."""
        tail = "" if self.rerank is None else "+rerank" + ("" if self.rerank == DEFAULT_RERANK else str(self.rerank))
        return f"{self.prefix}:{self.factory}{tail}"


MAX_RERANK = 100_000  # candidates a query's window score re-ranks at most


def parse_pooled(spec: str) -> PooledSpec:
    """``seq:FACTORY``, ``seq-gem3:FACTORY``, either with ``+rerank`` or ``+rerankN`` (N ≥ 1)."""
    found = _SPEC.match(spec)
    if found is None:
        raise InputError(f"--compare {spec}: a pooled sequence descriptor is seq:FACTORY or seq-gem3:FACTORY, "
                         "optionally followed by +rerank or +rerankN (for example seq:PQ3, seq-gem3:Flat+rerank)")
    prefix, factory, rerank, n = found.groups()
    if rerank is not None and n and not 1 <= int(n) <= MAX_RERANK:
        raise InputError(f"--compare {spec}: +rerank{n}: re-ranks at least one candidate and at most "
                         f"{MAX_RERANK:,} (each is scored over its whole window)")
    return PooledSpec(prefix, factory, None if rerank is None else int(n or DEFAULT_RERANK))


class Pooling:
    """How a window's rows become one: the mean, or GeM (``(mean of x^p)^(1/p)``, p = 3) of rows
    shifted by the references' per-column minimum and clamped at zero (GeM needs non-negative
    values; a query value below every reference's counts as that minimum). Sums are float64."""

    def __init__(self, how: str, shift: np.ndarray | None = None) -> None:
        if how == "gem" and shift is None:
            raise ValueError("GeM pooling needs the references' per-column minimum")
        self.how, self.shift = how, shift

    def lift(self, x: np.ndarray) -> np.ndarray:
        """Rows as they are summed (float64)."""
        x = np.asarray(x, np.float64)
        return x if self.how == "mean" else np.maximum(x - self.shift, 0.0) ** GEM_P

    def finish(self, sums: np.ndarray, L: int) -> np.ndarray:
        """Pooled rows (float32) from window sums."""
        mean = sums / L
        return np.asarray(mean if self.how == "mean" else np.cbrt(mean), np.float32)


class WindowPooler:
    """Pooled rows of every complete window of ``L`` consecutive rows, fed rows in order in any
    pieces (:meth:`push`). A window's sum is read from segments of ``L`` rows at fixed positions
    (multiples of ``L``): the sum of the rows from its start to the end of its segment, plus the
    rows of the next segment up to its last (van Herk and Gil-Werman's running sums, two adds a
    value however long ``L`` is), each a running sum within its segment, so the bytes do not
    depend on how the rows were cut."""

    def __init__(self, L: int, pooling: Pooling) -> None:
        self.L, self.pooling = L, pooling
        self._held = np.zeros((0, 0))  # lifted rows from the segment of the next window's start on
        self._first = 0  # row number of the first held row (a multiple of L)
        self._next = 0  # start of the next window to pool

    def push(self, x: np.ndarray) -> np.ndarray:
        """The pooled rows of the windows the rows so far complete, that earlier pushes did not give."""
        x = self.pooling.lift(x)
        held = np.concatenate([self._held, x]) if len(self._held) else x
        end = self._first + len(held)  # rows seen
        stop = max(self._next, end - self.L + 1)  # window starts now complete
        out = self._sums(held, stop - self._next) if stop > self._next else np.zeros((0, held.shape[1]))
        self._next = stop
        keep = stop // self.L * self.L  # the segment of the next window's start on
        self._held, self._first = held[keep - self._first :], keep
        return self.pooling.finish(out, self.L)

    def _sums(self, held: np.ndarray, n: int) -> np.ndarray:
        """Sums of the ``n`` windows from ``_next`` on over ``held`` (rows from ``_first``, a multiple of L)."""
        return segment_sums(np.ascontiguousarray(held), self._next - self._first, n, self.L)


@numba.njit(cache=True, nogil=True)
def segment_sums(held: np.ndarray, first: int, n: int, L: int) -> np.ndarray:
    """Sums of the ``n`` windows of ``L`` rows starting at rows ``first, first + 1, …`` of
    ``held``, whose row 0 starts a segment: the running sum from a window's start to its
    segment's end, plus the next segment's running sum from its start to the window's last row."""
    rows, d = held.shape
    prefix, suffix = np.empty_like(held), np.empty_like(held)
    for s in range(0, rows, L):
        e = min(rows, s + L)
        for c in range(d):
            prefix[s, c] = held[s, c]
            suffix[e - 1, c] = held[e - 1, c]
        for i in range(s + 1, e):
            for c in range(d):
                prefix[i, c] = prefix[i - 1, c] + held[i, c]
        for i in range(e - 2, s - 1, -1):
            for c in range(d):
                suffix[i, c] = suffix[i + 1, c] + held[i, c]
    out = np.empty((n, d))
    for w in range(n):
        j = first + w
        for c in range(d):
            out[w, c] = suffix[j, c] + prefix[j + L - 1, c] if j % L else suffix[j, c]
    return out


def pool_windows(rows: np.ndarray, pos: np.ndarray, L: int, pooling: Pooling) -> np.ndarray:
    """Pooled rows of the query windows centred at positions ``pos`` of consecutive ``rows``
    (each window's frames at consecutive positions), summed in order."""
    start = np.asarray(pos, np.int64) - L // 2
    out = np.zeros((len(start), rows.shape[1]))
    for i in range(L):
        out += pooling.lift(rows[start + i])
    return pooling.finish(out, L)


class PooledCodes:
    """One pooled encoding: for each ``L`` a FAISS code over the pooled rows of every complete
    reference window, whose row ``r`` is the window centred on reference ``r + ⌊L/2⌋``. The
    ``specs`` asked for that share it (``seq:F`` and ``seq:F+rerank``: one pooling, one code)
    read the same codes."""

    def __init__(self, specs: list[PooledSpec], dim: int, lengths: list[int], n_ref: int, nprobe: int,
                 threads: int = 1, sequences: WindowMask | None = None) -> None:
        self.specs, self.n_ref = specs, n_ref
        # many sequences: only the windows that exist are pooled, and code row e is the window
        # starting at reference starts[L][e] (single traverse: every window, row r starts at r)
        self.starts = {L: np.flatnonzero(sequences.mask(L)) - L // 2
                       for L in lengths if 1 < L <= n_ref} if sequences is not None else {}
        self.spec = PooledSpec(specs[0].prefix, specs[0].factory)  # the encoding: a pooling and a code
        named = specs[0].name  # as the user wrote it, for messages
        try:
            self.codes = {L: FaissCodes(self.spec.factory, dim, 1, nprobe, threads, windows=False)
                          for L in lengths if 1 < L <= n_ref}
        except InputError as err:
            raise InputError(str(err).replace(f"--compare {self.spec.factory}", f"--compare {named}", 1)) from None
        for L, codes in self.codes.items():
            if codes.ivf is not None and codes.ivf.nlist > self.windows(L):
                raise InputError(f"--compare {named}: {codes.ivf.nlist:,} inverted lists for "
                                 f"{self.windows(L):,} reference windows of {L} frames; FAISS needs at least one "
                                 "window per list to train")
        self.pooling = Pooling("mean") if self.spec.pooling == "mean" else None  # GeM's: once the minimum is known

    def windows(self, L: int) -> int:
        """Complete reference windows of ``L`` frames (of many sequences: those that exist)."""
        return len(self.starts[L]) if L in self.starts else self.n_ref - L + 1

    def centres(self, ids: np.ndarray, L: int) -> np.ndarray:
        """The centre of each found code row (−1 stays −1)."""
        start = self.starts[L][np.maximum(ids, 0)] if L in self.starts else ids
        return np.where(ids >= 0, start + L // 2, -1)

    def kept(self, L: int, first: int, n: int) -> tuple[np.ndarray, int]:
        """``(rows, e)``: which of the ``n`` windows starting at ``first, first + 1, …`` are
        encoded (positions among them), and the code row of the first of those."""
        if L not in self.starts:
            return np.arange(n), first
        lo, hi = np.searchsorted(self.starts[L], [first, first + n])
        return self.starts[L][lo:hi] - first, int(lo)

    @property
    def bytes_per_place(self) -> float:
        """What one ``L``'s encoding stores per place of the map (a window per place, less ``L − 1``)."""
        if not self.codes:
            return 0.0
        L = max(self.codes)
        return self.codes[L].bytes_per_place * self.windows(L) / self.n_ref


def pooled_encodings(specs: list[PooledSpec], dim: int, lengths: list[int], n_ref: int, nprobe: int,
                     threads: int = 1, sequences: WindowMask | None = None) -> list[PooledCodes]:
    """One :class:`PooledCodes` per pooling and code asked for, in the order first asked."""
    shared: dict[tuple[str, str], list[PooledSpec]] = {}
    for spec in specs:
        shared.setdefault((spec.prefix, spec.factory), []).append(spec)
    return [PooledCodes(group, dim, lengths, n_ref, nprobe, threads, sequences) for group in shared.values()]


def fit_pooled(methods: list[PooledCodes], ref: da.Array, progress: bool = True) -> None:
    """Train and encode every pooled encoding, every ``L``, in two streamed passes over ``ref``
    (a third before them for GeM's per-column minimum): the first pools the evenly spaced
    windows each code is trained on, the second pools every window and encodes it. Each code
    trains with FAISS and its BLAS on one thread, as the FAISS codes compared frame by frame
    do: the same codes whatever ``--workers``."""
    if any(m.spec.pooling == "gem" for m in methods):
        shift = np.asarray(ref.min(axis=0).compute(), np.float64)
        for m in methods:
            m.pooling = m.pooling or Pooling("gem", shift)
    jobs = [(m, L) for m in methods for L in m.codes]
    kinds = {(m.spec.pooling, L): m.pooling for m, L in jobs}  # pooled once, for every code of that pooling
    sample_at = {(id(m), L): training_rows(m.windows(L)) for m, L in jobs}
    samples: dict[tuple[int, int], list[np.ndarray]] = {key: [] for key in sample_at}
    timings = Timings(not progress)

    def stream(label: str, take: Callable[[PooledCodes, int, int, np.ndarray], None]) -> None:
        poolers = {kind: WindowPooler(kind[1], pooling) for kind, pooling in kinds.items()}
        done = dict.fromkeys(poolers, 0)
        bar = ChunkProgress(label, ref.numblocks[0]) if progress else None
        for i in range(ref.numblocks[0]):
            block = np.asarray(ref.blocks[i].compute(), np.float32)
            for lo in range(0, len(block), POOL_ROWS):
                for kind, pooler in poolers.items():
                    pooled = pooler.push(block[lo : lo + POOL_ROWS])
                    for m, L in jobs:
                        if (m.spec.pooling, L) == kind:
                            take(m, L, done[kind], pooled)
                    done[kind] += len(pooled)
            if bar:
                bar.update(1)

    def keep_sample(m: PooledCodes, L: int, first: int, pooled: np.ndarray) -> None:
        rows, e = m.kept(L, first, len(pooled))
        at = sample_at[(id(m), L)]
        chosen = at[(at >= e) & (at < e + len(rows))]
        samples[(id(m), L)].append(pooled[rows[chosen - e]])

    def encode(m: PooledCodes, L: int, first: int, pooled: np.ndarray) -> None:
        rows, _ = m.kept(L, first, len(pooled))
        if len(rows):
            m.codes[L].encode(pooled if len(rows) == len(pooled) else pooled[rows])

    with timings.stage(f"pool the training windows of {len(methods)} pooled encoding(s)"):
        stream("pool reference windows (training sample)", keep_sample)
    with timings.stage(f"train {len(jobs)} pooled code(s), one per encoding and L"), \
            threadpool_limits(limits=1, user_api="blas"):
        for m, L in jobs:
            m.codes[L].train(np.concatenate(samples.pop((id(m), L))))
            m.codes[L].start(m.windows(L))
    with timings.stage(f"pool and encode {ref.shape[0]:,} references' windows"):
        stream("pool and encode reference windows", encode)
        for m, L in jobs:
            m.codes[L].finish()
