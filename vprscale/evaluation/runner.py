"""The runner: it calls every method's per-frame work and localisation, and it alone times them.

Two figures come out of each call (docs/accounting.md, "How times are measured"):

- **cost per query per core** (``us_per_query``): the CPU time of the thread that did the
  work, with the method on one thread, per query, plus the per-frame work once (the cost of
  one new frame and its match in a sliding deployment). CPU time of one thread does not
  move with ``--workers`` or with other load on the machine, as wall time does. It is
  measured ``repeats`` times on an evenly spaced sample of at most ``TIMED_QUERIES`` centres
  and ``TIMED_FRAMES`` frames, and when each costs much — a flat scan, the baseline's scan
  of every place — as many as fit in ``TIMED_SECONDS`` of CPU, at least ``MIN_TIMED``
  (``timed_queries`` and ``timed_frames`` say how many), and reported as the median with the smallest and largest
  (``us_per_query_lo``, ``us_per_query_hi``). ``us_per_match`` is the median of the match
  alone (the window scores, without the per-frame work): where a frame costs thousands of
  times a match (a flat scan), ``us_per_query − us_per_frame`` is a small difference of two
  noisy figures, and the match's own cost is read here. The timed calls ask for
  the match and its score only (``n_best = 1``), what a deployed localiser answers; the
  20 best candidates the evaluation also records (for Recall@N) come from the answering
  call, untimed (keeping them costs CoarseHash 1.3–1.7× at 10M, which would be charged to
  the method rather than to the evaluation);
- **throughput** (``queries_per_s``): queries per second of wall time on all ``--workers``,
  from the call that produced the answers (for a method whose answers' frame state comes by
  a cheaper exact route, ``Algorithm.answers_apart``, its per-frame wall is its timed CPU
  per frame over the workers: the deployed work, not the evaluation's shortcut).

Only the timed kernels are repeated, never the whole grid; each is run once on one centre
first, so that compilation is never timed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from vprscale.evaluation.algorithms.base import Algorithm, Answer
from vprscale.method.kernels import N_BEST

TIMED_QUERIES = 1024  # centres a timing repeat localises (evenly spaced; all when there are fewer)
TIMED_FRAMES = 256  # frames a timing repeat works on, at most
# Fewer when each costs much (FAISS's flat scans: 30-60 ms a frame at 10M, 10x that at 100M; the
# baseline's scan, 15 ms a centre at 10M): as many as fit in TIMED_SECONDS of CPU a repeat, at least
# MIN_TIMED, judged from PROBED of them
TIMED_SECONDS = 1.0
MIN_TIMED = 16
PROBED = 8
DEFAULT_REPEATS = 3
# The results columns that measure the machine rather than the method's answers: everything
# else in an evaluation's tables is the same bytes for the same inputs, whatever the workers.
TIMING_COLUMNS = ("us_per_query", "us_per_query_lo", "us_per_query_hi", "us_per_frame", "us_per_match",
                  "queries_per_s", "timed_queries", "timed_frames")


def spread(n: int, limit: int | None) -> np.ndarray:
    """``limit`` evenly spaced positions of ``n`` (all when there are no more)."""
    if limit is None or n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


@dataclass
class FrameCost:
    """The per-frame work's cost: CPU µs per frame of each repeat, and wall µs per frame on all workers."""

    cpu_us: list[float]
    wall_us: float
    frames: int  # frames each repeat timed


