"""MSLS's tasks on a store of many sequences (docs/bring-your-own.md, "MSLS's tasks").

MSLS (Warburg et al., CVPR 2020) evaluates place recognition as four tasks: ``im2im`` (an image
against database images), ``seq2im`` (a query sequence against database images), ``im2seq``
and ``seq2seq``. A sequence is a window of ``seq_length`` (odd) frames of one sequence with
consecutive frame numbers, centred on a frame; a window whose centre is a panorama is left out,
and with a subtask (``s2w``: summer to winter, ``d2n``: day to night, …) so is one whose centre
is not in it, on either side. A database window is a *positive* of a query window when one of
its frames lies within the threshold (25 m) of one of the query's frames (same city); a query
with no positive is not evaluated. For the k = 1, 5, 10, 20 first answers of each query,
recall@k is the share of queries with a positive among them, and map@k the mean over queries of
``Σ_{i ≤ k, answer i a positive} (positives among the first i) / i``, divided by
``min(#positives, k)``: MSLS's ``evaluate.py``, whose prediction file
:func:`write_predictions` writes.

The positives are never listed: a query's count comes from the database frames within the
threshold (a grid per city, :mod:`vprscale.evaluation.positives`) and the windows that hold
them, and whether an answer is one from its frames' positions, so a task on 10M database
frames needs no query × database matrix.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from vprscale.core.errors import InputError
from vprscale.dataset.msls import SUBTASKS
from vprscale.evaluation.positives import Grid, grid, window_counts
from vprscale.protocol import Sequences

TASKS = ("im2im", "seq2im", "im2seq", "seq2seq")
KS = (1, 5, 10, 20)
QUERY_BLOCK = 1 << 12  # query windows whose positives are counted (or answers checked) at a time


def lengths(task: str, seq_length: int) -> tuple[int, int]:
    """``(query, database)`` window lengths of a task, as MSLS sets them."""
    if task not in TASKS:
        raise InputError(f"--task {task}: choose one of {', '.join(TASKS)}")
    if task == "im2im":
        return 1, 1
    if seq_length < 3 or seq_length % 2 == 0:
        raise InputError(f"--seq-length {seq_length}: {task} takes an odd sequence length of 3 or more")
    return {"seq2seq": (seq_length, seq_length), "seq2im": (seq_length, 1), "im2seq": (1, seq_length)}[task]


class Allowed:
    """The reference centres a task may answer, as the matchers read a map's windows
    (:attr:`vprscale.evaluation.algorithms.base.Algorithm.ref_windows`): one mask, whatever L."""

    def __init__(self, mask: np.ndarray) -> None:
        self._mask = np.ascontiguousarray(mask, np.uint8)

    def mask(self, L: int) -> np.ndarray:
        return self._mask


@dataclass
class Side:
    """One side of the store as a task reads it."""

    sequences: Sequences
    pos: np.ndarray | None
    city: np.ndarray
    pano: np.ndarray
    subtask: np.ndarray
    keys: np.ndarray  # (n, width) uint8

    @classmethod
    def read(cls, group: zarr.Group, side: str) -> Side:
        from vprscale.dataset.store import read_sequences

        n = group[f"{side}_seq"].shape[0]
        extra = {name: group[f"{side}_{name}"][:] if f"{side}_{name}" in group else default
                 for name, default in (("city", np.zeros(n, np.uint16)), ("pano", np.zeros(n, np.uint8)),
                                       ("subtask", np.ones(n, np.uint8)))}
        keys = group[f"{side}_key"][:] if f"{side}_key" in group else _row_keys(n)
        return cls(read_sequences(group, side), group[f"{side}_pos"][:] if f"{side}_pos" in group else None,
                   extra["city"], extra["pano"].astype(bool), extra["subtask"], keys)

    def kept(self, L: int, subtask: str) -> np.ndarray:
        """Centres of the windows of ``L`` a task keeps: the window exists, its centre is no
        panorama and belongs to ``subtask``."""
        bit = np.uint8(1 << SUBTASKS.index(subtask))
        exists = self.sequences.mask(L).astype(bool) if L > 1 else np.ones(self.sequences.n, bool)
        return exists & ~self.pano & ((self.subtask & bit) > 0)

    def key(self, rows: np.ndarray, L: int) -> list[str]:
        """MSLS's name of the windows of ``L`` centred on ``rows``: their frames' keys, comma-joined."""
        width = self.keys.shape[1]
        names = self.keys.view(f"S{width}").ravel()
        return [",".join(names[r].decode() for r in range(c - L // 2, c - L // 2 + L)) for c in rows]


def _row_keys(n: int) -> np.ndarray:
    """Row numbers as keys, for a store of your own without image keys."""
    text = np.char.encode(np.arange(n).astype(str))
    return text.view(np.uint8).reshape(n, -1) if n else np.zeros((0, 1), np.uint8)


class TaskSet:
    """One task on a store: its query windows (those with a positive), the database centres it
    may answer, and its positives (see the module's docstring)."""

    def __init__(self, group: zarr.Group, task: str, seq_length: int, subtask: str, threshold_m: float,
                 query: str = "query") -> None:
        if "ref_seq" not in group or f"{query}_seq" not in group:
            raise InputError("--task: the store holds no sequences; build it with --msls, or --ref-seq and --query-seq "
                             "(docs/bring-your-own.md)")
        if subtask not in SUBTASKS:
            raise InputError(f"--subtask {subtask}: choose one of {', '.join(SUBTASKS)}")
        if not threshold_m > 0:
            raise InputError(f"--threshold {threshold_m}: must be above 0 metres")
        self.task, self.subtask, self.threshold_m = task, subtask, float(threshold_m)
        self.q_len, self.db_len = lengths(task, seq_length)
        self.seq_length = 1 if task == "im2im" else seq_length
        self.db, self.q = Side.read(group, "ref"), Side.read(group, query)
        # a method matches the query's own windows (im2seq: single frames, answered by the database
        # window centred on each; seq2im: sequences, answered by their centre frames)
        self.match_length = self.q_len
        db_kept = self.db.kept(self.db_len, subtask)
        self.db_kept = db_kept  # database windows of the task: centres
        # what a method may answer: a kept database window's centre, which for seq2im must also
        # centre a window of the query's length (the matcher scores the query sequence against it)
        self.allowed = db_kept & (self.db.sequences.mask(self.q_len).astype(bool) if task == "seq2im" else True)
        centres = np.flatnonzero(self.q.kept(self.q_len, subtask))
        self.scored = self.db.pos is not None and self.q.pos is not None
        if self.scored:
            self._grids: dict[int, Grid] = {}
            half = self.db_len // 2  # the database frames inside some kept window, once for every city
            edges = np.zeros(len(db_kept) + 1, np.int64)
            kept = np.flatnonzero(db_kept)
            np.add.at(edges, kept - half, 1)
            np.add.at(edges, kept + half + 1, -1)
            self._covered = np.cumsum(edges)[:-1] > 0
            self._kept_before = np.cumsum(np.r_[0, db_kept.astype(np.int64)])  # kept centres before each row
            count = self.positives(centres)
            centres = centres[count > 0]  # MSLS evaluates only queries with a positive
            self.n_positives = count[count > 0]
        if not len(centres):
            raise InputError(f"--task {task} --subtask {subtask}: no query window of this store has one "
                             + ("(and a positive within the threshold)" if self.scored else ""))
        self.centres = centres

    def _grid(self, city: int) -> Grid:
        """The grid of the city's database frames that lie in a kept window (:mod:`.positives`)."""
        if city not in self._grids:
            rows = np.flatnonzero(self._covered & (self.db.city == city))
            self._grids[city] = grid(self.db.pos, rows, self.threshold_m)
        return self._grids[city]

    def positives(self, centres: np.ndarray) -> np.ndarray:
        """How many kept database windows are positives of each query window centred at ``centres``."""
        out = np.zeros(len(centres), np.int64)
        for city in np.unique(self.q.city[centres]):
            sel = np.flatnonzero(self.q.city[centres] == city)
            g = self._grid(int(city))
            out[sel] = window_counts(self.q.pos, centres[sel] - self.q_len // 2, self.q_len, g.keys, g.starts,
                                     g.members, g.origin, g.nx, g.ny, g.cell, self.db.pos, self._kept_before,
                                     self.db_len // 2, self.threshold_m)
        return out

    def hits(self, centres: np.ndarray, answers: np.ndarray) -> np.ndarray:
        """Whether each answer (database centre, −1: none) is a positive of its query window:
        one of its window's frames within the threshold of one of the query's, in the same city."""
        hq, hd = self.q_len // 2, self.db_len // 2
        found = answers >= 0
        a = np.where(found, answers, 0)
        qf = centres[:, None] - hq + np.arange(self.q_len)[None, :]  # (n, q_len)
        df = a[:, :, None] - hd + np.arange(self.db_len)[None, None, :]  # (n, k, db_len)
        df = np.clip(df, 0, len(self.db_kept) - 1)
        d = self.db.pos[df][:, :, :, None, :] - self.q.pos[qf][:, None, None, :, :]
        near = ((d**2).sum(axis=-1) <= self.threshold_m**2).any(axis=(2, 3))
        same = self.db.city[a] == self.q.city[centres][:, None]
        return found & near & same

    def metrics(self, centres: np.ndarray, answers: np.ndarray, n_positives: np.ndarray) -> dict[str, np.ndarray]:
        """Per query: whether a positive is among the first k (recall@k) and its average
        precision at k (map@k), for each k of ``KS``."""
        hit = np.concatenate([self.hits(centres[a : a + QUERY_BLOCK], answers[a : a + QUERY_BLOCK, : max(KS)])
                              for a in range(0, len(centres), QUERY_BLOCK)] or [np.zeros((0, max(KS)), bool)])
        first = np.cumsum(hit, axis=1)
        rank = np.arange(1, hit.shape[1] + 1)
        out = {}
        for k in KS:
            out[f"recall_at_{k}"] = first[:, : k].max(axis=1, initial=0) > 0
            out[f"map_at_{k}"] = (np.where(hit[:, :k], first[:, :k] / rank[:k], 0.0).sum(axis=1)
                                  / np.minimum(n_positives, k))
        return out


def keep_allowed(ranked: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """A ranking with the centres a task may not answer taken out, the rest moved up (−1 after)."""
    ok = (ranked >= 0) & allowed[np.maximum(ranked, 0)]
    order = np.argsort(~ok, axis=1, kind="stable")
    out = np.take_along_axis(np.where(ok, ranked, -1), order, axis=1)
    return out


def write_predictions(path: Path, task: TaskSet, centres: np.ndarray, answers: np.ndarray) -> int:
    """MSLS's prediction file: a line a query, its key (comma-joined keys for a window), then its
    answers' keys best first, space-separated; ``np.loadtxt`` (what MSLS's ``evaluate.py`` reads
    it with) wants as many on every line, so a query answered by fewer than ``max(KS)`` is padded
    with ``-``, which names no image (a miss, as an absent answer is). Returns the lines written."""
    width = max(KS)
    ans_len = task.db_len if task.task != "seq2im" else 1
    lines = []
    q_keys = task.q.key(centres, task.q_len)
    for i, qk in enumerate(q_keys):
        found = answers[i, :width][answers[i, :width] >= 0]
        names = task.db.key(found, ans_len) + ["-"] * (width - len(found))
        lines.append(" ".join([qk, *names]))
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return len(q_keys)
