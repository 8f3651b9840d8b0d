"""The CoarseHash method (docs/method.md): PCA, per-component scalar quantisation, hashing.

``CoarseHasher`` is an estimator: parameters in ``__init__``, ``fit`` on the reference rows,
fitted attributes ending in ``_``. Every method takes a numpy array or a Dask array; a numpy
input is run through the same chunked path, so both give identical bits.
"""

from __future__ import annotations

import math

import dask
import dask.array as da
import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted

from vprscale.core.errors import InputError
from vprscale.core.progress import compute
from vprscale.method.hashkernels import column_histogram, hash_rows, project_rows
from vprscale.method.kmeans1d import kmeans_1d
from vprscale.method.pca import ExactPCA, moments_of
from vprscale.method.validation import check_rows

_CHUNK = 65536
SPAN = 8.0  # the streamed histograms cover ±SPAN standard deviations of each component
SAMPLE_SPAN = 1 << 17  # rows of one span of the k-means sample: whole absolute blocks, a build chunk
SAMPLE_SPANS = 128  # spans (16.8M rows) the 1-D k-means sees at least; every reference below twice that


def _as_dask(x: np.ndarray | da.Array) -> da.Array:
    if isinstance(x, da.Array):
        return x
    x = np.asarray(x)
    return da.from_array(x, chunks=(_CHUNK, x.shape[1]))


def project(x: np.ndarray, mean: np.ndarray, components: np.ndarray) -> np.ndarray:
    """Centred projection of rows in float64 (each row's bits depend on that row alone)."""
    return project_rows(np.asarray(x), mean, np.ascontiguousarray(components.T))


