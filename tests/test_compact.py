"""The compact layout: the same addresses, lists and matches as the full layout of the same data."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.core.errors import InputError

from .conftest import write_recipe

LISTS = ("codes.parquet", "lists.parquet", "buckets.parquet")


@pytest.fixture(scope="module")
def compact_store(sources, tmp_path_factory) -> Path:
    """The tiny recipe (the one ``tiny_store`` is built from), in the compact layout."""
    from vprscale.dataset.build import BuildRequest, build

    root = tmp_path_factory.mktemp("compact")
    recipe = write_recipe(root / "tiny.toml")
    build(BuildRequest(scale=str(recipe), out=root / "out", deep1b=str(sources["fbin"]), fas=str(sources["fas"]),
                       workers=2, quiet=True, layout="compact"))
    return root / "out" / "tiny.zarr"


@pytest.fixture(scope="module")
def both_indexes(compact_store, tiny_store, tmp_path_factory) -> tuple[Path, Path]:
    from vprscale.jobs.indexing import build_index

    root = tmp_path_factory.mktemp("indexes")
    compact = Path(build_index(compact_store, out=root / "compact.index", quiet=True)["index"])
    full = Path(build_index(tiny_store, d=16, out=root / "full.index", quiet=True)["index"])
    return compact, full


def test_compact_store_keeps_only_what_is_read(compact_store):
    g = zarr.open_group(compact_store, mode="r")
    assert "ref" not in g and g.attrs["vprscale"]["layout"]["kind"] == "compact"
    n_ref = 50_000 + 2_500
    assert g["ref_hash"].shape == (n_ref,) and g["ref_hash"].dtype == np.uint16  # d = 16
    assert g["ref_err"].dtype == np.float32 and g["base_x1"].shape == (n_ref,)
    frames = g["query_frames"][:]
    assert len(frames) < 52_000 and np.all(np.diff(frames) > 0)  # only the evaluated windows, ascending
    assert g["query_qm1"].shape == (len(frames), 96) == g["query_qm2"].shape


def test_compact_rows_equal_the_full_rows(compact_store, tiny_store):
    """The kept query rows are the full store's rows of the same frames, bit for bit."""
    c, f = zarr.open_group(compact_store, mode="r"), zarr.open_group(tiny_store, mode="r")
    frames = c["query_frames"][:]
    for name in ("query_qm1", "query_qm2"):
        np.testing.assert_array_equal(c[name][:], f[name].get_orthogonal_selection((frames, slice(None))))
    np.testing.assert_array_equal(c["gt"][:], f["gt"][:][frames])
    np.testing.assert_array_equal(c["query_part"][:], f["query_part"][:][frames])


def test_same_addresses_lists_and_model(both_indexes):
    compact, full = both_indexes
    for name in LISTS:
        assert (compact / name).read_bytes() == (full / name).read_bytes(), name
    for name in ("mean", "components", "centres"):
        np.testing.assert_array_equal(np.load(compact / "model" / f"{name}.npy"),
                                      np.load(full / "model" / f"{name}.npy"), err_msg=name)


def test_sample_spans_keep_every_reference_up_to_the_threshold_then_every_s_th_span():
    from vprscale.method.coarsehash import SAMPLE_SPAN, SAMPLE_SPANS, sample_spans

    assert sample_spans(10_000_000) == [(0, 10_000_000)]
    below = (2 * SAMPLE_SPANS - 1) * SAMPLE_SPAN
    assert sample_spans(below) == [(0, below)] and len(sample_spans(below + 1)) == SAMPLE_SPANS
    spans = sample_spans(1_000_047_781)
    starts = np.array([a for a, _ in spans])
    assert len(spans) == 130 and np.all(np.diff(starts) == 59 * SAMPLE_SPAN)
    assert all(b - a == SAMPLE_SPAN for a, b in spans) and sum(b - a for a, b in spans) >= SAMPLE_SPANS * SAMPLE_SPAN


