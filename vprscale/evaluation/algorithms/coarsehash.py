"""CoarseHash (docs/method.md) as an evaluated method: one index, paper and aligned modes."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numba
import numpy as np

from vprscale.evaluation.accounting import method_ops
from vprscale.evaluation.algorithms.base import Algorithm, Run, sequence_modes
from vprscale.method.engine import Index, QueryFrames
from vprscale.method.kernels import in_list_distance, match_batch


class CoarseHash(Algorithm):
    """The method of the paper on a loaded index.

    Its paper-mode N_r at each L is also the baseline's candidate budget
    (:meth:`paper_n_r`), run even when paper mode itself is not reported.
    """

    name = "coarsehash"

    def __init__(self, index: Index, path: Path, dim: int) -> None:
        super().__init__()
        self.index, self.path, self.dim = index, path, dim
        self.qf: QueryFrames | None = None
        self.occupied = np.zeros(0, bool)
        self._paper: dict[int, Run] = {}
        self._centres: dict[int, np.ndarray] = {}
        self.bytes_per_place = self._bytes_per_place()

    def _bytes_per_place(self) -> float:
        """The map's code (⌈d·log2 K⌉ bits, the bit planes the windows are scored on) plus the
        inverted lists (ids, and per occupied address its address, offset and single best)."""
        idx = self.index
        lists = sum(np.asarray(a).dtype.itemsize * len(a) for a in (idx.ids, idx.addresses, idx.offsets, idx.best))
        return float(np.ceil(idx.d * np.log2(idx.k)) / 8 + lists / max(1, idx.n_ref))

    def columns(self) -> dict[str, Any]:
        return {"d": self.index.d, "K": self.index.k, "params": None}

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        return sequence_modes(L, requested)

    def _warm(self, rows: np.ndarray) -> None:
        self.index.query_frames(self.index.hash_queries(rows))

    def _prepare(self, noise: str, rows: np.ndarray) -> None:
        """Hash, nearest occupied address, list retrieval and bit planes of every frame."""
        h = self.index.hash_queries(rows)
        self.qf = self.index.query_frames(h, self.frames)
        self.occupied = self.index.addresses[self.qf.addr] == h
        self._paper, self._centres = {}, {}

    def localise(self, t: np.ndarray, L: int, mode: str | None, truth: np.ndarray) -> Run:
        idx, qf = self.index, self.qf
        assert qf is not None, "prepare() first"
        pos = qf.positions(t, L)
        self._centres[L] = t
        if L == 1:
            t0 = time.perf_counter()
            a = qf.addr[pos]
            match = idx.best[a]
            secs = time.perf_counter() - t0
            n_r = idx.offsets[a + 1] - idx.offsets[a]
            return self._run(match, n_r, secs, pos, L, in_list_distance(a, truth, idx.offsets, idx.ids))
        if mode == "paper" and L in self._paper:
            return self._paper[L]
        args = (L, mode == "aligned", *qf.kernel_args(), *idx.kernel_args())
        match_batch(pos[:1], *args)  # compile outside the timing
        t0 = time.perf_counter()
        match, n_r = match_batch(pos, *args)
        run = self._run(match, n_r, time.perf_counter() - t0, pos, L, None)
        if mode == "paper":
            self._paper[L] = run
        return run

    def paper_n_r(self, L: int) -> float:
        """Mean paper-mode N_r over the centres this method localised at ``L`` (paper mode is
        run now if it was not asked for)."""
        t = self._centres.get(L, np.zeros(0, np.int64))
        if L == 1 or not len(t):
            return 1.0
        if L not in self._paper:
            self.localise(t, L, "paper", np.zeros(len(t), np.int64))
        return float(self._paper[L].n_r.mean())

    def _run(self, match: np.ndarray, n_r: np.ndarray, secs: float, pos: np.ndarray, L: int,
             in_list: np.ndarray | None) -> Run:
        fallback = float(1 - self.occupied[pos].mean()) if len(pos) else 0.0
        ops = method_ops(self.dim, self.index.d, self.index.k, L, float(n_r.mean()) if len(n_r) else 0.0,
                         len(self.index.addresses), fallback)["total"]
        us = secs * numba.get_num_threads() / max(1, len(pos)) * 1e6 + self.us_per_frame
        return Run(np.asarray(match, np.int64), np.asarray(n_r, np.int64), us, self.us_per_frame, ops, in_list)
