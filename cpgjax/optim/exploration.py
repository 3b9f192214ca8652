r"""The exploration factor :math:`\beta` of the UCB (paper eqs. (12)-(14), Table III).

.. math::
    \beta = \beta_{init}\, \gamma^{\max(n - n_{decay},\, 0)} \quad\text{(eq. 12)}, \qquad
    \beta = \beta_{init,c}\, \gamma^{\max(n - n_{decay,c},\, 0)} \quad\text{(eq. 13)}

where :math:`n` counts the stored trials *in the current context* (eq. (14)): trial :math:`i`
counts when :math:`|c_k - c^i_k| \le t_k r_k` for every context component :math:`k`, with
:math:`t_k` the threshold and :math:`r_k` the width of the normalization range
(docs/decisions.md §11). Eq. (13) applies once the context has changed, i.e. once any stored trial
lies outside those thresholds (docs/decisions.md §12); eq. (12) otherwise. Inference mode (paper
Sec. IV-C) fixes :math:`\beta` (1e-6 in the paper).

Everything here is a pure jax function of arrays, so a batch of instances with their own
schedules, contexts and histories is one ``jax.vmap``. How :math:`\beta` multiplies
:math:`\sigma` (:math:`\beta` or :math:`\sqrt\beta`) is :func:`cpgjax.optim.acquisition.ucb_multiplier`.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp


class BetaSchedule(NamedTuple):
    """Per-instance exploration schedule of eqs. (12)-(13) (Table III values by default).

    Attributes (float32 scalars):
      beta_init: beta_init of eq. (12).
      gamma: decay rate.
      n_decay: trials before the decay starts.
      beta_init_changed: beta_init,c of eq. (13), used after a context change.
      n_decay_changed: n_decay,c of eq. (13).
    """

    beta_init: jax.Array
    gamma: jax.Array
    n_decay: jax.Array
    beta_init_changed: jax.Array
    n_decay_changed: jax.Array


def paper_schedule(beta_init=5.0, gamma=0.7, n_decay=10, beta_init_changed=1.5, n_decay_changed=3) -> BetaSchedule:
    """A :class:`BetaSchedule` of float32 scalars; defaults are the paper's Table III."""
    return BetaSchedule(
        *(jnp.asarray(v, jnp.float32) for v in (beta_init, gamma, n_decay, beta_init_changed, n_decay_changed))
    )


class BetaInfo(NamedTuple):
    """Result of :func:`exploration_beta`: beta, n of eq. (14), and whether the context
    changed (some stored trial outside the thresholds)."""

    beta: jax.Array
    num_in_context: jax.Array
    context_changed: jax.Array


def exploration_beta(
    schedule: BetaSchedule,
    stored_contexts: jax.Array,
    stored: jax.Array,
    context: jax.Array,
    context_tolerance: jax.Array,
    inference_mode: jax.Array,
    inference_beta: float,
) -> BetaInfo:
    """Beta of eqs. (12)-(14) for proposing at ``context``.

    Args:
      schedule: the instance's :class:`BetaSchedule`.
      stored_contexts: (capacity, C) contexts of the stored trials, physical units.
      stored: (capacity,) bool, which rows hold a trial.
      context: (C,) the current context, physical units.
      context_tolerance: (C,) :math:`t_k r_k` of eq. (14), physical units.
      inference_mode: () bool; beta is then ``inference_beta``.
      inference_beta: beta in inference mode.

    Returns:
      A :class:`BetaInfo`.
    """
    within = jnp.all(jnp.abs(stored_contexts - context) <= context_tolerance, axis=-1)
    num_in_context = jnp.sum(stored & within)
    changed = jnp.any(stored & ~within)
    normal = schedule.beta_init * schedule.gamma ** jnp.maximum(num_in_context - schedule.n_decay, 0.0)
    adapted = schedule.beta_init_changed * schedule.gamma ** jnp.maximum(num_in_context - schedule.n_decay_changed, 0.0)
    beta = jnp.where(inference_mode, inference_beta, jnp.where(changed, adapted, normal))
    return BetaInfo(beta, num_in_context, changed)
