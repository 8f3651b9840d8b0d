"""The public estimators follow scikit-learn's contract (check_estimator, clone, Pipeline)."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.pipeline import Pipeline
from sklearn.utils.estimator_checks import check_estimator

from vprscale import CoarseHasher, ExactPCA, RandomizedPCA

ESTIMATORS = [ExactPCA(), CoarseHasher(), CoarseHasher(k=3), RandomizedPCA(2)]  # widths fit 2-column data
# Checks that cannot apply here, and why.
NOT_APPLICABLE = {
    "check_array_api_input": "skipped by scikit-learn unless SCIPY_ARRAY_API is set; the estimators take "
                             "numpy and Dask arrays, not the array API",
}


@pytest.mark.parametrize("est", ESTIMATORS, ids=repr)
def test_check_estimator(est):
    results = check_estimator(est, on_fail=None, on_skip=None)
    bad = [(r["check_name"], r["status"], str(r["exception"])[:200]) for r in results
           if r["status"] != "passed" and r["check_name"] not in NOT_APPLICABLE]
    assert not bad
    assert len(results) > 40


def test_package_names_are_the_implementations():
    """``from vprscale import …`` gives the classes the modules define (not copies or stand-ins)."""
    import vprscale
    from vprscale.method import coarsehash, index, online, pca

    assert vprscale.Index is index.Index and vprscale.OnlineMatcher is online.OnlineMatcher
    assert vprscale.CoarseHasher is coarsehash.CoarseHasher and vprscale.ExactPCA is pca.ExactPCA
    with pytest.raises(AttributeError, match="no attribute 'Engine'"):
        vprscale.Engine  # noqa: B018


def test_clone_params_and_pipeline():
    x = np.random.default_rng(0).normal(size=(3000, 12)).astype(np.float32)
    h = CoarseHasher(d=4, k=2)
    assert h.get_params() == {"d": 4, "k": 2, "bins": 1 << 14}
    h2 = clone(h).set_params(d=5)
    assert h2.d == 5 and h.d == 4 and not hasattr(h2, "centres_")
    pipe = Pipeline([("pca", ExactPCA(8)), ("hash", CoarseHasher(d=4))]).fit(x)
    z = pipe.transform(x)
    assert z.shape == (3000, 4)
    y = ExactPCA(8).fit_transform(x)
    np.testing.assert_array_equal(pipe[-1].hash(y), CoarseHasher(d=4).fit(y).hash(y))


def test_every_method_checks_the_width():
    """A strided view of the wrong width used to hash past the array; now it is an error naming both widths."""
    x = np.random.default_rng(1).normal(size=(2000, 8)).astype(np.float32)
    h = CoarseHasher(d=3).fit(x)
    for method in (h.transform, h.quantize, h.hash):
        with pytest.raises(ValueError, match="5 features.*expecting 8"):
            method(x[:, :5])
    with pytest.raises(ValueError, match="5 features.*expecting 8"):
        ExactPCA(2).fit(x).transform(x[:, :5])
    np.testing.assert_array_equal(h.hash(x[::2]), h.hash(np.ascontiguousarray(x[::2])))


@pytest.mark.parametrize("cut", [1, 16383, 16384, 20000])
def test_exact_pca_partial_fit_equals_fit_exactly(cut):
    x = np.random.default_rng(2).normal(size=(40000, 10)).astype(np.float32) * np.arange(1, 11)
    whole = ExactPCA(4).fit(x)
    parts = ExactPCA(4).partial_fit(x[:cut]).partial_fit(x[cut:30000]).partial_fit(x[30000:])
    for attr in ("mean_", "components_", "explained_variance_", "moments_"):
        assert np.array_equal(getattr(whole, attr), getattr(parts, attr)), attr
    assert parts.n_samples_ == 40000
    with pytest.raises(ValueError, match="features"):
        parts.partial_fit(x[:10, :9])


def test_errors_name_arguments_not_flags():
    with pytest.raises(ValueError, match=r"^k = 1: "):
        CoarseHasher(k=1).fit(np.zeros((10, 4), np.float32))
    with pytest.raises(ValueError, match=r"^d = 9: "):
        CoarseHasher(d=9).fit(np.zeros((10, 4), np.float32))
