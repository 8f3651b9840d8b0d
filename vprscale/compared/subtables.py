"""Codes whose distances are sums of per-index table look-ups: product quantisers and additive
quantisers that keep their reconstruction's norm in the code.

A code of this kind is a few indices (one per sub-quantiser, codebook or norm level, at most 8
bits each: held one per byte) and a query frame's distance to it is ``Σ_m tables[m, index_m]``,
the window scores' *tables* form (:mod:`vprscale.compared.codescore`); over the residuals of an
inverted file it is the *residual tables* form: the frame's coarse distance to the place's list
plus the list's query-independent term (``per_list``) plus the frame's residual tables.

- A product quantiser's sub-quantisers cover disjoint sub-spaces: a table entry is the squared
  distance from the frame's sub-vector to a centroid, and a residual ``ρ`` splits as
  ``‖ρ‖² + 2⟨c_l, ρ⟩`` over them.
- An additive quantiser (residual RQ, local-search LSQ, their product forms) sums codewords
  over the whole space, so ``‖x̂‖²`` has cross terms between codebooks that no per-codebook
  table holds. FAISS's own table search needs that norm and stores it in the code
  (``…_Nqint8`` and the other quantised norms): ``‖y − x̂‖² = ‖y‖² − 2 Σ_m ⟨y, C_m[i_m]⟩ +
  norm(i_norm)``, one table per codebook and one for the norm's levels, the distance FAISS
  searches with. Over residuals the norm is ``‖ρ̂‖²`` and ``2⟨c_l, ρ̂⟩`` splits per codebook.
  Codes without a norm (``RQ3x8``: FAISS decodes them to search) or with a float32 one have no
  such tables. The fast-scan forms (``RQ4x4fs_Nrq2x4``: 4-bit codebooks, the norm in two 4-bit
  levels) keep the same kind of code; over an inverted file by residual (``…fsr``) their norm is
  the whole vector's, ``‖c_l + ρ̂‖²``: the distance is the frame's coarse distance, ``−‖c_l‖²``
  plus the norm as the list's term, and the frame's ``−2⟨y, C_m[i_m]⟩``.
"""

from __future__ import annotations

from typing import Any

import faiss
import numpy as np

# FAISS's search types that keep a norm of at most 8 bits in the code, each level's value a
# table entry: evenly spaced levels (qint) or a trained 1-d codebook (cqint, and the 2x4 forms).
_EVEN_LEVELS = {faiss.AdditiveQuantizer.ST_norm_qint8: 8, faiss.AdditiveQuantizer.ST_norm_qint4: 4}
_CODEBOOK_LEVELS = {faiss.AdditiveQuantizer.ST_norm_cqint8, faiss.AdditiveQuantizer.ST_norm_cqint4,
                    faiss.AdditiveQuantizer.ST_norm_lsq2x4, faiss.AdditiveQuantizer.ST_norm_rq2x4}
MAX_INDEX_BITS = 8  # one index per byte


def unpack_fields(codes: np.ndarray, widths: list[int]) -> np.ndarray:
    """Bit fields of ``widths`` bits packed least significant bit first (as FAISS's
    ``BitstringWriter`` packs them) as one byte each: (rows, fields)."""
    if all(w == 8 for w in widths):
        return np.ascontiguousarray(codes[:, : len(widths)])
    bits = np.unpackbits(codes, axis=1, bitorder="little")
    out = np.empty((len(codes), len(widths)), np.uint8)
    pos = 0
    for f, w in enumerate(widths):
        out[:, f] = (bits[:, pos : pos + w].astype(np.uint16) << np.arange(w, dtype=np.uint16)).sum(axis=1)
        pos += w
    return out


