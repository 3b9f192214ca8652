"""The 1 kHz deployment loop through the loopback simulated Go1 (127.0.0.1, ephemeral ports only).

One simulated Go1 process in lockstep pacing (one physics step per command) serves every test, and the loop's
transport waits for the answer to its last command before each tick (``LockstepTransport``), so the loop, its
observations and the physics advance together however loaded this machine is; each test resets the simulated Go1 and
injects its fault from the control port. No test asserts real-time figures: those are in
benchmarks/hardware_loop.py.
"""

import json
import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import cli, cpg
from cpgjax import hardware_io as hio
from cpgjax.deployment import calibrate, deploy, tick_log
from cpgjax.deployment import trials as robot_trials
from cpgjax.go1 import constants
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import foot_force, wire
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.trial import objective, params, protocol, tuned
from tests.test_outputs import undocumented

GATES = cpg.controller_gates("vmc_tegotae")
# Short soft start; a watchdog long enough for a loaded CI machine (the stale-state test shortens it).
LOOP = hio.LoopConfig(hold_s=0.1, ramp_s=0.2, end_damping_s=0.05, realtime_priority=None)
SAFETY = go1_safety.SafetyConfig(watchdog_ticks=100)
RUN_STARTS_AT = 300  # server ticks: connect 1 + hold 100 + ramp 200


@pytest.fixture(scope="module")
def controller():
    return compiled_controller.CompiledController()


@pytest.fixture(scope="module")
def robot():
    with sim.SimGo1Client(pacing="lockstep") as server:
        yield server


def _run(robot, controller, run_ticks=600, fault=None, safety=SAFETY, schedule=None, transport=None):
    robot.reset()
    if fault is not None:
        kind, value, ticks = fault
        robot.inject(kind, value, after_ticks=RUN_STARTS_AT + 100, ticks=ticks)
    transport = transport or go1_transport.LockstepTransport(robot.address)
    try:
        result = hio.run_loop(
            transport,
            controller,
            schedule or hio.FixedParams(params.midpoint(), run_ticks),
            deploy.sim_calibration(),
            GATES,
            LOOP,
            safety,
        )
    finally:
        transport.close()
    return result, transport, robot.stats()


def _assert_damped_after_trip(result, stats, reason):
    assert result.trip is not None and reason in result.trip, result.events
    assert result.events[-1][1] == "damp"
    assert stats["damping_commands"] > 0  # the robot received damping after the trip
    assert stats["bad_packets"] == 0 and stats["min_kp_cmd"] >= 0.0 and stats["max_abs_tau_cmd_nm"] <= 35.55


def _stale_run_ticks(result) -> int:
    return int(np.sum(~result.log.fresh & (result.log.phase == hio.RUN)))


# ------------------------------------------------------------------------------------- tolerated faults


@pytest.mark.parametrize("kind, value", [("drop", True), ("late_ms", 3.0), ("corrupt_crc", True), ("wrong_head", True)])
def test_short_packet_faults_are_ridden_out(robot, controller, kind, value):
    result, transport, stats = _run(robot, controller, fault=(kind, value, 5))
    assert result.trip is None, result.events
    if kind in ("corrupt_crc", "wrong_head"):
        assert transport.rejected["crc" if kind == "corrupt_crc" else "head"] >= 5
    if kind in ("drop", "corrupt_crc", "wrong_head"):
        assert _stale_run_ticks(result) >= 5  # the loop noticed and reused the last state


# ------------------------------------------------------------------------------------- trips → damping


def test_stale_tick_trips_the_watchdog(robot, controller):
    result, _, stats = _run(
        robot, controller, run_ticks=5000, fault=("freeze_tick", True, 10**6), safety=SAFETY._replace(watchdog_ticks=20)
    )
    _assert_damped_after_trip(result, stats, "stale state")


def test_persistent_corrupt_crc_trips_the_watchdog(robot, controller):
    result, transport, stats = _run(
        robot, controller, run_ticks=5000, fault=("corrupt_crc", True, 10**6), safety=SAFETY._replace(watchdog_ticks=20)
    )
    _assert_damped_after_trip(result, stats, "stale state")
    assert transport.rejected["crc"] >= 20


def test_tilt_beyond_the_threshold_damps(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=5000, fault=("push_roll_nm", 60.0, 10**6))
    _assert_damped_after_trip(result, stats, "tilt")


def test_remote_stop_buttons_damp(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=5000, fault=("buttons", ["L2", "B"], 10**6))
    _assert_damped_after_trip(result, stats, "remote stop")


