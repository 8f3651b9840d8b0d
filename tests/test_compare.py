"""``vprscale eval --compare``: FAISS compact codes evaluated beside CoarseHash (docs/protocol.md).

One shared evaluation of the tiny store with a FAISS method of each scoring form (product
quantiser tables: 8-bit, bit-packed and FAISS's 4-bit fast-scan codes; Hamming tables of
binary codes; residual tables of an IVF-PQ index; decoded vectors of RaBitQ and IVF
fast-scan RaBitQ; an HNSW graph's own rows), checked against FAISS itself
and against a brute-force window score. Each scoring form on its own, on small random data, is
in test_codescore.
"""

from __future__ import annotations

import json

import faiss
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.compared.codescore import REF_LEVEL_BYTES
from vprscale.compared.faisscodes import ID_BYTES, training_rows
from vprscale.evaluation.algorithms.faisscodes import FaissMethod
from vprscale.method.index import Index
from vprscale.method.kernels import N_BEST

from .conftest import SMALL_TRAINING, faiss_own

# (the additive quantisers, whose flat search decodes every code, are checked apart: test_new_codes_…). The 8-bit
# product quantisers are FAISS's `np` forms: FAISS's own index (`direct`) would otherwise spend 7.5 s a code on its
# polysemous training, which vprscale skips (test_codescore's PQ4 and IVF16,PQ4 compare the two trainings)
FACTORIES = ["PQ4np", "PQ4x6", "PQ6x4fs", "ITQ16,LSH", "IVF32,PQ4np", "RaBitQ", "IVF32,RaBitQfs", "HNSW32"]
L_SEQ = 9


