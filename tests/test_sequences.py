"""Many sequences (docs/bring-your-own.md, "Many sequences"): a window is L rows of one sequence
with consecutive frame numbers, and no method ever forms, scores or returns one that crosses a
sequence's end or a gap; the windows left out are counted."""

import json

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from vprscale.cli import main
from vprscale.compared.baseline import baseline_batch
from vprscale.method.kernels import ranked_lists, window_proposals
from vprscale.protocol import Sequences, query_centres

from .conftest import exact_method_in

DIM = 24


def brute_ok(seq: np.ndarray, frame: np.ndarray, t: int, L: int) -> bool:
    """The definition, row by row: L rows of one sequence, frame numbers one after another."""
    first = t - L // 2
    if first < 0 or first + L > len(seq):
        return False
    rows = range(first, first + L)
    return all(seq[r] == seq[first] and frame[r] == frame[first] + (r - first) for r in rows)


def test_a_window_exists_only_inside_one_sequence_without_a_gap():
    rng = np.random.default_rng(3)
    seq = np.repeat([7, 2, 7, 9], [5, 8, 1, 12])  # a key may come back later: that is another run
    frame = np.concatenate([np.arange(5), np.arange(8) + 100, [3], np.r_[np.arange(6), np.arange(7, 13)]])
    s = Sequences(seq, frame)
    assert s.runs == 5  # the last sequence has a gap (frame 6 missing): two runs
    for L in (1, 2, 3, 5, 6, 13):
        want = np.array([brute_ok(seq, frame, t, L) for t in range(len(seq))])
        assert (s.mask(L).astype(bool) == want).all(), L
        assert s.missing(L) == int((~want).sum())
    gt = rng.integers(0, 3, len(seq)) - 1  # some rows without truth
    got = query_centres(lambda t: gt[t], len(seq), len(seq), 1, 5, s).t
    assert list(got) == [t for t in range(len(seq)) if brute_ok(seq, frame, t, 5) and gt[t] >= 0]


