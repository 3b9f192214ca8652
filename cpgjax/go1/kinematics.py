"""Go1 leg kinematics: forward kinematics, analytic inverse kinematics and the leg Jacobian.

Leg frame: origin at the hip-abduction joint, axes parallel to the trunk (x forward, y left, z up).
Joint vector of one leg q = (q1 abduction, q2 thigh, q3 calf) in rad; side = -1 for right legs, +1 for left.
Link lengths (docs/go1-model.md): l1 = 0.08 m hip offset along y, l2 = l3 = 0.213 m thigh and calf.

All functions take one leg and are lifted over the four legs with ``jax.vmap`` (see ``legs_*``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

HIP_OFFSET_M = 0.08  # l1
THIGH_LENGTH_M = 0.213  # l2
CALF_LENGTH_M = 0.213  # l3

# Leg order everywhere: constants.LEG_NAMES (FR, FL, RR, RL, the SDK's motor order).
SIDE_SIGN = np.array([-1.0, 1.0, -1.0, 1.0])  # -1 right, +1 left
FRONT_SIGN = np.array([1.0, 1.0, -1.0, -1.0])  # +1 front, -1 hind
# Hip-abduction joint positions in the trunk frame [m].
HIP_POS_M = np.array(
    [[0.1881, -0.04675, 0.0], [0.1881, 0.04675, 0.0], [-0.1881, -0.04675, 0.0], [-0.1881, 0.04675, 0.0]]
)


def leg_fk(q_rad: jax.Array, side: jax.Array) -> jax.Array:
    """Foot position (3,) [m] in the leg frame for joint angles q_rad (3,)."""
    q1, q2, q3 = q_rad[0], q_rad[1], q_rad[2]
    l1, l2, l3 = HIP_OFFSET_M, THIGH_LENGTH_M, CALF_LENGTH_M
    s1, c1 = jnp.sin(q1), jnp.cos(q1)
    s2, c2 = jnp.sin(q2), jnp.cos(q2)
    s23, c23 = jnp.sin(q2 + q3), jnp.cos(q2 + q3)
    reach = l2 * c2 + l3 * c23  # length of the sagittal leg projected on the leg plane's -z axis
    return jnp.stack(
        [
            -l3 * s23 - l2 * s2,
            side * l1 * c1 + s1 * reach,
            side * l1 * s1 - c1 * reach,
        ]
    )


# d(foot position)/dq (3, 3) in the leg frame, rows x, y, z, columns q1, q2, q3: JAX's forward-mode derivative of
# leg_fk. A hand-written Jacobian cost the same inside the vmapped controller step (0.96–1.03×, batches 1–64,
# benchmarks/derivatives.py), so the derivative is the one of the function it differentiates.
leg_jacobian = jax.jacfwd(leg_fk)


def leg_ik(foot_m: jax.Array, side: jax.Array) -> jax.Array:
    """Joint angles (3,) [rad] placing the foot at foot_m (3,) in the leg frame (knee-backward branch, q3 < 0).

    Targets outside the workspace are projected onto it (the knee cosine is clipped to [-1, 1]).
    """
    x, y, z = foot_m[0], foot_m[1], foot_m[2]
    l1, l2, l3 = HIP_OFFSET_M, THIGH_LENGTH_M, CALF_LENGTH_M
    cos_knee = jnp.clip((x * x + y * y + z * z - l1 * l1 - l2 * l2 - l3 * l3) / (2.0 * l2 * l3), -1.0, 1.0)
    q3 = jnp.arctan2(-jnp.sqrt(1.0 - cos_knee * cos_knee), cos_knee)
    leg_plane = jnp.sqrt(jnp.maximum(y * y + z * z - l1 * l1, 0.0))
    q1 = jnp.arctan2(z, y) + jnp.arctan2(leg_plane, side * l1)
    q2 = jnp.arctan2(-x, leg_plane) - jnp.arctan2(l3 * jnp.sin(q3), l2 + l3 * jnp.cos(q3))
    q1 = jnp.arctan2(jnp.sin(q1), jnp.cos(q1))  # wrap to (-pi, pi]
    return jnp.stack([q1, q2, q3])


legs_fk = jax.vmap(leg_fk)  # (4, 3), (4,) -> (4, 3)
legs_jacobian = jax.vmap(leg_jacobian)  # (4, 3), (4,) -> (4, 3, 3)
legs_ik = jax.vmap(leg_ik)  # (4, 3), (4,) -> (4, 3)
