"""FAISS compact codes as a compared method (docs/protocol.md, "Compact codes").

Any FAISS ``index_factory`` string with standalone codes (``PQ3``, ``OPQ3,PQ3``, ``ITQ24,LSH``,
``IVF4096,PQ3``, ``RaBitQ``, ``IVF64,RaBitQfs``, ``RQ3x8``, ``LSQ3x8``, …) becomes a method that a
user would otherwise reach for to keep millions of places in a few bytes each, and ``HNSW32``
(a graph over the rows themselves, no code) the one a user reaches for when speed matters
more than bytes. It is trained on an evenly spaced sample of the references and holds every
reference's code; a query frame retrieves its top-k references with FAISS's own search,
and sequences are scored over the codes by :mod:`vprscale.compared.codescore`.

The references are encoded once, chunk by chunk, by the index's own ``sa_encode`` and
handed to it with ``add_sa_codes`` (what ``add`` does, without encoding twice); the same
codes, in reference order, are what the window scores read.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import partial
from typing import Any, NamedTuple

import faiss
import numpy as np

from vprscale.compared import codesearch, rabitq, subtables
from vprscale.compared.codescore import (
    REF_LEVEL_BYTES,
    coarse_levels,
    list_numbers,
    place_records,
    record_width,
    ref_scale,
    score_windows,
)
from vprscale.core.errors import InputError
from vprscale.method.kernels import window_proposals
from vprscale.protocol import NO_MASK

log = logging.getLogger(__name__)

TRAIN_ROWS = 1 << 18  # references a FAISS index is trained on (evenly spaced; all when there are fewer)
DEFAULT_NPROBE = 16  # inverted lists an IVF index visits per frame (FAISS's own default, 1, finds little)
DECODE_ROWS = 1 << 16  # codes decoded at a time
BLOCK_ROWS = 256  # rows one thread searches at a time (fixed: the bytes must not depend on threads)
# Rows one thread encodes at a time (fixed, as BLOCK_ROWS): an IVF's coarse assignment is a BLAS
# product, 2.6x cheaper per row on 4096 rows than on 256 (11 against 28 us a row at 4096 lists, 96-d).
ENCODE_ROWS = 4096  # divides every store's chunk rows (multiples of core.blocks.BLOCK)
ID_BYTES = 8  # FAISS inverted lists hold 64-bit ids
GRAPH_EF_SEARCH = 64  # candidates an HNSW search keeps at the bottom layer (FAISS's default, 16, is for k = 1)
FLOAT_BYTES = 4
# How far FAISS's float32 distances of product-quantiser codes may stray from exact ones, relative
# to the sum of a frame's largest table entries (a few roundings of each term; generous)
EXACT_ROUNDING = 1e-5
_POPCOUNT = np.array([bin(v).count("1") for v in range(256)], np.float32)


class FrameTerms(NamedTuple):
    """What the window scores need of each query frame (the forms' unused parts empty):
    per-byte ``tables`` (frames, bytes, 256), the frames' ``vectors`` (decoded-vector form;
    residual IVF-PQ codes: the frames as the coarse quantiser sees them), and for residual
    IVF-PQ codes the 8-bit ``levels`` of their distances to every inverted list and their
    ``scale`` (:func:`~vprscale.compared.codescore.coarse_levels`)."""

    tables: np.ndarray
    vectors: np.ndarray
    levels: np.ndarray = np.zeros((0, 0), np.uint8)
    scale: np.ndarray = np.zeros((0, 4))


_NO_TABLES, _NO_ROWS = np.zeros((0, 1, 1), np.float32), np.zeros((0, 0), np.float32)


def training_rows(n_ref: int) -> np.ndarray:
    """The references a FAISS index is trained on: ``TRAIN_ROWS`` evenly spaced (all when fewer)."""
    if n_ref <= TRAIN_ROWS:
        return np.arange(n_ref)
    return np.unique(np.linspace(0, n_ref - 1, TRAIN_ROWS).round().astype(np.int64))


def _innermost(index: Any) -> Any:
    """The index a factory's transforms lead to."""
    index = faiss.downcast_index(index)
    return faiss.downcast_index(index.index) if isinstance(index, faiss.IndexPreTransform) else index


# FAISS's fast-scan codes are laid out in blocks of ``bbs`` places and take no standalone codes
# (``add_sa_codes`` is refused, or for IVF ones writes them in the wrong layout): each is built
# from a plain twin holding the standalone codes, by FAISS's own constructor from that twin.
_FAST_SCAN = (faiss.IndexFastScan, faiss.IndexIVFFastScan)


def _pq_twin(fast: Any) -> Any:
    plain = faiss.IndexPQ(fast.d, fast.pq.M, fast.pq.nbits)
    plain.pq = fast.pq
    return plain


def _rabitq_twin(fast: Any) -> Any:
    plain = faiss.IndexRaBitQ(fast.d, fast.metric_type)
    plain.rabitq, plain.center, plain.qb = fast.rabitq, fast.center, fast.qb
    return plain


def _ivf_pq_twin(fast: Any) -> Any:
    plain = faiss.IndexIVFPQ(fast.quantizer, fast.d, fast.nlist, fast.pq.M, fast.pq.nbits)
    plain.pq, plain.by_residual = fast.pq, fast.by_residual
    return plain


def _ivf_rabitq_twin(fast: Any) -> Any:
    plain = faiss.IndexIVFRaBitQ(fast.quantizer, fast.d, fast.nlist)
    plain.rabitq, plain.qb, plain.by_residual = fast.rabitq, fast.qb, fast.by_residual
    return plain


def _aq_twin(fast: Any) -> Any:
    return faiss.IndexAdditiveQuantizer(fast.d, fast.aq, fast.metric_type)


def _ivf_aq_twin(fast: Any) -> Any:
    """A plain IVF index over the fast-scan one's additive quantiser, holding its standalone codes
    as bytes. FAISS builds an IVF fast-scan AQ index only from a plain one that is not by
    residual (the fast-scan codes keep the norm of the whole vector, not of the residual): to
    the copy the bytes are the same either way, and :meth:`FaissCodes._fast_scan_copy` gives
    the copy the original's ``by_residual``."""
    plain = faiss.IndexIVFAdditiveQuantizer(fast.aq, fast.quantizer, fast.d, fast.nlist, fast.metric_type)
    plain.code_size = fast.aq.code_size
    lists = faiss.ArrayInvertedLists(fast.nlist, plain.code_size)
    plain.replace_invlists(lists, True)
    lists.this.disown()  # the plain index owns its lists now
    plain.by_residual = False
    return plain


