"""The paper's trial figures as pure functions of a stored trial record: objective J (eq. 9), cost of transport
(eq. 10) and context (eq. 11). Pure and target-parametrized, so J can be recomputed for a new target velocity from
stored records (the paper's data reuse) by any caller, e.g. the optimizer, without touching the simulator.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cpgjax.go1.constants import GRAVITY_MPS2, TICK_S
from cpgjax.trial.protocol import TrialRecord

VELOCITY_WEIGHT = 1.0  # w1
COT_WEIGHT = 0.5  # w2
MAX_VELOCITY_REWARD = 0.85  # l_r
VELOCITY_KERNEL_WIDTH = 0.05  # [m²/s²], the 0.05 in eq. (9)
STEADY_DT_S = TICK_S  # Δt
# docs/decisions.md §10, degenerate trials: CoT divides by at least MIN_DISTANCE_M of forward progress (so standing
# still or walking backwards gives a large CoT), and J is bounded below by MIN_OBJECTIVE; a fall or a non-finite
# state gives exactly MIN_OBJECTIVE. Typical J of a walking gait is 1.5 … 2.3; the floor sits well below.
MIN_DISTANCE_M = 0.05
MIN_OBJECTIVE = -1.0


def cost_of_transport(record: TrialRecord) -> jax.Array:
    """CoT = Σ⟨|τ|, |q̇|⟩Δt / (m g d), eq. (10), with d ≥ MIN_DISTANCE_M (docs/decisions.md §10)."""
    distance = jnp.maximum(record.distance_m, MIN_DISTANCE_M)
    return record.energy_j / (record.total_mass_kg * GRAVITY_MPS2 * distance)


def velocity_reward(record: TrialRecord, target_velocity_mps) -> jax.Array:
    """w1 Δt Σ_i min(exp(−‖v_i − v*‖²/0.05), l_r) with v* = [v_x*, 0], the first term of eq. (9)."""
    target = jnp.stack([jnp.asarray(target_velocity_mps, jnp.float32), jnp.float32(0.0)])
    sq_error = jnp.sum((record.velocity_xy_mps - target) ** 2, axis=-1)
    per_step = jnp.minimum(jnp.exp(-sq_error / VELOCITY_KERNEL_WIDTH), MAX_VELOCITY_REWARD)
    return VELOCITY_WEIGHT * STEADY_DT_S * jnp.sum(per_step, axis=-1)


def objective(record: TrialRecord, target_velocity_mps, floor: float = MIN_OBJECTIVE) -> jax.Array:
    """J of eq. (9) for target velocity v_x*, always finite and ≥ ``floor``; ``floor`` after a fall or a non-finite
    simulation (docs/decisions.md §10; a study's ``objective_floor`` switch moves it)."""
    j = velocity_reward(record, target_velocity_mps) - COT_WEIGHT * cost_of_transport(record)
    degenerate = (record.fell > 0) | (record.failed > 0) | ~jnp.isfinite(j)
    return jnp.where(degenerate, floor, jnp.maximum(j, floor))


def mean_velocity(record: TrialRecord) -> jax.Array:
    """Mean (v_x, v_y) over the steady phase [m/s]."""
    return jnp.mean(record.velocity_xy_mps, axis=-2)


CONTEXT_NAMES = ("c_load", "c_slope")  # the components of context(), in order
CONTEXT_UNITS = ("N", "rad")


def context(record: TrialRecord) -> jax.Array:
    """The context c = [c_load [N], c_slope [rad]] of eq. (11) (``CONTEXT_NAMES``, ``CONTEXT_UNITS``)."""
    return jnp.stack([record.c_load_n, record.c_slope_rad], axis=-1)
