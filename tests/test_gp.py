"""GP regression (cpgjax.gp) and the acquisition maximizer against independent references.

The reference is a dense float64 NumPy GP written from the textbook formulas (Rasmussen &
Williams, Alg. 2.1) with the model of cpgjax.gp's docstring; cpgjax runs in float32.
"""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import gp
from cpgjax.optim import acquisition
from tests.numpy_reference import RefGP, ref_kernel

CONTEXT_DIMS = 2


BOTORCH = {"lengthscale": (3.0, 6.0), "outputscale": (2.0, 0.15), "noise": (1.1, 0.05)}  # BoTorch 0.5.0's
OTHER = {"lengthscale": (5.0, 2.5), "outputscale": (3.0, 1.0), "noise": (2.0, 40.0)}  # any other priors


def ref_log_prior(params, active, priors=BOTORCH):
    def gamma_logpdf(x, a, rate):
        from math import lgamma

        return a * np.log(rate) - lgamma(a) + (a - 1) * np.log(x) - rate * x

    ls = np.exp(np.asarray(params.log_lengthscales, np.float64))
    return (
        sum(gamma_logpdf(v, *priors["lengthscale"]) for v, on in zip(ls, active, strict=True) if on)
        + gamma_logpdf(float(np.exp(params.log_outputscale)), *priors["outputscale"])
        + gamma_logpdf(float(np.exp(params.log_noise)), *priors["noise"])
    )


def as_priors(priors) -> gp.Priors:
    return gp.Priors(**{name: gp.GammaPrior(*ab) for name, ab in priors.items()})


# ---- fixtures: data and compiled functions shared by the module ---------------------------


def random_params(rng, dims):
    return gp.GPParams(
        log_lengthscales=jnp.asarray(np.log(rng.uniform(0.2, 1.5, dims)), jnp.float32),
        log_outputscale=jnp.asarray(np.log(rng.uniform(0.5, 3.0)), jnp.float32),
        log_noise=jnp.asarray(np.log(rng.uniform(1e-3, 0.1)), jnp.float32),
        mean=jnp.asarray(rng.uniform(-0.5, 0.5), jnp.float32),
    )


def smooth_targets(inputs):
    return np.sin(6 * inputs[:, 0]) + inputs[:, 1] ** 2 - 2 * inputs[:, -1] + 0.5 * inputs[:, -2]


@pytest.fixture(scope="module")
def compiled():
    lml = jax.jit(gp.log_marginal_likelihood, static_argnums=3)
    grad = jax.jit(lambda *args: gp.log_posterior_and_gradient(*args)[1], static_argnums=3)

    @jax.jit
    def predict(params, dataset, active, queries):
        return gp.predict(gp.posterior(params, dataset, active, CONTEXT_DIMS), queries, CONTEXT_DIMS)

    fit = jax.jit(gp.fit, static_argnums=(3, 4))
    return dict(lml=lml, grad=grad, predict=predict, fit=fit)


@pytest.fixture(scope="module")
def problem():
    """30 points in 6-D (4 parameters, one inactive, + 2 contexts) and 20 queries."""
    rng = np.random.default_rng(0)
    inputs = rng.random((30, 6))
    active = np.array([True, True, False, True, True, True])
    return dict(
        inputs=inputs,
        targets=3.0 + 2.0 * smooth_targets(inputs),
        active=active,
        queries=rng.random((20, 6)),
        params=random_params(rng, 6),
    )


def dataset_of(inputs, targets, valid=None):
    valid = np.ones(len(targets), bool) if valid is None else valid
    return gp.Dataset(jnp.asarray(inputs, jnp.float32), jnp.asarray(targets, jnp.float32), jnp.asarray(valid))


# ---- posterior and likelihood against the reference -------------------------------------


def test_posterior_matches_dense_numpy_reference(compiled, problem):
    p = problem
    ref = RefGP(p["params"], p["inputs"], p["targets"], p["active"], CONTEXT_DIMS, gp.JITTER_RATIO)
    mean, var = compiled["predict"](
        p["params"],
        dataset_of(p["inputs"], p["targets"]),
        jnp.asarray(p["active"]),
        jnp.asarray(p["queries"], jnp.float32),
    )
    ref_mean, ref_var = ref.predict(p["queries"])
    scale = ref.y_std
    np.testing.assert_allclose(mean, ref_mean, atol=2e-4 * scale)
    np.testing.assert_allclose(var, ref_var, atol=2e-4 * scale**2, rtol=1e-3)
    # Not vacuous: the data shrink the variance well below the prior's at training inputs.
    _, train_var = ref.predict(p["inputs"][:5])
    assert np.all(train_var < 0.5 * ref.s2 * scale**2)