def test_one_stop_button_alone_does_not_stop(robot, controller):
    result, _, _ = _run(robot, controller, fault=("buttons", ["B"], 10**6))
    assert result.trip is None


def test_nan_command_is_never_sent(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=5000, fault=("nan_q", True, 10**6))
    _assert_damped_after_trip(result, stats, "non-finite command")


def test_power_protection_trips(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=5000, fault=("power", True, 10**6))
    _assert_damped_after_trip(result, stats, "power protection")


def test_motor_temperature_limit_damps(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=5000, fault=("temperature_c", 80, 10**6))
    _assert_damped_after_trip(result, stats, "motor temperature")


class _CtrlCAt(hio.FixedParams):
    def record(self, run_tick, out):
        if run_tick == 100:
            signal.raise_signal(signal.SIGINT)


def test_ctrl_c_is_a_stop_to_damping_not_a_trip(robot, controller):
    result, _, stats = _run(robot, controller, schedule=_CtrlCAt(params.midpoint()))
    assert result.trip is None and result.stopped, result.events
    assert result.events[-1][1:] == ("damp", "stopped (Ctrl-C)")
    assert stats["damping_commands"] > 0 and stats["max_abs_tau_cmd_nm"] <= 35.55


class _StallAt(hio.FixedParams):
    """Blocks the loop thread (sleeping, so not on the CPU) for ``stall_s`` at one run tick."""

    def __init__(self, params, run_ticks, stall_tick, stall_s):
        super().__init__(params, run_ticks)
        self.stall_tick, self.stall_s = stall_tick, stall_s

    def record(self, run_tick, out):
        super().record(run_tick, out)
        if run_tick == self.stall_tick:
            time.sleep(self.stall_s)


def test_a_stalled_tick_is_an_overrun_of_the_thread_not_running(robot, controller):
    result, _, _ = _run(robot, controller, run_ticks=300, schedule=_StallAt(params.midpoint(), 300, 100, 0.03))
    log = result.log
    assert result.overruns == int(np.sum(log.overrun)) >= 1  # every tick is logged here
    stalled = int(np.flatnonzero(log.phase == hio.RUN)[100])
    assert log.overrun[stalled] and log.work_s[stalled] >= 0.03 and log.work_cpu_s[stalled] < 0.02
    cause = hio.overrun_causes(log)[list(np.flatnonzero(log.overrun)).index(stalled)]
    assert hio.OVERRUN_CAUSES[cause] == "not_running"
    assert result.skipped_ticks >= 25  # the missed deadlines were dropped, not run in a burst ...
    assert 0.0 <= log.late_s[stalled + 1] < LOOP.period_s  # ... so the next tick starts less than a period late
    timing = result.timing()
    assert sum(timing[f"overruns_{name}"] for name in hio.OVERRUN_CAUSES) == result.overruns


def test_overrun_causes_name_the_largest_share_of_the_tick():
    n = 4
    log = hio.TickLog.allocate(n)._replace(
        late_s=np.array([0.9e-3, 0.0, 0.1e-3, 0.0], np.float32),  # woke late
        work_s=np.array([0.3e-3, 1.5e-3, 1.2e-3, 0.2e-3], np.float32),
        work_cpu_s=np.array([0.3e-3, 0.2e-3, 1.1e-3, 0.2e-3], np.float32),  # 1.3 ms not running; 1.1 ms of CPU
        overrun=np.array([True, True, True, False]),
    )
    assert [hio.OVERRUN_CAUSES[c] for c in hio.overrun_causes(log)] == ["late_start", "not_running", "work_cpu"]


_BLOCKING_WAITS = """
import logging, sys, numpy as np
logging.basicConfig(level=logging.WARNING)
if sys.argv[1] == "late":
    import jax.numpy as jnp
    jnp.zeros(1).block_until_ready()  # the CPU client exists before the controller asks for inline dispatch
from cpgjax import hardware_io as hio
from cpgjax.robot import controller as compiled_controller
controller = compiled_controller.CompiledController(warmup_calls=10)
x = compiled_controller.INPUT.zeros()
compiled_controller.INPUT.unravel(x).obs.imu_quat_wxyz[0] = 1.0
def waits():
    return int(next(l for l in open("/proc/thread-self/status") if l.startswith("voluntary_ctxt")).split()[1])
before = waits()
for _ in range(500):
    controller.step(x)
print(controller.inline_dispatch, waits() - before)
"""


