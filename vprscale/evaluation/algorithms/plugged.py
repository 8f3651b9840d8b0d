"""Your own method under the protocol (docs/bring-your-own.md): a small contract, like
big-ann-benchmarks' ``BaseANN``, and the adapter that makes it an evaluated method.

A method is any class (or callable returning an object) with:

- ``fit(ref)``: learn from, and store, the reference rows (a Dask array of float32 rows,
  id = row; call ``ref.compute()`` if it fits in memory, or stream ``ref.blocks``);
- ``query(frames, k) -> (ids, distances)``: each query row's ``k`` best references, best
  first, as two ``(len(frames), k)`` arrays, ids −1 (distance ignored) where fewer were
  found; distances are the method's own dissimilarity, lower is better;
- optionally ``pair_distances(frames, ref_ids) -> distances``: the dissimilarity of each
  row of ``frames`` to the one reference ``ref_ids[i]`` (same units as ``query``);
  without it the method is evaluated at L = 1 only;
- optionally ``name`` (the ``method`` column; default: the ``module:Class`` it was loaded
  as), ``family`` (the ``family`` column, e.g. ``graph``; default ``own``) and
  ``bytes_per_place`` (what it stores per place; NaN when absent).

The runner does the rest, as for the built-in methods: it times ``query`` as the
per-frame work and the window scores as the per-query work (CPU time of one thread, BLAS
held to that thread); L = 1 is the top-1 of ``query``; a sequence of L frames takes as
candidates the union of its frames' top-k (paper mode) or the centres their members imply
(aligned mode), and scores each centre ``c`` with ``Σ_l pair_distance(y_{t+l}, c + l)``,
a reference outside the map costing the window's largest distance, as for FAISS codes.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from vprscale.core.errors import InputError
from vprscale.evaluation.algorithms.base import Algorithm, Answer, sequence_modes, top_columns
from vprscale.method.kernels import N_BEST, ranked_lists, window_proposals
from vprscale.protocol import window_mask

PAIR_BLOCK = 1 << 18  # (frame, reference) pairs handed to pair_distances at a time (their rows: ~100 MB)


def with_working_directory() -> None:
    """Let ``--method`` name modules of the working directory (as ``python -m`` would), not
    only installed ones: the ``vprscale`` command does not put it on ``sys.path``."""
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())


def load_method(spec: str, installed: dict[str, str] | None = None) -> tuple[str, Any]:
    """``(label, method)``: a new instance of ``package.module:Class`` (a module installed or
    in the working directory; or an installed method's entry point, by name), checked for
    the contract's two required methods."""
    with_working_directory()
    target = (installed or {}).get(spec, spec)
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise InputError(f"--method {spec}: give package.module:Class, or the name of an installed method")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"--method {spec}: cannot be loaded ({exc})") from None
    if not isinstance(cls, type):  # never call an arbitrary function (os:system) to make a method
        raise InputError(f"--method {spec}: {module}.{attr} is a {type(cls).__name__}, not a class "
                         "(docs/bring-your-own.md)")
    try:
        method = cls()
    except Exception as exc:  # noqa: BLE001 - the user's constructor: its failure is the input's
        raise InputError(f"--method {spec}: {attr}() failed ({type(exc).__name__}: {exc})") from None
    missing = [m for m in ("fit", "query") if not callable(getattr(method, m, None))]
    if missing:
        raise InputError(f"--method {spec}: {type(method).__name__} has no {' or '.join(missing)} method "
                         "(docs/bring-your-own.md)")
    return str(getattr(method, "name", spec)), method


def check_found(label: str, ids: Any, dist: Any, n: int, k: int, n_ref: int) -> tuple[np.ndarray, np.ndarray]:
    """``query``'s answer as arrays, or a one-line error naming what is wrong with it."""
    ids, dist = np.asarray(ids), np.asarray(dist, np.float64)
    if ids.shape != (n, k) or dist.shape != (n, k):
        raise InputError(f"method {label}: query returned ids {ids.shape} and distances {dist.shape}; "
                         f"({n}, {k}) each expected")
    if not np.issubdtype(ids.dtype, np.integer):
        raise InputError(f"method {label}: query returned {ids.dtype} ids; integers expected")
    ids = ids.astype(np.int64)
    if ((ids < -1) | (ids >= n_ref)).any():
        raise InputError(f"method {label}: query returned an id outside −1 … {n_ref - 1:,}")
    if np.isnan(dist[ids >= 0]).any():
        raise InputError(f"method {label}: query returned a NaN distance")
    return ids, dist


