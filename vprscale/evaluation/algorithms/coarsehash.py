"""CoarseHash (docs/method.md) as an evaluated method: one index, paper and aligned modes."""

from __future__ import annotations

from typing import Any

import numpy as np

from vprscale.evaluation.accounting import method_ops
from vprscale.evaluation.algorithms.base import Algorithm, Answer, sequence_modes
from vprscale.method.index import Index, QueryFrames
from vprscale.method.invlists import in_list_distance
from vprscale.method.kernels import N_BEST
from vprscale.protocol import window_mask


class CoarseHash(Algorithm):
    """The method of the paper on a loaded index; its frame state is the index's
    :class:`~vprscale.method.index.QueryFrames`."""

    name = "coarsehash"
    family = "hashing"
    timed_side_by_side = True

    def __init__(self, index: Index, dim: int) -> None:
        self.index, self.dim = index, dim
        self.bytes_per_place = self._bytes_per_place()

    def _bytes_per_place(self) -> float:
        """What the engine holds per place: the codes (⌈d·log2 K⌉ bits, the bit planes the
        windows are scored on) and the inverted lists (packed ids, Elias–Fano directory)."""
        idx = self.index
        return float((idx.codes.nbytes + sum(idx.lists.nbytes().values())) / max(1, idx.n_ref))

    def columns(self) -> dict[str, Any]:
        return {"d": self.index.d, "K": self.index.k, "params": None}

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        return sequence_modes(L, requested)

    def frames(self, rows: np.ndarray) -> QueryFrames:
        """Hash, nearest occupied address, list retrieval and bit planes of every frame."""
        h, errors = self.index.hash_frames(rows)
        return self.index.query_frames(h, errors=errors)

    def localise(self, state: QueryFrames, pos: np.ndarray, L: int, mode: str | None,
                 n_best: int = N_BEST) -> Answer:
        top, score, n_r = self.index.answer(state, pos, L, mode, n_best, window_mask(self.ref_windows, L))
        return Answer(top, score, np.asarray(n_r, np.int64), self._ops(state, pos, L, n_r))

    def _ops(self, state: QueryFrames, pos: np.ndarray, L: int, n_r: np.ndarray) -> float:
        """Counted operations per query, with the share of frames whose own address was unoccupied."""
        fallback = float(np.mean(state.taken[pos] != state.hashes[pos])) if len(pos) else 0.0
        return method_ops(self.dim, self.index.d, self.index.k, L, float(np.mean(n_r)) if len(n_r) else 0.0,
                          self.index.occupied, fallback)["total"]

    def in_list(self, state: QueryFrames, pos: np.ndarray, truth: np.ndarray) -> np.ndarray:
        return in_list_distance(state.start, state.stop, state.ids, np.asarray(pos, np.int64), truth)


def create(context: Any) -> list[Algorithm]:
    """The registry's factory: CoarseHash on the evaluated index, always."""
    return [CoarseHash(context.index, context.dim)]
