"""``vprscale eval --nn``: 1-NN recall at 1, 10 and 100 (docs/protocol.md, "Nearest-neighbour recall").

The exact neighbours against numpy's brute force, whatever the chunking; CoarseHash's ranking
against a plain enumeration of every address; nn.parquet against FAISS's own search.
"""

from __future__ import annotations

import json

import dask.array as da
import numpy as np
import pyarrow.parquet as pq
import pytest
import zarr

from vprscale.cli import main
from vprscale.evaluation.nearest import coarse_ranking, exact_neighbours
from vprscale.method.index import Index

from .conftest import SMALL_TRAINING, faiss_own


@pytest.mark.parametrize("chunks", [1_000, 4_096, 7_000])
def test_exact_neighbours_are_numpys_brute_force(chunks):
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(9_000, 16)).astype(np.float32)
    rows = ref[rng.integers(0, len(ref), 300)] + rng.normal(scale=0.3, size=(300, 16)).astype(np.float32)
    found = exact_neighbours(da.from_array(ref, chunks=(chunks, 16)), rows, workers=2, progress=False)
    dist = ((rows.astype(np.float64)[:, None, :] - ref.astype(np.float64)[None]) ** 2).sum(axis=2)
    truth = dist.argmin(axis=1)
    near_tie = np.take_along_axis(dist, found[:, None], 1)[:, 0] <= dist.min(axis=1) * (1 + 1e-5)
    assert near_tie.all() and (found == truth).mean() > 0.99


def _plain_ranking(idx: Index, h: int, depth: int) -> list[int]:
    """Every occupied address, by (Hamming distance to ``h``, δ, address), its list in stored order."""
    occupied = idx.lists.addresses(np.arange(idx.lists.n_lists)).astype(np.int64)
    w = idx.weights()
    gaps = w[::-1, 0, 1]  # bit b is component d − 1 − b
    xor = occupied ^ h
    bits = (xor[:, None] >> np.arange(idx.d)) & 1
    order = np.lexsort((occupied, bits @ gaps, bits.sum(axis=1)))
    out: list[int] = []
    for slot in order:
        out += idx.lists.list_ids(int(slot)).tolist()
        if len(out) >= depth:
            break
    return out[:depth]


def test_coarsehash_ranking_is_every_address_by_hamming_then_delta(tiny_store, tiny_index):
    idx = Index.load(tiny_index)
    rows = zarr.open_group(tiny_store, mode="r")["query_qm1"][:2000:40]
    ranking = coarse_ranking(idx, rows, 100)
    for row, got in zip(idx.hash_queries(rows), ranking, strict=True):
        assert got.tolist() == _plain_ranking(idx, int(row), 100)


@pytest.fixture(scope="module")
def nearest(tiny_store, tiny_index, tmp_path_factory):
    out = tmp_path_factory.mktemp("nn")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("vprscale.compared.faisscodes.TRAIN_ROWS", SMALL_TRAINING)
        assert main(["eval", str(tiny_store), str(tiny_index), "--L", "1", "--noise", "qm1,qm2", "--no-baseline",
                     "--repeats", "1", "--compare", "PQ4np", "--compare", "IVF32,PQ4np", "--nn", "--nn-queries",
                     "500", "--out", str(out)]) == 0
    return pq.read_table(out / "nn.parquet").to_pandas(), json.loads((out / "eval.json").read_text()), out


@pytest.mark.slow
def test_nn_parquet_holds_each_method_on_each_noise_level(nearest):
    nn, meta, _ = nearest
    assert meta["nn_queries"] == 500
    assert sorted(zip(nn.noise, nn.method, strict=True)) == sorted(
        (n, m) for n in ("qm1", "qm2") for m in ("coarsehash", "faiss:PQ4np", "faiss:IVF32,PQ4np"))
    assert (nn.n_queries == 500).all() and (nn.timed_queries == 500).all() and (nn.threads == 1).all()
    assert (nn.us_per_query > 0).all()
    assert (nn.recall_at_1 <= nn.recall_at_10).all() and (nn.recall_at_10 <= nn.recall_at_100).all()
    bpp = nn.groupby("method").bytes_per_place.first()
    assert bpp["faiss:PQ4np"] == 4 and bpp["faiss:IVF32,PQ4np"] == 4 + 8  # code, and an IVF list entry's id
    assert list(nn.family.unique()) == ["hashing", "PQ"]


