"""The controller the robot runs: ``cpg.controller_step`` on one flat float32 vector, compiled ahead of time.

:class:`CompiledController` is the jitted step of the simulator (≈11 µs per call on this CPU) plus the robot-side
trial signals (leg-odometry velocity, power, load) in one flat output; :func:`pack_observation` writes a LowState's
observation (SI units, foot forces through the calibration) into the flat input.
"""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import attitude, kinematics
from cpgjax.go1.constants import TORQUE_LIMIT_NM
from cpgjax.robot import cpu_dispatch
from cpgjax.robot import protocol as proto
from cpgjax.robot.foot_force import FootForceCalibration
from cpgjax.trial import protocol

log = logging.getLogger(__name__)

OBS_SIZE = 35  # q 12 | dq 12 | quat 4 | gyro 3 | foot force 4
IN_SIZE = OBS_SIZE + 8 + 2 + 9  # obs | params 8 | gates 2 | CPG state (amplitude 4, phase 4, heading 1)
# Output layout (float32): torque | CPG state | rpy | stance | odometry velocity (v_x, v_y) | power ⟨|τ|, |q̇|⟩ [W] |
# mean foot force [N] | number of torques clipped to the motor limits | the guarded torque | 1 if every torque is
# finite (the guard of a torque command, ``safety.guard_command``, in the same compiled call: one dispatch a tick).
OUT_TORQUE, OUT_STATE, OUT_RPY, OUT_STANCE = slice(0, 12), slice(12, 21), slice(21, 24), slice(24, 28)
OUT_VELOCITY, OUT_POWER, OUT_LOAD, OUT_SATURATED = slice(28, 30), 30, 31, 32
OUT_GUARDED, OUT_FINITE = slice(33, 45), 45
OUT_SIZE = 46


def leg_odometry_velocity(obs: cpg.Observation, stance: jax.Array) -> jax.Array:
    """Trunk velocity (v_x, v_y) [m/s] in the heading (yaw-only, gravity-aligned) frame from the stance legs'
    kinematics: v_body = −(J(q) q̇ + ω × p_foot), averaged over stance legs (zero when none is in stance)."""
    q = obs.joint_pos_rad.reshape(4, 3)
    dq = obs.joint_vel_rad_s.reshape(4, 3)
    jac = kinematics.legs_jacobian(q, kinematics.SIDE_SIGN)
    foot_rel = jnp.einsum("lij,lj->li", jac, dq)
    p_foot = kinematics.legs_fk(q, kinematics.SIDE_SIGN) + jnp.asarray(kinematics.HIP_POS_M, q.dtype)
    v_legs = -(foot_rel + jnp.cross(obs.gyro_rad_s, p_foot))
    v_body = jnp.sum(stance[:, None] * v_legs, axis=0) / jnp.maximum(jnp.sum(stance), 1.0)
    v_world = attitude.quat_to_matrix(obs.imu_quat_wxyz) @ v_body
    return attitude.to_heading_frame(v_world, attitude.quat_to_rpy(obs.imu_quat_wxyz)[2])


def unpack_observation(x: jax.Array) -> cpg.Observation:
    return cpg.Observation(x[0:12], x[12:24], x[24:28], x[28:31], x[31:35])


def flat_step(config: cpg.CPGConfig, x: jax.Array) -> jax.Array:
    """``cpg.controller_step`` on one flat input vector (IN_SIZE,) → one flat output vector (OUT_SIZE,)."""
    obs = unpack_observation(x)
    params = x[OBS_SIZE:OBS_SIZE + 8]
    gates = cpg.Gates(x[OBS_SIZE + 8], x[OBS_SIZE + 9])
    s = x[OBS_SIZE + 10:]
    state, torque, diag = cpg.controller_step(config, cpg.CPGState(s[0:4], s[4:8], s[8]), params, gates, obs)
    velocity = leg_odometry_velocity(obs, diag.stance)
    pre = protocol.pre_step(obs, torque, diag, obs.joint_vel_rad_s)  # the trial's per-tick power, load, clipping
    guarded = jnp.clip(torque, -TORQUE_LIMIT_NM, TORQUE_LIMIT_NM)
    finite = jnp.all(jnp.isfinite(torque)).astype(torque.dtype)
    return jnp.concatenate([torque, state.amplitude, state.phase_rad, state.heading_ref_rad[None], diag.rpy_rad,
                            diag.stance, velocity, pre.power_w[None], pre.load_n[None], pre.saturated[None], guarded,
                            finite[None]])


def flat_initial_state(x_obs: jax.Array) -> jax.Array:
    """``cpg.init_state`` for the observation x_obs (OBS_SIZE,), as the flat CPG-state slice (9,)."""
    s = cpg.init_state(unpack_observation(x_obs))
    return jnp.concatenate([s.amplitude, s.phase_rad, s.heading_ref_rad[None]])


class CompiledController:
    """The controller step compiled ahead of time (``jit(...).lower(...).compile()``) and warmed up.

    ``step(x)`` takes the flat float32 input (IN_SIZE,) and returns the flat output (OUT_SIZE,) as NumPy;
    ``initial_state(x_obs)`` gives the CPG-state slice to start from.
    """

    def __init__(self, config: cpg.CPGConfig = cpg.CPGConfig(), warmup_calls: int = 200):
        self.inline_dispatch = cpu_dispatch.request_inline()
        if not self.inline_dispatch:
            log.warning("JAX's CPU client was created with asynchronous dispatch before the controller: each step "
                        "runs on an XLA worker thread at normal priority while the loop thread waits for it. Call "
                        "cpgjax.robot.cpu_dispatch.request_inline() at program start, before any JAX computation.")
        self.config = config
        x = np.zeros(IN_SIZE, np.float32)
        x[24] = 1.0  # identity quaternion
        self._step = jax.jit(lambda v: flat_step(config, v)).lower(x).compile()
        self._init = jax.jit(flat_initial_state).lower(x[:OBS_SIZE]).compile()
        for _ in range(warmup_calls):
            self.step(x)
        self.initial_state(x[:OBS_SIZE])

    def step(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self._step(x))

    def initial_state(self, x_obs: np.ndarray) -> np.ndarray:
        return np.asarray(self._init(x_obs))


def pack_observation(state: proto.RobotState, calibration: FootForceCalibration, out: np.ndarray) -> None:
    """Write the controller's observation (SI units) from a LowState into out[:OBS_SIZE]."""
    out[0:12] = state.q_rad
    out[12:24] = state.dq_rad_s
    out[24:28] = state.quaternion_wxyz
    out[28:31] = state.gyro_rad_s
    out[31:35] = calibration.to_newtons(state.foot_force_raw)
