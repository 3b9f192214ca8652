r"""The lockstep engine: Algorithm 1 for a whole batch of instances at once.

A study is a grid of instances — controller × seed × friction × slope × payload × target velocity × condition
schedule × data reuse (:class:`cpgjax.study.spec.StudySpec`) — each running
its own online optimization. Every trial is one lockstep
round for the whole batch::

    x = vmap(propose)(opt_state, c_prev, keys)          # eq. (8) argmax, or random for the first 2 trials
    sim_state, record = backend.trial(sim_state, x, gates)   # 1.5 s transition + 3 s steady phase
    opt_state = vmap(observe)(opt_state, x, c(record), record or J)   # eqs. (9)-(11), GP refit

A :class:`Schedule` changes an instance's conditions from a given trial on (payload +7.5 kg at trial 36, slope 0° → 10°
→ 12.5°, target 0.8 → 0.3 → 0.6 m/s, inference mode, the ramp: each of its trials on the slope climbed to,
``study_spec.walked``); a target change either reuses the stored trial records (paper Sec. III-A-2: ``set_target``
recomputes every stored J) or restarts the optimizer, per instance. The proposal of trial t uses the context measured in
trial t − 1 (Algorithm 1: context, then argmax); if trial t − 1 fell, the one it was proposed for (a fallen robot
measures no ground).

The optimizer's arrays are sharded along the batch axis over every device (``jax.sharding``), the simulator's over this
process's devices (``cpgjax.study.placement``). With several processes (``jax.distributed``,
``study.placement.initialize_distributed``, docs/scaling.md) each owns a contiguous block of instances, the rows of its
devices' shards (``Placement.rows``): it simulates only those, computes only their optimizer shards, and per trial sends
the other processes only their trial logs, the data of the report (``study.placement.exchange``). Keys are
``fold_in(PRNGKey(seed), trial)``, so an instance's random draws do not depend on the batch it is in or on the devices;
its numbers agree to float rounding only (XLA vectorizes differently for another batch size or shard), and a walking
robot amplifies a rounding difference within a trial or two, so one seed in two different batches gives statistically
equivalent, not identical, runs. How the instances are split over processes does not matter, only the optimizer's batch
per device: 2 processes × 1 CPU device give the bits of 1 process × 2 CPU devices. The state is checkpointed after every
trial (``cpgjax.study.files``) and :meth:`Engine.run` with ``resume=True`` continues from the last checkpoint to exactly
(bit for bit) the results of an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax.go1 import model as go1_model
from cpgjax.optim import bo
from cpgjax.optim import config as optimizer_config
from cpgjax.sim import backends
from cpgjax.sim.base import Backend
from cpgjax.study import batch as study_batch
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
from cpgjax.study import spec as study_spec
from cpgjax.study.spec import Conditions, StudySpec, instances, validate
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------- the engine


class Timing(NamedTuple):
    """Wall seconds spent, summed over trials (and resumed segments)."""

    simulation_s: float  # the backend's trials
    optimizer_s: float  # propose_s + observe_s
    propose_s: float  # β, keys, target changes, the UCB argmax (eq. 8)
    observe_s: float  # storing the observation and refitting the GP
    transfer_s: float  # device → host → device of the records
    exchange_s: float  # several processes: sending and awaiting the trial logs (includes waiting for the slowest)
    checkpoint_s: float


class Progress(NamedTuple):
    """Handed to the progress callback after every trial."""

    trial: int  # trials done
    num_trials: int
    best_by_group: dict[str, float]  # best J so far per group
    env_steps_per_s: float  # over this segment's trials after its first (which compiles), if there are any
    eta_s: float | None  # from those trials' pace; None after the segment's first trial


class StudyResult(NamedTuple):
    spec: StudySpec
    labels: list[dict[str, Any]]
    conditions: Conditions  # planned: the study's (study_spec.conditions)
    walked: Conditions  # what the trials walked: the ramp's trials at the slopes climbed to (study_spec.walked)
    trials: study_io.TrialLog  # every field (num_trials, B, ...)
    opt_state: bo.OptimizerState  # final, host arrays: instances rows[0] … rows[1] − 1 (all with one process)
    wall_s: float  # compute wall time, summed over resumed segments
    timing: Timing
    backend: str
    devices: list[str]
    rows: tuple[int, int]  # the instances this process simulated: [first, stop)


def _record_template(trial: protocol.TrialConfig) -> protocol.TrialRecord:
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    fields = {f: scalar for f in protocol.TrialRecord._fields}
    fields["velocity_xy_mps"] = jax.ShapeDtypeStruct((trial.steady_steps, 2), jnp.float32)
    return protocol.TrialRecord(**fields)


class _Run(NamedTuple):
    """What :meth:`Engine.run` carries from trial to trial (host-side; ``timing`` is updated in place)."""

    start: int  # the first trial of this segment (> 0 after a resume)
    opt_state: Any  # optimizer state, sharded
    sim_state: Any  # backend state (None before the first trial)
    context: np.ndarray  # (local rows, 2) context measured in the last trial
    logs: list  # a study_io.TrialLog (every instance) per completed trial
    wall_before: float  # compute wall time of earlier segments [s]
    timing: dict[str, float]  # Timing's fields, summed


@contextlib.contextmanager
def _timed(timing: dict[str, float], *keys: str):
    """Add the wall time of the block to each of ``timing[key]``."""
    t0 = time.perf_counter()
    yield
    elapsed = time.perf_counter() - t0
    for key in keys:
        timing[key] += elapsed


class _ShardedOptimizer(NamedTuple):
    """The optimizer's functions of the whole batch, sharded along it (``Placement.per_instance``)."""

    init: Callable  # (active dims, target velocity) → optimizer state
    propose: Callable  # (state, context, keys) → (x, fell back); eq. (8), or random for the first trials
    observe: Callable  # (state, x, context, observation, safety margin) → (state, accepted); eqs. (9)-(11)
    beta: Callable  # (state, context) → β and whether the context changed
    set_target: Callable | None  # (state, target velocity) → state, every stored J recomputed; None without records
    keys: Callable  # (seeds, trial) → fold_in(PRNGKey(seed), trial) per instance
    summary: Callable  # (records, target velocities) → (J, context, mean velocity, CoT), vmapped, jitted


