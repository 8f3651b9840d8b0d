"""``vprscale encode``: FAISS encodings stored beside a store, resumable, read by ``eval --compare``."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.compared.encoding import GRAPH, LISTS, SEARCHED, WINDOW, encoding_dir

# 8-bit, 4-bit fast-scan and residual codes; over an IVF, an additive quantiser's and RaBitQ's records, a fast-scan
# additive quantiser's codes; a graph. The IVF-PQ in FAISS's `np` form (its own index, built
# here for comparison, skips the polysemous training vprscale never does), the flat PQ in the plain one
FACTORIES = ["PQ4", "PQ6x4fs", "IVF32,PQ4np", "IVF32,RQ2x8_Nqint8", "IVF32,RQ4x4fs_Nrq2x4", "PCA16,IVF32,RaBitQ",
             "HNSW16"]


@pytest.fixture
def store(tiny_store, tmp_path) -> Path:
    """A copy of the tiny store, so that its encodings do not reach other tests' evaluations."""
    copy = tmp_path / "data" / "tiny.zarr"
    shutil.copytree(tiny_store, copy)
    return copy


def _compare(factories: list[str]) -> list[str]:
    return [arg for f in factories for arg in ("--compare", f)]


def _codes(store: Path) -> dict[str, bytes]:
    return {f: np.load(encoding_dir(store, f) / "codes.npy").tobytes() for f in FACTORIES}


def _fail_at_third_chunk(monkeypatch) -> Callable:
    """Make the encode pass (one chunk a group) fail at its third chunk; the real task call."""
    import vprscale.jobs.encoding as enc

    monkeypatch.setattr(enc, "ENCODE_GROUP", 1)
    real, calls = enc._EncodeChunk.__call__, {"n": 0}

    def failing(self, a, b):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk vanished")
        return real(self, a, b)

    monkeypatch.setattr(enc._EncodeChunk, "__call__", failing)
    return real


@pytest.mark.slow
def test_stored_encoding_answers_as_the_evaluation_s_own(store, tiny_index, tmp_path, monkeypatch, capfd,
                                                          small_training):
    """An evaluation reading the stored encodings gives the answers, scores included, of one
    that encodes in its own process (IVF-PQ's searched on on-disk inverted lists merged from
    several shards, its window records memory-mapped; IVF-RQ's and IVF-RaBitQ's likewise); and it
    says which it did. A graph is stored linked. FAISS's
    bookkeeping of its on-disk lists stays out of the commands' output."""
    import ctypes

    import vprscale.compared.encoding as stored_format

    monkeypatch.setattr(stored_format, "SHARD_ROWS", 20_000)  # 52,500 places: three shards merged
    argv = ["eval", str(store), str(tiny_index), "--L", "1,9", "--z", "97", "--noise", "qm1", "--no-baseline",
            "--repeats", "1", *_compare(FACTORIES)]
    assert main([*argv, "--out", str(tmp_path / "inproc")]) == 0
    assert main(["encode", str(store), *_compare(FACTORIES), "--workers", "2"]) == 0
    for f in FACTORIES:
        meta = json.loads((encoding_dir(store, f) / "encoding.json").read_text())
        assert meta["factory"] == f and meta["n_ref"] == 52_500 and "commit" in json.dumps(meta["provenance"])
    for f in ("IVF32,PQ4np", "IVF32,RQ2x8_Nqint8", "PCA16,IVF32,RaBitQ"):
        ivf = {p.name for p in encoding_dir(store, f).iterdir()}
        assert {SEARCHED, LISTS, WINDOW} <= ivf and not any(name.startswith("shard") for name in ivf)
    assert SEARCHED not in {p.name for p in encoding_dir(store, "PQ4").iterdir()}  # flat codes load in memory
    assert GRAPH in {p.name for p in encoding_dir(store, "HNSW16").iterdir()}  # the graph linked once, stored
    assert main([*argv, "--out", str(tmp_path / "stored")]) == 0
    ctypes.CDLL(None).fflush(None)  # whatever C's stdio still buffers, into the captured output
    printed = "".join(capfd.readouterr())
    assert "IO_FLAG_ONDISK" not in printed and "resizing" not in printed and "wrote" in printed
    tables = [pq.read_table(tmp_path / d / "queries.parquet").to_pandas().sort_values(["method", "mode", "L", "t"])
              .reset_index(drop=True) for d in ("inproc", "stored")]
    cols = ["method", "params", "mode", "L", "t", "match", "score", "n_r", "in_list", "top"]
    assert len(tables[0]) > 500 and tables[0][cols].astype(str).equals(tables[1][cols].astype(str))
    used = json.loads((tmp_path / "stored" / "eval.json").read_text())["compare"]
    assert all(used[f"faiss:{f}"]["encoding"] == str(encoding_dir(store, f)) for f in FACTORIES)
    assert json.loads((tmp_path / "inproc" / "eval.json").read_text())["compare"]["faiss:PQ4"]["encoding"] is None


