"""95 % intervals (experiments/stats.py) on hand-computed cases, and the transfer table's per-seed
measures and difference rows (experiments/paper/transfer_learning.py) on hand-written curves."""

import math
import warnings

import numpy as np
import pytest
from scipy import stats as scipy_stats

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


def test_welch_difference_over_groups_is_the_mean_over_groups_with_satterthwaite_degrees():
    a, b = [np.array([1.0, 2.0, 3.0]), np.array([2.0, 4.0])], [np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, 4.0])]
    found = stats.welch_difference(a, b)
    assert found.point == pytest.approx(0.5 * (1.0 + 1.0))
    terms = np.array([1 / 3, 2 / 2, 1 / 3, 3 / 3]) / 4  # w² s²/n with w = 1/2
    df = terms.sum() ** 2 / (terms**2 / np.array([2, 1, 2, 2])).sum()
    half = scipy_stats.t.ppf(0.975, df) * np.sqrt(terms.sum())
    assert (found.low, found.high) == pytest.approx((found.point - half, found.point + half))
    assert found.p == pytest.approx(2 * scipy_stats.t.sf(found.point / np.sqrt(terms.sum()), df))
    # one group: Welch's own interval and p (scipy.stats.ttest_ind)
    x, y = np.array([0.9, 0.8, 0.95, 0.7, 0.85]), np.array([0.6, 0.75, 0.7, 0.5, 0.65])
    test = scipy_stats.ttest_ind(x, y, equal_var=False)
    found = stats.welch_difference([x], [y])
    assert (found.low, found.high) == pytest.approx(tuple(test.confidence_interval(0.95)))
    assert found.p == pytest.approx(test.pvalue)
    # a contrast: +1 on one group, -1 on another
    contrast = stats.welch_difference(a, b, weights=[1.0, -1.0])
    assert contrast.point == pytest.approx(0.0)


def test_welch_difference_is_undefined_without_spread_or_with_one_seed():
    assert math.isnan(stats.welch_difference([np.full(5, 0.5)], [np.full(4, 0.2)]).low)
    assert math.isnan(stats.welch_difference([np.ones(1)], [np.arange(3.0)]).p)


def test_holm_adjusts_step_down_and_keeps_the_order():
    np.testing.assert_allclose(stats.holm([0.01, 0.04, 0.03]), [0.03, 0.06, 0.06])
    np.testing.assert_allclose(stats.holm([0.02]), [0.02])
    adjusted = stats.holm([np.nan, 0.01])
    assert math.isnan(adjusted[0]) and adjusted[1] == pytest.approx(0.02)  # nan counts as a check that never rejects


def test_above_p_is_the_binomial_upper_tail_at_the_floor():
    assert stats.above_p(0, 10, 0.1) == 1.0
    assert stats.above_p(10, 10, 0.5) == pytest.approx(0.5**10)
    assert stats.above_p(3, 10, 0.1) == pytest.approx(scipy_stats.binom.sf(2, 10, 0.1))
    with pytest.raises(ValueError, match="above_p"):
        stats.above_p(11, 10, 0.1)


# per-seed figures of two arms, 5 seeds each, as our runs give them: (name, draw A, mean A, draw B, mean B)
POPULATIONS = (
    ("normal, unequal spread", lambda r, n: r.normal(0.0, 1.0, n), 0.0, lambda r, n: r.normal(1.0, 2.0, n), 1.0),
    ("success rates near 1 (binomial over 1,280 episodes)", lambda r, n: r.binomial(1280, 0.97, n) / 1280, 0.97,
     lambda r, n: r.binomial(1280, 0.9, n) / 1280, 0.9),
    ("bounded, skewed to 1 (Beta)", lambda r, n: r.beta(40.0, 1.5, n), 40 / 41.5, lambda r, n: r.beta(20.0, 1.0, n),
     20 / 21),
    ("skewed (exponential) against normal", lambda r, n: r.exponential(1.0, n), 1.0,
     lambda r, n: r.normal(0.0, 1.0, n), 0.0),
    ("AUCs near 0 (Beta)", lambda r, n: r.beta(2.0, 30.0, n), 2 / 32, lambda r, n: r.beta(1.0, 20.0, n), 1 / 21),
)


@pytest.mark.parametrize("name, draw_a, mean_a, draw_b, mean_b", POPULATIONS, ids=[p[0] for p in POPULATIONS])
def test_welch_difference_covers_95_percent_at_5_seeds(name, draw_a, mean_a, draw_b, mean_b):
    """Simulated coverage of the 95 % interval of a difference of 5-seed arms, one group and the mean over four
    (each group's arms drawn from the population shifted by the group's index): within 2.5 points of 95 %
    (20,000 replicates: the simulation's own standard error is 0.15 points)."""
    rng, replicates = np.random.default_rng(0), 20_000
    for groups in (1, 4):
        a = [draw_a(rng, (replicates, 5)) + g for g in range(groups)]
        b = [draw_b(rng, (replicates, 5)) + g for g in range(groups)]
        found = stats.welch_difference(a, b)
        covered = ((found.low <= mean_a - mean_b) & (mean_a - mean_b <= found.high)).mean()
        assert abs(covered - 0.95) <= 0.025, f"{name}, {groups} group(s): coverage {covered:.3f}"


def test_bad_samples_are_refused_in_one_line():
    with pytest.raises(ValueError, match="arm A, group 0: expected a non-empty array"):
        stats.welch_difference([np.array([])], [np.ones(2)])
    with pytest.raises(ValueError, match="a: expected a non-empty 1-D array of finite values"):
        stats.welch_interval(np.array([np.nan, 1.0]), np.ones(2))
    with pytest.raises(ValueError, match="2 groups but 1 weights"):
        stats.welch_difference([np.ones(2)] * 2, [np.ones(2)] * 2, weights=[1.0])


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
    assert "| env steps to 0.3 | 150 | 300 | -150 | [-785, 485] |" in table
    assert "| env steps to 0.5 | 250 | 300 (1 of 2 censored*) | -50 | [-685, 585] |" in table


def test_fisher_p_is_the_exact_two_sided_p_of_two_fractions():
    # 5/5 against 0/5: of the C(10, 5) = 252 equally likely splits, the two as extreme give p = 2/252
    assert stats.fisher_p(5, 5, 0, 5) == pytest.approx(2 / 252)
    assert stats.fisher_p(0, 5, 0, 5) == 1.0
    with pytest.raises(ValueError, match="fisher_p"):
        stats.fisher_p(6, 5, 0, 5)
