"""The methods an evaluation localises with, behind one small interface (:class:`Algorithm`),
kept apart from the protocol and the metrics as big-ann-benchmarks keeps its algorithms."""

from vprscale.evaluation.algorithms.base import Algorithm, Run

__all__ = ["Algorithm", "Run"]
