"""A flat code's exact top-k by visiting code values in order (vprscale.compared.codesearch):
against a brute force over every place on every shape hypothesis finds (shared codes, ties,
fewer places than k, the pass past the budget), and against FAISS's own search of the same
codes for each enumerable kind of flat index."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vprscale.compared import codesearch
from vprscale.compared.faisscodes import FaissCodes


def _brute(dist: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k smallest (distance, id) pairs of each row of per-place ``dist``, −1 / inf padded."""
    out_d, out_i = np.full((len(dist), k), np.inf), np.full((len(dist), k), -1)
    for p, row in enumerate(dist):
        order = np.lexsort((np.arange(len(row)), row))[:k]
        out_d[p, : len(order)], out_i[p, : len(order)] = row[order], order
    return out_d, out_i


@settings(max_examples=60)
@given(data=st.data(), M=st.integers(1, 3), bits=st.sampled_from([2, 3, 8]), n=st.integers(1, 300),
       k=st.integers(1, 12), tight=st.booleans())
def test_pq_topk_is_the_brute_force_top_k(data, M, bits, n, k, tight):
    """Codes drawn from few values (places share codes, distances tie), integer tables (ties
    between values too); ``tight``: a budget of one visit, so every frame takes the pass."""
    ksub = 1 << bits
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, min(ksub, data.draw(st.integers(1, ksub))), (n, M))
    keys = codesearch.code_keys(idx.astype(np.uint8), bits)
    tables = rng.integers(0, 6, (5, M, ksub)).astype(np.float64)
    values, starts, ids = codesearch.code_lists(keys)
    dist, found = codesearch.pq_topk(tables, bits, values, starts, ids, k, 1 if tight else codesearch.budget(n))
    brute = np.stack([tables[p][np.arange(M), idx].sum(axis=1) for p in range(5)])
    want_d, want_i = _brute(brute, k)
    np.testing.assert_array_equal(found, want_i)
    np.testing.assert_array_equal(dist, want_d)


@settings(max_examples=60)
@given(data=st.data(), bits=st.integers(1, 20), n=st.integers(1, 300), k=st.integers(1, 12), tight=st.booleans())
def test_hamming_topk_is_the_brute_force_top_k(data, bits, n, k, tight):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    spread = data.draw(st.integers(1, bits))  # codes differing in their low bits only: many shared
    keys = rng.integers(0, 1 << spread, n).astype(np.int64)
    queries = rng.integers(0, 1 << bits, 5).astype(np.int64)
    values, starts, ids = codesearch.code_lists(keys)
    dist, found = codesearch.hamming_topk(queries, bits, values, starts, ids, k, 1 if tight else codesearch.budget(n))
    brute = np.array([[bin(int(q) ^ int(x)).count("1") for x in keys] for q in queries], np.float64)
    want_d, want_i = _brute(brute, k)
    np.testing.assert_array_equal(found, want_i)
    np.testing.assert_array_equal(dist, want_d)


def test_code_keys_read_faiss_packing():
    """Packed little-endian bytes and one index per byte give the same key: Σ index_m << (bits · m)."""
    idx = np.array([[1, 2, 3], [15, 0, 7]], np.uint8)
    packed = np.array([[1 | 2 << 4, 3], [15 | 0 << 4, 7]], np.uint8)
    want = idx[:, 0].astype(np.int64) | idx[:, 1].astype(np.int64) << 4 | idx[:, 2].astype(np.int64) << 8
    np.testing.assert_array_equal(codesearch.code_keys(idx, 4), want)
    np.testing.assert_array_equal(codesearch.code_keys(packed), want)


@pytest.fixture(scope="module")
def rows():
    """Clustered rows (places near one another share codes) and queries near them."""
    rng = np.random.default_rng(11)
    centres = rng.standard_normal((300, 32)).astype(np.float32) * 3
    x = (centres[rng.integers(0, 300, 40_000)] + 0.5 * rng.standard_normal((40_000, 32))).astype(np.float32)
    q = (x[rng.integers(0, len(x), 400)] + 0.3 * rng.standard_normal((400, 32))).astype(np.float32)
    return x, q


@pytest.mark.parametrize("factory", ["PQ2", "PQ4x4", "PQ4x6", "OPQ2,PQ2", "ITQ20,LSH", "LSH"])
def test_exact_search_is_faiss_search(rows, factory):
    """The exact top-k of each enumerable kind is FAISS's search of the same codes, ids and
    order (binary codes: their distances too; product quantisers: within float32 rounding)."""
    x, q = rows
    codes = FaissCodes(factory, x.shape[1], k=9)
    assert codes.enumerable
    codes.train(x[::4])
    codes.start(len(x))
    for lo in range(0, len(x), 7000):
        codes.encode(x[lo : lo + 7000])
    codes.finish()
    theirs_d, theirs_i = codes.search(q)
    ours_d, ours_i = codes.exact_search(q)
    same = (theirs_i == ours_i).all(axis=1)
    assert same.mean() >= 0.99  # the rest: places tied to float32 rounding
    np.testing.assert_allclose(ours_d, theirs_d, rtol=1e-5, atol=1e-4)
    if "LSH" in factory:
        assert same.all()
        np.testing.assert_array_equal(ours_d, theirs_d)
    codes.check_exact(q)  # and the evaluation's own check passes


