r"""Gaussian-process regression for contextual Bayesian optimization (paper Secs. II-C, II-D).

This module is the surrogate model of cpgjax's optimizer, the GP
:math:`\hat f(\mathbf{x}, \mathbf{c})` of eq. (7); the acquisition of eq. (8) lives in
:mod:`cpgjax.optim.acquisition`, the optimizer of Algorithm 1 in :mod:`cpgjax.optim.bo` (its static
configuration in :mod:`cpgjax.optim.config`, the exploration factor of eqs. (12)-(14) in
:mod:`cpgjax.optim.exploration`) and the black-box convenience loop in :mod:`cpgjax.optim.black_box`.

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

Priors (:class:`Priors`, Gamma densities of the constrained values, no Jacobian, as GPyTorch; a
fit is given its own). The objective's are :data:`BOTORCH_PRIORS`, the BoTorch 0.5.0
``SingleTaskGP`` defaults, the version pinned by bayesopt4ros, on which the paper's code was built:

* lengthscales, each active input: Gamma(3, 6) (rate form; mode 1/3, mean 1/2);
* output scale :math:`s^2`: Gamma(2, 0.15) (mode 6.7);
* noise variance :math:`\sigma^2` (standardized units): Gamma(1.1, 0.05);
* constant mean: none (flat).

Hyperparameters are the MAP: log marginal likelihood + log prior, maximized with Adam (optax)
for a fixed number of steps in log space, projected onto a box after every step. The chain
starts from the better (higher log posterior) of the caller's warm start (the previous fit:
in a BO loop the optimization is amortized over trials, so few steps per trial suffice) and a
fixed default start (a way out when new data, or data reuse, make the old fit poor). All of
it is deterministic. The gradient is analytic (Rasmussen & Williams eq. 5.9, written out in
:func:`_log_marginal_likelihood_gradient`), not traced through the factorization: one Cholesky
factorization, one triangular inversion and a handful of elementwise passes per step.

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
from jax import custom_batching

JITTER_RATIO = 1e-4
"""Diagonal jitter relative to the output scale: noise floor of ``1e-4 * s**2``."""

MIN_VARIANCE_RATIO = 1e-10
"""Posterior variances are clamped at ``1e-10 * s**2`` (standardized units)."""

_TRIANGULAR_LEAF = 32
"""Largest triangular block :func:`_cholesky_inverse` solves directly."""


def _one_matrix_per_lapack_call(fn):
    """``fn``, with a batching rule that loops over the batch (:func:`jax.lax.map`) instead of
    handing the whole batch to one LAPACK call.

    jaxlib's CPU LAPACK kernels split a large batch into pieces on XLA's intra-op thread pool
    and block until the pieces are done. When every pool thread is itself inside such a call
    (two independent batched factorizations of one program, on a two-thread pool), nobody is
    left to run the pieces and the program never ends (docs/backends.md, "LAPACK calls, one
    matrix at a time"). A call on one matrix runs on the calling thread, so looping keeps every GP
    factorization and solve deadlock-free at any batch size, at the same arithmetic per matrix.
    """

    @custom_batching.custom_vmap
    def unbatched(*args):
        return fn(*args)

    @unbatched.def_vmap
    def loop_over_batch(axis_size, in_batched, *args):
        args = tuple(
            arg if batched else jnp.broadcast_to(arg, (axis_size, *jnp.shape(arg)))
            for arg, batched in zip(args, in_batched, strict=True)
        )
        return jax.lax.map(lambda one: unbatched(*one), args), True

    return unbatched


_lower_cholesky = _one_matrix_per_lapack_call(lambda matrix: jax.lax.linalg.cholesky(matrix, symmetrize_input=False))
_solve_lower = _one_matrix_per_lapack_call(lambda lower, rhs: jsp.linalg.solve_triangular(lower, rhs, lower=True))
_cholesky_solve = _one_matrix_per_lapack_call(lambda lower, rhs: jsp.linalg.cho_solve((lower, True), rhs))


class GammaPrior(NamedTuple):
    """A Gamma(concentration, rate) density (rate form: mean concentration / rate)."""

    concentration: float
    rate: float

    @property
    def mean(self) -> float:
        """The density's mean, concentration / rate."""
        return self.concentration / self.rate


class Priors(NamedTuple):
    """The priors of a GP's hyperparameters (static: part of what a fit compiles).

    Attributes:
      lengthscale: on every active lengthscale (normalized input units).
      outputscale: on the output scale ``s**2``.
      noise: on the noise variance (standardized outcome units).
    """

    lengthscale: GammaPrior
    outputscale: GammaPrior
    noise: GammaPrior


BOTORCH_PRIORS = Priors(
    lengthscale=GammaPrior(3.0, 6.0), outputscale=GammaPrior(2.0, 0.15), noise=GammaPrior(1.1, 0.05)
)
"""BoTorch 0.5.0 ``SingleTaskGP``'s priors: the objective's (module docstring)."""

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
      cholesky_inverse: (capacity, capacity) inverse :math:`L^{-1}` of the lower Cholesky
        factor of the masked kernel matrix (prediction by matrix products, not solves).
      weights: (capacity,) ``K^{-1} (z - mean)`` with ``z`` the standardized targets.
      target_mean: () outcome mean used for standardization.
      target_std: () outcome std used for standardization.
    """

    params: GPParams
    inputs: jax.Array
    valid: jax.Array
    active: jax.Array
    cholesky_inverse: jax.Array
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


def default_params(num_inputs: int, priors: Priors = BOTORCH_PRIORS) -> GPParams:
    """The fixed default start of the fit: lengthscales at their prior's mean (0.5 under
    :data:`BOTORCH_PRIORS`), ``s**2 = 1``, noise variance 0.1, mean 0.

    Args:
      num_inputs: d, the number of input columns (parameters and context).
      priors: the hyperparameters' priors (the lengthscale prior's mean is used).

    Returns:
      float32 :class:`GPParams`, ``log_lengthscales`` (d,).
    """
    return GPParams(
        log_lengthscales=jnp.full((num_inputs,), jnp.log(priors.lengthscale.mean), jnp.float32),
        log_outputscale=jnp.zeros((), jnp.float32),
        log_noise=jnp.asarray(jnp.log(0.1), jnp.float32),
        mean=jnp.zeros((), jnp.float32),
    )


def matern52(squared_distance: jax.Array) -> jax.Array:
    r"""Matérn-5/2 correlation :math:`k_{5/2}(r)` of a scaled squared distance :math:`r^2`.

    The square root is guarded so the gradient at :math:`r = 0` (duplicates, the diagonal)
    is the correct 0 instead of NaN.

    Args:
      squared_distance: :math:`r^2`, any shape, ≥ 0.

    Returns:
      :math:`k_{5/2}(r)`, the shape of ``squared_distance``.
    """
    return matern52_and_derivative(squared_distance)[0]


def matern52_and_derivative(squared_distance: jax.Array) -> tuple[jax.Array, jax.Array]:
    r""":math:`k_{5/2}(r)` and :math:`\mathrm d k_{5/2} / \mathrm d(r^2) =
    -\tfrac56 (1 + \sqrt5 r)\, e^{-\sqrt5 r}` (finite at :math:`r = 0`), sharing one
    exponential.

    Args:
      squared_distance: :math:`r^2`, any shape, ≥ 0.

    Returns:
      (:math:`k_{5/2}(r)`, :math:`\mathrm d k_{5/2} / \mathrm d(r^2)`), each the shape of ``squared_distance``.
    """
    positive = squared_distance > 0.0
    distance = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared_distance, 1.0)), 0.0)
    sqrt5_r = jnp.sqrt(5.0) * distance
    decay = jnp.exp(-sqrt5_r)
    return ((1.0 + sqrt5_r + (5.0 / 3.0) * squared_distance) * decay, -(5.0 / 6.0) * (1.0 + sqrt5_r) * decay)


def squared_differences(inputs_a: jax.Array, inputs_b: jax.Array) -> jax.Array:
    """Per-input squared differences, (n, d) x (m, d) -> (d, n, m) (input axis first).

    Computed from exact differences (no ``|a|² + |b|² - 2ab`` cancellation), and once per fit:
    they do not depend on the hyperparameters.

    Args:
      inputs_a: (n, d) inputs.
      inputs_b: (m, d) inputs.

    Returns:
      (d, n, m), entry [k, i, j] = (inputs_a[i, k] − inputs_b[j, k])².
    """
    return (inputs_a.T[:, :, None] - inputs_b.T[:, None, :]) ** 2


def _inverse_squared_lengthscales(params: GPParams, active: jax.Array) -> jax.Array:
    return jnp.where(active, jnp.exp(-2.0 * params.log_lengthscales), 0.0)


def _block_squared_distances(
    inverse_sq_lengthscales: jax.Array, sq_differences: jax.Array, context_dims: int
) -> tuple[jax.Array, jax.Array | None]:
    """:math:`r_x^2` and :math:`r_c^2` (``None`` without context) from (d, n, m) differences."""
    num_x = sq_differences.shape[0] - context_dims
    r2_x = jnp.tensordot(inverse_sq_lengthscales[:num_x], sq_differences[:num_x], axes=1)
    if context_dims == 0:
        return r2_x, None
    return r2_x, jnp.tensordot(inverse_sq_lengthscales[num_x:], sq_differences[num_x:], axes=1)


def correlation(
    params: GPParams,
    inputs_a: jax.Array,
    inputs_b: jax.Array,
    active: jax.Array,
    context_dims: int,
) -> jax.Array:
    r"""Product-kernel correlation :math:`k_{5/2}(r_x) k_{5/2}(r_c)` (without :math:`s^2`).

    The squared distances are sums over the inputs of exact, lengthscale-scaled differences
    (one fused elementwise pass per input, no (d, n, m) intermediate and no
    ``|a|² + |b|² - 2ab`` cancellation).

    Args:
      params: hyperparameters (only the lengthscales are used).
      inputs_a: (n, d) normalized inputs.
      inputs_b: (m, d) normalized inputs.
      active: (d,) bool; inactive inputs contribute nothing to either distance.
      context_dims: static number of trailing context columns (0 for plain BO).

    Returns:
      (n, m) correlation matrix, entries in (0, 1].
    """
    inverse_lengthscales = jnp.where(active, jnp.exp(-params.log_lengthscales), 0.0)
    scaled_a, scaled_b = inputs_a * inverse_lengthscales, inputs_b * inverse_lengthscales

    def block_sq_distance(columns):
        return sum((scaled_a[:, None, k] - scaled_b[None, :, k]) ** 2 for k in columns)

    num_x = inputs_a.shape[-1] - context_dims
    corr = matern52(block_sq_distance(range(num_x)))
    if context_dims:
        corr = corr * matern52(block_sq_distance(range(num_x, num_x + context_dims)))
    return corr


def standardize(targets: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Standardize the valid targets; padded entries become 0.

    Args:
      targets: (capacity,) outcomes in their own units.
      valid: (capacity,) bool, which entries are data.

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
    return _Prepared(inputs, squared_differences(inputs, inputs), standardized, dataset.valid, target_mean, target_std)


class _Factored(NamedTuple):
    """The masked kernel of one set of hyperparameters, factored (see :func:`_factor`)."""

    correlation_x: jax.Array  # (capacity, capacity) k_{5/2}(r_x)
    correlation_c: jax.Array | None  # k_{5/2}(r_c), None without context
    derivative_x: jax.Array  # dk_{5/2}/d(r_x^2)
    derivative_c: jax.Array | None  # dk_{5/2}/d(r_c^2)
    residual: jax.Array  # (capacity,) standardized targets - mean, 0 on padded rows
    cholesky: jax.Array  # lower factor of the masked kernel matrix
    weights: jax.Array  # K^{-1} residual, 0 on padded rows


def _factor(params, prepared, active, context_dims) -> _Factored:
    """Masked covariance s²(C + ρI) + σ²I on valid rows (identity on padded rows), its
    Cholesky factor, and ``weights = K⁻¹ r`` for the residual ``r`` of the standardized
    targets about the constant mean."""
    r2_x, r2_c = _block_squared_distances(
        _inverse_squared_lengthscales(params, active), prepared.sq_differences, context_dims
    )
    corr_x, derivative_x = matern52_and_derivative(r2_x)
    corr_c, derivative_c = (None, None) if r2_c is None else matern52_and_derivative(r2_c)
    corr = corr_x if corr_c is None else corr_x * corr_c
    valid = prepared.valid
    eye = jnp.eye(valid.shape[0], dtype=corr.dtype)
    valid_block = jnp.exp(params.log_outputscale) * (corr + JITTER_RATIO * eye) + jnp.exp(params.log_noise) * eye
    kernel = jnp.where(valid[:, None] & valid[None, :], valid_block, eye)
    residual = jnp.where(valid, prepared.standardized - params.mean, 0.0)
    # The kernel is symmetric by construction ((a - b)² = (b - a)² exactly), and the
    # factorization reads one triangle: no symmetrizing pass (a 160 x 160 transpose and
    # average cost a quarter of a fit step).
    cholesky = _lower_cholesky(kernel)
    weights = _cholesky_solve(cholesky, residual)
    return _Factored(corr_x, corr_c, derivative_x, derivative_c, residual, cholesky, weights)


def _cholesky_inverse(cholesky: jax.Array) -> jax.Array:
    r""":math:`L^{-1}` of a lower-triangular factor by recursive halving (blocks of at most
    ``_TRIANGULAR_LEAF`` rows are solved directly):

    .. math::
        \begin{pmatrix} A & 0 \\ B & C \end{pmatrix}^{-1} =
        \begin{pmatrix} A^{-1} & 0 \\ -C^{-1} B A^{-1} & C^{-1} \end{pmatrix}.

    The result of one triangular solve against the identity, but with most of the work in
    matrix products, which XLA's CPU backend runs much faster than its triangular solve
    (benchmarks/RESULTS.md, "GP: the triangular inverse by matrix products").
    """
    size = cholesky.shape[0]
    if size <= _TRIANGULAR_LEAF:
        return _solve_lower(cholesky, jnp.eye(size, dtype=cholesky.dtype))
    half = size // 2
    upper_inverse = _cholesky_inverse(cholesky[:half, :half])
    lower_inverse = _cholesky_inverse(cholesky[half:, half:])
    off_diagonal = -(lower_inverse @ (cholesky[half:, :half] @ upper_inverse))
    return jnp.block([[upper_inverse, jnp.zeros((half, size - half), cholesky.dtype)], [off_diagonal, lower_inverse]])


def _log_marginal_likelihood(factored: _Factored, prepared: _Prepared) -> jax.Array:
    return (
        -0.5 * jnp.dot(factored.residual, factored.weights)
        - jnp.sum(jnp.log(jnp.diagonal(factored.cholesky)))
        - 0.5 * jnp.sum(prepared.valid) * jnp.log(2.0 * jnp.pi)
    )


def log_marginal_likelihood(params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int) -> jax.Array:
    r"""Log marginal likelihood of the standardized valid targets,
    :math:`-\tfrac12 r^\top K^{-1} r - \tfrac12\log|K| - \tfrac{n}{2}\log 2\pi`.

    Args:
      params: the hyperparameters.
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      context_dims: static number of trailing context columns.

    Returns:
      () the log marginal likelihood of the valid rows (padded rows add 0).
    """
    prepared = _prepare(dataset)
    return _log_marginal_likelihood(_factor(params, prepared, active, context_dims), prepared)


def _gamma_log_density(value, concentration, rate):
    return jax.scipy.stats.gamma.logpdf(value, concentration, scale=1.0 / rate)


def log_prior(params: GPParams, active: jax.Array, priors: Priors = BOTORCH_PRIORS) -> jax.Array:
    """Sum of the Gamma log densities of ``priors`` (active inputs only).

    Args:
      params: the hyperparameters (the mean has no prior).
      active: (d,) bool active-input mask; inactive lengthscales add 0.
      priors: the hyperparameters' priors.

    Returns:
      () the log prior density of the constrained values (no Jacobian of the log transform).
    """
    lengthscale_terms = _gamma_log_density(jnp.exp(params.log_lengthscales), *priors.lengthscale)
    return (
        jnp.sum(jnp.where(active, lengthscale_terms, 0.0))
        + _gamma_log_density(jnp.exp(params.log_outputscale), *priors.outputscale)
        + _gamma_log_density(jnp.exp(params.log_noise), *priors.noise)
    )


def _log_prior_gradient(params: GPParams, active: jax.Array, priors: Priors) -> GPParams:
    r"""Gradient of :func:`log_prior` in the log parameters: for a Gamma(a, b) density of
    :math:`v = e^u`, :math:`\partial_u \log p = (a - 1) - b v`."""

    def gamma_term(log_value, prior):
        concentration, rate = prior
        return (concentration - 1.0) - rate * jnp.exp(log_value)

    return GPParams(
        log_lengthscales=jnp.where(active, gamma_term(params.log_lengthscales, priors.lengthscale), 0.0),
        log_outputscale=gamma_term(params.log_outputscale, priors.outputscale),
        log_noise=gamma_term(params.log_noise, priors.noise),
        mean=jnp.zeros_like(params.mean),
    )


def _log_marginal_likelihood_gradient(
    params: GPParams,
    prepared: _Prepared,
    factored: _Factored,
    active: jax.Array,
    context_dims: int,
) -> GPParams:
    r"""Analytic gradient of the log marginal likelihood in the (log) hyperparameters. Written out because it pays:
    with the value, faster than ``jax.value_and_grad`` of the same log posterior (benchmarks/RESULTS.md,
    "Hand-written derivatives against JAX's"), and autodiff cannot pass the one-matrix-per-call LAPACK batching rule.

    Rasmussen & Williams eq. (5.9): :math:`\partial_\theta \log p =
    \tfrac12 \operatorname{tr}(W \partial_\theta K)` with :math:`W = \alpha\alpha^\top - K^{-1}`
    over the valid block (padded entries of :math:`K` do not depend on :math:`\theta`). With
    :math:`K = s^2 (k_x k_c + \rho I) + \sigma^2 I` and
    :math:`r_x^2 = \sum_{d \in x} \Delta_d^2 e^{-2 u_d}` (:math:`u_d = \log\ell_d`):

    * :math:`\partial_{\log s^2} = \tfrac12 s^2 \sum_{ij} W_{ij} (C_{ij} + \rho\,\delta_{ij})`,
    * :math:`\partial_{\log\sigma^2} = \tfrac12 \sigma^2 \operatorname{tr} W`,
    * :math:`\partial_{u_d} = -e^{-2u_d} \sum_{ij} s^2 W_{ij} k_c k'_x(r_x^2)\, \Delta_{d,ij}^2`
      for :math:`d \in x` (likewise with x and c swapped),
    * :math:`\partial_{m} = \sum_i \alpha_i` (the residual is :math:`z - m`).

    :math:`K^{-1} = L^{-\top} L^{-1}` from one triangular inversion of the Cholesky factor.
    """
    outputscale, noise = jnp.exp(params.log_outputscale), jnp.exp(params.log_noise)
    valid = prepared.valid
    cholesky_inverse = _cholesky_inverse(factored.cholesky)
    kernel_inverse = cholesky_inverse.T @ cholesky_inverse
    w = jnp.where(valid[:, None] & valid[None, :], jnp.outer(factored.weights, factored.weights) - kernel_inverse, 0.0)
    scaled_w = outputscale * w
    trace_w = jnp.trace(w)
    inverse_sq_lengthscales = _inverse_squared_lengthscales(params, active)
    num_x = prepared.sq_differences.shape[0] - context_dims

    def lengthscale_gradient(sq_differences, inverse_sq, derivative, other_factor):
        m = scaled_w * derivative if other_factor is None else scaled_w * derivative * other_factor
        return -inverse_sq * jnp.tensordot(sq_differences, m, axes=2)

    corr_x, corr_c = factored.correlation_x, factored.correlation_c
    gradients = [
        lengthscale_gradient(
            prepared.sq_differences[:num_x], inverse_sq_lengthscales[:num_x], factored.derivative_x, corr_c
        )
    ]
    if context_dims:
        gradients.append(
            lengthscale_gradient(
                prepared.sq_differences[num_x:], inverse_sq_lengthscales[num_x:], factored.derivative_c, corr_x
            )
        )
    corr = corr_x if corr_c is None else corr_x * corr_c
    return GPParams(
        log_lengthscales=jnp.concatenate(gradients),
        log_outputscale=0.5 * (jnp.sum(scaled_w * corr) + JITTER_RATIO * outputscale * trace_w),
        log_noise=0.5 * noise * trace_w,
        mean=jnp.sum(factored.weights),
    )


def log_posterior(
    params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int, priors: Priors = BOTORCH_PRIORS
):
    """The fit's objective: log marginal likelihood + log prior (unnormalized log MAP).

    Args:
      params: the hyperparameters.
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      context_dims: static number of trailing context columns.
      priors: the hyperparameters' priors.

    Returns:
      () :func:`log_marginal_likelihood` + :func:`log_prior`.
    """
    return log_marginal_likelihood(params, dataset, active, context_dims) + log_prior(params, active, priors)


def log_posterior_and_gradient(
    params: GPParams,
    dataset: Dataset,
    active: jax.Array,
    context_dims: int,
    priors: Priors = BOTORCH_PRIORS,
) -> tuple[jax.Array, GPParams]:
    """:func:`log_posterior` and its analytic gradient in the (log) hyperparameters.

    Args:
      params: the hyperparameters.
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      context_dims: static number of trailing context columns.
      priors: the hyperparameters' priors.

    Returns:
      (the log posterior (), its gradient as :class:`GPParams`: 0 for inactive lengthscales).
    """
    return _log_posterior_and_gradient(params, _prepare(dataset), active, context_dims, priors)


def _log_posterior_and_gradient(params, prepared, active, context_dims, priors):
    factored = _factor(params, prepared, active, context_dims)
    value = _log_marginal_likelihood(factored, prepared) + log_prior(params, active, priors)
    likelihood_gradient = _log_marginal_likelihood_gradient(params, prepared, factored, active, context_dims)
    gradient = jax.tree.map(jnp.add, likelihood_gradient, _log_prior_gradient(params, active, priors))
    return value, gradient


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
    priors: Priors = BOTORCH_PRIORS,
) -> GPParams:
    """MAP hyperparameters by projected Adam from the better of the warm and default starts.

    The start with the higher :func:`log_posterior` (ties and non-finite values go to the
    default start) runs ``config.num_steps`` Adam steps (cosine-decayed step size) on the
    negative log posterior per valid point (as GPyTorch's MLL / n), with the analytic gradient
    of :func:`log_posterior_and_gradient` (one Cholesky factorization and one triangular
    inversion per step); a step whose loss or gradient is not finite is skipped.

    Args:
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      warm_start: parameters to start from, e.g. the previous fit.
      context_dims: static number of trailing context columns.
      config: static fit settings.
      priors: the hyperparameters' priors (static).

    Returns:
      The fitted :class:`GPParams`.
    """
    prepared = _prepare(dataset)
    per_point = 1.0 / jnp.maximum(jnp.sum(dataset.valid), 1)

    def objective(params):
        value, gradient = _log_posterior_and_gradient(params, prepared, active, context_dims, priors)
        return -per_point * value, jax.tree.map(lambda g: -per_point * g, gradient)

    def start_loss(params):
        factored = _factor(params, prepared, active, context_dims)
        return -per_point * (_log_marginal_likelihood(factored, prepared) + log_prior(params, active, priors))

    schedule = optax.cosine_decay_schedule(config.learning_rate, config.num_steps, alpha=0.1)
    optimizer = optax.adam(schedule)

    def step(carry, _):
        params, opt_state = carry
        loss, grads = objective(params)
        updates, new_opt_state = optimizer.update(grads, opt_state, params)
        new_params = _project(optax.apply_updates(params, updates))
        finite = jnp.isfinite(loss) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)]))
        keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
        return (jax.tree.map(keep, new_params, params), jax.tree.map(keep, new_opt_state, opt_state)), None

    def run(start):
        start = _project(start)
        (params, _), _ = jax.lax.scan(step, (start, optimizer.init(start)), None, length=config.num_steps)
        return params

    default = default_params(dataset.inputs.shape[-1], priors)
    starts = jax.tree.map(lambda a, b: jnp.stack([a, b]), default, warm_start)
    start_losses = jax.vmap(lambda p: start_loss(_project(p)))(starts)
    start_losses = jnp.where(jnp.isfinite(start_losses), start_losses, jnp.inf)
    best = jnp.argmin(start_losses)
    return run(jax.tree.map(lambda leaf: leaf[best], starts))


def posterior(params: GPParams, dataset: Dataset, active: jax.Array, context_dims: int) -> Posterior:
    """Condition the GP on a dataset: one Cholesky factorization and its triangular inverse,
    reused by every :func:`predict`.

    Args:
      params: the hyperparameters, e.g. from :func:`fit`.
      dataset: the masked training set.
      active: (d,) bool active-input mask.
      context_dims: static number of trailing context columns.

    Returns:
      A :class:`Posterior`.
    """
    prepared = _prepare(dataset)
    factored = _factor(params, prepared, active, context_dims)
    return Posterior(
        params,
        prepared.inputs,
        dataset.valid,
        active,
        _cholesky_inverse(factored.cholesky),
        factored.weights,
        prepared.target_mean,
        prepared.target_std,
    )


def predict(post: Posterior, query_inputs: jax.Array, context_dims: int) -> tuple[jax.Array, jax.Array]:
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
    whitened = post.cholesky_inverse @ cross.T
    variance_z = jnp.maximum(
        outputscale - jnp.sum(whitened**2, axis=0),
        MIN_VARIANCE_RATIO * outputscale,
    )
    return post.target_mean + post.target_std * mean_z, post.target_std**2 * variance_z
