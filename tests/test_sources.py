"""Readers of the real layouts, on files written in those layouts, and the generator."""

from __future__ import annotations

import os
import zipfile

import numpy as np
import pytest

from vprscale.core.blocks import BLOCK
from vprscale.core.errors import InputError
from vprscale.dataset.sources.base import check_finite
from vprscale.dataset.sources.binfile import BinSource
from vprscale.dataset.sources.deep1b import FvecsSource, open_deep1b
from vprscale.dataset.sources.fas import open_fas
from vprscale.dataset.sources.synthetic import SUB_ROWS, Deep1BParams, SyntheticDeep1B, SyntheticFAS
from vprscale.dataset.sources.writers import write_fas_npz

from .conftest import DEEP_ROWS, SMALL_FAS


def _expected(n: int = DEEP_ROWS) -> np.ndarray:
    return SyntheticDeep1B(n, seed=3).read(0, n)


@pytest.mark.parametrize("layout", ["fvecs", "fbin"])
def test_deep1b_layouts_read_back_the_generator_rows(sources, layout):
    src = open_deep1b(sources[layout])
    assert (src.n_rows, src.dim) == (DEEP_ROWS, 96)
    expected = _expected()
    np.testing.assert_array_equal(src.read(0, DEEP_ROWS), expected)
    # A range that straddles the border between base_00 and base_01.
    np.testing.assert_array_equal(src.read(29_990, 30_010), expected[29_990:30_010])


def test_fvecs_directory_is_read_in_name_order(sources):
    src = FvecsSource(sources["fvecs"])
    assert [f.name for f in src.files] == ["base_00", "base_01", "base_02"]


def test_dask_view_keeps_data_out_of_the_graph(sources):
    x = BinSource(sources["fbin"]).to_dask(16384)
    graph_bytes = sum(len(repr(v)) for v in dict(x.__dask_graph__()).values())
    assert graph_bytes < 100_000
    np.testing.assert_array_equal(x[100:200].compute(), _expected()[100:200])


def test_fvecs_truncated_file_names_file_and_offset(tmp_path):
    data = (tmp_path / "base_00")
    rec = np.zeros((3, 97), "<f4")
    rec[:, 0] = np.array(96, "<i4").view("<f4")
    data.write_bytes(rec.tobytes()[:-10])
    with pytest.raises(InputError, match=r"base_00: size 1154 is not a multiple .* offset 776"):
        FvecsSource(data)


def test_fvecs_record_of_other_dimension_names_offset(tmp_path):
    rec = np.zeros((4, 97), "<f4")
    rec[:, 0] = np.array(96, "<i4").view("<f4")
    rec[2, 0] = np.array(95, "<i4").view("<f4")
    path = tmp_path / "x.fvecs"
    path.write_bytes(rec.tobytes())
    with pytest.raises(InputError, match=r"x.fvecs: offset 776: record dimension 95, expected 96"):
        FvecsSource(path).read(0, 4)


def test_nan_row_is_named(tmp_path):
    rows = np.ones((10, 96), "<f4")
    rows[7, 3] = np.nan
    path = tmp_path / "bad.fbin"
    path.write_bytes(np.array([10, 96], "<u4").tobytes() + rows.tobytes())
    with pytest.raises(InputError, match="row 7 holds NaN or Inf"):
        BinSource(path).read(0, 10)


def test_inf_row_is_named_in_fvecs(tmp_path):
    rec = np.ones((5, 97), "<f4")
    rec[:, 0] = np.array(96, "<i4").view("<f4")
    rec[4, 9] = np.inf
    path = tmp_path / "inf.fvecs"
    path.write_bytes(rec.tobytes())
    with pytest.raises(InputError, match="row 4 holds NaN or Inf"):
        FvecsSource(path).read(2, 5)


def test_finite_check_is_exact():
    """Huge finite values whose float32 row sum overflows pass; the first NaN/Inf row is named,
    including a row whose +Inf and −Inf would cancel into NaN and one with a lone −Inf."""
    rows = np.zeros((6, 96), np.float32)
    rows[1] = 3e38  # sum overflows to inf, yet every value is finite
    rows[2, :2] = (3e38, -3e38)
    check_finite(rows, 100, "x")
    for r, values in ((3, (np.inf, -np.inf)), (4, (-np.inf, 0.0)), (5, (np.nan, 1.0))):
        bad = rows.copy()
        bad[r, 10:12] = values
        bad[r + 1 :] = np.nan if r < 5 else bad[r + 1 :]
        with pytest.raises(InputError, match=f"x: row {100 + r} holds NaN or Inf"):
            check_finite(bad, 100, "x")


@pytest.mark.parametrize("extra", [-4, 4])
def test_fbin_size_must_match_header(tmp_path, extra):
    path = tmp_path / "bad.fbin"
    body = np.zeros(4 * 96, "<f4").tobytes()
    path.write_bytes(np.array([4, 96], "<u4").tobytes() + body + b"\0" * max(0, extra))
    if extra < 0:
        path.write_bytes(path.read_bytes()[:extra])
    with pytest.raises(InputError, match=r"bad.fbin: header says n = 4, d = 96 .* 1,544 bytes"):
        BinSource(path)


