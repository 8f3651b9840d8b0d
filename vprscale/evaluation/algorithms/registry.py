"""Where the grid finds the methods it evaluates: a registry, never a hand-written list.

Every entry is a factory ``create(context) -> list[Algorithm]``: given what one evaluation
of one index has at hand (:class:`Context`), it returns the methods it contributes (none
when the evaluation did not ask for it). The built-in methods are registered here by
module path: CoarseHash, the baseline, FAISS codes and pooled sequence descriptors
(``--compare``) and the methods of the small contract (``--method``, :mod:`.plugged`).

Installed packages add theirs under the entry-point group ``vprscale.algorithms``: a
factory (``name = "package.module:create"``) joins every evaluation, as the built-in ones
do; a class of the small contract (``name = "package.module:Class"``) becomes a method an
evaluation can ask for by name (``--method name``). Everything is imported only when used.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vprscale.core.errors import InputError

if TYPE_CHECKING:  # imported by what evaluates, not by ``vprscale methods``
    from vprscale.evaluation.algorithms.base import Algorithm
    from vprscale.method.index import Index

ENTRY_POINT_GROUP = "vprscale.algorithms"
BUILTIN = {  # in this order: the grid reports methods in the order they are created
    "coarsehash": "vprscale.evaluation.algorithms.coarsehash:create",
    "baseline": "vprscale.evaluation.algorithms.baseline:create",
    "faiss": "vprscale.evaluation.algorithms.faisscodes:create",
    "pooled": "vprscale.evaluation.algorithms.pooled:create",
    "methods": "vprscale.evaluation.algorithms.plugged:create",
}

Factory = Callable[["Context"], "list[Algorithm]"]


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
    pooled: list[Any] = field(default_factory=list)  # fitted pooled sequence descriptors (--compare seq:…)
    compare_queries: int | None = None
    flat_noise: list[str] | None = None  # noise levels flat (exhaustive-scan) FAISS codes run on (None: all)
    faiss_k: list[int] | None = None  # FAISS operating points: every k (None: the codes' own) …
    faiss_nprobe: list[int] | None = None  # … with every nprobe (IVF codes only)
    plugged: list[tuple[str, Any]] = field(default_factory=list)  # fitted --method methods, with their labels
    method_k: list[int] = field(default_factory=list)  # the k of each of their operating points
    ref_sequences: Any = None  # the map's sequences (:class:`vprscale.protocol.Sequences`; None: one traverse)


def _load(target: str) -> Any:
    module, _, attr = target.partition(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"method factory {target}: cannot be loaded ({exc})") from None


def is_method_class(obj: Any) -> bool:
    """Whether an entry point names a class of the small contract (rather than a factory)."""
    return isinstance(obj, type) and all(callable(getattr(obj, m, None)) for m in ("fit", "query"))


def registered() -> dict[str, tuple[str, str]]:
    """Every entry by name: ``(target, kind)``, kind ``built-in``, ``factory`` (an installed
    one, joining every evaluation) or ``method`` (an installed class, for ``--method name``)."""
    found = {name: (target, "built-in") for name, target in BUILTIN.items()}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name not in found:
            found[ep.name] = (ep.value, "method" if is_method_class(_load(ep.value)) else "factory")
    return found


def installed_methods() -> dict[str, str]:
    """The installed classes of the small contract, by name: what ``--method name`` may ask for."""
    return {name: target for name, (target, kind) in registered().items() if kind == "method"}


def create(context: Context) -> list[Algorithm]:
    """The methods every registered factory contributes to one evaluation of one index, each
    told the map's sequences (``ref_windows``), whose windows it must keep to."""
    found = [alg for target, kind in registered().values() if kind != "method" for alg in _load(target)(context)]
    for alg in found:
        alg.ref_windows = context.ref_sequences
    return found
