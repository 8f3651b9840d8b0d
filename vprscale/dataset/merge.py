"""Aligning Deep1B with FAS100K: PCA of each, variance rescaling and the query noise model.

``MergeTransform`` is fitted once per dataset (docs/dataset.md, steps 2–5) and then applied chunk by
chunk (steps 6–7) by pure numpy kernels, so workers receive only a few small matrices.
"""

from __future__ import annotations

import inspect

import dask
import numba
import numpy as np
from threadpoolctl import threadpool_limits

from vprscale.core.blocks import BLOCK, block_spans
from vprscale.core.kernelcache import share_kernels
from vprscale.core.progress import compute
from vprscale.dataset import fascache
from vprscale.dataset.gaussian import block_standard_normal
from vprscale.dataset.sources.fas import Traverse
from vprscale.method.pca import ExactPCA, RandomizedPCA, block_moments

share_kernels()

NOISE_STREAM = 17
_FAS_CHUNK = 4096


def _query_chunk(traverse: Traverse, comp: np.ndarray, mean: np.ndarray, noise_comp: np.ndarray, a: int, b: int,
                 n_kept: int) -> tuple[np.ndarray, np.ndarray]:
    """Projections of the kept queries in ``[a, b)`` and ``PCA(ref[gt]) − PCA(query)`` for all of them."""
    q = traverse.query.read(a, b)
    keep = max(0, min(b, n_kept) - a)
    proj = ((q[:keep] @ comp.T.astype(np.float32)).astype(np.float64) - mean @ comp.T).astype(np.float32)
    diff = traverse.ref.take(traverse.gt[a:b]) - q  # the PCA mean cancels
    return proj, (diff @ noise_comp.T.astype(np.float32)).astype(np.float64)


