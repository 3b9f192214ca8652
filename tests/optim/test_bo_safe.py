"""Safe optimization (docs/decisions.md §17): the trial's safety margin against a NumPy transcription of its
definition, the safe optimizer's proposal against a dense float64 reference GP on a small problem, its fallbacks,
its argument checks, and the black-box loop on a constrained test function."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import gp
from cpgjax.go1 import model as go1_model
from cpgjax.optim import black_box, bo
from cpgjax.optim import config as optimizer_config
from cpgjax.optim.acquisition import AcquisitionConfig
from cpgjax.trial import protocol
from tests.numpy_reference import RefGP

TRIAL = protocol.TrialConfig()


def reference_margin(height_m, floor_roll, floor_pitch, imu_roll, imu_pitch):
    """The definition: the worst of the tilt stop's, the fall tilt's and the height's margins, each 1 at level
    standing at the controller's height (0.30 m) and 0 at its threshold (0.7 rad IMU, 0.8 rad floor, 0.12 m)."""
    stop = 1.0 - max(abs(imu_roll), abs(imu_pitch)) / 0.7
    fall = 1.0 - max(abs(floor_roll), abs(floor_pitch)) / 0.8
    height = (height_m - 0.12) / (0.30 - 0.12)
    return min(stop, fall, height)


def quaternion_wxyz(roll, pitch):
    """Rotation R = Ry(pitch) Rx(roll) (yaw 0) as a unit quaternion."""
    qx = np.array([np.cos(roll / 2), np.sin(roll / 2), 0.0, 0.0])
    qy = np.array([np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0])
    w1, x1, y1, z1 = qy
    w2, x2, y2, z2 = qx
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


@pytest.mark.parametrize(
    "height_m, floor_roll, floor_pitch, imu_roll, imu_pitch",
    [
        (0.30, 0.0, 0.0, 0.0, 0.0),  # standing level: 1
        (0.21, 0.05, -0.1, 0.02, 0.03),  # half the clearance: 0.5
        (0.28, 0.6, 0.1, 0.1, 0.1),  # floor roll 0.6 of 0.8 rad
        (0.28, 0.1, 0.1, -0.1, 0.65),  # the IMU near the tilt stop
        (0.08, 0.0, 0.0, 0.0, 0.0),  # below the fall height: negative
        (0.25, 0.0, 1.2, 0.0, 1.0),  # beyond both tilts: negative
    ],
)
def test_tick_margin_is_the_worst_of_height_fall_tilt_and_tilt_stop(
    height_m, floor_roll, floor_pitch, imu_roll, imu_pitch
):
    ids = go1_model.indices()
    qpos = np.asarray(go1_model.standing_qpos(), np.float64).copy()
    qpos[ids.root_qpos + 2] = height_m
    qpos[ids.root_qpos + 3 : ids.root_qpos + 7] = quaternion_wxyz(floor_roll, floor_pitch)
    pre = protocol.PreStep(
        power_w=jnp.float32(0),
        load_n=jnp.float32(0),
        roll_rad=jnp.float32(imu_roll),
        pitch_rad=jnp.float32(imu_pitch),
        saturated=jnp.float32(0),
    )
    qpos = jnp.asarray(qpos, jnp.float32)
    qvel = jnp.zeros(6 + 12, jnp.float32)  # the free trunk and 12 joints
    row = protocol.tick_row(TRIAL, pre, qpos, qvel, jnp.asarray(False))
    expected = reference_margin(height_m, floor_roll, floor_pitch, imu_roll, imu_pitch)
    assert float(row.margin) == pytest.approx(expected, abs=1e-5)
    assert (float(row.margin) < 0) == bool(row.fell > 0 or max(abs(imu_roll), abs(imu_pitch)) > 0.7)
    failed = protocol.tick_row(TRIAL, pre, qpos, qvel, jnp.asarray(True))
    assert float(failed.margin) == protocol.FAILED_MARGIN


def test_a_trials_margin_is_its_worst_tick_transition_included():
    steady_margins = np.array([0.9, 0.4, 0.7], np.float32)
    ticks = protocol.Tick(
        velocity_xy_mps=jnp.zeros((3, 2)),
        power_w=jnp.zeros(3),
        load_n=jnp.zeros(3),
        roll_rad=jnp.zeros(3),
        pitch_rad=jnp.zeros(3),
        saturated=jnp.zeros(3),
        fell=jnp.zeros(3),
        failed=jnp.zeros(3),
        margin=jnp.asarray(steady_margins),
    )
    calm = protocol.summarize(
        ticks,
        jnp.float32(12.0),
        0.001,
        protocol.TransitionSummary.of(
            ticks._replace(margin=jnp.asarray([0.8, 0.95], jnp.float32), fell=jnp.zeros(2), failed=jnp.zeros(2))
        ),
    )
    assert float(calm.safety_margin) == pytest.approx(0.4)
    shaky = protocol.summarize(
        ticks,
        jnp.float32(12.0),
        0.001,
        protocol.TransitionSummary.of(
            ticks._replace(margin=jnp.asarray([0.8, -0.2], jnp.float32), fell=jnp.zeros(2), failed=jnp.zeros(2))
        ),
    )
    assert float(shaky.safety_margin) == pytest.approx(-0.2)
    alone = protocol.summarize(ticks, jnp.float32(12.0), 0.001, protocol.TransitionSummary.nothing())
    assert float(alone.safety_margin) == pytest.approx(0.4)


