"""The package's floors (docs/architecture.md) and the one owner of the index format."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import grimp
import numpy as np
import pyarrow.parquet as pq
import pytest

from vprscale.method.coarsehash import CoarseHasher
from vprscale.method.index import Index, read_index, write_index

ROOT = Path(__file__).resolve().parents[1]


def test_floors_contract_holds():
    """import-linter's layers contract in pyproject.toml: no floor imports a floor above it
    (function-level imports included)."""
    beside = Path(sys.executable).parent / "lint-imports"  # this environment's, activated or not
    done = subprocess.run([str(beside) if beside.is_file() else "lint-imports", "--config",
                           str(ROOT / "pyproject.toml")], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout


def test_no_module_imports_itself_through_another():
    graph = grimp.build_graph("vprscale")
    cycles = sorted({tuple(sorted((m, n))) for m in graph.modules for n in graph.find_modules_directly_imported_by(m)
                     if graph.chain_exists(importer=n, imported=m)})
    assert cycles == []


def test_method_floor_holds_no_store_job_or_lock():
    """method/ is the pure method: no Zarr store, no Dask cluster, no lock, no progress of a job."""
    graph = grimp.build_graph("vprscale", "zarr", "distributed", "filelock")
    method = graph.find_descendants("vprscale.method") | {"vprscale.method"}
    for name in method:
        imported = graph.find_modules_directly_imported_by(name)
        bad = {m for m in imported if m.split(".")[0] in ("zarr", "distributed", "filelock")
               or m in ("vprscale.core.cluster", "vprscale.core.zarrio", "vprscale.core.passes")}
        assert not bad, f"{name} imports {sorted(bad)}"


def test_import_leaves_the_environment_alone():
    code = ("import os; before = dict(os.environ); import vprscale; from vprscale import Index; "
            "print(dict(os.environ) == before)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT)
    assert done.stdout.strip() == "True", done.stderr


def test_index_build_equals_the_index_job(tiny_store, tiny_index):
    """``Index.build(ref)`` in memory gives the addresses, lists and single bests the
    ``vprscale index`` job writes for the same store."""
    import zarr

    job = read_index(tiny_index)
    ref = zarr.open_group(tiny_store, mode="r")["ref"][:]
    built = Index.build(ref, d=12, k=2)
    np.testing.assert_array_equal(built.codes, job.codes)
    np.testing.assert_array_equal(built.lists.ids, job.lists.ids)
    for part in ("occupied", "starts"):
        np.testing.assert_array_equal(getattr(built.lists, part).words(), getattr(job.lists, part).words(),
                                      err_msg=part)
    # the job's PCA comes from moments the build summed while writing the rows, this one from
    # the rows themselves: the centres agree to float rounding, the lists exactly
    np.testing.assert_allclose(built.centres, job.centres, rtol=1e-6)
    again = Index.build(ref, hasher=built.hasher)
    np.testing.assert_array_equal(again.lists.ids, built.lists.ids)
    assert f"n_ref={len(ref):,}" in repr(built) and len(repr(built)) < 200


def test_build_refuses_d_with_a_fitted_hasher():
    ref = np.random.default_rng(0).standard_normal((256, 8))
    hasher = CoarseHasher(d=4).fit(ref)
    with pytest.raises(ValueError, match="either d and k or a fitted hasher"):
        Index.build(ref, d=5, hasher=hasher)


def test_from_addresses_needs_one_error_per_address():
    hasher = CoarseHasher(d=2).fit(np.random.default_rng(0).standard_normal((64, 4)))
    with pytest.raises(ValueError, match="one per address"):
        Index.from_addresses(np.array([0, 1, 2], np.uint64), hasher, np.zeros(2))


def test_saved_index_is_the_job_format_and_every_command_reads_it(tiny_store, tiny_index, tmp_path, capsys):
    """An ``Index.save`` copy holds the files the index job writes, with equal bytes for the
    lists, and works with sql, occupancy, eval and localise."""
    from vprscale.cli import main

    original = tiny_index
    copy = tmp_path / "copy.index"
    Index.load(original).save(copy)
    written = {p.relative_to(original).as_posix() for p in original.rglob("*") if p.is_file()}
    assert {p.relative_to(copy).as_posix() for p in copy.rglob("*") if p.is_file()} == written
    for name in ("codes", "lists", "buckets"):
        assert (copy / f"{name}.parquet").read_bytes() == (original / f"{name}.parquet").read_bytes(), name
    for name in ("mean", "components", "centres", "explained_variance"):
        assert (copy / "model" / f"{name}.npy").read_bytes() == (original / "model" / f"{name}.npy").read_bytes()
    for table in ("components",):
        assert pq.read_table(copy / f"{table}.parquet").equals(pq.read_table(original / f"{table}.parquet")), table
    assert json.loads((copy / "index.json").read_text())["store"] == json.loads(
        (original / "index.json").read_text())["store"]

    n_ref = read_index(original).n_ref
    assert main(["sql", str(copy), "SELECT count(*) AS n FROM lists", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["n"] == n_ref
    assert main(["occupancy", str(copy), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["occupied"] == read_index(original).occupied
    matches = []
    for idx in (original, copy):
        out = tmp_path / f"ev-{idx.name}"
        assert main(["eval", str(tiny_store), str(idx), "--noise", "qm1", "--L", "1,50", "--modes", "paper",
                     "--no-baseline", "--repeats", "1", "--out", str(out), "-q"]) == 0
        matches.append(pq.read_table(out / "queries.parquet").to_pandas())
    assert len(matches[0]) > 0
    np.testing.assert_array_equal(matches[0].match.to_numpy(), matches[1].match.to_numpy())
    assert main(["localise", str(copy), str(tiny_store / "query_qm1"), "--L", "50", "--out",
                 str(tmp_path / "m.parquet"), "-q"]) == 0
    assert pq.read_table(tmp_path / "m.parquet").num_rows > 0


def test_saving_over_something_else_is_refused(tmp_path):
    hasher = CoarseHasher(d=3).fit(np.random.default_rng(0).standard_normal((128, 4)))
    idx = Index.build(np.random.default_rng(1).standard_normal((128, 4)), hasher=hasher)
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not an index directory"):
        write_index(idx, tmp_path / "x")
    assert (tmp_path / "x" / "keep.txt").read_text() == "mine"
    write_index(idx, tmp_path / "y")
    again = read_index(tmp_path / "y")
    np.testing.assert_array_equal(again.lists.ids, idx.lists.ids)
    np.testing.assert_array_equal(again.codes, idx.codes)
    shutil.rmtree(tmp_path / "y")


CALLED: list = []


def test_the_grid_asks_the_registry(tiny_store, tiny_index, tmp_path, capsys, monkeypatch):
    """``vprscale methods`` lists the registry; an installed package's entry point joins it, and
    the evaluation grid calls its factory like the built-in ones'."""
    from importlib.metadata import EntryPoint

    import vprscale.evaluation.algorithms.registry as registry
    from vprscale.cli import main

    plugin = EntryPoint("mine", "tests.test_architecture:_record_context", registry.ENTRY_POINT_GROUP)
    monkeypatch.setattr(registry, "entry_points", lambda group: [plugin] if group == registry.ENTRY_POINT_GROUP else [])
    assert main(["methods"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out[1:]] == ["coarsehash", "baseline", "faiss:FACTORY", "seq:FACTORY",
                                                        "CLASS", "mine"]
    assert "--compare FACTORY" in out[3] and "--compare seq:FACTORY" in out[4]
    assert "--method package.module:Class" in out[5]
    assert "installed factory tests.test_architecture:_record_context" in out[6]
    CALLED.clear()
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1", "--no-baseline",
                 "--repeats", "1", "--out", str(tmp_path / "e")]) == 0
    assert [c.index_path for c in CALLED] == [tiny_index] and CALLED[0].baseline is None


def _record_context(context) -> list:
    CALLED.append(context)
    return []
