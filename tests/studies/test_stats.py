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
    with pytest.raises(ValueError, match="at least 3 finite values per group, got 2 and 3"):
        stats.compare([1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="at least 3 finite pairs, got 2"):
        stats.paired([1.0, 2.0], [0.0, 0.5])


def test_below_three_values_there_is_no_interval_and_the_line_says_so():
    for ci in (stats.mean_ci([0.4, 2.0]), stats.nonnegative_ci([0.4, 2.0]), stats.mean_ci([0.7])):
        assert np.isnan(ci.low) and np.isnan(ci.high) and "[" not in str(ci)
    assert str(stats.mean_ci([0.4, 2.0])) == "1.200"
    assert stats.too_few_line(2) == "2 seeds: no interval or test below 3 seeds."
    assert stats.too_few_line(1) == "1 seed: no interval or test below 3 seeds."
    assert stats.too_few_line(3) == ""


def test_the_nonnegative_interval_is_scipys_t_interval_cut_at_zero():
    """SciPy's one-sample t interval, its part below 0 cut off; where it stays above 0 it is the t interval."""
    x = np.array([0.62, 0.55, 3.9, 0.58])  # one seed barely moved: the t interval reaches below 0
    reference = scipy_stats.ttest_1samp(x, 0.0).confidence_interval(0.95)
    ours = stats.nonnegative_ci(x)
    assert reference.low < 0.0 and ours.low == 0.0 and ours.high == pytest.approx(reference.high, rel=1e-12)
    assert ours.mean == pytest.approx(x.mean()) and ours.n == 4
    assert str(ours) == f"{x.mean():.3f} [0.000, {ours.high:.3f}]"
    y = np.random.default_rng(4).lognormal(-0.5, 0.3, 7)
    reference = scipy_stats.ttest_1samp(y, 0.0).confidence_interval(0.95)
    assert (stats.nonnegative_ci(y).low, stats.nonnegative_ci(y).high) == (
        pytest.approx(reference.low, rel=1e-12),
        pytest.approx(reference.high, rel=1e-12),
    )


def test_a_nonnegative_interval_never_goes_below_zero_and_keeps_the_t_coverage():
    """Skewed nonnegative seeds, many of them 0 (falls, CoT of runs that barely move): no interval goes below 0, and
    on lognormal seeds it covers the true mean as often as the t interval does (the cut never drops the mean)."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        x = rng.exponential(1.0, rng.integers(3, 8)) * (rng.random(1) < 0.8)
        assert stats.nonnegative_ci(x).low >= 0.0
    zero = stats.nonnegative_ci(np.zeros(4))
    assert (zero.low, zero.high) == (0.0, 0.0)
    true, covered_cut, covered_t = np.exp(0.5**2 / 2), 0, 0
    for _ in range(2000):
        x = rng.lognormal(0.0, 0.5, 4)
        cut, t = stats.nonnegative_ci(x), stats.mean_ci(x)
        covered_cut += cut.low <= true <= cut.high
        covered_t += t.low <= true <= t.high
    assert covered_cut == covered_t and covered_cut / 2000 > 0.9
    with pytest.raises(ValueError, match="1 negative values .the least -0.1.; a quantity of either sign takes mean_ci"):
        stats.nonnegative_ci([0.2, -0.1, 0.3])


def test_a_paired_line_below_three_pairs_says_there_is_no_test():
    assert stats.paired_text([1.0, 2.0, np.nan], [0.5, 1.0, 1.5]) == "no test below 3 pairs (n = 2)"
    a, b = [1.0, 2.0, 3.5, 4.0], [0.5, 1.0, 1.5, 3.0]
    assert stats.paired_text(a, b) == str(stats.paired(a, b))


@pytest.mark.parametrize("n_a, n_b", [(2, 2), (3, 3), (3, 4), (4, 4), (2, 6), (5, 5)])
def test_mann_whitneys_least_p_is_scipys_exact_p_of_separated_samples(n_a, n_b):
    """The most extreme ordering (every a below every b) gives the exact test's smallest two-sided p."""
    a, b = np.arange(n_a, dtype=float), n_a + np.arange(n_b, dtype=float)
    exact = scipy_stats.mannwhitneyu(a, b, alternative="two-sided", method="exact").pvalue
    assert stats.mann_whitney_least_p(n_a, n_b) == pytest.approx(exact, rel=1e-12)
    assert stats.mann_whitney_least_p(2, 2) == pytest.approx(1 / 3)


@pytest.mark.parametrize("n", [1, 3, 5, 6, 8])
def test_wilcoxons_least_p_is_scipys_exact_p_of_same_signed_differences(n):
    exact = scipy_stats.wilcoxon(np.arange(1.0, n + 1), method="exact").pvalue
    assert stats.wilcoxon_least_p(n) == pytest.approx(exact, rel=1e-12)
    assert stats.wilcoxon_least_p(5) == 0.0625


def test_a_rank_test_that_cannot_reach_five_percent_says_so_instead_of_its_p():
    small = stats.compare([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])  # 3 against 3: the least p is 0.1
    assert small.rank_least_p == pytest.approx(0.1)
    assert "Mann–Whitney cannot reach p < 0.05 at these sizes (least p 0.1)" in str(small)
    assert "Mann–Whitney p" not in str(small)
    large = stats.compare([1.0, 2.0, 3.0, 3.5], [4.0, 5.0, 6.0, 7.0])  # 4 against 4: 2/70
    assert f"Mann–Whitney p = {large.rank_p:.2g}" in str(large) and large.rank_p < 0.05
    pairs = stats.paired([1.0, 2.0, 3.0, 4.0, 5.0], [0.0, 0.5, 1.0, 1.5, 2.0])
    assert pairs.rank_least_p == 0.0625 and "Wilcoxon cannot reach p < 0.05" in str(pairs)


def test_effect_tests_equal_scipys_shifted_one_sided_tests():
    """TOST is two one-sided Welch tests of the difference shifted by ±margin (SciPy's ttest_ind_from_stats with
    ``alternative``); the one-sample forms are SciPy's ttest_1samp."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(0.52, 0.03, 20), rng.normal(0.50, 0.05, 5)
    effect = stats.effect_to_summary(a, b.mean(), b.std(ddof=1), b.size)
    margin = 0.04

    def welch(shift, alternative):
        return scipy_stats.ttest_ind_from_stats(
            a.mean() - shift,
            a.std(ddof=1),
            a.size,
            b.mean(),
            b.std(ddof=1),
            b.size,
            equal_var=False,
            alternative=alternative,
        ).pvalue

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
