"""The report's nearest-neighbour section (``eval --nn``: docs/protocol.md, "Nearest-neighbour
recall"), read from each evaluation's ``nn.parquet``: a table, and 1-NN recall against bytes per
place beside the figures the literature publishes for Deep1B (per core, as this suite times)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pandas as pd
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from vprscale.evaluation.comparison import method_colours, method_name
from vprscale.evaluation.nearest import DEPTHS, PUBLISHED

PUBLISHED_MARKERS = ("s", "D", "p", "h")  # one hollow marker per published point


def load_nn(runs: list[str]) -> pd.DataFrame:
    """Every evaluation's nearest-neighbour rows (none where it was run without ``--nn``)."""
    frames = [pd.read_parquet(Path(run) / "nn.parquet") for run in runs if (Path(run) / "nn.parquet").is_file()]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def nn_section(nn: pd.DataFrame, scales: list[str], out: Path, save: Callable[[Any, Path, str], None],
               table: Callable[[list[str], list[list[Any]]], str],
               palette: dict[str, Any] | None = None) -> list[str]:
    """The section (empty when no evaluation has ``nn.parquet``): per scale, noise and method its
    bytes per place, R@1, R@10, R@100 and CPU µs per query on one core; the published rows below,
    each with its thread count and its time per core; and ``fig_nn`` (in ``palette``'s colours)."""
    if nn.empty:
        return []
    order = {s: i for i, s in enumerate(scales)}
    nn = nn.assign(pos=nn.scale.map(order).fillna(len(order))).sort_values(["pos", "noise", "bytes_per_place"])
    rows = [[p.scale, p.noise.upper(), method_name(p.method), p.family, p.params, f"{p.bytes_per_place:.2f}",
             *(f"{getattr(p, f'recall_at_{r}'):.3f}" for r in DEPTHS), f"{p.us_per_query:,.1f}", p.n_queries]
            for p in nn.itertuples()]
    published = [[p["method"], f"{p['bytes_per_place']:.0f}", f"{p['recall_at_1']:.3f}", p["threads"],
                  f"{p['us_per_query'] * p['threads']:,.0f}", p["source"]] for p in PUBLISHED]
    _figure(nn, out, save, palette)
    return ["## Nearest-neighbour recall", "",
            "The share of Deep1B query rows whose exact nearest reference (brute force over every reference) is "
            "among a method's R best: CoarseHash's address lists expanded by Hamming distance, each FAISS code's "
            "own search (docs/protocol.md, \"Nearest-neighbour recall\"). B/entry: bytes of one entry of what "
            "answers this search (a FAISS code's code and id; CoarseHash's code and list entry), the field's "
            "bytes per vector; not the comparison's B/place, which also counts what scoring windows keeps. "
            "µs: CPU per query on one core.", "",
            table(["scale", "noise", "method", "family", "params", "B/entry", "R@1", "R@10", "R@100", "µs/q",
                   "queries"], rows), "",
            "Published on the real Deep1B at a billion vectors, for scale (another dataset than the rows above; "
            "times per core = time × threads):", "",
            table(["method", "B/vector", "R@1", "threads", "µs/q per core", "source"], published), "",
            "![nearest-neighbour recall against bytes per search entry](fig_nn.png)", ""]


def _figure(nn: pd.DataFrame, out: Path, save: Callable[[Any, Path, str], None],
            palette: dict[str, Any] | None) -> None:
    """R@1 and R@100 against bytes per search entry, one panel per scale and noise; the published
    points hollow, each its own marker named in the legend (labels beside points that lie close
    together ran into each other), the legend outside the panels, plain numbers on the log axis."""
    keys = list(dict.fromkeys(zip(nn.scale, nn.noise, strict=True)))
    fig, axes = plt.subplots(1, len(keys), figsize=(4.6 * len(keys) + 3.2, 3.8), squeeze=False, sharey=True,
                             layout="constrained")
    nn = nn.assign(method=nn.method.map(method_name))
    colours = method_colours(nn.method, palette)
    for ax, (scale, noise) in zip(axes[0], keys, strict=True):
        g = nn[(nn.scale == scale) & (nn.noise == noise)]
        for p in g.itertuples():
            ax.plot([p.bytes_per_place] * 2, [100 * p.recall_at_1, 100 * p.recall_at_100], "-",
                    color=colours[p.method], alpha=0.4)
            ax.plot(p.bytes_per_place, 100 * p.recall_at_1, "o", color=colours[p.method], label=f"{p.method} R@1")
            ax.plot(p.bytes_per_place, 100 * p.recall_at_100, "^", color=colours[p.method],
                    label=f"{p.method} R@100")
        for p, marker in zip(PUBLISHED, PUBLISHED_MARKERS, strict=False):
            ax.plot(p["bytes_per_place"], 100 * p["recall_at_1"], marker, mfc="none", color="black",
                    label=f"{p['method']}, R@1 (published)")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())  # 2, 3, … 9 × 10^k printed over each other
        ax.set_xlabel("bytes per search entry")
        ax.set_title(f"{scale} {noise.upper()}")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("1-NN recall (%)")
    handles, labels = axes[0][-1].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=6, loc="outside right center")
    save(fig, out, "fig_nn")
