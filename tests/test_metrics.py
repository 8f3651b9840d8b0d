"""The evaluation's metrics (vprscale.evaluation.metrics) against hand-worked cases."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vprscale.evaluation.metrics import (
    auc_pr,
    pr_curve,
    recall_at_full_precision,
    recall_curve,
    run_metrics,
    top_error,
    wilson,
)


def test_wilson_interval_matches_the_textbook_values():
    lo, hi = wilson(np.array([0.5, 0.0, 1.0]), 100)
    np.testing.assert_allclose(lo, [0.4038, 0.0, 0.9630], atol=1e-4)
    np.testing.assert_allclose(hi, [0.5962, 0.0370, 1.0], atol=1e-4)


def test_recall_at_n_counts_any_of_the_n_best_and_never_an_empty_place():
    top = np.array([[5, 40, -1], [90, 10, 12], [-1, -1, -1]])
    truth = np.array([40, 11, 0])
    np.testing.assert_array_equal(top_error(top, truth, 1), [35, 79, np.iinfo(np.int64).max])
    np.testing.assert_array_equal(top_error(top, truth, 3), [0, 1, np.iinfo(np.int64).max])


def test_precision_recall_over_distinct_thresholds():
    score = np.array([0.1, 0.2, 0.2, 0.5])
    correct = np.array([True, False, True, True])
    precision, recall = pr_curve(score, correct)
    np.testing.assert_allclose(precision, [1.0, 2 / 3, 3 / 4])  # the two 0.2s are accepted together
    np.testing.assert_allclose(recall, [0.25, 0.5, 0.75])
    assert recall_at_full_precision(precision, recall) == 0.25
    # trapezoids from (recall 0, precision 1): 0.25·1 + 0.25·(1 + 2/3)/2 + 0.25·(2/3 + 3/4)/2
    assert np.isclose(auc_pr(precision, recall), 0.25 + 0.25 * (5 / 6) + 0.25 * (17 / 24))


def test_a_perfect_ranking_has_full_precision_until_its_last_correct_match():
    score = np.arange(6.0)
    correct = np.array([True, True, True, False, False, False])
    precision, recall = pr_curve(score, correct)
    assert recall_at_full_precision(precision, recall) == 0.5
    assert np.isclose(auc_pr(precision, recall), 0.5)  # precision 1 up to recall 0.5, then flat


@given(st.lists(st.tuples(st.floats(0, 10, allow_nan=False), st.booleans(), st.floats(0.1, 5)), min_size=1,
                max_size=40))
def test_weights_scale_queries_as_repeats_would(rows):
    """A query of integer weight w counts as w copies of itself, in every metric."""
    score = np.array([r[0] for r in rows])
    correct = np.array([r[1] for r in rows])
    w = np.array([max(1, round(r[2])) for r in rows])
    weighted = pr_curve(score, correct, w.astype(float))
    repeated = pr_curve(np.repeat(score, w), np.repeat(correct, w))
    np.testing.assert_allclose(weighted, repeated)
    error = np.where(correct, 0, 30)
    np.testing.assert_allclose(recall_curve(error, w.astype(float)), recall_curve(np.repeat(error, w)))


def test_run_metrics_gives_each_radius_its_own_figures():
    truth = np.array([100, 200, 300])
    top = np.array([[100, 7], [205, 200], [330, 331]])
    error = np.abs(top[:, 0] - truth)
    got = run_metrics(error, top, truth, np.array([0.1, 0.2, 0.3]))
    assert got["recall"][0] == 1 / 3 and got["recall"][5] == 2 / 3
    assert got["recall_at_5"][0] == 2 / 3  # the second query's truth is its second candidate
    assert got["recall_at_p100"][0] == 1 / 3 and got["recall_at_p100"][5] == 2 / 3


@given(st.lists(st.tuples(st.integers(0, 6), st.booleans()), min_size=1, max_size=60))
def test_average_precision_is_scikit_learn_s_and_precision_at_full_recall_delta_descriptors(rows):
    """``ap`` equals scikit-learn's ``average_precision_score`` (confidence: the negated score; ties
    taken together) and ``precision_at_r100`` the precision of accepting every match scored at or
    below the worst-scored correct one, as Delta Descriptors computes it, on the same rows."""
    from sklearn.metrics import average_precision_score

    score = np.array([s for s, _ in rows], np.float64)
    correct = np.array([c for _, c in rows])
    error = np.where(correct, 0, 5)
    out = run_metrics(error, np.zeros((len(rows), 0), np.int64), np.zeros(len(rows), np.int64), score)
    if not correct.any():
        assert np.isnan(out["ap"][0]) and np.isnan(out["precision_at_r100"][0])
        return
    assert np.isclose(out["ap"][0], average_precision_score(correct, -score))
    worst = score[correct].max()
    assert np.isclose(out["precision_at_r100"][0], correct[score <= worst].mean())
    assert np.isclose(out["ap"][5], 1.0) and out["precision_at_r100"][5] == 1.0  # within 5 frames every match is right


@pytest.mark.parametrize("n", [1, 7, 5901, 123_457])
def test_a_wilson_interval_holds_its_recall_at_0_and_1(n):
    """A perfect (or null) method's interval ends at its recall: floating point put the upper bound
    of 1.0 over 5,901 queries at 0.9999999999999999, and the report's error bars went negative."""
    lo, hi = wilson(np.array([0.0, 1.0]), n)
    assert lo[0] == 0.0 and hi[1] == 1.0 and hi[0] > 0 and lo[1] < 1
