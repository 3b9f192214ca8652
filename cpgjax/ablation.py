r"""The lockstep engine: Algorithm 1 for a whole batch of instances at once.

A study is a grid of instances — controller × seed × friction × slope × payload × target velocity × condition
schedule × data reuse (:class:`StudySpec`) — each running its own online optimization. Every trial is one lockstep
round for the whole batch::

    x = vmap(propose)(opt_state, c_prev, keys)          # eq. (8) argmax, or random for the first 2 trials
    sim_state, record = backend.trial(sim_state, x, gates)   # 1.5 s transition + 3 s steady phase
    opt_state = vmap(observe)(opt_state, x, c(record), record or J)   # eqs. (9)-(11), GP refit

A :class:`Schedule` changes an instance's conditions from a given trial on (payload +7.5 kg at trial 36, slope
0° → 10° → 12.5°, target 0.8 → 0.3 → 0.6 m/s, inference mode); a target change either reuses the stored trial
records (paper Sec. III-A-2: ``set_target`` recomputes every stored J) or restarts the optimizer, per instance.
The proposal of trial t uses the context measured in trial t − 1 (Algorithm 1: context, then argmax).

The optimizer's arrays (and, with the MJX backend, the simulator's) are sharded along the batch axis over every
device (``jax.sharding``; several hosts through ``jax.distributed``, see :func:`initialize_distributed`). Keys are
``fold_in(PRNGKey(seed), trial)``, so an instance's random draws do not depend on the batch it is in or on the
devices; its numbers agree to float rounding only (XLA vectorizes differently for another batch size or shard), and
a walking robot amplifies a rounding difference within a trial or two, so one seed in two different batches gives
statistically equivalent, not identical, runs. The state is checkpointed after every trial (``cpgjax.study_io``) and
:meth:`Engine.run` with ``resume=True`` continues from the last checkpoint to exactly (bit for bit) the results of
an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cpgjax import backends, bo, cpg, go1_model, mjx_go1, objective, params as param_space, study_io

log = logging.getLogger(__name__)

CONDITION_FIELDS = ("friction", "slope_deg", "payload_kg", "target_velocity_mps")
SCHEDULE_FIELDS = CONDITION_FIELDS + ("inference",)
MAX_TARGET_VELOCITY_MPS = 2.0


class StudyError(ValueError):
    """A study option that cannot run; raised before any compute."""


class Change(NamedTuple):
    """From ``trial`` on, ``field`` (one of :data:`SCHEDULE_FIELDS`) takes ``value`` (inference: 0 or 1)."""

    trial: int
    field: str
    value: float


class Schedule(NamedTuple):
    """A named sequence of condition changes, one grid axis of a study."""

    label: str
    changes: tuple[Change, ...] = ()


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """A batch of online optimizations: the grid of instances, their schedules, and the static structure.

    Attributes:
      name: the study's name (output folder, metadata).
      num_trials: trials per instance (each 1.5 s + 3 s at the paper's timing).
      controllers, seeds, friction, slope_deg, payload_kg, target_velocity_mps, schedules, data_reuse: grid axes;
        an instance is one element of their product, in this order.
      group_by: instance labels whose combinations form the groups of the progress display and the summaries.
      trial: trial timing (static).
      optimizer: the optimizer's static structure; ``None`` = :func:`bo.paper_config` with capacity ``num_trials``.
    """

    name: str
    num_trials: int = 40
    controllers: tuple[str, ...] = ("vmc_tegotae",)
    seeds: tuple[int, ...] = (0,)
    friction: tuple[float, ...] = (0.6,)
    slope_deg: tuple[float, ...] = (0.0,)
    payload_kg: tuple[float, ...] = (0.0,)
    target_velocity_mps: tuple[float, ...] = (0.5,)
    schedules: tuple[Schedule, ...] = (Schedule("constant"),)
    data_reuse: tuple[bool, ...] = (True,)
    group_by: tuple[str, ...] = ("controller",)
    trial: mjx_go1.TrialConfig = mjx_go1.TrialConfig()
    optimizer: bo.OptimizerConfig | None = None

    def optimizer_config(self) -> bo.OptimizerConfig:
        return bo.paper_config(capacity=self.num_trials) if self.optimizer is None else self.optimizer


LABELS = ("controller", "seed", "friction", "slope_deg", "payload_kg", "target_velocity_mps", "schedule",
          "data_reuse")


def instances(spec: StudySpec) -> list[dict[str, Any]]:
    """The labels of every instance of the grid, in batch order."""
    axes = (spec.controllers, spec.seeds, spec.friction, spec.slope_deg, spec.payload_kg, spec.target_velocity_mps,
            [s.label for s in spec.schedules], spec.data_reuse)
    return [dict(zip(LABELS, combo)) for combo in itertools.product(*axes)]


class Conditions(NamedTuple):
    """Per-instance, per-trial conditions, each (B, num_trials)."""

    friction: np.ndarray
    slope_deg: np.ndarray
    payload_kg: np.ndarray
    target_velocity_mps: np.ndarray
    inference: np.ndarray  # bool


def conditions(spec: StudySpec) -> Conditions:
    """Apply every instance's schedule to its grid values (validated by :func:`validate`)."""
    labels = instances(spec)
    schedules = {s.label: s for s in spec.schedules}
    n = spec.num_trials
    out = {f: np.zeros((len(labels), n)) for f in SCHEDULE_FIELDS}
    for b, lab in enumerate(labels):
        for f in CONDITION_FIELDS:
            out[f][b] = lab[f]
        for change in sorted(schedules[lab["schedule"]].changes, key=lambda c: c.trial):
            out[change.field][b, change.trial:] = change.value
    out["inference"] = out["inference"] > 0.5
    return Conditions(**out)


def validate(spec: StudySpec) -> Conditions:
    """Check a study before any compute; returns its conditions.

    Raises:
      StudyError: the message names the option, the bad value and what is allowed.
    """
    def fail(msg):
        raise StudyError(f"study {spec.name!r}: {msg}")

    if not isinstance(spec.num_trials, int) or spec.num_trials < 1:
        fail(f"num_trials = {spec.num_trials!r}; need an integer >= 1")
    for axis in ("controllers", "seeds", "friction", "slope_deg", "payload_kg", "target_velocity_mps", "schedules",
                 "data_reuse"):
        values = getattr(spec, axis)
        if len(values) == 0:
            fail(f"grid axis {axis} is empty")
        if len(set(values)) != len(values):
            fail(f"grid axis {axis} has duplicates: {values}")
    for c in spec.controllers:
        if c not in cpg.CONTROLLERS:
            fail(f"unknown controller {c!r}; allowed: {cpg.CONTROLLERS}")
    for s in spec.seeds:
        if not isinstance(s, (int, np.integer)) or s < 0:
            fail(f"seed {s!r}: need a non-negative integer")
    for g in spec.group_by:
        if g not in LABELS:
            fail(f"group_by {g!r}: allowed labels {LABELS}")
    for schedule in spec.schedules:
        for change in schedule.changes:
            if change.field not in SCHEDULE_FIELDS:
                fail(f"schedule {schedule.label!r}: unknown field {change.field!r}; allowed: {SCHEDULE_FIELDS}")
            if not 0 <= change.trial < spec.num_trials:
                fail(f"schedule {schedule.label!r}: change at trial {change.trial} outside [0, {spec.num_trials})")
    config = spec.optimizer_config()
    if config.capacity < spec.num_trials:
        fail(f"optimizer capacity {config.capacity} < num_trials {spec.num_trials}")
    if config.num_parameters != param_space.NUM_PARAMS or config.num_contexts != 2:
        fail("the optimizer must search the 8 CPG parameters with the 2 contexts [c_load, c_slope]")
    if spec.trial.steady_steps < 1 or spec.trial.transition_steps < 0:
        fail(f"trial timing {spec.trial} needs steady_steps >= 1 and transition_steps >= 0")
    cond = conditions(spec)
    target = cond.target_velocity_mps
    if not np.all(np.isfinite(target)) or np.any(target <= 0) or np.any(target > MAX_TARGET_VELOCITY_MPS):
        bad = target[~(np.isfinite(target) & (target > 0) & (target <= MAX_TARGET_VELOCITY_MPS))][0]
        fail(f"target velocity {float(bad)!r} m/s outside (0, {MAX_TARGET_VELOCITY_MPS}]")
    try:
        for t in range(spec.num_trials):
            go1_model.make_scenarios(cond.friction[:, t], cond.slope_deg[:, t], cond.payload_kg[:, t])
    except ValueError as err:
        fail(f"trial {t}: {err}")
    return cond


# ----------------------------------------------------------------------------------------------- devices

def initialize_distributed() -> None:
    """Join a multi-host run (``jax.distributed.initialize()`` reads the coordinator from the environment or the
    cluster). Every process runs the same study; the batch is sharded over all processes' devices."""
    jax.distributed.initialize()


class Placement(NamedTuple):
    """How the batch sits on the devices: a 1-D mesh over axis ``batch``; the batch is padded to a multiple of the
    device count with copies of the last instance (their results are dropped)."""

    mesh: Mesh
    padded_size: int

    @property
    def sharding(self) -> NamedSharding:
        return NamedSharding(self.mesh, PartitionSpec("batch"))

    def put(self, tree):
        """Host or device arrays with a leading (padded) batch axis → arrays sharded along it."""
        sharding = self.sharding

        def one(x):
            x = np.asarray(x)
            return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])
        return jax.tree.map(one, tree)


