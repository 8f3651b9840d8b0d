"""FAISS compact codes (:mod:`vprscale.compared.faisscodes`) as evaluated methods."""

from __future__ import annotations

import sys
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import dask.array as da
import numba
import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vprscale.compared.faisscodes import FaissCodes, training_rows
from vprscale.evaluation.algorithms.base import Algorithm, Run, sequence_modes

SCAN_BUDGET = 2**35  # codes a run's frames may visit (~1 min of a flat 3-byte scan on 2 cores); beyond, a sample
MIN_SAMPLE = 16  # centres per run at least


def fit_codes(methods: list[FaissCodes], ref: da.Array, quiet: bool = False) -> None:
    """Train every method on the same evenly spaced references, then encode all of them in one
    streamed pass over ``ref`` (two reads of the references, whatever the number of methods).

    Each method trains on one thread (the methods side by side, on ``--workers`` threads):
    FAISS's OPQ and ITQ training give other rotations on other thread counts, and the codes
    must not depend on ``--workers``.
    """
    if not methods:
        return
    n_ref = ref.shape[0]
    sample = ref[training_rows(n_ref)].compute()
    with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(methods[0].threads) as pool:
        list(pool.map(partial(FaissCodes.train, sample=sample), methods))  # each on one thread of its own
    bar = tqdm(total=n_ref, desc="encode references", unit="row", unit_scale=True, file=sys.stderr,
               disable=True if quiet else None, leave=False)
    for m in methods:
        m.start(n_ref)
    for i in range(ref.numblocks[0]):
        x = np.asarray(ref.blocks[i].compute(), np.float32)
        for m in methods:
            m.encode(x)
        bar.update(len(x))
    for m in methods:
        m.finish()
    bar.close()


class FaissMethod(Algorithm):
    """One FAISS index: L = 1 is its top-1, L > 1 scores the window's candidates over the codes.

    Flat codes are searched exhaustively (every frame visits every place), so beyond a scan
    budget (``SCAN_BUDGET`` codes per run) a run localises an evenly spaced sample of centres.
    """

    def __init__(self, codes: FaissCodes, n_centres: int, max_L: int, query_limit: int | None) -> None:
        super().__init__()
        self.codes = codes
        self.name = codes.name
        self.bytes_per_place = codes.bytes_per_place
        if query_limit is None:
            scan = codes.scan_per_frame() * max_L
            query_limit = None if n_centres * scan <= SCAN_BUDGET else max(MIN_SAMPLE, int(SCAN_BUDGET // scan))
        self.query_limit = query_limit
        self.ids = np.zeros((0, codes.k), np.int64)
        self.tables = np.zeros((0, 1, 1), np.float32)
        self.q_vectors = np.zeros((0, 0), np.float32)

    def columns(self) -> dict[str, Any]:
        return {"d": None, "K": None, "params": self.codes.params}

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        return sequence_modes(L, requested)

    def frame_threads(self) -> int:
        return self.codes.threads

    def _warm(self, rows: np.ndarray) -> None:
        self.codes.search(rows)

    def _prepare(self, noise: str, rows: np.ndarray) -> None:
        """Each frame's top-k by FAISS's search, and its terms of the window scores."""
        _, self.ids = self.codes.search(rows)
        self.tables, self.q_vectors = self.codes.frame_terms(rows)

    def localise(self, t: np.ndarray, L: int, mode: str | None, truth: np.ndarray) -> Run:
        pos = self.window_positions(t, L)
        frame_ops = self.codes.frame_ops()
        if L == 1:
            ids = self.ids[pos]
            found = ids >= 0
            error = np.where(found, np.abs(ids - truth[:, None]), np.iinfo(np.int64).max)
            return Run(ids[:, 0], found.sum(axis=1), self.us_per_frame, self.us_per_frame, frame_ops,
                       error.min(axis=1) if ids.shape[1] else np.full(len(t), np.iinfo(np.int64).max))
        args = (L, mode == "aligned", self.ids, self.tables, self.q_vectors)
        self.codes.match(pos[:1], *args)  # compile outside the timing
        t0 = time.perf_counter()
        match, n_r = self.codes.match(pos, *args)
        us = (time.perf_counter() - t0) * numba.get_num_threads() / max(1, len(pos)) * 1e6 + self.us_per_frame
        n_r_mean = float(n_r.mean()) if len(n_r) else 0.0
        return Run(match, n_r, us, self.us_per_frame, frame_ops + L * n_r_mean * self.codes.pair_ops())
