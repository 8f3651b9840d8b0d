"""Never a wrong answer with exit 0: cluster paths, damaged outputs, outputs over inputs,
stale outputs, blank inputs, symlinks, leftovers and caps (one line, exit 2, nothing lost)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main
from vprscale.core.errors import InputError
from vprscale.core.publish import PartialOutput
from vprscale.method.index import read_index

from .conftest import write_recipe


def fails(capsys, argv: list[str], *words: str) -> str:
    """The command exits 2 with one line naming what is wrong (after any progress lines)."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    last = err.splitlines()[-1]
    for w in words:
        assert w in last, last
    return last


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture
def store_copy(tiny_store, tmp_path) -> Path:
    copy = tmp_path / "copy.zarr"
    shutil.copytree(tiny_store, copy)
    return copy


def test_a_missing_chunk_is_an_error_naming_it_never_zeros(store_copy, tmp_path, capsys):
    chunk = store_copy / "ref" / "c" / "1" / "0"
    chunk.unlink()
    fails(capsys, ["index", str(store_copy), "--out", str(tmp_path / "i")], str(chunk), "missing")
    assert not (tmp_path / "i").exists()
    import zarr

    from vprscale.core.zarrio import rows_of
    from vprscale.dataset.store import ATTR

    group = zarr.open_group(store_copy, mode="r")
    assert group.attrs[ATTR]["complete"]
    with pytest.raises(InputError, match="a chunk of a complete array is missing"):
        rows_of(group["ref"]).compute()


def test_overwritten_chunk_and_permuted_ids_are_caught(store_copy, tiny_store, tiny_index, tmp_path, capsys):
    chunk = store_copy / "ref" / "c" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[:4] = np.float32(np.nan).tobytes()  # a NaN in place: same size
    chunk.write_bytes(bytes(data))
    fails(capsys, ["index", str(store_copy), "--out", str(tmp_path / "i")], str(chunk), "content changed")
    fails(capsys, ["verify", str(store_copy)], str(chunk), "content changed")
    index = tmp_path / "copy.index"
    shutil.copytree(tiny_index, index)
    lists = pq.read_table(index / "lists.parquet")  # the ids permuted, the file rewritten to its very size
    ids = np.random.default_rng(0).permutation(lists["ref_id"].to_numpy())
    _rewrite_same_size(index / "lists.parquet", lists.set_column(1, "ref_id", pa.array(ids, pa.uint32())))
    fails(capsys, ["eval", str(tiny_store), str(index), "--L", "1", "--out", str(tmp_path / "e")],
          "lists.parquet", "content changed")
    fails(capsys, ["localise", str(index), str(tiny_store / "query_qm1")], "lists.parquet", "content changed")
    assert not (tmp_path / "e").exists()
    assert main(["verify", str(tiny_index)]) == 0
    assert "verified" in capsys.readouterr().out


def _rewrite_same_size(path: Path, table: pa.Table) -> None:
    """``table`` written over ``path`` uncompressed, cut or padded to the file's size: what a same-size
    edit leaves (only the checksum tells)."""
    size = path.stat().st_size
    pq.write_table(table, path, compression="none")
    data = path.read_bytes()
    path.write_bytes(data[:size].ljust(size, b"\0"))


def test_truncated_and_deleted_index_files_are_one_line(tiny_index, tmp_path, capsys):
    index = tmp_path / "copy.index"
    shutil.copytree(tiny_index, index)
    (index / "buckets.parquet").write_bytes((index / "buckets.parquet").read_bytes()[:-8])
    fails(capsys, ["occupancy", str(index)], "buckets.parquet", "bytes, its manifest says")
    (index / "buckets.parquet").unlink()
    fails(capsys, ["sql", str(index), "SELECT 1"], "buckets.parquet", "missing")


@pytest.mark.parametrize("case", ["localise-ids", "localise-zarr-json", "index-summary-store", "build-summary-source",
                                  "eval-into-store"])
