"""A study's definition: the grid of instances, their condition schedules, and validation before any compute.

A study (:class:`StudySpec`) is the product of its grid axes — controller × seed × friction × slope × payload ×
target velocity × schedule × data reuse — and each instance's conditions per trial follow its :class:`Schedule`
(:func:`conditions`). :func:`validate` rejects a bad option with a :class:`StudyError` naming it. The lockstep engine
that runs a study is :mod:`cpgjax.ablation`.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any, NamedTuple

import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.optim import config as optimizer_config
from cpgjax.trial import limits, optimizer_setting, protocol
from cpgjax.trial import params as param_space

CONDITION_FIELDS = ("friction", "slope_deg", "payload_kg", "target_velocity_mps")
SCHEDULE_FIELDS = CONDITION_FIELDS + ("inference", "ramp")


class StudyError(ValueError):
    """A study option that cannot run; raised before any compute."""


class Change(NamedTuple):
    """From ``trial`` on, ``field`` (one of :data:`SCHEDULE_FIELDS`) takes ``value`` (inference, ramp: 0 or 1)."""

    trial: int
    field: str
    value: float


class Randomization(NamedTuple):
    """Domain randomization: every trial of every instance draws its physics uniformly from these ranges (each a
    (low, high) pair; equal ends fix the value), so the optimizer tunes for a distribution, not one floor. The draws
    are a pure function of the instance and the trial (resume reproduces them)."""

    friction: tuple[float, float] = (0.4, 1.0)
    payload_kg: tuple[float, float] = (0.0, 5.0)
    mass_scale: tuple[float, float] = (0.9, 1.1)  # links' masses ±10 %
    latency_ticks: tuple[int, int] = (0, 2)  # integers, both ends included
    noise_scale: tuple[float, float] = (0.0, 2.0)  # sensor noise × the robot's (the go1 profile's)
    seed: int = 0


class Ramp(NamedTuple):
    """A continuous ramp, the terrain of the paper's Fig. slope_setting: the slope rises from ``start_deg`` at the
    bottom to ``end_deg`` over ``length_m`` of climb, then stays there. Trials whose ``ramp`` condition is on walk
    it: each trial's slope is the ramp's at the distance the instance has climbed since it reached the ramp, and a
    fall puts it back at the bottom (``cpgjax.ablation``; docs/decisions.md §4)."""

    start_deg: float
    end_deg: float
    length_m: float

    def slope_deg(self, climbed_m):
        """The slope [deg] after ``climbed_m`` of climb (NumPy, any shape)."""
        fraction = np.clip(np.asarray(climbed_m, np.float64) / self.length_m, 0.0, 1.0)
        return self.start_deg + (self.end_deg - self.start_deg) * fraction


class Schedule(NamedTuple):
    """A named sequence of condition changes, one grid axis of a study."""

    label: str
    changes: tuple[Change, ...] = ()


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """A batch of online optimizations: the grid of instances, their schedules, and the static structure.

    Attributes:
      name: the study's name (output folder, metadata).
      num_trials: trials per instance (each 1.5 s + 3 s at the paper's timing).
      controllers, seeds, friction, slope_deg, payload_kg, target_velocity_mps, schedules, data_reuse, physics:
        grid axes; an instance is one element of their product, in this order (physics: profile names of
        ``cpgjax.go1.physics.PROFILES``).
      group_by: instance labels whose combinations form the groups of the progress display and the summaries.
      randomize: domain randomization of every trial's physics (None: the grid's fixed values).
      trial: trial timing (static).
      optimizer: the optimizer's static structure; ``None`` = :func:`optimizer_setting.profile_config` of the first
        physics profile with capacity ``max_trials``.
      safe: safe optimization (docs/decisions.md §17): each instance's optimizer also models the trials' safety
        margins and proposes only where they are certified ≥ 0 (``OptimizerConfig.safe``).
      ramp: the continuous ramp that trials with the ``ramp`` condition walk (None: no trial does).
      max_trials: the trials the optimizers hold (their GP's capacity; ``None``: ``num_trials``). The GP's arithmetic
        depends on its padded size, so a run computes each trial exactly as another run of the same ``max_trials``
        does, whatever their ``num_trials``: a finished run can be extended up to ``max_trials`` trials with the
        results of a run of that many (``cpgjax.study.files.extension_of``).
    """

    name: str
    num_trials: int = 40
    controllers: tuple[str, ...] = ("vmc_tegotae",)
    seeds: tuple[int, ...] = (0,)
    friction: tuple[float, ...] = (0.6,)
    slope_deg: tuple[float, ...] = (0.0,)
    payload_kg: tuple[float, ...] = (0.0,)
    target_velocity_mps: tuple[float, ...] = (0.5,)
    schedules: tuple[Schedule, ...] = (Schedule("constant"),)
    data_reuse: tuple[bool, ...] = (True,)
    physics: tuple[str, ...] = (physics_profiles.DEFAULT_PROFILE,)
    randomize: Randomization | None = None
    group_by: tuple[str, ...] = ("controller",)
    trial: protocol.TrialConfig = protocol.TrialConfig()
    optimizer: optimizer_config.OptimizerConfig | None = None
    safe: bool = False
    max_trials: int | None = None  # max_trials and ramp: unset unless given, see study.files.fingerprint
    ramp: Ramp | None = None

    def optimizer_config(self) -> optimizer_config.OptimizerConfig:
        """``optimizer``, or the paper's setting with capacity ``max_trials`` (default ``num_trials``) and the c_load
        range of the physics profiles' foot-force signal (docs/decisions.md §11; :func:`validate` checks the profiles
        agree); safe with ``safe``."""
        config = (self.optimizer if self.optimizer is not None
                  else optimizer_setting.profile_config(self.physics[0], capacity=self.max_trials or self.num_trials))
        return dataclasses.replace(config, safe=True) if self.safe and not config.safe else config


LABELS = ("controller", "seed", "friction", "slope_deg", "payload_kg", "target_velocity_mps", "schedule",
          "data_reuse", "physics")


def instances(spec: StudySpec) -> list[dict[str, Any]]:
    """The labels of every instance of the grid, in batch order."""
    axes = (spec.controllers, spec.seeds, spec.friction, spec.slope_deg, spec.payload_kg, spec.target_velocity_mps,
            [s.label for s in spec.schedules], spec.data_reuse, spec.physics)
    return [dict(zip(LABELS, combo, strict=True)) for combo in itertools.product(*axes)]


class Conditions(NamedTuple):
    """Per-instance, per-trial conditions, each (B, num_trials)."""

    friction: np.ndarray
    slope_deg: np.ndarray
    payload_kg: np.ndarray
    target_velocity_mps: np.ndarray
    inference: np.ndarray  # bool
    ramp: np.ndarray  # bool: the trial walks the spec's ramp, whose slope the engine writes into slope_deg
    mass_scale: np.ndarray  # 1 unless randomized
    latency_ticks: np.ndarray  # int, −1 (the profile's) unless randomized
    noise_scale: np.ndarray  # sensor noise × the robot's; −1 (the profile's own) unless randomized


def conditions(spec: StudySpec) -> Conditions:
    """Apply every instance's schedule to its grid values (validated by :func:`validate`)."""
    labels = instances(spec)
    schedules = {s.label: s for s in spec.schedules}
    n = spec.num_trials
    out = {f: np.zeros((len(labels), n)) for f in SCHEDULE_FIELDS}
    for b, lab in enumerate(labels):
        for f in CONDITION_FIELDS:
            out[f][b] = lab[f]
        for change in sorted(schedules[lab["schedule"]].changes, key=lambda c: c.trial):
            out[change.field][b, change.trial:] = change.value
    out["inference"], out["ramp"] = out["inference"] > 0.5, out["ramp"] > 0.5
    out["mass_scale"], out["latency_ticks"] = np.ones((len(labels), n)), np.full((len(labels), n), -1, np.int64)
    out["noise_scale"] = np.full((len(labels), n), -1.0)
    if spec.randomize is not None:
        out.update(randomized(spec.randomize, len(labels), n))
    return Conditions(**out)


