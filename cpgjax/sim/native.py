"""The Go1 in C MuJoCo on the CPU: the paper's trial (``cpgjax.trial.protocol``) with native physics.

Physics: ``native_physics.BatchPhysics`` steps the whole batch one control tick per call, in place, on one thread
per core with one ``MjModel`` variant per instance, through ``cpgjax.sim.ffi_step`` or ``mujoco.batch`` from
Python (its stepping, ``native_physics.STEPPINGS``).

Control: a jitted, vmapped tick for the whole batch runs the shared sensor model (``cpgjax.go1.sensors.observe``)
and controller (``cpg.controller_step``) and writes the tick's record into a device buffer. With the ``ffi``
stepping (the default where ``cpgjax.sim.ffi_step`` builds) the whole trial is one compiled program: a
``lax.fori_loop`` whose body is the tick and the physics step, called through XLA's FFI; with two threads or more
an even batch runs in two halves whose controller and physics overlap (``_run_ffi_overlapped``). Otherwise the
host calls the tick once per control tick and steps the batch between calls, the buffer donated from call to call
(updated in place). At the end of a trial the buffer is summarized by ``protocol.summarize``, so a record means the
same thing whichever backend produced it.

Tick k is, as in the MJX backend (``cpgjax.mjx_go1``): observe S_k → controller → torque_k → physics step → S_{k+1}
→ record k.
Here the record's pre-step half (power, load, attitude, saturation) is computed with the control and its
post-step half (velocity, fall, failure) at the next call, which sees S_{k+1}:

    host:    [jit: finish record k−1 from S_k; observe S_k; control k] → [batch step: S_k → S_{k+1}] → [jit: ...]

Non-finite states: an instance that diverges in a physics step is put back to the standing pose by the physics
(``native_physics.BatchPhysics.step``) and its trial flagged ``failed`` here, like the MJX backend (see
docs/backends.md for the differences that remain).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import sensors
from cpgjax.go1 import terrain as terrains
from cpgjax.sim import ffi_step, native_physics
from cpgjax.sim.base import Backend
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol


class NativeState(NamedTuple):
    """Per-instance simulator and controller state between trials (leading batch axis on every leaf)."""

    physics: np.ndarray  # (B, nstate) float64 mjSTATE_FULLPHYSICS: clock [s], qpos, qvel (PhysicsLayout)
    warmstart: np.ndarray  # (B, nv) float64 qacc_warmstart for the next step (the last step's qacc)
    sensordata: np.ndarray  # (B, nsensordata) float64, as left by the last step (computed at its start, as in MJX)
    cpg: cpg.CPGState  # device arrays
    params: jax.Array  # (B, 8) the parameters applied at the end of the last trial
    io: physics_profiles.ActuatorSensorState  # device arrays: the physics profile's foot sensor and motors


# ----------------------------------------------------------------------------------------------- per-tick logic


class _Controller(NamedTuple):
    """The per-instance state on the controller's side of the physics step."""

    cpg: cpg.CPGState
    io: physics_profiles.ActuatorSensorState


@functools.partial(jax.jit, static_argnums=0)
def _rest_controller(cpg_config: cpg.CPGConfig, qpos, qvel, sensordata, gravity_mps2) -> _Controller:
    """The batch's controller at rest on its standing states (B, ...): a trial's start and a fallen instance's
    reset. One program, not one per operation."""
    obs = jax.vmap(sensors.observe)(qpos, qvel, sensordata, gravity_mps2)
    return _Controller(
        jax.vmap(functools.partial(cpg.init_state, config=cpg_config))(obs),
        jax.vmap(physics_profiles.init_state)(obs.foot_force_n),
    )


@functools.partial(jax.jit, static_argnums=0)
def _initial_phases(cpg_config: cpg.CPGConfig, phase_lag_rad) -> jax.Array:
    """The batch's oscillator phases at a start (B, 4) from its gaits' phase lags (B, 4, 4)."""
    return jax.vmap(functools.partial(cpg.initial_phase_rad, cpg_config))(phase_lag_rad)


class _Constants(NamedTuple):
    """Per-trial inputs of the jitted tick, each with a leading batch axis."""

    gravity_mps2: jax.Array  # (3,)
    reset: _Controller  # controller state after a reset
    prev_params: jax.Array  # (8,) start of the transition
    new_params: jax.Array  # (8,)
    gates: cpg.Gates
    profile: physics_profiles.ProfileArrays
    hfield_data: jax.Array | None  # (N,) the terrain model's heights (``terrain.hfield_data``); None on the plane