class ProductTables:
    """A product quantiser (FAISS's ``ProductQuantizer``) as tables: ``M`` sub-quantisers of ``ksub`` centroids."""

    def __init__(self, pq: Any) -> None:
        self.pq = pq
        self.columns, self.ksub = pq.M, pq.ksub
        self.cents = faiss.vector_to_array(pq.centroids).reshape(pq.M, pq.ksub, pq.dsub)

    def indices(self, codes: np.ndarray) -> np.ndarray:
        """Packed codes as one centroid index per sub-quantiser."""
        return unpack_fields(codes, [self.pq.nbits] * self.pq.M)

    def split(self, y: np.ndarray) -> np.ndarray:
        """The frames split by sub-quantiser: (frames, M, dsub)."""
        return y.reshape(len(y), self.pq.M, self.pq.dsub)

    def frame_tables(self, y: np.ndarray) -> np.ndarray:
        """Squared distances from each frame's sub-vectors to each centroid: (frames, M, ksub), float32."""
        ys = self.split(y)
        tables = ((ys**2).sum(-1)[:, :, None] - 2 * np.einsum("nmd,mkd->nmk", ys, self.cents)
                  + (self.cents**2).sum(-1)[None])
        return np.maximum(tables, 0).astype(np.float32)

    def residual_tables(self, y: np.ndarray) -> np.ndarray:
        """``−2⟨y[m], ρ_mv⟩``: a frame's part of its distance to a residual code."""
        return (-2 * np.einsum("nmd,mkd->nmk", self.split(y), self.cents)).astype(np.float32)

    def list_terms(self, centroids: np.ndarray) -> np.ndarray:
        """Per list ``l``, sub-quantiser ``m`` and code ``v``: ``‖ρ_mv‖² + 2⟨c_l[m], ρ_mv⟩``."""
        sub = centroids.reshape(len(centroids), self.pq.M, self.pq.dsub)
        return ((self.cents**2).sum(-1)[None, :, :]
                + 2 * np.einsum("lmd,mkd->lmk", sub, self.cents)).astype(np.float32)

    def table_ops(self, dim: int) -> float:
        """Operations of one frame's tables."""
        return 3.0 * self.ksub * dim


