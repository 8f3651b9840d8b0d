"""Your own descriptors as a store (``vprscale build --ref … --query NAME=… --gt …``): every
command reads it, and bad input is one line with nothing written."""

import re

import numpy as np
import pandas as pd
import pytest
import zarr

from vprscale.cli import main


def write_fbin(path, rows):
    """The .fbin layout: uint32 rows and dimensions, then float32 row-major."""
    with open(path, "wb") as fh:
        fh.write(np.array(rows.shape, "<u4").tobytes() + np.ascontiguousarray(rows, "<f4").tobytes())


@pytest.fixture
def own_files(tmp_path):
    """A walk of 6,000 places, seen again by 1,500 frames in two conditions; truth for all but 10."""
    rng = np.random.default_rng(1)
    n, dim = 6_000, 24
    walk = (np.cumsum(rng.normal(size=(n, dim)), axis=0) / 8 + rng.normal(size=(n, dim))).astype(np.float32)
    truth = np.arange(1_000, 2_500)
    files = {"ref": tmp_path / "ref.npy", "day": tmp_path / "day.fbin", "night": tmp_path / "night.npy",
             "gt": tmp_path / "gt.npy", "part": tmp_path / "part.npy"}
    np.save(files["ref"], walk)
    write_fbin(files["day"], walk[truth] + rng.normal(scale=0.3, size=(len(truth), dim)).astype(np.float32))
    np.save(files["night"], (walk[truth] + rng.normal(scale=0.8, size=(len(truth), dim))).astype(np.float64))
    gt = truth.copy()
    gt[:10] = -1
    np.save(files["gt"], gt)
    np.save(files["part"], (np.arange(len(truth)) >= 1_200).astype(np.int64))
    return files


def _build(files, out, *extra):
    return main(["build", "--ref", str(files["ref"]), "--query", f"day={files['day']}",
                 "--query", f"night={files['night']}", "--gt", str(files["gt"]), "--part", str(files["part"]),
                 "--out", str(out), "--name", "walk", "--stride", "5", "--workers", "2", *extra])


def test_own_descriptors_build_index_evaluate_and_query(own_files, tmp_path, capsys):
    out = tmp_path / "data"
    assert _build(own_files, out) == 0
    store = out / "walk.zarr"
    group = zarr.open_group(store, mode="r")
    np.testing.assert_array_equal(group["ref"][:], np.load(own_files["ref"]))
    np.testing.assert_array_equal(group["query_night"][:], np.load(own_files["night"]).astype(np.float32))
    np.testing.assert_array_equal(group["gt"][:], np.load(own_files["gt"]))
    assert main(["index", str(store), "--out", str(tmp_path / "walk.index")]) == 0
    assert main(["eval", str(store), str(tmp_path / "walk.index"), "--noise", "night", "--L", "1,20",
                 "--repeats", "1", "--no-baseline"]) == 0
    res = pd.read_parquet(tmp_path / "walk.index" / "eval" / "results.parquet")
    assert set(res.noise) == {"night"} and set(res.scale) == {"walk"}
    q = pd.read_parquet(tmp_path / "walk.index" / "eval" / "queries.parquet")
    assert (q[q.part == "fas"].t >= 1_200).all() and (q[q.part == "deep1b"].t < 1_200).all()  # --part's 0s, then 1s
    assert (q[(q.L == 20) & (q["mode"] == "aligned")].error <= 5).mean() > 0.9  # the walk is found again
    capsys.readouterr()
    assert main(["sql", str(tmp_path / "walk.index"), "SELECT DISTINCT noise FROM results", "--csv"]) == 0
    assert [w.strip('"') for w in capsys.readouterr().out.split()] == ["noise", "night"]
    assert main(["eval", str(store), str(tmp_path / "walk.index"), "--noise", "dusk", "--out",
                 str(tmp_path / "e2")]) == 2
    assert "no such query set; choose from day, night" in capsys.readouterr().err


