"""A study's definition: the grid of instances, their condition schedules, and validation before any compute.

A study (:class:`StudySpec`) is the product of its grid axes — controller × gait × seed × friction × slope × payload
× target velocity × schedule × data reuse × physics × roughness × terrain seed — and each instance's conditions per
trial follow its :class:`Schedule` (:func:`conditions`). :func:`validate` rejects a bad option with a
:class:`StudyError` naming it. The lockstep engine that runs a study is :mod:`cpgjax.ablation`.
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import pathlib
import re
import tomllib
from typing import Any, NamedTuple

import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains
from cpgjax.go1.constants import TICK_S
from cpgjax.optim import acquisition
from cpgjax.optim import config as optimizer_config
from cpgjax.trial import limits, objective, optimizer_setting, protocol
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
    fall puts it back at the bottom (:func:`walked`; docs/decisions.md §4)."""

    start_deg: float
    end_deg: float
    length_m: float

    def slope_deg(self, climbed_m):
        """The slope [deg] after ``climbed_m`` of climb (NumPy, any shape)."""
        fraction = np.clip(np.asarray(climbed_m, np.float64) / self.length_m, 0.0, 1.0)
        return self.start_deg + (self.end_deg - self.start_deg) * fraction


class Schedule(NamedTuple):
    """A named sequence of condition changes, one grid axis of a study. ``label`` is the schedule's value in the
    trial table and the reports; ``name``, a word, names its group in file names (``best_<name>.mp4``; empty: the
    label stands there)."""

    label: str
    changes: tuple[Change, ...] = ()
    name: str = ""

    def __repr__(self) -> str:  # without a name, the repr of a schedule before names existed (study.files.fingerprint)
        name = f", name={self.name!r}" if self.name else ""
        return f"Schedule(label={self.label!r}, changes={self.changes!r}{name})"


VMC_GATES = ("loaded", "phase")  # Switches.vmc_gate


class Switches(NamedTuple):
    """The readings of the paper it leaves open, one switch each (docs/decisions.md); every default is the reading the
    reproduction uses, so a study that sets one switch is a one-change run of it.

    Attributes:
      amplitude_form: eq. (1) as printed ("paper": r → μ) or as the lab's public code ("sqrt": r → √μ), §1.
      ucb_form: eq. (8) as printed ("paper": m + β·σ) or as BoTorch computes it ("botorch": m + √β·σ), §2.
      vmc_gate: VMC on the legs in the CPG's stance phase with a loaded foot ("loaded", > 10 N) or in the stance
        phase alone ("phase"), §7.
      objective_floor: J's lower bound, and the J of a fall (``trial.limits.OBJECTIVE_FLOOR``), §10.
    """

    amplitude_form: str = "paper"
    ucb_form: str = "paper"
    vmc_gate: str = "loaded"
    objective_floor: float = objective.MIN_OBJECTIVE

    def cpg_config(self, config: cpg.CPGConfig) -> cpg.CPGConfig:
        """``config`` with the controller's switches."""
        gate = config.vmc_contact_force_n if self.vmc_gate == "loaded" else -np.inf
        return config._replace(amplitude_form=self.amplitude_form, vmc_contact_force_n=gate)


SWITCH_VALUES: dict[str, tuple[str, ...] | limits.Range] = {
    "amplitude_form": cpg.AMPLITUDE_FORMS,
    "ucb_form": acquisition.UCB_FORMS,
    "vmc_gate": VMC_GATES,
    "objective_floor": limits.OBJECTIVE_FLOOR,
}


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """A batch of online optimizations: the grid of instances, their schedules, and the static structure.

    Attributes:
      name: the study's name (output folder, metadata).
      num_trials: trials per instance (each 1.5 s + 3 s at the paper's timing).
      controllers, seeds, friction, slope_deg, payload_kg, target_velocity_mps, schedules, data_reuse, physics:
        grid axes; an instance is one element of their product, in this order, with the gaits after the
        controllers (physics: profile names of ``cpgjax.go1.physics.PROFILES``).
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
      startup: how the controller starts from standing, at trial 0 and after every fall (``cpg.STARTUPS``,
        docs/decisions.md §18; None: the paper's start).
      switches: the paper's open readings (:class:`Switches`; None: every default).
      gaits: a grid axis of gaits (``cpg.GAITS``; None: the paper's trot alone, and the trial table has no gait
        column, as before gaits existed).
      terrain_amplitude_m, terrain_seed: grid axes of the ground (``cpgjax.go1.terrain``): a rough ground's
        peak-to-peak height [m] (0: the flat plane) and the seed of its heights; None: the flat plane alone, and the
        trial table has no terrain columns.
      foot_friction: a grid axis of the feet's μ (``go1_model.Scenario.foot_friction``: a contact takes the smaller
        of floor's and feet's); None: each physics profile's own feet, and the trial table has no foot_friction
        column.
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
    max_trials: int | None = None  # max_trials … switches: unset unless given, see study.files.fingerprint
    ramp: Ramp | None = None
    startup: str | None = None
    switches: Switches | None = None
    gaits: tuple[str, ...] | None = None
    terrain_amplitude_m: tuple[float, ...] | None = None
    terrain_seed: tuple[int, ...] | None = None
    foot_friction: tuple[float, ...] | None = None

    def axis(self, field: str) -> tuple:
        """The values of the grid axis ``field`` (a field name); an unset one's default (:data:`UNSET_AXES`)."""
        value = getattr(self, field)
        return UNSET_AXES[field] if value is None and field in UNSET_AXES else value

    def has_terrain(self) -> bool:
        """Whether the study sets a ground axis (its trial table then names each instance's ground)."""
        return self.terrain_amplitude_m is not None or self.terrain_seed is not None

    def switch_values(self) -> Switches:
        """``switches``, or every default."""
        return self.switches or Switches()

    def cpg_config(self) -> cpg.CPGConfig:
        """The controller's constants with the study's start-up (``cpg.STARTUPS``; None: the paper's) and switches."""
        return self.switch_values().cpg_config(cpg.with_startup(cpg.CPGConfig(), self.startup or cpg.DEFAULT_STARTUP))

    def optimizer_config(self) -> optimizer_config.OptimizerConfig:
        """``optimizer``, or the paper's setting with capacity ``max_trials`` (default ``num_trials``) and the c_load
        range of the physics profiles' foot-force signal (docs/decisions.md §11; :func:`validate` checks the profiles
        agree); safe with ``safe``."""
        config = (
            self.optimizer
            if self.optimizer is not None
            else optimizer_setting.profile_config(self.physics[0], capacity=self.max_trials or self.num_trials)
        )
        config = dataclasses.replace(config, safe=True) if self.safe and not config.safe else config
        if self.switches is None or config.ucb_form == self.switches.ucb_form:
            return config
        return dataclasses.replace(config, ucb_form=self.switches.ucb_form)