def hash_descriptors(x: np.ndarray, mean: np.ndarray, components: np.ndarray, centres: np.ndarray,
                     first: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(codes, addresses, quantisation errors, level counts)`` of descriptor rows, fused;
    ``first`` (float32, a value per row), when given, receives each row's first component."""
    return hash_rows(np.asarray(x), mean, np.ascontiguousarray(components.T), centres, centres.shape[1],
                     np.empty(0, np.float32) if first is None else first)


def sample_spans(n_ref: int) -> list[tuple[int, int]]:
    """The reference rows the 1-D k-means is fitted on, as absolute ``[a, b)`` spans.

    Fewer than ``2 × SAMPLE_SPANS`` spans of ``SAMPLE_SPAN`` rows (33.4M): all of them. Beyond,
    every s-th span with ``s = ⌊spans / SAMPLE_SPANS⌋``: at least ``SAMPLE_SPANS`` evenly
    spread spans, 16.8M rows (100M: 20M; 1B: 17M), whose centres differ from the whole set's
    by a few thousandths of a standard deviation (docs/dataset.md gives the measured effect),
    and a build at 1B draws its references twice instead of three times. A function of ``n_ref`` alone:
    the compact build and the index of a full store fit the same centres on the same rows.
    """
    step = -(-n_ref // SAMPLE_SPAN) // SAMPLE_SPANS
    if step <= 1:
        return [(0, n_ref)]
    return [(a, min(n_ref, a + SAMPLE_SPAN)) for a in range(0, n_ref, step * SAMPLE_SPAN)]


def pack(codes: np.ndarray, k: int) -> np.ndarray:
    """``h = Σ_j K^(d−j) q_j``: the first (highest-variance) component is the top digit."""
    h = np.zeros(len(codes), dtype=np.uint64)
    base = np.uint64(k)
    for j in range(codes.shape[1]):
        h = h * base + codes[:, j].astype(np.uint64)
    return h


def unpack(h: np.ndarray, d: int, k: int) -> np.ndarray:
    """Inverse of :func:`pack`: the codes of addresses ``h``."""
    h = np.asarray(h, dtype=np.uint64).copy()
    codes = np.empty((len(h), d), dtype=np.uint8)
    base = np.uint64(k)
    for j in range(d - 1, -1, -1):
        codes[:, j] = (h % base).astype(np.uint8)
        h //= base
    return codes


class CoarseHasher(TransformerMixin, BaseEstimator):
    """Coarse scalar-quantisation hashing of descriptors.

    Parameters
    ----------
    d : PCA components kept (hash digits); default ``⌈log2 N_ref⌉``.
    k : quantisation levels per component (K), at least 2.
    bins : histogram bins per component for the streamed 1-D k-means, over ±8 standard
        deviations of the component. The centres are the exact k-means optimum of the values
        moved to their bin midpoints (each moves by at most ``8σ / bins``), with the values
        beyond ±8σ kept exactly.

    Fitted attributes: ``d_``, ``mean_``, ``components_`` (d × D), ``explained_variance_``,
    ``centres_`` (d × K, ascending), ``ranges_`` (d × 2), ``n_ref_``, ``n_features_in_``.

    A scikit-learn transformer: ``transform`` gives the PCA projections (float64),
    ``quantize`` the per-component codes and ``hash`` the addresses; every method checks
    that its rows have the width the hasher was fitted on.
    """

    def __init__(self, d: int | None = None, k: int = 2, bins: int = 1 << 14) -> None:
        self.d, self.k, self.bins = d, k, bins

    def _check(self, n: int, dim: int) -> int:
        """The width d to fit; bad parameters are errors naming them."""
        if isinstance(self.k, bool) or not isinstance(self.k, int | np.integer) or self.k < 2:
            raise InputError(f"k = {self.k!r}: K must be an integer of at least 2")
        if self.k > 255:
            raise InputError(f"k = {self.k}: K must be at most 255 (codes are uint8)")
        d = self.d if self.d is not None else min(dim, max(1, math.ceil(math.log2(max(n, 2)))))
        if isinstance(d, bool) or not isinstance(d, int | np.integer) or not 1 <= d <= dim:
            raise InputError(f"d = {d!r}: must be an integer between 1 and the descriptor width {dim}")
        if self.k**d > 2**64:
            raise InputError(f"d = {d}, k = {self.k}: K^d = {self.k}^{d} addresses exceed 2^64")
        return int(d)

    @classmethod
    def from_fitted(cls, k: int, bins: int, n_ref: int, mean: np.ndarray, components: np.ndarray,
                    centres: np.ndarray, explained_variance: np.ndarray,
                    ranges: np.ndarray | None = None) -> CoarseHasher:
        """A fitted hasher from the arrays it learned (as an index or a compact store keeps them)."""
        hasher = cls(d=int(components.shape[0]), k=k, bins=bins)
        hasher.d_, hasher.n_features_in_, hasher.n_ref_ = int(components.shape[0]), int(components.shape[1]), n_ref
        hasher.mean_, hasher.components_, hasher.centres_ = mean, components, centres
        hasher.explained_variance_ = explained_variance
        if ranges is not None:
            hasher.ranges_ = ranges
        return hasher

    def fit(self, X: np.ndarray | da.Array, y: None = None, moments: np.ndarray | None = None) -> CoarseHasher:
        """Exact PCA, then per-component 1-D k-means; two streamed passes over the reference rows ``X``
        (the second over :func:`sample_spans` of them: every row up to 33.4M).

        ``moments`` (``[[XᵀX, Σx], [Σxᵀ, n]]`` of ``X``, e.g. the ones a build derives
        while it writes the rows) spare the PCA its pass.
        """
        x = _as_dask(check_rows(self, X, reset=True))
        self.fit_pca(moments if moments is not None else moments_of(x))
        parts = [dask.delayed(self.column_histogram)(blk) for a, b in sample_spans(len(x))
                 for blk in x[a:b].to_delayed().ravel()]
        self.fit_centres(compute(*parts, desc="histograms"))
        return self

    def fit_pca(self, moments: np.ndarray) -> CoarseHasher:
        """The PCA step of :meth:`fit`, from the summed moments of the reference rows."""
        dim = moments.shape[0] - 1
        n = int(moments[dim, dim])
        self.d_ = self._check(n, dim)
        self.n_features_in_ = dim
        pca = ExactPCA(self.d_).fit_moments(moments)
        self.mean_, self.components_ = pca.mean_, pca.components_
        self.explained_variance_ = pca.explained_variance_
        self.n_ref_ = n
        return self

    def _histogram_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, width)``: histograms over ±SPAN standard deviations (known exactly from the PCA)."""
        sigma = np.sqrt(np.maximum(self.explained_variance_, np.finfo(np.float64).tiny))
        return -SPAN * sigma, 2 * SPAN * sigma / self.bins

    def column_histogram(self, rows: np.ndarray) -> tuple:
        """One chunk's share of the k-means statistics (see :meth:`fit_centres`)."""
        lo, width = self._histogram_grid()
        return column_histogram(rows, self.mean_, np.ascontiguousarray(self.components_.T), lo, width, self.bins)

    def fit_centres(self, results: list[tuple]) -> CoarseHasher:
        """The k-means step of :meth:`fit`, from every chunk's :meth:`column_histogram`.

        The rare values beyond ±SPAN σ are kept exactly and enter the k-means as points of
        their own; everything here is a sum, a min or a max, so the chunking cannot matter.
        """
        lo, width = self._histogram_grid()
        counts = np.sum([r[0] for r in results], axis=0)
        self.ranges_ = np.stack([np.min([r[1][0] for r in results], axis=0),
                                 np.max([r[1][1] for r in results], axis=0)], axis=1)
        out_col = np.concatenate([r[2] for r in results])
        out_val = np.concatenate([r[3] for r in results])
        mids = lo[:, None] + (np.arange(self.bins) + 0.5) * width[:, None]
        centres = []
        for j in range(self.d_):
            extra = np.sort(out_val[out_col == j])  # sorted: the same points whatever the chunking
            below, above = extra[extra < lo[j]], extra[extra >= lo[j]]
            values = np.concatenate([below, mids[j], above])
            weights = np.concatenate([np.ones(len(below)), counts[j], np.ones(len(above))])
            centres.append(kmeans_1d(values, weights, self.k))
        self.centres_ = np.stack(centres)
        return self

    def _rows(self, x: np.ndarray | da.Array) -> np.ndarray | da.Array:
        check_is_fitted(self, "centres_")
        return check_rows(self, x, reset=False)

    def transform(self, X: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """PCA projection (float64) of rows."""
        x = self._rows(X)
        if isinstance(x, da.Array):
            return x.map_blocks(project, self.mean_, self.components_, dtype=np.float64,
                                chunks=(x.chunks[0], (self.components_.shape[0],)))
        return project(x, self.mean_, self.components_)

    def quantize(self, X: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """Per-component codes (uint8) of rows."""
        x = self._rows(X)

        def codes(b: np.ndarray) -> np.ndarray:
            return hash_descriptors(b, self.mean_, self.components_, self.centres_)[0]

        if isinstance(x, da.Array):
            return x.map_blocks(codes, dtype=np.uint8, chunks=(x.chunks[0], (self.d_,)))
        return codes(x)

    def hash(self, X: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """uint64 addresses of rows."""
        x = self._rows(X)

        def addresses(b: np.ndarray) -> np.ndarray:
            return hash_descriptors(b, self.mean_, self.components_, self.centres_)[1]

        if isinstance(x, da.Array):
            return x.map_blocks(addresses, drop_axis=1, dtype=np.uint64)
        return addresses(x)
