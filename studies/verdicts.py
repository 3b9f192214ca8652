"""The verdict table of docs/REPRODUCTION.md, recomputed from the runs' folders by the rule stated there before the
runs ("Criteria"):

    python studies/verdicts.py RESULTS_DIR                  # the verdicts of the paper studies found in RESULTS_DIR
    python studies/verdicts.py RESULTS_DIR --one-change     # and each one-change run RESULTS_DIR/<study>__<switch>

RESULTS_DIR holds one folder per paper study, named as the study (``controller_ablation``, ``load_adaptation``,
``friction``, ``multi_velocity``, ``slope_adaptation``, ``paper_hardware``); those present are judged, from their
``trials.parquet`` and ``metadata.json`` (the commit each ran at is printed). The load table's flat optimum walks each
seed's best unloaded gait again under the loads (native backend, a few seconds).

Every figure is a mean over seeds of each run's last 5 trials of its phase. A figure of the paper (a value, or a mean
± std over its 5 seeds) gets:

* **agrees**: equivalence within ±margin, the two one-sided tests (TOST) at 5 % after Holm's correction over the
  figure's family (the 90 % interval of the difference inside ±margin);
* **differs**: the two-sided test (Welch's from the paper's summary, or one-sample against a value) at 5 % after Holm
  over the family, and not equivalent;
* **inconclusive**: neither.

A claim of the paper (an effect in one direction, or a bound) gets **reproduced** when the one-sided test in the
claimed direction passes after Holm, **not reproduced** when the one-sided test against the claim (an effect at least
the margin in the claimed direction) passes after Holm, and **inconclusive** otherwise. Falls are counted per seed,
with a cluster bootstrap over seeds (``stats.cluster_bootstrap``).

``--one-change`` sets each ``<study>__<switch>`` folder beside its ``<study>``: the same seeds, so each figure's
change is a paired difference over seeds with its 95 % interval (paired t; Holm over the figures of each run), and
the verdict the run's own figures get by the same rule.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.studies import registry, stats
from cpgjax.study import files as study_io
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space

ALPHA = stats.ALPHA
LAST_TRIALS = registry.LAST_TRIALS
FIGURES = {"v_x": "velocity_x_mps", "CoT": "cost_of_transport", "J": "objective"}
UNITS = {"v_x": " m/s", "CoT": "", "J": ""}
NONNEGATIVE = {"CoT"}  # of FIGURES: cannot be negative
# The margins (docs/REPRODUCTION.md, "Criteria"): the paper's own seed-to-seed std of the figure where it gives one;
# for its load table, which gives none, the std of the same controller (VMC+Tegotae) at the same target on flat ground
# from its controller table, taken also as the load rows' spread over their 5 seeds.
LOAD_STD = dict(zip(FIGURES, (s for _, s in registry.PAPER_CONTROLLER_TABLE["vmc_tegotae"]), strict=True))
VELOCITY_MARGIN_MPS = registry.TRACKING_TOLERANCE_MPS  # a walk at v* counts within the tracking tolerance
HARDWARE_COT_MARGIN = 0.10  # twice the paper's seed std of VMC+Tegotae's CoT (0.050): one robot run, no spread given
RAMP_MARGIN_DEG = 1.25  # half the 2.5° step between the slopes the paper tests
FRICTION_TRIALS_BOUND = 10.0  # "prospective solutions within less than 10 trials"
PROSPECTIVE = 0.9  # a prospective solution: J ≥ this × the group's mean final J
# The paper's same-context tolerances t·r (its appendix: t_load 0.2 × r_load 40 N, t_slope 0.1 × r_slope 0.5 rad):
# "each estimator is capable of providing consistent contextual information".
CONTEXT_TOLERANCE = {"c_load_n": 0.2 * 40.0, "c_slope_rad": 0.1 * 0.5}
# The paper's hardware 10° adaptation (Sec. "Hardware Experiments"): "a decrease in ω_swing, x_offset,front and g_p;
# an increase in ω_stance, g_c, σ_N and x_offset,hind" from the flat optimum to the slope's.
HARDWARE_SLOPE_SHIFTS = {
    "omega_swing_rad_s": -1,
    "x_offset_front_m": -1,
    "ground_penetration_m": -1,
    "omega_stance_rad_s": +1,
    "ground_clearance_m": +1,
    "sigma_n": +1,
    "x_offset_hind_m": +1,
}


class Row(NamedTuple):
    """One verdict: what the paper says, ours, the effect and its tests (p-values before Holm)."""

    family: str
    figure: str
    paper: str
    ours: str
    effect: stats.Effect
    margin: float
    margin_source: str
    kind: str  # "figure": equivalence or difference; "claim_below" / "claim_above": the paper claims effect < / > 0
    note: str = ""

    def tests(self) -> tuple[float, float]:
        """(the test for the paper, the test against it), before Holm."""
        e = self.effect
        if self.kind == "figure":
            return e.equivalence_p(self.margin), e.two_sided_p()
        if self.kind == "claim_below":
            return e.below_p(0.0), e.above_p(-self.margin)
        return e.above_p(0.0), e.below_p(self.margin)


def _cell(values: np.ndarray, unit: str = "", nonnegative: bool = False) -> str:
    """ "mean [95 % CI]unit (n = …)"; ``nonnegative``: a quantity that cannot be negative (``stats.nonnegative_ci``)."""
    ci = stats.nonnegative_ci(values) if nonnegative else stats.mean_ci(values)
    return f"{ci}{unit} (n = {ci.n})"


def _final(cols: dict, name: str, stop: int, mask: np.ndarray) -> np.ndarray:
    """Each run's mean of ``name`` over its last LAST trials before ``stop`` (the runs in ``mask``)."""
    return registry.last_mean(cols[name][:, mask], stop)


