"""A pipeline under a wall-clock budget (``vprscale run --budget 2h``): which stage starts, and
the plan a dry run shows.

A batch job has a wall-clock limit (Slurm's ``--time``, a nightly window). A run under a budget
starts the stages that are out of date in order while the budget lasts. A stage whose job
checkpoints (:data:`CHECKPOINTED`: a build's and an encoding's passes) is given the budget's end
and stops at its last checkpoint that fits (:mod:`vprscale.core.deadline`); the next call resumes
it. A stage that cannot stop midway starts only if its estimate fits what is left, or first in a
call (else one longer than what is left could never run); one whose estimate is longer than the
whole budget is refused before any work. A stage never measured has nothing to judge by: it starts
while any budget is left, and the dry run says it may run past it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from vprscale.core.errors import InputError

CHECKPOINTED = frozenset({"build", "encode"})  # kinds whose job resumes from checkpoints of its passes
_UNITS = {"d": 86400, "h": 3600, "m": 60, "s": 1}
_DURATION = re.compile(r"(?:(\d+(?:\.\d+)?)([dhms]))+")


def parse_duration(text: str) -> float:
    """Seconds in ``2h``, ``90m``, ``1h30m``, ``45s`` or ``1.5d`` (Slurm-like units; a bare number is
    seconds)."""
    raw = text.strip().lower()
    if re.fullmatch(r"\d+(?:\.\d+)?", raw):
        seconds = float(raw)
    elif _DURATION.fullmatch(raw):
        seconds = sum(float(n) * _UNITS[u] for n, u in re.findall(r"(\d+(?:\.\d+)?)([dhms])", raw))
    else:
        raise InputError(f"--budget {text!r}: not a duration (e.g. 2h, 90m, 1h30m, 3600)")
    if seconds <= 0:
        raise InputError(f"--budget {text!r}: must be more than nothing")
    return seconds


@dataclass
class Pending:
    """A stage to run, as the budget sees it."""

    name: str
    kind: str
    seconds: float | None  # its estimate, what an earlier call spent on it deducted; None: never measured

    @property
    def checkpoints(self) -> bool:
        return self.kind in CHECKPOINTED


def check(stages: list[Pending], budget: float) -> None:
    """Refuse, before any work, a budget that a stage to run cannot stop within: one that cannot
    stop midway and is estimated longer than the whole budget would never fit a call."""
    for stage in stages:
        if not stage.checkpoints and stage.seconds is not None and stage.seconds > budget:
            raise InputError(f"--budget {words(budget)}: stage '{stage.name}' cannot stop midway and is estimated "
                             f"at {words(stage.seconds)}, longer than the whole budget: give a larger one")


def may_start(stage: Pending, left: float, first: bool) -> str | None:
    """Why ``stage`` does not start now with ``left`` seconds of the budget (None: it starts).
    ``first``: nothing has started in this call yet."""
    if first:
        return None  # every call starts a stage, however little is left: else none could ever progress
    if left <= 0:
        return "the budget is spent"
    if stage.checkpoints or stage.seconds is None or stage.seconds <= left:
        return None  # never measured: nothing to judge by, so progress rather than a call that does nothing
    return (f"'{stage.name}' cannot stop midway and is estimated at {words(stage.seconds)}, more than the "
            f"{words(left)} left")


def plan_calls(stages: list[Pending], budget: float) -> list[tuple[int, str]]:
    """Which call of ``vprscale run --budget`` runs each stage, by the rules of :func:`may_start`
    and the estimates: per stage, the call that ends it and a note. A stage never measured is
    counted as taking no time: the plan is then the fewest calls it may take."""
    check(stages, budget)
    notes: list[tuple[int, str]] = []
    call, left, first = 1, budget, True
    for stage in stages:
        if may_start(stage, left, first) is not None:
            call, left, first = call + 1, budget, True
        start = call
        if stage.seconds is None:
            notes.append((call, f"call {call} at the earliest; never measured, " + (
                "stops at a checkpoint if it must" if stage.checkpoints else "may run past the budget")))
        elif stage.checkpoints:
            need = stage.seconds
            while need > left:
                need, call, left = need - left, call + 1, budget
            left -= need
            notes.append((call, f"call {start}" if call == start else
                          f"calls {start}-{call}: stops at a checkpoint and continues"))
        else:
            left -= stage.seconds
            notes.append((call, f"call {call}; cannot stop midway"))
        first = False
    return notes


def words(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 5400 else f"{seconds / 60:.0f} min" if seconds >= 60 \
        else f"{seconds:.0f} s"
