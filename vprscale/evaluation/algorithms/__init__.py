"""The methods an evaluation localises with, behind one small interface (:class:`Algorithm`) and
found through a registry, kept apart from the protocol, the runner and the metrics as
big-ann-benchmarks keeps its algorithms."""

from vprscale.evaluation.algorithms.base import Algorithm, Answer

__all__ = ["Algorithm", "Answer"]
