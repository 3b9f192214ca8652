"""Physics profiles: named sets of contact, joint, actuator and foot-sensor fields of the simulated Go1.

A profile is data, chosen per instance (docs/decisions.md §15; every constant and its source in docs/physics.md):

* ``soft`` — MuJoCo's default soft contact, armature 0.01, light damping, no joint friction, the foot force as the
  world-frame contact normal force at 1 kHz, measured beside the other two in docs/physics.md.
* ``paper`` — the paper's Gazebo Go1 as closely as MuJoCo allows: near-rigid foot contact, the unitree_ros Gazebo
  joint damping and Coulomb friction, no reflected rotor inertia, Gazebo's velocity limits, and the paper's foot-force
  signal: the z component of the contact force in the calf frame, published at 100 Hz as the mean over the update's
  in-contact steps (the unitree_ros foot contact plugin), and Gazebo's friction rule (the smaller μ of floor and foot).
* ``go1`` — the best estimate of the real robot: reflected rotor inertia, joint friction, the DC-motor torque-speed
  envelope, actuation latency, and the foot sensor's int16 counts of the contact normal force.

``paper`` is the default of the command line and the Python API alike (:data:`DEFAULT_PROFILE`).

Model fields (floor contact ``solref``/``solimp``, ``dof_armature``, ``dof_damping``, ``dof_frictionloss``) are
applied to the MuJoCo model of each instance (batched model leaves in MJX, one ``MjModel`` per instance in C MuJoCo);
the actuator and sensor fields are per-instance arrays (:class:`ProfileArrays`) read by :func:`measure_foot_force` and
:func:`actuate` inside the compiled tick, so one batch can mix profiles and switching one never recompiles.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax.go1 import attitude, constants
from cpgjax.layout import FlatLayout

# Largest actuation latency a profile may have [ticks]; the command queue has this many slots (static).
MAX_LATENCY_TICKS = 4
FOOT_FRAMES = ("contact", "calf")


class PhysicsProfile(NamedTuple):
    """One profile's fields (per joint type: hip, thigh, calf; the same on the four legs)."""

    floor_solref: tuple[float, float]  # (time constant [s], damping ratio) of foot-floor contact (the floor's priority)
    floor_solimp: tuple[float, float, float, float, float]  # (d0, dwidth, width [m], midpoint, power)
    armature_kg_m2: tuple[float, float, float]  # reflected rotor inertia
    damping_nm_s_rad: tuple[float, float, float]  # viscous joint damping
    frictionloss_nm: tuple[float, float, float]  # Coulomb joint friction
    velocity_limit_rad_s: tuple[float, float, float]  # Gazebo: no torque along the motion beyond it (inf: none)
    no_load_speed_rad_s: tuple[float, float, float]  # DC-motor envelope: motoring |τ| ≤ τ_stall (1 − |q̇|/ω₀)
    latency_ticks: int  # the torque applied at tick k is the command of tick k − latency
    foot_force_frame: str  # "contact": world-frame contact normal; "calf": z of the contact force in the calf frame
    foot_force_period_ticks: int  # update period of the foot force (1: every tick; 10: 100 Hz), held between updates
    # True: each update reports the mean over the ticks since the last update in which the foot touched the floor
    # (0 with no contact), as the unitree_ros foot contact plugin does; False: the force of the update tick.
    foot_force_contact_mean: bool
    # A foot touches the floor (for that mean) while its sphere is less than this above it: ODE keeps a contact
    # within its contact_surface_layer without correcting it, so a stance foot moving inside the layer stays in
    # contact there (0: only a penetrating foot, MuJoCo's contact).
    foot_contact_layer_m: float
    foot_force_n_per_count: float  # > 0: the force is reported in int16 counts of this size (0: continuous)
    context_load_range_n: tuple[float, float]  # the c_load normalization range of this signal (decisions §11)
    # The feet's own μ under Gazebo's friction rule: a contact's μ is the smaller of the two surfaces'
    # (gazebo-classic ODEPhysics::Collide), so the floor's μ counts up to the feet's; inf: MuJoCo's rule, the floor's
    # μ (it has priority). A scenario's ``foot_friction`` replaces it (:func:`contact_friction`).
    foot_friction: float
    # Sensor noise, drawn every tick independently per reading, uniform in ± the amplitude (0: none).
    joint_pos_noise_rad: float = 0.0  # each encoder angle
    joint_vel_noise_rad_s: float = 0.0  # each joint velocity
    gyro_noise_rad_s: float = 0.0  # each gyro axis
    tilt_noise_rad: float = 0.0  # the IMU orientation, turned about the trunk's x and y axes by this much at most
    foot_force_noise_n: float = 0.0  # each foot force, before it is counted
    # Physics steps per 1 ms control tick, the tick's torques held (the model's timestep is 1 ms / this); the
    # native backend and the loopback Go1 (not MJX), one value per batch.
    physics_substeps: int = 1