def test_sampled_centres_are_the_sample_s_in_both_layouts(tmp_path, sources, tiny_store, monkeypatch):
    """Beyond the threshold the compact build and the index of a full store fit the centres on
    the same sampled references: the k-means of exactly those rows, and the same lists."""
    from vprscale.dataset.build import BuildRequest, build
    from vprscale.jobs.indexing import build_index
    from vprscale.method import coarsehash

    monkeypatch.setattr(coarsehash, "SAMPLE_SPAN", 16384)
    monkeypatch.setattr(coarsehash, "SAMPLE_SPANS", 2)  # 52,500 references: spans 0 and 2 of 16,384
    assert coarsehash.sample_spans(52_500) == [(0, 16384), (32768, 49152)]
    recipe = write_recipe(tmp_path / "tiny.toml")
    build(BuildRequest(scale=str(recipe), out=tmp_path / "out", deep1b=str(sources["fbin"]), fas=str(sources["fas"]),
                       workers=2, quiet=True, layout="compact"))
    compact = Path(build_index(tmp_path / "out" / "tiny.zarr", out=tmp_path / "c.index", quiet=True)["index"])
    full = Path(build_index(tiny_store, d=16, out=tmp_path / "f.index", quiet=True)["index"])
    for name in LISTS:
        assert (compact / name).read_bytes() == (full / name).read_bytes(), name
    for name in ("model/centres", "model/components"):
        np.testing.assert_array_equal(np.load(compact / f"{name}.npy"), np.load(full / f"{name}.npy"), err_msg=name)

    ref = zarr.open_group(tiny_store, mode="r")["ref"]
    model = {n: np.load(full / "model" / f"{n}.npy") for n in ("mean", "components", "explained_variance")}

    def centres(rows: np.ndarray) -> np.ndarray:
        fitted = coarsehash.CoarseHasher.from_fitted(2, 1 << 14, 52_500, model["mean"], model["components"], None,
                                                     model["explained_variance"])
        return fitted.fit_centres([fitted.column_histogram(rows)]).centres_

    sampled = centres(np.concatenate([ref[0:16384], ref[32768:49152]]))
    np.testing.assert_array_equal(np.load(full / "model" / "centres.npy"), sampled)
    assert not np.array_equal(centres(ref[:]), sampled)  # the sample is not the whole set


@pytest.mark.slow
def test_same_matches(both_indexes, compact_store, tiny_store, sources, tmp_path, small_training):
    """Every method, FAISS codes included (the compact store's references recomputed from its
    sources, the full store's read), answers the same on both layouts (the FAISS codes on an
    evenly spaced 300 of the centres: their search of every held frame was most of this test)."""
    compact, full = both_indexes
    # a flat, an IVF and a transformed code (PCA: OPQ's 50 rotations were a third of this test; test_compare and
    # test_codescore train OPQ)
    compare = ["--compare", "PQ4np", "--compare", "IVF32,PQ4np", "--compare", "PCA32,PQ4x6"]
    files = ["--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"])]
    tables = []
    for store, index, out, extra in ((compact_store, compact, tmp_path / "c", files),
                                     (tiny_store, full, tmp_path / "f", [])):
        assert main(["eval", str(store), str(index), "--L", "1,50", "--noise", "qm1", "--repeats", "1",
                     "--compare-queries", "300", "--out", str(out), *compare, *extra]) == 0
        tables.append(pq.read_table(out / "queries.parquet").to_pandas())
    cols = ["method", "params", "mode", "L", "t", "gt", "match", "score", "n_r", "in_list", "part"]
    assert {"faiss:PQ4np", "faiss:IVF32,PQ4np", "faiss:PCA32,PQ4x6"} < set(tables[0].method)
    assert len(tables[0]) > 1000 and tables[0][cols].equals(tables[1][cols])
    assert (tables[0][tables[0].method == "faiss:PQ4np"].groupby(["L", "mode"], dropna=False).size() == 300).all()


