"""The optimizer of Algorithm 1 (cpgjax.optim.bo): beta schedule and context counting on hand-built
histories, data reuse, validation, batching, and optimization of standard test functions."""

import functools
import operator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import gp
from cpgjax.optim import black_box, bo, exploration
from cpgjax.optim import config as optimizer_config
from cpgjax.optim.acquisition import AcquisitionConfig
from cpgjax.trial import optimizer_setting

SMALL = optimizer_setting.paper_config(
    capacity=12, fit=gp.FitConfig(30, 0.2), acquisition=AcquisitionConfig(128, 4, 15, 0.05)
)
LOWER, UPPER = np.array(SMALL.parameter_lower), np.array(SMALL.parameter_upper)
MIDPOINT = 0.5 * (LOWER + UPPER)
NOMINAL = jnp.array([40.0, -0.1])  # c = [c_load N, c_slope rad]


@pytest.fixture(scope="module")
def opt():
    return bo.make_optimizer(SMALL)


def toy_objective(x, context):
    """A smooth objective on the unit box, its peak moving with the context."""
    unit = (x - LOWER) / (UPPER - LOWER)
    peak = 0.3 + 0.4 * (context[0] - 15.0) / 60.0
    return jnp.exp(-4.0 * jnp.sum((unit - peak) ** 2)) + 0.1 * unit[0]


def history(opt, contexts, objectives=None):
    """A state whose stored trials have the given contexts (no fit: for beta only)."""
    state = opt.init()
    n = len(contexts)
    objectives = np.zeros(n) if objectives is None else objectives
    return state._replace(
        contexts=state.contexts.at[:n].set(jnp.asarray(contexts, jnp.float32)),
        objectives=state.objectives.at[:n].set(jnp.asarray(objectives, jnp.float32)),
        stored=state.stored.at[:n].set(True),
        num_stored=jnp.int32(n),
    )


# ---- beta, eqs. (12)-(14), docs/decisions.md §11-12 -------------------------------------------------


@pytest.mark.parametrize(
    "contexts, query, beta, n, changed",
    [
        ([], NOMINAL, 5.0, 0, False),
        ([[40.0, -0.1]] * 10, NOMINAL, 5.0, 10, False),  # decay starts after n_decay = 10
        ([[40.0, -0.1]] * 12, NOMINAL, 5.0 * 0.7**2, 12, False),
        # 8 trials at 40 N, then 4 at 55 N (|15 N| > t_load r_load = 0.2 * 40 = 8 N): changed.
        ([[40.0, -0.1]] * 8 + [[55.0, -0.1]] * 4, [55.0, -0.1], 1.5 * 0.7**1, 4, True),
        ([[40.0, -0.1]] * 8 + [[55.0, -0.1]] * 4, NOMINAL, 1.5 * 0.7**5, 8, True),
        # Threshold edges: 8 N in load (r_load = 55 − 15 = 40 N, docs/decisions.md §11), t_slope r_slope = 0.1 * 0.5 =
        # 0.05 rad in slope.
        (
            [[47.9, -0.1], [48.1, -0.1], [32.1, -0.1], [31.9, -0.1], [40.0, -0.149], [40.0, -0.151]],
            NOMINAL,
            1.5,
            3,
            True,
        ),
    ],
)
def test_beta_schedule_and_context_counting(opt, contexts, query, beta, n, changed):
    info = opt.beta(history(opt, np.reshape(contexts, (-1, 2))), jnp.asarray(query))
    assert info.beta == pytest.approx(beta, rel=1e-5)
    assert int(info.num_in_context) == n
    assert bool(info.context_changed) == changed


def test_beta_custom_schedule_and_inference_mode(opt):
    state = history(opt, [[40.0, -0.1]] * 3)._replace(
        schedule=exploration.paper_schedule(beta_init=2.0, gamma=0.5, n_decay=1)
    )
    assert opt.beta(state, NOMINAL).beta == pytest.approx(2.0 * 0.5**2)
    inference = opt.set_inference_mode(state, True)
    assert opt.beta(inference, NOMINAL).beta == pytest.approx(1e-6)


# ---- proposals ------------------------------------------------------------------------------