_MUJOCO_DEFAULT_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)  # MuJoCo XML reference, geom/solimp default

PROFILES: dict[str, PhysicsProfile] = {
    "soft": PhysicsProfile(
        floor_solref=(0.02, 1.0),  # MuJoCo's default (XML reference, geom/solref)
        floor_solimp=_MUJOCO_DEFAULT_SOLIMP,
        armature_kg_m2=(0.01, 0.01, 0.01),
        damping_nm_s_rad=(0.05, 0.05, 0.05),
        frictionloss_nm=(0.0, 0.0, 0.0),
        velocity_limit_rad_s=(np.inf,) * 3,
        no_load_speed_rad_s=(np.inf,) * 3,
        latency_ticks=0,
        foot_force_frame="contact",
        foot_force_period_ticks=1,
        foot_force_contact_mean=False,
        foot_contact_layer_m=0.0,
        foot_force_n_per_count=0.0,
        context_load_range_n=(15.0, 75.0),  # the world-frame normal reads ≈ 31 N standing: the widened range
        foot_friction=np.inf,
    ),
    "paper": PhysicsProfile(
        # The stiffest reference MuJoCo integrates stably: time constant 2 Δt (MuJoCo clamps smaller ones to 2 Δt,
        # XML reference, flag/refsafe), critically damped; impedance near 1 so the force follows it (near-rigid,
        # like the unitree_ros Gazebo foot contact kp 1e6, kd 1).
        floor_solref=(0.002, 1.0),
        floor_solimp=(0.99, 0.999, 0.001, 0.5, 2.0),
        armature_kg_m2=(0.0, 0.0, 0.0),  # Gazebo models no rotor
        damping_nm_s_rad=(0.01, 0.01, 0.01),
        frictionloss_nm=(0.2, 0.2, 0.2),  # unitree_ros go1_description
        velocity_limit_rad_s=(30.1, 30.1, 20.06),  # URDF joint velocity limits, applied as Gazebo does
        no_load_speed_rad_s=(np.inf,) * 3,
        latency_ticks=0,
        # unitree_ros foot contact plugin: 100 Hz, the mean over the update's in-contact physics steps
        foot_force_frame="calf",
        foot_force_period_ticks=10,
        foot_force_contact_mean=True,
        foot_contact_layer_m=0.001,  # unitree_gazebo earth.world: contact_surface_layer 0.001
        foot_force_n_per_count=0.0,
        context_load_range_n=(15.0, 55.0),  # the paper's range
        foot_friction=0.6,
    ),  # unitree_ros go1_description gazebo.xacro: the feet's mu1 = mu2 = 0.6
    "go1": PhysicsProfile(
        floor_solref=(0.02, 1.0),
        floor_solimp=_MUJOCO_DEFAULT_SOLIMP,  # no measured foot contact: MuJoCo's default
        # Rotor inertia 0.000111842 kg·m² (unitree_ros go1.urdf) × gear ratio² (6 hip and thigh, 9 knee: mjlab's Go1).
        armature_kg_m2=(0.000111842 * 6.0**2, 0.000111842 * 6.0**2, 0.000111842 * 9.0**2),
        damping_nm_s_rad=(0.01, 0.01, 0.01),
        frictionloss_nm=(0.2, 0.2, 0.2),  # unitree_ros go1_description
        velocity_limit_rad_s=(np.inf,) * 3,
        no_load_speed_rad_s=(30.1, 30.1, 20.06),  # URDF velocity limits as the no-load speed of the envelope
        latency_ticks=2,  # SDK UDP round trip + motor driver, 1-2 ms: the upper end
        # The foot pad's pressure sensor, calibrated on the robot so that the four feet carry its weight standing
        # (docs/decisions.md §3): the contact normal force, in counts of the loopback simulated Go1's scale.
        foot_force_frame="contact",
        foot_force_period_ticks=1,
        foot_force_contact_mean=False,
        foot_contact_layer_m=0.0,
        foot_force_n_per_count=0.5,  # cpgjax.robot.sim_server.FOOT_FORCE_N_PER_COUNT
        context_load_range_n=(15.0, 75.0),  # a weight-calibrated signal: ≈ 31 N standing, ≈ 68 N with 15 kg
        foot_friction=np.inf,  # MuJoCo's rule: the floor's μ
        # legged_gym's LeggedRobotCfg.noise.noise_scales (dof_pos, dof_vel, ang_vel, gravity), the proprioceptive
        # noise walk-these-ways uses for the Go1; no public Go1 foot-sensor noise figure: ±1 count, ours
        # (docs/physics.md).
        joint_pos_noise_rad=0.01,
        joint_vel_noise_rad_s=1.5,
        gyro_noise_rad_s=0.2,
        tilt_noise_rad=0.05,
        foot_force_noise_n=0.5,
    ),
}
# `paper` with unitree_ros's physics rate: earth.world steps ODE every 0.2 ms (max_step_size 0.0002, commit 7325aa5
# of 2022-02-09 to this day) where `paper` steps every 1 ms; the one-change run of the step (docs/physics.md).
PROFILES["paper_5khz"] = PROFILES["paper"]._replace(physics_substeps=5)
# What every command and the Python API simulate when none is named: the paper's simulator (docs/decisions.md §15).
DEFAULT_PROFILE = "paper"
ROBOT_PROFILE = "go1"  # the loopback simulated Go1 (cpgjax deploy --robot sim)


