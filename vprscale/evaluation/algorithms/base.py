"""The interface every evaluated method implements (docs/protocol.md, "Methods").

The grid (:mod:`vprscale.evaluation.evaluate`) knows nothing of how a method works: per
noise level it hands each method the query frames it needs (:meth:`Algorithm.prepare`, the
per-frame work, timed) and then asks it to localise the centres of each sequence length and
mode (:meth:`Algorithm.localise`). Adding a method means adding a class, not editing the loop.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from vprscale.method.engine import window_positions

SEQUENCE_MODES = ("paper", "aligned")


@dataclass
class Run:
    """One method's answers for the centres of one (noise, L, mode)."""

    match: np.ndarray
    n_r: np.ndarray
    us_per_query: float  # per query per core, per-frame work included
    us_per_frame: float | None  # of which the per-frame work
    ops_per_query: float
    in_list: np.ndarray | None = None  # L = 1: distance from the truth to the nearest id the frame retrieved


class Algorithm(ABC):
    """A localisation method under the protocol.

    ``name`` is the ``method`` column of the results, ``columns`` its other identifying
    columns (``d``, ``K``, ``params``), ``bytes_per_place`` what it stores per place to
    answer a query. ``query_limit`` is the number of centres per run it localises (an
    evenly spaced sample; None: all), for methods whose every query scans the whole map.
    """

    name: str
    bytes_per_place: float
    query_limit: int | None = None

    def __init__(self) -> None:
        self.frames = np.zeros(0, np.int64)
        self.us_per_frame = 0.0

    @abstractmethod
    def columns(self) -> dict[str, Any]:
        """``d``, ``K`` and ``params`` of this method's rows."""

    def modes(self, L: int, requested: list[str]) -> list[str | None]:
        """The modes this method reports at ``L`` (None: a method, or L, without modes);
        methods with candidate lists report the requested sequence modes for L > 1."""
        return [None]

    def prepare(self, noise: str, frames: np.ndarray, rows: np.ndarray) -> None:
        """Do the per-frame work on query ``frames`` (ascending) with descriptors ``rows``."""
        self.frames = np.asarray(frames, np.int64)
        self._warm(rows[:1])
        t0 = time.perf_counter()
        self._prepare(noise, rows)
        self.us_per_frame = (time.perf_counter() - t0) * self.frame_threads() / max(1, len(frames)) * 1e6

    def frame_threads(self) -> int:
        """Threads the per-frame work runs on (its wall time × threads is its time per core)."""
        return 1

    @abstractmethod
    def _warm(self, rows: np.ndarray) -> None:
        """Compile or load what the per-frame work runs, outside its timing."""

    @abstractmethod
    def _prepare(self, noise: str, rows: np.ndarray) -> None:
        """The per-frame work itself (timed by :meth:`prepare`)."""

    def window_positions(self, t: np.ndarray, L: int) -> np.ndarray:
        """Positions of centres ``t`` among the prepared frames (their windows' frames consecutive)."""
        return window_positions(self.frames, t, L)

    @abstractmethod
    def localise(self, t: np.ndarray, L: int, mode: str | None, truth: np.ndarray) -> Run:
        """Match every centre ``t`` (prepared with their whole windows) by sequences of ``L``."""


def sequence_modes(L: int, requested: list[str]) -> list[str | None]:
    """:meth:`Algorithm.modes` of a method with paper and aligned modes."""
    return [None] if L == 1 else [m for m in SEQUENCE_MODES if m in requested]