def test_random_phase_then_acquisition_and_inactive_midpoint(opt):
    key = jax.random.PRNGKey(0)
    seven = opt.init(active_dims=jnp.arange(8) < 7)  # no sigma_N (docs/decisions.md §13)
    first = np.asarray(opt.propose(seven, NOMINAL, key))
    assert np.all(first >= LOWER) and np.all(first <= UPPER)
    assert first[7] == pytest.approx(MIDPOINT[7], abs=1e-7)
    assert not np.allclose(first, opt.propose(seven, NOMINAL, jax.random.PRNGKey(1)))

    def observed(values):
        state = seven
        for i, value in enumerate(values):
            x = opt.propose(state, NOMINAL, jax.random.PRNGKey(10 + i))
            state, accepted = opt.observe(state, x, NOMINAL, jnp.float32(value))
            assert accepted
        return state

    one = observed([1.0])
    # Random phase: the proposal ignores the data.
    np.testing.assert_array_equal(opt.propose(one, NOMINAL, key), first)
    low, high = observed([1.0, 0.0]), observed([0.0, 1.0])
    x_low, x_high = opt.propose(low, NOMINAL, key), opt.propose(high, NOMINAL, key)
    assert not np.allclose(x_low, x_high)  # the acquisition phase follows the data
    for x in (x_low, x_high):
        assert np.all(np.asarray(x) >= LOWER) and np.all(np.asarray(x) <= UPPER)
        assert float(x[7]) == pytest.approx(MIDPOINT[7], abs=1e-7)


@pytest.fixture(scope="module")
def trained(opt):
    """A state with 10 observations of the toy objective at the nominal context."""
    state = opt.init()
    for i in range(10):
        x = opt.propose(state, NOMINAL, jax.random.PRNGKey(100 + i))
        state, _ = opt.observe(state, x, NOMINAL, toy_objective(x, NOMINAL))
    return state


def test_queries_best_observed_and_posterior_mean_argmax(opt, trained):
    values = np.asarray(trained.objectives[:10])
    x_best, c_best, j_best = opt.best_observed(trained)
    assert float(j_best) == values.max()
    np.testing.assert_array_equal(x_best, trained.parameters[int(np.argmax(values))])
    np.testing.assert_array_equal(c_best, NOMINAL)

    key = jax.random.PRNGKey(5)
    x_mean, mean_value = opt.posterior_mean_argmax(trained, NOMINAL, key)
    assert np.all(np.asarray(x_mean) >= LOWER) and np.all(np.asarray(x_mean) <= UPPER)
    # It maximizes the posterior mean: at least its value at every stored point.
    dataset = gp.Dataset(
        jnp.concatenate(
            [
                (trained.parameters - LOWER) / (UPPER - LOWER),
                (trained.contexts - np.array([15.0, -0.4])) / np.array([40.0, 0.5]),
            ],
            1,
        ),
        trained.objectives,
        trained.stored,
    )
    post = gp.posterior(trained.gp_params, dataset, jnp.ones(10, bool), 2)
    stored_means, _ = gp.predict(post, dataset.inputs[:10], 2)
    assert float(mean_value) >= float(stored_means.max()) - 1e-5
    # Inference mode (beta = 1e-6): the proposal maximizes the posterior mean as well.
    inference_x = opt.propose(opt.set_inference_mode(trained, True), NOMINAL, key)
    unit_query = jnp.concatenate([(inference_x - LOWER) / (UPPER - LOWER), dataset.inputs[0, 8:]])
    inference_mean, _ = gp.predict(post, unit_query[None], 2)
    spread = float(stored_means.max() - stored_means.min())
    assert float(inference_mean[0]) == pytest.approx(float(mean_value), abs=0.02 * spread)
    assert float(inference_mean[0]) >= float(stored_means.max()) - 1e-5


# ---- data reuse ---------------------------------------------------------------------------


class Record(NamedTuple):
    velocity_xy_mps: jax.Array  # (50, 2)
    energy: jax.Array  # ()


def record_objective(record, target_velocity):
    target = jnp.stack([target_velocity, 0.0])
    reward = jnp.minimum(jnp.exp(-jnp.sum((record.velocity_xy_mps - target) ** 2, -1) / 0.05), 0.85)
    return jnp.mean(reward) - 0.5 * record.energy


def numpy_record_objective(record, target_velocity):
    error = np.sum((np.asarray(record.velocity_xy_mps, np.float64) - [target_velocity, 0.0]) ** 2, -1)
    return np.mean(np.minimum(np.exp(-error / 0.05), 0.85)) - 0.5 * float(record.energy)


