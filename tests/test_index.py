"""The index directory, its storage accounting, the SQL sandbox and occupancy."""

from __future__ import annotations

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.method.coarsehash import pack, project

from .conftest import quantize


@pytest.fixture(scope="module")
def model(tiny_index):
    return {k: np.load(tiny_index / "model" / f"{k}.npy") for k in ("mean", "components", "centres")}


def test_lists_are_the_addresses_of_every_ref(tiny_index, tiny_store, model):
    from vprscale.method.index import read_index

    ref = zarr.open_group(tiny_store, mode="r")["ref"][:]
    y = project(ref, model["mean"], model["components"])
    h = pack(quantize(y, model["centres"])[0], 2)
    idx = read_index(tiny_index)
    np.testing.assert_array_equal(idx.ref_addresses(), h)  # P1, decoded from the bit planes
    buckets = pq.read_table(tiny_index / "buckets.parquet").to_pandas()
    np.testing.assert_array_equal(np.unique(h), buckets["hash"].to_numpy())
    np.testing.assert_array_equal(idx.lists.occupied.decode(), buckets["hash"].to_numpy())
    np.testing.assert_array_equal(idx.lists.starts.decode(), np.r_[buckets["offset"].to_numpy(), len(ref)])
    err = quantize(y, model["centres"])[1]
    for row in buckets.sample(200, random_state=0).itertuples():
        ids = np.flatnonzero(h == row.hash)
        got = idx.lists.list_ids(row.Index)
        assert row.size == len(ids) == len(got)
        assert got[0] == ids[np.argmin(err[ids])]  # the single best first, then the rest ascending
        np.testing.assert_array_equal(got[1:], np.setdiff1d(ids, got[:1]))


def test_any_parquet_reader_finds_the_lists_and_codes(tiny_index, tiny_store, model):
    """The index's tables, read by DuckDB and pyarrow themselves (no vprscale between): every place
    once in its address's list, sorted by (hash, ref_id), one single best a list (least error,
    ties to the smaller id); the codes every place's address; the buckets the lists' sizes."""
    import duckdb

    ref = zarr.open_group(tiny_store, mode="r")["ref"][:]
    y = project(ref, model["mean"], model["components"])
    levels, err = quantize(y, model["centres"])
    h = pack(levels, 2)
    con = duckdb.connect()
    lists = con.execute("SELECT hash, ref_id, best FROM read_parquet(?)", [str(tiny_index / "lists.parquet")]).df()
    order = np.lexsort((np.arange(len(h)), h))
    np.testing.assert_array_equal(lists["ref_id"].to_numpy(), order)  # sorted by hash, then id
    np.testing.assert_array_equal(lists["hash"].to_numpy(), h[order])
    best = lists[lists.best]
    want = {a: ids[np.argmin(err[ids])] for a, ids in ((a, np.flatnonzero(h == a)) for a in np.unique(h))}
    assert dict(zip(best.hash, best.ref_id, strict=True)) == want
    counted = con.execute("SELECT hash, count(*) AS n FROM read_parquet(?) GROUP BY hash ORDER BY hash",
                          [str(tiny_index / "lists.parquet")]).fetchnumpy()
    buckets = pq.read_table(tiny_index / "buckets.parquet").to_pandas()
    np.testing.assert_array_equal(counted["hash"], buckets["hash"])
    np.testing.assert_array_equal(counted["n"], buckets["size"])
    np.testing.assert_array_equal(buckets["offset"], np.r_[0, np.cumsum(buckets["size"])[:-1]])
    codes = pq.read_table(tiny_index / "codes.parquet")
    assert codes.schema.names == ["ref_id", "hash"]
    np.testing.assert_array_equal(codes["ref_id"].to_numpy(), np.arange(len(h)))
    np.testing.assert_array_equal(codes["hash"].to_numpy(), h)