def randomized(ranges: Randomization, batch: int, num_trials: int) -> dict[str, np.ndarray]:
    """Per-instance, per-trial draws (B, num_trials) of the randomized fields; instance b's draws depend on b and
    ``ranges.seed`` only."""
    draws = {f: np.zeros((batch, num_trials)) for f in ("friction", "payload_kg", "mass_scale", "noise_scale")}
    latency = np.zeros((batch, num_trials), np.int64)
    for b in range(batch):
        rng = np.random.default_rng([ranges.seed, b])
        for f in ("friction", "payload_kg", "mass_scale"):
            low, high = getattr(ranges, f)
            draws[f][b] = rng.uniform(low, high, num_trials)
        latency[b] = rng.integers(ranges.latency_ticks[0], ranges.latency_ticks[1] + 1, num_trials)
        draws["noise_scale"][b] = rng.uniform(*ranges.noise_scale, num_trials)  # drawn last: the others keep theirs
    return {**draws, "latency_ticks": latency}


def validate(spec: StudySpec) -> Conditions:
    """Check a study before any compute; returns its conditions.

    Raises:
      StudyError: the message names the option, the bad value and what is allowed.
    """
    def fail(msg):
        raise StudyError(f"study {spec.name!r}: {msg}")

    if not isinstance(spec.num_trials, int) or spec.num_trials < 1:
        fail(f"num_trials = {spec.num_trials!r}; need an integer >= 1")
    if spec.max_trials is not None and (not isinstance(spec.max_trials, int)
                                        or not spec.num_trials <= spec.max_trials <= limits.MAX_TRIALS):
        fail(f"max_trials = {spec.max_trials!r}; need an integer in [num_trials = {spec.num_trials}, "
             f"{limits.MAX_TRIALS}]")
    for axis in ("controllers", "seeds", "friction", "slope_deg", "payload_kg", "target_velocity_mps", "schedules",
                 "data_reuse", "physics"):
        values = getattr(spec, axis)
        if len(values) == 0:
            fail(f"grid axis {axis} is empty")
        if len(set(values)) != len(values):
            fail(f"grid axis {axis} has duplicates: {values}")
    for c in spec.controllers:
        if c not in cpg.CONTROLLERS:
            fail(f"unknown controller {c!r}; allowed: {cpg.CONTROLLERS}")
    for name in spec.physics:
        if name not in physics_profiles.PROFILES:
            fail(f"unknown physics profile {name!r}; allowed: {tuple(physics_profiles.PROFILES)}")
    ranges = {physics_profiles.get(name).context_load_range_n for name in spec.physics}
    if spec.optimizer is None and len(ranges) > 1:
        fail(f"physics profiles {spec.physics} normalize c_load over different ranges {sorted(ranges)}; run them as "
             f"separate studies or give an optimizer config")
    for s in spec.seeds:
        if not isinstance(s, (int, np.integer)) or s < 0:
            fail(f"seed {s!r}: need a non-negative integer")
    for g in spec.group_by:
        if g not in LABELS:
            fail(f"group_by {g!r}: allowed labels {LABELS}")
    for schedule in spec.schedules:
        for change in schedule.changes:
            if change.field not in SCHEDULE_FIELDS:
                fail(f"schedule {schedule.label!r}: unknown field {change.field!r}; allowed: {SCHEDULE_FIELDS}")
            if not 0 <= change.trial < spec.num_trials:
                fail(f"schedule {schedule.label!r}: change at trial {change.trial} outside [0, {spec.num_trials})")
    ramp_trials = any(c.field == "ramp" and c.value > 0.5 for s in spec.schedules for c in s.changes)
    if ramp_trials and spec.ramp is None:
        fail("a schedule puts trials on the ramp, and the study defines none (ramp)")
    if spec.ramp is not None:
        r = spec.ramp
        if not (r.length_m > 0 and limits.SLOPE_DEG.contains(r.start_deg) and limits.SLOPE_DEG.contains(r.end_deg)):
            fail(f"ramp {r}: need length_m > 0 and slopes in {limits.SLOPE_DEG}")
    config = spec.optimizer_config()
    if config.capacity < spec.num_trials:
        fail(f"optimizer capacity {config.capacity} < num_trials {spec.num_trials}")
    if config.num_parameters != param_space.NUM_PARAMS or config.num_contexts != 2:
        fail("the optimizer must search the 8 CPG parameters with the 2 contexts [c_load, c_slope]")
    if spec.trial.steady_steps < 1 or spec.trial.transition_steps < 0:
        fail(f"trial timing {spec.trial} needs steady_steps >= 1 and transition_steps >= 0")
    cond = conditions(spec)
    # the same ranges as the command line's options (cpgjax.trial.limits), for every trial's conditions
    for field, allowed in (("friction", limits.FRICTION), ("slope_deg", limits.SLOPE_DEG),
                           ("payload_kg", limits.PAYLOAD_KG), ("target_velocity_mps", limits.TARGET_VELOCITY_MPS)):
        values = np.asarray(getattr(cond, field), np.float64)
        bad = ~np.vectorize(allowed.contains)(values)
        if bad.any():
            b, t = np.argwhere(bad)[0]
            try:
                allowed.check(values[b, t], field)
            except ValueError as err:
                fail(f"instance {b}, trial {t}: {err}")
    try:
        for t in range(spec.num_trials):
            go1_model.make_scenarios(cond.friction[:, t], cond.slope_deg[:, t], cond.payload_kg[:, t],
                                     mass_scale=cond.mass_scale[:, t], latency_ticks=cond.latency_ticks[:, t],
                                     noise_scale=cond.noise_scale[:, t])
    except ValueError as err:
        fail(f"trial {t}: {err}")
    return cond