# ---- the safe optimizer ---------------------------------------------------------------------------------------

SAFE = optimizer_config.OptimizerConfig(
    parameter_lower=(0.0, 0.0),
    parameter_upper=(1.0, 1.0),
    capacity=12,
    safe=True,
    safe_beta=2.0,
    fit=gp.FitConfig(40, 0.2),
    acquisition=AcquisitionConfig(256, 8, 40, 0.05),
)
PEAK = np.array([0.85, 0.85])  # the objective's peak, outside the safe disk
SAFE_CENTRE, SAFE_RADIUS = np.array([0.3, 0.3]), 0.3
NO_CONTEXT = jnp.zeros((0,), jnp.float32)


def toy(u):
    """Objective and margin on the unit square: the peak lies outside the disk where the margin is ≥ 0."""
    return -float(np.sum((u - PEAK) ** 2)), SAFE_RADIUS - float(np.linalg.norm(u - SAFE_CENTRE))


@pytest.fixture(scope="module")
def safe_opt():
    return bo.make_optimizer(SAFE)


@pytest.fixture(scope="module")
def observed(safe_opt):
    points = np.array(
        [[0.3, 0.3], [0.45, 0.3], [0.3, 0.5], [0.45, 0.45], [0.15, 0.2], [0.9, 0.9], [0.75, 0.2], [0.15, 0.65]]
    )
    state = safe_opt.init()
    for u in points:
        j, g = toy(u)
        state, _ = safe_opt.observe(state, jnp.asarray(u, jnp.float32), NO_CONTEXT, jnp.float32(j), jnp.float32(g))
    return state, points


def test_the_margin_gp_fits_under_its_own_priors(observed):
    """The same observations, the margin GP given other priors: its hyperparameters are the MAP under those (the
    fit's objective is higher there than the default fit's), the objective's GP does not change."""
    state, points = observed
    values = np.array([toy(u) for u in points])
    priors = gp.Priors(
        lengthscale=gp.GammaPrior(8.0, 4.0), outputscale=gp.GammaPrior(2.0, 2.0), noise=gp.GammaPrior(2.0, 100.0)
    )
    own = bo.make_optimizer(dataclasses.replace(SAFE, margin_priors=priors))
    other = own.init()
    for u, (j, g) in zip(points, values, strict=True):
        other, _ = own.observe(other, jnp.asarray(u, jnp.float32), NO_CONTEXT, jnp.float32(j), jnp.float32(g))
    for a, b in zip(jax.tree.leaves(other.gp_params), jax.tree.leaves(state.gp_params), strict=True):
        np.testing.assert_array_equal(a, b)
    data = gp.Dataset(
        jnp.asarray(points, jnp.float32), jnp.asarray(values[:, 1], jnp.float32), jnp.ones(len(points), bool)
    )
    active = jnp.ones(2, bool)

    def log_map(params):
        return float(gp.log_posterior(params, data, active, 0, priors))

    assert log_map(other.margin_gp_params) > log_map(state.margin_gp_params)
    # Their lengthscale prior's mean is 2, BoTorch's 0.5: the same data fitted under it give longer lengthscales.
    assert np.mean(other.margin_gp_params.log_lengthscales) > np.mean(state.margin_gp_params.log_lengthscales) + 0.2


