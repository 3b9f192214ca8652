"""The transfer study (``cpgjax study transfer``): does force feedback (Tegotae) or VMC make a tuned gait survive a
change of physics?

Three arms each optimize the four controllers online (Algorithm 1, v* = 0.5 m/s, flat floor μ 0.6), under one physics
profile (docs/physics.md):

* ``paper`` — at home under the paper's Gazebo-like physics;
* ``go1`` — at home under the best estimate of the real robot;
* ``paper_randomized`` — under ``paper`` with every trial's physics drawn per instance (domain randomization:
  friction, payload, link masses ±10 %, actuation latency).

Each run's best parameters are then walked (a settling trial, then a measured trial) under every fixed profile and
under ``EVALUATION_DRAWS`` randomized physics (drawn with another seed than any training draw). The table gives, per
controller and arm, J, velocity, CoT and falls at home and away, and the drop of J. Each arm is its own engine run
with its own folder and checkpoint below the study's output folder, so ``--resume`` continues where it stopped; each
arm's folder also holds its trial table, metadata, each controller's best gait (``best_params/<group>.json``), every
run's evaluations (``evaluations.parquet``, :func:`write_evaluations`) and, after the study's table, each best gait's
video (``best_<group>.mp4``).
"""

from __future__ import annotations

import dataclasses
import itertools
import pathlib
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from cpgjax import cpg, outputs
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import registry, stats
from cpgjax.studies import video as study_video
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec

NAME = "transfer"
EVALUATIONS = "evaluations.parquet"  # in each arm's folder: its runs' best gaits walked away from home
OUTPUTS = (
    outputs.OutputFile(
        EVALUATIONS,
        "one row per (run, evaluation environment): the run's best gait walked away from home",
        outputs.check_parquet,
    ),
)
EVALUATION_RANDOMIZATION = study_spec.Randomization(seed=1)
EVALUATION_DRAWS = 8
# The fixed profiles every run is evaluated under: those that step the physics at the control tick (one batch steps
# at one rate; `paper_5khz` is `paper` at a finer step, not another robot).
ENVIRONMENT_PROFILES = tuple(name for name, p in physics_profiles.PROFILES.items() if p.physics_substeps == 1)


def specs(study: study_spec.StudyFile) -> list[study_spec.StudySpec]:
    """One study spec per arm of the study file ``study``: its study with the arm's name, physics profile and, for a
    randomized arm, the file's [randomize] ranges."""
    return [
        dataclasses.replace(
            study.spec,
            name=f"transfer_{arm.name}",
            physics=(arm.physics,),
            randomize=(study.spec.randomize or study_spec.Randomization()) if arm.randomized else None,
        )
        for arm in study.arms
    ]


class Environments:
    """Where the best parameters are evaluated: each fixed profile, then the randomized draws."""

    def __init__(self, home: str):
        self.names = list(ENVIRONMENT_PROFILES) + [f"randomized {k}" for k in range(EVALUATION_DRAWS)]
        draws = study_spec.randomized(EVALUATION_RANDOMIZATION, EVALUATION_DRAWS, 1)
        fixed = len(ENVIRONMENT_PROFILES)
        self.physics = list(ENVIRONMENT_PROFILES) + [home] * EVALUATION_DRAWS
        self.friction = [0.6] * fixed + draws["friction"][:, 0].tolist()
        self.payload_kg = [0.0] * fixed + draws["payload_kg"][:, 0].tolist()
        self.mass_scale = [1.0] * fixed + draws["mass_scale"][:, 0].tolist()
        self.latency_ticks = [-1] * fixed + draws["latency_ticks"][:, 0].tolist()
        self.noise_scale = [-1.0] * fixed + draws["noise_scale"][:, 0].tolist()


def evaluate(
    params: np.ndarray, controllers: list[str], env: Environments, trial_config, backend: str, target_mps: float
):
    """Every run's parameters (R, 8) in every environment (E), a settling trial then the measured one, J for the
    target ``target_mps``: (J, v_x, CoT, fell), each (R, E)."""
    runs, count = params.shape[0], len(env.names)
    scenario = go1_model.make_scenarios(
        friction=np.tile(env.friction, runs),
        payload_kg=np.tile(env.payload_kg, runs),
        physics=np.tile(env.physics, runs),
        mass_scale=np.tile(env.mass_scale, runs),
        latency_ticks=np.tile(env.latency_ticks, runs),
        noise_scale=np.tile(env.noise_scale, runs),
    )
    repeated = [c for c in controllers for _ in range(count)]
    v, cot, j, fell = registry.evaluate(
        np.repeat(params, count, axis=0), repeated, scenario, trial_config, backend, target_mps
    )
    return tuple(a.reshape(runs, count) for a in (j, v, cot, fell))


