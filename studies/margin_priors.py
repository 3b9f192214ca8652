"""What the safety margins of finished studies say about the margin GP's hyperparameters, measured.

    python studies/margin_priors.py RESULTS/controller_ablation [RESULTS/friction ...]

Each run of each folder's ``trials.parquet`` (one instance: a group and a seed) is one dataset, as the safe optimizer
would hold it: the optimized trials' parameters (unit cube; σ_N inactive without Tegotae) and contexts (the
optimizer's fixed ranges) as inputs, their ``safety_margin`` as targets. Every dataset is fitted by ``gp.fit`` (the
optimizer's own fit, more steps) under nearly flat priors, Gamma(1, 1e-3) on each hyperparameter: the
maximum-likelihood values. Printed: their medians and quartiles (lengthscales pooled over the active inputs), and the
priors of BoTorch's shapes (concentrations 3, 2, 1.1) whose means are those medians, a candidate for
``OptimizerConfig.margin_priors``. docs/decisions.md §17 gives a run and why the default is not that candidate.
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow.parquet as pq

from cpgjax import cpg, gp
from cpgjax.trial import optimizer_setting
from cpgjax.trial import params as param_space

FLAT = gp.GammaPrior(1.0, 1e-3)
FLAT_PRIORS = gp.Priors(lengthscale=FLAT, outputscale=FLAT, noise=FLAT)
FIT = gp.FitConfig(num_steps=300, learning_rate=0.05)
CONTEXT_COLUMNS = ("c_load_n", "c_slope_rad")


def datasets(folders: list[pathlib.Path]) -> tuple[gp.Dataset, np.ndarray]:
    """One padded dataset per run of every folder, and the (runs, d) active-input masks."""
    runs = []
    for folder in folders:
        table = pq.read_table(folder / "trials.parquet").to_pandas()
        table = table[~table["inference"] & table["accepted"] & np.isfinite(table["safety_margin"])]
        for _, run in table.groupby("instance"):
            # The context ranges the run's optimizer normalized with: its physics profile's (the study's first).
            config = optimizer_setting.profile_config(str(run["physics"].iloc[0]))
            lower, upper = np.asarray(config.context_lower), np.asarray(config.context_upper)
            unit = param_space.to_unit(run[list(param_space.PARAM_NAMES)].to_numpy())
            contexts = (run[list(CONTEXT_COLUMNS)].to_numpy() - lower) / (upper - lower)
            tegotae = cpg.controller_gates(str(run["controller"].iloc[0])).tegotae > 0
            active = np.concatenate([param_space.active_parameters(tegotae), np.ones(len(CONTEXT_COLUMNS), bool)])
            runs.append((np.concatenate([unit, contexts], axis=1), run["safety_margin"].to_numpy(), active))
    capacity = max(len(y) for _, y, _ in runs)
    inputs = np.zeros((len(runs), capacity, runs[0][0].shape[1]), np.float32)
    targets = np.zeros((len(runs), capacity), np.float32)
    valid = np.zeros((len(runs), capacity), bool)
    for i, (x, y, _) in enumerate(runs):
        inputs[i, : len(y)], targets[i, : len(y)], valid[i, : len(y)] = x, y, True
    return gp.Dataset(jnp.asarray(inputs), jnp.asarray(targets), jnp.asarray(valid)), np.stack([a for *_, a in runs])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=pathlib.Path)
    args = parser.parse_args()
    missing = [str(f) for f in args.folders if not (f / "trials.parquet").is_file()]
    if missing:
        parser.error(f"no trials.parquet in {', '.join(missing)}: give finished study folders")
    data, active = datasets(args.folders)
    dims = data.inputs.shape[-1]
    fit = jax.jit(
        jax.vmap(
            lambda ds, a: gp.fit(ds, a, gp.default_params(dims, FLAT_PRIORS), len(CONTEXT_COLUMNS), FIT, FLAT_PRIORS)
        )
    )
    fitted = fit(data, jnp.asarray(active))
    values = {
        "lengthscale": np.exp(np.asarray(fitted.log_lengthscales))[active],
        "outputscale": np.exp(np.asarray(fitted.log_outputscale)),
        "noise": np.exp(np.asarray(fitted.log_noise)),
    }
    print(
        f"{len(values['outputscale'])} runs, {int(np.asarray(data.valid).sum())} trials, "
        f"{int((np.asarray(data.targets)[np.asarray(data.valid)] < 0).sum())} with a negative margin; "
        "maximum-likelihood fits, median [quartiles]:"
    )
    for name, v in values.items():
        q1, median, q3 = np.percentile(v, [25, 50, 75])
        print(f"  {name}: {median:.4g} [{q1:.4g}, {q3:.4g}]")
    candidate = {
        name: gp.GammaPrior(
            getattr(gp.BOTORCH_PRIORS, name).concentration,
            getattr(gp.BOTORCH_PRIORS, name).concentration / np.median(v),
        )
        for name, v in values.items()
    }
    print(
        "candidate: gp.Priors("
        + ", ".join(f"{name}=gp.GammaPrior({p.concentration:g}, {p.rate:.3g})" for name, p in candidate.items())
        + ")"
    )


if __name__ == "__main__":
    main()