def test_no_output_over_an_input(case, tiny_store, tiny_index, sources, tmp_path, capsys):
    store, index = tmp_path / "s.zarr", tmp_path / "i.index"
    shutil.copytree(tiny_store, store)
    shutil.copytree(tiny_index, index)
    fbin = tmp_path / "d.fbin"
    shutil.copy(sources["fbin"], fbin)
    argv, target = {
        "localise-ids": (["localise", str(index), str(store / "query_qm1"), "--out", str(index / "lists.parquet")],
                         index / "lists.parquet"),
        "localise-zarr-json": (["localise", str(index), str(fbin), "--out", str(store / "zarr.json")],
                               store / "zarr.json"),
        "index-summary-store": (["index", str(store), "--out", str(tmp_path / "new.index"), "--summary",
                                 str(store / "zarr.json")], store / "zarr.json"),
        "build-summary-source": (["build", "--scale", str(write_recipe(tmp_path / "r.toml")), "--deep1b", str(fbin),
                                  "--fas", str(sources["fas"]), "--out", str(tmp_path / "o"), "--summary", str(fbin)],
                                 fbin),
        "eval-into-store": (["eval", str(store), str(index), "--out", str(store / "ev")], store / "ev"),
    }[case]
    before = target.read_bytes() if target.is_file() else None
    fails(capsys, argv, "would write" if case != "localise-zarr-json" else "lies inside")
    assert (target.read_bytes() if target.is_file() else None) == before
    assert not (tmp_path / "new.index").exists() and not (tmp_path / "o").exists()


def test_a_complete_store_of_other_sources_is_refused(tmp_path, sources, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml")
    args = ["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
            "--out", str(tmp_path / "out")]
    assert main(args) == 0
    before = _tree(tmp_path / "out" / "tiny.zarr")
    other = write_recipe(tmp_path / "tiny.toml", seed=9)
    assert other.exists()
    fails(capsys, args, "is a complete store of other recipe", "--force")
    assert _tree(tmp_path / "out" / "tiny.zarr") == before


def test_blank_fas_descriptors_are_refused(tmp_path, sources, capsys):
    bad = tmp_path / "fas.npz"
    with zipfile.ZipFile(sources["fas"]) as src, np.load(sources["fas"]) as arrays, zipfile.ZipFile(bad, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename in ("arr_0.npy", "arr_1.npy"):
                import io

                buf = io.BytesIO()
                np.save(buf, np.zeros_like(arrays[info.filename[:-4]]))
                data = buf.getvalue()
            dst.writestr(info, data)
    recipe = write_recipe(tmp_path / "tiny.toml")
    fails(capsys, ["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(bad),
                   "--out", str(tmp_path / "out")], "arr_0", "all equal")
    assert not (tmp_path / "out" / "tiny.zarr").exists()


def test_localise_refuses_a_nan_frame_and_an_impossible_length(tiny_index, tmp_path, capsys):
    frames = np.random.default_rng(0).standard_normal((300, 96)).astype(np.float32)
    frames[123, 5] = np.nan
    np.save(tmp_path / "q.npy", frames)
    fails(capsys, ["localise", str(tiny_index), str(tmp_path / "q.npy"), "--L", "5"], "frame 123", "NaN")
    fails(capsys, ["localise", str(tiny_index), str(tmp_path / "q.npy"), "--L", "1000000000"],
          "--L 1000000000", "longer than the 300 frames")


@pytest.mark.parametrize("dangling", [False, True])
def test_a_symlinked_output_is_refused_not_wedged(dangling, tmp_path, sources, capsys):
    recipe = write_recipe(tmp_path / "tiny.toml")
    out = tmp_path / "out"
    out.mkdir()
    real = tmp_path / "elsewhere.zarr"
    if not dangling:
        real.mkdir()
        (real / "keep.txt").write_text("mine")
    (out / "tiny.zarr").symlink_to(real)
    args = ["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
            "--out", str(out), "--force"]
    for _ in range(2):  # the same clear message every time, never a wedge
        fails(capsys, args, "symbolic link", "remove the link")
    assert dangling or (real / "keep.txt").read_text() == "mine"
    (out / "tiny.zarr").unlink()
    assert main(args) == 0


def test_an_empty_job_file_is_started_over(tmp_path):
    final = tmp_path / "x"
    partial = PartialOutput(final, {"job": 1})
    partial.path.mkdir(parents=True)
    (partial.path / ".job.json").write_text("")  # a kill while it was written
    assert partial.open() is False  # not resumed, started over, no JSON traceback
    (partial.path / "data.bin").write_bytes(b"1234")
    (partial.path / "sub").mkdir()
    (partial.path / "sub" / ".0.77.tmp").write_bytes(b"torn")  # a killed writer's temp file
    partial.publish()
    assert sorted(p.name for p in final.rglob("*")) == ["data.bin", "manifest.json", "sub"]
    manifest = json.loads((final / "manifest.json").read_text())
    assert set(manifest["files"]) == {"data.bin"} and manifest["files"]["data.bin"]["bytes"] == 4


def test_caps_refused_before_work(tiny_store, tiny_index, tmp_path, capsys):
    fails(capsys, ["eval", str(tiny_store), str(tiny_index), "--L", "1", "--compare", "PQ4", "--faiss-k",
                   "1000000000", "--out", str(tmp_path / "e")], "--faiss-k 1,000,000,000: at most")
    fails(capsys, ["eval", str(tiny_store), str(tiny_index), "--L", "1", "--compare", "IVF100000,PQ2",
                   "--out", str(tmp_path / "e")], "--compare IVF100000,PQ2", "100,000 inverted lists for 52,500")
    assert not (tmp_path / "e").exists()
    with pytest.raises(SystemExit):
        main(["build", "--scale", "20K", "--fas-dim", "1000000"])
    assert "more than 16,384" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["sql", str(tiny_index), "SELECT 1", "--threads", "1000000"])
    assert "more than 256" in capsys.readouterr().err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_relative_paths_on_a_cluster_whose_worker_runs_elsewhere(tiny_store, tiny_index, tmp_path):
    """A relative store path, a loopback scheduler and a worker started in another directory:
    the index equals the local one (the chunk files are found by absolute path, never read as zeros)."""
    port = _free_port()
    elsewhere = tmp_path / "worker-home"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                              "--port", str(port), "--no-dashboard"], cwd=elsewhere, env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://127.0.0.1:{port}",
                               "--nthreads", "1", "--no-dashboard"], cwd=elsewhere, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(4)
        here = os.getcwd()
        os.chdir(tiny_store.parent)
        try:
            code = main(["index", tiny_store.name, "--d", "12", "--out", str(tmp_path / "c.index"),
                         "--scheduler", f"tcp://127.0.0.1:{port}"])
        finally:
            os.chdir(here)
        assert code == 0
        mine, local = read_index(tmp_path / "c.index"), read_index(tiny_index)
        np.testing.assert_array_equal(mine.ref_addresses(), local.ref_addresses())
        assert mine.occupied == local.occupied > 1000
    finally:
        for p in (worker, sched):
            p.terminate()
            p.wait(timeout=30)