def get(name: str) -> PhysicsProfile:
    """The profile called ``name``.

    Raises:
      ValueError: an unknown name (the message lists the known ones).
    """
    if name not in PROFILES:
        raise ValueError(f"unknown physics profile {name!r}; allowed: {tuple(PROFILES)}")
    return PROFILES[name]


def _per_joint(values) -> np.ndarray:
    return np.tile(np.asarray(values, np.float64), len(constants.LEG_NAMES))


# ----------------------------------------------------------------------------------------------- model fields


def model_fields(profile: PhysicsProfile, floor_geom: int, joint_dof: np.ndarray, model: mujoco.MjModel) -> dict:
    """The profile's values of the MuJoCo model fields it sets (full arrays, shaped like ``model``'s)."""
    solref, solimp = np.array(model.geom_solref), np.array(model.geom_solimp)
    solref[floor_geom], solimp[floor_geom] = profile.floor_solref, profile.floor_solimp
    fields = {"geom_solref": solref, "geom_solimp": solimp}
    for name, values in (
        ("dof_armature", profile.armature_kg_m2),
        ("dof_damping", profile.damping_nm_s_rad),
        ("dof_frictionloss", profile.frictionloss_nm),
    ):
        array = np.array(getattr(model, name))
        array[joint_dof] = _per_joint(values)
        fields[name] = array
    return fields


