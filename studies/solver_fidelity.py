"""How much do the solver settings of our Go1 model change a trial, under each physics profile? (why go1.xml uses
the Newton iterations it does)

This study runs the same trials (the four controllers × flat / slippery / uphill / loaded, three back-to-back full
trials with the mid-range and two random parameter sets) with C MuJoCo (the native backend) under several solver
settings and compares v_x, CoT and c_load with a converged solver (100 iterations, 50 line-search iterations), once
per physics profile (docs/physics.md). Stiff contact is where few iterations fall short: the solver's contact forces
are then not the ones that moved the robot, and the foot-force signal reads high.

    python studies/solver_fidelity.py [--trials 3] [--physics soft,paper,go1] [--solvers 2:6,4:8,6:10]

Prints one row per instance and trial and a summary per profile (median and max |difference| to the converged solver,
falls). The settings are applied to the backend's C MuJoCo models after construction; only the standing reset's
initial sensor reading (one tick) comes from the model file's setting.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.sim import native as native_go1
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space

SOLVERS = {
    "2 iterations, 6 ls": (2, 6),
    "3 iterations, 6 ls": (3, 6),
    "4 iterations, 8 ls": (4, 8),
    "1 iteration, 6 ls": (1, 6),
    "converged (100, 50)": (100, 50),
}
REFERENCE = "converged (100, 50)"
SCENARIOS = {
    "flat μ 0.6": (0.6, 0.0, 0.0),
    "slippery μ 0.3": (0.3, 0.0, 0.0),
    "uphill 10°": (0.6, 10.0, 0.0),
    "15 kg": (0.6, 0.0, 15.0),
}


def run(iterations: int, ls_iterations: int, trial_params: np.ndarray, controllers, scenario) -> list:
    """Trial records (one per row of ``trial_params``, back to back) with the given solver iterations."""
    sim = native_go1.NativeBackend(scenario)
    for model in sim.physics.models:
        model.opt.iterations = iterations
        model.opt.ls_iterations = ls_iterations
    batch = scenario.batch_size
    gates = protocol.batch_gates(controllers)
    state = sim.reset(np.tile(trial_params[0], (batch, 1)))
    records = []
    for p in trial_params:
        state, record = sim.trial(state, np.tile(p, (batch, 1)), gates)
        records.append(jax.tree.map(np.asarray, record))
    sim.physics.close()
    return records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=3, help="back-to-back trials (first: mid-range parameters)")
    parser.add_argument("--physics", default=",".join(physics_profiles.PROFILES), help="comma list of profiles")
    parser.add_argument(
        "--solvers",
        help="comma list of iterations:line-search settings compared with the converged "
        f"solver (default: {', '.join(SOLVERS)})",
    )
    args = parser.parse_args()
    solvers = dict(SOLVERS)
    if args.solvers:
        settings = [tuple(int(v) for v in s.split(":")) for s in args.solvers.split(",")]
        solvers = {f"{i} iterations, {ls} ls": (i, ls) for i, ls in settings} | {REFERENCE: SOLVERS[REFERENCE]}
    for name in args.physics.split(","):
        print(f"\n## physics profile {name}\n")
        compare(name, args.trials, solvers)


def compare(physics: str, num_trials: int, solvers: dict) -> None:
    """The table and the summary of one physics profile."""
    rng = np.random.default_rng(0)
    trial_params = np.stack(
        [param_space.midpoint()] + [param_space.from_unit(rng.uniform(0.2, 0.8, 8)) for _ in range(num_trials - 1)]
    )
    rows = [(c, name) for c in cpg.CONTROLLERS for name in SCENARIOS]
    friction, slope, payload = (np.array([SCENARIOS[name][k] for _, name in rows]) for k in range(3))
    scenario = go1_model.make_scenarios(friction=friction, slope_deg=slope, payload_kg=payload, physics=physics)
    results = {label: run(*setting, trial_params, [c for c, _ in rows], scenario) for label, setting in solvers.items()}

    def figures(label, trial, i):
        r = jax.tree.map(lambda x: x[i], results[label][trial])
        return (
            float(objective.mean_velocity(r)[0]),
            float(objective.cost_of_transport(r)),
            float(r.c_load_n),
            bool(r.fell > 0),
        )

    print("| controller | scenario | trial | " + " | ".join(f"{label}: v_x [m/s], CoT" for label in solvers) + " |")
    print("|---|---|---|" + "---|" * len(solvers))
    diffs = {label: [] for label in solvers}
    falls = {label: 0 for label in solvers}
    for i, (controller, name) in enumerate(rows):
        for t in range(num_trials):
            cells = []
            ref = figures(REFERENCE, t, i)
            for label in solvers:
                vx, cot, load, fell = figures(label, t, i)
                cells.append(f"{vx:.3f}, {cot:.2f}" + (" (fell)" if fell else ""))
                diffs[label].append((abs(vx - ref[0]), abs(cot - ref[1]), abs(load - ref[2])))
                falls[label] += fell
            print(f"| {controller} | {name} | {t} | " + " | ".join(cells) + " |")
    print(
        f"\n| {physics}: solver (iterations, line search) | median abs. v_x diff [m/s] | max abs. v_x diff [m/s] "
        "| median abs. CoT diff | median abs. c_load diff [N] | trials that fell |"
    )
    print("|---|---|---|---|---|---|")
    for label in solvers:
        d = np.array(diffs[label])
        print(
            f"| {label} | {np.median(d[:, 0]):.4f} | {d[:, 0].max():.3f} | {np.median(d[:, 1]):.3f} "
            f"| {np.median(d[:, 2]):.2f} | {falls[label]} of {len(d)} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
