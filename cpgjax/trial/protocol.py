"""The paper's trial, one protocol for every backend and for the robot (paper Sec. "Implementation Details").

A trial continues from the current state: ``transition_steps`` ticks (1.5 s) during which the parameters are
interpolated linearly from the previous set to the new one (:func:`transition_params`), then ``steady_steps`` ticks
(T = 3 s at 1 kHz) whose per-tick rows (:class:`Tick`: heading-frame velocity, power ⟨|τ|, |q̇|⟩, mean foot force,
roll, pitch, clipped torques, fall, failure) are summarized into a :class:`TrialRecord` by :func:`summarize`; J, CoT
and the context come from it (``cpgjax.trial.objective``). Trials run back to back; after a fall the instance is
reset to standing (docs/decisions.md §8).

Here live the backend-neutral pieces: the timing (:class:`TrialConfig`), the blend, the per-tick sums
(:func:`pre_step` at control time, :func:`tick_row` after the physics step), the summary, the checks on parameters
and gates, and the per-tick log format of fixed-parameter rollouts (:class:`StepLog`). ``cpgjax.mjx_go1`` and
``cpgjax.sim.native`` run them in their own loops; the robot (``cpgjax.deployment.trials``) computes its per-tick row
with :func:`pre_step` in the compiled controller and summarizes with :func:`summarize`, keeping only what is really
different there: wall-clock ticks and safety.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import attitude, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1.constants import TILT_STOP_RAD
from cpgjax.trial import params as param_space


class TrialConfig(NamedTuple):
    """Trial timing, fall detection and the safety margin's scales (:func:`safety_margin`). Static: changing one
    recompiles."""

    transition_steps: int = 1500  # 1.5 s at 1 kHz
    steady_steps: int = 3000  # T
    fall_height_m: float = 0.12  # trunk origin below this height above the floor = fall
    fall_tilt_rad: float = 0.8  # |roll| or |pitch| relative to the floor beyond this = fall
    stop_tilt_rad: float = TILT_STOP_RAD  # the robot's tilt stop: IMU |roll| or |pitch| beyond this damps the motors
    standing_height_m: float = cpg.CPGConfig().body_height_m  # the trunk height the controller holds (h of eq. 5)


class TrialRecord(NamedTuple):
    """What one trial's 3 s steady phase leaves behind: enough to recompute J for any target velocity.

    Leading batch axes are allowed on every field (one record per instance, per trial, ...).
    """

    velocity_xy_mps: jax.Array  # (T, 2) trunk velocity (v_x, v_y) in the heading frame, every step
    energy_j: jax.Array  # Σ_i ⟨|τ_i|, |q̇_i|⟩ Δt, the numerator of eq. (10)
    distance_m: jax.Array  # forward distance Σ v_x Δt along the heading
    total_mass_kg: jax.Array  # robot + payload
    c_load_n: jax.Array  # eq. (11), mean foot normal force [N]
    c_slope_rad: jax.Array  # eq. (11), mean IMU pitch (nose-down positive)
    roll_mean_rad: jax.Array
    roll_std_rad: jax.Array
    pitch_std_rad: jax.Array
    saturation_fraction: jax.Array  # share of (tick, joint) torque commands clipped to the motor limit
    fell: jax.Array  # 1.0 if the trunk fell during the trial (height or tilt threshold)
    failed: jax.Array  # 1.0 if the simulation became non-finite (the instance was reset)
    safety_margin: jax.Array  # worst :func:`safety_margin` of the trial (transition and steady phase); < 0: unsafe


class Tick(NamedTuple):
    """Per-tick quantities recorded during the steady phase."""

    velocity_xy_mps: jax.Array  # (2,) heading frame
    power_w: jax.Array  # ⟨|τ|, |q̇|⟩
    load_n: jax.Array  # mean foot normal force
    roll_rad: jax.Array
    pitch_rad: jax.Array
    saturated: jax.Array  # number of clipped joint torques
    fell: jax.Array
    failed: jax.Array
    margin: jax.Array  # :func:`safety_margin` after the step; FAILED_MARGIN if the step failed


class PreStep(NamedTuple):
    """The half of a tick's record known at control time (before the physics step)."""

    power_w: jax.Array  # ⟨|τ|, |q̇|⟩
    load_n: jax.Array  # mean foot normal force
    roll_rad: jax.Array
    pitch_rad: jax.Array
    saturated: jax.Array  # number of clipped joint torques


