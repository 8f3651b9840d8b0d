"""One shared suite for every RowSource implementation (as zarr-python tests every store)."""

from __future__ import annotations

import numpy as np
import pytest

from vprscale.core.errors import InputError
from vprscale.dataset.sources.binfile import BinSource
from vprscale.dataset.sources.deep1b import FvecsSource
from vprscale.dataset.sources.fas import open_fas
from vprscale.dataset.sources.synthetic import SyntheticDeep1B, SyntheticFAS

from .conftest import SMALL_FAS


@pytest.fixture(params=["fvecs-dir", "fbin", "npz-member", "synthetic-deep1b", "synthetic-fas"])
def source(request, sources):
    kind = request.param
    if kind == "fvecs-dir":
        return FvecsSource(sources["fvecs"])
    if kind == "fbin":
        return BinSource(sources["fbin"])
    if kind == "npz-member":
        return open_fas(sources["fas"]).query
    if kind == "synthetic-deep1b":
        return SyntheticDeep1B(50_000, seed=4)
    return SyntheticFAS(4, SMALL_FAS).traverse().ref


def test_read_shapes_and_dtype(source):
    x = source.read(3, 103)
    assert x.shape == (100, source.dim) and x.dtype == np.float32 and x.flags.c_contiguous


def test_reads_agree_however_they_are_split(source):
    n = min(source.n_rows, 40_000)
    whole = source.read(0, n)
    parts = np.concatenate([source.read(a, min(n, a + 3_001)) for a in range(0, n, 3_001)])
    np.testing.assert_array_equal(whole, parts)


def test_take_and_dask_view_agree_with_read(source):
    idx = np.array([0, 5, 17, source.n_rows - 1, 5])
    expected = np.stack([source.read(i, i + 1)[0] for i in idx])
    np.testing.assert_array_equal(source.take(idx), expected)
    np.testing.assert_array_equal(source.to_dask(16384)[: 50].compute(), source.read(0, 50))


def test_head_and_out_of_range(source):
    assert source.head(10).n_rows == 10
    with pytest.raises(InputError, match="rows wanted"):
        source.head(source.n_rows + 1)
    with pytest.raises(InputError, match="outside"):
        source.read(0, source.n_rows + 1)


def test_fingerprint_names_the_source_and_survives_json(source):
    """The fingerprint is JSON as it is, and tells this source from a shorter view of it."""
    import json

    fp = source.fingerprint()
    assert json.loads(json.dumps(fp)) == fp
    assert source.head(source.n_rows - 1).fingerprint() != fp
