r"""Gaussian-process regression for contextual Bayesian optimization (paper Secs. II-C, II-D).

This module is the entry point of cpgjax's optimizer. It holds the GP surrogate
:math:`\hat f(\mathbf{x}, \mathbf{c})` of eq. (7); the acquisition of eq. (8) lives in
:mod:`cpgjax.acquisition` and the optimizer of Algorithm 1 in :mod:`cpgjax.bo`. Their
public names are re-exported here, so ``from cpgjax import gp`` then ``gp.make_optimizer``,
``gp.maximize``, ... is the one import other modules need.

Model (the Krause & Ong product kernel of the paper's Sec. II-D):

.. math::
    k((\mathbf{x}, \mathbf{c}), (\mathbf{x}', \mathbf{c}')) =
    s^2\, k_{5/2}(r_x)\, k_{5/2}(r_c), \qquad
    k_{5/2}(r) = (1 + \sqrt5 r + \tfrac53 r^2)\, e^{-\sqrt5 r},\qquad
    r_x^2 = \sum_{d \in x,\ \mathrm{active}} \frac{(x_d - x'_d)^2}{\ell_d^2},

and likewise :math:`r_c` over the context columns: Matérn-5/2 with one lengthscale per input
(ARD) in each factor and one output scale :math:`s^2`. Inputs are normalized to the unit cube
on *fixed* ranges by the caller (paper appendix, "Parameter Normalization"); the last
``context_dims`` columns are the context. Inactive inputs (``active`` mask, e.g. no
:math:`\sigma_N` for a controller without Tegotae) drop out of :math:`r` exactly.

Outcomes are standardized over the valid points (mean, unbiased std; a std below 1e-8 or
fewer than two points gives std 1, as BoTorch's ``Standardize``). The GP has a learned
constant mean and Gaussian noise :math:`\sigma^2`.

Priors (BoTorch 0.5.0 ``SingleTaskGP`` defaults, the version pinned by bayesopt4ros, on which
the paper's code was built; densities of the constrained values, no Jacobian, as GPyTorch):

* lengthscales, each active input: Gamma(3, 6) (rate form; mode 1/3, mean 1/2);
* output scale :math:`s^2`: Gamma(2, 0.15) (mode 6.7);
* noise variance :math:`\sigma^2` (standardized units): Gamma(1.1, 0.05);
* constant mean: none (flat).

Hyperparameters are the MAP: log marginal likelihood + log prior, maximized with Adam (optax)
for a fixed number of steps in log space, projected onto a box after every step. The chain
starts from the better (higher log posterior) of the caller's warm start (the previous fit:
in a BO loop the optimization is amortized over trials, so few steps per trial suffice) and a
fixed default start (a way out when new data, or data reuse, make the old fit poor). All of
it is deterministic.

Exact masking of a fixed-capacity dataset. A padded row ``i`` (``valid[i] = False``) gets
:math:`K_{ii} = 1`, :math:`K_{ij} = K_{ji} = 0`, residual 0 and zero cross-covariance to
queries: its Cholesky row is the unit row, it adds :math:`\log 1 = 0` to the log determinant
and 0 to the quadratic form, so the marginal likelihood, its gradient and the posterior equal
those of the valid rows alone. Padded inputs and targets are replaced by constants before any
arithmetic, so even NaN padding cannot leak through a gradient.

Precision: float32. The simulator (MJX) runs in float32 in the same process, and
``jax_enable_x64`` is global, so float64 here would either force it on everything or need
fragile scoping under the caller's ``jit``/``vmap``. Float32 is made robust by (1) unit-cube
inputs and standardized outcomes, (2) a relative jitter: the kernel matrix is
:math:`s^2 (C + \rho I) + \sigma^2 I` with :math:`\rho = 10^{-4}` (``JITTER_RATIO``), i.e. a
noise floor of :math:`10^{-4} s^2`, BoTorch's absolute floor 1e-4 at unit signal variance.
Measured (float32 Cholesky of Matérn-5/2 matrices): a ratio of 1e-5 already fails for 256
near-duplicate points, 1e-4 succeeds for 150 and 256 exact duplicates, near-duplicates and
near-constant kernels at any :math:`s^2` — its condition number is at most
:math:`1 + n/\rho`; (3) a clamp of the posterior variance at 1e-10 :math:`s^2`; (4) a fit that
skips any non-finite step. ``tests/test_gp.py`` checks posteriors against a float64 NumPy GP
(mean within 2e-4 outcome std), and with 160 points of exact and 1e-6 near-duplicates, with
random, constant or 1e4-offset outcomes, a finite fit and posterior within 2e-3 std of float64.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy as jsp
import optax

JITTER_RATIO = 1e-4
"""Diagonal jitter relative to the output scale: noise floor of ``1e-4 * s**2``."""

MIN_VARIANCE_RATIO = 1e-10
"""Posterior variances are clamped at ``1e-10 * s**2`` (standardized units)."""

LENGTHSCALE_PRIOR = (3.0, 6.0)
"""Gamma(concentration, rate) on every active lengthscale (normalized input units)."""

OUTPUTSCALE_PRIOR = (2.0, 0.15)
"""Gamma(concentration, rate) on the output scale ``s**2``."""

NOISE_PRIOR = (1.1, 0.05)
"""Gamma(concentration, rate) on the noise variance (standardized outcome units)."""

# The box the fit projects onto after every Adam step (log space; the mean in standardized
# units). It only guards against runaway values: the priors keep fits well inside it.
LOG_LENGTHSCALE_RANGE = (math.log(1e-2), math.log(1e2))
LOG_OUTPUTSCALE_RANGE = (math.log(1e-2), math.log(1e2))
LOG_NOISE_RANGE = (math.log(1e-6), math.log(10.0))
MEAN_RANGE = (-10.0, 10.0)


class GPParams(NamedTuple):
    """GP hyperparameters, unconstrained (log) where positive.

    Attributes:
      log_lengthscales: (d,) log ARD lengthscales in normalized input units.
      log_outputscale: () log of the output scale ``s**2``.
      log_noise: () log noise variance, standardized outcome units.
      mean: () constant mean, standardized outcome units.
    """

    log_lengthscales: jax.Array
    log_outputscale: jax.Array
    log_noise: jax.Array
    mean: jax.Array


class Dataset(NamedTuple):
    """A fixed-capacity training set; rows with ``valid = False`` have no influence.

    Attributes:
      inputs: (capacity, d) inputs in the unit cube; the last ``context_dims`` columns are
        the context.
      targets: (capacity,) outcomes in their own units (standardized internally).
      valid: (capacity,) bool, which rows are data.
    """

    inputs: jax.Array
    targets: jax.Array
    valid: jax.Array


class Posterior(NamedTuple):
    """Everything needed to predict at new inputs (see :func:`posterior`).

    Attributes:
      params: the hyperparameters used.
      inputs: (capacity, d) training inputs, padded rows replaced by constants.
      valid: (capacity,) bool.
      active: (d,) bool active-input mask.
      cholesky: (capacity, capacity) lower Cholesky factor of the masked kernel matrix.
      weights: (capacity,) ``K^{-1} (z - mean)`` with ``z`` the standardized targets.
      target_mean: () outcome mean used for standardization.
      target_std: () outcome std used for standardization.
    """

    params: GPParams
    inputs: jax.Array
    valid: jax.Array
    active: jax.Array
    cholesky: jax.Array
    weights: jax.Array
    target_mean: jax.Array
    target_std: jax.Array


class FitConfig(NamedTuple):
    """Static settings of the hyperparameter fit.

    Attributes:
      num_steps: Adam steps per fit (fixed: deterministic and vmappable).
      learning_rate: initial Adam step in log-parameter units; cosine-decayed to 10 %.
    """

    num_steps: int = 20
    learning_rate: float = 0.1


def default_params(num_inputs: int) -> GPParams:
    """The fixed default start of the fit: lengthscales 0.5 (the prior mean), ``s**2 = 1``,
    noise variance 0.1, mean 0."""
    return GPParams(
        log_lengthscales=jnp.full((num_inputs,), jnp.log(0.5), jnp.float32),
        log_outputscale=jnp.zeros((), jnp.float32),
        log_noise=jnp.asarray(jnp.log(0.1), jnp.float32),
        mean=jnp.zeros((), jnp.float32),
    )


def matern52(squared_distance: jax.Array) -> jax.Array:
    r"""Matérn-5/2 correlation :math:`k_{5/2}(r)` of a scaled squared distance :math:`r^2`.

    The square root is guarded so the gradient at :math:`r = 0` (duplicates, the diagonal)
    is the correct 0 instead of NaN.
    """
    positive = squared_distance > 0.0
    distance = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared_distance, 1.0)), 0.0)
    sqrt5_r = jnp.sqrt(5.0) * distance
    return (1.0 + sqrt5_r + (5.0 / 3.0) * squared_distance) * jnp.exp(-sqrt5_r)


def squared_differences(inputs_a: jax.Array, inputs_b: jax.Array) -> jax.Array:
    """Per-input squared differences, (n, d) x (m, d) -> (d, n, m) (input axis first).

    Computed from exact differences (no ``|a|² + |b|² - 2ab`` cancellation), and once per fit:
    they do not depend on the hyperparameters.
    """
    return (inputs_a.T[:, :, None] - inputs_b.T[:, None, :]) ** 2


@jax.custom_vjp
def _weighted_sum(weights: jax.Array, sq_differences: jax.Array) -> jax.Array:
    """``einsum('kl,kij->lij')``: (d, 2) weights x (d, n, m) -> (2, n, m).

    The custom VJP contracts the weight cotangent as one (d, n·m) x (n·m, 2) product; XLA's
    CPU transpose of the einsum is several times slower, and this is the fit's hot spot.
    """
    return jnp.einsum("kl,kij->lij", weights, sq_differences)


def _weighted_sum_forward(weights, sq_differences):
    return _weighted_sum(weights, sq_differences), (weights, sq_differences)


def _weighted_sum_backward(saved, cotangent):
    weights, sq_differences = saved
    num_inputs = sq_differences.shape[0]
    weights_cotangent = (sq_differences.reshape(num_inputs, -1)
                         @ cotangent.reshape(cotangent.shape[0], -1).T)
    return weights_cotangent, jnp.einsum("kl,lij->kij", weights, cotangent)


_weighted_sum.defvjp(_weighted_sum_forward, _weighted_sum_backward)


def correlation_from_squared_differences(
    params: GPParams, sq_differences: jax.Array, active: jax.Array, context_dims: int
) -> jax.Array:
    """:func:`correlation` from precomputed :func:`squared_differences` (d, n, m)."""
    num_inputs = sq_differences.shape[0]
    inverse_sq_lengthscales = jnp.where(active, jnp.exp(-2.0 * params.log_lengthscales), 0.0)
    is_context = jnp.arange(num_inputs) >= num_inputs - context_dims
    # Column 0 sums the parameter inputs (r_x^2), column 1 the context inputs (r_c^2).
    weights = jnp.stack([jnp.where(is_context, 0.0, inverse_sq_lengthscales),
                         jnp.where(is_context, inverse_sq_lengthscales, 0.0)], axis=-1)
    r2 = _weighted_sum(weights, sq_differences)
    return matern52(r2[0]) * matern52(r2[1])


def correlation(
    params: GPParams,
    inputs_a: jax.Array,
    inputs_b: jax.Array,
    active: jax.Array,
    context_dims: int,
) -> jax.Array:
    r"""Product-kernel correlation :math:`k_{5/2}(r_x) k_{5/2}(r_c)` (without :math:`s^2`).

    Args:
      params: hyperparameters (only the lengthscales are used).
      inputs_a: (n, d) normalized inputs.
      inputs_b: (m, d) normalized inputs.
      active: (d,) bool; inactive inputs contribute nothing to either distance.
      context_dims: static number of trailing context columns (0 for plain BO).

    Returns:
      (n, m) correlation matrix, entries in (0, 1].
    """
    return correlation_from_squared_differences(
        params, squared_differences(inputs_a, inputs_b), active, context_dims)


def standardize(targets: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Standardize the valid targets; padded entries become 0.

    Returns:
      (standardized targets (capacity,), mean (), std ()). The std is the unbiased one; with
      fewer than two valid points or a std below 1e-8 it is 1 (constant outcomes stay 0).
    """
    num_valid = jnp.sum(valid)
    safe = jnp.where(valid, targets, 0.0)
    mean = jnp.sum(safe) / jnp.maximum(num_valid, 1)
    centred = jnp.where(valid, targets - mean, 0.0)
    variance = jnp.sum(centred**2) / jnp.maximum(num_valid - 1, 1)
    std = jnp.sqrt(variance)
    std = jnp.where((num_valid >= 2) & (std >= 1e-8), std, 1.0)
    return centred / std, mean, std


