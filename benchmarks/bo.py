"""The GP-UCB optimizer (cpgjax.gp / cpgjax.optim.bo) against BoTorch, same machine, same run.

    python benchmarks/bo.py            # full (see benchmarks/RESULTS.md)
    python benchmarks/bo.py --quick    # under 2 minutes on a 2-core CPU

(a) one optimizer iteration (observe = fit, then propose = acquisition), 8-D, 40 and 150 points,
    one instance; (b) one iteration for 1, 20 and 1,000 vmapped instances against a Python loop
    over BoTorch; (c) simple regret after 40 evaluations on Hartmann-6 and Cosine8, both
    optimizers from the same 2 random initial points per seed and with the paper's beta schedule
    (multiplier 5 * 0.7^max(n - 10, 0) on sigma; BoTorch gets beta = multiplier^2, since its UCB
    uses sqrt(beta)), with a Mann-Whitney U test of the two regret samples (scipy, a BoTorch
    dependency).

BoTorch (the ``bench`` extra) is set up as the paper's stack (bayesopt4ros on BoTorch 0.5):
SingleTaskGP with ScaleKernel(Matern-5/2, ARD), Gamma(3, 6) / Gamma(2, 0.15) / Gamma(1.1, 0.05)
priors, noise >= 1e-4, Standardize; inputs in the unit cube; fit_gpytorch_mll (L-BFGS-B);
optimize_acqf with 10 restarts and 2000 raw samples; float64. Both libraries run with the same
CPU core: the process pins itself to one core (``--cpu``, default the last) and torch uses one
thread. On this 2-core machine, shared with other jobs, unpinned sub-millisecond XLA and torch
calls were 3-20x slower and bimodal (thread hand-offs across busy cores); pinned, the
repeated timings agree within a few percent.

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
import warnings


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, < 2 min")
    parser.add_argument("--cpu", type=int, default=(os.cpu_count() or 1) - 1, help="the CPU core to pin the process to")
    parser.add_argument("--seeds", type=int, default=None, help="seeds for (c)")
    return parser.parse_args()


BENCH_MODULES = ("torch", "botorch", "gpytorch", "scipy")  # the `bench` extra of pyproject.toml


def missing_modules() -> list[str]:
    return [name for name in BENCH_MODULES if importlib.util.find_spec(name) is None]


ARGS = parse_args()
if missing_modules():
    sys.exit(
        f"benchmarks/bo.py compares against BoTorch and needs {', '.join(missing_modules())}, not installed "
        f"here: pip install -e '.[bench]' (or make bench-deps)"
    )
os.sched_setaffinity(0, {ARGS.cpu})  # before jax and torch start their threads

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from botorch.acquisition import UpperConfidenceBound  # noqa: E402
from botorch.fit import fit_gpytorch_mll  # noqa: E402
from botorch.models import SingleTaskGP  # noqa: E402
from botorch.models.transforms import Standardize  # noqa: E402
from botorch.optim import optimize_acqf  # noqa: E402
from gpytorch.constraints import GreaterThan  # noqa: E402
from gpytorch.kernels import MaternKernel, ScaleKernel  # noqa: E402
from gpytorch.likelihoods import GaussianLikelihood  # noqa: E402
from gpytorch.mlls import ExactMarginalLogLikelihood  # noqa: E402
from gpytorch.priors import GammaPrior  # noqa: E402
from scipy.stats import mannwhitneyu  # noqa: E402
from timing import median_seconds  # noqa: E402  (benchmarks/timing.py)

from cpgjax import provenance  # noqa: E402
from cpgjax.optim import bo  # noqa: E402
from cpgjax.optim import config as optimizer_config  # noqa: E402

torch.set_num_threads(1)
warnings.filterwarnings("ignore")  # BoTorch's input-scaling and numerical notices

# ---- test functions (maximization form) ---------------------------------------------------

_H6_A = np.array(
    [[10, 3, 17, 3.5, 1.7, 8], [0.05, 10, 17, 0.1, 8, 14], [3, 3.5, 1.7, 10, 17, 8], [17, 8, 0.05, 10, 0.1, 14]]
)
_H6_P = 1e-4 * np.array(
    [
        [1312, 1696, 5569, 124, 8283, 5886],
        [2329, 4135, 8307, 3736, 1004, 9991],
        [2348, 1451, 3522, 2883, 3047, 6650],
        [4047, 8828, 8732, 5743, 1091, 381],
    ]
)
_H6_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])


def neg_hartmann6(x):
    """-Hartmann-6 on [0, 1]^6, maximum 3.32237."""
    return jnp.sum(_H6_ALPHA * jnp.exp(-jnp.sum(_H6_A * (x - _H6_P) ** 2, axis=-1)))


def cosine8(x):
    """Cosine8 on [-1, 1]^8, maximum 0.8 at 0."""
    return 0.1 * jnp.sum(jnp.cos(5 * jnp.pi * x)) - jnp.sum(x**2)


PROBLEMS = {
    "hartmann6": (neg_hartmann6, np.zeros(6), np.ones(6), 3.32237),
    "cosine8": (cosine8, -np.ones(8), np.ones(8), 0.8),
}


def paper_multiplier(num_observations):
    """The paper's UCB multiplier on sigma, eq. (12) with Table III values, no context."""
    return 5.0 * 0.7 ** max(num_observations - 10, 0)


