"""The hand-written reports of the paper's studies (``REPORTS``, by the name a study file's ``report`` key gives):
each sets the paper's figures beside ours and tests what the paper claims. The studies themselves are files
(``studies/*.toml``); a study without such a report gets the generic one (``cpgjax.studies.generic``).

======================  =======================================================================================
``controller_ablation`` the controller table (mean of the last 5 trials, mean and 95 % CI over seeds, tests against
                        the paper's table and between controllers) and the roll–pitch figure of the best parameters
``load_adaptation``     the load table, before/after adaptation, with the flat-ground optimum re-run loaded
``friction``            friction learning curves (paper Fig. sim_overview a)
``multi_velocity``      trials to track each target with and without data reuse (Fig. sim_overview b)
``slope_adaptation``    the slopes learned, inference mode on 10°…17.5° and the continuous ramp (Fig. sim_overview
                        c, Fig. slope_setting)
``paper_hardware``      the paper's hardware experiments predicted under the ``go1`` profile, per phase
======================  =======================================================================================

Every figure is a mean with its 95 % confidence interval over seeds (``cpgjax.studies.stats``).
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from cpgjax import ablation, cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.sim import backends
from cpgjax.studies import figures as study_figures
from cpgjax.studies import stats
from cpgjax.study import placement as study_placement
from cpgjax.trial import objective, protocol

Evaluation = dict[str, Any]
"""What a study's evaluate step walked beyond the engine's trials, by name (``Report.evaluate``, ``Study.evaluate``);
its report and files read it and simulate nothing."""

PAPER_SEEDS = 5  # the paper's tables' std is over 5 seeds
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


PAPER_HARDWARE_COT = {  # paper Sec. "Hardware Experiments": CoT ≈ these once tracked
    "flat 0.4 m/s": 0.8,
    "taped feet 0.4 m/s": 0.95,
    "0.6→0.3→0.5→0.6 m/s": {0.6: 0.95, 0.3: 0.70, 0.5: 0.90},
}
PAPER_HARDWARE_SLOPE_TRIALS = 20  # "stabilizes around this target once more within approximately 20 trials"


# ----------------------------------------------------------------------------------------------- analysis helpers


def last_mean(values: np.ndarray, stop: int, k: int = LAST_TRIALS) -> np.ndarray:
    """Mean over trials [stop − k, stop) of (N, B) values → (B,)."""
    return np.asarray(values)[max(stop - k, 0) : stop].mean(axis=0)


def mean_ci(values: np.ndarray) -> str:
    """Mean over seeds with its Student-t 95 % interval, as "mean [low, high]" (a quantity of either sign)."""
    return str(stats.mean_ci(values))


def nonnegative_ci(values: np.ndarray) -> str:
    """Mean over seeds of a quantity that cannot be negative (CoT, falls, trial counts) with its 95 % interval cut at
    0 (``stats.nonnegative_ci``), as "mean [low, high]"."""
    return str(stats.nonnegative_ci(values))


def in_effect(friction: float, labels: dict) -> float:
    """The μ an instance of ``labels`` (its physics profile and feet's μ) feels on a floor of μ ``friction``
    (``physics.contact_friction``)."""
    return float(
        physics_profiles.contact_friction(
            physics_profiles.get(str(labels["physics"])), friction, labels["foot_friction"]
        )
    )


def friction_text(friction: float, labels: dict) -> str:
    """A floor's μ as the reports write it: with the μ in effect beside it where the feet's is smaller."""
    mu = in_effect(friction, labels)
    return f"μ {friction:g}" + (f" ({mu:g} in effect)" if mu < friction else "")


def friction_note(result) -> str | None:
    """The note on floors the feet do not feel: for each (profile, feet's μ) of the study with a floor above the
    feet's μ, that such floors walk as the feet's, and why; None where every floor counts."""
    capped: dict[tuple[str, float], set[float]] = {}
    for b, lab in enumerate(result.labels):
        for mu in {float(v) for v in np.asarray(result.conditions.friction[b])}:
            if (feet := in_effect(mu, lab)) < mu:
                capped.setdefault((str(lab["physics"]), feet), set()).add(mu)
    if not capped:
        return None
    said = "; ".join(
        f"under physics {name}, μ {', '.join(f'{mu:g}' for mu in sorted(floors))} walked as {feet:g}"
        for (name, feet), floors in capped.items()
    )
    return (
        f"- Friction: a contact takes the smaller μ of floor and feet (Gazebo's rule, the paper's simulator), so a "
        f"floor above the feet's μ walks as the feet's ({said}): such rows are the feet's μ's rows. A study's "
        '`grid.foot_friction` at least the floor\'s makes the floor count (docs/physics.md "Friction").'
    )


def notes(result) -> str:
    """The notes under a study's tables: the line saying there is no interval or test below ``stats.MIN_SEEDS``
    seeds (where so), how the intervals are made, and what a J at its floor and a large CoT are."""
    floor = result.spec.switch_values().objective_floor
    too_few = stats.too_few_line(len(result.spec.seeds))
    lines = [f"- {too_few}"] if too_few else []
    lines += [note] if (note := friction_note(result)) else []
    lines += [
        "- Intervals: 95 % over seeds, Student-t; for CoT, falls and trial counts, which cannot be negative, its part "
        "below 0 cut off (an interval from 0 says the mean is not pinned down); a fall rate of the safety table: "
        "Clopper–Pearson over its trials. A rank test that cannot reach p < 0.05 at its sizes says so in place of p.",
        f"- J = {floor:g} is J's floor (the study's `objective_floor`, by default "
        f"`cpgjax.trial.objective.MIN_OBJECTIVE` = {objective.MIN_OBJECTIVE:g}; docs/decisions.md §10): a trial that "
        "fell or failed gets exactly it and no trial gets less, so a mean near it says most trials fell.",
        f"- CoT = energy / (m g d) with the forward distance d taken as at least {objective.MIN_DISTANCE_M:g} m "
        "(`cpgjax.trial.objective.MIN_DISTANCE_M`, docs/decisions.md §10; CoT has no other cap): a run that stands "
        f"still or walks backwards gets its energy over {objective.MIN_DISTANCE_M * 100:g} cm, a CoT of tens "
        "(e.g. 47.6), so a mean CoT far above 1 says a seed barely moved.",
    ]
    return "\nNotes:\n\n" + "\n".join(lines) + "\n"


def phase_starts(values: np.ndarray) -> list[int]:
    """Trials (of one instance's (N,) condition) at which the condition changes, with 0 first."""
    return [0] + [t for t in range(1, len(values)) if values[t] != values[t - 1]]


def evaluate(
    params: np.ndarray,
    controllers,
    scenario: go1_model.Scenario,
    trial_config,
    backend: str,
    target_mps: float,
    settle_trials: int = 1,
):
    """Fixed parameters (B, 8) on ``scenario``: ``settle_trials`` trials, then one measured trial.

    Returns (velocity_x, CoT, J, fell) arrays (B,), the first three of the measured trial, ``fell`` 1 where any of
    the trials fell."""
    sim = backends.make_backend(scenario, backend, trial_config=trial_config)
    gates = protocol.batch_gates(list(controllers))
    state = sim.reset(params)
    fell = np.zeros(params.shape[0])
    for _ in range(settle_trials + 1):
        state, record = sim.trial(state, params, gates)
        record = study_placement.fetch(record)
        fell = np.maximum(fell, np.asarray(record.fell))
    j = jax.vmap(objective.objective, in_axes=(0, None))(record, np.float32(target_mps))
    return (
        np.asarray(objective.mean_velocity(record))[:, 0],
        np.asarray(objective.cost_of_transport(record)),
        np.asarray(j),
        fell,
    )


def rollouts(
    params: np.ndarray, controllers, scenario, trial_config, backend: str, steps: int = 3000, gaits=None
) -> list:
    """Per-step logs (``protocol.StepLog`` of NumPy (T, ...)) of fixed parameters after one settling trial, each
    instance with its controller and gait (``gaits`` None: the trot)."""
    sim = backends.make_backend(scenario, backend, trial_config=trial_config)
    gates = protocol.batch_gates(list(controllers), gaits)
    state, _ = sim.trial(sim.reset(params, gates), params, gates)
    _, log = sim.rollout(state, params, gates, steps)
    log = study_placement.fetch(log)
    return [type(log)(*(field[b] for field in log)) for b in range(params.shape[0])]


def best_params(result, mask: np.ndarray, stop: int | None = None) -> tuple[np.ndarray, int, float]:
    """The best observed parameters among the instances in ``mask`` (and trials < stop): (x, instance, J)."""
    j = np.where(mask[None, :], result.trials.objective[:stop], -np.inf)
    t, b = np.unravel_index(np.argmax(j), j.shape)
    return result.trials.params[t, b], int(b), float(j[t, b])


# ----------------------------------------------------------------------------------------------- reports


def _labels(result, key) -> np.ndarray:
    return np.array([lab[key] for lab in result.labels])


def report_ablation(result: ablation.StudyResult) -> str:
    tr, n = result.trials, result.trials.objective.shape[0]
    controllers = _labels(result, "controller")
    rows = [
        "| controller | velocity [m/s] ours | paper | CoT ours | paper | J ours | paper | falls (all trials) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in cpg.CONTROLLERS:
        m = controllers == c
        if not m.any():
            continue
        v, cot, j = (last_mean(x[:, m], n) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
        p = PAPER_CONTROLLER_TABLE[c]
        rows.append(
            f"| {c} | {mean_ci(v)} | {p[0][0]:.3f} ± {p[0][1]:.3f} | {nonnegative_ci(cot)} | "
            f"{p[1][0]:.3f} ± {p[1][1]:.3f} | {mean_ci(j)} | {p[2][0]:.3f} ± {p[2][1]:.3f} | "
            f"{int(tr.fell[:, m].sum())}/{tr.fell[:, m].size} |"
        )
    return (
        f"Controller ablation, v* = 0.5 m/s: mean of the last {LAST_TRIALS} of {n} trials per run, then "
        f"{stats.over_seeds(len(result.spec.seeds))}; the paper's mean ± std over {PAPER_SEEDS} seeds.\n\n"
        + "\n".join(rows)
        + "\n"
        + ablation_verdicts(result)
    )


def evaluate_ablation(result: ablation.StudyResult, backend: str) -> Evaluation:
    """The best parameters of open loop and VMC+Tegotae walked again (3 s after a settling trial), for the paper's
    Fig. att_comp: ``best`` ((x, instance, J) per controller) and ``logs`` (per-step logs by ``best_<controller>``)."""
    controllers = _labels(result, "controller")
    picks = [c for c in ("open_loop", "vmc_tegotae") if (controllers == c).any()]
    if not picks:
        return {"best": [], "logs": {}}
    best = [best_params(result, controllers == c) for c in picks]
    params = np.stack([b[0] for b in best])
    scenario = go1_model.make_scenarios(
        friction=[result.spec.friction[0]] * len(picks), physics=[result.labels[b]["physics"] for _, b, _ in best]
    )
    logs = {
        f"best_{c}": lg
        for c, lg in zip(picks, rollouts(params, picks, scenario, result.spec.trial, backend), strict=True)
    }
    return {"best": best, "logs": logs}


def figures_ablation(result: ablation.StudyResult, evaluation: Evaluation, out: pathlib.Path) -> str:
    """learning_curves.png, and attitude.png with its table: the roll–pitch of open loop's and VMC+Tegotae's best
    parameters (the paper's Fig. att_comp, :func:`evaluate_ablation`)."""
    study_figures.learning_curves(out / "learning_curves.png", result, "controller")
    best, logs = evaluation["best"], evaluation["logs"]
    if not best:
        return ""
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
    present = [c for c in cpg.CONTROLLERS if (controllers == c).sum() >= stats.MIN_SEEDS]
    if not present:
        return ""
    lines = [
        "",
        "Ours − paper (Welch's test from the paper's mean ± std, n = 5):",
        "",
        "| controller | CoT | J |",
        "|---|---|---|",
    ]
    for c in present:
        p = PAPER_CONTROLLER_TABLE[c]
        cells = [
            stats.compare_to_summary(_final(result, m, controllers == c), *p[k], PAPER_SEEDS)
            for k, m in ((1, "cot"), (2, "objective"))
        ]
        lines.append(f"| {c} | {cells[0]} | {cells[1]} |")
    pairs = [
        (a, b)
        for a, b in (("tegotae", "open_loop"), ("vmc_tegotae", "vmc"), ("vmc", "open_loop"), ("vmc_tegotae", "tegotae"))
        if a in present and b in present
    ]
    if pairs:
        lines += [
            "",
            "Between controllers (ours; Welch's t and Mann–Whitney U, two-sided):",
            "",
            "| comparison | CoT | J |",
            "|---|---|---|",
        ]
        for a, b in pairs:
            cells = [
                stats.compare(_final(result, m, controllers == a), _final(result, m, controllers == b))
                for m in ("cot", "objective")
            ]
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
    return (
        f"{int(tr.fell[start:stop].sum())}/{tr.fell[start:stop].size} | {np.nanmean(c_load):.1f} | {spread:.1f} | "
        f"{int(tr.context_changed[start:stop].sum())}/{tr.context_changed[start:stop].size} | "
        f"{beta.min():.2g} – {beta.max():.2g}"
    )


def _load_phases(result: ablation.StudyResult) -> tuple[list[int], list[float]]:
    """The load study's phases: the first trial of each payload (then the trial count), and each phase's payload."""
    payload = result.conditions.payload_kg
    starts = phase_starts(payload[0]) + [result.trials.objective.shape[0]]
    return starts, [float(payload[0, s]) for s in starts[:-1]]


def evaluate_load(result: ablation.StudyResult, backend: str) -> Evaluation:
    """Each run's best parameters before the first payload change walked again under every later payload
    (``registry.evaluate``: a settling trial, then a measured one): ``flat_optimum`` maps a payload to the (velocity,
    CoT, J, fell) arrays over the runs."""
    starts, loads = _load_phases(result)
    flat = np.stack(
        [
            best_params(result, np.eye(len(result.labels), dtype=bool)[b], starts[1])[0]
            for b in range(len(result.labels))
        ]
    )
    walked = {}
    for load in loads:
        if load > 0:
            scenario = go1_model.make_scenarios(payload_kg=[load] * len(flat), physics=_labels(result, "physics"))
            walked[load] = evaluate(flat, _labels(result, "controller"), scenario, result.spec.trial, backend, 0.5)
    return {"flat_optimum": walked}


def report_load(result: ablation.StudyResult, evaluation: Evaluation) -> str:
    tr = result.trials
    starts, loads = _load_phases(result)
    rows = [
        "| load [kg] | velocity ours (flat optimum) | paper | CoT ours (flat optimum) | paper | "
        "J ours (flat optimum) | paper |",
        "|---|---|---|---|---|---|---|",
    ]
    config = result.spec.optimizer_config()
    tolerance = config.context_thresholds[0] * (config.context_upper[0] - config.context_lower[0])  # eq. (14)
    phases = [
        "| load [kg] (trials) | falls | c_load [N] | c_load spread within a run [N] (same-context tolerance "
        f"t_load·r_load = {tolerance:g} N) | trials with β_init,c | β |",
        "|---|---|---|---|---|---|",
    ]
    for load, start, stop in zip(loads, starts[:-1], starts[1:], strict=True):
        after = [last_mean(x, stop) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective)]
        before = evaluation["flat_optimum"].get(load)
        paper_after, paper_before = PAPER_LOAD_TABLE.get(load, (None, None))
        cells = []
        for k in range(3):
            ci = nonnegative_ci if k == 1 else mean_ci  # CoT cannot be negative
            ours = ci(after[k]) + (f" ({ci(before[k])})" if before is not None else " (-)")
            paper = (
                ""
                if paper_after is None
                else f"{paper_after[k]:.3f}" + (f" ({paper_before[k]:.3f})" if paper_before else " (-)")
            )
            cells += [ours, paper]
        rows.append(f"| {load:g} | " + " | ".join(cells) + " |")
        phases.append(f"| {load:g} ({start}–{stop - 1}) | {phase_diagnostics(result, start, stop)} |")
    text = (
        f"Load adaptation, v* = 0.5 m/s, payload changes at trials {starts[1:-1]} of {starts[-1]}; after: the last "
        f"{LAST_TRIALS} trials of each phase, {stats.over_seeds(len(result.spec.seeds))}; in "
        "parentheses: the best parameters found before the first payload change, re-run on the loaded robot. The "
        "paper gives no spread for this table.\n\n" + "\n".join(rows) + "\n\nPer phase:\n\n" + "\n".join(phases) + "\n"
    )
    return text


def report_friction(result: ablation.StudyResult) -> str:
    tr, n = result.trials, result.trials.objective.shape[0]
    friction = _labels(result, "friction")
    rows = [
        "| friction | μ in effect | velocity [m/s] | CoT | J | trials to a prospective solution (J ≥ 90 % of the "
        "run's best) |",
        "|---|---|---|---|---|---|",
    ]
    for f in result.spec.friction:
        m = friction == f
        mu = in_effect(f, result.labels[int(np.argmax(m))])
        j = tr.objective[:, m]
        first = [int(np.argmax(j[:, b] >= 0.9 * j[:, b].max())) + 1 for b in range(j.shape[1])]
        v, cot, final_j = (last_mean(x[:, m], n) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
        feet = "" if mu == f else " (the feet's)"
        rows.append(
            f"| {f} | {mu:g}{feet} | {mean_ci(v)} | {nonnegative_ci(cot)} | {mean_ci(final_j)} "
            f"| {nonnegative_ci(first)} |"
        )
    text = (
        f"Friction, v* = 0.5 m/s, VMC+Tegotae: last {LAST_TRIALS} of {n} trials, "
        f"{stats.over_seeds(len(result.spec.seeds))}. Paper: prospective solutions within < 10 trials for every "
        "friction (no table).\n\n" + "\n".join(rows) + "\n" + _versus(result, friction, 0.6, "friction")
    )
    return text


def _versus(result, labels: np.ndarray, reference, name: str) -> str:
    """Each group's final CoT and J against the reference group's (Welch's t and Mann–Whitney U on the seeds)."""
    ref = labels == reference
    others = [g for g in dict.fromkeys(labels.tolist()) if g != reference and (labels == g).sum() >= stats.MIN_SEEDS]
    if ref.sum() < stats.MIN_SEEDS or not others:
        return ""
    lines = [
        "",
        f"Against {name} = {reference} (Welch's t and Mann–Whitney U, two-sided):",
        "",
        f"| {name} | CoT | J |",
        "|---|---|---|",
    ]
    for g in others:
        cells = [stats.compare(_final(result, m, labels == g), _final(result, m, ref)) for m in ("cot", "objective")]
        lines.append(f"| {g} − {reference} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


def trials_to_track(velocity: np.ndarray, target: np.ndarray, fell: np.ndarray, start: int, stop: int) -> float:
    """Trials from ``start`` until the first with |v − v*| ≤ tolerance and no fall; a run that never tracks before
    ``stop`` counts as the phase's length + 1 (censored: the least it could have taken), so the mean keeps it."""
    ok = (np.abs(velocity[start:stop] - target[start:stop]) <= TRACKING_TOLERANCE_MPS) & (fell[start:stop] == 0)
    return float(np.argmax(ok) + 1) if ok.any() else float(stop - start + 1)


def report_multi_velocity(result: ablation.StudyResult) -> str:
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    starts = phase_starts(cond.target_velocity_mps[0]) + [n]
    reuse = _labels(result, "data_reuse")
    rows = [
        "| target [m/s] (trials) | data reuse | trials to track (mean [95 % CI]; a run that never tracks counts "
        "as the phase's length + 1) | runs never tracking | final velocity | final CoT |",
        "|---|---|---|---|---|---|",
    ]
    tracked = {}
    for s, e in zip(starts[:-1], starts[1:], strict=True):
        target = float(cond.target_velocity_mps[0, s])
        for flag in result.spec.data_reuse:
            bs = np.flatnonzero(reuse == flag)
            counts = np.array(
                [
                    trials_to_track(tr.velocity_xy_mps[:, b, 0], cond.target_velocity_mps[b], tr.fell[:, b], s, e)
                    for b in bs
                ]
            )
            never = int(np.sum(counts > e - s))
            tracked[(s, flag)] = counts
            rows.append(
                f"| {target:g} ({s}–{e - 1}) | {'yes' if flag else 'no (restart)'} | "
                f"{nonnegative_ci(counts)} | {never} | "
                f"{mean_ci(last_mean(tr.velocity_xy_mps[:, bs, 0], e))} | "
                f"{nonnegative_ci(last_mean(tr.cot[:, bs], e))} |"
            )
    text = (
        f"Multi-velocity tracking: a target counts as tracked from the first trial with |v_x − v*| ≤ "
        f"{TRACKING_TOLERANCE_MPS} m/s and no fall; final = mean of the last {LAST_TRIALS} trials of the phase; "
        f"{len(result.spec.seeds)} seeds. Paper: fewer trials after each change with data reuse (figure only).\n\n"
        + "\n".join(rows)
        + "\n"
    )
    if set(result.spec.data_reuse) == {True, False}:
        lines = [
            "",
            "Trials to track, reuse − restart (every run, the never-tracking ones censored as above; Welch's "
            "t and Mann–Whitney U):",
            "",
        ]
        for s in starts[1:-1]:
            a, b = tracked[(s, True)], tracked[(s, False)]
            verdict = (
                stats.compare(a, b)
                if min(a.size, b.size) >= stats.MIN_SEEDS
                else f"no test below {stats.MIN_SEEDS} runs per group"
            )
            lines.append(f"- {float(cond.target_velocity_mps[0, s]):g} m/s (from trial {s}): {verdict}")
        text += "\n".join(lines) + "\n"
    return text


def report_slope(result: ablation.StudyResult) -> str:
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    starts = _slope_phases(result)
    learn = starts[-1]
    rows = ["| slope [deg] (trials) | velocity | CoT | J | c_slope [rad] | falls |", "|---|---|---|---|---|---|"]
    for s, e in zip(starts[:-1], starts[1:], strict=True):
        v, cot, j, c_slope = (
            last_mean(x, e) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective, tr.context[..., 1])
        )
        rows.append(
            f"| {cond.slope_deg[0, s]:g} ({s}–{e - 1}) | {mean_ci(v)} | {nonnegative_ci(cot)} | {mean_ci(j)} | "
            f"{mean_ci(c_slope)} | {int(tr.fell[s:e].sum())} |"
        )
    text = (
        f"Slope adaptation, v* = 0.5 m/s, contextual BO; last {LAST_TRIALS} trials of each phase, "
        f"{len(result.spec.seeds)} seeds.\n\n" + "\n".join(rows) + "\n"
    )
    ramp = ramp_start(result)
    if learn < ramp:
        rows = ["| slope [deg] | velocity | J | falls / trials | paper |", "|---|---|---|---|---|"]
        inf_starts = phase_starts(cond.slope_deg[0, learn:ramp])
        bounds = [learn + s for s in inf_starts] + [ramp]
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            slope = float(cond.slope_deg[0, s])
            paper = "walks" if slope <= 15.0 else "not reported as walking"
            rows.append(
                f"| {slope:g} | {mean_ci(tr.velocity_xy_mps[s:e, :, 0])} | {mean_ci(tr.objective[s:e])} | "
                f"{int(tr.fell[s:e].sum())}/{tr.fell[s:e].size} | {paper} |"
            )
        text += "\nInference mode (β = 1e-6), trials " + f"{learn}–{ramp - 1}:\n\n" + "\n".join(rows) + "\n"
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
    tr, cond, ramp = result.trials, result.walked, result.spec.ramp
    slope = cond.slope_deg[:, start:].T  # (trials, B): the slope each trial started on
    fell = tr.fell[start:] > 0
    rows = ["| slopes [deg] | trials | velocity | J | falls / trials | paper |", "|---|---|---|---|---|---|"]
    for lo, hi in zip(RAMP_BANDS_DEG[:-1], RAMP_BANDS_DEG[1:], strict=True):
        band = (slope >= lo) & ((slope < hi) | (hi == RAMP_BANDS_DEG[-1]))  # the top band holds the top
        paper = "walks" if hi <= 15.0 else "walks up to 15°"
        figures = (
            f"{mean_ci(tr.velocity_xy_mps[start:, :, 0][band])} | {mean_ci(tr.objective[start:][band])} | "
            f"{int(fell[band].sum())}/{int(band.sum())}"
            if band.any()
            else "– | – | –"
        )
        rows.append(f"| {lo:g}–{hi:g} | {int(band.sum())} | {figures} | {paper} |")
    steepest = np.where(~fell, slope, -np.inf).max(axis=0)  # per seed; −inf: every ramp trial fell
    walked = np.isfinite(steepest)
    top = int(np.sum(steepest >= ramp.end_deg))
    return (
        f"\nContinuous ramp {ramp.start_deg:g}° → {ramp.end_deg:g}° over {ramp.length_m:g} m (the paper's Fig. "
        f"slope_setting), inference mode, trials {start}–{tr.objective.shape[0] - 1}; each trial starts on the "
        f"slope the instance has climbed to, a fall puts it back at the bottom:\n\n" + "\n".join(rows) + "\n\n"
        f"Steepest slope walked without a fall: {mean_ci(steepest[walked])}° over the {int(walked.sum())} of "
        f"{walked.size} seeds with one; {top} reached the top.\n"
    )


def report_hardware(result: ablation.StudyResult) -> str:
    tr, cond = result.trials, result.walked
    n = tr.objective.shape[0]
    schedules = _labels(result, "schedule")
    rows = [
        "| schedule | phase (trials) | v* [m/s] | v_x [m/s] | CoT | J | falls | trials to track after the change, "
        "a run never tracking counted as the phase's length + 1 (runs never tracking) | paper |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label in dict.fromkeys(schedules):
        bs = np.flatnonzero(schedules == label)
        b0 = bs[0]
        fields = np.stack([cond.friction[b0], cond.slope_deg[b0], cond.payload_kg[b0], cond.target_velocity_mps[b0]])
        starts = [0] + [t for t in range(1, n) if np.any(fields[:, t] != fields[:, t - 1])] + [n]
        for s, e in zip(starts[:-1], starts[1:], strict=True):
            target = float(cond.target_velocity_mps[b0, s])
            phase = (
                f"μ {cond.friction[b0, s]:g}, {cond.slope_deg[b0, s]:g}°, {cond.payload_kg[b0, s]:g} kg ({s}–{e - 1})"
            )
            counts = np.array(
                [
                    trials_to_track(tr.velocity_xy_mps[:, b, 0], cond.target_velocity_mps[b], tr.fell[:, b], s, e)
                    for b in bs
                ]
            )
            never = int(np.sum(counts > e - s))
            track = f"{nonnegative_ci(counts)} ({never})"
            paper = PAPER_HARDWARE_COT.get(label)
            if isinstance(paper, dict):
                paper = paper.get(target)
            paper_text = f"CoT ≈ {paper:g}" if isinstance(paper, float) else ""
            if label == "flat → 10°" and s > 0:
                paper_text = f"tracked again within ≈ {PAPER_HARDWARE_SLOPE_TRIALS} trials"
            v, cot, j = (last_mean(x[:, bs], e) for x in (tr.velocity_xy_mps[..., 0], tr.cot, tr.objective))
            rows.append(
                f"| {label} | {phase} | {target:g} | {mean_ci(v)} | {nonnegative_ci(cot)} | {mean_ci(j)} | "
                f"{int(tr.fell[s:e, bs].sum())}/{tr.fell[s:e, bs].size} | {track} | {paper_text} |"
            )
    text = (
        f"The paper's hardware experiments predicted under the `{result.labels[0]['physics']}` profile; per phase: "
        f"its last {LAST_TRIALS} trials, {stats.over_seeds(len(result.spec.seeds))}; tracked: the first "
        f"trial with |v_x − v*| ≤ {TRACKING_TOLERANCE_MPS} m/s and no fall. Taped feet: floor μ "
        f"{_taped_feet_friction(result)} (the paper gives none). The paper's figures are from one robot run "
        "each.\n\n" + "\n".join(rows) + "\n"
    )
    return text


def _taped_feet_friction(result) -> str:
    """The floor μ of the hardware study's taped-feet schedule (its study file's)."""
    for lab, mu in zip(result.labels, result.conditions.friction[:, 0], strict=True):
        if lab["schedule"].startswith("taped feet"):
            return f"{mu:g}"
    return "(no taped-feet schedule)"


def _figure(name: str, group_key: str, changes_of=None, **kwargs):
    """A study's learning-curve figure ``name``: J (and the context) per trial per ``group_key``, with a line at each
    trial where ``changes_of(result)`` changes (the condition's phases)."""

    def draw(result: ablation.StudyResult, out: pathlib.Path) -> str:
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


def figures_multi_velocity(result: ablation.StudyResult, out: pathlib.Path) -> str:
    target = result.conditions.target_velocity_mps[0]
    study_figures.learning_curves(
        out / "multi_velocity.png", result, "data_reuse", changes=phase_starts(target)[1:], target=target
    )
    return ""


def safety_summary(result) -> str:
    """Per group: falls during optimization (the trials not in inference mode) with the fall rate's 95 % interval,
    the runs' worst safety margin, and with ``--safe`` the proposals that fell back to a safe trial seen before."""
    tr, cond = result.trials, result.conditions
    n = tr.objective.shape[0]
    optimizing = cond.inference[:, :n].T == 0  # (n, B)
    names = np.array([", ".join(str(lab[g]) for g in result.spec.group_by) for lab in result.labels])
    safe = result.spec.safe
    rows = [
        f"| {', '.join(result.spec.group_by)} | falls during optimization / trials | fall rate [95 % CI] | "
        "runs' worst margin (median) |" + (" fallbacks |" if safe else ""),
        "|---|---|---|---|" + ("---|" if safe else ""),
    ]
    for name in dict.fromkeys(names):
        m = names == name
        falls, trials = int(((tr.fell[:, m] > 0) & optimizing[:, m]).sum()), int(optimizing[:, m].sum())
        worst = np.min(np.where(optimizing[:, m], tr.safety_margin[:, m], np.inf), axis=0)
        rate = stats.proportion_ci(falls, trials)
        rows.append(
            f"| {name} | {falls}/{trials} | {rate.mean:.3f} [{rate.low:.3f}, {rate.high:.3f}] | "
            f"{np.median(worst):.2f} |" + (f" {int(tr.safe_fallback[:, m].sum())} |" if safe else "")
        )
    return (
        "\nSafety during optimization ("
        + ("safe optimization, --safe" if safe else "unconstrained optimization")
        + "; margin < 0: a fall or a tilt stop, docs/decisions.md §17):\n\n"
        + "\n".join(rows)
        + "\n"
    )


def ablation_paper_marks(result) -> list[study_figures.PaperMark]:
    """The paper's J per controller (mean ± std over its 5 seeds) over the last trials it averages."""
    n = result.trials.objective.shape[0]
    return [
        study_figures.PaperMark(f"paper {c}", max(n - LAST_TRIALS, 0), n - 1, j[0], j[1], group=c)
        for c, (_, _, j) in PAPER_CONTROLLER_TABLE.items()
    ]


def load_paper_marks(result) -> list[study_figures.PaperMark]:
    """The paper's J after adaptation per payload (no spread given) over the last trials of each payload phase."""
    payload = result.conditions.payload_kg[0]
    starts = phase_starts(payload) + [result.trials.objective.shape[0]]
    return [
        study_figures.PaperMark(
            f"paper {float(payload[start]):g} kg",
            max(stop - LAST_TRIALS, start),
            stop - 1,
            PAPER_LOAD_TABLE[float(payload[start])][0][2],
        )
        for start, stop in zip(starts[:-1], starts[1:], strict=True)
        if float(payload[start]) in PAPER_LOAD_TABLE
    ]


def walks_nothing(*given) -> Evaluation:
    """The evaluate step of a report or a study that needs nothing walked again (whatever it is given): nothing."""
    del given
    return {}


def only(results: dict[str, ablation.StudyResult]) -> ablation.StudyResult:
    """The result of a study of one engine run."""
    (result,) = results.values()
    return result


def of_result(function: Callable[..., str]) -> Callable[..., str]:
    """A report or figure function of the result alone (and the folder), as a :class:`Report` field."""
    return lambda result, evaluation, *out: function(result, *out)


class Report(NamedTuple):
    """A one-folder study's report: the hand-written ones a study file names (``report = "<name>"``), and the
    generic one (``cpgjax.studies.generic``). ``cpgjax.studies.driver.one_folder`` makes it a study of the
    protocol (``Study``).

    Fields:
      report: (result, evaluation) → the table text; pure (it simulates nothing and writes no file).
      figures: (result, evaluation, out) → draws the study's figures into ``out``; returns text the table gains.
      evaluate: (result, backend) → what ``report`` and ``figures`` need walked again (an :data:`Evaluation`); the
        only one of the three that simulates.
      paper_marks: (result) → the paper's J values that summary.png marks; none where the paper gives no J.
    """

    report: Callable[..., str]
    figures: Callable[..., str]
    evaluate: Callable[..., Evaluation] = walks_nothing
    paper_marks: Callable[..., list] = lambda result: []


class Study(NamedTuple):
    """One study of any kind, as ``cpgjax.studies.driver.run`` runs it (docs/studies.md "One protocol"): the
    engine's runs, one step beyond them that simulates, a pure report, and its files.

    Fields:
      name: the study's name (its default folder ``results/<name>``).
      specs: the engine's runs: one, written into the study's folder, or several (a transfer study's arms), each
        in a folder of its name below it.
      evaluate: (results, backend) → an :data:`Evaluation`: what the report and the files need walked again (the
        best gaits, parameters under other conditions); the only step that simulates after the engine.
      report: (results, evaluation) → the table text; pure.
      write: (results, evaluation, text, out, notify) → writes the study's files after the trial tables and the
        metadata (table.md, figures, videos …); returns the table's final text.
      metadata: more keys for every run's ``metadata.json`` (a study file's path and text).
      plan: what a dry run's plan adds after the runs' plans.
      written_by: the command that writes its folders, as ``metadata.json`` records it (``cpgjax show`` reads it).
    """

    name: str
    specs: tuple
    evaluate: Callable[..., Evaluation]
    report: Callable[..., str]
    write: Callable[..., str]
    metadata: dict | None = None
    plan: str = ""
    written_by: str = "study"


REPORTS = {
    "controller_ablation": Report(
        of_result(report_ablation), figures_ablation, evaluate_ablation, ablation_paper_marks
    ),
    "load_adaptation": Report(
        report_load,
        of_result(
            _figure(
                "load_adaptation.png",
                "schedule",
                lambda r: phase_starts(r.conditions.payload_kg[0])[1:],
                context_index=0,
            )
        ),
        evaluate_load,
        load_paper_marks,
    ),
    "friction": Report(of_result(report_friction), of_result(_figure("friction.png", "friction"))),
    "multi_velocity": Report(of_result(report_multi_velocity), of_result(figures_multi_velocity)),
    "slope_adaptation": Report(
        of_result(report_slope),
        of_result(_figure("slope_adaptation.png", "schedule", lambda r: _slope_phases(r)[1:], context_index=1)),
    ),
    "paper_hardware": Report(of_result(report_hardware), of_result(_figure("paper_hardware.png", "schedule"))),
}
