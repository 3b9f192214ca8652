"""The Go1 in MuJoCo MJX: batched scenarios, the robot's sensor model, and the paper's trial.

A trial (paper Sec. "Implementation Details") continues from the current simulator state: 1.5 s of transition during
which the parameters are interpolated linearly from the previous set to the new one, then 3 s of steady state
(T = 3000 ticks at Δt = 1 ms) whose record gives J, CoT and the context (``cpgjax.trial.objective``). Trials run back to
back like the treadmill; after a fall the robot is reset to standing (decisions.md §8).

Everything is vmapped over instances — parameters, scenario (as per-instance model leaves), simulator and controller
state — and compiled once per batch shape. The batch is sharded over devices (``MJXBackend(devices=...)``): on a GPU
host over its GPUs, on a CPU over host devices (``jax_num_cpu_devices``, one per core, since XLA runs one device's
program on one thread). An instance whose state becomes non-finite is reset and its trial flagged
``failed``; ``jnp.where`` keeps the other instances bit-identical.
"""

from __future__ import annotations

import copy
import functools
import logging
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from mujoco import mjx

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.trial import params as param_space
from cpgjax.trial.objective import TrialRecord

log = logging.getLogger(__name__)


class TrialConfig(NamedTuple):
    """Trial timing and fall detection. Static: changing one recompiles."""

    transition_steps: int = 1500  # 1.5 s at 1 kHz
    steady_steps: int = 3000  # T
    fall_height_m: float = 0.12  # trunk origin below this height above the floor = fall
    fall_tilt_rad: float = 0.8  # |roll| or |pitch| relative to the floor beyond this = fall


class SimState(NamedTuple):
    """Per-instance simulator and controller state between trials (leading batch axis on every leaf)."""

    data: mjx.Data
    cpg: cpg.CPGState
    params: jax.Array  # (8,) the parameters applied at the end of the last trial (start of the next transition)


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


# ----------------------------------------------------------------------------------------------- sensor model

def _gravity_frame_quat(gravity: jax.Array) -> jax.Array:
    """Quaternion rotating floor-frame vectors into the gravity-aligned frame (shortest arc taking −ĝ to +z)."""
    up = -gravity / jnp.linalg.norm(gravity)
    q = jnp.stack([1.0 + up[2], up[1], -up[0], jnp.zeros_like(up[0])])  # (1 + u·z, u × z)
    return q / jnp.linalg.norm(q)


def _quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return jnp.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def observe(qpos: jax.Array, qvel: jax.Array, sensordata: jax.Array, gravity: jax.Array) -> cpg.Observation:
    """The controller's observation computed as the Go1's sensors would report it.

    IMU orientation relative to gravity (so a slope reads as pitch, decisions.md §4), gyro in the trunk frame, joint
    encoders, and each foot's contact normal force [N]. Works on MJX and C-MuJoCo arrays alike (one definition for
    every backend).
    """
    ids = go1_model.indices()
    r = ids.root_qpos
    quat_floor = qpos[r + 3:r + 7]
    return cpg.Observation(
        joint_pos_rad=qpos[ids.joint_qpos],
        joint_vel_rad_s=qvel[ids.joint_dof],
        imu_quat_wxyz=_quat_mul(_gravity_frame_quat(gravity), quat_floor),
        gyro_rad_s=qvel[ids.root_dof + 3:ids.root_dof + 6],
        foot_force_n=sensordata[ids.foot_force_sensor],
    )


def heading_velocity(qpos: jax.Array, qvel: jax.Array) -> jax.Array:
    """Trunk linear velocity (v_x, v_y) [m/s] in the heading (yaw-only) frame on the floor (decisions.md §9)."""
    ids = go1_model.indices()
    yaw = cpg.quat_to_rpy(qpos[ids.root_qpos + 3:ids.root_qpos + 7])[2]
    vx, vy = qvel[ids.root_dof], qvel[ids.root_dof + 1]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * vx + s * vy, -s * vx + c * vy])


# ----------------------------------------------------------------------------------------------- scenarios

class BatchModel(NamedTuple):
    """An MJX model whose scenario-dependent leaves carry a leading batch axis, and the matching vmap in_axes."""

    model: mjx.Model
    in_axes: mjx.Model
    scenario: go1_model.Scenario