def make_placement(batch_size: int, devices=None) -> Placement:
    devices = jax.devices() if devices is None else list(devices)
    padded = -(-batch_size // len(devices)) * len(devices)
    return Placement(Mesh(np.array(devices), ("batch",)), padded)


def fetch(tree):
    """Sharded (possibly multi-host) arrays → NumPy on this host."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils
        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree.map(np.asarray, tree)


def _pad(array: np.ndarray, size: int) -> np.ndarray:
    extra = size - array.shape[0]
    return array if extra == 0 else np.concatenate([array, np.repeat(array[-1:], extra, axis=0)])


# ----------------------------------------------------------------------------------------------- the engine

class TrialLog(NamedTuple):
    """What the engine keeps of one trial for every instance (leading axis B)."""

    params: np.ndarray  # (B, 8) proposed parameters, physical units
    context: np.ndarray  # (B, 2) measured [c_load N, c_slope rad]
    objective: np.ndarray  # (B,) J for the trial's target
    velocity_xy_mps: np.ndarray  # (B, 2) steady-phase mean
    cot: np.ndarray  # (B,)
    beta: np.ndarray  # (B,) β of the proposal
    context_changed: np.ndarray  # (B,) whether the proposal used β_init,c
    accepted: np.ndarray  # (B,) the optimizer stored the observation
    roll_std_rad: np.ndarray
    pitch_std_rad: np.ndarray
    saturation_fraction: np.ndarray
    energy_j: np.ndarray
    distance_m: np.ndarray
    total_mass_kg: np.ndarray
    fell: np.ndarray
    failed: np.ndarray


class Timing(NamedTuple):
    """Wall seconds spent, summed over trials (and resumed segments)."""

    simulation_s: float  # the backend's trials
    optimizer_s: float  # propose_s + observe_s
    propose_s: float  # β, keys, target changes, the UCB argmax (eq. 8)
    observe_s: float  # storing the observation and refitting the GP
    transfer_s: float  # device → host → device of the records
    checkpoint_s: float


class Progress(NamedTuple):
    """Handed to the progress callback after every trial."""

    trial: int  # trials done
    num_trials: int
    best_by_group: dict[str, float]  # best J so far per group
    env_steps_per_s: float
    eta_s: float


class StudyResult(NamedTuple):
    spec: StudySpec
    labels: list[dict[str, Any]]
    conditions: Conditions
    trials: TrialLog  # every field (num_trials, B, ...)
    opt_state: bo.OptimizerState  # final, host arrays (B, ...)
    wall_s: float  # compute wall time, summed over resumed segments
    timing: Timing
    backend: str
    devices: list[str]


def _record_template(trial: mjx_go1.TrialConfig) -> objective.TrialRecord:
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    fields = {f: scalar for f in objective.TrialRecord._fields}
    fields["velocity_xy_mps"] = jax.ShapeDtypeStruct((trial.steady_steps, 2), jnp.float32)
    return objective.TrialRecord(**fields)


def _where_batch(mask, a, b):
    def one(x, y):
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)
    return jax.tree.map(one, a, b)


class Engine:
    """Runs a :class:`StudySpec` in lockstep (see the module docstring).

    Args:
      spec: the study (validated here; a bad option raises :class:`StudyError` before any compute).
      backend: "auto" (native C MuJoCo on CPU-only machines, MJX with an accelerator), "mjx" or "native".
      devices: devices to shard the batch over (default: all, on every host).
    """

    def __init__(self, spec: StudySpec, *, backend: str = "auto", devices=None):
        self.conditions = validate(spec)
        self.spec = spec
        self.labels = instances(spec)
        self.backend_name = backends.resolve_backend(backend)
        self.batch_size = len(self.labels)
        self.placement = make_placement(self.batch_size, devices)
        size = self.placement.padded_size
        self.padded = Conditions(*(_pad(c, size) for c in self.conditions))
        controllers = _pad(np.array([lab["controller"] for lab in self.labels]), size)
        self.gates = mjx_go1.batch_gates(controllers.tolist())
        self.seeds = _pad(np.array([lab["seed"] for lab in self.labels]), size)
        self.reuse = _pad(np.array([lab["data_reuse"] for lab in self.labels]), size)
        self.active = np.ones((size, param_space.NUM_PARAMS), bool)
        self.active[:, param_space.SIGMA_N_INDEX] = self.gates.tegotae > 0  # decisions.md §13
        targets = self.padded.target_velocity_mps
        self.uses_records = bool(np.any(targets[:, 1:] != targets[:, :-1]))
        config = spec.optimizer_config()
        self.optimizer = (bo.make_optimizer(config, objective.objective, _record_template(spec.trial))
                          if self.uses_records else bo.make_optimizer(config))
        opt = self.optimizer
        init = (lambda a, t: opt.init(active_dims=a, target_velocity=t)) if self.uses_records else \
            (lambda a, t: opt.init(active_dims=a))
        self._init = jax.jit(jax.vmap(init))
        self._propose = jax.jit(jax.vmap(opt.propose))
        self._observe = jax.jit(jax.vmap(opt.observe))
        self._beta = jax.jit(jax.vmap(opt.beta))
        self._set_target = jax.jit(jax.vmap(opt.set_target)) if self.uses_records else None
        self._keys = jax.jit(jax.vmap(lambda seed, t: jax.random.fold_in(jax.random.PRNGKey(seed), t),
                                      in_axes=(0, None)))
        self._summary = jax.jit(jax.vmap(lambda r, v: (
            objective.objective(r, v), objective.context(r), objective.mean_velocity(r),
            objective.cost_of_transport(r))))
        self._sim = None

    # -- pieces ---------------------------------------------------------------------------------------------

    def scenario(self, trial: int) -> go1_model.Scenario:
        c = self.padded
        return go1_model.make_scenarios(c.friction[:, trial], c.slope_deg[:, trial], c.payload_kg[:, trial])

    def simulator(self, trial: int):
        """The backend for trial ``trial``'s scenario; rebuilt (reusing its compiled code where the backend
        allows) only when some instance's friction, slope or payload changes."""
        scenario = self.scenario(trial)
        if self._sim is None:
            self._sim = backends.make_backend(scenario, self.backend_name, trial_config=self.spec.trial)
        elif any(not np.array_equal(a, b) for a, b in zip(scenario, self._sim.scenario)):
            if hasattr(self._sim, "with_scenario"):
                self._sim = self._sim.with_scenario(scenario)
            else:
                if hasattr(getattr(self._sim, "physics", None), "close"):
                    self._sim.physics.close()
                self._sim = backends.make_backend(scenario, self.backend_name, trial_config=self.spec.trial)
        return self._sim

    def _place_sim(self, state):
        # MJX state lives on the devices, sharded like the optimizer's; the native backend's physics is host memory.
        return self.placement.put(fetch(state)) if self.backend_name == "mjx" else state

    def initial_opt_state(self) -> bo.OptimizerState:
        targets = jnp.asarray(self.padded.target_velocity_mps[:, 0], jnp.float32)
        return self._init(self.placement.put(self.active), self.placement.put(targets))

    def initial_context(self) -> np.ndarray:
        config = self.spec.optimizer_config()
        mid = 0.5 * (np.asarray(config.context_lower) + np.asarray(config.context_upper))
        return np.tile(mid, (self.placement.padded_size, 1)).astype(np.float32)

    def _change_targets(self, opt_state, trial: int):
        """Data reuse (``set_target``) or a fresh optimizer for instances whose target changes at ``trial``."""
        targets = self.padded.target_velocity_mps
        changed = targets[:, trial] != targets[:, trial - 1]
        if trial == 0 or not changed.any():
            return opt_state
        new_target = self.placement.put(jnp.asarray(targets[:, trial], jnp.float32))
        reused = self._set_target(opt_state, new_target)
        fresh = self._init(self.placement.put(self.active), new_target)
        fresh = _where_batch(self.placement.put(~self.reuse), fresh, reused)
        return _where_batch(self.placement.put(changed), fresh, opt_state)

    # -- the loop -------------------------------------------------------------------------------------------

    def run(self, out_dir=None, *, resume: bool = False,
            progress: Callable[[Progress], None] | None = None) -> StudyResult:
        """Run (or, with ``resume``, continue from ``out_dir``'s checkpoint) every trial of the study.

        With ``out_dir`` the state is checkpointed atomically after every trial.
        """
        spec, n = self.spec, self.spec.num_trials
        put = self.placement.put
        opt_state = self.initial_opt_state()
        context = self.initial_context()
        logs: list[TrialLog] = []
        sim_state, start, wall_before = None, 0, 0.0
        timing = {name: 0.0 for name in Timing._fields}
        if resume:
            ckpt = study_io.load_checkpoint(out_dir, spec)
            if ckpt is not None:
                start = ckpt.trial
                opt_state = put(jax.tree.unflatten(jax.tree.structure(opt_state), ckpt.opt_leaves))
                context, logs, wall_before = ckpt.context, list(ckpt.logs), ckpt.wall_s
                timing.update(ckpt.timing)
                if start < n:
                    sim_state = self._restore_sim(start, ckpt.sim_leaves)
                log.info("resumed %s at trial %d", spec.name, start)
        t_begin = time.perf_counter()
        env_steps = self.batch_size * (spec.trial.transition_steps + spec.trial.steady_steps)
        for t in range(start, n):
            t0 = time.perf_counter()
            opt_state = self._change_targets(opt_state, t)
            opt_state = opt_state._replace(inference_mode=put(self.padded.inference[:, t]))
            keys = self._keys(put(self.seeds.astype(np.uint32)), t)
            ctx = put(context)
            beta = self._beta(opt_state, ctx)
            x = fetch(self._propose(opt_state, ctx, keys)).astype(np.float64)
            # The proposal is in the box up to float32 rounding; the simulator validates strictly.
            x = np.clip(x, param_space.PARAM_LOWER, param_space.PARAM_UPPER)
            t1 = time.perf_counter()
            sim = self.simulator(t)
            if sim_state is None:
                sim_state = self._place_sim(sim.reset(x))
            sim_state, record = sim.trial(sim_state, x, self.gates)
            if self.backend_name == "mjx":  # keep the input sharding of the compiled trial (no recompilation)
                sim_state = jax.device_put(sim_state, self.placement.sharding)
            record = jax.block_until_ready(record)
            t2 = time.perf_counter()
            rec = fetch(record)
            target = self.padded.target_velocity_mps[:, t].astype(np.float32)
            j, new_context, velocity, cot = fetch(self._summary(rec, target))
            record_d, x_d = put(rec), put(x.astype(np.float32))
            t3 = time.perf_counter()
            observation = record_d if self.uses_records else put(j)
            opt_state, accepted = self._observe(opt_state, x_d, put(new_context), observation)
            accepted = jax.block_until_ready(accepted)
            t4 = time.perf_counter()
            logs.append(TrialLog(
                params=x, context=new_context, objective=j, velocity_xy_mps=velocity, cot=cot, beta=fetch(beta.beta),
                context_changed=fetch(beta.context_changed), accepted=fetch(accepted),
                roll_std_rad=rec.roll_std_rad, pitch_std_rad=rec.pitch_std_rad,
                saturation_fraction=rec.saturation_fraction, energy_j=rec.energy_j, distance_m=rec.distance_m,
                total_mass_kg=rec.total_mass_kg, fell=rec.fell, failed=rec.failed))
            context = np.asarray(new_context, np.float32)
            timing["simulation_s"] += t2 - t1
            timing["optimizer_s"] += (t1 - t0) + (t4 - t3)
            timing["propose_s"] += t1 - t0
            timing["observe_s"] += t4 - t3
            timing["transfer_s"] += t3 - t2
            wall = wall_before + time.perf_counter() - t_begin
            if out_dir is not None:
                t5 = time.perf_counter()
                study_io.save_checkpoint(out_dir, spec, study_io.Checkpoint(
                    trial=t + 1, opt_leaves=fetch(jax.tree.leaves(opt_state)),
                    sim_leaves=fetch(jax.tree.leaves(sim_state)), context=context, logs=logs, wall_s=wall,
                    timing=dict(timing)))
                timing["checkpoint_s"] += time.perf_counter() - t5
            if progress is not None:
                done = t + 1 - start
                rate = env_steps * done / max(time.perf_counter() - t_begin, 1e-9)
                progress(Progress(t + 1, n, self.best_by_group(logs), rate,
                                  (n - t - 1) * (time.perf_counter() - t_begin) / done))
        wall_s = wall_before + time.perf_counter() - t_begin
        return StudyResult(
            spec=spec, labels=self.labels, conditions=self.conditions, trials=self.stack(logs),
            opt_state=jax.tree.map(lambda a: a[:self.batch_size], fetch(opt_state)), wall_s=wall_s,
            timing=Timing(**timing), backend=self.backend_name, devices=[str(d) for d in self.placement.mesh.devices])

    def _restore_sim(self, trial: int, leaves):
        sim = self.simulator(max(trial - 1, 0))
        template = sim.reset(np.tile(param_space.midpoint(), (self.placement.padded_size, 1)))
        treedef = jax.tree.structure(template)
        kinds = [type(x) for x in jax.tree.leaves(template)]
        restored = [leaf if kind is np.ndarray else jnp.asarray(leaf) for leaf, kind in zip(leaves, kinds)]
        return self._place_sim(jax.tree.unflatten(treedef, restored))

    def stack(self, logs: list[TrialLog]) -> TrialLog:
        """Per-trial logs → one TrialLog of (num_trials, B, ...) arrays without the padding instances."""
        if not logs:
            return TrialLog(*(np.zeros((0, self.batch_size)) for _ in TrialLog._fields))
        return TrialLog(*(np.stack([np.asarray(f)[:self.batch_size] for f in field]) for field in zip(*logs)))

    def group_names(self) -> list[str]:
        return [", ".join(str(lab[g]) for g in self.spec.group_by) for lab in self.labels]

    def best_by_group(self, logs: list[TrialLog]) -> dict[str, float]:
        j = np.stack([np.asarray(lg.objective)[:self.batch_size] for lg in logs])  # (t, B)
        best: dict[str, float] = {}
        for b, name in enumerate(self.group_names()):
            best[name] = max(best.get(name, -np.inf), float(j[:, b].max()))
        return best


def run_study(spec: StudySpec, out_dir=None, *, resume: bool = False, backend: str = "auto", devices=None,
              progress=None) -> StudyResult:
    """Validate, build and run a study (see :class:`Engine`)."""
    return Engine(spec, backend=backend, devices=devices).run(out_dir, resume=resume, progress=progress)
