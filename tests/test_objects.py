"""Outputs on object storage: a real S3 endpoint (moto's server) on 127.0.0.1, started and
stopped with the tests; stores written there by URL, read back by URL, and a Dask cluster
whose workers share no directory with the client or each other."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from vprscale.cli import main
from vprscale.core.errors import InputError
from vprscale.core.localcopy import local_copy
from vprscale.core.objects import Remote
from vprscale.core.publish import ObjectOutput

moto_server = pytest.importorskip("moto.server")
pytest.importorskip("s3fs")

BUCKET = "vprscale-test"
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing-key-id", "AWS_SECRET_ACCESS_KEY": "testing-secret-never-shown",
               "AWS_DEFAULT_REGION": "us-east-1"}


@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture
def s3(endpoint, monkeypatch, tmp_path) -> dict[str, str]:
    """The environment of a job that writes to the test endpoint (a fresh bucket per test)."""
    import boto3

    env = {"AWS_ENDPOINT_URL": endpoint, **CREDENTIALS, "VPRSCALE_CACHE": str(tmp_path / "cache")}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    client = boto3.client("s3", endpoint_url=endpoint)
    if BUCKET in [b["Name"] for b in client.list_buckets().get("Buckets", [])]:
        for obj in client.list_objects_v2(Bucket=BUCKET).get("Contents", []):
            client.delete_object(Bucket=BUCKET, Key=obj["Key"])
    else:
        client.create_bucket(Bucket=BUCKET)
    import s3fs

    s3fs.S3FileSystem.clear_instance_cache()
    return env


def _objects(prefix: str) -> dict[str, int]:
    return Remote(prefix).files()


def _manifest_crcs(files: dict) -> dict[str, str]:
    """The manifest's checksums of a store's arrays and metadata (build.json holds timings)."""
    return {rel: e["crc32c"] for rel, e in files.items() if rel != "build.json"}


def test_a_store_built_to_s3_holds_the_same_bytes_and_is_read_back_by_url(s3, sources, tiny_store, capsys):
    """``build --out s3://…`` writes through zarr's own store, no local copy: the same object
    bytes as the local build (every chunk's CRC32C), the manifest written last and the job's
    bookkeeping gone; ``verify`` and the store reader open it by URL."""
    from vprscale.dataset.store import open_complete_group

    recipe = tiny_store.parent.parent / "tiny.toml"
    url = f"s3://{BUCKET}/data"
    assert main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
                 "--out", url, "-q"]) == 0
    names = _objects(f"{url}/tiny.zarr")
    assert "manifest.json" in names and not [n for n in names if n.startswith((".done", ".job"))]
    remote = json.loads(Remote(f"{url}/tiny.zarr/manifest.json").read_text())["files"]
    local = json.loads((tiny_store / "manifest.json").read_text())["files"]
    assert _manifest_crcs(remote) == _manifest_crcs(local)
    assert main(["verify", f"{url}/tiny.zarr"]) == 0
    assert f"{len(remote)} files with their sizes and checksums" in capsys.readouterr().out
    group = open_complete_group(f"{url}/tiny.zarr")
    np.testing.assert_array_equal(group["query_qm2"][:100], open_complete_group(tiny_store)["query_qm2"][:100])
    assert main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
                 "--out", url]) == 0
    assert "is complete" in capsys.readouterr().err  # a second run finds it whole and does nothing


def test_a_store_whose_manifest_was_never_written_is_not_opened(s3, sources, tiny_store, capsys):
    """On object storage the manifest, written last, is what makes an output complete: a job
    killed before it leaves objects no reader takes for a store, and ``verify`` says so."""
    from vprscale.dataset.store import open_complete_group

    recipe = tiny_store.parent.parent / "tiny.toml"
    url = f"s3://{BUCKET}/data"
    assert main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
                 "--out", url, "-q"]) == 0
    Remote(f"{url}/tiny.zarr/manifest.json").fs.rm_file(f"{BUCKET}/data/tiny.zarr/manifest.json")
    with pytest.raises(InputError, match="complete only once its manifest"):
        open_complete_group(f"{url}/tiny.zarr")
    assert main(["verify", f"{url}/tiny.zarr"]) == 2
    assert "manifest" in capsys.readouterr().err


def test_a_rebuild_resumes_from_the_markers_it_left(s3, tmp_path):
    """A job's key and done-markers live beside its objects: the same job resumes (from any
    client), another job starts over, and publishing leaves only the output and its manifest."""
    final = Remote(f"s3://{BUCKET}/out/x.zarr")
    first = ObjectOutput(final, {"job": 1})
    assert not first.open()
    (final / "a").write_bytes(b"chunk")
    first.mark("chunk-0")
    again = ObjectOutput(final, {"job": 1})
    assert again.open() and again.done("chunk-0") and not again.done("chunk-1")
    other = ObjectOutput(final, {"job": 2})
    assert not other.open() and not other.done("chunk-0") and not (final / "a").exists()
    (final / "b").write_bytes(b"rows")
    other.publish()
    assert set(final.files()) == {"b", "manifest.json"}


def test_force_keeps_the_replaced_output_beside(s3):
    """``--force`` on object storage moves the complete output to ``<name>.previous`` (then
    ``.previous.1``, …) before writing the new one, as it keeps it beside on a local disk."""
    final = Remote(f"s3://{BUCKET}/out/x.zarr")
    for n in range(3):
        job = ObjectOutput(final, {"job": n})
        job.open()
        (final / "v").write_bytes(str(n).encode())
        job.publish()
    assert (final / "v").read_bytes() == b"2"
    assert Remote(f"s3://{BUCKET}/out/x.zarr.previous/v").read_bytes() == b"1"
    assert Remote(f"s3://{BUCKET}/out/x.zarr.previous.1/v").read_bytes() == b"0"


@pytest.mark.parametrize(("out", "words"), [
    ("s3://no-such-bucket-here/data", "not found"),
    ("nosuchscheme://x/y", "not a URL vprscale can open"),
])
def test_a_bad_output_url_is_one_line_before_any_work(s3, recipe, out, words, capsys):
    assert main(["build", "--scale", str(recipe), "--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_credentials_reach_no_output_or_record(s3, sources, tiny_store):
    """The secret key is read by the storage client from the environment; no object written
    (the store's metadata, build.json, the manifest) holds it."""
    recipe = tiny_store.parent.parent / "tiny.toml"
    url = f"s3://{BUCKET}/data"
    assert main(["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
                 "--out", url, "-q"]) == 0
    root = Remote(f"{url}/tiny.zarr")
    for rel in root.files():
        if rel.endswith(".json"):
            text = (root / rel).read_text()
            assert CREDENTIALS["AWS_SECRET_ACCESS_KEY"] not in text and CREDENTIALS["AWS_ACCESS_KEY_ID"] not in text


def _start(cmd: list[str], cwd: Path, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_a_cluster_whose_workers_share_no_disk_builds_the_same_bytes(s3, sources, tiny_store, tmp_path):
    """A ``dask scheduler`` and two ``dask worker`` processes, each started in its own empty
    directory: the sources are fetched by URL (an HTTP server on 127.0.0.1), the store is
    written to S3, and every object equals the local build's."""
    from .test_fetch import Server

    data = sources["fbin"].read_bytes()
    server = Server(lambda a, b: data[a:b], len(data))
    env = {**os.environ, **s3}
    procs = []
    try:
        sched_dir = tmp_path / "scheduler"
        sched_dir.mkdir()
        address = sched_dir / "scheduler.json"
        procs.append(_start([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", "0", "--no-dashboard", "--scheduler-file", str(address)], sched_dir, env))
        for w in range(2):
            folder = tmp_path / f"worker{w}"
            folder.mkdir()
            procs.append(_start([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                 str(address), "--nthreads", "1", "--no-dashboard", "--local-directory",
                                 str(folder)], folder, {**env, "VPRSCALE_CACHE": str(folder / "cache")}))
        deadline = time.monotonic() + 60
        while not address.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        scheduler = json.loads(address.read_text())["address"]
        client_dir = tmp_path / "client"
        client_dir.mkdir()
        recipe = tmp_path / "client" / "tiny.toml"
        recipe.write_text((tiny_store.parent.parent / "tiny.toml").read_text())
        url = f"s3://{BUCKET}/cluster"
        run = subprocess.run([sys.executable, "-m", "vprscale.cli", "build", "--scale", str(recipe), "--deep1b",
                              server.url, "--fas", str(sources["fas"]), "--out", url, "--scheduler", scheduler,
                              "-q"], cwd=client_dir, env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        for step in (["index", f"{url}/tiny.zarr", "--d", "12"],
                     ["eval", f"{url}/tiny.zarr", f"{url}/tiny-d12-k2.index", "--L", "1,50", "--noise", "qm1",
                      "--no-baseline", "--out", f"{url}/run"]):
            run = subprocess.run([sys.executable, "-m", "vprscale.cli", *step, "--scheduler", scheduler, "-q"],
                                 cwd=client_dir, env=env, capture_output=True, text=True, timeout=600)
            assert run.returncode == 0, run.stderr
    finally:
        for p in reversed(procs):  # the workers first: they would wait for a scheduler that left
            p.kill()
            p.wait(timeout=30)
        server.close()
    remote = json.loads(Remote(f"{url}/tiny.zarr/manifest.json").read_text())["files"]
    local = json.loads((tiny_store / "manifest.json").read_text())["files"]
    differ = {k for k in local if k != "build.json" and remote.get(k) != local[k]}
    assert differ <= {"zarr.json"}  # the sources' records name the URL read, not the local file
    assert [p for p in (tmp_path / "worker0").rglob("*.zarr")] == []  # nothing of the store on a worker's disk
    index = json.loads(Remote(f"{url}/tiny-d12-k2.index/manifest.json").read_text())["files"]
    here = tmp_path / "tiny.index"
    assert main(["index", str(tiny_store), "--d", "12", "--out", str(here), "-q"]) == 0
    assert {k: v for k, v in index.items() if k != "index.json"} == {
        k: v for k, v in json.loads((here / "manifest.json").read_text())["files"].items() if k != "index.json"}
    assert main(["eval", str(tiny_store), str(here), "--L", "1,50", "--noise", "qm1", "--no-baseline", "--out",
                 str(tmp_path / "run"), "-q"]) == 0
    import pyarrow.parquet as pq

    answers = []
    for where in (local_copy(Remote(f"{url}/run")), tmp_path / "run"):
        q = pq.read_table(where / "queries.parquet").to_pandas()
        answers.append(q.sort_values(["L", "mode", "t"])[["L", "mode", "t", "match", "score"]].reset_index(drop=True))
    assert answers[0].equals(answers[1])  # every answer of the cluster's evaluation equals the local one's


def test_an_index_on_s3_is_used_from_a_verified_copy_in_the_cache(s3, tiny_store, tmp_path, capsys):
    """``index --out s3://…`` is made in the cache (it is memory-mapped while written) and uploaded,
    its manifest last; a command given its URL reads a local copy, fetched once and checked byte
    for byte against that manifest: a changed object is refused by name, a re-published index
    is fetched again."""
    url = f"s3://{BUCKET}/idx/tiny.index"
    assert main(["index", str(tiny_store), "--d", "12", "--out", url, "-q"]) == 0
    remote = Remote(url)
    assert "manifest.json" in remote.files() and "index.json" in remote.files()
    cache = Path(s3["VPRSCALE_CACHE"])
    capsys.readouterr()
    assert main(["occupancy", url, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["d"] == 12
    for copy in cache.glob("outputs/*"):
        shutil.rmtree(copy)
    codes = next(rel for rel in remote.files() if rel.endswith(".npy") and remote.files()[rel] > 1000)
    original = (remote / codes).read_bytes()
    (remote / codes).write_bytes(original[:-1] + bytes([original[-1] ^ 1]))  # same size, one bit
    assert main(["occupancy", url]) == 2
    assert "checksum differs" in capsys.readouterr().err
    (remote / codes).write_bytes(original)
    assert main(["index", str(tiny_store), "--d", "10", "--out", url, "-q", "--force"]) == 0
    capsys.readouterr()
    assert main(["occupancy", url, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["d"] == 10  # the re-published index, not the cached copy
    assert main(["eval", str(tiny_store), url, "--L", "1"]) == 2
    assert "--out" in capsys.readouterr().err
    out = tmp_path / "run"
    assert main(["eval", str(tiny_store), url, "--L", "1", "--noise", "qm1", "--no-baseline", "--out", str(out),
                 "-q"]) == 0
    assert json.loads((out / "eval.json").read_text())["indexes"] == [url]  # the URL, not the cache copy


def test_an_evaluation_on_s3_is_read_back_by_results_and_sql(s3, tiny_store, tiny_index, tmp_path, capsys):
    """``eval --out s3://…`` uploads the published evaluation (manifest last); ``results`` and
    ``sql`` read it by URL, the same rows as a local evaluation of the same grid; a second
    evaluation into it is refused without ``--force`` and, with it, keeps the first beside."""
    url = f"s3://{BUCKET}/runs/tiny"
    grid = ["--L", "1", "--noise", "qm1", "--no-baseline", "-q"]
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", url]) == 0
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", str(tmp_path / "local")]) == 0
    assert {"manifest.json", "eval.json", "results.parquet"} <= set(Remote(url).files())
    capsys.readouterr()
    assert main(["sql", url, "SELECT count(*) AS n FROM results", "--csv"]) == 0
    remote_rows = capsys.readouterr().out
    assert main(["sql", str(tmp_path / "local"), "SELECT count(*) AS n FROM results", "--csv"]) == 0
    assert remote_rows == capsys.readouterr().out and remote_rows.split()[-1] != "0"
    assert main(["results", url, "--where", "L = 1", "--csv"]) == 0
    assert "coarsehash" in capsys.readouterr().out
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", url]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", url, "--force"]) == 0
    assert "eval.json" in Remote(f"{url}.previous").files()
    report = f"s3://{BUCKET}/reports/tiny"
    assert main(["report", url, "--out", report, "-q"]) == 0
    assert {"report.md", "report.html", "manifest.json"} <= set(Remote(report).files())
    assert (Remote(report) / "report.md").read_text().startswith("#")
    assert main(["report", url, "--out", report, "-q"]) == 2  # a report is replaced only with --force


def test_an_endpoint_that_does_not_answer_is_one_line(s3, recipe, monkeypatch, capsys):
    """The storage client's own errors (here: a refused connection) are the storage's, not a bug."""
    import socket

    import s3fs

    with socket.socket() as sock:  # a port that was free a moment ago: nothing listens there
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{port}")
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    s3fs.S3FileSystem.clear_instance_cache()
    assert main(["build", "--scale", str(recipe), "--out", f"s3://{BUCKET}/data"]) == 2
    err = capsys.readouterr().err.strip()
    assert "storage failed" in err and len(err.splitlines()) == 1


@pytest.mark.filterwarnings("ignore:Object at:UserWarning")  # zarr lists build.json and the manifest beside arrays
@pytest.mark.parametrize("layout", ["full", "compact"])
def test_a_sharded_store_holds_the_same_arrays_in_fewer_objects(s3, sources, tiny_store, tmp_path, layout):
    """``--shard-chunks 2``: each array's chunks two to a shard (recorded in its zarr.json), each
    shard written whole by one task; the arrays equal the unsharded build's, on S3 in half the
    objects, and the index fitted from it equals the one fitted from the unsharded store."""
    import zarr

    from vprscale.jobs.indexing import build_index

    recipe = tiny_store.parent.parent / "tiny.toml"
    flags = ["--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]), "--layout", layout,
             "-q"]
    url = f"s3://{BUCKET}/sharded"
    assert main(["build", *flags, "--out", str(tmp_path / "plain")]) == 0
    assert main(["build", *flags, "--out", url, "--shard-chunks", "2"]) == 0
    plain, sharded = zarr.open_group(tmp_path / "plain" / "tiny.zarr", mode="r"), zarr.open_group(
        f"{url}/tiny.zarr", mode="r")
    big = "ref" if layout == "full" else "ref_hash"
    assert sharded[big].shards == (2 * plain[big].chunks[0], *plain[big].chunks[1:])
    assert plain[big].shards is None
    for name in plain.array_keys():
        np.testing.assert_array_equal(sharded[name][:], plain[name][:], err_msg=name)
    objects = [n for n in Remote(f"{url}/tiny.zarr").files() if n.startswith(f"{big}/c/")]
    files = [p for p in (tmp_path / "plain" / "tiny.zarr" / big / "c").rglob("*") if p.is_file()]
    assert len(objects) == -(-len(files) // 2)
    d = 12 if layout == "full" else None  # a compact store holds its own width's addresses
    indexes = [build_index(store, d=d, out=tmp_path / name, quiet=True) for store, name in
               ((tmp_path / "plain" / "tiny.zarr", "a.index"), (f"{url}/tiny.zarr", "b.index"))]
    crcs = [json.loads((tmp_path / n / "manifest.json").read_text())["files"] for n in ("a.index", "b.index")]
    assert {k: v for k, v in crcs[0].items() if k != "index.json"} == {k: v for k, v in crcs[1].items()
                                                                        if k != "index.json"}
    assert indexes[0]["occupied"] == indexes[1]["occupied"]


def test_an_encoding_beside_a_store_on_s3_is_made_once_and_evaluated_from_its_copy(s3, tiny_store, tiny_index, tmp_path,
                                                                                  small_training, capsys):
    """``encode s3://…/tiny.zarr --compare PQ4`` uploads the encoding beside the store (manifest
    last), a second run skips it, and an evaluation of the store by URL uses it (recorded in
    eval.json) with the same answers as from the local store's own encoding."""
    url = f"s3://{BUCKET}/enc"
    store = Remote(f"{url}/tiny.zarr")  # the tiny store's files as they are (building to s3 is another test's)
    store.fs.put(f"{tiny_store}/", f"{store.path}/", recursive=True)
    assert main(["encode", f"{url}/tiny.zarr", "--compare", "PQ4np", "-q"]) == 0
    assert "manifest.json" in Remote(f"{url}/tiny.faiss/PQ4np").files()
    capsys.readouterr()
    assert main(["encode", f"{url}/tiny.zarr", "--compare", "PQ4np"]) == 0
    assert "up to date, kept" in capsys.readouterr().out
    grid = ["--L", "1", "--noise", "qm1", "--no-baseline", "--compare", "PQ4np", "-q"]
    assert main(["eval", f"{url}/tiny.zarr", str(tiny_index), *grid, "--out", str(tmp_path / "remote")]) == 0
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", str(tmp_path / "local")]) == 0
    remote_eval = json.loads((tmp_path / "remote" / "eval.json").read_text())
    assert remote_eval["compare"]["faiss:PQ4np"]["encoding"]  # the stored encoding, not one trained by the eval
    import pyarrow.parquet as pq

    answers = [pq.read_table(tmp_path / run / "queries.parquet").to_pandas() for run in ("remote", "local")]
    faiss_rows = [a[a["method"] == "faiss:PQ4np"].sort_values(["L", "t"]).reset_index(drop=True) for a in answers]
    assert len(faiss_rows[0]) > 0 and faiss_rows[0]["match"].tolist() == faiss_rows[1]["match"].tolist()


def test_denied_credentials_are_one_line_and_never_shown(s3, recipe, monkeypatch, capsys):
    """With the server checking keys, the test's key is unknown to it: refused before any work,
    one line naming the URL and where credentials come from, and the secret not in it."""
    import moto.settings

    monkeypatch.setattr(moto.settings, "INITIAL_NO_AUTH_ACTION_COUNT", 0)
    assert main(["build", "--scale", str(recipe), "--out", f"s3://{BUCKET}/data"]) == 2
    err = capsys.readouterr().err.strip()
    assert "access denied" in err and "AWS_" in err and len(err.splitlines()) == 1
    assert CREDENTIALS["AWS_SECRET_ACCESS_KEY"] not in err


@pytest.mark.parametrize("failure", ["denied", "dead endpoint"])
@pytest.mark.parametrize("command", ["verify", "index", "results"])
def test_a_storage_that_fails_a_read_is_named_not_taken_for_a_missing_store(s3, tiny_store, monkeypatch, capsys,
                                                                           failure, command):
    """Reading a store, an index or an evaluation by URL when the storage refuses the credentials or
    does not answer: one line saying so, not "not a vprscale store"."""
    import socket

    import moto.settings
    import s3fs

    url = f"s3://{BUCKET}/data/tiny.zarr"
    if failure == "denied":
        monkeypatch.setattr(moto.settings, "INITIAL_NO_AUTH_ACTION_COUNT", 0)
    else:
        with socket.socket() as sock:  # a port that was free a moment ago: nothing listens there
            sock.bind(("127.0.0.1", 0))
            monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{sock.getsockname()[1]}")
        monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    s3fs.S3FileSystem.clear_instance_cache()
    capsys.readouterr()
    assert main([command, url]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a vprscale" not in err, err
    assert ("access denied" if failure == "denied" else "storage failed") in err, err


def _upload(local: Path, url: str) -> None:
    remote = Remote(url)
    remote.fs.put_file(str(local), remote.path)


def test_deep1b_rows_read_from_object_storage_equal_the_files(s3, sources):
    """``--deep1b s3://…/base.fbin``, an fvecs object, or a prefix of fvecs chunk objects: the
    rows, read by byte ranges, equal the local files'; a record of the wrong dimension is named."""
    from vprscale.dataset.sources.deep1b import open_deep1b

    local = open_deep1b(str(sources["fbin"]))
    _upload(sources["fbin"], f"s3://{BUCKET}/deep/base.fbin")
    chunks = sorted(p for p in sources["fvecs"].iterdir() if p.is_file())
    for p in chunks:
        _upload(p, f"s3://{BUCKET}/deep/base/{p.name}")
    for url in (f"s3://{BUCKET}/deep/base.fbin", f"s3://{BUCKET}/deep/base", f"s3://{BUCKET}/deep/base/{chunks[0].name}"):
        src = open_deep1b(url)
        rows = min(src.n_rows, local.n_rows)
        np.testing.assert_array_equal(src.read(rows - 5000, rows), local.read(rows - 5000, rows), err_msg=url)
        assert "testing" not in json.dumps(src.fingerprint())
    data = bytearray(chunks[0].read_bytes())
    data[4 * 97 * 10 : 4 * 97 * 10 + 4] = (95).to_bytes(4, "little")  # record 10 says d = 95
    Remote(f"s3://{BUCKET}/bad/base_00").write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"base_00: offset 3880: record dimension 95"):
        open_deep1b(f"s3://{BUCKET}/bad").read(0, 100)
    with pytest.raises(InputError, match="no fvecs object there"):
        open_deep1b(f"s3://{BUCKET}/nothing-here")


def test_a_build_from_sources_on_object_storage_equals_the_local_build(s3, sources, tiny_store, tmp_path, capsys):
    """``--deep1b s3://…/base.fbin --fas s3://…/fas.npz``: Deep1B read by ranges, FAS100K fetched
    once into the cache (its PCA reads it whole several times); the arrays equal the local
    build's, and the store's record of its sources (URL, size, version) does not change when the
    cache is cleared: a re-run finds the store complete."""
    import zarr

    _upload(sources["fbin"], f"s3://{BUCKET}/src/base.fbin")
    _upload(sources["fas"], f"s3://{BUCKET}/src/fas.npz")
    recipe = tiny_store.parent.parent / "tiny.toml"
    flags = ["build", "--scale", str(recipe), "--deep1b", f"s3://{BUCKET}/src/base.fbin", "--fas",
             f"s3://{BUCKET}/src/fas.npz", "--out", str(tmp_path / "data"), "-q"]
    assert main(flags) == 0
    built, local = (zarr.open_group(p, mode="r") for p in (tmp_path / "data" / "tiny.zarr", tiny_store))
    for name in ("ref", "query_qm1", "query_qm2", "gt", "fas_ref_pos"):
        np.testing.assert_array_equal(built[name][:], local[name][:], err_msg=name)
    assert f"s3://{BUCKET}/src/fas.npz" in json.dumps(built.attrs["vprscale"]["sources"])
    shutil.rmtree(Path(s3["VPRSCALE_CACHE"]) / "sources")
    capsys.readouterr()
    assert main(flags[:-1]) == 0
    assert "is complete" in capsys.readouterr().err


class CuttableProxy:
    """A TCP forwarder to the S3 endpoint on 127.0.0.1 that can be cut: every open connection is
    then closed and new ones are refused at once, as when a network goes away mid-job."""

    def __init__(self, target: str) -> None:
        import socket
        import threading

        host, port = target.removeprefix("http://").split(":")
        self.target = (host, int(port))
        self.cut = threading.Event()
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.server.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        import socket
        import threading

        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            if self.cut.is_set():
                client.close()
                continue
            upstream = socket.create_connection(self.target)
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src, dst) -> None:
        src.settimeout(0.1)
        try:
            while not self.cut.is_set():
                try:
                    data = src.recv(1 << 16)
                except TimeoutError:
                    continue
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            s.close()

    def close(self) -> None:
        self.server.close()


@pytest.mark.slow
def test_a_build_whose_storage_goes_away_stops_in_one_line_and_resumes(s3, sources, tiny_store, tmp_path):
    """The connection to the storage is cut once the job has started writing: exit 2, one line
    saying the work is kept; the same command then resumes the job (its key and markers are on the
    storage) and the store holds the same bytes as the local build."""
    proxy = CuttableProxy(s3["AWS_ENDPOINT_URL"])
    env = {**os.environ, **s3, "AWS_ENDPOINT_URL": proxy.url, "AWS_MAX_ATTEMPTS": "1"}
    recipe = tiny_store.parent.parent / "tiny.toml"
    url = f"s3://{BUCKET}/cut"
    cmd = [sys.executable, "-m", "vprscale.cli", "build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]),
           "--fas", str(sources["fas"]), "--out", url]
    try:
        job = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while not Remote(f"{url}/tiny.zarr/.job.json").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        proxy.cut.set()
        _, err = job.communicate(timeout=300)
        assert job.returncode == 2, err
        last = err.strip().splitlines()[-1]
        assert "storage failed" in last and "resume" in last and "Traceback" not in err
        assert "manifest.json" not in Remote(f"{url}/tiny.zarr").files()  # nothing that looks complete
        proxy.cut.clear()
        again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert again.returncode == 0, again.stderr
        assert "resuming the unfinished build" in again.stderr, again.stderr
    finally:
        proxy.close()
    remote = json.loads(Remote(f"{url}/tiny.zarr/manifest.json").read_text())["files"]
    local = json.loads((tiny_store / "manifest.json").read_text())["files"]
    assert _manifest_crcs(remote) == _manifest_crcs(local)


def test_fas_rows_by_url_are_read_where_the_client_copy_is_not(s3, sources, tmp_path, monkeypatch):
    """A FAS100K task sent to a worker that shares no disk with the client (here: the client's
    copy gone, another cache) opens the URL itself and reads the same rows."""
    import pickle

    from vprscale.dataset.sources.fas import open_fas

    _upload(sources["fas"], f"s3://{BUCKET}/src/fas.npz")
    local = open_fas(str(sources["fas"]))
    remote = open_fas(f"s3://{BUCKET}/src/fas.npz", quiet=True)
    sent = pickle.dumps(remote.query)
    shutil.rmtree(Path(s3["VPRSCALE_CACHE"]) / "sources")
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "worker-cache"))
    worker_side = pickle.loads(sent)
    np.testing.assert_array_equal(worker_side.read(100, 300), local.query.read(100, 300))
    assert (tmp_path / "worker-cache" / "sources").is_dir()  # its own copy, fetched once


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "force"])
def test_no_command_removes_objects_it_did_not_write(s3, sources, tiny_store, tiny_index, tmp_path, capsys, force):
    """Every command that writes under an ``s3://`` prefix (build, index, eval, report) refuses,
    in one line naming the prefix and before any work, one that holds someone's own objects (no
    vprscale manifest or job key beside them), with or without ``--force``: nothing removed, nothing
    replaced, nothing written there."""
    recipe = tiny_store.parent.parent / "tiny.toml"
    grid = ["--L", "1", "--noise", "qm1", "--no-baseline", "-q"]
    evaluation = tmp_path / "eval"
    assert main(["eval", str(tiny_store), str(tiny_index), *grid, "--out", str(evaluation)]) == 0
    commands = {
        "build": (["build", "--scale", str(recipe), "--deep1b", str(sources["fbin"]), "--fas", str(sources["fas"]),
                   "--out", f"s3://{BUCKET}/mine", "-q"], f"s3://{BUCKET}/mine/tiny.zarr"),
        "index": (["index", str(tiny_store), "--d", "12", "-q", "--out"], f"s3://{BUCKET}/mine"),
        "eval": (["eval", str(tiny_store), str(tiny_index), *grid, "--out"], f"s3://{BUCKET}/mine"),
        "report": (["report", str(evaluation), "-q", "--out"], f"s3://{BUCKET}/mine"),
    }
    manifests = {"none": None, "another tool's": b'{"version": 2, "entries": ["results.csv"]}',
                 "vprscale's, not listing them": b'{"format": 1, "files": {}}'}
    for (name, (argv, prefix)), (kind, manifest) in itertools.product(commands.items(), manifests.items()):
        theirs = {f"{prefix}/results.csv": b"method,recall\nmine,0.9\n", f"{prefix}/notes/a.txt": b"keep me"}
        if manifest is not None:  # a manifest.json makes nothing vprscale's that it does not list
            theirs[f"{prefix}/manifest.json"] = manifest
        for url, data in theirs.items():
            Remote(url).write_bytes(data)
        capsys.readouterr()
        argv = [*argv, prefix] if argv[-1] == "--out" else argv
        assert main([*argv, *force]) == 2, (name, kind)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a vprscale output" in err[0] and "results.csv" in err[0], (name, kind, err)
        assert Remote(prefix).files() == {url.removeprefix(prefix + "/"): len(data) for url, data in theirs.items()}
        assert all(Remote(url).read_bytes() == data for url, data in theirs.items()), (name, kind)
        Remote(prefix).remove()


def test_a_key_with_a_hash_is_shown_and_written_under_its_own_name(s3, tiny_store, tiny_index, capsys):
    """``#`` is part of an object's name on S3 (not a URL fragment, as over http): an evaluation
    written to ``…/run#2`` is there, and every line that names it names it whole."""
    url = f"s3://{BUCKET}/runs/run#2"
    assert str(Remote(url)) == url
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1", "--no-baseline", "-q",
                 "--repeats", "1", "--out", url]) == 0
    assert "eval.json" in Remote(url).files()
    assert url in capsys.readouterr().out
