"""The command line's checks, before anything runs: safety inputs refused before any robot is reached, no silent
overwrite, errors instead of tracebacks, one option per quantity, truthful `show`. None of these compiles a JAX
program: every refused input stops at parsing or at the output folder's check."""

import dataclasses
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import time
from typing import NamedTuple

import numpy as np
import pytest

import cpgjax
from cpgjax import ablation, cli, outputs, show
from cpgjax.deployment import calibrate, deploy, tick_log
from cpgjax.robot import foot_force, sim_server
from cpgjax.robot import safety as go1_safety
from cpgjax.sim import walk
from cpgjax.studies import driver as study_driver
from cpgjax.studies import optimize as study_optimize
from cpgjax.studies import options as study_options
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec
from cpgjax.trial import limits, tuned
from cpgjax.trial import params as param_space
from cpgjax.trial.condition import Condition

REPO = pathlib.Path(__file__).resolve().parent.parent


def _write(path: pathlib.Path, value) -> pathlib.Path:
    path.write_text(value if isinstance(value, str) else json.dumps(value))
    return path


def _refused(argv, capsys) -> str:
    """Run the command line, expecting argparse's refusal (exit 2); returns stderr."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(argv)
    assert exit_.value.code == 2
    return capsys.readouterr().err


@pytest.fixture
def no_robot(monkeypatch):
    """Fails the test if a robot connection, a simulated Go1 or a deploy run is started."""
    started = []

    def forbidden(*args, **kwargs):
        started.append(args)
        raise AssertionError("a robot connection was started")

    monkeypatch.setattr(deploy, "connect", forbidden)
    monkeypatch.setattr(sim_server, "SimGo1Client", forbidden)
    monkeypatch.setattr(deploy, "run", forbidden)
    monkeypatch.setattr(calibrate, "run", forbidden)
    return started


# ----------------------------------------------------------------------------------------------- safety inputs

GOOD_CALIBRATION = {"offset_counts": [14, -6, 22, 9], "newton_per_count": [0.5, 0.5, 0.5, 0.5]}
GOOD_PARAMS = {"params": param_space.as_dict(param_space.midpoint())}


def _bad_files(tmp_path: pathlib.Path) -> dict[str, pathlib.Path]:
    mid = param_space.as_dict(param_space.midpoint())
    return {
        "cal3": _write(tmp_path / "cal3.json", {"offset_counts": [1, 2, 3], "newton_per_count": [0.5] * 4}),
        "cal_scales": _write(
            tmp_path / "cal_scales.json", {"offset_counts": [0, 0, 0, 0], "newton_per_count": [-0.5, 0, 0.5, 1e9]}
        ),
        "cal_huge": _write(
            tmp_path / "cal_huge.json", {"offset_counts": [0, 0, 0, 0], "newton_per_count": [0.5, 0.5, 0.5, 1e9]}
        ),
        "cal_nan": _write(
            tmp_path / "cal_nan.json", '{"offset_counts": [0, 0, NaN, 0], "newton_per_count": [0.5, 0.5, 0.5, 0.5]}'
        ),
        "cal_key": _write(tmp_path / "cal_key.json", {"offset_counts": [0, 0, 0, 0]}),
        "cal_json": _write(tmp_path / "cal_json.json", '{"offset_counts": [0, 0'),
        "params_json": _write(tmp_path / "params_json.json", '{"params": {'),
        "params_key": _write(
            tmp_path / "params_key.json", {"params": {k: v for k, v in mid.items() if k != "sigma_n"}}
        ),
        "params_range": _write(tmp_path / "params_range.json", {"params": {**mid, "omega_swing_rad_s": 99.0}}),
    }


REFUSED = [  # (extra arguments, what stderr must say)
    (["--power-level", "99"], "argument --power-level: 99 is outside the allowed range 1 … 10"),
    (["--power-level", "0"], "argument --power-level: 0 is outside the allowed range 1 … 10"),
    (["--calibration", "{cal3}"], "offset_counts needs exactly 4 values"),
    (["--calibration", "{cal_scales}"], "newton_per_count[0] = -0.5 is outside the allowed range [0.001, 10]"),
    (["--calibration", "{cal_huge}"], "newton_per_count[3] = 1000000000.0 is outside the allowed range"),
    (["--calibration", "{cal_nan}"], "offset_counts[2] = nan is outside the allowed range"),
    (["--calibration", "{cal_key}"], "cal_key.json: missing key 'newton_per_count'"),
    (["--calibration", "{cal_json}"], "cal_json.json: not valid JSON"),
    (["--params", "{params_json}"], "params_json.json: not valid JSON"),
    (["--params", "{params_key}"], "params_key.json: missing key 'params.sigma_n'"),
    (["--params", "{params_range}"], "omega_swing_rad_s = 99.0 is outside the allowed range [16.0, 23.0]"),
    (["--optimize", "--trials", "0"], "argument --trials: 0: need an integer >= 1"),
    (["--optimize", "--trials", "-2"], "argument --trials: -2: need an integer >= 1"),
    (["--duration-s", "-1"], "argument --duration-s: -1.0 is outside the allowed range (0, 3600]"),
    (["--duration-s", "nan"], "argument --duration-s: nan is outside"),
    (["--transition-s", "-1"], "argument --transition-s: -1.0 is outside"),
    (["--steady-s", "0"], "argument --steady-s: 0.0 is outside the allowed range [0.001, 600]"),
    (["--target-velocity-mps", "-1"], "argument --target-velocity-mps: -1.0 is outside the allowed range (0, 2]"),
    (["--friction", "5"], "argument --friction: 5.0 is outside the allowed range [0.1, 1.5]"),
    (["--slope-deg", "60"], "argument --slope-deg: 60.0 is outside the allowed range (-45, 45)"),
    (["--payload-kg", "50"], "argument --payload-kg: 50.0 is outside the allowed range [0, 20]"),
    (["--cpu", "999"], "argument --cpu: 999 is outside this machine's CPUs"),
    (["--robot-port", "70000"], "argument --robot-port: 70000 is outside the allowed range 1 … 65535"),
    (["--seed", "-1"], "argument --seed: -1 is outside the allowed range 0 … 4294967295"),
    (["--seed", "4294967296"], "argument --seed: 4294967296 is outside the allowed range 0 … 4294967295"),
    (["--optimize", "--trials", "1001"], "argument --trials: 1001: need an integer <= 1000 (the GP keeps every trial"),
    (["--robot-ip", "robot.local"], "argument --robot-ip: 'robot.local' is not an IP address"),
    # options that do not apply to this run
    (["--robot-ip", "127.0.0.1"], "--robot-ip applies to --robot go1 only (the simulated Go1 listens on 127.0.0.1"),
    (["--robot-port", "9000", "--local-port", "9001"], "--robot-port, --local-port apply to --robot go1 only"),
    (["--trials", "3"], "--trials applies to --optimize only (a replay walks one set of parameters for --duration-s)"),
    (["--transition-s", "1", "--optimizer", "random"], "--optimizer, --transition-s apply to --optimize only"),
    (["--optimize", "--duration-s", "5"], "--duration-s applies to a replay only (--optimize runs --trials trials)"),
]


@pytest.mark.parametrize("extra, message", REFUSED, ids=[" ".join(e) for e, _ in REFUSED])
def test_deploy_refuses_a_bad_input_before_any_robot(extra, message, tmp_path, capsys, no_robot):
    files = _bad_files(tmp_path)
    err = _refused(
        ["deploy", "--robot", "sim", "--log-dir", str(tmp_path / "run")] + [e.format(**files) for e in extra], capsys
    )
    assert message in err and err.count("\n") == 1  # one line: no usage, no traceback
    assert no_robot == [] and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["deploy", "--robot", "go1", "--friction", "0.3", "--physics", "paper"],
            "--friction, --physics apply to --robot sim only",
        ),
        (["deploy", "--robot", "go1", "--sim-pacing", "lockstep"], "--sim-pacing applies to --robot sim only"),
        (["deploy", "calibrate", "--robot", "go1", "--lift-m", "0.5"], "--lift-m applies to --robot sim only"),
        (
            ["deploy", "calibrate", "--robot", "sim", "--robot-ip", "127.0.0.1"],
            "--robot-ip applies to --robot go1 only",
        ),
    ],
)
def test_an_option_of_the_other_robot_is_refused(argv, message, tmp_path, capsys, no_robot):
    calibration = _write(tmp_path / "cal.json", GOOD_CALIBRATION)
    argv = (
        [*argv, "--calibration", str(calibration)]
        if "calibrate" not in argv
        else [*argv, "--out", str(tmp_path / "c.json")]
    )
    try:
        code = cli.main(argv)
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2 and message in err and err.count("\n") == 1 and no_robot == []


CALIBRATE_REFUSED = [
    (["--mass-kg", "-5"], "argument --mass-kg: -5.0 is outside the allowed range [5, 40]"),
    (["--mass-kg", "500"], "argument --mass-kg: 500.0 is outside"),
    (["--air-s", "0"], "argument --air-s: 0.0 is outside"),
    (["--settle-s", "-1"], "argument --settle-s: -1.0 is outside"),
    (["--lift-m", "0"], "argument --lift-m: 0.0 is outside the allowed range (0, 1]"),
    (["--power-level", "11"], "argument --power-level: 11 is outside the allowed range 1 … 10"),
]


@pytest.mark.parametrize("extra, message", CALIBRATE_REFUSED, ids=[" ".join(e) for e, _ in CALIBRATE_REFUSED])
def test_calibrate_refuses_a_bad_input_before_any_robot(extra, message, tmp_path, capsys, no_robot):
    err = _refused(["deploy", "calibrate", "--robot", "sim", "--out", str(tmp_path / "c.json")] + extra, capsys)
    assert message in err and no_robot == [] and not (tmp_path / "c.json").exists()


def test_no_packet_reaches_the_loopback_robot_when_an_input_is_refused(tmp_path, capsys):
    """The real path (no stand-ins): a Go1 'robot' listening on 127.0.0.1 gets nothing from a refused deploy."""
    robot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    robot.bind(("127.0.0.1", 0))
    robot.settimeout(0.5)
    calibration = _write(tmp_path / "cal.json", GOOD_CALIBRATION)
    bad = _bad_files(tmp_path)
    try:
        for extra in (
            ["--power-level", "99"],
            ["--calibration", str(bad["cal_scales"])],
            ["--params", str(bad["params_key"])],
            ["--duration-s", "-1"],
        ):
            argv = [
                "deploy",
                "--robot",
                "go1",
                "--transport",
                "udp",
                "--robot-ip",
                "127.0.0.1",
                "--robot-port",
                str(robot.getsockname()[1]),
                "--calibration",
                str(calibration),
                "--no-realtime",
                "--log-dir",
                str(tmp_path / "run"),
            ] + extra
            _refused(argv, capsys)
            with pytest.raises(socket.timeout):
                robot.recvfrom(4096)
    finally:
        robot.close()


def test_accepted_files_parse_to_their_values(tmp_path):
    calibration = _write(tmp_path / "cal.json", GOOD_CALIBRATION)
    params = _write(tmp_path / "p.json", GOOD_PARAMS)
    args = cli.build_parser().parse_args(
        ["deploy", "--robot", "go1", "--calibration", str(calibration), "--params", str(params), "--power-level", "10"]
    )
    np.testing.assert_array_equal(args.calibration.offset_counts, [14, -6, 22, 9])
    np.testing.assert_array_equal(args.calibration.newton_per_count, [0.5] * 4)
    np.testing.assert_allclose(args.params.params, 0.5 * (param_space.PARAM_LOWER + param_space.PARAM_UPPER))
    assert args.power_level == 10


def test_safety_config_is_checked():
    assert go1_safety.check_safety(go1_safety.SafetyConfig()) == go1_safety.SafetyConfig()
    for bad, match in (
        (dict(power_level=99), "power_level = 99"),
        (dict(power_level=0), "power_level = 0"),
        (dict(kp_max_nm_rad=-1.0), "kp_max_nm_rad"),
        (dict(kd_max_nm_s_rad=1e6), "kd_max_nm_s_rad"),
        (dict(max_tilt_rad=float("nan")), "max_tilt_rad"),
        (dict(stop_buttons=("Z9",)), "stop_buttons"),
    ):
        with pytest.raises(ValueError, match=match):
            go1_safety.check_safety(go1_safety.SafetyConfig(**bad))


def test_a_negative_mass_gives_no_calibration():
    air = np.zeros((10, 4))
    standing = np.full((10, 4), 60.0)
    assert foot_force.calibrate_foot_force(air, standing, 12.0).newton_per_count[0] == pytest.approx(
        12.0 * 9.81 / 240.0, rel=1e-3
    )
    with pytest.raises(ValueError, match="newton_per_count"):
        foot_force.calibrate_foot_force(air, standing, -5.0)


class _Log(NamedTuple):
    objective: np.ndarray
    params: np.ndarray


TUNED = dict(
    controller="tegotae",
    gait="pace",
    physics="paper",
    friction=0.3,
    slope_deg=5.0,
    payload_kg=2.5,
    target_velocity_mps=0.7,
)


def test_optimize_best_params_replay_with_deploy(tmp_path):
    """`optimize` writes best_params.json with what it was tuned for; `deploy --params` reads back the best trial's
    parameters and that record."""
    params = param_space.from_unit(np.array([[[0.1] * 8], [[0.7] * 8], [[0.4] * 8]]))  # (trials, B=1, 8)
    log = _Log(objective=np.array([[0.5], [1.9], [1.2]]), params=params)
    path = tmp_path / "best_params.json"
    assert study_optimize.write_best_params(path, log, TUNED) == 1
    saved = json.loads(path.read_text())
    assert saved["trial"] == 1 and saved["objective"] == 1.9 and {k: saved[k] for k in TUNED} == TUNED
    args = cli.build_parser().parse_args(["deploy", "--robot", "sim", "--params", str(path)])
    np.testing.assert_allclose(args.params.params, params[1, 0])
    assert args.params.tuned_for == TUNED


def _tuned_file(tmp_path: pathlib.Path, **changes) -> pathlib.Path:
    path = tmp_path / "best_params.json"
    tuned.save(path, param_space.from_unit(np.full(8, 0.3)), {**TUNED, **changes}, objective=1.5, trial=4)
    return path


def test_deploy_params_replays_what_was_tuned_unless_overridden(tmp_path, capsys, monkeypatch):
    """Not deploy's own defaults (vmc_tegotae, go1 physics, friction 0.6, v* 0.5) but the file's; an option given on
    the command line wins, and one line says so."""
    ran = []
    monkeypatch.setattr(deploy, "run", lambda args: ran.append(args) or 0)
    path = _tuned_file(tmp_path)
    assert cli.main(["deploy", "--robot", "sim", "--params", str(path), "--log-dir", str(tmp_path / "a")]) == 0
    args = ran[-1]
    assert {k: getattr(args, k) for k in TUNED} == TUNED
    np.testing.assert_allclose(args.params, param_space.from_unit(np.full(8, 0.3)))
    err = capsys.readouterr().err
    assert (
        f"{path} tuned for controller tegotae, gait pace, physics paper, friction 0.3, slope 5°, payload 2.5 kg, "
        "v* 0.7 m/s"
    ) in err and "overrides" not in err
    assert (
        cli.main(
            [
                "deploy",
                "--robot",
                "sim",
                "--params",
                str(path),
                "--friction",
                "0.9",
                "--controller",
                "tegotae",
                "--log-dir",
                str(tmp_path / "b"),
            ]
        )
        == 0
    )
    args = ran[-1]
    assert args.friction == 0.9 and args.physics == "paper" and args.controller == "tegotae"
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if "tuned for" in ln]
    assert line.endswith("; --friction 0.9 overrides it")  # the same controller given again is no override


def test_a_robot_tuned_file_keeps_the_replays_own_scenario(tmp_path, capsys, monkeypatch):
    """A file tuned on the real robot records no physics, friction or slope (null): the replay keeps its own."""
    ran = []
    monkeypatch.setattr(deploy, "run", lambda args: ran.append(args) or 0)
    path = _tuned_file(tmp_path, physics=None, friction=None, slope_deg=None)
    assert cli.main(["deploy", "--robot", "sim", "--params", str(path), "--log-dir", str(tmp_path / "a")]) == 0
    assert (ran[-1].physics, ran[-1].friction, ran[-1].slope_deg, ran[-1].controller) == ("go1", 0.6, 0.0, "tegotae")
    assert "tuned for controller tegotae, gait pace, payload 2.5 kg, v* 0.7 m/s" in capsys.readouterr().err


def test_walk_params_walks_what_was_tuned(tmp_path, capsys, monkeypatch):
    walks = []

    def fake_walk(**kwargs):
        walks.append(kwargs)
        raise SystemExit(0)  # stop before the table: only what walk was asked for matters here

    monkeypatch.setattr(walk, "walk_trials", fake_walk)
    path = _tuned_file(tmp_path)
    with pytest.raises(SystemExit):
        cli.main(["walk", "--params", str(path), "--payload-kg", "0,5"])
    asked = walks[-1]
    assert (
        asked["controllers"],
        asked["gaits"],
        asked["physics"],
        asked["friction"],
        asked["slope_deg"],
        asked["payload_kg"],
        asked["target_velocity_mps"],
    ) == (("tegotae",), ("pace",), ("paper",), (0.3,), (5.0,), (0.0, 5.0), 0.7)
    np.testing.assert_allclose(asked["params"], param_space.from_unit(np.full(8, 0.3)))
    assert "; --payload-kg 0,5 overrides it" in capsys.readouterr().err


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("controller", "cpg9", "controller 'cpg9' is not one of open_loop"),
        ("gait", "gallop", "gait 'gallop' is not one of trot, pace, bound, walk, walk_diagonal, pronk"),
        ("physics", "moon", "physics 'moon' is not one of"),
        ("friction", 7.0, "friction = 7.0 is outside the allowed range [0.1, 1.5]"),
        ("target_velocity_mps", "fast", "target_velocity_mps 'fast' is not a number"),
    ],
)
def test_a_bad_tuned_for_field_is_refused_with_the_file_and_key(field, value, message, tmp_path, capsys, no_robot):
    path = tmp_path / "best_params.json"
    data = {"params": param_space.as_dict(param_space.midpoint()), **TUNED, field: value}
    _write(path, data)
    err = _refused(["deploy", "--robot", "sim", "--params", str(path)], capsys)
    assert f"parameter file {path}: {message}" in err


# ----------------------------------------------------------------------------------------------- output folders


@pytest.fixture
def no_engine(monkeypatch):
    def forbidden(*args, **kwargs):
        raise AssertionError("the engine was built")

    monkeypatch.setattr(ablation, "Engine", forbidden)


def test_out_pointing_at_a_file_fails_at_once(tmp_path, capsys, no_engine):
    target = _write(tmp_path / "afile", "keep")
    assert cli.main(["optimize", "--trials", "2", "--out", str(target)]) == 2
    assert f"{target} is a file, not a folder" in capsys.readouterr().err and target.read_text() == "keep"
    assert cli.main(["study", "friction", "--quick", "--out", str(target)]) == 2
    assert "is a file" in capsys.readouterr().err


OUTPUT_OPTIONS = (
    ["optimize", "--trials", "2", "--out"],
    ["study", "friction", "--quick", "--out"],
    ["deploy", "--robot", "sim", "--log-dir"],
    ["deploy", "calibrate", "--robot", "sim", "--out"],
)


@pytest.mark.parametrize("argv", OUTPUT_OPTIONS, ids=lambda a: a[0] + a[-1])
def test_an_empty_path_or_a_missing_parent_is_refused_before_anything_runs(argv, tmp_path, capsys, no_engine, no_robot):
    err = _refused([*argv, ""], capsys)
    assert err.count("\n") == 1 and "an empty path: name a folder or file to write" in err
    target = tmp_path / "missing" / "x"
    err = _refused([*argv, str(target)], capsys)
    assert err.count("\n") == 1 and f"its folder {target.parent} does not exist" in err
    assert not target.parent.exists()  # never created


@pytest.mark.parametrize("argv", OUTPUT_OPTIONS, ids=lambda a: a[0] + a[-1])
def test_an_unwritable_folder_is_refused_before_anything_runs(argv, tmp_path, capsys, no_engine, no_robot, monkeypatch):
    """A read-only file system (simulated: writing the probe file raises EROFS, which root meets too) gives one line
    and exit 2 before the engine or a robot starts."""
    write_bytes = pathlib.Path.write_bytes

    def read_only(self, data):
        if self.name.startswith(".cpgjax-write-check"):
            raise OSError(30, "Read-only file system")
        return write_bytes(self, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", read_only)
    target = tmp_path / "out"
    assert cli.main([*argv, str(target)]) == 2
    written_in = tmp_path if "calibrate" in argv else target  # calibrate's --out is a file
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"cannot write in {written_in}: it takes no new files (Read-only file system)" in err


@pytest.mark.skipif(not pathlib.Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_a_folder_in_a_file_system_that_takes_none_names_it(capsys, no_engine):
    """/proc exists but takes no new folder (mkdir fails with ENOENT): the line says that of /proc, not that a
    file is missing."""
    assert cli.main(["walk", "--out", "/proc/cpgjax-out", "--trials", "1"]) == 2
    assert capsys.readouterr().err == (
        "cpgjax walk: cannot create the folder /proc/cpgjax-out: /proc takes no new "
        "folders (No such file or directory)\n"
    )
    assert cli.main(["study", "friction", "--quick", "--out", "/proc/cpgjax-out", "--dry-run"]) == 2
    assert capsys.readouterr().err == (
        "cpgjax study: cannot write in /proc: it takes no new files (No such file or directory)\n"
    )


def test_a_non_empty_folder_is_not_overwritten(tmp_path, capsys, no_engine):
    robot_run = tmp_path / "run"
    robot_run.mkdir()
    _write(robot_run / "trials.parquet", "robot data")
    for argv in (
        ["optimize", "--trials", "2", "--out", str(robot_run)],
        ["study", "friction", "--quick", "--out", str(robot_run)],
    ):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert f"{robot_run} is not empty (trials.parquet): pass --overwrite" in err and "--resume" not in err
    assert (robot_run / "trials.parquet").read_text() == "robot data"


def test_transfer_study_folders(tmp_path, capsys, no_engine):
    out = tmp_path / "transfer"
    assert cli.main(["study", "transfer", "--quick", "--out", str(out), "--resume"]) == 2
    assert "--resume: no arm of" in capsys.readouterr().err and not out.exists()
    (out / "transfer_go1").mkdir(parents=True)
    _write(out / "transfer_go1" / "trials.parquet", "keep")
    assert cli.main(["study", "transfer", "--quick", "--out", str(out)]) == 2
    assert f"{out} is not empty (transfer_go1): pass --overwrite" in capsys.readouterr().err


def test_overwrite_starts_afresh(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    _write(out / study_io.CHECKPOINT, "old")
    with pytest.raises(study_spec.StudyError, match="--resume to continue its checkpoint, --overwrite"):
        study_io.claim_folder(out)
    assert study_io.claim_folder(out, overwrite=True) == out and not (out / study_io.CHECKPOINT).exists()


def _old_optimize_folder(out: pathlib.Path) -> list[str]:
    """What `optimize` and a study leave in their folder (names as they write them)."""
    out.mkdir()
    for name in (
        study_io.CHECKPOINT,
        "trials.parquet",
        "recording.rrd",
        "metadata.json",
        "best_params.json",
        "table.md",
        "learning_curves.png",
        "checkpoint.0of2.t000003.npz",
        "checkpoint.npz.tmp",
    ):
        _write(out / name, "old")
    (out / study_io.BEST_PARAMS).mkdir()
    _write(out / study_io.BEST_PARAMS / "controller=vmc.json", "old")
    (out / "transfer_go1").mkdir()
    _write(out / "transfer_go1" / "trials.parquet", "old")
    return sorted(p.name for p in out.iterdir())


def test_overwrite_replaces_the_whole_run(tmp_path, capsys, monkeypatch):
    """A replay written over an old --optimize folder: none of the old rows, recordings or parameters stay, so `show`
    cannot report them as the replay's."""
    assert tick_log.FILE_NAME in study_io.OUTPUT_FILES  # the robot's per-tick log is named there too
    monkeypatch.setattr(deploy, "run", lambda args: 0)
    out = tmp_path / "old"
    _old_optimize_folder(out)
    _write(out / tick_log.FILE_NAME, "old ticks")
    assert cli.main(["deploy", "--robot", "sim", "--log-dir", str(out)]) == 2
    err = capsys.readouterr().err
    assert "pass --overwrite to replace its files" in err and "--resume" not in err  # deploy cannot resume
    assert cli.main(["deploy", "--robot", "sim", "--log-dir", str(out), "--overwrite"]) == 0
    assert list(out.iterdir()) == []


