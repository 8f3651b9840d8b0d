"""CoarseHasher: addresses, bit order, ties, K > 2, 1-D k-means, numpy vs Dask."""

from __future__ import annotations

import itertools

import dask.array as da
import numpy as np
import pytest

from vprscale.core.errors import InputError
from vprscale.method.coarsehash import CoarseHasher, pack, unpack
from vprscale.method.kmeans1d import kmeans_1d
from vprscale.method.lists import inverted_lists

from .conftest import kmeans_1d_exact, quantize


def factorial_design(sigmas, repeat=5):
    """Rows at every sign combination of ±σ_j: the PCA axes are the coordinate axes."""
    signs = np.array(list(itertools.product([-1.0, 1.0], repeat=len(sigmas))))
    return np.repeat(signs * np.asarray(sigmas), repeat, axis=0), np.repeat(signs, repeat, axis=0)


def test_known_addresses_and_bit_order():
    sigmas = [4.0, 2.0, 1.0]
    # Shuffle the axes so that the first principal component is the *last* input column.
    x, signs = factorial_design(sigmas)
    x, signs = x[:, ::-1], signs[:, ::-1]
    h = CoarseHasher(d=3, k=2).fit(x)
    np.testing.assert_allclose(np.abs(h.components_), np.eye(3)[::-1], atol=1e-12)
    # Each value moves by at most half a histogram bin: 8σ / bins for the widest component.
    np.testing.assert_allclose(h.centres_, [[-4, 4], [-2, 2], [-1, 1]], atol=8 * 4 / h.bins)
    bits = (signs[:, ::-1] > 0).astype(np.uint64)  # in component order: σ = 4, 2, 1
    expected = bits[:, 0] * 4 + bits[:, 1] * 2 + bits[:, 2]
    np.testing.assert_array_equal(h.hash(x), expected)


def test_pack_first_component_is_most_significant_and_unpack_inverts():
    codes = np.array([[1, 0, 0], [0, 0, 1], [2, 1, 0]], dtype=np.uint8)
    np.testing.assert_array_equal(pack(codes[:2], 2), [4, 1])
    np.testing.assert_array_equal(pack(codes, 3), [9, 1, 21])
    np.testing.assert_array_equal(unpack(pack(codes, 3), 3, 3), codes)
    top = np.ones((1, 64), dtype=np.uint8)
    assert pack(top, 2)[0] == np.uint64(2**64 - 1)


def test_quantize_ties_take_the_smaller_centre():
    centres = np.array([[-1.0, 1.0], [0.0, 2.0]])
    y = np.array([[0.0, 1.0], [0.5, 1.5]])
    np.testing.assert_array_equal(quantize(y, centres)[0], [[0, 0], [1, 1]])


def test_k_greater_than_two():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(c, 0.05, size=(300, 1)) for c in (-3.0, 0.0, 3.0)])
    x = np.hstack([x, rng.normal(0, 0.01, size=(900, 1))])
    h = CoarseHasher(d=1, k=3).fit(x)
    np.testing.assert_allclose(np.sort(np.abs(h.centres_[0])), [0, 3, 3], atol=0.02)
    addr = h.hash(x)
    assert sorted(np.bincount(addr.astype(np.int64)).tolist()) == [300, 300, 300]