def make_batch_model(scenario: go1_model.Scenario) -> BatchModel:
    """Per-instance MJX model data for a whole batch of scenarios, in one call.

    Floor friction → ``geom_friction[floor, 0]`` (the floor has priority, decisions.md §5); slope → ``opt.gravity``;
    payload → every mass-dependent field, recomputed by ``mj_setConst`` once per distinct payload value.
    """
    ids = go1_model.indices()
    base = go1_model.load_model()
    mx = mjx.put_model(base)
    batch = scenario.batch_size
    fields = [f for f in go1_model.mass_dependent_fields() if hasattr(mx, f)]
    per_payload = {p: go1_model.model_with_payload(p) for p in sorted(set(scenario.payload_kg.tolist()))}
    updates = {f: jnp.asarray(np.stack([getattr(per_payload[p], f) for p in scenario.payload_kg.tolist()]),
                              dtype=getattr(mx, f).dtype) for f in fields}
    friction = np.broadcast_to(np.asarray(base.geom_friction), (batch,) + base.geom_friction.shape).copy()
    friction[:, ids.floor_geom, 0] = scenario.friction
    updates["geom_friction"] = jnp.asarray(friction, getattr(mx, "geom_friction").dtype)
    updates["opt.gravity"] = jnp.asarray(go1_model.gravity_vector(scenario.slope_deg), mx.opt.gravity.dtype)
    in_axes = jax.tree.map(lambda _: None, mx).tree_replace({k: 0 for k in updates})
    return BatchModel(model=mx.tree_replace(updates), in_axes=in_axes, scenario=scenario)


# ----------------------------------------------------------------------------------------------- one instance

def _standing_data(model: mjx.Model) -> mjx.Data:
    data = mjx.make_data(model).replace(qpos=jnp.asarray(go1_model.standing_qpos(), jnp.float32))
    return mjx.forward(model, data)


def _observe_data(model: mjx.Model, data: mjx.Data) -> cpg.Observation:
    return observe(data.qpos, data.qvel, data.sensordata, model.opt.gravity)


def _reset(model: mjx.Model, params: jax.Array) -> SimState:
    data = _standing_data(model)
    return SimState(data=data, cpg=cpg.init_state(_observe_data(model, data)), params=params)


def _where(cond, a, b):
    return jax.tree.map(lambda x, y: jnp.where(cond, x, y), a, b)


# What the next tick reads of mjx.Data: the sensors (observation) and the inputs of mjx.step; every other field is
# recomputed by mjx.step from these. Selecting only them per tick is much cheaper than selecting the whole Data.
_TICK_STATE_FIELDS = ("time", "qpos", "qvel", "qacc_warmstart", "sensordata")


def _reset_state_where(cond, reset: mjx.Data, data: mjx.Data) -> mjx.Data:
    """``data`` with its tick state taken from ``reset`` where ``cond``; derived fields are left to the next step."""
    return data.replace(**{f: jnp.where(cond, getattr(reset, f), getattr(data, f)) for f in _TICK_STATE_FIELDS})


class PreStep(NamedTuple):
    """The half of a tick's record known at control time (before the physics step)."""

    power_w: jax.Array  # ⟨|τ|, |q̇|⟩
    load_n: jax.Array  # mean foot normal force
    roll_rad: jax.Array
    pitch_rad: jax.Array
    saturated: jax.Array  # number of clipped joint torques


def pre_step(obs: cpg.Observation, torque: jax.Array, diag: cpg.Diagnostics) -> PreStep:
    """Record quantities of the state the controller saw and the torque it applied (shared by every backend)."""
    return PreStep(power_w=jnp.sum(jnp.abs(torque) * jnp.abs(obs.joint_vel_rad_s)),
                   load_n=jnp.mean(obs.foot_force_n), roll_rad=diag.rpy_rad[0], pitch_rad=diag.rpy_rad[1],
                   saturated=jnp.sum(diag.saturated))


