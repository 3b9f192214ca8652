r"""The sequential contextual-BO optimizer of Algorithm 1, as pure functions over a state.

:func:`make_optimizer` returns a :class:`ContextualBO`, a NamedTuple of pure functions in the
style of optax's ``init``/``update`` pairs::

    opt = make_optimizer(config, objective_fn, record_template)   # e.g. trial.optimizer_setting.paper_config()
    state = opt.init(target_velocity=jnp.array([0.5, 0.0]))
    x = opt.propose(state, context, key)              # physical units, shape (8,)
    state, accepted = opt.observe(state, x, context, record)
    state = opt.set_target(state, jnp.array([0.8, 0.0]))   # data reuse

Every function is jit-compiled and ``jax.vmap``-able over a batch of states (independent
data, contexts, keys, β schedules, active inputs and targets). Structure (dimensions,
capacity, step counts, the UCB form) is the static :class:`OptimizerConfig`
(:mod:`cpgjax.optim.config`). :func:`cpgjax.optim.black_box.maximize` wraps the optimizer for
black-box functions.

Algorithm 1, step by step:

* the surrogate is refitted in :meth:`observe` (and :meth:`set_target`), warm-started from the
  previous fit (:func:`cpgjax.gp.fit`);
* :meth:`propose` returns a uniform random point while fewer than ``num_random_proposals``
  (2) observations are stored, else :math:`\arg\max_x a(x; \beta, c)` of eq. (8) with the
  context held at the given value (:mod:`cpgjax.optim.acquisition`);
* :math:`\beta` follows eqs. (12)-(14) with the paper's context-sharing count
  (:mod:`cpgjax.optim.exploration`), per instance;
* inference mode fixes :math:`\beta = 10^{-6}` and skips the random phase (paper Sec. IV-C);
* data reuse (paper Sec. III-A-2): with an ``objective_fn(record, target_velocity)``, each
  observation stores its trial record, and :meth:`set_target` recomputes every stored
  objective for the new target velocity (vmapped over the record buffer).

Inactive parameters (``active_dims`` False, e.g. :math:`\sigma_N` without Tegotae) are excluded
from the kernel and are set to the box midpoint in every proposal.

Safe optimization (``OptimizerConfig.safe``, docs/decisions.md §17): every observation also
carries a safety margin :math:`g` (< 0: the trial was unsafe), and a second GP over the same
(parameters, context) inputs, with its own hyperparameters, models it. The random phase ends at
the first safe observation (margin ≥ 0); from then on a proposal maximizes eq. (8) over the safe
set :math:`\{x : \mu_g(x, c) - \beta_s\, \sigma_g(x, c) \ge 0\}`, the safe set of SafeOpt (Sui et
al., ICML 2015) without its Lipschitz constant, as in Berkenkamp et al.'s SafeOpt-MC (2016,
arXiv:1602.04450). When no point of the box is certified safe, the proposal repeats the parameters
of a safe observation, the one with the highest expected margin at the current context (so
parameters that fell in this context are not repeated); with no safe observation at all, it is
uniform random. :meth:`propose_with_fallback` says which. Context changes, inference mode and data
reuse act on the objective as without ``safe``; the margins do not depend on the target velocity.

Bad calls raise ``ValueError`` in the Python wrappers, before anything is compiled: wrong
shapes always; non-finite values, parameters outside the box and a full buffer whenever the
values are concrete (not traced). Under ``jit``/``vmap`` the same checks run on device: a bad
observation is not stored and ``observe`` returns ``accepted = False``.
"""

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import gp
from cpgjax.optim.acquisition import (
    INACTIVE_VALUE,
    lower_confidence_bound,
    maximize_acquisition,
    ucb_multiplier,
    upper_confidence_bound,
)
from cpgjax.optim.config import OptimizerConfig
from cpgjax.optim.exploration import (
    BetaInfo,
    BetaSchedule,
    exploration_beta,
    paper_schedule,
)

__all__ = [
    "BOX_TOLERANCE",
    "ContextualBO",
    "OptimizerState",
    "make_optimizer",
]

BOX_TOLERANCE = 1e-5
"""Relative slack (of the box width) when checking that observed parameters are in the box."""


