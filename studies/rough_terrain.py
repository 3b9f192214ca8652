"""Does force feedback's advantage grow or shrink on rough ground? The rough_terrain study (studies/rough_terrain.toml)
read from its folder, then its flat-ground gaits walked again on the rough grounds.

    python studies/rough_terrain.py results/rough_terrain [--no-rewalk]

**Advantage.** Per controller with feedback (VMC, Tegotae, both) and ground height A, its advantage over open loop:
the difference of the seeds' final values (each run's mean of its last 5 trials: J, CoT) and of each run's share of
trials that fell, feedback − open loop, Welch 95 % interval. Its change from flat to rough is the difference of the
two differences, (fb_A − ol_A) − (fb_0 − ol_0), four independent groups of seeds: its standard error is the root of
the four variances over their sizes, its degrees of freedom Welch–Satterthwaite's for a sum, and its test two-sided,
Holm-corrected over every (controller, height, figure) of the table. An advantage *grows* where the change is
significant in the direction of the advantage (J up, CoT and falls down), *shrinks* where it is significant the other
way, is *unchanged* where the change is equivalent to 0 within ±margin (TOST, Holm over the table) and
*inconclusive* otherwise. The margins (:data:`MARGINS`), fixed before the study's results were read: J and CoT the
paper's seed-to-seed std of VMC+Tegotae on flat ground (its controller table, as docs/REPRODUCTION.md's criteria),
falls 0.05 of the trials (one in 20).

**The context on rough ground.** What the paper's context estimator reads (c_load, c_slope of every trial that did
not fall), each run's mean, then mean [95 % CI] over the runs of every controller, per height; its difference from
the flat ground's against the thresholds of eq. (14) (t_load · r_load = 8 N, t_slope · r_slope = 0.05 rad): a
difference below them is a context the optimizer takes for the flat one.

**Flat-tuned gaits on rough ground** (skipped with ``--no-rewalk``). Where the context does not tell rough from
flat, contextual BO in inference mode proposes what it learnt on flat ground, near the flat run's best trial. Each
flat run's best trial (the highest J that did not fall) is walked on each rough ground (native backend: one settling
trial, one measured), and its J set against the final J of the runs optimized on that ground (Welch, Holm over the
table): the gait *transfers* where the two are equivalent within ±0.072 (TOST, J's margin), *re-tuning helps*
where the flat gait is significantly worse, and the verdict is *inconclusive* otherwise.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from cpgjax.go1 import model as go1_model
from cpgjax.studies import registry, stats
from cpgjax.study import files as study_io
from cpgjax.trial import optimizer_setting, protocol
from cpgjax.trial import params as param_space

FINAL_TRIALS = 5
FEEDBACK = ("vmc", "tegotae", "vmc_tegotae")
OPEN_LOOP = "open_loop"
# eq. (14)'s thresholds in the context's units: t · r, r the range width of docs/decisions.md §11
CONTEXT_THRESHOLDS = tuple(
    t * (hi - lo)
    for t, lo, hi in zip(
        optimizer_setting.PAPER_CONTEXT_THRESHOLDS,
        optimizer_setting.PAPER_CONTEXT_LOWER,
        optimizer_setting.PAPER_CONTEXT_UPPER,
        strict=True,
    )
)


def finals(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each run's final J and CoT (mean of its last FINAL_TRIALS trials) and its share of trials that fell, (B,)."""
    last = slice(-FINAL_TRIALS, None)
    fell = columns["fell"] | columns["failed"]
    return {
        "J": columns["objective"][last].mean(axis=0),
        "CoT": columns["cost_of_transport"][last].mean(axis=0),
        "falls": fell.mean(axis=0),
    }


def difference_of_differences(a1, b1, a0, b0) -> stats.Effect:
    """(mean a1 − mean b1) − (mean a0 − mean b0) of four independent samples: its SE and Welch–Satterthwaite dof."""
    groups = [np.asarray(g, np.float64) for g in (a1, b1, a0, b0)]
    terms = np.array([g.var(ddof=1) / g.size for g in groups])
    difference = (groups[0].mean() - groups[1].mean()) - (groups[2].mean() - groups[3].mean())
    se2 = float(terms.sum())
    if se2 == 0.0:
        return stats.Effect(float(difference), 0.0, float(sum(g.size - 1 for g in groups)))
    dof = se2**2 / float(sum(t**2 / (g.size - 1) for t, g in zip(terms, groups, strict=True)))
    return stats.Effect(float(difference), float(np.sqrt(se2)), float(dof))


