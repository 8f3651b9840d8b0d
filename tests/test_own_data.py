"""Your own descriptors as a store (``vprscale build --ref … --query NAME=… --gt …``): every
command reads it, and bad input is one line with nothing written."""

import numpy as np
import pandas as pd
import pytest
import zarr

from vprscale.cli import main


def write_fbin(path, rows):
    """The .fbin layout: uint32 rows and dimensions, then float32 row-major."""
    with open(path, "wb") as fh:
        fh.write(np.array(rows.shape, "<u4").tobytes() + np.ascontiguousarray(rows, "<f4").tobytes())


@pytest.fixture
def own_files(tmp_path):
    """A walk of 6,000 places, seen again by 1,500 frames in two conditions; truth for all but 10."""
    rng = np.random.default_rng(1)
    n, dim = 6_000, 24
    walk = (np.cumsum(rng.normal(size=(n, dim)), axis=0) / 8 + rng.normal(size=(n, dim))).astype(np.float32)
    truth = np.arange(1_000, 2_500)
    files = {"ref": tmp_path / "ref.npy", "day": tmp_path / "day.fbin", "night": tmp_path / "night.npy",
             "gt": tmp_path / "gt.npy", "part": tmp_path / "part.npy"}
    np.save(files["ref"], walk)
    write_fbin(files["day"], walk[truth] + rng.normal(scale=0.3, size=(len(truth), dim)).astype(np.float32))
    np.save(files["night"], (walk[truth] + rng.normal(scale=0.8, size=(len(truth), dim))).astype(np.float64))
    gt = truth.copy()
    gt[:10] = -1
    np.save(files["gt"], gt)
    np.save(files["part"], (np.arange(len(truth)) >= 1_200).astype(np.int64))
    return files


def _build(files, out, *extra):
    return main(["build", "--ref", str(files["ref"]), "--query", f"day={files['day']}",
                 "--query", f"night={files['night']}", "--gt", str(files["gt"]), "--part", str(files["part"]),
                 "--out", str(out), "--name", "walk", "--stride", "5", "--workers", "2", *extra])


def test_own_descriptors_build_index_evaluate_and_query(own_files, tmp_path, capsys):
    out = tmp_path / "data"
    assert _build(own_files, out) == 0
    store = out / "walk.zarr"
    group = zarr.open_group(store, mode="r")
    np.testing.assert_array_equal(group["ref"][:], np.load(own_files["ref"]))
    np.testing.assert_array_equal(group["query_night"][:], np.load(own_files["night"]).astype(np.float32))
    np.testing.assert_array_equal(group["gt"][:], np.load(own_files["gt"]))
    assert main(["index", str(store), "--out", str(tmp_path / "walk.index")]) == 0
    assert main(["eval", str(store), str(tmp_path / "walk.index"), "--noise", "night", "--L", "1,20",
                 "--repeats", "1", "--no-baseline"]) == 0
    res = pd.read_parquet(tmp_path / "walk.index" / "eval" / "results.parquet")
    assert set(res.noise) == {"night"} and set(res.scale) == {"walk"}
    q = pd.read_parquet(tmp_path / "walk.index" / "eval" / "queries.parquet")
    assert (q[q.part == "fas"].t >= 1_200).all() and (q[q.part == "deep1b"].t < 1_200).all()  # --part's 0s, then 1s
    assert (q[(q.L == 20) & (q["mode"] == "aligned")].error <= 5).mean() > 0.9  # the walk is found again
    capsys.readouterr()
    assert main(["sql", str(tmp_path / "walk.index"), "SELECT DISTINCT noise FROM results", "--csv"]) == 0
    assert [w.strip('"') for w in capsys.readouterr().out.split()] == ["noise", "night"]
    assert main(["eval", str(store), str(tmp_path / "walk.index"), "--noise", "dusk", "--out",
                 str(tmp_path / "e2")]) == 2
    assert "no such query set; choose from day, night" in capsys.readouterr().err