def test_index_json_and_storage(tiny_index):
    meta = json.loads((tiny_index / "index.json").read_text())
    assert meta["complete"] and meta["d"] == 12 and meta["k"] == 2 and meta["n_ref"] == 52_500
    assert meta["format"] == 4 and meta["layout"]["id_bits"] == 16 and meta["layout"]["code_bits"] == 12
    st = meta["storage"]
    assert st["P1"]["paper"] == 8 * 52_500 and st["P1"]["packed"] == 12 * 52_500 // 8
    assert st["P3"]["paper"] == 8 * 12 * 96 and st["P4"]["paper"] == 8 * 96 and st["P2"]["paper"] == 8 * 12 * 2
    # P1 on disk is the codes table, under 12 bits a place (the addresses' skew compresses)
    assert st["P1"]["disk"] == (tiny_index / "codes.parquet").stat().st_size < 12 * 52_500 // 8
    assert st["total"]["paper"] == sum(st[p]["paper"] for p in ("P1", "P2", "P3", "P4"))


def test_sql_lookup_and_formats(tiny_index, capsys):
    from vprscale.method.index import read_index

    idx = read_index(tiny_index)
    h = int(idx.lists.addresses(np.array([700]))[0])
    expected = sorted(idx.lists.list_ids(700).tolist())
    assert main(["sql", str(tiny_index), f"SELECT ref_id FROM lists WHERE hash = {h} ORDER BY ref_id", "--json"]) == 0
    got = [json.loads(line)["ref_id"] for line in capsys.readouterr().out.splitlines()]
    assert got == expected
    assert main(["sql", str(tiny_index), "SELECT count(*) AS n, sum(size) AS s FROM buckets", "--csv"]) == 0
    assert capsys.readouterr().out.splitlines()[1] == f"{idx.occupied},{idx.n_ref}"
    assert main(["sql", str(tiny_index), f"SELECT ref_id FROM lists WHERE best AND hash = {h}", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ref_id"] == idx.lists.best(np.array([700]))[0]


def test_sql_lists_view_is_every_place_once(tiny_index, capsys):
    """The ``lists`` view holds each place once at its own address."""
    from vprscale.method.index import read_index

    idx = read_index(tiny_index)
    assert main(["sql", str(tiny_index), "SELECT ref_id, hash FROM lists ORDER BY ref_id", "--csv"]) == 0
    rows = np.loadtxt(capsys.readouterr().out.splitlines()[1:], delimiter=",", dtype=np.uint64)
    np.testing.assert_array_equal(rows[:, 0], np.arange(idx.n_ref))
    np.testing.assert_array_equal(rows[:, 1], idx.ref_addresses())


@pytest.mark.parametrize(("query", "message"), [
    ("COPY (SELECT * FROM lists) TO '{tmp}/out.csv'", "only SELECT"),
    ("SELECT * FROM read_csv('/etc/passwd')", "Permission Error|disabled"),
    ("ATTACH '{tmp}/x.db' AS x", "only SELECT"),
    ("SELECT 1; SELECT 2", "exactly one statement"),
    ("INSTALL httpfs", "only SELECT"),
    ("LOAD httpfs", "only SELECT"),
    ("SET enable_external_access = true", "only SELECT"),
    ("CREATE TABLE t AS SELECT 1", "only SELECT"),
])
def test_sql_sandbox_refuses(tiny_index, tmp_path, capsys, query, message):
    import re

    code = main(["sql", str(tiny_index), query.format(tmp=tmp_path)])
    assert code == 2
    assert re.search(message, capsys.readouterr().err)
    assert not list(tmp_path.iterdir())


def test_occupancy_report(tiny_index, capsys):
    assert main(["occupancy", str(tiny_index), "--top", "3"]) == 0
    out = capsys.readouterr().out
    assert "52,500 refs in" in out and "of 4,096 addresses" in out
    model = pq.read_table(tiny_index / "components.parquet").to_pandas()
    shares = model.groupby("component")["share"].sum()
    np.testing.assert_allclose(shares, 1.0)


def test_index_refuses_bad_input(tiny_store, tmp_path, capsys):
    partial = tmp_path / "half.zarr"
    zarr.open_group(partial, mode="w").attrs["vprscale"] = {"complete": False}
    assert main(["index", str(partial)]) == 2
    assert "incomplete" in capsys.readouterr().err
    assert main(["index", str(tiny_store), "--d", "97", "--out", str(tmp_path / "i")]) == 2
    assert "d = 97: must be an integer between 1 and the descriptor width 96" in capsys.readouterr().err
    assert main(["index", str(tiny_store), "--k", "1", "--out", str(tmp_path / "i")]) == 2
    assert "k = 1: K must be an integer of at least 2" in capsys.readouterr().err
    assert main(["index", str(tiny_store), "--d", "41", "--k", "3", "--out", str(tmp_path / "i")]) == 2
    assert "exceed 2^64" in capsys.readouterr().err
    assert not (tmp_path / "i").exists()


@pytest.mark.parametrize("high", [2**20, 2**63])  # the packed (address, id) sort, and the stable-argsort fallback
def test_inverted_lists_sort_by_address_then_id(high):
    from vprscale.method.lists import inverted_lists

    rng = np.random.default_rng(4)
    h = rng.choice(rng.integers(0, high, 300, dtype=np.uint64), 5000)
    err = rng.integers(0, 3, 5000).astype(float)  # many ties for the single best
    lists = inverted_lists(h, err)
    order = np.argsort(h, kind="stable")
    np.testing.assert_array_equal(lists["order"], order)
    np.testing.assert_array_equal(lists["hash"], h[order])
    for a, off, size, best in zip(lists["addresses"], lists["offsets"], lists["sizes"], lists["best"], strict=True):
        ids = np.flatnonzero(h == a)
        assert off == np.searchsorted(h[order], a) and size == len(ids)
        assert best == ids[np.argmin(err[ids])]  # least error, ties to the smallest id


@pytest.mark.parametrize(("d", "k"), [(18, 2), (11, 3)])
def test_partitioned_lists_equal_the_in_memory_sort(tmp_path, d, k):
    """Sorting partition by partition (bounded memory) writes the files of one global sort, and
    those of an in-memory index of the same references (bit planes for K = 2, packed codes else;
    chunks of any length)."""
    from vprscale.method.coarsehash import CoarseHasher
    from vprscale.method.index import Index
    from vprscale.method.indexfile import TABLES, write_arrays, write_lists

    rng = np.random.default_rng(1)
    n = 100_000
    h = np.minimum(rng.integers(0, k**d, n), rng.integers(0, k**d, n)).astype(np.uint64)  # skewed buckets
    err = rng.random(n).astype(np.float32)
    err[::7] = 0.5  # ties: the smallest id is the single best
    bounds = [(a, min(n, a + 7000)) for a in range(0, n, 7000)]
    files = list(TABLES)
    got = {}
    for part_rows in (1 << 30, 5000):
        out = tmp_path / str(part_rows)
        out.mkdir()
        r = write_lists(out, lambda a, b: h[a:b], lambda a, b: err[a:b], bounds, n, d, k, quiet=True,
                        part_rows=part_rows)
        assert (r["partitions"] == 1) == (part_rows > n) and not (out / ".partitions").exists()
        assert sorted(p.name for p in out.iterdir()) == sorted(files)  # no work file left behind
        got[part_rows] = {f: (out / f).read_bytes() for f in files}
    assert got[5000] == got[1 << 30]
    centres = np.tile(np.linspace(-1.0, 1.0, k), (d, 1))
    hasher = CoarseHasher.from_fitted(k, 1 << 14, n, np.zeros(4), np.eye(d, 4), centres, np.ones(d))
    memory = tmp_path / "memory"
    memory.mkdir()
    idx = Index.from_addresses(h, hasher, err)
    write_arrays(memory, hasher, idx.ref_addresses(), idx.lists, {})
    assert {f: (memory / f).read_bytes() for f in files} == got[5000]


def _as_format_2(src, dst):
    """The directory format 2 wrote for the lists of ``src`` (plain arrays, ids ascending in a
    list, single bests apart, no manifest): what an index of an older vprscale looks like."""
    import shutil

    from vprscale.method.index import read_index
    from vprscale.method.lists import address_dtype

    idx = read_index(src)
    dst.mkdir()
    addr_t = address_dtype(idx.d, idx.k)
    offsets = idx.lists.starts.decode()
    ids = idx.lists.ids_range(0, idx.n_ref)
    best = ids[offsets[:-1]]
    for a in range(idx.occupied):
        ids[offsets[a]:offsets[a + 1]].sort()
    for name, arr, t in (("ref_hash", idx.ref_addresses(), addr_t), ("ids", ids, np.uint32),
                         ("addresses", idx.lists.occupied.decode(), addr_t), ("offsets", offsets, np.uint32),
                         ("best", best, np.uint32)):
        np.save(dst / f"{name}.npy", np.asarray(arr, t))
    shutil.copytree(src / "model", dst / "model")
    shutil.copy(src / "components.parquet", dst)
    meta = json.loads((src / "index.json").read_text())
    meta["format"] = 2
    del meta["layout"]
    (dst / "index.json").write_text(json.dumps(meta))
    (dst / "eval").mkdir()
    (dst / "eval" / "eval.json").write_text('{"mine": 1}')


def _as_format_3(src, dst):
    """The directory format 3 wrote for the lists of ``src``: the engine's succinct files (format 3's
    own, the form the engine still decodes into), buckets for SQL, the model and a manifest."""
    import shutil

    from vprscale.core.manifest import write_manifest
    from vprscale.method.engine import EngineWriter
    from vprscale.method.index import read_index

    idx = read_index(src)
    dst.mkdir()
    writer = EngineWriter(dst, idx.n_ref, idx.d, idx.k)
    writer.codes(0, idx.ref_addresses())
    offsets = idx.lists.starts.decode()
    writer.lists(idx.lists.occupied.decode(), np.diff(offsets), idx.lists.ids_range(0, idx.n_ref))
    layout = writer.close()
    shutil.copy(src / "buckets.parquet", dst)
    shutil.copytree(src / "model", dst / "model")
    shutil.copy(src / "components.parquet", dst)
    meta = json.loads((src / "index.json").read_text())
    meta.update({"format": 3, "layout": layout})
    (dst / "index.json").write_text(json.dumps(meta))
    write_manifest(dst)
    (dst / "eval").mkdir()
    (dst / "eval" / "eval.json").write_text('{"mine": 1}')


@pytest.mark.parametrize("fmt", [2, 3])
def test_an_old_index_is_refused_then_upgraded_without_refitting(tiny_index, tiny_store, tmp_path, capsys, fmt):
    from vprscale.method.indexfile import TABLES

    old = tmp_path / "old.index"
    (_as_format_2 if fmt == 2 else _as_format_3)(tiny_index, old)
    assert main(["localise", str(old), str(tiny_store / "query_qm1"), "--out", str(tmp_path / "m.parquet")]) == 2
    err = capsys.readouterr().err
    assert f"an index of format {fmt}" in err and f"vprscale index --upgrade {old}" in err
    assert main(["index", "--upgrade", str(old)]) == 0
    out = capsys.readouterr().out
    assert f"converted from format {fmt}" in out and "the index is" in out and "× the floor" in out
    for name in (*TABLES, "components.parquet", "model/centres.npy"):
        assert (old / name).read_bytes() == (tiny_index / name).read_bytes(), name  # what a fresh index writes
    assert not list(old.glob("*.npy")) and (old / "eval" / "eval.json").read_text() == '{"mine": 1}'
    capsys.readouterr()
    assert main(["verify", str(old)]) == 2  # the index verifies; its evaluation, of before manifests, cannot be
    assert "index verified" in capsys.readouterr().out
    assert main(["index", "--upgrade", str(old)]) == 0
    assert "format 4 already" in capsys.readouterr().out
    assert main(["index", "--upgrade", str(tmp_path / "nowhere")]) == 2
    assert "no index.json" in capsys.readouterr().err


def test_a_newer_index_is_refused_in_one_line(tiny_index, tmp_path, capsys):
    """What an older vprscale meets: an index of a format it does not know, refused by name."""
    import shutil

    new = tmp_path / "new.index"
    shutil.copytree(tiny_index, new)
    meta = json.loads((new / "index.json").read_text())
    (new / "index.json").write_text(json.dumps({**meta, "format": 5}))
    assert main(["occupancy", str(new)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("index format 5 is newer than this vprscale reads (4); upgrade vprscale")
    assert len(err.splitlines()) == 1


def test_bench_format_times_both_layouts_on_the_same_matches(tiny_store, tiny_index, capsys):
    """``bench format`` writes format 3's files of the index and rebuilds format 2's plain arrays,
    checks every layout gives the same matches, and prints each one's bytes, cost and the ratios
    (no time is asserted)."""
    assert main(["bench", "format", str(tiny_store), "--index", str(tiny_index), "--L", "20"]) == 0
    out = capsys.readouterr().out
    for L in (1, 20):  # the tables against format 3's files of the same index, answers checked equal
        assert re.search(rf"L = {L} paper, per query.*tables [\d.]+ .*files [\d.]+ .*tables / files = [\d.]+×", out)
    assert re.search(r"per-frame work \(look-up.*tables [\d.]+ .*files [\d.]+ .*tables / files = [\d.]+×", out)
    new, old = (float(x) for x in re.search(r"format 4 \(Parquet tables\) ([\d.]+) B/place .*"
                                            r"format 3 \(succinct .npy files\) ([\d.]+)", out).groups())
    assert new < old and re.search(r"load: decoded in memory, [\d.]+ s", out)
    for what in ("per-frame work", "L = 1 paper", "L = 20 paper", "L = 20 aligned"):
        assert re.search(rf"{what}.*succinct [\d.]+ .*plain [\d.]+ .*succinct / plain = [\d.]+×", out), what
    plain, succinct = (float(x) for x in re.search(r"succinct ([\d.]+), plain ([\d.]+)", out).groups()[::-1])
    assert succinct < plain  # bytes per place in memory


def test_bench_online_prints_push_against_the_batch_for_each_L(tiny_store, tiny_index, capsys):
    """``bench online`` with no ``--L``: L = 1, 50 and 100 in one run (both modes for sequences),
    each line with push's CPU time, its latency, push_many's and the batch's, and both ratios
    (the matches are checked equal inside; no time is asserted)."""
    assert main(["bench", "online", str(tiny_store), "--index", str(tiny_index)]) == 0
    out = capsys.readouterr().out
    number = r"(\d+\.\d+)"
    for L, mode in ((1, "paper"), (50, "paper"), (50, "aligned"), (100, "paper"), (100, "aligned")):
        line = re.search(rf"L = {L} +{mode} +push {number} µs a frame \(latency median {number}, p99 {number}\), "
                         rf"push_many {number} µs a frame, batch {number} µs a query; push / batch {number}, "
                         rf"push / push_many {number}", out)
        assert line, (L, mode)
        push, _, _, many, batch, to_batch, to_many = (float(v) for v in line.groups())
        assert to_batch == pytest.approx(push / batch, rel=0.05, abs=0.01)  # of the unrounded figures
        assert to_many == pytest.approx(push / many, rel=0.05, abs=0.01)


def test_a_large_index_is_decoded_once_into_a_checked_cache_and_mapped(tiny_index, tmp_path, monkeypatch, caplog):
    """Above the in-memory size an index's tables are decoded once into the engine cache; later
    loads memory-map it; a damaged or stale cache is decoded again, never read; where the cache
    cannot be written the arrays are decoded in memory. The same arrays every way."""
    import logging
    import shutil

    from vprscale.method import engine
    from vprscale.method.index import read_index

    want = read_index(tiny_index)  # in memory: below the threshold
    monkeypatch.setattr(engine, "IN_MEMORY_PLACES", 0)
    index = tmp_path / "copy.index"
    shutil.copytree(tiny_index, index)

    def same(idx):
        np.testing.assert_array_equal(idx.codes, want.codes)
        np.testing.assert_array_equal(idx.lists.ids, want.lists.ids)
        np.testing.assert_array_equal(idx.lists.starts.decode(), want.lists.starts.decode())
        np.testing.assert_array_equal(idx.lists.occupied.decode(), want.lists.occupied.decode())

    caplog.set_level(logging.INFO, logger="vprscale.method.engine")
    first = read_index(index)
    same(first)
    (cache,) = (tmp_path / "vprscale-cache" / "engines").iterdir()
    assert "decoding" in caplog.text and isinstance(first.lists.ids, np.memmap)
    caplog.clear()
    again = read_index(index)
    same(again)
    assert "decoding" not in caplog.text and isinstance(again.codes, np.memmap)
    ids = cache / "ids.npy"
    ids.write_bytes(ids.read_bytes()[:-8] + b"\xff" * 8)  # damaged: the manifest's checksum differs
    same(read_index(index))
    assert "decoding" in caplog.text
    caplog.clear()
    manifest = json.loads((index / "manifest.json").read_text())
    (index / "manifest.json").write_text(json.dumps(manifest, indent=2))  # re-published: another manifest
    same(read_index(index))
    assert "decoding" in caplog.text and len(list(cache.parent.iterdir())) == 1  # replaced, not beside
    caplog.clear()
    (cache / "manifest.json").unlink()  # then ids altered: without its manifest the folder is not trusted
    ids.write_bytes(ids.read_bytes()[:-8] + b"\xff" * 8)
    same(read_index(index))
    assert "decoding" in caplog.text
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("VPRSCALE_CACHE", str(tmp_path / "a-file" / "cache"))  # cannot be made, even by root
    same(read_index(index))
    assert "in memory" in caplog.text
    # an engines folder that is a link, or that others can write, is not used: nothing written through it
    caplog.clear()
    target, linked = tmp_path / "elsewhere", tmp_path / "linked-cache"
    target.mkdir()
    linked.mkdir()
    (linked / "engines").symlink_to(target)
    monkeypatch.setenv("VPRSCALE_CACHE", str(linked))
    same(read_index(index))
    assert "symbolic link" in caplog.text and not any(target.iterdir())
    shared = tmp_path / "shared-cache" / "engines"
    shared.mkdir(parents=True)
    shared.chmod(0o777)
    monkeypatch.setenv("VPRSCALE_CACHE", str(shared.parent))
    same(read_index(index))
    assert "writable by other users" in caplog.text and not any(shared.iterdir())


def test_bench_format_builds_no_plain_arrays_past_its_bound(tiny_store, tiny_index, monkeypatch):
    """Past ``PLAIN_PLACES`` (a billion places would take tens of GB and a sort per list, and were
    killed for memory) the plain side is one line saying so, not an attempt."""
    from vprscale.jobs import formatbench

    monkeypatch.setattr(formatbench, "PLAIN_PLACES", 1000)
    out = formatbench.bench_format(str(tiny_store), str(tiny_index))
    assert out.startswith("plain arrays (format 2's layout): not built for 52,500 places, above 1,000")
