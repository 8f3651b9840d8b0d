"""Every descriptor format vprscale reads, each written by its own reference tool (numpy, h5py,
pyarrow; the bin and vecs forms by their published layouts, with numpy), read as the same rows;
an own-data store built from any of them is the same bytes; each form's damage is one line."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main
from vprscale.core.errors import InputError
from vprscale.dataset.sources.rows import open_rows, read_labels

N, D = 3000, 24


@pytest.fixture(scope="module")
def rows() -> np.ndarray:
    """Integer-valued rows (exact in every value type) of a drifting route, so a store of them localises."""
    rng = np.random.default_rng(7)
    route = np.cumsum(rng.integers(-3, 4, size=(N, D)), axis=0)
    return np.clip(route - route.min(), 0, 120).astype(np.float32)


def _bin(path: Path, x: np.ndarray, dtype: str) -> Path:
    """big-ann-benchmarks' layout: uint32 n, uint32 d, then the values row-major."""
    with open(path, "wb") as f:
        np.array(x.shape, "<u4").tofile(f)
        x.astype(dtype).tofile(f)
    return path


def _vecs(path: Path, x: np.ndarray, dtype: str) -> Path:
    """TEXMEX's layout: each record an int32 dimension, then the values."""
    head = np.full((len(x), 1), x.shape[1], "<i4").view("u1")
    body = x.astype(dtype).view("u1").reshape(len(x), -1)
    np.concatenate([head, body], axis=1).tofile(path)
    return path


def _write(form: str, x: np.ndarray, where: Path) -> str:
    """``x`` in ``form`` under ``where``; returns how vprscale is told to read it."""
    where.mkdir()
    if form == "npy":
        np.save(where / "x.npy", x.astype(np.float16))
        return str(where / "x.npy")
    if form == "npy shards":  # numbered as writers number them: 2 before 10
        for i, part in enumerate(np.array_split(x, 11)):
            np.save(where / f"emb_{i}.npy", part)
        return str(where)
    if form in ("fbin", "f16bin", "u8bin", "i8bin"):
        dtype = {"fbin": "<f4", "f16bin": "<f2", "u8bin": "u1", "i8bin": "i1"}[form]
        return str(_bin(where / f"x.{form}", x - (60 if form == "i8bin" else 0), dtype))
    if form in ("fvecs", "bvecs"):
        return str(_vecs(where / f"x.{form}", x, "<f4" if form == "fvecs" else "u1"))
    if form == "hdf5":
        with h5py.File(where / "x.hdf5", "w") as f:
            f.create_dataset("train", data=x, chunks=(700, D))
            f.create_dataset("test", data=x[:10])
        return f"{where / 'x.hdf5'}:train"
    if form == "parquet list":
        pq.write_table(pa.table({"id": np.arange(N), "emb": pa.array(list(x))}), where / "x.parquet",
                       row_group_size=700)
        return f"{where / 'x.parquet'}:emb"
    if form == "parquet fixed dir":  # a directory of files, a fixed-size list column
        for i, part in enumerate(np.array_split(x, 3)):
            values = pa.FixedSizeListArray.from_arrays(pa.array(part.ravel(), pa.float32()), D)
            pq.write_table(pa.table({"emb": values}), where / f"part-{i}.parquet", row_group_size=400)
        return str(where)
    raise AssertionError(form)


FORMS = ["npy", "npy shards", "fbin", "f16bin", "u8bin", "i8bin", "fvecs", "bvecs", "hdf5", "parquet list",
         "parquet fixed dir"]


@pytest.mark.parametrize("form", FORMS)
def test_every_format_reads_the_same_rows(rows, tmp_path, form):
    src = open_rows(_write(form, rows, tmp_path / "f"))
    want = rows - (60 if form == "i8bin" else 0)
    assert (src.n_rows, src.dim) == (N, D)
    np.testing.assert_array_equal(src.read(0, N), want)
    np.testing.assert_array_equal(src.read(1234, 2345), want[1234:2345])  # across shards, files and row groups
    np.testing.assert_array_equal(src.take(np.array([2999, 0, 1500])), want[[2999, 0, 1500]])
    assert src.fingerprint()["rows"] == N


def test_a_store_is_the_same_bytes_from_any_format(rows, tmp_path):
    """The same rows in HDF5 and in Parquet shards, beside .npy: the same own-data store."""
    gt = tmp_path / "gt.npy"
    np.save(gt, np.arange(N))
    stores = {}
    for form in ("npy", "hdf5", "parquet fixed dir"):
        spec = _write(form if form != "npy" else "npy shards", rows, tmp_path / form.replace(" ", "-"))
        out = tmp_path / f"out-{form.replace(' ', '-')}"
        assert main(["build", "--ref", spec, "--query", f"q={spec}", "--gt", str(gt), "--out", str(out),
                     "--name", "own", "--quiet"]) == 0
        (store,) = out.glob("*.zarr")
        stores[form] = {p.relative_to(store).as_posix(): p.read_bytes() for p in sorted(store.rglob("*"))
                        if p.is_file() and "c/" in p.relative_to(store).as_posix()}
    assert stores["npy"] and stores["npy"] == stores["hdf5"] == stores["parquet fixed dir"]