def test_log_marginal_likelihood_and_gradient_match_reference(compiled, problem):
    p = problem
    active = jnp.asarray(p["active"])
    data = dataset_of(p["inputs"], p["targets"])
    ref = RefGP(p["params"], p["inputs"], p["targets"], p["active"], CONTEXT_DIMS, gp.JITTER_RATIO)
    lml = compiled["lml"](p["params"], data, active, CONTEXT_DIMS)
    np.testing.assert_allclose(lml, ref.log_marginal_likelihood(), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(
        gp.log_prior(p["params"], active), ref_log_prior(p["params"], p["active"]), rtol=1e-5, atol=1e-4
    )

    # The fit's analytic gradient against central differences of the float64 reference.
    def ref_objective(flat):
        params = gp.GPParams(flat[:6], flat[6], flat[7], flat[8])
        ref_gp = RefGP(params, p["inputs"], p["targets"], p["active"], CONTEXT_DIMS, gp.JITTER_RATIO)
        return ref_gp.log_marginal_likelihood() + ref_log_prior(params, p["active"])

    flat = np.concatenate([np.asarray(leaf, np.float64).ravel() for leaf in p["params"]])
    step = 1e-5
    numeric = np.array(
        [(ref_objective(flat + step * e) - ref_objective(flat - step * e)) / (2 * step) for e in np.eye(len(flat))]
    )
    grads = compiled["grad"](p["params"], data, active, CONTEXT_DIMS)
    analytic = np.concatenate([np.ravel(leaf) for leaf in grads])
    assert numeric[2] == pytest.approx(0.0, abs=1e-6)  # the inactive lengthscale is inert
    np.testing.assert_allclose(analytic, numeric, rtol=2e-3, atol=2e-3)


def test_a_gp_given_its_own_priors_fits_under_them(problem):
    """Priors other than BoTorch's (the safe optimizer's margin GP takes its own, ``OptimizerConfig.margin_priors``):
    the log prior and the log posterior's gradient against the reference under those priors."""
    p = problem
    active = jnp.asarray(p["active"])
    data = dataset_of(p["inputs"], p["targets"])
    priors = as_priors(OTHER)
    assert gp.BOTORCH_PRIORS == as_priors(BOTORCH)
    np.testing.assert_allclose(
        gp.log_prior(p["params"], active, priors), ref_log_prior(p["params"], p["active"], OTHER), rtol=1e-5, atol=1e-4
    )
    value, grads = jax.jit(gp.log_posterior_and_gradient, static_argnums=(3, 4))(
        p["params"], data, active, CONTEXT_DIMS, priors
    )
    ref = RefGP(p["params"], p["inputs"], p["targets"], p["active"], CONTEXT_DIMS, gp.JITTER_RATIO)
    np.testing.assert_allclose(
        value, ref.log_marginal_likelihood() + ref_log_prior(p["params"], p["active"], OTHER), rtol=1e-5, atol=2e-3
    )
    # d/du log Gamma(e^u; a, b) = (a - 1) - b e^u on each hyperparameter, the likelihood's part unchanged.
    _, default_grads = gp.log_posterior_and_gradient(p["params"], data, active, CONTEXT_DIMS)
    for name, field in (("outputscale", "log_outputscale"), ("noise", "log_noise")):
        value_now = float(np.exp(getattr(p["params"], field)))
        shift = ((OTHER[name][0] - 1) - OTHER[name][1] * value_now) - (
            (BOTORCH[name][0] - 1) - BOTORCH[name][1] * value_now
        )
        assert float(getattr(grads, field) - getattr(default_grads, field)) == pytest.approx(shift, rel=1e-4, abs=1e-4)
    assert gp.default_params(3, priors).log_lengthscales[0] == pytest.approx(np.log(5.0 / 2.5))


@pytest.mark.parametrize("size", [5, 33, 100, 160])
def test_cholesky_inverse_matches_numpy(size):
    """The recursive block inverse of a Cholesky factor (used by the fit's gradient and by every
    prediction) against NumPy's float64 inverse."""
    rng = np.random.default_rng(size)
    points = rng.random((size, 3))
    kernel = np.exp(-np.sum((points[:, None] - points[None]) ** 2, -1) / 0.1) + 1e-2 * np.eye(size)
    cholesky = np.linalg.cholesky(kernel)
    inverse = np.asarray(jax.jit(gp._cholesky_inverse)(jnp.asarray(cholesky, jnp.float32)))
    expected = np.linalg.inv(cholesky)
    np.testing.assert_allclose(inverse, expected, atol=2e-5 * np.abs(expected).max())
    assert np.all(np.triu(inverse, 1) == 0.0)


# ---- kernel properties --------------------------------------------------------------------


def test_kernel_is_symmetric_positive_semidefinite_and_ignores_inactive_inputs(problem):
    p = problem
    x = jnp.asarray(p["inputs"], jnp.float32)
    active = jnp.asarray(p["active"])
    corr = np.asarray(gp.correlation(p["params"], x, x, active, CONTEXT_DIMS), np.float64)
    np.testing.assert_allclose(corr, corr.T, atol=1e-7)
    np.testing.assert_allclose(np.diag(corr), 1.0, atol=1e-7)
    assert np.linalg.eigvalsh(corr).min() > -1e-5
    ref = ref_kernel(
        p["inputs"],
        p["inputs"],
        np.exp(np.asarray(p["params"].log_lengthscales, np.float64)),
        1.0,
        p["active"],
        CONTEXT_DIMS,
    )
    np.testing.assert_allclose(corr, ref, atol=1e-6)
    shifted = x.at[:, 2].set(0.123)  # only the inactive column changes
    np.testing.assert_array_equal(
        gp.correlation(p["params"], shifted, x, active, CONTEXT_DIMS),
        gp.correlation(p["params"], x, x, active, CONTEXT_DIMS),
    )


def test_standardize_matches_numpy():
    y = np.array([1.0, 4.0, 2.0, 8.0, 99.0])
    valid = np.array([True, True, True, True, False])
    z, mean, std = gp.standardize(jnp.asarray(y, jnp.float32), jnp.asarray(valid))
    assert mean == pytest.approx(y[:4].mean())
    assert std == pytest.approx(y[:4].std(ddof=1), rel=1e-6)
    np.testing.assert_allclose(z[:4], (y[:4] - y[:4].mean()) / y[:4].std(ddof=1), rtol=1e-6)
    assert z[4] == 0.0
    _, _, constant_std = gp.standardize(jnp.full(5, 7.0), jnp.ones(5, bool))
    _, _, single_std = gp.standardize(jnp.asarray([3.0, 0.0]), jnp.asarray([True, False]))
    assert constant_std == 1.0 and single_std == 1.0


# ---- exact masking -----------------------------------------------------------------------


def test_padded_rows_have_no_influence(compiled, problem):
    """Same data, unpadded vs scattered among 20 garbage rows (NaN, inf, huge): identical up
    to float32 rounding (a 50- and a 30-row factorization round differently: measured 3e-6
    of the outcome scale; a leak of the padding would show at order 1)."""
    p = problem
    active = jnp.asarray(p["active"])
    rng = np.random.default_rng(1)
    capacity = 50
    rows = np.sort(rng.choice(capacity, size=30, replace=False))
    inputs = np.full((capacity, 6), np.nan)
    targets = np.full(capacity, np.inf)
    inputs[::3], targets[1::3] = 1e6, -1e30
    valid = np.zeros(capacity, bool)
    inputs[rows], targets[rows], valid[rows] = p["inputs"], p["targets"], True
    plain, padded = dataset_of(p["inputs"], p["targets"]), dataset_of(inputs, targets, valid)

    np.testing.assert_allclose(
        compiled["lml"](p["params"], padded, active, CONTEXT_DIMS),
        compiled["lml"](p["params"], plain, active, CONTEXT_DIMS),
        rtol=1e-6,
    )
    for g_pad, g_plain in zip(
        compiled["grad"](p["params"], padded, active, CONTEXT_DIMS),
        compiled["grad"](p["params"], plain, active, CONTEXT_DIMS),
        strict=True,
    ):
        np.testing.assert_allclose(g_pad, g_plain, rtol=1e-4, atol=1e-4)
    queries = jnp.asarray(p["queries"], jnp.float32)
    scale = np.std(p["targets"], ddof=1)
    mean_pad, var_pad = compiled["predict"](p["params"], padded, active, queries)
    mean_plain, var_plain = compiled["predict"](p["params"], plain, active, queries)
    np.testing.assert_allclose(mean_pad, mean_plain, rtol=0, atol=3e-5 * scale)
    np.testing.assert_allclose(var_pad, var_plain, rtol=0, atol=3e-5 * scale**2)
    start = gp.default_params(6)
    fit_pad = compiled["fit"](padded, active, start, CONTEXT_DIMS, gp.FitConfig())
    fit_plain = compiled["fit"](plain, active, start, CONTEXT_DIMS, gp.FitConfig())
    for a, b in zip(fit_pad, fit_plain, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3)


# ---- the fit -----------------------------------------------------------------------------


def test_fit_reaches_a_stationary_point_and_finds_relevant_inputs(compiled):
    """y depends on inputs 0 and 1 only; the fit's lengthscales must say so, and the reference
    log posterior must be (nearly) flat at the fitted hyperparameters."""
    rng = np.random.default_rng(2)
    x = rng.random((40, 4))
    y = np.sin(5 * x[:, 0]) + np.cos(4 * x[:, 1]) + 0.01 * rng.normal(size=40)
    active = np.ones(4, bool)
    data = dataset_of(x, y)
    start = gp.default_params(4)
    fitted = compiled["fit"](data, jnp.asarray(active), start, 0, gp.FitConfig(200, 0.2))
    ls = np.exp(np.asarray(fitted.log_lengthscales))
    assert max(ls[0], ls[1]) < 0.5 * min(ls[2], ls[3])  # the Gamma(3, 6) prior caps ~2

    def ref_objective(flat):
        params = gp.GPParams(flat[:4], flat[4], flat[5], flat[6])
        return RefGP(params, x, y, active, 0, gp.JITTER_RATIO).log_marginal_likelihood() + ref_log_prior(params, active)

    def ref_gradient(params):
        flat = np.concatenate([np.asarray(leaf, np.float64).ravel() for leaf in params])
        return np.array(
            [(ref_objective(flat + 1e-5 * e) - ref_objective(flat - 1e-5 * e)) / 2e-5 for e in np.eye(len(flat))]
        )

    assert (
        ref_objective(np.concatenate([np.ravel(v) for v in fitted]))
        > ref_objective(np.concatenate([np.ravel(v) for v in start])) + 10.0
    )
    assert np.linalg.norm(ref_gradient(fitted)) < 0.05 * np.linalg.norm(ref_gradient(start))


@pytest.mark.parametrize("targets_kind", ["random", "constant", "offset"])
def test_float32_robust_with_duplicates_and_near_duplicates(compiled, targets_kind):
    """160 points: 40 distinct inputs, each twice exactly and twice within 1e-6 (float32 ulp
    scale): the fit and posterior are finite and match the float64 reference."""
    rng = np.random.default_rng(3)
    base = rng.random((40, 6))
    x = np.concatenate([base, base, base + 1e-6 * rng.random((40, 6)), base - 1e-6])
    if targets_kind == "random":
        y = np.tile(smooth_targets(base), 4) + 0.05 * rng.normal(size=160)
    elif targets_kind == "constant":
        y = np.full(160, 2.5)
    else:  # a large offset with small variation: standardization has to carry it
        y = 1e4 + 1e-2 * np.tile(smooth_targets(base), 4)
    active = jnp.ones(6, bool)
    data = dataset_of(x, y)
    fitted = compiled["fit"](data, active, gp.default_params(6), CONTEXT_DIMS, gp.FitConfig())
    assert all(np.all(np.isfinite(leaf)) for leaf in fitted)
    queries = np.concatenate([base[:10], rng.random((10, 6))])
    mean, var = compiled["predict"](fitted, data, active, jnp.asarray(queries, jnp.float32))
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var > 0)
    ref = RefGP(
        fitted, np.asarray(x, np.float32), np.asarray(y, np.float32), np.ones(6, bool), CONTEXT_DIMS, gp.JITTER_RATIO
    )
    ref_mean, ref_var = ref.predict(np.asarray(queries, np.float32))
    np.testing.assert_allclose(mean, ref_mean, atol=2e-3 * ref.y_std + 1e-3 * abs(ref.y_mean))
    np.testing.assert_allclose(var, ref_var, atol=2e-3 * ref.y_std**2)