class _Carry(NamedTuple):
    """Controller-side state carried from tick to tick. In the compiled trial of the ``ffi`` stepping every field
    is its pytree; between the per-tick calls of the other steppings ``controller`` and ``pending`` travel as flat
    vectors and ``rows`` as one flat row per tick (``_Packing``): a handful of buffers per call keeps the per-tick
    dispatch cheap, and inside one program the pytrees spare the per-tick packing (what it costs: docs/backends.md,
    "How the native backend works")."""

    controller: _Controller | jax.Array  # the batch's _Controller (B, ...), or (C,) flat
    pending: object  # the batch's pre-step half of the last tick's row (B, ...), or (P,) flat
    step: jax.Array  # () int32, control ticks issued so far in this run
    rows: object  # the recorder's row of every tick (N, B, ...), or (N, R) one flat row per tick


class _Recorder(NamedTuple):
    """What a run records: the pre-step half of a row (at control time) and the row (after the physics step)."""

    pending: Callable  # (qpos, control: protocol.Control) -> pending
    row: Callable  # (trial_config, pending, qpos, qvel, failed, ground_height_m) -> row


def _trial_pending(qpos, c: protocol.Control) -> protocol.PreStep:
    del qpos
    return protocol.pre_step(c.obs, c.torque_nm, c.diag, c.joint_vel_rad_s)


def _log_pending(qpos, c: protocol.Control):
    # Feet before the step: MJX logs geom_xpos, which mjx.step computes at the start of the step.
    return (
        c.torque_nm,
        c.obs.foot_force_n,
        sensors.foot_positions(qpos),
        c.cpg.amplitude,
        c.cpg.phase_rad,
        c.diag.foot_target_m,
        c.diag.rpy_rad,
    )


def _log_row(trial_config, pending, qpos, qvel, failed, ground_height_m) -> protocol.StepLog:
    """``protocol.StepLog`` row with the MJX rollout's definitions (qpos, qvel after the step)."""
    del trial_config, failed, ground_height_m
    torque, force, feet, amplitude, phase, target, rpy = pending
    return protocol.StepLog(
        qpos=qpos,
        qvel=qvel,
        torque_nm=torque,
        foot_force_n=force,
        foot_pos_m=feet,
        amplitude=amplitude,
        phase_rad=phase,
        foot_target_m=target,
        rpy_rad=rpy,
    )


TRIAL_RECORDER = _Recorder(pending=_trial_pending, row=protocol.tick_row)
LOG_RECORDER = _Recorder(pending=_log_pending, row=_log_row)


def _control(
    cpg_config: cpg.CPGConfig,
    recorder: _Recorder,
    n_transition: int,
    k: jax.Array,
    consts: _Constants,
    controller: _Controller,
    qpos,
    qvel,
    sensordata,
):
    """The shared control tick for one instance at tick k, with the transition's linear parameter interpolation."""
    fraction = protocol.transition_fraction(k.astype(jnp.float32), n_transition)
    params = jnp.where(
        k < n_transition, protocol.transition_params(consts.prev_params, consts.new_params, fraction), consts.new_params
    )
    c = protocol.control(
        cpg_config,
        consts.profile,
        controller.io,
        controller.cpg,
        params,
        consts.gates,
        qpos,
        qvel,
        sensordata,
        consts.gravity_mps2,
    )
    return _Controller(c.cpg, c.io), c.torque_nm, recorder.pending(qpos, c)


class _Program(NamedTuple):
    """A run's compiled pieces for one recorder and trial timing (:meth:`NativeBackend._program`)."""

    packing: _Packing
    pending: object  # jax.ShapeDtypeStruct pytree of the batch's pre-step half of a row
    row: object  # jax.ShapeDtypeStruct pytree of the batch's row
    tick: Callable  # _advance on pytrees (consts, carry, host_in): what the ffi stepping's loop runs each tick
    run: Callable  # jitted _run_ffi: every tick and physics step of a run (the ffi stepping)
    advance: Callable  # jitted _advance on the flat carry: finish row k−1, control tick k (per-tick steppings)
    complete: Callable  # jitted _complete on the flat carry: finish the last row
    unpack_rows: Callable  # jitted: flat rows (N, R) → rows (N, B, ...)
    summarize: Callable  # jitted _summarize: rows → trial records