def test_ground_truth_from_ibin_and_ivecs_is_the_first_neighbour(tmp_path):
    ids = np.random.default_rng(0).integers(0, 1 << 30, size=(50, 10)).astype("<i4")
    dist = np.random.default_rng(1).random((50, 10)).astype("<f4")
    with open(tmp_path / "gt.ibin", "wb") as f:  # big-ann-benchmarks: ids, then distances
        np.array(ids.shape, "<u4").tofile(f)
        ids.tofile(f)
        dist.tofile(f)
    _vecs(tmp_path / "gt.ivecs", ids, "<i4")
    for name in ("gt.ibin", "gt.ivecs"):
        np.testing.assert_array_equal(read_labels(tmp_path / name, 50, "--gt"), ids[:, 0])
    with pytest.raises(InputError, match=r"gt.ibin: .*50 values for 40 query rows|gt.ibin: 50 --gt values"):
        read_labels(tmp_path / "gt.ibin", 40, "--gt")
    # records of differing k whose sizes still add up to whole records of the first k: refused, not shifted
    with open(tmp_path / "mixed.ivecs", "wb") as f:
        for k, rows in ((10, ids[:2]), (4, ids[2:5, :4]), (6, ids[5:6, :6])):  # 3 × 20 + 28 bytes: 2 records
            for row in rows:
                np.r_[k, row].astype("<i4").tofile(f)
        for row in ids[7:]:
            np.r_[10, row].astype("<i4").tofile(f)
    assert (tmp_path / "mixed.ivecs").stat().st_size % 44 == 0
    with pytest.raises(InputError, match=r"mixed.ivecs: offset 88: a record of k = 4, the first holds 10"):
        read_labels(tmp_path / "mixed.ivecs", 50, "--gt")


@pytest.mark.parametrize(("form", "damage", "message"), [
    ("u8bin", "truncate", r"x.u8bin: header says n = 3000, d = 24 \(a file of 72,008 bytes\) but the file has"),
    ("bvecs", "truncate", r"x.bvecs: size .* is not a multiple of the record size 28"),
    ("parquet list", "ragged", r"x.parquet:emb: row 1700 holds 23 values, the rows before it 24"),
    ("npy shards", "width", r"emb_10.npy: rows of 23 values, the shards before it 24"),
    ("hdf5", "key", r"x.hdf5:train: no dataset 'train' in the file \(it holds other\)"),
    ("fbin", "nan", r"x.fbin: row 2021 holds NaN or Inf"),
])
def test_damage_is_one_line_naming_file_and_row(rows, tmp_path, form, damage, message):
    spec = _write(form, rows, tmp_path / "f")
    path = Path(spec.rsplit(":", 1)[0]) if form in ("hdf5", "parquet list") else Path(spec)
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:-3])
    elif damage == "ragged":
        bad = [list(r) for r in rows]
        bad[1700] = bad[1700][:-1]
        pq.write_table(pa.table({"emb": pa.array(bad, pa.list_(pa.float32()))}), path, row_group_size=700)
    elif damage == "width":
        np.save(path / "emb_10.npy", rows[:5, :-1])
    elif damage == "key":
        path.unlink()
        with h5py.File(path, "w") as f:
            f.create_dataset("other", data=rows)
    elif damage == "nan":
        x = rows.copy()
        x[2021, 5] = np.nan
        _bin(path, x, "<f4")
    with pytest.raises(InputError, match=message):
        open_rows(spec).read(0, N)


@pytest.mark.parametrize("form", ["u8bin", "f16bin", "bvecs"])
def test_the_bin_and_vecs_forms_read_by_url_as_from_a_file(rows, tmp_path, form):
    """Served by a loopback HTTP server, read by byte ranges: the rows of the local file."""
    from .test_fetch import Server

    local = Path(_write(form, rows, tmp_path / "f"))
    data = local.read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    try:
        src = open_rows(server.url.rsplit("/", 1)[0] + f"/x.{form}")
        np.testing.assert_array_equal(src.read(0, N), open_rows(local).read(0, N))
        assert src.fingerprint()["format"] == form
    finally:
        server.close()


@pytest.mark.parametrize("form", ["npy", "npy shards", "u8bin", "fvecs", "hdf5", "parquet list"])
def test_a_relative_path_is_read_from_any_working_directory(rows, tmp_path, monkeypatch, form):
    """A source named by a relative path reads the same rows where its tasks run in another
    directory, as a cluster's workers do (never a missing file, never another file)."""
    spec = _write(form, rows, tmp_path / "f")
    monkeypatch.chdir(tmp_path)
    path, sep, key = spec.rpartition(":") if form in ("hdf5", "parquet list") else (spec, "", "")
    src = open_rows(f"{Path(path).relative_to(tmp_path)}{sep}{key}")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    np.testing.assert_array_equal(src.read(0, N), rows)


def _external_storage(f, secret: Path) -> None:
    f.create_dataset("train", shape=(2, 8), dtype="u1", external=[(str(secret), 0, 16)])