def test_scanning_codes_are_not_enumerable():
    """Fast-scan product quantisers rank by 8-bit tables, IVF codes probe lists, others decode:
    their answers come from FAISS's search."""
    for factory in ("PQ4x4fs", "IVF16,PQ2", "SQ8", "PQ8"):  # PQ8: 64 bits, beyond one key
        assert not FaissCodes(factory, 32, k=3).enumerable


def test_check_exact_catches_a_wrong_top_k(rows, monkeypatch):
    """A broken exact search (one place swapped for another) is caught before any answer is used."""
    x, q = rows
    codes = FaissCodes("PQ2", x.shape[1], k=5)
    codes.train(x[::4])
    codes.start(len(x))
    codes.encode(x)
    codes.finish()
    right = codes.exact_search

    def wrong(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, i = right(r)
        i[3, 0] = (i[3, 0] + 1) % len(x)
        return d, i

    monkeypatch.setattr(codes, "exact_search", wrong)
    with pytest.raises(RuntimeError, match="query row 3"):
        codes.check_exact(q[:8])


def test_bench_codes_prints_the_frame_search_against_faiss(tiny_store, capsys, monkeypatch):
    """``vprscale bench codes``: for enumerable codes, a line per code with FAISS's search and the
    enumeration's µs per frame, and the frames on which both found the same ids (all, here). A
    distance-computer time within the timing noise (a median difference not above 0, given here
    for PQ4np) is said so, with no ratio made of it."""
    import vprscale.jobs.codesbench as codesbench
    from vprscale.cli import main

    measured = codesbench._faiss_distance_computer
    monkeypatch.setattr(codesbench, "_faiss_distance_computer", lambda codes, query, repeats: (
        (-1.0, -3.0, 2.0) if codes.factory == "PQ4np" else measured(codes, query, repeats)))
    assert main(["bench", "codes", str(tiny_store), "--compare", "PQ4np", "--compare", "ITQ16,LSH", "--compare",
                 "PQ6x4fs", "--L", "5"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out[:out.index("a frame's top-16")].splitlines()[2:] if line}
    assert list(rows) == ["PQ4np", "ITQ16,LSH", "PQ6x4fs"]
    assert "within noise" in rows["PQ4np"] and "-1.00" not in rows["PQ4np"]
    assert rows["PQ4np"].split()[-3] == "-"  # ours / distance computer
    section = out[out.index("a frame's top-16"):].splitlines()[2:]
    assert [line.split()[0] for line in section] == ["PQ4np", "ITQ16,LSH"]  # the fast-scan code scans
    for line in section:
        assert line.split()[-1] == "256/256"


def test_bench_codes_times_faiss_distance_computer_on_fast_scan_ivf_and_few_places(tiny_store, capsys):
    """The distance-computer column of an IVF fast-scan code reads its searched copy's lists (the
    trained index holds none: FAISS aborted the process), and fewer places than FAISS's random
    index would propose are all proposed."""
    from vprscale.cli import main

    assert main(["bench", "codes", str(tiny_store), "--compare", "IVF16,PQ4x4fsr", "--places", "3000",
                 "--L", "5"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("IVF16,PQ4x4fsr"))
    computer = float(line.split()[7])  # FAISS: distance comp. (median)
    assert computer > 0


def test_bench_assign_prints_each_coarse_quantisers_cost_and_its_agreement_with_the_exact_list(tiny_store, capsys):
    """``vprscale bench assign``: a line per IVF code with its CPU µs a row, the ratio to the first
    and the share of rows sent to their exact nearest list (all, for a flat quantiser); a code
    without a coarse assignment, or a compact store, is one line and exit 2."""
    from vprscale.cli import main

    assert main(["bench", "assign", str(tiny_store), "--compare", "IVF32,PQ4", "--compare", "IVF8,PQ4",
                 "--compare", "IVF32_HNSW32,PQ4"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in lines[1:]}
    assert list(rows) == ["IVF32,PQ4", "IVF8,PQ4", "IVF32_HNSW32,PQ4"]
    assert " 1.00× " in rows["IVF32,PQ4"]
    for factory in ("IVF32,PQ4", "IVF8,PQ4"):
        assert rows[factory].endswith("exact list for 100.0% of rows")
    assert float(rows["IVF8,PQ4"].split()[1]) > 0
    assert main(["bench", "assign", str(tiny_store), "--compare", "PQ4"]) == 2
    assert "--compare PQ4: not an IVF code" in capsys.readouterr().err
