"""The block standard-normal sampler: numpy's SFC64 bits, exact ziggurat tables, N(0, 1) draws."""

from __future__ import annotations

import math

import numpy as np

from vprscale.core.blocks import block_rng
from vprscale.dataset.gaussian import LAYERS, R, V, _sfc64, block_standard_normal, ziggurat_tables


def test_bit_stream_is_numpys_sfc64():
    rng = block_rng(5, 17, 2)
    a, b, c, n = (np.uint64(v) for v in rng.bit_generator.state["state"]["state"])
    ours = []
    for _ in range(1000):
        # numba boxes a tuple's uint64 values as signed Python ints: back to uint64 each step
        out, a, b, c, n = (np.uint64(v % 2**64) for v in _sfc64(a, b, c, n))
        ours.append(out)
    np.testing.assert_array_equal(np.array(ours, np.uint64), rng.bit_generator.random_raw(1000))


def test_every_layer_has_the_same_area():
    w, k, f = ziggurat_tables()
    x = w * 2.0**52
    layers = x[1:] * (f[:-1] - f[1:])  # layer i: width x_i, densities f(x_i) … f(x_{i−1})
    tail = math.sqrt(math.pi / 2) * math.erfc(R / math.sqrt(2))
    base = R * math.exp(-0.5 * R * R) + tail  # rectangle up to R, then the tail
    np.testing.assert_allclose(np.append(layers, [base, x[0] * math.exp(-0.5 * R * R)]), V, rtol=1e-8)
    assert len(x) == LAYERS and k[1] == 0 and np.all(np.diff(x[1:]) > 0)
    # the fast-accept threshold of a layer is the width of the layer above
    np.testing.assert_allclose(k[2:] / 2.0**52 * x[2:], x[1:-1], rtol=1e-12)


def test_draws_are_standard_normal():
    z = np.concatenate([block_standard_normal(0, 9, b, (1 << 20,)) for b in range(4)]).astype(np.float64)
    n = len(z)
    assert abs(z.mean()) < 5 / math.sqrt(n)
    assert abs(z.var() - 1) < 5 * math.sqrt(2 / n)
    assert abs(np.mean(z**3)) < 5 * math.sqrt(15 / n)
    assert abs(np.mean(z**4) - 3) < 5 * math.sqrt(96 / n)
    p_tail = math.erfc(R / math.sqrt(2))  # |z| > R: drawn by the tail branch only
    assert abs(np.mean(np.abs(z) > R) - p_tail) < 5 * math.sqrt(p_tail / n)
    s = np.sort(z)[::97]
    cdf = 0.5 * (1 + np.array([math.erf(v / math.sqrt(2)) for v in s]))
    ks = np.abs(cdf - np.arange(len(s)) * 97 / n).max()
    assert ks < 1.95 / math.sqrt(n) + 97 / n  # Kolmogorov–Smirnov at the 0.1 % level


def test_a_block_is_a_pure_function_of_its_key():
    a = block_standard_normal(1, 17, 3, (64, 96))
    assert a.dtype == np.float32 and a.shape == (64, 96)
    np.testing.assert_array_equal(a, block_standard_normal(1, 17, 3, (64, 96)))
    assert not np.array_equal(a, block_standard_normal(1, 17, 4, (64, 96)))
    assert not np.array_equal(a, block_standard_normal(2, 17, 3, (64, 96)))
    # a longer draw of the same block starts with the same values
    np.testing.assert_array_equal(a.ravel(), block_standard_normal(1, 17, 3, (128 * 96,))[: 64 * 96])
