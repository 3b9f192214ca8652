"""The report of any study, made from its definition: what a study file without a hand-written report gets.

Per group (the study's ``group_by``) and per phase (the stretches between the schedule's condition changes):
v_x, CoT, J and the falls, each as mean [95 % CI] over the group's seeds of each run's last ``LAST_TRIALS`` trials
of the phase (and the phase's falls of all its trials); the trials to a prospective solution; then the comparisons
the study file names (or every pair of groups that differ in one label) with Welch's t and Mann–Whitney's U on the
seeds (``cpgjax.studies.stats``), and the learning curves of every group (``learning_curves.png``).
"""

from __future__ import annotations

import itertools
import pathlib

import numpy as np

from cpgjax import ablation
from cpgjax.studies import figures as study_figures
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import registry, stats
from cpgjax.studies.registry import LAST_TRIALS
from cpgjax.study import spec as study_spec

PROSPECTIVE_FRACTION = 0.9  # a prospective solution: a trial that walked with J ≥ this × the run's final J


def _final(values: np.ndarray, runs: np.ndarray, phase: tuple[int, int]) -> np.ndarray:
    """(R,) each run's mean of its last LAST_TRIALS trials of ``phase`` of (N, B) ``values``."""
    start, stop = phase
    return np.asarray(values)[max(stop - LAST_TRIALS, start) : stop][:, runs].mean(axis=0)


def trials_to_prospective(objective: np.ndarray, fell: np.ndarray, phase: tuple[int, int]) -> float:
    """Trials from the phase's start to its first trial that walked with J ≥ PROSPECTIVE_FRACTION × the run's final
    J (the mean of its last LAST_TRIALS trials of the phase); NaN where the final J is not positive or no trial
    reaches it."""
    start, stop = phase
    final = objective[max(stop - LAST_TRIALS, start) : stop].mean()
    ok = (objective[start:stop] >= PROSPECTIVE_FRACTION * final) & (fell[start:stop] == 0)
    return float(np.argmax(ok) + 1) if final > 0 and ok.any() else np.nan


def _metrics(result) -> dict[str, tuple]:
    """Each metric's (interval over seeds, (N, B) values): CoT cannot be negative."""
    tr = result.trials
    return {
        "v_x [m/s]": (stats.mean_ci, tr.velocity_xy_mps[..., 0]),
        "CoT": (stats.nonnegative_ci, tr.cot),
        "J": (stats.mean_ci, tr.objective),
    }