def feet_friction(profile: PhysicsProfile, foot_friction):
    """The feet's μ: a scenario's ``foot_friction``, or where it is −1 the profile's own (inf: the feet have none, and
    the floor's μ holds)."""
    foot = np.asarray(foot_friction, np.float64)
    return np.where(foot < 0.0, profile.foot_friction, foot)


def contact_friction(profile: PhysicsProfile, friction, foot_friction=-1.0):
    """The sliding μ of a foot-floor contact on a floor of μ ``friction``: the smaller of the floor's and the feet's
    (:func:`feet_friction`; Gazebo's rule, the paper's simulator), which is the floor's where the feet have none."""
    return np.minimum(np.asarray(friction, np.float64), feet_friction(profile, foot_friction))


def apply_to_model(model: mujoco.MjModel, profile: PhysicsProfile, floor_geom: int, joint_dof: np.ndarray) -> None:
    """Write the profile's model fields into a C-MuJoCo model (in place)."""
    for name, value in model_fields(profile, floor_geom, joint_dof, model).items():
        getattr(model, name)[:] = value


# ----------------------------------------------------------------------------------------------- per-tick arrays


class NoisyReadings(NamedTuple):
    """The sensor readings that carry noise, by name: per reading its noise amplitude (a profile's, shape ()) or one
    tick's uniform draws (:func:`noise_draws`, one per axis)."""

    joint_pos: jax.Array  # [rad]; draws (12,)
    joint_vel: jax.Array  # [rad/s]; draws (12,)
    gyro: jax.Array  # [rad/s]; draws (3,)
    tilt: jax.Array  # [rad] the IMU's orientation about the trunk's x and y; draws (2,)
    foot_force: jax.Array  # [N]; draws (4,)


class ProfileArrays(NamedTuple):
    """The actuator and sensor fields of a profile as arrays (a leading batch axis when batched)."""

    stall_torque_nm: jax.Array  # (12,)
    no_load_speed_rad_s: jax.Array  # (12,) inf: no envelope
    velocity_limit_rad_s: jax.Array  # (12,) inf: no limit
    latency_ticks: jax.Array  # () int32
    calf_frame: jax.Array  # () bool: the calf-frame z signal, else the contact normal
    force_period_ticks: jax.Array  # () int32
    force_contact_mean: jax.Array  # () bool: each update reports the mean over its in-contact ticks
    contact_layer_m: jax.Array  # () float32: a foot touches the floor within this clearance
    force_n_per_count: jax.Array  # () float32, 0: continuous
    noise: NoisyReadings  # () float32 each, the noise amplitudes of the readings
    noise_seed: jax.Array  # () uint32, this instance's noise stream


def arrays(profile: PhysicsProfile) -> ProfileArrays:
    """One instance's :class:`ProfileArrays` (NumPy)."""
    if profile.foot_force_frame not in FOOT_FRAMES:
        raise ValueError(f"foot_force_frame {profile.foot_force_frame!r}; allowed: {FOOT_FRAMES}")
    if not 0 <= profile.latency_ticks <= MAX_LATENCY_TICKS:
        raise ValueError(f"latency_ticks {profile.latency_ticks}; allowed: 0 … {MAX_LATENCY_TICKS}")
    if profile.foot_force_period_ticks < 1:
        raise ValueError(f"foot_force_period_ticks {profile.foot_force_period_ticks}; allowed: ≥ 1")
    return ProfileArrays(
        stall_torque_nm=np.asarray(constants.TORQUE_LIMIT_NM, np.float32),
        no_load_speed_rad_s=_per_joint(profile.no_load_speed_rad_s).astype(np.float32),
        velocity_limit_rad_s=_per_joint(profile.velocity_limit_rad_s).astype(np.float32),
        latency_ticks=np.int32(profile.latency_ticks),
        calf_frame=np.bool_(profile.foot_force_frame == "calf"),
        force_period_ticks=np.int32(profile.foot_force_period_ticks),
        force_contact_mean=np.bool_(profile.foot_force_contact_mean),
        contact_layer_m=np.float32(profile.foot_contact_layer_m),
        force_n_per_count=np.float32(profile.foot_force_n_per_count),
        noise=NoisyReadings(
            *(
                np.float32(a)
                for a in (
                    profile.joint_pos_noise_rad,
                    profile.joint_vel_noise_rad_s,
                    profile.gyro_noise_rad_s,
                    profile.tilt_noise_rad,
                    profile.foot_force_noise_n,
                )
            )
        ),
        noise_seed=np.uint32(0),
    )


