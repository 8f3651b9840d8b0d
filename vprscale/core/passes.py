"""Resumable streamed passes: chunk tasks run group by group, their results reduced in chunk order.

A pass over a billion rows takes minutes; a killed job must not start it again. A pass is a
list of chunk row ranges and a task per chunk; chunks run in groups on the active Dask
scheduler (threads here, or a distributed cluster), and after each group the reduction so
far is saved in the job's work folder with the number of chunks it covers. A re-run loads
it and goes on from the next chunk. Results are folded strictly in chunk order, so a
reduction that is order-sensitive (a float64 sum of moments) gives the same bits however
the pass was interrupted or scheduled.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import dask

from vprscale.core import deadline
from vprscale.core.private import owned
from vprscale.core.progress import ChunkProgress, run_tasks

S = TypeVar("S")
log = logging.getLogger(__name__)


def reduce_pass(work: Path, name: str, bounds: list[tuple[int, int]], task: Callable[[int, int], Any],
                fold: Callable[[S, Any], S], state: S, group: int = 16, quiet: bool = False,
                checkpoint: str | None = None) -> S:
    """Fold ``task(a, b)`` of every chunk into ``state``, in chunk order, resumably.

    ``work`` holds the checkpoint ``<checkpoint or name>.pass``: the state after the first
    ``n`` chunks. ``name`` is what the progress shows. Under a deadline
    (:mod:`vprscale.core.deadline`) a group starts only if the last one's time still fits before it.
    """
    ckpt = work / f"{checkpoint or name}.pass"
    done = 0
    if ckpt.is_file() and owned(ckpt):  # a pickle: loaded only where nobody else could have written it
        with ckpt.open("rb") as f:
            done, state = pickle.load(f)
    elif ckpt.is_file():
        log.warning("%s: a checkpoint another user could have written; not loaded, the pass starts over", ckpt)
    progress = None if quiet else ChunkProgress(name, len(bounds), done)
    run = dask.delayed(task, pure=True)  # the task object (small matrices, a reader) is hashed once
    last = 0.0  # the last group's wall time: what the next one is expected to take
    for g in range(done, len(bounds), group):
        deadline.check(last, f"{name}: {g:,} of {len(bounds):,} chunks done")
        started = time.perf_counter()
        results = dask.compute(*[run(a, b) for a, b in bounds[g : g + group]])
        for r in results:
            state = fold(state, r)
        done = min(len(bounds), g + group)
        tmp = ckpt.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as f:  # this user's alone
            pickle.dump((done, state), f, protocol=pickle.HIGHEST_PROTOCOL)
        tmp.replace(ckpt)
        deadline.progressed()
        if progress:
            progress.update(len(results))
        last = time.perf_counter() - started
    return state


def run_groups(tasks: list[Any], name: str, group: int = 16) -> None:
    """Run Dask tasks that each keep what they make (a chunk written and marked done), a group at a
    time: under a deadline a group starts only if the last one's time still fits before it, as
    :func:`reduce_pass`'s do, so a stage of such tasks stops at a checkpoint too."""
    last = 0.0
    for g in range(0, len(tasks), group):
        deadline.check(last, f"{name}: {g:,} of {len(tasks):,} tasks done")
        started = time.perf_counter()
        run_tasks(tasks[g : g + group], name)
        deadline.progressed()
        last = time.perf_counter() - started
