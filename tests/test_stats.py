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
