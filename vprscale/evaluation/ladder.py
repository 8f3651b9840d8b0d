"""The report's ladder at a glance: one row per scale, the figures a reader quotes.

A report over several scales answers one question first: what does CoarseHash keep, find and
cost at each rung, and what does a FAISS code find in the same bytes. Each cell is read from
the rows the report's other tables hold (nothing is computed here that they do not show):

- the whole index's bytes per place, as the storage table measures it;
- CoarseHash's recall within 20 frames on the main query set at L = 50 and 100, paper and
  aligned mode, at the scale's main width, with its time per query per core (paper mode);
- the FAISS code (a compared code, or a pooled sequence descriptor held in one) that finds most
  within 20 frames at the longest L among those that keep no more bytes per place than
  CoarseHash does in the same evaluation, in its best mode and operating point. An IVF code keeps
  an 8-byte id a place beside its code, so at CoarseHash's size the flat codes are the ones that
  qualify; where none was evaluated the cell says so.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import pandas as pd

from vprscale.core.plaintext import markdown
from vprscale.evaluation.comparison import OURS, best_first, named_modes, series_label
from vprscale.evaluation.results import main_noise

RADIUS = 20
LENGTHS = (50, 100)
MODES = ("paper", "aligned")


def percent(x: float | None) -> str:
    """A share as the report's tables print it: ``87.5``; ``–`` where there is none."""
    return "–" if x is None or x != x else f"{100 * x:.1f}"


def _us(row: pd.Series | None) -> str:
    us = math.nan if row is None else float(row.get("us_per_query", math.nan))
    return "–" if not math.isfinite(us) else f"{us:,.1f}"


def _coarsehash(rows: pd.DataFrame, mode: str, L: int) -> pd.Series | None:
    hit = rows[(rows.method == OURS) & (rows["mode"] == mode) & (rows.L == L)]
    return None if hit.empty else hit.iloc[0]


def _best_code(rows: pd.DataFrame, bytes_cap: float | None, L: int) -> str:
    """The compared FAISS code (or pooled descriptor) at most ``bytes_cap`` bytes a place that finds
    most at ``L``, as ``PQ3 k=64 (aligned): 41.2 % at 3.00 B/place, 210.5 µs``."""
    if "bytes_per_place" not in rows.columns or bytes_cap is None:
        return "–"
    codes = named_modes(rows[~rows.method.isin({OURS, "baseline"}) & (rows.L == L)])
    codes = codes[codes.family.ne("own")]
    if codes.empty:
        return "–"  # no FAISS code evaluated at this scale
    codes = codes[codes.bytes_per_place <= bytes_cap * (1 + 1e-9)]
    if codes.empty:
        return "none evaluated at these bytes"
    b = best_first(codes).iloc[0]
    params = b.get("params")
    at = f" {params}" if isinstance(params, str) and params else ""
    name = series_label(b.method, b["mode"], None).replace(" (", f"{at} (", 1)
    return (f"{markdown(name)}: {percent(b.recall)} % at {b.bytes_per_place:.2f} B/place, "
            f"{b.us_per_query:,.1f} µs")


def ladder_section(res: pd.DataFrame, indexes: list[dict[str, Any]], scales: list[str], mains: dict[str, int],
                   whole_bytes: Callable[[dict[str, Any]], int | None],
                   table: Callable[[list[str], list[list[Any]]], str]) -> list[str]:
    """The report's "ladder at a glance" section; empty for a report of one scale or without
    sequences (there is no ladder to read)."""
    noise = main_noise(res)
    longest = max(LENGTHS)
    rows = []
    for scale in scales:
        sub = res[(res.scale == scale) & (res.part == "all") & (res.noise == noise) & (res.radius == RADIUS)]
        main = sub[(sub.method != OURS) | (sub.d == mains[scale])]
        cells = {(mode, L): _coarsehash(main, mode, L) for mode in MODES for L in LENGTHS}
        if all(c is None for c in cells.values()):
            continue
        index = next((i for i in indexes if i["store"]["scale"] == scale and i["d"] == mains[scale]
                      and i["store"].get("rescale") is not False), None)
        whole = whole_bytes(index) if index else None
        paper = [cells["paper", L] for L in LENGTHS]
        ours = next((c for c in (cells["paper", longest], cells["aligned", longest]) if c is not None), None)
        cap = math.nan if ours is None else float(ours.get("bytes_per_place", math.nan))
        rows.append([markdown(scale), mains[scale],
                     "–" if not whole else f"{whole / index['n_ref']:.2f}",
                     *(percent(None if c is None else c.recall) for c in cells.values()),
                     " / ".join(_us(c) for c in paper),
                     _best_code(main, cap if math.isfinite(cap) else None, longest)])
    if len(rows) < 2:
        return []
    heads = ["scale", "d", "index B/place",
             *(f"{mode} L={L}" for mode in MODES for L in LENGTHS),
             "µs/query/core (paper, L=50 / 100)", f"best FAISS code at ≤ CoarseHash's bytes, L={longest}"]
    return ["## The ladder at a glance", "",
            f"CoarseHash at each scale's main width on {markdown(noise.upper())}: recall within {RADIUS} frames (%) "
            "of all queries, paper and aligned mode; the whole index's bytes per place (the storage table's); "
            "its time per query per core (paper mode, median). The last column is the compared FAISS code "
            f"(or pooled sequence descriptor) that finds most within {RADIUS} frames at L = {longest} among those "
            "keeping no more bytes per place than CoarseHash in the same evaluation (IVF codes keep an 8-byte id "
            "a place beside their code, so the flat codes qualify), with its bytes and time.", "",
            table(heads, rows), ""]