def _sharded_optimizer(
    spec: StudySpec, config: optimizer_config.OptimizerConfig, placement: study_placement.Placement, uses_records: bool
) -> _ShardedOptimizer:
    """The optimizer of ``config`` for the batch of ``placement``: observing trial records (``uses_records``: some
    target changes, and ``set_target`` recomputes every stored J) or J, scored with ``spec``'s objective floor."""
    score = functools.partial(objective.objective, floor=spec.switch_values().objective_floor)
    opt = bo.make_optimizer(config, score, _record_template(spec.trial)) if uses_records else bo.make_optimizer(config)
    init = (
        (lambda a, t: opt.init(active_dims=a, target_velocity=t))
        if uses_records
        else (lambda a, t: opt.init(active_dims=a))
    )

    def observe_unconstrained(state, x, c, observation, margin):
        del margin  # only a safe optimizer learns it
        return opt.observe(state, x, c, observation)

    return _ShardedOptimizer(
        init=placement.per_instance(init),
        propose=placement.per_instance(opt.propose_with_fallback),
        observe=placement.per_instance(opt.observe if config.safe else observe_unconstrained),
        beta=placement.per_instance(opt.beta),
        set_target=placement.per_instance(opt.set_target) if uses_records else None,
        keys=placement.per_instance(lambda seed, t: jax.random.fold_in(jax.random.PRNGKey(seed), t), in_axes=(0, None)),
        summary=jax.jit(
            jax.vmap(
                lambda r, v: (
                    score(r, v),
                    objective.context(r),
                    objective.mean_velocity(r),
                    objective.cost_of_transport(r),
                )
            )
        ),
    )


