"""Unitary operations per query (paper §Discussion, docs/accounting.md), and how a measured time is shown."""

from __future__ import annotations

import math
from typing import Any

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


def time_cell(row: Any) -> str:
    """µs per query as a report shows it: the median of the repeats, with their range when there is one."""
    lo, hi = getattr(row, "us_per_query_lo", None), getattr(row, "us_per_query_hi", None)
    if lo is None or hi is None or lo != lo or hi != hi:
        return f"{row.us_per_query:,.2f}"
    return f"{row.us_per_query:,.2f} ({lo:,.2f}–{hi:,.2f})"