@pytest.mark.skipif(not os.path.exists("/proc/thread-self/status"), reason="counts context switches from /proc")
@pytest.mark.parametrize("when", ["first", "late"])
def test_the_controller_step_runs_on_the_loop_thread_unless_jax_computed_first(when):
    """The loop thread must not block on an XLA worker thread in each step (priority inversion): with inline CPU
    dispatch its 500 steps make (almost) no voluntary context switch; a process that computed with JAX before the
    controller keeps asynchronous dispatch, which the controller reports and warns about."""
    out = subprocess.run(
        [sys.executable, "-c", _BLOCKING_WAITS, when],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert out.returncode == 0, out.stderr
    inline, waits = out.stdout.split()
    if when == "first":
        assert inline == "True" and int(waits) <= 5  # measured 0; with asynchronous dispatch 280–650 on 2 cores
    else:  # how often the loop thread then blocks depends on the machine (a worker may finish within Eigen's spin)
        assert inline == "False" and "asynchronous dispatch" in out.stderr


def test_no_robot_gives_up_after_the_connect_timeout(controller):
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))  # a port where nobody answers
        transport = go1_transport.UdpTransport(silent.getsockname())
        result = hio.run_loop(
            transport,
            controller,
            hio.FixedParams(params.midpoint(), 10),
            deploy.sim_calibration(),
            GATES,
            LOOP._replace(connect_timeout_s=0.05),
            SAFETY,
        )
        transport.close()
    assert result.trip.startswith("no robot state")


def test_busy_wait_loop_never_sleeps(robot, controller, monkeypatch):
    sleeps = []
    monkeypatch.setattr(hio.time, "sleep", lambda s: sleeps.append(s))
    transport = go1_transport.LockstepTransport(robot.address)
    robot.reset()
    try:
        result = hio.run_loop(
            transport,
            controller,
            hio.FixedParams(params.midpoint(), 200),
            deploy.sim_calibration(),
            GATES,
            LOOP._replace(busy_wait=True),
            SAFETY,
        )
    finally:
        transport.close()
    assert result.trip is None and "busy-wait" in result.realtime and result.ticks > 500
    assert sleeps == []


def test_busy_wait_at_realtime_priority_is_refused_while_the_kernel_throttles(controller, monkeypatch):
    """A SCHED_FIFO thread that never sleeps would be stopped for 50 ms every second by the kernel's real-time
    throttling: refused before anything is sent, with the setting named."""
    monkeypatch.setattr(hio, "rt_throttling", lambda: (950_000, 1_000_000))
    transport = go1_transport.UdpTransport(("127.0.0.1", 9))  # never used: refused before the first tick
    with pytest.raises(ValueError, match=r"sched_rt_runtime_us = 950000.*50 ms every 1000 ms"):
        hio.run_loop(
            transport,
            controller,
            hio.FixedParams(params.midpoint(), 10),
            deploy.sim_calibration(),
            GATES,
            LOOP._replace(busy_wait=True, realtime_priority=80),
            SAFETY,
        )
    transport.close()
    monkeypatch.setattr(hio, "rt_throttling", lambda: None)  # throttling off: allowed (priority where permitted)
    transport = go1_transport.UdpTransport(("127.0.0.1", 9))
    result = hio.run_loop(
        transport,
        controller,
        hio.FixedParams(params.midpoint(), 10),
        deploy.sim_calibration(),
        GATES,
        LOOP._replace(busy_wait=True, realtime_priority=80, connect_timeout_s=0.02),
        SAFETY,
    )
    transport.close()
    assert result.trip.startswith("no robot state")
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # restored after the loop


# ------------------------------------------------------------------------------------- guards and units


def test_guard_clamps_before_encoding_and_refuses_nan():
    safety = go1_safety.SafetyConfig()
    cmd = go1_safety.pd_command(np.full(12, 5.0), kp=500.0, kd=-1.0)._replace(tau_nm=np.full(12, 200.0))
    guarded, reason = go1_safety.guard_command(cmd, safety)
    assert reason is None
    np.testing.assert_array_equal(guarded.tau_nm, constants.TORQUE_LIMIT_NM)
    np.testing.assert_array_equal(guarded.kp_nm_rad, safety.kp_max_nm_rad)
    np.testing.assert_array_equal(guarded.kd_nm_s_rad, 0.0)
    np.testing.assert_array_equal(guarded.q_rad, np.minimum(5.0, constants.JOINT_UPPER_RAD))
    wire.encode_low_cmd(guarded)  # encodable: nothing would wrap
    torque_mode, _ = go1_safety.guard_command(go1_safety.torque_command(np.zeros(12)), safety)
    assert np.all(torque_mode.q_rad == wire.POS_STOP_F)  # the stop marker survives (position term stays off)
    _, reason = go1_safety.guard_command(go1_safety.torque_command(np.full(12, np.nan)), safety)
    assert reason == "non-finite command (tau)"


