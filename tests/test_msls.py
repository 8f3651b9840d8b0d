"""MSLS as it is (docs/bring-your-own.md, "MSLS"): its layout builds into a store, its tasks are
evaluated with its definitions, and the prediction files vprscale writes score, under MSLS's
own published scoring (re-implemented here from mapillary_sls's msls.py and eval.py, apart
from vprscale's code), exactly what vprscale reports."""

import json
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main

from .conftest import CHROMIUM, chromium, exact_method_in

CITIES = "cph,sf"
SUBTASK_NAMES = ["all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d"]


@pytest.fixture(scope="module")
def msls(tmp_path_factory):
    """A synthetic MSLS tree of two cities, built into a store with its descriptors in a keyed
    Parquet file (rows in another order than MSLS's), and indexed."""
    root = tmp_path_factory.mktemp("msls")
    assert main(["synth", "--msls", "--out", str(root / "MSLS"), "--frames", "6000", "--cities", CITIES,
                 "--dim", "32", "-q"]) == 0
    rows = np.load(root / "MSLS" / "descriptors.npy")
    keys = (root / "MSLS" / "keys.txt").read_text().split()
    order = np.random.default_rng(0).permutation(len(keys))  # any order: the build sorts them by key
    pq.write_table(pa.table({"key": [keys[i] for i in order],
                             "emb": pa.FixedSizeListArray.from_arrays(rows[order].ravel(), rows.shape[1])}),
                   root / "desc.parquet", row_group_size=1000)
    assert main(["build", "--msls", str(root / "MSLS"), "--cities", CITIES, "--descriptors",
                 str(root / "desc.parquet"), "--out", str(root / "data"), "-q"]) == 0
    assert main(["index", str(root / "data" / "msls.zarr"), "--out", str(root / "data" / "msls.index"), "-q"]) == 0
    return root


# --- MSLS's scoring, as mapillary_sls publishes it (datasets/msls.py, utils/eval.py) ---------------------------