def test_safe_proposal_maximizes_the_ucb_over_the_reference_safe_set(safe_opt, observed):
    state, points = observed
    x, fell_back = safe_opt.propose_with_fallback(state, NO_CONTEXT, jax.random.PRNGKey(3))
    assert not bool(fell_back)
    beta = float(safe_opt.beta(state, NO_CONTEXT).beta)
    active = np.ones(2, bool)
    values = np.array([toy(u) for u in points])
    objective_gp = RefGP(state.gp_params, points, values[:, 0], active, 0, gp.JITTER_RATIO)
    margin_gp = RefGP(state.margin_gp_params, points, values[:, 1], active, 0, gp.JITTER_RATIO)

    def bounds(queries):
        mean, var = objective_gp.predict(queries)
        g_mean, g_var = margin_gp.predict(queries)
        return mean + beta * np.sqrt(np.maximum(var, 0)), g_mean - 2.0 * np.sqrt(np.maximum(g_var, 0))

    axis = np.linspace(0.0, 1.0, 201)
    grid = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    ucb, lcb = bounds(grid)
    assert lcb[np.argmax(ucb)] < 0.0  # not vacuous: the unconstrained UCB argmax is not certified safe
    best_safe = np.max(np.where(lcb >= 0.0, ucb, -np.inf))
    ucb_x, lcb_x = bounds(np.asarray(x, np.float64)[None])
    assert lcb_x[0] >= -1e-3  # certified safe by the reference
    # The safe maximum lies on the safe set's edge, where the UCB still rises outward; the refinement stops just
    # inside it (acquisition.CONSTRAINT_CUSHION): within 0.15 of the objective's std of the dense grid's maximum.
    scale = np.std(values[:, 0], ddof=1)
    assert ucb_x[0] >= best_safe - 0.15 * scale
    assert ucb_x[0] > np.max(np.where(lcb >= 0.0, ucb, -np.inf)[np.linalg.norm(grid - 0.3, axis=1) < 0.15])


def test_no_certified_point_repeats_the_safe_observation_rated_safest(observed):
    """β_s = 1e4 certifies nothing: the proposal is the safe observation with the highest expected margin by the
    dense reference GP."""
    state, points = observed
    cautious = bo.make_optimizer(optimizer_config.OptimizerConfig(**{**SAFE.__dict__, "safe_beta": 1e4}))
    x, fell_back = cautious.propose_with_fallback(state, NO_CONTEXT, jax.random.PRNGKey(0))
    values = np.array([toy(u) for u in points])
    margin_gp = RefGP(state.margin_gp_params, points, values[:, 1], np.ones(2, bool), 0, gp.JITTER_RATIO)
    mean, _ = margin_gp.predict(points)
    assert bool(fell_back)
    np.testing.assert_allclose(np.asarray(x), points[np.argmax(np.where(values[:, 1] >= 0, mean, -np.inf))], atol=1e-6)


def test_fallback_does_not_repeat_parameters_that_fell_in_this_context():
    """One context dimension: two gaits safe at c = 0.1; the better one (a) fell at c = 0.9. At c = 0.9 nothing is
    certified, and the fallback walks b, the safe gait with the higher expected margin there, not a again."""
    config = optimizer_config.OptimizerConfig(
        parameter_lower=(0.0, 0.0),
        parameter_upper=(1.0, 1.0),
        context_lower=(0.0,),
        context_upper=(1.0,),
        context_thresholds=(0.1,),
        capacity=6,
        safe=True,
        fit=gp.FitConfig(40, 0.2),
        acquisition=AcquisitionConfig(256, 8, 40, 0.05),
    )
    opt = bo.make_optimizer(config)
    a, b = [0.3, 0.3], [0.7, 0.7]
    state = opt.init()
    for x, c, j, g in ((a, 0.1, 2.0, 0.5), (b, 0.1, 1.0, 0.4), (a, 0.9, -1.0, -2.0), ([0.2, 0.8], 0.9, -1.0, -1.5)):
        state, _ = opt.observe(
            state, jnp.asarray(x, jnp.float32), jnp.asarray([c], jnp.float32), jnp.float32(j), jnp.float32(g)
        )
    x, back = opt.propose_with_fallback(state, jnp.asarray([0.9], jnp.float32), jax.random.PRNGKey(1))
    assert bool(back)
    np.testing.assert_allclose(np.asarray(x), b, atol=1e-6)
    # Where both were safe, a is expected safer (0.5 against 0.4 measured): the rule judges in the current context.
    at_home, back_home = opt.propose_with_fallback(state, jnp.asarray([0.1], jnp.float32), jax.random.PRNGKey(1))
    assert bool(back_home)  # four points certify nothing, even here
    np.testing.assert_allclose(np.asarray(at_home), a, atol=1e-6)


def test_nothing_safe_seen_proposes_a_random_point_and_says_so(safe_opt):
    state = safe_opt.init()
    for u in ([0.9, 0.9], [0.8, 0.1], [0.1, 0.9]):
        j, g = toy(np.array(u))
        state, _ = safe_opt.observe(state, jnp.asarray(u, jnp.float32), NO_CONTEXT, jnp.float32(j), jnp.float32(g))
    x1, back1 = safe_opt.propose_with_fallback(state, NO_CONTEXT, jax.random.PRNGKey(1))
    x2, _ = safe_opt.propose_with_fallback(state, NO_CONTEXT, jax.random.PRNGKey(2))
    assert bool(back1) and np.all((np.asarray(x1) >= 0) & (np.asarray(x1) <= 1))
    assert not np.allclose(np.asarray(x1), np.asarray(x2))