def test_an_encoding_is_not_redone_and_bad_input_is_refused(store, capsys):
    capsys.readouterr()
    assert main(["encode", str(store), "--compare", "PQ4x4", "--workers", "1"]) == 0
    n_ref = zarr.open_group(store, mode="r")["ref"].shape[0]
    said = capsys.readouterr().out  # the field's units: rows a second per core, GB of float32 rows a second
    assert f"encoded {n_ref:,} rows ({n_ref * 96 * 4 / 1e9:.2f} GB) in " in said and "per core on 1 core," in said
    before = (encoding_dir(store, "PQ4x4") / "codes.npy").stat().st_mtime_ns
    assert main(["encode", str(store), "--compare", "PQ4x4"]) == 0
    assert "encoded" not in capsys.readouterr().out  # nothing encoded: no throughput
    assert (encoding_dir(store, "PQ4x4") / "codes.npy").stat().st_mtime_ns == before
    capsys.readouterr()
    for argv, message in ((["--compare", "Banana"], "--compare Banana: not a FAISS index_factory string"),
                          (["--compare", "IVF100000,PQ4"], "100,000 inverted lists for 52,500 references")):
        assert main(["encode", str(store), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1
    assert not encoding_dir(store, "Banana").exists()


@pytest.mark.slow
def test_killed_encoding_resumes_to_the_bytes_of_one_run_on_any_workers(store, monkeypatch, capsys, small_training):
    """A run that fails after some chunks resumes from its checkpoint (the chunks done are not
    redone) and ends with the codes an uninterrupted run wrote, on 1 or 2 workers."""
    import vprscale.jobs.encoding as enc

    assert main(["encode", str(store), *_compare(FACTORIES), "--workers", "2"]) == 0
    whole = _codes(store)
    real = _fail_at_third_chunk(monkeypatch)
    # not the input's fault nor vprscale's: one line naming the error, exit 1, no traceback
    assert main(["encode", str(store), "--compare", "PQ4", "--force", "--workers", "1"]) == 1
    assert "vprscale encode: failed: disk vanished" in capsys.readouterr().err
    monkeypatch.setattr(enc._EncodeChunk, "__call__", real)
    counted = {"n": 0}

    def counting(self, a, b):
        counted["n"] += 1
        return real(self, a, b)

    monkeypatch.setattr(enc._EncodeChunk, "__call__", counting)
    assert main(["encode", str(store), "--compare", "PQ4", "--force", "--workers", "1"]) == 0
    assert counted["n"] == 4 - 2  # 52,500 rows in chunks of 16,384: two were done before the failure
    assert main(["encode", str(store), "--compare", "IVF32,PQ4np", "--force", "--workers", "1"]) == 0
    assert _codes(store) == whole


@pytest.mark.slow
def test_compact_store_encodes_to_the_full_store_s_bytes(store, sources, tmp_path):
    """The compact layout's references are recomputed from the sources: the same codes."""
    from vprscale.dataset.build import BuildRequest, build

    from .conftest import write_recipe

    recipe = write_recipe(tmp_path / "tiny.toml")
    build(BuildRequest(scale=str(recipe), out=tmp_path / "compact", deep1b=str(sources["fbin"]),
                       fas=str(sources["fas"]), workers=2, quiet=True, layout="compact"))
    compact = tmp_path / "compact" / "tiny.zarr"
    assert main(["encode", str(compact), *_compare(FACTORIES), "--deep1b", str(sources["fbin"]),
                 "--fas", str(sources["fas"])]) == 0
    assert main(["encode", str(store), *_compare(FACTORIES)]) == 0
    assert _codes(compact) == _codes(store)


def test_methods_share_one_sample_one_pass_and_one_coarse_assignment(store, monkeypatch):
    """Encoded together, the methods draw one training sample and read each chunk once, and the
    IVF codes of one coarse quantiser assign each chunk's rows once between them: the codes are
    the ones each method writes alone (FAISS's own standalone codes)."""
    import vprscale.jobs.encoding as enc
    from vprscale.compared.faisscodes import FaissCodes

    together = ["IVF32,PQ4x4", "IVF32,RQ2x4_Nqint8", "IVF32,RaBitQ", "PQ4x4"]  # 4-bit: cheap to train
    alone = {}
    for f in together:
        assert main(["encode", str(store), "--compare", f, "--workers", "1"]) == 0
        alone[f] = np.load(encoding_dir(store, f) / "codes.npy")
    calls = {"pick": 0, "chunk": 0, "assign": 0}

    def counted(cls, name, key):
        real = getattr(cls, name)

        def wrapper(self, *args):
            calls[key] += 1
            return real(self, *args)

        monkeypatch.setattr(cls, name, wrapper)

    counted(enc._Pick, "__call__", "pick")
    counted(enc._EncodeChunk, "__call__", "chunk")
    counted(FaissCodes, "assign_rows", "assign")
    assert main(["encode", str(store), *_compare(together), "--force", "--workers", "2"]) == 0
    assert calls == {"pick": 4, "chunk": 4, "assign": 4}  # 52,500 rows: four chunks of 16,384
    for f in together:
        np.testing.assert_array_equal(np.load(encoding_dir(store, f) / "codes.npy"), alone[f], err_msg=f)


def test_a_resumed_joint_pass_never_skips_a_method_started_afresh(store, monkeypatch, capsys):
    """A joint pass killed midway resumes only for the same code arrays: once one of its methods
    has been encoded again on its own (a fresh array), the joint run starts the pass over, and
    every method ends with the codes of an uninterrupted run."""
    import vprscale.jobs.encoding as enc

    pair = ["PQ4x4", "IVF32,PQ4x4"]
    assert main(["encode", str(store), *_compare(pair), "--workers", "1"]) == 0
    whole = {f: np.load(encoding_dir(store, f) / "codes.npy") for f in pair}
    real = _fail_at_third_chunk(monkeypatch)
    assert main(["encode", str(store), *_compare(pair), "--force", "--workers", "1"]) == 1  # two chunks done
    monkeypatch.setattr(enc._EncodeChunk, "__call__", real)
    shutil.rmtree(encoding_dir(store, "IVF32,PQ4x4").with_name(".IVF32_PQ4x4.partial"))  # that one started afresh
    assert main(["encode", str(store), *_compare(pair), "--force", "--workers", "1"]) == 0
    for f in pair:
        np.testing.assert_array_equal(np.load(encoding_dir(store, f) / "codes.npy"), whole[f], err_msg=f)


def test_inverted_lists_resume_after_a_failure(store, monkeypatch):
    """A run that fails while writing the on-disk lists' shards resumes without re-encoding or
    rewriting the shards already written, and publishes the lists of an uninterrupted run."""
    import faiss

    import vprscale.compared.encoding as stored_format
    import vprscale.jobs.encoding as enc

    monkeypatch.setattr(stored_format, "SHARD_ROWS", 20_000)
    assert main(["encode", str(store), "--compare", "IVF32,PQ4x4", "--workers", "1"]) == 0
    out = encoding_dir(store, "IVF32,PQ4x4")
    whole = {name: (out / name).read_bytes() for name in (LISTS, WINDOW)}
    written: list[str] = []
    real_write = faiss.write_index

    def failing_write(index, path):
        if "shard" in str(path):
            written.append(path)
            if len(written) == 2:
                raise OSError("disk vanished")
        return real_write(index, path)

    monkeypatch.setattr(stored_format.faiss, "write_index", failing_write)
    assert main(["encode", str(store), "--compare", "IVF32,PQ4x4", "--force", "--workers", "1"]) == 1
    encoded = {"n": 0}
    real_chunk = enc._EncodeChunk.__call__

    def counting(self, a, b):
        encoded["n"] += 1
        return real_chunk(self, a, b)

    monkeypatch.setattr(enc._EncodeChunk, "__call__", counting)
    assert main(["encode", str(store), "--compare", "IVF32,PQ4x4", "--force", "--workers", "1"]) == 0
    assert encoded["n"] == 0 and len(written) == 2 + 2  # the first shard kept; the second and third written
    assert {name: (out / name).read_bytes() for name in (LISTS, WINDOW)} == whole


@pytest.mark.parametrize("field, value, message", [
    ("format", 2, "not an encoding of PQ4x4 in this version's format; re-run vprscale encode with --force"),
    ("store_identity", "0123456789abcdef", "encodes another store than"),
])
def test_a_stale_encoding_is_refused_in_one_line(store, tiny_index, tmp_path, capsys, field, value, message):
    """An evaluation does not read an encoding of an older format or of another store: one
    line naming it, exit 2, and no evaluation written."""
    assert main(["encode", str(store), "--compare", "PQ4x4", "--workers", "1"]) == 0
    meta_file = encoding_dir(store, "PQ4x4") / "encoding.json"
    meta_file.write_text(json.dumps({**json.loads(meta_file.read_text()), field: value}))
    capsys.readouterr()
    out = tmp_path / "e"
    assert main(["eval", str(store), str(tiny_index), "--L", "1", "--compare", "PQ4x4", "--no-baseline",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and str(encoding_dir(store, "PQ4x4")) in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_a_budget_stops_an_encoding_before_its_graph_is_linked_and_the_next_run_links_it(store, monkeypatch, capsys):
    """Under a deadline (``vprscale run --budget``) the encode pass checkpoints, and a graph's link (one
    step, most of an hour at 10M) does not start once the deadline has passed: exit 75 with the codes
    kept; the next run links the graph without encoding again, to the bytes of an uninterrupted run."""
    import vprscale.jobs.encoding as enc
    from vprscale.core import deadline

    real_encode, linked = enc._encode, []

    def encode_then_run_out(*args, **kwargs):
        real_encode(*args, **kwargs)
        monkeypatch.setenv(deadline.ENV, "0")  # the budget ends as the codes are written

    monkeypatch.setattr(enc, "_encode", encode_then_run_out)
    real_graph = enc.write_graph
    monkeypatch.setattr(enc, "write_graph", lambda *a, **k: linked.append(1) or real_graph(*a, **k))
    assert main(["encode", str(store), "--compare", "HNSW16", "--workers", "1"]) == deadline.EXIT_MORE
    err = capsys.readouterr().err
    assert "stopped at a checkpoint, the time budget spent (HNSW16: every reference encoded, its graph not " \
           "written yet)" in err and not linked
    assert not encoding_dir(store, "HNSW16").exists()  # nothing published half made
    monkeypatch.delenv(deadline.ENV)
    monkeypatch.setattr(enc, "_encode", real_encode)
    counted = {"n": 0}
    real_chunk = enc._EncodeChunk.__call__
    monkeypatch.setattr(enc._EncodeChunk, "__call__", lambda self, a, b: counted.update(n=counted["n"] + 1)
                        or real_chunk(self, a, b))
    assert main(["encode", str(store), "--compare", "HNSW16", "--workers", "1"]) == 0
    assert linked == [1] and counted["n"] == 0  # the codes were kept: no chunk encoded again
    graph = (encoding_dir(store, "HNSW16") / GRAPH).read_bytes()
    assert main(["encode", str(store), "--compare", "HNSW16", "--force", "--workers", "1"]) == 0
    assert (encoding_dir(store, "HNSW16") / GRAPH).read_bytes() == graph