class _FastScan(NamedTuple):
    """How a fast-scan code is built from standalone codes: the plain twin that takes them, the
    FAISS class whose constructor packs the twin's codes into a fast-scan copy, and the fields
    that constructor does not carry over from the trained original."""

    twin: Callable[[Any], Any]
    copy: Callable[[Any, int], Any]
    kept: tuple[str, ...] = ()


_RABITQ = (faiss.IndexRaBitQ, faiss.IndexRaBitQFastScan, faiss.IndexIVFRaBitQ, faiss.IndexIVFRaBitQFastScan)
_AQ_FAST_SCAN = (faiss.IndexAdditiveQuantizerFastScan, faiss.IndexIVFAdditiveQuantizerFastScan)
_AQ_KEPT = ("rescale_norm", "norm_scale")
_FAST_SCANS: dict[type, _FastScan] = {
    faiss.IndexPQFastScan: _FastScan(_pq_twin, faiss.IndexPQFastScan),
    faiss.IndexRaBitQFastScan: _FastScan(_rabitq_twin, faiss.IndexRaBitQFastScan),
    faiss.IndexIVFPQFastScan: _FastScan(_ivf_pq_twin, faiss.IndexIVFPQFastScan),
    faiss.IndexIVFRaBitQFastScan: _FastScan(_ivf_rabitq_twin, faiss.IndexIVFRaBitQFastScan),
    faiss.IndexAdditiveQuantizerFastScan: _FastScan(_aq_twin, faiss.IndexAdditiveQuantizerFastScan, _AQ_KEPT),
    faiss.IndexIVFAdditiveQuantizerFastScan: _FastScan(_ivf_aq_twin, faiss.IndexIVFAdditiveQuantizerFastScan,
                                                       ("by_residual", *_AQ_KEPT)),
}


def _fast_scan(inner: Any) -> _FastScan | None:
    """How the fast-scan ``inner`` is built from standalone codes (``None``: it cannot be)."""
    return next((how for cls, how in _FAST_SCANS.items() if isinstance(inner, cls)), None)


def _plain_twin(inner: Any) -> Any:
    """An empty plain index like the fast-scan ``inner`` (trained), to take its standalone codes."""
    plain = _fast_scan(inner).twin(inner)
    plain.is_trained = True
    return plain


def graph_rows(index: Any) -> np.ndarray:
    """The rows a linked graph (``HNSW32``, or a transform then one) holds in its flat storage,
    as bytes (places, 4·D): a read-only view of FAISS's memory, not a copy."""
    inner = _innermost(index)
    storage = faiss.downcast_index(inner.storage)
    rows = faiss.rev_swig_ptr(storage.get_xb(), inner.ntotal * inner.d).reshape(inner.ntotal, inner.d)
    rows.flags.writeable = False  # the graph's own rows
    return rows.view(np.uint8)


def _add_standalone(index: Any, codes: np.ndarray, start: int) -> None:
    """Add standalone codes of ids ``start`` on (an IVF index takes them with their ids)."""
    if isinstance(index, faiss.IndexIVF):
        index.add_sa_codes(codes, np.arange(start, start + len(codes), dtype=np.int64))
    else:
        index.add_sa_codes(codes)


def _form(inner: Any) -> str:
    """How the window scores read a FAISS index's codes (:mod:`vprscale.compared.codescore`):
    binary codes by Hamming tables, codes with per-index tables (:mod:`~vprscale.compared.subtables`)
    by their tables, flat or over an inverted file's residuals, any other decoded."""
    if isinstance(inner, faiss.IndexLSH):
        return "hamming"
    if isinstance(inner, _RABITQ) and inner.rabitq.nb_bits == 1 and inner.metric_type == faiss.METRIC_L2:
        return "factors" if not isinstance(inner, faiss.IndexIVF) or inner.by_residual else "vectors"
    if not subtables.has_tables(inner):
        return "vectors"
    if isinstance(inner, faiss.IndexIVF) and inner.metric_type != faiss.METRIC_L2:
        return "vectors"
    if isinstance(inner, faiss.IndexIVF) and inner.by_residual:
        return "residual"
    return "tables"  # flat, or an inverted file of the rows' own codes (``IVF…,PQ…fs``): the list number aside