def _float32_inside(bounds, toward: float) -> np.ndarray:
    """Bounds as float32 values that are inside the float64 box: a float32 rounding that
    falls outside is moved one ulp toward ``toward`` (+inf for lower, -inf for upper)."""
    exact = np.asarray(bounds, np.float64)
    rounded = exact.astype(np.float32)
    outside = rounded < exact if toward > 0 else rounded > exact
    return np.where(outside, np.nextafter(rounded, np.float32(toward)), rounded)


class OptimizerState(NamedTuple):
    """Per-instance state; every leaf is an array (batch it by stacking).

    Attributes:
      parameters: (capacity, P) observed parameters, physical units.
      contexts: (capacity, C) contexts of the observations, physical units.
      objectives: (capacity,) objective values (recomputed by ``set_target``).
      stored: (capacity,) bool, rows holding an observation (a prefix).
      records: trial records with a leading capacity axis (``()`` without data reuse).
      num_stored: () int32.
      target_velocity: the objective's target (shape of the ``init`` argument; (0,) without
        data reuse).
      active_dims: (P,) bool, parameters seen by the kernel and the proposals.
      schedule: the :class:`BetaSchedule`.
      inference_mode: () bool; beta = ``inference_beta`` and no random phase.
      gp_params: the last fitted GP hyperparameters (warm start of the next fit).
      margins: (capacity,) safety margins of the observations (``()`` without ``safe``).
      margin_gp_params: the margin GP's last hyperparameters (``()`` without ``safe``).
    """

    parameters: jax.Array
    contexts: jax.Array
    objectives: jax.Array
    stored: jax.Array
    records: Any
    num_stored: jax.Array
    target_velocity: jax.Array
    active_dims: jax.Array
    schedule: BetaSchedule
    inference_mode: jax.Array
    gp_params: gp.GPParams
    margins: Any
    margin_gp_params: Any


OBSERVATION_FIELDS = ("parameters", "contexts", "objectives", "stored", "records", "margins")
"""The fields of :class:`OptimizerState` with a capacity axis: row k holds the k-th observation stored since ``init``,
and the rows past ``num_stored`` hold ``init``'s values (``observe`` writes row ``num_stored`` only when it stores)."""


def _rows_axis(state: OptimizerState) -> int:
    return np.ndim(state.stored) - 1  # after any batch axes


def first_rows(state: OptimizerState, rows: int) -> OptimizerState:
    """``state`` (batched or not) with its observation buffers cut to their first ``rows`` rows, as host arrays: all
    it holds beyond ``init``'s values when at most ``rows`` observations were stored since ``init`` (e.g. after
    ``rows`` trials). :func:`full_rows` puts the rest back. A checkpoint of a study with data reuse then holds the
    trial records stored so far, not the whole capacity's."""
    cut = (slice(None),) * _rows_axis(state) + (slice(0, rows),)
    return state._replace(
        **{f: jax.tree.map(lambda leaf: np.asarray(leaf)[cut], getattr(state, f)) for f in OBSERVATION_FIELDS}
    )


def full_rows(fresh: OptimizerState, cut: OptimizerState) -> OptimizerState:
    """The state :func:`first_rows` cut, as host arrays: ``cut``'s observation rows written over the buffers of
    ``fresh``, a state from ``init`` with the same batch axes."""

    def put(full, part):
        full = np.array(full)
        full[(slice(None),) * _rows_axis(fresh) + (slice(0, np.shape(part)[_rows_axis(fresh)]),)] = part
        return full

    return cut._replace(**{f: jax.tree.map(put, getattr(fresh, f), getattr(cut, f)) for f in OBSERVATION_FIELDS})


class ContextualBO(NamedTuple):
    """The optimizer's pure functions (see the module docstring). Signatures:

    * ``init(active_dims=None, schedule=None, target_velocity=None) -> OptimizerState``
    * ``propose(state, context, key) -> x`` (P,), physical units
    * ``propose_with_fallback(state, context, key) -> (x, fell_back)``: ``fell_back`` is True when
      a safe optimizer certified no point safe (always False without ``safe``)
    * ``observe(state, x, context, observation, margin=None) -> (state, accepted)``;
      ``observation`` is a scalar objective, or a trial record when built with ``objective_fn``;
      ``margin`` the trial's safety margin, required with ``safe`` and refused without
    * ``set_target(state, target_velocity) -> state`` (data reuse)
    * ``set_inference_mode(state, enabled) -> state``
    * ``beta(state, context) -> BetaInfo``
    * ``best_observed(state) -> (x, context, objective)``
    * ``posterior_mean_argmax(state, context, key) -> (x, posterior mean)``
    """

    init: Callable[..., OptimizerState]
    propose: Callable[..., jax.Array]
    propose_with_fallback: Callable[..., tuple[jax.Array, jax.Array]]
    observe: Callable[..., tuple[OptimizerState, jax.Array]]
    set_target: Callable[..., OptimizerState]
    set_inference_mode: Callable[..., OptimizerState]
    beta: Callable[..., BetaInfo]
    best_observed: Callable[..., tuple[jax.Array, jax.Array, jax.Array]]
    posterior_mean_argmax: Callable[..., tuple[jax.Array, jax.Array]]


