"""The interface every evaluated method implements (docs/protocol.md, "Methods").

A method does two things, and the runner (:mod:`vprscale.evaluation.runner`) times both:

- :meth:`Algorithm.frames`: the per-frame work on query frames (hash and list look-up, a
  FAISS search, a projection), done once per frame and shared by every window that holds
  it; it returns whatever the method keeps of the frames (its *frame state*);
- :meth:`Algorithm.localise`: the match of each centre by sequences of ``L`` frames, read
  from the frame state.

Nothing here measures time: a method never times itself, so every method's figures mean the
same thing. Methods are found through the registry (:mod:`.registry`), never a hand-written
list in the grid.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from vprscale.method.kernels import N_BEST
from vprscale.protocol import SEQUENCE_MODES, WindowMask


@dataclass
class Answer:
    """One method's answers for the centres of one (noise, L, mode) (docs/protocol.md, "Scores").

    ``top`` holds each centre's best candidates, best first (as many columns as asked for,
    ``N_BEST`` in the answers; −1 where there were fewer; ``top[:, 0]`` is the match),
    ``score`` the match's score in the method's own units, lower meaning more confident.

    Recall@N is read from a ranking of at least N candidates, as the field reads it
    (docs/protocol.md, "Recall@N"): a method whose operating point weighs fewer (a FAISS
    code retrieving k = 2 per frame, the baseline's budget of one at L = 1) gives that
    ranking apart, as ``ranked`` (the ``N_BEST`` best of it, best first) with ``n_ranked``,
    the candidates it ranked per centre; otherwise its ``top`` is that ranking.
    """

    top: np.ndarray  # (centres, n_best) int64
    score: np.ndarray  # float64 per centre
    n_r: np.ndarray  # candidates scored per centre
    ops_per_query: float  # counted unitary operations per query (docs/accounting.md)
    ranked: np.ndarray | None = None  # (centres, N_BEST) int64: the Recall@N ranking, when not ``top``
    n_ranked: np.ndarray | None = None  # candidates that ranking weighed per centre

    @property
    def match(self) -> np.ndarray:
        """The matched reference id of each centre."""
        return self.top[:, 0]

    @property
    def ranking(self) -> tuple[np.ndarray, np.ndarray]:
        """``(best, weighed)``: the ranking Recall@N reads (its ``N_BEST`` best) and the
        candidates it weighed per centre."""
        if self.ranked is None:
            return self.top, self.n_r
        return self.ranked, self.n_r if self.n_ranked is None else self.n_ranked


class Algorithm(ABC):
    """A localisation method under the protocol.

    ``name`` is the ``method`` column of the results, ``family`` the kind of method it is (the
    ``family`` column: ``hashing``, ``PQ``, ``additive``, ``binary``, ``graph``, ``exact``,
    ``sequence descriptor``, ``baseline``, or a plugged method's own, ``own`` by default, as
    VIBE tags methods), :meth:`columns` its other identifying
    columns (``d``, ``K``, ``params``), ``bytes_per_place`` what it stores per place to
    answer a query. ``query_limit`` is the number of centres per run it localises (an
    evenly spaced sample; None: all), for methods whose every query scans the whole map;
    ``noises`` the noise levels it runs on (None: all the evaluation's).
    ``threads`` is how many threads the runner lets it use (1 while it is being timed).
    ``timed_side_by_side``: its :meth:`frames` and :meth:`localise` may run on several threads at
    once (no state they change, no process-wide setting), so the runner times its repeats side
    by side, each on a thread of its own (the built-in methods; a plugged one is timed one
    repeat after another).
    """

    name: str
    family: str = "own"
    bytes_per_place: float
    query_limit: int | None = None
    noises: list[str] | None = None
    threads: int = 1
    answers_apart: bool = False  # the answers' frame state comes from answer_frames, not frames
    timed_side_by_side: bool = False
    # A map of many sequences (None: one traverse): a centre whose window does not exist is never
    # a candidate, a scored centre or an answer (:func:`vprscale.protocol.window_mask` of it)
    ref_windows: WindowMask | None = None

    def runs_on(self, noise: str) -> bool:
        """Whether this method runs on query set ``noise`` (``noises``)."""
        return self.noises is None or noise in self.noises

    @abstractmethod
    def columns(self) -> dict[str, Any]:
        """``d``, ``K`` and ``params`` of this method's rows."""

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        """The modes this method reports at ``L`` (None: a method, or L, without modes)."""
        return [None]

    def prepare(self, noise: str, frames: np.ndarray, rows: np.ndarray,  # noqa: B027 - optional hook
                centres: dict[int, np.ndarray]) -> None:
        """Untimed set-up for one noise level, before any timed work (default: nothing).

        ``frames`` (ascending) and their descriptor ``rows`` are every frame of the
        evaluation, ``centres`` every centre of each L, before the method's own sample.
        """

    @abstractmethod
    def frames(self, rows: np.ndarray) -> Any:
        """The per-frame work on query descriptor ``rows`` (consecutive held frames, in order);
        returns the frame state that :meth:`localise` reads."""

    def answer_frames(self, rows: np.ndarray) -> Any:
        """The frame state the evaluation's answers are read from: :meth:`frames`'s.

        A method whose deployed per-frame work is costlier than needed to know its result
        (a flat code scans every place for what its code values' order gives exactly,
        :mod:`vprscale.compared.codesearch`) may compute the same state here by the cheaper
        route and set ``answers_apart``: the runner then times :meth:`frames` alone, as
        deployed, and the method checks in :meth:`prepare` that both routes agree."""
        return self.frames(rows)

    @abstractmethod
    def localise(self, state: Any, pos: np.ndarray, L: int, mode: str | None, n_best: int = N_BEST) -> Answer:
        """Match the centres at positions ``pos`` of the frame state (each with its whole
        window of ``L`` frames held, at consecutive positions) by sequences of ``L``, with
        each centre's ``n_best`` best candidates (the runner times ``n_best = 1``: the match
        and its score, as a deployed localiser answers)."""

    def in_list(self, state: Any, pos: np.ndarray, truth: np.ndarray) -> np.ndarray | None:
        """L = 1: each frame's distance from its truth to the nearest id it retrieved (the
        in-list bound); None for methods without lists. Untimed."""
        return None


def top_columns(ids: np.ndarray, distances: np.ndarray, n_best: int = N_BEST) -> tuple[np.ndarray, np.ndarray]:
    """``(top, score)`` of an L = 1 answer from a ranked search's ``(ids, distances)`` rows
    (−1 padded): its first ``n_best`` ids, −1 padded to that width, and the first distance
    (inf where nothing was found)."""
    ids = np.asarray(ids, np.int64).reshape(len(ids), -1)
    top = np.full((len(ids), n_best), -1, np.int64)
    top[:, : min(n_best, ids.shape[1])] = ids[:, :n_best]
    first = np.asarray(distances, np.float64).reshape(len(ids), -1)[:, 0] if ids.shape[1] else np.full(len(ids), np.inf)
    return top, np.where(top[:, 0] >= 0, first, np.inf)


def sequence_modes(L: int, requested: list[str]) -> list[str | None]:
    """:meth:`Algorithm.modes` of a method with paper and aligned modes."""
    return [None] if L == 1 else [m for m in SEQUENCE_MODES if m in requested]