def batch_arrays(names, latency_ticks=None, noise_scale=None, noise_seed=None) -> ProfileArrays:
    """:class:`ProfileArrays` with a leading batch axis, one row per profile name. Per row (domain
    randomization): ``latency_ticks`` (−1: the profile's own) replaces the profile's latency, ``noise_scale`` (−1:
    the profile's own) replaces its sensor noise by that multiple of the robot's (ROBOT_PROFILE's), and
    ``noise_seed`` chooses the instance's noise stream."""
    rows = [arrays(get(str(n))) for n in names]
    batch = jax.tree.map(lambda *field: np.stack(field), *rows)
    if latency_ticks is not None:
        override = np.asarray(latency_ticks, np.int32)
        batch = batch._replace(latency_ticks=np.where(override >= 0, override, batch.latency_ticks).astype(np.int32))
    if noise_scale is not None:
        scale = np.asarray(noise_scale, np.float32)
        batch = batch._replace(
            noise=jax.tree.map(
                lambda robot, own: np.where(scale >= 0, scale * robot, own).astype(np.float32),
                arrays(get(ROBOT_PROFILE)).noise,
                batch.noise,
            )
        )
    if noise_seed is not None:
        batch = batch._replace(noise_seed=np.asarray(noise_seed, np.uint32))
    return batch


# ----------------------------------------------------------------------------------------------- sensor and motors


class ActuatorSensorState(NamedTuple):
    """What the profile's sensor and motors remember between ticks (per instance)."""

    held_force_n: jax.Array  # (4,) the foot force of the last update
    force_sum_n: jax.Array  # (4,) the sum of the in-contact ticks' forces since the last update
    contact_ticks: jax.Array  # (4,) float32, the in-contact ticks since the last update
    commands_nm: jax.Array  # (MAX_LATENCY_TICKS + 1, 12) the last commands, newest first
    tick: jax.Array  # () int32 ticks since the reset


def calf_rotations(qpos: jax.Array, root_qpos: int, joint_qpos: np.ndarray) -> jax.Array:
    """Calf-body rotation matrices (4, 3, 3), calf frame → floor frame, from qpos: trunk ⊗ Rx(hip) ⊗ Ry(thigh + knee)
    (the model's body frames carry no rotation of their own)."""
    trunk = attitude.quat_to_matrix(qpos[root_qpos + 3 : root_qpos + 7])
    q = qpos[joint_qpos].reshape(4, 3)
    c1, s1 = jnp.cos(q[:, 0]), jnp.sin(q[:, 0])
    c23, s23 = jnp.cos(q[:, 1] + q[:, 2]), jnp.sin(q[:, 1] + q[:, 2])
    one, zero = jnp.ones_like(c1), jnp.zeros_like(c1)
    rx = jnp.stack(
        [jnp.stack([one, zero, zero], -1), jnp.stack([zero, c1, -s1], -1), jnp.stack([zero, s1, c1], -1)], -2
    )
    ry = jnp.stack(
        [jnp.stack([c23, zero, s23], -1), jnp.stack([zero, one, zero], -1), jnp.stack([-s23, zero, c23], -1)], -2
    )
    return trunk @ rx @ ry


