"""What keeps the real-time rehearsal (``cpgjax deploy --robot sim``) and the robot's loop from stalling: the simulated
Go1's clock locked to the commands, its cheaper sensor report, where deploy places its processes, locked memory,
idle CPUs polling, the loop's timing floor, the optimizer compiled before the robot walks, and a finished trial
handed to the optimizer without blocking the loop. The trip counts of the rehearsal itself are measured by
benchmarks/rehearsal.py (real time; not asserted in a test on a shared machine)."""

import logging
import multiprocessing
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from cpgjax import hardware_io as hio
from cpgjax.deployment import deploy
from cpgjax.deployment import trials as robot_trials
from cpgjax.deployment.options import RobotOptions
from cpgjax.go1 import attitude
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1.constants import GRAVITY_MPS2, TICK_S
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import cpu_wakeup, wire
from cpgjax.robot import sim_server as sim
from cpgjax.trial import params, protocol
from tests.deployment.test_options import ROBOT


def test_the_simulated_go1s_clock_locks_to_just_after_the_commands():
    """Commands arrive every 1 ms at an arbitrary phase (with jitter); the clock, stepped as serve_forever steps it,
    settles at PHASE_AFTER_COMMAND_S after them, never moves a deadline by more than PHASE_STEP_MAX_S, and keeps a
    1 kHz rate; with no new commands its phase stays put."""
    rng = np.random.default_rng(0)
    period = TICK_S
    deadline, command_phase = 0.0, 0.63e-3  # the loop sends 630 µs into the simulated Go1's period
    steps, phases = [], []
    for k in range(400):
        nominal = (k - 1) * period + command_phase
        command = nominal + rng.normal(0.0, 20e-6)  # the newest command before tick k, as it arrived
        shift = sim.phase_correction(command, deadline + period)
        steps.append(shift)
        deadline += period + shift
        phases.append((deadline - nominal - period) % period)  # where the next tick falls after the commands
    steps = np.abs(steps)
    assert steps.max() <= sim.PHASE_STEP_MAX_S + 1e-12
    locked = np.array(phases[-100:])
    assert abs(np.mean(locked) - sim.PHASE_AFTER_COMMAND_S) < 10e-6, np.mean(locked)
    assert np.all(np.abs(locked - sim.PHASE_AFTER_COMMAND_S) < 30e-6)  # the jitter is filtered, not followed
    # The rate: 400 ticks took 400 periods give or take the phase moved (< one period).
    assert abs(deadline - 400 * period) < period
    # No new commands: the error to the old command's phase is already ~0, nothing moves.
    assert abs(sim.phase_correction(command, deadline + 50 * period)) < 10e-6


def test_the_simulated_go1_reports_its_imu_as_the_numpy_attitude_defines_it():
    """The compiled sensor report (quaternion, gyro, specific force, roll-pitch-yaw, joints, raw foot counts)
    against the NumPy definitions applied to its own quaternion, and the foot counts against the robot's weight
    while it stands (soft profile: the contact normal force, no sensor noise)."""
    physics = sim.Go1Physics(physics="soft")
    stand_q_rad = go1_model.standing_qpos()[physics.ids.joint_qpos]
    stand = sim.command_vector(
        wire.MotorCommand(
            np.full(12, wire.MODE_SERVO), stand_q_rad, np.zeros(12), np.zeros(12), np.full(12, 70.0), np.full(12, 1.5)
        )
    )
    for _ in range(1500):  # settle on its feet under a standing PD command (1.5 s)
        physics.step(stand)
    state = sim.robot_state(physics.sense(), np.zeros(12), 7)
    quat = state.quaternion_wxyz
    np.testing.assert_allclose(np.linalg.norm(quat), 1.0, atol=1e-5)
    np.testing.assert_allclose(state.rpy_rad, attitude.quat_to_rpy(quat), atol=1e-5)
    np.testing.assert_allclose(state.accel_mps2, GRAVITY_MPS2 * attitude.quat_to_matrix(quat)[2], atol=1e-4)
    np.testing.assert_allclose(state.q_rad, physics.data.qpos[physics.ids.joint_qpos], atol=1e-6)
    assert state.foot_force_raw.dtype == np.int16 and state.tick_ms == 7
    feet_n = (state.foot_force_raw - sim.FOOT_FORCE_OFFSET_COUNTS) * sim.FOOT_FORCE_N_PER_COUNT
    weight_n = deploy.robot_mass_kg(0.0) * GRAVITY_MPS2
    assert np.all(feet_n > 0) and abs(feet_n.sum() - weight_n) < 0.02 * weight_n, (feet_n, weight_n)