def test_kmeans_1d_matches_brute_force():
    rng = np.random.default_rng(7)
    for _ in range(40):
        n, k = int(rng.integers(3, 10)), int(rng.integers(2, 5))
        x = np.sort(rng.normal(size=n) * rng.integers(1, 6, n))
        k = min(k, n)
        best = min(
            (sum(((x[a:b] - x[a:b].mean()) ** 2).sum() for a, b in zip((0, *c), (*c, n), strict=True)), c)
            for c in itertools.combinations(range(1, n), k - 1))
        cuts = (0, *best[1], n)
        expected = [x[a:b].mean() for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
        np.testing.assert_allclose(kmeans_1d_exact(x, k), expected, rtol=1e-12, atol=1e-12)


def test_values_beyond_the_histogram_are_kept_exactly():
    rng = np.random.default_rng(4)
    x = np.zeros((20_000, 2))
    x[:, 0] = rng.normal(0, 1, 20_000)
    x[:10, 0] = 50.0  # far beyond 8σ: must pull the upper centre by exactly their share
    x[:, 1] = rng.normal(0, 0.1, 20_000)
    h = CoarseHasher(d=1, k=2).fit(x)
    y = (x - x.mean(0)) @ h.components_[0]
    exact = kmeans_1d_exact(y, 2)
    np.testing.assert_allclose(h.centres_[0], exact, atol=8 * np.sqrt(h.explained_variance_[0]) / h.bins)


def test_histogram_kmeans_error_bound():
    rng = np.random.default_rng(3)
    col = np.concatenate([rng.normal(-1, 0.3, 5000), rng.normal(1.5, 0.5, 7000)])
    exact = kmeans_1d_exact(col, 2)
    bins = 256
    lo, hi = col.min(), col.max()
    w = (hi - lo) / bins
    counts = np.bincount(np.clip(((col - lo) / w).astype(int), 0, bins - 1), minlength=bins)
    approx = kmeans_1d(lo + (np.arange(bins) + 0.5) * w, counts, 2)
    assert np.all(np.abs(approx - exact) <= w)


def test_numpy_and_dask_give_identical_addresses():
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(150_000, 96)) * np.linspace(2, 0.1, 96)).astype(np.float32)
    a = CoarseHasher(k=2).fit(x)
    b = CoarseHasher(k=2).fit(da.from_array(x, chunks=(32768, 96)))
    assert a.d_ == b.d_ == 18
    np.testing.assert_array_equal(a.centres_, b.centres_)
    np.testing.assert_array_equal(a.hash(x), b.hash(da.from_array(x, chunks=(16384, 96))).compute())


def test_single_best_is_least_error_with_ties_to_the_smallest_id():
    h = np.array([5, 3, 5, 5, 3], dtype=np.uint64)
    err = np.array([0.5, 0.2, 0.1, 0.1, 0.2])
    lists = inverted_lists(h, err)
    np.testing.assert_array_equal(lists["addresses"], [3, 5])
    np.testing.assert_array_equal(lists["sizes"], [2, 3])
    np.testing.assert_array_equal(lists["best"], [1, 2])
    np.testing.assert_array_equal(lists["order"], [1, 4, 0, 2, 3])


@pytest.mark.parametrize(("d", "k", "message"), [
    (97, 2, "d = 97: must be an integer between 1 and the descriptor width 96"),
    (41, 3, "K\\^d = 3\\^41 addresses exceed 2\\^64"),
    (10, 1, "k = 1: K must be an integer of at least 2"),
])
def test_bad_parameters(d, k, message):
    with pytest.raises(InputError, match=message):
        CoarseHasher(d=d, k=k).fit(np.zeros((10, 96), np.float32))


def test_projection_bits_depend_only_on_the_row():
    """Rows projected four at a time, one at a time, or shifted within the input agree bit for bit."""
    from vprscale.method.hashkernels import project_rows

    rng = np.random.default_rng(3)
    x = rng.normal(size=(37, 96)).astype(np.float32)
    mean, w = rng.normal(size=96), rng.normal(size=(96, 20))
    whole = project_rows(x, mean, w)
    one_by_one = np.vstack([project_rows(x[i:i + 1], mean, w) for i in range(len(x))])
    np.testing.assert_array_equal(whole, one_by_one)
    np.testing.assert_array_equal(whole[3:], project_rows(x[3:], mean, w))
    np.testing.assert_allclose(whole, (x.astype(np.float64) - mean) @ w, rtol=1e-10, atol=1e-10)


def test_hashing_gives_the_baseline_map_of_the_same_rows_bit_for_bit():
    """A compact build takes the baseline's map (each row's first component, float32) from the
    hashing's own projection: the bits of projecting on the first component alone."""
    from vprscale.dataset.compact import baseline_map
    from vprscale.method.coarsehash import hash_descriptors

    rng = np.random.default_rng(7)
    x = rng.standard_normal((5003, 96)).astype(np.float32)
    hasher = CoarseHasher(d=13).fit(x)
    first = np.full(len(x), np.nan, np.float32)
    with_first = hash_descriptors(x, hasher.mean_, hasher.components_, hasher.centres_, first)
    np.testing.assert_array_equal(first, baseline_map(x, hasher.mean_, hasher.components_))
    for got, plain in zip(with_first, hash_descriptors(x, hasher.mean_, hasher.components_, hasher.centres_),
                          strict=True):
        np.testing.assert_array_equal(got, plain)
