"""The typed options of ``cpgjax deploy`` (:class:`DeployOptions`) and ``cpgjax deploy calibrate``
(:class:`CalibrateOptions`), and the rules that span them, checked once on construction: which robot, the Go1's
calibration, the options that do not apply to the chosen robot or mode, and the safety limits and the foot-force
calibration the loop runs with. Each value is converted and range-checked where it is read (the command line's
types, :mod:`cpgjax.trial.limits`); :mod:`cpgjax.deployment.deploy` and :mod:`cpgjax.deployment.calibrate` read
nothing else.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import ClassVar

import numpy as np

from cpgjax.robot import foot_force
from cpgjax.robot import safety as go1_safety

ROBOTS = ("sim", "go1")
GO1_ONLY = ("robot_ip", "robot_port", "local_port")  # how to reach the Go1; the simulated Go1's are its own
SIM_ONLY = ("sim_pacing", "friction", "slope_deg", "physics")  # what only the simulated Go1 simulates


def flag(name: str) -> str:
    """The command line's option of the field ``name``: ``--robot-ip`` for ``robot_ip``."""
    return f"--{name.replace('_', '-')}"


@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotOptions:
    """Which robot, how to reach it and how the 1 kHz loop runs: what ``deploy`` and ``deploy calibrate`` share.

    Raises:
      ValueError: on construction, with the message to show: the first rule of :meth:`problem` broken, or a safety
        limit outside its range (:func:`go1_safety.check_safety`).
    """

    robot: str | None  # "sim" (the loopback simulated Go1) or "go1"; None: not chosen (refused)
    transport: str | None  # "udp" or "sdk"; None: sdk on the Go1, udp on the simulated Go1
    robot_ip: str
    robot_port: int
    local_port: int
    power_level: int  # the SDK's power protection level (trips above 100 W each)
    sim_pacing: str  # "realtime" or "lockstep"
    friction: float  # the simulated floor's Coulomb friction μ
    slope_deg: float
    payload_kg: float
    physics: str  # the simulated Go1's physics profile
    seed: int  # the optimizer's seed, and the simulated sensors' noise stream
    no_realtime: bool  # do not ask for SCHED_FIFO
    cpu: int | None  # the loop's CPU; None: deploy.loop_cpu chooses
    busy_wait: bool
    idle_halt: bool
    overwrite: bool  # write into a non-empty output folder or over an existing file
    given: frozenset[str] = frozenset()  # the fields the command line gave (the others hold defaults)

    sim_only: ClassVar[tuple[str, ...]] = SIM_ONLY

    def __post_init__(self):
        if problem := self.problem():
            raise ValueError(problem)
        go1_safety.check_safety(self.safety)

    @property
    def safety(self) -> go1_safety.SafetyConfig:
        """The loop's safety limits: the defaults at this run's power level."""
        return go1_safety.SafetyConfig(power_level=self.power_level)

    def rules(self) -> list[tuple[tuple[str, ...], bool, str]]:
        """(fields, whether giving any of them is refused, why) of each class of options that may not apply."""
        return [
            (
                GO1_ONLY,
                self.robot == "sim",
                "to --robot go1 only (the simulated Go1 listens on 127.0.0.1 on a port of its own)",
            ),
            (self.sim_only, self.robot == "go1", "to --robot sim only"),
        ]

    def missing(self) -> str | None:
        """What the chosen robot needs and the options lack; None if nothing."""
        return None

    def conflict(self) -> str | None:
        """An option that contradicts the others beyond :meth:`rules`; None if none does."""
        return None

    def problem(self) -> str | None:
        """Why this run cannot start from its options, the first rule broken in this order: no robot, what it
        needs (:meth:`missing`), a given option that does not apply to it (:meth:`rules`), a :meth:`conflict`;
        None if none is."""
        if self.robot is None:
            return "the following arguments are required: --robot"
        if self.robot not in ROBOTS:
            return f"--robot {self.robot!r} is not one of {', '.join(ROBOTS)}"
        if missing := self.missing():
            return missing
        for names, refused, why in self.rules():
            named = [flag(name) for name in names if name in self.given]
            if refused and named:
                return f"{', '.join(named)} {'applies' if len(named) == 1 else 'apply'} {why}"
        return self.conflict()


@dataclasses.dataclass(frozen=True, kw_only=True)
class DeployOptions(RobotOptions):
    """``cpgjax deploy``: a replay of parameters or an online optimization, on the robot of :class:`RobotOptions`.

    Raises:
      ValueError: on construction, as :class:`RobotOptions` does and: the Go1 without a calibration, a calibration
        outside its ranges (:func:`foot_force.check_calibration`), a replay's option with ``optimize`` or the
        reverse, ``safe`` but with the contextual BO.
    """

    log_dir: pathlib.Path | None  # the run's folder, claimed before the run; None: cpgjax.cli claims a fresh one
    calibration: foot_force.FootForceCalibration | None  # None: the simulated Go1's exact one (sim only)
    params: np.ndarray | None  # (8,) the parameters to replay, or an optimization's trial 0; None: see first_params
    params_path: str | None  # the parameter file they were read from (run.json records it)
    optimize: bool  # online optimization; False: a replay of ``params`` for ``duration_s``
    optimizer: str  # "bo" or "random"
    trials: int
    safe: bool  # the contextual BO's safe proposals
    controller: str
    gait: str
    startup: str
    target_velocity_mps: float
    duration_s: float  # a replay's run time
    transition_s: float  # each optimization trial's parameter transition
    steady_s: float  # each optimization trial's measured steady phase
    command_line: str | None = None  # what run.json records as the command

    def __post_init__(self):
        super().__post_init__()
        if self.calibration is not None:
            foot_force.check_calibration(self.calibration)

    def rules(self) -> list[tuple[tuple[str, ...], bool, str]]:
        return [
            *super().rules(),
            (
                ("trials", "optimizer", "transition_s", "steady_s"),
                not self.optimize,
                "to --optimize only (a replay walks one set of parameters for --duration-s)",
            ),
            (("duration_s",), self.optimize, "to a replay only (--optimize runs --trials trials)"),
        ]

    def missing(self) -> str | None:
        if self.robot == "go1" and self.calibration is None:
            return "--robot go1 needs --calibration FILE (run `cpgjax deploy calibrate` first, see docs/hardware.md)"
        return None

    def conflict(self) -> str | None:
        if self.safe and not (self.optimize and self.optimizer == "bo"):
            return "--safe applies to --optimize with --optimizer bo only (it constrains the contextual BO's proposals)"
        return None


@dataclasses.dataclass(frozen=True, kw_only=True)
class CalibrateOptions(RobotOptions):
    """``cpgjax deploy calibrate``: the two measuring stands on the robot of :class:`RobotOptions` and where the
    calibration goes.

    Raises:
      ValueError: on construction, as :class:`RobotOptions` does (``lift_m`` is the simulated Go1's only).
    """

    out: pathlib.Path  # the calibration JSON, each stand's per-tick log next to it (calibrate.tick_log_paths)
    air_s: float  # measuring time with the feet in the air
    stand_s: float  # measuring time standing still
    settle_s: float  # holding the pose before each measurement
    mass_kg: float | None  # the robot's total mass; None: cpgjax's Go1 model + payload_kg
    lift_m: float  # how high the simulated Go1 is hung up

    sim_only: ClassVar[tuple[str, ...]] = (*SIM_ONLY, "lift_m")