TEMPLATE = Record(jax.ShapeDtypeStruct((50, 2), jnp.float32), jax.ShapeDtypeStruct((), jnp.float32))


@pytest.fixture(scope="module")
def reuse_opt():
    return bo.make_optimizer(SMALL, record_objective, TEMPLATE)


def make_records(num):
    rng = np.random.default_rng(7)
    return [
        Record(
            jnp.asarray(rng.uniform(0.2, 0.9) + 0.05 * rng.normal(size=(50, 2)), jnp.float32),
            jnp.float32(rng.uniform(0.1, 0.5)),
        )
        for _ in range(num)
    ]


def test_data_reuse_equals_recomputation_from_scratch(reuse_opt):
    records = make_records(6)
    xs = [jnp.asarray(LOWER + (UPPER - LOWER) * (i + 0.5) / 6, jnp.float32) for i in range(6)]

    def run(target):
        state = reuse_opt.init(target_velocity=jnp.float32(target))
        for x, record in zip(xs, records, strict=True):
            state, _ = reuse_opt.observe(state, x, NOMINAL, record)
        return state

    reused = reuse_opt.set_target(run(0.3), jnp.float32(0.8))
    scratch = run(0.8)
    expected = [numpy_record_objective(r, 0.8) for r in records]
    np.testing.assert_allclose(reused.objectives[:6], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(reused.objectives, scratch.objectives, rtol=1e-6, atol=1e-7)
    assert float(reused.target_velocity) == pytest.approx(0.8)
    assert not np.allclose(run(0.3).objectives[:6], expected)  # the target matters
    np.testing.assert_array_equal(reuse_opt.best_observed(reused)[0], xs[int(np.argmax(expected))])
    # The surrogate was refitted on the recomputed objectives.
    assert not np.allclose(reused.gp_params.mean, run(0.3).gp_params.mean)

    with pytest.raises(ValueError, match="set_target needs"):
        bo.make_optimizer(SMALL).set_target(bo.make_optimizer(SMALL).init(), 0.8)


def test_a_state_cut_to_its_observed_rows_is_restored_over_a_fresh_one(reuse_opt):
    """``first_rows`` keeps the observation buffers' first rows (the trial records too); ``full_rows`` over a fresh
    state gives back every leaf, for one instance and for a batch whose instances stored different counts."""
    records = make_records(3)
    xs = [jnp.asarray(LOWER + (UPPER - LOWER) * (i + 0.5) / 3, jnp.float32) for i in range(3)]
    state = reuse_opt.init(target_velocity=jnp.float32(0.5))
    states = []
    for x, record in zip(xs, records, strict=True):
        state, _ = reuse_opt.observe(state, x, NOMINAL, record)
        states.append(state)
    assert state.stored.shape[0] > 3  # the capacity
    init = reuse_opt.init(target_velocity=jnp.float32(0.5))
    stack = functools.partial(jax.tree.map, lambda *a: np.stack(a))
    for full, fresh in ((state, init), (stack(state, states[1]), stack(init, init))):
        cut = bo.first_rows(full, 3)
        assert cut.records.velocity_xy_mps.shape[-3] == 3 and cut.stored.shape[-1] == 3
        for a, b in zip(jax.tree.leaves(bo.full_rows(fresh, cut)), jax.tree.leaves(full), strict=True):
            np.testing.assert_array_equal(a, b)


def test_non_finite_record_is_rejected(reuse_opt):
    state = reuse_opt.init(target_velocity=jnp.float32(0.5))
    bad = Record(jnp.full((50, 2), jnp.nan, jnp.float32), jnp.float32(0.1))
    with pytest.raises(ValueError, match="non-finite objective"):
        reuse_opt.observe(state, jnp.asarray(MIDPOINT, jnp.float32), NOMINAL, bad)
    with pytest.raises(ValueError, match="structure"):
        reuse_opt.observe(state, jnp.asarray(MIDPOINT, jnp.float32), NOMINAL, jnp.float32(1.0))
    with pytest.raises(ValueError, match="target_velocity is required"):
        reuse_opt.init()


# ---- validation ---------------------------------------------------------------------------


def test_bad_calls_fail_with_clear_errors(opt):
    state = opt.init()
    x = jnp.asarray(MIDPOINT, jnp.float32)
    with pytest.raises(ValueError, match=r"x must have shape \(8,\)"):
        opt.observe(state, x[:7], NOMINAL, 1.0)
    with pytest.raises(ValueError, match=r"context must have shape \(2,\)"):
        opt.propose(state, jnp.zeros(3), jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"x\[2\] = 30.0 is outside its range \[16.0, 23.0\]"):
        opt.observe(state, x.at[2].set(30.0), NOMINAL, 1.0)
    with pytest.raises(ValueError, match="objective value must be finite"):
        opt.observe(state, x, NOMINAL, jnp.float32(np.inf))
    with pytest.raises(ValueError, match="context must be finite"):
        opt.observe(state, x, jnp.array([np.nan, 0.0]), 1.0)
    full = state._replace(num_stored=jnp.int32(SMALL.capacity))
    with pytest.raises(ValueError, match="capacity exceeded"):
        opt.observe(full, x, NOMINAL, 1.0)
    with pytest.raises(ValueError, match="no observation stored"):
        opt.best_observed(state)
    with pytest.raises(ValueError, match=r"state.parameters must have shape \(12, 8\)"):
        opt.propose(jax.tree.map(lambda a: jnp.stack([a, a]), state), NOMINAL, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="lower < upper"):
        optimizer_config.OptimizerConfig((0.0, 1.0), (1.0, 1.0))
    with pytest.raises(ValueError, match="context_thresholds"):
        optimizer_config.OptimizerConfig((0.0,), (1.0,), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="ucb_form"):
        optimizer_setting.paper_config(ucb_form="sqrt")
    # An inactive parameter may hold any finite value.
    seven = opt.init(active_dims=jnp.arange(8) < 7)
    _, accepted = opt.observe(seven, x.at[7].set(-5.0), NOMINAL, 1.0)
    assert accepted


# ---- batching -----------------------------------------------------------------------------


def test_vmapped_instances_equal_unbatched_runs(opt):
    """Three instances with their own keys, contexts, schedules and active inputs (7 and 8
    parameters), run 4 trials vmapped and one by one on the same data: same random-phase
    proposals bit for bit, same stored data, and acquisition-phase proposals equal up to
    float32 round-off, which XLA's batched kernels produce differently and the fit's Adam
    steps and the acquisition's top-k choice amplify (measured <= 0.5 % of the box width;
    asserted <= 2 %). Then a non-finite and an over-capacity observation are rejected per
    instance under vmap."""
    inits = [
        opt.init(),
        opt.init(active_dims=jnp.arange(8) < 7),
        opt.init(schedule=exploration.paper_schedule(beta_init=1.0, gamma=0.5, n_decay=2)),
    ]
    contexts = jnp.array([[40.0, -0.1], [55.0, 0.0], [20.0, -0.3]])
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    stack = lambda trees: jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)  # noqa: E731
    batched = stack(inits)
    propose_b, observe_b = jax.jit(jax.vmap(opt.propose)), jax.jit(jax.vmap(opt.observe))
    single = list(inits)
    for trial in range(4):
        trial_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, trial)
        xs = propose_b(batched, contexts, trial_keys)
        ys = jax.vmap(toy_objective)(xs, contexts)
        batched, accepted = observe_b(batched, xs, contexts, ys)
        assert np.all(accepted)
        for i in range(3):
            x = opt.propose(single[i], contexts[i], trial_keys[i])
            tolerance = 0.0 if trial < SMALL.num_random_proposals else 0.02
            np.testing.assert_allclose((xs[i] - x) / (UPPER - LOWER), 0.0, atol=tolerance)
            single[i], _ = opt.observe(single[i], xs[i], contexts[i], ys[i])
    for i in range(3):
        instance = jax.tree.map(operator.itemgetter(i), batched)
        for a, b in zip(
            jax.tree.leaves(instance._replace(gp_params=())),
            jax.tree.leaves(single[i]._replace(gp_params=())),
            strict=True,
        ):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(instance.gp_params, single[i].gp_params, strict=True):
            np.testing.assert_allclose(a, b, atol=0.05)
    assert float(batched.parameters[1, 0, 7]) == pytest.approx(MIDPOINT[7], abs=1e-7)

    ys = jnp.array([1.0, jnp.nan, 1.0])
    full = batched._replace(num_stored=batched.num_stored.at[2].set(SMALL.capacity))
    after, accepted = observe_b(full, xs, contexts, ys)
    np.testing.assert_array_equal(accepted, [True, False, False])
    np.testing.assert_array_equal(after.num_stored, [5, 4, SMALL.capacity])
    np.testing.assert_array_equal(after.objectives[1], full.objectives[1])
    assert np.all(np.isfinite(after.objectives))