class _Packing(NamedTuple):
    """How the pytrees crossing the jitted boundary are flattened (``ravel_pytree``'s unravel functions) and how
    the host input row is laid out: [physics state | sensordata | failed]."""

    consts: Callable
    controller: Callable
    pending: Callable
    row: Callable
    layout: native_physics.PhysicsLayout
    nsensordata: int


def _host_inputs(packing: _Packing, host_in: jax.Array):
    """(qpos, qvel, sensordata, failed) of the batch from the packed float32 host input (B, W)."""
    lay = packing.layout
    sensordata = host_in[:, lay.size : lay.size + packing.nsensordata]
    return host_in[:, lay.qpos], host_in[:, lay.qvel], sensordata, host_in[:, -1] > 0.5


def _store_rows(rows, k: jax.Array, row):
    """``rows`` (N, B, ...) with tick ``k``'s row set, leaf by leaf."""
    return jax.tree.map(lambda r, x: r.at[k].set(x), rows, row)


def _store_flat_row(rows, k: jax.Array, row):
    """``rows`` (N, R), one flat row per tick, with tick ``k``'s row set."""
    return rows.at[k].set(ravel_pytree(row)[0])


def _ground_under_trunk_m(consts: _Constants, qpos: jax.Array) -> jax.Array | None:
    """The ground's height under each trunk origin (B,) on the batch's height fields; None on the plane."""
    if consts.hfield_data is None:
        return None
    r = go1_model.indices().root_qpos
    return jax.vmap(terrains.ground_height_m)(consts.hfield_data, qpos[:, r], qpos[:, r + 1])


def _complete(
    trial_config, recorder: _Recorder, packing: _Packing, store: Callable, consts: _Constants, carry: _Carry, host_in
) -> _Carry:
    """Finish the last tick's row from the state after its step (already reset where it failed); ``store`` writes
    it into ``carry.rows`` (``_store_rows`` or ``_store_flat_row``)."""
    qpos, qvel, _, failed = _host_inputs(packing, host_in)
    row = jax.vmap(functools.partial(recorder.row, trial_config))(
        carry.pending, qpos, qvel, failed, _ground_under_trunk_m(consts, qpos)
    )
    controller = protocol.where_batch(failed, consts.reset, carry.controller)
    return carry._replace(controller=controller, rows=store(carry.rows, carry.step - 1, row))


def _advance(
    cpg_config,
    trial_config,
    recorder: _Recorder,
    packing: _Packing,
    store: Callable,
    consts: _Constants,
    carry: _Carry,
    host_in,
) -> tuple[_Carry, jax.Array]:
    """The whole host-side tick: finish row k−1, then observe and control tick k.

    On the first tick of a run there is no row k−1; the row it writes for k − 1 = −1 is overwritten: by the run's
    real last row where ``store`` indexes from the end (``_store_rows``, ``_store_flat_row``), by row 0 at the next
    tick where it clamps to the first (the overlapped trial's).
    """
    carry = _complete(trial_config, recorder, packing, store, consts, carry, host_in)
    qpos, qvel, sensordata, _ = _host_inputs(packing, host_in)
    control = functools.partial(_control, cpg_config, recorder, trial_config.transition_steps, carry.step)
    controller, torque, pending = jax.vmap(control)(consts, carry.controller, qpos, qvel, sensordata)
    return _Carry(controller=controller, pending=pending, step=carry.step + 1, rows=carry.rows), torque


def _unravel(tree) -> Callable:
    """``ravel_pytree``'s unravel function for ``tree`` (arrays or ``jax.ShapeDtypeStruct``): found by tracing, so
    nothing is computed or compiled. (The function depends on the leaves' shapes and dtypes only.)"""
    found = []
    jax.eval_shape(lambda t: found.append(ravel_pytree(t)[1]), tree)
    return found[0]


def _flat_size(shapes) -> int:
    """The length of ``ravel_pytree``'s vector for a pytree of ``jax.ShapeDtypeStruct``."""
    return sum(int(np.prod(s.shape)) for s in jax.tree.leaves(shapes))


def _unflatten(packing: _Packing, carry: _Carry) -> _Carry:
    """The flat carry of the per-tick calls with its controller and pending half as pytrees (the rows stay one
    flat row per tick, written by ``_store_flat_row``)."""
    return carry._replace(controller=packing.controller(carry.controller), pending=packing.pending(carry.pending))