def startup_field(name: str | None) -> str | None:
    """A start-up's name (``cpg.STARTUPS``) as :attr:`StudySpec.startup` holds it: the paper's, the default, unset."""
    return None if name == cpg.DEFAULT_STARTUP else name


UNSET_AXES = {
    "gaits": (cpg.DEFAULT_GAIT,),
    "terrain_amplitude_m": (0.0,),
    "terrain_seed": (0,),
    "foot_friction": (-1.0,),
}
"""The values of the grid axes a study leaves unset (None): the paper's trot on the flat plane, on each profile's own
feet."""

LABELS = (
    "controller",
    "gait",
    "seed",
    "friction",
    "slope_deg",
    "payload_kg",
    "target_velocity_mps",
    "schedule",
    "data_reuse",
    "physics",
    "terrain_amplitude_m",
    "terrain_seed",
    "foot_friction",
)


def label_values(spec: StudySpec) -> dict[str, tuple]:
    """Each label of :data:`LABELS` → the values its grid axis takes, in batch order."""
    return dict(
        zip(
            LABELS,
            (
                spec.controllers,
                spec.axis("gaits"),
                spec.seeds,
                spec.friction,
                spec.slope_deg,
                spec.payload_kg,
                spec.target_velocity_mps,
                tuple(s.label for s in spec.schedules),
                spec.data_reuse,
                spec.physics,
                spec.axis("terrain_amplitude_m"),
                spec.axis("terrain_seed"),
                spec.axis("foot_friction"),
            ),
            strict=True,
        )
    )


def ground(labels: dict[str, Any]) -> terrains.Ground:
    """An instance's ground from its labels: rough of its amplitude and seed, or the flat plane at amplitude 0."""
    amplitude = float(labels["terrain_amplitude_m"])
    if amplitude == 0.0:
        return terrains.FLAT_GROUND
    return terrains.Ground("rough", amplitude, int(labels["terrain_seed"]))


def instances(spec: StudySpec) -> list[dict[str, Any]]:
    """The labels of every instance of the grid, in batch order."""
    return [dict(zip(LABELS, combo, strict=True)) for combo in itertools.product(*label_values(spec).values())]


class Conditions(NamedTuple):
    """Per-instance, per-trial conditions, each (B, num_trials)."""

    friction: np.ndarray
    slope_deg: np.ndarray
    payload_kg: np.ndarray
    target_velocity_mps: np.ndarray
    inference: np.ndarray  # bool
    ramp: np.ndarray  # bool: the trial walks the spec's ramp (its slope walked: :func:`walked`)
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
            out[change.field][b, change.trial :] = change.value
    out["inference"], out["ramp"] = out["inference"] > 0.5, out["ramp"] > 0.5
    out["mass_scale"], out["latency_ticks"] = np.ones((len(labels), n)), np.full((len(labels), n), -1, np.int64)
    out["noise_scale"] = np.full((len(labels), n), -1.0)
    if spec.randomize is not None:
        out.update(randomized(spec.randomize, len(labels), n))
    return Conditions(**out)


