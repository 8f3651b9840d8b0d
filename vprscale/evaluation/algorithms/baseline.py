"""The d = 1 baseline (docs/method.md) as an evaluated method."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import zarr

from vprscale.compared.baseline import baseline_batch
from vprscale.dataset.compact import baseline_map
from vprscale.dataset.rawchunks import rows_of
from vprscale.evaluation.accounting import baseline_ops
from vprscale.evaluation.algorithms.base import Algorithm, Run
from vprscale.evaluation.algorithms.coarsehash import CoarseHash
from vprscale.method.index import ref_moments
from vprscale.method.pca import ExactPCA, moments_of

FLOAT_BYTES = 4  # the baseline's map: one float32 per place


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
    """SeqSLAM on one principal component; its N_r is CoarseHash's paper-mode mean N_r at
    the same L (``coarse``), so both methods score as many candidates."""

    name = "baseline"
    bytes_per_place = float(FLOAT_BYTES)

    def __init__(self, base: BaselineMap, coarse: CoarseHash, dim: int, query_limit: int | None) -> None:
        super().__init__()
        self.base, self.coarse, self.dim, self.query_limit = base, coarse, dim, query_limit
        self.x_range = float(np.ptp(base.x)) if len(base.x) else 0.0
        self.y = np.zeros(0)

    def columns(self) -> dict[str, Any]:
        return {"d": 1, "K": None, "params": None}

    def _warm(self, rows: np.ndarray) -> None:
        self.base.project(rows)

    def _prepare(self, noise: str, rows: np.ndarray) -> None:
        self.y = self.base.project(rows)

    def localise(self, t: np.ndarray, L: int, mode: str | None, truth: np.ndarray) -> Run:
        nr = max(1, int(round(self.coarse.paper_n_r(L))))
        pos = self.window_positions(t, L)
        baseline_batch(pos[:1], L, nr, self.base.x, self.y, self.x_range)  # compile outside the timing
        t0 = time.perf_counter()
        match, n_r = baseline_batch(pos, L, nr, self.base.x, self.y, self.x_range)
        us = (time.perf_counter() - t0) * numba.get_num_threads() / max(1, len(pos)) * 1e6 + self.us_per_frame
        return Run(match, n_r, us, self.us_per_frame, baseline_ops(self.dim, len(self.base.x), L, nr)["total"])