@pytest.mark.parametrize("log_lengthscale", [np.log(1e-2), np.log(1e2)])
@pytest.mark.parametrize("log_outputscale", [np.log(1e-2), np.log(1e2)])
def test_cholesky_finite_at_hyperparameter_extremes(compiled, log_lengthscale, log_outputscale):
    rng = np.random.default_rng(4)
    base = rng.random((50, 6))
    x = np.concatenate([base, base, base + 1e-7, base[:10]])
    data = dataset_of(x, rng.normal(size=len(x)))
    params = gp.GPParams(
        jnp.full(6, log_lengthscale, jnp.float32),
        jnp.float32(log_outputscale),
        jnp.float32(np.log(1e-6)),
        jnp.float32(0),
    )
    active = jnp.ones(6, bool)
    assert np.isfinite(compiled["lml"](params, data, active, CONTEXT_DIMS))
    assert all(np.all(np.isfinite(g)) for g in compiled["grad"](params, data, active, CONTEXT_DIMS))
    mean, var = compiled["predict"](params, data, active, jnp.asarray(base[:5], jnp.float32))
    assert np.all(np.isfinite(mean)) and np.all(var > 0)


# ---- acquisition maximizer -------------------------------------------------------------------


def test_maximize_acquisition_finds_a_known_maximum_and_respects_the_box():
    optimum = jnp.array([0.3, 0.8, 0.5, 0.05, 0.97])
    active = jnp.array([True, True, False, True, True])

    def bowl(points):  # maximum at `optimum` (clipped value 1 for the inactive input)
        return -jnp.sum(jnp.where(active, (points - optimum) ** 2, 0.0), axis=-1)

    best, value = jax.jit(lambda key: acquisition.maximize_acquisition(bowl, key, active))(jax.random.PRNGKey(0))
    np.testing.assert_allclose(best[active], optimum[active], atol=2e-3)
    assert best[2] == acquisition.INACTIVE_VALUE
    assert value > -1e-5

    def outside(points):  # increasing in every input: the maximum is the corner of the box
        return jnp.sum(points, axis=-1)

    corner, _ = acquisition.maximize_acquisition(outside, jax.random.PRNGKey(1), active)
    np.testing.assert_allclose(corner[active], 1.0)


