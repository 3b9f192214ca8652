"""GP-UCB for black-box functions: :func:`maximize`, a convenience loop over the optimizer of
:mod:`cpgjax.optim.bo` (Algorithm 1 without a context) for users who want to try it on their own
problems. One compiled optimizer per configuration is cached, so repeated calls (seeds) do
not recompile. The loop runs in Python, one evaluation of ``fn`` per trial; for many
independent runs at once, ``jax.vmap`` the optimizer's ``propose``/``observe`` instead
(``benchmarks/bo.py`` does so).
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
    """Result of :func:`maximize`: the best point and value, and the whole history."""

    best_x: np.ndarray
    best_value: float
    xs: np.ndarray
    values: np.ndarray


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
) -> MaximizeResult:
    """Maximize a black-box ``fn`` over a box with GP-UCB (Algorithm 1, no context).

    Args:
      fn: maps a (d,) NumPy array to a finite float.
      bounds: (2, d) array-like, lower then upper bounds.
      num_trials: evaluations of ``fn`` (including the random ones).
      seed: seed of the PRNG keys.
      num_random_proposals: initial uniform random proposals (ignored for the points given
        in ``initial_xs``, which are evaluated first).
      ucb_form, schedule, fit, acquisition: as in :class:`OptimizerConfig` / ``init``.
      initial_xs: optional (k, d) points to evaluate first (e.g. a shared initial design).

    Returns:
      A :class:`MaximizeResult`.
    """
    bounds = np.asarray(bounds, np.float64)
    if bounds.ndim != 2 or bounds.shape[0] != 2:
        raise ValueError(f"bounds must have shape (2, d), got {bounds.shape}")
    if num_trials < 1:
        raise ValueError(f"num_trials must be >= 1, got {num_trials}")
    config = OptimizerConfig(
        parameter_lower=tuple(bounds[0]), parameter_upper=tuple(bounds[1]),
        capacity=num_trials, num_random_proposals=num_random_proposals, ucb_form=ucb_form,
        fit=fit, acquisition=acquisition,
    )
    optimizer = _black_box_optimizer(config)
    state = optimizer.init(schedule=schedule)
    initial = np.zeros((0, bounds.shape[1])) if initial_xs is None else np.asarray(initial_xs)
    no_context = jnp.zeros((0,), jnp.float32)
    key = jax.random.PRNGKey(seed)
    xs, values = [], []
    for trial in range(num_trials):
        key, subkey = jax.random.split(key)
        x = initial[trial] if trial < len(initial) else np.asarray(
            optimizer.propose(state, no_context, subkey))
        value = float(fn(np.asarray(x, np.float64)))
        state, _ = optimizer.observe(state, jnp.asarray(x, jnp.float32), no_context,
                                     jnp.float32(value))
        xs.append(np.asarray(x, np.float64))
        values.append(value)
    values_np = np.asarray(values)
    best = int(np.argmax(values_np))
    return MaximizeResult(xs[best], float(values_np[best]), np.stack(xs), values_np)