def _is_concrete(*values) -> bool:
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(values))


def _check_shape(name: str, value, shape: tuple) -> None:
    if np.shape(value) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {np.shape(value)}")


def _check_finite(name: str, value) -> None:
    array = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {array}")


class _Static(NamedTuple):
    """What the optimizer's functions close over: the static configuration and the arrays derived from it."""

    config: OptimizerConfig
    objective_fn: Callable | None  # with it, observations are trial records (data reuse)
    record_template: Any
    template_tree: Any  # record_template's tree structure (None without data reuse)
    template_specs: tuple  # (shape, dtype) of each record leaf
    lower: jax.Array  # (P,) parameter box, float32
    width: jax.Array
    lower_inside: jax.Array  # the box's float32 bounds that are inside the float64 box
    upper_inside: jax.Array
    context_lower: jax.Array  # (C,) context normalisation range
    context_width: jax.Array
    context_tolerance: jax.Array  # (C,) context-change thresholds in physical units

    @property
    def reuses_data(self) -> bool:
        return self.objective_fn is not None


def _static(config: OptimizerConfig, objective_fn, record_template) -> _Static:
    if (objective_fn is None) != (record_template is None):
        raise ValueError("objective_fn and record_template must be given together")
    tree, specs = None, ()
    if objective_fn is not None:
        leaves, tree = jax.tree.flatten(record_template)
        specs = tuple((tuple(leaf.shape), jnp.dtype(leaf.dtype)) for leaf in leaves)
    lower = jnp.asarray(config.parameter_lower, jnp.float32)
    context_lower = jnp.asarray(config.context_lower, jnp.float32)
    context_width = jnp.asarray(config.context_upper, jnp.float32) - context_lower
    return _Static(
        config=config,
        objective_fn=objective_fn,
        record_template=record_template,
        template_tree=tree,
        template_specs=specs,
        lower=lower,
        width=jnp.asarray(config.parameter_upper, jnp.float32) - lower,
        # Proposals are clipped to these, so float32 rounding never leaves the float64 box.
        lower_inside=jnp.asarray(_float32_inside(config.parameter_lower, np.inf)),
        upper_inside=jnp.asarray(_float32_inside(config.parameter_upper, -np.inf)),
        context_lower=context_lower,
        context_width=context_width,
        context_tolerance=jnp.asarray(config.context_thresholds, jnp.float32) * context_width,
    )


# ----------------------------------------------------------------------------------------------- pure cores (jitted)


def _inputs(s: _Static, state: OptimizerState) -> jax.Array:
    return jnp.concatenate(
        [(state.parameters - s.lower) / s.width, (state.contexts - s.context_lower) / s.context_width], axis=-1
    )


def _learned(s: _Static, state: OptimizerState) -> jax.Array:
    """(capacity,) bool: the stored observations the GP(s) learn from, those with a finite J (and margin, with
    ``safe``). Both GPs of a safe optimizer learn from the same observations at the same inputs, so the
    hyperparameter-free part of their datasets (``gp.squared_differences``) is one expression, which XLA computes
    once for both. A stored row's margin is finite (``observe`` refuses any other), so this is what each GP would
    learn from alone."""
    learned = state.stored & jnp.isfinite(state.objectives)
    return learned & jnp.isfinite(state.margins) if s.config.safe else learned


def _dataset(s: _Static, state: OptimizerState) -> gp.Dataset:
    return gp.Dataset(_inputs(s, state), state.objectives, _learned(s, state))


def _margin_dataset(s: _Static, state: OptimizerState) -> gp.Dataset:
    return gp.Dataset(_inputs(s, state), state.margins, _learned(s, state))


def _kernel_active(s: _Static, state: OptimizerState) -> jax.Array:
    return jnp.concatenate([state.active_dims, jnp.ones((s.config.num_contexts,), bool)])


