"""The metrics of an evaluation (docs/protocol.md, "Recall" and "Scores"), apart from the
methods and the datasets, as big-ann-benchmarks keeps them.

Every function takes per-query arrays of one run and optional per-query ``weights`` (a
stratified sample weights each part by its share of the query rows; None: every query
counts once):

- recall at radius r: share of queries whose match lies within r frames of the truth;
- Recall@N at radius r: share with any of the N best of a ranking of at least N candidates
  within r (the ranking is the method's: :class:`~vprscale.evaluation.algorithms.base.Answer`);
- precision–recall: a match is accepted when its score ≤ θ; precision = correct accepted /
  accepted, recall = correct accepted / queries (as SeqSLAM and OpenSeqSLAM2 count it),
  correct = within r; AUC-PR is the trapezoid area under that curve over every distinct
  θ, and recall at 100 % precision the largest recall before the first accepted mistake;
  ``auc_pr_correct`` is the same area with recall over the correct matches (VPR-Bench's
  form: the loosest threshold reaches recall 1 whatever the share of correct matches);
  ``ap``, average precision, the step sum Σ (Rₙ − Rₙ₋₁)·Pₙ over those thresholds with that
  recall (scikit-learn's ``average_precision_score``, which CaseVPR and VPR-Bench report);
  ``precision_at_r100``, the precision once every correct match is accepted (Delta
  Descriptors' precision at 100 % recall);
- 95 % Wilson intervals for every recall (recall, Recall@N, recall at 100 % precision).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

RADII = np.arange(21)  # recall radii, in frames (20 frames = 100 m on FAS)
TOP_N = (1, 5, 10, 20)  # Recall@N columns
Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def _weights(n: int, weights: np.ndarray | None) -> np.ndarray:
    return np.ones(n) if weights is None else np.asarray(weights, np.float64)


def recall_curve(error: np.ndarray, weights: np.ndarray | None = None, radii: np.ndarray = RADII) -> np.ndarray:
    """Recall at each radius (frames: r = 0 … 20) from each query's error (``|match − truth|``
    in frames, or the match's distance in metres); NaN without queries."""
    if len(error) == 0:
        return np.full(len(radii), np.nan)
    w = _weights(len(error), weights)
    return (w[:, None] * (np.asarray(error)[:, None] <= np.asarray(radii)[None, :])).sum(axis=0) / w.sum()


def top_distance(top: np.ndarray, query_pos: np.ndarray, ref_pos_at: Callable[[np.ndarray], np.ndarray],
                 n: int) -> np.ndarray:
    """Each query's smallest distance in metres from its position to one of its ``n`` best
    candidates' (``ref_pos_at(ids)``: NaN where a place has no position; such places, and −1
    places, never count: infinite)."""
    top = np.asarray(top, np.int64)[:, :n]
    if not top.shape[1]:
        return np.full(len(top), np.inf)
    d = np.linalg.norm(ref_pos_at(top) - np.asarray(query_pos)[:, None, :], axis=2)
    return np.where((top >= 0) & np.isfinite(d), d, np.inf).min(axis=1)


def top_error(top: np.ndarray, truth: np.ndarray, n: int) -> np.ndarray:
    """Each query's smallest ``|candidate − truth|`` over its ``n`` best candidates (−1
    places, where there were fewer, never count)."""
    top = np.asarray(top, np.int64)[:, :n]
    err = np.where(top >= 0, np.abs(top - np.asarray(truth, np.int64)[:, None]), np.iinfo(np.int64).max)
    return err.min(axis=1) if top.shape[1] else np.full(len(top), np.iinfo(np.int64).max)


