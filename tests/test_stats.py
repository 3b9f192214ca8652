"""The study statistics (cpgjax.studies.stats) against independent references: SciPy's own two-sample tests on raw data,
textbook values of the t distribution, and the coverage of the intervals on simulated seeds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as scipy_stats

from cpgjax.studies import stats


def test_mean_ci_is_the_student_t_interval():
    x = np.array([2.1, 2.3, 1.9, 2.2, 2.0])
    ci = stats.mean_ci(x)
    # t_{0.975, 4} = 2.776 (tables); s = 0.1581
    half = 2.776445 * np.std(x, ddof=1) / np.sqrt(5)
    assert ci.mean == pytest.approx(2.1) and ci.n == 5
    assert ci.low == pytest.approx(2.1 - half, rel=1e-6) and ci.high == pytest.approx(2.1 + half, rel=1e-6)


def test_welch_from_summaries_equals_scipys_test_on_the_raw_samples():
    rng = np.random.default_rng(0)
    a, b = rng.normal(0.52, 0.02, 20), rng.normal(0.58, 0.05, 5)
    ours = stats.compare(a, b)
    reference = scipy_stats.ttest_ind(a, b, equal_var=False)
    assert ours.t_p == pytest.approx(reference.pvalue, rel=1e-9)
    ci = reference.confidence_interval(0.95)
    assert (ours.low, ours.high) == (pytest.approx(ci.low, rel=1e-9), pytest.approx(ci.high, rel=1e-9))
    summary = stats.compare_to_summary(a, b.mean(), b.std(ddof=1), b.size)
    assert summary.t_p == pytest.approx(reference.pvalue, rel=1e-9)
    assert ours.rank_p == pytest.approx(scipy_stats.mannwhitneyu(a, b).pvalue)


def test_intervals_cover_the_true_mean_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    covered = 0
    for _ in range(2000):
        ci = stats.mean_ci(rng.normal(1.0, 0.3, 20))
        covered += ci.low <= 1.0 <= ci.high
    assert 0.935 <= covered / 2000 <= 0.965
    diffs = 0
    for _ in range(2000):
        c = stats.compare(rng.normal(1.0, 0.3, 20), rng.normal(1.2, 0.1, 7))
        diffs += c.low <= -0.2 <= c.high
    assert 0.93 <= diffs / 2000 <= 0.97


def test_paired_comparison_is_the_one_sample_test_of_the_differences():
    rng = np.random.default_rng(2)
    a = rng.normal(0.0, 1.0, 30)
    b = a + rng.normal(0.3, 0.2, 30)
    c = stats.paired(b, a)
    d = b - a
    assert c.difference == pytest.approx(d.mean())
    assert c.t_p == pytest.approx(scipy_stats.ttest_1samp(d, 0.0).pvalue)
    assert c.rank_p == pytest.approx(scipy_stats.wilcoxon(d).pvalue)
    assert c.differs


def test_proportion_interval_is_clopper_pearson():
    ci = stats.proportion_ci(0, 20)
    # no success in 20: the exact upper bound is 1 − 0.025^(1/20)
    assert ci.low == 0.0 and ci.high == pytest.approx(1 - 0.025 ** (1 / 20), rel=1e-6)


def test_too_few_values_are_refused_with_the_counts():
    with pytest.raises(ValueError, match="at least 2 finite values per group, got 1 and 3"):
        stats.compare([1.0], [1.0, 2.0, 3.0])


def test_effect_tests_equal_scipys_shifted_one_sided_tests():
    """TOST is two one-sided Welch tests of the difference shifted by ±margin (SciPy's ttest_ind_from_stats with
    ``alternative``); the one-sample forms are SciPy's ttest_1samp."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(0.52, 0.03, 20), rng.normal(0.50, 0.05, 5)
    effect = stats.effect_to_summary(a, b.mean(), b.std(ddof=1), b.size)
    margin = 0.04

    def welch(shift, alternative):
        return scipy_stats.ttest_ind_from_stats(a.mean() - shift, a.std(ddof=1), a.size, b.mean(), b.std(ddof=1),
                                                b.size, equal_var=False, alternative=alternative).pvalue

    assert effect.two_sided_p() == pytest.approx(welch(0.0, "two-sided"), rel=1e-9)
    tost = max(welch(-margin, "greater"), welch(margin, "less"))
    assert effect.equivalence_p(margin) == pytest.approx(tost, rel=1e-9)
    assert effect.below_p(0.01) == pytest.approx(welch(0.01, "less"), rel=1e-9)
    assert effect.above_p(-0.01) == pytest.approx(welch(-0.01, "greater"), rel=1e-9)
    low, high = effect.interval()
    one = stats.effect_to_value(a, 0.5)
    assert one.two_sided_p() == pytest.approx(scipy_stats.ttest_1samp(a, 0.5).pvalue, rel=1e-9)
    assert one.below_p(0.0) == pytest.approx(scipy_stats.ttest_1samp(a, 0.5, alternative="less").pvalue, rel=1e-9)
    ci = scipy_stats.ttest_1samp(a, 0.5).confidence_interval(0.95)
    assert one.interval() == (pytest.approx(ci.low - 0.5, rel=1e-9), pytest.approx(ci.high - 0.5, rel=1e-9))
    assert low < effect.difference < high


def test_holm_against_the_textbook_example():
    """Holm (1979) step-down: sorted p 0.01, 0.02, 0.03, 0.04 of m = 4 → 0.04, 0.06, 0.06, 0.06 (each max(previous,
    (m − rank)·p)), returned in the input's order; NaN is left out of the family."""
    adjusted = stats.holm([0.03, 0.01, np.nan, 0.04, 0.02])
    np.testing.assert_allclose(adjusted, [0.06, 0.04, np.nan, 0.06, 0.06])
    np.testing.assert_allclose(stats.holm([0.5, 0.9]), [1.0, 1.0])  # capped at 1


def test_the_cluster_bootstrap_resamples_seeds_not_trials():
    """Ten seeds, one of which holds every fall: a pooled binomial interval of the fall rate is narrow, the cluster
    bootstrap's reaches down to 0 (a resample without that seed) and covers the pooled rate."""
    clusters = [np.zeros(50)] * 9 + [np.ones(50)]
    rate = stats.cluster_bootstrap(clusters, lambda cs: np.concatenate(cs).mean(), draws=2000)
    pooled = stats.proportion_ci(50, 500)
    assert rate.mean == pytest.approx(0.1) and rate.n == 10
    assert rate.low == 0.0 and rate.high > 0.25
    assert pooled.high - pooled.low < 0.06