# ---- optimization of standard test functions (known optima) ------------------------------


def branin(x):
    b, c, t = 5.1 / (4 * np.pi**2), 5 / np.pi, 1 / (8 * np.pi)
    return (x[1] - b * x[0] ** 2 + c * x[0] - 6) ** 2 + 10 * (1 - t) * np.cos(x[0]) + 10


H6_A = np.array(
    [[10, 3, 17, 3.5, 1.7, 8], [0.05, 10, 17, 0.1, 8, 14], [3, 3.5, 1.7, 10, 17, 8], [17, 8, 0.05, 10, 0.1, 14]]
)
H6_P = 1e-4 * np.array(
    [
        [1312, 1696, 5569, 124, 8283, 5886],
        [2329, 4135, 8307, 3736, 1004, 9991],
        [2348, 1451, 3522, 2883, 3047, 6650],
        [4047, 8828, 8732, 5743, 1091, 381],
    ]
)
H6_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])


def neg_hartmann6(x):  # maximum 3.32237 at (0.20169, 0.150011, 0.476874, 0.275332, 0.311652, 0.6573)
    return jnp.sum(H6_ALPHA * jnp.exp(-jnp.sum(H6_A * (x - H6_P) ** 2, axis=-1)))


def cosine8(x):  # maximum 0.8 at 0 on [-1, 1]^8
    return 0.1 * jnp.sum(jnp.cos(5 * jnp.pi * x)) - jnp.sum(x**2)


