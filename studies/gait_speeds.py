"""Which gait is cheapest at each speed: the gaits study (studies/gaits.toml) read from its folder.

    python studies/gait_speeds.py results/gaits [--figure PATH]

Per gait and target v*, each seed's final values, the mean of its last 5 trials (as every report): v_x and CoT, and
the share of its trials that fell (a seed's trials depend on each other: the interval resamples seeds). A
seed *tracks* v* when its final |v_x − v*| ≤ 0.05 m/s (the tracking tolerance of docs/REPRODUCTION.md's criteria)
with no fall in those trials; a gait *walks* v* when at least half its seeds track it. CoT is compared over the
tracking seeds only (the cost of a gait at a speed it does not walk is no cost of that speed), with a seed bootstrap
interval (CoT is positive; a t interval can cross 0 on skewed samples).

At each v* the walking gait of the lowest mean CoT is set against every other walking gait: Welch's t (two-sided)
and Mann–Whitney's U, Welch's p Holm-corrected over every such pair of the study. It is *the cheapest* where each of
its differences is significant after the correction; otherwise the table names the gaits it cannot be told from.
Prints the table (markdown) and draws CoT against the achieved velocity, one curve per gait (``--figure``, default
``<folder>/cot_by_speed.png``).
"""

from __future__ import annotations

import argparse
import pathlib
from typing import NamedTuple

import numpy as np
from scipy import stats as scipy_stats

from cpgjax.studies import stats
from cpgjax.study import files as study_io

FINAL_TRIALS = 5
TRACKING_TOLERANCE_MPS = 0.05
WALKS_FRACTION = 0.5


class Cell(NamedTuple):
    """One gait at one target velocity: its seeds' final values."""

    gait: str
    target_mps: float
    velocity_mps: np.ndarray  # (seeds,) final v_x
    cot: np.ndarray  # (seeds,) final CoT
    tracks: np.ndarray  # (seeds,) bool
    fall_fraction: np.ndarray  # (seeds,) the share of the seed's trials that fell

    @property
    def walks(self) -> bool:
        return bool(self.tracks.mean() >= WALKS_FRACTION)


def cells(columns: dict[str, np.ndarray]) -> list[Cell]:
    """Every (gait, v*) of a gaits study's trial table (``study_io.read_trials``'s (trials, instances) arrays)."""
    last = slice(-FINAL_TRIALS, None)
    velocity = columns["velocity_x_mps"][last].mean(axis=0)
    cot = columns["cost_of_transport"][last].mean(axis=0)
    falls = columns["fell"] | columns["failed"]
    fell = falls[last].any(axis=0)
    gait, target = columns["gait"][0], columns["target_velocity_mps"][0]
    tracks = (np.abs(velocity - target) <= TRACKING_TOLERANCE_MPS) & ~fell
    out = []
    for g in dict.fromkeys(gait):
        for v in np.unique(target):
            here = (gait == g) & (target == v)
            out.append(Cell(str(g), float(v), velocity[here], cot[here], tracks[here], falls[:, here].mean(axis=0)))
    return out


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else np.nan


def bootstrap_ci(values: np.ndarray) -> stats.Interval:
    """The mean with a percentile 95 % interval of seed resamples (``stats.cluster_bootstrap``, one value a seed)."""
    if len(values) < stats.MIN_SEEDS:
        return stats.Interval(_mean(values), np.nan, np.nan, len(values))
    return stats.cluster_bootstrap(list(values), _mean)


class Cheapest(NamedTuple):
    target_mps: float
    gait: str
    # (gait, cheapest − it, Welch p, Mann–Whitney p); None and NaN below stats.MIN_SEEDS tracking seeds in either
    rivals: list[tuple[str, stats.Effect | None, float, float]]


def cheapest_by_speed(all_cells: list[Cell]) -> tuple[list[Cheapest], np.ndarray]:
    """At each v*: the walking gait of the lowest mean CoT and its differences to the other walking gaits; and the
    Holm-corrected Welch p of every difference, in the order of the rivals."""
    out, pvalues = [], []
    for v in sorted({c.target_mps for c in all_cells}):
        walking = [c for c in all_cells if c.target_mps == v and c.walks]
        if not walking:
            out.append(Cheapest(v, "", []))
            continue
        best = min(walking, key=lambda c: _mean(c.cot[c.tracks]))
        rivals = []
        for c in walking:
            if c is best:
                continue
            a, b = best.cot[best.tracks], c.cot[c.tracks]
            if min(a.size, b.size) < stats.MIN_SEEDS:
                rivals.append((c.gait, None, np.nan, np.nan))
                pvalues.append(np.nan)
                continue
            effect = stats.effect_between(a, b)
            rank_p = float(scipy_stats.mannwhitneyu(a, b, alternative="two-sided").pvalue)
            rivals.append((c.gait, effect, effect.two_sided_p(), rank_p))
            pvalues.append(effect.two_sided_p())
        out.append(Cheapest(v, best.gait, rivals))
    return out, stats.holm(pvalues)