def pre_step(obs: sensors.Observation, torque: jax.Array, diag: cpg.Diagnostics, joint_vel_rad_s: jax.Array) -> PreStep:
    """Record quantities of the state the controller saw and the torque it applied (shared by every backend).

    The power is |τ|·|q̇| with ``joint_vel_rad_s`` the joints' true velocity in a simulator (sensor noise would bias
    it upwards) and the measured one on the robot; the load is the force the controller read (the context)."""
    return PreStep(
        power_w=jnp.sum(jnp.abs(torque) * jnp.abs(joint_vel_rad_s)),
        load_n=jnp.mean(obs.foot_force_n),
        roll_rad=diag.rpy_rad[0],
        pitch_rad=diag.rpy_rad[1],
        saturated=jnp.sum(diag.saturated),
    )


FAILED_MARGIN = -1.0
"""The safety margin of a tick whose simulation became non-finite (it is reset, so nothing else is known)."""


def safety_margin(
    trial_config: TrialConfig,
    imu_roll_rad,
    imu_pitch_rad,
    trunk_height_m=None,
    floor_roll_rad=None,
    floor_pitch_rad=None,
):
    r"""How far one state is from unsafe, signed and continuous (docs/decisions.md §17): the worst of

    * the tilt stop's margin :math:`1 - \max(|\phi|, |\theta|) / \theta_{stop}` with the IMU's roll and pitch (gravity
      frame, what the robot's safety layer reads);
    * the fall tilt's margin :math:`1 - \max(|\phi_f|, |\theta_f|) / \theta_{fall}` with the floor-frame roll and
      pitch (the fall rule of :func:`tick_row`);
    * the height margin :math:`(z - z_{fall}) / (h - z_{fall})` of the trunk origin above the floor, 1 at the height
      the controller holds.

    1 is standing level at the held height, 0 is a threshold, < 0 a fall or a tilt stop. The robot measures neither
    the trunk's height nor the floor: it passes the IMU's angles only. NumPy or JAX.
    """
    tilt = jnp.maximum(jnp.abs(imu_roll_rad), jnp.abs(imu_pitch_rad))
    margin = 1.0 - tilt / trial_config.stop_tilt_rad
    if floor_roll_rad is not None:
        floor_tilt = jnp.maximum(jnp.abs(floor_roll_rad), jnp.abs(floor_pitch_rad))
        margin = jnp.minimum(margin, 1.0 - floor_tilt / trial_config.fall_tilt_rad)
    if trunk_height_m is not None:
        clearance = trial_config.standing_height_m - trial_config.fall_height_m
        margin = jnp.minimum(margin, (trunk_height_m - trial_config.fall_height_m) / clearance)
    return margin


def tick_row(
    trial_config: TrialConfig,
    pre: PreStep,
    qpos: jax.Array,
    qvel: jax.Array,
    failed: jax.Array,
    ground_height_m: jax.Array | None = None,
) -> Tick:
    """A tick's record from its pre-step half and the state after the step (and after a reset, if ``failed``).

    Fall: trunk origin less than ``fall_height_m`` above the ground under it (``ground_height_m``, from
    ``cpgjax.go1.terrain``; None: the plane z = 0) or floor-frame |roll| or |pitch| above ``fall_tilt_rad``. A failed
    tick contributes nothing to the sums (velocity, power, load, attitude are zeroed). The margin takes the IMU's
    angles of the state the controller saw (the pre-step half) and the trunk's height and floor-frame tilt after the
    step."""
    ids = go1_model.indices()
    floor_rpy = attitude.quat_to_rpy(qpos[ids.root_qpos + 3 : ids.root_qpos + 7])
    height_m = qpos[ids.root_qpos + 2]
    if ground_height_m is not None:
        height_m = height_m - ground_height_m
    fell = (
        (height_m < trial_config.fall_height_m)
        | (jnp.abs(floor_rpy[0]) > trial_config.fall_tilt_rad)
        | (jnp.abs(floor_rpy[1]) > trial_config.fall_tilt_rad)
    )
    margin = safety_margin(trial_config, pre.roll_rad, pre.pitch_rad, height_m, floor_rpy[0], floor_rpy[1])
    finite = jnp.where(failed, 0.0, 1.0)
    return Tick(
        velocity_xy_mps=finite * sensors.heading_velocity(qpos, qvel),
        power_w=finite * pre.power_w,
        load_n=finite * pre.load_n,
        roll_rad=finite * pre.roll_rad,
        pitch_rad=finite * pre.pitch_rad,
        saturated=pre.saturated,
        fell=fell.astype(jnp.float32),
        failed=failed.astype(jnp.float32),
        margin=jnp.where(failed, FAILED_MARGIN, margin).astype(jnp.float32),
    )