def _refit_objective(s: _Static, state: OptimizerState) -> OptimizerState:
    params = gp.fit(_dataset(s, state), _kernel_active(s, state), state.gp_params, s.config.num_contexts, s.config.fit)
    return state._replace(gp_params=params)


def _refit(s: _Static, state: OptimizerState) -> OptimizerState:
    """Both GPs with ``safe``, else the objective's."""
    state = _refit_objective(s, state)
    if not s.config.safe:
        return state
    params = gp.fit(
        _margin_dataset(s, state),
        _kernel_active(s, state),
        state.margin_gp_params,
        s.config.num_contexts,
        s.config.fit,
        s.config.margin_priors,
    )
    return state._replace(margin_gp_params=params)


def _beta(s: _Static, state: OptimizerState, context) -> BetaInfo:
    return exploration_beta(
        state.schedule,
        state.contexts,
        state.stored,
        context,
        s.context_tolerance,
        state.inference_mode,
        s.config.inference_beta,
    )


def _to_physical(s: _Static, unit_point) -> jax.Array:
    return jnp.clip(s.lower + unit_point * s.width, s.lower_inside, s.upper_inside)


def _condition(s: _Static, state: OptimizerState) -> gp.Posterior:
    return gp.posterior(state.gp_params, _dataset(s, state), _kernel_active(s, state), s.config.num_contexts)


def _condition_margin(s: _Static, state: OptimizerState) -> gp.Posterior:
    return gp.posterior(
        state.margin_gp_params, _margin_dataset(s, state), _kernel_active(s, state), s.config.num_contexts
    )


def _queries(s: _Static, context, unit_points) -> jax.Array:
    """(q, P + C) GP inputs: unit-cube parameters with the context held fixed."""
    unit_context = (context - s.context_lower) / s.context_width
    contexts = jnp.broadcast_to(unit_context, (unit_points.shape[0], s.config.num_contexts))
    return jnp.concatenate([unit_points, contexts], axis=-1)


def _maximize_ucb(s: _Static, post, state: OptimizerState, context, key, multiplier, margin_post=None):
    """The UCB maximizer (eq. 8) over the unit box of the active parameters, the context held fixed; with the margin
    GP's posterior, over the points whose margin LCB (β_s) is ≥ 0 (value −inf when none is found)."""
    num_contexts = s.config.num_contexts

    def acquisition(unit_points):
        return upper_confidence_bound(post, _queries(s, context, unit_points), multiplier, num_contexts)

    def margin_lower_bound(unit_points):
        return lower_confidence_bound(margin_post, _queries(s, context, unit_points), s.config.safe_beta, num_contexts)

    return maximize_acquisition(
        acquisition, key, state.active_dims, s.config.acquisition, None if margin_post is None else margin_lower_bound
    )


def _safe_observations(state: OptimizerState) -> jax.Array:
    """(capacity,) bool: the stored observations whose trial was safe (margin ≥ 0)."""
    return state.stored & (state.margins >= 0.0) & jnp.isfinite(state.objectives)


def _safest_safe_observed(s: _Static, state: OptimizerState, context, margin_post):
    """Unit-cube parameters of the observation that was safe (margin ≥ 0) and whose expected margin (the margin GP's
    posterior mean) at the current context is the highest, and whether any safe observation exists. Judged at this
    context, parameters that were safe elsewhere but fell here rank low, so a fall is not repeated. The mean, not the
    lower bound: the bound would rate a gait known to fall here above one never tried here."""
    safe = _safe_observations(state)
    unit = (state.parameters - s.lower) / s.width
    expected, _ = gp.predict(margin_post, _queries(s, context, unit), s.config.num_contexts)
    best = jnp.argmax(jnp.where(safe, expected, -jnp.inf))
    return unit[best], jnp.any(safe)


