"""Walk the simulated Go1 with fixed CPG parameters for a few back-to-back trials and report the paper's trial figures.

Used by ``cpgjax walk`` and studies/walk_evidence.py.
"""

from __future__ import annotations

import itertools
import time
from typing import NamedTuple

import jax
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.sim import backends
from cpgjax.trial import limits, objective, protocol
from cpgjax.trial import params as param_space


class WalkRow(NamedTuple):
    controller: str
    friction: float
    slope_deg: float
    payload_kg: float
    physics: str
    vx_mps: float
    vy_mps: float
    cot: float
    objective: float  # J for target_velocity_mps
    target_velocity_mps: float
    c_load_n: float
    c_slope_rad: float
    roll_std_rad: float
    pitch_std_rad: float
    falls: int  # trials (of all run) in which the robot fell


def walk(controllers=cpg.CONTROLLERS, friction=(0.6,), slope_deg=(0.0,), payload_kg=(0.0,), params=None,
         num_trials: int = 2, target_velocity_mps: float = 0.5,
         trial_config: protocol.TrialConfig = protocol.TrialConfig(), backend: str = "auto",
         physics=(physics_profiles.DEFAULT_PROFILE,), progress=print) -> tuple[list[WalkRow], dict]:
    """Every combination of controller × friction × slope × payload × physics profile, ``num_trials`` trials back to
    back with the same parameters (default: the middle of the paper's ranges) on ``backend``
    (:func:`backends.make_backend`). Figures are those of the last trial; ``falls`` counts trials with a fall over the
    whole walk.

    Raises:
      ValueError: ``num_trials`` < 1 or a target velocity outside ``limits.TARGET_VELOCITY_MPS``, before any compute.
    """
    limits.check_count(num_trials, "num_trials")
    limits.TARGET_VELOCITY_MPS.check(target_velocity_mps, "target_velocity_mps")
    grid = list(itertools.product(controllers, friction, slope_deg, payload_kg, physics))
    scenario = go1_model.make_scenarios(friction=[g[1] for g in grid], slope_deg=[g[2] for g in grid],
                                        payload_kg=[g[3] for g in grid], physics=[g[4] for g in grid])
    p = np.tile(param_space.midpoint() if params is None else params, (len(grid), 1))
    gates = protocol.batch_gates([g[0] for g in grid])
    sim = backends.make_backend(scenario, backend, trial_config=trial_config)
    t0 = time.perf_counter()
    state = sim.reset(p)
    falls = np.zeros(len(grid), int)
    compile_s = None
    for k in range(num_trials):
        state, record = sim.trial(state, p, gates)
        falls += np.asarray(record.fell > 0)
        if compile_s is None:
            compile_s = time.perf_counter() - t0
            t1 = time.perf_counter()
        progress(f"{k + 1}/{num_trials} trials done ({time.perf_counter() - t0:.1f} s)")
    run_s = time.perf_counter() - t1
    steps = len(grid) * (num_trials - 1) * (trial_config.transition_steps + trial_config.steady_steps)
    j = jax.vmap(objective.objective, in_axes=(0, None))(record, target_velocity_mps)
    cot = objective.cost_of_transport(record)
    v = objective.mean_velocity(record)
    rows = [WalkRow(c, f, s, m, ph, float(v[i, 0]), float(v[i, 1]), float(cot[i]), float(j[i]), target_velocity_mps,
                    float(record.c_load_n[i]), float(record.c_slope_rad[i]), float(record.roll_std_rad[i]),
                    float(record.pitch_std_rad[i]), int(falls[i]))
            for i, (c, f, s, m, ph) in enumerate(grid)]
    timing = {"compile_and_first_trial_s": compile_s, "env_steps_per_s": steps / run_s if num_trials > 1 else None}
    return rows, timing


def markdown_table(rows: list[WalkRow]) -> str:
    """The rows as a markdown table; J is that of the walk's target velocity."""
    head = ("| controller | friction | slope [°] | payload [kg] | physics | v_x [m/s] | v_y [m/s] | CoT "
            f"| J (v*={rows[0].target_velocity_mps:g} m/s) "
            "| c_load [N] | c_slope [rad] | roll std [rad] | pitch std [rad] | falls |")
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        lines.append(f"| {r.controller} | {r.friction:.1f} | {r.slope_deg:.1f} | {r.payload_kg:.1f} | {r.physics} "
                     f"| {r.vx_mps:.3f} "
                     f"| {r.vy_mps:.3f} | {r.cot:.3f} | {r.objective:.3f} | {r.c_load_n:.1f} | {r.c_slope_rad:.3f} "
                     f"| {r.roll_std_rad:.3f} | {r.pitch_std_rad:.3f} | {r.falls} |")
    return "\n".join(lines)