def _interval(effect: stats.Effect) -> str:
    low, high = effect.interval()
    return f"{effect.difference:+.3f} [{low:+.3f}, {high:+.3f}]"


BETTER_UP = {"J": True, "CoT": False, "falls": False}
MARGINS = {"J": 0.072, "CoT": 0.050, "falls": 0.05}


def advantage_table(columns: dict[str, np.ndarray]) -> str:
    """Markdown: each feedback controller's advantage over open loop per height, and its change from flat."""
    values, controller, height = finals(columns), columns["controller"][0], columns["terrain_amplitude_m"][0]
    heights = sorted(set(height.tolist()))
    rows, effects = [], []
    for c in FEEDBACK:
        for a in heights:
            for figure, v in values.items():
                fb, ol = v[(controller == c) & (height == a)], v[(controller == OPEN_LOOP) & (height == a)]
                here = stats.effect_between(fb, ol)
                change = None
                if a != heights[0]:
                    change = difference_of_differences(
                        fb,
                        ol,
                        v[(controller == c) & (height == heights[0])],
                        v[(controller == OPEN_LOOP) & (height == heights[0])],
                    )
                rows.append((c, a, figure, here, change))
                effects.append(change)
    p = stats.holm([np.nan if e is None else e.two_sided_p() for e in effects])
    p_same = stats.holm(
        [np.nan if e is None else e.equivalence_p(MARGINS[r[2]]) for e, r in zip(effects, rows, strict=True)]
    )
    lines = [
        "| controller | ground height [m] | figure | feedback − open loop (95 % CI) | change from flat "
        "(95 % CI) | p (Holm) | TOST p (Holm, margin) | on rough ground the advantage |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (c, a, figure, here, change), p_holm, p_tost in zip(rows, p, p_same, strict=True):
        if change is None:
            lines.append(f"| {c} | {a:g} | {figure} | {_interval(here)} | – | – | – | – |")
            continue
        better = change.difference > 0 if BETTER_UP[figure] else change.difference < 0
        verdict = (
            ("grows" if better else "shrinks")
            if p_holm < stats.ALPHA
            else "unchanged"
            if p_tost < stats.ALPHA
            else "inconclusive"
        )
        lines.append(
            f"| {c} | {a:g} | {figure} | {_interval(here)} | {_interval(change)} | {p_holm:.2g} "
            f"| {p_tost:.2g} (±{MARGINS[figure]:g}) | {verdict} |"
        )
    return "\n".join(lines)


def context_table(columns: dict[str, np.ndarray]) -> str:
    """Markdown: the context the estimator reads per height (every run of every controller), its difference from
    flat ground and eq. (14)'s threshold."""
    walked = ~(columns["fell"] | columns["failed"])
    height = columns["terrain_amplitude_m"][0]
    per_run = {
        name: np.array(
            [columns[name][walked[:, b], b].mean() if walked[:, b].any() else np.nan for b in range(walked.shape[1])]
        )
        for name in ("c_load_n", "c_slope_rad")
    }
    heights = sorted(set(height.tolist()))
    lines = [
        "| ground height [m] | c_load [N] | c_load − flat (threshold ±{:g} N) | c_slope [rad] | c_slope − flat "
        "(threshold ±{:g} rad) |".format(*CONTEXT_THRESHOLDS),
        "|---|---|---|---|---|",
    ]
    for a in heights:
        cells = []
        for v, threshold in zip(per_run.values(), CONTEXT_THRESHOLDS, strict=True):
            here = v[height == a]
            cells.append(str(stats.mean_ci(here)))
            if a == heights[0]:
                cells.append("–")
            else:
                effect = stats.effect_between(here, v[height == heights[0]])
                inside = (
                    "inside"
                    if abs(effect.interval()[0]) < threshold and abs(effect.interval()[1]) < threshold
                    else "not inside"
                )
                cells.append(f"{_interval(effect)} ({inside} the threshold)")
        lines.append(f"| {a:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def rewalk_table(columns: dict[str, np.ndarray], backend: str = "native") -> str:
    """Markdown: each flat run's best gait walked on every rough ground, its J against the runs optimized there."""
    controller, height = columns["controller"][0], columns["terrain_amplitude_m"][0]
    terrain_seed = int(columns["terrain_seed"][0][0])
    walked = ~(columns["fell"] | columns["failed"])
    flat = np.flatnonzero(height == 0.0)
    j = np.where(walked, columns["objective"], -np.inf)
    best_trial = np.argmax(j[:, flat], axis=0)
    params = np.stack(
        [[columns[n][t, b] for n in param_space.PARAM_NAMES] for t, b in zip(best_trial, flat, strict=True)]
    )
    rough = sorted(a for a in set(height.tolist()) if a > 0.0)
    k = len(flat)
    scenario = go1_model.make_scenarios(
        friction=np.tile(columns["friction"][0][flat], len(rough)),
        physics=np.tile(columns["physics"][0][flat], len(rough)),
        terrain="rough",
        terrain_amplitude_m=np.repeat(rough, k),
        terrain_seed=terrain_seed,
    )
    target = float(columns["target_velocity_mps"][0][0])
    _, _, j_rewalk, fell = registry.evaluate(
        np.tile(params, (len(rough), 1)),
        list(controller[flat]) * len(rough),
        scenario,
        protocol.TrialConfig(),
        backend,
        target,
    )
    j_final = finals(columns)["J"]
    rows, effects = [], []
    for i, a in enumerate(rough):
        for c in dict.fromkeys(controller[flat].tolist()):
            mine = controller[flat] == c
            moved = j_rewalk[i * k : (i + 1) * k][mine]
            tuned = j_final[(controller == c) & (height == a)]
            effect = stats.effect_between(moved, tuned)
            rows.append((a, c, moved, tuned, int(fell[i * k : (i + 1) * k][mine].sum()), effect))
            effects.append(effect.two_sided_p())
    p = stats.holm(effects)
    p_same = stats.holm([r[-1].equivalence_p(MARGINS["J"]) for r in rows])
    lines = [
        "| ground height [m] | controller | flat-tuned gait, J on this ground (falls) | re-tuned here, final J "
        "| flat-tuned − re-tuned (95 % CI) | p (Holm) | TOST p (Holm, ±0.072) | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (a, c, moved, tuned, falls, effect), p_holm, p_tost in zip(rows, p, p_same, strict=True):
        verdict = (
            ("re-tuning helps" if effect.difference < 0 else "the flat gait is better")
            if p_holm < stats.ALPHA
            else "transfers"
            if p_tost < stats.ALPHA
            else "inconclusive"
        )
        lines.append(
            f"| {a:g} | {c} | {stats.mean_ci(moved)} ({falls}/{moved.size}) | {stats.mean_ci(tuned)} "
            f"| {_interval(effect)} | {p_holm:.2g} | {p_tost:.2g} | {verdict} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=pathlib.Path, help="a rough_terrain study's results folder")
    parser.add_argument("--no-rewalk", action="store_true", help="leave out the flat-tuned gaits walked again")
    parser.add_argument("--backend", default="native", help="the rewalk's backend (default: native)")
    args = parser.parse_args(argv)
    trials = args.folder / "trials.parquet"
    if not trials.is_file():
        parser.error(f"{trials}: no such file (run `cpgjax study rough_terrain` first)")
    columns = study_io.read_trials(trials)
    if "terrain_amplitude_m" not in columns:
        parser.error(f"{trials} has no terrain columns: not a study with a terrain axis")
    print("Feedback's advantage over open loop, and its change from flat ground:\n")
    print(advantage_table(columns))
    print("\nThe context the estimator reads:\n")
    print(context_table(columns))
    if not args.no_rewalk:
        print("\nFlat-tuned gaits walked on rough ground:\n")
        print(rewalk_table(columns, args.backend))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