def _propose(s: _Static, state: OptimizerState, context, key) -> tuple[jax.Array, jax.Array]:
    """Random in the box for the first ``num_random_proposals`` trials (not in inference mode; with ``safe`` only until
    a trial is safe), then the UCB argmax (over the safe set with ``safe``); and whether a safe optimizer fell back
    (module docstring)."""
    config = s.config
    random_key, acquisition_key = jax.random.split(key)
    use_random = (state.num_stored < config.num_random_proposals) & ~state.inference_mode
    if config.safe:  # a safe trial seeds the safe set: no more random proposals
        use_random = use_random & ~jnp.any(_safe_observations(state))

    def random_point():
        uniform = jax.random.uniform(random_key, (config.num_parameters,), jnp.float32)
        return jnp.where(state.active_dims, uniform, INACTIVE_VALUE)

    def ucb_point():
        multiplier = ucb_multiplier(_beta(s, state, context).beta, config.ucb_form)
        if not config.safe:
            point, _ = _maximize_ucb(s, _condition(s, state), state, context, acquisition_key, multiplier)
            return point, jnp.zeros((), bool)
        margin_post = _condition_margin(s, state)
        point, value = _maximize_ucb(s, _condition(s, state), state, context, acquisition_key, multiplier, margin_post)
        found = jnp.isfinite(value)
        repeat, any_safe = _safest_safe_observed(s, state, context, margin_post)
        fallback = jnp.where(any_safe, repeat, random_point())
        return jnp.where(found, point, fallback), ~found

    point, fell_back = jax.lax.cond(use_random, lambda: (random_point(), jnp.zeros((), bool)), ucb_point)
    return _to_physical(s, point), fell_back


def _observe(s: _Static, state: OptimizerState, x, context, observation, margin) -> tuple[OptimizerState, jax.Array]:
    """Store one observation (if finite, in the box and within capacity) and refit the GP(s)."""
    capacity = s.config.capacity
    if s.reuses_data:
        objective = jnp.asarray(s.objective_fn(observation, state.target_velocity), jnp.float32)
    else:
        objective = jnp.asarray(observation, jnp.float32)
    slack = BOX_TOLERANCE * s.width
    in_box = jnp.where(state.active_dims, (x >= s.lower - slack) & (x <= s.lower + s.width + slack), True)
    accepted = (
        jnp.isfinite(objective)
        & jnp.all(jnp.isfinite(x))
        & jnp.all(jnp.isfinite(context))
        & jnp.all(in_box)
        & (state.num_stored < capacity)
    )
    if s.config.safe:
        accepted = accepted & jnp.isfinite(margin)
    row = jnp.minimum(state.num_stored, capacity - 1)
    written = state._replace(
        parameters=state.parameters.at[row].set(x),
        contexts=state.contexts.at[row].set(context),
        objectives=state.objectives.at[row].set(objective),
        stored=state.stored.at[row].set(True),
        records=(
            jax.tree.map(lambda buf, r: buf.at[row].set(r), state.records, observation)
            if s.reuses_data
            else state.records
        ),
        num_stored=state.num_stored + 1,
        margins=(state.margins.at[row].set(jnp.asarray(margin, jnp.float32)) if s.config.safe else state.margins),
    )
    new_state = jax.lax.cond(accepted, lambda: _refit(s, written), lambda: state)
    return new_state, accepted


def _set_target(s: _Static, state: OptimizerState, target_velocity) -> OptimizerState:
    """Data reuse: every stored J recomputed for a new target from the stored records, then a refit of the
    objective's GP (the margins do not depend on the target)."""
    recomputed = jax.vmap(s.objective_fn, in_axes=(0, None))(state.records, target_velocity)
    objectives = jnp.where(state.stored, jnp.asarray(recomputed, jnp.float32), 0.0)
    return _refit_objective(s, state._replace(objectives=objectives, target_velocity=target_velocity))


def _best_observed(state: OptimizerState):
    valid = state.stored & jnp.isfinite(state.objectives)
    scores = jnp.where(valid, state.objectives, -jnp.inf)
    best = jnp.argmax(scores)
    return state.parameters[best], state.contexts[best], scores[best]


def _posterior_mean_argmax(s: _Static, state: OptimizerState, context, key):
    post = _condition(s, state)
    unit_point, standardized = _maximize_ucb(s, post, state, context, key, jnp.zeros((), jnp.float32))
    return _to_physical(s, unit_point), post.target_mean + post.target_std * standardized


class _Compiled(NamedTuple):
    """The jitted cores of one optimizer."""

    propose: Callable
    observe: Callable
    set_target: Callable
    beta: Callable
    best_observed: Callable
    posterior_mean_argmax: Callable


# ----------------------------------------------------------------------------------------------- public functions
# Python-level validation of the arguments (clear errors before any compute), then the jitted core.