def _objective_at_paper_floor(cols: dict) -> dict:
    """The trials with J at the paper's floor of −1 (a one-change run of the floor records its own): J is
    max(J, −1), a fall −1, the same J the reproduction's runs record."""
    out = dict(cols)
    out["objective"] = np.where(
        cols["fell"] | cols["failed"], objective.MIN_OBJECTIVE, np.maximum(cols["objective"], objective.MIN_OBJECTIVE)
    )
    return out


# ----------------------------------------------------------------------------------------------- studies


def controller_rows(cols: dict) -> list[Row]:
    n = cols["objective"].shape[0]
    controller = cols["controller"][0]
    rows = []
    for c, paper in registry.PAPER_CONTROLLER_TABLE.items():
        m = controller == c
        if m.sum() < 2:
            continue
        for (name, column), (mean, std) in zip(FIGURES.items(), paper, strict=True):
            ours = _final(cols, column, n, m)
            rows.append(
                Row(
                    "controller table",
                    f"{c} {name}",
                    f"{mean:.3f} ± {std:.3f} (n = 5)",
                    _cell(ours, UNITS[name], name in NONNEGATIVE),
                    stats.effect_to_summary(ours, mean, std, registry.PAPER_SEEDS),
                    std,
                    "the paper's std",
                    "figure",
                    _falls_note(cols, 0, n, m) if name == "J" else "",
                )
            )
    claims = []
    cot = {
        c: _final(cols, "cost_of_transport", n, controller == c)
        for c in cpg.CONTROLLERS
        if (controller == c).sum() >= 2
    }
    table = {c: p[1] for c, p in registry.PAPER_CONTROLLER_TABLE.items()}
    for a, b in (("tegotae", "open_loop"), ("vmc_tegotae", "vmc"), ("vmc_tegotae", "tegotae")):
        if a in cot and b in cot:
            paper_effect = table[a][0] - table[b][0]
            claims.append(
                Row(
                    "controller claims",
                    f"CoT {a} − {b} < 0",
                    f"{paper_effect:+.3f}",
                    f"{np.mean(cot[a]) - np.mean(cot[b]):+.3f}",
                    stats.effect_between(cot[a], cot[b]),
                    table[a][1],
                    f"the paper's std of {a}'s CoT",
                    "claim_below",
                )
            )
    return rows + claims