def _change_targets(
    sharded: _ShardedOptimizer,
    batch: study_batch.InstanceBatch,
    placement: study_placement.Placement,
    opt_state,
    trial: int,
):
    """Data reuse (``set_target``) or a fresh optimizer for instances whose target changes at ``trial``."""
    targets = batch.padded.target_velocity_mps
    changed = targets[:, trial] != targets[:, trial - 1]
    if trial == 0 or not changed.any():
        return opt_state
    new_target = placement.put(jnp.asarray(targets[:, trial], jnp.float32))
    reused = sharded.set_target(opt_state, new_target)
    fresh = sharded.init(placement.put(batch.active), new_target)
    fresh = protocol.where_batch(placement.put(~batch.reuse), fresh, reused)
    return protocol.where_batch(placement.put(changed), fresh, opt_state)


def _clip_context(config: optimizer_config.OptimizerConfig, trial: int, context: np.ndarray, real: int) -> np.ndarray:
    """The measured contexts clipped to ``config``'s ranges for the GP (docs/decisions.md §11), with a log line when
    any of the first ``real`` rows (the instances, not the padding's copies) is; the trial log keeps the measured
    values."""
    clipped, messages = optimizer_config.clip_context(
        config, context[:real], objective.CONTEXT_NAMES, objective.CONTEXT_UNITS
    )
    if messages:
        log.warning(
            "trial %d: %d context value(s) outside the GP's range, clipped; first: %s",
            trial,
            len(messages),
            messages[0],
        )
    return np.concatenate([clipped, np.clip(context[real:], config.context_lower, config.context_upper)]).astype(
        np.float32
    )


def group_names(spec: StudySpec, labels: list[dict[str, Any]]) -> list[str]:
    """Each instance's group: its labels' values of ``spec.group_by``, joined by ", ".

    Args:
      spec: the study.
      labels: each instance's labels (``study_spec.instances``).

    Returns:
      One name per instance, in the order of ``labels``.
    """
    return [", ".join(str(lab[g]) for g in spec.group_by) for lab in labels]


def best_by_group(spec: StudySpec, labels: list[dict[str, Any]], logs: list[study_io.TrialLog]) -> dict[str, float]:
    """The best objective J so far per group (:func:`group_names`).

    Args:
      spec: the study.
      labels: each instance's labels (``study_spec.instances``), B of them.
      logs: one trial log per completed trial (at least one), each with every row of the padded batch.

    Returns:
      Group name → the largest J over the logs' trials and the group's instances.
    """
    j = np.stack([np.asarray(lg.objective)[: len(labels)] for lg in logs])  # (t, B)
    best: dict[str, float] = {}
    for b, name in enumerate(group_names(spec, labels)):
        best[name] = max(best.get(name, -np.inf), float(j[:, b].max()))
    return best


