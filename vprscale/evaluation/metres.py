"""The report's table of recall within radii in metres (``eval --radius-m``: docs/protocol.md,
"Recall within metres"), read from each evaluation's ``results_m.parquet``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from vprscale.evaluation.comparison import named_modes, series_label


def load_metres(runs: list[str]) -> pd.DataFrame:
    """Every evaluation's rows in metres (none where it was run without ``--radius-m``)."""
    frames = [pd.read_parquet(Path(run) / "results_m.parquet") for run in runs
              if (Path(run) / "results_m.parquet").is_file()]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def metres_section(res: pd.DataFrame, scales: list[str], table) -> list[str]:
    """The section: per scale, noise, L and method, the recall and Recall@N within each radius in
    metres (the evaluations' rows, :func:`load_metres`), for every part with positions; empty
    when no evaluation has them."""
    if res.empty:
        return []
    order = {s: i for i, s in enumerate(scales)}
    res = named_modes(res).assign(pos=res.scale.map(order).fillna(len(order)))
    rows: list[list[Any]] = []
    for p in res.sort_values(["pos", "noise", "part", "L", "method", "mode", "radius_m"]).itertuples():
        params = getattr(p, "params", None)
        name = series_label(p.method, p.mode, p.d) + (f" {params}" if isinstance(params, str) and params else "")
        rows.append([p.scale, p.noise.upper(), p.part, p.L, name, p.family, f"{p.radius_m:g}", p.n_queries,
                     *(f"{100 * v:.1f}" if v == v else "–" for v in
                       (p.recall, p.recall_lo, p.recall_hi, p.recall_at_5, p.recall_at_20))])
    return ["## Recall within metres", "",
            "A match is correct when its reference lies within the radius of the query's position (as "
            "VPR-methods-evaluation counts its positives; docs/protocol.md, \"Recall within metres\"), for the "
            "parts whose queries have positions (a recipe's store: the FAS part, from FAS100K's poses).", "",
            table(["scale", "noise", "part", "L", "method (mode)", "family", "radius m", "queries", "recall %", "low %",
                   "high %", "R@5 %", "R@20 %"], rows), ""]