def context_rows(cols: dict, family: str, field: str, phases: list[tuple[int, int]], label) -> list[Row]:
    """Per phase, each run's std of the context ``field`` over its walking (not fallen) trials, against the paper's
    same-context tolerance: the claim that the estimator is consistent (a spread below it)."""
    rows = []
    bound = CONTEXT_TOLERANCE[field]
    for start, stop in phases:
        values = np.where(cols["fell"][start:stop] | cols["failed"][start:stop], np.nan, cols[field][start:stop])
        enough = np.sum(np.isfinite(values), axis=0) >= 2
        spread = np.nanstd(values[:, enough], axis=0, ddof=1)
        if spread.size < 2:
            continue
        rows.append(
            Row(
                family,
                f"{label(start)}: {field} spread within a run < t·r = {bound:g}",
                f"< {bound:g}",
                _cell(spread),
                stats.effect_to_value(spread, bound),
                0.0,
                "the tolerance itself",
                "claim_below",
                f"{int(enough.sum())} runs with 2 or more walking trials",
            )
        )
    return rows


def _phases(values: np.ndarray) -> list[tuple[int, int]]:
    starts = registry.phase_starts(values) + [values.shape[0]]
    return list(zip(starts[:-1], starts[1:], strict=True))


def _flat_optimum(cols: dict, stop: int, loads: list[float], trial_config) -> dict[float, tuple]:
    """Each seed's best gait of trials < ``stop`` walked again under each load: (v_x, CoT, J) arrays per load."""
    j = np.where(cols["fell"][:stop] | cols["failed"][:stop], -np.inf, cols["objective"][:stop])
    best = np.argmax(j, axis=0)
    b = np.arange(j.shape[1])
    params = np.stack([cols[name][best, b] for name in param_space.PARAM_NAMES], axis=-1)
    out = {}
    for load in loads:
        scenario = go1_model.make_scenarios(payload_kg=[load] * len(b), physics=list(cols["physics"][0]))
        v, cot, jj, _ = registry.evaluate(params, list(cols["controller"][0]), scenario, trial_config, "native", 0.5)
        out[load] = (v, cot, jj)
    return out


def load_rows(cols: dict, trial_config) -> list[Row]:
    rows = []
    phases = _phases(cols["payload_kg"][:, 0])
    loads = [float(cols["payload_kg"][s, 0]) for s, _ in phases]
    flat = _flat_optimum(cols, phases[1][0], [x for x in loads if x > 0], trial_config) if len(phases) > 1 else {}
    everyone = np.ones(cols["objective"].shape[1], bool)
    for load, (start, stop) in zip(loads, phases, strict=True):
        after, before = registry.PAPER_LOAD_TABLE.get(load, (None, None))
        if after is None:
            continue
        for k, (name, column) in enumerate(FIGURES.items()):
            ours = _final(cols, column, stop, everyone)
            std = LOAD_STD[name]
            rows.append(
                Row(
                    "load table",
                    f"{load:g} kg {name} adapted",
                    f"{after[k]:.3f}",
                    _cell(ours, UNITS[name], name in NONNEGATIVE),
                    stats.effect_to_summary(ours, after[k], std, registry.PAPER_SEEDS),
                    std,
                    "the paper's VMC+Tegotae std (flat)",
                    "figure",
                    _falls_note(cols, start, stop) if name == "J" else "",
                )
            )
            if before is not None and load in flat:
                ours = flat[load][k]
                rows.append(
                    Row(
                        "load table",
                        f"{load:g} kg {name} flat optimum",
                        f"{before[k]:.3f}",
                        _cell(ours, UNITS[name], name in NONNEGATIVE),
                        stats.effect_to_summary(ours, before[k], std, registry.PAPER_SEEDS),
                        std,
                        "the paper's VMC+Tegotae std (flat)",
                        "figure",
                    )
                )
    return rows + context_rows(
        cols, "load table", "c_load_n", phases, lambda start: f"{cols['payload_kg'][start, 0]:g} kg"
    )