class Engine:
    """Runs a :class:`StudySpec` in lockstep (see the module docstring).

    Args:
      spec: the study (validated here; a bad option raises :class:`StudyError` before any compute).
      backend: "auto" (native C MuJoCo on CPU-only machines, MJX with an accelerator), "mjx" or "native".
      devices: devices to shard the batch over (default: all, on every host); every process needs one among them.

    Raises:
      StudyError: an option :func:`validate` refuses, or (MJX) a batch per device that ``backends.check_mjx_layout``
        refuses; the message names the study.
    """

    def __init__(self, spec: StudySpec, *, backend: str = "auto", devices=None):
        self.conditions = validate(spec)
        self.spec = spec
        self.labels = instances(spec)
        self.backend_name = backends.resolve_backend(backend)
        self.batch_size = len(self.labels)
        self.placement = study_placement.make_placement(self.batch_size, devices)
        self.instance_rows = self.placement.instance_rows(self.batch_size)  # this process's instances
        self.local_instances = self.instance_rows[1] - self.instance_rows[0]  # its rows before the padding's copies
        if self.backend_name == "mjx":  # before any compute
            local = self.placement.local_devices
            try:
                backends.check_mjx_layout((self.placement.rows[1] - self.placement.rows[0]) // len(local), local)
            except ValueError as err:
                raise study_spec.StudyError(f"study {spec.name!r}: {err}") from None
        self.batch = study_batch.instance_batch(self.labels, self.conditions, self.placement)
        self.optimizer_config = spec.optimizer_config()
        self.sharded = _sharded_optimizer(spec, self.optimizer_config, self.placement, self.batch.uses_records)
        self._sim = None

    # -- pieces ---------------------------------------------------------------------------------------------

    def simulator(self, trial: int, conditions: Conditions | None = None) -> Backend:
        """The backend of this process's instances for trial ``trial``'s scenario (under ``conditions``, see
        ``InstanceBatch.scenario_at``), on this process's devices; rebuilt (reusing its compiled code where the backend
        allows) only when one of its instances' conditions change.

        Args:
          trial: the trial whose conditions the scenario takes, 0 … ``num_trials`` − 1.
          conditions: the padded batch's conditions, each (padded B, num_trials) (default: ``batch.padded``).

        Returns:
          The backend of the padded batch's rows ``placement.rows``; the one of the previous call while their
          scenario is unchanged.
        """
        first, stop = self.placement.rows
        scenario = go1_model.Scenario(*(field[first:stop] for field in self.batch.scenario(trial, conditions)))
        if self._sim is None:
            self._sim = backends.make_backend(
                scenario,
                self.backend_name,
                self.spec.cpg_config(),
                self.spec.trial,
                devices=self.placement.local_devices,
            )
        elif any(not np.array_equal(a, b) for a, b in zip(scenario, self._sim.scenario, strict=True)):
            self._sim = self._sim.with_scenario(scenario)
        return self._sim

    def initial_opt_state(self) -> bo.OptimizerState:
        """Every instance's optimizer state before its first trial: ``init`` with its active parameters (and, where
        the engine observes trial records, the target velocity of its first trial).

        Returns:
          The padded batch's optimizer state, sharded along the batch over the placement's devices.
        """
        targets = jnp.asarray(self.batch.padded.target_velocity_mps[:, 0], jnp.float32)
        return self.sharded.init(self.placement.put(self.batch.active), self.placement.put(targets))

    def initial_context(self) -> np.ndarray:
        """(local rows, 2): the middle of the optimizer's context ranges.

        Returns:
          (local rows, 2) float32, each row [c_load N, c_slope rad] (``objective.CONTEXT_NAMES``), one per row of
          ``placement.rows``.
        """
        config = self.optimizer_config
        mid = 0.5 * (np.asarray(config.context_lower) + np.asarray(config.context_upper))
        first, stop = self.placement.rows
        return np.tile(mid, (stop - first, 1)).astype(np.float32)

    # -- the loop -------------------------------------------------------------------------------------------

    def run(
        self, out_dir=None, *, resume: bool = False, progress: Callable[[Progress], None] | None = None
    ) -> StudyResult:
        """Run (or, with ``resume``, continue from ``out_dir``'s checkpoint) every trial of the study.

        With ``out_dir`` the state is checkpointed atomically after every trial (each process its own instances).
        ``progress`` is called on process 0 only.

        Args:
          out_dir: the directory of the checkpoints (None: none are written).
          resume: continue from ``out_dir``'s newest checkpoint; with none there, start at trial 0.
          progress: called with a :class:`Progress` after every trial (None: not called).

        Returns:
          The study's :class:`StudyResult`: every instance's trials, this process's final optimizer state, the wall
          time and its :class:`Timing`, both summed over resumed segments.
        """
        spec, n = self.spec, self.spec.num_trials
        run = self._start(out_dir, resume)
        t_begin = t_first = time.perf_counter()
        env_steps = self.batch_size * (spec.trial.transition_steps + spec.trial.steady_steps)
        for t in range(run.start, n):
            run = self._trial(run, t)
            wall = run.wall_before + time.perf_counter() - t_begin
            if out_dir is not None:
                with _timed(run.timing, "checkpoint_s"):
                    self._checkpoint(out_dir, run, t, wall)
            if t == run.start:
                t_first = time.perf_counter()  # the first trial compiles: the pace is that of the later ones
            if progress is not None and jax.process_index() == 0:
                paced = t - run.start
                if paced:
                    per_trial = max(time.perf_counter() - t_first, 1e-9) / paced
                    figures = env_steps / per_trial, (n - t - 1) * per_trial
                else:
                    figures = env_steps / max(time.perf_counter() - t_begin, 1e-9), None
                progress(Progress(t + 1, n, best_by_group(self.spec, self.labels, run.logs), *figures))
        wall_s = run.wall_before + time.perf_counter() - t_begin
        rows = self.instance_rows
        walked = Conditions(*(c[: self.batch_size] for c in self.walked(run.logs)))
        return StudyResult(
            spec=spec,
            labels=self.labels,
            conditions=self.conditions,
            walked=walked,
            trials=study_io.stacked(run.logs, self.batch_size),
            opt_state=jax.tree.map(lambda a: a[: rows[1] - rows[0]], self.placement.local(run.opt_state)),
            wall_s=wall_s,
            timing=Timing(**run.timing),
            backend=self.backend_name,
            devices=[str(d) for d in self.placement.mesh.devices.flat],
            rows=rows,
        )

    def _start(self, out_dir, resume: bool) -> _Run:
        """The run's state before its first trial: fresh, or restored from ``out_dir``'s checkpoint."""
        run = _Run(
            start=0,
            opt_state=self.initial_opt_state(),
            sim_state=None,
            context=self.initial_context(),
            logs=[],
            wall_before=0.0,
            timing={name: 0.0 for name in Timing._fields},
        )
        ckpt = (
            study_io.resume_checkpoint(
                out_dir, self.spec, self.placement.local(run.opt_state), self.placement, self.batch_size
            )
            if resume
            else None
        )
        if ckpt is None:
            return run
        opt_state = self.placement.put_local(jax.tree.unflatten(jax.tree.structure(run.opt_state), ckpt.opt_leaves))
        sim_state = self._restore_sim(ckpt.trial, ckpt.sim_leaves) if ckpt.trial < self.spec.num_trials else None
        log.info("resumed %s at trial %d", self.spec.name, ckpt.trial)
        return _Run(
            start=ckpt.trial,
            opt_state=opt_state,
            sim_state=sim_state,
            context=ckpt.context,
            logs=ckpt.logs,
            wall_before=ckpt.wall_s,
            timing={**run.timing, **ckpt.timing},
        )

    def _trial(self, run: _Run, t: int) -> _Run:
        """Trial ``t`` for this process's instances: propose (eq. 8), simulate, summarize (eqs. 9-11), observe; then
        every process's trial logs."""
        put, put_local, local, timing = self.placement.put, self.placement.put_local, self.placement.local, run.timing
        first, stop = self.placement.rows
        with _timed(timing, "propose_s", "optimizer_s"):
            opt_state = _change_targets(self.sharded, self.batch, self.placement, run.opt_state, t)
            opt_state = opt_state._replace(inference_mode=put(self.batch.padded.inference[:, t]))
            keys = self.sharded.keys(put(self.batch.seeds.astype(np.uint32)), t)
            ctx = put_local(run.context)
            beta = self.sharded.beta(opt_state, ctx)
            x, fell_back = self.sharded.propose(opt_state, ctx, keys)
            # In the box as they are: the optimizer rounds its bounds inward to float32 (optim.bo), so no proposal
            # crosses the float64 box that the simulator validates.
            x, fell_back = local(x).astype(np.float64), local(fell_back)
            real = self.local_instances
            if fell_back[:real].any():
                log.warning(
                    "trial %d: %d instance(s) had no parameters certified safe for their context and repeat "
                    "the safe trial with the highest expected margin there (docs/decisions.md §17)",
                    t,
                    int(fell_back[:real].sum()),
                )
        with _timed(timing, "simulation_s"):
            sim = self.simulator(t, self.walked(run.logs))
            sim_state = sim.reset(x, self.batch.local_gates) if run.sim_state is None else run.sim_state
            sim_state, record = sim.trial(sim_state, x, self.batch.local_gates)
            record = jax.block_until_ready(record)
        with _timed(timing, "transfer_s"):
            rec = study_placement.fetch(record)
            target = self.batch.padded.target_velocity_mps[first:stop, t].astype(np.float32)
            j, new_context, velocity, cot = study_placement.fetch(self.sharded.summary(rec, target))
            # A trial that fell measured a robot on the ground (its feet carry nothing: c_load ≈ 0 N), not the
            # ground it walked: the optimizer takes the context the trial was proposed for, as on the robot
            # (deployment.trials), both for this observation and for the next proposal (docs/decisions.md §11).
            unmeasured = ((np.asarray(rec.fell) > 0) | (np.asarray(rec.failed) > 0))[:, None]
            gp_context = _clip_context(
                self.optimizer_config, t, np.where(unmeasured, run.context, new_context), self.local_instances
            )
            record_d, x_d = put_local(rec), put_local(x.astype(np.float32))
        with _timed(timing, "observe_s", "optimizer_s"):
            observation = record_d if self.batch.uses_records else put_local(j)
            opt_state, accepted = self.sharded.observe(
                opt_state, x_d, put_local(gp_context), observation, put_local(rec.safety_margin)
            )
            accepted = jax.block_until_ready(accepted)
        trial_log = study_io.TrialLog(
            params=x,
            context=new_context,
            objective=j,
            velocity_xy_mps=velocity,
            cot=cot,
            beta=local(beta.beta),
            context_changed=local(beta.context_changed),
            accepted=local(accepted),
            roll_std_rad=rec.roll_std_rad,
            pitch_std_rad=rec.pitch_std_rad,
            saturation_fraction=rec.saturation_fraction,
            energy_j=rec.energy_j,
            distance_m=rec.distance_m,
            total_mass_kg=rec.total_mass_kg,
            fell=rec.fell,
            failed=rec.failed,
            safety_margin=rec.safety_margin,
            safe_fallback=fell_back,
        )
        with _timed(timing, "exchange_s"):
            parts = study_placement.exchange(trial_log)
            trial_log = study_io.TrialLog(*(np.concatenate(f) for f in zip(*parts, strict=True)))
        return run._replace(
            opt_state=opt_state,
            sim_state=sim_state,
            context=np.asarray(gp_context, np.float32),
            logs=run.logs + [trial_log],
        )

    def walked(self, logs: list[study_io.TrialLog]) -> Conditions:
        """The padded batch's conditions walked after the trials of ``logs`` (``study_spec.walked``): the ramp's
        trials at the slopes climbed to. The logs hold every instance, so each process computes the same slopes, and
        a resume computes them again from its logs.

        Args:
          logs: one trial log per completed trial, each with every row of the padded batch.

        Returns:
          The padded batch's conditions, each (padded B, num_trials); the trials after trial ``len(logs)`` keep the
          planned slopes.
        """
        distance_m = np.array([np.asarray(lg.distance_m) for lg in logs])
        fell = np.array([np.asarray(lg.fell) for lg in logs])
        return study_spec.walked(self.batch.padded, self.spec.ramp, distance_m, fell, self.spec.trial)

    def _checkpoint(self, out_dir, run: _Run, t: int, wall_s: float) -> None:
        """This process's instances (not their padding copies) after trial ``t``; once every process has written
        trial t, the files a resume no longer needs are deleted (``study_io.prune_checkpoints``)."""
        first = self.placement.rows[0]
        shard = study_io.Shard(jax.process_index(), jax.process_count(), first)
        ckpt = study_io.process_checkpoint(
            t + 1,
            self.placement.local(run.opt_state),
            run.sim_state,
            run.context,
            run.logs,
            (first, self.local_instances),
            wall_s,
            run.timing,
        )
        study_io.save_checkpoint(out_dir, self.spec, ckpt, self.backend_name, shard)
        # Trial t's logs came from every process, so each has written trial t − 1 (one process: t itself).
        complete = t + 1 if shard.num_processes == 1 else t
        if complete > run.start:
            study_io.prune_checkpoints(out_dir, shard, complete)

    def _restore_sim(self, trial: int, leaves):
        sim = self.simulator(max(trial - 1, 0))
        first, stop = self.placement.rows
        template = sim.reset(np.tile(param_space.midpoint(), (stop - first, 1)))
        treedef = jax.tree.structure(template)
        kinds = [type(x) for x in jax.tree.leaves(template)]
        restored = [leaf if kind is np.ndarray else jnp.asarray(leaf) for leaf, kind in zip(leaves, kinds, strict=True)]
        return jax.tree.unflatten(treedef, restored)  # the backend places it on its devices
