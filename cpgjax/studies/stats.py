"""The statistics behind every "agrees" and "differs" of a study: means with 95 % confidence intervals, and two-sample
comparisons with an effect size, its confidence interval and a test (SciPy's).

* :func:`mean_ci` — the mean over seeds with the Student-t 95 % interval (v_x, J: quantities of either sign).
* :func:`nonnegative_ci` — the mean over seeds of a quantity that cannot be negative (CoT, falls, trial counts): the
  Student-t 95 % interval with its part below 0 cut off, which keeps the t interval's coverage.
* Below :data:`MIN_SEEDS` values no interval and no test is given (:func:`too_few_line` is the table's line saying
  so); a rank test that cannot reach p < 0.05 at its sample size says so (:func:`mann_whitney_least_p`,
  :func:`wilcoxon_least_p`: the smallest two-sided p of the exact tests) instead of printing its p.
* :func:`compare` — two independent groups (e.g. two controllers, or ours against the paper's summary): the difference
  of means with the Welch–Satterthwaite 95 % interval, Welch's t-test and, on raw samples, Mann–Whitney's U test.
* :func:`compare_to_summary` — our seeds against a published mean ± std over n seeds (the paper gives no raw data):
  Welch's test from the two summaries.
* :func:`paired` — one change on the same instances (e.g. one physics component swapped): the mean paired difference
  with its t interval and the Wilcoxon signed-rank test.
* :class:`Effect` — a difference with its standard error and degrees of freedom (:func:`effect_to_summary`,
  :func:`effect_to_value`, :func:`effect_between`), and the tests a verdict needs: two-sided, equivalence within a
  margin (TOST) and one-sided; :func:`holm` corrects a family of p-values.
* :func:`cluster_bootstrap` — an interval of a statistic of clustered data (trials within seeds) that resamples the
  clusters, so trials that depend on each other within a seed are not counted as independent.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
ALPHA = 1.0 - CONFIDENCE
MIN_SEEDS = 3  # fewer values: no interval and no test (a t interval of 2 values is ±12.7·|a − b|/2 wide, of 1 has no
# width; Mann–Whitney on 2 against 2 cannot go below p = 1/3)


class Interval(NamedTuple):
    """A mean with its 95 % interval over ``n`` values; ``low`` and ``high`` NaN where no interval is given (fewer
    than MIN_SEEDS values)."""

    mean: float
    low: float
    high: float
    n: int

    def __str__(self) -> str:
        return self.cell()

    def cell(self, sign: str = "") -> str:
        """ "mean [low, high]", or the mean alone where there is no interval; ``sign`` "+" writes every sign."""
        if np.isnan(self.low) or np.isnan(self.high):
            return f"{self.mean:{sign}.3f}"
        return f"{self.mean:{sign}.3f} [{self.low:{sign}.3f}, {self.high:{sign}.3f}]"


def over_seeds(n: int) -> str:
    """What a table's cells are over ``n`` seeds: "mean [95 % CI] over n seeds", or below MIN_SEEDS the mean alone."""
    return (
        f"mean [95 % CI] over {n} seeds"
        if n >= MIN_SEEDS
        else f"mean over {n} seed{'' if n == 1 else 's'} (no interval below {MIN_SEEDS})"
    )


def too_few_line(n: int) -> str:
    """The line a table gives where its groups have ``n`` < MIN_SEEDS seeds (its cells then hold means alone); empty
    from MIN_SEEDS on."""
    if n >= MIN_SEEDS:
        return ""
    return f"{n} seed{'' if n == 1 else 's'}: no interval or test below {MIN_SEEDS} seeds."


def mann_whitney_least_p(n_a: int, n_b: int) -> float:
    """The smallest two-sided p of Mann–Whitney's exact U test with n_a and n_b values (no ties): each tail's most
    extreme ordering has probability 1 / C(n_a + n_b, n_a), so 2 / C(n_a + n_b, n_a), at most 1 (2 vs 2: 1/3)."""
    return min(1.0, 2.0 / math.comb(n_a + n_b, n_a))


def wilcoxon_least_p(n: int) -> float:
    """The smallest two-sided p of Wilcoxon's exact signed-rank test on n non-zero differences: every sign alike,
    probability 1 / 2^n per tail, so 2 / 2^n, at most 1 (n = 5: 0.0625)."""
    return min(1.0, 2.0 / 2.0**n)


