"""The CoarseHash method (SPEC §3.1–3.2): PCA, per-component scalar quantisation, hashing.

``CoarseHasher`` is an estimator: parameters in ``__init__``, ``fit`` on the reference rows,
fitted attributes ending in ``_``. Every method takes a numpy array or a Dask array; a numpy
input is run through the same chunked path, so both give identical bits.
"""

from __future__ import annotations

import math

import dask.array as da
import numpy as np

from vprscale.blocks import apply_by_block
from vprscale.errors import InputError
from vprscale.kmeans1d import kmeans_1d
from vprscale.pca import ExactPCA
from vprscale.progress import compute

_CHUNK = 65536


def _as_dask(x: np.ndarray | da.Array) -> da.Array:
    if isinstance(x, da.Array):
        return x
    x = np.asarray(x)
    return da.from_array(x, chunks=(_CHUNK, x.shape[1]))


def _project_rows(x: np.ndarray, mean: np.ndarray, components: np.ndarray) -> np.ndarray:
    return (np.asarray(x, np.float64) - mean) @ components.T


def project(x: np.ndarray, mean: np.ndarray, components: np.ndarray, start: int = 0) -> np.ndarray:
    """Centred projection in float64 of rows whose first one is row ``start`` of their array."""
    return apply_by_block(_project_rows, x, start, mean, components)


def _project_chunk(x: np.ndarray, mean: np.ndarray, components: np.ndarray,
                   block_info: dict | None = None) -> np.ndarray:
    start = block_info[0]["array-location"][0][0] if block_info else 0
    return project(x, mean, components, start)


def quantize_with_error(y: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Codes ``argmin_k |y_j − c_jk|`` (uint8; ties: the smaller k) and ``Σ_j min_k |y_j − c_jk|``.

    One elementwise pass per level k over the (rows × d) block: no (rows × d × K)
    temporary and no reduction along a short axis.
    """
    best = np.abs(y - centres[:, 0])
    codes = np.zeros(y.shape, dtype=np.uint8)
    for k in range(1, centres.shape[1]):
        dist = np.abs(y - centres[:, k])
        closer = dist < best  # strict: a tie keeps the smaller level
        np.copyto(codes, np.uint8(k), where=closer)
        np.minimum(best, dist, out=best)
    return codes, best.sum(axis=1)


def quantize_projected(y: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """``argmin_k |y_j − c_jk|`` per column (ties: the smaller k), as uint8 codes."""
    return quantize_with_error(y, centres)[0]


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


def quantization_error(y: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """``Σ_j min_k |y_j − c_jk|``: how far a row is from its address (SPEC §3.1 single best)."""
    return quantize_with_error(y, centres)[1]


def _column_range(y: np.ndarray) -> np.ndarray:
    return np.stack([y.min(axis=0), y.max(axis=0)])[None]


def _column_histograms(y: np.ndarray, lo: np.ndarray, width: np.ndarray, bins: int) -> np.ndarray:
    idx = np.clip(((y - lo) / width).astype(np.int64), 0, bins - 1)
    offsets = idx + np.arange(y.shape[1]) * bins
    return np.bincount(offsets.ravel(), minlength=y.shape[1] * bins).reshape(1, y.shape[1], bins)


class CoarseHasher:
    """Coarse scalar-quantisation hashing of descriptors.

    Parameters
    ----------
    d : PCA components kept (hash digits); default ``⌈log2 N_ref⌉``.
    k : quantisation levels per component (K), at least 2.
    bins : histogram bins per component for the streamed 1-D k-means. The centres are the
        exact k-means optimum of the values moved to their bin midpoints: each value moves
        by at most ``(max − min) / (2 · bins)`` of its component.

    Fitted attributes: ``d_``, ``mean_``, ``components_`` (d × D), ``explained_variance_``,
    ``centres_`` (d × K, ascending), ``ranges_`` (d × 2), ``n_ref_``.
    """

    def __init__(self, d: int | None = None, k: int = 2, bins: int = 1 << 14) -> None:
        self.d, self.k, self.bins = d, k, bins

    def _check(self, n: int, dim: int) -> int:
        if self.k < 2:
            raise InputError(f"--k {self.k}: K must be at least 2")
        if self.k > 255:
            raise InputError(f"--k {self.k}: K must be at most 255 (codes are uint8)")
        d = self.d if self.d is not None else max(1, math.ceil(math.log2(n)))
        if not 1 <= d <= dim:
            raise InputError(f"--d {d}: must be between 1 and the descriptor width {dim}")
        if self.k**d > 2**64:
            raise InputError(f"--d {d} --k {self.k}: K^d = {self.k}^{d} addresses exceed 2^64")
        return d

    def fit(self, ref: np.ndarray | da.Array) -> CoarseHasher:
        """Exact PCA, then per-component 1-D k-means; three streamed passes over ``ref``."""
        x = _as_dask(ref)
        n, dim = x.shape
        self.d_ = self._check(n, dim)
        pca = ExactPCA(self.d_).fit(x)
        self.mean_, self.components_ = pca.mean_, pca.components_
        self.explained_variance_ = pca.explained_variance_
        y = self.transform(x)
        ranges = y.map_blocks(_column_range, chunks=((1,) * y.numblocks[0], (2,), (self.d_,)),
                              new_axis=2, dtype=np.float64)
        (ranges,) = compute(ranges)
        self.ranges_ = np.stack([ranges[:, 0].min(axis=0), ranges[:, 1].max(axis=0)], axis=1)
        lo = self.ranges_[:, 0]
        width = np.maximum((self.ranges_[:, 1] - lo) / self.bins, np.finfo(np.float64).tiny)
        hist = y.map_blocks(_column_histograms, lo, width, self.bins, new_axis=2,
                            chunks=((1,) * y.numblocks[0], (self.d_,), (self.bins,)), dtype=np.int64)
        (counts,) = compute(hist.sum(axis=0))
        mids = lo[:, None] + (np.arange(self.bins) + 0.5) * width[:, None]
        self.centres_ = np.stack([kmeans_1d(mids[j], counts[j], self.k) for j in range(self.d_)])
        self.n_ref_ = n
        return self

    def transform(self, x: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """PCA projection (float64) of rows."""
        if isinstance(x, da.Array):
            return x.map_blocks(_project_chunk, self.mean_, self.components_, dtype=np.float64,
                                chunks=(x.chunks[0], (self.components_.shape[0],)))
        return project(x, self.mean_, self.components_)

    def quantize(self, x: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """Per-component codes (uint8) of rows."""
        y = self.transform(x)
        if isinstance(y, da.Array):
            return y.map_blocks(quantize_projected, self.centres_, dtype=np.uint8)
        return quantize_projected(y, self.centres_)

    def hash(self, x: np.ndarray | da.Array) -> np.ndarray | da.Array:
        """uint64 addresses of rows."""
        q = self.quantize(x)
        if isinstance(q, da.Array):
            return q.map_blocks(pack, self.k, drop_axis=1, dtype=np.uint64)
        return pack(q, self.k)