# ---- BoTorch, the paper's stack -----------------------------------------------------------


def botorch_iteration(unit_x: np.ndarray, y: np.ndarray, multiplier: float):
    """Fit + acquisition; returns (next unit point, fit seconds, acquisition seconds)."""
    t0 = time.perf_counter()
    train_x = torch.as_tensor(unit_x, dtype=torch.float64)
    train_y = torch.as_tensor(y, dtype=torch.float64).reshape(-1, 1)
    dims = train_x.shape[1]
    kernel = ScaleKernel(
        MaternKernel(nu=2.5, ard_num_dims=dims, lengthscale_prior=GammaPrior(3.0, 6.0)),
        outputscale_prior=GammaPrior(2.0, 0.15),
    )
    likelihood = GaussianLikelihood(
        noise_prior=GammaPrior(1.1, 0.05), noise_constraint=GreaterThan(1e-4, transform=None, initial_value=2.0)
    )
    model = SingleTaskGP(
        train_x, train_y, covar_module=kernel, likelihood=likelihood, outcome_transform=Standardize(m=1)
    )
    fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
    t1 = time.perf_counter()
    bounds = torch.stack([torch.zeros(dims), torch.ones(dims)]).to(torch.float64)
    candidate, _ = optimize_acqf(
        UpperConfidenceBound(model, beta=multiplier**2), bounds=bounds, q=1, num_restarts=10, raw_samples=2000
    )
    t2 = time.perf_counter()
    return candidate[0].numpy(), t1 - t0, t2 - t1


def botorch_run(fn, lower, upper, initial_unit, num_evals):
    f = jax.jit(fn)
    xs = [u for u in initial_unit]
    ys = [float(f(lower + u * (upper - lower))) for u in xs]
    while len(ys) < num_evals:
        unit, _, _ = botorch_iteration(np.stack(xs), np.array(ys), paper_multiplier(len(ys)))
        xs.append(unit)
        ys.append(float(f(lower + unit * (upper - lower))))
    return max(ys)


# ---- cpgjax -------------------------------------------------------------------------------


def stack(trees):
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def filled_state(opt, config, rng, num_points):
    """A state holding ``num_points`` random Cosine8-style observations (8-D, no context)."""
    lower, upper = np.array(config.parameter_lower), np.array(config.parameter_upper)
    x = lower + rng.random((num_points, 8)) * (upper - lower)
    y = np.array([float(cosine8(v)) for v in x])
    state = opt.init()
    return (
        state._replace(
            parameters=state.parameters.at[:num_points].set(x),
            objectives=state.objectives.at[:num_points].set(y),
            stored=state.stored.at[:num_points].set(True),
            num_stored=jnp.int32(num_points),
        ),
        x,
        y,
    )


def vmapped_iteration(opt):
    """Jitted, vmapped (observe the last point, then propose): one BO iteration per instance."""

    def iteration(state, x, y, key):
        state, _ = opt.observe(state, x, jnp.zeros((0,)), y)
        return opt.propose(state, jnp.zeros((0,)), key), state

    return jax.jit(jax.vmap(iteration))