class _Prepared(NamedTuple):
    """The hyperparameter-free part of a dataset, computed once per fit or posterior."""

    inputs: jax.Array  # (capacity, d), padded rows replaced by 0.5
    sq_differences: jax.Array  # (d, capacity, capacity)
    standardized: jax.Array  # (capacity,), padded rows 0
    valid: jax.Array
    target_mean: jax.Array
    target_std: jax.Array


def _prepare(dataset: Dataset) -> _Prepared:
    inputs = jnp.where(dataset.valid[:, None], dataset.inputs, 0.5)
    standardized, target_mean, target_std = standardize(dataset.targets, dataset.valid)
    return _Prepared(inputs, squared_differences(inputs, inputs), standardized, dataset.valid,
                     target_mean, target_std)


def _kernel_and_residual(params, prepared, active, context_dims):
    """Masked covariance s²(C + ρI) + σ²I on valid rows (identity on padded rows), and the
    masked residual of the standardized targets about the constant mean."""
    outputscale = jnp.exp(params.log_outputscale)
    noise = jnp.exp(params.log_noise)
    valid = prepared.valid
    corr = correlation_from_squared_differences(params, prepared.sq_differences, active,
                                                context_dims)
    eye = jnp.eye(valid.shape[0], dtype=corr.dtype)
    valid_block = outputscale * (corr + JITTER_RATIO * eye) + noise * eye
    kernel = jnp.where(valid[:, None] & valid[None, :], valid_block, eye)
    residual = jnp.where(valid, prepared.standardized - params.mean, 0.0)
    return kernel, residual


