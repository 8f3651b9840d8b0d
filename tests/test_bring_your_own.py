"""Your own method under the protocol (docs/bring-your-own.md): the page's example runs as it
stands, the shared contract suite holds for it and for every built-in method (and fails a
broken one), and its evaluated matches are those of an exact search and window score."""

import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import zarr

from vprscale.core.errors import InputError

DOC = Path(__file__).parents[1] / "docs" / "bring-your-own.md"


@pytest.fixture
def exact_l2(tmp_path, monkeypatch):
    """The page's example method, written where the page says (``exact_l2.py`` in the working
    directory), imported as ``--method`` would."""
    code = next(b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S) if "class ExactL2" in b)
    (tmp_path / "exact_l2.py").write_text(code)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("exact_l2", None)
    import exact_l2

    yield exact_l2.ExactL2
    sys.modules.pop("exact_l2", None)


@pytest.mark.slow
def test_the_pages_own_descriptors_example_runs_as_written(tmp_path, monkeypatch, capsys):
    """The page's first two blocks as a new user runs them: the numpy that makes the inputs, then
    every ``vprscale`` line of the shell block. The small store's chunks fit its data, and a store
    without parts reports the ``all`` part only."""
    import shlex

    from vprscale.cli import main

    blocks = DOC.read_text()
    make = re.findall(r"```python\n(.*?)```", blocks, re.S)[0]
    shell = re.findall(r"```bash\n(.*?)```", blocks, re.S)[0]
    monkeypatch.chdir(tmp_path)
    exec(compile(make, "bring-your-own.md", "exec"), {})
    for line in shell.strip().splitlines():
        argv = shlex.split(line)
        assert argv[0] == "vprscale"
        assert main(argv[1:]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    store_bytes = sum(f.stat().st_size for f in (tmp_path / "data" / "mine.zarr").rglob("*") if f.is_file())
    assert store_bytes < 5e6
    assert "  all " in out and "deep1b" not in out and " fas " not in out
    import pyarrow.parquet as pq

    assert set(pq.read_table(tmp_path / "data" / "mine.eval" / "results.parquet").column("part").to_pylist()) == {"all"}


def test_the_pages_example_passes_the_contract_suite(exact_l2):
    from vprscale.testing import check_algorithm

    check_algorithm(exact_l2)


def test_the_contract_suite_fails_a_broken_method(exact_l2):
    from vprscale.testing import check_algorithm

    class WorstFirst(exact_l2):
        def query(self, frames, k):
            ids, dist = super().query(frames, k)
            return ids[:, ::-1], dist[:, ::-1]

    class FarPairs(exact_l2):
        def pair_distances(self, frames, ref_ids):
            return super().pair_distances(frames, ref_ids) + 1.0

    with pytest.raises(AssertionError, match="not ascending"):
        check_algorithm(WorstFirst)
    with pytest.raises(AssertionError, match="disagrees"):
        check_algorithm(FarPairs)


def _nearest(dist: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` least distances' ids, ties to the smaller id: a stable argsort's first ``k``."""
    cut = np.partition(dist, k - 1)[k - 1]
    ids = np.flatnonzero(dist <= cut)
    return ids[np.argsort(dist[ids], kind="stable")][:k]


def _window_score(ref, y, c, t, L):
    """Brute force: Σ_l ‖y_{t+l} − ref_{c+l}‖², a place outside the map costing ``largest``."""
    half = L // 2
    d = [((y[t + i - half] - ref[c + i - half]) ** 2).sum() if 0 <= c + i - half < len(ref) else None
         for i in range(L)]
    return d


@pytest.mark.slow
def test_an_outside_method_evaluates_as_an_exact_search(exact_l2, tiny_store, tiny_index, tmp_path):
    """``eval --method exact_l2:ExactL2``: L = 1 matches are numpy's argmin over the references;
    L = 5 matches have the least brute-force window score over the union of the window's top-k."""
    from vprscale.cli import main

    out = tmp_path / "mine.eval"
    assert main(["eval", str(tiny_store), str(tiny_index), "--method", "exact_l2:ExactL2", "--method-k", "4",
                 "--noise", "qm1", "--L", "1,5", "--modes", "paper", "--no-baseline", "--repeats", "1",
                 "--z", "97", "--out", str(out)]) == 0  # every 97th centre: a brute force over 52,500 places
    q = pd.read_parquet(out / "queries.parquet")
    mine = q[q.method == "exact-l2"]
    assert set(mine.params) == {"k=4"} and set(mine.L) == {1, 5}
    group = zarr.open_group(tiny_store, mode="r")
    ref = group["ref"][:].astype(np.float64)
    y = group["query_qm1"]
    one = mine[mine.L == 1].iloc[::3]
    for t, m, score in zip(one.t, one.match, one.score, strict=True):
        dist = ((ref - y[t].astype(np.float64)) ** 2).sum(axis=1)
        assert m == dist.argmin() and np.isclose(score, dist.min())
    five = mine[mine.L == 5].iloc[::5]
    L, half = 5, 2
    for t, m, score in zip(five.t, five.match, five.score, strict=True):
        rows = y[t - half:t - half + L].astype(np.float64)
        top = [_nearest(((ref - r) ** 2).sum(axis=1), 4) for r in rows]
        cand = sorted({int(c) for ids in top for c in ids})
        terms = {c: _window_score(ref, rows, c, half, L) for c in cand}  # the window's rows, centred at half
        largest = max(x for d in terms.values() for x in d if x is not None)
        scores = {c: sum(largest if x is None else x for x in d) for c, d in terms.items()}
        best = min(scores.values())
        assert m == min(c for c, s in scores.items() if np.isclose(s, best, rtol=1e-9))
        assert np.isclose(score, best)
    results = pd.read_parquet(out / "results.parquet")
    assert {"recall_lo", "recall_hi", "recall_at_5", "auc_pr"} <= set(results.columns)


def test_every_built_in_method_passes_the_shared_answers_suite(tiny_store, tiny_index, exact_l2, small_training):
    """The second half of the contract suite, on CoarseHash, the baseline, a FAISS code and a
    plugged method, each created by the registry as an evaluation would."""
    from vprscale.compared.faisscodes import FaissCodes
    from vprscale.core.zarrio import rows_of
    from vprscale.dataset.store import store_layout
    from vprscale.evaluation.algorithms import registry
    from vprscale.evaluation.algorithms.baseline import load_baseline_map
    from vprscale.evaluation.algorithms.faisscodes import fit_codes
    from vprscale.method.index import Index
    from vprscale.testing import check_answers

    group = zarr.open_group(tiny_store, mode="r")
    idx = Index.load(tiny_index).warm()
    codes = [FaissCodes("PQ4np", 96, 8), FaissCodes("IVF16,PQ4np", 96, 8)]
    fit_codes(codes, rows_of(group["ref"]), quiet=True)
    mine = exact_l2()
    mine.fit(rows_of(group["ref"]))
    context = registry.Context(index_path=tiny_index, index=idx, dim=96, n_query=group["gt"].shape[0],
                               n_centres=100, lengths=[1, 5], workers=2,
                               baseline=load_baseline_map(group, store_layout(group)), compared=codes,
                               plugged=[("exact-l2", mine)], method_k=[4])
    algorithms = registry.create(context)
    assert [a.name for a in algorithms] == ["coarsehash", "baseline", "faiss:PQ4np", "faiss:IVF16,PQ4np", "exact-l2"]
    rows = group["query_qm1"][40_000:40_300]
    for alg in algorithms:
        alg.prepare("qm1", np.arange(300), rows, {1: np.arange(0, 300, 7), 5: np.arange(2, 290, 7)})
        check_answers(alg, rows, idx.n_ref)


def test_a_method_that_cannot_be_loaded_or_lacks_the_contract_is_one_line(exact_l2, tiny_store, tiny_index):
    from vprscale.evaluation.algorithms.plugged import load_method

    with pytest.raises(InputError, match="cannot be loaded"):
        load_method("exact_l2:Missing")
    with pytest.raises(InputError, match="package.module:Class"):
        load_method("exact_l2")
    with pytest.raises(InputError, match="no fit or query"):
        load_method("collections:OrderedDict")


def test_a_pipeline_stage_re_runs_when_its_methods_source_changes(exact_l2, tmp_path):
    from vprscale.core.digests import DigestCache
    from vprscale.jobs.pipeline import Stage, _inputs

    stage = Stage("eval-mine", "eval", {"store": "build", "methods": ["exact_l2:ExactL2"]})
    digests = DigestCache(tmp_path / "digests.json")
    before = _inputs(stage, digests)
    path = tmp_path / "exact_l2.py"
    path.write_text(path.read_text() + "\n# tuned\n")
    assert _inputs(stage, digests) != before and set(before) == {"method:exact_l2:ExactL2"}