def msls_windows(folder: Path, seq_length: int, subtask: str) -> tuple[list[str], list[np.ndarray]]:
    """``arange_as_seq`` then the subtask and panorama filters of the centre frame."""
    info = pd.read_csv(folder / "seq_info.csv", index_col=0)
    sub = pd.read_csv(folder / "subtask_index.csv", index_col=0)
    raw = pd.read_csv(folder / "raw.csv", index_col=0)
    keys, idxs = [], []
    for idx in range(len(info)):
        if idx < seq_length // 2 or idx >= len(info) - seq_length // 2:
            continue
        seq_idx = np.arange(-seq_length // 2, seq_length // 2) + 1 + idx
        seq = info.iloc[seq_idx]
        if len(np.unique(seq["sequence_key"])) == 1 and (seq["frame_number"].diff()[1:] == 1).all():
            keys.append(",".join(seq["key"]))
            idxs.append(seq_idx)
    keep = [i for i, idx in enumerate(idxs) if sub[subtask].values[idx[len(idx) // 2]]
            and not raw["pano"].values[idx[len(idx) // 2]]]
    return [keys[i] for i in keep], [idxs[i] for i in keep]


def msls_queries_and_positives(root: Path, task: str, seq_length: int, subtask: str, threshold: float = 25.0):
    from sklearn.neighbors import NearestNeighbors

    q_len, db_len = {"im2im": (1, 1), "seq2seq": (seq_length, seq_length), "seq2im": (seq_length, 1),
                     "im2seq": (1, seq_length)}[task]
    query_keys, positive_keys = [], []
    for city in CITIES.split(","):
        base = root / "train_val" / city
        q_keys, q_idxs = msls_windows(base / "query", q_len, subtask)
        db_keys, db_idxs = msls_windows(base / "database", db_len, subtask)
        q_pos = pd.read_csv(base / "query" / "postprocessed.csv", index_col=0)
        db_pos = pd.read_csv(base / "database" / "postprocessed.csv", index_col=0)
        uq, udb = np.unique(np.concatenate(q_idxs)), np.unique(np.concatenate(db_idxs))
        neigh = NearestNeighbors(algorithm="brute").fit(db_pos.loc[udb, ["easting", "northing"]].values)
        _, near = neigh.radius_neighbors(q_pos.loc[uq, ["easting", "northing"]].values, threshold)
        db_idx_arr = np.asarray(db_idxs)
        for key, idx in zip(q_keys, q_idxs, strict=True):
            frames = np.where(np.isin(uq, idx))[0]
            pos_frames = np.unique([p for f in frames for p in near[f]]).astype(int)
            if len(pos_frames):
                windows = np.unique(np.where(np.isin(db_idx_arr, udb[pos_frames]).reshape(db_idx_arr.shape))[0])
                query_keys.append(key)
                positive_keys.append([db_keys[w] for w in windows])
    return query_keys, positive_keys


def msls_scores(predictions: np.ndarray, query_keys, positive_keys, ks=(1, 5, 10, 20)) -> dict[str, float]:
    pred2gt = [np.where(predictions[:, 0:1] == key)[0][0] for key in query_keys]
    ranks = predictions[pred2gt, 1:]
    recall = np.zeros(len(ks))
    for qidx in range(ranks.shape[0]):
        for i, k in enumerate(ks):
            if np.sum(np.isin(ranks[qidx, :k], positive_keys[qidx])) > 0:
                recall[i:] += 1
                break
    recall /= ranks.shape[0]

    def apk(pidx, rank, k):
        rank = list(rank[:k])
        score, hits = 0.0, 0.0
        for i, p in enumerate(rank):
            if p in pidx and p not in rank[:i]:
                hits += 1.0
                score += hits / (i + 1.0)
        return score / min(len(pidx), k)

    out = {f"recall_at_{k}": recall[i] for i, k in enumerate(ks)}
    out |= {f"map_at_{k}": np.mean([apk(p, r, k) for p, r in zip(positive_keys, ranks, strict=True)]) for k in ks}
    return out


# ---------------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("task, seq_length, subtask", [("im2im", 1, "all"), ("seq2seq", 5, "all"),
                                                       ("seq2im", 3, "o2n"), ("im2seq", 3, "all")])
def test_msls_scores_vprscale_s_predictions_as_vprscale_does(msls, task, seq_length, subtask, capsys, monkeypatch):
    out = msls / f"eval-{task}"
    pred = msls / f"pred-{task}.csv"
    argv = ["eval", str(msls / "data" / "msls.zarr"), str(msls / "data" / "msls.index"), "--task", task,
            "--subtask", subtask, "--compare", "PQ4", "--out", str(out), "--export-msls", str(pred), "-q"]
    if task != "im2im":
        argv += ["--seq-length", str(seq_length)]
    if task.startswith("seq"):  # a pooled descriptor's windows: only MSLS's database windows
        argv += ["--compare", "seq:PQ4"]
    if task == "seq2seq":  # a method of your own answers the tasks too
        argv += ["--method", exact_method_in(msls, "exactmsls", monkeypatch), "--method-k", "8"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    results = pq.read_table(out / "results.parquet").to_pandas()
    results = results[results["part"] == "all"]
    query_keys, positive_keys = msls_queries_and_positives(msls / "MSLS", task, seq_length, subtask)
    assert len(query_keys) > 100
    files = sorted(msls.glob(f"pred-{task}.*.csv"))
    assert len(files) == len(results) >= 3  # coarsehash (two modes at L > 1), baseline, faiss:PQ4
    for row in results.itertuples():
        name = row.method.replace(":", "_") + (f"-{row.mode}" if isinstance(row.mode, str) else "")
        predictions = np.loadtxt(msls / f"pred-{task}.{name}.csv", ndmin=2, dtype=str)  # as evaluate.py reads it
        assert set(predictions[:, 0]) == set(query_keys)  # a prediction for every query MSLS evaluates, no other
        assert predictions.shape[1] == 21
        theirs = msls_scores(predictions, query_keys, positive_keys)
        for metric, value in theirs.items():
            assert getattr(row, metric) == pytest.approx(value, abs=1e-12), (row.method, row.mode, metric)
            assert f"{value:.3f}" in printed
    # the task is not trivial for these methods, nor beyond them
    assert 0.05 < results["recall_at_1"].max() and results["recall_at_1"].min() < 0.99


def test_a_bad_msls_tree_is_one_line(tmp_path, capsys):
    root = tmp_path / "MSLS"
    assert main(["synth", "--msls", "--out", str(root), "--frames", "600", "--cities", "cph,sf", "-q"]) == 0
    desc = ["--descriptors", str(root / "descriptors.npy"), "--keys", str(root / "keys.txt")]
    cases = [
        (["--cities", "cph,paris"], "--cities paris: no paris folder"),
        (["--cities", "cph", "--keys", str(tmp_path / "short.txt")], "keys for"),
        (["--cities", "cph", "--keys", str(tmp_path / "dup.txt")], "is there twice"),
        (["--cities", "cph", "--keys", str(tmp_path / "other.txt")], "no descriptor for image"),
    ]
    keys = (root / "keys.txt").read_text().split()
    (tmp_path / "short.txt").write_text("\n".join(keys[:-1]) + "\n")
    (tmp_path / "dup.txt").write_text("\n".join([keys[0], *keys[:-1]]) + "\n")
    (tmp_path / "other.txt").write_text("\n".join(["zz" + k for k in keys[:1]] + keys[1:]) + "\n")
    for extra, message in cases:
        argv = ["build", "--msls", str(root), *desc, "--out", str(tmp_path / "data"), *extra]
        assert main(argv) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (extra, err)
    os.remove(root / "train_val" / "sf" / "query" / "raw.csv")
    assert main(["build", "--msls", str(root), *desc, "--cities", "cph,sf", "--out", str(tmp_path / "data")]) == 2
    assert "raw.csv: missing" in capsys.readouterr().err
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").iterdir())


@pytest.mark.slow
def test_the_pages_msls_example_runs_as_written(tmp_path, monkeypatch, capsys):
    """docs/bring-your-own.md's MSLS block, line by line, as a new user runs it."""
    import re
    import shlex

    doc = (Path(__file__).parents[1] / "docs" / "bring-your-own.md").read_text()
    block = next(b for b in re.findall(r"```bash\n(.*?)```", doc, re.S) if "synth --msls" in b)
    monkeypatch.chdir(tmp_path)
    for line in block.strip().splitlines():
        argv = shlex.split(line)
        assert argv[0] == "vprscale"
        assert main(argv[1:]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "recall_at_1" in out and "seq:PQ8" in out and "map_at_20" in out
    assert (tmp_path / "data" / "pred.coarsehash-paper.csv").is_file()
    assert (tmp_path / "data" / "pred.seq_PQ8.csv").is_file()


@pytest.mark.slow
def test_a_test_city_without_positions_is_exported_not_scored(tmp_path, capsys):
    """MSLS's test cities have no positions: the store builds, a task says it cannot score, and
    --export-msls writes the predictions MSLS's server would score, one line per query window."""
    import shutil

    root = tmp_path / "MSLS"
    assert main(["synth", "--msls", "--out", str(root), "--frames", "1000", "--cities", "athens", "-q"]) == 0
    (root / "test").mkdir()
    shutil.move(root / "train_val" / "athens", root / "test" / "athens")
    for side in ("database", "query"):
        for name in ("postprocessed.csv", "raw.csv"):
            (root / "test" / "athens" / side / name).unlink()
    assert main(["build", "--msls", str(root), "--cities", "athens", "--descriptors", str(root / "descriptors.npy"),
                 "--keys", str(root / "keys.txt"), "--out", str(tmp_path / "data"), "-q"]) == 0
    store, index = tmp_path / "data" / "msls.zarr", tmp_path / "data" / "msls.index"
    assert main(["index", str(store), "--out", str(index), "-q"]) == 0
    capsys.readouterr()
    base = ["eval", str(store), str(index), "--task", "seq2seq", "--seq-length", "3", "--no-baseline", "-q"]
    assert main([*base, "--out", str(tmp_path / "e1")]) == 2
    assert "holds no positions" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "e2"), "--modes", "paper", "--export-msls",
                 str(tmp_path / "p.csv")]) == 0
    lines = (tmp_path / "p.csv").read_text().splitlines()
    _, idxs = msls_windows_test(root / "test" / "athens" / "query", 3)
    assert len(lines) == len(idxs) and all(len(line.split(" ")) == 21 for line in lines)


def msls_windows_test(folder: Path, seq_length: int) -> tuple[list[str], list[np.ndarray]]:
    """MSLS's test mode: windows of the subtask 'all' (no panorama filter: no raw.csv)."""
    info = pd.read_csv(folder / "seq_info.csv", index_col=0)
    keys, idxs = [], []
    for idx in range(seq_length // 2, len(info) - seq_length // 2):
        seq = info.iloc[np.arange(-seq_length // 2, seq_length // 2) + 1 + idx]
        if len(np.unique(seq["sequence_key"])) == 1 and (seq["frame_number"].diff()[1:] == 1).all():
            keys.append(",".join(seq["key"]))
            idxs.append(idx)
    return keys, idxs


@pytest.mark.slow
def test_a_task_evaluation_is_reported_apart_from_the_frame_grid(msls, capsys):
    """``report`` draws a task's scores as ``vprscale results`` reads them, every method and city,
    and refuses in one line to mix them with an evaluation of the frame grid."""
    out = msls / "eval-report"
    assert main(["eval", str(msls / "data" / "msls.zarr"), str(msls / "data" / "msls.index"), "--task", "im2im",
                 "--no-baseline", "--out", str(out), "-q"]) == 0
    assert main(["report", str(out), "--out", str(msls / "report"), "-q"]) == 0
    md = (msls / "report" / "report.md").read_text()
    res = pd.read_parquet(out / "results.parquet")
    assert "### im2im, subtask all, positives within 25 m" in md
    for row in res.itertuples():  # every row, as results.parquet holds it
        line = next(x for x in md.splitlines() if x.startswith(f"| CoarseHash d={int(row.d)} (single) | {row.part} |"))
        assert f"| {100 * row.recall_at_1:.1f} |" in line and f"| {row.map_at_20:.3f} |" in line
    assert (msls / "report" / "fig_tasks.png").is_file() and (msls / "report" / "task_table.csv").is_file()
    page = (msls / "report" / "report.html").read_text()
    rows = json.loads(page.split('<script id="rows" type="application/json">', 1)[1].split("</script>", 1)[0])
    assert len(rows) == 4 * len(res)  # every row of results.parquet at each k
    for row in res.itertuples():
        for k in (1, 5, 10, 20):
            r = next(r for r in rows if r["series"] == f"CoarseHash d={int(row.d)} (single)" and r["part"] == row.part
                     and r["k"] == k)
            assert r["recall"] == getattr(row, f"recall_at_{k}") and r["map"] == getattr(row, f"map_at_{k}")
    assert "im2im, subtask all, positives within 25 m</h" in page  # report.md below, whole
    grid = msls / "eval-grid"
    assert main(["eval", str(msls / "data" / "msls.zarr"), str(msls / "data" / "msls.index"), "--L", "1,3",
                 "--no-baseline", "--out", str(grid), "-q"]) == 0
    capsys.readouterr()
    assert main(["report", str(out), str(grid), "--out", str(msls / "report2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a report draws one or the other" in err[0]
    assert not (msls / "report2").exists()
    capsys.readouterr()
    assert main(["results", str(out)]) == 0
    assert "map_at_20" in capsys.readouterr().out


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (.ci/run installs it)")
def test_the_task_report_page_draws_each_city_it_is_asked_for(msls):
    """The tasks' report.html, opened by headless Chromium from the file alone: no error, both
    figures drawn over every query at first (a point a method and k), and a city's rows alone
    when the address asks for that city."""
    out = msls / "eval-page"
    assert main(["eval", str(msls / "data" / "msls.zarr"), str(msls / "data" / "msls.index"), "--task", "im2im",
                 "--compare", "PQ4", "--no-baseline", "--out", str(out), "-q"]) == 0
    assert main(["report", str(out), "--out", str(msls / "page"), "-q"]) == 0
    res = pd.read_parquet(out / "results.parquet")
    page = (msls / "page" / "report.html").as_uri()
    for part in ("all", *CITIES.split(",")):
        loaded = chromium("--dump-dom", page + ("" if part == "all" else f"#part={part}"))
        assert ":CONSOLE" not in loaded.stderr, loaded.stderr
        dom = loaded.stdout
        assert 'data-drawn="yes"' in dom and '<pre id="page-errors" hidden=""></pre>' in dom
        for fig in ("fig-recall", "fig-map"):
            block = dom.split(f'id="{fig}"', 1)[1].split('class="figure"', 1)[0]
            assert int(re.search(r'data-points="(\d+)"', block).group(1)) == 4 * int((res.part == part).sum()) > 0
            assert block.count('class="point"') > 0  # Plotly drew them
            table = dom.split(f'id="{fig}-table"', 1)[1].split("</table>", 1)[0]
            assert set(re.findall(r'data-part="([^"]+)"', table)) == {part}
            series = set(re.findall(r'data-series="([^"]+)"', table))
            assert {s.split(" ")[0] for s in series} == {"CoarseHash", "PQ4"}