def test_the_candidate_kernels_keep_to_the_windows_that_exist():
    """Proposals (CoarseHash's, the FAISS codes', own methods') and the baseline's scan never
    hold a centre the mask rules out, and do hold such centres without it."""
    rng = np.random.default_rng(0)
    n_ref, L = 400, 9
    seq = np.repeat(np.arange(8), 50)
    frame = np.tile(np.arange(50), 8)
    frame[220:] += 1  # a gap inside sequence 4
    valid = Sequences(seq, frame).mask(L)
    ids = rng.integers(0, n_ref, size=(60, 6))
    pos = np.arange(L // 2, 60 - L // 2)
    for aligned in (False, True):
        cand, first, n_r = window_proposals(pos, L, aligned, ranked_lists(ids), n_ref, valid)
        found = np.concatenate([cand[first[i]:first[i] + n_r[i]] for i in range(len(pos))])
        assert len(found) and valid[found].all()
        cand, first, n_r = window_proposals(pos, L, aligned, ranked_lists(ids), n_ref)
        found = np.concatenate([cand[first[i]:first[i] + n_r[i]] for i in range(len(pos))])
        assert not valid[found].all()  # the test holds crossing proposals to leave out
    x = rng.normal(size=n_ref)
    y = rng.normal(size=80)
    top, _, _ = baseline_batch(np.arange(10, 70), L, 40, x, y, float(np.ptp(x)), valid, 20)
    assert (top >= 0).all() and valid[top].all()
    top, _, _ = baseline_batch(np.arange(10, 70), L, 40, x, y, float(np.ptp(x)), np.zeros(0, np.uint8), 20)
    assert not valid[top].all()


def _drives(tmp_path, sequences: bool = True):
    """A route seen by drives of different lengths: the references four drives (one with a gap in
    its frame numbers), the queries three others, over the same places, one after another in the
    files, so that a window running off a drive's end lands somewhere else on the route."""
    rng = np.random.default_rng(11)
    route = np.cumsum(rng.normal(size=(1400, DIM)), axis=0) / 10
    ref_drives = [np.arange(0, 420), np.arange(500, 760), np.arange(300, 560), np.r_[np.arange(900, 1100),
                                                                                     np.arange(1110, 1400)]]
    query_drives = [np.arange(40, 400), np.arange(520, 740), np.arange(950, 1380)]

    def table(drives, prefix):
        keys = [f"{prefix}{i:03d}" for i in range(len(drives))]
        return pd.DataFrame({"key": [f"{prefix}{i}-{j}" for i, d in enumerate(drives) for j in range(len(d))],
                             "frame_number": np.concatenate([d - d[0] for d in drives]),
                             "sequence_key": [keys[i] for i, d in enumerate(drives) for _ in d]})

    ref_places, query_places = np.concatenate(ref_drives), np.concatenate(query_drives)
    ref = route[ref_places] + rng.normal(scale=0.05, size=(len(ref_places), DIM))
    query = route[query_places] + rng.normal(scale=0.15, size=(len(query_places), DIM))
    first_row = {p: r for r, p in reversed(list(enumerate(ref_places)))}
    gt = np.array([first_row.get(p, -1) for p in query_places])
    for name, a in (("ref", ref), ("query", query), ("gt", gt)):
        np.save(tmp_path / f"{name}.npy", a.astype(np.float32) if name != "gt" else a)
    table(ref_drives, "r").to_csv(tmp_path / "ref_seq.csv")  # MSLS's seq_info.csv: an unnamed index first
    pq.write_table(__import__("pyarrow").Table.from_pandas(table(query_drives, "q")), tmp_path / "query_seq.parquet")
    argv = ["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'query.npy'}",
            "--gt", str(tmp_path / "gt.npy"), "--out", str(tmp_path / "data"), "--quiet"]
    if sequences:
        argv += ["--ref-seq", str(tmp_path / "ref_seq.csv"), "--query-seq", str(tmp_path / "query_seq.parquet"),
                 "--name", "drives"]
    else:
        argv += ["--name", "oneroute"]
    assert main(argv) == 0
    return ref_places, query_places


@pytest.fixture
def exact_method(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return exact_method_in(tmp_path, "exactseq", monkeypatch)


def _evaluate(tmp_path, name: str, method: str, capsys) -> tuple[pd.DataFrame, str]:
    store, index, out = (tmp_path / "data" / f"{name}.zarr", tmp_path / "data" / f"{name}.index",
                         tmp_path / "data" / f"{name}.eval")
    assert main(["index", str(store), "--out", str(index), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["eval", str(store), str(index), "--L", "1,9", "--z", "3", "--compare", "PQ4x4", "--compare",
                 "seq:PQ4x4", "--compare", "seq:PQ4x4+rerank", "--method", method, "--out", str(out),
                 "--quiet"]) == 0
    return pq.read_table(out / "queries.parquet").to_pandas(), capsys.readouterr().out


@pytest.mark.slow
def test_no_method_forms_scores_or_returns_a_window_across_drives(tmp_path, exact_method, capsys):
    ref_places, query_places = _drives(tmp_path)
    seq = pd.read_csv(tmp_path / "ref_seq.csv")
    ref_seq = Sequences(pd.factorize(seq["sequence_key"])[0], seq["frame_number"].to_numpy())
    qseq = pd.read_parquet(tmp_path / "query_seq.parquet")
    query_seq = Sequences(pd.factorize(qseq["sequence_key"])[0], qseq["frame_number"].to_numpy())
    queries, printed = _evaluate(tmp_path, "drives", exact_method, capsys)
    long = queries[queries["L"] == 9]
    assert set(long["method"]) == {"coarsehash", "baseline", "faiss:PQ4x4", "seq:PQ4x4", "seq:PQ4x4+rerank",
                                   exact_method}
    assert query_seq.window_ok(long["t"].to_numpy(), 9).all()  # every query a window of one drive
    returned = np.concatenate(long["top"].to_numpy())
    returned = returned[returned >= 0]
    assert len(returned) > 10 * len(long) and ref_seq.mask(9)[returned].all()  # every answer one too
    for method, rows in long.groupby("method"):  # and the answers are good ones: the matcher works
        near = np.abs(ref_places[rows["match"]] - query_places[rows["t"]]) <= 3  # drives overlap: by place
        assert near.mean() > (0.95 if method == exact_method else 0.1), method  # by chance: 0.005
    eval_json = json.loads((tmp_path / "data" / "drives.eval" / "eval.json").read_text())
    counted = eval_json["windows"]["9"]
    assert counted["places_without_window"] == ref_seq.missing(9) == 5 * 8  # 4 drives, one with a gap: 5 runs
    t = np.arange(0, len(query_places), 3)
    assert counted["query_centres_without_window"] == int((~query_seq.window_ok(t, 9)).sum()) > 0
    assert f"{counted['query_centres_without_window']:,} query centres and 40 places have no window" in printed

    # the same rows as one traverse: the test's data does draw windows across drives, so the
    # checks above would catch a matcher that forms them
    _drives(tmp_path, sequences=False)
    queries, _ = _evaluate(tmp_path, "oneroute", exact_method, capsys)
    long = queries[queries["L"] == 9]
    assert not query_seq.window_ok(long["t"].to_numpy(), 9).all()
    for method, rows in long.groupby("method"):
        returned = np.concatenate(rows["top"].to_numpy())
        assert not ref_seq.mask(9)[returned[returned >= 0]].all(), method


@pytest.mark.parametrize("flags, message", [
    (["--ref-seq", "REF"], "--query-seq missing"),
    (["--ref-seq", "REF", "--query-seq", "SHORT"], "3 query sequences rows for"),
    (["--ref-seq", "REF", "--query-seq", "NOCOL"], "needs a sequence_key or sequence column"),
    (["--ref-seq", "REF", "--query-seq", "NULL"], "row 1 has no frame_number"),
])
def test_bad_sequences_are_one_line(tmp_path, capsys, flags, message):
    n = 40
    np.save(tmp_path / "ref.npy", np.random.default_rng(0).normal(size=(n, 8)).astype(np.float32))
    np.save(tmp_path / "gt.npy", np.arange(n))
    files = {"REF": tmp_path / "ref.csv", "SHORT": tmp_path / "short.csv", "NOCOL": tmp_path / "nocol.csv",
             "NULL": tmp_path / "null.csv"}
    pd.DataFrame({"sequence_key": ["a"] * n, "frame_number": np.arange(n)}).to_csv(files["REF"], index=False)
    pd.DataFrame({"sequence_key": ["a"] * 3, "frame_number": np.arange(3)}).to_csv(files["SHORT"], index=False)
    pd.DataFrame({"drive": ["a"] * n, "frame_number": np.arange(n)}).to_csv(files["NOCOL"], index=False)
    (files["NULL"]).write_text("sequence_key,frame_number\na,0\na,\n" + "".join(f"a,{i}\n" for i in range(2, n)))
    argv = ["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'ref.npy'}", "--gt",
            str(tmp_path / "gt.npy"), "--out", str(tmp_path / "data"), *[str(files.get(f, f)) for f in flags]]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "data" / "ref.zarr").exists()


@pytest.mark.slow
def test_query_sets_of_any_lengths_each_with_its_own_truth(tmp_path, capsys):
    """Two query sets of different drives and lengths, each with its own truth and sequences
    (one by --gt, one by positions): each is evaluated on its own centres and windows."""
    ref_places, query_places = _drives(tmp_path, sequences=False)
    rng = np.random.default_rng(5)
    query = np.load(tmp_path / "query.npy")
    qseq = pd.read_parquet(tmp_path / "query_seq.parquet")
    short = qseq["sequence_key"] != "q002"  # the night set: the first two drives only, 580 rows
    np.save(tmp_path / "night.npy", query[short.to_numpy()] + rng.normal(scale=0.05, size=query[short].shape)
            .astype(np.float32))
    qseq[short].to_csv(tmp_path / "night_seq.csv", index=False)
    np.save(tmp_path / "ref_pos.npy", np.c_[ref_places * 5.0, np.zeros(len(ref_places))])  # 5 m between places
    np.save(tmp_path / "night_pos.npy", np.c_[query_places[short.to_numpy()] * 5.0, np.zeros(int(short.sum()))])
    np.save(tmp_path / "day_pos.npy", np.c_[query_places * 5.0, np.zeros(len(query_places))])
    argv = ["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'query.npy'}",
            "--query", f"night={tmp_path / 'night.npy'}", "--gt", f"day={tmp_path / 'gt.npy'}",
            "--ref-seq", str(tmp_path / "ref_seq.csv"), "--query-seq", f"day={tmp_path / 'query_seq.parquet'}",
            "--query-seq", f"night={tmp_path / 'night_seq.csv'}", "--ref-pos", str(tmp_path / "ref_pos.npy"),
            "--query-pos", f"day={tmp_path / 'day_pos.npy'}", "--query-pos", f"night={tmp_path / 'night_pos.npy'}",
            "--gt-radius-m", "3", "--name", "sets", "--out", str(tmp_path / "data"), "-q"]
    assert main(argv) == 0
    store, index = tmp_path / "data" / "sets.zarr", tmp_path / "data" / "sets.index"
    assert main(["index", str(store), "--out", str(index), "-q"]) == 0
    assert main(["eval", str(store), str(index), "--L", "1,9", "--out", str(tmp_path / "ev"), "-q",
                 "--radius-m", "10"]) == 0
    res = pq.read_table(tmp_path / "ev" / "results.parquet").to_pandas()
    n = res[(res.radius == 0) & (res.method == "coarsehash")].groupby(["noise", "L"])["n_queries"].max()
    night_seq = Sequences(pd.factorize(qseq[short]["sequence_key"])[0], qseq[short]["frame_number"].to_numpy())
    day_seq = Sequences(pd.factorize(qseq["sequence_key"])[0], qseq["frame_number"].to_numpy())
    day_truth = np.load(tmp_path / "gt.npy") >= 0  # the night set's: all of its places are in the map
    assert n[("night", 9)] == int(night_seq.mask(9).sum()) < n[("day", 9)] == int((day_seq.mask(9) & day_truth).sum())
    queries = pq.read_table(tmp_path / "ev" / "queries.parquet").to_pandas()
    night = queries[(queries.noise == "night") & (queries.L == 1) & (queries.method == "coarsehash")]
    assert night["t"].max() < short.sum() and (night["gt"] >= 0).all()
    place = query_places[short.to_numpy()][night["t"]]
    assert (np.abs(ref_places[night["gt"]] - place) == 0).all()  # its truth by position: the same place
    capsys.readouterr()
    # one --gt for sets of different lengths is refused, naming the fix
    assert main(["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'query.npy'}",
                 "--query", f"night={tmp_path / 'night.npy'}", "--gt", str(tmp_path / "gt.npy"),
                 "--out", str(tmp_path / "data2")]) == 2
    assert "give each its own, --gt NAME=PATH" in capsys.readouterr().err


@pytest.mark.slow
def test_the_online_matcher_keeps_to_the_map_s_windows_as_the_batch_does(tmp_path, capsys):
    """``localise --store``: a stream matched frame by frame answers what the batch answers with
    the map's window mask, and never a window across drives."""
    from vprscale.method.index import Index
    from vprscale.protocol import window_mask

    _drives(tmp_path)
    store, index = tmp_path / "data" / "drives.zarr", tmp_path / "data" / "drives.index"
    assert main(["index", str(store), "--out", str(index), "-q"]) == 0
    seq = pd.read_csv(tmp_path / "ref_seq.csv")
    valid = window_mask(Sequences(pd.factorize(seq["sequence_key"])[0], seq["frame_number"].to_numpy()), 9)
    frames = np.load(tmp_path / "query.npy")[:300]
    np.save(tmp_path / "stream.npy", frames)
    out = tmp_path / "online.parquet"
    assert main(["localise", str(index), str(tmp_path / "stream.npy"), "--L", "9", "--top", "5", "--store",
                 str(store), "--out", str(out)]) == 0
    online = pq.read_table(out).to_pandas().dropna(subset=["match"])
    idx = Index.load(index)
    qf = idx.query_frames(idx.hash_frames(frames)[0], errors=idx.hash_frames(frames)[1])
    centres = online["centre"].to_numpy(np.int64)
    top, _, _ = idx.answer(qf, qf.positions(centres, 9), 9, "paper", 5, valid)
    np.testing.assert_array_equal(online["match"].to_numpy(np.int64), top[:, 0])
    assert valid[online["match"].to_numpy(np.int64)].all()
    capsys.readouterr()
    assert main(["localise", str(index), str(tmp_path / "stream.npy"), "--store", str(tmp_path / "data" / "x.zarr"),
                 "--out", str(tmp_path / "x.parquet")]) == 2