def test_one_line_where_a_traceback_was(tiny_store, tiny_index, tmp_path, capsys):
    recipe = tmp_path / "bad.toml"
    recipe.write_bytes(b'scale = "x\xff"\n')
    fails(capsys, ["build", "--scale", str(recipe), "--out", str(tmp_path / "o")], "bad.toml", "not UTF-8")
    fails(capsys, ["index", str(tiny_store), "--out", "/"], "--out /", "names no directory")
    fails(capsys, ["sql", str(tiny_index), "UPDATE EXTENSIONS"], "only SELECT")
    assert main(["sql", str(tiny_index), "SELECT [1, 2] AS l, map([1], [2]) AS m, 3 AS n", "--csv"]) == 0
    assert capsys.readouterr().out.splitlines()[1] == '"[1, 2]","[[1, 2]]",3'


def test_a_full_disk_is_one_line_and_the_rerun_finishes(small_filesystem, tiny_store, capsys):
    out = small_filesystem / "t.index"
    free = os.statvfs(small_filesystem).f_bavail * os.statvfs(small_filesystem).f_frsize
    (small_filesystem / "filler").write_bytes(bytes(max(0, free - 100_000)))  # room for half an index
    fails(capsys, ["index", str(tiny_store), "--d", "12", "--out", str(out)], "the disk is full", "run the same")
    assert not out.exists()  # nothing half-published
    subprocess.run(["mount", "-o", "remount,size=20m", str(small_filesystem)], check=True)
    assert main(["index", str(tiny_store), "--d", "12", "--out", str(out)]) == 0
    assert read_index(out).n_ref == 52_500


def test_a_broken_zarr_json_is_one_line(store_copy, tmp_path, capsys):
    (store_copy / "zarr.json").write_text('{"zarr_format": 3, "node_type": "gro')
    fails(capsys, ["index", str(store_copy), "--out", str(tmp_path / "i")], "zarr.json")


def test_a_read_only_folder_is_refused_before_any_work(read_only_folder, tiny_store, tiny_index, capsys):
    ro = read_only_folder
    for argv in (["synth", "--out", str(ro / "s"), "--deep1b-rows", "100"],
                 ["report", str(tiny_index), "--out", str(ro / "r")],
                 ["localise", str(tiny_index), str(tiny_store / "query_qm1"), "--out", str(ro / "m.csv")],
                 ["index", str(tiny_store), "--out", str(ro / "a" / "i")],
                 ["eval", str(tiny_store), str(tiny_index), "--L", "1", "--out", str(ro / "e")],
                 ["index", str(tiny_store), "--out", str(ro.parent / "i"), "--summary", str(ro / "s.json")]):
        fails(capsys, argv, str(ro), "not writable", "nothing was written")
    assert not any(ro.iterdir()) and not (ro.parent / "i").exists()


