"""The report's nearest-neighbour section (``eval --nn``: docs/protocol.md, "Nearest-neighbour
recall"), read from each evaluation's ``nn.parquet``: a table, and 1-NN recall against bytes per
place beside the figures the literature publishes for Deep1B (per core, as this suite times)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pandas as pd

from vprscale.evaluation.comparison import series_colours
from vprscale.evaluation.nearest import DEPTHS, PUBLISHED


def load_nn(runs: list[str]) -> pd.DataFrame:
    """Every evaluation's nearest-neighbour rows (none where it was run without ``--nn``)."""
    frames = [pd.read_parquet(Path(run) / "nn.parquet") for run in runs if (Path(run) / "nn.parquet").is_file()]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def nn_section(nn: pd.DataFrame, scales: list[str], out: Path, save: Callable[[Any, Path, str], None],
               table: Callable[[list[str], list[list[Any]]], str]) -> list[str]:
    """The section (empty when no evaluation has ``nn.parquet``): per scale, noise and method its
    bytes per place, R@1, R@10, R@100 and CPU µs per query on one core; the published rows below,
    each with its thread count and its time per core; and ``fig_nn``."""
    if nn.empty:
        return []
    order = {s: i for i, s in enumerate(scales)}
    nn = nn.assign(pos=nn.scale.map(order).fillna(len(order))).sort_values(["pos", "noise", "bytes_per_place"])
    rows = [[p.scale, p.noise.upper(), p.method, p.family, p.params, f"{p.bytes_per_place:.2f}",
             *(f"{getattr(p, f'recall_at_{r}'):.3f}" for r in DEPTHS), f"{p.us_per_query:,.1f}", p.n_queries]
            for p in nn.itertuples()]
    published = [[p["method"], f"{p['bytes_per_place']:.0f}", f"{p['recall_at_1']:.3f}", p["threads"],
                  f"{p['us_per_query'] * p['threads']:,.0f}", p["source"]] for p in PUBLISHED]
    _figure(nn, out, save)
    return ["## Nearest-neighbour recall", "",
            "The share of Deep1B query rows whose exact nearest reference (brute force over every reference) is "
            "among a method's R best: CoarseHash's address lists expanded by Hamming distance, each FAISS code's "
            "own search (docs/protocol.md, \"Nearest-neighbour recall\"). Bytes per place: what answers the "
            "search (a FAISS code's entry; CoarseHash's codes and lists). µs: CPU per query on one core.", "",
            table(["scale", "noise", "method", "family", "params", "B/place", "R@1", "R@10", "R@100", "µs/q",
                   "queries"], rows), "",
            "Published on the real Deep1B at a billion vectors, for scale (another dataset than the rows above; "
            "times per core = time × threads):", "",
            table(["method", "B/vector", "R@1", "threads", "µs/q per core", "source"], published), "",
            "![nearest-neighbour recall against bytes per place](fig_nn.png)", ""]


def _figure(nn: pd.DataFrame, out: Path, save: Callable[[Any, Path, str], None]) -> None:
    """R@1 and R@100 against bytes per place, one panel per scale and noise; the published points hollow."""
    keys = list(dict.fromkeys(zip(nn.scale, nn.noise, strict=True)))
    fig, axes = plt.subplots(1, len(keys), figsize=(4.6 * len(keys), 3.8), squeeze=False, sharey=True)
    methods = list(dict.fromkeys(nn.method))
    colours = dict(zip(methods, series_colours([f"{m} (single)" for m in methods]).values(), strict=True))
    for ax, (scale, noise) in zip(axes[0], keys, strict=True):
        g = nn[(nn.scale == scale) & (nn.noise == noise)]
        for p in g.itertuples():
            ax.plot([p.bytes_per_place] * 2, [100 * p.recall_at_1, 100 * p.recall_at_100], "-",
                    color=colours[p.method], alpha=0.4)
            ax.plot(p.bytes_per_place, 100 * p.recall_at_1, "o", color=colours[p.method], label=f"{p.method} R@1")
            ax.plot(p.bytes_per_place, 100 * p.recall_at_100, "^", color=colours[p.method],
                    label=f"{p.method} R@100")
        for i, p in enumerate(PUBLISHED):  # labels above and below in turn: the points lie close
            ax.plot(p["bytes_per_place"], 100 * p["recall_at_1"], "s", mfc="none", color="black")
            ax.annotate(p["method"].split(" (")[0], (p["bytes_per_place"], 100 * p["recall_at_1"]), fontsize=6,
                        xytext=(4, 6 if i % 2 else -10), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("bytes per place")
        ax.set_title(f"{scale} {noise.upper()}")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("1-NN recall (%)")
    axes[0][-1].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.02, 0.5))
    save(fig, out, "fig_nn")
