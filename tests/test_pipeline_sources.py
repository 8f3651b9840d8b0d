"""A pipeline's build stage of your own descriptors or of MSLS, and MSLS's tasks in an eval stage
(docs/pipelines.md): the stages run the commands their keys name, the files they name are their
inputs (a changed byte re-runs the build and what reads it, nothing else does), and a bad stage
is one line before anything runs."""

import json

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main

from .test_own_data import own_files  # noqa: F401  (the fixture)

OWN = """
name = "walk"
out = "data/walk"
[[stages]]
name = "walk"
kind = "build"
ref = "{ref}"
query = ["day={day}", "night={night}"]
gt = ["{gt}"]
part = ["{part}"]
stride = 5
[[stages]]
name = "index"
kind = "index"
store = "walk"
[[stages]]
name = "eval"
kind = "eval"
store = "walk"
index = "index"
noise = ["night"]
L = [1, 20]
baseline = false
repeats = 1
"""


def _own_pipeline(tmp_path, files) -> str:
    path = tmp_path / "walk.toml"
    path.write_text(OWN.format(**{k: v.name for k, v in files.items()}))
    return str(path)


def _plan(pipeline: str, capsys) -> dict[str, str]:
    """Each stage's verdict in a dry run: ``run`` with its reasons, or ``skip``."""
    capsys.readouterr()
    assert main(["run", pipeline, "--dry-run"]) == 0
    lines = [line.split(None, 2) for line in capsys.readouterr().out.splitlines() if line[:4] in ("run ", "skip")]
    return {name: f"{verdict} {rest}" for verdict, name, rest in lines}


def test_a_pipeline_builds_your_own_descriptors_and_a_changed_file_re_runs_what_reads_it(
        own_files, tmp_path, capsys, monkeypatch):  # noqa: F811
    monkeypatch.chdir(tmp_path)
    pipeline = _own_pipeline(tmp_path, own_files)
    assert main(["run", pipeline]) == 0
    store = tmp_path / "data" / "walk" / "walk.zarr"  # named for its stage
    res = pd.read_parquet(next((tmp_path / "data" / "walk").rglob("results.parquet")))
    assert set(res.noise) == {"night"} and set(res.scale) == {"walk"} and set(res.L) == {1, 20}
    assert store.is_dir()
    assert all(v.startswith("skip") for v in _plan(pipeline, capsys).values())
    # a changed truth: the build re-runs, saying why, and so does everything that reads it
    gt = np.load(own_files["gt"])
    gt[20] = gt[21]
    np.save(own_files["gt"], gt)
    plan = _plan(pipeline, capsys)
    assert plan["walk"].startswith("run") and "input gt:gt.npy changed" in plan["walk"]
    assert plan["index"].startswith("run") and plan["eval"].startswith("run")
    # touched, not changed: nothing re-runs
    np.save(own_files["gt"], gt)
    assert main(["run", pipeline]) == 0
    np.save(own_files["gt"], gt)
    assert all(v.startswith("skip") for v in _plan(pipeline, capsys).values())