@pytest.fixture(scope="module")
def compared(tiny_store, tiny_index, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    argv = ["eval", str(tiny_store), str(tiny_index), "--L", f"1,{L_SEQ}", "--z", "97", "--noise", "qm1",
            "--out", str(out), "--workers", "2"]
    for factory in FACTORIES:
        argv += ["--compare", factory]
    with pytest.MonkeyPatch.context() as mp:  # several blocks of decoded codes, as at scale
        mp.setattr("vprscale.compared.faisscodes.DECODE_ROWS", 10_000)
        mp.setattr("vprscale.compared.faisscodes.TRAIN_ROWS", SMALL_TRAINING)
        assert main(argv) == 0
    return {"results": pq.read_table(out / "results.parquet").to_pandas(),
            "queries": pq.read_table(out / "queries.parquet").to_pandas(),
            "meta": json.loads((out / "eval.json").read_text()), "out": out}



@pytest.fixture(scope="module")
def direct(tiny_store, compared):
    """Each factory built with FAISS directly (:func:`faiss_own`), on the rows vprscale trained on."""
    group = zarr.open_group(tiny_store, mode="r")
    ref = group["ref"][:]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("vprscale.compared.faisscodes.TRAIN_ROWS", SMALL_TRAINING)  # as `compared` trained
        train = ref[training_rows(len(ref))]
    return ref, group["query_qm1"], {factory: faiss_own(factory, train, ref) for factory in FACTORIES}


def _k(compared, factory: str) -> int:
    return int(compared["meta"]["compare"][f"faiss:{factory}"]["k"][0])


# flat float product-quantiser codes: vprscale answers them by its exact top-k (float64 sums,
# vprscale.compared.codesearch), FAISS by float32 sums, so places FAISS finds at one float32 distance may
# come in either order; every other code's ranking is FAISS's search itself
EXACT_SEARCH = {"PQ4np", "PQ4x6"}


def assert_faiss_ranking(ours: np.ndarray, factory: str, index, y: np.ndarray, k: int) -> None:
    """``ours`` (a row of place ids per query row of ``y``) is the first ranks of FAISS's own
    top-``k`` of ``index``: the same ids rank by rank, but for a code of :data:`EXACT_SEARCH`, where
    ranks differ, each of our places at FAISS's distance of that rank (a tie to float32 rounding,
    in another order)."""
    dist, ids = (a[:, : ours.shape[1]] for a in index.search(y, k))
    differ = ours != ids
    if factory not in EXACT_SEARCH or not differ.any():
        np.testing.assert_array_equal(ours, ids)
        return
    rows, ranks = np.nonzero(differ)
    decoded = np.stack([index.reconstruct(int(i)) for i in ours[rows, ranks]]).astype(np.float64)
    own = ((y[rows].astype(np.float64) - decoded) ** 2).sum(axis=1)
    np.testing.assert_allclose(own, dist[rows, ranks], rtol=1e-5)
    ordered = np.sort(ours, axis=1)
    assert (ordered[:, 1:] != ordered[:, :-1]).all()  # no place twice


@pytest.mark.parametrize("factory", FACTORIES)
def test_single_frame_agrees_with_a_direct_faiss_search(compared, direct, factory):
    """L = 1 is FAISS's own top-1, and the in-list bound is over FAISS's own top-k."""
    _, query, indexes = direct
    q = compared["queries"]
    rows = q[(q.method == f"faiss:{factory}") & (q.L == 1)].sort_values("t")
    assert len(rows) > 100
    y = query.get_orthogonal_selection((rows.t.to_numpy(), slice(None)))
    assert_faiss_ranking(rows["match"].to_numpy()[:, None], factory, indexes[factory], y, _k(compared, factory))
    _, ids = indexes[factory].search(y, _k(compared, factory))
    found = np.where(ids >= 0, np.abs(ids - rows["gt"].to_numpy()[:, None]), np.iinfo(np.int64).max)
    np.testing.assert_array_equal(rows.in_list.to_numpy(), found.min(axis=1))
    np.testing.assert_array_equal(rows.n_r.to_numpy(), (ids >= 0).sum(axis=1))


def _rabitq_estimates(index, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """RaBitQ's estimate of the distance from each query row to each reference row, from the
    rows' standalone codes as FAISS's ``RaBitQDistanceComputerNotQ`` computes it: ``max(0, A +
    ‖y − c‖² − 2·D·(c1·Σ_{bit} (y − c)_j − Σ_j (y − c)_j / √d))`` with ``c1 = 2 / √d``, ``c`` the
    code's centre (the index's, or its list's centroid)."""
    inner = faiss.downcast_index(index)
    ivf = faiss.try_extract_index_ivf(inner)
    d, codes = inner.d, index.sa_encode(x)
    lb = ivf.coarse_code_size() if ivf is not None else 0
    if ivf is not None:
        lists = codes[:, :lb].astype(np.int64) @ (256 ** np.arange(lb, dtype=np.int64))
        centre = ivf.quantizer.reconstruct_n(0, ivf.nlist).astype(np.float64)[lists]
    else:
        centre = np.broadcast_to(faiss.vector_to_array(inner.center).astype(np.float64), (len(x), d))
    nb = (d + 7) // 8
    bits = np.unpackbits(codes[:, lb : lb + nb], axis=1, bitorder="little")[:, :d].astype(np.float64)
    a, dp = codes[:, lb + nb : lb + nb + 8].copy().view(np.float32).astype(np.float64).T
    out = np.empty((len(y), len(x)))
    for i, row in enumerate(y.astype(np.float64)):
        q = row[None, :] - centre
        final = 2 / np.sqrt(d) * (bits * q).sum(axis=1) - q.sum(axis=1) / np.sqrt(d)
        out[i] = np.maximum(0, a + (q**2).sum(axis=1) - 2 * dp * final)
    return out


def _distances(index, factory: str, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Distance of each query row to each reference row as the window scores define it (float64,
    brute force): to the decoded code, RaBitQ's estimate, the Hamming distance of binary codes."""
    if "RaBitQ" in factory:
        return _rabitq_estimates(index, y, x)
    if "LSH" in factory:  # binary codes: the Hamming distance of the codes
        qc, rc = np.unpackbits(index.sa_encode(y), axis=1), np.unpackbits(index.sa_encode(x), axis=1)
        return (qc[:, None, :] != rc[None, :, :]).sum(axis=2).astype(np.float64)
    decoded = x if "HNSW" in factory else index.sa_decode(index.sa_encode(x))  # a graph holds the rows
    decoded = decoded.astype(np.float64)
    return ((y.astype(np.float64)[:, None, :] - decoded[None, :, :]) ** 2).sum(axis=2)


@pytest.mark.parametrize("mode", ["paper", "aligned"])
@pytest.mark.parametrize("factory", FACTORIES)
def test_sequence_match_is_the_brute_force_window_argmin(compared, direct, factory, mode):
    """Every match minimises the window score over the candidates, recomputed from FAISS's
    own top-k lists and decoded codes; and the candidates counted are those lists' union."""
    ref, query, indexes = direct
    index, k, half = indexes[factory], _k(compared, factory), L_SEQ // 2
    q = compared["queries"]
    rows = q[(q.method == f"faiss:{factory}") & (q.L == L_SEQ) & (q["mode"] == mode)].sort_values("t")
    rows = rows.iloc[:: max(1, len(rows) // 40)]
    agree = 0
    for t, match, n_r in zip(rows.t, rows["match"], rows.n_r, strict=True):
        y = query[t - half : t - half + L_SEQ]
        _, lists = index.search(y, k)
        cand = {int(r) - ((i - half) if mode == "aligned" else 0) for i in range(L_SEQ) for r in lists[i] if r >= 0}
        cand = np.array(sorted(c for c in cand if 0 <= c < len(ref)))
        assert n_r == len(cand)
        terms = np.full((len(cand), L_SEQ), np.nan)
        for i in range(L_SEQ):
            r = cand + i - half
            inside = (r >= 0) & (r < len(ref))
            terms[inside, i] = _distances(index, factory, y[i : i + 1], ref[r[inside]])[0]
        scores = np.where(np.isnan(terms), np.nanmax(terms), terms).sum(axis=1)
        assert match in cand
        best = scores.min()
        assert scores[cand == match][0] <= best + 1e-4 * max(1.0, abs(best))
        agree += int(match == cand[np.argmin(scores)])
    assert agree >= 0.9 * len(rows)


def test_every_method_states_its_bytes_per_place(compared, tiny_store, tiny_index):
    res = compared["results"]
    dim = zarr.open_group(tiny_store, mode="r")["ref"].shape[1]
    per_method = res.groupby("method")["bytes_per_place"].unique()
    assert set(per_method.index) == {"coarsehash", "baseline", *(f"faiss:{f}" for f in FACTORIES)}
    assert all(len(v) == 1 and v[0] > 0 for v in per_method)
    assert per_method["faiss:PQ4np"][0] == 4 and per_method["faiss:ITQ16,LSH"][0] == 2
    assert per_method["faiss:PQ4x6"][0] == 3 and per_method["faiss:PQ6x4fs"][0] == 3  # 24 bits
    # list entry; the code in id order with its list number and its distance term's level
    assert per_method["faiss:IVF32,PQ4np"][0] == 4 + ID_BYTES + 5 + REF_LEVEL_BYTES
    assert per_method["faiss:RaBitQ"][0] == faiss.index_factory(dim, "RaBitQ").sa_code_size()  # bits and factors
    assert per_method["faiss:HNSW32"][0] > 4 * dim + 2 * 32 * 4  # its row, and at least its bottom layer's links
    assert per_method["baseline"][0] == 4
    idx = Index.load(tiny_index)
    engine = idx.codes.nbytes + sum(idx.lists.nbytes().values())
    assert per_method["coarsehash"][0] == pytest.approx(engine / 52_500)  # codes, packed ids and directory
    assert 12 / 8 + 16 / 8 < per_method["coarsehash"][0] < 12 / 8 + 16 / 8 + 1


@pytest.mark.slow
def test_flat_codes_on_a_sample_beyond_the_scan_budget(tiny_store, tiny_index, tmp_path, monkeypatch,
                                                       small_training):
    """A run whose frames would visit more codes than the budget localises an evenly spaced
    sample of the centres (the same ones for every scanning flat method), never fewer than
    the floor; IVF visits a few lists per frame and an enumerable flat code (PQ4) finds its
    top-k without a scan: both localise every centre, whatever the budget."""
    import vprscale.evaluation.algorithms.faisscodes as fc
    import vprscale.evaluation.algorithms.pooled  # noqa: F401  (imported now, it binds the real budget, not the one patched here)

    runs = {}
    for floor, budget in ((30, 52_500 * 5 * 40), (40, 52_500 * 5 * 40), (1000, 52_500 * 5 * 40), (30, 1)):
        monkeypatch.setattr(fc, "MIN_CENTRES", floor)
        monkeypatch.setattr(fc, "SCAN_BUDGET", budget)
        out = tmp_path / f"e{floor}-{budget}"
        assert main(["eval", str(tiny_store), str(tiny_index), "--L", "5", "--z", "97", "--noise", "qm1",
                     "--modes", "paper", "--no-baseline", "--compare", "PQ6x4fs", "--compare", "IVF32,PQ4np",
                     "--compare", "PQ4np", "--faiss-nprobe", "1", "--repeats", "1", "--out", str(out)]) == 0
        res = pq.read_table(out / "results.parquet").to_pandas()
        runs[floor, budget] = res[res.part == "all"].groupby("method")["n_queries"].first()
    n = runs[30, 52_500 * 5 * 40]
    assert n["faiss:PQ6x4fs"] == 40 and n["faiss:IVF32,PQ4np"] == n["coarsehash"] > 40  # the budget's 40 over 30
    assert runs[40, 52_500 * 5 * 40]["faiss:PQ6x4fs"] == 40
    assert runs[1000, 52_500 * 5 * 40]["faiss:PQ6x4fs"] == n["coarsehash"] < 1000  # the floor: all when fewer
    tight = runs[30, 1]  # beyond any budget: scanning flat codes at the floor, the others still at every centre
    assert tight["faiss:PQ6x4fs"] == 30 and tight["faiss:IVF32,PQ4np"] == n["coarsehash"]
    assert all(run["faiss:PQ4np"] == n["coarsehash"] for run in runs.values())


def test_flat_codes_run_on_the_flat_noise_levels_only(tiny_store, tiny_index, tmp_path, small_training):
    """``--flat-noise qm1``: flat codes whose evaluation scans every code per frame (fast-scan
    PQ) run on QM1 alone; IVF codes, enumerable flat codes (PQ4np: no scan) and CoarseHash on
    every noise level; the evaluation records what was run."""
    out = tmp_path / "e"
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1,5", "--z", "97", "--noise", "qm1,qm2",
                 "--flat-noise", "qm1", "--modes", "paper", "--no-baseline", "--compare", "PQ6x4fs", "--compare",
                 "IVF32,PQ4np", "--compare", "PQ4np", "--repeats", "1", "--out", str(out)]) == 0
    res = pq.read_table(out / "results.parquet").to_pandas()
    ran = res.groupby("method")["noise"].agg(lambda n: sorted(set(n)))
    assert ran["faiss:PQ6x4fs"] == ["qm1"]
    assert ran["faiss:IVF32,PQ4np"] == ran["faiss:PQ4np"] == ran["coarsehash"] == ["qm1", "qm2"]
    assert json.loads((out / "eval.json").read_text())["flat_noise"] == ["qm1"]


@pytest.mark.parametrize("argv, message", [
    (["--compare", "PQ4", "--noise", "qm1", "--flat-noise", "qm2"], "--flat-noise qm2: not among the evaluated"),
    (["--compare", "PQ4", "--flat-noise", "qm1,qm1"], "--flat-noise: a query set is given twice"),
    (["--compare", "PQ5"], "--compare PQ5: not a FAISS index_factory string"),
    (["--compare", "Banana"], "--compare Banana: not a FAISS index_factory string"),
    (["--compare", "PQ4", "--compare", "PQ4"], "--compare: PQ4 given twice"),
    (["--compare", "PQ4", "--d", "8,10"], "--compare: compares with one index at a time"),
    # what FAISS builds and then crashes on (a segfault, an assertion, an allocation), refused first
    (["--compare", "IVF0,PQ3"], "--compare IVF0,PQ3: an inverted file of 0 lists"),
    (["--compare", "HNSW0"], "--compare HNSW0: an HNSW graph of M = 0"),
    (["--compare", "HNSW1"], "--compare HNSW1: an HNSW graph of M = 1"),
    (["--compare", "IVF999999999,PQ3"], "--compare IVF999999999,PQ3: 999,999,999 is more than"),
    (["--compare", "IVF100000,PQ3"], "--compare IVF100000,PQ3: 100,000 inverted lists for 52,500"),
    (["--compare", "OPQ0,PQ3"], "--compare OPQ0,PQ3: an OPQ rotation for 0 sub-spaces"),
    (["--compare", "PCA0,PQ3"], "--compare PCA0,PQ3: a transform to 0 dimensions"),
    (["--compare", "LSH0"], "--compare LSH0: a code of 0 bytes"),
    (["--compare", "seq:PQ3+rerank99999999999999"], "+rerank99999999999999: re-ranks at least one"),
])
def test_bad_compare_input_is_one_line_and_exit_2(tiny_store, tiny_index, tmp_path, capsys, argv, message):
    out = tmp_path / "e"
    index = [] if "--d" in argv else [str(tiny_index)]
    assert main(["eval", str(tiny_store), *index, "--L", "1", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_same_matches_whatever_the_workers(tiny_store, tiny_index, tmp_path, small_training):
    """FAISS trains on one thread and encodes and searches fixed blocks each on one thread, so
    one worker gives the lists and matches two give (FAISS's own threading changes its OPQ and
    ITQ rotations and IVF distances in the last bit with the thread count, flipping near-ties)."""
    threaded = ["OPQ4,PQ4x6", "IVF32,PQ4np"]  # the forms whose FAISS threading changed bytes
    runs = []
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        argv = ["eval", str(tiny_store), str(tiny_index), "--L", str(L_SEQ), "--z", "97", "--noise", "qm1",
                "--modes", "aligned", "--no-baseline", "--out", str(out), "--workers", str(workers)]
        for factory in threaded:
            argv += ["--compare", factory]
        assert main(argv) == 0
        q = pq.read_table(out / "queries.parquet").to_pandas()
        runs.append(q[q.method.str.startswith("faiss:")].sort_values(["method", "L", "t"]).reset_index(drop=True))
    one, two = runs
    assert set(one.method) == {f"faiss:{f}" for f in threaded} and len(one) == len(two) > 1000
    for col in ("method", "t", "match", "n_r"):
        np.testing.assert_array_equal(one[col].to_numpy(), two[col].to_numpy())


def test_report_draws_and_tells_the_comparison(compared, tmp_path):
    """The report's comparison: its figure, one sentence per noise and L, and a table row per
    method, mode and L, with the recall, bytes and times of the results."""
    assert main(["report", str(compared["out"]), "--out", str(tmp_path / "r")]) == 0
    text = (tmp_path / "r" / "report.md").read_text()
    section = text.split("## CoarseHash against the other methods")[1].split("\n## ")[0]
    for fig in ("fig_compare", "fig_compare_bytes", "fig_compare_trends", "fig_pr"):  # one per noise level
        assert (tmp_path / "r" / f"{fig}_qm1.png").stat().st_size > 10_000 and f"({fig}_qm1.png)" in text
    assert "## Scores: precision–recall, AUC-PR and Recall@N" in text
    words = [line for line in section.splitlines() if line.startswith("- tiny, QM1, L = ")]
    assert len(words) == 2
    res = compared["results"]
    row = res[(res.method == "faiss:PQ4np") & (res.L == L_SEQ) & (res["mode"] == "aligned") & (res.part == "all")
              & (res.radius == 20)].iloc[0]
    time = f"{row.us_per_query:,.2f} ({row.us_per_query_lo:,.2f}–{row.us_per_query_hi:,.2f})"
    recall = f"{100 * row.recall:.1f} ({100 * row.recall_lo:.1f}–{100 * row.recall_hi:.1f})"
    assert f"| PQ4np {row.params} (aligned) | PQ | 4.00 | {time} | {recall} | {row.n_queries} |" in section
    # every ratio is of medians measured in the same run (one evaluation here)
    assert "different runs" not in section and "faster" in section or "slower" in section
    section, points = section.split("### Operating points")
    assert section.count("| tiny | QM1 |") == 3 * (1 + len(FACTORIES))  # L = 1: single; L = 9: two modes
    # operating points: per L, the best within CoarseHash's bytes and within its speed
    assert points.count("| tiny | QM1 |") == 4 and points.count("B/place |") == 2 and points.count("q/s/core |") == 2
    ours = res[(res.method == "coarsehash") & (res.L == L_SEQ) & (res["mode"] == "paper") & (res.part == "all")
               & (res.radius == 20)].iloc[0]
    within = res[(res.L == L_SEQ) & (res.part == "all") & (res.radius == 20)
                 & (res.bytes_per_place <= ours.bytes_per_place)]
    top = within.sort_values("recall", ascending=False).iloc[0]
    assert f": {100 * top.recall:.1f} ({100 * top.recall_lo:.1f}–{100 * top.recall_hi:.1f}) |" in points


def test_trends_draw_coarsehash_as_one_line_across_scales(tmp_path):
    """Against scale, CoarseHash (a different d at each scale) is one series per mode, joined
    across the scales, as each compared method is."""
    from vprscale.evaluation.comparison import fig_compare_trends, series_label

    rows = [(scale, method, d, recall) for scale, d in (("1M", 20), ("10M", 24))
            for method, recall in (("coarsehash", 0.9 if d == 20 else 0.8), ("faiss:PQ3", 0.95))]
    points = pd.DataFrame([{"scale": s, "noise": "qm1", "method": m, "mode": "aligned", "L": 100, "d": d,
                            "recall": r, "recall_lo": r - 0.01, "recall_hi": r + 0.01, "bytes_per_place": 3.0,
                            "us_per_query": 10.0, "series": series_label(m, "aligned", d)} for s, m, d, r in rows])
    drawn = {}
    fig_compare_trends(points, ["1M", "10M"], "qm1", tmp_path, lambda fig, out, name: drawn.setdefault(name, fig))
    by_scale = drawn["fig_compare_trends_qm1"].axes[2]  # a 2 × 2 grid: the first panel of the second row
    lines = {line.get_label(): list(line.get_ydata()) for line in by_scale.get_lines()}
    assert lines["CoarseHash (aligned)"] == [90.0, 80.0] and lines["PQ3 (aligned)"] == [95.0, 95.0]
    assert not any("d=" in label for label in lines)


def test_a_method_keeps_its_colour_and_its_modes_their_line_styles():
    """Colours go to methods (CoarseHash one at every width), line styles to modes, so a
    report's thirty-odd families need no more colours than it has methods."""
    from vprscale.evaluation.comparison import series_colours, series_label, series_line, series_marker

    families = [series_label(m, mode, d) for m, d in (("coarsehash", 20), ("coarsehash", 24), ("faiss:PQ3", None),
                                                      ("faiss:IVF4096,PQ3", None))
                for mode in ("aligned", "paper", "single")]
    colours = series_colours(families)
    assert len({colours[f] for f in families}) == 3
    ours = {colours[f"CoarseHash d={d} ({mode})"] for d in (20, 24) for mode in ("aligned", "paper", "single")}
    assert len(ours) == 1
    assert colours["PQ3 (aligned)"] != colours["IVF4096,PQ3 (aligned)"] != colours["CoarseHash d=20 (aligned)"]
    assert len({series_line(series_label("faiss:PQ3", mode, None)) for mode in ("aligned", "paper", "single")}) == 3
    assert len({series_marker(series_label("faiss:PQ3", mode, None)) for mode in ("aligned", "paper", "single")}) == 3


def test_a_report_draws_each_method_in_one_colour_whatever_else_a_figure_draws(tmp_path):
    """The comparison figure draws three codes, the nearest-neighbour figure two of them: with the
    report's palette of all its methods, HNSW32 is the same colour in both (a palette of each
    figure's own methods would give it the third colour in one and the second in the other)."""
    from matplotlib.colors import to_hex

    from vprscale.evaluation.comparison import fig_compare, method_colours, series_label
    from vprscale.evaluation.nnreport import _figure

    palette = method_colours(["CoarseHash", "AQ8", "HNSW32", "baseline"])
    rows = [{"scale": "1M", "noise": "qm1", "method": m, "mode": "aligned", "L": 50,
             "d": 20 if m == "coarsehash" else None, "recall": 0.5, "bytes_per_place": 3.0, "us_per_query": 5.0}
            for m in ("coarsehash", "faiss:AQ8", "faiss:HNSW32")]
    points = pd.DataFrame(rows).assign(qps=2e5)
    points["series"] = [series_label(m, "aligned", d) for m, d in zip(points.method, points.d, strict=True)]
    nn = pd.DataFrame({"scale": "1M", "noise": "qm1", "method": ["coarsehash", "faiss:HNSW32"],
                       "bytes_per_place": [3.0, 40.0], "recall_at_1": [0.3, 0.6], "recall_at_100": [0.5, 0.9]})
    drawn = {}
    keep = lambda fig, out, name: drawn.setdefault(name, fig)  # noqa: E731
    fig_compare(points, ["1M"], "qm1", tmp_path, keep, palette)
    _figure(nn, tmp_path, keep, palette)

    def colour(fig, label: str) -> str:
        return {to_hex(line.get_color()) for ax in fig.axes for line in ax.get_lines()
                if line.get_label().startswith(label)}

    assert colour(drawn["fig_compare_qm1"], "HNSW32") == colour(drawn["fig_nn"], "HNSW32") == {
        to_hex(palette["HNSW32"])}
    assert colour(drawn["fig_nn"], "CoarseHash") == {to_hex(palette["CoarseHash"])}
    # CoarseHash's colour is its own, however many methods a report compares
    many = method_colours(["CoarseHash", *(f"PQ{i}" for i in range(40))])
    assert sum(c == many["CoarseHash"] for c in many.values()) == 1
    assert len(set(many.values())) == 38  # a colour for each of 37 others before one repeats


def test_the_legend_names_methods_and_modes_apart_and_panels_share_axes(tmp_path):
    """Nine families (three methods in three modes) take a legend of six entries outside the
    panels: each method in its colour, each mode by its marker and line; panels share axes."""
    from vprscale.evaluation.comparison import fig_compare, series_label

    rows = [{"scale": s, "noise": "qm2", "method": m, "mode": mode, "L": L, "d": 20 if m == "coarsehash" else None,
             "recall": 0.5, "recall_lo": 0.4, "recall_hi": 0.6, "bytes_per_place": 3.0, "us_per_query": u}
            for s in ("1M", "10M") for m in ("coarsehash", "faiss:PQ3", "faiss:HNSW32") for L in (1, 50)
            for mode in (("single",) if L == 1 else ("paper", "aligned")) for u in (5.0, 50.0)]
    points = pd.DataFrame(rows)
    points["series"] = [series_label(m, mode, d) for m, mode, d in zip(points.method, points["mode"], points.d,
                                                                          strict=True)]
    points["qps"] = 1e6 / points.us_per_query
    drawn = {}
    assert fig_compare(points, ["1M", "10M"], "qm2", tmp_path,
                       lambda fig, out, name: drawn.setdefault(name, fig)) == "fig_compare_qm2"
    fig = drawn["fig_compare_qm2"]
    labels = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert labels == ["CoarseHash", "PQ3", "HNSW32", "single frame", "paper mode", "aligned mode"]
    first = fig.axes[0]
    assert all(ax.get_shared_x_axes().joined(first, ax) and ax.get_shared_y_axes().joined(first, ax)
               for ax in fig.axes)


def test_pareto_front_keeps_the_points_nothing_beats_on_both_axes():
    from vprscale.evaluation.comparison import pareto_front

    points = pd.DataFrame({"qps": [100, 90, 80, 50, 40, 10], "recall": [0.5, 0.4, 0.7, 0.7, 0.9, 0.85]})
    front = pareto_front(points)
    assert list(front.index) == [0, 2, 4]  # 1 is beaten by 0; 3 by 2 (as good, slower); 5 by 4


def test_every_operating_point_is_its_own_row(tiny_store, tiny_index, direct, tmp_path, small_training):
    """--faiss-k and --faiss-nprobe take lists: each (k, nprobe) of an IVF code, and each k of a
    flat one, is its own method row with its params, answered as FAISS answers at that point."""
    out = tmp_path / "points"
    assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1", "--no-baseline",
                 "--compare", "IVF32,PQ4np", "--compare", "PQ4np", "--faiss-k", "3,6", "--faiss-nprobe", "1,4",
                 "--repeats", "1", "--out", str(out)]) == 0
    q = pq.read_table(out / "queries.parquet").to_pandas()
    points = q.groupby(["method", "params"]).size()
    assert sorted(points.index) == sorted([("faiss:IVF32,PQ4np", f"k={k} nprobe={n}") for k in (3, 6) for n in (1, 4)]
                                          + [("faiss:PQ4np", "k=3"), ("faiss:PQ4np", "k=6")])
    _, query, indexes = direct
    ivf = faiss.extract_index_ivf(indexes["IVF32,PQ4np"])
    try:
        for k, n in ((3, 1), (6, 4)):
            ivf.nprobe = n
            rows = q[(q.method == "faiss:IVF32,PQ4np") & (q.params == f"k={k} nprobe={n}")].sort_values("t")
            _, ids = indexes["IVF32,PQ4np"].search(query.get_orthogonal_selection((rows.t.to_numpy(), slice(None))), k)
            np.testing.assert_array_equal(rows["match"].to_numpy(), ids[:, 0])
            np.testing.assert_array_equal(rows.n_r.to_numpy(), (ids >= 0).sum(axis=1))
    finally:
        ivf.nprobe = 16
    # the report keeps every operating point: one row each in its comparison table
    assert main(["report", str(out), "--out", str(tmp_path / "r")]) == 0
    text = (tmp_path / "r" / "report.md").read_text()
    for k in (3, 6):
        for n in (1, 4):
            assert f"| IVF32,PQ4np k={k} nprobe={n} (single) |" in text
        assert f"| PQ4np k={k} (single) |" in text


def test_operating_points_share_their_ranking_and_answer_as_alone(tiny_store, tiny_index, tmp_path, small_training,
                                                                 monkeypatch):
    """Operating points of one code differing only in k (both below N_BEST) search the frames'
    top N_BEST once per noise level and share the ranking's window answers, yet each answers
    (match, score, Recall@N ranking) as it does evaluated alone."""
    searches = []
    search = FaissMethod._search
    monkeypatch.setattr(FaissMethod, "_search", lambda self, rows: searches.append(self.k) or search(self, rows))
    common = ["--L", "1,9", "--noise", "qm1", "--no-baseline", "--compare", "IVF16,PQ4np", "--repeats", "1",
              "--modes", "paper", "--faiss-nprobe", "1"]
    assert main(["eval", str(tiny_store), str(tiny_index), *common, "--faiss-k", "3,6", "--out", str(tmp_path / "both"),
                 "-q"]) == 0
    assert len(searches) == 1  # the answers' search at N_BEST, for both points
    assert main(["eval", str(tiny_store), str(tiny_index), *common, "--faiss-k", "6", "--out", str(tmp_path / "alone"),
                 "-q"]) == 0
    both, alone = (pq.read_table(tmp_path / run / "queries.parquet").to_pandas() for run in ("both", "alone"))
    faiss_rows = both[both.method == "faiss:IVF16,PQ4np"]
    assert set(faiss_rows.params) == {"k=3 nprobe=1", "k=6 nprobe=1"}
    mine = faiss_rows[faiss_rows.params == "k=6 nprobe=1"].sort_values(["L", "mode", "t"]).reset_index(drop=True)
    theirs = alone[alone.method == "faiss:IVF16,PQ4np"].sort_values(["L", "mode", "t"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(mine, theirs)
    # the two points' rankings are one ranking; their matches come from their own k
    k3 = faiss_rows[faiss_rows.params == "k=3 nprobe=1"].sort_values(["L", "mode", "t"]).reset_index(drop=True)
    np.testing.assert_array_equal(np.stack(k3.top.to_numpy()), np.stack(mine.top.to_numpy()))
    assert (k3.n_r <= 3 * 9).all() and (k3.n_r.to_numpy() <= mine.n_r.to_numpy()).all()


def test_recall_at_n_ranks_at_least_n_whatever_the_operating_point(compared, direct):
    """Recall@N reads a ranking of at least N candidates: at L = 1 a FAISS code's ``top`` is
    FAISS's own top ``N_BEST`` though its operating point retrieves k < N_BEST (its match is
    still its top-1 at k), the baseline's are its ``N_BEST`` nearest though its budget is one;
    ``ranked_mean`` says how many each ranking weighed, and Recall@N never falls with N."""
    _, query, indexes = direct
    q, res = compared["queries"], compared["results"]
    for factory in ("PQ4np", "IVF32,PQ4np", "HNSW32"):
        assert _k(compared, factory) < N_BEST
        rows = q[(q.method == f"faiss:{factory}") & (q.L == 1)].sort_values("t")
        y = query.get_orthogonal_selection((rows.t.to_numpy(), slice(None)))
        assert_faiss_ranking(np.stack(rows.top.to_numpy()), factory, indexes[factory], y, N_BEST)
        runs = res[(res.method == f"faiss:{factory}") & (res.L == 1) & (res.part == "all")]
        assert (runs.ranked_mean == N_BEST).all() and (runs.nr_mean <= _k(compared, factory)).all()
    base = q[(q.method == "baseline") & (q.L == 1)]
    assert (base.n_r == 1).all() and (np.stack(base.top.to_numpy()) >= 0).all()
    assert (np.stack(base.top.to_numpy())[:, 0] == base["match"]).all()
    for _, run in res[res.part == "all"].groupby(["method", "params", "mode", "L"], dropna=False):
        r = run.sort_values("radius")
        for lo, hi in (("recall", "recall_at_5"), ("recall_at_5", "recall_at_10"), ("recall_at_10", "recall_at_20")):
            assert (r[lo].to_numpy() <= r[hi].to_numpy() + 1e-12).all()
        for name in ("recall", "recall_at_20", "recall_at_p100"):
            assert (r[f"{name}_lo"] <= r[name] + 1e-12).all() and (r[name] <= r[f"{name}_hi"] + 1e-12).all()


@pytest.mark.parametrize("flags", [["--best-bytes", "5"], ["--best-qps", "2000"], ["--best-bytes", "40", "--best-qps",
                                                                                     "500"]])
def test_best_operating_points_are_each_familys_best_within_the_budget(compared, capsys, flags):
    """``results --best-bytes B`` / ``--best-qps Q``: per noise, L and family, the point of best
    recall within 20 frames among those within the budget, as recomputed from the results."""
    assert main(["results", str(compared["out"]), *flags, "--csv"]) == 0
    from io import StringIO

    got = pd.read_csv(StringIO(capsys.readouterr().out))
    res = compared["results"]
    res = res[(res.radius == 20) & (res.part == "all")].assign(mode=lambda r: r["mode"].fillna("single"))
    res = res.assign(qps=1e6 / res.us_per_query)
    budget = dict(zip(flags[::2], map(float, flags[1::2]), strict=True))
    within = res[(res.bytes_per_place <= budget.get("--best-bytes", np.inf)) & (res.qps >= budget.get("--best-qps", 0))]
    expected = within.groupby(["noise", "L", "method", "mode"], dropna=False).recall.max()
    assert len(got) == len(expected) > 0
    assert (got.bytes_per_place <= budget.get("--best-bytes", np.inf)).all()
    assert (got.qps_per_core >= budget.get("--best-qps", 0)).all()
    assert sorted(got.recall.round(12)) == sorted(expected.round(12))
    assert main(["results", str(compared["out"]), *flags]) == 0  # the table for the eye names each method
    shown = capsys.readouterr().out.splitlines()
    assert "series" in shown[0] and "family" in shown[0] and "qps_per_core" in shown[0]
    assert {f for f in got.series} <= {f for f in got.series if any(f in line for line in shown[1:])}
    assert not got.family.isna().any()


def test_best_needs_the_recall_table_and_a_held_radius(compared, capsys):
    for argv, message in ((["--best-bytes", "4", "--queries"], "--best-bytes/--best-qps: operating points come"),
                          (["--best-qps", "10", "--radius", "99"], "--radius 99: the evaluations hold radii 0 … 20")):
        assert main(["results", str(compared["out"]), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1


def test_every_method_names_its_family_wherever_it_is_shown(compared, capsys):
    """The ``family`` column (VIBE's tags) on every row: hashing, PQ, binary, graph, the baseline;
    ``vprscale results`` shows it beside the method; the baseline at L > 1 is a sequence series."""
    from vprscale.compared.faisscodes import code_family
    from vprscale.evaluation.comparison import with_series

    res = compared["results"]
    families = res.groupby("method").family.agg(set).to_dict()
    assert families == {"coarsehash": {"hashing"}, "baseline": {"baseline"}, "faiss:PQ4np": {"PQ"},
                        "faiss:PQ4x6": {"PQ"}, "faiss:PQ6x4fs": {"PQ"}, "faiss:ITQ16,LSH": {"binary"},
                        "faiss:IVF32,PQ4np": {"PQ"}, "faiss:RaBitQ": {"binary"}, "faiss:IVF32,RaBitQfs": {"binary"},
                        "faiss:HNSW32": {"graph"}}
    assert [code_family(f) for f in ("RQ4x8", "IVF256,LSQ4x8", "PRQ2x4x8", "IVF1024_HNSW32,PQ8", "Flat")] == [
        "additive", "additive", "additive", "PQ", "exact"]
    shown = with_series(res[res.method == "baseline"])
    assert set(shown[shown.L > 1].series) == {"baseline (sequence)"} and set(shown[shown.L == 1].series) == {
        "baseline (single)"}
    assert main(["results", str(compared["out"]), "--where", "radius = 20 AND part = 'all'"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert "family" in table[0] and any("hashing" in line for line in table) and any("graph" in line for line in table)


def test_faiss_s_training_messages_are_said_once_not_printed_raw(caplog, capfd):
    """FAISS's k-means prints its warning on the process's stderr once per sub-quantiser, raw,
    between the command's own lines; it is said once, as a log line naming the code."""
    import logging

    from vprscale.compared.faisscodes import FaissCodes

    caplog.set_level(logging.INFO, logger="vprscale.compared.faisscodes")
    codes = FaissCodes("PQ2", 16, k=1)
    codes.train(np.random.default_rng(0).standard_normal((2000, 16)).astype(np.float32))
    err = capfd.readouterr().err  # where the log goes if the command line configured it (no propagation)
    assert not any(line.startswith("WARNING clustering") for line in err.splitlines()), err  # nothing raw
    line = "FAISS, training PQ2: WARNING clustering 2000 points to 256 centroids"
    assert max(caplog.text.count(line), err.count(line)) == 1, (caplog.text, err)  # once, wherever the log goes
