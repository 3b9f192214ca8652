"""Safe GP-UCB (cpgjax.optim.bo with OptimizerConfig.safe) against the unconstrained optimizer, same machine, same run.

    python benchmarks/safe_bo.py            # full (see benchmarks/RESULTS.md)
    python benchmarks/safe_bo.py --quick    # a few minutes on a 2-core CPU

(a) Cost: one optimizer iteration (observe = store and refit, then propose = acquisition) of the paper's setting
    (8 parameters, 2 contexts), safe against unconstrained, at 40 and 150 stored points, for 1 and 20 vmapped instances.
    The process pins itself to one core (``--cpu``), as benchmarks/bo.py does, so the two are timed alike. The two
    iterations are timed in alternation, one of each per pair, so that a drift of the machine's speed falls on both;
    the ratio is the geometric mean of the pairs' ratios with its 95 % interval (Student t on the log ratios).
(b) A standard constrained test function, Gardner et al. (ICML 2014, "Bayesian optimization with inequality
    constraints", their first simulated problem): minimize cos(2x) cos(y) + sin(x) over [0, 6]² subject to
    cos(x) cos(y) − sin(x) sin(y) ≤ 0.5. Here: maximize the negative, margin = 0.5 − constraint. Each seed starts both
    optimizers from the same 2 random feasible points; the figures are the violations (evaluations with margin < 0)
    and the simple regret of the best feasible evaluation against the constrained optimum of a 2001² grid, with 95 %
    intervals over seeds and a Mann–Whitney U test of safe against unconstrained.

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer timed pairs and seeds")
    parser.add_argument("--cpu", type=int, default=(os.cpu_count() or 1) - 1, help="the CPU core to pin to")
    parser.add_argument("--seeds", type=int, default=None, help="seeds for (b) (default 20, --quick 6)")
    return parser.parse_args()


ARGS = parse_args()
os.sched_setaffinity(0, {ARGS.cpu})  # before jax starts its threads

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import mannwhitneyu  # noqa: E402

from cpgjax.optim import black_box, bo  # noqa: E402
from cpgjax.studies import stats  # noqa: E402
from cpgjax.trial import optimizer_setting  # noqa: E402


def toy(unit):
    """An objective and a margin on the paper's unit box (8 parameters)."""
    return -jnp.sum((unit - 0.7) ** 2), 0.5 - jnp.linalg.norm(unit - 0.4)


def iteration(safe: bool, stored: int, batch: int):
    """One vmapped observe + propose with ``stored`` points already observed, compiled, as a call that waits for
    its result."""
    config = optimizer_setting.paper_config(capacity=stored + 1, safe=safe)
    opt = bo.make_optimizer(config)
    lower, width = np.array(config.parameter_lower), np.array(config.parameter_upper) - np.array(config.parameter_lower)
    rng = np.random.default_rng(0)
    unit = rng.random((batch, stored + 1, 8)).astype(np.float32)
    contexts = np.tile([35.0, -0.1], (batch, stored + 1, 1)).astype(np.float32)
    objective, margin = jax.vmap(jax.vmap(toy))(jnp.asarray(unit))
    state = jax.vmap(lambda _: opt.init())(jnp.arange(batch))
    n = stored
    state = state._replace(
        parameters=state.parameters.at[:, :n].set(jnp.asarray(lower + unit[:, :n] * width)),
        contexts=state.contexts.at[:, :n].set(jnp.asarray(contexts[:, :n])),
        objectives=state.objectives.at[:, :n].set(objective[:, :n]),
        stored=state.stored.at[:, :n].set(True),
        num_stored=jnp.full((batch,), n, jnp.int32),
        margins=state.margins.at[:, :n].set(margin[:, :n]) if safe else state.margins,
    )
    x = jnp.asarray(lower + unit[:, n] * width, jnp.float32)
    c = jnp.asarray(contexts[:, n])
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(batch))
    if safe:
        observe = jax.jit(jax.vmap(opt.observe))
        args = (state, x, c, objective[:, n], margin[:, n])
    else:
        observe = jax.jit(jax.vmap(lambda s, x, c, j: opt.observe(s, x, c, j)))
        args = (state, x, c, objective[:, n])
    propose = jax.jit(jax.vmap(opt.propose_with_fallback))

    def once():
        new_state, _ = observe(*args)
        return jax.block_until_ready(propose(new_state, c, keys))

    once()  # compiles
    return once


