"""The comparison section of a report: CoarseHash against every other method evaluated beside
it (FAISS codes with ``--compare``, your own with ``--method``), as ann-benchmarks and
big-ann-benchmarks draw it.

Each series (a method in one mode) has one point per operating point (its
``params``: k, nprobe). The figures, one of each per noise level (``…_qm1.png``,
``…_qm2.png``: the levels where the methods part most must not hide behind the easiest):

- ``fig_compare``: recall within 20 frames against queries per second per core (log axis),
  per scale (columns) and L (rows), with each series' Pareto front drawn and labelled;
- ``fig_compare_bytes``: recall against bytes per place, per scale and L, on an axis that
  spans the data;
- ``fig_compare_trends``: each series' best recall against L, and against scale.

A series' colour is its method's (CoarseHash's the same at every width), its marker and
line style its mode's (``MODE_MARKERS``, ``MODE_LINES``); the legend names the methods and
the modes apart (ten methods in three modes are thirteen entries, not thirty); panels of a
figure share their axes; every recall carries its 95 % Wilson interval. Everything here is
read from the results; nothing is written in advance of the data.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator

from vprscale.compared.faisscodes import code_family
from vprscale.compared.pooled import is_pooled
from vprscale.core.plaintext import markdown
from vprscale.evaluation.accounting import time_cell
from vprscale.evaluation.results import noise_order

RADIUS = 20
OURS = "coarsehash"
NOT_COMPARED = {OURS, "baseline"}
MODE_LINES = {"aligned": "-", "paper": "--", "single": ":", "sequence": "-."}  # a series' line style, by its mode
MODE_MARKERS = {"aligned": "^", "paper": "o", "single": "s", "sequence": "D"}  # and its marker
TITLE_SIZE = 10


def _plain(v: float, _pos: int) -> str:
    return f"{v:g}"


def _si(v: float, _pos: int) -> str:
    for unit, scale in (("M", 1e6), ("k", 1e3)):
        if v >= scale:
            return f"{v / scale:g}{unit}"
    return f"{v:g}"


def shared_legend(fig, axes) -> None:
    """One legend below the panels, outside the data: each method any panel drew (its colour),
    then each mode (its marker and line style, in black)."""
    colours: dict[str, Any] = {}
    modes: dict[str, None] = {}
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            method, mode = method_and_mode(lab)
            colours.setdefault(method, h.get_color() if isinstance(h, Line2D) else h.get_facecolor()[0])
            modes.setdefault(mode)
    handles = [Line2D([], [], color=c, lw=2.5, label=m) for m, c in colours.items()]
    handles += [Line2D([], [], color="black", marker=MODE_MARKERS[m], ls=MODE_LINES[m],
                       label={"single": "single frame", "sequence": "sequences (no mode)"}.get(m, f"{m} mode"))
               for m in modes if m in MODE_LINES]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(6, len(handles)), fontsize=8)


def _points(res: pd.DataFrame) -> pd.DataFrame:
    """One row per (scale, noise, method, mode, L, params): recall within 20 frames over all queries with its
    interval, bytes, µs and queries per second per core, at scales where a method was compared."""
    sub = res[(res.part == "all") & (res.radius == RADIUS) & res.method.ne("baseline")]
    if "bytes_per_place" not in sub:
        return sub.iloc[:0]
    others = sub[~sub.method.isin(NOT_COMPARED)]
    sub = sub[sub.scale.isin(set(others.scale))]
    # CoarseHash at the width the other methods were compared with (the index they share)
    shared = others.groupby("scale")["index"].first()
    sub = sub[sub.method.ne(OURS) | (sub["index"] == sub.scale.map(shared))]
    cols = ["scale", "noise", "method", "mode", "L", "d", "recall", "bytes_per_place", "us_per_query", "n_queries",
            *(c for c in ("us_per_query_lo", "us_per_query_hi", "recall_lo", "recall_hi", "run", "params", "family")
              if c in res.columns)]
    out = with_series(sub[cols].reset_index(drop=True))
    out["qps"] = 1e6 / out.us_per_query.clip(lower=1e-9)
    return out


def named_modes(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with a null ``mode`` named (``single`` at L = 1, ``sequence`` above: a method that
    matches sequences without modes, as the baseline does at L = 50 and 100) and each method's
    ``family`` (:func:`method_family` for results older than the column)."""
    rows = rows.assign(mode=[mode_name(m, L) for m, L in zip(rows["mode"], rows["L"], strict=True)])
    if "family" not in rows.columns:
        rows["family"] = [method_family(m) for m in rows.method]
    return rows