def write_evaluations(path, result, env: Environments, evaluation: tuple) -> pathlib.Path:
    """``evaluations.parquet``: one row per (run, environment) of :func:`evaluate`'s results for one arm, run-major
    (docs/outputs.md). A fixed profile's latency and noise are its own (null)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    j, v, cot, fell = (np.asarray(a) for a in evaluation)
    runs, count = j.shape
    per_env = lambda values: np.tile(np.asarray(values), runs)  # noqa: E731
    latency, noise = per_env(env.latency_ticks).astype(np.int64), per_env(env.noise_scale).astype(np.float64)
    columns = {
        "instance": np.repeat(np.arange(runs, dtype=np.int64), count),
        "controller": np.repeat([lab["controller"] for lab in result.labels], count),
        "seed": np.repeat(np.array([lab["seed"] for lab in result.labels], np.int64), count),
        "environment": per_env(env.names),
        "physics": per_env(env.physics),
        "friction": per_env(env.friction).astype(np.float64),
        "payload_kg": per_env(env.payload_kg).astype(np.float64),
        "mass_scale": per_env(env.mass_scale).astype(np.float64),
        "latency_ticks": pa.array(latency, mask=latency < 0),
        "noise_scale": pa.array(noise, mask=noise < 0),
        "objective": j.ravel().astype(np.float64),
        "velocity_x_mps": v.ravel().astype(np.float64),
        "cost_of_transport": cot.ravel().astype(np.float64),
        "fell": fell.ravel() > 0,
    }
    pq.write_table(pa.table(columns), path)
    return pathlib.Path(path)


def _best(result) -> np.ndarray:
    """Each run's best observed parameters (R, 8)."""
    j = result.trials.objective
    t = np.argmax(j, axis=0)
    return result.trials.params[t, np.arange(j.shape[1])]


class _Transfer(NamedTuple):
    """One controller of one arm, per seed (S,): J at home, J under the worst other fixed profile (the one with the
    lowest mean over seeds), J averaged over the randomized draws, the drops J away − J at home, and whether the
    seed's gait fell in any environment away from home."""

    home: np.ndarray
    worst_fixed: np.ndarray
    randomized: np.ndarray
    fell_away: np.ndarray

    @property
    def drop_worst_fixed(self) -> np.ndarray:
        return self.worst_fixed - self.home

    @property
    def drop_randomized(self) -> np.ndarray:
        return self.randomized - self.home


def _arm_label(home: str, randomized: bool) -> str:
    """How the table names where an arm optimized: its home profile, with randomization or not."""
    return home + (" + randomization" if randomized else "")


def _runs(result, controller: str) -> np.ndarray:
    """(R,) bool: the runs of ``controller`` in an arm's result."""
    return np.array([lab["controller"] == controller for lab in result.labels])


def _transfer(result, evaluation: tuple, controller: str, home: str) -> _Transfer:
    fixed = list(ENVIRONMENT_PROFILES)
    runs = _runs(result, controller)
    jm, fell = evaluation[0][runs], evaluation[3][runs]
    home_col = fixed.index(home)
    away_fixed = [k for k in range(len(fixed)) if k != home_col]
    worst_col = away_fixed[int(np.argmin(jm[:, away_fixed].mean(axis=0)))]
    return _Transfer(
        home=jm[:, home_col],
        worst_fixed=jm[:, worst_col],
        randomized=jm[:, len(fixed) :].mean(axis=1),
        fell_away=np.delete(fell, home_col, axis=1).any(axis=1),
    )