def test_power_protection_counts_like_the_sdk():
    safety = go1_safety.SafetyConfig(power_level=1)
    hot = wire.RobotState(
        0,
        np.array([1.0, 0, 0, 0]),
        np.zeros(3),
        np.zeros(3),
        np.zeros(3),
        np.full(12, 10, np.uint8),
        np.zeros(12),
        np.full(12, 1.0),
        np.full(12, 10.0),
        np.zeros(12),
        np.zeros(4),
        bytes(40),
    )  # 120 W > 100 W
    cold = hot._replace(dq_rad_s=np.zeros(12))
    counter, reasons = 0, []
    for state in [hot] * 5 + [cold] + [hot] * 2:
        counter, reason = go1_safety.power_protect(counter, state, safety)
        reasons.append(reason)
    assert reasons[:7] == [None] * 7 and reasons[7] is not None  # 5 up, 1 down, 2 up → 6


def test_foot_force_calibration_recovers_the_simulated_sensor(tmp_path):
    rng = np.random.default_rng(0)
    weight_n = 12.74 * 9.81
    true = deploy.sim_calibration()
    air = true.offset_counts + rng.integers(-2, 3, (201, 4))  # symmetric sensor noise: the minimum would be biased
    standing = true.offset_counts + np.round(weight_n / 4 / true.newton_per_count) + rng.integers(-2, 3, (500, 4))
    cal = foot_force.calibrate_foot_force(air, standing, 12.74)
    np.testing.assert_allclose(cal.offset_counts, true.offset_counts)
    np.testing.assert_allclose(cal.newton_per_count, true.newton_per_count, rtol=0.02)
    cal.save(tmp_path / "cal.json")
    np.testing.assert_array_equal(
        foot_force.FootForceCalibration.load(tmp_path / "cal.json").offset_counts, cal.offset_counts
    )


# ------------------------------------------------------------------------------------- parity and walking


