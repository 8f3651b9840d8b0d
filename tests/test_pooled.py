"""``--compare seq:…``: pooled sequence descriptors beside CoarseHash (docs/protocol.md, "Sequence descriptors").

The pooling against numpy's own means, whatever the pieces the rows come in; one evaluation of
the tiny store with a mean-pooled and a GeM-pooled re-ranked descriptor against a brute-force
search over every reference window and a brute-force CoarseHash window score.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.compared.pooled import Pooling, WindowPooler, parse_pooled, pool_windows, pooled_encodings
from vprscale.method.index import Index

L_SEQ = 9


def _direct(x: np.ndarray, L: int, how: str, shift: np.ndarray | None = None) -> np.ndarray:
    """Every window's pooled row by numpy's sliding windows (float64)."""
    x = x.astype(np.float64)
    if how == "gem":
        x = np.maximum(x - shift, 0) ** 3
    mean = np.lib.stride_tricks.sliding_window_view(x, L, axis=0).mean(axis=2)
    return mean if how == "mean" else np.cbrt(mean)


@pytest.mark.parametrize("how", ["mean", "gem"])
@pytest.mark.parametrize("L", [2, 7, 50])
def test_reference_windows_are_the_same_bytes_whatever_the_pieces(how, L):
    rng = np.random.default_rng(L)
    x = rng.normal(size=(1_000, 6)).astype(np.float32)
    pooling = Pooling(how, x.min(axis=0).astype(np.float64) if how == "gem" else None)
    whole = WindowPooler(L, pooling).push(x)
    assert whole.shape == (len(x) - L + 1, 6) and whole.dtype == np.float32
    np.testing.assert_allclose(whole, _direct(x, L, how, pooling.shift), rtol=1e-5, atol=1e-6)
    for cuts in ([1, 2, 3, 500], [L - 1, L, L + 1], list(range(13, 1_000, 13)), [999]):
        pooler = WindowPooler(L, pooling)
        pieces = [pooler.push(part) for part in np.split(x, cuts)]
        assert np.concatenate(pieces).tobytes() == whole.tobytes()
    # a query window, pooled alone, is the same window
    pos = np.array([L // 2, 400, len(x) - 1 - (L - 1 - L // 2)])
    np.testing.assert_allclose(pool_windows(x, pos, L, pooling), whole[pos - L // 2], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("spec", "name", "rerank"), [
    ("seq:PQ3", "seq:PQ3", None), ("seq-gem3:IVF64,PQ3+rerank", "seq-gem3:IVF64,PQ3+rerank", 20),
    ("seq:Flat+rerank50", "seq:Flat+rerank50", 50)])
def test_compare_strings(spec, name, rerank):
    parsed = parse_pooled(spec)
    assert parsed.name == name and parsed.rerank == rerank


@pytest.fixture(scope="module")
def pooled(tiny_store, tiny_index, tmp_path_factory):
    out = tmp_path_factory.mktemp("pooled")
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", f"1,{L_SEQ}", "--z", "97", "--noise", "qm1",
                 "--modes", "paper", "--no-baseline", "--repeats", "1", "--out", str(out),
                 "--compare", "seq:Flat", "--compare", "seq-gem3:Flat+rerank", "--compare", "seq:PQ4np",
                 "--compare", "seq:Flat+rerank5"]) == 0
    group = zarr.open_group(tiny_store, mode="r")
    return {"results": pq.read_table(out / "results.parquet").to_pandas(),
            "queries": pq.read_table(out / "queries.parquet").to_pandas(),
            "meta": json.loads((out / "eval.json").read_text()),
            "ref": group["ref"][:], "query": group["query_qm1"][:], "out": out}


def _rows(pooled, method: str):
    q = pooled["queries"]
    return q[q.method == method].sort_values("t")


@pytest.mark.slow
def test_pooled_methods_run_on_sequences_only_as_their_family(pooled):
    res = pooled["results"]
    seq = res[res.method.str.startswith("seq")]
    assert set(seq.method) == {"seq:Flat", "seq-gem3:Flat+rerank", "seq:PQ4np", "seq:Flat+rerank5"}
    assert set(seq.L) == {L_SEQ} and seq["mode"].isna().all()
    assert set(seq.family) == {"sequence descriptor"}
    dim, n_ref = pooled["ref"].shape[1], len(pooled["ref"])
    bpp = seq.groupby("method").bytes_per_place.first()
    assert bpp["seq:Flat"] == pytest.approx(4 * dim * (n_ref - L_SEQ + 1) / n_ref)
    assert bpp["seq:PQ4np"] == pytest.approx(4 * (n_ref - L_SEQ + 1) / n_ref)
    coarse = res[res.method == "coarsehash"].bytes_per_place.iloc[0]
    assert bpp["seq-gem3:Flat+rerank"] == pytest.approx(bpp["seq:Flat"] + coarse)
    assert pooled["meta"]["pooled"]["seq-gem3:Flat+rerank"] == {
        "pooling": "gem", "factory": "Flat", "rerank": 20, "lengths": [L_SEQ],
        "bytes_per_place": pytest.approx(bpp["seq:Flat"])}


@pytest.mark.slow
def test_mean_pooled_match_is_the_nearest_reference_window(pooled):
    """seq:Flat: each match is the reference window whose mean is nearest the query window's
    (brute force over every complete window), its ranking the nearest twenty in order."""
    ref_w = _direct(pooled["ref"], L_SEQ, "mean")
    rows = _rows(pooled, "seq:Flat")
    assert len(rows) > 100
    exact = 0
    for t, match, top, score in zip(rows.t, rows["match"], rows.top, rows.score, strict=True):
        y = pooled["query"][t - L_SEQ // 2 : t - L_SEQ // 2 + L_SEQ].astype(np.float64).mean(axis=0)
        dist = ((ref_w - y) ** 2).sum(axis=1)
        best = dist.min()
        assert dist[match - L_SEQ // 2] <= best * (1 + 1e-4) + 1e-6
        assert score == pytest.approx(best, rel=1e-4, abs=1e-6)
        theirs = np.argsort(dist, kind="stable")[:20] + L_SEQ // 2
        assert len(set(theirs) & set(top)) >= 18  # float32 near-ties aside
        exact += int(match == theirs[0])
    assert exact >= 0.95 * len(rows)


def _digits(h: np.ndarray, d: int, k: int) -> np.ndarray:
    """Each address's quantisation level per component (the first component is the top digit)."""
    return np.stack([(h // np.uint64(k) ** np.uint64(d - 1 - j)) % np.uint64(k) for j in range(d)], axis=1)


@pytest.mark.slow
def test_reranked_match_is_coarsehash_best_among_the_pooled_proposals(pooled, tiny_index):
    """seq-gem3:Flat+rerank: the GeM-pooled windows' twenty nearest (brute force), ranked by
    CoarseHash's window score computed here from the addresses and the fixed-point weights."""
    idx = Index.load(tiny_index)
    d, k, half, n_ref = idx.d, idx.k, L_SEQ // 2, idx.n_ref
    w = idx.weights()
    dmax = int(w[:, 0, k - 1].sum())
    ref_digits = _digits(idx.ref_addresses(), d, k)
    shift = pooled["ref"].min(axis=0).astype(np.float64)
    ref_w = _direct(pooled["ref"], L_SEQ, "gem", shift)
    rows = _rows(pooled, "seq-gem3:Flat+rerank").iloc[::4]
    assert len(rows) > 25
    same = 0
    for t, match, top, score in zip(rows.t, rows["match"], rows.top, rows.score, strict=True):
        frames = pooled["query"][t - half : t - half + L_SEQ]
        y = np.cbrt((np.maximum(frames.astype(np.float64) - shift, 0) ** 3).mean(axis=0))
        proposed = np.argsort(((ref_w - y) ** 2).sum(axis=1), kind="stable")[:20] + half
        q_digits = _digits(idx.hash_queries(frames), d, k)

        def window_score(c: int, q_digits=q_digits) -> int:
            s = 0
            for i in range(L_SEQ):
                r = c - half + i
                s += dmax if not 0 <= r < n_ref else int(w[np.arange(d), ref_digits[r], q_digits[i]].sum())
            return s

        scores = {int(c): window_score(int(c)) for c in set(proposed) | set(top)}
        ranked = [int(c) for c in top if c >= 0]
        assert [scores[c] for c in ranked] == sorted(scores[c] for c in ranked)  # best first
        assert len(set(ranked) & set(proposed)) >= 18  # the pooled code's proposals, float32 near-ties aside
        assert match == ranked[0] and score == pytest.approx(scores[match] / dmax)
        same += int(set(ranked) == {int(c) for c in proposed})
        if set(ranked) == {int(c) for c in proposed}:
            assert scores[match] == min(scores.values())
    assert same >= 0.9 * len(rows)


@pytest.mark.slow
def test_a_code_and_its_reranking_share_one_encoding(pooled):
    """seq:Flat+rerank5 re-ranks the five windows seq:Flat retrieves: the same encoding, searched once more."""
    plain, reranked = _rows(pooled, "seq:Flat"), _rows(pooled, "seq:Flat+rerank5")
    assert plain.t.tolist() == reranked.t.tolist()
    for top, again in zip(plain.top, reranked.top, strict=True):
        assert set(again[:5]) == set(top[:5]) and (again[5:] == -1).all()
    shared = pooled_encodings([parse_pooled(s) for s in ("seq:PQ3", "seq-gem3:PQ3", "seq:PQ3+rerank")], 96, [1, 50],
                              10_000, 16)
    assert [[s.name for s in p.specs] for p in shared] == [["seq:PQ3", "seq:PQ3+rerank"], ["seq-gem3:PQ3"]]
    assert [list(p.codes) for p in shared] == [[50], [50]]


@pytest.mark.parametrize(("spec", "says"), [
    ("seq:", "seq:FACTORY or seq-gem3:FACTORY"), ("seq:PQ3y", "--compare seq:PQ3y: not a FAISS index_factory"),
    ("seq:IVF100000,PQ3", "inverted lists for"), ("seq:PQ3+rerank0", "at least one")])
def test_bad_pooled_strings_are_one_line_and_exit_2(tiny_store, tiny_index, tmp_path, capsys, spec, says):
    code = main(["eval", str(tiny_store), str(tiny_index), "--L", "9", "--noise", "qm1", "--no-baseline",
                 "--compare", spec, "--out", str(tmp_path / "e")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and says in err and "\n" not in err and not (tmp_path / "e").exists()


def test_encode_says_pooled_descriptors_are_encoded_by_eval(tiny_store, capsys):
    assert main(["encode", str(tiny_store), "--compare", "seq:PQ3"]) == 2
    assert "encoded by vprscale eval, one encoding per L" in capsys.readouterr().err


@pytest.mark.slow
def test_report_tables_pooled_descriptors_as_sequence_methods(pooled, tmp_path):
    """The report draws the paper's figures from CoarseHash and the baseline alone, and files the
    pooled descriptors with the compared methods, each as a sequence series of its family."""
    assert main(["report", str(pooled["out"]), "--out", str(tmp_path / "r")]) == 0
    md = (tmp_path / "r" / "report.md").read_text()
    for name in ("seq:Flat", "seq-gem3:Flat+rerank", "seq:PQ4np"):
        assert f"| {name} pooling=" in md and f"{name} (sequence)" in md
    recall_table = md[md.index("## Recall (%) at radii"):].split("\n## ")[0]
    assert "seq" not in recall_table and "sequence descriptor" in md


def test_a_pooled_descriptor_without_a_sequence_length_is_refused(tiny_store, tiny_index, tmp_path, capsys):
    """At L = 1 a pooled window is the frame: asking for one there alone would pool and encode for nothing."""
    code = main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1", "--compare", "seq:PQ4np",
                 "--out", str(tmp_path / "e")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "evaluate an --L above 1" in err and "\n" not in err and not (tmp_path / "e").exists()