def test_fbin_reads_rows_past_2_31_bytes(tmp_path):
    """A sparse 6M-row fbin: rows whose byte offsets pass 2^31 (and 2^32) are read where they are."""
    n, d = 6_000_000, 96
    path = tmp_path / "big.fbin"
    rows = {5_600_000: 1.5, 5_999_999: -2.25, 11: 3.0}  # 5.6M × 96 × 4 B > 2^31
    with path.open("wb") as f:
        f.write(np.array([n, d], "<u4").tobytes())
        f.truncate(8 + 4 * n * d)  # a hole: the filesystem stores only the rows written below
        for r, v in rows.items():
            f.seek(8 + 4 * r * d)
            f.write(np.full(d, v, "<f4").tobytes())
    src = BinSource(path)
    assert src.n_rows == n and 8 + 4 * 5_600_000 * d > 2**31
    for r, v in rows.items():
        np.testing.assert_array_equal(src.read(r, r + 1), np.full((1, d), v, np.float32))
    np.testing.assert_array_equal(src.read(5_599_999, 5_600_001)[0], np.zeros(d, np.float32))


def test_fingerprint_changes_when_a_file_changes(tmp_path):
    rows = np.ones((50_000, 96), "<f4")
    path = tmp_path / "x.fbin"
    path.write_bytes(np.array([50_000, 96], "<u4").tobytes() + rows.tobytes())
    before = BinSource(path).fingerprint()
    assert BinSource(path).fingerprint() == before
    with path.open("r+b") as f:  # one value in the middle, far from the sampled head and tail
        f.seek(8 + 4 * 96 * 25_000)
        f.write(np.float32(7.0).tobytes())
    later = before["files"][0]["mtime_ns"] + 1_000_000_000  # a write within the clock tick keeps mtime
    os.utime(path, ns=(later, later))
    assert BinSource(path).fingerprint() != before


def test_fas_npz_round_trip(sources):
    tr = open_fas(sources["fas"])
    ref = SyntheticFAS(3, SMALL_FAS).traverse()
    assert (tr.ref.n_rows, tr.query.n_rows, tr.ref.dim) == (3000, 2000, 128)
    np.testing.assert_array_equal(tr.ref.read(0, 3000), ref.ref.read(0, 3000))
    np.testing.assert_array_equal(tr.query.read(1990, 2000), ref.query.read(1990, 2000))
    np.testing.assert_array_equal(tr.gt, ref.gt)


def test_fas_compressed_npz_is_read_through_a_cache(tmp_path, monkeypatch, sources):
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "cache"))
    plain = open_fas(sources["fas"])
    arrays = {f"arr_{i}": a for i, a in enumerate([plain.ref.read(0, 3000), plain.query.read(0, 2000),
                                                    plain.gt, plain.ref_pos, plain.query_pos])}
    np.savez_compressed(tmp_path / "c.npz", **arrays)
    tr = open_fas(tmp_path / "c.npz")
    np.testing.assert_array_equal(tr.query.read(5, 50), arrays["arr_1"][5:50])
    cached = next((tmp_path / "cache").rglob("arr_1.npy"))
    cached.write_bytes(cached.read_bytes()[:1000])  # a kill or a full disk cut the cache file short
    tr = open_fas(tmp_path / "c.npz")  # it is written again, not read short on every run
    np.testing.assert_array_equal(tr.query.read(1990, 2000), arrays["arr_1"][1990:2000])


def _npz(tmp_path, **changes):
    base = {"arr_0": np.zeros((20, 128), "f4"), "arr_1": np.zeros((10, 128), "f4"),
            "arr_2": np.arange(10), "arr_3": np.zeros((20, 3)), "arr_4": np.zeros((10, 3))}
    base.update(changes)
    np.savez(tmp_path / "f.npz", **base)
    return tmp_path / "f.npz"


@pytest.mark.parametrize(("changes", "message"), [
    ({"arr_2": np.arange(10) + 15}, r"arr_2 row 5: ground truth 20 outside \[0, 20\)"),
    ({"arr_2": np.arange(9)}, "arr_2 must be 10 integer ground-truth indices"),
    ({"arr_1": np.zeros((10, 64), "f4")}, "arr_0 has 128 columns but arr_1 has 64"),
    ({"arr_0": np.zeros((20, 128), "f8")}, "arr_0 must be a 2-D float32 array"),
    ({"arr_4": np.zeros((9, 3))}, "arr_4 must hold 10 positions"),
])
def test_fas_validation(tmp_path, changes, message):
    with pytest.raises(InputError, match=message):
        open_fas(_npz(tmp_path, **changes))


