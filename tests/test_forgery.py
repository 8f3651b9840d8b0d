"""Nothing forged is served: every reader of a published output (store, index, evaluation,
encoding, report inputs) checks it against its manifest, an output of the manifest era without
one is refused, and no reader follows a symbolic link out of a published folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main

from .test_reliability import fails


@pytest.fixture(scope="module")
def evaluated(tiny_store, tiny_index, tmp_path_factory) -> Path:
    """A copy of the tiny index with its evaluation in ``eval/`` (CoarseHash and one FAISS code)."""
    index = tmp_path_factory.mktemp("forgery") / "tiny.index"
    shutil.copytree(tiny_index, index)
    assert main(["eval", str(tiny_store), str(index), "--L", "1,5", "--z", "97", "--noise", "qm1",
                 "--repeats", "1", "-q"]) == 0
    return index


@pytest.fixture
def index(evaluated, tmp_path) -> Path:
    copy = tmp_path / "i.index"
    shutil.copytree(evaluated, copy)
    return copy


def _same_size_edit(file: Path) -> None:
    """One byte changed in the middle of ``file``, its size kept: only a checksum can tell."""
    data = bytearray(file.read_bytes())
    data[len(data) // 2] ^= 0xFF
    file.write_bytes(bytes(data))


def _readers_of_results(index: Path, tmp_path: Path) -> list[list[str]]:
    return [["sql", str(index), "SELECT count(*) FROM results"], ["results", str(index)],
            ["report", str(index / "eval"), "--out", str(tmp_path / "r")], ["verify", str(index)]]


def test_a_tampered_results_file_is_served_by_no_reader(index, tmp_path, capsys):
    _same_size_edit(index / "eval" / "results.parquet")
    for argv in _readers_of_results(index, tmp_path):
        fails(capsys, argv, "results.parquet", "content changed")
    assert not (tmp_path / "r").exists()


def test_an_evaluation_without_its_manifest_is_refused(index, tmp_path, capsys):
    (index / "eval" / "manifest.json").unlink()
    for argv in _readers_of_results(index, tmp_path):
        fails(capsys, argv, "no manifest.json", "re-create it", "vprscale eval")


def test_an_evaluation_without_its_manifest_and_its_record_s_provenance_is_refused(index, tmp_path, capsys):
    """Removing the provenance key of eval.json too does not turn the checks off: the results' own
    Parquet metadata still says a vprscale that publishes manifests wrote them."""
    (index / "eval" / "manifest.json").unlink()
    record = json.loads((index / "eval" / "eval.json").read_text())
    record.pop("provenance")
    (index / "eval" / "eval.json").write_text(json.dumps(record))
    for argv in _readers_of_results(index, tmp_path):
        fails(capsys, argv, "no manifest.json", "re-create it")


def test_an_index_of_format_3_or_later_without_its_manifest_is_refused(index, tiny_store, tmp_path, capsys):
    (index / "manifest.json").unlink()
    lists = pq.read_table(index / "lists.parquet")  # what the missing manifest would have caught
    ids = np.random.default_rng(0).permutation(lists["ref_id"].to_numpy())
    pq.write_table(lists.set_column(1, "ref_id", pa.array(ids, pa.uint32())), index / "lists.parquet")
    for argv in (["occupancy", str(index)], ["sql", str(index), "SELECT 1"], ["verify", str(index)],
                 ["localise", str(index), str(tiny_store / "query_qm1"), "--L", "5"],
                 ["eval", str(tiny_store), str(index), "--L", "1", "--out", str(tmp_path / "e")]):
        fails(capsys, argv, str(index), "no manifest.json", "vprscale index")
    assert not (tmp_path / "e").exists()


def test_a_store_without_its_manifest_is_refused(tiny_store, tiny_index, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    shutil.copytree(tiny_store, store)
    (store / "manifest.json").unlink()
    fails(capsys, ["verify", str(store)], "no manifest.json", "re-create it")
    fails(capsys, ["index", str(store), "--out", str(tmp_path / "i")], "no manifest.json", "vprscale build")
    fails(capsys, ["localise", str(tiny_index), str(store / "query_qm1"), "--L", "5"], "no manifest.json")
    assert not (tmp_path / "i").exists()


def test_a_tampered_store_array_is_not_localised(tiny_store, tiny_index, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    shutil.copytree(tiny_store, store)
    _same_size_edit(store / "query_qm1" / "c" / "0" / "0")
    fails(capsys, ["localise", str(tiny_index), str(store / "query_qm1"), "--L", "5"], "query_qm1", "content changed")


@pytest.mark.parametrize("where", ["file", "folder"])
def test_no_reader_follows_a_symbolic_link_out_of_a_published_folder(where, index, tiny_store, tmp_path, capsys):
    """The same bytes elsewhere, linked in: refused, though every size and checksum would match."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if where == "file":
        target = index / "eval" / "results.parquet"
        shutil.copy(target, elsewhere / target.name)
        target.unlink()
        target.symlink_to(elsewhere / target.name)
        fails(capsys, ["results", str(index)], "results.parquet", "symbolic link")
        fails(capsys, ["report", str(index / "eval"), "--out", str(tmp_path / "r")], "symbolic link")
        fails(capsys, ["verify", str(index)], "symbolic link")
    else:
        model = index / "model"
        shutil.copytree(model, elsewhere / "model")
        shutil.rmtree(model)
        model.symlink_to(elsewhere / "model")
        fails(capsys, ["occupancy", str(index)], str(model), "symbolic link")
        fails(capsys, ["localise", str(index), str(tiny_store / "query_qm1"), "--L", "5"], "symbolic link")


