r"""Upper-confidence-bound acquisition (paper eq. (8)) and its maximization over the box.

.. math::
    a(\mathbf{x}; \beta, \mathbf{c}) = \mu(\mathbf{x}; \mathbf{c}) + \beta\,\sigma(\mathbf{x}; \mathbf{c})

is the paper's form (``ucb_form="paper"``, the default). BoTorch's ``UpperConfidenceBound``
multiplies :math:`\sigma` by :math:`\sqrt\beta` instead (``ucb_form="botorch"``;
docs/decisions.md §2). :math:`\sigma` is the latent standard deviation, without observation
noise, as in BoTorch.

The maximizer works in the unit cube of the parameters, with the context held fixed by the
caller: ``num_candidates`` quasi-random points (an :math:`R_d` low-discrepancy sequence,
Roberts 2018, with a random shift per call), then the ``num_restarts`` best of them are
refined by projected Adam for ``num_steps`` steps (clip to the cube, inactive inputs reset to
0.5 after every step). Adam is per-coordinate, so ascending the sum of the restarts'
acquisitions is exactly independent ascent per restart. The best of the refined points and
the best candidate is returned; every point it can return is inside the box.

With a ``constraint`` (the safe optimizer's lower confidence bound of the safety margin,
:mod:`cpgjax.optim.bo`), only points where it is ≥ 0 count: the candidates are ranked among the
feasible ones, the refinement ascends the acquisition minus ``CONSTRAINT_PENALTY`` times the
constraint's shortfall below ``CONSTRAINT_CUSHION`` (so a start outside the feasible set is pushed
into it), and the returned value is −inf when no finalist is feasible. The constraint is expected
in standardized units, as the acquisition.
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cpgjax import gp

UCB_FORMS = ("paper", "botorch")

INACTIVE_VALUE = 0.5
"""Unit-cube value of inactive inputs in every proposal (the box midpoint)."""

CONSTRAINT_PENALTY = 100.0
"""Weight of a constraint's violation in the refinement's objective (acquisition units per constraint unit)."""

CONSTRAINT_CUSHION = 0.01
"""The refinement penalizes constraint values below this (not below 0), so that its last steps, which straddle the
feasible set's edge by about a step, end inside it."""


class AcquisitionConfig(NamedTuple):
    """Static settings of the acquisition maximizer.

    Attributes:
      num_candidates: quasi-random points evaluated first.
      num_restarts: best candidates refined by projected Adam.
      num_steps: Adam steps per restart.
      learning_rate: initial Adam step in unit-cube units; cosine-decayed to 10 %.
    """

    num_candidates: int = 1024
    num_restarts: int = 8
    num_steps: int = 50
    learning_rate: float = 0.05


def ucb_multiplier(beta: jax.Array, ucb_form: str) -> jax.Array:
    """The factor on :math:`\\sigma` in eq. (8): ``beta`` ("paper") or ``sqrt(beta)``
    ("botorch")."""
    if ucb_form == "paper":
        return beta
    if ucb_form == "botorch":
        return jnp.sqrt(beta)
    raise ValueError(f"ucb_form must be one of {UCB_FORMS}, got {ucb_form!r}")


def upper_confidence_bound(
    post: gp.Posterior, query_inputs: jax.Array, multiplier: jax.Array, context_dims: int
) -> jax.Array:
    """Eq. (8), ``mu + multiplier * sigma``, at (q, d) normalized inputs, shape (q,).

    In standardized outcome units (``(a - target_mean) / target_std``): the same argmax as in
    the objective's units, and a gradient scale that does not depend on the objective's.
    """
    mean, variance = gp.predict(post, query_inputs, context_dims)
    return (mean - post.target_mean + multiplier * jnp.sqrt(variance)) / post.target_std


