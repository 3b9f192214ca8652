"""The 8 optimized CPG parameters: names, the paper's ranges (appendix table "Optimization parameter ranges"),
mapping to and from the unit box, and validation.

Order (paper, Sec. "Locomotion Optimization"): x = [g_c, g_p, ω_swing, ω_stance, μ, x_offset,front, x_offset,hind, σ_N].
Parameters are always carried in physical units; the unit box is only the optimizer's coordinate system.
"""

from __future__ import annotations

import numpy as np

PARAM_NAMES = (
    "ground_clearance_m",  # g_c
    "ground_penetration_m",  # g_p
    "omega_swing_rad_s",  # ω_swing
    "omega_stance_rad_s",  # ω_stance
    "amplitude_mu",  # μ, the CPG's intrinsic amplitude (not a friction)
    "x_offset_front_m",  # x_offset for the front legs
    "x_offset_hind_m",  # x_offset for the hind legs
    "sigma_n",  # σ_N, Tegotae feedback gain [rad/(s·N)]
)
NUM_PARAMS = len(PARAM_NAMES)
PARAM_LOWER = np.array([0.06, 0.005, 16.0, 10.0, 0.9, -0.06, -0.06, 0.05])
PARAM_UPPER = np.array([0.10, 0.015, 23.0, 15.0, 1.7, -0.01, -0.01, 0.30])
SIGMA_N_INDEX = PARAM_NAMES.index("sigma_n")


def midpoint() -> np.ndarray:
    """The centre of the parameter box (8,), physical units."""
    return 0.5 * (PARAM_LOWER + PARAM_UPPER)


def active_parameters(tegotae) -> np.ndarray:
    """Which parameters the optimizer searches, (..., 8) bool, for controllers with (True) or without (False)
    Tegotae (``tegotae``: a bool or an array of them): without it σ_N, the Tegotae gain, has no effect and is an
    inactive input, held at the box midpoint (docs/decisions.md §13)."""
    tegotae = np.asarray(tegotae, bool)
    active = np.ones(tegotae.shape + (NUM_PARAMS,), bool)
    active[..., SIGMA_N_INDEX] = tegotae
    return active


def hold_inactive(params, active) -> np.ndarray:
    """Parameters (..., 8) with the inactive ones (``active`` False, :func:`active_parameters`) at the box midpoint."""
    return np.where(active, params, midpoint())


def to_unit(params):
    """Physical parameters (..., 8) -> unit box [0, 1]^8. Works on NumPy and JAX arrays."""
    return (params - PARAM_LOWER) / (PARAM_UPPER - PARAM_LOWER)


def from_unit(unit):
    """Unit box (..., 8) -> physical parameters."""
    return PARAM_LOWER + unit * (PARAM_UPPER - PARAM_LOWER)


def as_dict(params) -> dict[str, float]:
    """One parameter vector (8,) as {name: value}."""
    return {name: float(v) for name, v in zip(PARAM_NAMES, np.asarray(params), strict=True)}


def validate(params, *, what: str = "params") -> np.ndarray:
    """Check a batch (..., 8) of physical parameters; return it as float64 NumPy.

    Raises:
      ValueError: wrong trailing size, or any value non-finite or outside the paper's range. The message names the
        parameter, the offending value, its index in the batch and the allowed range.
    """
    arr = np.asarray(params, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != NUM_PARAMS:
        raise ValueError(f"{what}: expected shape (..., {NUM_PARAMS}) ordered {PARAM_NAMES}, got {arr.shape}")
    flat = arr.reshape(-1, NUM_PARAMS)
    bad = ~np.isfinite(flat) | (flat < PARAM_LOWER) | (flat > PARAM_UPPER)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        where = f" (instance {row})" if flat.shape[0] > 1 else ""
        raise ValueError(
            f"{what}: {PARAM_NAMES[col]} = {float(flat[row, col])!r}{where} is outside the allowed range "
            f"[{PARAM_LOWER[col]}, {PARAM_UPPER[col]}]"
        )
    return arr