def mode_name(mode: Any, L: int) -> str:
    """A row's mode, a null one named (:func:`named_modes`)."""
    return mode if isinstance(mode, str) else "sequence" if L > 1 else "single"


def method_family(method: str) -> str:
    """The ``family`` of a ``method`` column's value, for results written before the column was
    (what the methods themselves say now, :attr:`~vprscale.evaluation.algorithms.base.Algorithm.family`)."""
    if method.startswith("faiss:"):
        return code_family(method.removeprefix("faiss:"))
    if is_pooled(method):
        return "sequence descriptor"
    return {OURS: "hashing", "baseline": "baseline"}.get(method, "own")


def with_series(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with ``mode`` and ``family`` named (:func:`named_modes`) and each row's ``series``
    (:func:`series_label`), as every figure and table groups them."""
    rows = named_modes(rows)
    rows["series"] = [series_label(m, mode, d) for m, mode, d in zip(rows.method, rows["mode"], rows.d, strict=True)]
    return rows


def best_first(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` from the best operating point down: highest recall, then fewer bytes, then faster."""
    return rows.sort_values(["recall", "bytes_per_place", "us_per_query"], ascending=[False, True, True])


def series_label(method: str, mode: str, d: Any) -> str:
    """``PQ3 (aligned)``; CoarseHash with its width, ``CoarseHash d=24 (aligned)``, unless ``d`` is None."""
    if method != OURS:
        return f"{method_name(method)} ({mode})"
    return f"CoarseHash{'' if d is None else f' d={int(d)}'} ({mode})"


def _label(method: str, mode: str, d: Any, params: Any = None) -> str:
    at = f" {params}" if isinstance(params, str) and params and method != OURS else ""
    return series_label(method, mode, d).replace(" (", f"{at} (", 1)


def pareto_front(points: pd.DataFrame, x: str = "qps", y: str = "recall") -> pd.DataFrame:
    """The points no other point beats on both ``x`` and ``y`` (higher is better on both),
    by ``x`` descending: a point joins when its ``y`` exceeds that of every faster point."""
    ordered = points.sort_values([x, y], ascending=[False, False])
    best = -np.inf
    keep = []
    for i, v in zip(ordered.index, ordered[y], strict=True):
        if v > best:
            keep.append(i)
            best = v
    return ordered.loc[keep]


def panels(rows: int, cols: int, width: float, height: float, sharey: bool | str = True) -> tuple[Any, Any]:
    """A figure of ``rows`` × ``cols`` panels of ``width`` × ``height`` inches sharing their x
    axis, and their y axis (or, with ``sharey="row"``, each row its own)."""
    return plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False, sharex=True, sharey=sharey,
                        layout="constrained")


def method_and_mode(series: str) -> tuple[str, str]:
    """``("PQ3", "aligned")`` of ``PQ3 (aligned)``; CoarseHash without its width."""
    method, _, mode = series.rpartition(" (")
    return re.sub(r" d=\d+$", "", method), mode.rstrip(")")


def method_name(method: str) -> str:
    """A method as figures name it: ``CoarseHash``, ``PQ3`` (a FAISS factory string), ``seq:PQ3``."""
    return "CoarseHash" if method == OURS else method.removeprefix("faiss:")


def method_colours(methods: Iterable[str], given: dict[str, Any] | None = None) -> dict[str, Any]:
    """One colour per method (named as :func:`method_name` names it): ``given``'s, then the
    others', the rest by name; no greys (the grid's colour). CoarseHash's is its own; the
    others are tab20's strong shades, its light ones, then tab20b's, 37 before one repeats (a
    ladder's report compares about thirty methods, each scale's codes at its own size). A
    report draws every figure from one such table of all its methods, so a method keeps its
    colour from figure to figure whatever else each draws."""
    tab20 = plt.get_cmap("tab20").colors  # pairs of a strong and a light shade; 14 and 15 are the greys
    ours, *others = [tab20[i] for i in (*range(0, 20, 2), *range(1, 20, 2)) if i not in (14, 15)]
    others += plt.get_cmap("tab20b").colors
    colours = dict(given or {})
    for m in sorted(set(methods) - set(colours)):
        colours[m] = ours if m == "CoarseHash" else others[sum(k != "CoarseHash" for k in colours) % len(others)]
    return colours