def _check_state(s: _Static, state) -> None:
    if not isinstance(state, OptimizerState):
        raise TypeError(f"expected an OptimizerState, got {type(state).__name__}")
    _check_shape("state.parameters", state.parameters, (s.config.capacity, s.config.num_parameters))
    _check_shape("state.contexts", state.contexts, (s.config.capacity, s.config.num_contexts))


def _check_context(s: _Static, context) -> None:
    _check_shape("context", context, (s.config.num_contexts,))
    if _is_concrete(context):
        _check_finite("context", context)


def _init(s: _Static, active_dims=None, schedule=None, target_velocity=None) -> OptimizerState:
    """A fresh state. ``active_dims``: (P,) bool, default all True; ``schedule``: default :func:`paper_schedule`;
    ``target_velocity``: required with data reuse."""
    config = s.config
    num_params, num_contexts = config.num_parameters, config.num_contexts
    if active_dims is None:
        active_dims = jnp.ones((num_params,), bool)
    _check_shape("active_dims", active_dims, (num_params,))
    if _is_concrete(active_dims) and not np.any(np.asarray(active_dims)):
        raise ValueError("active_dims must enable at least one parameter")
    if s.reuses_data:
        if target_velocity is None:
            raise ValueError("target_velocity is required with objective_fn (data reuse)")
        target = jnp.asarray(target_velocity, jnp.float32)
        records = jax.tree.map(lambda leaf: jnp.zeros((config.capacity, *leaf.shape), leaf.dtype), s.record_template)
    else:
        if target_velocity is not None:
            raise ValueError("target_velocity needs an objective_fn (data reuse)")
        target, records = jnp.zeros((0,), jnp.float32), ()
    return OptimizerState(
        parameters=jnp.zeros((config.capacity, num_params), jnp.float32),
        contexts=jnp.zeros((config.capacity, num_contexts), jnp.float32),
        objectives=jnp.zeros((config.capacity,), jnp.float32),
        stored=jnp.zeros((config.capacity,), bool),
        records=records,
        num_stored=jnp.zeros((), jnp.int32),
        target_velocity=target,
        active_dims=jnp.asarray(active_dims, bool),
        schedule=paper_schedule() if schedule is None else schedule,
        inference_mode=jnp.zeros((), bool),
        gp_params=gp.default_params(num_params + num_contexts),
        margins=jnp.zeros((config.capacity,), jnp.float32) if config.safe else (),
        margin_gp_params=gp.default_params(num_params + num_contexts, config.margin_priors) if config.safe else (),
    )


def _propose_with_fallback_checked(s: _Static, jitted: _Compiled, state, context, key):
    _check_state(s, state)
    _check_context(s, context)
    return jitted.propose(state, jnp.asarray(context, jnp.float32), key)


def _propose_checked(s: _Static, jitted: _Compiled, state, context, key):
    return _propose_with_fallback_checked(s, jitted, state, context, key)[0]


def _check_observation(s: _Static, state, x, context, observation) -> None:
    """x in the box (active parameters), room left, and an observation of the expected kind and shape."""
    config = s.config
    _check_shape("x", x, (config.num_parameters,))
    concrete = _is_concrete(state, x, context, observation)
    if concrete:
        _check_finite("x", x)
        x_np, active = np.asarray(x, np.float64), np.asarray(state.active_dims)
        lo, hi = np.asarray(config.parameter_lower), np.asarray(config.parameter_upper)
        slack = BOX_TOLERANCE * (hi - lo)
        outside = active & ((x_np < lo - slack) | (x_np > hi + slack))
        if np.any(outside):
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"x[{i}] = {x_np[i]} is outside its range [{lo[i]}, {hi[i]}]")
        if int(state.num_stored) >= config.capacity:
            raise ValueError(f"capacity exceeded: all {config.capacity} rows are stored")
    if s.reuses_data:
        leaves, tree = jax.tree.flatten(observation)
        if tree != s.template_tree:
            raise ValueError(f"trial record structure {tree} differs from the template {s.template_tree}")
        for i, (leaf, (shape, _)) in enumerate(zip(leaves, s.template_specs, strict=True)):
            _check_shape(f"trial record leaf {i}", leaf, shape)
    else:
        _check_shape("objective value (this optimizer has no objective_fn)", observation, ())
        if concrete:
            _check_finite("objective value", observation)


