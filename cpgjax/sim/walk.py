"""Walk the simulated Go1 with fixed CPG parameters for a few back-to-back trials and report the paper's trial figures.

Used by ``cpgjax walk`` (:func:`run_walk`: every trial, :func:`walk_trials`, its :func:`trials_table`, and in a
folder ``walk.parquet`` of :func:`trial_columns` and ``metadata.json``) and studies/walk_evidence.py (each walk's last
trial: :func:`walk`, :func:`markdown_table`).
"""

from __future__ import annotations

import itertools
import json
import pathlib
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

import cpgjax
from cpgjax import compile_cache, cpg, outputs, provenance
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains
from cpgjax.sim import backends
from cpgjax.trial import limits, objective, protocol
from cpgjax.trial import params as param_space
from cpgjax.trial.condition import Condition

TABLE = "walk.parquet"  # cpgjax walk --out: every trial, the columns of trial_columns
OUTPUTS = (
    outputs.OutputFile(
        TABLE, "one row per trial of each walk: conditions, parameters, J, velocity, CoT, falls", outputs.check_parquet
    ),
)


class WalkRow(NamedTuple):
    """One walk's row of :func:`walk`: its last trial's figures."""

    controller: str
    physics: str
    condition: Condition
    vx_mps: float
    vy_mps: float
    cot: float
    objective: float  # J for the condition's target velocity
    c_load_n: float
    c_slope_rad: float
    roll_std_rad: float
    pitch_std_rad: float
    falls: int  # trials (of all run) in which the robot fell


class WalkTrial(NamedTuple):
    """One trial of one walk (one combination of the grid): its conditions, parameters and trial figures."""

    walk: int  # the walk's row in the grid
    trial: int
    controller: str
    physics: str
    condition: Condition
    friction_in_effect: float  # the μ the feet feel: the smaller of floor's and feet's (go1_model.effective_friction)
    params: np.ndarray  # (8,)
    record: protocol.TrialRecord  # of this trial (one instance's fields)
    objective: float
    velocity_xy_mps: np.ndarray  # (2,) steady-phase mean
    cot: float