@jax.custom_vjp
def _gaussian_log_density(kernel: jax.Array, residual: jax.Array) -> jax.Array:
    r"""``log N(residual; 0, kernel)`` without the :math:`2\pi` term, by Cholesky.

    Custom VJP: :math:`\partial/\partial K = \tfrac12(\alpha\alpha^\top - K^{-1})`,
    :math:`\partial/\partial r = -\alpha` with :math:`\alpha = K^{-1} r` (Rasmussen &
    Williams eq. 5.9), cheaper than differentiating through the factorization.
    """
    return _gaussian_log_density_forward(kernel, residual)[0]


def _gaussian_log_density_forward(kernel, residual):
    cholesky = jnp.linalg.cholesky(kernel)
    weights = jsp.linalg.cho_solve((cholesky, True), residual)
    value = -0.5 * jnp.dot(residual, weights) - jnp.sum(jnp.log(jnp.diagonal(cholesky)))
    return value, (cholesky, weights)


def _gaussian_log_density_backward(saved, cotangent):
    cholesky, weights = saved
    eye = jnp.eye(cholesky.shape[0], dtype=cholesky.dtype)
    kernel_inverse = jsp.linalg.cho_solve((cholesky, True), eye)
    kernel_cotangent = 0.5 * cotangent * (jnp.outer(weights, weights) - kernel_inverse)
    return kernel_cotangent, -cotangent * weights