def lower_confidence_bound(
    post: gp.Posterior, query_inputs: jax.Array, multiplier: jax.Array, context_dims: int
) -> jax.Array:
    """``(mu - multiplier * sigma) / target_std`` at (q, d) normalized inputs, shape (q,): the
    lower bound in units of the outcome's standard deviation, with the sign of the bound in the
    outcome's own units (the safe optimizer compares it with 0)."""
    mean, variance = gp.predict(post, query_inputs, context_dims)
    return (mean - multiplier * jnp.sqrt(variance)) / post.target_std


def _rd_sequence(num_points: int, dims: int) -> np.ndarray:
    """First ``num_points`` points of the R_d sequence in [0, 1)^dims (float64, static)."""
    phi = 2.0
    for _ in range(64):  # fixed point of phi = (1 + phi)^(1 / (dims + 1))
        phi = (1.0 + phi) ** (1.0 / (dims + 1))
    alpha = (1.0 / phi) ** np.arange(1, dims + 1)
    return np.mod(np.arange(1, num_points + 1)[:, None] * alpha[None, :], 1.0)


def quasi_random_points(key: jax.Array, num_points: int, dims: int) -> jax.Array:
    """``num_points`` low-discrepancy points in the unit cube, randomly shifted (mod 1)."""
    base = jnp.asarray(_rd_sequence(num_points, dims), jnp.float32)
    shift = jax.random.uniform(key, (dims,), jnp.float32)
    return jnp.mod(base + shift, 1.0)


def _project(points: jax.Array, active: jax.Array) -> jax.Array:
    return jnp.where(active, jnp.clip(points, 0.0, 1.0), INACTIVE_VALUE)


def maximize_acquisition(
    acquisition: Callable[[jax.Array], jax.Array],
    key: jax.Array,
    active: jax.Array,
    config: AcquisitionConfig = AcquisitionConfig(),
    constraint: Callable[[jax.Array], jax.Array] | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Maximize a batched acquisition over the unit cube (inactive inputs fixed at 0.5).

    Args:
      acquisition: maps (q, d) unit-cube points to (q,) values; the context is closed over.
      key: PRNG key for the random shift of the candidates.
      active: (d,) bool active-input mask.
      config: static maximizer settings.
      constraint: optional; maps (q, d) points to (q,) values, feasible where ≥ 0.

    Returns:
      (best point (d,) in the unit cube, its acquisition value ()); with a constraint, the best
      feasible point, and a value of −inf when no finalist is feasible.
    """
    dims = active.shape[0]
    finite_or_worst = lambda v: jnp.where(jnp.isfinite(v), v, -jnp.inf)  # noqa: E731

    def feasible_values(points):
        values = finite_or_worst(acquisition(points))
        return values if constraint is None else jnp.where(constraint(points) >= 0.0, values, -jnp.inf)

    def refined_objective(points):
        values = acquisition(points)
        if constraint is not None:
            values = values - CONSTRAINT_PENALTY * jax.nn.relu(CONSTRAINT_CUSHION - constraint(points))
        return -jnp.sum(values)

    candidates = _project(quasi_random_points(key, config.num_candidates, dims), active)
    candidate_values = feasible_values(candidates)
    _, start_index = jax.lax.top_k(candidate_values, config.num_restarts)
    starts = candidates[start_index]

    schedule = optax.cosine_decay_schedule(config.learning_rate, config.num_steps, alpha=0.1)
    optimizer = optax.adam(schedule)
    negative_sum = jax.grad(refined_objective)

    def step(carry, _):
        points, opt_state = carry
        grads = negative_sum(points)
        grads = jnp.where(jnp.isfinite(grads), grads, 0.0)
        updates, opt_state = optimizer.update(grads, opt_state, points)
        return (_project(optax.apply_updates(points, updates), active), opt_state), None

    (refined, _), _ = jax.lax.scan(step, (starts, optimizer.init(starts)), None, length=config.num_steps)
    finalists = jnp.concatenate([refined, candidates[start_index[:1]]])
    finalist_values = feasible_values(finalists)
    best = jnp.argmax(finalist_values)
    return finalists[best], finalist_values[best]