def test_overwrite_refuses_what_cpgjax_did_not_write(tmp_path, capsys, no_engine):
    out = tmp_path / "old"
    before = _old_optimize_folder(out)
    _write(out / "notes.txt", "mine")
    (out / "data").mkdir()
    assert cli.main(["optimize", "--trials", "2", "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1
        and (
            f"{out}: --overwrite replaces only what cpgjax wrote, and data, notes.txt are not "
            "cpgjax's: move them, or write somewhere else"
        )
        in err
    )
    assert sorted(p.name for p in out.iterdir()) == sorted([*before, "notes.txt", "data"])  # nothing deleted
    assert (out / "trials.parquet").read_text() == "old"


def test_deploy_and_calibrate_outputs(tmp_path, capsys, monkeypatch):
    folders = []
    monkeypatch.setattr(deploy, "run", lambda args: folders.append(args.log_dir) or 0)
    monkeypatch.setattr(calibrate, "run", lambda args: 0)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["deploy", "--robot", "sim"]) == 0 and cli.main(["deploy", "--robot", "sim"]) == 0
    assert folders[0] != folders[1] and all(f.parent == pathlib.Path("runs/deploy") and f.is_dir() for f in folders)
    _write(folders[0] / "trials.parquet", "3 trials")
    assert cli.main(["deploy", "--robot", "sim", "--log-dir", str(folders[0])]) == 2
    assert "is not empty (trials.parquet): pass --overwrite" in capsys.readouterr().err
    assert cli.main(["deploy", "--robot", "sim", "--log-dir", str(folders[0]), "--overwrite"]) == 0
    old = _write(tmp_path / "go1_calibration.json", "previous")
    assert cli.main(["deploy", "calibrate", "--robot", "sim"]) == 2
    assert "go1_calibration.json exists: pass --overwrite" in capsys.readouterr().err and old.read_text() == "previous"
    assert cli.main(["deploy", "calibrate", "--robot", "sim", "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert cli.main(["deploy", "calibrate", "--robot", "sim", "--overwrite"]) == 0


# ----------------------------------------------------------------------------------------------- checkpoints, resume


def _optimize_spec(trials=2):
    return study_options.OptimizeOptions(trials=trials).spec()


def _fake_checkpoint(out: pathlib.Path, spec, trial: int, backend: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(trial=trial, fingerprint=study_io.fingerprint(spec), backend=backend)
    np.savez(out / study_io.CHECKPOINT, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))


def _truncated(path: pathlib.Path) -> None:
    np.savez(path, meta=np.zeros(1000, np.uint8), other=np.arange(10_000))
    path.write_bytes(path.read_bytes()[:3000])


def test_a_full_disk_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    """The checkpoint of trial 2 cannot be written (ENOSPC): the error says which trials are kept, the previous
    checkpoint still loads with its trials, and no temporary file is left."""
    spec = _optimize_spec(trials=4)
    log = study_io.TrialLog(*(np.zeros(1) for _ in study_io.TrialLog._fields))
    ckpt = study_io.Checkpoint(2, [np.zeros((1, 3))], [np.ones((1, 2))], np.zeros((1, 2)), [log, log], 1.0, {})
    study_io.save_checkpoint(tmp_path, spec, ckpt, "native")

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    with pytest.raises(
        study_io.OutputError,
        match=r"writing the checkpoint of trial 2 in .* failed \(No space left "
        r"on device\); trials 0…1 are kept in its checkpoint: free space, then the same command with "
        r"--resume continues",
    ):
        study_io.save_checkpoint(tmp_path, spec, ckpt._replace(trial=3, logs=[log] * 3), "native")
    monkeypatch.undo()
    assert study_io.load_checkpoint(tmp_path, spec).trial == 2 and sorted(os.listdir(tmp_path)) == [study_io.CHECKPOINT]


def test_ctrl_c_while_a_checkpoint_is_written_leaves_no_temporary_file(tmp_path, monkeypatch):
    """Ctrl-C in the middle of writing trial 3's checkpoint: the interrupt goes on, the checkpoint of trial 2 is the
    folder's only file, and it loads."""
    spec = _optimize_spec(trials=4)
    log = study_io.TrialLog(*(np.zeros(1) for _ in study_io.TrialLog._fields))
    ckpt = study_io.Checkpoint(2, [np.zeros((1, 3))], [np.ones((1, 2))], np.zeros((1, 2)), [log, log], 1.0, {})
    study_io.save_checkpoint(tmp_path, spec, ckpt, "native")

    def interrupted(f, **arrays):
        f.write(b"half a checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", interrupted)
    with pytest.raises(KeyboardInterrupt):
        study_io.save_checkpoint(tmp_path, spec, ckpt._replace(trial=3, logs=[log] * 3), "native")
    monkeypatch.undo()
    assert sorted(os.listdir(tmp_path)) == [study_io.CHECKPOINT]
    assert study_io.load_checkpoint(tmp_path, spec).trial == 2


@pytest.mark.parametrize("damage", ["garbage", "empty", "truncated", "pickled"])
def test_a_corrupt_checkpoint_is_named(damage, tmp_path, capsys, no_engine):
    out = tmp_path / "out"
    out.mkdir()
    path = out / study_io.CHECKPOINT
    if damage == "garbage":
        path.write_bytes(b"\x80\x04 not a checkpoint at all" * 10)
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "truncated":
        _truncated(path)
    else:
        np.savez(path, meta=np.array([{"trial": 1}], dtype=object))
    with pytest.raises(study_spec.StudyError) as err:
        study_io.checkpoint_meta(out)
    assert f"checkpoint {path} is corrupt" in str(err.value) and "pickle" not in str(err.value).lower()
    assert cli.main(["optimize", "--trials", "2", "--out", str(out), "--resume"]) == 2
    printed = capsys.readouterr().err
    assert "is corrupt" in printed and "pickle" not in printed.lower() and "Traceback" not in printed


def test_resume_needs_a_checkpoint_of_the_same_backend(tmp_path, capsys, no_engine):
    out = tmp_path / "out"
    assert cli.main(["optimize", "--trials", "2", "--out", str(out), "--resume"]) == 2
    assert "--resume: there is no checkpoint" in capsys.readouterr().err and not out.exists()
    spec = _optimize_spec()
    _fake_checkpoint(out, spec, 1, "mjx")
    assert cli.main(["optimize", "--trials", "2", "--out", str(out), "--resume", "--backend", "native"]) == 2
    assert "written on the mjx backend, this run would use native: resume with --backend mjx" in capsys.readouterr().err
    assert study_io.resume_point(out, spec, "mjx") == 1
    with pytest.raises(study_spec.StudyError, match="different study definition .it does not record its fields"):
        study_io.resume_point(out, _optimize_spec(trials=3), "mjx")  # a checkpoint of an older cpgjax


def test_a_different_definition_is_refused_naming_the_fields(tmp_path, capsys, no_engine):
    out = tmp_path / "out"
    _checkpoint_of(out, _optimize_spec(trials=12), 1)
    assert (
        cli.main(
            [
                "optimize",
                "--trials",
                "12",
                "--friction",
                "0.9",
                "--controller",
                "vmc",
                "--out",
                str(out),
                "--resume",
                "--backend",
                "native",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1
        and (
            "was written by a different study definition (controllers ('vmc_tegotae',) there, "
            "('vmc',) here; friction (0.6,) there, (0.9,) here); use another --out"
        )
        in err
    )
    assert cli.main(["optimize", "--trials", "20", "--out", str(out), "--resume", "--backend", "native"]) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1
        and (
            "--trials 20: the run in this folder holds 12 trials in its optimizers (its "
            "--max-trials, by default its --trials)"
        )
        in err
        and "run it afresh" in err
    )


def _checkpoint_of(out: pathlib.Path, spec, trial: int) -> None:
    log = study_io.TrialLog(*(np.zeros(1) for _ in study_io.TrialLog._fields))
    study_io.save_checkpoint(
        out, spec, study_io.Checkpoint(trial, [], [], np.zeros((1, 2)), [log] * trial, 1.0, {}), "native"
    )


def test_extending_a_run_needs_its_optimizers_capacity_and_its_conditions(tmp_path):
    """``--resume --trials N`` continues a run only where the result is a run of N: the same optimizer capacity
    (``--max-trials``), trials already done ≤ N, and the conditions those trials ran under; otherwise one line
    saying what to run."""
    out = tmp_path / "out"
    _checkpoint_of(out, dataclasses.replace(_optimize_spec(trials=12), max_trials=30), 12)
    assert study_io.resume_point(out, dataclasses.replace(_optimize_spec(trials=30), max_trials=30), "native") == 12
    assert study_io.resume_point(out, _optimize_spec(trials=30), "native") == 12  # room for 30 either way
    with pytest.raises(study_spec.StudyError, match="resume with --trials 20 --max-trials 30 to continue it"):
        study_io.resume_point(out, _optimize_spec(trials=20), "native")
    with pytest.raises(study_spec.StudyError, match="has done 12 trials already; --resume with --trials 12 or more"):
        study_io.resume_point(out, dataclasses.replace(_optimize_spec(trials=10), max_trials=30), "native")
    with pytest.raises(study_spec.StudyError, match="holds 30 trials .* run it afresh"):
        study_io.resume_point(out, _optimize_spec(trials=40), "native")
    # a study whose condition changes scale with its trials: another length is another study
    studies = tmp_path / "load"
    _checkpoint_of(studies, study_driver.read("load_adaptation", seeds=1, trials=24).spec, 24)
    with pytest.raises(study_spec.StudyError, match=r"schedules .* \(its condition changes scale with --trials"):
        study_io.resume_point(studies, study_driver.read("load_adaptation", seeds=1, trials=30).spec, "native")
    # a schedule written with trial numbers that stay: the conditions of the trials done must be those they ran under
    fixed = dataclasses.replace(
        _optimize_spec(trials=12),
        max_trials=30,
        schedules=(study_spec.Schedule("s", (study_spec.Change(8, "payload_kg", 5.0),)),),
    )
    _checkpoint_of(tmp_path / "fixed", fixed, 12)
    assert study_io.resume_point(tmp_path / "fixed", dataclasses.replace(fixed, num_trials=30), "native") == 12


def test_max_trials_below_the_trials_is_refused_in_one_line(tmp_path, capsys):
    assert cli.main(["optimize", "--trials", "10", "--max-trials", "5", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == "cpgjax optimize: --max-trials 5: need at least --trials (10)\n"
    assert cli.main(["study", "friction", "--quick", "--max-trials", "10", "--out", str(tmp_path / "s")]) == 2
    assert capsys.readouterr().err == "cpgjax study: --max-trials 10: need at least the run's 12 trials\n"


def test_resume_says_where_and_ctrl_c_says_how_to_resume(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    _fake_checkpoint(out, _optimize_spec(), 1, "native")

    class Interrupted:
        def __init__(self, spec, backend):
            pass

        def run(self, *args, **kwargs):
            raise KeyboardInterrupt

    monkeypatch.setattr(ablation, "Engine", Interrupted)
    argv = ["optimize", "--trials", "2", "--out", str(out), "--resume", "--backend", "native"]
    assert cli.main(argv) == cli.INTERRUPTED == 130
    err = capsys.readouterr().err
    assert f"resuming {out} at trial 1 (trials are numbered from 0; 1 of 2 are done)" in err
    assert f"resume with: cpgjax optimize --trials 2 --out {out} --resume --backend native\n" in err


def test_a_ctrl_c_lost_in_a_callback_still_stops_after_the_trial(tmp_path, capsys, monkeypatch):
    """SIGINT while Python runs a callback whose exceptions it ignores (as JAX's garbage-collection callback): the
    KeyboardInterrupt is lost there, and the run stops after the trial it was in, with its checkpoint and exit
    130, instead of running to the end."""
    out = tmp_path / "out"
    spec = _optimize_spec(trials=6)
    trials_run = []

    class SwallowsOneInterrupt:
        def __init__(self, spec, backend):
            pass

        def run(self, out_dir, resume, progress):
            for t in range(spec.num_trials):
                trials_run.append(t)
                _fake_checkpoint(out_dir, spec, t + 1, "native")
                if t == 1:
                    try:  # what an ignored-exception callback does with the signal's KeyboardInterrupt
                        os.kill(os.getpid(), signal.SIGINT)
                        time.sleep(0.1)
                    except KeyboardInterrupt:
                        pass
                progress(ablation.Progress(t + 1, spec.num_trials, {"vmc_tegotae": 1.0}, 1.0, None))
            raise AssertionError("ran to the end")

    monkeypatch.setattr(ablation, "Engine", SwallowsOneInterrupt)
    argv = ["optimize", "--trials", "6", "--out", str(out), "--backend", "native"]
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own, as in a terminal
    try:
        assert cli.main(argv) == 130 and trials_run == [0, 1]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the command's handler is gone
    finally:
        signal.signal(signal.SIGINT, previous)
    assert f"trials 0…1 are saved in {out / study_io.CHECKPOINT}" in capsys.readouterr().err


def test_a_ctrl_c_lost_after_the_last_trial_still_exits_130(tmp_path, capsys, monkeypatch):
    """Lost after the last trial's check, the request still makes the exit status 130 once the outputs are
    written (the run finished: nothing to resume)."""

    def finishes_after_a_lost_interrupt(study, options):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.1)
        except KeyboardInterrupt:
            pass
        return study_driver.StudyRun("the table", options.out, None)

    monkeypatch.setattr(study_driver, "run", finishes_after_a_lost_interrupt)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert cli.main(["study", "friction", "--quick", "--out", str(tmp_path / "s")]) == 130
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "cpgjax study: interrupted as it finished; its outputs are written" in capsys.readouterr().err


def test_ctrl_c_in_a_study_prints_the_resume_command(tmp_path, capsys, monkeypatch):
    out = tmp_path / "study"

    def interrupted(study, options):
        _fake_checkpoint(options.out, study.specs[0], 3, "native")
        raise KeyboardInterrupt

    monkeypatch.setattr(study_driver, "run", interrupted)
    assert cli.main(["study", "friction", "--quick", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert f"trials 0…2 are saved in {out / study_io.CHECKPOINT}" in err and "Traceback" not in err
    assert f"resume with: cpgjax study friction --quick --out {out} --resume" in err


# ----------------------------------------------------------------------------------------------- options


def _subparsers(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                yield from _subparsers(sub)


def test_every_option_shows_its_default():
    for name, sub in _subparsers(cli.build_parser()):
        assert sub.formatter_class is cli._HelpFormatter, name
        for action in sub._actions:
            if not action.option_strings or action.dest == "help":
                continue
            assert action.help, (name, action.dest)
            if action.default is None:
                assert "default" in action.help or "required" in action.help, (name, action.dest)
    deploy_help = next(sub for name, sub in _subparsers(cli.build_parser()) if name == "deploy").format_help()
    assert "(default: 9)" in " ".join(deploy_help.split())


def test_one_name_unit_and_range_for_the_scenario_in_every_command(capsys):
    subs = dict(_subparsers(cli.build_parser()))
    for command in ("walk", "optimize", "deploy", "calibrate"):
        options = {s for a in subs[command]._actions for s in a.option_strings}
        assert {"--friction", "--slope-deg", "--payload-kg"} <= options, command
        assert not {"--slope", "--payload", "--target", "--target-velocity"} & options, command
    for command in (["walk"], ["optimize"], ["deploy", "--robot", "sim"]):
        assert "[0.1, 1.5]" in _refused(command + ["--friction", "5"], capsys)
        assert "(0, 2]" in _refused(command + ["--target-velocity-mps", "-1"], capsys)
    with pytest.raises(study_spec.StudyError, match=r"friction = 5.0 is outside the allowed range \[0.1, 1.5\]"):
        study_spec.validate(study_spec.StudySpec("x", friction=(5.0,)))
    with pytest.raises(study_spec.StudyError, match=r"payload_kg = 30.0 is outside the allowed range \[0, 20\]"):
        study_spec.validate(study_spec.StudySpec("x", payload_kg=(30.0,)))


def test_walk_refuses_zero_trials_and_names_its_target(capsys):
    assert "argument --trials: 0: need an integer >= 1" in _refused(["walk", "--trials", "0"], capsys)
    with pytest.raises(ValueError, match="num_trials = 0"):
        walk.walk(num_trials=0)
    row = walk.WalkRow(
        controller="vmc",
        physics="paper",
        condition=Condition(target_velocity_mps=0.8),
        vx_mps=0.5,
        vy_mps=0.0,
        cot=0.6,
        objective=1.8,
        c_load_n=30.0,
        c_slope_rad=0.0,
        roll_std_rad=0.01,
        pitch_std_rad=0.01,
        falls=0,
    )
    assert "| J (v*=0.8 m/s) |" in walk.markdown_table([row])


def test_version_and_no_warp_probe_on_stdout():
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-m", "cpgjax.cli", "--version"],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=120,
    )
    assert done.returncode == 0 and done.stdout == f"cpgjax {cpgjax.__version__}\n"


def test_progress_lines_count_trials_done_and_wait_for_the_pace(capsys):
    show = cli._progress_printer(sys.stdout)
    show(ablation.Progress(1, 12, {"vmc": 1.5}, 100.0, None))
    show(ablation.Progress(2, 12, {"vmc": 1.6}, 900.0, 600.0))
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("1/12 trials done") and out[0].endswith("ETA after the next trial")
    assert out[1].endswith("ETA 10.0 min")


# ----------------------------------------------------------------------------------------------- show

RRD = b"RRF2" + bytes(100) + outputs.RRD_FOOTER + bytes(4)  # a header, a body, rerun's footer


def test_show_lists_every_file_and_names_each_damaged_one(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    _write(out / "metadata.json", {"study": "optimize", "backend": "native"})  # no instances
    _write(out / "best_params.json", {"params": param_space.as_dict(param_space.midpoint()), **TUNED})
    assert cli.main(["show", str(out), "--no-viewer"]) == 0
    printed = capsys.readouterr().out
    assert f"{out}: a `cpgjax optimize` folder" in printed and "optimize: on native" in printed
    assert "best_params.json     the best trial's parameters and what they were tuned for" in printed
    assert f"next: replay the best: cpgjax deploy --robot sim --params {out / 'best_params.json'}" in printed
    assert "KeyError" not in printed and "(no rerun recording" not in printed
    _write(out / "metadata.json", '{"study": ')
    _write(out / "trials.parquet", "PAR1 truncated")
    _write(out / "recording.rrd", "")
    (out / "learning_curves.png").write_bytes(b"GIF89a")
    assert cli.main(["show", str(out), "--no-viewer"]) == 1  # damaged files: not a clean result
    printed = capsys.readouterr().out
    for name, problem in (
        ("metadata.json", "corrupt or truncated (JSONDecodeError"),
        ("trials.parquet", "corrupt or truncated"),
        ("recording.rrd", "empty"),
        ("learning_curves.png", "not a PNG image"),
    ):
        (line,) = [ln for ln in printed.splitlines() if ln.startswith(f"  {name} ")]
        assert f"[{name}: {problem}" in line
    assert "Traceback" not in printed and "metadata.json is damaged" in printed


def test_show_detects_a_truncated_recording_and_tick_log(tmp_path, capsys):
    """A recording rerun finished ends with its footer; cut short it does not. A per-tick log cut mid-batch too."""
    import rerun as rr

    out = tmp_path / "run"
    out.mkdir()
    rec = rr.RecordingStream("cpgjax_test")
    rec.save(str(out / "trials.rrd"))
    rec.log("x", rr.Scalars(1.0))
    rec.flush()
    rec.disconnect()
    assert cli.main(["show", str(out), "--no-viewer"]) == 2  # a recording alone is no result folder
    assert "holds no cpgjax results" in capsys.readouterr().err
    _write(out / "run.json", {"trip": None, "stopped": False})
    assert cli.main(["show", str(out), "--no-viewer"]) == 0
    assert "trials.rrd: truncated" not in capsys.readouterr().out
    data = (out / "trials.rrd").read_bytes()
    (out / "trials.rrd").write_bytes(data[: len(data) // 2])
    _write(out / "run.json", '{"trip": nu')
    assert cli.main(["show", str(out), "--no-viewer"]) == 1
    printed = capsys.readouterr().out
    assert "[trials.rrd: truncated (no rerun footer" in printed and "[run.json: corrupt or truncated" in printed
    assert "Traceback" not in printed


def test_show_names_the_command_that_metadata_json_says_wrote_the_folder(tmp_path, capsys):
    """metadata.json's ``written_by`` names the folder's command; a folder from before the key is told by its files."""
    out = tmp_path / "run"
    out.mkdir()
    _write(out / outputs.METADATA, {"study": "friction", "written_by": "optimize"})
    assert cli.main(["show", str(out), "--no-viewer"]) == 0
    assert f"{out}: a `cpgjax optimize` folder" in capsys.readouterr().out
    _write(out / outputs.METADATA, {"study": "friction"})
    assert cli.main(["show", str(out), "--no-viewer"]) == 0
    assert f"{out}: a `cpgjax study` folder" in capsys.readouterr().out


def test_show_refuses_a_folder_that_is_no_result(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert cli.main(["show", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"cpgjax show: {tmp_path} holds no cpgjax results" in err


def test_show_a_calibration_file(tmp_path, capsys):
    path = _write(tmp_path / "go1_calibration.json", GOOD_CALIBRATION)
    assert cli.main(["show", str(path)]) == 1  # its stands' per-tick logs are missing
    printed = capsys.readouterr().out
    assert "offsets [14.0, -6.0, 22.0, 9.0] counts" in printed and "go1_calibration.air.ticks.arrows" in printed
    assert f"next: cpgjax deploy --robot go1 --calibration {path}" in printed


def _fake_viewer(tmp_path: pathlib.Path, seconds: float) -> pathlib.Path:
    script = tmp_path / "viewer"
    script.write_text(f'#!/bin/sh\necho "$@" > {tmp_path}/viewer_args\nsleep {seconds}\nexit 3\n')
    script.chmod(0o755)
    return script


def test_show_opens_a_viewer_only_where_one_can_run(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    (out / "recording.rrd").write_bytes(RRD)
    _write(out / "metadata.json", {"study": "friction"})
    monkeypatch.setattr(show, "VIEWER_START_S", 0.5)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(show, "_viewer", lambda: str(_fake_viewer(tmp_path, 0)))
    assert cli.main(["show", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "no display here" in printed and "rerun recording.rrd" in printed and "opened" not in printed
    assert not (tmp_path / "viewer_args").exists()
    monkeypatch.setenv("DISPLAY", ":0")
    assert cli.main(["show", str(out)]) == 1  # the viewer dies at once: not "opened"
    assert "exited at once (status 3)" in capsys.readouterr().out
    monkeypatch.setattr(show, "_viewer", lambda: str(_fake_viewer(tmp_path, 2)))
    assert cli.main(["show", str(out)]) == 0
    assert "opened" in capsys.readouterr().out
    assert (tmp_path / "viewer_args").read_text().split() == ["--bind", "127.0.0.1", str(out / "recording.rrd")]


# ----------------------------------------------------------------------------------------------- outputs


def test_recording_paths_carry_the_study_labels():
    labels = [
        dict(controller="vmc_tegotae", seed=s, friction=f, data_reuse=True, schedule="constant")
        for f in (0.3, 0.9)
        for s in (0, 1)
    ]
    paths = [study_io.instance_path(labels, b) for b in range(len(labels))]
    assert len(set(paths)) == 4
    assert "friction\\=0.3" in paths[0] and "friction\\=0.9" in paths[2]
    assert "controller\\=vmc_tegotae" in paths[0] and "seed\\=1" in paths[1]
    assert "data_reuse" not in paths[0] and "schedule" not in paths[0]  # the same for every instance


@pytest.mark.slow
def test_ctrl_c_in_a_real_optimization_saves_and_says_how_to_resume(tmp_path):
    """SIGINT to a running `cpgjax optimize` (C MuJoCo, a few short trials): exit 130, the checkpoint of the last
    finished trial kept, the resume command printed, no traceback."""
    out = tmp_path / "opt"
    env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_PLATFORMS": "cpu"}
    argv = ["optimize", "--trials", "12", "--out", str(out), "--backend", "native"]
    # Python keeps SIGINT ignored in a child whose parent ignores it (a test run started in the background of a
    # non-interactive shell): give the command Python's own Ctrl-C handler, as a terminal would.
    start = (
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "sys.argv = ['cpgjax', *sys.argv[1:]]; runpy.run_module('cpgjax.cli', run_name='__main__')"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", start, *argv],
        env=env,
        cwd=REPO,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None and not (out / study_io.CHECKPOINT).exists():
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    saved = study_io.checkpoint_meta(out)["trial"]
    assert proc.returncode == 130 and 1 <= saved < 12, err
    assert f"resume with: cpgjax {' '.join(argv)} --resume" in err and "Traceback" not in err


def test_the_botorch_benchmark_says_what_to_install():
    import importlib.util

    if importlib.util.find_spec("torch") is not None and importlib.util.find_spec("botorch") is not None:
        pytest.skip("the bench extra is installed here")
    done = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "bo.py"), "--quick"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "pip install -e '.[bench]' (or make bench-deps)" in done.stderr


def test_a_study_dry_run_checks_everything_and_touches_nothing(tmp_path, capsys):
    """``study --dry-run`` prints the plan and exits 0 without creating the folder; a non-empty folder is refused as a
    run would refuse it, and with --overwrite nothing is deleted; --resume reports where it would start."""
    out = tmp_path / "ablation"
    assert cli.main(["study", "controller_ablation", "--quick", "--out", str(out), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert (
        f"controller_ablation: 8 instances (4 controllers, 2 seeds) × 12 trials of 4.5 s: {8 * 12 * 4500:,} env-steps"
        in text
        and "nothing computed (--dry-run)" in text
    )
    assert not out.exists()
    spec = study_driver.read("controller_ablation", quick=True).spec
    _fake_checkpoint(out, spec, 3, "native")
    assert cli.main(["study", "controller_ablation", "--quick", "--out", str(out), "--dry-run"]) == 2
    assert "is not empty (checkpoint.npz): pass --resume" in capsys.readouterr().err
    assert cli.main(["study", "controller_ablation", "--quick", "--out", str(out), "--dry-run", "--overwrite"]) == 0
    assert (out / study_io.CHECKPOINT).exists()
    assert cli.main(["study", "controller_ablation", "--quick", "--out", str(out), "--dry-run", "--resume"]) == 0
    assert f"resuming {out} at trial 3" in capsys.readouterr().out


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        cli.main([*argv, "--help"])
    assert exit_.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_the_help_says_what_the_defaults_and_requirements_are(capsys):
    """`demo --help` says what the demo runs, `deploy --help` lists --robot under "required", and `study --help`
    gives the minimum of --trials and what --quick runs in the paper's studies (their files' [quick] tables)."""
    assert "online optimization of the four CPG controllers" in _help(["demo"], capsys)
    assert "required: --robot {sim,go1}" in _help(["deploy"], capsys)
    text = _help(["study"], capsys)
    assert f"at least {limits.MIN_STUDY_TRIALS};" in text
    quick = [study_driver.read(name, quick=True).spec for name in study_driver.paper_studies()]
    assert {len(s.seeds) for s in quick} == {2}
    low, high = min(s.num_trials for s in quick), max(s.num_trials for s in quick)
    assert f"2 seeds, {low} to {high} trials" in text


def test_ctrl_c_stopping_the_web_viewer_says_so_not_that_outputs_are_written(tmp_path, capsys, monkeypatch):
    """`show --web` runs until Ctrl-C: that ends it with exit 0 and one line saying the viewer stopped, not the
    study's "interrupted as it finished; its outputs are written"."""
    from cpgjax.studies import viewer as study_viewer

    (tmp_path / "recording.rrd").write_bytes(b"")
    stopped = []

    class Viewer:
        pid = 1

        def wait(self):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
            raise AssertionError("not interrupted")

    monkeypatch.setattr(study_viewer, "serve", lambda recording, port: Viewer())
    monkeypatch.setattr(study_viewer, "stop", stopped.append)
    monkeypatch.setattr(show, "_summarize", lambda args: 0)  # the folder's listing, checked by the tests of show
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert cli.main(["show", str(tmp_path), "--web"]) == 0
    finally:
        signal.signal(signal.SIGINT, previous)
    err = capsys.readouterr().err
    assert "the viewer is stopped" in err and "outputs are written" not in err and len(stopped) == 1


def test_deploy_help_shows_robot_as_required(capsys):
    with pytest.raises(SystemExit):
        cli.main(["deploy", "--help"])
    usage = capsys.readouterr().out.split("\n\n")[0]
    assert usage.startswith("usage: cpgjax deploy --robot {sim,go1} [options]")
    assert "[--robot" not in usage


def test_dry_run_estimates_the_wall_time_from_this_machines_measured_rate(tmp_path, capsys, monkeypatch):
    from cpgjax.study import rate

    monkeypatch.setenv("CPGJAX_CACHE_DIR", str(tmp_path / "cache"))
    argv = ["study", "friction", "--quick", "--dry-run", "--backend", "native", "--out", str(tmp_path / "f")]
    assert cli.main(argv) == 0
    assert "no native study has run on this machine yet, so no wall-time estimate" in capsys.readouterr().out
    # 6 instances × 12 trials × 4,500 steps = 324,000 env-steps; at a measured 5,400 env-steps/s that is 60 s
    rate.record("native", {"env_steps_per_s": 5400.0, "wall_s": 100.0}, "controller_ablation", 8)
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert (
        "324,000 env-steps" in out
        and "about 1.0 min at this machine's latest measured rate (5,400 env-steps/s: "
        "controller_ablation, 8 instances, "
        in out
    )