def batched_regrets(fn, lower, upper, optimum, num_evals, num_seeds):
    """Simple regret of ``num_seeds`` independent runs, vmapped as one batch."""
    opt = bo.make_optimizer(optimizer_config.OptimizerConfig(tuple(lower), tuple(upper), capacity=num_evals))
    propose, observe = jax.jit(jax.vmap(opt.propose)), jax.jit(jax.vmap(opt.observe))
    states = jax.tree.map(lambda leaf: jnp.stack([leaf] * num_seeds), opt.init())
    no_context = jnp.zeros((num_seeds, 0))
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    best = np.full(num_seeds, -np.inf)
    for trial in range(num_evals):
        xs = propose(states, no_context, jax.vmap(jax.random.fold_in, (0, None))(keys, trial))
        ys = jax.vmap(fn)(xs)
        states, _ = observe(states, xs, no_context, ys)
        best = np.maximum(best, np.asarray(ys))
    return optimum - best


def test_maximize_finds_the_branin_minimum():
    """Branin (minimum 0.397887), 40 evaluations, 3 seeds: median regret <= 0.05, all <= 0.1
    (measured: 0.059, 0.0098, 0.0011)."""
    regrets = []
    for seed in range(3):
        result = black_box.maximize(lambda x: -branin(x), [[-5.0, 0.0], [10.0, 15.0]], num_trials=40, seed=seed)
        assert result.xs.shape == (40, 2) and result.best_value == result.values.max()
        assert branin(result.best_x) == pytest.approx(-result.best_value)
        regrets.append(-result.best_value - 0.397887)
    assert np.median(regrets) <= 0.05 and max(regrets) <= 0.1, regrets


def test_hartmann6_and_cosine8_within_tolerance():
    """8 seeds, 50 evaluations each. Hartmann-6 (optimum 3.32237; a local optimum traps some
    runs): at least 3 seeds within 0.01 of the optimum (measured: 4). Cosine8 (8-D, optimum
    0.8): median regret <= 0.25 (measured: 0.09)."""
    h6 = batched_regrets(neg_hartmann6, np.zeros(6), np.ones(6), 3.32237, 50, 8)
    c8 = batched_regrets(cosine8, -np.ones(8), np.ones(8), 0.8, 50, 8)
    assert np.sum(h6 <= 0.01) >= 3, h6
    assert np.median(c8) <= 0.25, c8