def single_iteration(num_points, capacity, repeats, rng):
    """(a) cpgjax: median ms of observe (fit) and propose (acquisition), one instance."""
    config = optimizer_config.OptimizerConfig((-1.0,) * 8, (1.0,) * 8, capacity=capacity)
    opt = bo.make_optimizer(config)
    state, x, y = filled_state(opt, config, rng, num_points - 1)
    new_x = jnp.asarray(rng.uniform(-1, 1, 8), jnp.float32)
    new_y = cosine8(new_x)
    key = jax.random.PRNGKey(0)
    observe = jax.jit(lambda s: opt.observe(s, new_x, jnp.zeros((0,)), new_y)[0])
    propose = jax.jit(lambda s: opt.propose(s, jnp.zeros((0,)), key))
    fit_s = median_seconds(observe, state, repeats=repeats)
    acq_s = median_seconds(propose, observe(state), repeats=repeats)
    return 1e3 * fit_s, 1e3 * acq_s, np.vstack([x, np.asarray(new_x)]), np.append(y, float(new_y))


def botorch_single_iteration(x, y, repeats):
    unit = (x + 1.0) / 2.0
    runs = [botorch_iteration(unit, y, paper_multiplier(len(y))) for _ in range(repeats)]
    return 1e3 * float(np.median([r[1] for r in runs])), 1e3 * float(np.median([r[2] for r in runs]))


def batched_iteration(batch, repeats, rng, num_points=40):
    """(b) cpgjax: wall ms of one vmapped iteration for ``batch`` instances, 40 points each."""
    config = optimizer_config.OptimizerConfig((-1.0,) * 8, (1.0,) * 8, capacity=num_points)
    opt = bo.make_optimizer(config)
    states = stack([filled_state(opt, config, rng, num_points - 1)[0] for _ in range(batch)])
    xs = jnp.asarray(rng.uniform(-1, 1, (batch, 8)), jnp.float32)
    ys = jax.vmap(cosine8)(xs)
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    return 1e3 * median_seconds(vmapped_iteration(opt), states, xs, ys, keys, repeats=repeats)


# ---- (c) regret ---------------------------------------------------------------------------


def initial_points(seed, dims):
    return np.random.default_rng(seed).random((2, dims))


def cpgjax_regret(name, seeds, num_evals):
    """All seeds as one vmapped batch; returns the simple regret per seed."""
    fn, lower, upper, optimum = PROBLEMS[name]
    dims = len(lower)
    config = optimizer_config.OptimizerConfig(tuple(lower), tuple(upper), capacity=num_evals)
    opt = bo.make_optimizer(config)
    propose, observe = jax.jit(jax.vmap(opt.propose)), jax.jit(jax.vmap(opt.observe))
    evaluate = jax.jit(jax.vmap(fn))
    batch = len(seeds)
    states = stack([opt.init() for _ in seeds])
    no_context = jnp.zeros((batch, 0))
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    initial = np.stack([lower + initial_points(s, dims) * (upper - lower) for s in seeds])
    best = np.full(batch, -np.inf)
    for trial in range(num_evals):
        if trial < 2:
            xs = jnp.asarray(initial[:, trial], jnp.float32)
        else:
            xs = propose(states, no_context, jax.vmap(jax.random.fold_in, (0, None))(keys, trial))
        ys = evaluate(xs)
        states, accepted = observe(states, xs, no_context, ys)
        assert bool(jnp.all(accepted))
        best = np.maximum(best, np.asarray(ys))
    return optimum - best


def botorch_regret(name, seeds, num_evals):
    fn, lower, upper, optimum = PROBLEMS[name]
    return np.array([optimum - botorch_run(fn, lower, upper, initial_points(s, len(lower)), num_evals) for s in seeds])


def quartiles(values):
    q25, q50, q75 = np.percentile(values, [25, 50, 75])
    return round(float(q50), 4), round(float(q25), 4), round(float(q75), 4)


