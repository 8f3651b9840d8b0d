"""Reading a stored array's rows from its raw chunk files agrees with zarr, or falls back to zarr."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from zarr.codecs import ZstdCodec

from vprscale.rawchunks import raw_chunk_dir, rows_of


def stored(tmp_path, compressors=None):
    x = np.random.default_rng(0).normal(size=(1000, 7)).astype(np.float32)
    a = zarr.create_array(tmp_path / "s.zarr", shape=x.shape, chunks=(300, 7), dtype="float32",
                          compressors=compressors, fill_value=0.0)
    a[:] = x
    return a, x


def test_raw_chunks_equal_zarr_including_the_short_last_chunk(tmp_path):
    a, x = stored(tmp_path)
    assert raw_chunk_dir(a) is not None
    got = rows_of(a)
    assert got.chunks[0] == (300, 300, 300, 100)
    np.testing.assert_array_equal(got.compute(), x)


def test_compressed_arrays_are_read_through_zarr(tmp_path):
    a, x = stored(tmp_path, compressors=ZstdCodec())
    assert raw_chunk_dir(a) is None
    np.testing.assert_array_equal(rows_of(a).compute(), x)


def test_a_chunk_left_out_as_fill_reads_as_fill_and_a_short_file_is_an_error(tmp_path):
    a, x = stored(tmp_path)
    directory = raw_chunk_dir(a)
    (directory / "1" / "0").unlink()
    got = rows_of(a).compute()
    np.testing.assert_array_equal(got[300:600], 0.0)
    np.testing.assert_array_equal(got[:300], x[:300])
    (directory / "2" / "0").write_bytes(b"\0" * 12)
    with pytest.raises(OSError, match="2/0: chunk file holds 12 bytes"):
        rows_of(a).compute()


def test_whole_chunk_writes_give_zarrs_bytes_and_partial_writes_go_through_zarr(tmp_path):
    from vprscale.rawchunks import write_rows

    x = np.random.default_rng(1).normal(size=(1000, 7)).astype(np.float32)
    arrays = [zarr.create_array(tmp_path / f"{name}.zarr", shape=x.shape, chunks=(300, 7), dtype="float32",
                                compressors=None, fill_value=0.0) for name in ("direct", "zarr")]
    for start in (0, 300, 600, 900):  # the last chunk holds 100 rows and is stored padded
        write_rows(arrays[0], start, x[start:start + 300])
        arrays[1][start:start + 300] = x[start:start + 300]
    direct, via_zarr = (raw_chunk_dir(a) for a in arrays)
    for i in range(4):
        assert (direct / str(i) / "0").read_bytes() == (via_zarr / str(i) / "0").read_bytes()
    np.testing.assert_array_equal(arrays[0][:], x)
    write_rows(arrays[0], 10, x[:5] + 1)  # part of a chunk: through zarr, the rest kept
    np.testing.assert_array_equal(arrays[0][10:15], x[:5] + 1)
    np.testing.assert_array_equal(arrays[0][:10], x[:10])
    assert not list(raw_chunk_dir(arrays[0]).rglob("*.tmp"))


def test_an_oversized_chunk_file_is_an_error(tmp_path):
    a, x = stored(tmp_path)
    f = raw_chunk_dir(a) / "0" / "0"
    f.write_bytes(f.read_bytes() + b"\0" * 4)
    with pytest.raises(OSError, match="0/0: chunk file holds 8404 bytes, expected 8400"):
        rows_of(a).compute()
