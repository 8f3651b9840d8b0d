"""Operating points named as big-ann-benchmarks names them: for each series, the best
recall it reaches within a budget — at or under B bytes per place, or at or above Q queries
per second per core — among the operating points evaluated (each ``k``, ``nprobe``, ``d``…).

A series is a method and its mode (``IVF4096,PQ3 (paper)``, ``CoarseHash d=24 (aligned)``):
what a user picks, before tuning its parameters. Queries per second per core are
``10⁶ / us_per_query``, the cost of a query on one core (docs/accounting.md), so a budget
means the same on any machine's core count.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from vprscale.evaluation.comparison import OURS, best_first, with_series

if TYPE_CHECKING:
    import pandas as pd

RADIUS = 20  # the report's recall radius, in frames (100 m on FAS)
SHOWN = ("scale", "noise", "L", "series", "family", "params", "d", "recall", "recall_lo", "recall_hi",
         "bytes_per_place", "qps_per_core")


def best_points(res: pd.DataFrame, max_bytes: float | None = None, min_qps: float | None = None,
                radius: int = RADIUS, part: str = "all") -> pd.DataFrame:
    """Per scale, noise, L and series, the operating point of best recall at ``radius`` within
    the budget (ties: fewer bytes, then more queries per second); families with no point
    within it are left out. ``scale`` is absent from evaluations of your own data: one scale."""
    rows = with_series(res[(res.radius == radius) & (res.part == part)])
    if "scale" not in rows.columns:
        rows["scale"] = ""
    rows["qps_per_core"] = 1e6 / rows.us_per_query
    if max_bytes is not None:
        rows = rows[rows.bytes_per_place <= max_bytes]
    if min_qps is not None:
        rows = rows[rows.qps_per_core >= min_qps]
    best = best_first(rows).groupby(["scale", "noise", "L", "series"], sort=False, dropna=False).head(1)
    return best.sort_values(["scale", "noise", "L", "recall"], ascending=[True, True, True, False])[
        [c for c in SHOWN if c in best.columns]].reset_index(drop=True)


def _interval(p: Any) -> str:
    return f"{100 * p.recall:.1f} ({100 * p.recall_lo:.1f}–{100 * p.recall_hi:.1f})"


def operating_section(res: pd.DataFrame, scales: list[str], table: Callable[[list[str], list[list[Any]]], str]
                      ) -> list[str]:
    """The report's operating points: at each scale, noise and L, the two best families within
    CoarseHash's own budgets there (its paper mode's bytes per place, and its queries per
    second per core), read from the results; empty when nothing was compared."""
    rows = res[(res.radius == RADIUS) & (res.part == "all")]
    if {"bytes_per_place", "us_per_query"} - set(rows.columns):  # results of a vprscale before 0.3
        return []
    if not rows.method.ne(OURS).any() or not rows.method.eq(OURS).any():
        return []
    out: list[list[Any]] = []
    for (scale, noise, L), run in rows.groupby(["scale", "noise", "L"], sort=False):
        ours = run[(run.method == OURS) & run["mode"].fillna("paper").eq("paper")]
        if ours.empty or scale not in scales:
            continue
        ours = ours.sort_values("recall", ascending=False).iloc[0]
        for budget, kwargs in ((f"≤ {ours.bytes_per_place:.2f} B/place", {"max_bytes": ours.bytes_per_place}),
                               (f"≥ {1e6 / ours.us_per_query:,.0f} q/s/core", {"min_qps": 1e6 / ours.us_per_query})):
            best = best_points(run, **kwargs).head(2)
            cells = [f"{p.series.replace(' (', f' {p.params} (', 1) if isinstance(p.params, str) else p.series}: "
                     f"{_interval(p)}" for p in best.itertuples()]
            out.append([scale, str(noise).upper(), L, budget, *(cells + ["–"] * (2 - len(cells)))])
    order = {s: i for i, s in enumerate(scales)}
    out.sort(key=lambda r: (order[r[0]], r[1], r[2]))
    return ["### Operating points", "",
            "As big-ann-benchmarks names them: each series' (a method in one mode) best recall within 20 frames "
            "among the "
            "operating points evaluated, within a budget — here CoarseHash's own at that scale, noise and L "
            "(its paper mode's bytes per place, and its queries per second per core, the inverse of µs per "
            "query). The two best families within each budget, with the recall's 95 % interval; "
            "`vprscale results RUNS --best-bytes B` or `--best-qps Q` gives every series within any budget.", "",
            table(["scale", "noise", "L", "budget", "best", "second"], out), ""]
