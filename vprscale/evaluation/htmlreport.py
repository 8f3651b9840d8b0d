"""``report.html``: the report as one self-contained page people explore, beside ``report.md``.

What ann-benchmarks' site gives and what users of benchmark reports ask for most — the
numbers behind a plot — without a server or a network: the page embeds plotly.js and every
recall row of the results (over all queries, every radius), and draws from them in the
browser:

- recall against queries per second per core, against bytes per place, and against the
  localisation radius, every point hoverable (method, parameters, mode, L, scale, noise,
  recall with its 95 % interval, µs per query, bytes per place, queries); where evaluations
  counted radii in metres (``eval --radius-m``), recall against the radius in metres too, per
  part with positions;
- filters by scale, noise level, L, mode and method, and the recall radius the first two
  figures read (every noise level is there: none is left out);
- under each figure the table it draws, and a button that downloads it as CSV (the rows the
  filters leave), and the whole table likewise;
- the provenance block of the report on top;
- below, the whole of ``report.md``: every figure (embedded), table and line of it
  (:mod:`vprscale.evaluation.mdhtml`), so the page alone is the report.

Errors in the page are written into it (``#page-errors``), so a headless browser can tell a
page that drew from one that failed. :func:`fill_page` is the page without its figures: the
report of MSLS's tasks (:mod:`vprscale.evaluation.taskreport`) fills it with its own script, and
both scripts share ``report_common.js`` (filters kept in the address, tables, CSV downloads).
Colours and markers are the PNG figures' (one colour per method, one marker per mode:
:mod:`vprscale.evaluation.comparison`).
"""

from __future__ import annotations

import html
import re
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.colors import to_hex

from vprscale.core.plaintext import script_json
from vprscale.evaluation.comparison import method_and_mode, series_colours, with_series
from vprscale.evaluation.mdhtml import inline, render

# The page's template, its script and what that shares with the tasks' page (package data)
PAGE, SCRIPT, COMMON = "report_page.html", "report_page.js", "report_common.js"
# The columns the page holds per recall row (those an evaluation has)
COLUMNS = ("scale", "noise", "method", "series", "family", "mode", "L", "d", "params", "radius", "recall", "recall_lo",
           "recall_hi", "recall_at_20", "bytes_per_place", "us_per_query", "qps_per_core", "n_queries", "run")
SYMBOLS = {"aligned": "triangle-up", "paper": "circle", "single": "square"}  # the PNG figures' MODE_MARKERS
# The page's figures: id, title, the column on x, its label (recall on y)
FIGURES = (("fig-qps", "Recall against queries per second per core", "qps_per_core", "queries per second per core"),
           ("fig-bytes", "Recall against bytes per place", "bytes_per_place", "bytes per place"),
           ("fig-radius", "Recall against the localisation radius", "radius", "radius (frames)"))
# Drawn from the rows in metres, when there are any
METRES_FIGURE = ("fig-metres", "Recall against the radius in metres (parts with positions)", "radius_m", "radius (m)")
METRES_COLUMNS = (*COLUMNS[: COLUMNS.index("radius")], "part", "radius_m", *COLUMNS[COLUMNS.index("radius") + 1 :])


def page_rows(res: pd.DataFrame, columns: tuple[str, ...] = COLUMNS) -> pd.DataFrame:
    """The rows the page draws: every method's recall over all queries at every radius (rows in
    metres: over each part with positions, ``columns`` ``METRES_COLUMNS``)."""
    rows = with_series(res[res.part == "all"] if "radius" in columns else res)
    rows["method"] = [method_and_mode(f)[0] for f in rows.series]  # CoarseHash one method at every width
    for missing in {"bytes_per_place", "us_per_query"} - set(rows.columns):  # results of a vprscale before 0.3
        rows[missing] = np.nan
    rows["qps_per_core"] = 1e6 / rows.us_per_query.clip(lower=1e-9)
    return rows[[c for c in columns if c in rows.columns]].reset_index(drop=True)


def _json(rows: pd.DataFrame) -> str:
    """The rows as JSON records (NaN as null), safe inside a ``<script>`` element whatever a label holds."""
    clean = rows.astype(object).where(rows.notna(), None)
    records = [{k: (v.item() if isinstance(v, np.generic) else v) for k, v in r.items()}
               for r in clean.to_dict("records")]
    return script_json(records, separators=(",", ":"))


INTRO = ("Every recall row of the results over all queries, drawn in the page: hover a point for its method, "
         "parameters and figures; the filters choose what is drawn; each figure's table is under it, and downloads "
         "as CSV. Recall is the share of query centres matched within the radius (frames; 20 frames = 100 m on "
         "FAS), with its 95 % Wilson interval.")


def write_html(res: pd.DataFrame, metres: pd.DataFrame, provenance_lines: list[str], title: str, out: Path,
               report_md: str = "", palette: dict[str, Any] | None = None) -> Path:
    """Write ``out/report.html`` from the results ``res``, the rows in metres ``metres`` (empty
    when no evaluation counted them), the report's provenance lines and the whole of ``report.md``
    (``report_md``, its figures read from ``out``), which the page holds below its own figures;
    each method in its colour of ``palette``, the PNG figures'."""
    rows = page_rows(res)
    rows_m = page_rows(metres, METRES_COLUMNS) if len(metres) else rows.iloc[:0]
    figures = FIGURES + ((METRES_FIGURE,) if len(rows_m) else ())
    families = list(dict.fromkeys([*rows.series, *rows_m.series]))
    colours = {method_and_mode(f)[0]: to_hex(c) for f, c in series_colours(families, palette).items()}
    script = (resources.files(__package__) / SCRIPT).read_text("utf-8")
    script = (script.replace("@COLOURS@", script_json(colours)).replace("@SYMBOLS@", script_json(SYMBOLS))
              .replace("@FIGURES@", script_json(figures)))
    return fill_page(out, title, INTRO, provenance_lines, script, rows, rows_m, report_md)


def fill_page(out: Path, title: str, intro: str, provenance_lines: list[str], script: str, rows: pd.DataFrame,
              rows_m: pd.DataFrame, report_md: str) -> Path:
    """Write ``out/report.html``: the page's template around ``script`` (which draws from the
    embedded ``rows`` and ``rows_m``), the provenance lines on top and the whole of ``report_md``
    below, plotly.js inside; every value inserted as text or JSON that cannot close a script."""
    from plotly.offline import get_plotlyjs

    here = resources.files(__package__)
    template, common = (here / PAGE).read_text("utf-8"), (here / COMMON).read_text("utf-8")
    provenance = "".join(f"<li>{inline(line.removeprefix('- '))}</li>" for line in provenance_lines
                         if line.startswith("- "))
    values = {"TITLE": html.escape(title), "INTRO": html.escape(intro), "PROVENANCE": provenance,
              "SCRIPT": f"{common}\n{script}",
              "ROWS": _json(rows), "ROWSM": _json(rows_m), "REPORT": render(report_md, out),
              "PLOTLY": get_plotlyjs().replace("</script", "<\\/script")}
    page = re.sub(r"@([A-Z]+)@", lambda m: values[m.group(1)], template)  # one pass: inserted text is not rescanned
    path = out / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
