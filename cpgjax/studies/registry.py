"""The paper's simulation results as studies of the lockstep engine (``cpgjax.ablation``): one entry per result.

======================  =======================================================================================
``controller_ablation`` 4 controllers × 20 seeds × 40 trials at v* = 0.5 m/s: the controller table (mean of the
                        last 5 trials, mean and 95 % CI over seeds, tests against the paper's table and between
                        controllers) and the roll–pitch figure of the best parameters
``load_adaptation``     payload 0 → 7.5 kg (trial 36) → 15 kg (trial 58): the load table, before/after adaptation
``friction``            friction 0.3 / 0.6 / 0.9 learning curves (paper Fig. sim_overview a)
``multi_velocity``      target 0.8 → 0.3 → 0.6 m/s with and without data reuse (Fig. sim_overview b)
``slope_adaptation``    slope 0° → 10° → 12.5° with contextual BO, then inference mode (β = 1e-6) on 10°…17.5°
                        and up the continuous 10° → 17.5° ramp (Fig. sim_overview c, Fig. slope_setting)
``paper_hardware``      the paper's hardware experiments predicted under the ``go1`` profile: v* = 0.4 m/s on flat
                        and on slippery ground (taped feet), 0.6 → 0.3 → 0.5 → 0.6 m/s, a 10° slope, 5 / 10 / 15 kg
======================  =======================================================================================

The paper used 5 seeds; the studies default to 20 (``DEFAULT_SEEDS``), and every figure is a mean with its 95 %
confidence interval over seeds (``cpgjax.studies.stats``).

Each writes to its output folder: ``table.md`` (the paper's numbers beside ours), PNG figures (the study's own and
``optimization_progress.png``: the best J so far and the parameters per group), ``trials.parquet``,
``recording.rrd`` (with each group's best gait, full body), ``metadata.json`` and the engine's ``checkpoint.npz``
(``cpgjax.study.files``), each group's best gait of its final phase, ``best_params/<group>.json`` (what a replay
runs), and its video ``best_<group>.mp4`` (``cpgjax.studies.video``).
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import sys
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from cpgjax import ablation, cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.sim import backends
from cpgjax.studies import figures as study_figures
from cpgjax.studies import stats
from cpgjax.studies import video as study_video
from cpgjax.study import files as study_io
from cpgjax.study import scene as study_scene
from cpgjax.study import spec as study_spec
from cpgjax.study.spec import Change, Schedule, StudySpec
from cpgjax.trial import limits, objective, protocol

DEFAULT_SEEDS = 20  # the paper used 5 (its tables' std is over 5 seeds: PAPER_SEEDS)
PAPER_SEEDS = 5
QUICK_SEEDS = 2
LAST_TRIALS = 5  # "averaging the outcomes of the last five trials"
TRACKING_TOLERANCE_MPS = 0.05  # a target counts as tracked from the first trial with |v_x − v*| ≤ this, no fall

PAPER_CONTROLLER_TABLE = {  # velocity, CoT, J: mean, std over 5 seeds (paper Table "controller comparison")
    "open_loop": ((0.477, 0.045), (0.931, 0.138), (1.638, 0.516)),
    "vmc": ((0.494, 0.028), (0.919, 0.149), (1.643, 0.139)),
    "tegotae": ((0.500, 0.012), (0.583, 0.024), (2.153, 0.042)),
    "vmc_tegotae": ((0.509, 0.023), (0.518, 0.050), (2.167, 0.072)),
}
PAPER_LOAD_TABLE = {  # load kg: (velocity, CoT, J) after adaptation, (same) with the flat-ground optimum
    0.0: ((0.491, 0.510, 2.175), None),
    7.5: ((0.524, 0.489, 2.213), (0.403, 0.564, 1.9735)),
    15.0: ((0.528, 0.523, 2.189), (0.341, 0.905, 1.270)),
}


PHYSICS = (physics_profiles.PAPER_STUDIES_PROFILE,)  # the paper's Gazebo-like physics (docs/physics.md)


def _scaled(trial: int, paper_total: int, total: int) -> int:
    """A schedule's change trial scaled from the paper's run length to ours."""
    return int(round(trial * total / paper_total))


def seed_range(seeds: int | None, quick: bool, default: int = DEFAULT_SEEDS) -> tuple[int, ...]:
    """The seeds 0 … n − 1 of a study: n = ``seeds`` if given, else ``QUICK_SEEDS`` with ``quick``, else ``default``."""
    return tuple(range(seeds if seeds is not None else (QUICK_SEEDS if quick else default)))


# ----------------------------------------------------------------------------------------------- specs

def ablation_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    return StudySpec("controller_ablation", num_trials=trials or (12 if quick else 40), controllers=cpg.CONTROLLERS,
                     seeds=seed_range(seeds, quick), target_velocity_mps=(0.5,), physics=PHYSICS)


def load_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    n = trials or (24 if quick else 80)
    schedule = Schedule("0→7.5→15 kg", (Change(_scaled(36, 80, n), "payload_kg", 7.5),
                                         Change(_scaled(58, 80, n), "payload_kg", 15.0)))
    return StudySpec("load_adaptation", num_trials=n, seeds=seed_range(seeds, quick), schedules=(schedule,),
                     group_by=("schedule",), physics=PHYSICS)


def friction_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    return StudySpec("friction", num_trials=trials or (12 if quick else 40), seeds=seed_range(seeds, quick),
                     friction=(0.3, 0.6, 0.9), group_by=("friction",), physics=PHYSICS)


def multi_velocity_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    n = trials or (42 if quick else 140)
    schedule = Schedule("0.8→0.3→0.6 m/s", (Change(_scaled(40, 140, n), "target_velocity_mps", 0.3),
                                             Change(_scaled(90, 140, n), "target_velocity_mps", 0.6)))
    return StudySpec("multi_velocity", num_trials=n, seeds=seed_range(seeds, quick), target_velocity_mps=(0.8,),
                     schedules=(schedule,), data_reuse=(True, False), group_by=("data_reuse",), physics=PHYSICS)


INFERENCE_SLOPES_DEG = (10.0, 12.5, 15.0, 17.5)
# The paper's continuous ramp (Fig. slope_setting) rises from 10° to 17.5°; the paper gives no length. 12 m: a gait
# that tracks v* = 0.5 m/s reaches the top in about 5 of its 12 trials there, one at 0.25 m/s by the last.
RAMP = study_spec.Ramp(start_deg=10.0, end_deg=17.5, length_m=12.0)


def slope_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    n = trials or (36 if quick else 104)
    per_slope = 1 if quick else 3  # inference mode: this many trials on each slope, then 4 × as many on the ramp
    ramp = n - 4 * per_slope
    learn = ramp - 4 * per_slope
    if learn < 4:
        raise study_spec.StudyError(f"--trials {n}: the slope study needs at least {8 * per_slope + 4} trials (its "
                                    f"last {8 * per_slope} are in inference mode)")
    changes = [Change(_scaled(40, 80, learn), "slope_deg", 10.0), Change(_scaled(60, 80, learn), "slope_deg", 12.5),
               Change(learn, "inference", 1.0)]
    changes += [Change(learn + k * per_slope, "slope_deg", s) for k, s in enumerate(INFERENCE_SLOPES_DEG)]
    changes += [Change(ramp, "ramp", 1.0)]
    return StudySpec("slope_adaptation", num_trials=n, seeds=seed_range(seeds, quick),
                     schedules=(Schedule("0→10→12.5° + inference 10…17.5° + ramp", tuple(changes)),),
                     group_by=("schedule",), physics=PHYSICS, ramp=RAMP)


HARDWARE_TARGET_MPS = 0.4  # the paper's hardware experiments track 0.4 m/s (except the velocity schedule)
# The paper's "slippery terrain (i.e. taped feet)" gives no μ: ours is the paper's slippery floor in simulation (0.3).
TAPED_FEET_FRICTION = 0.3
HARDWARE_VELOCITIES_MPS = (0.6, 0.3, 0.5, 0.6)
HARDWARE_LOADS_KG = (0.0, 5.0, 10.0, 15.0)
PAPER_HARDWARE_COT = {  # paper Sec. "Hardware Experiments": CoT ≈ these once tracked
    "flat 0.4 m/s": 0.8, "taped feet 0.4 m/s": 0.95,
    "0.6→0.3→0.5→0.6 m/s": {0.6: 0.95, 0.3: 0.70, 0.5: 0.90},
}
PAPER_HARDWARE_SLOPE_TRIALS = 20  # "stabilizes around this target once more within approximately 20 trials"


def hardware_spec(seeds=None, trials=None, quick=False) -> StudySpec:
    """The paper's hardware experiments as one study under the ``go1`` profile: a prediction of the robot. Flat
    ground and taped feet at 0.4 m/s; 0.6 → 0.3 → 0.5 → 0.6 m/s in equal phases; flat, then 10° from the middle on
    (the robot learned flat ground first); flat, then 5, 10 and 15 kg added in equal phases over the second half."""
    n = trials or (24 if quick else 60)
    quarter, half = n // 4, n // 2
    loads = [Change(half + k * (n - half) // 3, "payload_kg", kg) for k, kg in enumerate(HARDWARE_LOADS_KG[1:])]
    schedules = (
        Schedule("flat 0.4 m/s"),
        Schedule("taped feet 0.4 m/s", (Change(0, "friction", TAPED_FEET_FRICTION),)),
        Schedule("0.6→0.3→0.5→0.6 m/s", tuple(Change(k * quarter, "target_velocity_mps", v)
                                              for k, v in enumerate(HARDWARE_VELOCITIES_MPS))),
        Schedule("flat → 10°", (Change(half, "slope_deg", 10.0),)),
        Schedule("0→5→10→15 kg", tuple(loads)),
    )
    return StudySpec("paper_hardware", num_trials=n, seeds=seed_range(seeds, quick),
                     target_velocity_mps=(HARDWARE_TARGET_MPS,), schedules=schedules, group_by=("schedule",),
                     physics=(physics_profiles.ROBOT_PROFILE,))


# ----------------------------------------------------------------------------------------------- analysis helpers

def last_mean(values: np.ndarray, stop: int, k: int = LAST_TRIALS) -> np.ndarray:
    """Mean over trials [stop − k, stop) of (N, B) values → (B,)."""
    return np.asarray(values)[max(stop - k, 0):stop].mean(axis=0)


def mean_ci(values: np.ndarray) -> str:
    """Mean over seeds with its 95 % confidence interval, as "mean [low, high]"."""
    return str(stats.mean_ci(values))


def phase_starts(values: np.ndarray) -> list[int]:
    """Trials (of one instance's (N,) condition) at which the condition changes, with 0 first."""
    return [0] + [t for t in range(1, len(values)) if values[t] != values[t - 1]]


def evaluate(params: np.ndarray, controllers, scenario: go1_model.Scenario, trial_config, backend: str,
             target_mps: float, settle_trials: int = 1):
    """Fixed parameters (B, 8) on ``scenario``: ``settle_trials`` trials, then one measured trial.

    Returns (velocity_x, CoT, J, fell) arrays (B,), the first three of the measured trial, ``fell`` 1 where any of
    the trials fell."""
    sim = backends.make_backend(scenario, backend, trial_config=trial_config)
    gates = protocol.batch_gates(list(controllers))
    state = sim.reset(params)
    fell = np.zeros(params.shape[0])
    for _ in range(settle_trials + 1):
        state, record = sim.trial(state, params, gates)
        record = ablation.fetch(record)
        fell = np.maximum(fell, np.asarray(record.fell))
    j = jax.vmap(objective.objective, in_axes=(0, None))(record, np.float32(target_mps))
    return (np.asarray(objective.mean_velocity(record))[:, 0], np.asarray(objective.cost_of_transport(record)),
            np.asarray(j), fell)


def rollouts(params: np.ndarray, controllers, scenario, trial_config, backend: str, steps: int = 3000) -> list:
    """Per-step logs (``protocol.StepLog`` of NumPy (T, ...)) of fixed parameters after one settling trial."""
    sim = backends.make_backend(scenario, backend, trial_config=trial_config)
    gates = protocol.batch_gates(list(controllers))
    state, _ = sim.trial(sim.reset(params), params, gates)
    _, log = sim.rollout(state, params, gates, steps)
    log = ablation.fetch(log)
    return [type(log)(*(field[b] for field in log)) for b in range(params.shape[0])]


def best_params(result, mask: np.ndarray, stop: int | None = None) -> tuple[np.ndarray, int, float]:
    """The best observed parameters among the instances in ``mask`` (and trials < stop): (x, instance, J)."""
    j = np.where(mask[None, :], result.trials.objective[:stop], -np.inf)
    t, b = np.unravel_index(np.argmax(j), j.shape)
    return result.trials.params[t, b], int(b), float(j[t, b])


def _best_run(result, mask: np.ndarray) -> tuple[int, int]:
    """(instance, trial): among the instances in ``mask``, the run with the best final objective (mean of its last
    trials), and its best trial of the final condition phase; the trials on a ramp do not count (their slopes differ
    by instance and trial)."""
    tr, cond = result.trials, result.conditions
    n = ramp_start(result)
    b = int(np.argmax(np.where(mask, last_mean(tr.objective, n), -np.inf)))
    fields = (cond.friction[b], cond.slope_deg[b], cond.payload_kg[b], cond.target_velocity_mps[b])
    start = max(max(phase_starts(f[:n])) for f in fields)
    return b, start + int(np.argmax(tr.objective[start:n, b]))


def group_name(labels: dict, group_by) -> str:
    """A group's name in file names: its label values (a controller by name, other labels as label + value), joined
    by ``_``, arrows as ``-`` and anything else but letters, digits, ``.``, ``-`` and ``_`` dropped."""
    parts = [str(labels[k]) if k == "controller" else f"{k}{labels[k]}" for k in group_by]
    return re.sub(r"[^A-Za-z0-9._-]", "", "_".join(parts).replace("→", "-"))


def best_gaits(result) -> list[study_video.Gait]:
    """Per group of the study (``spec.group_by``): the best parameters of :func:`_best_run` among its instances, in
    the conditions of the last trial before a ramp."""
    tr, cond = result.trials, result.conditions
    n = ramp_start(result)
    names = np.array([group_name(lab, result.spec.group_by) for lab in result.labels])
    gaits = []
    for name in dict.fromkeys(names):
        b, t = _best_run(result, names == name)
        gaits.append(study_video.Gait(
            group=str(name), params=np.asarray(tr.params[t, b], np.float64), controller=result.labels[b]["controller"],
            friction=float(cond.friction[b, n - 1]), slope_deg=float(cond.slope_deg[b, n - 1]),
            payload_kg=float(cond.payload_kg[b, n - 1]), physics=str(result.labels[b]["physics"]),
            transition_steps=result.spec.trial.transition_steps, steady_steps=result.spec.trial.steady_steps,
            target_velocity_mps=float(cond.target_velocity_mps[b, n - 1]), objective=float(tr.objective[t, b]),
            instance=b, trial=t))
    return gaits


def save_best_gaits(out: pathlib.Path, result) -> list[study_video.Gait]:
    """Each group's :func:`best_gaits` as ``out/best_params/<group>.json``, what ``deploy --params`` and
    ``walk --params`` replay as tuned and what the study films (``best_<group>.mp4``)."""
    gaits = best_gaits(result)
    for gait in gaits:
        study_video.save_gait(out, gait, seed=int(result.labels[gait.instance]["seed"]), study=result.spec.name)
    return gaits


def gait_rollouts(gaits: list[study_video.Gait], backend: str, steps: int | None = None) -> list:
    """The per-step logs of ``gaits`` (one batch): a settling trial of the gaits' lengths, then ``steps`` ticks
    (default: the steady phase's length, 3 s in the paper's trial)."""
    config = protocol.TrialConfig(transition_steps=gaits[0].transition_steps, steady_steps=gaits[0].steady_steps)
    if any((g.transition_steps, g.steady_steps) != (config.transition_steps, config.steady_steps) for g in gaits):
        raise study_spec.StudyError("the gaits were found with different trial lengths; film them one at a time")
    scenario = go1_model.make_scenarios(friction=[g.friction for g in gaits], slope_deg=[g.slope_deg for g in gaits],
                                        payload_kg=[g.payload_kg for g in gaits], physics=[g.physics for g in gaits])
    return rollouts(np.stack([g.params for g in gaits]), [g.controller for g in gaits], scenario, config, backend,
                    config.steady_steps if steps is None else steps)


# ----------------------------------------------------------------------------------------------- reports

def _labels(result, key) -> np.ndarray:
    return np.array([lab[key] for lab in result.labels])


def report_ablation(result, backend: str) -> str:
    tr, n = result.trials, result.trials.objective.shape[0]
    controllers = _labels(result, "controller")
    rows = ["| controller | velocity [m/s] ours | paper | CoT ours | paper | J ours | paper | falls (all trials) |",
            "|---|---|---|---|---|---|---|---|"]
    for c in cpg.CONTROLLERS:
        m = controllers == c
        if not m.any():
            continue
        v, cot, j = (last_mean(x[:, m], n) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
        p = PAPER_CONTROLLER_TABLE[c]
        rows.append(f"| {c} | {mean_ci(v)} | {p[0][0]:.3f} ± {p[0][1]:.3f} | {mean_ci(cot)} | "
                    f"{p[1][0]:.3f} ± {p[1][1]:.3f} | {mean_ci(j)} | {p[2][0]:.3f} ± {p[2][1]:.3f} | "
                    f"{int(tr.fell[:, m].sum())}/{tr.fell[:, m].size} |")
    return (f"Controller ablation, v* = 0.5 m/s: mean of the last {LAST_TRIALS} of {n} trials per run, then mean "
            f"[95 % CI] over {len(result.spec.seeds)} seeds; the paper's mean ± std over {PAPER_SEEDS} seeds.\n\n"
            + "\n".join(rows) + "\n" + ablation_verdicts(result))


def figures_ablation(result, out: pathlib.Path, backend: str) -> str:
    """learning_curves.png, and attitude.png with its table: the roll–pitch of open loop's and VMC+Tegotae's best
    parameters (the paper's Fig. att_comp), each walked again."""
    controllers = _labels(result, "controller")
    study_figures.learning_curves(out / "learning_curves.png", result, "controller")
    picks = [c for c in ("open_loop", "vmc_tegotae") if (controllers == c).any()]
    if not picks:
        return ""
    best = [best_params(result, controllers == c) for c in picks]
    params = np.stack([b[0] for b in best])
    scenario = go1_model.make_scenarios(friction=[result.spec.friction[0]] * len(picks),
                                        physics=[result.labels[b]["physics"] for _, b, _ in best])
    logs = {f"best_{c}": lg for c, lg in zip(picks, rollouts(params, picks, scenario, result.spec.trial, backend),
                                             strict=True)}
    study_figures.attitude(out / "attitude.png", logs)
    text = "\nRoll–pitch of the best parameters (3 s after a settling trial), std [rad]:\n\n"
    text += "| controller | best J (instance) | roll std | pitch std |\n|---|---|---|---|\n"
    for (c, lg), (_, b, jb) in zip(logs.items(), best, strict=True):
        text += f"| {c} | {jb:.3f} (#{b}) | {np.std(lg.rpy_rad[:, 0]):.4f} | {np.std(lg.rpy_rad[:, 1]):.4f} |\n"
    return text


def _final(result, metric: str, mask: np.ndarray) -> np.ndarray:
    """Per-run mean of the last LAST_TRIALS trials of a metric (velocity, cot, objective) for the runs in mask."""
    tr, n = result.trials, result.trials.objective.shape[0]
    values = {"velocity": tr.velocity_xy_mps[..., 0], "cot": tr.cot, "objective": tr.objective}[metric]
    return last_mean(values[:, mask], n)


def ablation_verdicts(result) -> str:
    """Ours against the paper's table (Welch's test from its mean ± std over 5 seeds), and the controllers against
    each other (Welch and Mann–Whitney on our seeds): the effect, its 95 % interval and the p-values."""
    controllers = _labels(result, "controller")
    present = [c for c in cpg.CONTROLLERS if (controllers == c).sum() >= 2]
    lines = ["", "Ours − paper (Welch's test from the paper's mean ± std, n = 5):", "",
             "| controller | CoT | J |", "|---|---|---|"]
    for c in present:
        p = PAPER_CONTROLLER_TABLE[c]
        cells = [stats.compare_to_summary(_final(result, m, controllers == c), *p[k], PAPER_SEEDS)
                 for k, m in ((1, "cot"), (2, "objective"))]
        lines.append(f"| {c} | {cells[0]} | {cells[1]} |")
    pairs = [(a, b) for a, b in (("tegotae", "open_loop"), ("vmc_tegotae", "vmc"), ("vmc", "open_loop"),
                                 ("vmc_tegotae", "tegotae")) if a in present and b in present]
    if pairs:
        lines += ["", "Between controllers (ours; Welch's t and Mann–Whitney U, two-sided):", "",
                  "| comparison | CoT | J |", "|---|---|---|"]
        for a, b in pairs:
            cells = [stats.compare(_final(result, m, controllers == a), _final(result, m, controllers == b))
                     for m in ("cot", "objective")]
            lines.append(f"| {a} − {b} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def phase_diagnostics(result, start: int, stop: int) -> str:
    """One phase's falls, the spread of c_load over its trials (std per run, mean over runs) against the same-context
    tolerance t_load·r_load, the trials that used β_init,c and the range of β."""
    tr = result.trials
    steady = tr.fell[start:stop] == 0
    c_load = np.where(steady, tr.context[start:stop, :, 0], np.nan)
    spread = np.nanmean(np.nanstd(c_load, axis=0)) if steady.any() else np.nan
    beta = tr.beta[start:stop]
    return (f"{int(tr.fell[start:stop].sum())}/{tr.fell[start:stop].size} | {np.nanmean(c_load):.1f} | {spread:.1f} | "
            f"{int(tr.context_changed[start:stop].sum())}/{tr.context_changed[start:stop].size} | "
            f"{beta.min():.2g} – {beta.max():.2g}")


def report_load(result, backend: str) -> str:
    tr, cond = result.trials, result.conditions
    starts = phase_starts(cond.payload_kg[0]) + [tr.objective.shape[0]]
    loads = [float(cond.payload_kg[0, s]) for s in starts[:-1]]
    flat = np.stack([best_params(result, np.eye(len(result.labels), dtype=bool)[b], starts[1])[0]
                     for b in range(len(result.labels))])
    rows = ["| load [kg] | velocity ours (flat optimum) | paper | CoT ours (flat optimum) | paper | "
            "J ours (flat optimum) | paper |", "|---|---|---|---|---|---|---|"]
    config = result.spec.optimizer_config()
    tolerance = config.context_thresholds[0] * (config.context_upper[0] - config.context_lower[0])  # eq. (14)
    phases = ["| load [kg] (trials) | falls | c_load [N] | c_load spread within a run [N] (same-context tolerance "
              f"t_load·r_load = {tolerance:g} N) | trials with β_init,c | β |", "|---|---|---|---|---|---|"]
    for load, start, stop in zip(loads, starts[:-1], starts[1:], strict=True):
        after = [last_mean(x, stop) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective)]
        before = None
        if load > 0:
            scenario = go1_model.make_scenarios(payload_kg=[load] * len(flat), physics=_labels(result, "physics"))
            before = evaluate(flat, _labels(result, "controller"), scenario, result.spec.trial, backend, 0.5)
        paper_after, paper_before = PAPER_LOAD_TABLE.get(load, (None, None))
        cells = []
        for k in range(3):
            ours = mean_ci(after[k]) + (f" ({mean_ci(before[k])})" if before is not None else " (-)")
            paper = "" if paper_after is None else f"{paper_after[k]:.3f}" + (
                f" ({paper_before[k]:.3f})" if paper_before else " (-)")
            cells += [ours, paper]
        rows.append(f"| {load:g} | " + " | ".join(cells) + " |")
        phases.append(f"| {load:g} ({start}–{stop - 1}) | {phase_diagnostics(result, start, stop)} |")
    text = (f"Load adaptation, v* = 0.5 m/s, payload changes at trials {starts[1:-1]} of {starts[-1]}; after: mean "
            f"[95 % CI] of the last {LAST_TRIALS} trials of each phase over {len(result.spec.seeds)} seeds; in "
            "parentheses: the best parameters found before the first payload change, re-run on the loaded robot. The "
            "paper gives no spread for this table.\n\n" + "\n".join(rows) + "\n\nPer phase:\n\n"
            + "\n".join(phases) + "\n")
    return text


def report_friction(result, backend: str) -> str:
    tr, n = result.trials, result.trials.objective.shape[0]
    friction = _labels(result, "friction")
    rows = ["| friction | velocity [m/s] | CoT | J | trials to a prospective solution (J ≥ 90 % of the run's best) |",
            "|---|---|---|---|---|"]
    for f in result.spec.friction:
        m = friction == f
        j = tr.objective[:, m]
        first = [int(np.argmax(j[:, b] >= 0.9 * j[:, b].max())) + 1 for b in range(j.shape[1])]
        rows.append(f"| {f} | " + " | ".join(mean_ci(last_mean(x[:, m], n)) for x in
                                            (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
                    + f" | {mean_ci(first)} |")
    text = (f"Friction, v* = 0.5 m/s, VMC+Tegotae: last {LAST_TRIALS} of {n} trials, mean [95 % CI] over "
            f"{len(result.spec.seeds)} seeds. Paper: prospective solutions within < 10 trials for every friction "
            "(no table).\n\n" + "\n".join(rows) + "\n" + _versus(result, friction, 0.6, "friction"))
    return text


def _versus(result, labels: np.ndarray, reference, name: str) -> str:
    """Each group's final CoT and J against the reference group's (Welch's t and Mann–Whitney U on the seeds)."""
    ref = labels == reference
    others = [g for g in dict.fromkeys(labels.tolist()) if g != reference and (labels == g).sum() >= 2]
    if ref.sum() < 2 or not others:
        return ""
    lines = ["", f"Against {name} = {reference} (Welch's t and Mann–Whitney U, two-sided):", "",
             f"| {name} | CoT | J |", "|---|---|---|"]
    for g in others:
        cells = [stats.compare(_final(result, m, labels == g), _final(result, m, ref)) for m in ("cot", "objective")]
        lines.append(f"| {g} − {reference} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def trials_to_track(velocity: np.ndarray, target: np.ndarray, fell: np.ndarray, start: int, stop: int) -> float:
    """Trials from ``start`` until the first with |v − v*| ≤ tolerance and no fall (NaN if never before stop)."""
    ok = (np.abs(velocity[start:stop] - target[start:stop]) <= TRACKING_TOLERANCE_MPS) & (fell[start:stop] == 0)
    return float(np.argmax(ok) + 1) if ok.any() else np.nan


def _finite_counts(counts: np.ndarray) -> np.ndarray:
    return counts[np.isfinite(counts)]


def report_multi_velocity(result, backend: str) -> str:
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    starts = phase_starts(cond.target_velocity_mps[0]) + [n]
    reuse = _labels(result, "data_reuse")
    rows = ["| target [m/s] (trials) | data reuse | trials to track (mean [95 % CI] of the runs that track, "
            "never-tracked runs) | final velocity | final CoT |", "|---|---|---|---|---|"]
    tracked = {}
    for s, e in zip(starts[:-1], starts[1:], strict=True):
        target = float(cond.target_velocity_mps[0, s])
        for flag in result.spec.data_reuse:
            bs = np.flatnonzero(reuse == flag)
            counts = np.array([trials_to_track(tr.velocity_xy_mps[:, b, 0], cond.target_velocity_mps[b], tr.fell[:, b],
                                               s, e) for b in bs])
            never = int(np.isnan(counts).sum())
            tracked[(s, flag)] = counts
            rows.append(f"| {target:g} ({s}–{e - 1}) | {'yes' if flag else 'no (restart)'} | "
                        f"{stats.mean_ci(counts)} ({never}) | "
                        f"{mean_ci(last_mean(tr.velocity_xy_mps[:, bs, 0], e))} | "
                        f"{mean_ci(last_mean(tr.cot[:, bs], e))} |")
    text = (f"Multi-velocity tracking: a target counts as tracked from the first trial with |v_x − v*| ≤ "
            f"{TRACKING_TOLERANCE_MPS} m/s and no fall; final = mean of the last {LAST_TRIALS} trials of the phase; "
            f"{len(result.spec.seeds)} seeds. Paper: fewer trials after each change with data reuse (figure only).\n\n"
            + "\n".join(rows) + "\n")
    if set(result.spec.data_reuse) == {True, False}:
        lines = ["", "Trials to track, reuse − restart (runs that track; Welch's t and Mann–Whitney U):", ""]
        for s in starts[1:-1]:
            a, b = _finite_counts(tracked[(s, True)]), _finite_counts(tracked[(s, False)])
            verdict = stats.compare(a, b) if min(a.size, b.size) >= 2 else "too few tracking runs"
            lines.append(f"- {float(cond.target_velocity_mps[0, s]):g} m/s (from trial {s}): {verdict}")
        text += "\n".join(lines) + "\n"
    return text


def report_slope(result, backend: str) -> str:
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    starts = _slope_phases(result)
    learn = starts[-1]
    rows = ["| slope [deg] (trials) | velocity | CoT | J | c_slope [rad] | falls |", "|---|---|---|---|---|---|"]
    for s, e in zip(starts[:-1], starts[1:], strict=True):
        rows.append(f"| {cond.slope_deg[0, s]:g} ({s}–{e - 1}) | " + " | ".join(
            mean_ci(last_mean(x, e)) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective, tr.context[..., 1]))
            + f" | {int(tr.fell[s:e].sum())} |")
    text = (f"Slope adaptation, v* = 0.5 m/s, contextual BO; last {LAST_TRIALS} trials of each phase, "
            f"{len(result.spec.seeds)} seeds.\n\n" + "\n".join(rows) + "\n")
    ramp = ramp_start(result)
    if learn < ramp:
        rows = ["| slope [deg] | velocity | J | falls / trials | paper |", "|---|---|---|---|---|"]
        inf_starts = phase_starts(cond.slope_deg[0, learn:ramp])
        bounds = [learn + s for s in inf_starts] + [ramp]
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            slope = float(cond.slope_deg[0, s])
            paper = "walks" if slope <= 15.0 else "not reported as walking"
            rows.append(f"| {slope:g} | {mean_ci(tr.velocity_xy_mps[s:e, :, 0])} | {mean_ci(tr.objective[s:e])} | "
                        f"{int(tr.fell[s:e].sum())}/{tr.fell[s:e].size} | {paper} |")
        text += ("\nInference mode (β = 1e-6), trials " + f"{learn}–{ramp - 1}:\n\n" + "\n".join(rows) + "\n")
    if ramp < n:
        text += report_ramp(result, ramp)
    return text


RAMP_BANDS_DEG = (10.0, 12.5, 15.0, 17.5)  # the ramp's trials grouped by the slope they started on


def ramp_start(result) -> int:
    """The first trial on the continuous ramp (the trial count if none)."""
    on = result.conditions.ramp[0]
    return int(np.argmax(on)) if on.any() else result.trials.objective.shape[0]


def report_ramp(result, start: int) -> str:
    """The continuous ramp in inference mode: per band of slopes, the trials that started there (pooled over
    seeds), and per seed the steepest slope a trial walked without falling."""
    tr, cond, ramp = result.trials, result.conditions, result.spec.ramp
    slope = cond.slope_deg[:, start:].T  # (trials, B): the slope each trial started on
    fell = tr.fell[start:] > 0
    rows = ["| slopes [deg] | trials | velocity | J | falls / trials | paper |", "|---|---|---|---|---|---|"]
    for lo, hi in zip(RAMP_BANDS_DEG[:-1], RAMP_BANDS_DEG[1:], strict=True):
        band = (slope >= lo) & ((slope < hi) | (hi == RAMP_BANDS_DEG[-1]))  # the top band holds the top
        paper = "walks" if hi <= 15.0 else "walks up to 15°"
        figures = (f"{mean_ci(tr.velocity_xy_mps[start:, :, 0][band])} | {mean_ci(tr.objective[start:][band])} | "
                   f"{int(fell[band].sum())}/{int(band.sum())}" if band.any() else "– | – | –")
        rows.append(f"| {lo:g}–{hi:g} | {int(band.sum())} | {figures} | {paper} |")
    steepest = np.where(~fell, slope, -np.inf).max(axis=0)  # per seed; −inf: every ramp trial fell
    walked = np.isfinite(steepest)
    top = int(np.sum(steepest >= ramp.end_deg))
    return (f"\nContinuous ramp {ramp.start_deg:g}° → {ramp.end_deg:g}° over {ramp.length_m:g} m (the paper's Fig. "
            f"slope_setting), inference mode, trials {start}–{tr.objective.shape[0] - 1}; each trial starts on the "
            f"slope the instance has climbed to, a fall puts it back at the bottom:\n\n" + "\n".join(rows) + "\n\n"
            f"Steepest slope walked without a fall: {mean_ci(steepest[walked])}° over the {int(walked.sum())} of "
            f"{walked.size} seeds with one; {top} reached the top.\n")


def report_hardware(result, backend: str) -> str:
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    schedules = _labels(result, "schedule")
    rows = ["| schedule | phase (trials) | v* [m/s] | v_x [m/s] | CoT | J | falls | trials to track after the change "
            "(runs never tracking) | paper |", "|---|---|---|---|---|---|---|---|---|"]
    for label in dict.fromkeys(schedules):
        bs = np.flatnonzero(schedules == label)
        b0 = bs[0]
        fields = np.stack([cond.friction[b0], cond.slope_deg[b0], cond.payload_kg[b0], cond.target_velocity_mps[b0]])
        starts = [0] + [t for t in range(1, n) if np.any(fields[:, t] != fields[:, t - 1])] + [n]
        for s, e in zip(starts[:-1], starts[1:], strict=True):
            target = float(cond.target_velocity_mps[b0, s])
            phase = (f"μ {cond.friction[b0, s]:g}, {cond.slope_deg[b0, s]:g}°, {cond.payload_kg[b0, s]:g} kg "
                     f"({s}–{e - 1})")
            counts = np.array([trials_to_track(tr.velocity_xy_mps[:, b, 0], cond.target_velocity_mps[b], tr.fell[:, b],
                                               s, e) for b in bs])
            never = int(np.isnan(counts).sum())
            track = f"{stats.mean_ci(counts)} ({never})" if never < len(counts) else f"— ({never})"
            paper = PAPER_HARDWARE_COT.get(label)
            if isinstance(paper, dict):
                paper = paper.get(target)
            paper_text = f"CoT ≈ {paper:g}" if isinstance(paper, float) else ""
            if label == "flat → 10°" and s > 0:
                paper_text = f"tracked again within ≈ {PAPER_HARDWARE_SLOPE_TRIALS} trials"
            rows.append(f"| {label} | {phase} | {target:g} | " + " | ".join(
                mean_ci(last_mean(x[:, bs], e)) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
                + f" | {int(tr.fell[s:e, bs].sum())}/{tr.fell[s:e, bs].size} | {track} | {paper_text} |")
    text = (f"The paper's hardware experiments predicted under the `{result.labels[0]['physics']}` profile; per phase: "
            f"mean [95 % CI] of its last {LAST_TRIALS} trials over {len(result.spec.seeds)} seeds; tracked: the first "
            f"trial with |v_x − v*| ≤ {TRACKING_TOLERANCE_MPS} m/s and no fall. Taped feet: floor μ "
            f"{TAPED_FEET_FRICTION:g} (the paper gives none). The paper's figures are from one robot run each.\n\n"
            + "\n".join(rows) + "\n")
    return text


def _figure(name: str, group_key: str, changes_of=None, **kwargs):
    """A study's learning-curve figure ``name``: J (and the context) per trial per ``group_key``, with a line at each
    trial where ``changes_of(result)`` changes (the condition's phases)."""
    def draw(result, out: pathlib.Path, backend: str) -> str:
        del backend
        changes = [] if changes_of is None else changes_of(result)
        study_figures.learning_curves(out / name, result, group_key, changes=changes, **kwargs)
        return ""
    return draw


def _slope_phases(result) -> list[int]:
    """The slope study's learning phases: the first trial of each slope, then the first inference-mode trial (the
    trial count if none)."""
    inference = result.conditions.inference[0]
    learn = int(np.argmax(inference)) if inference.any() else result.trials.objective.shape[0]
    return phase_starts(result.conditions.slope_deg[0, :learn]) + [learn]


def figures_multi_velocity(result, out: pathlib.Path, backend: str) -> str:
    del backend
    target = result.conditions.target_velocity_mps[0]
    study_figures.learning_curves(out / "multi_velocity.png", result, "data_reuse",
                                  changes=phase_starts(target)[1:], target=target)
    return ""


def safety_summary(result) -> str:
    """Per group: falls during optimization (the trials not in inference mode) with the fall rate's 95 % interval,
    the runs' worst safety margin, and with ``--safe`` the proposals that fell back to a safe trial seen before."""
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    optimizing = cond.inference[:, :n].T == 0  # (n, B)
    names = np.array([", ".join(str(lab[g]) for g in result.spec.group_by) for lab in result.labels])
    safe = result.spec.safe
    rows = [f"| {', '.join(result.spec.group_by)} | falls during optimization / trials | fall rate [95 % CI] | "
            "runs' worst margin (median) |" + (" fallbacks |" if safe else ""),
            "|---|---|---|---|" + ("---|" if safe else "")]
    for name in dict.fromkeys(names):
        m = names == name
        falls, trials = int(((tr.fell[:, m] > 0) & optimizing[:, m]).sum()), int(optimizing[:, m].sum())
        worst = np.min(np.where(optimizing[:, m], tr.safety_margin[:, m], np.inf), axis=0)
        rate = stats.proportion_ci(falls, trials)
        rows.append(f"| {name} | {falls}/{trials} | {rate.mean:.3f} [{rate.low:.3f}, {rate.high:.3f}] | "
                    f"{np.median(worst):.2f} |" + (f" {int(tr.safe_fallback[:, m].sum())} |" if safe else ""))
    return ("\nSafety during optimization (" + ("safe optimization, --safe" if safe else "unconstrained optimization")
            + "; margin < 0: a fall or a tilt stop, docs/decisions.md §17):\n\n" + "\n".join(rows) + "\n")


def ablation_paper_marks(result) -> list[study_figures.PaperMark]:
    """The paper's J per controller (mean ± std over its 5 seeds) over the last trials it averages."""
    n = result.trials.objective.shape[0]
    return [study_figures.PaperMark(f"paper {c}", max(n - LAST_TRIALS, 0), n - 1, j[0], j[1], group=c)
            for c, (_, _, j) in PAPER_CONTROLLER_TABLE.items()]


def load_paper_marks(result) -> list[study_figures.PaperMark]:
    """The paper's J after adaptation per payload (no spread given) over the last trials of each payload phase."""
    payload = result.conditions.payload_kg[0]
    starts = phase_starts(payload) + [result.trials.objective.shape[0]]
    return [study_figures.PaperMark(f"paper {float(payload[start]):g} kg", max(stop - LAST_TRIALS, start), stop - 1,
                                    PAPER_LOAD_TABLE[float(payload[start])][0][2])
            for start, stop in zip(starts[:-1], starts[1:], strict=True) if float(payload[start]) in PAPER_LOAD_TABLE]


class Study(NamedTuple):
    name: str
    make_spec: Callable[..., StudySpec]
    report: Callable[..., str]  # (result, backend) → the table text; writes no file
    figures: Callable[..., str]  # (result, out, backend) → the study's figures; returns text the table gains
    description: str
    # (result) → the paper's J values that summary.png marks; none where the paper gives no J for the result
    paper_marks: Callable[..., list] = lambda result: []


STUDIES = {s.name: s for s in (
    Study("controller_ablation", ablation_spec, report_ablation, figures_ablation,
          "4 controllers × seeds × 40 trials, v* = 0.5 m/s", ablation_paper_marks),
    Study("load_adaptation", load_spec, report_load,
          _figure("load_adaptation.png", "schedule", lambda r: phase_starts(r.conditions.payload_kg[0])[1:],
                  context_index=0),
          "payload 0 → 7.5 → 15 kg with contextual BO", load_paper_marks),
    Study("friction", friction_spec, report_friction, _figure("friction.png", "friction"),
          "friction 0.3 / 0.6 / 0.9 learning curves"),
    Study("multi_velocity", multi_velocity_spec, report_multi_velocity, figures_multi_velocity,
          "0.8 → 0.3 → 0.6 m/s, with/without reuse"),
    Study("slope_adaptation", slope_spec, report_slope,
          _figure("slope_adaptation.png", "schedule", lambda r: _slope_phases(r)[1:], context_index=1),
          "0° → 10° → 12.5°, then inference mode on 10°…17.5° and up the 10° → 17.5° ramp"),
    Study("paper_hardware", hardware_spec, report_hardware, _figure("paper_hardware.png", "schedule"),
          "the hardware experiments under go1: flat, taped feet, 0.6→0.3→0.5→0.6 m/s, 10°, 5/10/15 kg"),

)}


def make_spec(name: str, *, seeds=None, trials=None, quick=False, physics: str | None = None,
              safe: bool = False, max_trials: int | None = None) -> StudySpec:
    if name not in STUDIES:
        raise study_spec.StudyError(f"unknown study {name!r}; available: {', '.join(STUDIES)}")
    if seeds is not None and seeds < 1:
        raise study_spec.StudyError(f"--seeds {seeds}: need at least 1")
    if trials is not None and trials < limits.MIN_STUDY_TRIALS:
        raise study_spec.StudyError(f"--trials {trials}: need at least {limits.MIN_STUDY_TRIALS} "
                                    f"({limits.MIN_STUDY_TRIALS_REASON})")
    spec = STUDIES[name].make_spec(seeds=seeds, trials=trials, quick=quick)
    if physics is not None:
        spec = dataclasses.replace(spec, physics=(physics,))
    if safe:
        spec = dataclasses.replace(spec, safe=True)
    if max_trials is not None:
        if max_trials < spec.num_trials:
            raise study_spec.StudyError(f"--max-trials {max_trials}: need at least the run's {spec.num_trials} trials")
        spec = dataclasses.replace(spec, max_trials=max_trials)
    study_spec.validate(spec)
    return spec


def notify_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def write_outputs(result, out: pathlib.Path, backend: str, name: str | None = None, command: str | None = None,
                  notify: Callable[[str], None] = notify_stderr) -> str:
    """Every file of a finished study; returns the table text. The trial table, the metadata and each group's best
    gait (``best_params/<group>.json``, :func:`save_best_gaits`) first (they cannot fail but for the disk), then
    table.md, then the study's figures (the ablation's table then gains the attitude rows its figure walks), the
    recording, and last the gaits' figures and videos (``best_<group>.mp4``,
    :mod:`cpgjax.studies.video`), with a line to ``notify`` per video, or one saying why there is none.

    Raises:
      study_io.OutputError: a file could not be written; the message names it and what was kept.
    """
    out.mkdir(parents=True, exist_ok=True)
    with study_io.writing(out, "trials.parquet"):
        study_io.write_trials(result, out / "trials.parquet")
    with study_io.writing(out, "metadata.json"):
        study_io.write_metadata(result, out / "metadata.json", command=command)
    with study_io.writing(out, f"{study_io.BEST_PARAMS}/"):
        gaits = save_best_gaits(out, result)
    study = STUDIES[name or result.spec.name]
    report = study.report(result, backend)
    tail = f"{safety_summary(result)}\nRun: {study_figures.run_line(result, study_io.run_figures(result))}\n"
    with study_io.writing(out, "table.md"):
        text = f"# {result.spec.name}\n\n{report}{tail}"
        (out / "table.md").write_text(text)
    with study_io.writing(out, "the study's figures"):
        extra = study.figures(result, out, backend)
        study_figures.optimization_progress(out / "optimization_progress.png", result, [
            group_name(lab, result.spec.group_by) for lab in result.labels])
    if extra:
        with study_io.writing(out, "table.md"):
            text = f"# {result.spec.name}\n\n{report}{extra}{tail}"
            (out / "table.md").write_text(text)
    logs = gait_rollouts(gaits, backend)
    with study_io.writing(out, "recording.rrd"):
        study_io.write_recording(result, out / "recording.rrd", [
            study_scene.Rollout(log, g.group, g.controller, result.labels[g.instance]["seed"], g.friction,
                                g.slope_deg, g.payload_kg) for g, log in zip(gaits, logs, strict=True)])
    with study_io.writing(out, "the best gaits' figures and videos"):
        study_figures.attitude_by_group(out / "attitude_best_gaits.png", gaits, logs)
        filmed = study_video.write_videos(out, gaits, logs, notify)
        # filmed: the videos written, for a prefix of the gaits (none where no OpenGL backend works)
        strips = {g.group: list(info["strip"]) for g, info in zip(gaits, filmed, strict=False)}
        study_figures.summary(out / "summary.png", result, text, gaits, strips,
                              study.paper_marks(result))
    return text


def output_folder(name: str, out=None) -> pathlib.Path:
    """A study's output folder: ``out``, by default ``results/<name>``."""
    return pathlib.Path(out or pathlib.Path("results") / name)


def run_plan(spec, out_dir, backend: str, start: int) -> str:
    """One line on what a study run would compute (``--dry-run``): instances, trials, env-steps, where it writes."""
    batch = len(study_spec.instances(spec))
    steps = spec.trial.transition_steps + spec.trial.steady_steps
    remaining = batch * (spec.num_trials - start) * steps
    axes = ", ".join(f"{len(getattr(spec, a))} {a}" for a in ("controllers", "seeds", "friction", "slope_deg",
                                                               "payload_kg", "target_velocity_mps", "schedules",
                                                               "data_reuse", "physics") if len(getattr(spec, a)) > 1)
    where = f"resuming {out_dir} at trial {start}" if start else f"writing {out_dir}/"
    return (f"{spec.name}: {batch} instances ({axes or 'one'}) × {spec.num_trials} trials of {steps * 0.001:g} s"
            f"{', safe' if spec.safe else ''}: {remaining:,} env-steps ({remaining * 0.001 / 3600:.2f} robot-hours) "
            f"on the {backend} backend, {where}")


def resume_notice(out: pathlib.Path, start: int, num_trials: int) -> str:
    return f"resuming {out} at trial {start} (trials are numbered from 0; {start} of {num_trials} are done)"


def run(name: str, *, seeds=None, trials=None, quick=False, out=None, resume=False, overwrite=False, backend="auto",
        progress=None, physics: str | None = None, command: str | None = None,
        notify: Callable[[str], None] | None = None, safe: bool = False, dry_run: bool = False,
        max_trials: int | None = None) -> tuple[str, pathlib.Path]:
    """Run (or resume) a study and write its outputs; returns (table text, output folder). ``physics``: the
    profile every instance simulates (default: the study's own); ``safe``: safe optimization (docs/decisions.md §17);
    ``max_trials``: the trials the run can later be extended to (``StudySpec.max_trials``).
    The output folder is checked first
    (:func:`study_io.open_run`: a non-empty one needs ``resume`` or ``overwrite``); ``notify`` gets the line that
    says where a resume starts; ``command`` goes into ``metadata.json``. ``dry_run``: every check, then the run's
    plan (:func:`run_plan`) as the text, nothing computed or written."""
    spec = make_spec(name, seeds=seeds, trials=trials, quick=quick, physics=physics, safe=safe,
                     max_trials=max_trials)
    out = output_folder(name, out)
    backend_name = backends.resolve_backend(backend)
    start = study_io.open_run(out, spec, backend_name, resume=resume, overwrite=overwrite, dry_run=dry_run)
    if dry_run:
        return run_plan(spec, out, backend_name, start), out
    if start and notify is not None and jax.process_index() == 0:
        notify(resume_notice(out, start, spec.num_trials))
    engine = ablation.Engine(spec, backend=backend)
    result = engine.run(out, resume=resume, progress=progress)
    if jax.process_index() > 0:  # one process writes the study's files (docs/scaling.md)
        return f"process {jax.process_index()}: instances {result.rows[0]}–{result.rows[1] - 1} done", out
    return write_outputs(result, out, engine.backend_name, name, command, notify or notify_stderr), out
