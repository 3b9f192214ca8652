"""The Go1 in MuJoCo MJX: batched scenarios and the paper's trial as one compiled scan per trial.

The trial itself (1.5 s transition with the linear parameter blend, then 3 s steady phase, the per-tick rows and their
summary into a ``TrialRecord``) is the backend-neutral protocol of ``cpgjax.trial.protocol``; the observation is the
sensor model of ``cpgjax.go1.sensors``. This module runs them on MJX: sensors → controller → ``mjx.step`` per tick,
``lax.scan`` over the ticks of a trial, reset to standing after a fall (docs/decisions.md §8).

Everything is vmapped over instances — parameters, scenario (as per-instance model leaves), simulator and controller
state — and compiled once per batch shape. The batch is sharded over devices (``MJXBackend(devices=...)``): on a GPU
host over its GPUs, on a CPU over host devices (``jax_num_cpu_devices``, one per core, since XLA runs one device's
program on one thread). An instance whose state becomes non-finite is reset and its trial flagged
``failed``; ``jnp.where`` keeps the other instances bit-identical.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import logging
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import sensors
from cpgjax.go1 import terrain as terrains
from cpgjax.sim.base import Backend
from cpgjax.trial import protocol


def _import_mjx_without_its_warp_probe():
    """``mujoco.mjx``, imported with the two lines its import prints to stdout when NVIDIA Warp is absent ("Failed to
    import warp…", always so on a CPU) dropped, so that importing cpgjax prints nothing and they cannot land in a
    redirected output; other output passes."""
    probe = io.StringIO()
    with contextlib.redirect_stdout(probe):
        from mujoco import mjx
    sys.stdout.write(
        "".join(
            line
            for line in probe.getvalue().splitlines(keepends=True)
            if not line.startswith(("Failed to import warp:", "Failed to import mujoco_warp:"))
        )
    )
    return mjx


mjx = _import_mjx_without_its_warp_probe()

log = logging.getLogger(__name__)

MIN_FRICTIONLOSS_NM = 1e-6  # the smallest joint friction-loss bound MJX is given (see make_batch_model)


class SimState(NamedTuple):
    """Per-instance simulator and controller state between trials (leading batch axis on every leaf)."""

    data: mjx.Data
    cpg: cpg.CPGState
    params: jax.Array  # (8,) the parameters applied at the end of the last trial (start of the next transition)
    io: physics_profiles.ActuatorSensorState  # the physics profile's foot sensor and motors


# ----------------------------------------------------------------------------------------------- scenarios


class BatchModel(NamedTuple):
    """An MJX model whose scenario-dependent leaves carry a leading batch axis, the matching vmap in_axes, and the
    physics profiles' per-instance actuator and sensor arrays."""

    model: mjx.Model
    in_axes: mjx.Model
    scenario: go1_model.Scenario
    profile: physics_profiles.ProfileArrays  # (B, ...) leaves


def make_batch_model(scenario: go1_model.Scenario) -> BatchModel:
    """Per-instance MJX model data for a whole batch of scenarios, in one call.

    Floor friction → ``geom_friction[floor, 0]`` (the floor has priority, docs/decisions.md §5), the μ in effect
    with the feet's (``go1_model.effective_friction``); slope →
    ``opt.gravity``; payload and physics profile → every field they change, recomputed by ``mj_setConst`` once per
    distinct (payload, profile); terrain → the terrain model (``go1_model.load_terrain_model``) when some instance
    is not flat, its ``hfield_data`` per instance (a flat batch keeps the plane and its program).

    Args:
      scenario: the batch of B scenarios.

    Returns:
      A :class:`BatchModel` (model leaves that vary with the scenario (B, ...), the rest shared).

    Raises:
      ValueError: a physics profile of ``scenario`` steps its physics more than once per control tick.
    """
    fine = sorted({str(name) for name in scenario.physics if physics_profiles.get(str(name)).physics_substeps != 1})
    if fine:
        raise ValueError(
            f"physics profile {fine[0]!r} steps its physics more than once per control tick, which the "
            "MJX backend does not: use the native backend"
        )
    ids = go1_model.indices()
    terrain = go1_model.has_terrain(scenario)
    base = (go1_model.load_terrain_model() if terrain else go1_model.load_model()).__copy__()
    # Every joint carries friction-loss rows whatever the profiles of this batch (a profile without joint friction
    # has a zero bound there), so that switching profiles never changes the compiled program.
    base.dof_frictionloss[ids.joint_dof] = 1.0
    mx = mjx.put_model(base)
    batch = scenario.batch_size
    fields = [f for f in go1_model.scenario_dependent_fields() if hasattr(mx, f)]
    keys = list(
        zip(
            scenario.payload_kg.tolist(),
            scenario.physics.tolist(),
            scenario.mass_scale.tolist(),
            [terrain] * batch,
            strict=True,
        )
    )
    per_key = {k: go1_model.model_with_payload(*k) for k in dict.fromkeys(keys)}
    updates = {
        f: jnp.asarray(np.stack([getattr(per_key[k], f) for k in keys]), dtype=getattr(mx, f).dtype) for f in fields
    }
    # A zero bound makes MJX's friction-loss row act as a stiff constraint on the joint (the gait it costs:
    # docs/physics.md), so MJX carries a negligible bound where a profile has no joint friction.
    updates["dof_frictionloss"] = jnp.maximum(updates["dof_frictionloss"], MIN_FRICTIONLOSS_NM)
    friction = np.broadcast_to(np.asarray(base.geom_friction), (batch,) + base.geom_friction.shape).copy()
    friction[:, ids.floor_geom, 0] = go1_model.effective_friction(scenario)
    updates["geom_friction"] = jnp.asarray(friction, mx.geom_friction.dtype)
    updates["opt.gravity"] = jnp.asarray(go1_model.gravity_vector(scenario.slope_deg), mx.opt.gravity.dtype)
    if terrain:
        updates["hfield_data"] = jnp.asarray(
            np.stack([terrains.hfield_data(go1_model.scenario_ground(scenario, i)) for i in range(batch)]),
            mx.hfield_data.dtype,
        )
    in_axes = jax.tree.map(lambda _: None, mx).tree_replace({k: 0 for k in updates})
    return BatchModel(
        model=mx.tree_replace(updates),
        in_axes=in_axes,
        scenario=scenario,
        profile=physics_profiles.batch_arrays(
            scenario.physics, scenario.latency_ticks, scenario.noise_scale, scenario.noise_seed
        ),
    )


# ----------------------------------------------------------------------------------------------- one instance


def _standing_data(model: mjx.Model, legs_rad: jax.Array | None = None) -> mjx.Data:
    qpos = jnp.asarray(go1_model.standing_qpos(), jnp.float32)
    if legs_rad is not None:  # the start's leaning pose
        qpos = qpos.at[go1_model.indices().joint_qpos].set(legs_rad)
    return mjx.forward(model, mjx.make_data(model).replace(qpos=qpos))


def _reset(cpg_config: cpg.CPGConfig, model: mjx.Model, params: jax.Array, phase_lag_rad: jax.Array) -> SimState:
    """Standing, the controller at rest in its gait's phases (``phase_lag_rad``); with the start's lean the robot
    reads its IMU's pitch standing and stands leaning (``cpg.lean_x_m``), as the robot's soft start does."""
    data = _standing_data(model)
    obs = sensors.observe(data.qpos, data.qvel, data.sensordata, model.opt.gravity)
    if cpg_config.start_lean:
        data = _standing_data(model, cpg.standing_pose_rad(cpg_config, obs.imu_quat_wxyz))
        obs = sensors.observe(data.qpos, data.qvel, data.sensordata, model.opt.gravity)
    return SimState(
        data=data,
        cpg=cpg.init_state(obs, cpg_config, phase_lag_rad=phase_lag_rad),
        params=params,
        io=physics_profiles.init_state(obs.foot_force_n),
    )


def _control(
    cpg_config: cpg.CPGConfig,
    model: mjx.Model,
    profile: physics_profiles.ProfileArrays,
    data: mjx.Data,
    io: physics_profiles.ActuatorSensorState,
    cpg_state: cpg.CPGState,
    params: jax.Array,
    gates: cpg.Gates,
) -> tuple[protocol.Control, mjx.Data]:
    """The shared control tick, then one physics step with its torques."""
    c = protocol.control(
        cpg_config, profile, io, cpg_state, params, gates, data.qpos, data.qvel, data.sensordata, model.opt.gravity
    )
    ctrl = jnp.zeros(model.nu, c.torque_nm.dtype).at[go1_model.indices().actuator].set(c.torque_nm)
    return c, mjx.step(model, data.replace(ctrl=ctrl))


# What the next tick reads of mjx.Data: the sensors (observation) and the inputs of mjx.step; every other field is
# recomputed by mjx.step from these. Selecting only them per tick is much cheaper than selecting the whole Data.
_TICK_STATE_FIELDS = ("time", "qpos", "qvel", "qacc_warmstart", "sensordata")


def _reset_tick_state_where(cond, reset: mjx.Data, data: mjx.Data) -> mjx.Data:
    """``data`` with its tick state taken from ``reset`` where ``cond``; derived fields are left to the next step."""
    return data.replace(**{f: jnp.where(cond, getattr(reset, f), getattr(data, f)) for f in _TICK_STATE_FIELDS})


def _ground_under_trunk_m(model: mjx.Model, qpos: jax.Array) -> jax.Array | None:
    """The ground's height under the trunk origin on the terrain model's height field; None on the plane."""
    if model.nhfield == 0:
        return None
    r = go1_model.indices().root_qpos
    return terrains.ground_height_m(model.hfield_data, qpos[r], qpos[r + 1])


def _wrapped(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """On the terrain model, ``data`` with the trunk moved by whole periods of the terrain into its central period
    (``terrain.wrap_xy_m``: the ground under it is the same); on the plane, ``data``."""
    if model.nhfield == 0:
        return data
    r = go1_model.indices().root_qpos
    return data.replace(qpos=data.qpos.at[r : r + 2].set(terrains.wrap_xy_m(data.qpos[r : r + 2])))


def _tick(
    cpg_config: cpg.CPGConfig,
    trial_config: protocol.TrialConfig,
    model: mjx.Model,
    profile: physics_profiles.ProfileArrays,
    gates: cpg.Gates,
    reset: SimState,
    state: SimState,
    params_now: jax.Array,
) -> tuple[SimState, protocol.Tick]:
    """Sensors → controller → motors → one physics step; a non-finite result is replaced by the standing reset."""
    c, stepped = _control(cpg_config, model, profile, state.data, state.io, state.cpg, params_now, gates)
    failed = ~(jnp.all(jnp.isfinite(stepped.qpos)) & jnp.all(jnp.isfinite(stepped.qvel)))
    data = _reset_tick_state_where(failed, reset.data, stepped)
    cpg_state = protocol.where_batch(failed, reset.cpg, c.cpg)
    io = protocol.where_batch(failed, reset.io, c.io)
    pre = protocol.pre_step(c.obs, c.torque_nm, c.diag, c.joint_vel_rad_s)
    row = protocol.tick_row(trial_config, pre, data.qpos, data.qvel, failed, _ground_under_trunk_m(model, data.qpos))
    return state._replace(data=data, cpg=cpg_state, io=io), row


def _trial(
    cpg_config: cpg.CPGConfig,
    trial_config: protocol.TrialConfig,
    model: mjx.Model,
    profile: physics_profiles.ProfileArrays,
    state: SimState,
    new_params: jax.Array,
    gates: cpg.Gates,
) -> tuple[SimState, protocol.TrialRecord]:
    """One trial of one instance: transition (linear interpolation) then steady phase; reset after a fall; on a
    terrain, the trunk moved back into the terrain's central period at the end (``_wrapped``)."""
    reset = _reset(cpg_config, model, new_params, gates.phase_lag_rad)
    tick = functools.partial(_tick, cpg_config, trial_config, model, profile, gates, reset)
    n_transition = trial_config.transition_steps

    def transition_body(carry, k):
        s, worst = carry
        fraction = protocol.transition_fraction(k, n_transition)
        s, t = tick(s, protocol.transition_params(state.params, new_params, fraction))
        return (s, worst.add(t)), None

    def steady_body(s, _):
        return tick(s, new_params)

    (s, transition), _ = jax.lax.scan(
        transition_body, (state, protocol.TransitionSummary.nothing()), jnp.arange(n_transition, dtype=jnp.float32)
    )
    s, ticks = jax.lax.scan(steady_body, s, None, length=trial_config.steady_steps)

    total_mass = model.body_subtreemass[go1_model.indices().trunk_body]
    record = protocol.summarize(ticks, total_mass, cpg_config.dt_s, transition)
    end = s._replace(data=_wrapped(model, s.data), params=new_params)
    return protocol.where_batch((record.fell > 0) | (record.failed > 0), reset, end), record


def rollout_log(
    cpg_config: cpg.CPGConfig,
    model: mjx.Model,
    profile: physics_profiles.ProfileArrays,
    state: SimState,
    params: jax.Array,
    gates: cpg.Gates,
    num_steps: int,
) -> tuple[SimState, protocol.StepLog]:
    """``num_steps`` ticks of one instance with constant parameters, logging every tick. Not vmapped: wrap it.

    Args:
      cpg_config: the controller constants (static).
      model: the instance's MJX model.
      profile: the instance's physics-profile arrays.
      state: the instance's state.
      params: the 8 physical parameters (8,).
      gates: the instance's controller variant and gait.
      num_steps: T, the number of ticks (static).

    Returns:
      (the state after the ticks, ``params`` as its parameters; the ``protocol.StepLog`` of (T, ...) arrays).
    """
    ids = go1_model.indices()

    def body(s, _):
        c, data = _control(cpg_config, model, profile, s.data, s.io, s.cpg, params, gates)
        row = protocol.StepLog(
            qpos=data.qpos,
            qvel=data.qvel,
            torque_nm=c.torque_nm,
            foot_force_n=c.obs.foot_force_n,
            foot_pos_m=data.geom_xpos[ids.foot_geom],
            amplitude=c.cpg.amplitude,
            phase_rad=c.cpg.phase_rad,
            foot_target_m=c.diag.foot_target_m,
            rpy_rad=c.diag.rpy_rad,
        )
        return s._replace(data=data, cpg=c.cpg, io=c.io), row

    s, log_rows = jax.lax.scan(body, state, None, length=num_steps)
    return s._replace(params=params), log_rows


# ----------------------------------------------------------------------------------------------- batch interface


def _batch_mesh(batch_size: int, devices) -> Mesh:
    """A 1-D mesh (axis ``batch``) over ``devices`` (default: every device, when the batch divides among them,
    otherwise the first device alone, said in a log line)."""
    if devices is None:
        devices = jax.devices()
        if batch_size % len(devices):
            log.info(
                "batch %d does not divide over %d devices; running on %s only", batch_size, len(devices), devices[0]
            )
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
    for another. (``check_vma=False``: MJX's internals are not written for varying-axis typing.)

    Args:
      fn: the function of one instance.
      in_axes: ``jax.vmap``'s in_axes of ``fn``'s arguments: 0 (batched) or None (replicated) per leaf.
      mesh: a mesh with axis ``batch``.

    Returns:
      The batched function, its outputs split along the batch axis over ``mesh``.
    """
    specs = jax.tree.map(
        lambda axis: PartitionSpec() if axis is None else PartitionSpec("batch"),
        in_axes,
        is_leaf=lambda axis: axis is None,
    )
    return jax.shard_map(
        jax.vmap(fn, in_axes=in_axes), mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"), check_vma=False
    )


class MJXBackend(Backend):
    """A batch of simulated Go1s in MJX behind the interface of every backend (``cpgjax.sim.base.Backend``).

    >>> sim = MJXBackend(go1_model.make_scenarios(friction=[0.3, 0.6, 0.9]))
    >>> state = sim.reset(params)                         # params (3, 8), physical units
    >>> state, record = sim.trial(state, new_params, gates)   # gates: cpg.Gates of (3,) arrays

    ``devices``: the devices to shard the batch over (default: all of them when the batch divides among them).
    """

    name = "mjx"

    def __init__(
        self,
        scenario: go1_model.Scenario,
        cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
        trial_config: protocol.TrialConfig = protocol.TrialConfig(),
        *,
        devices=None,
    ):
        self.scenario = scenario
        self.cpg_config = cpg_config
        self.trial_config = trial_config
        self.mesh = _batch_mesh(scenario.batch_size, devices)
        self.batch = self._placed(make_batch_model(scenario))
        axes = self.batch.in_axes
        self._reset = jax.jit(per_shard(functools.partial(_reset, cpg_config), (axes, 0, 0), self.mesh))
        trial = functools.partial(_trial, cpg_config, trial_config)
        self._trial = jax.jit(per_shard(trial, (axes, 0, 0, 0, 0), self.mesh), donate_argnums=(2,))
        self._rollouts = {}  # num_steps → compiled rollout, on first use

    @property
    def batch_size(self) -> int:
        """B, the number of instances (``scenario.batch_size``)."""
        return self.scenario.batch_size

    @property
    def sharding(self) -> NamedSharding:
        """Where batched arrays live: split along the batch axis over ``self.mesh``."""
        return NamedSharding(self.mesh, PartitionSpec("batch"))

    def _placed(self, batch: BatchModel) -> BatchModel:
        replicated = NamedSharding(self.mesh, PartitionSpec())
        model = jax.tree.map(
            lambda x, axis: jax.device_put(x, self.sharding if axis == 0 else replicated), batch.model, batch.in_axes
        )
        return batch._replace(model=model, profile=jax.device_put(batch.profile, self.sharding))

    def _put(self, tree):
        return jax.device_put(tree, self.sharding)

    def reset(self, params, gates: cpg.Gates | None = None) -> SimState:
        """Every instance standing at the origin with its CPG at rest in its gait's phases (``gates``; None: trot);
        ``params`` become the 'previous' set.

        Args:
          params: (B, 8) physical parameters, checked by ``protocol.check_params``.
          gates: the instances' gates, broadcast to the batch; only their phase lags are read here.

        Returns:
          The batch's :class:`SimState`.
        """
        gates = protocol.check_gates(cpg.Gates(0.0, 0.0) if gates is None else gates, self.batch_size)
        return self._reset(
            self.batch.model, self._put(protocol.check_params(params, self.batch_size)), self._put(gates.phase_lag_rad)
        )

    def trial(self, state: SimState, new_params, gates: cpg.Gates) -> tuple[SimState, protocol.TrialRecord]:
        """One trial for every instance (the input state is consumed). Returns the next state and the records.

        Args:
          state: the batch's :class:`SimState` (consumed: its buffers are donated).
          new_params: (B, 8) physical parameters of this trial, checked by ``protocol.check_params``.
          gates: the instances' gates, broadcast to the batch.

        Returns:
          (the next :class:`SimState`, the ``protocol.TrialRecord`` of (B, ...) arrays).
        """
        return self._trial(
            self.batch.model,
            self.batch.profile,
            self._put(state),
            self._put(protocol.check_params(new_params, self.batch_size)),
            self._put(protocol.check_gates(gates, self.batch_size)),
        )

    def with_scenario(self, scenario: go1_model.Scenario) -> MJXBackend:
        """This backend for another batch of scenarios of the same size, sharing the compiled trial and rollout
        (the scenario enters them as model data, so nothing recompiles). Simulator states carry over unchanged:
        the lockstep engine (``cpgjax.ablation``) uses it when a payload, slope or friction schedule changes.

        Args:
          scenario: the other batch of scenarios, B of them.

        Returns:
          A copy of this backend with ``scenario`` and its batch model.

        Raises:
          ValueError: ``scenario``'s batch size differs from this backend's, or it would switch between the plane
            and the terrain model (``go1_model.check_same_model``).
        """
        if scenario.batch_size != self.batch_size:
            raise ValueError(f"scenario batch {scenario.batch_size} != backend batch {self.batch_size}")
        go1_model.check_same_model(self.scenario, scenario)
        other = copy.copy(self)
        other.scenario = scenario
        other.batch = self._placed(make_batch_model(scenario))
        return other

    def rollout(self, state: SimState, params, gates: cpg.Gates, num_steps: int) -> tuple[SimState, protocol.StepLog]:
        """``num_steps`` logged ticks with constant parameters for every instance (log arrays are (B, T, ...)).

        Args:
          state: the batch's :class:`SimState`.
          params: (B, 8) physical parameters, checked by ``protocol.check_params``.
          gates: the instances' gates, broadcast to the batch.
          num_steps: T, the number of ticks (each new value compiles once).

        Returns:
          (the state after the ticks, the ``protocol.StepLog`` of (B, T, ...) arrays).
        """
        if num_steps not in self._rollouts:
            fn = functools.partial(rollout_log, self.cpg_config, num_steps=num_steps)
            self._rollouts[num_steps] = jax.jit(per_shard(fn, (self.batch.in_axes, 0, 0, 0, 0), self.mesh))
        return self._rollouts[num_steps](
            self.batch.model,
            self.batch.profile,
            self._put(state),
            self._put(protocol.check_params(params, self.batch_size)),
            self._put(protocol.check_gates(gates, self.batch_size)),
        )