def walk_trials(
    controllers=cpg.CONTROLLERS,
    gaits=(cpg.DEFAULT_GAIT,),
    friction=(0.6,),
    slope_deg=(0.0,),
    payload_kg=(0.0,),
    params=None,
    num_trials: int = 2,
    target_velocity_mps: float = 0.5,
    trial_config: protocol.TrialConfig = protocol.TrialConfig(),
    backend: str = "auto",
    physics=(physics_profiles.DEFAULT_PROFILE,),
    progress=print,
    cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
    ground: terrains.Ground = terrains.FLAT_GROUND,
    foot_friction: float = -1.0,
) -> tuple[list[WalkTrial], dict]:
    """Every combination of controller × gait × friction × slope × payload × physics profile on ``ground`` with the
    feet's μ ``foot_friction`` (−1: each profile's own),
    ``num_trials`` trials back to back with the same parameters (default: the middle of the paper's ranges) on
    ``backend``
    (:func:`backends.make_backend`) with the controller's ``cpg_config`` (its start-up); returns every trial of every
    walk, walk-major, and the timing.

    Raises:
      ValueError: ``num_trials`` < 1, a target velocity outside ``limits.TARGET_VELOCITY_MPS`` or a terrain that
        ``go1_model.make_scenarios`` refuses, before any compute.
    """
    limits.check_count(num_trials, "num_trials")
    limits.TARGET_VELOCITY_MPS.check(target_velocity_mps, "target_velocity_mps")
    grid = list(itertools.product(controllers, gaits, friction, slope_deg, payload_kg, physics))
    scenario = go1_model.make_scenarios(
        friction=[g[2] for g in grid],
        slope_deg=[g[3] for g in grid],
        payload_kg=[g[4] for g in grid],
        physics=[g[5] for g in grid],
        foot_friction=foot_friction,
        **ground._asdict(),
    )
    in_effect = go1_model.effective_friction(scenario)
    p = np.tile(param_space.midpoint() if params is None else params, (len(grid), 1))
    gates = protocol.batch_gates([g[0] for g in grid], [g[1] for g in grid])
    sim = backends.make_backend(scenario, backend, cpg_config, trial_config)
    figures = jax.vmap(
        lambda r: (
            objective.objective(r, target_velocity_mps),
            objective.mean_velocity(r),
            objective.cost_of_transport(r),
        )
    )
    t0 = time.perf_counter()
    state = sim.reset(p, gates)
    records = []
    compile_s = None
    for k in range(num_trials):
        state, record = sim.trial(state, p, gates)
        records.append(jax.tree.map(np.asarray, (record, *figures(record))))
        if compile_s is None:
            compile_s = time.perf_counter() - t0
            t1 = time.perf_counter()
        progress(f"{k + 1}/{num_trials} trials done ({time.perf_counter() - t0:.1f} s)")
    run_s = time.perf_counter() - t1
    steps = len(grid) * (num_trials - 1) * (trial_config.transition_steps + trial_config.steady_steps)
    conditions = [
        Condition(
            friction=float(f),
            slope_deg=float(s),
            payload_kg=float(m),
            target_velocity_mps=float(target_velocity_mps),
            gait=g,
            foot_friction=float(foot_friction),
            ground=ground,
        )
        for _, g, f, s, m, _ in grid
    ]
    trials = [
        WalkTrial(
            walk=i,
            trial=k,
            controller=c,
            physics=ph,
            condition=conditions[i],
            friction_in_effect=float(in_effect[i]),
            params=p[i],
            record=protocol.TrialRecord(*(field[i] for field in record)),
            objective=float(j[i]),
            velocity_xy_mps=v[i],
            cot=float(cot[i]),
        )
        for i, (c, _, _, _, _, ph) in enumerate(grid)
        for k, (record, j, v, cot) in enumerate(records)
    ]
    timing = {"compile_and_first_trial_s": compile_s, "env_steps_per_s": steps / run_s if num_trials > 1 else None}
    return trials, timing


def walk(
    controllers=cpg.CONTROLLERS,
    friction=(0.6,),
    slope_deg=(0.0,),
    payload_kg=(0.0,),
    params=None,
    num_trials: int = 2,
    target_velocity_mps: float = 0.5,
    trial_config: protocol.TrialConfig = protocol.TrialConfig(),
    backend: str = "auto",
    physics=(physics_profiles.DEFAULT_PROFILE,),
    progress=print,
) -> tuple[list[WalkRow], dict]:
    """:func:`walk_trials`, one row per walk: the figures of its last trial; ``falls`` counts trials with a fall over
    the whole walk.

    Raises:
      ValueError: as :func:`walk_trials`, before any compute.
    """
    trials, timing = walk_trials(
        controllers=controllers,
        friction=friction,
        slope_deg=slope_deg,
        payload_kg=payload_kg,
        params=params,
        num_trials=num_trials,
        target_velocity_mps=target_velocity_mps,
        trial_config=trial_config,
        backend=backend,
        physics=physics,
        progress=progress,
    )
    last = [t for t in trials if t.trial == num_trials - 1]
    falls = [sum(int(u.record.fell > 0) for u in trials if u.walk == t.walk) for t in last]
    rows = [
        WalkRow(
            controller=t.controller,
            physics=t.physics,
            condition=t.condition,
            vx_mps=float(t.velocity_xy_mps[0]),
            vy_mps=float(t.velocity_xy_mps[1]),
            cot=t.cot,
            objective=t.objective,
            c_load_n=float(t.record.c_load_n),
            c_slope_rad=float(t.record.c_slope_rad),
            roll_std_rad=float(t.record.roll_std_rad),
            pitch_std_rad=float(t.record.pitch_std_rad),
            falls=n,
        )
        for t, n in zip(last, falls, strict=True)
    ]
    return rows, timing