def prospective_trials(j: np.ndarray, threshold: float) -> np.ndarray:
    """Per run (columns of ``j``), the trial count (1-based) to the first J ≥ ``threshold``; a run that never gets
    there counts as the run's length + 1 (censored)."""
    reached = j >= threshold
    return np.where(reached.any(axis=0), np.argmax(reached, axis=0) + 1, j.shape[0] + 1).astype(np.float64)


def friction_rows(cols: dict) -> list[Row]:
    n = cols["objective"].shape[0]
    friction = cols["friction"][0]
    rows = []
    for mu in np.unique(friction):
        m = friction == mu
        if m.sum() < 2:
            continue
        j = cols["objective"][:, m]
        threshold = PROSPECTIVE * float(np.mean(registry.last_mean(j, n)))
        counts = prospective_trials(j, threshold)
        random = int(np.sum(counts <= 2))  # trials 0 and 1 are random draws (Algorithm 1)
        rows.append(
            Row(
                "friction",
                f"μ {mu:g}: trials to J ≥ {PROSPECTIVE:g} × the group's final J < 10",
                "< 10",
                _cell(counts, nonnegative=True),
                stats.effect_to_value(counts, FRICTION_TRIALS_BOUND),
                0.0,
                "the bound itself",
                "claim_below",
                f"threshold J {threshold:.3f}; {random} of {counts.size} runs reach it in the 2 random trials; "
                f"{int(np.sum(counts > n))} never",
            )
        )
    return rows


def _slope_parts(cols: dict) -> tuple[int, int]:
    """The slope study's first inference-mode trial and its first ramp trial (the trial count where there is none)."""
    inference, ramp = cols["inference"][:, 0], cols["ramp"][:, 0]
    return (
        int(np.argmax(inference)) if inference.any() else inference.size,
        int(np.argmax(ramp)) if ramp.any() else ramp.size,
    )


def slope_rows(cols: dict) -> list[Row]:
    rows = []
    learn, ramp_at = _slope_parts(cols)
    everyone = np.ones(cols["objective"].shape[1], bool)
    target = float(cols["target_velocity_mps"][0, 0])
    learning = _phases(cols["slope_deg"][:learn, 0])
    rows += context_rows(cols, "slope", "c_slope_rad", learning, lambda start: f"{cols['slope_deg'][start, 0]:g}°")
    for start, stop in learning:
        slope = float(cols["slope_deg"][start, 0])
        if slope == 0.0:
            continue
        ours = _final(cols, "velocity_x_mps", stop, everyone)
        rows.append(
            Row(
                "slope",
                f"{slope:g}° adapted: v_x at v* = {target:g} m/s",
                f"{target:g} (walks)",
                _cell(ours, " m/s"),
                stats.effect_to_value(ours, target),
                VELOCITY_MARGIN_MPS,
                "the tracking tolerance",
                "figure",
                _falls_note(cols, start, stop),
            )
        )
    for start, stop in _phases(cols["slope_deg"][learn:ramp_at, 0]):
        start, stop = start + learn, stop + learn
        slope = float(cols["slope_deg"][start, 0])
        if slope > 15.0:
            continue
        ours = cols["velocity_x_mps"][start:stop].mean(axis=0)  # inference: every trial of the phase
        rows.append(
            Row(
                "slope",
                f"inference {slope:g}°: v_x at v* = {target:g} m/s",
                f"{target:g} (walks)",
                _cell(ours, " m/s"),
                stats.effect_to_value(ours, target),
                VELOCITY_MARGIN_MPS,
                "the tracking tolerance",
                "figure",
                _falls_note(cols, start, stop),
            )
        )
    if ramp_at < cols["ramp"].shape[0]:
        slope = cols["slope_deg"][ramp_at:]
        fell = cols["fell"][ramp_at:] | cols["failed"][ramp_at:]
        steepest = np.where(~fell, slope, -np.inf).max(axis=0)
        walked = np.isfinite(steepest)
        rows.append(
            Row(
                "slope",
                "ramp: steepest slope walked without a fall",
                "15°",
                _cell(steepest[walked], "°"),
                stats.effect_to_value(steepest[walked], 15.0),
                RAMP_MARGIN_DEG,
                "half the 2.5° step of the paper's slopes",
                "figure",
                f"{int(walked.sum())} of {walked.size} seeds walked a ramp trial",
            )
        )
    return rows