@dataclass
class Timing:
    """The timing columns of one run (see the module's docstring)."""

    us_per_query: float
    us_per_query_lo: float
    us_per_query_hi: float
    us_per_frame: float
    us_per_match: float
    queries_per_s: float
    repeats: int
    timed_queries: int
    timed_frames: int

    def columns(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _cpu_us(fn: Callable[[], Any], n: int) -> float:
    """CPU µs of the calling thread per item while ``fn()`` runs."""
    t0 = time.thread_time()
    fn()
    return (time.thread_time() - t0) / max(1, n) * 1e6


def _timed(n: int, limit: int, cost_us: Callable[[np.ndarray], float]) -> np.ndarray:
    """Positions of ``n`` items a timing repeat works on: evenly spaced, at most ``limit``, as
    many as fit in ``TIMED_SECONDS`` of CPU at ``cost_us`` (CPU µs an item of the positions
    given, probed on ``PROBED`` of them), at least ``MIN_TIMED``."""
    probe = cost_us(spread(n, PROBED))
    fit = int(TIMED_SECONDS * 1e6 / max(probe, 1e-3))
    return spread(n, min(limit, max(MIN_TIMED, fit)))


class Runner:
    """Runs methods on ``workers`` threads for their answers, and on one thread for their costs."""

    def __init__(self, workers: int, repeats: int = DEFAULT_REPEATS) -> None:
        if repeats < 1:
            raise ValueError(f"repeats = {repeats}: must be at least 1")
        self.workers, self.repeats = workers, repeats
        self._timing: ThreadPoolExecutor | None = None  # the threads timing repeats run on side by side

    @contextmanager
    def _threads(self, alg: Algorithm, n: int) -> Iterator[None]:
        before = numba.get_num_threads(), alg.threads
        numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
        alg.threads = n
        try:
            yield
        finally:
            numba.set_num_threads(before[0])
            alg.threads = before[1]

    def _repeated(self, alg: Algorithm, measure: Callable[[], float]) -> list[float]:
        """``repeats`` results of ``measure`` (a CPU time of the calling thread, with the method on
        one thread): side by side on up to ``workers`` threads when the method allows it
        (:attr:`~vprscale.evaluation.algorithms.base.Algorithm.timed_side_by_side`); what another
        thread does meanwhile does not enter a thread's own CPU time."""
        if not alg.timed_side_by_side or min(self.workers, self.repeats) == 1:
            return [measure() for _ in range(self.repeats)]
        if self._timing is None:  # kept: a fresh thread's first calls cost more than a warm one's
            self._timing = ThreadPoolExecutor(min(self.workers, self.repeats), thread_name_prefix="timing",
                                              initializer=numba.set_num_threads, initargs=(1,))
        return list(self._timing.map(lambda _: measure(), range(self.repeats)))

    def frames(self, alg: Algorithm, rows: np.ndarray) -> tuple[Any, FrameCost]:
        """The method's frame state for ``rows``, and what the per-frame work cost."""
        with self._threads(alg, 1):
            alg.frames(rows[:1])  # compile and load outside the timing
        with self._threads(alg, self.workers):
            t0 = time.perf_counter()
            state = alg.answer_frames(rows)
            wall = (time.perf_counter() - t0) / max(1, len(rows)) * 1e6
        with self._threads(alg, 1):
            sample = rows[_timed(len(rows), TIMED_FRAMES, lambda p: _cpu_us(lambda: alg.frames(rows[p]), len(p)))]
            cpu = self._repeated(alg, lambda: _cpu_us(lambda: alg.frames(sample), len(sample)))
        if alg.answers_apart:  # the state came by another route: the deployed work's wall, on all workers
            wall = float(np.median(cpu)) / self.workers
        return state, FrameCost(cpu, wall, len(sample))

    def localise(self, alg: Algorithm, state: Any, pos: np.ndarray, L: int, mode: str | None,
                 frame: FrameCost) -> tuple[Answer, Timing]:
        """The method's answers for the centres at ``pos``, and their timing columns."""
        with self._threads(alg, 1):
            alg.localise(state, pos[:1], L, mode, 1)  # compile outside the timing
        with self._threads(alg, self.workers):
            t0 = time.perf_counter()
            answer = alg.localise(state, pos, L, mode, N_BEST)
            wall = time.perf_counter() - t0
        with self._threads(alg, 1):  # the match and its score, as deployed (the 20-best list is the evaluation's)
            sample = pos[_timed(len(pos), TIMED_QUERIES,
                                lambda p: _cpu_us(lambda: alg.localise(state, pos[p], L, mode, 1), len(p)))]
            match = self._repeated(alg, lambda: _cpu_us(lambda: alg.localise(state, sample, L, mode, 1), len(sample)))
        per_query = [m + f for m, f in zip(match, frame.cpu_us, strict=True)]
        n = len(pos)
        seconds = wall + n * frame.wall_us * 1e-6
        timing = Timing(float(np.median(per_query)), float(min(per_query)), float(max(per_query)),
                        float(np.median(frame.cpu_us)), float(np.median(match)),
                        n / seconds if n and seconds > 0 else float("nan"), self.repeats, len(sample), frame.frames)
        return answer, timing
