"""PCA: exact moments vs numpy, the sign rule, and the randomized solver vs exact where the spectrum has a gap."""

from __future__ import annotations

import dask.array as da
import numpy as np

from vprscale.method.pca import ExactPCA, RandomizedPCA, orthonormal, sign_flip


def _data(n=6000, d=200, rank=12, seed=0):
    rng = np.random.default_rng(seed)
    scales = np.r_[np.linspace(10, 4, rank), np.full(d - rank, 0.3)]  # a gap after `rank` components
    basis, _ = np.linalg.qr(rng.normal(size=(d, d)))
    return ((rng.normal(size=(n, d)) * scales) @ basis.T + 3.0).astype(np.float32)


def _exact(x, k):
    x = x.astype(np.float64)
    cov = np.cov(x, rowvar=False, bias=True)
    w, v = np.linalg.eigh(cov)
    order = np.argsort(w)[::-1][:k]
    return sign_flip(v[:, order].T), w[order]


def test_exact_pca_matches_numpy_and_the_sign_rule():
    x = _data(d=40, rank=5)
    pca = ExactPCA(10).fit(da.from_array(x, chunks=(16384, 40)))
    comp, var = _exact(x, 10)
    np.testing.assert_allclose(pca.components_, comp, atol=1e-8)
    np.testing.assert_allclose(pca.explained_variance_, var, rtol=1e-9)
    top = np.argmax(np.abs(pca.components_), axis=1)
    assert np.all(pca.components_[np.arange(10), top] > 0)


def test_randomized_pca_leading_components_match_exact_where_the_spectrum_has_a_gap():
    x = _data()
    r = RandomizedPCA(12, seed=1)
    proj = r.fit_transform(da.from_array(x, chunks=(1000, 200)))
    comp, var = _exact(x, 12)
    np.testing.assert_allclose(r.components_, comp, atol=2e-4)
    np.testing.assert_allclose(r.explained_variance_, var, rtol=1e-3)
    direct = (x.astype(np.float64) - x.mean(0, dtype=np.float64)) @ comp.T
    np.testing.assert_allclose(proj, direct, atol=2e-3 * np.abs(direct).max())


def test_orthonormal_basis():
    y = np.random.default_rng(2).normal(size=(500, 30))
    q = orthonormal(y)
    np.testing.assert_allclose(q.T @ q, np.eye(30), atol=1e-12)
    # Same column space: projecting y on q reproduces y.
    np.testing.assert_allclose(q @ (q.T @ y), y, atol=1e-10)


def test_merge_projects_queries_in_the_pca_pass_as_a_separate_pass_would():
    """With every FAS reference kept, the queries are projected in the PCA's last pass and the
    noise model comes from projection differences; both agree with the separate query pass."""
    from vprscale.dataset.merge import MergeTransform
    from vprscale.dataset.sources.synthetic import FasParams, SyntheticFAS

    traverse = SyntheticFAS(3, FasParams(dim=128, n_ref=3000, n_query=2000)).traverse()
    from vprscale.method.pca import moments_of

    deep = da.from_array(np.random.default_rng(0).normal(size=(2000, 96)).astype(np.float32), chunks=(500, 96))
    m = MergeTransform(96, traverse.ref.n_rows, 1500, seed=3).fit(moments_of(deep), traverse)
    assert m.noise_pca_ is m.fas_pca_ and m.fas_query_.shape == (1500, 96)
    fq, mu, sd = m._queries(traverse)
    np.testing.assert_allclose(m.fas_query_, fq, atol=1e-5 * np.abs(fq).max())
    np.testing.assert_allclose(m.noise_mean_, mu, atol=1e-5 * sd.max())
    np.testing.assert_allclose(m.noise_std_, sd, rtol=1e-5)


def test_randomized_pca_is_close_to_exact_on_a_slowly_decaying_spectrum():
    """512-d rows whose spectrum decays as k^-0.5: the leading 24 of 96 components agree with an
    exact PCA within 2.5e-3 of each column's standard deviation (one power iteration: ~8e-2)."""
    rng = np.random.default_rng(0)
    n, d = 12_000, 512
    basis, _ = np.linalg.qr(rng.standard_normal((d, d)))
    x = ((rng.standard_normal((n, d)) * np.arange(1, d + 1) ** -0.5) @ basis.T).astype(np.float32)
    xc = x.astype(np.float64) - x.mean(axis=0)
    _, vecs = np.linalg.eigh(xc.T @ xc / n)
    exact = xc @ sign_flip(vecs[:, ::-1][:, :96].T)[:24].T
    got = RandomizedPCA(96, seed=0).fit_transform(da.from_array(x, chunks=(4096, d)))[:, :24]
    err = np.abs(got - exact).max(axis=0) / exact.std(axis=0)
    assert err.max() < 2.5e-3