def rank_p_text(p: float, least_p: float, label: str = "") -> str:
    """A rank test's p after ``label`` (e.g. "p = "), or where the test cannot go below ALPHA at its sizes
    (``least_p``, its smallest p) a phrase saying so in its place."""
    if least_p >= ALPHA:
        return f"cannot reach p < {ALPHA:g} at these sizes (least p {least_p:.2g})"
    return f"{label}{p:.2g}"


class Comparison(NamedTuple):
    """a − b: the difference of means, its 95 % interval, and two tests' two-sided p-values: a t-test (Welch's, or
    the paired one) and a rank test (Mann–Whitney's U, or Wilcoxon's signed rank for pairs)."""

    difference: float
    low: float
    high: float
    t_p: float
    rank_p: float  # NaN where only summaries are known
    n_a: int
    n_b: int
    tests: tuple[str, str] = ("Welch", "Mann–Whitney")
    rank_least_p: float = 0.0  # the smallest p the rank test can give at these sizes (exact, two-sided)

    @property
    def differs(self) -> bool:
        """The t-test rejects equal means at the 5 % level."""
        return bool(self.t_p < ALPHA)

    def rank_text(self) -> str:
        """The rank test's p as :func:`rank_p_text` writes it."""
        return rank_p_text(self.rank_p, self.rank_least_p)

    def __str__(self) -> str:
        rank = (
            ""
            if np.isnan(self.rank_p)
            else (f", {self.tests[1]} {rank_p_text(self.rank_p, self.rank_least_p, 'p = ')}")
        )
        n = f"n = {self.n_a}" if self.tests[0] == "paired t" else f"n = {self.n_a}, {self.n_b}"
        return (
            f"Δ = {self.difference:+.3f} [{self.low:+.3f}, {self.high:+.3f}], {self.tests[0]} p = "
            f"{self.t_p:.2g}{rank} ({n})"
        )


def _finite(values) -> np.ndarray:
    x = np.asarray(values, np.float64).ravel()
    return x[np.isfinite(x)]


def mean_ci(values) -> Interval:
    """Mean and Student-t 95 % interval of the finite values (no interval below MIN_SEEDS values)."""
    x = _finite(values)
    if x.size == 0:
        return Interval(np.nan, np.nan, np.nan, 0)
    m = float(np.mean(x))
    if x.size < MIN_SEEDS:
        return Interval(m, np.nan, np.nan, int(x.size))
    half = float(stats.t.ppf(1.0 - ALPHA / 2, x.size - 1) * np.std(x, ddof=1) / np.sqrt(x.size))
    return Interval(m, m - half, m + half, int(x.size))


def nonnegative_ci(values) -> Interval:
    """Mean and 95 % interval of finite values that cannot be negative (one value a seed): the Student-t interval
    (:func:`mean_ci`) with its part below 0 cut off. The mean lies in [0, ∞), so wherever the t interval covers it so
    does the cut one: the coverage is the t interval's; no interval below MIN_SEEDS values.

    Raises:
      ValueError: a value is negative.
    """
    x = _finite(values)
    if np.any(x < 0.0):
        raise ValueError(
            f"nonnegative_ci got {int(np.sum(x < 0.0))} negative values (the least {x.min():g}); a "
            "quantity of either sign takes mean_ci"
        )
    ci = mean_ci(x)
    return ci._replace(low=max(ci.low, 0.0)) if ci.n >= MIN_SEEDS else ci


def _welch(mean_a, var_a, n_a, mean_b, var_b, n_b) -> tuple[float, float, float, float]:
    """(difference, low, high, p) of Welch's test from the groups' means, sample variances and sizes."""
    effect = _welch_effect(mean_a, var_a, n_a, mean_b, var_b, n_b)
    return (effect.difference, *effect.interval(), effect.two_sided_p())


def compare(a, b) -> Comparison:
    """Two independent samples (e.g. two controllers' final J over seeds): mean(a) − mean(b) with its Welch 95 %
    interval, Welch's t-test and Mann–Whitney's U test (both two-sided).

    Raises:
      ValueError: fewer than MIN_SEEDS finite values in a group.
    """
    x, y = _finite(a), _finite(b)
    if x.size < MIN_SEEDS or y.size < MIN_SEEDS:
        raise ValueError(f"compare needs at least {MIN_SEEDS} finite values per group, got {x.size} and {y.size}")
    diff, low, high, p = _welch(x.mean(), x.var(ddof=1), x.size, y.mean(), y.var(ddof=1), y.size)
    mw = float(stats.mannwhitneyu(x, y, alternative="two-sided").pvalue)
    return Comparison(
        diff, low, high, p, mw, int(x.size), int(y.size), rank_least_p=mann_whitney_least_p(x.size, y.size)
    )