def _flatten(carry: _Carry) -> _Carry:
    return carry._replace(controller=ravel_pytree(carry.controller)[0], pending=ravel_pytree(carry.pending)[0])


def _flat_advance(packing: _Packing, advance: Callable, consts_flat, carry: _Carry, host_in):
    """``_advance`` (with ``_store_flat_row``) on the flat arguments of the per-tick calls."""
    carry, torque = advance(packing.consts(consts_flat), _unflatten(packing, carry), host_in)
    return _flatten(carry), torque


def _flat_complete(packing: _Packing, complete: Callable, consts_flat, carry: _Carry, host_in):
    """``_complete`` (with ``_store_flat_row``) on the flat arguments of the per-tick calls."""
    return _flatten(complete(packing.consts(consts_flat), _unflatten(packing, carry), host_in))


def _run_ffi(advance: Callable, complete: Callable, num_steps: int, handle, consts, carry: _Carry, host_in) -> _Carry:
    """A run's ``num_steps`` ticks in one program: each tick's ``_advance``, then the physics step through the FFI
    (``ffi_step.call``), whose output is the next tick's host input; then ``_complete``. ``handle`` names the
    stepper (``ffi_step.Stepper.handle``)."""

    def tick(_, loop):
        carry, host_in = loop
        carry, torque = advance(consts, carry, host_in)
        return carry, ffi_step.call(handle, torque, host_in.shape)

    carry, host_in = jax.lax.fori_loop(0, num_steps, tick, (carry, host_in))
    return complete(consts, carry, host_in)


def overlapped(batch_size: int, nthread: int) -> bool:
    """Whether the compiled trial runs the batch in two halves whose controller and physics overlap
    (``_run_ffi_overlapped``): with two threads or more and an even batch (an odd one runs whole)."""
    return nthread >= 2 and batch_size >= 2 and batch_size % 2 == 0


def _run_ffi_overlapped(
    advance: Callable, complete: Callable, num_steps: int, handle, consts, carry: _Carry, host_in
) -> _Carry:
    """``_run_ffi`` with the batch in two halves a and b whose controller and physics overlap: while the stepper's
    threads step one half, the program computes the other half's tick. ``advance`` and ``complete`` are
    ``_advance`` and ``_complete`` without their row store.

        half-tick j = 0, 1, …, 2N − 1:  the control of half j mod 2, tick ⌊j/2⌋ · start its step, finish the other's

    (``ffi_step.alternate``; the first finishes nothing). A finish steps on this thread what the threads have not
    taken of its half, then of the half just started. Both halves run one ``_advance`` (the loop's body, compiled
    once), on their slices of every batched argument: every instance sees the ticks of ``_run_ffi``. The order of
    the calls is fixed by data (each takes the torques computed from the last one's output)."""
    half, width = host_in.shape[0] // 2, host_in.shape[1]

    def halves(x, axis=0):  # the batch axis split into (2, half)
        return x.reshape(*x.shape[:axis], 2, half, *x.shape[axis + 1 :])

    # Slices and updates by lax's dynamic ops, which clamp their indices: unlike indexing and .at[].set on a traced
    # index, they put no index normalization and no bounds select into the loop's body (fewer of XLA's thunks).
    def store(p):  # tick k's row of half p into rows (N, 2, half, ...); k = −1 (the first tick) clamps to row 0
        return lambda rows, k, row: jax.tree.map(
            lambda r, x: jax.lax.dynamic_update_slice(r, x[None, None], (k, p) + (0,) * x.ndim), rows, row
        )

    def of_half(tree, p):
        return jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, p, keepdims=False), tree)

    consts, in_halves = jax.tree.map(halves, consts), halves(host_in)
    carry = carry._replace(
        controller=jax.tree.map(halves, carry.controller),
        pending=jax.tree.map(halves, carry.pending),
        rows=jax.tree.map(functools.partial(halves, axis=1), carry.rows),
    )

    def half_tick(j, loop):
        carry, in_p = loop
        p = j % 2
        tick = carry._replace(controller=of_half(carry.controller, p), pending=of_half(carry.pending, p), step=j // 2)
        tick, torque = advance(store(p), of_half(consts, p), tick, in_p)
        in_other = jnp.where(j == 0, in_halves[1], ffi_step.alternate(handle, torque, p, width))
        put = functools.partial(jax.tree.map, lambda whole, x: jax.lax.dynamic_update_index_in_dim(whole, x, p, 0))
        return carry._replace(
            controller=put(carry.controller, tick.controller), pending=put(carry.pending, tick.pending), rows=tick.rows
        ), in_other

    carry, in_a = jax.lax.fori_loop(0, 2 * num_steps, half_tick, (carry, in_halves[0]))

    def last_row(p, rows, in_p):  # half p's row of the last tick, from the state after its last step
        return complete(
            store(p),
            of_half(consts, p),
            carry._replace(
                controller=of_half(carry.controller, p),
                pending=of_half(carry.pending, p),
                rows=rows,
                step=jnp.int32(num_steps),
            ),
            in_p,
        )

    end_a = last_row(0, carry.rows, in_a)
    end_b = last_row(1, end_a.rows, ffi_step.finish(handle, in_a, (half, 2 * half), width))
    return _Carry(
        controller=jax.tree.map(lambda x, y: jnp.concatenate([x, y]), end_a.controller, end_b.controller),
        pending=jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), carry.pending),
        step=jnp.int32(num_steps),
        rows=jax.tree.map(lambda x: x.reshape(x.shape[0], -1, *x.shape[3:]), end_b.rows),
    )