def report_palette(methods: Iterable[str]) -> dict[str, Any]:
    """A report's one table of colours, of its results' ``method`` values (``faiss:PQ3``)."""
    return method_colours(map(method_name, set(methods)))


def series_colours(families: list[str], palette: dict[str, Any] | None = None) -> dict[str, Any]:
    """Each series' colour: its method's in ``palette`` (the report's :func:`method_colours`;
    a method missing there, or no palette, gets the next), whatever its mode or CoarseHash's
    width (:func:`series_line` tells the modes apart)."""
    by_method = method_colours((method_and_mode(f)[0] for f in families), palette)
    return {f: by_method[method_and_mode(f)[0]] for f in families}


def series_line(series: str) -> str:
    """A series' line style: its mode's (``MODE_LINES``)."""
    return MODE_LINES.get(method_and_mode(series)[1], "-")


def series_marker(series: str) -> str:
    """A series' marker: its mode's (``MODE_MARKERS``)."""
    return MODE_MARKERS.get(method_and_mode(series)[1], "o")


def _families(points: pd.DataFrame) -> list[str]:
    first = points.sort_values(["method"], key=lambda c: c.ne(OURS)).series
    return list(dict.fromkeys(first))


def _recall_bars(ax, g: pd.DataFrame, x: str, colour: Any) -> None:
    if "recall_lo" in g and g.recall_lo.notna().any():
        below, above = (g.recall - g.recall_lo).clip(lower=0), (g.recall_hi - g.recall).clip(lower=0)  # older bounds
        ax.errorbar(g[x], 100 * g.recall, yerr=[100 * below, 100 * above], fmt="none", ecolor=colour, lw=0.7, alpha=0.7)


def _recall_axis(ax, title: str, xlabel: str, first: bool) -> None:
    """The common finish of a recall panel: 0–100 %, grid, title, labels (the y label on the first)."""
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3, which="both")
    ax.set_title(title, fontsize=TITLE_SIZE)
    ax.set_xlabel(xlabel)
    if first:
        ax.set_ylabel(f"recall within {RADIUS} frames (%)")


def _grid(points: pd.DataFrame, scales: list[str], noise: str) -> tuple[list[str], list[int]]:
    """The scales and lengths a noise level's figure draws."""
    here = points[points.noise == noise]
    return [s for s in scales if s in set(here.scale)], sorted(here.L.unique())


def fig_compare(points: pd.DataFrame, scales: list[str], noise: str, out: Path, save,
                palette: dict[str, Any] | None = None) -> str:
    """Recall against queries per second per core at one noise level, each series' Pareto front
    drawn and labelled; returns the figure's name."""
    scales, lengths = _grid(points, scales, noise)
    families = _families(points)
    colours = series_colours(families, palette)
    fig, axes = panels(len(lengths), len(scales), 5.2, 3.8)
    for r, L in enumerate(lengths):
        for c, scale in enumerate(scales):
            ax = axes[r][c]
            sub = points[(points.noise == noise) & (points.scale == scale) & (points.L == L)]
            for fam, g in sub.groupby("series", sort=False):
                front = pareto_front(g)
                ax.scatter(g.qps, 100 * g.recall, s=14, color=colours[fam], alpha=0.35, lw=0,
                           marker=series_marker(fam))
                ax.plot(front.qps, 100 * front.recall, marker=series_marker(fam), ls=series_line(fam), ms=5, lw=1.3,
                        color=colours[fam], label=fam)
                _recall_bars(ax, front, "qps", colours[fam])
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(FuncFormatter(_si))
            _recall_axis(ax, f"{scale}, {noise.upper()}, L = {L}", "queries per second per core", c == 0)
    shared_legend(fig, axes)
    fig.suptitle(f"{noise.upper()}: recall against throughput, every operating point (dots), "
                 "each method's Pareto front (lines)")
    name = f"fig_compare_{noise}"
    save(fig, out, name)
    return name


