"""The Go1's sensor model: what the robot's sensors report, computed from a simulator state.

One definition for every simulator (MJX, C MuJoCo, the loopback simulated Go1): the controller's observation as the
Go1's ``LowState`` reports it in SI units, and the simulator-side quantities the trial records (velocity in the heading
frame, foot positions).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from cpgjax.go1 import attitude, kinematics
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles


class Observation(NamedTuple):
    """Exactly what the Go1 reports each tick (LowState), in SI units; motor order FR, FL, RR, RL × (hip, thigh,
    calf)."""

    joint_pos_rad: jax.Array  # (12,)
    joint_vel_rad_s: jax.Array  # (12,)
    imu_quat_wxyz: jax.Array  # (4,) trunk orientation relative to gravity (IMU frame = trunk frame)
    gyro_rad_s: jax.Array  # (3,) trunk angular velocity in the trunk frame
    foot_force_n: jax.Array  # (4,) foot normal forces [N]


def observe(qpos: jax.Array, qvel: jax.Array, sensordata: jax.Array, gravity: jax.Array) -> Observation:
    """The controller's observation computed as the Go1's sensors would report it.

    IMU orientation relative to gravity (so a slope reads as pitch, docs/decisions.md §4), gyro in the trunk frame,
    joint encoders, and each foot's contact normal force [N], summed over its contacts on a height field
    (``physics.foot_normal_force``). Works on MJX and C-MuJoCo arrays alike, of the flat or the terrain model.
    """
    ids = go1_model.indices()
    r = ids.root_qpos
    quat_floor = qpos[r + 3 : r + 7]
    return Observation(
        joint_pos_rad=qpos[ids.joint_qpos],
        joint_vel_rad_s=qvel[ids.joint_dof],
        imu_quat_wxyz=attitude.quat_mul(attitude.gravity_frame_quat(gravity), quat_floor),
        gyro_rad_s=qvel[ids.root_dof + 3 : ids.root_dof + 6],
        foot_force_n=foot_normal_force_n(sensordata),
    )


def foot_normal_force_n(sensordata: jax.Array) -> jax.Array:
    """Each foot's contact normal force (4,) [N] from the sensor data of the flat model (its one contact) or of the
    terrain model (its contacts summed, ``physics.foot_normal_force``)."""
    slots = go1_model.foot_contact_slots(sensordata.shape[-1])
    if slots.ndim == 2:
        return sensordata[go1_model.indices().foot_force_sensor]
    return physics_profiles.foot_normal_force(sensordata[slots])


def measure(
    profile: physics_profiles.ProfileArrays,
    io: physics_profiles.ActuatorSensorState,
    qpos: jax.Array,
    qvel: jax.Array,
    sensordata: jax.Array,
    gravity: jax.Array,
) -> tuple[physics_profiles.ActuatorSensorState, Observation]:
    """The observation under a physics profile: :func:`observe` with the profile's foot-force signal (contact normal
    or calf-frame z), its sensor noise (uniform, drawn every tick), the force counted when the sensor counts, and
    updated and held at the profile's rate (``physics_profiles.foot_sensor_update``). On a height field a foot counts
    as in contact for the profile's mean while it has a contact force (its contact layer is the plane's only)."""
    ids = go1_model.indices()
    obs = observe(qpos, qvel, sensordata, gravity)
    u = physics_profiles.noise_draws(profile, io.tick)
    amplitude = profile.noise
    contact_data = sensordata[go1_model.foot_contact_slots(sensordata.shape[-1])]
    signal = physics_profiles.foot_force_signal(profile, qpos, contact_data, ids.root_qpos, ids.joint_qpos)
    on_plane = contact_data.ndim == 2
    if on_plane:
        clearance = foot_positions(qpos)[:, 2] - go1_model.FOOT_RADIUS_M
    force = physics_profiles.count(profile, signal + amplitude.foot_force * u.foot_force)
    # On a height field a foot touches while it has a contact force (the profile's contact layer is the plane's).
    touching = physics_profiles.touching(profile, clearance) if on_plane else obs.foot_force_n > 0.0
    io, held = physics_profiles.foot_sensor_update(profile, io, force, touching)
    # The IMU's orientation turned in the trunk frame about x and y by the tilt noise (rotation vector → quaternion;
    # sin(θ/2)/θ = sinc(θ/2π)/2 is finite at θ = 0).
    turn = amplitude.tilt * jnp.concatenate([u.tilt, jnp.zeros(1, u.tilt.dtype)])
    angle = jnp.linalg.norm(turn)
    tilt = jnp.concatenate([jnp.cos(angle / 2)[None], 0.5 * jnp.sinc(angle / (2 * jnp.pi)) * turn])
    return io, obs._replace(
        joint_pos_rad=obs.joint_pos_rad + amplitude.joint_pos * u.joint_pos,
        joint_vel_rad_s=obs.joint_vel_rad_s + amplitude.joint_vel * u.joint_vel,
        imu_quat_wxyz=attitude.quat_mul(obs.imu_quat_wxyz, tilt.astype(obs.imu_quat_wxyz.dtype)),
        gyro_rad_s=obs.gyro_rad_s + amplitude.gyro * u.gyro,
        foot_force_n=held,
    )


def heading_velocity(qpos: jax.Array, qvel: jax.Array) -> jax.Array:
    """Trunk linear velocity (v_x, v_y) [m/s] in the heading (yaw-only) frame on the floor (docs/decisions.md §9)."""
    ids = go1_model.indices()
    yaw = attitude.quat_to_rpy(qpos[ids.root_qpos + 3 : ids.root_qpos + 7])[2]
    return attitude.to_heading_frame(qvel[ids.root_dof : ids.root_dof + 2], yaw)


def foot_positions(qpos: jax.Array) -> jax.Array:
    """Foot-sphere centres (4, 3) [m] in the floor frame from qpos (the model's leg geometry is ``kinematics``)."""
    ids = go1_model.indices()
    r = ids.root_qpos
    legs = kinematics.legs_fk(qpos[ids.joint_qpos].reshape(4, 3), jnp.asarray(kinematics.SIDE_SIGN, qpos.dtype))
    return qpos[r : r + 3] + attitude.quat_rotate(
        qpos[r + 3 : r + 7], jnp.asarray(kinematics.HIP_POS_M, qpos.dtype) + legs
    )