@pytest.mark.parametrize("edit, message", [
    (("ref = ", "scale = \"20K\"\nref = "), "give one of 'scale' (a recipe), 'ref' (your own descriptors) or "
                                            "'msls' (MSLS as it is laid out), not 'scale' and 'ref'"),
    (("stride = 5", "stride = 5\nrescale = false"), "key 'rescale' is not an option of a build of your own "
                                                    "descriptors ('ref')"),
    (("gt = [", "xgt = ["), "unknown key 'xgt' for a build stage"),
    (("gt = [\"gt.npy\"]", "cities = [\"cph\"]"), "key 'cities' is not an option of a build of your own"),
    (("part = [\"part.npy\"]", "part = [\"gone.npy\"]"), "stage 'walk': key 'part': gone.npy: no such file or folder"),
    (("L = [1, 20]", "L = [1, 20]\ntask = \"seq2seq\""), "key 'L': a task sets its own lengths ('seq_length')"),
    (("L = [1, 20]", "L = [1, 20]\nsubtask = \"o2n\""), "key 'subtask' is MSLS's task's; give 'task' too"),
    (("L = [1, 20]", "task = \"seq2sq\""), "key 'task' must be one of im2im, seq2im, im2seq, seq2seq, got 'seq2sq'"),
    (('[[stages]]\nname = "index"', '[[stages]]\nname = "20K"\nkind = "build"\nref = "ref.npy"\n'
                                    'query = ["day=day.fbin"]\ngt = ["gt.npy"]\n[[stages]]\nname = "b"\n'
                                    'kind = "build"\nscale = "20K"\n[[stages]]\nname = "index"'),
     "stages '20K' and 'b' both write 20K.zarr"),
])
def test_a_bad_build_or_task_stage_is_one_line_before_anything_runs(own_files, tmp_path, capsys, monkeypatch,  # noqa: F811
                                                                   edit, message):
    monkeypatch.chdir(tmp_path)
    pipeline = _own_pipeline(tmp_path, own_files)
    text = open(pipeline).read()
    assert edit[0] in text
    open(pipeline, "w").write(text.replace(edit[0], edit[1], 1))
    capsys.readouterr()
    assert main(["run", pipeline]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not list(tmp_path.rglob("*.zarr")) and not list(tmp_path.rglob("*.index"))  # nothing ran


MSLS = """
name = "msls"
out = "data/msls"
[[stages]]
name = "cities"
kind = "build"
msls = "MSLS"
cities = ["cph", "sf"]
descriptors = "MSLS/descriptors.npy"
keys = "MSLS/keys.txt"
[[stages]]
name = "index"
kind = "index"
store = "cities"
[[stages]]
name = "seq2seq"
kind = "eval"
store = "cities"
index = "index"
task = "seq2seq"
seq_length = 3
subtask = "all"
threshold = 25.0
baseline = false
compare = ["seq:PQ4"]
"""


def test_a_pipeline_builds_msls_and_evaluates_its_task(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["synth", "--msls", "--out", "MSLS", "--frames", "3000", "--cities", "cph,sf", "--dim", "32",
                 "-q"]) == 0
    (tmp_path / "msls.toml").write_text(MSLS)
    assert main(["run", "msls.toml"]) == 0
    evals = list((tmp_path / "data" / "msls").rglob("results.parquet"))
    assert len(evals) == 1
    res = pq.read_table(evals[0]).to_pandas()
    assert {"recall_at_1", "map_at_20"} <= set(res.columns)
    assert {"coarsehash", "seq:PQ4"} <= set(res.method)
    task = json.loads((evals[0].parent / "eval.json").read_text())["task"]
    assert task == {**task, "task": "seq2seq", "seq_length": 3, "subtask": "all"}
    # one of the chosen cities' tables changed: the build re-runs
    table = tmp_path / "MSLS" / "train_val" / "sf" / "query" / "raw.csv"
    text = table.read_text()
    table.write_text(text + "\n")
    assert "input msls changed" in _plan("msls.toml", capsys)["cities"]
    table.write_text(text)
    assert _plan("msls.toml", capsys)["cities"].startswith("skip")
    # a report stage draws the task's report; one that mixes it with the frame grid is refused when read
    report = '[[stages]]\nname = "report"\nkind = "report"\nresults = ["seq2seq"]\nout = "reports/msls"\n'
    (tmp_path / "msls.toml").write_text(MSLS + report)
    assert main(["run", "msls.toml"]) == 0
    md = (tmp_path / "reports" / "msls" / "report.md").read_text()
    assert "### seq2seq, 3 frames, subtask all, positives within 25 m" in md
    assert (tmp_path / "reports" / "msls" / "fig_tasks.png").is_file()
    grid = '[[stages]]\nname = "grid"\nkind = "eval"\nstore = "cities"\nindex = "index"\nL = [1, 3]\n'
    (tmp_path / "bad.toml").write_text(MSLS + grid + report.replace('["seq2seq"]', '["seq2seq", "grid"]'))
    capsys.readouterr()
    assert main(["run", "bad.toml", "--dry-run"]) == 2
    assert "'seq2seq' evaluates MSLS's task, 'grid' the frame grid" in capsys.readouterr().err


def test_two_evaluations_of_one_index_each_keep_their_own_results(own_files, tmp_path, capsys,  # noqa: F811
                                                                  monkeypatch):
    """Both would write INDEX/eval: each writes <out>/<stage> instead, the report reads both, and
    a second run finds everything up to date (the first is not lost to the second, nor re-run)."""
    monkeypatch.chdir(tmp_path)
    pipeline = _own_pipeline(tmp_path, own_files)
    more = ('[[stages]]\nname = "eval-long"\nkind = "eval"\nstore = "walk"\nindex = "index"\nnoise = ["night"]\n'
            'L = [40]\nbaseline = false\nrepeats = 1\n'
            '[[stages]]\nname = "report"\nkind = "report"\nresults = ["eval", "eval-long"]\nout = "reports/walk"\n')
    with open(pipeline, "a") as fh:
        fh.write(more)
    assert main(["run", pipeline, "-q"]) == 0
    out = tmp_path / "data" / "walk"
    assert {*pd.read_parquet(out / "eval" / "results.parquet").L} == {1, 20}
    assert {*pd.read_parquet(out / "eval-long" / "results.parquet").L} == {40}
    recall = pd.read_csv(tmp_path / "reports" / "walk" / "recall_table.csv")
    assert {*recall.L} == {1, 20, 40}
    assert all(v.startswith("skip") for v in _plan(pipeline, capsys).values())