def effect_n(best: Cheapest, gait: str, all_cells: list[Cell]) -> tuple[int, int]:
    """The tracking seeds of the cheapest gait and of ``gait`` at ``best``'s v*."""

    def n(g):
        return int(next(c for c in all_cells if c.gait == g and c.target_mps == best.target_mps).tracks.sum())

    return n(best.gait), n(gait)


def table(all_cells: list[Cell]) -> str:
    """Markdown: each cell's tracking seeds, v_x and CoT; then the cheapest gait at each v* with its tests."""
    lines = [
        "| gait | v* [m/s] | seeds tracking | final v_x [m/s] (all seeds) | final CoT (tracking seeds, "
        "bootstrap CI) | falls / trials per seed (bootstrap CI) |",
        "|---|---|---|---|---|---|",
    ]
    for c in all_cells:
        cot = bootstrap_ci(c.cot[c.tracks])
        shown = (
            "–"
            if not c.tracks.any()
            else f"{cot.mean:.3f} (no interval below {stats.MIN_SEEDS} seeds)"
            if np.isnan(cot.low)
            else str(cot)
        )
        lines.append(
            f"| {c.gait} | {c.target_mps:g} | {int(c.tracks.sum())}/{c.tracks.size} "
            f"| {stats.mean_ci(c.velocity_mps)} | {shown} | {bootstrap_ci(c.fall_fraction)} |"
        )
    best, holm = cheapest_by_speed(all_cells)
    lines += [
        "",
        "| v* [m/s] | cheapest walking gait | CoT difference to each other walking gait: cheapest − it, "
        "Welch 95 % CI, Welch p (Holm), Mann–Whitney p (n) | verdict |",
        "|---|---|---|---|",
    ]
    k = 0
    for b in best:
        if not b.gait:
            lines.append(f"| {b.target_mps:g} | no gait walks it | – | – |")
            continue
        parts, tied = [], []
        for gait, effect, _, rank_p in b.rivals:
            if effect is None:
                parts.append(f"{gait}: no test (fewer than {stats.MIN_SEEDS} tracking seeds)")
            else:
                low, high = effect.interval()
                n_best, n_gait = effect_n(b, gait, all_cells)
                least_p = stats.mann_whitney_least_p(n_best, n_gait)
                parts.append(
                    f"{gait}: {effect.difference:+.3f} [{low:+.3f}, {high:+.3f}], p = {holm[k]:.2g}, "
                    f"MW {stats.rank_p_text(rank_p, least_p, 'p = ')} (n = {n_best}, {n_gait})"
                )
            if not holm[k] < stats.ALPHA:
                tied.append(gait)
            k += 1
        verdict = (
            "the only walking gait"
            if not b.rivals
            else "cheapest"
            if not tied
            else f"not shown cheaper than {', '.join(tied)}"
        )
        lines.append(f"| {b.target_mps:g} | {b.gait} | {'; '.join(parts) or '–'} | {verdict} |")
    return "\n".join(lines)


def figure(all_cells: list[Cell], path: pathlib.Path) -> None:
    """CoT (tracking seeds, bootstrap interval) against the achieved v_x (its t interval), one curve per gait, the
    targets a gait does not walk left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for gait in dict.fromkeys(c.gait for c in all_cells):
        pts = [
            (stats.mean_ci(c.velocity_mps[c.tracks]), bootstrap_ci(c.cot[c.tracks]))
            for c in all_cells
            if c.gait == gait and c.walks
        ]
        if not pts:
            continue
        x = np.array([p[0].mean for p in pts])
        y = np.array([p[1].mean for p in pts])
        xerr = np.array([[p[0].mean - p[0].low, p[0].high - p[0].mean] for p in pts]).T
        yerr = np.array([[p[1].mean - p[1].low, p[1].high - p[1].mean] for p in pts]).T
        ax.errorbar(x, y, xerr=xerr, yerr=yerr, marker="o", capsize=3, label=gait)
    ax.set_xlabel("achieved v_x [m/s] (seeds tracking v*)")
    ax.set_ylabel("cost of transport (mechanical)")
    ax.set_title("CoT against speed per gait, VMC+Tegotae, 95 % CIs")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=pathlib.Path, help="a gaits study's results folder (its trials.parquet)")
    parser.add_argument(
        "--figure", type=pathlib.Path, help="where to draw the figure (default: <folder>/cot_by_speed.png)"
    )
    args = parser.parse_args(argv)
    trials = args.folder / "trials.parquet"
    if not trials.is_file():
        parser.error(f"{trials}: no such file (run `cpgjax study gaits` first)")
    columns = study_io.read_trials(trials)
    if "gait" not in columns:
        parser.error(f"{trials} has no gait column: not a study with a gaits axis")
    all_cells = cells(columns)
    print(table(all_cells))
    out = args.figure or args.folder / "cot_by_speed.png"
    figure(all_cells, out)
    print(f"\nfigure: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
