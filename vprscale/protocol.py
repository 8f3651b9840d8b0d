"""Which query centres an evaluation localises (the protocol of ``docs/protocol.md``).

Centres are ``t = 0, z, 2z, …`` with a ground truth and the whole window of ``L`` frames
inside the query set. At 10M places and beyond that stride leaves only a handful of
centres in the FAS part (3 at 10M), whose curves would mean nothing; the FAS part is then
sampled with a stride of its own, the largest that gives it at least ``MIN_FAS`` centres.
Such a stratified sample no longer has the parts in their proportions, so the overall
figure weights each part by its share of the query rows (:func:`part_weights`).

The same function decides which query rows a compact store keeps (the windows of the
centres) and which centres an evaluation of that store localises, so the two agree.

This module is the protocol's one home: its constants (part codes, the evaluated lengths,
``MIN_FAS``) and its window arithmetic. It imports nothing of vprscale's, so the method,
the dataset build and the evaluation all read the same definitions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

MIN_FAS = 200  # FAS centres at least, per sequence length
DEEP1B, FAS = 0, 1  # part codes of ``ref_part`` / ``query_part``
PARTS = {"all": None, "deep1b": DEEP1B, "fas": FAS}  # the parts results are reported for (None: every row)
EVAL_LENGTHS = (1, 50, 100)  # the paper's sequence lengths: the default grid, and the windows a compact store keeps
SEQUENCE_MODES = ("paper", "aligned")
MAX_BEST = 1 << 10  # candidates a window's best-first list may keep online (localise --top)


def check_window(L: int, mode: str) -> None:
    """A sequence length and mode the matchers accept (ValueError naming the one that is not)."""
    if mode not in SEQUENCE_MODES:
        raise ValueError(f"mode = {mode!r}: choose 'paper' or 'aligned'")
    if isinstance(L, bool) or not isinstance(L, int | np.integer) or L < 1:
        raise ValueError(f"L = {L!r}: must be a positive integer")


def window_start(t: np.ndarray | int, L: int) -> np.ndarray | int:
    """First frame of the window of ``L`` centred on ``t``: ``t − ⌊L/2⌋`` (docs/method.md)."""
    return t - L // 2


def centre_lag(L: int) -> int:
    """Frames between a window's centre and its last frame: a window completed by frame u is centred on u − lag."""
    return L - 1 - L // 2


@dataclass(frozen=True)
class Centres:
    """The centres for one sequence length, and whether the FAS part has its own stride."""

    t: np.ndarray
    fas_stride: int | None  # None: the FAS part follows the common stride


class Sequences:
    """Rows that are many sequences (drives, MSLS ``sequence_key``s), each with frame numbers.

    A window of ``L`` frames is ``L`` consecutive rows of one sequence whose frame numbers
    follow one another; a window that would cross from one sequence into the next, or over a
    gap in the frame numbers, does not exist. Rows are cut into *runs*, the longest stretches
    of rows that are one sequence with consecutive frame numbers; a window exists where it
    lies inside one run. Single-traverse data has no :class:`Sequences` (None), and its
    windows are any ``L`` consecutive rows, as the paper's.
    """

    def __init__(self, sequence: np.ndarray, frame: np.ndarray) -> None:
        sequence, frame = np.asarray(sequence, np.int64), np.asarray(frame, np.int64)
        if sequence.shape != frame.shape or sequence.ndim != 1:
            raise ValueError(f"sequence ids {sequence.shape} and frame numbers {frame.shape} must be one per row")
        self.n = len(sequence)
        cut = np.ones(self.n, bool)  # a run starts at row 0 and wherever the sequence or the frame count breaks
        cut[1:] = (sequence[1:] != sequence[:-1]) | (frame[1:] != frame[:-1] + 1)
        starts = np.flatnonzero(cut)
        self.runs = len(starts)
        run = np.cumsum(cut) - 1
        self.run_start = starts[run]  # first row of each row's run
        self.run_stop = np.append(starts[1:], self.n)[run]  # one past its last row
        self._masks: dict[int, np.ndarray] = {}

    def window_ok(self, t: np.ndarray, L: int) -> np.ndarray:
        """Whether the window of ``L`` centred on each row ``t`` exists (``t`` in ``[0, n)``)."""
        t = np.asarray(t, np.int64)
        first = window_start(t, L)
        return (first >= self.run_start[t]) & (first + L <= self.run_stop[t])

    def mask(self, L: int) -> np.ndarray:
        """One byte a row, 1 where the window of ``L`` centred there exists: what the matchers
        read to never form, score or return a window that does not (kept per ``L``)."""
        if L not in self._masks:
            self._masks[L] = self.window_ok(np.arange(self.n, dtype=np.int64), L).astype(np.uint8)
        return self._masks[L]

    def missing(self, L: int) -> int:
        """Rows on which no window of ``L`` can be centred (near a sequence's ends or a gap)."""
        return int(self.n - self.mask(L).sum())