def _falls_note(cols: dict, start: int, stop: int, mask: np.ndarray | None = None) -> str:
    """The phase's falls, the seeds that hold them and the fall rate with a bootstrap over seeds."""
    fell = (cols["fell"][start:stop] | cols["failed"][start:stop]).astype(np.float64)
    if mask is not None:
        fell = fell[:, mask]
    rate = stats.cluster_bootstrap(list(fell.T), lambda cs: float(np.mean(np.concatenate(cs))))
    seeds = int(np.sum(fell.sum(axis=0) > 0))
    return (
        f"falls {int(fell.sum())}/{fell.size}, in {seeds} of {fell.shape[1]} seeds; rate "
        f"{rate.mean:.3f} [{rate.low:.3f}, {rate.high:.3f}] (seed bootstrap)"
    )


def track_counts(cols: dict, start: int, stop: int, mask: np.ndarray) -> np.ndarray:
    """Trials from ``start`` to track v* (``registry.trials_to_track``: a run that never tracks counts as the phase's
    length + 1)."""
    return np.array(
        [
            registry.trials_to_track(
                cols["velocity_x_mps"][:, b], cols["target_velocity_mps"][:, b], cols["fell"][:, b], start, stop
            )
            for b in np.flatnonzero(mask)
        ]
    )


def multi_velocity_rows(cols: dict) -> list[Row]:
    rows = []
    reuse = cols["data_reuse"][0]
    for start, stop in _phases(cols["target_velocity_mps"][:, 0])[1:]:
        target = float(cols["target_velocity_mps"][start, 0])
        a, b = track_counts(cols, start, stop, reuse), track_counts(cols, start, stop, ~reuse)
        if min(a.size, b.size) < 2:
            continue
        never = (int(np.sum(a > stop - start)), int(np.sum(b > stop - start)))
        rows.append(
            Row(
                "multi-velocity",
                f"{target:g} m/s: trials to track, reuse − restart < 0",
                "fewer with reuse",
                f"{np.mean(a):.2f} vs {np.mean(b):.2f}",
                stats.effect_between(a, b),
                0.0,
                "no effect",
                "claim_below",
                f"never tracked (counted as {stop - start + 1}): {never[0]} with reuse, {never[1]} without",
            )
        )
    first = _phases(cols["target_velocity_mps"][:, 0])[1][0]  # the paper's trials 40–60 begin at the first change
    window = min(20, cols["objective"].shape[0] - first)
    if window >= 2 * LAST_TRIALS and reuse.sum() >= 2:
        cot = cols["cost_of_transport"][first : first + window][:, reuse]
        walked = ~(cols["fell"] | cols["failed"])[first : first + window][:, reuse]
        early = np.nanmean(np.where(walked[:LAST_TRIALS], cot[:LAST_TRIALS], np.nan), axis=0)
        late = np.nanmean(np.where(walked[-LAST_TRIALS:], cot[-LAST_TRIALS:], np.nan), axis=0)
        change = late - early
        rows.append(
            Row(
                "multi-velocity",
                f"CoT falls over trials {first}–{first + window - 1} (reuse): last 5 − first 5 < 0",
                "falls (figure)",
                _cell(change),
                stats.effect_to_value(change, 0.0),
                0.0,
                "no effect",
                "claim_below",
                "walking trials only",
            )
        )
    return rows