def trial_columns(trials: list[WalkTrial]) -> dict[str, np.ndarray]:
    """``walk.parquet``'s columns (docs/outputs.md): one row per (walk, trial); floats float64."""
    cols: dict[str, np.ndarray] = {
        "walk": np.array([t.walk for t in trials], np.int64),
        "trial": np.array([t.trial for t in trials], np.int64),
    }
    cols["controller"] = np.array([t.controller for t in trials])
    cols["gait"] = np.array([t.condition.gait for t in trials])
    cols["physics"] = np.array([t.physics for t in trials])
    cols["friction"] = np.array([t.condition.friction for t in trials], np.float64)
    cols["friction_in_effect"] = np.array([t.friction_in_effect for t in trials], np.float64)
    for name in ("foot_friction", "slope_deg", "payload_kg", "target_velocity_mps"):
        cols[name] = np.array([getattr(t.condition, name) for t in trials], np.float64)
    cols["terrain"] = np.array([t.condition.ground.terrain for t in trials])
    cols["terrain_amplitude_m"] = np.array([t.condition.ground.terrain_amplitude_m for t in trials], np.float64)
    cols["terrain_seed"] = np.array([t.condition.ground.terrain_seed for t in trials], np.int64)
    cols["terrain_step_m"] = np.array([t.condition.ground.terrain_step_m for t in trials], np.float64)
    params = np.array([t.params for t in trials], np.float64).reshape(len(trials), param_space.NUM_PARAMS)
    for i, name in enumerate(param_space.PARAM_NAMES):
        cols[name] = params[:, i]
    record = {
        name: np.array([getattr(t.record, name) for t in trials], np.float64)
        for name in (
            "c_load_n",
            "c_slope_rad",
            "roll_std_rad",
            "pitch_std_rad",
            "saturation_fraction",
            "energy_j",
            "distance_m",
            "total_mass_kg",
            "safety_margin",
        )
    }
    cols.update(
        c_load_n=record.pop("c_load_n"),
        c_slope_rad=record.pop("c_slope_rad"),
        objective=np.array([t.objective for t in trials], np.float64),
        velocity_x_mps=np.array([t.velocity_xy_mps[0] for t in trials], np.float64),
        velocity_y_mps=np.array([t.velocity_xy_mps[1] for t in trials], np.float64),
        cost_of_transport=np.array([t.cot for t in trials], np.float64),
        **record,
    )
    cols["fell"] = np.array([t.record.fell > 0 for t in trials], bool)
    cols["failed"] = np.array([t.record.failed > 0 for t in trials], bool)
    return cols


def trials_table(trials: list[WalkTrial]) -> str:
    """Every trial of every walk as a markdown table, labeled by walk and trial (numbered from 0)."""
    head = (
        "| walk | trial | controller | gait | friction | μ in effect | slope [°] | payload [kg] | physics "
        f"| v_x [m/s] | CoT | J (v*={trials[0].condition.target_velocity_mps:g} m/s) | c_load [N] | c_slope [rad] "
        "| fell |"
    )
    lines = [head, "|" + "---|" * 15]
    for t in trials:
        c = t.condition
        lines.append(
            f"| {t.walk} | {t.trial} | {t.controller} | {c.gait} | {c.friction:g} "
            f"| {t.friction_in_effect:g} | {c.slope_deg:.1f} "
            f"| {c.payload_kg:.1f} | {t.physics} | {t.velocity_xy_mps[0]:.3f} | {t.cot:.3f} "
            f"| {t.objective:.3f} | {float(t.record.c_load_n):.1f} | {float(t.record.c_slope_rad):.3f} "
            f"| {bool(t.record.fell > 0)} |"
        )
    return "\n".join(lines)