class MergeTransform:
    """Fitted alignment of the two sources (docs/dataset.md, steps 2–5).

    Parameters
    ----------
    dim : components kept of each source (D = 96); the large corpus may be wider (its PCA keeps D).
    n_fas_ref, n_fas_query : FAS rows kept in the dataset.
    seed : seed of the randomized FAS PCA and of the query noise.
    rescale : match Deep1B's per-component spread to FAS's (step 4); off only for the
        ablation of the paper's Fig. 4d.

    Fitted attributes: ``deep_pca_`` (exact PCA of homogenised Deep1B), ``fas_pca_``
    (PCA of the kept FAS reference rows), ``noise_pca_`` (PCA of all FAS reference rows),
    ``scale_`` (per-column rescaling of Deep1B), ``noise_mean_`` / ``noise_std_`` (μ_n, σ_n),
    ``fas_ref_`` / ``fas_query_`` (the kept FAS rows, projected).
    """

    def __init__(self, dim: int, n_fas_ref: int, n_fas_query: int, seed: int, rescale: bool = True) -> None:
        self.dim, self.n_fas_ref, self.n_fas_query, self.seed = dim, n_fas_ref, n_fas_query, seed
        self.rescale = rescale

    def fit(self, deep_moments: np.ndarray, traverse: Traverse) -> MergeTransform:
        """Fit from the summed moments of the homogenised Deep1B rows (:func:`~vprscale.method.pca.block_moments`)
        and the FAS traverse."""
        self.deep_moments_ = deep_moments
        self.deep_pca_ = ExactPCA(self.dim).fit_moments(deep_moments)
        cached = fascache.load(self._fas_key(traverse))
        if cached is None:
            # BLAS on one thread, as in every job's Dask work (core.cluster): its sums split by thread
            # count, and a fit from plain Python would otherwise cache other last bits for every job
            with threadpool_limits(limits=1, user_api="blas"):
                self._fit_fas(traverse)
            fascache.save(self._fas_key(traverse), self._fas_arrays())
        else:
            self._set_fas(cached)
        fas_std = self.fas_ref_.astype(np.float64).std(axis=0)
        self.scale_ = fas_std / np.sqrt(self.deep_pca_.explained_variance_) if self.rescale else np.ones(self.dim)
        return self

    def _fas_key(self, traverse: Traverse) -> dict:
        """What the FAS part of the fit depends on: the traverse, the rows kept, D and the seed."""
        return {"traverse": traverse.fingerprint(), "n_fas_ref": self.n_fas_ref, "n_fas_query": self.n_fas_query,
                "dim": self.dim, "seed": self.seed,
                "code": fascache.code_digest(__file__, inspect.getfile(RandomizedPCA))}

    def _fas_arrays(self) -> dict[str, np.ndarray]:
        return {"fas_mean": self.fas_pca_.mean_, "fas_components": self.fas_pca_.components_,
                "fas_variance": self.fas_pca_.explained_variance_, "noise_pca_mean": self.noise_pca_.mean_,
                "noise_pca_components": self.noise_pca_.components_,
                "noise_pca_variance": self.noise_pca_.explained_variance_, "fas_ref": self.fas_ref_,
                "fas_query": self.fas_query_, "noise_mean": self.noise_mean_, "noise_std": self.noise_std_}

    def _set_fas(self, a: dict[str, np.ndarray]) -> None:
        self.fas_pca_ = _fitted(RandomizedPCA(self.dim, seed=self.seed), a["fas_mean"], a["fas_components"],
                                a["fas_variance"], len(a["fas_ref"]))
        same = np.array_equal(a["noise_pca_components"], a["fas_components"])
        self.noise_pca_ = self.fas_pca_ if same else _fitted(
            RandomizedPCA(self.dim, seed=self.seed), a["noise_pca_mean"], a["noise_pca_components"],
            a["noise_pca_variance"], None)
        self.fas_ref_, self.fas_query_ = a["fas_ref"], a["fas_query"]
        self.noise_mean_, self.noise_std_ = a["noise_mean"], a["noise_std"]

    def _fit_fas(self, traverse: Traverse) -> None:
        """Steps 3 and 5: the FAS PCA of the kept references, the noise PCA, the kept FAS rows
        projected and the noise model, from the traverse alone (so every scale that keeps the same
        FAS rows shares them: :mod:`~vprscale.dataset.fascache`)."""
        self.fas_pca_ = RandomizedPCA(self.dim, seed=self.seed)
        if self.n_fas_ref == traverse.ref.n_rows:
            # The PCA of the kept rows is the noise PCA: the queries are projected in its last
            # pass, and a truth pair's difference is the difference of two projections.
            self.noise_pca_ = self.fas_pca_
            self.fas_ref_, queries = self.fas_pca_.fit_project(traverse.ref.to_dask(_FAS_CHUNK),
                                                               [traverse.query.to_dask(_FAS_CHUNK)])
            delta = self.fas_ref_[traverse.gt].astype(np.float64) - queries
            self.fas_query_ = queries[: self.n_fas_query]
            self.noise_mean_, self.noise_std_ = delta.mean(axis=0), delta.std(axis=0)
        else:
            self.fas_ref_ = self.fas_pca_.fit_transform(traverse.ref.head(self.n_fas_ref).to_dask(_FAS_CHUNK))
            self.noise_pca_ = RandomizedPCA(self.dim, seed=self.seed).fit(traverse.ref.to_dask(_FAS_CHUNK))
            self.fas_query_, self.noise_mean_, self.noise_std_ = self._queries(traverse)

    @property
    def deep_matrix_(self) -> np.ndarray:
        """The (W × D) map of centred homogenised corpus rows (W wide: D for Deep1B) to reference rows:
        PCA, then rescaling."""
        return self.deep_pca_.components_.T * self.scale_

    def ref_moments(self) -> np.ndarray:
        """Moments ``[[RᵀR, Σr], [Σrᵀ, n]]`` of the dataset's reference rows, without a pass over them.

        The Deep1B part is an affine image ``(h − μ)A`` of the homogenised rows, so its
        moments follow from theirs: ``Σr = (Σh − nμ)A`` and ``RᵀR = Aᵀ(HᵀH − μΣhᵀ − Σhμᵀ +
        nμμᵀ)A``; the FAS part's are summed from its (few) rows. The index fits its PCA on
        these, so a store that never writes its reference rows (the compact layout) is
        indexed exactly like one that does.
        """
        d, m = self.dim, self.deep_moments_
        w = m.shape[0] - 1  # the corpus's own width (96 for Deep1B; 128 for BIGANN's SIFT, say)
        hh, sh, n = m[:w, :w], m[:w, w], m[w, w]
        mu = self.deep_pca_.mean_
        a = self.deep_matrix_
        centred = hh - np.outer(mu, sh) - np.outer(sh, mu) + n * np.outer(mu, mu)
        out = np.zeros((d + 1, d + 1))
        out[:d, :d] = a.T @ centred @ a
        out[:d, d] = out[d, :d] = (sh - n * mu) @ a
        out[d, d] = n
        return out + block_moments(self.fas_ref_, 0).sum(axis=0)

    def _queries(self, traverse: Traverse) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pass over the FAS queries: the kept ones projected, and the noise model (step 5),
        when the noise PCA (of every FAS reference) is not the dataset's FAS PCA."""
        n = traverse.query.n_rows
        fas, noise = self.fas_pca_, self.noise_pca_
        parts = [dask.delayed(_query_chunk)(traverse, fas.components_, fas.mean_, noise.components_, a,
                                            min(n, a + _FAS_CHUNK), self.n_fas_query)
                 for a in range(0, n, _FAS_CHUNK)]
        results = compute(*parts, desc="FAS query pass")
        delta = np.concatenate([r[1] for r in results])
        return np.concatenate([r[0] for r in results]), delta.mean(axis=0), delta.std(axis=0)