@pytest.mark.slow
def test_nn_recalls_are_faiss_own_search_against_brute_force(nearest, tiny_store):
    """The recalls of a FAISS code: its own top 100 of the same rows, against the exact neighbours
    by numpy's brute force."""
    nn, _, _ = nearest
    group = zarr.open_group(tiny_store, mode="r")
    ref = group["ref"][:]
    from vprscale.compared.faisscodes import training_rows
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("vprscale.compared.faisscodes.TRAIN_ROWS", SMALL_TRAINING)
        index = faiss_own("PQ4np", ref[training_rows(len(ref))], ref)
    n_deep = json.loads(json.dumps(dict(group.attrs)))["vprscale"]["layout"]["n_deep1b"]
    frames = np.unique(np.linspace(0, n_deep - 1, 500).round().astype(np.int64))
    rows = group["query_qm1"][:][frames]
    truth = np.array([((ref - r) ** 2).sum(axis=1).argmin() for r in rows.astype(np.float64)])
    _, ids = index.search(rows, 100)
    got = nn[(nn.noise == "qm1") & (nn.method == "faiss:PQ4np")].iloc[0]
    for r in (1, 10, 100):
        assert got[f"recall_at_{r}"] == pytest.approx((ids[:, :r] == truth[:, None]).any(axis=1).mean(), abs=0.005)


def test_nn_needs_binary_addresses(tiny_store, tmp_path, capsys):
    from vprscale.jobs.indexing import build_index

    build_index(tiny_store, d=8, k=3, out=tmp_path / "k3.index", quiet=True)
    code = main(["eval", str(tiny_store), str(tmp_path / "k3.index"), "--L", "1", "--noise", "qm1", "--nn",
                 "--out", str(tmp_path / "e")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--nn" in err and "K = 3" in err and not (tmp_path / "e").exists()


def test_addresses_of_one_hamming_distance_come_cheapest_first():
    """Within a Hamming distance, the addresses CoarseHash's δ puts nearer come first (ties by value)."""
    from vprscale.evaluation.nearest import _masks

    gaps = np.array([5, 1, 3, 1])
    assert _masks(4, 1, gaps).tolist() == [0b0010, 0b1000, 0b0100, 0b0001]
    two = _masks(4, 2, gaps)
    cost = [sum(int(gaps[b]) for b in range(4) if m >> b & 1) for m in two.tolist()]
    assert cost == sorted(cost) and two.tolist()[:2] == [0b1010, 0b0110]


@pytest.mark.slow
def test_report_shows_the_nn_table_beside_the_published_figures(nearest, tmp_path):
    nn, _, out = nearest
    assert main(["report", str(out), "--out", str(tmp_path / "r")]) == 0
    md = (tmp_path / "r" / "report.md").read_text()
    section = md[md.index("## Nearest-neighbour recall"):]
    section = section[: section.find("\n## ", 3) if "\n## " in section[3:] else None]
    assert section.count("| tiny |") == len(nn) and "OPQ20_80,IMI2x14,PQ20" in section
    assert f"| {nn.recall_at_100.iloc[0]:.3f} |" in section
    assert (tmp_path / "r" / "fig_nn.png").is_file()


@pytest.mark.slow
def test_the_sql_console_has_the_nn_table(nearest, capsys):
    nn, _, out = nearest
    capsys.readouterr()
    assert main(["sql", str(out), "SELECT method, recall_at_100 FROM nn WHERE noise = 'qm1' ORDER BY method",
                 "--json"]) == 0
    got = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    want = nn[nn.noise == "qm1"].sort_values("method")
    assert [r["method"] for r in got] == want.method.tolist()
    assert [r["recall_at_100"] for r in got] == pytest.approx(want.recall_at_100.tolist())


def test_nn_needs_query_rows_in_the_first_part(tmp_path, capsys):
    rng = np.random.default_rng(2)
    ref = rng.normal(size=(3_000, 16)).astype(np.float32)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "q.npy", ref[:600] + 0.1)
    np.save(tmp_path / "gt.npy", np.arange(600))
    np.save(tmp_path / "part.npy", np.ones(600, np.uint8))  # every query row in the second part
    assert main(["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"q={tmp_path / 'q.npy'}", "--gt",
                 str(tmp_path / "gt.npy"), "--part", str(tmp_path / "part.npy"), "--out", str(tmp_path), "-q"]) == 0
    assert main(["index", str(tmp_path / "ref.zarr"), "--out", str(tmp_path / "i"), "-q"]) == 0
    capsys.readouterr()
    code = main(["eval", str(tmp_path / "ref.zarr"), str(tmp_path / "i"), "--L", "1", "--nn", "--out",
                 str(tmp_path / "e")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--nn: the store has no query rows in its first part" in err and not (tmp_path / "e").exists()