def _rollout_torques(obs_sequence: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Torques of the MJX rollout's controller path (``cpg.controller_step`` vmapped over instances and scanned
    over ticks, as in ``mjx_go1``) for a given flat observation sequence (T, OBSERVATION.size)."""

    def rollout(obs_seq, p_inst, gates):
        state0 = cpg.init_state(compiled_controller.OBSERVATION.unravel(obs_seq[0]))

        def body(state, x):
            state, torque, _ = cpg.controller_step(
                cpg.CPGConfig(), state, p_inst, gates, compiled_controller.OBSERVATION.unravel(x)
            )
            return state, torque

        return jax.lax.scan(body, state0, obs_seq)[1]

    batched = jax.jit(jax.vmap(rollout))(
        jnp.asarray(obs_sequence)[None], jnp.asarray(p, jnp.float32)[None], protocol.check_gates(GATES, 1)
    )
    return np.asarray(batched[0])


def test_loop_torques_equal_the_rollout_for_the_same_observations(robot, controller):
    result, _, _ = _run(robot, controller, run_ticks=800)
    run = result.log.phase == hio.RUN
    obs, loop_torque = result.log.obs[run], result.log.controller_torque_nm[run]
    assert obs.shape[0] == 800
    expected = _rollout_torques(obs, params.midpoint())
    np.testing.assert_allclose(loop_torque, expected, rtol=1e-4, atol=1e-3)
    sent = result.log.torque_nm[run]  # after the guard; the wire then truncates to 1/256 N·m
    np.testing.assert_allclose(
        sent, np.clip(expected, -constants.TORQUE_LIMIT_NM, constants.TORQUE_LIMIT_NM), atol=1e-3
    )


def test_the_simulated_go1_walks_forward_under_the_deployed_controller(robot, controller):
    result, _, stats = _run(robot, controller, run_ticks=2500)
    assert result.trip is None
    assert stats["trunk_xy_m"][0] > 0.5 and abs(stats["trunk_xy_m"][1]) < 0.3  # ≈ 0.5 m/s for 2.5 s
    assert stats["trunk_height_m"] > 0.2  # still standing when the run ended (then damping for 50 ms)


def test_the_official_sdk_drives_the_simulated_go1(robot, controller):
    pytest.importorskip("unitree_legged_sdk.robot_interface")
    transport = go1_transport.SdkTransport("127.0.0.1", robot.port, deploy._free_port(), power_level=9)
    result, _, stats = _run(robot, controller, run_ticks=1000, transport=transport)
    assert result.trip is None, result.events
    assert stats["trunk_xy_m"][0] > 0.2 and stats["bad_packets"] == 0


def test_a_replay_reports_how_the_robot_walked_in_each_trial(robot, controller):
    """A replay cut into trials (0.3 s settling + 0.6 s measured): two complete trials in 2000 ticks, each with J,
    velocity, distance and CoT from the robot's own sensors; the distance is the velocity times the measured time
    (Σ v_x Δt = mean v_x · T)."""
    replay = robot_trials.ReplayTrials(params.midpoint(), 2000, protocol.TrialConfig(300, 600))
    result, _, _ = _run(robot, controller, schedule=replay)
    assert result.trip is None, result.events
    tuned_for = dict(
        controller="vmc_tegotae",
        gait="trot",
        physics="go1",
        friction=0.6,
        slope_deg=0.0,
        payload_kg=0.0,
        target_velocity_mps=0.5,
    )
    rows = replay.rows(12.74, 0.5, 0, tuned_for)
    assert [r["trial"] for r in rows] == [0, 1]
    for r in rows:
        assert r["velocity_x_mps"] > 0.2 and r["cost_of_transport"] > 0.0 and np.isfinite(r["objective"])
        assert r["distance_m"] == pytest.approx(r["velocity_x_mps"] * 0.6, rel=1e-4)
        assert r["controller"] == "vmc_tegotae" and undocumented("robot trials.parquet", r) == []


def test_online_optimization_of_a_few_short_trials(robot, controller, tmp_path):
    """Random search stands in for the contextual BO (cpgjax.optim.bo) until that lands."""
    robot.reset()
    transport = go1_transport.LockstepTransport(robot.address)
    tuned_for = dict(
        controller="vmc_tegotae",
        gait="trot",
        physics="go1",
        friction=0.6,
        slope_deg=0.0,
        payload_kg=0.0,
        target_velocity_mps=0.5,
    )
    spec = robot_trials.OptimizerSpec("random", 0, 0.5, True, 12.74, str(tmp_path), tuned_for)
    try:
        result, rows, _ = robot_trials.online_optimization(
            transport,
            controller,
            deploy.sim_calibration(),
            GATES,
            spec,
            params.midpoint(),
            3,
            protocol.TrialConfig(300, 600),
            LOOP,
            SAFETY,
        )
    finally:
        transport.close()
    assert result.trip is None, result.events
    assert [r["trial"] for r in rows] == [0, 1, 2]
    assert all(np.isfinite(r["objective"]) and 15.0 < r["c_load_n"] < 50.0 for r in rows)
    assert rows[0]["velocity_x_mps"] > 0.2  # the midpoint gait walks forward (leg odometry)
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "trials.parquet")
    assert table.num_rows == 3 and undocumented("robot trials.parquet", table.schema.names) == []
    assert table["controller"].to_pylist() == ["vmc_tegotae"] * 3 and table["fell"].to_pylist() == [False] * 3
    assert (tmp_path / "trials.rrd").stat().st_size > 0
    best, recorded, _ = tuned.load(tmp_path / "best_params.json")
    assert recorded == tuned_for
    best_row = rows[int(np.argmax([r["objective"] for r in rows]))]
    np.testing.assert_allclose(best, [best_row[name] for name in params.PARAM_NAMES])
    replay, _, _ = _run(robot, controller, run_ticks=300, schedule=hio.FixedParams(best, 300))
    assert replay.trip is None


def _optimize_with_a_fault(robot, controller, tmp_path, kind, value, recover):
    """Three short trials of random search with a fault injected 200 ticks into trial 1 (after trial 0's 900 and its
    wait for a proposal, a few ticks in lockstep)."""
    robot.reset()
    robot.inject(kind, value, after_ticks=RUN_STARTS_AT + 900 + 200, ticks=10**6)
    transport = go1_transport.LockstepTransport(robot.address)
    tuned_for = dict(
        controller="vmc_tegotae",
        gait="trot",
        physics="go1",
        friction=0.6,
        slope_deg=0.0,
        payload_kg=0.0,
        target_velocity_mps=0.5,
    )
    spec = robot_trials.OptimizerSpec("random", 0, 0.5, True, 12.74, str(tmp_path), tuned_for)
    try:
        return robot_trials.online_optimization(
            transport,
            controller,
            deploy.sim_calibration(),
            GATES,
            spec,
            params.midpoint(),
            3,
            protocol.TrialConfig(300, 600),
            LOOP,
            SAFETY,
            recover=recover,
        )
    finally:
        transport.close()


def test_a_tilt_stop_during_online_optimization_is_an_unsafe_trial_then_the_robot_stands_up(
    robot, controller, tmp_path
):
    """docs/decisions.md §17: the stop ends trial 1 as fallen, with a margin ≤ 0 and J at its minimum; the robot is
    put back on its feet (here the simulated Go1's reset, which also ends the push), stands up through the soft start
    and walks trial 2."""
    calls = []

    def recover(trial, reason):
        calls.append((trial, reason))
        robot.reset()
        return True

    result, rows, windows = _optimize_with_a_fault(robot, controller, tmp_path, "push_roll_nm", 60.0, recover)
    assert result.trip is None, result.events
    assert [trial for trial, _ in calls] == [1] and calls[0][1].startswith("tilt:")
    assert [(tick, reason) for tick, reason in result.safety_stops] == [(result.safety_stops[0][0], calls[0][1])]
    assert [r["trial"] for r in rows] == [0, 1, 2]
    assert [r["fell"] for r in rows] == [False, True, False]
    assert [r["safety_stop"] for r in rows] == [None, calls[0][1], None]
    assert rows[1]["safety_margin"] <= 0.0 < min(rows[0]["safety_margin"], rows[2]["safety_margin"])
    assert rows[1]["objective"] == pytest.approx(objective.MIN_OBJECTIVE)
    assert rows[2]["velocity_x_mps"] > 0.2  # it walks again after standing up
    messages = [message for _, _, message in result.events]
    assert messages.count("first robot state; holding the measured pose") == 2  # two loops, each with a soft start
    assert len(windows) == 2 and windows[0][1] < windows[1][0]  # trials 0 and 2, in run ticks of the whole run
    assert result.ticks == sum(1 for _ in result.log.phase) and len(result.loop_starts) == 2
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "trials.parquet")
    assert table["fell"].to_pylist() == [False, True, False]
    assert undocumented("robot trials.parquet", table.schema.names) == []


def test_upright_puts_the_simulated_go1_back_at_the_origin_while_its_clock_runs_on(robot, controller):
    result, _, _ = _run(robot, controller, run_ticks=600)
    assert result.trip is None
    walked = robot.stats()
    robot.upright()
    after = robot.stats()
    assert after["tick"] == walked["tick"] > 0 and after["commands"] == walked["commands"]
    assert np.abs(walked["trunk_xy_m"]).max() > 0.02 and np.abs(after["trunk_xy_m"]).max() < 1e-9


def test_deploys_recovery_asks_the_operator_on_the_robot_and_rights_the_simulated_go1(monkeypatch):
    class Server:
        uprights = 0

        def upright(self):
            Server.uprights += 1

    assert deploy.stand_up(Server())(1, "tilt: …") and Server.uprights == 1
    prompts = []
    monkeypatch.setattr("builtins.input", lambda prompt: prompts.append(prompt) or "")
    assert deploy.stand_up(None)(4, "tilt: roll +0.9 rad") and "trial 4" in prompts[0] and "Enter" in prompts[0]
    for interruption in (EOFError, KeyboardInterrupt):

        def refuse(prompt, interruption=interruption):
            raise interruption

        monkeypatch.setattr("builtins.input", refuse)
        assert not deploy.stand_up(None)(4, "tilt: roll +0.9 rad")


def test_a_stop_not_caused_by_the_gait_still_ends_an_online_optimization(robot, controller, tmp_path):
    calls = []
    result, rows, _ = _optimize_with_a_fault(
        robot, controller, tmp_path, "buttons", ["L2", "B"], lambda trial, reason: calls.append(trial) or True
    )
    assert result.trip is not None and "remote stop" in result.trip and calls == []
    assert [r["trial"] for r in rows] == [0] and not rows[0]["fell"] and result.safety_stops == ()


def test_deploy_optimize_starts_from_the_optimizers_random_proposal(tmp_path):
    """docs/decisions.md §16 on the robot: without --params, trial 0 walks the contextual BO's first proposal (random,
    nothing stored yet), not the box's midpoint; the command finishes cleanly and its best_params.json replays."""
    import pyarrow.parquet as pq

    run = tmp_path / "run"
    code = cli.main(
        [
            "deploy",
            "--robot",
            "sim",
            "--sim-pacing",
            "lockstep",
            "--no-realtime",
            "--optimize",
            "--trials",
            "2",
            "--transition-s",
            "0.1",
            "--steady-s",
            "0.2",
            "--seed",
            "3",
            "--log-dir",
            str(run),
        ]
    )
    assert code == 0
    table = pq.read_table(run / "trials.parquet").to_pydict()
    first = np.array([table[name][0] for name in params.PARAM_NAMES])
    reference = robot_trials.BayesianOptimizer(3, True).propose(np.zeros(2))  # a fresh optimizer's first draw
    np.testing.assert_allclose(first, reference, rtol=1e-6)
    assert not np.allclose(first, params.midpoint())
    assert np.all((first >= params.PARAM_LOWER) & (first <= params.PARAM_UPPER))
    replayed = tuned.load(run / "best_params.json")
    assert replayed.params.shape == (8,)
    assert replayed.tuned_for == dict(
        controller="vmc_tegotae",
        gait="trot",
        physics="go1",
        friction=0.6,
        slope_deg=0.0,
        payload_kg=0.0,
        target_velocity_mps=0.5,
    )  # deploy's defaults, all recorded