def test_a_compressed_member_is_checked_before_it_is_unpacked(tmp_path, monkeypatch):
    """A small compressed ``.npz`` whose descriptor member unpacks to hundreds of MB of the wrong
    shape, or whose ground truth is far longer than the queries, is refused from its headers:
    nothing is unpacked into the cache, nothing that large is loaded."""
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "cache"))
    base = {"arr_0": np.zeros((20, 128), "f4"), "arr_1": np.zeros((10, 128), "f4"), "arr_2": np.arange(10),
            "arr_3": np.zeros((20, 3)), "arr_4": np.zeros((10, 3))}
    np.savez_compressed(tmp_path / "wide.npz", **{**base, "arr_0": np.zeros(50_000_000, "f8")})  # 400 MB in 0.4
    with pytest.raises(InputError, match="arr_0 must be a 2-D float32 array"):
        open_fas(tmp_path / "wide.npz")
    assert not list((tmp_path / "cache").rglob("*.npy")) and not list((tmp_path / "cache").rglob("*.tmp"))
    np.savez_compressed(tmp_path / "long.npz", **{**base, "arr_2": np.zeros(50_000_000, "i8")})
    loaded = []
    monkeypatch.setattr(np, "load", lambda *a, **k: loaded.append(a) or np.zeros(0))
    with pytest.raises(InputError, match="arr_2 must be 10 integer ground-truth indices, got shape"):
        open_fas(tmp_path / "long.npz")
    assert not loaded
    monkeypatch.undo()
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "cache"))
    # the descriptors are fine, another member is not: refused from the headers, arr_0 not unpacked
    big = np.zeros((200_000, 128), "f4")  # 100 MB unpacked
    for name, change, words in (("narrow", {"arr_1": np.zeros((10, 64), "f4")}, "arr_0 has 128 columns but arr_1"),
                                ("poses", {"arr_4": np.zeros((9, 3))}, "arr_4 must hold 10 positions")):
        np.savez_compressed(tmp_path / f"{name}.npz", **{**base, "arr_0": big, "arr_3": np.zeros((200_000, 3)),
                                                        **change})
        with pytest.raises(InputError, match=words):
            open_fas(tmp_path / f"{name}.npz")
        assert not list((tmp_path / "cache").rglob("*.npy")) and not list((tmp_path / "cache").rglob("*.tmp"))


def test_fas_missing_array_and_not_a_zip(tmp_path):
    np.savez(tmp_path / "m.npz", arr_0=np.zeros((2, 2), "f4"))
    with pytest.raises(InputError, match="missing array arr_1"):
        open_fas(tmp_path / "m.npz")
    (tmp_path / "z.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not an .npz"):
        open_fas(tmp_path / "z.npz")


def test_synthetic_rows_do_not_depend_on_how_they_are_read():
    src = SyntheticDeep1B(50_000, seed=9)
    whole = src.read(0, 50_000)
    pieces = np.concatenate([src.read(a, min(50_000, a + 7_777)) for a in range(0, 50_000, 7_777)])
    np.testing.assert_array_equal(whole, pieces)
    # The first rows do not depend on how many rows the source holds.
    np.testing.assert_array_equal(SyntheticDeep1B(1000, seed=9).read(0, 1000), whole[:1000])
    assert not np.array_equal(SyntheticDeep1B(1000, seed=10).read(0, 1000), whole[:1000])


@pytest.mark.parametrize("params", [Deep1BParams(), Deep1BParams(dim=7, n_clusters=500)])
def test_synthetic_rows_read_alone_are_the_whole_block_s(params):
    """A range is drawn from its own sub-blocks with the stream skipped before them: every row
    equals the whole block's, at any offset (an odd width and a cluster count that is not a
    power of two leave half a 64-bit draw buffered at the skip)."""
    src = SyntheticDeep1B(3 * BLOCK + 500, seed=4, params=params)
    whole = src.read(0, src.n_rows)
    for lo, hi in [(BLOCK - 20, BLOCK + 20), (1, 2), (SUB_ROWS - 1, SUB_ROWS + 1), (2 * BLOCK - 1, 3 * BLOCK + 3),
                   (3 * BLOCK + 499, 3 * BLOCK + 500), (5 * SUB_ROWS + 3, 9 * SUB_ROWS)]:
        np.testing.assert_array_equal(src.read(lo, hi), whole[lo:hi], err_msg=f"rows {lo}-{hi}")


def test_synthetic_fas_files_are_byte_identical_for_a_seed(tmp_path):
    a = write_fas_npz(SyntheticFAS(1, SMALL_FAS).traverse(), tmp_path / "a.npz")
    b = write_fas_npz(SyntheticFAS(1, SMALL_FAS).traverse(), tmp_path / "b.npz")
    with zipfile.ZipFile(a) as za, zipfile.ZipFile(b) as zb:
        for name in za.namelist():
            assert za.read(name) == zb.read(name)


def test_synthetic_fas_ground_truth_is_the_nearest_reference_frame():
    fas = SyntheticFAS(2, SMALL_FAS)
    tr = fas.traverse()
    s = fas.positions("query")
    assert np.all(np.abs(s - 5.0 * tr.gt) <= 2.5 + 1e-9)
    assert np.all(np.diff(tr.gt) > -20)  # the query repeats the route in order, up to jitter