def walked(planned: Conditions, ramp: Ramp | None, distance_m, fell, trial: protocol.TrialConfig) -> Conditions:
    """The conditions the trials walk: ``planned`` with each trial on the ramp (``planned.ramp``) at the ramp's slope
    of the distance its instance has climbed since it reached the ramp, given the trials done so far (docs/decisions.md
    §4). A trial climbs its forward distance, the steady phase's (what the record measures) scaled to the whole trial;
    sliding back lowers it, never below the bottom; a fall puts the instance back at the bottom. A trial's slope
    depends only on the trials before it, so ``k`` trials done give the slopes of trials 0 … k.

    Args:
      planned: the study's conditions (:func:`conditions`), each (B, num_trials).
      ramp: the study's ramp (None: no trial is on it).
      distance_m: (k, B) each done trial's steady-phase forward distance [m] (``TrialRecord.distance_m``).
      fell: (k, B) each done trial's fall flag (> 0: it fell).
      trial: the trials' timing, whose whole length over the steady phase's scales the distance.

    Returns:
      ``planned`` with the slopes of the ramp's trials 0 … k walked; the later trials' slopes are the planned ones.
    """
    done = len(distance_m)
    if ramp is None or not planned.ramp[:, : done + 1].any():
        return planned
    scale = (trial.transition_steps + trial.steady_steps) / trial.steady_steps
    slope_deg = np.array(planned.slope_deg, copy=True)
    climbed = np.zeros(slope_deg.shape[0])
    for t in range(min(done + 1, slope_deg.shape[1])):
        on = planned.ramp[:, t]
        slope_deg[:, t] = np.where(on, ramp.slope_deg(climbed), slope_deg[:, t])
        if t < done:
            moved = np.maximum(climbed + scale * np.asarray(distance_m[t], np.float64), 0.0)
            climbed = np.where(on & ~(np.asarray(fell[t]) > 0), moved, 0.0)
    return planned._replace(slope_deg=slope_deg)


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
    if spec.max_trials is not None and (
        not isinstance(spec.max_trials, int) or not spec.num_trials <= spec.max_trials <= limits.MAX_TRIALS
    ):
        fail(
            f"max_trials = {spec.max_trials!r}; need an integer in [num_trials = {spec.num_trials}, "
            f"{limits.MAX_TRIALS}]"
        )
    for axis in (
        "controllers",
        "gaits",
        "seeds",
        "friction",
        "slope_deg",
        "payload_kg",
        "target_velocity_mps",
        "schedules",
        "data_reuse",
        "physics",
        "terrain_amplitude_m",
        "terrain_seed",
        "foot_friction",
    ):
        values = spec.axis(axis)
        if len(values) == 0:
            fail(f"grid axis {axis} is empty")
        if len(set(values)) != len(values):
            fail(f"grid axis {axis} has duplicates: {values}")
    for c in spec.controllers:
        if c not in cpg.CONTROLLERS:
            fail(f"unknown controller {c!r}; allowed: {cpg.CONTROLLERS}")
    for g in spec.axis("gaits"):
        if g not in cpg.GAITS:
            fail(f"unknown gait {g!r}; allowed: {', '.join(cpg.GAITS)}")
    if spec.startup is not None and spec.startup not in cpg.STARTUPS:
        fail(f"unknown startup {spec.startup!r}; allowed: {', '.join(cpg.STARTUPS)}")
    for key, value in spec.switch_values()._asdict().items():
        allowed = SWITCH_VALUES[key]
        if isinstance(allowed, limits.Range):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not allowed.contains(value):
                fail(f"switch {key} = {value!r}; allowed: a number in {allowed} ({allowed.reason})")
        elif value not in allowed:
            fail(f"switch {key} = {value!r}; allowed: {', '.join(allowed)}")
    for name in spec.physics:
        if name not in physics_profiles.PROFILES:
            fail(f"unknown physics profile {name!r}; allowed: {tuple(physics_profiles.PROFILES)}")
    ranges = {physics_profiles.get(name).context_load_range_n for name in spec.physics}
    if spec.optimizer is None and len(ranges) > 1:
        fail(
            f"physics profiles {spec.physics} normalize c_load over different ranges {sorted(ranges)}; run them as "
            f"separate studies or give an optimizer config"
        )
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
    for field, allowed in (
        ("friction", limits.FRICTION),
        ("slope_deg", limits.SLOPE_DEG),
        ("payload_kg", limits.PAYLOAD_KG),
        ("target_velocity_mps", limits.TARGET_VELOCITY_MPS),
    ):
        values = np.asarray(getattr(cond, field), np.float64)
        bad = ~np.vectorize(allowed.contains)(values)
        if bad.any():
            b, t = np.argwhere(bad)[0]
            try:
                allowed.check(values[b, t], field)
            except ValueError as err:
                fail(f"instance {b}, trial {t}: {err}")
    labels = instances(spec)
    terrain = terrains.ground_fields(map(ground, labels))
    physics, feet = ([lab[k] for lab in labels] for k in ("physics", "foot_friction"))
    try:
        for t in range(spec.num_trials):
            go1_model.make_scenarios(
                cond.friction[:, t],
                cond.slope_deg[:, t],
                cond.payload_kg[:, t],
                physics,
                mass_scale=cond.mass_scale[:, t],
                latency_ticks=cond.latency_ticks[:, t],
                noise_scale=cond.noise_scale[:, t],
                foot_friction=feet,
                **terrain,
            )
    except ValueError as err:
        fail(f"trial {t}: {err}")
    return cond


# ----------------------------------------------------------------------------------------------- study files
#
# A study file (TOML, docs/studies.md) states a StudySpec and what its report needs beyond it. Every key is read by
# one function below, which names the file and the key's path (``grid.friction[2]``) in its refusal; the defaults
# are StudySpec's own.

