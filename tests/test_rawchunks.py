"""Reading a stored array's rows from its raw chunk files agrees with zarr, or falls back to zarr."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from zarr.codecs import ZstdCodec

from vprscale.core.errors import InputError
from vprscale.core.zarrio import raw_chunk_dir, rows_of


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
    with pytest.raises(InputError, match="2/0: chunk file holds 12 bytes"):
        rows_of(a).compute()


def test_whole_chunk_writes_give_zarrs_bytes_and_partial_writes_go_through_zarr(tmp_path):
    from vprscale.core.zarrio import write_rows

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
    with pytest.raises(InputError, match="0/0: chunk file holds 8,404 bytes, expected 8,400"):
        rows_of(a).compute()


def _fallbacks(tmp_path):
    """Arrays the raw path must not touch, each with its data."""
    from zarr.codecs import BytesCodec
    from zarr.storage import MemoryStore

    x = np.random.default_rng(2).normal(size=(1000, 8)).astype(np.float32)
    layouts = {
        "zstd": dict(compressors=ZstdCodec()),
        "sharded": dict(shards=(600, 8), compressors=None),
        "column chunks": dict(chunks=(300, 4), compressors=None),
        "big-endian": dict(serializer=BytesCodec(endian="big"), compressors=None),
        "v2 chunk keys": dict(chunk_key_encoding={"name": "v2", "separator": "."}, compressors=None),
        "memory store": dict(compressors=None),
    }
    for name, kw in layouts.items():
        store = MemoryStore() if name == "memory store" else tmp_path / f"{name.replace(' ', '_')}.zarr"
        chunks = kw.pop("chunks", (300, 8))
        a = zarr.create_array(store, shape=x.shape, chunks=chunks, dtype="float32", fill_value=0.0, **kw)
        a[:] = x
        yield name, a, x


def test_every_other_layout_falls_back_to_zarr(tmp_path):
    from vprscale.core.zarrio import write_rows

    for name, a, x in _fallbacks(tmp_path):
        assert raw_chunk_dir(a) is None, name
        np.testing.assert_array_equal(rows_of(a).compute(), x, err_msg=name)
        write_rows(a, 0, x[:300] * 2)
        np.testing.assert_array_equal(a[:300], x[:300] * 2, err_msg=name)


def test_an_unpadded_edge_chunk_is_read_as_it_is(tmp_path):
    a, x = stored(tmp_path)
    edge = raw_chunk_dir(a) / "3" / "0"
    edge.write_bytes(x[900:].tobytes())  # 100 rows, not padded to 300 (as some writers store it)
    np.testing.assert_array_equal(rows_of(a).compute(), x)
