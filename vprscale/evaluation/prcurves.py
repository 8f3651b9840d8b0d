"""The VPR metrics section of a report (docs/protocol.md, "Scores"): precision–recall curves
from every query's score, AUC-PR, recall at 100 % precision and Recall@N, as VPR-Bench and
SeqNet report them, for every method at every L.

A match is correct within ``RADIUS`` frames of the truth; the curves accept matches in
order of their score (lower is more confident). The figures, one per noise level
(``fig_pr_qm1.png``, …), are per series (a method in one mode) at its first operating point; the table gives
every operating point of every noise level, read from the results.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow.parquet as pq

from vprscale.evaluation.comparison import (
    TITLE_SIZE,
    named_modes,
    panels,
    series_colours,
    series_label,
    series_line,
    shared_legend,
    with_series,
)
from vprscale.evaluation.metrics import pr_curve
from vprscale.evaluation.results import noise_order

RADIUS = 20
COLUMNS = ("scale", "noise", "method", "mode", "L", "d", "params", "index", "error", "score")


def load_queries(runs: list[str]) -> pd.DataFrame:
    """The scored per-query rows of every query set, from each evaluation folder (older
    evaluations, without scores, are left out)."""
    frames = []
    for run in runs:
        file = Path(run) / "queries.parquet"
        if not file.is_file():
            continue
        names = set(pq.read_schema(file).names)
        if "score" not in names:
            continue
        table = pq.read_table(file, columns=[c for c in COLUMNS if c in names])
        frames.append(table.to_pandas())
    if not frames:
        return pd.DataFrame(columns=list(COLUMNS))
    q = pd.concat(frames, ignore_index=True)
    return with_series(q)


def _first_points(q: pd.DataFrame) -> pd.DataFrame:
    """Each series' first operating point (its smallest params, as text) and its main index."""
    keys = q[["scale", "series", "params", "index"]].drop_duplicates().astype(str)
    first = keys.sort_values(["scale", "series", "params", "index"]).groupby(["scale", "series"]).head(1)
    merged = q.astype({"params": str, "index": str}).merge(first, on=["scale", "series", "params", "index"])
    return merged


def fig_pr(q: pd.DataFrame, scales: list[str], noise: str, out: Path, save,
           palette: dict[str, Any] | None = None) -> str | None:
    """Precision against recall at one noise level, per scale (columns) and L (rows); the
    figure's name, or None when there is nothing to draw.

    Long sequences keep most methods at or near 100 % precision until late, where a linear
    precision axis draws their curves on one another: the vertical axis is the share of false
    matches among those accepted, 1 − precision, on a scale linear below 0.1 % and logarithmic
    above (0 at the top), so 0.01 % and 1 % of false matches stand apart."""
    q = _first_points(q[q.noise == noise])
    scales = [s for s in scales if s in set(q.scale)]
    lengths = sorted(q.L.unique())
    if not scales or not lengths:
        return None
    families = list(dict.fromkeys(q.sort_values("method", key=lambda c: c.ne("coarsehash")).series))
    colours = series_colours(families, palette)
    fig, axes = panels(len(lengths), len(scales), 4.4, 3.5, sharey=True)
    for r, L in enumerate(lengths):
        for c, scale in enumerate(scales):
            ax = axes[r][c]
            drawn = list(q[(q.scale == scale) & (q.L == L)].groupby("series", sort=False))
            for i, (fam, g) in enumerate(drawn):  # thick to thin: a curve drawn over another leaves it an outline
                precision, recall = pr_curve(g.score.to_numpy(), g.error.to_numpy() <= RADIUS)
                ax.plot(100 * recall, 100 * (1 - precision), lw=3.2 - 2.4 * i / max(1, len(drawn) - 1),
                        ls=series_line(fam), color=colours[fam], label=fam)
            ax.set(xlim=(0, 100))
            ax.set_yscale("symlog", linthresh=0.1, linscale=0.5)
            ax.set_ylim(100, 0)  # no false match at the top
            ax.set_yticks([0, 0.1, 1, 10, 100], ["0", "0.1", "1", "10", "100"])
            ax.set_title(f"{scale}, {noise.upper()}, L = {L}", fontsize=TITLE_SIZE)
            ax.grid(alpha=0.3)
            if r == len(lengths) - 1:
                ax.set_xlabel(f"recall within {RADIUS} frames (%)")
            if c == 0:
                ax.set_ylabel("false among accepted (%)")
    shared_legend(fig, axes)
    fig.suptitle(f"{noise.upper()}: precision–recall, matches accepted in order of their score")
    name = f"fig_pr_{noise}"
    save(fig, out, name)
    return name


PR_SCORES = ("auc_pr_correct", "ap", "precision_at_r100")  # columns an older evaluation may lack


def pr_section(res: pd.DataFrame, runs: list[str], scales: list[str], out: Path, save, table,
               palette: dict[str, Any] | None = None) -> list[str]:
    """The report's section: the figure (in ``palette``'s colours), and the table of every method
    and operating point."""
    if "auc_pr" not in res.columns:
        return []
    q = load_queries(runs)
    drawn = [] if q.empty else [fig_pr(q, scales, noise, out, save, palette) for noise in noise_order(q.noise)]
    sub = named_modes(res[(res.part == "all") & (res.radius == RADIUS)])
    rows: list[list[Any]] = []
    order = {s: i for i, s in enumerate(scales)}
    noises = {n: i for i, n in enumerate(noise_order(sub.noise))}
    sub = sub.assign(pos=sub.scale.map(order), level=sub.noise.map(noises))
    for p in sub.sort_values(["pos", "level", "L", "method", "mode", "d"]).itertuples():
        name = series_label(p.method, p.mode, p.d)
        params = getattr(p, "params", None)
        rows.append([p.scale, p.noise.upper(), p.L, name + (f" {params}" if isinstance(params, str) and params else ""),
                     p.family,
                     *(f"{100 * v:.1f}" if v == v else "–" for v in
                       (p.recall, p.recall_at_5, p.recall_at_10, p.recall_at_20, p.recall_at_p100)),
                     *(f"{v:.3f}" if v == v else "–" for v in
                       (p.auc_pr, *(getattr(p, c, float("nan")) for c in PR_SCORES)))])
    return ["## Scores: precision–recall, AUC-PR and Recall@N", "",
            f"Every answer carries its match's score (lower is more confident) and its 20 best candidates. "
            f"A match is correct within {RADIUS} frames of the truth (100 m on FAS); Recall@N counts a centre "
            "whose N best hold a correct one; the precision–recall curve accepts matches in order of their "
            "score, AUC-PR is its trapezoid area and R@100%P the recall reached before the first accepted "
            "mistake. Recall@N ranks at least N candidates whatever the operating point's own budget "
            "(docs/protocol.md, \"Recall@N\"). AUC-PR's recall is over all queries (SeqSLAM's); "
            "AUC-PR (VPR-Bench) is over the correct matches, and so are AP (average precision) and P@100%R "
            "(the precision once every correct match is accepted, as Delta Descriptors reports it). All "
            "queries of every noise level (a stratified "
            "run weights each part by its share of the query rows in the table; the curves count each "
            "localised centre once).", "",
            *(line for name in drawn if name for line in (f"![{name}]({name}.png)", "")),
            table(["scale", "noise", "L", "method (mode)", "family", "R@1 %", "R@5 %", "R@10 %", "R@20 %", "R@100%P %",
                   "AUC-PR", "AUC-PR (VPR-Bench)", "AP", "P@100%R"], rows), ""]