def main():
    quick = ARGS.quick
    repeats = 3 if quick else 10
    rng = np.random.default_rng(0)
    figures = {
        "benchmark": "bo",
        "machine": provenance.machine(),
        "pinned_cpu": ARGS.cpu,
        "quick": quick,
        "load_avg_1min_start": round(os.getloadavg()[0], 2),
    }
    t_start = time.time()

    # (a) one iteration, one instance.
    sizes = [(40, 40, "40pts"), (150, 160, "150pts")]
    if not quick:
        sizes.insert(1, (40, 160, "40pts_capacity160"))
    for num_points, capacity, label in sizes:
        fit_ms, acq_ms, x, y = single_iteration(num_points, capacity, repeats, rng)
        figures[f"fit_ms_{label}"] = round(fit_ms, 2)
        figures[f"acq_ms_{label}"] = round(acq_ms, 2)
        figures[f"iter_ms_{label}"] = round(fit_ms + acq_ms, 2)
        if capacity == 160 and num_points == 40:
            continue
        bt_fit, bt_acq = botorch_single_iteration(x, y, 2 if quick else 5)
        figures[f"botorch_fit_ms_{label}"] = round(bt_fit, 1)
        figures[f"botorch_acq_ms_{label}"] = round(bt_acq, 1)
        figures[f"botorch_iter_ms_{label}"] = round(bt_fit + bt_acq, 1)
        figures[f"speedup_vs_botorch_{label}"] = round((bt_fit + bt_acq) / (fit_ms + acq_ms), 1)
        print(f"(a) {label}: cpgjax {fit_ms:.1f} + {acq_ms:.1f} ms, BoTorch {bt_fit:.0f} + {bt_acq:.0f} ms", flush=True)

    # (b) batches (40 points each); BoTorch loops are linear in the batch, measured on up to
    # `measured` instances and extrapolated beyond.
    batches = (1, 20) if quick else (1, 20, 1000)
    measured = 3 if quick else 20
    x40, y40 = single_iteration(40, 40, 1, rng)[2:]
    t0 = time.perf_counter()
    for _ in range(measured):
        botorch_iteration((x40 + 1) / 2, y40, paper_multiplier(40))
    botorch_per_instance_ms = 1e3 * (time.perf_counter() - t0) / measured
    for batch in batches:
        ms = batched_iteration(batch, repeats, rng)
        figures[f"batch_iter_ms_{batch}"] = round(ms, 2)
        figures[f"batch_iter_ms_per_instance_{batch}"] = round(ms / batch, 3)
        figures[f"botorch_loop_iter_ms_{batch}"] = round(botorch_per_instance_ms * batch, 1)
        figures[f"speedup_vs_botorch_loop_{batch}"] = round(botorch_per_instance_ms * batch / ms, 1)
        print(
            f"(b) batch {batch}: cpgjax {ms:.1f} ms, BoTorch loop {botorch_per_instance_ms * batch:.0f} ms", flush=True
        )
    figures["botorch_loop_measured_instances"] = measured

    # (c) regret.
    num_seeds = ARGS.seeds or (2 if quick else 20)
    num_evals = 10 if quick else 40
    seeds = list(range(num_seeds))
    figures.update(regret_seeds=num_seeds, regret_evaluations=num_evals)
    for name in PROBLEMS:
        ours = cpgjax_regret(name, seeds, num_evals)
        theirs = botorch_regret(name, seeds, num_evals)
        for prefix, values in (("", ours), ("botorch_", theirs)):
            median, q25, q75 = quartiles(values)
            figures[f"{prefix}{name}_regret_median"] = median
            figures[f"{prefix}{name}_regret_q25"] = q25
            figures[f"{prefix}{name}_regret_q75"] = q75
        # Two-sided Mann-Whitney U test of "same regret distribution": a small p (< 0.05) means
        # a difference beyond seed noise.
        p_value = float(mannwhitneyu(ours, theirs).pvalue)
        figures[f"{name}_regret_mannwhitney_p"] = round(p_value, 3)
        print(
            f"(c) {name}: regret cpgjax {quartiles(ours)}, BoTorch {quartiles(theirs)}"
            f" (median, q25, q75); Mann-Whitney p = {p_value:.2f}",
            flush=True,
        )

    figures["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    figures["wall_s"] = round(time.time() - t_start, 1)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