def test_a_results_folder_that_is_no_published_evaluation_is_refused(index, tmp_path, capsys):
    """A results.parquet alone (no eval.json, no manifest) could come from anywhere."""
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(index / "eval" / "results.parquet", bare)
    fails(capsys, ["results", str(bare)], "not a published evaluation")
    fails(capsys, ["report", str(bare / "results.parquet"), "--out", str(tmp_path / "r")], "not a published evaluation")
    fails(capsys, ["sql", str(bare), "SELECT 1"], "not a published evaluation")


def test_a_manifest_naming_a_file_outside_its_output_is_refused(index, capsys):
    manifest = json.loads((index / "manifest.json").read_text())
    manifest["files"]["../outside"] = {"bytes": 1, "crc32c": "00000000"}
    (index / "manifest.json").write_text(json.dumps(manifest))
    fails(capsys, ["occupancy", str(index)], "manifest.json", "'../outside'", "not a file of the output")


def test_verify_covers_the_evaluation_inside_an_index(index, capsys):
    capsys.readouterr()
    assert main(["verify", str(index)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(": ")[1].split(" verified")[0] for line in lines] == ["index", "evaluation"]
    assert lines[1].startswith(f"{index / 'eval'}:")


def test_verify_refuses_an_evaluation_whose_record_and_manifest_were_removed(index, capsys):
    """A forger who deletes an index's evaluation record, results and manifest but leaves its
    queries does not get the index verified as if it had no evaluation."""
    for name in ("eval.json", "manifest.json", "results.parquet"):
        (index / "eval" / name).unlink()
    fails(capsys, ["verify", str(index)], str(index / "eval"))


def test_a_stored_encoding_without_its_manifest_or_with_changed_codes_is_refused(tiny_store, tiny_index, tmp_path,
                                                                                 small_training, capsys):
    store = tmp_path / "s.zarr"
    shutil.copytree(tiny_store, store)
    assert main(["encode", str(store), "--compare", "PQ4np", "-q"]) == 0
    encoding = tmp_path / "s.faiss" / "PQ4np"
    capsys.readouterr()
    assert main(["verify", str(encoding)]) == 0
    assert "encoding verified" in capsys.readouterr().out
    evaluate = ["eval", str(store), str(tiny_index), "--L", "1", "--compare", "PQ4np", "--out", str(tmp_path / "e")]
    _same_size_edit(encoding / "codes.npy")
    fails(capsys, evaluate, "codes.npy", "content changed")
    (encoding / "manifest.json").unlink()
    fails(capsys, evaluate, "no manifest.json", "vprscale encode")
    fails(capsys, ["verify", str(encoding)], "no manifest.json")
    assert not (tmp_path / "e").exists()


def _forged(tiny_index: Path, tmp_path: Path, edit) -> Path:
    """A copy of the tiny index with ``edit(folder)`` applied and its manifest written again: a
    forgery that every checksum passes, which only the tables' own checks can catch."""
    from vprscale.core.manifest import write_manifest

    forged = tmp_path / "forged.index"
    shutil.copytree(tiny_index, forged)
    (forged / "manifest.json").unlink()
    edit(forged)
    write_manifest(forged)
    return forged


def _meta(key: str, change):
    def edit(folder: Path) -> None:
        meta = json.loads((folder / "index.json").read_text())
        meta[key] = change(meta[key])
        (folder / "index.json").write_text(json.dumps(meta))
    return edit


def _table(name: str, column: str, change):
    def edit(folder: Path) -> None:
        table = pq.read_table(folder / name)
        values = table.column(column).to_numpy().copy()
        change(values)
        field = table.schema.field(column)
        table = table.set_column(table.schema.get_field_index(column), column, pa.array(values, field.type))
        pq.write_table(table, folder / name)
    return edit


def _last(values: np.ndarray, value) -> None:
    values[-1] = value


def _duplicate(values: np.ndarray) -> None:
    values[-1] = values[0]  # the last list's last id: now also the first list's first


@pytest.mark.parametrize("edit, words", [
    (_meta("d", lambda d: d + 3), "index.json"),
    (_meta("d", lambda d: d - 1), "index.json"),
    (_meta("n_ref", lambda n: n + 1000), "index"),
    (_meta("n_ref", lambda n: n - 1), "index"),
    (_meta("k", lambda k: 0), "k is 0"),
    (_meta("d", lambda d: 99), "64 bits"),
    (_table("lists.parquet", "ref_id", lambda v: _last(v, 52_500 + 7)), "ref_id outside"),
    (_table("lists.parquet", "ref_id", _duplicate), "index"),
    (_table("codes.parquet", "hash", lambda v: _last(v, 1 << 40)), "above K^d"),
    (_table("buckets.parquet", "hash", lambda v: _last(v, 0)), "ascending"),
], ids=["d-above", "d-below", "n_ref-above", "n_ref-below", "k-zero", "d-huge", "id-out-of-range", "id-twice",
        "code-out-of-range", "buckets-unsorted"])
def test_a_forged_index_whose_tables_disagree_with_its_index_json_is_refused(tiny_store, tiny_index, tmp_path,
                                                                            capsys, edit, words):
    """Tables and index.json that disagree (a lie about d, k or n_ref, an id out of range or in two
    lists, a code of more than d digits) are refused in one line by every reader, never evaluated
    with another recall or crashed on inside a kernel."""
    forged = _forged(tiny_index, tmp_path, edit)
    fails(capsys, ["occupancy", str(forged)], words)
    fails(capsys, ["eval", str(tiny_store), str(forged), "--L", "5", "--z", "97", "--noise", "qm1", "--repeats",
                   "1", "--out", str(tmp_path / "e"), "-q"])
    assert not (tmp_path / "e").exists()
