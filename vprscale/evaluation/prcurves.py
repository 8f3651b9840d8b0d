"""The VPR metrics section of a report (docs/protocol.md, "Scores"): precision–recall curves
from every query's score, AUC-PR, recall at 100 % precision and Recall@N, as VPR-Bench and
SeqNet report them, for every method at every L.

A match is correct within ``RADIUS`` frames of the truth; the curves accept matches in
order of their score (lower is more confident). The figures are per method family at its
first operating point; the table gives every operating point, read from the results.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pandas as pd
import pyarrow.parquet as pq

from vprscale.evaluation.comparison import family_colours, family_label, family_line, shared_legend
from vprscale.evaluation.metrics import pr_curve
from vprscale.evaluation.results import main_noise

RADIUS = 20
COLUMNS = ("scale", "noise", "method", "mode", "L", "d", "params", "index", "error", "score")


def load_queries(runs: list[str], res: pd.DataFrame) -> pd.DataFrame:
    """The scored per-query rows of the report's main query set, from each evaluation folder
    (older evaluations, without scores, are left out)."""
    noise = main_noise(res)
    frames = []
    for run in runs:
        file = Path(run) / "queries.parquet"
        if not file.is_file():
            continue
        names = set(pq.read_schema(file).names)
        if "score" not in names:
            continue
        table = pq.read_table(file, columns=[c for c in COLUMNS if c in names], filters=[("noise", "=", noise)])
        frames.append(table.to_pandas())
    if not frames:
        return pd.DataFrame(columns=list(COLUMNS))
    q = pd.concat(frames, ignore_index=True)
    q["mode"] = q["mode"].fillna("single")
    q["family"] = [family_label(m, mode, d) for m, mode, d in zip(q.method, q["mode"], q.d, strict=True)]
    return q


def _first_points(q: pd.DataFrame) -> pd.DataFrame:
    """Each family's first operating point (its smallest params, as text) and its main index."""
    keys = q[["scale", "family", "params", "index"]].drop_duplicates().astype(str)
    first = keys.sort_values(["scale", "family", "params", "index"]).groupby(["scale", "family"]).head(1)
    merged = q.astype({"params": str, "index": str}).merge(first, on=["scale", "family", "params", "index"])
    return merged


def fig_pr(q: pd.DataFrame, scales: list[str], out: Path, save) -> bool:
    """Precision against recall per scale (columns) and L (rows)."""
    q = _first_points(q)
    scales = [s for s in scales if s in set(q.scale)]
    lengths = sorted(q.L.unique())
    if not scales or not lengths:
        return False
    families = list(dict.fromkeys(q.sort_values("method", key=lambda c: c.ne("coarsehash")).family))
    colours = family_colours(families)
    fig, axes = plt.subplots(len(lengths), len(scales), figsize=(4.4 * len(scales), 3.5 * len(lengths)),
                             squeeze=False, sharex=True, sharey=True, layout="constrained")
    for r, L in enumerate(lengths):
        for c, scale in enumerate(scales):
            ax = axes[r][c]
            for fam, g in q[(q.scale == scale) & (q.L == L)].groupby("family", sort=False):
                precision, recall = pr_curve(g.score.to_numpy(), g.error.to_numpy() <= RADIUS)
                ax.plot(100 * recall, 100 * precision, lw=1.2, ls=family_line(fam), color=colours[fam], label=fam)
            ax.set(xlim=(0, 100), ylim=(0, 102), title=f"{scale}, {main_noise(q).upper()}, L = {L}")
            ax.grid(alpha=0.3)
            if r == len(lengths) - 1:
                ax.set_xlabel(f"recall within {RADIUS} frames (%)")
            if c == 0:
                ax.set_ylabel("precision (%)")
    shared_legend(fig, axes)
    fig.suptitle("Precision–recall: matches accepted in order of their score")
    save(fig, out, "fig_pr")
    return True


def pr_section(res: pd.DataFrame, runs: list[str], scales: list[str], out: Path, save, table) -> list[str]:
    """The report's section: the figure, and the table of every method and operating point."""
    if "auc_pr" not in res.columns:
        return []
    q = load_queries(runs, res)
    drawn = not q.empty and fig_pr(q, scales, out, save)
    noise = main_noise(res)
    sub = res[(res.part == "all") & (res.radius == RADIUS) & (res.noise == noise)].copy()
    sub["mode"] = sub["mode"].fillna("single")
    rows: list[list[Any]] = []
    order = {s: i for i, s in enumerate(scales)}
    sub = sub.assign(pos=sub.scale.map(order)).sort_values(["pos", "L", "method", "mode", "d"])
    for p in sub.itertuples():
        name = family_label(p.method, p.mode, p.d)
        params = getattr(p, "params", None)
        rows.append([p.scale, p.L, name + (f" {params}" if isinstance(params, str) and params else ""),
                     *(f"{100 * v:.1f}" if v == v else "–" for v in
                       (p.recall, p.recall_at_5, p.recall_at_10, p.recall_at_20, p.recall_at_p100)),
                     f"{p.auc_pr:.3f}" if p.auc_pr == p.auc_pr else "–"])
    return ["## Scores: precision–recall, AUC-PR and Recall@N", "",
            f"Every answer carries its match's score (lower is more confident) and its 20 best candidates. "
            f"A match is correct within {RADIUS} frames of the truth (100 m on FAS); Recall@N counts a centre "
            "whose N best hold a correct one; the precision–recall curve accepts matches in order of their "
            "score, AUC-PR is its trapezoid area and R@100%P the recall reached before the first accepted "
            f"mistake. {noise.upper()}, all queries (a stratified run weights each part by its share of the "
            "query rows in the table; the curves count each localised centre once).", "",
            *(["![PR](fig_pr.png)", ""] if drawn else []),
            table(["scale", "L", "method (mode)", "R@1 %", "R@5 %", "R@10 %", "R@20 %", "R@100%P %", "AUC-PR"],
                  rows), ""]
