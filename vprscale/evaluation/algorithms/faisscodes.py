"""FAISS compact codes (:mod:`vprscale.compared.faisscodes`) as evaluated methods."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from threading import Lock
from typing import Any

import dask.array as da
import numpy as np
from threadpoolctl import threadpool_limits

from vprscale.compared.faisscodes import FaissCodes, code_family, training_rows
from vprscale.core.progress import ChunkProgress, Timings
from vprscale.evaluation.algorithms.base import Algorithm, Answer, sequence_modes, top_columns
from vprscale.evaluation.runner import spread
from vprscale.method.kernels import N_BEST, ranked_lists
from vprscale.protocol import window_mask

SCAN_BUDGET = 2**35  # codes a run's frames may visit (~1 min of a flat 3-byte scan on 2 cores); beyond, a sample
MIN_CENTRES = 1000  # centres a run localises at least, whatever the budget (recall's 95 % interval within ±3 points)
MISSING = np.iinfo(np.int64).max  # in-list distance of a frame that retrieved nothing
CHECKED_FRAMES = 64  # frames on which an enumerable code's exact top-k is checked against FAISS's search


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
    timings = Timings(quiet)
    rows = training_rows(n_ref)
    with timings.stage(f"train {len(methods)} FAISS method(s) on {len(rows):,} references"):
        sample = ref[rows].compute()
        with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(methods[0].threads) as pool:
            list(pool.map(partial(FaissCodes.train, sample=sample), methods))  # each on one thread of its own
    with timings.stage(f"encode {n_ref:,} references"):
        progress = None if quiet else ChunkProgress("encode references", ref.numblocks[0])
        for m in methods:
            m.start(n_ref)
        for i in range(ref.numblocks[0]):
            x = np.asarray(ref.blocks[i].compute(), np.float32)
            for m in methods:
                m.encode(x)
            if progress:
                progress.update(1)
    # what needs every code, each method on a thread of its own (side by side: a graph links on one core)
    with timings.stage(f"finish {len(methods)} FAISS method(s): fast-scan copies, graph links, decoded vectors"):
        linking = [m for m in methods if m.finish_blocks]
        bar = (ChunkProgress("link graphs", sum(m.finish_blocks for m in linking), unit="blocks")
               if linking and not quiet else None)
        lock = Lock()

        def tick(n: int) -> None:
            with lock:
                bar.update(n)

        with ThreadPoolExecutor(methods[0].threads) as pool:
            list(pool.map(lambda m: m.finish(tick if bar and m.finish_blocks else None), methods))


def _bytes_digest(a: np.ndarray) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(a).tobytes(), digest_size=16).digest()


class SharedRanking:
    """The Recall@N ranking of one code at one ``nprobe``, shared by its operating points that
    differ only in k, each below ``N_BEST``: they all search the frames' top ``N_BEST`` and score
    the windows of those lists, the same work and the same answers whatever their k, so it is
    done once per noise level rather than once per k (in the quickstart, two values of k, it was
    a third of the evaluation's CPU). Held for the last frames searched only (a new noise level
    or sample replaces it); what the runner times (the match alone) never comes from here. The
    arrays handed out are shared: nothing downstream writes into an answer's ranking or state."""

    def __init__(self) -> None:
        self._frames = b""  # digest of the frames the held search is of
        self._found: tuple | None = None  # (dist, ids, ranking) of those frames at N_BEST
        self._answers: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def search(self, rows: np.ndarray, search: Callable[[], tuple[np.ndarray, np.ndarray]]) -> tuple:
        """``(dist, ids, ranking)`` of ``rows`` at ``N_BEST``: ``search()``'s, run once per frames."""
        digest = _bytes_digest(rows)
        if self._found is None or digest != self._frames:
            dist, ids = search()
            self._frames, self._answers = digest, {}
            self._found = dist, ids, ranked_lists(ids)
        return self._found

    def answer(self, ranking: tuple, pos: np.ndarray, L: int, mode: str | None, n_best: int,
               answer: Callable[[], Answer]) -> tuple[np.ndarray, np.ndarray]:
        """``(top, n_r)`` of the windows at ``pos`` over ``ranking``: ``answer()``'s, once per
        window set, when ``ranking`` is the one held (any other is answered, not kept)."""
        if self._found is None or ranking is not self._found[2]:
            got = answer()
            return got.top, got.n_r
        key = (_bytes_digest(pos), L, mode, n_best)
        if key not in self._answers:
            got = answer()
            self._answers[key] = got.top, got.n_r
        return self._answers[key]


