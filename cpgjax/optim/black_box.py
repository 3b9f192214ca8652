"""GP-UCB for black-box functions: :func:`maximize`, a convenience loop over the optimizer of
:mod:`cpgjax.optim.bo` (Algorithm 1 without a context) for users who want to try it on their own
problems. One compiled optimizer per configuration is cached, so repeated calls (seeds) do
not recompile. The loop runs in Python, one evaluation of ``fn`` per trial; for many
independent runs at once, ``jax.vmap`` the optimizer's ``propose``/``observe`` instead
(``benchmarks/bo.py`` does so).

With ``safe=True``, ``fn`` returns ``(value, margin)`` and the optimizer is the safe one of
:mod:`cpgjax.optim.bo` (docs/decisions.md §17): proposals stay where the margin GP's lower
confidence bound is ≥ 0, from the first UCB trial on; the best point is the best one whose
margin was ≥ 0.
"""

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import gp
from cpgjax.optim.acquisition import AcquisitionConfig
from cpgjax.optim.bo import ContextualBO, make_optimizer
from cpgjax.optim.config import OptimizerConfig
from cpgjax.optim.exploration import BetaSchedule


@functools.lru_cache(maxsize=16)
def _black_box_optimizer(config: OptimizerConfig) -> ContextualBO:
    """One compiled optimizer per configuration, so repeated :func:`maximize` calls (seeds)
    do not recompile."""
    return make_optimizer(config)


class MaximizeResult(NamedTuple):
    """Result of :func:`maximize`: the best point and value, and the whole history (with ``safe``: the best point
    among those with margin ≥ 0, every margin, and which proposals fell back to a safe point seen before)."""

    best_x: np.ndarray
    best_value: float
    xs: np.ndarray
    values: np.ndarray
    margins: np.ndarray | None = None
    fell_back: np.ndarray | None = None


def maximize(
    fn: Callable[[np.ndarray], float],
    bounds,
    num_trials: int,
    seed: int = 0,
    *,
    num_random_proposals: int = 2,
    ucb_form: str = "paper",
    schedule: BetaSchedule | None = None,
    fit: gp.FitConfig = gp.FitConfig(),
    acquisition: AcquisitionConfig = AcquisitionConfig(),
    initial_xs=None,
    safe: bool = False,
    safe_beta: float = 2.0,
) -> MaximizeResult:
    """Maximize a black-box ``fn`` over a box with GP-UCB (Algorithm 1, no context).

    Args:
      fn: maps a (d,) NumPy array to a finite float; with ``safe``, to ``(value, margin)``, the
        evaluation being unsafe where ``margin < 0``.
      bounds: (2, d) array-like, lower then upper bounds.
      num_trials: evaluations of ``fn`` (including the random ones).
      seed: seed of the PRNG keys.
      num_random_proposals: initial uniform random proposals (ignored for the points given
        in ``initial_xs``, which are evaluated first).
      ucb_form, schedule, fit, acquisition: as in :class:`OptimizerConfig` / ``init``.
      initial_xs: optional (k, d) points to evaluate first (e.g. a shared initial design, or
        points known to be safe).
      safe, safe_beta: safe optimization and its β_s (:class:`OptimizerConfig`).

    Returns:
      A :class:`MaximizeResult`.
    """
    bounds = np.asarray(bounds, np.float64)
    if bounds.ndim != 2 or bounds.shape[0] != 2:
        raise ValueError(f"bounds must have shape (2, d), got {bounds.shape}")
    if num_trials < 1:
        raise ValueError(f"num_trials must be >= 1, got {num_trials}")
    config = OptimizerConfig(
        parameter_lower=tuple(bounds[0]),
        parameter_upper=tuple(bounds[1]),
        capacity=num_trials,
        num_random_proposals=num_random_proposals,
        ucb_form=ucb_form,
        fit=fit,
        acquisition=acquisition,
        safe=safe,
        safe_beta=safe_beta,
    )
    optimizer = _black_box_optimizer(config)
    state = optimizer.init(schedule=schedule)
    initial = np.zeros((0, bounds.shape[1])) if initial_xs is None else np.asarray(initial_xs)
    no_context = jnp.zeros((0,), jnp.float32)
    key = jax.random.PRNGKey(seed)
    xs, values, margins, fell_back = [], [], [], []
    for trial in range(num_trials):
        key, subkey = jax.random.split(key)
        if trial < len(initial):
            x, back = initial[trial], False
        else:
            x, back = optimizer.propose_with_fallback(state, no_context, subkey)
            x, back = np.asarray(x), bool(back)
        evaluated = fn(np.asarray(x, np.float64))
        value, margin = (float(evaluated[0]), float(evaluated[1])) if safe else (float(evaluated), None)
        state, _ = optimizer.observe(
            state,
            jnp.asarray(x, jnp.float32),
            no_context,
            jnp.float32(value),
            None if margin is None else jnp.float32(margin),
        )
        xs.append(np.asarray(x, np.float64))
        values.append(value)
        margins.append(margin)
        fell_back.append(back)
    values_np = np.asarray(values)
    if not safe:
        best = int(np.argmax(values_np))
        return MaximizeResult(xs[best], float(values_np[best]), np.stack(xs), values_np)
    margins_np = np.asarray(margins)
    ranked = np.where(margins_np >= 0.0, values_np, -np.inf)
    best = int(np.argmax(ranked))
    return MaximizeResult(xs[best], float(ranked[best]), np.stack(xs), values_np, margins_np, np.asarray(fell_back))