def contact_force_world(contact_data: jax.Array) -> jax.Array:
    """The force the floor exerts on a foot (..., 3) [N], floor frame, from a contact sensor slot's (force | normal |
    tangent) data (..., 9). The sensor's frame (normal, tangent, normal × tangent) points from the foot (the sensor's
    first geom) into the floor, so its force is the foot's push on the floor: the reaction is its negative."""
    force, normal, tangent = contact_data[..., 0:3], contact_data[..., 3:6], contact_data[..., 6:9]
    bitangent = jnp.cross(normal, tangent)
    return -(force[..., 0:1] * normal + force[..., 1:2] * tangent + force[..., 2:3] * bitangent)


def foot_normal_force(contact_data: jax.Array) -> jax.Array:
    """Each foot's contact normal force (4,) [N] from its contact sensor data: (4, 9), the one contact of a foot on
    the plane, or (4, K, 9), its K contact slots on a height field (empty slots zero), whose normal forces add (each
    along its own contact's normal)."""
    if contact_data.ndim == 3:
        return jnp.sum(contact_data[..., 0], axis=1)
    return contact_data[:, 0]


def foot_force_signal(
    profile: ProfileArrays, qpos: jax.Array, contact_data: jax.Array, root_qpos: int, joint_qpos: np.ndarray
) -> jax.Array:
    """The profile's instantaneous foot-force signal (4,) [N]: the contact normal force, or the z component of the
    contact force in the calf frame (noise-free, continuous). ``contact_data`` as :func:`foot_normal_force` takes
    it; with several contacts per foot the normal forces add, and the calf-frame force is that of the sum of the
    contacts' floor-frame forces."""
    normal = foot_normal_force(contact_data)
    rotations = calf_rotations(qpos, root_qpos, joint_qpos)
    world = contact_force_world(contact_data)
    if contact_data.ndim == 3:
        world = jnp.sum(world, axis=1)
    calf = jnp.einsum("lji,lj->li", rotations, world)[:, 2]
    return jnp.where(profile.calf_frame, calf, normal)


def count(profile: ProfileArrays, force_n: jax.Array) -> jax.Array:
    """The force as the sensor reports it: rounded to its counts when it has them [N]."""
    step = profile.force_n_per_count
    return jnp.where(step > 0, jnp.round(force_n / jnp.where(step > 0, step, 1.0)) * step, force_n)


NOISE_DRAWS = FlatLayout(NoisyReadings(np.zeros(12), np.zeros(12), np.zeros(3), np.zeros(2), np.zeros(4)))
NUM_NOISY_READINGS = NOISE_DRAWS.size


_GOLDEN_GAMMA = np.uint32(0x9E3779B9)  # SplitMix's increment: 2³² / golden ratio


def _fmix32(x: jax.Array) -> jax.Array:
    """MurmurHash3's 32-bit finalizer (the output function of SplitMix32): a bijection of uint32 that mixes every
    input bit into every output bit."""
    x = (x ^ (x >> 16)) * np.uint32(0x85EBCA6B)
    x = (x ^ (x >> 13)) * np.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def noise_draws(profile: ProfileArrays, tick: jax.Array) -> NoisyReadings:
    """Uniform draws in [−1, 1), one per noisy reading (:data:`NOISE_DRAWS`), for one tick of one instance: a pure
    function of the instance's noise seed and the tick, so a run and its resume see the same noise.

    A counter-based SplitMix32 stream (the state for (seed, tick), advanced by the golden gamma per reading, each
    output finalized by ``_fmix32``), not ``jax.random``: in the vmapped 1 kHz tick, threefry made the batch-20
    control tick 3.4–4.3× slower (``benchmarks/control_tick.py``), and sensor noise needs equidistributed,
    uncorrelated draws, not a cryptographic generator (tests/go1/test_physics.py checks their moments and correlations).
    """
    seed = jnp.asarray(profile.noise_seed, jnp.uint32)
    state = _fmix32(_fmix32(seed + _GOLDEN_GAMMA) ^ jnp.asarray(tick).astype(jnp.uint32))
    counter = state + _GOLDEN_GAMMA * jnp.arange(1, NUM_NOISY_READINGS + 1, dtype=jnp.uint32)
    return NOISE_DRAWS.unravel((_fmix32(counter) >> 8).astype(jnp.float32) * np.float32(2.0**-23) - 1.0)


