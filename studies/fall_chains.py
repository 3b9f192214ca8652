"""Do falls come in chains? Per study folder: the probability that an optimized trial falls after a trial that fell
and after one that walked (the same condition, the trial before also optimized), and the contexts that fallen and
walking trials measured (docs/decisions.md §11).

    python studies/fall_chains.py results/slope_adaptation [more folders]
    python studies/fall_chains.py results/slope_adaptation --rewalk slope_adaptation

Reads each folder's ``trials.parquet``. Per condition (the rates differ between conditions): the two probabilities
pooled over the runs, and their difference with a 95 % interval from a cluster bootstrap over the runs (each run's
trials resampled together: the trials of one seed depend on each other, so a test that counts them as independent,
such as Fisher's on the pooled counts, overstates the evidence), with the number of runs that hold the falls.

``--rewalk STUDY`` (the registry name the folder ran) asks why a trial after a fall falls. After a fall the robot
is reset to standing (docs/decisions.md §8), so that trial starts from rest on the condition. For every such trial
it walks again, on the native backend, with the study's scenario of that trial:

* as in the study: from standing, the fallen trial's parameters as the transition's start (this must give the
  study's outcome, a check);
* the instance's last gait that walked that condition before the fall, from standing: one trial;
* the same gait arriving walking: one trial on the condition's flat-ground counterpart (slope 0°, no payload) from
  standing, then one trial on the condition (the scenario switched under the walking robot, as when a study's
  condition changes), counted where the flat trial walked.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from cpgjax import ablation
from cpgjax.sim import backends
from cpgjax.studies import driver as study_driver
from cpgjax.studies import stats
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

CONDITIONS = ("friction", "slope_deg", "payload_kg", "target_velocity_mps")


def chains(columns: dict[str, np.ndarray]) -> dict:
    """Per condition of one study's trials (``columns``, as ``study_io.read_trials`` gives them; the values of the
    conditions that vary, as a label): the falls after a fall and after a walk (falls, trials) and the median
    measured contexts of the optimized trials that fell and that walked; over every instance. Falls are counted per
    condition because their rate differs between conditions (pooled, the conditions without falls would make a fall
    look likelier after a fall)."""
    fell = (columns["fell"] > 0) | (columns["failed"] > 0)
    optimized = columns["inference"] == 0
    condition = np.stack([columns[c] for c in CONDITIONS], axis=-1)
    varying = [i for i, c in enumerate(CONDITIONS) if np.unique(columns[c]).size > 1]
    pairs = optimized[1:] & optimized[:-1] & np.all(condition[1:] == condition[:-1], axis=-1)
    out = {}
    for values in np.unique(condition[optimized][:, varying], axis=0):
        here = np.all(condition[..., varying] == values, axis=-1)
        label = ", ".join(f"{CONDITIONS[i]} {v:g}" for i, v in zip(varying, values, strict=True)) or "all"
        after_fall, after_walk = (fell[1:][pairs & here[1:] & fell[:-1]], fell[1:][pairs & here[1:] & ~fell[:-1]])
        fallen, walked = here & optimized & fell, here & optimized & ~fell
        after_fall_at, after_walk_at = pairs & here[1:] & fell[:-1], pairs & here[1:] & ~fell[:-1]
        per_run = [
            (
                int((fell[1:, b] & after_fall_at[:, b]).sum()),
                int(after_fall_at[:, b].sum()),
                int((fell[1:, b] & after_walk_at[:, b]).sum()),
                int(after_walk_at[:, b].sum()),
            )
            for b in range(fell.shape[1])
        ]
        out[label] = dict(
            after_fall=(int(after_fall.sum()), after_fall.size),
            after_walk=(int(after_walk.sum()), after_walk.size),
            per_run=per_run,
            runs_with_falls=int(np.sum(np.any(fallen, axis=0))),
            falls=int(fallen.sum()),
            trials=int((here & optimized).sum()),
            contexts={
                name: tuple(float(np.median(columns[name][m])) if m.any() else np.nan for m in (fallen, walked))
                for name in ("c_load_n", "c_slope_rad")
            },
        )
    return out


def rewalk(folder: pathlib.Path, study: str) -> str:
    """The three walks of ``--rewalk`` (module docstring), as one line."""
    columns = study_io.read_trials(folder / "trials.parquet")
    fell = (columns["fell"] > 0) | (columns["failed"] > 0)
    optimized = columns["inference"] == 0
    condition = np.stack([columns[c] for c in CONDITIONS], axis=-1)
    params = np.stack([columns[name] for name in param_space.PARAM_NAMES], axis=-1)
    cases = []  # (trial, instance, last params that walked this condition before the fall)
    for t, b in zip(
        *np.nonzero(fell[:-1] & optimized[:-1] & optimized[1:] & np.all(condition[1:] == condition[:-1], axis=-1)),
        strict=True,
    ):
        walked = [k for k in range(t) if not fell[k, b] and np.array_equal(condition[k, b], condition[t, b])]
        if walked:
            cases.append((t + 1, b, params[walked[-1], b]))
    if not cases:
        return f"{folder}: no trial after a fall with an earlier walk on its condition"
    spec = study_driver.read(study).spec
    engine = ablation.Engine(spec, backend="native")
    scenario = engine.batch.scenario_at(np.array([t for t, _, _ in cases]), np.array([b for _, b, _ in cases]))
    level = scenario._replace(
        slope_deg=np.zeros_like(scenario.slope_deg), payload_kg=np.zeros_like(scenario.payload_kg)
    )
    gates = protocol.batch_gates([str(columns["controller"][t, b]) for t, b, _ in cases])
    x = np.stack([params[t, b] for t, b, _ in cases])
    x_before = np.stack([params[t - 1, b] for t, b, _ in cases])
    x_walked = np.stack([w for _, _, w in cases])

    def one_trial(sim, state, p):
        state, record = sim.trial(state, p, gates)
        return state, np.asarray(study_placement.fetch(record).fell) > 0

    sim = backends.make_backend(scenario, "native", trial_config=spec.trial)
    _, as_walked = one_trial(sim, sim.reset(x_before), x)
    _, from_standing = one_trial(sim, sim.reset(x_walked), x_walked)
    flat = backends.make_backend(level, "native", trial_config=spec.trial)
    state, flat_fell = one_trial(flat, flat.reset(x_walked), x_walked)
    _, arriving = one_trial(flat.with_scenario(scenario), state, x_walked)
    expected = np.array([fell[t, b] for t, b, _ in cases])
    n, m = len(cases), int((~flat_fell).sum())
    return (
        f"{folder}: {n} trials after a fall (with an earlier walk on the condition). Walked again as in the "
        f"study: {int(as_walked.sum())} fell (the study: {int(expected.sum())}; "
        f"{'the same trials' if np.array_equal(as_walked, expected) else 'NOT the same trials'}). The last gait "
        f"that walked the condition, from standing: {int(from_standing.sum())} of {n} fell "
        f"({stats.proportion_ci(int(from_standing.sum()), n)}); arriving walking from level ground: "
        f"{int((arriving & ~flat_fell).sum())} of {m} fell "
        f"({stats.proportion_ci(int((arriving & ~flat_fell).sum()), m)})."
    )


def chain_difference(per_run: list) -> float:
    """P(fall | the trial before fell) − P(fall | it walked), pooled over the runs given (NaN where either has no
    case)."""
    k_f, n_f, k_w, n_w = np.sum(np.asarray(per_run, np.float64).reshape(-1, 4), axis=0)
    return k_f / n_f - k_w / n_w if n_f > 0 and n_w > 0 else np.nan


def report(folder: pathlib.Path) -> str:
    lines = []
    for label, c in chains(study_io.read_trials(folder / "trials.parquet")).items():
        (k_f, n_f), (k_w, n_w) = c["after_fall"], c["after_walk"]
        difference = stats.cluster_bootstrap(c["per_run"], chain_difference)
        contexts = "; ".join(
            f"{name} median {fallen:.3g} fallen, {walked:.3g} walking"
            for name, (fallen, walked) in c["contexts"].items()
        )
        lines.append(
            f"{folder}, {label}: {c['falls']} falls in {c['trials']} optimized trials, in "
            f"{c['runs_with_falls']} of {len(c['per_run'])} runs. A fall after a fall: {k_f}/{n_f}; after a "
            f"walk: {k_w}/{n_w}; difference {difference.mean:+.3f} [{difference.low:+.3f}, "
            f"{difference.high:+.3f}] (95 %, bootstrap over the runs). Measured contexts: {contexts}."
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=pathlib.Path, nargs="+", help="study folders with a trials.parquet")
    parser.add_argument(
        "--rewalk",
        metavar="STUDY",
        help="walk the trials after falls again (the registry name of the study the folders ran)",
    )
    args = parser.parse_args()
    for folder in args.folders:
        print(report(folder))
        if args.rewalk:
            print(rewalk(folder, args.rewalk))


if __name__ == "__main__":
    main()
