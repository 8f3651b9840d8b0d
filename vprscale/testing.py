"""The shared contract suite of evaluated methods, for yours as for the built-in ones
(docs/bring-your-own.md), in the spirit of scikit-learn's ``check_estimator``.

``check_algorithm(Method)`` fits a method of the small contract on a small synthetic traverse
and checks what the evaluation relies on: ``query``'s shapes, ids and order, answers that do
not depend on how frames are batched, ``pair_distances`` that agree with ``query``'s own
distances, and then the method under the runner (L = 1 and sequences in both modes): one
best-first list per centre, the same answers on one thread or two and for any subset of
centres. Every built-in method passes the second half (:func:`check_answers`) in vprscale's
own tests. A failed check raises ``AssertionError`` naming it.
"""

from __future__ import annotations

from typing import Any

import dask.array as da
import numpy as np

from vprscale.evaluation.algorithms.base import Algorithm
from vprscale.evaluation.algorithms.plugged import Plugged
from vprscale.evaluation.runner import Runner
from vprscale.method.kernels import N_BEST
from vprscale.protocol import SEQUENCE_MODES, window_positions

N_REF, N_FRAMES, DIM, K = 3000, 400, 16, 8


def traverse(seed: int = 0) -> tuple[da.Array, np.ndarray, np.ndarray]:
    """``(ref, frames, truth)``: a smooth random walk of ``N_REF`` places (Dask, 4 chunks) and
    a noisy second pass over ``N_FRAMES`` of them, frame i at place ``truth[i]``."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(size=(N_REF, DIM)), axis=0) / 8 + rng.normal(size=(N_REF, DIM))
    truth = np.arange(1000, 1000 + N_FRAMES)
    frames = walk[truth] + rng.normal(scale=0.3, size=(N_FRAMES, DIM))
    return da.from_array(walk.astype(np.float32), chunks=N_REF // 4), frames.astype(np.float32), truth


def check_algorithm(method: Any) -> None:
    """Check a method of the small contract (a class, or an instance not yet fitted)."""
    m = method() if isinstance(method, type) else method
    name = getattr(m, "name", type(m).__name__)
    for attr in ("fit", "query"):
        assert callable(getattr(m, attr, None)), f"{name}: no {attr} method"
    ref, frames, truth = traverse()
    m.fit(ref)
    ids, dist = (np.asarray(a) for a in m.query(frames, K))
    assert ids.shape == (N_FRAMES, K) and dist.shape == (N_FRAMES, K), \
        f"{name}: query returned {ids.shape} ids and {dist.shape} distances for {N_FRAMES} frames, k = {K}"
    assert np.issubdtype(ids.dtype, np.integer), f"{name}: query's ids are {ids.dtype}, not integers"
    assert ((ids >= -1) & (ids < N_REF)).all(), f"{name}: an id outside −1 … {N_REF - 1}"
    found = ids >= 0
    assert (found[:, :-1] >= found[:, 1:]).all(), f"{name}: a −1 before a found id (pad at the end)"
    assert all(len(set(r[r >= 0])) == (r >= 0).sum() for r in ids), f"{name}: an id twice in one frame's list"
    d = np.where(found, dist, np.inf)
    assert (np.diff(d, axis=1)[found[:, 1:]] >= 0).all(), f"{name}: distances not ascending (best first)"
    halves = [np.asarray(m.query(frames[s], K)[0]) for s in (slice(0, 150), slice(150, None))]
    assert np.array_equal(np.concatenate(halves), ids), f"{name}: query's answer depends on the batch of frames"
    if callable(getattr(m, "pair_distances", None)):
        rows = np.flatnonzero(found[:, 0])
        pd_ = np.asarray(m.pair_distances(frames[rows], ids[rows, 0]), np.float64)
        assert pd_.shape == (len(rows),), f"{name}: pair_distances returned {pd_.shape}, ({len(rows)},) expected"
        assert np.allclose(pd_, dist[rows, 0], rtol=1e-4, atol=1e-5), \
            f"{name}: pair_distances disagrees with query's distances of the same pairs"
    check_answers(Plugged(name, m, K, N_REF), frames, N_REF)


def check_answers(alg: Algorithm, rows: np.ndarray, n_ref: int, lengths: tuple[int, ...] = (1, 5)) -> None:
    """Check an evaluated method (:class:`~vprscale.evaluation.algorithms.base.Algorithm`) of
    a map of ``n_ref`` places on query ``rows`` (a traverse, in order) under the runner."""
    frames = np.arange(len(rows))
    answers = {}
    for workers in (1, 2):
        runner = Runner(workers, repeats=1)
        state, cost = runner.frames(alg, rows)
        assert len(cost.cpu_us) == 1 and cost.cpu_us[0] >= 0
        for L in lengths:
            t = np.arange(L // 2, len(rows) - L, 7)
            pos = window_positions(frames, t, L)
            for mode in alg.modes(L, list(SEQUENCE_MODES)):
                answer, timing = runner.localise(alg, state, pos, L, mode, cost)
                where = f"{alg.name}, L = {L}, {mode or 'single frame'}"
                assert answer.top.shape == (len(t), N_BEST) and answer.top.dtype == np.int64, \
                    f"{where}: top is {answer.top.shape} {answer.top.dtype}, ({len(t)}, {N_BEST}) int64 expected"
                assert answer.score.shape == (len(t),) and answer.n_r.shape == (len(t),), f"{where}: shapes"
                top = answer.top
                assert ((top >= -1) & (top < n_ref)).all(), f"{where}: a candidate outside the map"
                assert ((top[:, :-1] >= 0) | (top[:, 1:] < 0)).all(), f"{where}: a −1 before a candidate"
                assert all(len(set(r[r >= 0])) == (r >= 0).sum() for r in top), f"{where}: a candidate twice"
                assert not np.isnan(answer.score[top[:, 0] >= 0]).any(), f"{where}: a NaN score"
                assert (answer.n_r >= 0).all(), f"{where}: a negative candidate count"
                assert timing.us_per_query >= 0 and timing.repeats == 1, f"{where}: timing"
                part = answer if L == 1 else runner.localise(alg, state, pos[1::3], L, mode, cost)[0]
                if L > 1:
                    assert np.array_equal(part.top, top[1::3]), f"{where}: answers depend on the other centres"
                key = (L, mode)
                if key in answers:
                    assert np.array_equal(answers[key].top, top), f"{where}: answers depend on the workers"
                    assert np.array_equal(answers[key].score, answer.score), f"{where}: scores depend on workers"
                answers[key] = answer