def test_ucb_forms():
    beta = jnp.float32(4.0)
    assert acquisition.ucb_multiplier(beta, "paper") == 4.0
    assert acquisition.ucb_multiplier(beta, "botorch") == 2.0
    with pytest.raises(ValueError, match="ucb_form"):
        acquisition.ucb_multiplier(beta, "sqrt")


_CONCURRENT_FITS = """
import jax, jax.numpy as jnp
from cpgjax import gp
batch, capacity, d = 64, 160, 10
inputs = jax.random.uniform(jax.random.key(0), (2, batch, capacity, d))
targets, valid, active = jnp.sin(inputs.sum(-1)), jnp.ones((2, batch, capacity), bool), jnp.ones(d, bool)
def one(x, y, v):
    data = gp.Dataset(x, y, v)
    return gp.posterior(gp.fit(data, active, gp.default_params(d), 2), data, active, 2).weights.sum()
two = jax.jit(lambda x, y, v: jax.vmap(one)(x[0], y[0], v[0]) + jax.vmap(one)(x[1], y[1], v[1]))
for _ in range(3):
    two(inputs, targets, valid).block_until_ready()
print("done")
"""


def test_two_concurrent_batched_fits_complete_on_a_two_thread_pool():
    """Two independent batched fits in one program finish (docs/backends.md, "LAPACK calls, one
    matrix at a time"): with whole batches handed to jaxlib's LAPACK kernels, both of XLA's
    intra-op threads wait in the kernels for pieces no thread is left to run, at the first call
    on this 2-core machine. The child runs with two CPUs, whatever the machine has."""
    cpus = sorted(os.sched_getaffinity(0))[:2]
    if len(cpus) < 2:
        pytest.skip("needs two CPUs: the stall needs a thread pool of two")
    child = subprocess.run(
        [sys.executable, "-c", _CONCURRENT_FITS],
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        preexec_fn=lambda: os.sched_setaffinity(0, cpus),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert child.returncode == 0, child.stderr[-2000:]
    assert child.stdout.strip().endswith("done")