def _virtual(f, secret: Path) -> None:
    with h5py.File(secret.with_suffix(".hdf5"), "w") as other:
        other["rows"] = np.ones((4, 8), np.float32)
    layout = h5py.VirtualLayout(shape=(4, 8), dtype=np.float32)
    layout[:] = h5py.VirtualSource(str(secret.with_suffix(".hdf5")), "rows", shape=(4, 8))
    f.create_virtual_dataset("train", layout)


def _external_link(f, secret: Path) -> None:
    with h5py.File(secret.with_suffix(".hdf5"), "w") as other:
        other.create_group("g")["rows"] = np.ones((4, 8), np.float32)
    f["train"] = h5py.ExternalLink(str(secret.with_suffix(".hdf5")), "/g/rows")


def _linked_group(f, secret: Path) -> None:
    with h5py.File(secret.with_suffix(".hdf5"), "w") as other:
        other.create_group("g")["train"] = np.ones((4, 8), np.float32)
    f["group"] = h5py.ExternalLink(str(secret.with_suffix(".hdf5")), "/g")


@pytest.mark.parametrize("plant, key, words", [
    (_external_storage, "train", "external raw files"),
    (_virtual, "train", "virtual dataset"),
    (_external_link, "train", "external link"),
    (_linked_group, "group/train", "external link"),
])
def test_an_hdf5_file_reads_nothing_outside_itself(tmp_path, plant, key, words):
    """External storage, a virtual dataset or an external link would make the named file read
    another (an environment, a key, any file the user can read) into a store: each is refused."""
    secret = tmp_path / "secret"
    secret.write_bytes(b"AWS_SECRET_ACCESS_KEY=abcdefgh")
    with h5py.File(tmp_path / "x.hdf5", "w") as f:
        plant(f, secret)
    with pytest.raises(InputError, match=words):
        open_rows(f"{tmp_path / 'x.hdf5'}:{key}")


def _fvecs_chunks(x: np.ndarray, where: Path) -> Path:
    where.mkdir()
    for i, part in enumerate(np.array_split(x, 3)):
        _vecs(where / f"base_{i:02d}", part, "<f4")
    return where


@pytest.mark.parametrize("damage, words", [
    ("dangling link", "a symbolic link to nothing"),
    ("link loop", "a loop of links"),
    ("folder", "not a file"),
    ("gap", "chunk base_01 is missing"),
])
def test_a_chunk_folder_with_a_chunk_missing_is_refused_not_read_short(rows, tmp_path, damage, words):
    """A chunk that cannot be read, or a gap in the chunks' numbering, would shift every later row
    (and every truth id pointing past it) onto another row: refused, naming the chunk."""
    folder = _fvecs_chunks(rows, tmp_path / "fvecs")
    assert open_rows(str(folder)).n_rows == N
    middle = folder / "base_01"
    middle.unlink()
    if damage == "dangling link":
        middle.symlink_to(tmp_path / "nowhere")
    elif damage == "link loop":
        middle.symlink_to(middle)
    elif damage == "folder":
        middle.mkdir()
    with pytest.raises(InputError, match=words):
        open_rows(str(folder))


@pytest.mark.parametrize("form, gone, words", [
    ("npy shards", "emb_4.npy", "chunk emb_4.npy is missing"),
    ("parquet fixed dir", "part-1.parquet", "chunk part-1.parquet is missing"),
])
def test_shards_with_a_gap_in_their_numbering_are_refused(rows, tmp_path, form, gone, words):
    spec = _write(form, rows, tmp_path / "f")
    (tmp_path / "f" / gone).unlink()
    with pytest.raises(InputError, match=words):
        open_rows(spec)


def test_hdf5_ground_truth_and_an_hdf5_file_of_one_dataset(rows, tmp_path):
    """ann-benchmarks keeps the truth beside the vectors (``neighbors``, n × k, nearest first): it
    is read as ``--gt FILE.hdf5:neighbors``, its first column. A file of one 2-D dataset is read
    without naming it, as a Parquet file of one list column is; one of several says which it holds."""
    ids = np.random.default_rng(0).integers(0, 1000, size=(50, 10)).astype(np.int32)
    with h5py.File(tmp_path / "ann.hdf5", "w") as f:
        f["train"], f["test"], f["neighbors"] = rows, rows[:50], ids
    np.testing.assert_array_equal(read_labels(f"{tmp_path / 'ann.hdf5'}:neighbors", 50, "--gt"), ids[:, 0])
    with pytest.raises(InputError, match="ann.hdf5:train: an integer dataset of ids"):
        read_labels(f"{tmp_path / 'ann.hdf5'}:train", 50, "--gt")
    with pytest.raises(InputError, match="name the dataset of descriptors .* 2-D datasets: neighbors, test, train"):
        open_rows(str(tmp_path / "ann.hdf5"))
    with h5py.File(tmp_path / "one.hdf5", "w") as f:
        f["emb"] = rows
    src = open_rows(str(tmp_path / "one.hdf5"))
    assert src.name.endswith("one.hdf5:emb") and src.n_rows == N
    np.testing.assert_array_equal(src.read(0, 10), rows[:10])