def test_margins_are_required_by_a_safe_optimizer_and_refused_by_another(safe_opt):
    state, x = safe_opt.init(), jnp.asarray([0.3, 0.3], jnp.float32)
    with pytest.raises(ValueError, match="needs each observation's safety margin"):
        safe_opt.observe(state, x, NO_CONTEXT, jnp.float32(1.0))
    with pytest.raises(ValueError, match="margin must be finite"):
        safe_opt.observe(state, x, NO_CONTEXT, jnp.float32(1.0), jnp.float32(np.nan))
    plain = bo.make_optimizer(optimizer_config.OptimizerConfig(**{**SAFE.__dict__, "safe": False}))
    with pytest.raises(ValueError, match="needs a safe optimizer"):
        plain.observe(plain.init(), x, NO_CONTEXT, jnp.float32(1.0), jnp.float32(0.5))
    with pytest.raises(ValueError, match="safe_beta"):
        optimizer_config.OptimizerConfig(**{**SAFE.__dict__, "safe_beta": -1.0})


def test_black_box_safe_run_violates_far_less_and_finds_the_constrained_optimum():
    """25 evaluations from the same two safe starting points: the unconstrained run walks out of the disk to the
    peak, the safe one stays inside and ends near the disk's point closest to the peak."""
    start = [[0.3, 0.3], [0.35, 0.25]]
    plain = black_box.maximize(lambda u: toy(u)[0], [[0, 0], [1, 1]], 25, seed=1, initial_xs=start)
    safe = black_box.maximize(toy, [[0, 0], [1, 1]], 25, seed=1, initial_xs=start, safe=True)
    violations = lambda xs: int(sum(toy(u)[1] < 0 for u in xs))  # noqa: E731
    constrained_best = toy(SAFE_CENTRE + SAFE_RADIUS * (PEAK - SAFE_CENTRE) / np.linalg.norm(PEAK - SAFE_CENTRE))[0]
    assert violations(plain.xs) >= 10
    assert violations(safe.xs) <= 2
    assert toy(safe.best_x)[1] >= 0 and safe.best_value >= constrained_best - 0.02
    np.testing.assert_array_equal(safe.margins, [toy(u)[1] for u in safe.xs])


# ------------------------------------------------------------------------------------- safety stops on the robot


def test_only_the_trips_a_gait_causes_become_unsafe_trials():
    from cpgjax.robot import safety

    state_reasons = [
        "tilt: roll +0.812 rad, pitch +0.010 rad beyond ±0.7 rad",
        "power protection: Σ|tauEst·dq| = 1210 W > 900 W (level 9)",
        "the SDK's power protection tripped",
    ]
    other = [
        "remote stop buttons L2+B pressed",
        "motor temperature: motor 3 at 80 °C ≥ 70 °C",
        "no robot state within 2.0 s",
        "non-finite command (tau)",
        "stale state: no new robot tick for 6 ticks",
        None,
    ]
    assert [safety.is_gait_trip(r) for r in state_reasons] == [True] * 3
    assert [safety.is_gait_trip(r) for r in other] == [False] * len(other)


def test_a_stopped_trial_fell_with_the_stops_margin_and_the_figures_it_walked():
    from cpgjax.deployment import trials
    from cpgjax.trial import objective

    walked = np.zeros((40, 7), np.float32)
    walked[:, 0], walked[:, 3], walked[:, 4] = 0.3, 30.0, 0.35  # v_x, load, a roll of half the tilt stop
    record = trials.stopped_trial_record(walked, -0.16, 12.74)
    assert float(record.fell) == 1.0 and float(record.safety_margin) == pytest.approx(-0.16)
    assert float(objective.objective(record, 0.5)) == objective.MIN_OBJECTIVE
    np.testing.assert_allclose(np.mean(np.asarray(record.velocity_xy_mps)[:, 0]), 0.3, rtol=1e-6)
    # The steady ticks' own margin is the worst when it is below the stop's (the stop's is at most 0).
    assert float(trials.stopped_trial_record(walked, 0.0, 12.74).safety_margin) == pytest.approx(0.0)
    walked[5, 4] = 0.84  # 1.2 × the tilt stop
    assert float(trials.stopped_trial_record(walked, -0.1, 12.74).safety_margin) == pytest.approx(-0.2, abs=1e-6)
    before_steady = trials.stopped_trial_record(np.zeros((0, 7), np.float32), -0.05, 12.74)
    assert float(before_steady.safety_margin) == pytest.approx(-0.05) and float(before_steady.fell) == 1.0
    assert np.isnan(float(before_steady.distance_m)) and float(before_steady.total_mass_kg) == pytest.approx(12.74)