def tick_row(trial_config: TrialConfig, pre: PreStep, qpos: jax.Array, qvel: jax.Array, failed: jax.Array) -> Tick:
    """A tick's record from its pre-step half and the state after the step (and after a reset, if ``failed``).

    Fall: trunk origin below ``fall_height_m`` or floor-frame |roll| or |pitch| above ``fall_tilt_rad``. A failed
    tick contributes nothing to the sums (velocity, power, load, attitude are zeroed)."""
    ids = go1_model.indices()
    floor_rpy = cpg.quat_to_rpy(qpos[ids.root_qpos + 3:ids.root_qpos + 7])
    fell = ((qpos[ids.root_qpos + 2] < trial_config.fall_height_m)
            | (jnp.abs(floor_rpy[0]) > trial_config.fall_tilt_rad)
            | (jnp.abs(floor_rpy[1]) > trial_config.fall_tilt_rad))
    finite = jnp.where(failed, 0.0, 1.0)
    return Tick(
        velocity_xy_mps=finite * heading_velocity(qpos, qvel),
        power_w=finite * pre.power_w,
        load_n=finite * pre.load_n,
        roll_rad=finite * pre.roll_rad,
        pitch_rad=finite * pre.pitch_rad,
        saturated=pre.saturated,
        fell=fell.astype(jnp.float32),
        failed=failed.astype(jnp.float32),
    )


def _tick(cpg_config: cpg.CPGConfig, trial_config: TrialConfig, model: mjx.Model, gates: cpg.Gates,
          reset: SimState, data: mjx.Data, cpg_state: cpg.CPGState, params_now: jax.Array):
    """Sensors → controller → one physics step; a non-finite result is replaced by the standing reset."""
    ids = go1_model.indices()
    obs = _observe_data(model, data)
    cpg_state, torque, diag = cpg.controller_step(cpg_config, cpg_state, params_now, gates, obs)
    ctrl = jnp.zeros(model.nu, torque.dtype).at[ids.actuator].set(torque)
    stepped = mjx.step(model, data.replace(ctrl=ctrl))
    failed = ~(jnp.all(jnp.isfinite(stepped.qpos)) & jnp.all(jnp.isfinite(stepped.qvel)))
    data = _reset_state_where(failed, reset.data, stepped)
    cpg_state = _where(failed, reset.cpg, cpg_state)
    return data, cpg_state, tick_row(trial_config, pre_step(obs, torque, diag), data.qpos, data.qvel, failed)


def summarize(steady: Tick, total_mass_kg: jax.Array, dt_s: float, transition_fell: jax.Array,
              transition_failed: jax.Array) -> TrialRecord:
    """The trial record (eqs. 10-11 inputs, attitude statistics, flags) from the steady phase's ticks (T, ...);
    a fall or failure during the transition counts for the trial too. Shared by every backend."""
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
        fell=jnp.maximum(jnp.max(steady.fell), transition_fell),
        failed=jnp.maximum(jnp.max(steady.failed), transition_failed),
    )


def _trial(cpg_config: cpg.CPGConfig, trial_config: TrialConfig, model: mjx.Model, state: SimState,
           new_params: jax.Array, gates: cpg.Gates) -> tuple[SimState, TrialRecord]:
    """One trial of one instance: transition (linear interpolation) then steady phase; reset after a fall."""
    reset = _reset(model, new_params)
    tick = functools.partial(_tick, cpg_config, trial_config, model, gates, reset)
    n_transition = trial_config.transition_steps

    def transition_body(carry, k):
        data, cpg_state, fell, failed = carry
        blend = (k + 1.0) / n_transition
        data, cpg_state, t = tick(data, cpg_state, state.params + blend * (new_params - state.params))
        return (data, cpg_state, jnp.maximum(fell, t.fell), jnp.maximum(failed, t.failed)), None

    def steady_body(carry, _):
        data, cpg_state = carry
        data, cpg_state, t = tick(data, cpg_state, new_params)
        return (data, cpg_state), t

    zero = jnp.float32(0.0)
    (data, cpg_state, fell_tr, failed_tr), _ = jax.lax.scan(
        transition_body, (state.data, state.cpg, zero, zero), jnp.arange(n_transition, dtype=jnp.float32))
    (data, cpg_state), ticks = jax.lax.scan(steady_body, (data, cpg_state), None, length=trial_config.steady_steps)

    total_mass = model.body_subtreemass[go1_model.indices().trunk_body]
    record = summarize(ticks, total_mass, cpg_config.dt_s, fell_tr, failed_tr)
    end = SimState(data=data, cpg=cpg_state, params=new_params)
    return _where((record.fell > 0) | (record.failed > 0), reset, end), record


