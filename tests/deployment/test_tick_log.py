"""The deploy run's per-tick log (``cpgjax.deployment.tick_log``) survives trips, Ctrl-C and kills; Ctrl-C is a stop.

Against the loopback simulated Go1 in lockstep pacing (127.0.0.1 only), so the outcome does not depend on the load.
"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cpgjax import cpg
from cpgjax import hardware_io as hio
from cpgjax.deployment import deploy, tick_log
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.trial import params
from tests.test_outputs import undocumented

LOOP = hio.LoopConfig(
    hold_s=0.1, ramp_s=0.2, end_damping_s=0.05, realtime_priority=None, flush_ticks=250, log_ticks=1000
)


def test_a_trip_keeps_every_tick_up_to_it(tmp_path):
    """A motor over its temperature limit trips the loop; the log read back holds every tick, the trip tick and the
    damping after it, with the same observations and commands as the loop's own record (a ring buffer smaller than
    the run: the file has the ticks the ring no longer holds)."""
    controller = compiled_controller.CompiledController(warmup_calls=10)
    with sim.SimGo1Client(pacing="lockstep") as robot:
        robot.inject("temperature_c", 80, after_ticks=1200)
        transport = go1_transport.LockstepTransport(robot.address)
        with tick_log.TickLogWriter(tmp_path / tick_log.FILE_NAME) as sink:
            result = hio.run_loop(
                transport,
                controller,
                hio.FixedParams(params.midpoint(), 5000),
                deploy.sim_calibration(),
                cpg.controller_gates("vmc_tegotae"),
                LOOP,
                go1_safety.SafetyConfig(),
                sink,
            )
        transport.close()
    assert result.trip is not None and "motor temperature" in result.trip
    table, complete = tick_log.read_tick_log(tmp_path / tick_log.FILE_NAME)
    assert complete and table.num_rows == result.ticks > 1200
    np.testing.assert_array_equal(table["tick"].to_numpy(), np.arange(result.ticks))
    phase = table["phase"].to_numpy()
    trip_tick = next(t for t, name, message in result.events if "motor temperature" in message)
    assert phase[trip_tick] == hio.DAMP and np.all(phase[trip_tick:] == hio.DAMP)
    assert np.any(phase[:trip_tick] == hio.RUN)
    tail = slice(result.ticks - result.log.phase.shape[0], result.ticks)  # what the ring buffer still holds
    np.testing.assert_array_equal(np.stack(table["q_rad"].to_numpy(zero_copy_only=False))[tail], result.log.q_rad)
    np.testing.assert_array_equal(
        np.stack(table["torque_nm"].to_numpy(zero_copy_only=False))[tail], result.log.torque_nm
    )
    damping = np.stack(table["torque_nm"].to_numpy(zero_copy_only=False))[phase == hio.DAMP]
    assert np.all(damping == 0.0) and np.all(table["command_kd"].to_numpy()[phase == hio.DAMP] > 0)


def _start_deploy(log_dir):
    """``cpgjax deploy`` replaying for a minute against a lockstep simulated Go1, in a session of its own (a
    signal to its process group reaches every process, like a terminal's Ctrl-C); returns once a batch is logged."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cpgjax.cli",
            "deploy",
            "--robot",
            "sim",
            "--sim-pacing",
            "lockstep",
            "--duration-s",
            "60",
            "--log-dir",
            str(log_dir),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    path, give_up = log_dir / tick_log.FILE_NAME, time.monotonic() + 240
    while not (path.exists() and tick_log.read_tick_log(path)[0].num_rows >= 2000):
        if proc.poll() is not None or time.monotonic() > give_up:
            proc.kill()
            pytest.fail(f"deploy did not log 2000 ticks: {proc.communicate()[0][-2000:]}")
        time.sleep(0.2)
    return proc


def test_ctrl_c_in_deploy_is_a_stop_with_the_log_flushed(tmp_path):
    proc = _start_deploy(tmp_path)
    os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out[-2000:]
    assert "stopped by Ctrl-C" in out and "Traceback" not in out and "safety trip" not in out
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["trip"] is None and run["stopped"] and run["events"][-1][2] == "stopped (Ctrl-C)"
    assert run["command"] == f"cpgjax deploy --robot sim --sim-pacing lockstep --duration-s 60 --log-dir {tmp_path}"
    assert run["cpgjax_version"] and "git_commit" in run and run["environment"]["cpu_count"] >= 1
    assert undocumented("run.json", run) == []  # docs/outputs.md
    table, complete = tick_log.read_tick_log(tmp_path / tick_log.FILE_NAME)
    assert complete and table.num_rows == run["timing"]["ticks"]
    assert table["phase"].to_numpy()[-1] == hio.DAMP
    summary = tick_log.summarize_run(tmp_path)
    assert "ended: stopped by Ctrl-C" in summary and f"command: {run['command']} (cpgjax " in summary


def test_a_killed_deploy_keeps_its_logged_batches(tmp_path):
    proc = _start_deploy(tmp_path)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    table, _ = tick_log.read_tick_log(tmp_path / tick_log.FILE_NAME)
    assert table.num_rows >= 2000 and table.num_rows % hio.LoopConfig().flush_ticks == 0
    np.testing.assert_array_equal(table["tick"].to_numpy(), np.arange(table.num_rows))
    assert not (tmp_path / "run.json").exists()
    summary = tick_log.summarize_run(tmp_path)
    assert "ended: unknown: no run.json" in summary and f"{table.num_rows} ticks" in summary


# A parameter file's parameters and what they were tuned for, none of them deploy's defaults.
REPLAYED = {
    "ground_clearance_m": 0.085,
    "ground_penetration_m": 0.012,
    "omega_swing_rad_s": 20.5,
    "omega_stance_rad_s": 12.0,
    "amplitude_mu": 1.2,
    "x_offset_front_m": -0.03,
    "x_offset_hind_m": -0.04,
    "sigma_n": 0.2,
}
TUNED_FOR = dict(
    controller="tegotae",
    gait="trot",
    physics="paper",
    friction=0.8,
    slope_deg=2.0,
    payload_kg=1.5,
    target_velocity_mps=0.4,
)


def test_a_replay_on_the_simulated_go1_logs_its_true_state_beside_the_estimate(tmp_path):
    """``deploy --robot sim --params FILE`` writes the simulated Go1's true trunk state per physics step
    (sim_truth.parquet) and each trial's true velocity and distance beside the robot's leg-odometry estimate, in
    trials.parquet, run.json and the printed lines. The true distance is checked against the trunk's displacement
    read from the file directly. run.json's ``ran`` holds what was walked: the file's parameters, its controller,
    physics and conditions, but the friction given on the command line."""
    import pyarrow.parquet as pq

    params_file = tmp_path / "tuned.json"
    params_file.write_text(json.dumps({"params": REPLAYED, **TUNED_FOR}))
    run_dir = tmp_path / "run"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "cpgjax.cli",
            "deploy",
            "--robot",
            "sim",
            "--sim-pacing",
            "lockstep",
            "--params",
            str(params_file),
            "--friction",
            "0.9",
            "--duration-s",
            "9.5",
            "--log-dir",
            str(run_dir),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    truth = pq.read_table(run_dir / deploy.TRUTH_FILE)
    assert undocumented("sim_truth.parquet", truth.column_names) == []
    ticks, _ = tick_log.read_tick_log(run_dir / tick_log.FILE_NAME)
    assert truth.num_rows >= ticks.num_rows - 2  # a physics step for every loop tick (lockstep)
    rows = pq.read_table(run_dir / "trials.parquet").to_pylist()
    assert [r["trial"] for r in rows] == [0, 1]
    assert undocumented("robot trials.parquet", rows[0]) == []
    run_ticks = ticks["robot_tick_ms"].to_numpy()[ticks["phase"].to_numpy() == hio.RUN]
    x = dict(zip(truth["tick_ms"].to_numpy(), truth["x_m"].to_numpy(), strict=True))
    for r in rows:
        first, last = run_ticks[r["trial"] * 4500 + 1500], run_ticks[r["trial"] * 4500 + 4499]
        assert r["true_distance_m"] == pytest.approx(x[last] - x[first], rel=0.05, abs=0.02)
        assert r["true_velocity_x_mps"] == pytest.approx(r["true_distance_m"] / 3.0, rel=1e-3)
        assert r["velocity_x_mps"] == pytest.approx(r["true_velocity_x_mps"], rel=0.25)  # odometry: an estimate
    run = json.loads((run_dir / "run.json").read_text())
    assert run["trials"][1]["true_velocity_x_mps"] == pytest.approx(rows[1]["true_velocity_x_mps"])
    assert undocumented("run.json", run) == []
    assert run["ran"] == {
        **TUNED_FOR,
        "friction": 0.9,
        "mode": "replay",
        "robot": "sim",
        "startup": "paper",
        "transition_s": 1.5,
        "steady_s": 3.0,
        "duration_s": 9.5,
        "num_trials": None,
        "optimizer": None,
        "seed": 0,
        "params_file": str(params_file),
        "params": REPLAYED,
        "trial_params": None,
    }
    # the outcome on stdout, the progress on stderr
    assert "(the simulated Go1's truth: v_x" in out.stdout and "how the robot walked" in out.stdout
    assert "overruns         do not apply: lockstep pacing" in out.stdout
    assert "how the robot walked" not in out.stderr


@pytest.mark.parametrize(
    "overruns, causes, verdict",
    [
        (1, (1, 0, 0), "verdict: met the loop's target of at most 1 per 10k ticks"),
        (2, (0, 0, 2), "verdict: missed the loop's target of at most 1 per 10k ticks (2.00); most were work cpu: "),
        (
            30,
            (25, 5, 0),
            "verdict: missed the loop's target of at most 1 per 10k ticks (30.00); most were late start: --busy-wait",
        ),
    ],
)
def test_the_timing_says_whether_the_overruns_met_the_loops_target(overruns, causes, verdict):
    timing = {
        "ticks": 10_000,
        "overruns": overruns,
        "overruns_per_10k_ticks": float(overruns),
        **{f"overruns_{name}": n for name, n in zip(hio.OVERRUN_CAUSES, causes, strict=True)},
        **{f"{k}_{q}_us": 100.0 for k in ("step", "work", "period") for q in ("median", "p99", "max")},
    }
    assert hio.timing_table(timing).splitlines()[-1].startswith(verdict)
