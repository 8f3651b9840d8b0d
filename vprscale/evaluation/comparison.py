"""The compact-code comparison of a report: recall within 20 frames against bytes per place and
against time per query, for CoarseHash and every FAISS method evaluated beside it
(``vprscale eval --compare``), with its table and what it says in words.

Everything here is read from the results; nothing is written in advance of the data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.ticker import FuncFormatter

from vprscale.evaluation.accounting import time_cell
from vprscale.evaluation.results import noise_order

MARKERS = {1: "o", 50: "s", 100: "^"}
RADIUS = 20


def _plain(v: float, _pos: int) -> str:
    return f"{v:g}"


def _blank(v: float, _pos: int) -> str:
    return ""


def _points(res: pd.DataFrame) -> pd.DataFrame:
    """One row per (scale, noise, method, mode, L): R@20 over all queries, bytes, µs, queries."""
    sub = res[(res.part == "all") & (res.radius == RADIUS) & res.method.ne("baseline")]
    if "bytes_per_place" not in sub:
        return sub.iloc[:0]
    compared = set(sub.loc[sub.method.str.startswith("faiss:"), "scale"])
    sub = sub[sub.scale.isin(compared) & sub.bytes_per_place.notna()]
    # CoarseHash at the width the FAISS methods were compared with (the index they share)
    shared = sub[sub.method.str.startswith("faiss:")].groupby("scale")["index"].first()
    sub = sub[sub.method.str.startswith("faiss:") | (sub["index"] == sub.scale.map(shared))]
    cols = ["scale", "noise", "method", "mode", "L", "d", "recall", "bytes_per_place", "us_per_query", "n_queries",
            *(c for c in ("us_per_query_lo", "us_per_query_hi", "run", "params") if c in res.columns)]
    return sub[cols].assign(mode=sub["mode"].fillna("single")).reset_index(drop=True)


def _label(method: str, mode: str, d: Any, params: Any = None) -> str:
    name = f"CoarseHash d={int(d)}" if method == "coarsehash" else method.removeprefix("faiss:")
    at = f" {params}" if isinstance(params, str) and params and method != "coarsehash" else ""
    return f"{name}{at} ({mode})"


def fig_compare(points: pd.DataFrame, scales: list[str], out: Path, save) -> None:
    """Rows: QM1, QM2; columns: each compared scale against bytes, then against µs."""
    noises = noise_order(points.noise)
    scales = [s for s in scales if s in set(points.scale)]
    fig, axes = plt.subplots(len(noises), 2 * len(scales), figsize=(4.0 * 2 * len(scales), 3.6 * len(noises)),
                             squeeze=False, sharey=True, layout="constrained")
    methods = sorted(points.method.unique(), key=lambda m: (m != "coarsehash", m))
    colours = {m: plt.get_cmap("tab10")(i) for i, m in enumerate(methods)}
    for r, noise in enumerate(noises):
        for c, scale in enumerate(scales):
            sub = points[(points.noise == noise) & (points.scale == scale)]
            for k, (xcol, xlabel) in enumerate((("bytes_per_place", "bytes per place"),
                                                 ("us_per_query", "µs per query per core"))):
                ax = axes[r][2 * c + k]
                for row in sub.itertuples():
                    hollow = row.mode == "aligned"
                    ax.scatter(getattr(row, xcol), 100 * row.recall, marker=MARKERS.get(row.L, "D"), s=36,
                               color="none" if hollow else colours[row.method], edgecolors=colours[row.method])
                    if xcol == "us_per_query" and getattr(row, "us_per_query_lo", None) is not None:
                        ax.errorbar(row.us_per_query, 100 * row.recall, fmt="none", ecolor=colours[row.method],
                                    lw=0.8, xerr=[[row.us_per_query - row.us_per_query_lo],
                                                  [row.us_per_query_hi - row.us_per_query]])
                ax.set_xscale("log")
                ax.xaxis.set_major_formatter(FuncFormatter(_plain))
                ax.xaxis.set_minor_formatter(FuncFormatter(_plain if xcol == "bytes_per_place" else _blank))
                ax.set_ylim(0, 100)
                ax.grid(alpha=0.3, which="both")
                ax.set_xlabel(xlabel)
                ax.set_title(f"{scale}, {noise.upper()}")
                if 2 * c + k == 0:
                    ax.set_ylabel(f"recall within {RADIUS} frames (%)")
    handles = [plt.Line2D([], [], ls="", marker="o", color=colours[m], label=m.removeprefix("faiss:"))
               for m in methods]
    handles += [plt.Line2D([], [], ls="", marker=MARKERS[L], color="grey", label=f"L = {L}") for L in MARKERS]
    handles += [plt.Line2D([], [], ls="", marker="o", color="grey", label="filled: paper mode / single"),
                plt.Line2D([], [], ls="", marker="o", color="grey", markerfacecolor="none", label="hollow: aligned")]
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize=8)
    fig.suptitle("CoarseHash against FAISS compact codes: recall vs bytes per place and vs time per query")
    save(fig, out, "fig_compare")


def _best(sub: pd.DataFrame) -> pd.Series:
    """The row with the highest recall (ties: fewer bytes, then less time)."""
    return sub.sort_values(["recall", "bytes_per_place", "us_per_query"], ascending=[False, True, True]).iloc[0]


def _words(points: pd.DataFrame, scales: list[str]) -> list[str]:
    """Where CoarseHash wins and where it loses, per scale, noise and L, read from the points."""
    lines = []
    for scale in [s for s in scales if s in set(points.scale)]:
        for noise in noise_order(points.noise):
            for L in sorted(points.L.unique()):
                sub = points[(points.scale == scale) & (points.noise == noise) & (points.L == L)]
                ours, theirs = sub[sub.method == "coarsehash"], sub[sub.method != "coarsehash"]
                if ours.empty or theirs.empty:
                    continue
                o, t = _best(ours), _best(theirs)
                gap = 100 * (o.recall - t.recall)
                verdict = "CoarseHash finds more" if gap > 1 else "FAISS finds more" if gap < -1 else "recall is level"
                faster = t.us_per_query / max(o.us_per_query, 1e-9)
                same_run = getattr(o, "run", None) == getattr(t, "run", None)
                smaller = t.bytes_per_place / o.bytes_per_place
                lines.append(
                    f"- {scale}, {noise.upper()}, L = {L}: {verdict} ({100 * o.recall:.1f} % for CoarseHash "
                    f"{o['mode']} against {100 * t.recall:.1f} % for {t.method.removeprefix('faiss:')} {t['mode']}, "
                    f"the best compared method); CoarseHash answers in {o.us_per_query:,.1f} µs against "
                    f"{t.us_per_query:,.1f} µs ("
                    + (f"{_times(faster)} {'faster' if faster >= 1 else 'slower'}" if same_run else "different runs")
                    + ") and keeps "
                    f"{o.bytes_per_place:.2f} bytes per place against {t.bytes_per_place:.2f} "
                    f"({_times(smaller)} {'less' if smaller >= 1 else 'more'}).")
    return lines


def _times(ratio: float) -> str:
    ratio = ratio if ratio >= 1 else 1 / ratio
    return f"{ratio:,.0f}×" if ratio >= 10 else f"{ratio:.2f}×"


def compare_section(res: pd.DataFrame, scales: list[str], out: Path, save, table) -> list[str]:
    """The report's comparison section (figure, words, table); empty when nothing was compared."""
    points = _points(res)
    if points.empty or not points.method.str.startswith("faiss:").any():
        return []
    fig_compare(points, scales, out, save)
    rows: list[list[Any]] = []
    for p in points.sort_values(["scale", "noise", "L", "method", "mode"], key=_scale_key(scales)).itertuples():
        rows.append([p.scale, p.noise.upper(), p.L, _label(p.method, p.mode, p.d, getattr(p, "params", None)),
                     f"{p.bytes_per_place:.2f}",
                     time_cell(p), f"{100 * p.recall:.1f}", int(p.n_queries)])
    return ["## CoarseHash against FAISS compact codes", "",
            "The same centres, truths and window score (docs/protocol.md, \"Compact codes\"): a FAISS method's "
            "frame retrieves its top-k references (k = CoarseHash's mean list size, the same candidate budget), "
            "and its windows are scored on its codes. Bytes per place count the code and whatever else the "
            "method keeps per place to answer (CoarseHash: its bit planes and inverted lists; IVF: 64-bit ids "
            "and the codes again in id order). Times are per query per core with the per-frame work included; "
            "a flat FAISS index scans every code for every frame, so past a scan budget its runs localise an "
            "evenly spaced sample of the centres (the queries column).", "",
            "![compare](fig_compare.png)", "", *_words(points, scales), "",
            table(["scale", "noise", "L", "method (mode)", "B/place", "µs/query", "R@20 %", "queries"], rows), ""]


def _scale_key(scales: list[str]):
    order = {s: i for i, s in enumerate(scales)}

    def key(col: pd.Series) -> pd.Series:
        return col.map(order) if col.name == "scale" else col if col.dtype != object else col.astype(str)

    return key