class StepLog(NamedTuple):
    """Per-tick log of a rollout with constant parameters (figures, recordings, backend comparisons)."""

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


def rollout_log(cpg_config: cpg.CPGConfig, model: mjx.Model, state: SimState, params: jax.Array, gates: cpg.Gates,
                num_steps: int) -> tuple[SimState, StepLog]:
    """``num_steps`` ticks of one instance with constant parameters, logging every tick. Not vmapped: wrap it."""
    ids = go1_model.indices()

    def body(carry, _):
        data, cpg_state = carry
        obs = _observe_data(model, data)
        cpg_state, torque, diag = cpg.controller_step(cpg_config, cpg_state, params, gates, obs)
        data = mjx.step(model, data.replace(ctrl=jnp.zeros(model.nu, torque.dtype).at[ids.actuator].set(torque)))
        row = StepLog(qpos=data.qpos, qvel=data.qvel, torque_nm=torque, foot_force_n=obs.foot_force_n,
                      foot_pos_m=data.geom_xpos[ids.foot_geom], amplitude=cpg_state.amplitude,
                      phase_rad=cpg_state.phase_rad, foot_target_m=diag.foot_target_m, rpy_rad=diag.rpy_rad)
        return (data, cpg_state), row

    (data, cpg_state), log_rows = jax.lax.scan(body, (state.data, state.cpg), None, length=num_steps)
    return SimState(data=data, cpg=cpg_state, params=params), log_rows


# ----------------------------------------------------------------------------------------------- batch interface

def check_params(params, batch_size: int) -> jax.Array:
    """Validated parameters (batch_size, 8) as float32 (``params.validate``: range and finiteness per parameter)."""
    arr = param_space.validate(params)
    if arr.shape != (batch_size, param_space.NUM_PARAMS):
        raise ValueError(f"params: expected shape ({batch_size}, {param_space.NUM_PARAMS}), got {arr.shape}")
    return jnp.asarray(arr, jnp.float32)


def check_gates(gates: cpg.Gates, batch_size: int) -> cpg.Gates:
    """Gates broadcast to (batch_size,) float32 each."""
    return cpg.Gates(*(jnp.broadcast_to(jnp.asarray(g, jnp.float32), (batch_size,)) for g in gates))


def _batch_mesh(batch_size: int, devices) -> Mesh:
    """A 1-D mesh (axis ``batch``) over ``devices`` (default: every device, when the batch divides among them,
    otherwise the first device alone, said in a log line)."""
    if devices is None:
        devices = jax.devices()
        if batch_size % len(devices):
            log.info("batch %d does not divide over %d devices; running on %s only", batch_size, len(devices),
                     devices[0])
            devices = devices[:1]
    devices = list(devices)
    if batch_size % len(devices):
        raise ValueError(f"batch size {batch_size} must be a multiple of the device count {len(devices)}")
    return Mesh(np.array(devices), ("batch",))


def per_shard(fn, in_axes, mesh: Mesh):
    """``jax.vmap(fn, in_axes)`` applied by each device of ``mesh`` to its own slice of the batch (``jax.shard_map``
    over axis ``batch``; arguments with in_axes None are replicated).

    With the batch merely sharded (GSPMD), the vmapped solver's while-loop condition "any instance not done" becomes
    a cross-device all-reduce in every iteration; per shard, each device loops on its own instances and never waits
    for another. (``check_vma=False``: MJX's internals are not written for varying-axis typing.)"""
    specs = jax.tree.map(lambda axis: PartitionSpec() if axis is None else PartitionSpec("batch"), in_axes,
                         is_leaf=lambda axis: axis is None)
    return jax.shard_map(jax.vmap(fn, in_axes=in_axes), mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"),
                         check_vma=False)


