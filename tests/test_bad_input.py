"""Bad input anywhere: one line naming what is wrong, exit status 2, nothing published or lost."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main

from .conftest import write_recipe


def _fails(capsys, argv: list[str], *words: str) -> str:
    """The command exits 2 and its last line on stderr (after any progress lines) is the error."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    err = err.splitlines()[-1]
    assert err.startswith("vprscale "), err
    for w in words:
        assert w in err, err
    return err


def test_pickled_array_in_the_fas_file(tmp_path, sources, capsys):
    bad = tmp_path / "fas.npz"
    with zipfile.ZipFile(sources["fas"]) as src, zipfile.ZipFile(bad, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "arr_2.npy":
                buf = io.BytesIO()
                np.save(buf, np.array([{"x": 1}] * 5, dtype=object), allow_pickle=True)
                data = buf.getvalue()
            dst.writestr(info, data)
    recipe = write_recipe(tmp_path / "tiny.toml")
    _fails(capsys, ["build", "--scale", str(recipe), "--fas", str(bad), "--out", str(tmp_path / "o")], "arr_2")
    assert not (tmp_path / "o" / "tiny.zarr").exists()


@pytest.mark.parametrize(("field", "value", "word"), [
    ("seed", -7, "seed"), ("chunk_rows", 2**34, "chunk_rows"), ("scale", "../../x", "scale"),
    ("scale", "/abs/x", "scale"),
])
def test_bad_recipe_values(tmp_path, capsys, field, value, word):
    recipe = write_recipe(tmp_path / "r.toml", **{field: value})
    _fails(capsys, ["build", "--scale", str(recipe), "--out", str(tmp_path / "o"), "--dry-run"], word)
    assert not list(tmp_path.parent.glob("x*"))


def test_values_that_overflow_after_homogenising_are_rejected(tmp_path, sources, capsys):
    from vprscale.dataset.sources.synthetic import SyntheticDeep1B
    from vprscale.dataset.sources.writers import write_fvecs

    f = deep = tmp_path / "deep.fvecs"
    write_fvecs(SyntheticDeep1B(20_000, seed=3), deep)
    raw = np.fromfile(f, "<f4").reshape(-1, 97)
    raw[5000, 1:3] = 3e38  # two finite values in one row
    raw.tofile(f)
    recipe = write_recipe(tmp_path / "tiny.toml", deep1b_rows_read=20_000, deep1b_rows_kept=16_384)
    _fails(capsys, ["build", "--scale", str(recipe), "--deep1b", str(deep), "--fas", str(sources["fas"]),
                    "--out", str(tmp_path / "o")], "overflow", str(deep), "4,9")
    assert not (tmp_path / "o" / "tiny.zarr").exists()


def test_index_out_an_existing_file_is_kept(tiny_store, tmp_path, capsys):
    mine = tmp_path / "notes.txt"
    mine.write_text("mine")
    _fails(capsys, ["index", str(tiny_store), "--d", "8", "--out", str(mine)], "not a vprscale index")
    assert mine.read_text() == "mine"


def test_bad_summary_path_fails_before_any_work(tiny_store, tmp_path, capsys):
    out = tmp_path / "i.index"
    _fails(capsys, ["index", str(tiny_store), "--d", "8", "--out", str(out), "--summary",
                    str(tmp_path / "missing" / "s.json")], "--summary")
    _fails(capsys, ["index", str(tiny_store), "--d", "8", "--out", str(out), "--summary", str(tmp_path)], "--summary")
    assert not out.exists()


def test_report_inputs(tiny_index, tmp_path, capsys):
    _fails(capsys, ["report", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")], "results.parquet")
    other = tmp_path / "other.parquet"
    shutil.copy(tiny_index / "buckets.parquet", other)
    _fails(capsys, ["report", str(other), "--out", str(tmp_path / "r")], "no evaluation here")
    old = tmp_path / "old"  # an evaluation of before manifests: its files are read as they are
    old.mkdir()
    (old / "eval.json").write_text("{}")
    shutil.copy(tiny_index / "buckets.parquet", old / "results.parquet")
    _fails(capsys, ["report", str(old), "--out", str(tmp_path / "r")], "not a vprscale results file")
    cut = old / "results.parquet"
    cut.write_bytes((tiny_index / "buckets.parquet").read_bytes()[:500])
    _fails(capsys, ["report", str(cut), "--out", str(tmp_path / "r")], "Parquet")
    afile = tmp_path / "afile"
    afile.write_text("x")
    _fails(capsys, ["report", str(cut), "--out", str(afile)], "is a file")
    assert not (tmp_path / "r").exists()


def test_sql_on_a_damaged_index(tiny_index, tmp_path, capsys):
    broken = tmp_path / "broken.index"
    shutil.copytree(tiny_index, broken)
    (broken / "index.json").write_text("{not json")
    _fails(capsys, ["sql", str(broken), "SELECT 1"], "index.json")
    (broken / "index.json").write_text((tiny_index / "index.json").read_text())
    (broken / "buckets.parquet").unlink()
    _fails(capsys, ["sql", str(broken), "SELECT 1"], "buckets.parquet")


def test_synth_of_more_than_the_disk_holds_writes_nothing(tmp_path, capsys):
    """10^11 rows (about 77 TB) are refused before a byte is written, naming the rows asked for."""
    _fails(capsys, ["synth", "--out", str(tmp_path / "s"), "--deep1b-rows", "100000000000"], "GiB free",
           "--deep1b-rows 100,000,000,000")
    assert not any(p.is_file() for p in (tmp_path / "s").rglob("*"))


def test_synth_out_a_file(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    _fails(capsys, ["synth", "--out", str(afile), "--deep1b-rows", "100"], "is a file")
    assert afile.read_text() == "x"


def test_empty_lists_do_not_overwrite_results(tiny_store, tiny_index, tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1", "--no-baseline",
                 "--out", str(out)]) == 0
    before = (out / "results.parquet").read_bytes()
    capsys.readouterr()
    for flag in ("--noise", "--modes", "--L"):
        _fails(capsys, ["eval", str(tiny_store), str(tiny_index), flag, "", "--out", str(out)], flag)
    assert (out / "results.parquet").read_bytes() == before


def test_reindexing_keeps_evaluations(tiny_store, tmp_path, capsys):
    index = tmp_path / "x.index"
    assert main(["index", str(tiny_store), "--d", "8", "--out", str(index)]) == 0
    assert main(["eval", str(tiny_store), str(index), "--L", "1", "--noise", "qm1", "--no-baseline"]) == 0
    capsys.readouterr()
    _fails(capsys, ["index", str(tiny_store), "--d", "8", "--out", str(index)], "--force")
    assert (index / "eval" / "results.parquet").is_file()
    assert main(["index", str(tiny_store), "--d", "8", "--out", str(index), "--force"]) == 0
    kept = tmp_path / "x.index.previous-eval"
    assert (kept / "results.parquet").is_file() and not (index / "eval").exists()
    assert json.loads((index / "index.json").read_text())["complete"]
    # a second --force keeps the first one's copy too: the latest in .previous-eval, the earlier one numbered
    first = (kept / "results.parquet").read_bytes()
    assert main(["eval", str(tiny_store), str(index), "--L", "1", "--noise", "qm2", "--no-baseline"]) == 0
    second = (index / "eval" / "results.parquet").read_bytes()
    assert main(["index", str(tiny_store), "--d", "8", "--out", str(index), "--force"]) == 0
    assert (kept / "results.parquet").read_bytes() == second
    assert (tmp_path / "x.index.previous-eval.1" / "results.parquet").read_bytes() == first


def test_index_and_eval_on_one_index_are_serialised(tiny_store, tmp_path, capsys):
    """An evaluation holds its index's lock shared: re-indexing meanwhile is refused, not run
    under it, while another evaluation into another output runs; an evaluation is refused
    while the index is being written."""
    from vprscale.core.publish import exclusive, shared

    index = tmp_path / "y.index"
    assert main(["index", str(tiny_store), "--d", "8", "--out", str(index)]) == 0
    before = (index / "lists.parquet").read_bytes()
    capsys.readouterr()
    with shared(index):  # what `vprscale eval STORE y.index` holds while it runs
        _fails(capsys, ["index", str(tiny_store), "--d", "9", "--out", str(index), "--force"], "another vprscale job")
        assert main(["eval", str(tiny_store), str(index), "--L", "1", "--no-baseline", "--noise", "qm1",
                     "--out", str(tmp_path / "second")]) == 0
    with exclusive(index):  # what `vprscale index --out y.index` holds while it writes
        _fails(capsys, ["eval", str(tiny_store), str(index), "--L", "1", "--no-baseline"], "another vprscale job")
    assert (index / "lists.parquet").read_bytes() == before


def test_an_output_name_too_long_for_its_companions_is_one_line(tiny_store, tiny_index, tmp_path, capsys):
    """A 250-byte output name leaves no room for ``.<name>.partial`` and its lock: refused with
    one line before any work, nothing written."""
    name = "x" * 250
    for argv in (["index", str(tiny_store), "--d", "8", "--out", str(tmp_path / name)],
                 ["eval", str(tiny_store), str(tiny_index), "--L", "1", "--out", str(tmp_path / name)],
                 ["report", str(tiny_index / "eval"), "--out", str(tmp_path / name)]):
        _fails(capsys, argv, "the output's name is 250 bytes; at most 241 leave room")
    assert list(tmp_path.iterdir()) == []


def _null_first(folder: Path) -> str:
    x = np.random.default_rng(0).standard_normal((100, 8)).astype(np.float32)
    rows = [None] + [list(r) for r in x[1:]]
    pq.write_table(pa.table({"emb": pa.array(rows, pa.list_(pa.float32()))}), folder / "null.parquet")
    return f"{folder / 'null.parquet'}:emb"


def _later_file_without_the_column(folder: Path) -> str:
    x = np.random.default_rng(0).standard_normal((100, 8)).astype(np.float32)
    (folder / "parts").mkdir()
    for i, name in enumerate(("emb", "other")):
        rows = pa.array([list(r) for r in x[50 * i : 50 * (i + 1)]], pa.list_(pa.float32()))
        pq.write_table(pa.table({name: rows}), folder / "parts" / f"part-{i}.parquet")
    return f"{folder / 'parts'}:emb"


def _link_loop(folder: Path) -> str:
    (folder / "loop.npy").symlink_to(folder / "loop.npy")
    return str(folder / "loop.npy")


@pytest.mark.parametrize("make, words", [
    (_null_first, "null.parquet:emb: row 0 is null"),
    (_later_file_without_the_column, "part-1.parquet: no column 'emb', which the files before it hold"),
    (_link_loop, "--ref"),
])
def test_a_bad_reference_file_is_bad_input_not_a_bug(tmp_path, capsys, make, words):
    """Each of these was reported as vprscale's own failure (exit 1, "internal error"): a Parquet
    file whose first row is null, a Parquet folder whose later file lacks the column, a reference
    that is a loop of symbolic links. Each is the input's fault: one line naming it, exit 2."""
    x = np.random.default_rng(1).standard_normal((100, 8)).astype(np.float32)
    np.save(tmp_path / "q.npy", x)
    np.save(tmp_path / "gt.npy", np.arange(100))
    ref = make(tmp_path)
    last = _fails(capsys, ["build", "--ref", ref, "--query", f"q={tmp_path / 'q.npy'}", "--gt",
                          str(tmp_path / "gt.npy"), "--out", str(tmp_path / "o")], words)
    assert "internal error" not in last and not (tmp_path / "o" / "own.zarr").exists()
