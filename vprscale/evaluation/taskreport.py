"""The report of MSLS's tasks (``vprscale report`` on evaluations run with ``eval --task``).

A task's evaluation has no frame grid to draw (no noise levels, radii or L sweep): its answer
is a ranked list a query, scored by MSLS's recall@k and map@k at k = 1, 5, 10, 20. The report
gives, per task, sequence length and subtask, each method's scores over every query and city
by city, with its bytes per place and time per query per core; and ``fig_tasks``: recall@k
against k over every query, one panel per task, as MSLS's papers draw it; and ``report.html``,
the frame report's page for these rows (:mod:`vprscale.evaluation.htmlreport`): recall@k and
mAP@k against k drawn in the browser, every point hoverable, filtered by task, city and method,
each figure's table under it as CSV, the whole of ``report.md`` below.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import pandas as pd
from matplotlib.colors import to_hex

from vprscale.core.plaintext import script_json
from vprscale.evaluation.comparison import (
    OURS,
    TITLE_SIZE,
    method_and_mode,
    panels,
    series_colours,
    series_line,
    series_marker,
    shared_legend,
    with_series,
)
from vprscale.evaluation.htmlreport import SYMBOLS, fill_page
from vprscale.evaluation.tasks import KS

KEY = ["task", "seq_length", "subtask", "threshold_m"]
SCRIPT = "task_page.js"  # the page's script (package data)
INTRO = ("Every score of the evaluations, drawn in the page: recall@k and mAP@k against k, a line per method "
         "(mode); hover a point for its figures; the filters choose the task, the queries (all, or a city's) and "
         "the method; each figure's table is under it, and downloads as CSV.")


def task_title(task: str, seq_length: int, subtask: str, threshold_m: float) -> str:
    """``seq2seq, 5 frames, subtask all, positives within 25 m``."""
    frames = "" if task == "im2im" else f", {int(seq_length)} frames"
    return f"{task}{frames}, subtask {subtask}, positives within {threshold_m:g} m"


def task_sections(res: pd.DataFrame, out: Path, save: Callable[[Any, Path, str], None],
                  table: Callable[[list[str], list[list[Any]]], str],
                  palette: dict[str, Any] | None = None) -> list[str]:
    """The figure and a table per task (every method and mode, all queries first, then each city)."""
    res = _ordered(with_series(res.copy()))
    name = fig_tasks(res, out, save, palette)
    md = ["## MSLS's tasks", "",
          "Each query is answered by a ranked list of database windows (MSLS's definitions: "
          "docs/bring-your-own.md, \"MSLS's tasks\"). R@k: the share of queries with a positive among the k "
          "first; mAP@k: MSLS's mean average precision at k. B/place: bytes a method keeps per database "
          "frame; µs/query: CPU time of one thread per query, the median of the repeats.", "",
          f"![recall@k against k]({name}.png)", ""]
    for key, g in res.groupby(KEY, sort=False):
        rows = [[p.series, p.part, f"{int(p.n_queries):,}",
                 *(f"{100 * getattr(p, f'recall_at_{k}'):.1f}" for k in KS),
                 *(f"{getattr(p, f'map_at_{k}'):.3f}" for k in KS),
                 f"{p.bytes_per_place:.2f}", f"{p.us_per_query:,.1f}"]
                for p in g.itertuples()]
        md += [f"### {task_title(*key)}", "",
               table(["method (mode)", "queries of", "queries", *(f"R@{k} %" for k in KS),
                      *(f"mAP@{k}" for k in KS), "B/place", "µs/query"], rows), ""]
    return md


def fig_tasks(res: pd.DataFrame, out: Path, save: Callable[[Any, Path, str], None],
              palette: dict[str, Any] | None) -> str:
    """Recall@k against k over every query, one panel per task; the figure's name."""
    whole = res[res.part == "all"]
    keys = list(dict.fromkeys(map(tuple, whole[KEY].itertuples(index=False))))
    colours = series_colours(list(dict.fromkeys(whole.series)), palette)
    fig, axes = panels(1, len(keys), 4.6, 3.6)
    for ax, key in zip(axes[0], keys, strict=True):
        g = whole[(whole[KEY] == pd.Series(key, index=KEY)).all(axis=1)]
        for p in g.itertuples():
            ax.plot(KS, [100 * getattr(p, f"recall_at_{k}") for k in KS], marker=series_marker(p.series),
                    ls=series_line(p.series), color=colours[p.series], label=p.series)
        ax.set(xscale="log", ylim=(0, 102), xlabel="k (answers read)")
        ax.set_xticks(KS, [str(k) for k in KS])
        ax.minorticks_off()
        ax.set_title(task_title(*key), fontsize=TITLE_SIZE)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("recall@k (%)")
    shared_legend(fig, axes)
    fig.suptitle("MSLS's tasks: recall@k, every query")
    save(fig, out, "fig_tasks")
    return "fig_tasks"


def write_task_html(res: pd.DataFrame, provenance_lines: list[str], title: str, out: Path, report_md: str,
                    palette: dict[str, Any] | None) -> Path:
    """``out/report.html`` of the task scores ``res``: one row a task, method (mode), queries and k,
    each method in its colour of ``palette``, the PNG figure's."""
    res = _ordered(with_series(res.copy()))
    rows = pd.DataFrame([{"task": task_title(*(getattr(p, c) for c in KEY)), "method": method_and_mode(p.series)[0],
                          "series": p.series,
                          "mode": p.mode, "part": p.part, "k": k, "recall": getattr(p, f"recall_at_{k}"),
                          "map": getattr(p, f"map_at_{k}"), "bytes_per_place": p.bytes_per_place,
                          "us_per_query": p.us_per_query, "n_queries": int(p.n_queries)}
                         for p in res.itertuples() for k in KS])
    colours = {method_and_mode(f)[0]: to_hex(c)
               for f, c in series_colours(list(dict.fromkeys(res.series)), palette).items()}
    script = (resources.files(__package__) / SCRIPT).read_text("utf-8")
    script = (script.replace("@COLOURS@", script_json(colours)).replace("@SYMBOLS@", script_json(SYMBOLS))
              .replace("@KS@", script_json(list(KS))))
    return fill_page(out, title, INTRO, provenance_lines, script, rows, rows.iloc[:0], report_md)


def _ordered(res: pd.DataFrame) -> pd.DataFrame:
    """CoarseHash first, then the others by name; each method's modes together; all queries before
    each city."""
    return res.assign(_ours=res.method.ne(OURS), _all=res.part.ne("all")).sort_values(
        [*KEY, "_ours", "series", "_all", "part"], kind="stable").drop(columns=["_ours", "_all"])