# ------------------------------------------------------------------------------------- foot-force calibration


def test_calibration_measured_through_the_simulated_go1_recovers_its_sensor(robot, tmp_path):
    def lifted(hung_up):
        if hung_up:
            robot.reset()
            robot.lift(0.3)
        else:
            robot.reset()

    transport = go1_transport.LockstepTransport(robot.address)
    try:
        m = calibrate.measure(
            transport, deploy.robot_mass_kg(0.0), lifted, air_s=0.3, stand_s=0.5, settle_s=0.3, loop=LOOP, safety=SAFETY
        )
    finally:
        transport.close()
    true = deploy.sim_calibration()
    assert len(m.air_counts) >= 250 and len(m.standing_counts) >= 450
    np.testing.assert_array_equal(m.calibration.offset_counts, true.offset_counts)  # feet in the air: zero force
    np.testing.assert_allclose(m.calibration.newton_per_count, true.newton_per_count, rtol=0.02)
    assert np.all(np.mean(m.standing_counts, axis=0) > true.offset_counts + 40)  # every foot carried load


def test_deploy_calibrate_command_writes_the_file_the_loop_loads(tmp_path):
    out = tmp_path / "cal.json"
    code = cli.main(
        [
            "deploy",
            "calibrate",
            "--robot",
            "sim",
            "--sim-pacing",
            "lockstep",
            "--no-realtime",
            "--out",
            str(out),
            "--air-s",
            "0.3",
            "--stand-s",
            "0.5",
            "--settle-s",
            "0.3",
        ]
    )
    assert code == 0
    cal = foot_force.FootForceCalibration.load(out)
    np.testing.assert_array_equal(cal.offset_counts, deploy.sim_calibration().offset_counts)
    np.testing.assert_allclose(cal.newton_per_count, deploy.sim_calibration().newton_per_count, rtol=0.02)
    info = json.loads(out.read_text())
    assert info["robot"] == "sim" and info["air_samples"] >= 250 and info["standing_samples"] >= 450
    # Each stand's per-tick log, as a deploy run keeps one: the air stand's feet carry nothing, the standing
    # stand's carry the robot (raw counts well above their offsets).
    logs = calibrate.tick_log_paths(out)
    feet = {}
    for stand, path in logs.items():
        table, complete = tick_log.read_tick_log(path)
        phase = table["phase"].to_numpy()
        assert complete and np.any(phase == hio.STAND) and phase[-1] == hio.DAMP
        raw = np.stack(table["foot_force_raw"].to_numpy(zero_copy_only=False))[phase == hio.STAND]
        feet[stand] = np.mean(raw, axis=0) - deploy.sim_calibration().offset_counts
    assert np.all(np.abs(feet["air"]) < 2) and np.all(feet["standing"] > 20), feet
    # A second calibration into the same name is refused before anything moves (its tick logs included).
    out.unlink()
    assert cli.main(["deploy", "calibrate", "--robot", "sim", "--sim-pacing", "lockstep", "--out", str(out)]) == 2