def init_state(force_n: jax.Array) -> ActuatorSensorState:
    """At a reset: the sensor holds the force of the reset state, the command queue is empty."""
    return ActuatorSensorState(
        held_force_n=jnp.asarray(force_n, jnp.float32),
        force_sum_n=jnp.zeros(4, jnp.float32),
        contact_ticks=jnp.zeros(4, jnp.float32),
        commands_nm=jnp.zeros((MAX_LATENCY_TICKS + 1, constants.NUM_JOINTS), jnp.float32),
        tick=jnp.zeros((), jnp.int32),
    )


def touching(profile: ProfileArrays, foot_clearance_m: jax.Array) -> jax.Array:
    """(4,) bool: each foot within the profile's contact layer of the floor (clearance of the foot sphere [m],
    negative when it penetrates)."""
    return foot_clearance_m < profile.contact_layer_m


def foot_sensor_update(
    profile: ProfileArrays, state: ActuatorSensorState, force_n: jax.Array, contact: jax.Array
) -> tuple[ActuatorSensorState, jax.Array]:
    """The force the controller reads at this tick (4,) [N], updated every ``force_period_ticks`` ticks and held
    between updates.

    An update reports the force of its own tick, or, with ``force_contact_mean``, the mean over the ticks since the
    previous update (this one included) in which the foot was in ``contact`` (:func:`touching`), and 0 when it never
    was: the unitree_ros foot contact plugin averages the contact entries collected since its last 100 Hz update.
    """
    touching = contact.astype(jnp.float32)
    sums = state.force_sum_n + touching * force_n
    ticks = state.contact_ticks + touching
    update = state.tick % profile.force_period_ticks == 0
    mean = jnp.where(ticks > 0, sums / jnp.maximum(ticks, 1.0), 0.0)
    held = jnp.where(update, jnp.where(profile.force_contact_mean, mean, force_n), state.held_force_n)
    return state._replace(
        held_force_n=held, force_sum_n=jnp.where(update, 0.0, sums), contact_ticks=jnp.where(update, 0.0, ticks)
    ), held


def actuate(
    profile: ProfileArrays, state: ActuatorSensorState, command_nm: jax.Array, joint_vel_rad_s: jax.Array
) -> tuple[ActuatorSensorState, jax.Array]:
    """The torque the motors apply this tick (12,) [N·m] for the controller's command, and the next state.

    The command of ``latency_ticks`` ticks ago, limited by the DC-motor envelope (when motoring, |τ| ≤
    τ_stall (1 − |q̇|/ω₀); braking up to τ_stall) and by Gazebo's velocity limit (no torque in the direction of
    motion beyond it, gazebo-classic ``Joint::CheckAndTruncateForce``).
    """
    commands = jnp.concatenate([command_nm[None].astype(jnp.float32), state.commands_nm[:-1]])
    torque = commands[profile.latency_ticks]
    motoring = torque * joint_vel_rad_s > 0
    envelope = profile.stall_torque_nm * jnp.clip(
        1.0 - jnp.abs(joint_vel_rad_s) / profile.no_load_speed_rad_s, 0.0, 1.0
    )
    limit = jnp.where(motoring, envelope, profile.stall_torque_nm)
    torque = jnp.clip(torque, -limit, limit)
    beyond = (jnp.abs(joint_vel_rad_s) > profile.velocity_limit_rad_s) & motoring
    torque = jnp.where(beyond, 0.0, torque)
    return state._replace(commands_nm=commands, tick=state.tick + 1), torque