def fig_compare_bytes(points: pd.DataFrame, scales: list[str], noise: str, out: Path, save,
                      palette: dict[str, Any] | None = None) -> str:
    """Recall against bytes per place at one noise level (each series' best operating point),
    per scale and L, on an axis spanning the data; returns the figure's name."""
    scales, lengths, colours, best = _setup(points, scales, noise, palette)
    lo, hi = best.bytes_per_place.min(), best.bytes_per_place.max()
    fig, axes = panels(len(lengths), len(scales), 5.2, 3.4)
    for r, L in enumerate(lengths):
        for c, scale in enumerate(scales):
            ax = axes[r][c]
            for fam, g in best[(best.scale == scale) & (best.L == L)].groupby("series", sort=False):
                ax.scatter(g.bytes_per_place, 100 * g.recall, marker=series_marker(fam), s=34, color=colours[fam],
                           label=fam)
                _recall_bars(ax, g, "bytes_per_place", colours[fam])
            ax.set_xscale("log")
            ax.set_xlim(lo / 1.4, hi * 1.4)
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(FuncFormatter(_plain))
            ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _p: ""))
            _recall_axis(ax, f"{scale}, {noise.upper()}, L = {L}", "bytes per place", c == 0)
    shared_legend(fig, axes)
    fig.suptitle(f"{noise.upper()}: recall against storage, each method's best operating point")
    name = f"fig_compare_bytes_{noise}"
    save(fig, out, name)
    return name


def fig_compare_trends(points: pd.DataFrame, scales: list[str], noise: str, out: Path, save,
                       palette: dict[str, Any] | None = None) -> str:
    """Each series' best recall against L (one panel per scale) and against scale (one per L),
    at one noise level; returns the figure's name."""
    scales, lengths, _, best = _setup(points, scales, noise, palette)
    # CoarseHash is compared at each scale's own width (d = ⌈log2 N_ref⌉): against scale it is
    # one line per mode, in its one colour (the tables give d)
    best = best.assign(series=[series_label(m, mode, None) for m, mode in zip(best.method, best["mode"], strict=True)])
    colours = series_colours(list(best.series), palette)
    order = {s: i for i, s in enumerate(scales)}
    fig, axes = plt.subplots(2, max(len(scales), len(lengths)), figsize=(4.6 * max(len(scales), len(lengths)), 7),
                             squeeze=False, sharey=True, layout="constrained")
    for c, scale in enumerate(scales):
        ax = axes[0][c]
        for fam, g in best[best.scale == scale].groupby("series", sort=False):
            g = g.sort_values("L")
            ax.plot(g.L, 100 * g.recall, marker=series_marker(fam), ls=series_line(fam), ms=5, color=colours[fam],
                    label=fam)
            _recall_bars(ax, g, "L", colours[fam])
        ax.set(xlabel="sequence length L (frames)", ylim=(0, 102))
        ax.set_title(f"{scale}, {noise.upper()}: recall vs L", fontsize=TITLE_SIZE)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    for c, L in enumerate(lengths):
        ax = axes[1][c]
        for fam, g in best[best.L == L].groupby("series", sort=False):
            g = g.assign(pos=g.scale.map(order)).sort_values("pos")
            ax.plot(g.pos, 100 * g.recall, marker=series_marker(fam), ls=series_line(fam), ms=5, color=colours[fam],
                    label=fam)
            _recall_bars(ax, g, "pos", colours[fam])
        ax.set_xticks(range(len(scales)), scales)
        ax.set(xlabel="scale (places)", ylim=(0, 102))
        ax.set_title(f"L = {L}, {noise.upper()}: recall vs scale", fontsize=TITLE_SIZE)
        ax.grid(alpha=0.3)
    for row in axes:
        row[0].set_ylabel(f"recall within {RADIUS} frames (%)")
        for ax in row:
            if not ax.has_data():
                ax.set_visible(False)
    shared_legend(fig, axes)
    fig.suptitle(f"{noise.upper()}: each method's best operating point against sequence length and against scale")
    name = f"fig_compare_trends_{noise}"
    save(fig, out, name)
    return name


def _setup(points: pd.DataFrame, scales: list[str], noise: str, palette: dict[str, Any] | None
           ) -> tuple[list[str], list[int], dict[str, Any], pd.DataFrame]:
    """What a best-point figure of one noise level draws: the scales and lengths, the colours,
    and each series' best operating point per scale and L."""
    scales, lengths = _grid(points, scales, noise)
    return scales, lengths, series_colours(_families(points), palette), _best_points(points[points.noise == noise])