def _deploy_args(**kw):
    return RobotOptions(**{**ROBOT, **kw})


def test_the_simulated_go1s_sensor_noise_follows_its_seed():
    """``deploy --seed`` chooses the simulated sensors' noise stream (the go1 profile's noise): two seeds read the
    joints differently, each within the noise amplitude of the true angles, and one seed repeats after a reset."""
    amplitude = physics_profiles.get("go1").joint_pos_noise_rad
    assert amplitude > 0
    a, b = sim.Go1Physics(physics="go1", noise_seed=0), sim.Go1Physics(physics="go1", noise_seed=7)
    q = sim.REPORT.slices.q_rad  # the report's joint angles
    first, other = a.sense()[q], b.sense()[q]
    a.reset()
    np.testing.assert_array_equal(a.sense()[q], first)
    assert np.all(first != other)
    truth = a.data.qpos[a.ids.joint_qpos]
    for reading in (first, other):
        assert np.all(np.abs(reading - truth) <= amplitude * (1 + 1e-5) + 1e-6), (reading - truth, amplitude)


def test_deploy_puts_the_simulated_go1_on_the_loops_cpu_and_the_rest_elsewhere():
    cpus = sorted(os.sched_getaffinity(0))
    realtime = deploy.loop_cpu(_deploy_args())
    assert realtime == (cpus[-1] if len(cpus) > 1 else None)
    assert deploy.loop_cpu(_deploy_args(sim_pacing="lockstep")) is None  # no deadlines: nothing to protect
    assert deploy.loop_cpu(_deploy_args(robot="go1")) == realtime  # the robot: the loop has the last CPU to itself
    assert deploy.loop_cpu(_deploy_args(robot="go1", cpu=cpus[0])) == cpus[0]
    assert deploy.loop_cpu(_deploy_args(cpu=cpus[0])) == cpus[0]
    loop, _ = deploy.loop_and_safety(_deploy_args())
    assert loop.cpu == realtime and loop.lock_memory and loop.poll_idle
    assert not deploy.loop_and_safety(_deploy_args(idle_halt=True))[0].poll_idle
    others = hio.cpus_besides(loop.cpu)
    if realtime is not None:
        assert others == set(cpus) - {realtime}
    assert deploy.SIM_PRIORITY > deploy.LOOP_PRIORITY > deploy.LOG_WRITER_PRIORITY