NO_MASK = np.zeros(0, np.uint8)  # single-traverse data: every window inside the map exists


class WindowMask(Protocol):
    """What the matchers read of a map's windows: a byte a place for each L (:class:`Sequences`,
    or a task's answerable centres)."""

    def mask(self, L: int) -> np.ndarray: ...


def window_mask(sequences: WindowMask | None, L: int) -> np.ndarray:
    """The matchers' mask of centres whose window of ``L`` exists (``NO_MASK``: all of them)."""
    return NO_MASK if sequences is None or L == 1 else sequences.mask(L)


def _valid(t: np.ndarray, gt_at: Callable[[np.ndarray], np.ndarray], n_query: int, L: int,
           sequences: Sequences | None = None) -> np.ndarray:
    first = window_start(t, L)
    t = t[(first >= 0) & (first + L <= n_query)]
    if sequences is not None:
        t = t[sequences.window_ok(t, L)]
    return t[gt_at(t) >= 0]


def query_centres(gt_at: Callable[[np.ndarray], np.ndarray], n_query: int, n_deep: int, z: int,
                  L: int, sequences: Sequences | None = None) -> Centres:
    """The evaluated centres for sequences of ``L``; ``gt_at(t)`` is the truth of frames ``t`` (−1: none).
    With the query rows' ``sequences``, a centre whose window crosses a sequence's end or a gap is none."""
    common = _valid(np.arange(0, n_query, z, dtype=np.int64), gt_at, n_query, L, sequences)
    n_fas = n_query - n_deep
    if n_fas == 0 or int((common >= n_deep).sum()) >= MIN_FAS:
        return Centres(common, None)
    stride = max(1, n_fas // MIN_FAS)
    while True:
        fas = _valid(np.arange(n_deep, n_query, stride, dtype=np.int64), gt_at, n_query, L, sequences)
        if len(fas) >= MIN_FAS or stride == 1:
            break
        stride -= 1
    return Centres(np.concatenate([common[common < n_deep], fas]), stride)


def part_weights(n_query: int, n_deep: int) -> dict[str, float]:
    """Each part's share of the query rows: the weights of a stratified overall figure."""
    return {"deep1b": n_deep / n_query, "fas": (n_query - n_deep) / n_query}


def window_frames(centres: list[np.ndarray], lengths: list[int]) -> np.ndarray:
    """Every query frame inside some evaluated window (ascending)."""
    frames = [(window_start(c[:, None], L) + np.arange(L)[None, :]).ravel()
              for c, L in zip(centres, lengths, strict=True)]
    return np.unique(np.concatenate(frames)) if frames else np.empty(0, np.int64)


def window_positions(frames: np.ndarray, t: np.ndarray, L: int) -> np.ndarray:
    """Positions of frames ``t`` among the held ``frames`` (ascending), each with the whole
    window of ``L`` centred on it held, so that a window's frames are consecutive positions."""
    t = np.asarray(t, np.int64)
    pos = np.searchsorted(frames, t)
    first, last = pos - L // 2, pos - L // 2 + L - 1
    ok = (first >= 0) & (last < len(frames))
    ok[ok] &= (frames[first[ok]] == t[ok] - L // 2) & (frames[last[ok]] == t[ok] - L // 2 + L - 1)
    if not ok.all():
        raise ValueError(f"frame {t[~ok][0]}: its window of {L} is not among the query frames held")
    return pos