def markdown_table(rows: list[WalkRow]) -> str:
    """The rows as a markdown table; J is that of the walk's target velocity."""
    head = (
        "| controller | friction | slope [°] | payload [kg] | physics | v_x [m/s] | v_y [m/s] | CoT "
        f"| J (v*={rows[0].condition.target_velocity_mps:g} m/s) "
        "| c_load [N] | c_slope [rad] | roll std [rad] | pitch std [rad] | falls |"
    )
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        c = r.condition
        lines.append(
            f"| {r.controller} | {c.friction:.1f} | {c.slope_deg:.1f} | {c.payload_kg:.1f} | {r.physics} "
            f"| {r.vx_mps:.3f} "
            f"| {r.vy_mps:.3f} | {r.cot:.3f} | {r.objective:.3f} | {r.c_load_n:.1f} | {r.c_slope_rad:.3f} "
            f"| {r.roll_std_rad:.3f} | {r.pitch_std_rad:.3f} | {r.falls} |"
        )
    return "\n".join(lines)


class WalkOptions(NamedTuple):
    """What ``cpgjax walk`` walks (the grid and trials of :func:`walk_trials`) and where it writes."""

    controllers: tuple[str, ...]
    gaits: tuple[str, ...]
    friction: tuple[float, ...]
    slope_deg: tuple[float, ...]
    payload_kg: tuple[float, ...]
    physics: tuple[str, ...]
    num_trials: int
    params: np.ndarray | None  # (8,); None: the middle of the paper's ranges
    target_velocity_mps: float
    backend: str
    startup: str  # the controller's start-up (cpg.with_startup)
    ground: terrains.Ground
    foot_friction: float  # the feet's μ (−1: each profile's own)
    out: pathlib.Path | None  # a folder for walk.parquet and metadata.json (claimed by the caller); None: none
    command_line: str  # what metadata.json records as the command


def run_walk(
    options: WalkOptions, report: Callable[[str], None] = print, progress: Callable[[str], None] = print
) -> None:
    """``cpgjax walk``: every trial of ``options`` (:func:`walk_trials`, ``progress`` after each), its
    :func:`trials_table` and the timing to ``report``; with ``options.out``, ``walk.parquet`` (:func:`trial_columns`)
    and ``metadata.json`` there (docs/outputs.md), then a line naming them.

    Raises:
      ValueError: as :func:`walk_trials`, before any compute.
    """
    trials, timing = walk_trials(
        controllers=options.controllers,
        gaits=options.gaits,
        friction=options.friction,
        slope_deg=options.slope_deg,
        payload_kg=options.payload_kg,
        num_trials=options.num_trials,
        params=options.params,
        target_velocity_mps=options.target_velocity_mps,
        backend=options.backend,
        physics=options.physics,
        progress=progress,
        cpg_config=cpg.with_startup(cpg.CPGConfig(), options.startup),
        ground=options.ground,
        foot_friction=options.foot_friction,
    )
    report(trials_table(trials))
    pace = timing["env_steps_per_s"]
    report(
        f"compilation and the first trial {timing['compile_and_first_trial_s']:.1f} s"
        + ("" if pace is None else f"; then {pace:,.0f} env-steps/s")
    )
    if options.out is not None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table(trial_columns(trials)), options.out / TABLE)
        meta = dict(
            study="walk",
            written_by="walk",
            command=options.command_line,
            cpgjax_version=cpgjax.__version__,
            git_commit=provenance.git_commit(),
            walks=len({t.walk for t in trials}),
            trials=options.num_trials,
            backend=backends.resolve_backend(options.backend),
            startup=options.startup,
            terrain=options.ground._asdict(),
            **timing,
            environment=provenance.environment(),
            compiled_programs=compile_cache.counts(),
        )
        (options.out / outputs.METADATA).write_text(json.dumps(meta, indent=2, default=str))
        report(f"outputs in {options.out}/ (walk.parquet: every trial, docs/outputs.md)")