_gaussian_log_density.defvjp(_gaussian_log_density_forward, _gaussian_log_density_backward)


def _log_marginal_likelihood(params, prepared, active, context_dims):
    kernel, residual = _kernel_and_residual(params, prepared, active, context_dims)
    num_valid = jnp.sum(prepared.valid)
    return _gaussian_log_density(kernel, residual) - 0.5 * num_valid * jnp.log(2.0 * jnp.pi)


def log_marginal_likelihood(
    params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int
) -> jax.Array:
    r"""Log marginal likelihood of the standardized valid targets,
    :math:`-\tfrac12 r^\top K^{-1} r - \tfrac12\log|K| - \tfrac{n}{2}\log 2\pi`."""
    return _log_marginal_likelihood(params, _prepare(dataset), active, context_dims)


def _gamma_log_density(value, concentration, rate):
    return jax.scipy.stats.gamma.logpdf(value, concentration, scale=1.0 / rate)


def log_prior(params: GPParams, active: jax.Array) -> jax.Array:
    """Sum of the Gamma log densities listed in the module docstring (active inputs only)."""
    lengthscale_terms = _gamma_log_density(jnp.exp(params.log_lengthscales), *LENGTHSCALE_PRIOR)
    return (
        jnp.sum(jnp.where(active, lengthscale_terms, 0.0))
        + _gamma_log_density(jnp.exp(params.log_outputscale), *OUTPUTSCALE_PRIOR)
        + _gamma_log_density(jnp.exp(params.log_noise), *NOISE_PRIOR)
    )


def log_posterior(params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int):
    """The fit's objective: log marginal likelihood + log prior (unnormalized log MAP)."""
    return log_marginal_likelihood(params, dataset, active, context_dims) + log_prior(
        params, active)


def _project(params: GPParams) -> GPParams:
    return GPParams(
        log_lengthscales=jnp.clip(params.log_lengthscales, *LOG_LENGTHSCALE_RANGE),
        log_outputscale=jnp.clip(params.log_outputscale, *LOG_OUTPUTSCALE_RANGE),
        log_noise=jnp.clip(params.log_noise, *LOG_NOISE_RANGE),
        mean=jnp.clip(params.mean, *MEAN_RANGE),
    )


