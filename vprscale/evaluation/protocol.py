"""Which query centres an evaluation localises (the protocol of ``docs/protocol.md``).

Centres are ``t = 0, z, 2z, …`` with a ground truth and the whole window of ``L`` frames
inside the query set. At 10M places and beyond that stride leaves only a handful of
centres in the FAS part (3 at 10M), whose curves would mean nothing; the FAS part is then
sampled with a stride of its own, the largest that gives it at least ``MIN_FAS`` centres.
Such a stratified sample no longer has the parts in their proportions, so the overall
figure weights each part by its share of the query rows (:func:`part_weights`).

The same function decides which query rows a compact store keeps (the windows of the
centres) and which centres an evaluation of that store localises, so the two agree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

MIN_FAS = 200  # FAS centres at least, per sequence length


@dataclass(frozen=True)
class Centres:
    """The centres for one sequence length, and whether the FAS part has its own stride."""

    t: np.ndarray
    fas_stride: int | None  # None: the FAS part follows the common stride


def _valid(t: np.ndarray, gt_at: Callable[[np.ndarray], np.ndarray], n_query: int, L: int) -> np.ndarray:
    half = L // 2
    t = t[(t - half >= 0) & (t - half + L <= n_query)]
    return t[gt_at(t) >= 0]


def query_centres(gt_at: Callable[[np.ndarray], np.ndarray], n_query: int, n_deep: int, z: int,
                  L: int) -> Centres:
    """The evaluated centres for sequences of ``L``; ``gt_at(t)`` is the truth of frames ``t`` (−1: none)."""
    common = _valid(np.arange(0, n_query, z, dtype=np.int64), gt_at, n_query, L)
    n_fas = n_query - n_deep
    if n_fas == 0 or int((common >= n_deep).sum()) >= MIN_FAS:
        return Centres(common, None)
    stride = max(1, n_fas // MIN_FAS)
    while True:
        fas = _valid(np.arange(n_deep, n_query, stride, dtype=np.int64), gt_at, n_query, L)
        if len(fas) >= MIN_FAS or stride == 1:
            break
        stride -= 1
    return Centres(np.concatenate([common[common < n_deep], fas]), stride)


def part_weights(n_query: int, n_deep: int) -> dict[str, float]:
    """Each part's share of the query rows: the weights of a stratified overall figure."""
    return {"deep1b": n_deep / n_query, "fas": (n_query - n_deep) / n_query}


def window_frames(centres: list[np.ndarray], lengths: list[int]) -> np.ndarray:
    """Every query frame inside some evaluated window (ascending)."""
    frames = [(c[:, None] + np.arange(L)[None, :] - L // 2).ravel() for c, L in zip(centres, lengths, strict=True)]
    return np.unique(np.concatenate(frames)) if frames else np.empty(0, np.int64)