def hardware_rows(cols: dict) -> list[Row]:
    rows = []
    schedule = cols["schedule"][0]
    for label in dict.fromkeys(schedule.tolist()):
        m = schedule == label
        b0 = int(np.flatnonzero(m)[0])
        fields = np.stack([cols[c][:, b0] for c in ("friction", "slope_deg", "payload_kg", "target_velocity_mps")])
        n = fields.shape[1]
        starts = [0] + [t for t in range(1, n) if np.any(fields[:, t] != fields[:, t - 1])] + [n]
        for s, e in zip(starts[:-1], starts[1:], strict=True):
            target = float(cols["target_velocity_mps"][s, b0])
            paper = registry.PAPER_HARDWARE_COT.get(label)
            if isinstance(paper, dict):
                paper = paper.get(target)
            if isinstance(paper, float):
                ours = _final(cols, "cost_of_transport", e, m)
                rows.append(
                    Row(
                        "hardware (go1)",
                        f"{label}, trials {s}–{e - 1}: CoT",
                        f"≈ {paper:g}",
                        _cell(ours, nonnegative=True),
                        stats.effect_to_value(ours, paper),
                        HARDWARE_COT_MARGIN,
                        "2 × the paper's VMC+Tegotae CoT std",
                        "figure",
                    )
                )
            if label == "flat → 10°" and s > 0:
                counts = track_counts(cols, s, e, m)
                paper_trials = registry.PAPER_HARDWARE_SLOPE_TRIALS
                rows.append(
                    Row(
                        "hardware (go1)",
                        f"{label}: tracked again within {paper_trials} trials",
                        f"within ≈ {paper_trials}",
                        _cell(counts, nonnegative=True),
                        stats.effect_to_value(counts, paper_trials),
                        0.0,
                        "the bound itself",
                        "claim_below",
                        f"never tracked (counted as {e - s + 1}): {int(np.sum(counts > e - s))}",
                    )
                )
                rows += parameter_shift_rows(cols, m, s, e)
    return rows


def parameter_shift_rows(cols: dict, mask: np.ndarray, change: int, stop: int) -> list[Row]:
    """Per parameter the paper names, each run's change from its best flat gait (trials < ``change``) to its best
    gait on the slope (trials ``change`` … ``stop``), in the paper's direction (claims in the units of the
    parameter)."""

    def best(lo, hi):
        j = np.where(cols["fell"][lo:hi] | cols["failed"][lo:hi], -np.inf, cols["objective"][lo:hi])[:, mask]
        return lo + np.argmax(j, axis=0)

    flat, slope = best(0, change), best(change, stop)
    runs = np.flatnonzero(mask)
    rows = []
    for name, sign in HARDWARE_SLOPE_SHIFTS.items():
        shift = cols[name][slope, runs] - cols[name][flat, runs]
        rows.append(
            Row(
                "hardware (go1)",
                f"10°: {name} {'decreases' if sign < 0 else 'increases'}",
                "decreases" if sign < 0 else "increases",
                _cell(shift),
                stats.effect_to_value(shift, 0.0),
                0.0,
                "no effect",
                "claim_below" if sign < 0 else "claim_above",
                "best slope gait − best flat gait, per run",
            )
        )
    return rows


STUDIES: dict[str, Callable[..., list[Row]]] = {
    "controller_ablation": lambda cols, trial: controller_rows(cols),
    "load_adaptation": load_rows,
    "friction": lambda cols, trial: friction_rows(cols),
    "multi_velocity": lambda cols, trial: multi_velocity_rows(cols),
    "slope_adaptation": lambda cols, trial: slope_rows(cols),
    "paper_hardware": lambda cols, trial: hardware_rows(cols),
}


