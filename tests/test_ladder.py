"""The report's ladder at a glance (vprscale/evaluation/ladder.py): one row per scale, each cell
read from the results it names."""

from __future__ import annotations

import pandas as pd

from vprscale.evaluation.ladder import ladder_section
from vprscale.evaluation.report import _md_table


def _row(scale, method, mode, L, recall, bytes_, us, d=20, params=None, noise="qm1", radius=20):
    return {"scale": scale, "noise": noise, "method": method, "mode": mode, "L": L, "d": d, "part": "all",
            "radius": radius, "recall": recall, "bytes_per_place": bytes_, "us_per_query": us, "params": params}


def _results() -> pd.DataFrame:
    rows = []
    for scale, d, base in (("1M", 20, 0.5), ("10M", 24, 0.3)):
        for L in (1, 50, 100):
            rows += [_row(scale, "coarsehash", "paper", L, base + L / 1000, 6.0, 2.0 * L, d),
                     _row(scale, "coarsehash", "aligned", L, base + L / 500, 6.0, 2.5 * L, d),
                     # a narrower index of the same scale (a d sweep): not the main width, not shown
                     _row(scale, "coarsehash", "paper", L, 0.99, 6.0, 1.0, d - 4),
                     _row(scale, "coarsehash", "paper", L, 0.98, 6.0, 1.0, d, noise="qm2"),
                     _row(scale, "coarsehash", "paper", L, 0.97, 6.0, 1.0, d, radius=0),
                     _row(scale, "baseline", None, L, 0.01, 4.0, 300.0, 1)]
    # 1M: a flat code within CoarseHash's bytes, one larger that finds more, two operating points of one
    rows += [_row("1M", "faiss:PQ3", "aligned", 100, 0.61, 3.0, 120.0, params="k=4"),
             _row("1M", "faiss:PQ3", "aligned", 100, 0.64, 3.0, 180.0, params="k=16"),
             _row("1M", "faiss:PQ3", "paper", 100, 0.40, 3.0, 110.0, params="k=4"),
             _row("1M", "faiss:IVF1024,PQ3", "aligned", 100, 0.95, 14.0, 90.0, params="k=4 nprobe=16"),
             _row("1M", "faiss:PQ3", "aligned", 50, 0.99, 3.0, 60.0, params="k=4")]
    # 10M: only a code larger than CoarseHash's bytes
    rows += [_row("10M", "faiss:IVF4096,PQ3", "aligned", 100, 0.9, 14.0, 95.0, params="k=4 nprobe=16")]
    return pd.DataFrame(rows)


def _indexes() -> list[dict]:
    return [{"store": {"scale": s}, "d": d, "n_ref": n, "whole": w}
            for s, d, n, w in (("1M", 20, 1_000_000, 6_500_000), ("10M", 24, 10_000_000, 71_000_000),
                               ("10M", 20, 10_000_000, 1))]


def _table(res: pd.DataFrame, scales: list[str]) -> dict[str, list[str]]:
    lines = ladder_section(res, _indexes(), scales, {"1M": 20, "10M": 24}, lambda i: i["whole"], _md_table)
    assert lines[0] == "## The ladder at a glance"
    return {cells[0]: cells for cells in ([c.strip() for c in line.strip("|").split("|")]
                                          for line in "\n".join(lines).splitlines() if line.startswith("| 1"))}


def test_each_scale_reads_coarsehash_at_its_main_width_and_the_best_code_within_its_bytes():
    rows = _table(_results(), ["1M", "10M"])
    assert list(rows) == ["1M", "10M"]
    # scale, d, index B/place, paper L=50, paper L=100, aligned L=50, aligned L=100, µs (paper), best code
    assert rows["1M"][:7] == ["1M", "20", "6.50", "55.0", "60.0", "60.0", "70.0"]
    assert rows["10M"][:7] == ["10M", "24", "7.10", "35.0", "40.0", "40.0", "50.0"]
    assert rows["1M"][7] == "100.0 / 200.0"
    # the flat code within 6 bytes a place that finds most at L = 100 (its best operating point and
    # mode), not the IVF code of 14 bytes that finds more
    assert rows["1M"][8] == "PQ3 k=16 (aligned): 64.0 % at 3.00 B/place, 180.0 µs"
    assert rows["10M"][8] == "none evaluated at these bytes"


def test_a_scale_without_compared_codes_or_a_single_scale():
    res = _results()
    rows = _table(res[~res.method.str.startswith("faiss:") | (res.scale == "1M")], ["1M", "10M"])
    assert rows["10M"][8] == "–"
    assert ladder_section(res[res.scale == "1M"], _indexes(), ["1M"], {"1M": 20}, lambda i: i["whole"],
                          _md_table) == []  # one scale: no ladder to read