def _best_points(points: pd.DataFrame) -> pd.DataFrame:
    """Per (scale, L, series): the operating point of highest recall (ties: fewer bytes, then faster)."""
    return best_first(points).groupby(["scale", "L", "series"], sort=False).head(1)


def _best(sub: pd.DataFrame) -> pd.Series:
    """The row with the highest recall (ties: fewer bytes, then less time)."""
    return best_first(sub).iloc[0]


TIMES = ("us_per_query", "us_per_query_lo", "us_per_query_hi", "us_per_frame")  # what a run measured of a row


def as_run_measured(row: pd.Series, run: Any, twins: pd.DataFrame | None, radius: int = RADIUS) -> pd.Series:
    """``row`` with the times ``run`` measured of it, where that run evaluated the same point too
    (a CoarseHash grid evaluated again beside other methods: a d sweep's main width, a scale's
    evaluations split across parts); ``row`` itself otherwise. ``twins`` holds every row of a
    point more than one run evaluated (:func:`vprscale.evaluation.report.load_results`). The
    recall must be the same, or the runs did not evaluate the same point."""
    if twins is None or twins.empty or row.get("run") == run:
        return row
    key = (twins.run == run) & (twins.radius == radius) & (twins.part == "all") & (twins.recall == row.recall)
    for col in ("scale", "noise", "method", "L", "d"):
        key &= twins[col] == row[col]
    found = [i for i, m, L in zip(twins.index[key], twins["mode"][key], twins.L[key], strict=True)
             if mode_name(m, L) == mode_name(row["mode"], row.L)]
    if not found:
        return row
    twin, out = twins.loc[found[0]], row.copy()
    for col in (*TIMES, "run"):
        if col in out.index and col in twin.index:
            out[col] = twin[col]
    return out


def _words(points: pd.DataFrame, scales: list[str], twins: pd.DataFrame | None = None) -> list[str]:
    """Per scale, noise and L, read from the points: CoarseHash's best point, the fastest compared
    point that reaches its recall, and the compared point that finds most, kept apart.

    A speed-up is quoted only against a point of the same recall: the fastest compared operating
    point whose recall reaches the lower end of CoarseHash's 95 % interval (its recall, where no
    interval was measured). Quoting it against the compared point of highest recall instead would
    set CoarseHash against a slower setting of the same code (a larger k) that finds a query or
    two more, and flatter it several times over."""
    lines = []
    for scale in [s for s in scales if s in set(points.scale)]:
        for noise in noise_order(points.noise):
            for L in sorted(points.L.unique()):
                sub = points[(points.scale == scale) & (points.noise == noise) & (points.L == L)]
                ours, theirs = sub[sub.method == OURS], sub[sub.method != OURS]
                if ours.empty or theirs.empty:
                    continue
                o, best = _best(ours), _best(theirs)
                floor = o.recall_lo if "recall_lo" in o and o.recall_lo == o.recall_lo else o.recall
                reach = theirs[theirs.recall >= floor].sort_values(["us_per_query", "bytes_per_place"])
                if not reach.empty:  # CoarseHash's time as the run of the point it is set against measured it
                    o = as_run_measured(o, reach.iloc[0].get("run"), twins)
                line = (f"- {markdown(scale)}, {markdown(noise.upper())}, L = {L}: CoarseHash {markdown(o['mode'])} "
                        f"finds {100 * o.recall:.1f} % in {o.us_per_query:,.1f} µs with {o.bytes_per_place:.2f} "
                        "bytes per place. ")
                if reach.empty:
                    line += (f"No compared point reaches it; the one that finds most, {_point(best)}, finds "
                             f"{100 * best.recall:.1f} % in {best.us_per_query:,.1f} µs.")
                else:
                    t = reach.iloc[0]
                    line += (f"The fastest compared point at the same recall (within CoarseHash's 95 % interval or "
                             f"above) is {_point(t)}: {100 * t.recall:.1f} % in {t.us_per_query:,.1f} µs; CoarseHash "
                             f"{_faster(o, t)} and keeps {_times(t.bytes_per_place / o.bytes_per_place)} "
                             f"{'fewer' if t.bytes_per_place >= o.bytes_per_place else 'more'} bytes per place.")
                    if best.recall > t.recall:
                        line += (f" The compared point that finds most, {_point(best)}, finds "
                                 f"{100 * best.recall:.1f} % in {best.us_per_query:,.1f} µs.")
                lines.append(line)
    return lines