def paired_cost(stored: int, batch: int, pairs: int) -> dict:
    """Wall seconds of an unconstrained and a safe iteration timed in alternation, ``pairs`` of each (after one
    untimed warm-up pair): their medians, and the geometric mean of the per-pair ratios safe / unconstrained with
    its 95 % interval."""
    calls = {"unconstrained": iteration(False, stored, batch), "safe": iteration(True, stored, batch)}
    seconds = {name: [] for name in calls}
    for timed in [False] + [True] * pairs:
        for name, call in calls.items():
            t0 = time.perf_counter()
            call()
            if timed:
                seconds[name].append(time.perf_counter() - t0)
    log_ratio = stats.mean_ci(np.log(seconds["safe"]) - np.log(seconds["unconstrained"]))
    return {
        "unconstrained_s": float(np.median(seconds["unconstrained"])),
        "safe_s": float(np.median(seconds["safe"])),
        "ratio": float(np.exp(log_ratio.mean)),
        "ratio_ci": [float(np.exp(log_ratio.low)), float(np.exp(log_ratio.high))],
        "pairs": pairs,
    }


def gardner(x):
    """Gardner et al. 2014's first simulated problem in maximization form: (−f, 0.5 − c)."""
    value = np.cos(2 * x[0]) * np.cos(x[1]) + np.sin(x[0])
    constraint = np.cos(x[0]) * np.cos(x[1]) - np.sin(x[0]) * np.sin(x[1])
    return -value, 0.5 - constraint


def constrained_optimum() -> float:
    axis = np.linspace(0.0, 6.0, 2001)
    x, y = np.meshgrid(axis, axis, indexing="ij")
    value, margin = gardner(np.stack([x, y]))
    return float(np.max(np.where(margin >= 0, value, -np.inf)))


def feasible_start(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    points = []
    while len(points) < 2:
        x = rng.uniform(0.0, 6.0, 2)
        if gardner(x)[1] >= 0.0:
            points.append(x)
    return np.stack(points)


def constrained_runs(seeds: int, trials: int) -> dict:
    best = constrained_optimum()
    figures = {}
    for safe in (False, True):
        violations, regrets = [], []
        for seed in range(seeds):
            fn = gardner if safe else (lambda x: gardner(x)[0])
            run = black_box.maximize(
                fn, [[0.0, 0.0], [6.0, 6.0]], trials, seed=seed, initial_xs=feasible_start(seed), safe=safe
            )
            margins = np.array([gardner(x)[1] for x in run.xs])
            values = np.array([gardner(x)[0] for x in run.xs])
            violations.append(int((margins < 0).sum()))
            regrets.append(best - float(np.max(np.where(margins >= 0, values, -np.inf))))
        figures["safe" if safe else "unconstrained"] = {"violations": violations, "regret": regrets}
    for key in ("violations", "regret"):
        a, b = figures["safe"][key], figures["unconstrained"][key]
        figures[f"{key}_mann_whitney_p"] = float(mannwhitneyu(a, b).pvalue)
    figures["constrained_optimum"] = best
    return figures


def main() -> None:
    pairs = 10 if ARGS.quick else 30
    seeds = ARGS.seeds or (6 if ARGS.quick else 20)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, pinned to CPU {ARGS.cpu}; "
        f"jax {jax.__version__}"
    )
    cost = {}
    for stored in (40, 150):
        for batch in (1, 20):
            c = paired_cost(stored, batch, pairs)
            cost[f"{stored} points x {batch}"] = c
            print(
                f"(a) {stored} points, {batch} instance(s): unconstrained {c['unconstrained_s'] * 1e3:.1f} ms, safe "
                f"{c['safe_s'] * 1e3:.1f} ms (medians of {pairs}), ratio {c['ratio']:.2f} "
                f"[{c['ratio_ci'][0]:.2f}, {c['ratio_ci'][1]:.2f}]",
                flush=True,
            )
    trials = 30
    runs = constrained_runs(seeds, trials)
    for arm in ("unconstrained", "safe"):
        v, r = runs[arm]["violations"], runs[arm]["regret"]
        print(
            f"(b) {arm}: violations per {trials} evaluations {stats.mean_ci(v)}, simple regret {stats.mean_ci(r)} "
            f"over {seeds} seeds"
        )
    print(
        f"(b) safe vs unconstrained, Mann–Whitney U: violations p = {runs['violations_mann_whitney_p']:.2g}, "
        f"regret p = {runs['regret_mann_whitney_p']:.2g}"
    )
    print(json.dumps({"cost": cost, "constrained": runs, "seeds": seeds, "trials": trials}))


if __name__ == "__main__":
    main()
