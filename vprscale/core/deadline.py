"""A wall-clock deadline that a job stops at, at a checkpoint: how ``vprscale run --budget``
ends a stage inside the budget without losing its work.

A pipeline run under a budget gives each stage that checkpoints the end of the budget in the
environment (``VPRSCALE_DEADLINE``, seconds since the epoch). A resumable pass asks before each
group of chunks whether the group still fits, judging by the last group's time; when it does
not, :class:`BudgetSpent` ends the job with exit status 75 (``EX_TEMPFAIL`` of sysexits.h:
"try again later"). Nothing is wrong and nothing is lost: the checkpoints are on disk and the
same command continues from them.
"""

from __future__ import annotations

import math
import os
import time

ENV = "VPRSCALE_DEADLINE"
EXIT_MORE = 75  # more to do: the budget is spent, the work so far is kept


class BudgetSpent(Exception):  # noqa: N818 - not an error: the job stopped where it was told to
    """The deadline came before the job's end; the message says where it stopped."""


def deadline() -> float | None:
    """The deadline this process was given (None: no budget). A value that is not a number is
    vprscale's own bug (only ``vprscale run`` sets it), so it is not silently ignored."""
    raw = os.environ.get(ENV)
    if not raw:
        return None
    value = float(raw)
    if not math.isfinite(value):
        raise ValueError(f"{ENV}={raw!r} is not a time")
    return value


_progressed = False  # whether this process finished a unit of work since it started (see check)


def progressed() -> None:
    """Say that a unit of work (a group of chunks, a step) is finished and kept on disk."""
    global _progressed
    _progressed = True


def check(next_seconds: float, where: str) -> None:
    """Stop (raise :class:`BudgetSpent`) if work expected to take ``next_seconds`` would end past
    the deadline; ``where`` says what was done so far, for the message.

    A process stops only once it has finished a unit of work (:func:`progressed`): a call that
    stopped at its first checkpoint would stop there again on every call, and a requeued job
    would never end (a budget shorter than a process's start). So every call progresses, by one
    unit past its deadline at most."""
    end = deadline()
    if end is not None and _progressed and time.time() + next_seconds > end:
        raise BudgetSpent(where)