def _byte_tables(tables: np.ndarray) -> np.ndarray:
    """Per-byte tables of 4-bit product-quantiser codes from per-sub-quantiser ones (frames,
    M, 16): byte ``b`` packs index ``2b`` in its low and ``2b + 1`` in its high nibble (FAISS
    packs least significant bit first), so its table at ``hi · 16 + lo`` is the sum of
    theirs; an odd last sub-quantiser pairs with a zero table (its high nibble is 0)."""
    if tables.shape[1] % 2:
        tables = np.concatenate([tables, np.zeros_like(tables[:, :1])], axis=1)
    low, high = tables[:, 0::2], tables[:, 1::2]
    return (high[:, :, :, None] + low[:, :, None, :]).reshape(len(tables), low.shape[1], 256)


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of the places' codes or vectors: memory-mapped from a stored encoding
    they are read-only, encoded in this process writable; one view type for both keeps
    :func:`score_windows` to one compiled signature (about 17 s of numba a signature, first run)."""
    view = a.view()
    view.flags.writeable = False
    return view


def _one_thread(fn: Callable[[np.ndarray], Any], x: np.ndarray) -> Any:
    """``fn(x)`` with FAISS (and the BLAS it links, threaded by OpenMP) on this thread alone."""
    faiss.omp_set_num_threads(1)  # OpenMP's thread count is per calling thread
    return fn(x)


@contextmanager
def _said_once(factory: str) -> Iterator[None]:
    """What FAISS's C++ prints on the process's standard error while it trains (its k-means says
    "WARNING clustering 2000 points to 256 centroids: please provide at least 9984 training points"
    once per sub-quantiser, raw, between a command's own lines), gathered and said once per
    distinct line, as a log line naming the code."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as said:
        os.dup2(said.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            said.seek(0)
            lines = dict.fromkeys(x.strip() for x in said.read().decode(errors="replace").splitlines() if x.strip())
    for line in lines:
        log.info("  FAISS, training %s: %s", factory, line)


def _encode_blocks(x: np.ndarray, start: int) -> list[np.ndarray]:
    """Rows from id ``start`` cut at the multiples of ``ENCODE_ROWS``: the blocks FAISS encodes."""
    x = np.ascontiguousarray(x, np.float32)
    cuts = np.arange(ENCODE_ROWS - start % ENCODE_ROWS, len(x), ENCODE_ROWS) if len(x) else []
    return np.split(x, cuts) if len(x) else [x]


def _faiss_reason(err: Exception) -> str:
    """FAISS's own message, without the C++ location that precedes it."""
    text = " ".join(str(err).split())
    return re.sub(r"^Error in .*? at \S+:\d+: ", "", text)[:200]



ADDITIVE = ("RQ", "LSQ", "PRQ", "PLSQ")  # FAISS's additive quantisers, by their factory names


MAX_FACTORY_NUMBER = 1 << 22  # the largest count a factory string may ask for (lists, neighbours, bits …)


def _check_sizes(factory: str) -> None:
    """Refuse a count no comparison needs before FAISS allocates for it (``IVF999999999`` asks for
    a billion centroids and fails inside FAISS's allocator)."""
    for number in re.findall(r"\d+", factory):
        if int(number) > MAX_FACTORY_NUMBER:
            raise InputError(f"--compare {factory}: {int(number):,} is more than any compared code uses "
                             f"(at most {MAX_FACTORY_NUMBER:,} lists, neighbours or bits)")


def _check_built(factory: str, index: Any) -> None:
    """Refuse what FAISS builds but crashes on later (a native assertion or a segfault, no
    exception): no inverted lists, an HNSW graph of M < 2, a transform to 0
    dimensions or an OPQ of 0 sub-spaces, a code of 0 bytes."""
    index = faiss.downcast_index(index)
    if isinstance(index, faiss.IndexPreTransform):
        for i in range(index.chain.size()):
            transform = faiss.downcast_VectorTransform(index.chain.at(i))
            if isinstance(transform, faiss.OPQMatrix) and transform.M < 1:
                raise InputError(f"--compare {factory}: an OPQ rotation for {transform.M} sub-spaces; it needs at "
                                 "least 1 (OPQ3,PQ3: as many as the product quantiser's)")
            if transform.d_out < 1:
                raise InputError(f"--compare {factory}: a transform to {transform.d_out} dimensions "
                                 f"({type(transform).__name__}); it needs at least 1")
    inner = _innermost(index)
    ivf = faiss.try_extract_index_ivf(inner)
    if ivf is not None and ivf.nlist < 1:
        raise InputError(f"--compare {factory}: an inverted file of {ivf.nlist} lists; it needs at least 1")
    if isinstance(inner, faiss.IndexHNSW):
        try:
            m = inner.hnsw.nb_neighbors(0) // 2  # the bottom layer holds 2M links a node
        except RuntimeError:  # M = 1: FAISS made no layer at all
            m = 1
        if m < 2:
            raise InputError(f"--compare {factory}: an HNSW graph of M = {m} links a node; it needs at least 2 "
                             "(HNSW32 is the usual)")
    elif index.sa_code_size() < 1:
        raise InputError(f"--compare {factory}: a code of 0 bytes a place; it needs at least one bit a place")


def code_family(factory: str) -> str:
    """The family of a FAISS factory string, by the component that holds the codes (the last;
    an ``IVF…_HNSW`` coarse quantiser does not make an IVF code a graph): ``graph`` (HNSW),
    ``additive`` (RQ, LSQ and their product forms), ``binary`` (LSH, ITQ + LSH, RaBitQ),
    ``PQ`` (PQ, with OPQ or PCA before it, flat or in IVF lists), ``exact`` (Flat), else ``other``."""
    parts = factory.split(",")
    code = parts[-1]
    if parts[0].startswith("HNSW"):
        return "graph"
    if any(code.startswith(name) for name in ADDITIVE) or code.startswith("RQ"):
        return "additive"
    if code.startswith(("LSH", "RaBitQ")) or code.startswith("ITQ"):
        return "binary"
    if code.startswith("PQ") or code.startswith("OPQ"):
        return "PQ"
    if code == "Flat":
        return "exact"
    return "other"

class FaissCodes:
    """One FAISS ``index_factory`` index over the references, with sequence matching on its codes.

    ``k`` is the number of references each query frame retrieves (its list), ``nprobe`` the
    inverted lists an IVF index visits per frame. ``windows``: whether sequences are scored
    over its codes; without, only FAISS's search reads them (a pooled sequence descriptor's
    code, :mod:`vprscale.compared.pooled`), and nothing but the FAISS index is kept.

    ``threads`` Python threads run FAISS's encoding and searches, each on blocks of
    ``BLOCK_ROWS`` rows with FAISS single-threaded. FAISS's own multi-threading would give
    other bytes on other thread counts (its BLAS products, OPQ rotations and IVF coarse
    distances, change in the last bit, which flips near-ties); blocks of a fixed size, each
    on one thread, give the same codes and lists whatever ``threads`` is.
    """

    def __init__(self, factory: str, dim: int, k: int, nprobe: int = DEFAULT_NPROBE, threads: int = 1,
                 windows: bool = True) -> None:
        _check_sizes(factory)
        try:
            index = faiss.index_factory(dim, factory)
            if not isinstance(_innermost(index), faiss.IndexHNSWFlat):  # a graph holds rows, not codes
                index.sa_code_size()
        except (RuntimeError, TypeError) as err:
            raise InputError(f"--compare {factory}: not a FAISS index_factory string with standalone codes for "
                             f"{dim}-d rows ({_faiss_reason(err)})") from None
        except MemoryError:
            raise InputError(f"--compare {factory}: FAISS cannot allocate this index here") from None
        _check_built(factory, index)
        if index.metric_type != faiss.METRIC_L2:
            raise InputError(f"--compare {factory}: the index does not search by L2 distance")
        inner = _innermost(index)
        if isinstance(inner, _FAST_SCAN) and _fast_scan(inner) is None:
            raise InputError(f"--compare {factory}: FAISS's fast-scan form of this code cannot be built from "
                             "standalone codes; the fast-scan forms compared are PQ…fs, RaBitQfs and the additive "
                             "quantisers' …x4fs (RQ, LSQ and their product forms), flat or IVF")
        if isinstance(inner, faiss.IndexHNSW) and not isinstance(inner, faiss.IndexHNSWFlat):
            raise InputError(f"--compare {factory}: an HNSW graph is compared over the rows themselves (HNSW32, "
                             "or a transform then HNSW32), not over codes")
        self.factory, self.dim, self.k, self.nprobe, self.threads = factory, dim, k, nprobe, threads
        self.windows = windows  # whether windows are scored over the codes (else FAISS's search alone reads them)
        self.bind(index)
        self.codes = np.zeros((0, self.code_bytes), np.uint8)
        self._filled = 0
        self.vectors = _NO_ROWS
        self.per_list = _NO_TABLES  # residual form: ‖ρ‖² + 2⟨c_l, ρ⟩ per list, sub-quantiser and code
        self.ref_base = np.zeros(0)  # residual form: per list, the smallest ‖ρ‖² + 2⟨c_l, ρ⟩ its codes can give
        self.ref_step, self.ref_err = 0.0, 0.0  # residual form: a place's term level's step and error
        self.centroids = _NO_ROWS  # residual form: the coarse centroids
        self.centroid_norm = 0.0  # residual form: their largest squared norm
        self._code_centres = np.zeros((0, 0))  # factors form: the centres its codes are relative to
        self._twin: Any = None  # a fast-scan code: the plain index taking its standalone codes
        self._values: tuple[np.ndarray, ...] | None = None  # enumerable codes: their distinct values' lists
        self._walked = 0.0  # a graph: distances per frame of its last search
        self._pending = _NO_ROWS  # rows given to encode that do not yet fill a block

    def bind(self, index: Any) -> None:
        """Work on ``index`` (a fresh one from the factory, or a trained one read from disk)."""
        self.index = self.searched = index
        self.chain = ([faiss.downcast_VectorTransform(index.chain.at(i)) for i in range(index.chain.size())]
                      if isinstance(index, faiss.IndexPreTransform) else [])
        self.inner = _innermost(index)
        self.ivf = faiss.try_extract_index_ivf(self.inner)
        self.graph = isinstance(self.inner, faiss.IndexHNSWFlat)
        self.set_point(self.k, self.nprobe)
        self.form = _form(self.inner)
        self._subs: subtables.ProductTables | subtables.AdditiveTables | None = None

    @property
    def subs(self) -> subtables.ProductTables | subtables.AdditiveTables:
        """The tables view of a trained index's codes (``tables`` and ``residual`` forms)."""
        if self._subs is None:
            self._subs = subtables.tables_of(self.inner)
        return self._subs

    def set_point(self, k: int, nprobe: int) -> None:
        """Search at operating point ``k`` and ``nprobe`` (the inverted lists an IVF frame
        visits): on the trained index and on its searched copy (a fast-scan code's)."""
        self.k, self.nprobe = k, nprobe
        for index in {id(i): i for i in (self.inner, self.searched_inner)}.values():
            ivf = faiss.try_extract_index_ivf(index)
            if ivf is not None:
                ivf.nprobe = nprobe
            if isinstance(index, faiss.IndexHNSW):
                index.hnsw.efSearch = self.ef_search

    @property
    def nibbles(self) -> bool:
        """Whether this is a 4-bit product quantiser (FAISS's fast-scan codes among them): the
        window scores read its packed bytes, each byte's two indices through one 256-entry
        table, the sum of their two 16-entry ones (two look-ups become one). 8-bit codes are
        their indices already; other widths are unpacked into one index per byte."""
        return self.form == "tables" and isinstance(self.inner, (faiss.IndexPQ, faiss.IndexPQFastScan)) \
            and self.inner.pq.nbits == 4

    @property
    def name(self) -> str:
        return f"faiss:{self.factory}"

    @property
    def params(self) -> str:
        if self.graph:
            return f"k={self.k} efSearch={self.ef_search}"
        return f"k={self.k}" + (f" nprobe={self.nprobe}" if self.ivf is not None else "")

    @property
    def ef_search(self) -> int:
        """Candidates a graph's search keeps at the bottom layer at this point's k."""
        return max(GRAPH_EF_SEARCH, self.k)

    @property
    def scans(self) -> bool:
        """Whether a frame's search visits every place: a flat code's (not an IVF's lists, not
        a graph's walk)."""
        return self.ivf is None and not self.graph

    @property
    def n_ref(self) -> int:
        return len(self.codes)

    @property
    def bytes_per_place(self) -> float:
        """What the method stores per place to answer a query.

        A flat index: its code (whose position is the id). An IVF index: its list entry
        (code and 64-bit id), and for sequences each place's code again in id order, where
        the window scores find it (with its list number); residual IVF-PQ codes also keep
        the level of each place's query-independent distance term there (one byte). A graph:
        its row (float32) and its share of the graph, as built (FAISS's neighbour lists of
        32-bit ids, each place's list offset and level).
        """
        if self.graph:
            hnsw = self.inner.hnsw
            links = hnsw.neighbors.size() * 4 + hnsw.offsets.size() * 8 + hnsw.levels.size() * 4
            return float(FLOAT_BYTES * self.inner.d + links / max(1, self.n_ref))
        if not self.windows:
            return self.entry_bytes
        if self.form == "factors":  # its record (signs, list number, factors), rounded up to whole float32s
            kept = rabitq.record_width(self.inner.d, self._list_bytes)
        else:
            kept = self.inner.sa_code_size() + (REF_LEVEL_BYTES if self.form == "residual" else 0)  # a term's level
        return float(kept if self.ivf is None else self.ivf.code_size + ID_BYTES + kept)

    @property
    def entry_bytes(self) -> float:
        """What FAISS's own index stores per place to answer a frame's search (not the windows'
        records): a flat code, an IVF list's code and 64-bit id, a graph's row and links."""
        if self.graph:
            return self.bytes_per_place
        return float(self.inner.sa_code_size() if self.ivf is None else self.ivf.code_size + ID_BYTES)

    def scan_per_frame(self) -> float:
        """Places (codes) a frame's search visits: all of them, the probed lists' share, or
        the distances a graph's walk computed per frame in the last search (FAISS counts them)."""
        if self.graph:
            return self._walked
        if self.ivf is None:
            return float(self.n_ref)
        return self.n_ref * min(1.0, self.nprobe / self.ivf.nlist) + self.ivf.nlist

    def frame_ops(self) -> float:
        """Unitary operations of a frame's search (transform, distance tables or coarse step, scan)."""
        transform = sum(2.0 * t.d_in * t.d_out for t in self.chain)
        width = self.codes.shape[1] if self.windows else self.code_bytes  # the bytes a scan reads of a place
        tables = 0.0  # decoded vectors (a graph's rows): none
        if self.form in ("tables", "residual"):
            tables = self.subs.table_ops(self.dim)  # a frame's tables
            tables += 256.0 * width if self.nibbles else 0.0  # and their byte sums
        elif self.form == "hamming":
            tables = 256.0 * width
        elif self.form == "factors":
            tables = 2.0 * 256 * self.inner.d  # a frame's sign tables
        coarse = 3.0 * self.dim * self.ivf.nlist if self.ivf is not None else 0.0
        # the window scores' coarse row, beside the search's, and its 8-bit levels (add, range, scale, round)
        coarse = 2 * coarse + 6.0 * self.ivf.nlist if self.form == "residual" else coarse
        scan = 3.0 * self.inner.d if self.graph else width  # a walk's distance, or a scanned code's bytes
        return transform + tables + coarse + scan * self.scan_per_frame()

    def pair_ops(self) -> float:
        """Operations of one (candidate, frame) term of a window score."""
        if self.form == "residual":
            return 2.0 * self.code_width + 3  # the look-ups, the list's level and the place's
        if self.form == "factors":  # the look-ups, the factors, and over an inverted file the coarse distance
            return self.code_width + 4.0 + (3.0 * self.inner.d if self.ivf is not None else 0.0)
        return float(self.codes.shape[1]) if self.form != "vectors" else 3.0 * self.vectors.shape[1]

    @property
    def code_width(self) -> int:
        """Bytes of a place's code that the window scores look up in a frame's tables (a
        residual place's record also holds its list number and its term's level)."""
        if self.form == "factors":
            return rabitq.sign_bytes(self.inner.d)
        return self.subs.columns if self.form == "residual" else self.codes.shape[1]

    @property
    def _list_bytes(self) -> int:
        """Bytes of a list number in a standalone code (none for a flat index)."""
        return self.ivf.coarse_code_size() if self.ivf is not None else 0

    @property
    def records_on_disk(self) -> bool:
        """Whether a stored encoding keeps this method's inverted lists on disk and its window
        records beside them (an IVF index whose windows read records in place; not a fast-scan
        one, whose lists FAISS lays out in blocks in memory, built from the stored codes)."""
        return self.ivf is not None and self.form in ("residual", "factors") and not isinstance(self.inner, _FAST_SCAN)

    def _transform(self, x: np.ndarray) -> np.ndarray:
        for t in self.chain:
            x = t.apply(x)
        return np.ascontiguousarray(x, np.float32)

    def train(self, sample: np.ndarray) -> None:
        """Train on ``sample`` with FAISS on the calling thread alone (its results change with its
        threads), at ``nprobe`` 1: FAISS's residual fast-scan additive quantisers estimate their
        norm scale from each row's one nearest list but read ``nprobe`` lists of it.

        A product quantiser is trained without FAISS's polysemous renumbering (as its ``np``
        forms): the renumbering only serves FAISS's Hamming pre-filter, which no search here
        uses, costs about 7.5 s a code whatever the sample, and leaves the centroids, so every
        neighbour and distance, as they were (docs/protocol.md)."""
        if getattr(self.inner, "do_polysemous_training", False):
            self.inner.do_polysemous_training = False
        nprobe = self.nprobe
        self.set_point(self.k, 1)
        try:
            with _said_once(self.factory):
                _one_thread(self.index.train, np.ascontiguousarray(sample, np.float32))
        finally:
            self.set_point(self.k, nprobe)

    def start(self, n_ref: int) -> None:
        """Make room for the codes of ``n_ref`` references (after :meth:`train`), then
        :meth:`encode` them block by block, in order, then :meth:`finish`."""
        if not self.windows:  # nothing kept beside FAISS's index but a graph's rows, which it links at finish
            width = self.code_bytes if self.graph else 0
        elif self.form == "residual":  # a record: the table indices, the list number, the term's level
            width = record_width(self.subs.columns, self.ivf.coarse_code_size())
            self._residual_tables()
        elif self.form == "factors":
            width = rabitq.record_width(self.inner.d, self._list_bytes)
            self._centres()
        else:
            width = self.subs.columns if self.form == "tables" and not self.nibbles else self.code_bytes
        self.codes = np.empty((n_ref, width), np.uint8)
        self._filled, self._pending = 0, _NO_ROWS
        self._values = None
        self._twin = _plain_twin(self.inner) if isinstance(self.inner, _FAST_SCAN) else None

    def _blocks(self, fn: Callable[[np.ndarray], Any], x: np.ndarray, rows: int = BLOCK_ROWS) -> list[Any]:
        """``fn`` of each block of ``rows`` rows of ``x``, on ``threads`` threads, in order."""
        x = np.ascontiguousarray(x, np.float32)
        return self._each(fn, [x[i : i + rows] for i in range(0, len(x), rows)] or [x])

    def _each(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        """``fn`` of each item, on ``threads`` threads (FAISS on one thread each), in order."""
        if self.threads == 1:  # on the calling thread, where its CPU time is measured
            return [_one_thread(fn, item) for item in items]
        with ThreadPoolExecutor(self.threads) as pool:
            return list(pool.map(partial(_one_thread, fn), items))

    def encode(self, x: np.ndarray) -> None:
        """Encode and add the next references, in whatever chunks they come: rows are held
        back until they fill a block of :meth:`encode_rows` (the rest at :meth:`finish`)."""
        rows = np.concatenate([self._pending, np.asarray(x, np.float32)]) if len(self._pending) else x
        whole = len(rows) - (self._filled + len(rows)) % ENCODE_ROWS
        self._pending = np.array(rows[whole:], np.float32)
        if whole:
            self.add_codes(self.encode_rows(rows[:whole], self._filled))

    @property
    def code_bytes(self) -> int:
        """Bytes of a place's standalone code (a graph's: its transformed row, float32)."""
        return FLOAT_BYTES * self.inner.d if self.graph else self.inner.sa_code_size()

    def encode_rows(self, x: np.ndarray, start: int, lists: np.ndarray | None = None) -> np.ndarray:
        """FAISS's standalone codes of the references ``x`` from id ``start`` on (a graph's:
        the transformed rows' bytes), in blocks of ``ENCODE_ROWS`` at fixed offsets, on one
        FAISS thread each: some encoders' results depend on the rows encoded together (LSQ
        searches each block's codes with a generator seeded per call), so the blocks must not
        depend on how the rows arrive: a caller gives whole blocks (every store's chunks are
        multiples of ``ENCODE_ROWS``), or rows through :meth:`encode`, which holds them back.
        ``lists``: the rows' inverted lists when already known (:meth:`assign_rows` of a method
        of the same :attr:`coarse_key`), so that the coarse search is not made again."""
        blocks = _encode_blocks(x, start)
        if self.graph:
            return np.concatenate(self._each(self._transform, blocks)).view(np.uint8)
        if lists is not None:
            return np.concatenate(self._each(self._encode_assigned, list(zip(blocks, np.split(lists, np.cumsum(
                [len(b) for b in blocks[:-1]])), strict=True))))
        return np.concatenate(self._each(lambda b: self.inner.sa_encode(self._transform(b)), blocks))

    @property
    def coarse_key(self) -> bytes | None:
        """What decides this IVF code's list assignments (its trained coarse centroids), for
        methods that take rows as they come (no transform before the IVF); else None. Methods
        of equal keys assign every row to the same list: :meth:`assign_rows` once serves them all."""
        if self.ivf is None or self.chain:
            return None
        centroids = self.ivf.quantizer.reconstruct_n(0, self.ivf.nlist)
        return hashlib.blake2b(np.ascontiguousarray(centroids, np.float32).tobytes(), digest_size=16).digest()

    def assign_rows(self, x: np.ndarray, start: int) -> np.ndarray:
        """Each row's inverted list, as FAISS's standalone encoding assigns it (its quantiser's
        ``assign``, in the blocks and on the one thread :meth:`encode_rows` uses)."""
        return np.concatenate(self._each(lambda b: self.ivf.quantizer.assign(b, 1).ravel(), _encode_blocks(x, start)))

    def _encode_assigned(self, item: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """FAISS's standalone codes of a block whose lists are known: ``sa_encode`` is the
        quantiser's ``assign`` then ``encode_vectors`` with the list numbers, so this is its second half."""
        rows, lists = item
        rows, lists = np.ascontiguousarray(rows, np.float32), np.ascontiguousarray(lists, np.int64)
        out = np.empty((len(rows), self.code_bytes), np.uint8)
        self.ivf.encode_vectors(len(rows), faiss.swig_ptr(rows), faiss.swig_ptr(lists), faiss.swig_ptr(out), True)
        return out

    def add_codes(self, codes: np.ndarray) -> None:
        """Add the next references by their standalone codes (:meth:`encode_rows`, or stored ones).

        A fast-scan index cannot take standalone codes, and a graph's links depend on how its
        rows arrive: both are built from them all at :meth:`finish`."""
        if isinstance(self.inner, _FAST_SCAN):
            _add_standalone(self._twin, codes, self._filled)
        elif not self.graph:
            self.inner.add_sa_codes(codes)
        lo, self._filled = self._filled, self._filled + len(codes)
        if not self.windows and not self.graph:
            return
        if self.form in ("residual", "factors"):
            codes = self.window_records(codes)
        elif self.form == "tables" and not self.nibbles:
            codes = self.subs.indices(codes[:, self._list_bytes :])
        self.codes[lo : self._filled] = codes

    def window_records(self, codes: np.ndarray) -> np.ndarray:
        """What the window scores read of residual IVF-PQ places, from their standalone codes
        (after :meth:`start`): their records (:func:`~vprscale.compared.codescore.place_records`),
        with the 8-bit level of each place's ``‖ρ‖² + 2⟨c_l, ρ⟩`` above its list's smallest
        (:func:`~vprscale.compared.codescore.ref_scale`); of RaBitQ places, their
        :func:`~vprscale.compared.rabitq.records`."""
        if self.form == "factors":
            return rabitq.records(codes, self.inner.d, self._list_bytes, self._code_centres)
        coarse = self.ivf.coarse_code_size()  # a standalone IVF code: the list number (little-endian), the PQ code
        lists = list_numbers(codes, coarse)
        sub = self.subs.indices(codes[:, coarse:])
        terms = np.asarray(sum(self.per_list[lists, m, sub[:, m]] for m in range(sub.shape[1])), np.float32)
        rise = (terms - self.ref_base[lists]) / (self.ref_step or 1.0)
        level = np.clip(np.floor(rise), 0, 255).astype(np.uint8)
        return place_records(sub, codes[:, :coarse], level)

    def attach(self, index: Any, records: np.ndarray) -> None:
        """Work on a populated IVF ``index`` (inverted lists on disk, say) and its places'
        window records (:meth:`window_records`; memory-mapped, say), or a linked graph and its
        rows' bytes (:meth:`encode_rows`), instead of adding codes."""
        self.bind(index)
        self.codes, self._filled = records, len(records)
        self._values = None
        if self.graph:
            self.vectors = self.codes.view(np.float32)
        elif self.form == "residual":
            self._residual_tables()
        elif self.form == "factors":
            self._centres()

    def finish(self, progress: Callable[[int], None] | None = None) -> None:
        """Encode the rows held back, then what needs every code: a fast-scan code's searched
        copy, a graph's links and decoded vectors. ``progress`` is called with each block of
        ``ENCODE_ROWS`` rows a graph links (the long part: a graph of 10M rows links on one
        core for about half an hour; :attr:`finish_blocks` of them)."""
        if len(self._pending):
            rows, self._pending = self._pending, _NO_ROWS
            self.add_codes(self.encode_rows(rows, self._filled))
        if self._filled != len(self.codes):
            raise ValueError(f"{self._filled:,} of {len(self.codes):,} references encoded")
        if isinstance(self.inner, _FAST_SCAN):
            self._fast_scan_copy()
        if self.graph:
            self._link(progress)
        self.index.ntotal = self.inner.ntotal
        if self.graph:  # the rows themselves, as the graph holds them
            self.vectors = self.codes.view(np.float32)
        elif self.form == "vectors" and self.windows:  # decoded once, block by block, as the inner index searches
            self.vectors = np.empty((len(self.codes), self.inner.d), np.float32)
            for i in range(0, len(self.codes), DECODE_ROWS):
                self.vectors[i : i + DECODE_ROWS] = self.inner.sa_decode(self.codes[i : i + DECODE_ROWS])

    @property
    def finish_blocks(self) -> int:
        """The blocks :meth:`finish` reports (a graph's: those it links; none otherwise)."""
        return -(-len(self.codes) // ENCODE_ROWS) if self.graph else 0

    def _link(self, progress: Callable[[int], None] | None) -> None:
        """Build the graph from every row, on one FAISS thread, in blocks of ``ENCODE_ROWS``
        at fixed offsets: FAISS inserts a block's rows level by level, and its threads race
        for the links, so the same blocks on one thread give the same graph however the rows
        arrived."""
        rows = self.codes.view(np.float32)
        for lo in range(0, len(rows), ENCODE_ROWS):
            _one_thread(self.inner.add, np.ascontiguousarray(rows[lo : lo + ENCODE_ROWS]))
            if progress is not None:
                progress(1)

    def _fast_scan_copy(self) -> None:
        """The searched index of a fast-scan code, built by FAISS's own constructor from the
        plain twin that took its standalone codes (:meth:`add_codes`); the transforms of the
        chain, if any, go before it. The trained index stays as it was: it encodes and
        transforms."""
        how = _fast_scan(self.inner)
        fast = how.copy(self._twin, self.inner.bbs)
        for field in how.kept:
            setattr(fast, field, getattr(self.inner, field))
        self._twin = None  # the fast-scan copy holds the codes now
        if not self.chain:
            self.searched = fast
        else:
            self.searched = faiss.IndexPreTransform(fast)  # keeps a reference to ``fast``
            for t in reversed(self.chain):  # owned by ``self.index``, which lives as long
                self.searched.prepend_transform(t)
        self.set_point(self.k, self.nprobe)

    @property
    def searched_inner(self) -> Any:
        """The index the searches end in, after the transforms (for a fast-scan code, its copy holding the codes)."""
        return faiss.downcast_index(self.searched.index) if self.chain else self.searched

    def _centres(self) -> None:
        """What RaBitQ codes are relative to (float64, for their records): a flat index's
        centre, or the coarse centroids of an inverted file (which the windows also read)."""
        if self.ivf is None:
            self._code_centres = faiss.vector_to_array(self.inner.center).astype(np.float64)[None, :]
            return
        self.centroids = np.ascontiguousarray(self.ivf.quantizer.reconstruct_n(0, self.ivf.nlist), np.float32)
        self._code_centres = self.centroids.astype(np.float64)

    def _residual_tables(self) -> None:
        """The coarse centroids, their largest squared norm and, per list ``l``, sub-quantiser ``m`` and code ``v``,
        ``‖ρ_mv‖² + 2⟨c_l[m], ρ_mv⟩`` (the query-independent part of a residual distance), and the scale of
        its levels (:func:`~vprscale.compared.codescore.ref_scale`)."""
        self.centroids = np.ascontiguousarray(self.ivf.quantizer.reconstruct_n(0, self.ivf.nlist), np.float32)
        self.centroid_norm = float((self.centroids.astype(np.float64) ** 2).sum(axis=1).max())  # for coarse_levels
        self.per_list = self.subs.list_terms(self.centroids)
        self.ref_base, self.ref_step, self.ref_err = ref_scale(self.per_list)

    def search(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FAISS's top-k of each query row: ``(distances, ids)`` (ids −1 where fewer were found)."""
        if self.graph:
            faiss.cvar.hnsw_stats.reset()
        found = self._blocks(self._search_block if self._norm_left_out else lambda b: self.searched.search(b, self.k),
                             rows)
        if self.graph:
            self._walked = faiss.cvar.hnsw_stats.ndis / max(1, len(rows))
        return np.concatenate([d for d, _ in found]), np.concatenate([i for _, i in found])

    def _search_block(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FAISS's search of a block of rows, transformed once, with the ``‖y‖²`` its distances
        leave out added back (:attr:`_norm_left_out`)."""
        y = self._transform(rows)
        dist, ids = self.searched_inner.search(y, self.k)
        return np.where(ids >= 0, dist + (y.astype(np.float64) ** 2).sum(axis=1)[:, None], dist).astype(np.float32), ids

    @property
    def _norm_left_out(self) -> bool:
        """Whether FAISS's search leaves the frame's ``‖y‖²`` out of its distances: its fast-scan
        additive quantisers rank by ``‖x̂‖² − 2⟨y, x̂⟩``, the same places in the same order, and
        :meth:`search` adds it back (a score is a squared distance, comparable across frames)."""
        return isinstance(self.inner, _AQ_FAST_SCAN) and self.inner.metric_type == faiss.METRIC_L2

    @property
    def enumerable(self) -> bool:
        """Whether a frame's exact top-k can be found by visiting code values in order of
        distance rather than every place (:mod:`vprscale.compared.codesearch`): flat product
        quantisers searched with float tables (not fast-scan ones, whose 8-bit look-up
        tables rank places approximately) and binary codes, of at most 62 bits."""
        if self.form == "tables" and isinstance(self.inner, faiss.IndexPQ):
            return self.inner.pq.M * self.inner.pq.nbits <= codesearch.MAX_KEY_BITS
        return self.form == "hamming" and self.inner.nbits <= codesearch.MAX_KEY_BITS

    def _value_lists(self) -> tuple[np.ndarray, ...]:
        """The distinct code values and their places (:func:`~vprscale.compared.codesearch.code_lists`), built once."""
        if self._values is None:
            self._values = codesearch.code_lists(self._keys(self.codes))
        return self._values

    def _keys(self, codes: np.ndarray) -> np.ndarray:
        """Codes as they are held (:meth:`add_codes`), one int64 key each
        (:func:`~vprscale.compared.codesearch.code_keys`)."""
        unpacked = self.form == "tables" and self.inner.pq.nbits not in (4, 8)  # one index per byte
        return codesearch.code_keys(codes, self.inner.pq.nbits if unpacked else None)

    def exact_search(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`search` finds, without scanning every place (:attr:`enumerable` codes):
        ``(distances, ids)`` of each row's k nearest places by (distance, id), in blocks of
        ``BLOCK_ROWS`` on ``threads`` threads (the same bytes for any threads)."""
        values, starts, ids = self._value_lists()
        limit = codesearch.budget(len(values))

        def block(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            y = self._transform(b)
            if self.form == "hamming":
                keys = codesearch.code_keys(self.inner.sa_encode(y))
                return codesearch.hamming_topk(keys, self.inner.nbits, values, starts, ids, self.k, limit)
            return codesearch.pq_topk(self._exact_tables(y), self.inner.pq.nbits, values, starts, ids, self.k, limit)

        found = self._blocks(block, rows)
        return (np.concatenate([d for d, _ in found]).astype(np.float32),
                np.concatenate([i for _, i in found]))

    def _exact_tables(self, y: np.ndarray) -> np.ndarray:
        """Float64 tables of squared distances from each frame's sub-vectors to each centroid (frames, M, ksub)."""
        ys, cents = self.subs.split(y).astype(np.float64), self.subs.cents.astype(np.float64)
        return (ys**2).sum(-1)[:, :, None] - 2 * np.einsum("nmd,mkd->nmk", ys, cents) + (cents**2).sum(-1)[None]

    def check_exact(self, rows: np.ndarray) -> None:
        """Raise if :meth:`exact_search` and FAISS's :meth:`search` disagree on ``rows`` beyond
        places tied to float32 rounding (FAISS sums float32 tables; binary codes must agree
        exactly): the evaluation's answers then come from the first, its times from the second."""
        theirs, ours = self.search(rows), self.exact_search(rows)
        y = np.concatenate(self._blocks(self._transform, rows))  # as exact_search transforms: the same bits
        keys = self._keys(self.codes[np.maximum(ours[1], 0).ravel()]).reshape(ours[1].shape)
        if self.form == "hamming":
            scale, rounding = np.zeros(len(rows)), 0.0
            true = codesearch.hamming_distances(codesearch.code_keys(self.inner.sa_encode(y)), keys)
        else:
            tables = self._exact_tables(y)
            scale, rounding = tables.max(axis=2).sum(axis=1), EXACT_ROUNDING
            true = codesearch.pq_distances(tables, self.inner.pq.nbits, keys)
        # each place found at its own code's distance, and the lists FAISS's up to rounding
        fine = ((ours[1] < 0) | (np.abs(true - ours[0]) <= rounding * scale[:, None])).all(axis=1)
        fine &= codesearch.agree(*theirs, *ours, scale, rounding)
        if not fine.all():
            p = int(np.flatnonzero(~fine)[0])
            raise RuntimeError(f"{self.name}: the exact top-k of query row {p} ({ours[1][p].tolist()}) is not FAISS's "
                               f"({theirs[1][p].tolist()}); {int((~fine).sum())} of {len(rows)} rows differ")

    def frame_terms(self, rows: np.ndarray) -> FrameTerms:
        """What the window scores need of each query frame (:class:`FrameTerms`)."""
        if self.form == "residual":
            return self._residual_frames(np.ascontiguousarray(rows, np.float32))
        y = self._transform(np.asarray(rows, np.float32))
        if self.form == "hamming":
            q = self.inner.sa_encode(y)
            return FrameTerms(_POPCOUNT[q[:, :, None] ^ np.arange(256, dtype=np.uint8)[None, None, :]], _NO_ROWS)
        if self.form == "factors":  # one centre (a flat index's, an IVF's single list): its distances in scale[:, 0]
            one = self._list_bytes == 0
            centre_dist = ((y.astype(np.float64) - self._code_centres[0]) ** 2).sum(axis=1) if one else 0.0
            scale = np.zeros((len(y), 4))
            scale[:, 0] = centre_dist
            return FrameTerms(rabitq.sign_tables(y), y, scale=scale)
        if self.form == "tables":
            tables = self.subs.frame_tables(y)
            return FrameTerms(_byte_tables(tables) if self.nibbles else tables, _NO_ROWS)
        return FrameTerms(_NO_TABLES, y)

    def _residual_frames(self, rows: np.ndarray) -> FrameTerms:
        """:class:`FrameTerms` of residual IVF-PQ codes, block by block (FAISS's BLAS on one
        thread each: the same bits for any threads), each block written into place (7.5 KB a
        frame at 4,096 lists: a million frames' blocks and their concatenation took 15 GB)."""
        n = len(rows)
        terms = FrameTerms(np.empty((n, self.subs.columns, self.subs.ksub), np.float32),
                           np.empty((n, self.inner.d), np.float32), np.empty((n, self.ivf.nlist), np.uint8),
                           np.empty((n, 4)))

        def fill(lo: int) -> None:
            for whole, part in zip(terms, self._residual_terms(rows[lo : lo + BLOCK_ROWS]), strict=True):
                whole[lo : lo + len(part)] = part

        self._each(fill, list(range(0, len(rows), BLOCK_ROWS)))
        return terms

    def _residual_terms(self, rows: np.ndarray) -> tuple[np.ndarray, ...]:
        """A block's ``−2⟨y[m], ρ_mv⟩`` tables, its frames, and the levels of their distances to
        every list (:func:`~vprscale.compared.codescore.coarse_levels`; the distances themselves
        are not kept: 16 KB a frame)."""
        y = self._transform(rows)
        tables = self.subs.residual_tables(y)
        levels, scale = coarse_levels(faiss.pairwise_distances(y, self.centroids), self.ref_base, y,
                                      self.centroid_norm, self.ref_step, self.ref_err)
        return tables, y, levels, scale

    def match(self, positions: np.ndarray, L: int, aligned: bool, lists: tuple, terms: FrameTerms,
              n_best: int = 1, valid: np.ndarray = NO_MASK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sequence match of the windows centred at query-frame ``positions``: ``(top, scores,
        n_r)``, the ``n_best`` best candidates best first (:func:`score_windows`).

        ``lists`` are the frames' top-k lists (:func:`vprscale.method.kernels.ranked_lists`);
        candidates come from :func:`vprscale.method.kernels.window_proposals`, never a centre
        whose window ``valid`` rules out (a byte a place; empty: all).
        """
        positions = np.asarray(positions, np.int64)
        cand, first, n_r = window_proposals(positions, L, aligned, lists, self.n_ref, valid)
        top, scores = self.score(positions, L, cand, first, n_r, terms, n_best)
        return top, scores, n_r

    def score(self, positions: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray, n_r: np.ndarray,
              terms: FrameTerms, n_best: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """:func:`score_windows` of given candidates over this method's codes, in its form."""
        codes = self.codes if self.form != "vectors" else np.zeros((0, 1), np.uint8)
        vectors = self.codes.view(np.float32) if self.form == "factors" else self.vectors
        return score_windows(np.ascontiguousarray(positions, np.int64), L, cand, first, n_r, self.n_ref,
                             terms.tables, terms.levels, terms.scale, self.per_list, _read_only(codes), terms.vectors,
                             _read_only(vectors), self.centroids, n_best)