def table(arms: tuple[study_spec.Arm, ...], arm_results: dict, evaluations: dict) -> str:
    """The transfer table: per controller and arm, at home and away (J, v_x, CoT, falls) and the drop of J, means
    with 95 % intervals over seeds where they are compared (``stats.mean_ci``)."""
    fixed = list(ENVIRONMENT_PROFILES)
    head = (
        "| controller | optimized under | J at home | "
        + " | ".join(f"J {p}" for p in fixed)
        + " | J randomized | drop: worst fixed | drop: randomized | v_x home / randomized [m/s] | "
        "CoT home / randomized | falls away |"
    )
    rows = [head, "|" + "---|" * (len(fixed) + 9)]
    for c in cpg.CONTROLLERS:
        for arm, home, randomized in arms:
            result, (j, v, cot, fell) = arm_results[arm], evaluations[arm]
            m = _runs(result, c)
            home_col = fixed.index(home)
            t = _transfer(result, evaluations[arm], c, home)
            label = _arm_label(home, randomized)
            away = [k for k in range(j.shape[1]) if k != home_col]
            rows.append(
                f"| {c} | {label} | {stats.mean_ci(t.home)} | "
                + " | ".join(f"{j[m][:, k].mean():.3f}" for k in range(len(fixed)))
                + f" | {stats.mean_ci(t.randomized)} | {stats.mean_ci(t.drop_worst_fixed).cell('+')} | "
                f"{stats.mean_ci(t.drop_randomized).cell('+')} | {v[m][:, home_col].mean():.3f} / "
                f"{v[m][:, len(fixed) :].mean():.3f} | {cot[m][:, home_col].mean():.3f} / "
                f"{cot[m][:, len(fixed) :].mean():.3f} | {int(fell[m][:, away].sum())}/{fell[m].shape[0] * len(away)} |"
            )
    return "\n".join(rows) + "\n"


def comparisons(arms: tuple[study_spec.Arm, ...], arm_results: dict, evaluations: dict) -> str:
    """The table's differences tested over seeds (``stats.compare``: Welch's t and Mann–Whitney's U; the runs of
    two controllers or two arms are independent optimizations):

    - per arm, each controller's drops against open loop's (does feedback make a tuned gait survive better?);
    - per controller, the randomization arm against the ``paper`` arm: J at home (the cost of training under
      randomization) and the randomized drop (what it buys away from home);
    - per arm, each controller's seeds whose gait fell away from home against open loop's (Fisher's exact test; the
      unit is the seed, since one gait walks every environment).
    """
    rows = [
        "| comparison | quantity | difference [95 % CI] | Welch p | Mann–Whitney p | seeds |",
        "|---|---|---|---|---|---|",
    ]

    def row(name: str, quantity: str, a, b) -> None:
        d = stats.compare(a, b)
        rows.append(
            f"| {name} | {quantity} | {d.difference:+.3f} [{d.low:+.3f}, {d.high:+.3f}] | {d.t_p:.2g} | "
            f"{d.rank_text()} | {d.n_a} / {d.n_b} |"
        )

    per_arm = {
        arm: {c: _transfer(arm_results[arm], evaluations[arm], c, home) for c in cpg.CONTROLLERS}
        for arm, home, _ in arms
    }
    baseline = cpg.CONTROLLERS[0]
    for arm, home, randomized in arms:
        label = _arm_label(home, randomized)
        for c in cpg.CONTROLLERS[1:]:
            a, b = per_arm[arm][c], per_arm[arm][baseline]
            row(
                f"{c} − {baseline}, optimized under {label}",
                "drop: worst fixed",
                a.drop_worst_fixed,
                b.drop_worst_fixed,
            )
            row(f"{c} − {baseline}, optimized under {label}", "drop: randomized", a.drop_randomized, b.drop_randomized)
    # a randomized arm against the arm at home under its profile without randomization
    pairs = [
        (dr.name, plain.name, dr.physics)
        for dr in arms
        if dr.randomized
        for plain in arms
        if not plain.randomized and plain.physics == dr.physics
    ][:1]
    for (dr, plain, home), c in itertools.product(pairs, cpg.CONTROLLERS):
        a, b = per_arm[dr][c], per_arm[plain][c]
        row(f"{c}: {home} + randomization − {home}", "J at home", a.home, b.home)
        row(f"{c}: {home} + randomization − {home}", "drop: randomized", a.drop_randomized, b.drop_randomized)
    falls = [
        "| optimized under | controller | seeds whose gait fell away | open loop's | Fisher p |",
        "|---|---|---|---|---|",
    ]
    for arm, home, randomized in arms:
        label = _arm_label(home, randomized)
        b = per_arm[arm][baseline].fell_away
        for c in cpg.CONTROLLERS[1:]:
            a = per_arm[arm][c].fell_away
            falls.append(
                f"| {label} | {c} | {a.sum()}/{a.size} | {b.sum()}/{b.size} | "
                f"{stats.fisher_p(a.sum(), a.size, b.sum(), b.size):.2g} |"
            )
    return "\n".join(rows) + "\n\n" + "\n".join(falls) + "\n"


