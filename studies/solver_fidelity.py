"""How much do the solver settings of our Go1 model change a trial? (why go1.xml uses 2 Newton iterations)

The model steps with Newton, 2 iterations and 6 line-search iterations (``cpgjax/assets/go1.xml``) — few, for speed.
This study runs the same trials (the four controllers × flat / slippery / uphill / loaded, three back-to-back full
trials with the mid-range and two random parameter sets) with C MuJoCo (the native backend) under several solver
settings and compares v_x and CoT with a converged solver (100 iterations, 50 line-search iterations).

    python studies/solver_fidelity.py [--trials 3]

Prints one row per instance and trial and a summary (median and max |difference| to the converged solver, falls).
The settings are applied to the backend's C MuJoCo models after construction; only the standing reset's initial
sensor reading (one tick) comes from the model file's setting.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native as native_go1
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space

SOLVERS = {"model (2, 6)": (2, 6), "1 iteration, 6 ls": (1, 6), "1 iteration, 4 ls": (1, 4),
           "converged (100, 50)": (100, 50)}
REFERENCE = "converged (100, 50)"
SCENARIOS = {"flat μ 0.6": (0.6, 0.0, 0.0), "slippery μ 0.3": (0.3, 0.0, 0.0), "uphill 10°": (0.6, 10.0, 0.0),
             "15 kg": (0.6, 0.0, 15.0)}


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
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    trial_params = np.stack([param_space.midpoint()] + [param_space.from_unit(rng.uniform(0.2, 0.8, 8))
                                                        for _ in range(args.trials - 1)])
    rows = [(c, name) for c in cpg.CONTROLLERS for name in SCENARIOS]
    friction, slope, payload = (np.array([SCENARIOS[name][k] for _, name in rows]) for k in range(3))
    scenario = go1_model.make_scenarios(friction=friction, slope_deg=slope, payload_kg=payload)
    results = {label: run(*setting, trial_params, [c for c, _ in rows], scenario)
               for label, setting in SOLVERS.items()}

    def figures(label, trial, i):
        r = jax.tree.map(lambda x: x[i], results[label][trial])
        return (float(objective.mean_velocity(r)[0]), float(objective.cost_of_transport(r)), bool(r.fell > 0))

    print("| controller | scenario | trial | " + " | ".join(f"{label}: v_x [m/s], CoT" for label in SOLVERS) + " |")
    print("|---|---|---|" + "---|" * len(SOLVERS))
    diffs = {label: [] for label in SOLVERS}
    falls = {label: 0 for label in SOLVERS}
    for i, (controller, name) in enumerate(rows):
        for t in range(args.trials):
            cells = []
            ref = figures(REFERENCE, t, i)
            for label in SOLVERS:
                vx, cot, fell = figures(label, t, i)
                cells.append(f"{vx:.3f}, {cot:.2f}" + (" (fell)" if fell else ""))
                diffs[label].append((abs(vx - ref[0]), abs(cot - ref[1])))
                falls[label] += fell
            print(f"| {controller} | {name} | {t} | " + " | ".join(cells) + " |")
    print("\n| solver (iterations, line search) | median abs. v_x diff [m/s] | max abs. v_x diff [m/s] "
          "| median abs. CoT diff | trials that fell |")
    print("|---|---|---|---|---|")
    for label in SOLVERS:
        d = np.array(diffs[label])
        print(f"| {label} | {np.median(d[:, 0]):.4f} | {d[:, 0].max():.3f} | {np.median(d[:, 1]):.3f} "
              f"| {falls[label]} of {len(d)} |")


if __name__ == "__main__":
    main()