class MJXBackend:
    """A batch of simulated Go1s in MJX behind the trial interface shared by every backend.

    >>> sim = MJXBackend(go1_model.make_scenarios(friction=[0.3, 0.6, 0.9]))
    >>> state = sim.reset(params)                         # params (3, 8), physical units
    >>> state, record = sim.trial(state, new_params, gates)   # gates: cpg.Gates of (3,) arrays

    ``devices``: the devices to shard the batch over (default: all of them when the batch divides among them).
    """

    name = "mjx"

    def __init__(self, scenario: go1_model.Scenario, cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
                 trial_config: TrialConfig = TrialConfig(), *, devices=None):
        self.scenario = scenario
        self.cpg_config = cpg_config
        self.trial_config = trial_config
        self.mesh = _batch_mesh(scenario.batch_size, devices)
        self.batch = self._placed(make_batch_model(scenario))
        axes = self.batch.in_axes
        self._reset = jax.jit(per_shard(_reset, (axes, 0), self.mesh))
        trial = functools.partial(_trial, cpg_config, trial_config)
        self._trial = jax.jit(per_shard(trial, (axes, 0, 0, 0), self.mesh), donate_argnums=(1,))
        self._rollouts = {}  # num_steps → compiled rollout, on first use

    @property
    def batch_size(self) -> int:
        return self.scenario.batch_size

    @property
    def sharding(self) -> NamedSharding:
        """Where batched arrays live: split along the batch axis over ``self.mesh``."""
        return NamedSharding(self.mesh, PartitionSpec("batch"))

    def _placed(self, batch: BatchModel) -> BatchModel:
        replicated = NamedSharding(self.mesh, PartitionSpec())
        model = jax.tree.map(lambda x, axis: jax.device_put(x, self.sharding if axis == 0 else replicated),
                             batch.model, batch.in_axes)
        return batch._replace(model=model)

    def _put(self, tree):
        return jax.device_put(tree, self.sharding)

    def reset(self, params) -> SimState:
        """Every instance standing at the origin with its CPG at rest; ``params`` become the 'previous' set."""
        return self._reset(self.batch.model, self._put(check_params(params, self.batch_size)))

    def trial(self, state: SimState, new_params, gates: cpg.Gates) -> tuple[SimState, TrialRecord]:
        """One trial for every instance (the input state is consumed). Returns the next state and the records."""
        return self._trial(self.batch.model, self._put(state), self._put(check_params(new_params, self.batch_size)),
                           self._put(check_gates(gates, self.batch_size)))

    def with_scenario(self, scenario: go1_model.Scenario) -> "MJXBackend":
        """This backend for another batch of scenarios of the same size, sharing the compiled trial and rollout
        (the scenario enters them as model data, so nothing recompiles). Simulator states carry over unchanged:
        the lockstep engine (``cpgjax.ablation``) uses it when a payload, slope or friction schedule changes."""
        if scenario.batch_size != self.batch_size:
            raise ValueError(f"scenario batch {scenario.batch_size} != backend batch {self.batch_size}")
        other = copy.copy(self)
        other.scenario = scenario
        other.batch = self._placed(make_batch_model(scenario))
        return other

    def rollout(self, state: SimState, params, gates: cpg.Gates, num_steps: int) -> tuple[SimState, StepLog]:
        """``num_steps`` logged ticks with constant parameters for every instance (log arrays are (B, T, ...))."""
        if num_steps not in self._rollouts:
            fn = functools.partial(rollout_log, self.cpg_config, num_steps=num_steps)
            self._rollouts[num_steps] = jax.jit(per_shard(fn, (self.batch.in_axes, 0, 0, 0), self.mesh))
        return self._rollouts[num_steps](self.batch.model, self._put(state),
                                         self._put(check_params(params, self.batch_size)),
                                         self._put(check_gates(gates, self.batch_size)))


def batch_gates(controllers) -> cpg.Gates:
    """Gates (each (B,)) for a sequence of controller names (see ``cpg.CONTROLLERS``)."""
    gates = [cpg.controller_gates(c) for c in controllers]
    return cpg.Gates(vmc=np.array([g.vmc for g in gates]), tegotae=np.array([g.tegotae for g in gates]))