@pytest.mark.parametrize("damage, message", [
    ("nan", "night.npy: row 700 holds NaN or Inf"),
    ("gt-length", "gt.npy: 1,499 ground truth values for 1,500 query rows"),
    ("gt-range", "gt.npy: row 3 holds 6000, not a reference row"),
    ("gt-unsigned", "gt.npy: row 5 holds 18446744073709551615, beyond any row number"),
    ("part-order", "part.npy: parts must be 0 for the first query rows, then 1"),
    ("dims", "day.fbin: query rows have 23 dimensions, the references 24"),
])
def test_bad_own_input_is_one_line_and_writes_nothing(own_files, tmp_path, capsys, damage, message):
    if damage == "nan":
        night = np.load(own_files["night"])
        night[700, 5] = np.nan
        np.save(own_files["night"], night)
    elif damage == "gt-length":
        np.save(own_files["gt"], np.load(own_files["gt"])[:-1])
    elif damage == "gt-range":
        gt = np.load(own_files["gt"])
        gt[3] = 6_000
        np.save(own_files["gt"], gt)
    elif damage == "gt-unsigned":  # 2^64 − 1 wrapped to −1 ("no truth"): truths vanished with exit 0
        gt = np.maximum(np.load(own_files["gt"]), 0).astype(np.uint64)
        gt[5] = np.iinfo(np.uint64).max
        np.save(own_files["gt"], gt)
    elif damage == "part-order":
        np.save(own_files["part"], np.load(own_files["part"])[::-1])
    else:
        write_fbin(own_files["day"], np.zeros((1_500, 23), np.float32))
    out = tmp_path / "data"
    assert _build(own_files, out) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "error" in line]
    assert len(err) == 1 and message in err[0], err  # a NaN is found while the rows stream, after progress lines
    assert not (out / "walk.zarr").exists()


def test_an_existing_own_store_is_kept_without_force(own_files, tmp_path, capsys):
    out = tmp_path / "data"
    assert _build(own_files, out) == 0
    before = (out / "walk.zarr" / "manifest.json").read_bytes()
    assert _build(own_files, out) == 2
    assert "already holds a store; --force replaces it" in capsys.readouterr().err
    assert (out / "walk.zarr" / "manifest.json").read_bytes() == before
    assert _build(own_files, out, "--force") == 0


@pytest.mark.parametrize(("rows", "dim"), [(3, 50_000), (300, 40_000), (70_000, 96)])
def test_own_chunks_are_sized_by_bytes_not_rows(rows, dim, tmp_path, capsys):
    """Chunks of at most 32 MiB whatever the width, a power of two of rows (blocks start on chunks),
    and the rows as given."""
    from vprscale.dataset.own import CHUNK_BYTES

    rng = np.random.default_rng(1)
    ref = rng.standard_normal((rows, dim), dtype=np.float32)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "q.npy", ref[::-1].copy())
    np.save(tmp_path / "gt.npy", np.arange(rows)[::-1].copy())
    assert main(["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'q.npy'}", "--gt",
                 str(tmp_path / "gt.npy"), "--name", "w", "--out", str(tmp_path / "data"), "-q"]) == 0
    store = zarr.open_group(tmp_path / "data" / "w.zarr", mode="r")
    chunk = store["ref"].chunks[0]
    assert chunk * dim * 4 <= CHUNK_BYTES and chunk & (chunk - 1) == 0 or chunk == rows
    assert chunk == min(rows, 1 << (CHUNK_BYTES // (4 * dim)).bit_length() - 1)
    assert np.array_equal(store["ref"][:], ref) and np.array_equal(store["query_day"][:], ref[::-1])
    on_disk = sum(f.stat().st_size for f in (tmp_path / "data" / "w.zarr").rglob("*") if f.is_file())
    assert on_disk <= 2 * (ref.nbytes + chunk * dim * 4) + (1 << 20)  # the data, and at most a chunk's padding


def test_an_own_store_larger_than_the_free_disk_is_refused_before_work(own_files, small_filesystem, capsys):
    from .test_reliability import fails

    argv = ["build", "--ref", str(own_files["ref"]), "--query", f"day={own_files['day']}", "--gt",
            str(own_files["gt"]), "--out", str(small_filesystem / "data")]
    fails(capsys, argv, "--out", "GiB free")
    assert not any((small_filesystem / "data").iterdir())
