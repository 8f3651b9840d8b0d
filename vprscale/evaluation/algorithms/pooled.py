"""Pooled sequence descriptors (:mod:`vprscale.compared.pooled`) as evaluated methods."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from vprscale.compared.pooled import PooledCodes, PooledSpec, pool_windows
from vprscale.evaluation.accounting import method_ops
from vprscale.evaluation.algorithms.base import Algorithm, Answer, top_columns
from vprscale.evaluation.algorithms.coarsehash import CoarseHash
from vprscale.evaluation.algorithms.faisscodes import MIN_CENTRES, SCAN_BUDGET
from vprscale.method.index import Index, QueryFrames
from vprscale.method.kernels import N_BEST, NO_CANDIDATE


class PooledFrames(NamedTuple):
    """A pooled method's frame state: the frames' rows, and with re-ranking CoarseHash's per-frame work."""

    rows: np.ndarray
    coarse: QueryFrames | None


class PooledMethod(Algorithm):
    """One pooled descriptor: each query window of ``L`` frames is pooled into one row and
    searched in that ``L``'s code; its nearest pooled reference window is the match (``score``:
    FAISS's distance), its ``N_BEST`` nearest the Recall@N ranking. With re-ranking the code
    retrieves ``rerank`` windows and CoarseHash's window score ranks them (``score``: CoarseHash's,
    in δ_max units); the method then stores both. Not run at L = 1, where a pooled window is
    the frame itself: the FAISS code compared frame by frame."""

    family = "sequence descriptor"
    timed_side_by_side = True

    def __init__(self, pooled: PooledCodes, spec: PooledSpec, index: Index, dim: int, n_centres: int,
                 query_limit: int | None) -> None:
        self.pooled, self.index, self.dim = pooled, index, dim
        self.name = spec.name
        self.rerank = spec.rerank
        self.coarse = CoarseHash(index, dim) if self.rerank else None
        self.bytes_per_place = pooled.bytes_per_place + (self.coarse.bytes_per_place if self.coarse else 0.0)
        first = next(iter(pooled.codes.values()), None)
        if query_limit is None and first is not None and first.scans:  # a flat code scans every window
            query_limit = None if n_centres * pooled.n_ref <= SCAN_BUDGET else max(
                MIN_CENTRES, int(SCAN_BUDGET // pooled.n_ref))
        self.query_limit = query_limit

    @property
    def threads(self) -> int:
        return next((c.threads for c in self.pooled.codes.values()), 1)

    @threads.setter
    def threads(self, n: int) -> None:
        for codes in self.pooled.codes.values():
            codes.threads = n

    def columns(self) -> dict[str, Any]:
        codes = next(iter(self.pooled.codes.values()), None)
        params = [f"pooling={self.pooled.spec.pooling}"]
        if codes is not None and codes.ivf is not None:
            params.append(f"nprobe={codes.nprobe}")
        if self.rerank:
            params.append(f"rerank={self.rerank}")
        return {"d": None, "K": None, "params": " ".join(params)}  # d and K: CoarseHash's own rows

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        return [None] if L in self.pooled.codes else []

    def frames(self, rows: np.ndarray) -> PooledFrames:
        """The frames' rows as they are (a window is pooled when it is matched); with re-ranking,
        CoarseHash's hash and list look-up of every frame."""
        return PooledFrames(np.ascontiguousarray(rows, np.float32), self.coarse.frames(rows) if self.coarse else None)

    def localise(self, state: PooledFrames, pos: np.ndarray, L: int, mode: str | None,
                 n_best: int = N_BEST) -> Answer:
        codes = self.pooled.codes[L]
        k = self.rerank or n_best
        codes.set_point(k, codes.nprobe)
        dist, ids = codes.search(pool_windows(state.rows, pos, L, self.pooled.pooling))
        centres = self.pooled.centres(ids, L)
        n_r = (ids >= 0).sum(axis=1)
        ops = self.dim * L + codes.frame_ops()  # the pooling's adds, the pooled row's search
        if not self.rerank:
            return Answer(*top_columns(centres, dist, n_best), n_r, ops)
        scores = self.index.window_scores(state.coarse, pos, centres, L)
        order = np.lexsort((centres, scores), axis=1)[:, :n_best]  # by score, ties to the smaller centre
        top = np.where(np.take_along_axis(scores, order, 1) < NO_CANDIDATE,
                       np.take_along_axis(centres, order, 1), -1)
        best = np.take_along_axis(scores, order[:, :1], 1)[:, 0]
        score = np.where(top[:, 0] >= 0, best / float(self.index.delta_tables()[2]), np.inf)
        padded = np.full((len(top), n_best), -1, np.int64)
        padded[:, : top.shape[1]] = top
        coarse = method_ops(self.dim, self.index.d, self.index.k, L, float(k), self.index.occupied, 0.0)
        return Answer(padded, score, n_r, ops + coarse["total"] - coarse["candidate_lists"])


def create(context: Any) -> list[Algorithm]:
    """The registry's factory: one method per pooled descriptor compared (``--compare seq:…``),
    those of one pooling and code on one encoding."""
    return [PooledMethod(p, spec, context.index, context.dim, context.n_centres, context.compare_queries)
            for p in context.pooled for spec in p.specs]