def wilson(p: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """95 % Wilson score interval ``(lo, hi)`` of proportions ``p`` observed on ``n`` queries."""
    p = np.asarray(p, np.float64)
    if n == 0:
        return np.full_like(p, np.nan), np.full_like(p, np.nan)
    z2 = Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 * np.sqrt(np.maximum(p * (1 - p), 0) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return np.clip(centre - half, 0, p), np.clip(centre + half, p, 1)  # around p, whatever the rounding at 0 and 1


def pr_curve(score: np.ndarray, correct: np.ndarray, weights: np.ndarray | None = None,
             over_correct: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(precision, recall)`` at every distinct score threshold, ascending θ; recall over
    every query, or with ``over_correct`` over the correct matches (VPR-Bench's form)."""
    score = np.asarray(score, np.float64)
    w = _weights(len(score), weights)
    order = np.argsort(score, kind="stable")
    s, ok, w = score[order], np.asarray(correct, bool)[order], w[order]
    ends = np.r_[np.flatnonzero(np.diff(s) != 0), len(s) - 1] if len(s) else np.zeros(0, np.int64)
    accepted = np.cumsum(w)[ends]
    hits = np.cumsum(w * ok)[ends]
    total = (w * ok).sum() if over_correct else w.sum()
    return (np.divide(hits, accepted, out=np.zeros_like(hits), where=accepted > 0),
            hits / total if total > 0 else np.zeros_like(hits))


def auc_pr(precision: np.ndarray, recall: np.ndarray) -> float:
    """Trapezoid area under a precision–recall curve, from recall 0 at the first point's precision."""
    if len(recall) == 0:
        return float("nan")
    r = np.r_[0.0, recall]
    p = np.r_[precision[0], precision]
    return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) / 2))


def average_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """Σ (Rₙ − Rₙ₋₁)·Pₙ over a curve's thresholds (recall over the correct matches), from R₀ = 0."""
    if len(recall) == 0:
        return float("nan")
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def precision_at_full_recall(precision: np.ndarray, recall: np.ndarray) -> float:
    """The precision at the first threshold that accepts every correct match (recall over the
    correct matches reaching 1)."""
    full = np.flatnonzero(recall >= 1 - 1e-12)
    return float(precision[full[0]]) if len(full) else float("nan")


def recall_at_full_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """The largest recall reached while every accepted match is correct (0 if the first is not)."""
    perfect = np.flatnonzero(precision < 1)
    upto = perfect[0] if len(perfect) else len(precision)
    return float(recall[upto - 1]) if upto > 0 else 0.0


RECALLS = ("recall", *(f"recall_at_{n}" for n in TOP_N[1:]), "recall_at_p100")  # each with its interval


def run_metrics(error: np.ndarray, top: np.ndarray, truth: np.ndarray, score: np.ndarray,
                weights: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Every metric of one run's queries, per radius in frames: ``recall``, ``recall_at_N`` (N of
    ``TOP_N`` above 1; ``top`` is the ranking's best, best first), ``auc_pr``,
    ``auc_pr_correct``, ``ap``, ``precision_at_r100`` and ``recall_at_p100`` (arrays over
    ``RADII``), and the 95 % Wilson
    interval of every one of ``RECALLS`` (``…_lo``, ``…_hi``: a weighted run's from its
    number of queries)."""
    return metrics_at(error, {n: top_error(top, truth, n) for n in TOP_N[1:]}, score, weights, RADII)


def metrics_at(error: np.ndarray, nearest: dict[int, np.ndarray], score: np.ndarray, weights: np.ndarray | None,
               radii: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`run_metrics` for any error and radii (frames, or metres with positions): ``nearest``
    holds, for each N of ``TOP_N`` above 1, each query's smallest error over its N best."""
    out = {"recall": recall_curve(error, weights, radii)}
    for n in TOP_N[1:]:
        out[f"recall_at_{n}"] = recall_curve(nearest[n], weights, radii)
    auc, auc_correct, full, ap, p_full = (np.full(len(radii), np.nan) for _ in range(5))
    if len(error):
        for i, r in enumerate(radii):
            correct = np.asarray(error) <= r
            precision, recall = pr_curve(score, correct, weights)
            auc[i], full[i] = auc_pr(precision, recall), recall_at_full_precision(precision, recall)
            if correct.any():
                curve = pr_curve(score, correct, weights, over_correct=True)
                auc_correct[i], ap[i], p_full[i] = auc_pr(*curve), average_precision(*curve), \
                    precision_at_full_recall(*curve)
    out["auc_pr"], out["auc_pr_correct"], out["recall_at_p100"] = auc, auc_correct, full
    out["ap"], out["precision_at_r100"] = ap, p_full
    for name in RECALLS:
        out[f"{name}_lo"], out[f"{name}_hi"] = wilson(out[name], len(error))
    return out