GRID_AXES = {  # a study file's [grid] key → (StudySpec field, element kind, allowed values)
    "controllers": ("controllers", "str", cpg.CONTROLLERS),
    "gaits": ("gaits", "str", tuple(cpg.GAITS)),
    "friction": ("friction", "float", limits.FRICTION),
    "slope_deg": ("slope_deg", "float", limits.SLOPE_DEG),
    "payload_kg": ("payload_kg", "float", limits.PAYLOAD_KG),
    "target_velocity_mps": ("target_velocity_mps", "float", limits.TARGET_VELOCITY_MPS),
    "physics": ("physics", "str", tuple(physics_profiles.PROFILES)),
    "data_reuse": ("data_reuse", "bool", (True, False)),
    "terrain_amplitude_m": ("terrain_amplitude_m", "float", limits.ROUGHNESS_M),
    "terrain_seed": ("terrain_seed", "int", limits.TERRAIN_SEEDS),
    "foot_friction": ("foot_friction", "float", limits.FRICTION),
}
SCHEDULE_RANGES = {
    "friction": limits.FRICTION,
    "slope_deg": limits.SLOPE_DEG,
    "payload_kg": limits.PAYLOAD_KG,
    "target_velocity_mps": limits.TARGET_VELOCITY_MPS,
}  # inference and ramp: true or false
TOP_KEYS = (
    "name",
    "description",
    "report",
    "trials",
    "max_trials",
    "seeds",
    "group_by",
    "safe",
    "startup",
    "switches",
    "comparisons",
    "grid",
    "schedules",
    "ramp",
    "randomize",
    "trial",
    "quick",
    "paper",
    "transfer",
)
QUICK_KEYS = ("trials", "seeds", "max_trials", "schedules")
STUDY_FILE_SUFFIX = ".toml"
WORD = r"[A-Za-z0-9._-]+"  # a schedule's name: it becomes part of file names


class Contrast(NamedTuple):
    """A comparison a study's report makes: the groups whose ``axis`` label is ``a`` against those where it is
    ``b``, in each combination of the other ``group_by`` labels."""

    axis: str
    a: Any
    b: Any


class Arm(NamedTuple):
    """One arm of a study whose report runs several engine runs (the transfer study): its own folder ``name``, its
    physics profile, and whether its trials draw their physics (the file's ``[randomize]`` ranges)."""

    name: str
    physics: str
    randomized: bool


class StudyFile(NamedTuple):
    """A study file, read: the study it defines and what the file says beyond it."""

    spec: StudySpec
    path: Any  # pathlib.Path of the file
    source: str  # the file as written
    description: str
    report: str  # the name of a hand-written report (cpgjax.studies.registry.REPORTS); "" for the generic one
    contrasts: tuple[Contrast, ...]  # the comparisons to report; () for every pair of groups differing in one label
    paper: dict  # the paper's reference figures ([paper]), for the report to set beside ours
    arms: tuple[Arm, ...]  # [transfer] arms; () for a study of one engine run

    def metadata(self) -> dict:
        """What a run's ``metadata.json`` records of its study file: the path and the text as it was run."""
        return {"study_file": str(self.path), "study_file_text": self.source}


def scaled_trial(trial: int, written: int, run: int) -> int:
    """A schedule's change trial, written for a run of ``written`` trials, in a run of ``run`` trials."""
    return int(round(trial * run / written))