class TransitionSummary(NamedTuple):
    """What the transition phase adds to a trial's record: its worst moments (scalars, or batched)."""

    fell: jax.Array  # 1.0 if any transition tick fell
    failed: jax.Array  # 1.0 if any transition tick failed
    margin: jax.Array  # the smallest tick margin

    @classmethod
    def of(cls, ticks: Tick, axis: int = 0) -> TransitionSummary:
        """The summary of transition ticks stacked along ``axis`` (none: nothing to add)."""
        return cls(
            fell=jnp.max(ticks.fell, axis=axis, initial=0.0),
            failed=jnp.max(ticks.failed, axis=axis, initial=0.0),
            margin=jnp.min(ticks.margin, axis=axis, initial=jnp.inf),
        )

    @classmethod
    def nothing(cls) -> TransitionSummary:
        """No transition ticks recorded (the robot's steady phase alone)."""
        return cls(fell=jnp.float32(0.0), failed=jnp.float32(0.0), margin=jnp.float32(jnp.inf))

    def add(self, tick: Tick) -> TransitionSummary:
        """The summary with one more transition tick (a scan's carry)."""
        return TransitionSummary(
            fell=jnp.maximum(self.fell, tick.fell),
            failed=jnp.maximum(self.failed, tick.failed),
            margin=jnp.minimum(self.margin, tick.margin),
        )


def summarize(steady: Tick, total_mass_kg: jax.Array, dt_s: float, transition: TransitionSummary) -> TrialRecord:
    """The trial record (eqs. 10-11 inputs, attitude statistics, flags, the worst safety margin) from the steady
    phase's ticks (T, ...); a fall, failure or low margin during the transition counts for the trial too. Shared by
    every backend."""
    steps = steady.power_w.shape[0]
    return TrialRecord(
        velocity_xy_mps=steady.velocity_xy_mps,
        energy_j=jnp.sum(steady.power_w) * dt_s,
        distance_m=jnp.sum(steady.velocity_xy_mps[:, 0]) * dt_s,
        total_mass_kg=total_mass_kg,
        c_load_n=jnp.mean(steady.load_n),
        c_slope_rad=jnp.mean(steady.pitch_rad),
        roll_mean_rad=jnp.mean(steady.roll_rad),
        roll_std_rad=jnp.std(steady.roll_rad),
        pitch_std_rad=jnp.std(steady.pitch_rad),
        saturation_fraction=jnp.sum(steady.saturated) / (12.0 * steps),
        fell=jnp.maximum(jnp.max(steady.fell), transition.fell),
        failed=jnp.maximum(jnp.max(steady.failed), transition.failed),
        safety_margin=jnp.minimum(jnp.min(steady.margin), transition.margin),
    )


class Control(NamedTuple):
    """One control tick's output (:func:`control`)."""

    io: physics_profiles.ActuatorSensorState
    cpg: cpg.CPGState
    obs: sensors.Observation  # what the controller read (with the profile's sensor noise)
    joint_vel_rad_s: jax.Array  # (12,) the joints' true velocity
    torque_nm: jax.Array  # (12,) the torque the motors apply
    diag: cpg.Diagnostics