def group_table(result) -> str:
    """Per group and phase: v_x, CoT, J, falls and trials to a prospective solution."""
    tr, cond = result.trials, result.conditions
    names, all_phases = study_gaits.group_names(result), study_gaits.phases(result)
    rows = [
        f"| group | phase | v_x [m/s] | CoT | J | falls in the last {LAST_TRIALS} trials | falls / trials | trials "
        "to a prospective solution (runs never reaching one) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(names):
        runs = np.flatnonzero(names == name)
        for phase in all_phases[runs[0]]:
            start, stop = phase
            cells = [str(interval(_final(v, runs, phase))) for interval, v in _metrics(result).values()]
            cells.append(str(stats.nonnegative_ci(_final(tr.fell, runs, phase) * min(LAST_TRIALS, stop - start))))
            counts = np.array([trials_to_prospective(tr.objective[:, b], tr.fell[:, b], phase) for b in runs])
            never = int(np.isnan(counts).sum())
            reached = f"{stats.nonnegative_ci(counts)} ({never})" if never < counts.size else f"– ({never})"
            falls = tr.fell[start:stop][:, runs]
            ramp = ", on the ramp" if cond.ramp[runs[0], start] else ""
            rows.append(
                f"| {name} | {study_gaits.phase_text(result, runs[0], phase)}{ramp} | "
                + " | ".join(cells)
                + f" | {int(falls.sum())}/{falls.size} | {reached} |"
            )
    return "\n".join(rows) + "\n"


def contrasts(result, given: tuple[study_spec.Contrast, ...]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, runs a, runs b) of each comparison: ``given`` in every combination of the other ``group_by`` labels,
    or by default every pair of groups whose labels differ in one."""
    group_by, labels = result.spec.group_by, result.labels
    keys = [tuple(lab[k] for k in group_by) for lab in labels]
    groups = list(dict.fromkeys(keys))
    runs = {g: np.array([i for i, k in enumerate(keys) if k == g]) for g in groups}
    names = dict(zip(keys, study_gaits.group_names(result), strict=True))
    pairs = []
    if given:
        for c in given:
            axis = group_by.index(c.axis)
            for g in groups:
                if g[axis] == c.a:
                    other = g[:axis] + (c.b,) + g[axis + 1 :]
                    if other in runs:
                        pairs.append((g, other))
    else:
        pairs = [
            (a, b) for a, b in itertools.combinations(groups, 2) if sum(x != y for x, y in zip(a, b, strict=True)) == 1
        ]
    return [(f"{names[a]} − {names[b]}", runs[a], runs[b]) for a, b in pairs]


def comparison_table(result, given: tuple[study_spec.Contrast, ...]) -> str:
    """Each comparison per phase (both groups' phases where they have the same ones, else the final phase): J and
    CoT, a − b with its 95 % interval, Welch's and Mann–Whitney's p."""
    rows = ["| comparison | phase | J: a − b | CoT: a − b |", "|---|---|---|---|"]
    tr, all_phases = result.trials, study_gaits.phases(result)
    pairs = contrasts(result, given)
    for name, a, b in pairs:
        pa, pb = all_phases[a[0]], all_phases[b[0]]
        for phase in pa if pa == pb else pa[-1:]:
            cells = [
                str(stats.compare(_final(v, a, phase), _final(v, b, phase)))
                if min(a.size, b.size) >= stats.MIN_SEEDS
                else f"no test below {stats.MIN_SEEDS} seeds ({a.size} and {b.size})"
                for v in (tr.objective, tr.cot)
            ]
            rows.append(f"| {name} | trials {phase[0]}–{phase[1] - 1} | {cells[0]} | {cells[1]} |")
    if not pairs:
        return "\nNo two groups differ in one label: nothing to compare.\n"
    return (
        "\nComparisons (Welch's t and Mann–Whitney U, two-sided, on the seeds' final values; not corrected for "
        "multiple comparisons):\n\n" + "\n".join(rows) + "\n"
    )


def paper_lines(paper: dict) -> str:
    """The study file's [paper] figures, as given."""
    if not paper:
        return ""
    return (
        "\nThe paper (the study file's [paper] table):\n\n"
        + "\n".join(f"- {key}: {value}" for key, value in paper.items())
        + "\n"
    )


def report_for(
    given: tuple[study_spec.Contrast, ...] = (), paper: dict | None = None, description: str = ""
) -> registry.Report:
    """The generic report of a study whose file names ``given`` comparisons, ``paper`` figures and a
    ``description``."""

    def report(result: ablation.StudyResult) -> str:
        n = result.trials.objective.shape[0]
        head = f"{description}\n\n" if description else ""
        return (
            head + f"{result.spec.name}: per group and phase, each run's mean of its last {LAST_TRIALS} trials "
            f"of the phase, then {stats.over_seeds(len(result.spec.seeds))}; a prospective solution: the "
            f"first trial of the phase that walked with J ≥ {PROSPECTIVE_FRACTION:g} × the run's final J. {n} "
            f"trials per run.\n\n" + group_table(result) + comparison_table(result, given) + paper_lines(paper or {})
        )

    def figures(result: ablation.StudyResult, out: pathlib.Path) -> str:
        changes = sorted({s for p in study_gaits.phases(result) for s, _ in p} - {0})
        study_figures.learning_curves(
            out / "learning_curves.png", result, "group", changes=changes, groups=list(study_gaits.group_names(result))
        )
        return ""

    return registry.Report(registry.of_result(report), registry.of_result(figures))