def test_go1_profile_foot_sensor_is_recovered_by_deploy_calibrate(tmp_path):
    """The loopback Go1 under the go1 physics profile (latency, envelope, joint friction, quantized counts of the
    contact normal force): the calibration recovers the simulated sensor's offsets and scale."""
    out = tmp_path / "cal.json"
    code = cli.main(
        [
            "deploy",
            "calibrate",
            "--robot",
            "sim",
            "--physics",
            "go1",
            "--sim-pacing",
            "lockstep",
            "--no-realtime",
            "--out",
            str(out),
            "--air-s",
            "0.3",
            "--stand-s",
            "0.5",
            "--settle-s",
            "0.3",
        ]
    )
    assert code == 0
    cal = foot_force.FootForceCalibration.load(out)
    np.testing.assert_array_equal(cal.offset_counts, sim.FOOT_FORCE_OFFSET_COUNTS)
    np.testing.assert_allclose(cal.newton_per_count, sim.FOOT_FORCE_N_PER_COUNT, rtol=0.02)


def test_the_compiled_step_guards_its_torque_as_the_safety_guard_does(controller):
    """The run phase's guard runs inside the compiled step (one dispatch a tick): its torque and finiteness flag
    must be what ``safety.guard_command`` makes of the controller's torque command, saturated and NaN alike."""
    rng = np.random.default_rng(0)
    layout, result = compiled_controller.INPUT, compiled_controller.OUTPUT
    x = layout.zeros()
    inputs = layout.unravel(x)
    inputs.params[:] = params.midpoint()
    inputs.gates.vmc[...] = inputs.gates.tegotae[...] = 1.0
    clipped = 0
    for k in range(40):
        x[layout.slices.obs] = rng.normal(0.0, 3.0, compiled_controller.OBSERVATION.size)
        inputs.obs.imu_quat_wxyz[:] /= np.linalg.norm(inputs.obs.imu_quat_wxyz)
        if k == 39:
            inputs.obs.joint_pos_rad[3] = np.nan
        out = result.unravel(controller.step(x))
        torque = out.torque_nm.astype(np.float64)
        guarded, reason = go1_safety.guard_command(go1_safety.torque_command(torque), SAFETY)
        assert bool(out.finite) == (reason is None)
        if reason is None:
            np.testing.assert_allclose(out.guarded_torque_nm, guarded.tau_nm, rtol=1e-6)
            clipped += int(np.any(np.abs(torque) > constants.TORQUE_LIMIT_NM))
    assert reason is not None and clipped > 0  # both cases were exercised