def control(
    cpg_config: cpg.CPGConfig,
    profile: physics_profiles.ProfileArrays,
    io: physics_profiles.ActuatorSensorState,
    cpg_state: cpg.CPGState,
    params: jax.Array,
    gates: cpg.Gates,
    qpos: jax.Array,
    qvel: jax.Array,
    sensordata: jax.Array,
    gravity: jax.Array,
) -> Control:
    """Sensors → controller → motors for one instance, under its physics profile; every backend's tick."""
    io, obs = sensors.measure(profile, io, qpos, qvel, sensordata, gravity)
    cpg_state, command, diag = cpg.controller_step(cpg_config, cpg_state, params, gates, obs)
    joint_vel_rad_s = qvel[go1_model.indices().joint_dof]
    io, torque = physics_profiles.actuate(profile, io, command, joint_vel_rad_s)  # the motors feel the true velocity
    return Control(io=io, cpg=cpg_state, obs=obs, joint_vel_rad_s=joint_vel_rad_s, torque_nm=torque, diag=diag)


def transition_fraction(tick, transition_steps: int):
    """The blend fraction (k + 1) / n of transition tick k (reaches 1 at the last transition tick)."""
    return (tick + 1.0) / max(transition_steps, 1)


def transition_params(previous, new, fraction):
    """The linear parameter blend of the transition: previous + fraction · (new − previous). NumPy or JAX."""
    return previous + fraction * (new - previous)


@jax.jit  # one program for the whole tree where called eagerly (a backend's or the engine's host step)
def where_batch(mask, a, b):
    """Pytree ``a`` where ``mask`` else ``b``, leaf by leaf; ``mask`` has the leading batch axes of every leaf
    (a scalar mask selects whole trees) and is broadcast over the trailing axes."""

    def one(x, y):
        return jnp.where(jnp.reshape(mask, jnp.shape(mask) + (1,) * (jnp.ndim(x) - jnp.ndim(mask))), x, y)

    return jax.tree.map(one, a, b)


def check_params(params, batch_size: int) -> jax.Array:
    """Validated parameters (batch_size, 8) as float32 (``params.validate``: range and finiteness per parameter)."""
    arr = param_space.validate(params)
    if arr.shape != (batch_size, param_space.NUM_PARAMS):
        raise ValueError(f"params: expected shape ({batch_size}, {param_space.NUM_PARAMS}), got {arr.shape}")
    return jnp.asarray(arr, jnp.float32)


def check_gates(gates: cpg.Gates, batch_size: int) -> cpg.Gates:
    """Gates broadcast to the batch as float32: the modules (batch_size,), the phase lags (batch_size, 4, 4)."""

    def batched(g, shape):
        return jnp.broadcast_to(jnp.asarray(g, jnp.float32), (batch_size,) + shape)

    return cpg.Gates(batched(gates.vmc, ()), batched(gates.tegotae, ()), batched(gates.phase_lag_rad, (4, 4)))


def batch_gates(controllers, gaits=None) -> cpg.Gates:
    """Gates (modules (B,), phase lags (B, 4, 4)) for a sequence of controller names (``cpg.CONTROLLERS``) and
    their gaits (``cpg.GAITS``; None: every instance the paper's trot)."""
    gaits = [cpg.DEFAULT_GAIT] * len(controllers) if gaits is None else list(gaits)
    gates = [cpg.controller_gates(c, g) for c, g in zip(controllers, gaits, strict=True)]
    return cpg.Gates(*(np.stack([getattr(g, f) for g in gates]) for f in cpg.Gates._fields))


class StepLog(NamedTuple):
    """Per-tick log of a rollout with constant parameters (figures, recordings, backend comparisons); both backends
    write it with these definitions."""

    qpos: jax.Array  # (T, nq) floor frame
    qvel: jax.Array  # (T, nv)
    torque_nm: jax.Array  # (T, 12) applied joint torques
    foot_force_n: jax.Array  # (T, 4)
    foot_pos_m: jax.Array  # (T, 4, 3) foot centres, floor frame, of the state at the start of the tick (the step's
    #                        kinematics), while qpos/qvel are the state after it
    amplitude: jax.Array  # (T, 4) r_i
    phase_rad: jax.Array  # (T, 4) θ_i
    foot_target_m: jax.Array  # (T, 4, 3) leg-frame targets
    rpy_rad: jax.Array  # (T, 3) IMU roll, pitch, yaw
