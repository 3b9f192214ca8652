"""How a study runs, as typed options: :class:`StudyOptions` for a study file or a paper study (``cpgjax study``,
``cpgjax demo``, ``cpgjax.studies.driver.run_file``) and :class:`OptimizeOptions` for one online optimization
(``cpgjax optimize``). Each checks its rules once, on construction, before anything is read or computed, and raises
``StudyError`` with one line naming the option, its value and what is allowed (docs/cli.md, "Inputs and their
ranges"); the command line turns its arguments into one of them and makes one call.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from collections.abc import Callable
from typing import Any

from cpgjax import cpg
from cpgjax.go1 import physics as physics_profiles
from cpgjax.study import spec as study_spec
from cpgjax.trial import limits, tuned


def _count(
    value: int | None,
    option: str,
    minimum: int,
    reason: str = "",
    maximum: int = limits.MAX_TRIALS,
    maximum_reason: str = limits.MAX_TRIALS_REASON,
) -> None:
    if value is None:
        return
    try:
        limits.check_count(value, option, minimum, reason, maximum, maximum_reason)
    except ValueError as err:
        raise study_spec.StudyError(str(err)) from None


def _trials(trials: int | None, max_trials: int | None, minimum: int, reason: str = "") -> None:
    """``trials`` and ``max_trials`` each in ``minimum`` … ``limits.MAX_TRIALS``."""
    _count(trials, "--trials", minimum, reason)
    _count(max_trials, "--max-trials", minimum, reason)


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """Where and how a run goes: its folder, resume or overwrite, the backend, a dry run, the command line recorded
    in ``metadata.json``, and what the driver calls back (``progress`` after every trial, ``notify`` with a line).

    Raises:
      StudyError: ``resume`` with ``overwrite``.
    """

    out: pathlib.Path | None = None  # None: results/<study>
    resume: bool = False
    overwrite: bool = False
    backend: str = "auto"  # cpgjax.sim.backends.BACKENDS
    dry_run: bool = False
    command: str | None = None
    progress: Callable[[Any], None] | None = None
    notify: Callable[[str], None] | None = None

    def __post_init__(self):
        if self.resume and self.overwrite:
            raise study_spec.StudyError(
                "--resume and --overwrite exclude each other (resume keeps the folder's trials, overwrite removes them)"
            )


@dataclasses.dataclass(frozen=True)
class StudyOptions(RunOptions):
    """A study file's run: what replaces the file's values (``cpgjax.study.spec.read``'s overrides: the [quick]
    table, seeds 0 … ``seeds`` − 1, ``trials``, ``max_trials``, ``physics``, ``safe``, ``startup``, ``gaits``), how
    many local processes cooperate (``processes``, or ``distributed``: one of several started elsewhere), and the
    run options.

    Raises:
      StudyError: a count out of its range (seeds 1 … ``limits.MAX_SEEDS``, trials and max_trials
        ``limits.MIN_STUDY_TRIALS`` … ``limits.MAX_TRIALS``; the study file's reader checks max_trials against the
        run's trials), ``processes`` beyond this machine's CPUs or with ``distributed``, and :class:`RunOptions`'
        rules.
    """

    quick: bool = False
    seeds: int | None = None
    trials: int | None = None
    max_trials: int | None = None
    physics: str | None = None
    safe: bool = False
    startup: str | None = None
    gaits: tuple[str, ...] | None = None
    processes: int | None = None
    distributed: bool = False

    def __post_init__(self):
        super().__post_init__()
        _count(self.seeds, "--seeds", 1, maximum=limits.MAX_SEEDS, maximum_reason=limits.MAX_SEEDS_REASON)
        _trials(self.trials, self.max_trials, limits.MIN_STUDY_TRIALS, limits.MIN_STUDY_TRIALS_REASON)
        if self.processes is not None:
            cpus = os.cpu_count() or 1
            if not 1 <= self.processes <= cpus:
                raise study_spec.StudyError(
                    f"--processes {self.processes} is outside the allowed range 1 … {cpus} (local processes, at most "
                    "one per CPU of this machine; a cluster starts its processes itself: --distributed)"
                )
            if self.distributed:
                raise study_spec.StudyError(
                    "--processes and --distributed exclude each other (--processes starts --distributed processes)"
                )

    def overrides(self) -> dict[str, Any]:
        """The keyword arguments of ``cpgjax.study.spec.read`` these options give."""
        return dict(
            quick=self.quick,
            seeds=self.seeds,
            trials=self.trials,
            physics=self.physics,
            safe=self.safe,
            max_trials=self.max_trials,
            startup=self.startup,
            gaits=self.gaits,
        )


@dataclasses.dataclass(frozen=True)
class OptimizeOptions(RunOptions):
    """One online optimization (Algorithm 1) of one controller and gait, under one scenario and target, with one
    optimizer seed: a study of one instance (:meth:`spec`), and the run options.

    Raises:
      StudyError: trials or max_trials outside ``limits.MIN_TRIALS`` … ``limits.MAX_TRIALS``, ``max_trials`` below
        ``trials``, and :class:`RunOptions`' rules (the names and the scenario's values are checked with the study,
        ``cpgjax.study.spec.validate``).
    """

    controller: str = "vmc_tegotae"
    gait: str = cpg.DEFAULT_GAIT
    seed: int = 0
    trials: int = 40
    max_trials: int | None = None
    friction: float = 0.6
    slope_deg: float = 0.0
    payload_kg: float = 0.0
    target_velocity_mps: float = 0.5
    foot_friction: float | None = None
    physics: str = physics_profiles.DEFAULT_PROFILE
    safe: bool = False
    startup: str = cpg.DEFAULT_STARTUP

    def __post_init__(self):
        super().__post_init__()
        _trials(self.trials, self.max_trials, limits.MIN_TRIALS)
        if self.max_trials is not None and self.max_trials < self.trials:
            raise study_spec.StudyError(f"--max-trials {self.max_trials}: need at least --trials ({self.trials})")

    def spec(self) -> study_spec.StudySpec:
        """The one-instance study of these options."""
        return study_spec.StudySpec(
            "optimize",
            num_trials=self.trials,
            controllers=(self.controller,),
            gaits=None if self.gait == cpg.DEFAULT_GAIT else (self.gait,),
            seeds=(self.seed,),
            friction=(self.friction,),
            slope_deg=(self.slope_deg,),
            payload_kg=(self.payload_kg,),
            target_velocity_mps=(self.target_velocity_mps,),
            physics=(self.physics,),
            safe=self.safe,
            max_trials=self.max_trials,
            startup=study_spec.startup_field(self.startup),
            foot_friction=None if self.foot_friction is None else (self.foot_friction,),
        )

    def tuned_for(self) -> dict[str, Any]:
        """What the run's best parameters were tuned for (``cpgjax.trial.tuned.TUNED_FOR``'s keys)."""
        return {name: getattr(self, name) for name in tuned.TUNED_FOR}