def test_compact_store_from_files_needs_its_sources_to_compare(both_indexes, compact_store, sources, tmp_path,
                                                              capsys):
    out = tmp_path / "e"
    assert main(["eval", str(compact_store), str(both_indexes[0]), "--L", "1", "--compare", "PQ4",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "--deep1b" in err and "compact store built from files" in err and len(err.splitlines()) == 1
    assert main(["eval", str(compact_store), str(both_indexes[0]), "--L", "1", "--compare", "PQ4", "--out", str(out),
                 "--deep1b", str(sources["fbin"]), "--fas", str(sources["fbin"])]) == 2
    err = capsys.readouterr().err.strip()  # a FAS file that is not one: named, one line
    assert "base.fbin: not an .npz" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_compact_store_refuses_what_it_cannot_answer(compact_store, both_indexes, tmp_path, capsys):
    from vprscale.jobs.indexing import build_index

    with pytest.raises(InputError, match="d = 16"):
        build_index(compact_store, d=12, out=tmp_path / "x.index", quiet=True)
    assert main(["eval", str(compact_store), str(both_indexes[0]), "--L", "7", "--out", str(tmp_path / "e")]) == 2
    assert "this compact store holds the query windows of L = [1, 50, 100]" in capsys.readouterr().err
    assert not (tmp_path / "e" / "results.parquet").exists()


COMPACT_ARRAYS = ("ref_hash", "ref_err", "base_x1", "query_qm1", "query_qm2", "query_frames", "gt", "query_part")


def _compact_bytes(path: Path) -> dict[str, bytes]:
    g = zarr.open_group(path, mode="r")
    return {k: g[k][:].tobytes() for k in COMPACT_ARRAYS} | {"model": g["transforms/coarsehash/centres"][:].tobytes()}


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace (installed by .ci/run)")
def test_killed_compact_build_resumes_from_its_checkpoints_to_identical_bytes(tmp_path, sources):
    """Killed in the middle of the moments pass, then of the hashing pass: same bytes as one run.

    strace kills the build as it is about to save a pass's second checkpoint (its first, after
    16 of the 37 chunks, is on disk): the same point on any machine under any load, where a
    test that watched for the file could see a fast build finish first."""
    import subprocess
    import sys

    recipe = write_recipe(tmp_path / "tiny.toml", deep1b_rows_read=600_000, deep1b_rows_kept=600_000,
                          layout="compact")
    cmd = [sys.executable, "-m", "vprscale.cli", "build", "--scale", str(recipe), "--fas", str(sources["fas"]),
           "--out", str(tmp_path / "a"), "--workers", "1"]
    work = tmp_path / "a" / ".tiny.zarr.partial" / ".work"
    renames = "rename,renameat,renameat2"
    for name in ("Deep1B moments", "hash references"):
        killed = subprocess.run([shutil.which("strace"), "-f", "-qq", "-P", str(work / f"{name}.tmp"), "-e",
                                 f"trace={renames}", "-e", f"inject={renames}:signal=KILL:when=2", *cmd],
                                capture_output=True, text=True)
        assert killed.returncode != 0, f"the build was not killed at its second {name} checkpoint"
        assert (work / f"{name}.pass").is_file(), killed.stderr[-2000:]
        assert not (tmp_path / "a" / "tiny.zarr").exists()
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    assert "resumed" in out.stdout
    from vprscale.dataset.build import BuildRequest, build

    build(BuildRequest(scale=str(recipe), out=tmp_path / "b", fas=str(sources["fas"]), workers=2, quiet=True))
    assert _compact_bytes(tmp_path / "a" / "tiny.zarr") == _compact_bytes(tmp_path / "b" / "tiny.zarr")


@pytest.mark.slow
def test_distributed_compact_build_equals_local(compact_store, sources, tmp_path, monkeypatch):
    """On a cluster of worker processes, with a relative --out (the workers do not share our directory)."""
    from distributed import LocalCluster

    from vprscale.dataset.build import BuildRequest, build

    recipe = write_recipe(tmp_path / "tiny.toml")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        monkeypatch.chdir(tmp_path)
        build(BuildRequest(scale=str(recipe), out=Path("d"), deep1b=str(sources["fbin"]), fas=str(sources["fas"]),
                           scheduler=cluster.scheduler_address, quiet=True, layout="compact"))
    assert _compact_bytes(compact_store) == _compact_bytes(tmp_path / "d" / "tiny.zarr")
