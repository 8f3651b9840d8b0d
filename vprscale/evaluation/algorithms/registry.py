"""Where the grid finds the methods it evaluates: a registry, never a hand-written list.

Every entry is a factory ``create(context) -> list[Algorithm]``: given what one evaluation
of one index has at hand (:class:`Context`), it returns the methods it contributes (none
when the evaluation did not ask for it). The built-in methods are registered here by
module path, and installed packages add theirs under the entry-point group
``vprscale.algorithms`` (``name = "package.module:create"``); every factory is imported
only when an evaluation runs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from vprscale.core.errors import InputError
from vprscale.evaluation.algorithms.base import Algorithm
from vprscale.method.index import Index

ENTRY_POINT_GROUP = "vprscale.algorithms"
BUILTIN = {  # in this order: the grid reports methods in the order they are created
    "coarsehash": "vprscale.evaluation.algorithms.coarsehash:create",
    "baseline": "vprscale.evaluation.algorithms.baseline:create",
    "faiss": "vprscale.evaluation.algorithms.faisscodes:create",
}

Factory = Callable[["Context"], list[Algorithm]]


@dataclass
class Context:
    """What one evaluation of one index offers the factories."""

    index_path: Path
    index: Index
    dim: int  # descriptor width
    n_query: int  # query rows of the store
    n_centres: int  # most centres of any evaluated L
    lengths: list[int]
    workers: int
    baseline: Any = None  # the baseline's map (None: --no-baseline)
    baseline_queries: int | None = None
    compared: list[Any] = field(default_factory=list)  # fitted FAISS codes (--compare)
    compare_queries: int | None = None
    faiss_k: list[int] | None = None  # FAISS operating points: every k (None: the codes' own) …
    faiss_nprobe: list[int] | None = None  # … with every nprobe (IVF codes only)


def _load(target: str) -> Factory:
    module, _, attr = target.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"method factory {target}: cannot be loaded ({exc})") from None


def factories() -> dict[str, str]:
    """Every registered factory by name: the built-in ones, then the installed packages' entry points."""
    found = dict(BUILTIN)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep.value)
    return found


def create(context: Context) -> list[Algorithm]:
    """The methods every registered factory contributes to one evaluation of one index."""
    return [alg for target in factories().values() for alg in _load(target)(context)]
