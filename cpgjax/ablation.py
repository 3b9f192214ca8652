r"""The lockstep engine: Algorithm 1 for a whole batch of instances at once.

A study is a grid of instances — controller × seed × friction × slope × payload × target velocity × condition
schedule × data reuse (:class:`StudySpec`, defined in :mod:`cpgjax.study.spec` and re-exported here) — each running
its own online optimization. Every trial is one lockstep
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
statistically equivalent, not identical, runs. The state is checkpointed after every trial (``cpgjax.study.files``) and
:meth:`Engine.run` with ``resume=True`` continues from the last checkpoint to exactly (bit for bit) the results of
an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cpgjax.go1 import model as go1_model
from cpgjax.optim import bo
from cpgjax.optim import config as optimizer_config
from cpgjax.sim import backends
from cpgjax.study import files as study_io
from cpgjax.study.spec import Conditions, StudySpec, instances, validate
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space

log = logging.getLogger(__name__)


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
    env_steps_per_s: float  # over this segment's trials after its first (which compiles), if there are any
    eta_s: float | None  # from those trials' pace; None after the segment's first trial


class StudyResult(NamedTuple):
    spec: StudySpec
    labels: list[dict[str, Any]]
    conditions: Conditions
    trials: study_io.TrialLog  # every field (num_trials, B, ...)
    opt_state: bo.OptimizerState  # final, host arrays (B, ...)
    wall_s: float  # compute wall time, summed over resumed segments
    timing: Timing
    backend: str
    devices: list[str]


def _record_template(trial: protocol.TrialConfig) -> protocol.TrialRecord:
    scalar = jax.ShapeDtypeStruct((), jnp.float32)
    fields = {f: scalar for f in protocol.TrialRecord._fields}
    fields["velocity_xy_mps"] = jax.ShapeDtypeStruct((trial.steady_steps, 2), jnp.float32)
    return protocol.TrialRecord(**fields)


def _where_batch(mask, a, b):
    def one(x, y):
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)
    return jax.tree.map(one, a, b)


class _Run(NamedTuple):
    """What :meth:`Engine.run` carries from trial to trial (host-side; ``timing`` is updated in place)."""

    start: int  # the first trial of this segment (> 0 after a resume)
    opt_state: Any  # optimizer state, sharded
    sim_state: Any  # backend state (None before the first trial)
    context: np.ndarray  # (B, 2) context measured in the last trial
    logs: list  # a study_io.TrialLog per completed trial
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
        self.gates = protocol.batch_gates(controllers.tolist())
        self.seeds = _pad(np.array([lab["seed"] for lab in self.labels]), size)
        self.physics = _pad(np.array([lab["physics"] for lab in self.labels]), size)
        self.reuse = _pad(np.array([lab["data_reuse"] for lab in self.labels]), size)
        self.active = np.ones((size, param_space.NUM_PARAMS), bool)
        self.active[:, param_space.SIGMA_N_INDEX] = self.gates.tegotae > 0  # docs/decisions.md §13
        targets = self.padded.target_velocity_mps
        self.uses_records = bool(np.any(targets[:, 1:] != targets[:, :-1]))
        config = self.optimizer_config = spec.optimizer_config()
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
        return go1_model.make_scenarios(c.friction[:, trial], c.slope_deg[:, trial], c.payload_kg[:, trial],
                                        self.physics, c.mass_scale[:, trial], c.latency_ticks[:, trial],
                                        c.noise_scale[:, trial], self.seeds)  # one noise stream per seed

    def simulator(self, trial: int):
        """The backend for trial ``trial``'s scenario; rebuilt (reusing its compiled code where the backend
        allows) only when some instance's friction, slope or payload changes."""
        scenario = self.scenario(trial)
        if self._sim is None:
            self._sim = backends.make_backend(scenario, self.backend_name, trial_config=self.spec.trial,
                                              devices=self.placement.mesh.devices.tolist())
        elif any(not np.array_equal(a, b) for a, b in zip(scenario, self._sim.scenario)):
            self._sim = self._sim.with_scenario(scenario)
        return self._sim

    def initial_opt_state(self) -> bo.OptimizerState:
        targets = jnp.asarray(self.padded.target_velocity_mps[:, 0], jnp.float32)
        return self._init(self.placement.put(self.active), self.placement.put(targets))

    def initial_context(self) -> np.ndarray:
        config = self.optimizer_config
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
            if progress is not None:
                paced = t - run.start
                if paced:
                    per_trial = max(time.perf_counter() - t_first, 1e-9) / paced
                    figures = env_steps / per_trial, (n - t - 1) * per_trial
                else:
                    figures = env_steps / max(time.perf_counter() - t_begin, 1e-9), None
                progress(Progress(t + 1, n, self.best_by_group(run.logs), *figures))
        wall_s = run.wall_before + time.perf_counter() - t_begin
        return StudyResult(
            spec=spec, labels=self.labels, conditions=self.conditions, trials=self.stack(run.logs),
            opt_state=jax.tree.map(lambda a: a[:self.batch_size], fetch(run.opt_state)), wall_s=wall_s,
            timing=Timing(**run.timing), backend=self.backend_name,
            devices=[str(d) for d in self.placement.mesh.devices])

    def _start(self, out_dir, resume: bool) -> _Run:
        """The run's state before its first trial: fresh, or restored from ``out_dir``'s checkpoint."""
        run = _Run(start=0, opt_state=self.initial_opt_state(), sim_state=None, context=self.initial_context(),
                   logs=[], wall_before=0.0, timing={name: 0.0 for name in Timing._fields})
        ckpt = study_io.load_checkpoint(out_dir, self.spec) if resume else None
        if ckpt is None:
            return run
        opt_state = self.placement.put(jax.tree.unflatten(jax.tree.structure(run.opt_state), ckpt.opt_leaves))
        sim_state = self._restore_sim(ckpt.trial, ckpt.sim_leaves) if ckpt.trial < self.spec.num_trials else None
        log.info("resumed %s at trial %d", self.spec.name, ckpt.trial)
        return _Run(start=ckpt.trial, opt_state=opt_state, sim_state=sim_state, context=ckpt.context,
                    logs=list(ckpt.logs), wall_before=ckpt.wall_s, timing={**run.timing, **ckpt.timing})

    def _trial(self, run: _Run, t: int) -> _Run:
        """Trial ``t`` for the whole batch: propose (eq. 8), simulate, summarize (eqs. 9-11), observe."""
        put, timing = self.placement.put, run.timing
        with _timed(timing, "propose_s", "optimizer_s"):
            opt_state = self._change_targets(run.opt_state, t)
            opt_state = opt_state._replace(inference_mode=put(self.padded.inference[:, t]))
            keys = self._keys(put(self.seeds.astype(np.uint32)), t)
            ctx = put(run.context)
            beta = self._beta(opt_state, ctx)
            x = fetch(self._propose(opt_state, ctx, keys)).astype(np.float64)
            # The proposal is in the box up to float32 rounding; the simulator validates strictly.
            x = np.clip(x, param_space.PARAM_LOWER, param_space.PARAM_UPPER)
        with _timed(timing, "simulation_s"):
            sim = self.simulator(t)
            sim_state = sim.reset(x) if run.sim_state is None else run.sim_state
            sim_state, record = sim.trial(sim_state, x, self.gates)
            record = jax.block_until_ready(record)
        with _timed(timing, "transfer_s"):
            rec = fetch(record)
            target = self.padded.target_velocity_mps[:, t].astype(np.float32)
            j, new_context, velocity, cot = fetch(self._summary(rec, target))
            gp_context = self._clip_context(t, new_context)
            record_d, x_d = put(rec), put(x.astype(np.float32))
        with _timed(timing, "observe_s", "optimizer_s"):
            observation = record_d if self.uses_records else put(j)
            opt_state, accepted = self._observe(opt_state, x_d, put(gp_context), observation)
            accepted = jax.block_until_ready(accepted)
        trial_log = study_io.TrialLog(
            params=x, context=new_context, objective=j, velocity_xy_mps=velocity, cot=cot, beta=fetch(beta.beta),
            context_changed=fetch(beta.context_changed), accepted=fetch(accepted),
            roll_std_rad=rec.roll_std_rad, pitch_std_rad=rec.pitch_std_rad,
            saturation_fraction=rec.saturation_fraction, energy_j=rec.energy_j, distance_m=rec.distance_m,
            total_mass_kg=rec.total_mass_kg, fell=rec.fell, failed=rec.failed)
        return run._replace(opt_state=opt_state, sim_state=sim_state, context=np.asarray(gp_context, np.float32),
                            logs=run.logs + [trial_log])

    def _clip_context(self, trial: int, context: np.ndarray) -> np.ndarray:
        """The measured contexts clipped to the optimizer's ranges for the GP (docs/decisions.md §11), with a log line
        when any is; the trial log keeps the measured values."""
        clipped, messages = optimizer_config.clip_context(self.optimizer_config, context[:self.batch_size])
        if messages:
            log.warning("trial %d: %d context value(s) outside the GP's range, clipped; first: %s", trial,
                        len(messages), messages[0])
        return np.concatenate([clipped, np.clip(context[self.batch_size:], self.optimizer_config.context_lower,
                                                self.optimizer_config.context_upper)]).astype(np.float32)

    def _checkpoint(self, out_dir, run: _Run, t: int, wall_s: float) -> None:
        study_io.save_checkpoint(out_dir, self.spec, study_io.Checkpoint(
            trial=t + 1, opt_leaves=fetch(jax.tree.leaves(run.opt_state)),
            sim_leaves=fetch(jax.tree.leaves(run.sim_state)), context=run.context, logs=run.logs, wall_s=wall_s,
            timing=dict(run.timing)), self.backend_name)

    def _restore_sim(self, trial: int, leaves):
        sim = self.simulator(max(trial - 1, 0))
        template = sim.reset(np.tile(param_space.midpoint(), (self.placement.padded_size, 1)))
        treedef = jax.tree.structure(template)
        kinds = [type(x) for x in jax.tree.leaves(template)]
        restored = [leaf if kind is np.ndarray else jnp.asarray(leaf) for leaf, kind in zip(leaves, kinds)]
        return jax.tree.unflatten(treedef, restored)  # the backend places it on its devices

    def stack(self, logs: list[study_io.TrialLog]) -> study_io.TrialLog:
        """Per-trial logs → one study_io.TrialLog of (num_trials, B, ...) arrays without the padding instances."""
        if not logs:
            return study_io.TrialLog(*(np.zeros((0, self.batch_size)) for _ in study_io.TrialLog._fields))
        return study_io.TrialLog(*(np.stack([np.asarray(f)[:self.batch_size] for f in field]) for field in zip(*logs)))

    def group_names(self) -> list[str]:
        return [", ".join(str(lab[g]) for g in self.spec.group_by) for lab in self.labels]

    def best_by_group(self, logs: list[study_io.TrialLog]) -> dict[str, float]:
        j = np.stack([np.asarray(lg.objective)[:self.batch_size] for lg in logs])  # (t, B)
        best: dict[str, float] = {}
        for b, name in enumerate(self.group_names()):
            best[name] = max(best.get(name, -np.inf), float(j[:, b].max()))
        return best


def run_study(spec: StudySpec, out_dir=None, *, resume: bool = False, backend: str = "auto", devices=None,
              progress=None) -> StudyResult:
    """Validate, build and run a study (see :class:`Engine`)."""
    return Engine(spec, backend=backend, devices=devices).run(out_dir, resume=resume, progress=progress)
