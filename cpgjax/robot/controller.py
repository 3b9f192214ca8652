"""The controller the robot runs: ``cpg.controller_step`` on one flat float32 vector, compiled ahead of time.

:class:`CompiledController` is the jitted step of the simulator (≈11 µs per call on this CPU) plus the robot-side
trial signals (leg-odometry velocity, power, load) in one flat output; :func:`pack_observation` writes a LowState's
observation (SI units, foot forces through the calibration) into the flat input.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import attitude, kinematics, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.go1.constants import TORQUE_LIMIT_NM
from cpgjax.layout import FlatLayout
from cpgjax.robot import cpu_dispatch, wire
from cpgjax.robot.foot_force import FootForceCalibration
from cpgjax.trial import protocol

log = logging.getLogger(__name__)


def _zeros(*shape) -> np.ndarray:
    return np.zeros(shape, np.float32)


class ControllerInput(NamedTuple):
    """The compiled step's input, one flat float32 vector laid out by :data:`INPUT` (every field read by name)."""

    obs: sensors.Observation  # the LowState's observation in SI units (foot forces through the calibration)
    params: np.ndarray  # (8,) the CPG parameters of this tick
    gates: cpg.Gates  # the controller variant
    state: cpg.CPGState  # the CPG state carried from the last tick


class ControllerOutput(NamedTuple):
    """The compiled step's output, one flat float32 vector laid out by :data:`OUTPUT`: the controller's torque and
    state, the robot-side trial signals, and the guard of the torque command (``safety.guard_command``) in the same
    compiled call, so a tick costs one dispatch."""

    torque_nm: np.ndarray  # (12,) the controller's torque
    state: cpg.CPGState  # the CPG state for the next tick
    rpy_rad: np.ndarray  # (3,)
    stance: np.ndarray  # (4,)
    velocity_mps: np.ndarray  # (2,) leg-odometry (v_x, v_y) in the heading frame
    power_w: np.ndarray  # () ⟨|τ|, |q̇|⟩
    load_n: np.ndarray  # () mean foot force
    saturated: np.ndarray  # () number of torques clipped to the motor limits
    guarded_torque_nm: np.ndarray  # (12,) the torque clipped to the motor limits
    finite: np.ndarray  # () 1 if every torque is finite


OBSERVATION = FlatLayout(sensors.Observation(_zeros(12), _zeros(12), _zeros(4), _zeros(3), _zeros(4)))
STATE = FlatLayout(cpg.CPGState(_zeros(4), _zeros(4), _zeros(), _zeros(), _zeros()))
GATES = FlatLayout(cpg.Gates(_zeros(), _zeros(), _zeros(4, 4)))
INPUT = FlatLayout(
    ControllerInput(
        OBSERVATION.unravel(OBSERVATION.zeros()), _zeros(8), GATES.unravel(GATES.zeros()), STATE.unravel(STATE.zeros())
    )
)
OUTPUT = FlatLayout(
    ControllerOutput(
        _zeros(12),
        STATE.unravel(STATE.zeros()),
        _zeros(3),
        _zeros(4),
        _zeros(2),
        _zeros(),
        _zeros(),
        _zeros(),
        _zeros(12),
        _zeros(),
    )
)


def leg_odometry_velocity(obs: sensors.Observation, stance: jax.Array) -> jax.Array:
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


def flat_step(config: cpg.CPGConfig, x: jax.Array) -> jax.Array:
    """``cpg.controller_step`` on one flat input vector (:data:`INPUT`) → one flat output vector (:data:`OUTPUT`)."""
    inputs = INPUT.unravel(x)
    obs = inputs.obs
    state, torque, diag = cpg.controller_step(config, inputs.state, inputs.params, inputs.gates, obs)
    pre = protocol.pre_step(obs, torque, diag, obs.joint_vel_rad_s)  # the trial's per-tick power, load, clipping
    return OUTPUT.ravel(
        ControllerOutput(
            torque_nm=torque,
            state=state,
            rpy_rad=diag.rpy_rad,
            stance=diag.stance,
            velocity_mps=leg_odometry_velocity(obs, diag.stance),
            power_w=pre.power_w,
            load_n=pre.load_n,
            saturated=pre.saturated,
            guarded_torque_nm=jnp.clip(torque, -TORQUE_LIMIT_NM, TORQUE_LIMIT_NM),
            finite=jnp.all(jnp.isfinite(torque)).astype(torque.dtype),
        )
    )