def compare_to_summary(a, mean_b: float, std_b: float, n_b: int) -> Comparison:
    """Our samples ``a`` against a published mean ± std over ``n_b`` seeds: Welch's test from the summaries (the
    published std is taken as the sample std)."""
    x = _finite(a)
    if x.size < MIN_SEEDS or n_b < 2:
        raise ValueError(
            f"compare_to_summary needs at least {MIN_SEEDS} values of ours and 2 of theirs, got {x.size} and {n_b}"
        )
    diff, low, high, p = _welch(x.mean(), x.var(ddof=1), x.size, mean_b, std_b**2, n_b)
    return Comparison(diff, low, high, p, np.nan, int(x.size), int(n_b))


def paired(a, b) -> Comparison:
    """The same instances under two settings: mean(a − b) with its t 95 % interval, the paired t-test's p and the
    Wilcoxon signed-rank test's; pairs with a non-finite value are dropped."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired samples need the same length, got {a.size} and {b.size}")
    keep = np.isfinite(a) & np.isfinite(b)
    d = a[keep] - b[keep]
    if d.size < MIN_SEEDS:
        raise ValueError(f"paired needs at least {MIN_SEEDS} finite pairs, got {d.size}")
    ci = mean_ci(d)
    pair_tests = ("paired t", "Wilcoxon")
    least = wilcoxon_least_p(int(np.count_nonzero(d)))  # Wilcoxon leaves out the zero differences
    if np.all(d == 0.0):
        return Comparison(0.0, 0.0, 0.0, 1.0, 1.0, int(d.size), int(d.size), pair_tests, least)
    t_p = float(stats.ttest_1samp(d, 0.0).pvalue)
    w_p = float(stats.wilcoxon(d).pvalue)
    return Comparison(ci.mean, ci.low, ci.high, t_p, w_p, int(d.size), int(d.size), pair_tests, least)


def paired_text(a, b) -> str:
    """:func:`paired`'s line, or where there are fewer than MIN_SEEDS finite pairs one saying there is no test."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    n = int(np.sum(np.isfinite(a) & np.isfinite(b))) if a.shape == b.shape else MIN_SEEDS
    return str(paired(a, b)) if n >= MIN_SEEDS else f"no test below {MIN_SEEDS} pairs (n = {n})"


def proportion_ci(successes: int, trials: int) -> Interval:
    """A proportion with its Clopper–Pearson (exact) 95 % interval."""
    if trials <= 0:
        return Interval(np.nan, np.nan, np.nan, 0)
    ci = stats.binomtest(int(successes), int(trials)).proportion_ci(CONFIDENCE, method="exact")
    return Interval(successes / trials, float(ci.low), float(ci.high), int(trials))


def fisher_p(successes_a: int, trials_a: int, successes_b: int, trials_b: int) -> float:
    """Fisher's exact test (two-sided) of two proportions, successes_a / trials_a against successes_b / trials_b; NaN
    when either group is empty."""
    if trials_a <= 0 or trials_b <= 0:
        return np.nan
    table = [[int(successes_a), int(trials_a - successes_a)], [int(successes_b), int(trials_b - successes_b)]]
    return float(stats.fisher_exact(table).pvalue)


