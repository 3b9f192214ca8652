"""A study run with ``--safe`` against the same study without it (same seeds): falls during adaptation, final J and
velocity, trials to recover after each condition change, and safety's cost, per group (docs/decisions.md §17).

    python studies/safe_comparison.py results/load_adaptation results/load_adaptation_safe
    python studies/safe_comparison.py results/slope_paper results/slope_lean_ramp --names paper,lean_ramp

Reads each folder's ``trials.parquet``. Per phase of the conditions (payload, slope, friction, target; inference-mode
trials are their own phase): falls during the phase's optimized trials, the final J and velocity (mean of the phase's
last 5 trials per run; mean [95 % CI] over seeds), and the trials from the phase's start to its first prospective
trial (no fall, J ≥ 90 % of the run's best in the phase). Safe against unconstrained: the falls' ratio with a paired
Wilcoxon test over seeds; final J paired over seeds (the same seed in both runs: paired t and Wilcoxon). Each arm's
falls by where they came from (:func:`fall_breakdown`).
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from cpgjax.studies import registry, stats
from cpgjax.study import files as study_io

LAST_TRIALS = 5
CONDITIONS = ("payload_kg", "slope_deg", "friction", "target_velocity_mps", "inference")


def phases(columns, instance: int) -> list[tuple[int, int]]:
    """[start, stop) of each phase of one instance: a new phase wherever any condition changes."""
    fields = [columns[c][:, instance] for c in CONDITIONS]
    starts = sorted(set().union(*(registry.phase_starts(f) for f in fields))) + [len(fields[0])]
    return list(zip(starts[:-1], starts[1:], strict=True))


def recover(j: np.ndarray, fell: np.ndarray) -> float:
    ok = (fell == 0) & (j >= 0.9 * j.max())
    return float(np.argmax(ok) + 1) if ok.any() else np.nan


def fall_breakdown(columns) -> dict[str, int]:
    """Where an arm's falls during optimization came from: the first trial of a condition (proposed for the
    context of the one before), a trial right after a fall (a restart from standing, docs/REPRODUCTION.md), a
    fallback (nothing certified safe), and the rest (proposals after a walking trial)."""
    fell = (columns["fell"] > 0) | (columns["failed"] > 0)
    optimized = columns["inference"] == 0
    condition = np.stack([columns[c] for c in CONDITIONS[:-1]], axis=-1)
    first, after_fall = np.zeros_like(fell), np.zeros_like(fell)
    first[1:] = np.any(condition[1:] != condition[:-1], axis=-1)
    after_fall[1:] = fell[:-1] & ~first[1:]
    fallback = columns["safe_fallback"] > 0
    counted = fell & optimized
    return {
        "first trial of a condition": int((counted & first).sum()),
        "after a fall": int((counted & after_fall).sum()),
        "fallback": int((counted & ~first & ~after_fall & fallback).sum()),
        "after a walk": int((counted & ~first & ~after_fall & ~fallback).sum()),
    }


def group_keys(columns) -> np.ndarray:
    labels = [c for c in ("controller", "schedule") if c in columns]
    return np.array([", ".join(str(columns[c][0, b]) for c in labels) for b in range(columns["instance"].shape[1])])


def compare(
    unsafe_dir: pathlib.Path,
    safe_dir: pathlib.Path,
    names: tuple[str, str] = ("unconstrained", "safe"),
    what: str | None = None,
) -> str:
    """The comparison of the module docstring; ``names`` label the two arms (another pair of the same study, for
    example two start-ups: ``("paper", "lean_ramp")``), ``what`` the first sentence's subject."""
    a, b = names
    runs = {
        a: study_io.read_trials(unsafe_dir / "trials.parquet"),
        b: study_io.read_trials(safe_dir / "trials.parquet"),
    }
    base = runs[a]
    groups = group_keys(base)
    subject = what or f"Safe (`--safe`, {safe_dir}) against unconstrained ({unsafe_dir})"
    lines = [
        f"{subject}, the same seeds. Per phase: falls in "
        "its optimized trials (total over seeds), final J and v_x (mean of its last "
        f"{LAST_TRIALS} trials per run, mean [95 % CI] over seeds), trials to a prospective solution (no fall, "
        "J ≥ 90 % of the run's best in the phase; runs that never reach one in parentheses); tests paired over "
        "seeds.",
        "",
    ]
    lines += [
        f"| group | phase (trials) | falls {a} | falls {b} | final J {a} | final J {b} | "
        f"J {b} − {a} (paired t, Wilcoxon) | v_x {a} | v_x {b} | to recover {a} | "
        f"to recover {b} |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    totals = {a: [], b: []}
    for group in dict.fromkeys(groups):
        members = np.flatnonzero(groups == group)
        for start, stop in phases(base, members[0]):
            cells = {}
            for arm, columns in runs.items():
                j, fell = columns["objective"][:, members], columns["fell"][:, members]
                v = columns["velocity_x_mps"][:, members]
                inference = columns["inference"][start, members[0]] > 0
                falls = fell[start:stop].sum(axis=0)
                if not inference:
                    totals[arm].append(falls)
                final = slice(max(stop - LAST_TRIALS, start), stop)
                to_recover = np.array([recover(j[start:stop, k], fell[start:stop, k]) for k in range(len(members))])
                cells[arm] = dict(
                    falls=int(falls.sum()),
                    j=j[final].mean(axis=0),
                    v=v[final].mean(axis=0),
                    recover=to_recover,
                    inference=inference,
                )
            u, s = cells[a], cells[b]
            never = lambda r: int(np.isnan(r).sum())  # noqa: E731
            label = f"{start}–{stop - 1}" + (" inference" if u["inference"] else "")
            lines.append(
                f"| {group} | {label} | {u['falls']} | {s['falls']} | {stats.mean_ci(u['j'])} | "
                f"{stats.mean_ci(s['j'])} | {stats.paired_text(s['j'], u['j'])} | {stats.mean_ci(u['v'])} | "
                f"{stats.mean_ci(s['v'])} | {stats.nonnegative_ci(u['recover'])} ({never(u['recover'])}) | "
                f"{stats.nonnegative_ci(s['recover'])} ({never(s['recover'])}) |"
            )
    falls_u = np.sum(totals[a], axis=0) if totals[a] else np.zeros(1)
    falls_s = np.sum(totals[b], axis=0) if totals[b] else np.zeros(1)
    ratio = falls_u.sum() / max(falls_s.sum(), 1)
    lines += [
        "",
        f"Falls during optimization, all phases: {int(falls_u.sum())} {a}, {int(falls_s.sum())} "
        f"{b} ({ratio:.1f}× fewer{'' if falls_s.sum() else f', {b} had none: a lower bound'}); per run, {b} − "
        f"{a}: {stats.paired_text(falls_s, falls_u)}.",
    ]
    for arm, columns in runs.items():
        parts = ", ".join(f"{label} {count}" for label, count in fall_breakdown(columns).items())
        lines.append(f"Falls of the {arm} run by where they came from: {parts}.")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("unconstrained", type=pathlib.Path, help="the study folder without --safe")
    parser.add_argument("safe", type=pathlib.Path, help="the same study with --safe")
    parser.add_argument(
        "--names",
        default="unconstrained,safe",
        help="the two arms' names in the table (e.g. paper,lean_ramp for two start-ups)",
    )
    args = parser.parse_args()
    names = tuple(args.names.split(","))
    if len(names) != 2:
        parser.error(f"--names {args.names!r}: need two names, comma-separated")
    what = (
        None
        if names == ("unconstrained", "safe")
        else f"{names[1]} ({args.safe}) against {names[0]} ({args.unconstrained})"
    )
    print(compare(args.unconstrained, args.safe, names, what))


if __name__ == "__main__":
    main()