class _Reader:
    """Reads one study file's values, each by its key path, refusing the first bad one with the file and path."""

    def __init__(self, path):
        self.path = path

    def fail(self, key: str, message: str):
        raise StudyError(f"{self.path}: {key}: {message}")

    def table(self, value, key: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> dict:
        if not isinstance(value, dict):
            self.fail(key, f"need a table, got {_kind(value)}")
        for k in value:
            if k not in allowed:
                close = difflib.get_close_matches(k, allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                where = f"{key}.{k}" if key else k
                raise StudyError(
                    f"{self.path}: unknown key {where!r}{hint}; allowed{' in ' + key if key else ''}: "
                    f"{', '.join(allowed)}"
                )
        for k in required:
            if k not in value:
                self.fail(f"{key}.{k}" if key else k, "missing (required)")
        return value

    def integer(self, value, key: str, low: int = 0, high: int | None = None, reason: str = "") -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, f"need an integer, got {_kind(value)} {value!r}")
        if value < low or (high is not None and value > high):
            bounds = f"in [{low}, {high}]" if high is not None else f">= {low}"
            self.fail(
                key,
                f"{value} is outside the allowed range: need an integer {bounds}" + (f" ({reason})" if reason else ""),
            )
        return value

    def number(self, value, key: str, allowed: limits.Range | None = None) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(key, f"need a number, got {_kind(value)} {value!r}")
        if allowed is not None:
            try:
                allowed.check(value, key)
            except ValueError as err:
                raise StudyError(f"{self.path}: {err}") from None
        elif not np.isfinite(value):
            self.fail(key, f"{value!r}: need a finite number")
        return float(value)

    def boolean(self, value, key: str) -> bool:
        if not isinstance(value, bool):
            self.fail(key, f"need true or false, got {_kind(value)} {value!r}")
        return value

    def string(self, value, key: str, allowed: tuple[str, ...] | None = None, pattern: str | None = None) -> str:
        if not isinstance(value, str):
            self.fail(key, f"need a string, got {_kind(value)} {value!r}")
        if allowed is not None and value not in allowed:
            self.fail(key, f"{value!r} is not allowed; allowed: {', '.join(map(str, allowed))}")
        if pattern is not None and not re.fullmatch(pattern, value):
            self.fail(key, f"{value!r}: need a word of letters, digits, '.', '-' and '_' (it names files)")
        return value

    def array(self, value, key: str, allow_scalar: bool = False) -> list:
        if allow_scalar and not isinstance(value, (list, dict)):
            return [value]
        if not isinstance(value, list):
            self.fail(key, f"need a list, got {_kind(value)} {value!r}")
        return value

    def element(self, value, key: str, kind: str, allowed):
        if kind == "float":
            return self.number(value, key, allowed)
        if kind == "int":
            return self.integer(value, key, 0, allowed - 1)
        if kind == "bool":
            return self.boolean(value, key)
        return self.string(value, key, allowed)

    def axis(self, value, key: str, kind: str, allowed) -> tuple:
        values = [self.element(v, f"{key}[{i}]", kind, allowed) for i, v in enumerate(self.array(value, key, True))]
        if not values:
            self.fail(key, "empty; an axis needs at least one value")
        for i, v in enumerate(values):
            if v in values[:i]:
                self.fail(f"{key}[{i}]", f"{v!r} is already in the axis at [{values.index(v)}]")
        return tuple(values)

    def seeds(self, value, key: str) -> tuple[int, ...]:
        if isinstance(value, list):
            seeds = tuple(self.integer(v, f"{key}[{i}]", 0) for i, v in enumerate(value))
            if not seeds:
                self.fail(key, "empty; need at least one seed")
            if len(set(seeds)) != len(seeds):
                self.fail(key, f"duplicate seeds in {list(seeds)}")
            return seeds
        return tuple(range(self.integer(value, key, 1, limits.MAX_SEEDS, limits.MAX_SEEDS_REASON)))

    def fields(self, entry: dict, key: str) -> list[tuple[str, float]]:
        """A change's or phase's condition values, in the file's order: (field, value) with inference and ramp as
        1.0 / 0.0."""
        out = []
        for field, value in entry.items():
            if field in SCHEDULE_RANGES:
                out.append((field, self.number(value, f"{key}.{field}", SCHEDULE_RANGES[field])))
            elif field in ("inference", "ramp"):
                out.append((field, 1.0 if self.boolean(value, f"{key}.{field}") else 0.0))
        return out

    def schedule(self, value, key: str, written: int, run: int) -> Schedule:
        """One [[schedules]] entry, its change trials scaled from a run of ``written`` trials to one of ``run``."""
        entry = self.table(value, key, ("name", "label", "changes", "phases"), ("name",))
        name = self.string(entry["name"], f"{key}.name", pattern=WORD)
        label = self.string(entry.get("label", name), f"{key}.label")
        if ("changes" in entry) == ("phases" in entry):
            self.fail(key, "give either changes (by trial number) or phases (named stretches of given lengths)")
        changes = []
        if "changes" in entry:
            for i, change in enumerate(self.array(entry["changes"], f"{key}.changes")):
                where = f"{key}.changes[{i}]"
                change = self.table(change, where, ("trial", *SCHEDULE_FIELDS), ("trial",))
                trial = self.integer(
                    change["trial"],
                    f"{where}.trial",
                    0,
                    written - 1,
                    f"the trials are numbered 0 … {written - 1}, trials = {written}",
                )
                values = self.fields(change, where)
                if not values:
                    self.fail(where, f"changes nothing; give one of {', '.join(SCHEDULE_FIELDS)}")
                changes += [Change(scaled_trial(trial, written, run), f, v) for f, v in values]
        else:
            phases = self.array(entry["phases"], f"{key}.phases")
            lengths, fixed, values = [], [], []
            for i, phase in enumerate(phases):
                where = f"{key}.phases[{i}]"
                phase = self.table(phase, where, ("name", "trials", "fixed", *SCHEDULE_FIELDS), ("trials",))
                if "name" in phase:
                    self.string(phase["name"], f"{where}.name")
                lengths.append(self.integer(phase["trials"], f"{where}.trials", 1, limits.MAX_TRIALS))
                fixed.append(self.boolean(phase.get("fixed", False), f"{where}.fixed"))
                values.append(self.fields(phase, where))
            if not phases:
                self.fail(f"{key}.phases", "empty; need at least one phase")
            if sum(lengths) != written:
                self.fail(f"{key}.phases", f"the phases' trials add up to {sum(lengths)}, the study has {written}")
            for start, v in zip(_phase_starts(lengths, fixed, run, self, key), values, strict=True):
                changes += [Change(start, f, x) for f, x in v]
        return Schedule(label, tuple(changes), name)

    def schedules(self, value, key: str, written: int, run: int) -> tuple[Schedule, ...]:
        entries = self.array(value, key)
        if not entries:
            self.fail(key, "empty; leave the key out for one constant schedule")
        out = tuple(self.schedule(e, f"{key}[{i}]", written, run) for i, e in enumerate(entries))
        for i, s in enumerate(out):
            for j, other in enumerate(out[:i]):
                if s.name == other.name or s.label == other.label:
                    self.fail(f"{key}[{i}]", f"name or label the same as {key}[{j}]'s; each schedule is a group")
        return out


def _phase_starts(lengths: list[int], fixed: list[bool], run: int, reader: _Reader, key: str) -> list[int]:
    """The first trial of each phase in a run of ``run`` trials: fixed phases keep their lengths, the others share
    the rest in proportion to theirs (``scaled_trial`` of their running total)."""
    fixed_total = sum(n for n, f in zip(lengths, fixed, strict=True) if f)
    scaled_total, left = sum(lengths) - fixed_total, run - fixed_total
    if (scaled_total == 0 and left != 0) or (scaled_total > 0 and left < sum(not f for f in fixed)):
        reader.fail(
            f"{key}.phases",
            f"a run of {run} trials: the fixed phases hold {fixed_total} trials and each "
            f"other phase needs at least one",
        )
    starts, fixed_before, scaled_before = [], 0, 0
    for n, f in zip(lengths, fixed, strict=True):
        starts.append(fixed_before + (scaled_trial(scaled_before, scaled_total, left) if scaled_total else 0))
        fixed_before, scaled_before = fixed_before + (n if f else 0), scaled_before + (0 if f else n)
    for i in range(1, len(starts)):
        if starts[i] <= starts[i - 1]:
            reader.fail(f"{key}.phases[{i - 1}]", f"empty in a run of {run} trials")
    return starts


def _kind(value) -> str:
    return {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "a table",
    }.get(type(value), type(value).__name__)


def read(
    path,
    *,
    quick: bool = False,
    seeds: int | None = None,
    trials: int | None = None,
    physics: str | None = None,
    safe: bool = False,
    max_trials: int | None = None,
    startup: str | None = None,
    gaits: tuple[str, ...] | None = None,
) -> StudyFile:
    """Read and check the study file ``path`` with the command line's overrides (each as ``cpgjax study``'s
    option: ``quick`` the file's [quick] values, ``seeds`` seeds 0 … n − 1, ``trials`` the run's length with every
    change trial scaled to it, ``physics`` one profile for every instance, ``safe``, ``max_trials``, ``startup``,
    ``gaits`` the grid's gaits axis).

    Raises:
      StudyError: the message names the file, the key's path and what is allowed; before any compute.
    """
    path = pathlib.Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise StudyError(f"{path}: cannot read the study file ({err})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise StudyError(f"{path}: not valid TOML ({err})") from None
    r = _Reader(path)
    r.table(data, "", TOP_KEYS, ("name",))
    quick_table = r.table(data["quick"], "quick", QUICK_KEYS) if "quick" in data else {}
    level = {**data, **quick_table} if quick else data

    def at(key: str) -> str:  # a key's path where this run reads it
        return f"quick.{key}" if quick and key in quick_table else key

    name = r.string(data["name"], "name", pattern=WORD)
    default = StudySpec(name)
    length = {
        k: r.integer(t.get("trials", default.num_trials), f"{k}trials", 1, limits.MAX_TRIALS, limits.MAX_TRIALS_REASON)
        for k, t in (("", data), ("quick.", quick_table))
    }
    run = length["quick." if quick and "trials" in quick_table else ""] if trials is None else trials
    # a schedule's trial numbers are those of a run of the trials beside it
    written = length["quick." if quick and {"schedules", "trials"} <= set(quick_table) else ""]
    fields: dict[str, Any] = {"num_trials": run}
    grid = r.table(data.get("grid", {}), "grid", tuple(GRID_AXES))
    for key, (field, kind, allowed) in GRID_AXES.items():
        if key in grid:
            fields[field] = r.axis(grid[key], f"grid.{key}", kind, allowed)
    if seeds is not None:
        fields["seeds"] = tuple(range(seeds))
    elif "seeds" in level:
        fields["seeds"] = r.seeds(level["seeds"], at("seeds"))
    if "schedules" in level:
        fields["schedules"] = r.schedules(level["schedules"], at("schedules"), written, run)
    if "max_trials" in level:
        fields["max_trials"] = r.integer(
            level["max_trials"], at("max_trials"), 1, limits.MAX_TRIALS, limits.MAX_TRIALS_REASON
        )
    if max_trials is not None:
        if max_trials < run:
            raise StudyError(f"--max-trials {max_trials}: need at least the run's {run} trials")
        fields["max_trials"] = max_trials
    if "group_by" in data:
        fields["group_by"] = tuple(
            r.string(g, f"group_by[{i}]", LABELS) for i, g in enumerate(r.array(data["group_by"], "group_by", True))
        )
        if not fields["group_by"]:
            r.fail("group_by", f"empty; name one or more of {', '.join(LABELS)}")
    fields["safe"] = safe or r.boolean(data.get("safe", False), "safe")
    chosen = startup_field(
        startup or (r.string(data["startup"], "startup", tuple(cpg.STARTUPS)) if "startup" in data else None)
    )
    if chosen is not None:
        fields["startup"] = chosen
    if "switches" in data:
        switches = r.table(data["switches"], "switches", Switches._fields, ())

        def switch(key, value):
            allowed = SWITCH_VALUES[key]
            return (
                r.number(value, f"switches.{key}", allowed)
                if isinstance(allowed, limits.Range)
                else r.string(value, f"switches.{key}", allowed)
            )

        fields["switches"] = Switches(**{key: switch(key, value) for key, value in switches.items()})
    if "ramp" in data:
        ramp = r.table(data["ramp"], "ramp", Ramp._fields, Ramp._fields)
        fields["ramp"] = Ramp(
            r.number(ramp["start_deg"], "ramp.start_deg", limits.SLOPE_DEG),
            r.number(ramp["end_deg"], "ramp.end_deg", limits.SLOPE_DEG),
            r.number(ramp["length_m"], "ramp.length_m", _RAMP_LENGTH_M),
        )
    if "randomize" in data:
        fields["randomize"] = _randomization(r, data["randomize"])
    if "trial" in data:
        timing = r.table(data["trial"], "trial", ("transition_s", "steady_s"))
        base = default.trial
        fields["trial"] = base._replace(
            **{
                f"{k}_steps": int(round(r.number(timing[f"{k}_s"], f"trial.{k}_s", allowed) / TICK_S))
                for k, allowed in (("transition", limits.TRANSITION_S), ("steady", limits.STEADY_S))
                if f"{k}_s" in timing
            }
        )
    if physics is not None:
        fields["physics"] = (physics,)
    if gaits is not None:
        fields["gaits"] = tuple(gaits)
    spec = StudySpec(name, **fields)
    contrasts = _contrasts(r, data.get("comparisons", []), spec)
    arms = ()
    if "transfer" in data:
        transfer = r.table(data["transfer"], "transfer", ("arms",), ("arms",))
        arms = tuple(
            _arm(r, a, f"transfer.arms[{i}]") for i, a in enumerate(r.array(transfer["arms"], "transfer.arms"))
        )
        if not arms:
            r.fail("transfer.arms", "empty; need at least one arm")
    paper = r.table(data.get("paper", {}), "paper", tuple(data.get("paper", {})))
    try:
        validate(spec)
    except StudyError as err:
        raise StudyError(f"{path}: {err}") from None
    return StudyFile(
        spec,
        path,
        text,
        r.string(data.get("description", ""), "description"),
        r.string(data.get("report", ""), "report"),
        contrasts,
        paper,
        arms,
    )


def load(path, **overrides) -> StudySpec:
    """The study the file ``path`` defines (:func:`read`, with the same overrides)."""
    return read(path, **overrides).spec


_RAMP_LENGTH_M = limits.Range(0.0, 1000.0, "the ramp's length of climb", low_open=True)


def _randomization(r: _Reader, value) -> Randomization:
    table = r.table(value, "randomize", Randomization._fields)
    out = {}
    for field in ("friction", "payload_kg", "mass_scale", "noise_scale", "latency_ticks"):
        if field not in table:
            continue
        key = f"randomize.{field}"
        pair = r.array(table[field], key)
        if len(pair) != 2:
            r.fail(key, f"need [low, high], got {pair!r}")
        if field == "latency_ticks":
            low, high = (r.integer(v, f"{key}[{i}]", 0, 100, "ticks of 1 ms") for i, v in enumerate(pair))
        else:
            allowed = {"friction": limits.FRICTION, "payload_kg": limits.PAYLOAD_KG}.get(field, _SCALE)
            low, high = (r.number(v, f"{key}[{i}]", allowed) for i, v in enumerate(pair))
        if low > high:
            r.fail(key, f"[{low}, {high}]: need low <= high")
        out[field] = (low, high)
    if "seed" in table:
        out["seed"] = r.integer(table["seed"], "randomize.seed", 0)
    return Randomization(**out)


_SCALE = limits.Range(0.0, 10.0, "a multiple of the model's own value")


def _contrasts(r: _Reader, value, spec: StudySpec) -> tuple[Contrast, ...]:
    values_of = label_values(spec)
    schedule_names = {s.name: s.label for s in spec.schedules if s.name}
    out = []
    for i, entry in enumerate(r.array(value, "comparisons")):
        key = f"comparisons[{i}]"
        entry = r.table(entry, key, Contrast._fields, Contrast._fields)
        axis = r.string(entry["axis"], f"{key}.axis", spec.group_by)
        allowed = tuple(values_of[axis])
        pair = []
        for side in ("a", "b"):
            v = schedule_names.get(entry[side], entry[side]) if axis == "schedule" else entry[side]
            match = [x for x in allowed if x == v and type(x) is not bool or x is v]
            if not match:
                r.fail(
                    f"{key}.{side}",
                    f"{v!r} is not a value of the study's {axis} axis; allowed: {', '.join(map(str, allowed))}",
                )
            pair.append(match[0])
        if pair[0] == pair[1]:
            r.fail(key, "a and b are the same group")
        out.append(Contrast(axis, *pair))
    return tuple(out)


def _arm(r: _Reader, value, key: str) -> Arm:
    arm = r.table(value, key, ("name", "physics", "randomize"), ("name", "physics"))
    return Arm(
        r.string(arm["name"], f"{key}.name", pattern=WORD),
        r.string(arm["physics"], f"{key}.physics", tuple(physics_profiles.PROFILES)),
        r.boolean(arm.get("randomize", False), f"{key}.randomize"),
    )


def template() -> str:
    """A study file of every key with its default, unit and allowed range, as comments beside the values a new
    study starts from (``cpgjax study --template PATH``); it runs as written."""
    d, r = StudySpec("my_study"), Randomization()
    # the axes a study may leave unset keep the trial table of the trot on the flat plane: left as comments
    grid = "\n".join(
        f"# {key}: {kind}s in {_allowed_text(allowed)}; default {list(d.axis(field))}\n"
        f"{'# ' if field in UNSET_AXES else ''}{key} = {_toml(list(d.axis(field)))}"
        for key, (field, kind, allowed) in GRID_AXES.items()
    )
    fields = ", ".join(SCHEDULE_RANGES)
    ranges = "; ".join(f"{k} in {v}" for k, v in SCHEDULE_RANGES.items())
    timing = f"{d.trial.transition_steps * TICK_S:g} s of transition, {d.trial.steady_steps * TICK_S:g} s measured"
    return f'''# A cpgjax study file (docs/studies.md): `cpgjax study THIS_FILE.toml`. Every key but `name` may be left
# out; each comment gives the key's default, unit and allowed range. An instance is one element of the product of the
# [grid] axes × the seeds × the schedules; each instance optimizes its gait online, trial by trial.

name = "my_study"  # a word (letters, digits, . - _): the output folder results/<name>/ and the metadata
description = ""  # one line on what the study asks
trials = {d.num_trials}  # trials per run (each {timing}); in [1, {limits.MAX_TRIALS}]
seeds = 5  # seeds 0 … N-1 per group, or a list such as [0, 3, 7]; default {list(d.seeds)}; at most {limits.MAX_SEEDS}
# max_trials = 80  # the trials the run can later be extended to (--resume --trials N); default: trials
group_by = {_toml(list(d.group_by))}  # labels whose combinations are the report's groups: {", ".join(LABELS)}
safe = false  # safe optimization: proposals only where a second GP certifies the safety margin >= 0
startup = "{cpg.DEFAULT_STARTUP}"  # how the robot starts standing (trial 0, after a fall): {", ".join(cpg.STARTUPS)}
# report = ""  # a hand-written report of the paper's studies; left out: the generic report of any study

# The readings the paper leaves open (docs/decisions.md §1, §2, §7, §10); set one to run a one-change study of it.
# [switches]
# amplitude_form = "paper"  # eq. (1): "paper" (r → μ) or "sqrt" (r → √μ, the lab's public code)
# ucb_form = "paper"  # eq. (8): "paper" (m + β·σ) or "botorch" (m + √β·σ)
# vmc_gate = "loaded"  # VMC on stance legs: "loaded" (stance phase and foot force > 10 N) or "phase" (phase alone)
# objective_floor = -1.0  # J's lower bound and the J of a fall; in [-20, -0.5]

# The comparisons the report makes (default: every pair of groups that differ in one label): the groups whose `axis`
# label is `a` against those where it is `b`, in each combination of the other group_by labels.
# comparisons = [{{ axis = "controller", a = "tegotae", b = "open_loop" }}]

[grid]
{grid}

# Schedules of condition changes, one group each (a grid axis; default: one constant schedule). Each has a `name`
# (a word: it names the group's files) and a `label` (the trial table's and the report's, default the name), and
# either `changes` by trial number (numbered from 0) or `phases` of given lengths that add up to `trials`. A
# change or phase sets any of {fields} ({ranges}), inference (true: β = 1e-6, no exploration) and ramp (true:
# walk the [ramp]). A run of another length (--trials) scales the trial numbers; a phase with fixed = true keeps its
# length and the others share the rest.
#
# [[schedules]]
# name = "load"
# label = "0→10 kg"
# changes = [{{ trial = 20, payload_kg = 10.0 }}]
#
# [[schedules]]
# name = "slope_then_inference"
# phases = [
#   {{ name = "learn flat", trials = 30 }},
#   {{ name = "learn 10°", trials = 5, slope_deg = 10.0 }},
#   {{ name = "inference 10°", trials = 5, fixed = true, inference = true }},
# ]

# The continuous ramp that trials with ramp = true walk: from start_deg to end_deg over length_m of climb.
# [ramp]
# start_deg = 10.0  # [deg], in {limits.SLOPE_DEG}
# end_deg = 17.5  # [deg], in {limits.SLOPE_DEG}
# length_m = 12.0  # [m], in {_RAMP_LENGTH_M}

# Domain randomization: every trial draws its physics uniformly from [low, high] (the table's presence turns it on).
# [randomize]
# friction = {list(r.friction)}  # in {limits.FRICTION}
# payload_kg = {list(r.payload_kg)}  # [kg], in {limits.PAYLOAD_KG}
# mass_scale = {list(r.mass_scale)}  # the links' masses × this, in {_SCALE}
# latency_ticks = {list(r.latency_ticks)}  # actuation latency [1 ms ticks], integers, both ends included
# noise_scale = {list(r.noise_scale)}  # sensor noise × the robot's, in {_SCALE}
# seed = {r.seed}  # the draws' seed

# Trial timing (the paper's: 1.5 s of transition, 3 s measured).
# [trial]
# transition_s = {d.trial.transition_steps * TICK_S:g}  # [s], in {limits.TRANSITION_S}
# steady_s = {d.trial.steady_steps * TICK_S:g}  # [s], in {limits.STEADY_S}

# What --quick runs instead: trials, seeds, max_trials and schedules.
[quick]
trials = 12
seeds = 2

# The paper's figures to set beside ours, as the report lists them (any keys).
# [paper]
# J = "2.17 ± 0.07 (VMC+Tegotae, 5 seeds)"
'''


def _allowed_text(allowed) -> str:
    if isinstance(allowed, int):  # an integer axis: 0 … allowed − 1
        return f"0 … {allowed - 1}"
    return str(allowed) if isinstance(allowed, limits.Range) else ", ".join(map(_toml, allowed))


def _toml(value) -> str:
    """A value in TOML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return f"{value!r}"
