"""Every descriptor form by URL (docs/bring-your-own.md, "Formats"): ``.npy`` (a file, or on
object storage a prefix of shards), an HDF5 dataset and a Parquet list column (a file, or a
prefix of files), over a loopback HTTP server and a loopback S3 endpoint (moto), each written by
its format's own tool (numpy, h5py, pyarrow), read by byte ranges to the rows the same file gives
locally."""

from __future__ import annotations

import io

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main
from vprscale.dataset.sources.rows import open_rows

from .test_fetch import _bytes_server
from .test_objects import BUCKET, endpoint, s3  # noqa: F401 - the loopback S3 endpoint's fixtures

h5py = pytest.importorskip("h5py")


@pytest.fixture(scope="module")
def rows() -> np.ndarray:
    return np.random.default_rng(5).normal(size=(3_000, 24)).astype(np.float32)


def _npy(x: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, x)
    return buf.getvalue()


def _hdf5(x: np.ndarray, path) -> bytes:
    with h5py.File(path, "w") as f:
        f.create_dataset("train", data=x, chunks=(500, x.shape[1]))
        f.create_dataset("test", data=x[:10])
    return path.read_bytes()


def _parquet(x: np.ndarray) -> bytes:
    buf = io.BytesIO()
    table = pa.table({"id": np.arange(len(x)), "emb": pa.FixedSizeListArray.from_arrays(x.ravel(), x.shape[1])})
    pq.write_table(table, buf, row_group_size=700)
    return buf.getvalue()


@pytest.mark.parametrize("form", ["npy", "hdf5", "parquet"])
def test_each_form_by_http_reads_the_rows_it_holds(rows, tmp_path, form):
    data = {"npy": lambda: _npy(rows), "hdf5": lambda: _hdf5(rows, tmp_path / "x.hdf5"),
            "parquet": lambda: _parquet(rows)}[form]()
    for server in _bytes_server(data):
        name = {"npy": "x.npy", "hdf5": "x.hdf5:train", "parquet": "x.parquet:emb"}[form]
        src = open_rows(server.url.rsplit("/", 1)[0] + "/" + name)
        assert (src.n_rows, src.dim) == rows.shape
        np.testing.assert_array_equal(src.read(0, len(rows)), rows)
        np.testing.assert_array_equal(src.read(1_234, 2_345), rows[1_234:2_345])  # across chunks and row groups
        assert src.fingerprint()["rows"] == len(rows)


def test_a_truncated_npy_by_url_is_one_line(rows, capsys):
    for server in _bytes_server(_npy(rows)[:-100]):
        code = main(["build", "--ref", server.url.rsplit("/", 1)[0] + "/x.npy", "--query", "q=x", "--gt", "x",
                     "--out", "/nonexistent"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "a truncated or foreign file" in err and "\n" not in err


def test_shards_and_parquet_files_under_an_s3_prefix_are_one_table(rows, s3):  # noqa: F811 - the fixture
    import boto3

    client = boto3.client("s3", endpoint_url=s3["AWS_ENDPOINT_URL"])
    parts = np.split(rows, [1_000, 1_001, 2_500])  # one shard of a single row
    for i, part in enumerate(parts):  # names whose numbers sort as numbers: 2 before 10
        client.put_object(Bucket=BUCKET, Key=f"shards/emb_{[8, 9, 10, 11][i]}.npy", Body=_npy(part))
        client.put_object(Bucket=BUCKET, Key=f"tables/part-{[8, 9, 10, 11][i]}.parquet", Body=_parquet(part))
    client.put_object(Bucket=BUCKET, Key="shards/README.txt", Body=b"not a shard")
    for url in (f"s3://{BUCKET}/shards", f"s3://{BUCKET}/tables:emb"):
        src = open_rows(url)
        assert (src.n_rows, src.dim) == rows.shape, url
        np.testing.assert_array_equal(src.read(0, len(rows)), rows)
        np.testing.assert_array_equal(src.read(999, 1_002), rows[999:1_002])