def test_a_pipeline_whose_out_is_read_only_is_one_line(read_only_folder, tmp_path, capsys):
    """A pipeline's ``out`` on a read-only filesystem: planning works, running is refused in one
    line naming the pipeline and the folder (it failed as "a bug in vprscale")."""
    path = tmp_path / "p.toml"
    path.write_text(f'name = "p"\nout = "{read_only_folder / "out"}"\n[[stages]]\nname = "b"\nkind = "build"\n'
                    'scale = "20K"\n')
    capsys.readouterr()
    assert main(["run", str(path), "--dry-run"]) == 0
    fails(capsys, ["run", str(path)], str(path), str(read_only_folder / "out"))
    assert not any(read_only_folder.iterdir())


def test_a_zarr_array_declaring_more_rows_than_it_holds_is_one_line(tiny_index, tmp_path, capsys):
    """10^11 declared rows with one chunk written: refused at once, not a 2 TB allocation or hours
    of fill values matched as frames."""
    import zarr

    arr = zarr.create_array(tmp_path / "huge.zarr", shape=(10**11, 96), chunks=(4096, 96), dtype="f4")
    arr[:10] = np.ones((10, 96), np.float32)
    fails(capsys, ["localise", str(tiny_index), str(tmp_path / "huge.zarr"), "--L", "5"],
          "declares 100,000,000,000 rows", "1 are written")


@pytest.mark.parametrize("where", ["not a scheduler", "no workers", "not an address"])
def test_a_scheduler_that_cannot_run_the_job_is_one_line_in_time(where, tiny_store, tmp_path, capsys, monkeypatch):
    """``--scheduler`` at a port where another server listens, at a scheduler with no worker, or at
    something that is no address: one line and exit 2 within the waits, never a hang."""
    import http.server
    import threading

    monkeypatch.setattr("vprscale.core.cluster.CONNECT_S", 2.0)
    monkeypatch.setattr("vprscale.core.cluster.WORKERS_S", 2.0)
    stop = []
    if where == "not a scheduler":
        httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        stop.append(httpd.shutdown)
        address, words = f"tcp://127.0.0.1:{httpd.server_address[1]}", ("no Dask scheduler answered",)
    elif where == "no workers":
        from distributed import LocalCluster

        cluster = LocalCluster(n_workers=0, processes=False, dashboard_address=None, scheduler_port=0)
        stop.append(cluster.close)
        address, words = cluster.scheduler_address, ("has no worker", "leave --scheduler out")
    else:
        address, words = "not a url", ("--scheduler not a url",)
    started = time.monotonic()
    try:
        fails(capsys, ["index", str(tiny_store), "--d", "12", "--out", str(tmp_path / "i.index"), "--scheduler",
                       address], *words)
    finally:
        for s in stop:
            s()
    assert time.monotonic() - started < 30 and not (tmp_path / "i.index").exists()
    # nothing of the failed client is left to this process's Dask: a local job runs as ever
    assert main(["index", str(tiny_store), "--d", "12", "--out", str(tmp_path / "j.index"), "-q"]) == 0


@pytest.mark.slow
def test_a_scheduler_killed_mid_job_is_one_line_and_the_job_resumes(sources, tmp_path):
    """The scheduler is killed while a build runs on it: one line and exit 2, no traceback (not
    "a bug in vprscale"); the same command, locally, finishes the store."""
    from .conftest import write_recipe

    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                              "--port", str(port), "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://127.0.0.1:{port}",
                               "--nthreads", "1", "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    argv = [sys.executable, "-m", "vprscale.cli", "build", "--scale", str(write_recipe(tmp_path / "tiny.toml")),
            "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]), "--out", str(tmp_path / "o")]
    try:
        job = subprocess.Popen([*argv, "--scheduler", f"tcp://127.0.0.1:{port}"], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        done = tmp_path / "o" / ".tiny.zarr.partial" / ".done"
        while not (done.is_dir() and any(done.iterdir())) and time.monotonic() < deadline:
            time.sleep(0.05)  # the build is under way on the cluster once a first unit of it is done
        sched.kill()
        _, err = job.communicate(timeout=300)
    finally:
        for p in (worker, sched):
            p.kill()
            p.wait(timeout=30)
    assert job.returncode == 2, err
    assert "Traceback" not in err and "bug in vprscale" not in err, err
    assert "Dask cluster failed" in err.strip().splitlines()[-1]
    assert subprocess.run([*argv, "-q"], env=env, capture_output=True).returncode == 0