class Effect(NamedTuple):
    """A difference of means ``difference`` (ours − theirs) with its standard error and the t distribution's degrees
    of freedom (Welch–Satterthwaite for two groups, n − 1 for one)."""

    difference: float
    se: float
    dof: float

    def interval(self, confidence: float = CONFIDENCE) -> tuple[float, float]:
        half = float(stats.t.ppf(0.5 + confidence / 2, self.dof) * self.se)
        return self.difference - half, self.difference + half

    def two_sided_p(self) -> float:
        """H0: no difference."""
        return (
            float(2.0 * stats.t.sf(abs(self.difference) / self.se, self.dof))
            if self.se > 0
            else float(self.difference == 0.0)
        )

    def equivalence_p(self, margin: float) -> float:
        """The two one-sided tests (TOST) of H0: |difference| ≥ margin; p < α shows equivalence within ±margin (the
        (1 − 2α) interval lies inside it)."""
        if self.se == 0.0:
            return float(abs(self.difference) >= margin)
        lower = stats.t.sf((self.difference + margin) / self.se, self.dof)  # H0: difference ≤ −margin
        upper = stats.t.cdf((self.difference - margin) / self.se, self.dof)  # H0: difference ≥ +margin
        return float(max(lower, upper))

    def below_p(self, bound: float) -> float:
        """One-sided test of H0: difference ≥ bound (p < α shows difference < bound)."""
        if self.se == 0.0:
            return float(self.difference >= bound)
        return float(stats.t.cdf((self.difference - bound) / self.se, self.dof))

    def above_p(self, bound: float) -> float:
        """One-sided test of H0: difference ≤ bound (p < α shows difference > bound)."""
        if self.se == 0.0:
            return float(self.difference <= bound)
        return float(stats.t.sf((self.difference - bound) / self.se, self.dof))


def _welch_effect(mean_a, var_a, n_a, mean_b, var_b, n_b) -> Effect:
    """The Welch–Satterthwaite :class:`Effect` of mean_a − mean_b from the groups' means, sample variances and
    sizes."""
    se2 = var_a / n_a + var_b / n_b
    if se2 == 0.0:
        return Effect(float(mean_a - mean_b), 0.0, float(n_a + n_b - 2))
    dof = se2**2 / ((var_a / n_a) ** 2 / (n_a - 1) + (var_b / n_b) ** 2 / (n_b - 1))
    return Effect(float(mean_a - mean_b), float(np.sqrt(se2)), float(dof))


def effect_to_summary(a, mean_b: float, std_b: float, n_b: int) -> Effect:
    """Our samples ``a`` − a published mean ± std over ``n_b`` seeds (Welch from the summaries)."""
    x = _finite(a)
    if x.size < 2 or n_b < 2:
        raise ValueError(f"effect_to_summary needs at least 2 values per group, got {x.size} and {n_b}")
    return _welch_effect(x.mean(), x.var(ddof=1), x.size, mean_b, std_b**2, n_b)


def effect_to_value(a, value: float) -> Effect:
    """Our samples ``a`` − a fixed value (one-sample t)."""
    x = _finite(a)
    if x.size < 2:
        raise ValueError(f"effect_to_value needs at least 2 values, got {x.size}")
    return Effect(float(x.mean() - value), float(np.std(x, ddof=1) / np.sqrt(x.size)), float(x.size - 1))


def effect_between(a, b) -> Effect:
    """mean(a) − mean(b) of two independent samples (Welch)."""
    x, y = _finite(a), _finite(b)
    if x.size < 2 or y.size < 2:
        raise ValueError(f"effect_between needs at least 2 finite values per group, got {x.size} and {y.size}")
    return _welch_effect(x.mean(), x.var(ddof=1), x.size, y.mean(), y.var(ddof=1), y.size)


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjustment of one family's p-values (same order; NaN stays NaN and does not count): the k-th
    smallest of m becomes max over j ≤ k of min(1, (m − j + 1)·p_(j))."""
    p = np.asarray(pvalues, np.float64)
    out = np.full(p.shape, np.nan)
    keep = np.flatnonzero(np.isfinite(p))
    order = keep[np.argsort(p[keep], kind="stable")]
    m, running = order.size, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def cluster_bootstrap(clusters: list, statistic, draws: int = 10_000, seed: int = 0) -> Interval:
    """``statistic(list of clusters)`` with the percentile 95 % interval of ``draws`` resamples of the clusters with
    replacement (each cluster whole: the trials of one seed stay together). Resamples where the statistic is not
    finite (e.g. no trial after a fall drawn) are left out; ``n`` is the number of clusters."""
    rng = np.random.default_rng(seed)
    value = float(statistic(clusters))
    picks = rng.integers(0, len(clusters), size=(draws, len(clusters)))
    boot = np.array([statistic([clusters[i] for i in row]) for row in picks], np.float64)
    boot = boot[np.isfinite(boot)]
    if boot.size == 0:
        return Interval(value, np.nan, np.nan, len(clusters))
    low, high = np.quantile(boot, [ALPHA / 2, 1.0 - ALPHA / 2])
    return Interval(value, float(low), float(high), len(clusters))
