"""The rules of ``cpgjax deploy``'s and ``cpgjax deploy calibrate``'s options (:mod:`cpgjax.deployment.options`),
each checked once on the options themselves: a rule broken refuses the options on construction, with the message
the command line shows (tests/test_cli.py checks that it shows it, with nothing sent to a robot)."""

import dataclasses
import pathlib

import numpy as np
import pytest

from cpgjax.deployment.options import GO1_ONLY, SIM_ONLY, CalibrateOptions, DeployOptions, RobotOptions
from cpgjax.robot import foot_force

# What the simulated Go1's run takes from the command line by default (tests address 127.0.0.1 only).
ROBOT = dict(
    robot="sim",
    transport=None,
    robot_ip="127.0.0.1",
    robot_port=8007,
    local_port=8082,
    power_level=9,
    sim_pacing="realtime",
    friction=0.6,
    slope_deg=0.0,
    payload_kg=0.0,
    physics="go1",
    seed=0,
    no_realtime=False,
    cpu=None,
    busy_wait=False,
    idle_halt=False,
    overwrite=False,
)
CALIBRATION = foot_force.FootForceCalibration(np.array([14.0, -6.0, 22.0, 9.0]), np.full(4, 0.5))
REPLAY = DeployOptions(
    **ROBOT,
    log_dir=None,
    calibration=None,
    params=None,
    params_path=None,
    optimize=False,
    optimizer="bo",
    trials=10,
    safe=False,
    controller="vmc_tegotae",
    gait="trot",
    startup="paper",
    target_velocity_mps=0.5,
    duration_s=10.0,
    transition_s=1.5,
    steady_s=3.0,
)
OPTIMIZE = dataclasses.replace(REPLAY, optimize=True)
GO1 = dataclasses.replace(REPLAY, robot="go1", calibration=CALIBRATION)
CALIBRATE = CalibrateOptions(
    **ROBOT, out=pathlib.Path("go1_calibration.json"), air_s=2.0, stand_s=3.0, settle_s=1.0, mass_kg=None, lift_m=0.3
)


def _refused(options, message: str, **changes) -> None:
    with pytest.raises(ValueError) as err:
        dataclasses.replace(options, **changes)
    assert str(err.value).startswith(message), err.value


def test_options_that_keep_every_rule_are_made_and_frozen():
    for options in (
        REPLAY,
        OPTIMIZE,
        GO1,
        CALIBRATE,
        dataclasses.replace(GO1, given=frozenset(GO1_ONLY)),
        dataclasses.replace(REPLAY, given=frozenset(SIM_ONLY)),
        dataclasses.replace(OPTIMIZE, safe=True, given=frozenset({"trials", "steady_s"})),
    ):
        assert options.problem() is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        REPLAY.seed = 1


def test_a_run_needs_a_robot():
    _refused(REPLAY, "the following arguments are required: --robot", robot=None)
    _refused(REPLAY, "--robot 'go2' is not one of sim, go1", robot="go2")


def test_the_go1_needs_a_calibration():
    _refused(GO1, "--robot go1 needs --calibration FILE (run `cpgjax deploy calibrate` first", calibration=None)


def test_how_to_reach_the_go1_does_not_apply_to_the_simulated_go1():
    for options in (REPLAY, CALIBRATE):
        _refused(
            options,
            "--robot-ip, --local-port apply to --robot go1 only (the simulated Go1 listens on 127.0.0.1",
            given=frozenset({"robot_ip", "local_port"}),
        )


def test_what_the_simulated_go1_simulates_does_not_apply_to_the_go1():
    _refused(GO1, "--friction, --physics apply to --robot sim only", given=frozenset({"physics", "friction"}))
    _refused(
        dataclasses.replace(CALIBRATE, robot="go1"), "--lift-m applies to --robot sim only", given=frozenset({"lift_m"})
    )


def test_an_optimizations_options_do_not_apply_to_a_replay():
    _refused(
        REPLAY,
        "--trials, --steady-s apply to --optimize only (a replay walks one set of parameters for --duration-s)",
        given=frozenset({"steady_s", "trials"}),
    )


def test_a_replays_duration_does_not_apply_to_an_optimization():
    _refused(
        OPTIMIZE,
        "--duration-s applies to a replay only (--optimize runs --trials trials)",
        given=frozenset({"duration_s"}),
    )


def test_safe_needs_an_optimization_with_the_bo():
    message = "--safe applies to --optimize with --optimizer bo only"
    _refused(REPLAY, message, safe=True)
    _refused(OPTIMIZE, message, safe=True, optimizer="random")


def test_the_safety_limits_are_checked():
    for options in (REPLAY, CALIBRATE):
        _refused(options, "safety power_level = 11 is outside the allowed range 1 … 10", power_level=11)


def test_the_calibration_is_checked():
    bad = foot_force.FootForceCalibration(np.zeros(4), np.array([0.5, 0.5, -0.5, 0.5]))
    _refused(GO1, "calibration: newton_per_count[2] = -0.5 is outside the allowed range", calibration=bad)


def test_the_first_rule_broken_is_the_one_shown():
    """No robot before what the Go1 needs, before an option that does not apply, before --safe."""
    given = frozenset({"sim_pacing", "trials"})
    _refused(GO1, "the following arguments are required: --robot", robot=None, calibration=None, given=given)
    _refused(GO1, "--robot go1 needs --calibration", calibration=None, given=given, safe=True)
    _refused(GO1, "--sim-pacing applies to --robot sim only", given=given, safe=True)


def test_robot_options_alone_keep_the_robots_rules():
    _refused(RobotOptions(**ROBOT), "--robot-port applies to --robot go1 only", given=frozenset({"robot_port"}))