def _point(p: pd.Series) -> str:
    """A compared operating point as the summary names it: ``ITQ16,LSH k=4 (aligned)``."""
    return markdown(_label(p.method, p["mode"], p.d, p.get("params")))


def _faster(o: pd.Series, t: pd.Series) -> str:
    """``answers 40× faster`` for two points of one run; times of different runs are not set
    against each other."""
    if o.get("run") != t.get("run"):
        return "answers in a different run (times not compared)"
    ratio = t.us_per_query / max(o.us_per_query, 1e-9)
    return f"answers {_times(ratio)} {'faster' if ratio >= 1 else 'slower'}"


def _recall_cell(p: Any) -> str:
    lo, hi = getattr(p, "recall_lo", None), getattr(p, "recall_hi", None)
    if lo is None or lo != lo:
        return f"{100 * p.recall:.1f}"
    return f"{100 * p.recall:.1f} ({100 * lo:.1f}–{100 * hi:.1f})"


def _times(ratio: float) -> str:
    ratio = ratio if ratio >= 1 else 1 / ratio
    return f"{ratio:,.0f}×" if ratio >= 10 else f"{ratio:.2f}×"


def compare_section(res: pd.DataFrame, scales: list[str], out: Path, save, table,
                    palette: dict[str, Any] | None = None, twins: pd.DataFrame | None = None) -> list[str]:
    """The report's comparison section (figures in ``palette``'s colours, words, table); empty
    when nothing was compared. ``twins``: the rows of points several runs evaluated, so a speed-up
    is quoted from one run's times wherever one run measured both points (:func:`as_run_measured`)."""
    points = _points(res)
    if points.empty or not points.method.ne(OURS).any():
        return []
    figures = [draw(points, scales, noise, out, save, palette) for noise in noise_order(points.noise)
               for draw in (fig_compare, fig_compare_bytes, fig_compare_trends)]
    rows: list[list[Any]] = []
    for p in points.sort_values(["scale", "noise", "L", "method", "mode"], key=_scale_key(scales)).itertuples():
        rows.append([p.scale, p.noise.upper(), p.L, _label(p.method, p.mode, p.d, getattr(p, "params", None)),
                     p.family, f"{p.bytes_per_place:.2f}",
                     time_cell(p), _recall_cell(p), int(p.n_queries)])
    return ["## CoarseHash against the other methods", "",
            "The same centres, truths and window score (docs/protocol.md, \"Compact codes\"): another method's "
            "frame retrieves its top-k references (by default k = CoarseHash's mean list size, the same "
            "candidate budget; each k and nprobe evaluated is an operating point), and its windows are scored "
            "on its own distances. Bytes per place count the code and whatever else the method keeps per "
            "place to answer (CoarseHash: its bit planes and inverted lists; IVF: 64-bit ids and the codes "
            "again in id order, for IVF-PQ with each place's distance term). Times are per query per core "
            "with the per-frame work included, so queries "
            "per second per core is their inverse; a flat FAISS index scans every code for every frame, so "
            "past a scan budget its runs localise an evenly spaced sample of the centres, never fewer than "
            "1,000 unless asked (the queries column, and the recall intervals, say how many). Lines join "
            "each method's Pareto front: the "
            "operating points no other point of the method beats on both recall and throughput.", "",
            "FAISS's codes are trained (k-means, OPQ and ITQ rotations) with the processor's own BLAS, whose "
            "last bits differ between processor families: on another processor than the one the provenance "
            "names, their rows may differ, by several points for the rotated codes (OPQ, ITQ) at small radii; "
            "CoarseHash's and the baseline's are exact, the same bytes on any machine.", "",
            *(line for name in figures for line in (f"![{name}]({name}.png)", "")), *_words(points, scales, twins), "",
            table(["scale", "noise", "L", "method (mode)", "family", "B/place", "µs/query",
                   "within 20 frames % (95 % interval)", "queries"], rows), ""]


def _scale_key(scales: list[str]):
    order = {s: i for i, s in enumerate(scales)}

    def key(col: pd.Series) -> pd.Series:
        return col.map(order) if col.name == "scale" else col if col.dtype != object else col.astype(str)

    return key