def test_the_simulated_go1_motor_law():
    """The compiled motor law against the SDK's motor law written out per motor (docs/go1-sdk.md §1.8): servo
    τ = tau + Kp (q* − q) + Kd (dq* − dq), the position term off at PosStopF, the velocity term off at VelStopF,
    damping mode −20 dq, clipped to the motor limits."""
    rng = np.random.default_rng(1)
    q, dq = rng.normal(0, 1, 12), rng.normal(0, 5, 12)
    mode = np.where(np.arange(12) % 5 == 4, wire.MODE_DAMPING, wire.MODE_SERVO).astype(np.uint8)
    q_cmd = np.where(np.arange(12) % 3 == 0, wire.POS_STOP_F, rng.normal(0, 1, 12))
    dq_cmd = np.where(np.arange(12) % 4 == 1, wire.VEL_STOP_F, rng.normal(0, 2, 12))
    cmd = wire.MotorCommand(mode, q_cmd, dq_cmd, rng.normal(0, 10, 12), rng.uniform(0, 80, 12), rng.uniform(0, 5, 12))
    expected = np.empty(12)
    for i in range(12):
        if mode[i] != wire.MODE_SERVO:
            tau = -sim.BRAKE_KD_NM_S_RAD * dq[i]
        else:
            tau = cmd.tau_nm[i]
            if q_cmd[i] != wire.POS_STOP_F:
                tau += cmd.kp_nm_rad[i] * (q_cmd[i] - q[i])
            if dq_cmd[i] != wire.VEL_STOP_F:
                tau += cmd.kd_nm_s_rad[i] * (dq_cmd[i] - dq[i])
        expected[i] = np.clip(tau, -constants.TORQUE_LIMIT_NM[i], constants.TORQUE_LIMIT_NM[i])
    c32 = sim.COMMAND.unravel(sim.command_vector(cmd))
    got = np.asarray(sim.motor_torque(c32, q.astype(np.float32), dq.astype(np.float32)))
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-4)
    assert np.any(np.abs(expected) == constants.TORQUE_LIMIT_NM)  # the clip was exercised


def test_a_lost_optimizer_process_ends_the_run_with_a_trip_and_damping(robot, controller, tmp_path):
    """The runner waits for trial 1's parameters from a process that is gone: the loop damps, and the run ends on a
    trip naming it, instead of an exception out of the 1 kHz loop (which would send no damping)."""

    class Gone:  # the loop's end of a pipe whose other end closed
        def poll(self, timeout=0.0):
            return True

        def recv(self):
            raise EOFError

        def send(self, message):
            pass

    runner = robot_trials.TrialRunner(Gone(), params.midpoint(), 3, protocol.TrialConfig(100, 200))
    result, _, stats = _run(robot, controller, schedule=runner)
    assert result.trip is not None and "optimizer process ended while trial 1" in result.trip
    assert runner.trials_done == 1 and result.events[-1][1] == "damp" and stats["damping_commands"] > 0
