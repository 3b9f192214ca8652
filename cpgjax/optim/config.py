"""Static structure of the contextual-BO optimizer (:class:`OptimizerConfig`) and the paper's
setting (:func:`paper_config`).

A configuration fixes everything that shapes the compiled program: the parameter box and the
context normalization ranges (physical units), the context-sharing thresholds of eq. (14), the
dataset capacity, the length of the random phase, the UCB form (docs/decisions.md §2) and the
static settings of the GP fit and of the acquisition maximizer. Changing it recompiles; per-
instance data (β schedules, active inputs, targets) live in the optimizer state instead
(:mod:`cpgjax.optim.bo`).
"""

import dataclasses

import numpy as np

from cpgjax import gp
from cpgjax.go1 import physics as physics_profiles
from cpgjax.optim.acquisition import UCB_FORMS, AcquisitionConfig
from cpgjax.trial import params as param_space

PAPER_CONTEXT_LOWER = (15.0, -0.4)
PAPER_CONTEXT_UPPER = (55.0, 0.1)
"""The paper's ranges of c = [c_load (N), c_slope (rad)]: r_load = 40 N, r_slope = 0.5 rad (docs/decisions.md §11).
A physics profile whose foot-force signal reads otherwise carries its own c_load range
(``cpgjax.go1.physics.PhysicsProfile.context_load_range_n``)."""

PAPER_CONTEXT_THRESHOLDS = (0.2, 0.1)
"""t_load, t_slope of eq. (14), as fractions of the range widths."""


@dataclasses.dataclass(frozen=True)
class OptimizerConfig:
    """Static structure of an optimizer (changing it recompiles).

    Attributes:
      parameter_lower, parameter_upper: the box, physical units, one entry per parameter.
      context_lower, context_upper: fixed normalization ranges of the context (empty: none).
      context_thresholds: t_k of eq. (14) per context component, fraction of the range width.
      capacity: maximum number of stored observations.
      num_random_proposals: proposals drawn uniformly at random before the GP is used.
      ucb_form: "paper" (mu + beta*sigma, eq. (8)) or "botorch" (mu + sqrt(beta)*sigma).
      inference_beta: beta in inference mode.
      fit: settings of the hyperparameter fit (of both GPs when ``safe``).
      acquisition: settings of the acquisition maximizer.
      safe: safe optimization (docs/decisions.md §17): a second GP models each observation's
        safety margin, and proposals maximize the UCB of the objective where the margin's lower
        confidence bound is ≥ 0.
      safe_beta: β_s, the multiplier on the margin GP's σ in that lower bound (2: a one-sided
        97.7 % bound under a Gaussian posterior).
    """

    parameter_lower: tuple[float, ...]
    parameter_upper: tuple[float, ...]
    context_lower: tuple[float, ...] = ()
    context_upper: tuple[float, ...] = ()
    context_thresholds: tuple[float, ...] = ()
    capacity: int = 160
    num_random_proposals: int = 2
    ucb_form: str = "paper"
    inference_beta: float = 1e-6
    fit: gp.FitConfig = gp.FitConfig()
    acquisition: AcquisitionConfig = AcquisitionConfig()
    safe: bool = False
    safe_beta: float = 2.0

    def __post_init__(self):
        _check_box("parameter", self.parameter_lower, self.parameter_upper)
        if len(self.parameter_lower) == 0:
            raise ValueError("at least one parameter is needed")
        _check_box("context", self.context_lower, self.context_upper)
        if len(self.context_thresholds) != len(self.context_lower):
            raise ValueError(
                f"context_thresholds has {len(self.context_thresholds)} entries, expected one"
                f" per context component ({len(self.context_lower)})"
            )
        if any(not t >= 0.0 for t in self.context_thresholds):
            raise ValueError(f"context_thresholds must be >= 0, got {self.context_thresholds}")
        if self.capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {self.capacity}")
        if self.num_random_proposals < 0:
            raise ValueError(f"num_random_proposals must be >= 0, got {self.num_random_proposals}")
        if self.ucb_form not in UCB_FORMS:
            raise ValueError(f"ucb_form must be one of {UCB_FORMS}, got {self.ucb_form!r}")
        if self.acquisition.num_restarts > self.acquisition.num_candidates:
            raise ValueError("acquisition.num_restarts must not exceed num_candidates")
        if not (np.isfinite(self.safe_beta) and self.safe_beta >= 0.0):
            raise ValueError(f"safe_beta must be finite and >= 0, got {self.safe_beta}")

    @property
    def num_parameters(self) -> int:
        return len(self.parameter_lower)

    @property
    def num_contexts(self) -> int:
        return len(self.context_lower)


def _check_box(name, lower, upper):
    if len(lower) != len(upper):
        raise ValueError(f"{name} bounds differ in length: {len(lower)} vs {len(upper)}")
    for i, (lo, hi) in enumerate(zip(lower, upper, strict=True)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"{name} bounds [{i}] must be finite with lower < upper, got"
                             f" [{lo}, {hi}]")


def clip_context(config: OptimizerConfig, context: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Contexts (..., C) clipped to the normalization ranges for the GP input, and one message per clipped value
    (docs/decisions.md §11: never silently). The caller logs the messages; the unclipped values stay in the record."""
    context = np.asarray(context)
    lower, upper = np.asarray(config.context_lower), np.asarray(config.context_upper)
    clipped = np.clip(context, lower, upper)
    names, units = ("c_load", "c_slope"), ("N", "rad")
    messages = [f"instance {idx[0] if len(idx) > 1 else 0}: {names[idx[-1]]} = {context[idx]:.4g} "
                f"{units[idx[-1]]} outside [{lower[idx[-1]]:g}, {upper[idx[-1]]:g}], clipped for the GP"
                for idx in zip(*np.nonzero(clipped != context), strict=True)] if len(lower) == 2 else []
    return clipped.astype(context.dtype), messages


def profile_config(physics: str, **overrides) -> OptimizerConfig:
    """:func:`paper_config` with the c_load normalization range of a physics profile's foot-force signal
    (docs/decisions.md §11)."""
    load_lower, load_upper = physics_profiles.get(physics).context_load_range_n
    return paper_config(**{"context_lower": (load_lower, PAPER_CONTEXT_LOWER[1]),
                           "context_upper": (load_upper, PAPER_CONTEXT_UPPER[1]), **overrides})


def paper_config(**overrides) -> OptimizerConfig:
    """The paper's setting: the Table I box of :mod:`cpgjax.trial.params` (physical units, order
    [g_c, g_p, ω_swing, ω_stance, μ, x_off_front, x_off_hind, σ_N]), the context ranges of
    docs/decisions.md §11 and the thresholds of eq. (14)."""
    settings = dict(
        parameter_lower=tuple(float(v) for v in param_space.PARAM_LOWER),
        parameter_upper=tuple(float(v) for v in param_space.PARAM_UPPER),
        context_lower=PAPER_CONTEXT_LOWER,
        context_upper=PAPER_CONTEXT_UPPER,
        context_thresholds=PAPER_CONTEXT_THRESHOLDS,
    )
    settings.update(overrides)
    return OptimizerConfig(**settings)
