"""The paper's setting of the generic optimizer (``cpgjax.optim``) for the Go1's trials: the parameter box of
:mod:`cpgjax.trial.params`, the context ranges of docs/decisions.md §11 and the thresholds of eq. (14). Studies
(``cpgjax.study.spec``) and the robot (``cpgjax.deployment.trials``) both take their optimizer configuration from here.
"""

from cpgjax.go1 import physics as physics_profiles
from cpgjax.optim.config import OptimizerConfig
from cpgjax.trial import params as param_space

PAPER_CONTEXT_LOWER = (15.0, -0.4)
PAPER_CONTEXT_UPPER = (55.0, 0.1)
"""The paper's ranges of c = [c_load (N), c_slope (rad)]: r_load = 40 N, r_slope = 0.5 rad (docs/decisions.md §11).
A physics profile whose foot-force signal reads otherwise carries its own c_load range
(``cpgjax.go1.physics.PhysicsProfile.context_load_range_n``)."""

PAPER_CONTEXT_THRESHOLDS = (0.2, 0.1)
"""t_load, t_slope of eq. (14), as fractions of the range widths."""


def profile_config(physics: str, **overrides) -> OptimizerConfig:
    """:func:`paper_config` with the c_load normalization range of a physics profile's foot-force signal
    (docs/decisions.md §11)."""
    load_lower, load_upper = physics_profiles.get(physics).context_load_range_n
    return paper_config(
        **{
            "context_lower": (load_lower, PAPER_CONTEXT_LOWER[1]),
            "context_upper": (load_upper, PAPER_CONTEXT_UPPER[1]),
            **overrides,
        }
    )


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
