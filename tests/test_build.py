"""The dataset build against a direct in-memory numpy computation of SPEC §2."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr

from vprscale.cli import main
from vprscale.dataset.build import BuildRequest, build
from vprscale.dataset.sources.deep1b import open_deep1b
from vprscale.dataset.sources.fas import open_fas

from .conftest import write_recipe

ARRAYS = ("ref", "query_qm1", "query_qm2", "gt", "ref_part", "query_part")


def run_build(recipe, out, sources, layout="fbin", **kw):
    deep = sources.get(layout)
    req = BuildRequest(scale=str(recipe), out=out, deep1b=str(deep) if deep else None, fas=str(sources["fas"]),
                       workers=kw.pop("workers", 2), quiet=True, **kw)
    return build(req)


def exact_pca(x: np.ndarray, k: int = 96):
    mean = x.mean(axis=0)
    cov = np.cov(x - mean, rowvar=False, bias=True)
    w, v = np.linalg.eigh(cov)
    comp = v[:, np.argsort(w)[::-1][:k]].T
    idx = np.argmax(np.abs(comp), axis=1)
    comp *= np.sign(comp[np.arange(k), idx])[:, None]
    return mean, comp


@pytest.fixture(scope="module")
def built(tiny_store, sources):
    return zarr.open_group(tiny_store, mode="r"), sources


def direct(sources):
    """SPEC §2 steps 1–8 in memory with plain numpy (float64 throughout)."""
    raw = open_deep1b(sources["fvecs"]).read(0, 60_000).astype(np.float64)
    n, w = 60_000, 40
    csum = np.vstack([np.zeros(96), np.cumsum(raw, axis=0)])
    i = np.arange(50_000)
    a, b = np.maximum(0, i - w // 2), np.minimum(n, i + w // 2)
    h = (csum[b] - csum[a]) / (b - a)[:, None]
    mean, comp = exact_pca(h)
    deep = (h - mean) @ comp.T
    tr = open_fas(sources["fas"])
    fref = tr.ref.read(0, 3000).astype(np.float64)
    fq = tr.query.read(0, 2000).astype(np.float64)
    fmean, fcomp = exact_pca(fref[:2500])
    fas_ref, fas_q = (fref[:2500] - fmean) @ fcomp.T, (fq - fmean) @ fcomp.T
    deep *= fas_ref.std(axis=0) / deep.std(axis=0)
    _, ncomp = exact_pca(fref)
    delta = (fref[tr.gt] - fq) @ ncomp.T
    gt = np.concatenate([np.arange(50_000), np.where(tr.gt < 2500, 50_000 + tr.gt, -1)])
    return {"deep": deep, "fas_ref": fas_ref, "fas_q": fas_q, "mu": delta.mean(0), "sigma": delta.std(0),
            "gt": gt, "h": h}


@pytest.fixture(scope="module")
def expected(built):
    return direct(built[1])


def test_store_layout_and_provenance(built):
    g, _ = built
    assert g["ref"].shape == (52_500, 96) and g["query_qm1"].shape == (52_000, 96)
    assert g["gt"].dtype == np.int64 and g["ref_part"].dtype == np.uint8
    meta = g.attrs["vprscale"]
    assert meta["complete"] is True
    assert meta["recipe"]["scale"] == "tiny" and meta["seed"] == 5
    assert meta["sources"]["deep1b"]["format"] == "fbin"
    assert {"numpy", "dask", "zarr", "vprscale"} <= set(meta["versions"])
    assert g["transforms/deep1b_components"].shape == (96, 96)


def test_homogenised_pca_matches_direct_computation(built, expected):
    g, _ = built
    np.testing.assert_allclose(g["ref"][:50_000], expected["deep"], atol=2e-5, rtol=1e-4)
    np.testing.assert_allclose(g["transforms/deep1b_mean"][:], expected["h"].mean(0), atol=1e-8)


def test_fas_part_matches_direct_pca(built, expected):
    g, _ = built
    np.testing.assert_allclose(g["ref"][50_000:], expected["fas_ref"], atol=2e-5)
    np.testing.assert_allclose(g["query_qm1"][50_000:], expected["fas_q"], atol=2e-5)
    np.testing.assert_array_equal(g["query_qm1"][50_000:], g["query_qm2"][50_000:])


def test_rescaled_spreads_are_equal(built):
    g, _ = built
    ref = g["ref"][:].astype(np.float64)
    np.testing.assert_allclose(ref[:50_000].std(0), ref[50_000:].std(0), rtol=1e-4)


def test_noise_model_and_query_noise(built, expected):
    g, _ = built
    np.testing.assert_allclose(g["transforms/noise_mean"][:], expected["mu"], atol=1e-6)
    np.testing.assert_allclose(g["transforms/noise_std"][:], expected["sigma"], rtol=1e-5)
    ref = g["ref"][:50_000].astype(np.float64)
    n = len(ref)
    for name, s in (("query_qm1", 1.0), ("query_qm2", 2.0)):
        noise = g[name][:50_000] - ref
        sigma = s * expected["sigma"]
        assert np.all(np.abs(noise.mean(0) - expected["mu"]) < 5 * sigma / np.sqrt(n))
        assert np.all(np.abs(noise.std(0) / sigma - 1) < 5 / np.sqrt(2 * n))


def test_ground_truth_and_parts(built, expected):
    g, _ = built
    np.testing.assert_array_equal(g["gt"][:], expected["gt"])
    assert (expected["gt"][50_000:] == -1).any()  # the truncation to 2500 FAS refs drops some
    np.testing.assert_array_equal(g["ref_part"][:], np.r_[np.zeros(50_000), np.ones(2500)])
    np.testing.assert_array_equal(g["query_part"][:], np.r_[np.zeros(50_000), np.ones(2000)])


def _arrays(path):
    g = zarr.open_group(path, mode="r")
    return {k: g[k][:] for k in ARRAYS} | {"components": g["transforms/deep1b_components"][:]}


def test_same_bytes_whatever_chunk_size_workers_and_layout(built, sources, tmp_path):
    g, _ = built
    recipe = write_recipe(tmp_path / "tiny.toml", chunk_rows=32768)
    run_build(recipe, tmp_path / "o", sources, layout="fvecs", workers=1)
    other = _arrays(tmp_path / "o" / "tiny.zarr")
    base = {k: g[k][:] for k in ARRAYS} | {"components": g["transforms/deep1b_components"][:]}
    for k in base:
        assert base[k].tobytes() == other[k].tobytes(), k


def test_the_fas_fit_is_computed_once_per_source_and_never_stale(sources, tmp_path, monkeypatch):
    """A second build keeping the same FAS rows takes the FAS PCA, noise model and projected rows
    from the cache (the solver is not run: here it would fail) and writes the same bytes; a build
    keeping other FAS rows, or from another FAS file, does not take them."""
    from vprscale.method.pca import RandomizedPCA

    recipe = write_recipe(tmp_path / "tiny.toml")
    run_build(recipe, tmp_path / "a", sources)

    def refuse(*args, **kwargs):
        raise AssertionError("the FAS PCA was computed again")

    monkeypatch.setattr(RandomizedPCA, "fit_project", refuse)
    monkeypatch.setattr(RandomizedPCA, "fit", refuse)
    monkeypatch.setattr(RandomizedPCA, "fit_transform", refuse)
    run_build(recipe, tmp_path / "b", sources, rescale=False)  # the ablation shares it
    run_build(write_recipe(tmp_path / "wide.toml", chunk_rows=32768), tmp_path / "c", sources)
    assert _arrays(tmp_path / "a" / "tiny.zarr")["ref"].tobytes() == _arrays(tmp_path / "c" / "tiny.zarr")[
        "ref"].tobytes()
    with pytest.raises(AssertionError, match="computed again"):
        run_build(write_recipe(tmp_path / "fewer.toml", fas_ref_rows=2000), tmp_path / "d", sources)
    other = tmp_path / "fas2.npz"
    shutil.copy(sources["fas"], other)
    with pytest.raises(AssertionError, match="computed again"):
        build(BuildRequest(scale=str(recipe), out=tmp_path / "e", deep1b=str(sources["fbin"]), fas=str(other),
                           quiet=True))


def test_centred_in_the_window_pass_and_projected_in_place_are_the_recipe_s_bits():
    """``window_mean`` less the mean (float32, after its own rounding) and one product per
    absolute block written in place give the rows of the recipe's formula, ``(h − mean) @ M``
    in float32 per absolute block, whatever range is asked."""
    from vprscale.core.blocks import BLOCK, apply_by_block
    from vprscale.dataset.homogenise import window_mean
    from vprscale.dataset.merge import project_centred, project_rows
    from vprscale.dataset.sources.synthetic import SyntheticDeep1B

    src = SyntheticDeep1B(3 * BLOCK, seed=2)
    rng = np.random.default_rng(1)
    mean, matrix = rng.standard_normal(96) * 0.01, rng.standard_normal((96, 96))
    for a, b in [(0, 3 * BLOCK), (BLOCK - 7, 2 * BLOCK + 5), (5, 6)]:
        h = window_mean(src, src.n_rows, a, b, 40)
        np.testing.assert_array_equal(project_centred(window_mean(src, src.n_rows, a, b, 40, mean), a, matrix),
                                      apply_by_block(project_rows, h, a, mean, matrix))


@pytest.mark.slow
def test_fas_fit_has_the_same_bits_from_python_and_from_a_job(tmp_path, monkeypatch):
    """The FAS part of the fit (a randomized PCA of 47,781 × 4,096 rows) gives the same bits
    called from plain Python, with BLAS on every core, as inside a job's Dask work (one BLAS
    thread): a fit cached by either is the other's, and a compact store's transforms refit from
    Python are its own."""
    from threadpoolctl import threadpool_limits

    from vprscale.core.cluster import dask_client
    from vprscale.dataset.merge import MergeTransform
    from vprscale.dataset.sources.synthetic import SyntheticFAS
    from vprscale.method.pca import moments_of

    traverse = SyntheticFAS(0).traverse()
    moments = moments_of(np.random.default_rng(0).standard_normal((4096, 96)))
    fits = []
    for where in ("python", "job"):
        monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / where))  # fitted afresh each time
        if where == "python":
            with threadpool_limits(limits=2, user_api="blas"):
                fits.append(MergeTransform(96, 47_781, 26_638, 0).fit(moments, traverse))
        else:
            with dask_client(None, 2):
                fits.append(MergeTransform(96, 47_781, 26_638, 0).fit(moments, traverse))
    for name in ("fas_ref_", "fas_query_", "noise_mean_", "noise_std_", "scale_"):
        np.testing.assert_array_equal(getattr(fits[0], name), getattr(fits[1], name), err_msg=name)


def test_plain_zarr_lists_a_store_without_a_warning(tiny_store, tmp_path):
    """A store lists with plain zarr as any Zarr group does: its metadata is consolidated before it
    is published, so zarr does not warn on every listing of the files it does not know (build.json,
    manifest.json), a recipe's store and your own alike."""
    import warnings

    rng = np.random.default_rng(0)
    np.save(tmp_path / "ref.npy", rng.standard_normal((500, 8)).astype(np.float32))
    np.save(tmp_path / "gt.npy", np.arange(500))
    assert main(["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'ref.npy'}", "--gt",
                 str(tmp_path / "gt.npy"), "--name", "mine", "--out", str(tmp_path), "-q"]) == 0
    for store in (tiny_store, tmp_path / "mine.zarr"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            group = zarr.open_group(str(store), mode="r")
            assert "ref" in set(group.keys()) and group["ref"].shape[0] > 0