def flat_initial_state(config: cpg.CPGConfig, x_obs: jax.Array, x_gates: jax.Array) -> jax.Array:
    """``cpg.init_state`` for the flat observation x_obs (:data:`OBSERVATION`) in the gait of the flat gates x_gates
    (:data:`GATES`), as the flat CPG state (:data:`STATE`, ``x[INPUT.slices.state]``)."""
    gates = GATES.unravel(x_gates)
    return STATE.ravel(cpg.init_state(OBSERVATION.unravel(x_obs), config, phase_lag_rad=gates.phase_lag_rad))


class CompiledController:
    """The controller step compiled ahead of time (``jit(...).lower(...).compile()``) and warmed up.

    ``step(x)`` takes the flat float32 input (:data:`INPUT`) and returns the flat output (:data:`OUTPUT`) as NumPy;
    ``initial_state(x_obs, x_gates)`` gives the flat CPG state (``x[INPUT.slices.state]``) to start from.
    """

    def __init__(self, config: cpg.CPGConfig = cpg.CPGConfig(), warmup_calls: int = 200):
        self.inline_dispatch = cpu_dispatch.request_inline()
        if not self.inline_dispatch:
            log.warning(
                "JAX's CPU client was created with asynchronous dispatch before the controller: each step "
                "runs on an XLA worker thread at normal priority while the loop thread waits for it. Call "
                "cpgjax.robot.cpu_dispatch.request_inline() at program start, before any JAX computation."
            )
        self.config = config
        x = INPUT.zeros()
        INPUT.unravel(x).obs.imu_quat_wxyz[0] = 1.0  # identity quaternion
        self._step = jax.jit(lambda v: flat_step(config, v)).lower(x).compile()
        self._init = (
            jax.jit(lambda v, g: flat_initial_state(config, v, g))
            .lower(x[INPUT.slices.obs], x[INPUT.slices.gates])
            .compile()
        )
        # Without the lean the standing pose is the constant one: nothing to compile.
        self._stand = (
            jax.jit(lambda q: cpg.standing_pose_rad(config, q)).lower(np.float32([1, 0, 0, 0])).compile()
            if config.start_lean
            else None
        )
        for _ in range(warmup_calls):
            self.step(x)
        self.initial_state(x[INPUT.slices.obs], x[INPUT.slices.gates])
        self.standing_pose_rad(np.array([1.0, 0.0, 0.0, 0.0]))

    def step(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self._step(x))

    def initial_state(self, x_obs: np.ndarray, x_gates: np.ndarray) -> np.ndarray:
        return np.asarray(self._init(x_obs, x_gates))

    def standing_pose_rad(self, imu_quat_wxyz: np.ndarray) -> np.ndarray:
        """The soft start's standing joint angles (12,) for the IMU's orientation (``cpg.standing_pose_rad``)."""
        if self._stand is None:
            return go1_model.standing_qpos()[go1_model.indices().joint_qpos]
        return np.asarray(self._stand(np.asarray(imu_quat_wxyz, np.float32)), np.float64)


def pack_observation(state: wire.RobotState, calibration: FootForceCalibration, obs: sensors.Observation) -> None:
    """Write the controller's observation (SI units) from a LowState into ``obs``, the named views of a flat input
    (``INPUT.unravel(x).obs``)."""
    obs.joint_pos_rad[:] = state.q_rad
    obs.joint_vel_rad_s[:] = state.dq_rad_s
    obs.imu_quat_wxyz[:] = state.quaternion_wxyz
    obs.gyro_rad_s[:] = state.gyro_rad_s
    obs.foot_force_n[:] = calibration.to_newtons(state.foot_force_raw)