def test_memory_lock_keeps_the_process_pages_resident():
    """In a child process (the lock is process-wide): after lock() the kernel counts locked memory, or lock() says
    why not."""
    code = (
        "from cpgjax.robot import memory_lock; import numpy as np; note = memory_lock.lock(); "
        "a = np.ones(1 << 20); "
        "lck = [l for l in open('/proc/self/status') if l.startswith('VmLck')][0].split()[1]; "
        "print(note, '|', lck)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    note, locked_kb = out.stdout.strip().splitlines()[-1].split(" | ")
    if note != "memory locked":
        assert note.startswith("memory not locked (")
        pytest.skip(note)
    assert int(locked_kb) > 8 * 1024, locked_kb  # at least the 8 MB array touched after the lock


def _latency_target_us() -> int:
    """The kernel's current CPU wake-up latency target (reading /dev/cpu_dma_latency gives it as an s32)."""
    with open(cpu_wakeup.LATENCY_FILE, "rb") as f:
        return int.from_bytes(f.read(4), sys.byteorder, signed=True)


def _idle_entries() -> tuple[int, int]:
    """Entries into the polling idle state and into every other idle state, summed over the CPUs (cpuidle's
    counters)."""
    poll = other = 0
    for state in Path("/sys/devices/system/cpu").glob("cpu[0-9]*/cpuidle/state[0-9]*"):
        usage = int((state / "usage").read_text())
        if (state / "name").read_text().strip() == "POLL":
            poll += usage
        else:
            other += usage
    return poll, other


def test_the_polling_request_keeps_idle_cpus_from_halting_until_released():
    """While the request is held the kernel's latency target is 0 and the idle CPUs enter no halting state (its
    own counters); released, the target is back. Skips where the request is not permitted, and where another
    process holds one already (another test's robot loop on a parallel worker: the target stays 0 until it ends)."""
    if _latency_target_us() == 0:
        pytest.skip("another process holds a CPU wake-up latency request")
    note, release = cpu_wakeup.request_polling()
    if note != cpu_wakeup.REQUESTED:
        assert note.startswith("idle CPUs may halt (")
        pytest.skip(note)
    try:
        assert _latency_target_us() == 0
        time.sleep(0.05)  # idle periods begun before the request end
        poll_before, halts_before = _idle_entries()
        time.sleep(0.5)  # this process asleep: the CPUs idle
        poll_after, halts_after = _idle_entries()
    finally:
        release()
    assert halts_after - halts_before <= 5, (halts_after - halts_before, poll_after - poll_before)
    assert _latency_target_us() > 0  # no request of ours is left


def test_the_polling_request_says_why_it_was_not_made(tmp_path):
    note, release = cpu_wakeup.request_polling(str(tmp_path / "no_such_device"))
    assert note.startswith("idle CPUs may halt (") and "No such file" in note
    release()


def test_the_idle_loop_measures_each_wake_up_and_drops_the_deadlines_a_stall_missed(monkeypatch):
    """One 5 ms stall in the wait: the wake-up after it is ≈5 ms late, the missed deadlines are dropped (the next
    wake-ups are on time again), and every other wake-up is within a period."""
    loop = hio.LoopConfig(realtime_priority=None, lock_memory=False, poll_idle=False)
    wait, calls = hio._wait_until, [0]

    def stalled_wait(deadline, spin_s):
        calls[0] += 1
        if calls[0] == 100:
            time.sleep(0.005)
        wait(deadline, spin_s)

    monkeypatch.setattr(hio, "_wait_until", stalled_wait)
    late = hio.idle_loop_lateness_s(0.3, loop)
    assert late.shape == (300,) and np.isfinite(late).all()
    assert 0.0035 <= late[100] <= 0.05, late[100]
    # Back on time at once: the stall's deadlines were dropped (kept, the next wake-ups would be ≈3, 2, 1 ms late).
    assert min(late[101], late[102]) < 0.5 * loop.period_s, late[100:104]
    assert np.median(late[:100]) < 0.2 * loop.period_s and np.median(late[101:]) < 0.2 * loop.period_s


def test_after_its_warm_up_the_optimizer_compiles_nothing_and_proposes_as_a_fresh_one(caplog):
    """The robot's first proposal must not wait for a compiler: after ``warm_up``, one ``observe`` and one
    ``propose`` compile nothing (JAX's own compile log), and the warm-up changed neither the state nor the key (the
    proposal equals a fresh optimizer's after the same observation)."""
    context, x = np.array([100.0, 0.05]), params.midpoint()
    warmed = robot_trials.BayesianOptimizer(3, True)
    warmed.warm_up(x, context, None, 0.7)
    with caplog.at_level(logging.WARNING), jax.log_compiles(True):
        warmed.observe(x, context, None, 1.0)
        proposal = warmed.propose(context)
    compiled = [r.getMessage()[:120] for r in caplog.records if r.getMessage().startswith("Compiling")]
    assert not compiled, compiled
    fresh = robot_trials.BayesianOptimizer(3, True)
    fresh.observe(x, context, None, 1.0)
    np.testing.assert_array_equal(proposal, fresh.propose(context))


def test_a_finished_trial_never_blocks_the_loop_while_the_optimizer_is_not_reading():
    """A trial's signals are larger than the connection's buffer: handed over in the loop's thread, the tick that
    finished the trial waited until the optimizer's process read them (1.9 s once). Now that tick is a queue put,
    and the message arrives once the other end reads."""
    timing = protocol.TrialConfig(transition_steps=10, steady_steps=4000)
    conn, other_end = multiprocessing.get_context("spawn").Pipe()
    mailer = robot_trials._Mailer(conn, None)
    runner = robot_trials.TrialRunner(conn, params.midpoint(), 2, timing, mailer)
    out = compiled_controller.OUTPUT.zeros()
    slowest = [0.0]

    def walk_one_trial():
        for tick in range(timing.transition_steps + timing.steady_steps):
            t0 = time.perf_counter()
            runner.record(tick, out)
            slowest[0] = max(slowest[0], time.perf_counter() - t0)

    walker = threading.Thread(target=walk_one_trial, daemon=True)
    walker.start()
    walker.join(timeout=20.0)
    assert not walker.is_alive(), "the loop blocked on handing a trial to the optimizer"
    assert slowest[0] < 0.05, slowest[0]
    assert other_end.poll(10.0)
    kind, trial, x, signals, _ = other_end.recv()
    assert kind == "trial" and trial == 0 and signals.shape == (4000, len(robot_trials._SIGNALS))
    np.testing.assert_array_equal(x, params.midpoint().astype(np.float32).astype(np.float64))
    mailer.close()
    conn.close()
    other_end.close()
