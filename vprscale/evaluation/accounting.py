"""Unitary operations per query (paper §Discussion, docs/accounting.md)."""

from __future__ import annotations

import math

WORD_BITS = 64  # p: the precision of the xor in the sequence distance


def method_ops(dim: int, d: int, k: int, L: int, n_r: float, occupied: int, fallback_share: float) -> dict[str, float]:
    """Operations of one CoarseHash query, by step, and their total."""
    ops = {
        "mean_subtraction": dim,
        "projection": d * (2 * dim - 1),
        "quantisation": d * (2 * k - 1),
        "hash": 2 * d - 1,
        "candidate_lists": 1 + fallback_share * math.log2(max(2, occupied)),
        "sequence_matching": L * n_r * (d / WORD_BITS + d - 1),
    }
    ops["total"] = sum(ops.values())
    return ops


def baseline_ops(dim: int, n_ref: int, L: int, n_r: float) -> dict[str, float]:
    """Operations of one baseline query (d = 1): projection, a full scan, sequence matching."""
    ops = {
        "mean_subtraction": dim,
        "projection": 2 * dim - 1,
        "scan": 3 * 1 * n_ref,
        "sequence_matching": 3 * L * n_r,
    }
    ops["total"] = sum(ops.values())
    return ops