# ----------------------------------------------------------------------------------------------- verdicts


def verdicts(rows: list[Row]) -> list[tuple[Row, float, float, str]]:
    """Each row with its two tests after Holm's correction over its family, and its verdict."""
    out = []
    for family in dict.fromkeys(r.family for r in rows):
        members = [r for r in rows if r.family == family]
        tests = np.array([r.tests() for r in members])
        p_for, p_against = stats.holm(tests[:, 0]), stats.holm(tests[:, 1])
        for r, pf, pa in zip(members, p_for, p_against, strict=True):
            if r.kind == "figure":
                verdict = "agrees" if pf < ALPHA else "differs" if pa < ALPHA else "inconclusive"
            else:
                verdict = "reproduced" if pf < ALPHA else "not reproduced" if pa < ALPHA else "inconclusive"
            out.append((r, float(pf), float(pa), verdict))
    return out


def table(judged: list[tuple[Row, float, float, str]]) -> str:
    lines = [
        "| family | figure | paper | ours (mean [95 % CI], seeds) | ours − paper [95 % CI] | margin | "
        "p for (Holm) | p against (Holm) | verdict | note |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r, pf, pa, verdict in judged:
        low, high = r.effect.interval()
        margin = f"±{r.margin:g} ({r.margin_source})" if r.kind == "figure" else f"{r.margin:g} ({r.margin_source})"
        lines.append(
            f"| {r.family} | {r.figure} | {r.paper} | {r.ours} | {r.effect.difference:+.3f} "
            f"[{low:+.3f}, {high:+.3f}] | {margin} | {pf:.2g} | {pa:.2g} | **{verdict}** | {r.note} |"
        )
    return "\n".join(lines)


def _commit(folder: pathlib.Path) -> str:
    meta = json.loads((folder / "metadata.json").read_text())
    return str(meta.get("git_commit"))


def _columns(folder: pathlib.Path) -> dict:
    return study_io.read_trials(folder / "trials.parquet")


def study_rows(name: str, folder: pathlib.Path) -> list[Row]:
    cols = _objective_at_paper_floor(_columns(folder))
    return STUDIES[name](cols, protocol.TrialConfig())


def one_change(base: pathlib.Path, changed: pathlib.Path, name: str) -> str:
    """The figures of a one-change run against its base run, paired over seeds (both runs' figures as
    :func:`study_rows` builds them), and the verdict each gets on its own."""
    a, b = study_rows(name, base), study_rows(name, changed)
    base_cols, changed_cols = _columns(base), _columns(changed)
    if not np.array_equal(base_cols["seed"], changed_cols["seed"]):
        raise SystemExit(f"{changed}: not the seeds of {base}")
    judged_a, judged_b = verdicts(a), verdicts(b)
    lines = [
        f"{changed.name} (commit {_commit(changed)}) against {base.name} (commit {_commit(base)}):",
        "",
        "| figure | base | one change | change | base verdict | one-change verdict |",
        "|---|---|---|---|---|---|",
    ]
    for (ra, _, _, va), (rb, _, _, vb) in zip(judged_a, judged_b, strict=True):
        change = rb.effect.difference - ra.effect.difference
        lines.append(f"| {ra.figure} | {ra.ours} | {rb.ours} | {change:+.3f} | {va} | {vb}{' ←' if va != vb else ''} |")
    return "\n".join(lines)


def paired_changes(base: pathlib.Path, changed: pathlib.Path, name: str) -> str:
    """Per headline figure (the per-seed finals of the figure rows), the paired difference one change − base."""
    ca, cb = _objective_at_paper_floor(_columns(base)), _objective_at_paper_floor(_columns(changed))
    n = ca["objective"].shape[0]
    groups = {
        "controller_ablation": "controller",
        "load_adaptation": "payload_kg",
        "slope_adaptation": "slope_deg",
    }.get(name)
    if groups is None:
        return ""
    out = [
        "",
        "| group | figure | one change − base, paired over seeds [95 % CI] | paired t p | Holm |",
        "|---|---|---|---|---|",
    ]
    entries = []
    if groups == "controller":
        for c in cpg.CONTROLLERS:
            m = ca["controller"][0] == c
            if m.sum() >= 2:
                for fig, column in FIGURES.items():
                    entries.append((c, fig, _final(ca, column, n, m), _final(cb, column, n, m)))
    elif groups == "slope_deg":
        learn, ramp_at = _slope_parts(ca)
        everyone = np.ones(ca["objective"].shape[1], bool)
        for start, stop in _phases(ca["slope_deg"][:learn, 0]):
            for fig, column in FIGURES.items():
                entries.append(
                    (
                        f"{ca['slope_deg'][start, 0]:g}°",
                        fig,
                        _final(ca, column, stop, everyone),
                        _final(cb, column, stop, everyone),
                    )
                )
        for start, stop in _phases(ca["slope_deg"][learn:ramp_at, 0]):
            start, stop = start + learn, stop + learn
            entries.append(
                (
                    f"inference {ca['slope_deg'][start, 0]:g}°",
                    "v_x",
                    *(c["velocity_x_mps"][start:stop].mean(axis=0) for c in (ca, cb)),
                )
            )
        entries.append(
            (
                "all",
                "falls per run",
                (ca["fell"] | ca["failed"]).sum(axis=0).astype(np.float64),
                (cb["fell"] | cb["failed"]).sum(axis=0).astype(np.float64),
            )
        )
    else:
        everyone = np.ones(ca["objective"].shape[1], bool)
        for start, stop in _phases(ca["payload_kg"][:, 0]):
            for fig, column in FIGURES.items():
                entries.append(
                    (
                        f"{ca['payload_kg'][start, 0]:g} kg",
                        fig,
                        _final(ca, column, stop, everyone),
                        _final(cb, column, stop, everyone),
                    )
                )
        fell_a = (ca["fell"] | ca["failed"]).sum(axis=0).astype(np.float64)
        fell_b = (cb["fell"] | cb["failed"]).sum(axis=0).astype(np.float64)
        entries.append(("all", "falls per run", fell_a, fell_b))
    comparisons = [stats.paired(after, before) for _, _, before, after in entries]
    adjusted = stats.holm([c.t_p for c in comparisons])
    for (group, fig, _, _), c, h in zip(entries, comparisons, adjusted, strict=True):
        out.append(f"| {group} | {fig} | {c.difference:+.3f} [{c.low:+.3f}, {c.high:+.3f}] | {c.t_p:.2g} | {h:.2g} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("results", type=pathlib.Path, help="the folder holding one folder per study")
    parser.add_argument(
        "--one-change", action="store_true", help="also set each <study>__<switch> folder against its <study>"
    )
    args = parser.parse_args(argv)
    if not args.results.is_dir():
        print(f"verdicts.py: {args.results}: not a folder", file=sys.stderr)
        return 2
    found = [name for name in STUDIES if (args.results / name / "trials.parquet").is_file()]
    if not found:
        print(
            f"verdicts.py: {args.results}: no study folder with a trials.parquet; looked for {', '.join(STUDIES)}",
            file=sys.stderr,
        )
        return 2
    rows = [r for name in found for r in study_rows(name, args.results / name)]
    print("Runs: " + ", ".join(f"{name} at {_commit(args.results / name)}" for name in found) + "\n")
    print(table(verdicts(rows)))
    if args.one_change:
        for name in found:
            for changed in sorted(args.results.glob(f"{name}__*")):
                if (changed / "trials.parquet").is_file():
                    print("\n" + one_change(args.results / name, changed, name))
                    print(paired_changes(args.results / name, changed, name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