class Plugged(Algorithm):
    """A method of the contract above as an evaluated method, at one ``k`` (its ``params``)."""

    def __init__(self, label: str, method: Any, k: int, n_ref: int, query_limit: int | None = None) -> None:
        self.name, self.method, self.k, self.n_ref, self.query_limit = label, method, k, n_ref, query_limit
        self.family = str(getattr(method, "family", "own"))
        self.bytes_per_place = float(getattr(method, "bytes_per_place", float("nan")))
        self.scores = callable(getattr(method, "pair_distances", None))

    def columns(self) -> dict[str, Any]:
        return {"d": None, "K": None, "params": f"k={self.k}"}

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        if L > 1 and not self.scores:
            return []  # no pair distances: no window scores
        return sequence_modes(L, requested)

    def frames(self, rows: np.ndarray) -> tuple:
        """``(rows, ids, distances, lists)``: each frame's top-k by the method's ``query``."""
        with threadpool_limits(limits=self.threads):
            ids, dist = self.method.query(np.ascontiguousarray(rows, np.float32), self.k)
        ids, dist = check_found(self.name, ids, dist, len(rows), self.k, self.n_ref)
        return rows, ids, dist, ranked_lists(ids)

    def answer_frames(self, rows: np.ndarray) -> tuple:
        """:meth:`frames`'s state, with the frames' top ``N_BEST`` for the Recall@N ranking
        when this point's k is smaller (a second ``query``)."""
        state = self.frames(rows)
        if self.k >= N_BEST:
            return state
        k, self.k = self.k, N_BEST
        try:
            return *state, self.frames(rows)
        finally:
            self.k = k

    def localise(self, state: tuple, pos: np.ndarray, L: int, mode: str | None, n_best: int = N_BEST) -> Answer:
        answer = self._answer(state[:4], pos, L, mode, n_best)
        if len(state) > 4 and n_best > 1:
            ranked = self._answer(state[4], pos, L, mode, n_best)
            answer.ranked, answer.n_ranked = ranked.top, ranked.n_r
        return answer

    def _answer(self, state: tuple, pos: np.ndarray, L: int, mode: str | None, n_best: int) -> Answer:
        rows, ids, dist, lists = state
        pos = np.asarray(pos, np.int64)
        if L == 1:
            return Answer(*top_columns(ids[pos], dist[pos], n_best), (ids[pos] >= 0).sum(axis=1), float("nan"))
        cand, first, n_r = window_proposals(pos, L, mode == "aligned", lists, self.n_ref,
                                            window_mask(self.ref_windows, L))
        with threadpool_limits(limits=self.threads):
            top, score = self._score(rows, pos, L, cand, first, n_r, n_best)
        return Answer(top, score, n_r, float("nan"))

    def _score(self, rows: np.ndarray, pos: np.ndarray, L: int, cand: np.ndarray, first: np.ndarray,
               n_r: np.ndarray, n_best: int) -> tuple[np.ndarray, np.ndarray]:
        """Best-first candidates and the best score of each window, in blocks of queries."""
        top = np.full((len(pos), n_best), -1, np.int64)
        score = np.full(len(pos), np.inf)
        offsets = np.arange(L) - L // 2
        ends = np.cumsum(n_r)  # each query's candidates, packed one after another
        starts = ends - n_r
        packed = cand[np.repeat(first[:-1] - starts, n_r) + np.arange(ends[-1] if len(ends) else 0)]
        lo = 0
        while lo < len(pos):  # queries whose pairs fill one block (at least one query)
            hi = max(lo + 1, int(np.searchsorted(ends, starts[lo] + PAIR_BLOCK // L, "right")))
            c = packed[starts[lo]:ends[hi - 1]]
            owner = np.repeat(np.arange(lo, hi), n_r[lo:hi])  # the query of each candidate
            r = c[:, None] + offsets[None, :]
            p = pos[owner][:, None] + offsets[None, :]
            inside = (r >= 0) & (r < self.n_ref)
            d = np.asarray(self.method.pair_distances(rows[p[inside]], r[inside]), np.float64)
            if d.shape != (int(inside.sum()),) or np.isnan(d).any():
                raise InputError(f"method {self.name}: pair_distances returned shape {d.shape} (or NaN); "
                                 f"one distance per pair, ({int(inside.sum())},), expected")
            pair_owner = np.broadcast_to(owner[:, None], r.shape)[inside]
            largest = np.zeros(hi, np.float64)
            np.maximum.at(largest, pair_owner, d)
            sums = np.bincount(np.broadcast_to(np.arange(len(c))[:, None], r.shape)[inside], d, len(c))
            s = sums + (L - inside.sum(axis=1)) * largest[owner]
            order = np.lexsort((c, s, owner))  # per query: by score, ties to the smaller centre
            rank = np.arange(len(c)) - np.repeat(starts[lo:hi] - starts[lo], n_r[lo:hi])
            keep = order[rank < n_best]
            top[owner[keep], rank[rank < n_best]] = c[keep]
            best = order[rank == 0]
            score[owner[best]] = s[best]
            lo = hi
        return top, score


def create(context: Any) -> list[Algorithm]:
    """The registry's factory: every ``--method`` the evaluation was given, at every k."""
    return [Plugged(label, method, k, context.index.n_ref, context.compare_queries)
            for label, method in context.plugged for k in context.method_k]
