"""Why the slope-adaptation study fails under the ``paper`` profile (docs/REPRODUCTION.md, slope adaptation): which
parameters climb, measured on a finished study's ``trials.parquet``.

For every seed of a ``cpgjax study slope_adaptation`` run, three parameter sets are walked (C MuJoCo, VMC+Tegotae, one
settling trial then one measured trial at the study's target, under the study's profile) on 0°, 10° and 12.5°:

* the mid-range parameters (the same for every seed);
* the seed's best flat-ground parameters (trials before the first slope change): where the slope phases start from;
* the seed's best parameters seen during the 10° phase.

If the flat optimum falls on 10° where the mid-range set climbs, the optimizer starts the slope phase from a gait that
the slope breaks; if the best 10° set climbs 10° but not 12.5°, good gaits exist but do not carry over.

    python studies/slope_evidence.py RESULTS/slope_adaptation [--backend native]
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np
import pyarrow.parquet as pq

from cpgjax.go1 import model as go1_model
from cpgjax.studies import registry
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

SLOPES_DEG = (0.0, 10.0, 12.5)


def parameter_sets(table: dict) -> dict[str, np.ndarray]:
    """(seeds, 8) parameters of each kind, seed-major, from the study's trial table."""
    seeds = np.unique(table["seed"])
    slope = table["slope_deg"]
    first_change = int(table["trial"][slope > 0].min())
    ten = (slope == 10.0) & ~table["inference"].astype(bool)
    sets = {"mid-range": np.tile(param_space.midpoint(), (len(seeds), 1)), "best flat": [], "best 10°": []}
    for s in seeds:
        mine = table["seed"] == s
        for name, mask in (("best flat", mine & (table["trial"] < first_change)), ("best 10°", mine & ten)):
            i = np.flatnonzero(mask)[np.argmax(table["objective"][mask])]
            sets[name].append([table[p][i] for p in param_space.PARAM_NAMES])
    return {k: np.asarray(v, np.float64) for k, v in sets.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=pathlib.Path, help="a slope_adaptation output folder (with trials.parquet)")
    parser.add_argument("--backend", default="native", choices=("native", "mjx"))
    args = parser.parse_args(argv)
    table = {k: np.asarray(v) for k, v in pq.read_table(args.study / "trials.parquet").to_pydict().items()}
    physics, target = str(table["physics"][0]), float(table["target_velocity_mps"][0])
    sets = parameter_sets(table)
    names = list(sets)
    runs = np.concatenate([sets[n] for n in names])  # (kinds × seeds, 8)
    grid = [(s, r) for s in SLOPES_DEG for r in range(len(runs))]
    scenario = go1_model.make_scenarios(slope_deg=[s for s, _ in grid], physics=physics)
    v, cot, j, fell = registry.evaluate(
        runs[[r for _, r in grid]], ["vmc_tegotae"] * len(grid), scenario, protocol.TrialConfig(), args.backend, target
    )
    seeds = len(runs) // len(names)
    print(f"{args.study}: physics {physics}, v* {target} m/s, {seeds} seeds; mean over seeds (falls / seeds)\n")
    print("| parameters | " + " | ".join(f"{s:g}°: v_x [m/s] / J / falls" for s in SLOPES_DEG) + " |")
    print("|---|" + "---|" * len(SLOPES_DEG))
    for k, name in enumerate(names):
        cells = []
        for a in range(len(SLOPES_DEG)):
            rows = slice(a * len(runs) + k * seeds, a * len(runs) + (k + 1) * seeds)
            cells.append(f"{v[rows].mean():.3f} / {j[rows].mean():.2f} / {int(fell[rows].sum())}/{seeds}")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