class FaissMethod(Algorithm):
    """One FAISS index: L = 1 is its top-1, L > 1 scores the window's candidates over the codes.

    The frame state is each frame's top-k (FAISS's own search) and its terms of the window
    scores; for the answers, when k < ``N_BEST``, also each frame's top ``N_BEST``, from which
    the Recall@N ranking is drawn (the field's Recall@N ranks at least N candidates, whatever
    the operating point's k). FAISS searches flat codes exhaustively (every frame visits every place). Most
    (product quantisers with float tables, binary codes) are *enumerable*: the evaluation
    finds the same top-k by visiting code values in order of distance
    (:mod:`vprscale.compared.codesearch`), times FAISS's own search as deployed, and checks
    that the two agree (:meth:`prepare`); they localise every centre. The others (fast-scan
    PQ, decoded-vector codes) scan, so beyond a scan budget (``SCAN_BUDGET`` codes per run) a
    run localises an evenly spaced sample, never fewer than ``MIN_CENTRES`` centres: a recall
    from 34 centres (what the budget alone left at 10M) has a 95 % interval ±16 points wide,
    one from 1,000 about ±3; and ``flat_noise`` may run them on fewer noise levels.
    """

    timed_side_by_side = True

    def __init__(self, codes: FaissCodes, n_centres: int, max_L: int, query_limit: int | None,
                 k: int | None = None, nprobe: int | None = None, flat_noise: list[str] | None = None,
                 shared: SharedRanking | None = None) -> None:
        self.codes, self.shared = codes, shared
        self.name, self.family = codes.name, code_family(codes.factory)
        self.k, self.nprobe = k or codes.k, nprobe or codes.nprobe  # this operating point's query arguments
        self.bytes_per_place = codes.bytes_per_place
        self._apply()
        self.scans = codes.scans and not codes.enumerable  # its evaluation visits every code per frame
        self.answers_apart = codes.enumerable
        if query_limit is None and self.scans:  # an IVF frame visits a few lists: every centre
            scan = codes.scan_per_frame() * max_L
            query_limit = None if n_centres * scan <= SCAN_BUDGET else max(MIN_CENTRES, int(SCAN_BUDGET // scan))
        self.query_limit = query_limit
        self.noises = flat_noise if self.scans else None
        self._frame_ops = 0.0  # counted operations of a frame's search, at this point (a graph's walk varies)

    @property
    def threads(self) -> int:  # FAISS's searches run on the codes' threads
        return self.codes.threads

    @threads.setter
    def threads(self, n: int) -> None:
        self.codes.threads = n

    def _apply(self) -> None:
        """Set this operating point's k and nprobe on the codes (operating points share one trained index)."""
        self.codes.set_point(self.k, self.nprobe)

    def columns(self) -> dict[str, Any]:
        self._apply()
        return {"d": None, "K": None, "params": self.codes.params}

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        return sequence_modes(L, requested)

    def frames(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each frame's top-k by FAISS's search, and its terms of the window scores (the counted
        operations are the answers' search's, :meth:`answer_frames`: the runner times this one on
        several threads at once, and FAISS counts a graph's distances in one global tally)."""
        self._apply()
        return self._state(rows, *self.codes.search(rows))

    def _state(self, rows: np.ndarray, dist: np.ndarray, ids: np.ndarray, ranking: tuple | None = None) -> tuple:
        """The frame state of ``rows`` whose top-k are ``(dist, ids)``."""
        return ids, dist, ranked_lists(ids), self.codes.frame_terms(rows), ranking

    def _search(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The answers' top-k: for an enumerable flat code found without a scan
        (:meth:`~vprscale.compared.faisscodes.FaissCodes.exact_search`), else FAISS's search."""
        return self.codes.exact_search(rows) if self.answers_apart else self.codes.search(rows)

    def answer_frames(self, rows: np.ndarray) -> tuple:
        """:meth:`frames`'s state by :meth:`_search`, with the frames' top ``N_BEST`` for the
        Recall@N ranking when this point's k is smaller. One search at ``N_BEST`` gives both:
        a frame's top-k is the head of its top-``N_BEST`` (the same distances as a search at k;
        only places at exactly equal distances may come in another order), and the search,
        which dominates an IVF code's evaluation, is not run twice."""
        self.codes.set_point(max(self.k, N_BEST), self.nprobe)
        ranking = None
        if self.shared is not None:
            dist, ids, lists = self.shared.search(rows, lambda: self._search(rows))
        else:
            dist, ids = self._search(rows)
            lists = ranked_lists(ids) if self.k < N_BEST else None
        if self.k < N_BEST:
            ranking = ids, dist, lists
            dist, ids = np.ascontiguousarray(dist[:, : self.k]), np.ascontiguousarray(ids[:, : self.k])
        self._apply()
        state = self._state(rows, dist, ids, ranking)
        self._frame_ops = self.codes.frame_ops()
        return state

    def prepare(self, noise: str, frames: np.ndarray, rows: np.ndarray, centres: dict[int, np.ndarray]) -> None:
        """For an enumerable flat code: check on ``CHECKED_FRAMES`` frames that its exact top-k
        is FAISS's search's (the answers come from the one, the times from the other)."""
        if self.answers_apart:
            self._apply()
            self.codes.check_exact(rows[spread(len(rows), CHECKED_FRAMES)])

    def localise(self, state: tuple, pos: np.ndarray, L: int, mode: str | None, n_best: int = N_BEST) -> Answer:
        self._apply()
        ids, dist, lists, terms, ranking = state
        answer = self._answer(ids, dist, lists, terms, pos, L, mode, n_best)
        if ranking is not None and n_best > 1:
            ranked = partial(self._answer, *ranking, terms, pos, L, mode, n_best)
            if self.shared is not None:
                answer.ranked, answer.n_ranked = self.shared.answer(ranking[2], pos, L, mode, n_best, ranked)
            else:
                got = ranked()
                answer.ranked, answer.n_ranked = got.top, got.n_r
        return answer

    def _answer(self, ids: np.ndarray, dist: np.ndarray, lists: tuple, terms: Any, pos: np.ndarray, L: int,
                mode: str | None, n_best: int) -> Answer:
        """The answers from the frames' lists ``ids`` (and their ``dist``): L = 1 FAISS's own
        ranking and distances, L > 1 the window scores of the lists' proposals."""
        if L == 1:
            return Answer(*top_columns(ids[pos], dist[pos], n_best), (ids[pos] >= 0).sum(axis=1), self._frame_ops)
        top, scores, n_r = self.codes.match(pos, L, mode == "aligned", lists, terms, n_best,
                                            window_mask(self.ref_windows, L))
        n_r_mean = float(n_r.mean()) if len(n_r) else 0.0
        return Answer(top, scores[:, 0], n_r, self._frame_ops + L * n_r_mean * self.codes.pair_ops())

    def in_list(self, state: tuple, pos: np.ndarray, truth: np.ndarray) -> np.ndarray:
        ids = state[0][pos]
        error = np.where(ids >= 0, np.abs(ids - truth[:, None]), MISSING)
        return error.min(axis=1) if ids.shape[1] else np.full(len(pos), MISSING)


def create(context: Any) -> list[Algorithm]:
    """The registry's factory: one method per FAISS code the evaluation compares (``--compare``) and
    operating point (every ``--faiss-k``, with every ``--faiss-nprobe`` for IVF codes), in that order;
    the points of a code at one nprobe whose k are below ``N_BEST`` share their ranking
    (:class:`SharedRanking`) when there are several."""
    found: list[Algorithm] = []
    for codes in context.compared:
        nprobes = (context.faiss_nprobe or [codes.nprobe]) if codes.ivf is not None else [codes.nprobe]
        ks = context.faiss_k or [codes.k]
        below = sum(k < N_BEST for k in ks) > 1
        shared = {n: SharedRanking() if below else None for n in nprobes}
        for k in ks:
            found += [FaissMethod(codes, context.n_centres, max(context.lengths), context.compare_queries, k, n,
                                  context.flat_noise, shared[n] if k < N_BEST else None) for n in nprobes]
    return found