@pytest.mark.parametrize("damage, message", [
    ("nan", "night.npy: row 700 holds NaN or Inf"),
    ("gt-length", "gt.npy: 1,499 ground truth values for 1,500 query rows"),
    ("gt-range", "gt.npy: row 3 holds 6000, not a reference row"),
    ("gt-unsigned", "gt.npy: row 5 holds 18446744073709551615, beyond any row number"),
    ("part-order", "part.npy: parts must be 0 for the first query rows, then 1"),
    ("dims", "day.fbin: query rows have 23 dimensions, the references 24"),
])
def test_bad_own_input_is_one_line_and_writes_nothing(own_files, tmp_path, capsys, damage, message):
    if damage == "nan":
        night = np.load(own_files["night"])
        night[700, 5] = np.nan
        np.save(own_files["night"], night)
    elif damage == "gt-length":
        np.save(own_files["gt"], np.load(own_files["gt"])[:-1])
    elif damage == "gt-range":
        gt = np.load(own_files["gt"])
        gt[3] = 6_000
        np.save(own_files["gt"], gt)
    elif damage == "gt-unsigned":  # 2^64 − 1 wrapped to −1 ("no truth"): truths vanished with exit 0
        gt = np.maximum(np.load(own_files["gt"]), 0).astype(np.uint64)
        gt[5] = np.iinfo(np.uint64).max
        np.save(own_files["gt"], gt)
    elif damage == "part-order":
        np.save(own_files["part"], np.load(own_files["part"])[::-1])
    else:
        write_fbin(own_files["day"], np.zeros((1_500, 23), np.float32))
    out = tmp_path / "data"
    assert _build(own_files, out) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "error" in line]
    assert len(err) == 1 and message in err[0], err  # a NaN is found while the rows stream, after progress lines
    assert not (out / "walk.zarr").exists()


def test_an_existing_own_store_is_kept_without_force(own_files, tmp_path, capsys):
    out = tmp_path / "data"
    assert _build(own_files, out) == 0
    before = (out / "walk.zarr" / "manifest.json").read_bytes()
    assert _build(own_files, out) == 2
    assert "already holds a store; --force replaces it" in capsys.readouterr().err
    assert (out / "walk.zarr" / "manifest.json").read_bytes() == before
    assert _build(own_files, out, "--force") == 0