def _check_margin(s: _Static, margin) -> None:
    if not s.config.safe:
        if margin is not None:
            raise ValueError("a safety margin needs a safe optimizer (OptimizerConfig(safe=True))")
        return
    if margin is None:
        raise ValueError("a safe optimizer needs each observation's safety margin (observe(..., margin=m))")
    _check_shape("margin", margin, ())
    if _is_concrete(margin):
        _check_finite("margin", margin)


def _observe_checked(s: _Static, jitted: _Compiled, state, x, context, observation, margin=None):
    _check_state(s, state)
    _check_context(s, context)
    _check_observation(s, state, x, context, observation)
    _check_margin(s, margin)
    new_state, accepted = jitted.observe(
        state,
        jnp.asarray(x, jnp.float32),
        jnp.asarray(context, jnp.float32),
        observation,
        jnp.zeros((), jnp.float32) if margin is None else jnp.asarray(margin, jnp.float32),
    )
    if _is_concrete(accepted) and not bool(accepted):
        raise ValueError(
            "observation rejected: objective_fn returned a non-finite objective for this trial "
            "record; the state is unchanged"
        )
    return new_state, accepted


def _set_target_checked(s: _Static, jitted: _Compiled, state, target_velocity):
    if not s.reuses_data:
        raise ValueError("set_target needs an optimizer built with objective_fn")
    _check_state(s, state)
    _check_shape("target_velocity", target_velocity, state.target_velocity.shape)
    if _is_concrete(target_velocity):
        _check_finite("target_velocity", target_velocity)
    return jitted.set_target(state, jnp.asarray(target_velocity, jnp.float32))


def _set_inference_mode(s: _Static, state, enabled):
    """Inference mode (paper Sec. IV-C): beta = ``inference_beta``, no random phase."""
    _check_state(s, state)
    return state._replace(inference_mode=jnp.asarray(enabled, bool))


def _beta_checked(s: _Static, jitted: _Compiled, state, context):
    _check_state(s, state)
    _check_context(s, context)
    return jitted.beta(state, jnp.asarray(context, jnp.float32))


def _best_observed_checked(s: _Static, jitted: _Compiled, state):
    """Best stored observation (x, context, J); J = -inf when nothing is stored."""
    _check_state(s, state)
    if _is_concrete(state) and int(state.num_stored) == 0:
        raise ValueError("best_observed: no observation stored yet")
    return jitted.best_observed(state)


def _posterior_mean_argmax_checked(s: _Static, jitted: _Compiled, state, context, key):
    """Maximizer of the posterior mean mu(x; c) at the given context, and mu there."""
    _check_state(s, state)
    _check_context(s, context)
    return jitted.posterior_mean_argmax(state, jnp.asarray(context, jnp.float32), key)


def make_optimizer(
    config: OptimizerConfig,
    objective_fn: Callable[[Any, jax.Array], jax.Array] | None = None,
    record_template: Any = None,
) -> ContextualBO:
    """Build the optimizer of Algorithm 1.

    Args:
      config: static structure.
      objective_fn: ``objective_fn(record, target_velocity) -> J`` (a jax-traceable scalar
        function). With it, ``observe`` takes trial records and ``set_target`` reuses them.
      record_template: a pytree of arrays or ``jax.ShapeDtypeStruct`` with the shapes and
        dtypes of one trial record; required with ``objective_fn``.

    Returns:
      A :class:`ContextualBO`: each function validates its arguments, then runs its jitted core.
    """
    s = _static(config, objective_fn, record_template)
    jitted = _Compiled(
        propose=jax.jit(functools.partial(_propose, s)),
        observe=jax.jit(functools.partial(_observe, s)),
        set_target=jax.jit(functools.partial(_set_target, s)),
        beta=jax.jit(functools.partial(_beta, s)),
        best_observed=jax.jit(_best_observed),
        posterior_mean_argmax=jax.jit(functools.partial(_posterior_mean_argmax, s)),
    )
    return ContextualBO(
        init=functools.partial(_init, s),
        propose=functools.partial(_propose_checked, s, jitted),
        propose_with_fallback=functools.partial(_propose_with_fallback_checked, s, jitted),
        observe=functools.partial(_observe_checked, s, jitted),
        set_target=functools.partial(_set_target_checked, s, jitted),
        set_inference_mode=functools.partial(_set_inference_mode, s),
        beta=functools.partial(_beta_checked, s, jitted),
        best_observed=functools.partial(_best_observed_checked, s, jitted),
        posterior_mean_argmax=functools.partial(_posterior_mean_argmax_checked, s, jitted),
    )
