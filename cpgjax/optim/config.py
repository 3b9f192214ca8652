"""Static structure of the contextual-BO optimizer (:class:`OptimizerConfig`), and the clipping of
measured contexts to its ranges (:func:`clip_context`).

A configuration fixes everything that shapes the compiled program: the parameter box and the
context normalization ranges (physical units), the context-sharing thresholds of eq. (14), the
dataset capacity, the length of the random phase, the UCB form (docs/decisions.md §2) and the
static settings of the GP fit and of the acquisition maximizer. Changing it recompiles; per-
instance data (β schedules, active inputs, targets) live in the optimizer state instead
(:mod:`cpgjax.optim.bo`). The optimizer knows nothing of the robot: its parameters and contexts
are whatever the boxes say. The paper's setting for the Go1 is
``cpgjax.trial.optimizer_setting.paper_config``.
"""

import dataclasses
from collections.abc import Sequence

import numpy as np

from cpgjax import gp
from cpgjax.optim.acquisition import UCB_FORMS, AcquisitionConfig


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
      margin_priors: the margin GP's hyperparameter priors, its own: the objective's GP has
        ``gp.BOTORCH_PRIORS``, which are also this default (docs/decisions.md §17 says why).
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
    margin_priors: gp.Priors = gp.BOTORCH_PRIORS

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
            raise ValueError(f"{name} bounds [{i}] must be finite with lower < upper, got [{lo}, {hi}]")


def clip_context(
    config: OptimizerConfig, context: np.ndarray, names: Sequence[str], units: Sequence[str]
) -> tuple[np.ndarray, list[str]]:
    """Contexts (..., C) clipped to the normalization ranges for the GP input, and one message per clipped value
    naming the instance (the leading index), the component (``names``, ``units``: one per component) and the range
    (docs/decisions.md §11: never silently). The caller logs the messages; the unclipped values stay in the record.

    Raises:
      ValueError: ``names`` or ``units`` do not have one entry per context component.
    """
    if len(names) != config.num_contexts or len(units) != config.num_contexts:
        raise ValueError(f"{len(names)} names and {len(units)} units for {config.num_contexts} context components")
    context = np.asarray(context)
    lower, upper = np.asarray(config.context_lower), np.asarray(config.context_upper)
    # Compared in the context's precision, so a value already clipped to a bound (rounded to it) is inside.
    clipped = np.clip(context, lower, upper).astype(context.dtype)
    messages = [
        f"instance {idx[0] if len(idx) > 1 else 0}: {names[idx[-1]]} = {context[idx]:.4g} "
        f"{units[idx[-1]]} outside [{lower[idx[-1]]:g}, {upper[idx[-1]]:g}], clipped for the GP"
        for idx in zip(*np.nonzero(clipped != context), strict=True)
    ]
    return clipped, messages