def _evaluate(study: study_spec.StudyFile, results: dict, backend: str) -> registry.Evaluation:
    """Every arm's best parameters walked in every environment (``environments``, by arm: its
    :class:`Environments`; ``evaluations``, by arm: :func:`evaluate`'s arrays), and each arm's best gaits (``gaits``)
    with their per-step logs (``gait_logs``) for the videos."""
    target = study.spec.target_velocity_mps[0]
    environments = {arm: Environments(home) for arm, home, _ in study.arms}
    evaluations, gaits, logs = {}, {}, {}
    for (arm, _, _), result in zip(study.arms, results.values(), strict=True):
        evaluations[arm] = evaluate(
            _best(result),
            [lab["controller"] for lab in result.labels],
            environments[arm],
            result.spec.trial,
            backend,
            target,
        )
        gaits[arm] = study_gaits.best_gaits(result)
        logs[arm] = study_gaits.gait_rollouts(gaits[arm], backend)
    return {"environments": environments, "evaluations": evaluations, "gaits": gaits, "gait_logs": logs}


def _report(study: study_spec.StudyFile, results: dict, evaluation: registry.Evaluation) -> str:
    """The study's table.md: what was run, the transfer table and its tests over seeds."""
    arm_results = dict(zip((arm.name for arm in study.arms), results.values(), strict=True))
    evaluations = evaluation["evaluations"]
    env, fixed = evaluation["environments"][study.arms[0].name], len(ENVIRONMENT_PROFILES)
    draws = ", ".join(
        f"μ {f:.2f} / {p:.1f} kg / mass ×{s:.2f} / {lat} ms / noise ×{z:.1f}"
        for f, p, s, lat, z in zip(
            env.friction[fixed:],
            env.payload_kg[fixed:],
            env.mass_scale[fixed:],
            env.latency_ticks[fixed:],
            env.noise_scale[fixed:],
            strict=True,
        )
    )
    first = next(iter(results.values())).spec
    n, runs, target = first.num_trials, len(first.seeds), study.spec.target_velocity_mps[0]
    wall = sum(result.wall_s for result in results.values())
    return (
        f"# transfer\n\nEach controller optimized online for {n} trials ({runs} seeds) under one physics profile "
        f"(or under randomized physics), then its best parameters walked — one settling trial, one measured "
        f"trial, v* = {target:g} m/s — under every fixed profile (flat, μ 0.6) and under {EVALUATION_DRAWS} "
        f"randomized physics ({draws}, on the arm's home profile). J at home, J randomized and the drops: mean "
        f"[95 % interval] over seeds; the profiles' J: means; drop: J away − J at home (the worst other fixed "
        f"profile by its mean; the mean over the randomized draws).\n\n"
        + table(study.arms, arm_results, evaluations)
        + (
            f"\n## Differences, tested over {runs} seeds\n\n" + comparisons(study.arms, arm_results, evaluations)
            if runs >= stats.MIN_SEEDS
            else f"\n{stats.too_few_line(runs)}\n"
        )
        + f"\nOptimization wall time {wall:.0f} s (all arms).\n"
    )


def _write(
    study: study_spec.StudyFile,
    results: dict,
    evaluation: registry.Evaluation,
    text: str,
    out: pathlib.Path,
    notify: Callable[[str], None],
) -> str:
    """Each arm's best gaits (``best_params/``) and evaluations (``evaluations.parquet``), the study's table.md, then
    each arm's videos (after the table: filming never costs a result)."""
    for (arm, _, _), result in zip(study.arms, results.values(), strict=True):
        folder = out / result.spec.name
        with study_io.writing(folder, "best_params/"):
            study_gaits.save_gaits(folder, result, evaluation["gaits"][arm])
        with study_io.writing(folder, EVALUATIONS):
            write_evaluations(
                folder / EVALUATIONS, result, evaluation["environments"][arm], evaluation["evaluations"][arm]
            )
    out.mkdir(parents=True, exist_ok=True)
    (out / study_io.TABLE).write_text(text)
    for (arm, _, _), result in zip(study.arms, results.values(), strict=True):
        with study_io.writing(out / result.spec.name, "the best gaits' videos"):
            study_video.write_videos(
                out / result.spec.name, evaluation["gaits"][arm], evaluation["gait_logs"][arm], notify
            )
    return text


def study(definition: study_spec.StudyFile) -> registry.Study:
    """The transfer study of the study file ``definition`` (with its arms) as a study of the protocol: every arm its
    own engine run and folder, then the evaluations, the table and the videos."""
    return registry.Study(
        definition.spec.name,
        tuple(specs(definition)),
        lambda results, backend: _evaluate(definition, results, backend),
        lambda results, evaluation: _report(definition, results, evaluation),
        lambda results, evaluation, text, out, notify: _write(definition, results, evaluation, text, out, notify),
        metadata=definition.metadata(),
        plan="then each arm's best gaits walked in every evaluation environment",
    )