def _summarize(
    trial_config: protocol.TrialConfig, dt_s: float, ticks: protocol.Tick, total_mass_kg
) -> protocol.TrialRecord:
    """Trial records (B, ...) from the run's rows (N, B, ...) with ``protocol.summarize`` (steady phase, plus the
    transition's falls, failures and worst margin)."""
    n_transition = trial_config.transition_steps
    steady = jax.tree.map(lambda x: x[n_transition:], ticks)
    transition = protocol.TransitionSummary.of(jax.tree.map(lambda x: x[:n_transition], ticks))
    return jax.vmap(protocol.summarize, in_axes=(1, 0, None, 0))(steady, total_mass_kg, dt_s, transition)


# ----------------------------------------------------------------------------------------------- batch interface


class NativeBackend(Backend):
    """A batch of simulated Go1s in C MuJoCo behind the interface of every backend (``cpgjax.sim.base.Backend``;
    fast on CPUs).

    >>> sim = NativeBackend(go1_model.make_scenarios(friction=[0.3, 0.6, 0.9]))
    >>> state = sim.reset(params)                               # params (3, 8), physical units
    >>> state, record = sim.trial(state, new_params, gates)     # the same protocol.TrialRecord as MJXBackend.trial
    """

    name = "native"

    def __init__(
        self,
        scenario: go1_model.Scenario,
        cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
        trial_config: protocol.TrialConfig = protocol.TrialConfig(),
        *,
        nthread: int | None = None,
        stepping: str | None = None,
    ):
        self.scenario = scenario
        self.cpg_config = cpg_config
        self.trial_config = trial_config
        lean_m = np.asarray(cpg.lean_x_m(cpg_config, go1_model.standing_imu_pitch_rad(scenario.slope_deg)))
        self.physics = native_physics.BatchPhysics(
            scenario, nthread=nthread, stepping=stepping, stand_foot_shift_m=lean_m
        )
        self._gravity = jnp.asarray(self.physics.gravity_mps2, jnp.float32)
        self._total_mass = jnp.asarray(self.physics.total_mass_kg, jnp.float32)
        lay, standing = self.physics.layout, self.physics.standing_physics.astype(np.float32)
        self._reset = _rest_controller(
            cpg_config,
            standing[:, lay.qpos],
            standing[:, lay.qvel],
            self.physics.standing_sensordata.astype(np.float32),
            self._gravity,
        )
        self._profile = jax.tree.map(
            jnp.asarray,
            physics_profiles.batch_arrays(
                scenario.physics, scenario.latency_ticks, scenario.noise_scale, scenario.noise_seed
            ),
        )
        self._host_in = np.zeros((self.batch_size, lay.size + self.physics.sensordata.shape[1] + 1), np.float32)
        self._hfield_data = (
            jnp.asarray(np.stack([m.hfield_data for m in self.physics.models]), jnp.float32)
            if go1_model.has_terrain(scenario)
            else None
        )
        self._compiled = {}

    @property
    def batch_size(self) -> int:
        return self.scenario.batch_size

    def with_scenario(self, scenario: go1_model.Scenario) -> NativeBackend:
        """This backend for another batch of scenarios; the compiled tick is reused when the batch size is the same
        (scenario values reach it as data). This backend's thread pool is released."""
        go1_model.check_same_model(self.scenario, scenario)
        other = NativeBackend(
            scenario, self.cpg_config, self.trial_config, nthread=self.physics.nthread, stepping=self.physics.stepping
        )
        if scenario.batch_size == self.batch_size:
            other._compiled = self._compiled
        self.physics.close()
        return other

    def reset(self, params, gates: cpg.Gates | None = None) -> NativeState:
        """Every instance standing at the origin with its CPG at rest in its gait's phases (``gates``; None: trot);
        ``params`` become the 'previous' set."""
        params = protocol.check_params(params, self.batch_size)
        p = self.physics
        rest = self._rest(protocol.check_gates(cpg.Gates(0.0, 0.0) if gates is None else gates, self.batch_size))
        return NativeState(
            physics=p.standing_physics.copy(),
            warmstart=np.zeros_like(p.warmstart),
            sensordata=p.standing_sensordata.copy(),
            cpg=rest.cpg,
            params=params,
            io=rest.io,
        )

    def _rest(self, gates: cpg.Gates) -> _Controller:
        """The controller at rest (a start's, a fall's reset) with the phases of the instances' gaits."""
        phase = _initial_phases(self.cpg_config, gates.phase_lag_rad)
        return self._reset._replace(cpg=self._reset.cpg._replace(phase_rad=phase))

    def _constants(self, prev_params, new_params, gates) -> _Constants:
        gates = protocol.check_gates(gates, self.batch_size)
        return _Constants(
            self._gravity,
            self._rest(gates),
            jnp.asarray(prev_params, jnp.float32),
            new_params,
            gates,
            self._profile,
            self._hfield_data,
        )

    def _program(self, recorder: _Recorder, trial_config: protocol.TrialConfig) -> _Program:
        """The run's compiled pieces (:class:`_Program`), compiled once per recorder and trial timing."""
        key = (recorder, trial_config)
        if key not in self._compiled:
            p = self.physics
            consts = self._constants(
                jnp.zeros((self.batch_size, param_space.NUM_PARAMS)),
                jnp.zeros((self.batch_size, param_space.NUM_PARAMS)),
                cpg.Gates(0.0, 0.0),
            )

            p_layout = _Packing(None, None, None, None, p.layout, p.sensordata.shape[1])

            def one_tick(consts):
                qpos, qvel, _, failed = _host_inputs(p_layout, jnp.zeros(self._host_in.shape))
                control = functools.partial(_control, self.cpg_config, recorder, 1, jnp.int32(0))
                _, _, pending = jax.vmap(control)(consts, consts.reset, qpos, qvel, jnp.zeros(p.sensordata.shape))
                row = jax.vmap(functools.partial(recorder.row, trial_config))(
                    pending, qpos, qvel, failed, _ground_under_trunk_m(consts, qpos)
                )
                return pending, row

            pending, row = jax.eval_shape(one_tick, consts)
            packing = _Packing(
                consts=_unravel(consts),
                controller=_unravel(self._reset),
                pending=_unravel(pending),
                row=_unravel(row),
                layout=p.layout,
                nsensordata=p.sensordata.shape[1],
            )
            advance = functools.partial(_advance, self.cpg_config, trial_config, recorder, packing)
            complete = functools.partial(_complete, trial_config, recorder, packing)
            tick = functools.partial(advance, _store_rows)
            num_steps = trial_config.transition_steps + trial_config.steady_steps
            run = (
                functools.partial(_run_ffi_overlapped, advance, complete, num_steps)
                if overlapped(self.batch_size, p.nthread)
                else functools.partial(_run_ffi, tick, functools.partial(complete, _store_rows), num_steps)
            )
            flat_advance = functools.partial(_flat_advance, packing, functools.partial(advance, _store_flat_row))
            flat_complete = functools.partial(_flat_complete, packing, functools.partial(complete, _store_flat_row))
            self._compiled[key] = _Program(
                packing=packing,
                pending=pending,
                row=row,
                tick=tick,
                run=jax.jit(run, donate_argnums=(2,)),
                advance=jax.jit(flat_advance, donate_argnums=(1,)),
                complete=jax.jit(flat_complete, donate_argnums=(1,)),
                unpack_rows=jax.jit(jax.vmap(packing.row)),
                summarize=jax.jit(functools.partial(_summarize, trial_config, self.cpg_config.dt_s)),
            )
        return self._compiled[key]

    def _pack_host_inputs(self, failed: np.ndarray) -> np.ndarray:
        p, buf = self.physics, self._host_in
        buf[:, : p.layout.size] = p.physics
        buf[:, p.layout.size : -1] = p.sensordata
        buf[:, -1] = failed
        return buf

    @staticmethod
    def _first_carry(program: _Program, controller: _Controller, num_steps: int, flat: bool) -> _Carry:
        """The carry of a run's first tick: pytrees for the compiled trial, flat for the per-tick calls."""
        if flat:
            return _Carry(
                controller=ravel_pytree(controller)[0],
                pending=np.zeros(_flat_size(program.pending), np.float32),
                step=np.int32(0),
                rows=np.zeros((num_steps, _flat_size(program.row)), np.float32),
            )
        return _Carry(
            controller=jax.tree.map(jnp.array, controller),  # a copy: the run updates it in place
            pending=jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), program.pending),
            step=np.int32(0),
            rows=jax.tree.map(lambda s: np.zeros((num_steps, *s.shape), s.dtype), program.row),
        )

    def _run(
        self, state: NativeState, recorder: _Recorder, trial_config: protocol.TrialConfig, consts: _Constants
    ) -> tuple[_Controller, object]:
        """Run ``transition_steps + steady_steps`` ticks from ``state``; returns the controller-side state and the
        recorder's rows (N, B, ...). The physics state is left in ``self.physics``."""
        program = self._program(recorder, trial_config)
        num_steps = trial_config.transition_steps + trial_config.steady_steps
        p = self.physics
        p.set_state(state.physics, state.warmstart, state.sensordata)
        controller = _Controller(state.cpg, state.io)
        failed = np.zeros(self.batch_size, bool)
        if p.stepping == "ffi":
            carry = program.run(
                p.ffi_handle,
                consts,
                self._first_carry(program, controller, num_steps, flat=False),
                self._pack_host_inputs(failed),
            )
            # The program steps the physics arrays in place: done before anything reads or frees them (JAX may
            # return before a computation finishes).
            carry = jax.block_until_ready(carry)
            return carry.controller, carry.rows
        consts_flat = ravel_pytree(consts)[0]
        carry = self._first_carry(program, controller, num_steps, flat=True)
        advance = program.advance  # one attribute lookup, not one per tick
        for _ in range(num_steps):
            carry, torque = advance(consts_flat, carry, self._pack_host_inputs(failed))
            failed = p.step(np.asarray(torque))
        carry = program.complete(consts_flat, carry, self._pack_host_inputs(failed))
        return program.packing.controller(carry.controller), program.unpack_rows(carry.rows)

    def trial(self, state: NativeState, new_params, gates: cpg.Gates) -> tuple[NativeState, protocol.TrialRecord]:
        """One trial for every instance. Returns the next state and the records (same fields as MJXBackend's)."""
        new_params = protocol.check_params(new_params, self.batch_size)
        consts = self._constants(state.params, new_params, gates)
        controller, ticks = self._run(state, TRIAL_RECORDER, self.trial_config, consts)
        record = self._program(TRIAL_RECORDER, self.trial_config).summarize(ticks, self._total_mass)
        fell = np.asarray(record.fell) > 0
        self.physics.reset(fell)
        if self._hfield_data is not None:  # back into the terrain's central period: the same ground under the robot
            root = self.physics.layout.qpos.start + go1_model.indices().root_qpos
            xy = self.physics.physics[:, root : root + 2]  # a view: moved in place
            xy[:] = terrains.wrap_xy_m(xy)
        controller = protocol.where_batch(fell, consts.reset, controller)
        return NativeState(*self.physics.get_state(), cpg=controller.cpg, params=new_params, io=controller.io), record

    def rollout(
        self, state: NativeState, params, gates: cpg.Gates, num_steps: int
    ) -> tuple[NativeState, protocol.StepLog]:
        """``num_steps`` logged ticks with constant parameters for every instance (log arrays are (B, T, ...))."""
        params = protocol.check_params(params, self.batch_size)
        config = protocol.TrialConfig(transition_steps=0, steady_steps=num_steps)
        controller, rows = self._run(state, LOG_RECORDER, config, self._constants(params, params, gates))
        log = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), rows)
        return NativeState(*self.physics.get_state(), cpg=controller.cpg, params=params, io=controller.io), log
