"""95 % intervals (experiments/stats.py) on hand-computed cases, and the transfer table's per-seed
measures and difference rows (experiments/paper/transfer_learning.py) on hand-written curves."""

import math
import warnings

import numpy as np
import pytest

from experiments import report, stats
from experiments.paper import protocol, transfer_learning


def test_student_interval_of_three_values():
    mean, low, high = stats.student_interval(np.array([1.0, 2.0, 3.0]))
    half = 4.302652729749464 / math.sqrt(3)  # t(0.975, 2) · s / √n, s = 1
    assert (mean, low, high) == pytest.approx((2.0, 2.0 - half, 2.0 + half))
    assert math.isnan(stats.student_interval(np.array([0.5]))[1])


def test_rate_interval_is_the_student_interval_clipped_to_the_range_of_a_rate():
    mean, low, high = stats.rate_interval(np.array([1.0, 1.0, 1.0, 1.0, 0.0]))
    _, t_low, t_high = stats.student_interval(np.array([1.0, 1.0, 1.0, 1.0, 0.0]))
    assert (mean, low, high) == pytest.approx((0.8, t_low, 1.0)) and t_high > 1.3  # 0.245-1.355 unclipped
    assert stats.rate_interval(np.array([0.0, 0.0, 0.1]))[1] == 0.0
    assert math.isnan(stats.rate_interval(np.array([0.5]))[1])
    np.testing.assert_allclose(stats.rate_interval(np.array([0.4, 0.5, 0.6])), stats.student_interval(
        np.array([0.4, 0.5, 0.6])))  # inside [0, 1]: unchanged


def test_welch_interval_of_a_known_difference():
    # equal variances 1 and n = 3: se = √(2/3), Welch's df = 4, t(0.975, 4) = 2.7764451
    diff, low, high = stats.welch_interval(np.array([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 2.0]))
    half = 2.7764451051977987 * math.sqrt(2 / 3)
    assert (diff, low, high) == pytest.approx((1.0, 1.0 - half, 1.0 + half))
    assert math.isnan(stats.welch_interval(np.full(3, 0.5), np.full(3, 0.2))[1])  # no spread: undefined


def test_welch_interval_with_one_arm_without_spread_is_the_other_arms_interval_without_a_warning():
    # every transfer seed censored at 20,480,000 env steps: scipy warns of precision loss, which is not one
    censored = np.full(5, 20_480_000.0)
    other = np.array([20_480_000.0, 19_000_000.0, 20_480_000.0, 18_500_000.0, 20_480_000.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        diff, low, high = stats.welch_interval(censored, other)
    expected = 20_480_000.0 - other.mean()
    half = 2.7764451051977987 * other.std(ddof=1) / math.sqrt(5)  # t(0.975, 4): Welch's df is the other arm's n − 1
    assert (diff, low, high) == pytest.approx((expected, expected - half, expected + half))


def test_bootstrap_of_constant_arms_is_the_difference_itself():
    assert stats.bootstrap_difference([np.full(5, 0.5)], [np.full(4, 0.2)]) == pytest.approx((0.3, 0.3, 0.3))
    # the statistic is the mean over groups (tasks) of each group's mean over seeds
    assert stats.bootstrap_difference([np.ones(2), np.full(3, 3.0)], [np.zeros(2)]) == pytest.approx((2.0, 2.0, 2.0))


def test_bootstrap_of_symmetric_data_is_centred_and_a_pure_function():
    base = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    diff, low, high = stats.bootstrap_difference([base + 1.0], [base])
    assert diff == 1.0 and low < 1.0 < high
    assert (1.0 - low) == pytest.approx(high - 1.0, abs=0.05)  # symmetric data, symmetric interval
    assert stats.bootstrap_difference([base + 1.0], [base]) == (diff, low, high)
    assert stats.bootstrap_difference([base + 1.0], [base], seed=1) != (diff, low, high)


def test_bad_samples_are_refused_in_one_line():
    with pytest.raises(ValueError, match="arm A, group 0: expected a non-empty 1-D array"):
        stats.bootstrap_difference([np.array([])], [np.ones(2)])
    with pytest.raises(ValueError, match="a: expected a non-empty 1-D array of finite values"):
        stats.welch_interval(np.array([np.nan, 1.0]), np.ones(2))


def curve(label: str, rows) -> report.Curve:
    """Per-epoch per-seed success rows; epochs of 100 env steps per seed."""
    success = np.array(rows, float)
    epochs = np.arange(1, len(rows) + 1, dtype=float)
    return report.Curve("panel", label, label, epochs, 100 * epochs, 10 * epochs, success)


TRANSFER = curve("transfer", [(0.2, 0.4), (0.4, 0.6), (0.6, 0.8)])
SCRATCH = curve("scratch", [(0.0, 0.2), (0.1, 0.1), (0.3, 0.5)])


def test_seed_measures_censor_a_seed_that_never_reaches_a_threshold():
    measures = protocol.seed_measures(SCRATCH)
    np.testing.assert_allclose(measures["AUC"][0], [0.4 / 3, 0.8 / 3])
    np.testing.assert_array_equal(measures["env steps to 0.3"][0], [300, 300])
    steps, censored = measures["env steps to 0.5"]
    np.testing.assert_array_equal(steps, [300, 300])  # seed 0 never gets there: its run's 300 env steps
    np.testing.assert_array_equal(censored, [True, False])


def test_difference_table_rows():
    table = transfer_learning.difference_table(TRANSFER, SCRATCH)
    # AUC: transfer seeds 0.4, 0.6; scratch 0.133, 0.267 -> difference 0.3
    assert "| AUC | 0.500 | 0.200 | 0.300 |" in table
    # to 0.3: transfer 200, 100; scratch 300, 300 -> -150; to 0.5: transfer 300, 200; scratch 300 (censored), 300
    # Welch: se 50 (scratch has no spread), df 1, t(0.975, 1) = 12.706 -> ± 635
    assert "| env steps to 0.3 | 150 | 300 | -150 | [-200, -100] | [-785, 485] |" in table
    assert "| env steps to 0.5 | 250 | 300 (1 of 2 censored*) | -50 | [-100, 0] | [-685, 585] |" in table


def test_fisher_p_is_the_exact_two_sided_p_of_two_fractions():
    # 5/5 against 0/5: of the C(10, 5) = 252 equally likely splits, the two as extreme give p = 2/252
    assert stats.fisher_p(5, 5, 0, 5) == pytest.approx(2 / 252)
    assert stats.fisher_p(0, 5, 0, 5) == 1.0
    with pytest.raises(ValueError, match="fisher_p"):
        stats.fisher_p(6, 5, 0, 5)