def _fitted(pca: RandomizedPCA, mean: np.ndarray, components: np.ndarray, variance: np.ndarray,
            n: int | None) -> RandomizedPCA:
    """A randomized PCA as its fit left it, from its cached attributes."""
    pca.mean_, pca.components_, pca.explained_variance_ = mean, components, variance
    pca.n_features_in_ = components.shape[1]
    if n is not None:
        pca.n_samples_ = n
    return pca


def project_rows(h: np.ndarray, mean: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """PCA-project and rescale homogenised rows.

    float32 products: 96-term dot products of centred rows lose ~1e-7 relative, far below
    the float32 output's own rounding, at a fifth of the float64 cost.
    """
    return (h - mean.astype(np.float32)) @ matrix.astype(np.float32)


def project_centred(centred: np.ndarray, start: int, matrix: np.ndarray) -> np.ndarray:
    """:func:`project_rows` of rows already centred (``h − mean`` in float32, first row at
    absolute ``start``), one product per absolute block as :func:`~vprscale.core.blocks.apply_by_block`
    makes them (the same bits), written in place into one array."""
    out = np.empty((len(centred), matrix.shape[1]), np.float32)
    m32 = matrix.astype(np.float32)
    for _, lo, hi in block_spans(start, start + len(centred)):
        np.matmul(centred[lo - start : hi - start], m32, out=out[lo - start : hi - start])
    return out


def noisy_rows(ref: np.ndarray, start: int, seed: int, mean: np.ndarray, std: np.ndarray,
               strengths: tuple[float, ...]) -> list[np.ndarray]:
    """Query rows ``ref + μ_n + s·σ_n·z`` for each strength ``s``, one shared draw ``z`` per row.

    ``z`` is drawn per absolute block of rows, so it does not depend on the chunking; the
    QM1 and QM2 queries share it (common random numbers make the two noise levels
    directly comparable).
    """
    z = np.empty_like(ref)
    for b, lo, hi in block_spans(start, start + len(ref)):
        full = block_standard_normal(seed, NOISE_STREAM, b, (BLOCK, ref.shape[1]))
        z[lo - start : hi - start] = full[lo - b * BLOCK : hi - b * BLOCK]
    mean32, std32 = mean.astype(np.float32), std.astype(np.float32)
    return [_add_noise(ref, z, mean32, np.float32(s) * std32) for s in strengths]


@numba.njit(cache=True, nogil=True)
def _add_noise(ref: np.ndarray, z: np.ndarray, mean: np.ndarray, scaled_std: np.ndarray) -> np.ndarray:
    """``ref + (mean + scaled_std · z)`` in float32, in numpy's order of operations, in one pass
    (numpy's three temporaries made this cost as much as drawing ``z``)."""
    out = np.empty_like(ref)
    for i in range(ref.shape[0]):
        for j in range(ref.shape[1]):
            out[i, j] = ref[i, j] + (mean[j] + scaled_std[j] * z[i, j])
    return out