class AdditiveTables:
    """An additive quantiser (FAISS's ``AdditiveQuantizer``) with its norm in the code, as tables:
    one column per codebook, then the norm's. Columns hold ``ksub`` entries (the widest
    field's); a narrower field's unused entries repeat its first, so a column's smallest and
    largest entries are its codes' own."""

    def __init__(self, aq: Any, dim: int, whole_norm: bool = False) -> None:
        self.aq, self.dim, self.whole_norm = aq, dim, whole_norm  # whole_norm: residual codes, the vector's norm
        self.widths = [int(b) for b in faiss.vector_to_array(aq.nbits)] + [int(aq.norm_bits)]
        self.columns, self.ksub = len(self.widths), 1 << max(self.widths)
        self.books = self._codewords()
        self.norms = _pad(self._norm_levels(), self.ksub)

    @staticmethod
    def supports(aq: Any) -> bool:
        """Whether the code keeps a norm of at most 8 bits and indices of at most 8."""
        return ((aq.search_type in _EVEN_LEVELS or aq.search_type in _CODEBOOK_LEVELS)
                and int(faiss.vector_to_array(aq.nbits).max()) <= MAX_INDEX_BITS)

    def _decode(self, indices: np.ndarray) -> np.ndarray:
        """FAISS's reconstruction of unpacked indices (rows, M)."""
        indices = np.ascontiguousarray(indices, np.int32)
        out = np.empty((len(indices), self.dim), np.float32)
        self.aq.decode_unpacked(faiss.swig_ptr(indices), faiss.swig_ptr(out), len(indices))
        return out

    def _codewords(self) -> np.ndarray:
        """Each codebook's codewords in the whole space (M, ksub, d), from FAISS's own
        reconstructions (product forms keep theirs per sub-space): codebook ``m``'s ``k``-th is
        the reconstruction of index ``k`` at ``m`` and 0 elsewhere, less that of all zeros for
        ``m > 0``, so that any code's codewords sum to its reconstruction."""
        m_count = self.aq.M
        zero = self._decode(np.zeros((1, m_count)))
        books = np.empty((m_count, self.ksub, self.dim), np.float32)
        for m in range(m_count):
            one = np.zeros((1 << self.widths[m], m_count))
            one[:, m] = np.arange(1 << self.widths[m])
            books[m] = _pad(self._decode(one) - (zero if m else 0), self.ksub)
        return books

    def _norm_levels(self) -> np.ndarray:
        """The norm each of its code's values stands for (FAISS's ``decode_qint8`` and kin)."""
        st = self.aq.search_type
        if st in _EVEN_LEVELS:
            n = 1 << _EVEN_LEVELS[st]
            return (np.arange(n) + 0.5) / n * (self.aq.norm_max - self.aq.norm_min) + self.aq.norm_min
        qnorm = self.aq.qnorm
        return faiss.rev_swig_ptr(qnorm.get_xb(), qnorm.ntotal).astype(np.float64)

    def indices(self, codes: np.ndarray) -> np.ndarray:
        """Packed codes as their codebook indices and norm level."""
        return unpack_fields(codes, self.widths)

    def _inner(self, y: np.ndarray) -> np.ndarray:
        """``−2⟨y, C_m[k]⟩`` of each frame, with a column for the norm left at 0."""
        tables = np.zeros((len(y), self.columns, self.ksub), np.float32)
        tables[:, :-1] = -2 * np.einsum("nd,mkd->nmk", y, self.books)
        return tables

    def frame_tables(self, y: np.ndarray) -> np.ndarray:
        """A frame's distance to a code: its codebooks' look-ups and the norm column holding
        ``‖y‖²`` plus each level's norm."""
        tables = self._inner(y)
        tables[:, -1] = ((y.astype(np.float64) ** 2).sum(axis=1)[:, None] + self.norms[None, :]).astype(np.float32)
        return tables

    def residual_tables(self, y: np.ndarray) -> np.ndarray:
        """``−2⟨y, C_m[k]⟩``: a frame's part of its distance to a residual code (the norm is the list's term)."""
        return self._inner(y)

    def list_terms(self, centroids: np.ndarray) -> np.ndarray:
        """Per list ``l``: ``2⟨c_l, C_m[k]⟩`` per codebook, and the norm column ``‖ρ̂‖²``'s levels;
        when the code keeps the whole vector's norm, ``‖c_l + ρ̂‖² − ‖c_l‖²`` in the norm column
        alone (the same sum, the cross terms inside the stored norm)."""
        terms = np.empty((len(centroids), self.columns, self.ksub), np.float32)
        if self.whole_norm:
            terms[:, :-1] = 0
            own = (centroids.astype(np.float64) ** 2).sum(axis=1)
            terms[:, -1] = self.norms[None, :] - own[:, None]
            return terms
        terms[:, :-1] = 2 * np.einsum("ld,mkd->lmk", centroids, self.books)
        terms[:, -1] = self.norms[None, :]
        return terms

    def table_ops(self, dim: int) -> float:
        """Operations of one frame's tables (an inner product per codeword)."""
        return 2.0 * (self.columns - 1) * self.ksub * dim


def _pad(rows: np.ndarray, n: int) -> np.ndarray:
    """``rows`` extended to ``n`` by repeating the first."""
    return np.concatenate([rows, np.repeat(rows[:1], n - len(rows), axis=0)]) if len(rows) < n else rows


_PRODUCT = (faiss.IndexPQ, faiss.IndexPQFastScan, faiss.IndexIVFPQ, faiss.IndexIVFPQFastScan)
_ADDITIVE = (faiss.IndexAdditiveQuantizer, faiss.IndexIVFAdditiveQuantizer, faiss.IndexAdditiveQuantizerFastScan,
             faiss.IndexIVFAdditiveQuantizerFastScan)


def has_tables(inner: Any) -> bool:
    """Whether a FAISS index's codes (flat or IVF; trained or not) have a tables view."""
    if isinstance(inner, _PRODUCT):
        return inner.pq.nbits <= MAX_INDEX_BITS
    return isinstance(inner, _ADDITIVE) and AdditiveTables.supports(inner.aq)


def tables_of(inner: Any) -> ProductTables | AdditiveTables:
    """The tables view of a trained FAISS index's codes (:func:`has_tables`)."""
    if isinstance(inner, _PRODUCT):
        return ProductTables(inner.pq)
    whole_norm = isinstance(inner, faiss.IndexIVFAdditiveQuantizerFastScan) and inner.by_residual
    return AdditiveTables(inner.aq, inner.aq.d, whole_norm)