def fit(
    dataset: Dataset,
    active: jax.Array,
    warm_start: GPParams,
    context_dims: int,
    config: FitConfig = FitConfig(),
) -> GPParams:
    """MAP hyperparameters by projected Adam from the better of the warm and default starts.

    The start with the higher :func:`log_posterior` (ties and non-finite values go to the
    default start) runs ``config.num_steps`` Adam steps (cosine-decayed step size) on the
    negative log posterior per valid point (as GPyTorch's MLL / n); a step whose loss or
    gradient is not finite is skipped.

    Args:
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      warm_start: parameters to start from, e.g. the previous fit.
      context_dims: static number of trailing context columns.
      config: static fit settings.

    Returns:
      The fitted :class:`GPParams`.
    """
    prepared = _prepare(dataset)
    per_point = 1.0 / jnp.maximum(jnp.sum(dataset.valid), 1)
    objective = jax.value_and_grad(
        lambda p: -per_point * (_log_marginal_likelihood(p, prepared, active, context_dims)
                                + log_prior(p, active)))
    schedule = optax.cosine_decay_schedule(config.learning_rate, config.num_steps, alpha=0.1)
    optimizer = optax.adam(schedule)

    def step(carry, _):
        params, opt_state = carry
        loss, grads = objective(params)
        updates, new_opt_state = optimizer.update(grads, opt_state, params)
        new_params = _project(optax.apply_updates(params, updates))
        finite = jnp.isfinite(loss) & jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)])
        )
        keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
        return (jax.tree.map(keep, new_params, params),
                jax.tree.map(keep, new_opt_state, opt_state)), None

    def run(start):
        start = _project(start)
        (params, _), _ = jax.lax.scan(
            step, (start, optimizer.init(start)), None, length=config.num_steps
        )
        return params

    default = default_params(dataset.inputs.shape[-1])
    starts = jax.tree.map(lambda a, b: jnp.stack([a, b]), default, warm_start)
    start_losses = jax.vmap(lambda p: objective(_project(p))[0])(starts)
    start_losses = jnp.where(jnp.isfinite(start_losses), start_losses, jnp.inf)
    best = jnp.argmin(start_losses)
    return run(jax.tree.map(lambda leaf: leaf[best], starts))


def posterior(
    params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int
) -> Posterior:
    """Condition the GP on a dataset: one Cholesky factorization, reused by :func:`predict`."""
    prepared = _prepare(dataset)
    kernel, residual = _kernel_and_residual(params, prepared, active, context_dims)
    _, (cholesky, weights) = _gaussian_log_density_forward(kernel, residual)
    return Posterior(params, prepared.inputs, dataset.valid, active, cholesky, weights,
                     prepared.target_mean, prepared.target_std)


def predict(
    post: Posterior, query_inputs: jax.Array, context_dims: int
) -> tuple[jax.Array, jax.Array]:
    r"""Posterior mean :math:`\mu` and latent variance :math:`\sigma^2` (no observation noise).

    Args:
      post: a :class:`Posterior`.
      query_inputs: (q, d) normalized query inputs.
      context_dims: static number of trailing context columns.

    Returns:
      (mean (q,), variance (q,)), both in the outcome's own units.
    """
    params = post.params
    outputscale = jnp.exp(params.log_outputscale)
    cross = outputscale * correlation(params, query_inputs, post.inputs, post.active, context_dims)
    cross = jnp.where(post.valid[None, :], cross, 0.0)
    mean_z = params.mean + cross @ post.weights
    whitened = jsp.linalg.solve_triangular(post.cholesky, cross.T, lower=True)
    variance_z = jnp.maximum(
        outputscale - jnp.sum(whitened**2, axis=0),
        MIN_VARIANCE_RATIO * outputscale,
    )
    return post.target_mean + post.target_std * mean_z, post.target_std**2 * variance_z


_REEXPORTED = {
    "acquisition": ("AcquisitionConfig", "maximize_acquisition", "ucb_multiplier"),
    "bo": (
        "BetaInfo", "BetaSchedule", "ContextualBO", "MaximizeResult", "OptimizerConfig",
        "OptimizerState", "PAPER_CONTEXT_LOWER", "PAPER_CONTEXT_UPPER",
        "PAPER_CONTEXT_THRESHOLDS", "make_optimizer", "maximize", "paper_config",
        "paper_schedule",
    ),
}


def __getattr__(name):
    """Re-export the acquisition and optimizer API lazily (PEP 562; avoids an import cycle,
    since :mod:`cpgjax.bo` imports this module)."""
    import importlib

    for module_name, names in _REEXPORTED.items():
        if name in names:
            return getattr(importlib.import_module(f"cpgjax.{module_name}"), name)
    raise AttributeError(f"module 'cpgjax.gp' has no attribute {name!r}")
