"""The d = 1 baseline (docs/method.md) as an evaluated method."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr

from vprscale.compared.baseline import baseline_batch
from vprscale.core.zarrio import rows_of
from vprscale.dataset.compact import baseline_map
from vprscale.dataset.store import ref_moments
from vprscale.evaluation.accounting import baseline_ops
from vprscale.evaluation.algorithms.base import Algorithm, Answer
from vprscale.evaluation.algorithms.coarsehash import CoarseHash
from vprscale.method.kernels import N_BEST
from vprscale.method.pca import ExactPCA, moments_of
from vprscale.protocol import window_mask, window_positions

FLOAT_BYTES = 4  # the baseline's map: one float32 per place
SUBSAMPLE = 64  # baseline queries per run at 10^8 query rows and beyond (each scans every place)


@dataclass
class BaselineMap:
    """The d = 1 baseline's map (every reference's first principal component) and its projection."""

    x: np.ndarray  # float32, one per reference
    mean: np.ndarray
    component: np.ndarray  # (1, D)

    def project(self, rows: np.ndarray) -> np.ndarray:
        return baseline_map(rows, self.mean, self.component).astype(np.float64)


def load_baseline_map(group: zarr.Group, layout: dict[str, Any]) -> BaselineMap:
    """The baseline's map: kept by a compact build, else projected chunk by chunk from ``ref``.

    Its PCA (d = 1) is the first component of the references' PCA, fitted on the moments
    the build derived, so both layouts give the baseline the same map.
    """
    if layout["kind"] == "compact":
        model = group["transforms/coarsehash"]
        return BaselineMap(group["base_x1"][:], model["mean"][:], model["components"][:1])
    ref = rows_of(group["ref"])
    moments = ref_moments(group)
    pca = ExactPCA(1).fit_moments(moments if moments is not None else moments_of(ref))
    x = ref.map_blocks(baseline_map, pca.mean_, pca.components_, drop_axis=1, dtype=np.float32).compute()
    return BaselineMap(x, pca.mean_, pca.components_)


class Baseline(Algorithm):
    """SeqSLAM on one principal component.

    Its N_r at each L is CoarseHash's paper-mode mean N_r over every centre of that L, on
    the same index and noise (``coarse``), so both methods score as many candidates; it is
    worked out, untimed, in :meth:`prepare`.
    """

    name = "baseline"
    family = "baseline"
    timed_side_by_side = True
    bytes_per_place = float(FLOAT_BYTES)

    def __init__(self, base: BaselineMap, coarse: CoarseHash, dim: int, query_limit: int | None) -> None:
        self.base, self.coarse, self.dim, self.query_limit = base, coarse, dim, query_limit
        self.x_range = float(np.ptp(base.x)) if len(base.x) else 0.0
        self.budget: dict[int, int] = {}

    def columns(self) -> dict[str, Any]:
        return {"d": 1, "K": None, "params": None}

    def prepare(self, noise: str, frames: np.ndarray, rows: np.ndarray, centres: dict[int, np.ndarray]) -> None:
        self.coarse.ref_windows = self.ref_windows  # its budget: CoarseHash's N_r over the same windows
        state = self.coarse.frames(rows)
        self.budget = {}
        for L, t in centres.items():
            n_r = self.coarse.localise(state, window_positions(frames, t, L), L, "paper").n_r if L > 1 else []
            self.budget[L] = max(1, int(round(float(np.mean(n_r)) if len(n_r) else 1.0)))

    def frames(self, rows: np.ndarray) -> np.ndarray:
        return self.base.project(rows)

    def localise(self, state: np.ndarray, pos: np.ndarray, L: int, mode: str | None, n_best: int = N_BEST) -> Answer:
        nr = self.budget[L]
        valid = window_mask(self.ref_windows, L)
        top, scores, n_r = baseline_batch(pos, L, nr, self.base.x, state, self.x_range, valid, n_best)
        answer = Answer(top, scores[:, 0], n_r, baseline_ops(self.dim, len(self.base.x), L, nr)["total"])
        if 1 < n_best and nr < n_best:  # the Recall@N ranking weighs at least N (its budget at L = 1 is one)
            answer.ranked, _, answer.n_ranked = baseline_batch(pos, L, n_best, self.base.x, state, self.x_range,
                                                               valid, n_best)
        return answer


def baseline_limit(requested: int | None, n_query: int) -> int | None:
    """Queries the baseline localises per run (None: all).

    Each query scans every place (~0.1 s at 10^8 places), so at 10^8 query rows and beyond a
    run localises an evenly spaced sample; ``--baseline-queries`` sets its size anywhere.
    """
    if requested is not None:
        return requested
    return SUBSAMPLE if n_query >= 10**8 else None


def create(context: Any) -> list[Algorithm]:
    """The registry's factory: the baseline, unless the evaluation was run without it."""
    if context.baseline is None:
        return []
    return [Baseline(context.baseline, CoarseHash(context.index, context.dim), context.dim,
                     baseline_limit(context.baseline_queries, context.n_query))]