@pytest.mark.parametrize(("rows", "dim"), [(3, 50_000), (300, 40_000), (70_000, 96)])
def test_own_chunks_are_sized_by_bytes_not_rows(rows, dim, tmp_path, capsys):
    """Chunks of at most 32 MiB whatever the width, a power of two of rows (blocks start on chunks),
    and the rows as given."""
    from vprscale.dataset.own import CHUNK_BYTES

    rng = np.random.default_rng(1)
    ref = rng.standard_normal((rows, dim), dtype=np.float32)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "q.npy", ref[::-1].copy())
    np.save(tmp_path / "gt.npy", np.arange(rows)[::-1].copy())
    assert main(["build", "--ref", str(tmp_path / "ref.npy"), "--query", f"day={tmp_path / 'q.npy'}", "--gt",
                 str(tmp_path / "gt.npy"), "--name", "w", "--out", str(tmp_path / "data"), "-q"]) == 0
    store = zarr.open_group(tmp_path / "data" / "w.zarr", mode="r")
    chunk = store["ref"].chunks[0]
    assert chunk * dim * 4 <= CHUNK_BYTES and chunk & (chunk - 1) == 0 or chunk == rows
    assert chunk == min(rows, 1 << (CHUNK_BYTES // (4 * dim)).bit_length() - 1)
    assert np.array_equal(store["ref"][:], ref) and np.array_equal(store["query_day"][:], ref[::-1])
    on_disk = sum(f.stat().st_size for f in (tmp_path / "data" / "w.zarr").rglob("*") if f.is_file())
    assert on_disk <= 2 * (ref.nbytes + chunk * dim * 4) + (1 << 20)  # the data, and at most a chunk's padding


def test_an_own_store_larger_than_the_free_disk_is_refused_before_work(own_files, small_filesystem, capsys):
    from .test_reliability import fails

    argv = ["build", "--ref", str(own_files["ref"]), "--query", f"day={own_files['day']}", "--gt",
            str(own_files["gt"]), "--out", str(small_filesystem / "data")]
    fails(capsys, argv, "--out", "GiB free")
    assert not any((small_filesystem / "data").iterdir())


def test_positions_count_every_reference_within_a_radius_in_metres(own_files, tmp_path, capsys):
    """``--ref-pos`` (.npy) and ``--query-pos`` (@UTM@ image names), then ``eval --radius-m``: a
    match is correct when its reference lies within R metres of the query (VPR-methods-evaluation's
    positives); every figure recomputed here from the per-query rows and the positions."""
    rng = np.random.default_rng(4)
    n_ref = np.load(own_files["ref"]).shape[0]
    steps = rng.uniform(1.0, 3.0, n_ref)  # a road: 1-3 m between places, east then north
    ref_pos = np.c_[500_000 + np.cumsum(steps), 4_100_000 + 0.3 * np.cumsum(steps)]
    truth = np.arange(1_000, 2_500)  # own_files' query rows show these places
    query_pos = ref_pos[truth] + rng.normal(scale=2.0, size=(len(truth), 2))
    np.save(tmp_path / "ref_pos.npy", ref_pos)
    names = [f"queries/@{e:.2f}@{n:.2f}@17@S@037@.jpg" for e, n in query_pos]
    (tmp_path / "query_names.txt").write_text("\n".join(names) + "\n")
    query_pos = np.round(query_pos, 2)
    out = tmp_path / "data"
    argv = ["build", "--ref", str(own_files["ref"]), "--query", f"night={own_files['night']}", "--gt",
            str(own_files["gt"]), "--ref-pos", str(tmp_path / "ref_pos.npy"), "--query-pos",
            str(tmp_path / "query_names.txt"), "--out", str(out), "-q"]
    assert main(argv) == 0
    store, index = out / "ref.zarr", tmp_path / "walk.index"
    np.testing.assert_array_equal(zarr.open_group(store, mode="r")["query_pos"][:], query_pos)
    assert main(["index", str(store), "--out", str(index), "-q"]) == 0
    assert main(["eval", str(store), str(index), "--L", "1,20", "--radius-m", "5,25", "--repeats", "1",
                 "--no-baseline", "-q"]) == 0
    res = pd.read_parquet(index / "eval" / "results_m.parquet")
    q = pd.read_parquet(index / "eval" / "queries.parquet")
    assert sorted(set(res.radius_m)) == [5.0, 25.0] and "radius" not in res.columns
    for (L, mode), runs in q.groupby(["L", q["mode"].fillna("-")]):
        distance = np.linalg.norm(ref_pos[runs.match] - query_pos[runs.t], axis=1)
        np.testing.assert_allclose(runs.error_m, distance)
        top5 = np.array([np.linalg.norm(ref_pos[[i for i in t[:5] if i >= 0]] - query_pos[c], axis=1)
                         .min(initial=np.inf) for t, c in zip(runs["top"], runs.t, strict=True)])
        for radius in (5.0, 25.0):
            row = res[(res.L == L) & (res["mode"].fillna("-") == mode) & (res.radius_m == radius)
                      & (res.part == "all")].iloc[0]
            assert row.recall == pytest.approx((distance <= radius).mean())
            assert row.recall_at_5 == pytest.approx((top5 <= radius).mean())
            assert row.recall_lo <= row.recall <= row.recall_hi
    assert res[(res.radius_m == 25.0)].recall.max() > 0.5  # the walk is found again, within 25 m
    capsys.readouterr()
    assert main(["results", str(index), "--metres", "--where", "radius_m = 25 AND L = 20", "--csv"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 3  # the header and the paper and aligned rows
    assert main(["sql", str(index), "SELECT count(*) AS n FROM results_m", "--csv"]) == 0
    assert capsys.readouterr().out.split()[1] == str(len(res))
    assert main(["report", str(index / "eval"), "--out", str(tmp_path / "report"), "-q"]) == 0
    text = (tmp_path / "report" / "report.md").read_text()
    best = res[(res.L == 20) & (res["mode"] == "aligned") & (res.radius_m == 25.0) & (res.part == "all")].iloc[0]
    assert "## Recall within metres" in text
    row = (f"| ref | NIGHT | all | 20 | CoarseHash d=13 (aligned) | hashing | 25 | {best.n_queries} | "
           f"{100 * best.recall:.1f} |")
    assert row in text
    # a report of your own data: every figure it shows is there, no noise level it does not hold, no
    # comparison with the paper's datasets, which these are not
    shown = re.findall(r"!\[[^]]*\]\(([^)]+)\)", text)
    assert shown and all((tmp_path / "report" / name).is_file() for name in shown)
    assert "QM1" not in text and "QM2" not in text and "cannot be downloaded" not in text
    assert "## The paper's text figures beside ours" not in text
    # nor a section it has nothing for (no baseline was evaluated), parts it does not have, a
    # rescaling it never had, or an HTML entity
    assert "vs baseline" not in text and "| Deep1B |" not in text and "| FAS |" not in text
    assert "(no rescale)" not in text and "&amp;" not in text and "R@20 %)" not in text
    for table in re.findall(r"(?m)(?:^\|.*\n)+", text):
        assert len(table.splitlines()) > 2, table  # a header and its rows, never a header alone


@pytest.mark.parametrize(("case", "message"), [
    ("one side", "--query-pos missing"),
    ("rows", "ref_pos.npy: 5,999 reference positions for 6,000 rows"),
    ("columns", "ref_pos.npy: reference positions must be numbers in 2 or 3 columns"),
    ("name", "names.txt: line 2 ('b.jpg') has no @UTM_east@UTM_north@"),
    ("number", "names.txt: line 2 ('@1.2.3@4@.jpg') has no @UTM_east@UTM_north@"),
    ("nan", "ref_pos.npy: row 7 of the reference positions is not a finite number"),
])
def test_bad_positions_are_one_line_and_write_nothing(own_files, tmp_path, capsys, case, message):
    from .test_reliability import fails

    ref_pos = np.zeros((6_000, 2))
    if case == "rows":
        ref_pos = ref_pos[1:]
    elif case == "columns":
        ref_pos = np.zeros((6_000, 4))
    elif case == "nan":
        ref_pos[7, 1] = np.nan
    np.save(tmp_path / "ref_pos.npy", ref_pos)
    (tmp_path / "names.txt").write_text("x/@1@2@.jpg\n" + ("@1.2.3@4@.jpg" if case == "number" else "b.jpg") + "\n")
    argv = ["build", "--ref", str(own_files["ref"]), "--query", f"day={own_files['day']}", "--gt",
            str(own_files["gt"]), "--ref-pos", str(tmp_path / "ref_pos.npy"), "--out", str(tmp_path / "data")]
    if case != "one side":
        argv += ["--query-pos", str(tmp_path / ("names.txt" if case in ("name", "number") else "q.npy"))]
        np.save(tmp_path / "q.npy", np.zeros((1_500, 2)))
    if case in ("name", "number"):
        argv[argv.index("--ref-pos") + 1] = str(tmp_path / "names.txt")
    fails(capsys, argv, message)
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").iterdir())


def test_radius_in_metres_needs_a_store_with_positions(own_files, tmp_path, capsys):
    from .test_reliability import fails

    out = tmp_path / "data"
    assert _build(own_files, out) == 0
    assert main(["index", str(out / "walk.zarr"), "--out", str(tmp_path / "i"), "-q"]) == 0
    fails(capsys, ["eval", str(out / "walk.zarr"), str(tmp_path / "i"), "--radius-m", "25"], "holds no positions")
    fails(capsys, ["eval", str(out / "walk.zarr"), str(tmp_path / "i"), "--radius-m", "25,-1"], "above 0")


def test_the_truth_follows_from_positions_when_no_gt_is_given(own_files, tmp_path, capsys):
    """``--ref-pos`` and ``--query-pos`` without ``--gt``: each query row's truth is its nearest
    reference by position (ties: the smaller row), or none beyond ``--gt-radius-m``; as a brute-force
    search finds it. Without positions ``--gt`` is still asked for, in one line."""
    from .test_reliability import fails

    rng = np.random.default_rng(7)
    ref_pos = rng.integers(0, 400, size=(6_000, 2)).astype(np.float64)  # on a grid of metres: ties happen
    query_pos = ref_pos[np.arange(1_000, 2_500)] + rng.normal(scale=4.0, size=(1_500, 2))
    query_pos[:40] += 10_000  # far from every reference: no truth
    np.save(tmp_path / "ref_pos.npy", ref_pos)
    np.save(tmp_path / "query_pos.npy", query_pos)
    argv = ["build", "--ref", str(own_files["ref"]), "--query", f"day={own_files['day']}", "--out",
            str(tmp_path / "data"), "--name", "walk", "--gt-radius-m", "6", "-q"]
    fails(capsys, argv, "--gt missing")
    positions = ["--ref-pos", str(tmp_path / "ref_pos.npy"), "--query-pos", str(tmp_path / "query_pos.npy")]
    assert main([*argv, *positions]) == 0
    gt = zarr.open_group(tmp_path / "data" / "walk.zarr", mode="r")["gt"][:]
    distance = np.linalg.norm(query_pos[:, None, :] - ref_pos[None, :, :], axis=2)
    expected = np.where(distance.min(axis=1) <= 6, distance.argmin(axis=1), -1)  # argmin: the first of equals
    np.testing.assert_array_equal(gt, expected)
    assert (gt[:40] == -1).all() and (gt >= 0).sum() > 1_000
