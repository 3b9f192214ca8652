"""The MJX Go1: C-MuJoCo agreement, scenario physics, trial records, objective and failure isolation."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from cpgjax import cpg
from cpgjax.go1 import constants, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space


def test_model_names_and_mass():
    m = go1_model.load_model()
    ids = go1_model.indices()
    assert m.opt.timestep == pytest.approx(0.001)
    assert [
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n))
        for n in go1_model.JOINT_NAMES
    ] == list(go1_model.JOINT_NAMES)
    assert m.body_subtreemass[ids.trunk_body] == pytest.approx(13.10, abs=0.01)  # docs/go1-model.md: 13.10 kg
    np.testing.assert_allclose(m.actuator_ctrlrange[ids.actuator, 1], constants.TORQUE_LIMIT_NM)
    heavy = go1_model.model_with_payload(15.0)
    assert heavy.body_subtreemass[ids.trunk_body] == pytest.approx(13.10 + 15.0, abs=0.01)


def test_the_trunk_carries_the_four_hip_rotors_as_gazebo_lumps_them():
    """The trunk link of unitree_ros const.xacro (commit 5dee20c: mass, centre of mass, full inertia) and its four
    fixed hip rotors, lumped by MuJoCo's compiler (fusestatic), against go1.xml's trunk (docs/go1-model.md)."""
    rotors = "".join(
        f'<body pos="{0.11215 * sx} {0.04675 * sy} 0"><inertial pos="0 0 0" mass="0.089" '
        f'fullinertia="0.000111842 0.000059647 0.000059647 0 0 0"/></body>'
        for sx in (1, -1)
        for sy in (1, -1)
    )
    lumped = mujoco.MjModel.from_xml_string(
        '<mujoco><compiler fusestatic="true" inertiafromgeom="false"/><worldbody><body><freejoint/>'
        '<inertial pos="0.0223 0.002 -0.0005" mass="5.204" fullinertia="0.0168128557 0.063009565 0.0716547275 '
        f'-0.0002296769 -0.0002945293 -0.0000418731"/>{rotors}</body></worldbody></mujoco>'
    )
    assert lumped.nbody == 2  # the rotors are inside the trunk
    m = go1_model.load_model()
    trunk = go1_model.indices().trunk_body
    assert m.body_mass[trunk] == pytest.approx(lumped.body_mass[1], abs=1e-9)
    np.testing.assert_allclose(m.body_ipos[trunk], lumped.body_ipos[1], atol=1e-8)
    np.testing.assert_allclose(m.body_inertia[trunk], lumped.body_inertia[1], rtol=1e-5)
    # The same principal axes (a quaternion and its negative are one rotation).
    assert abs(np.dot(m.body_iquat[trunk], lumped.body_iquat[1])) == pytest.approx(1.0, abs=1e-6)


def test_c_mujoco_agrees_with_mjx_over_a_short_closed_loop_rollout(short_sim):
    """MJX (float32, JAX) and C MuJoCo (float64) driven by the same jitted controller for 300 ticks (0.3 s)."""
    steps = 300
    p = np.tile(param_space.midpoint(), (short_sim.batch_size, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * short_sim.batch_size)
    _, log = short_sim.rollout(short_sim.reset(p), p, gates, steps)

    m = go1_model.scenario_model(short_sim.scenario, 0)
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos()
    mujoco.mj_forward(m, d)
    ids = go1_model.indices()
    observe = jax.jit(sensors.observe)
    step = jax.jit(cpg.controller_step, static_argnums=0)
    obs = observe(d.qpos, d.qvel, d.sensordata, m.opt.gravity)
    params = jnp.asarray(p[0], jnp.float32)
    gate = cpg.controller_gates("vmc_tegotae")
    state = cpg.init_state(obs)
    qpos = []
    for _ in range(steps):
        obs = observe(d.qpos, d.qvel, d.sensordata, m.opt.gravity)
        state, tau, _ = step(cpg.CPGConfig(), state, params, gate, obs)
        d.ctrl[ids.actuator] = np.asarray(tau)
        mujoco.mj_step(m, d)
        qpos.append(d.qpos.copy())
    qpos = np.array(qpos)
    mjx_qpos = np.asarray(log.qpos[0])
    # Tolerance: 2 mm trunk position and 0.02 rad joint angles after 0.3 s of contact-rich walking; the difference
    # comes from float32 vs float64 and the solvers' iteration counts (see docs/simulation.md).
    np.testing.assert_allclose(mjx_qpos[:, :3], qpos[:, :3], atol=2e-3)
    np.testing.assert_allclose(mjx_qpos[:, ids.joint_qpos], qpos[:, ids.joint_qpos], atol=2e-2)


def test_walks_forward_without_falling(two_trials):
    _, record = two_trials
    walking = [0, 1, 2, 4, 5]  # all but the 0.1-friction floor, on which mid-range parameters may slip and fall
    assert np.all(np.asarray(record.fell)[walking] == 0) and np.all(np.asarray(record.failed) == 0)
    v = np.asarray(objective.mean_velocity(record))
    unloaded = [0, 2, 4, 5]
    assert np.all((0.3 < v[unloaded, 0]) & (v[unloaded, 0] < 0.8)) and np.all(np.abs(v[unloaded, 1]) < 0.1)
    assert v[1, 0] > 0.05  # 15 kg payload: slower with parameters not adapted to it (paper, load table), but forward


def test_scenarios_have_their_physical_effect(two_trials):
    _, record = two_trials
    load = np.asarray(record.c_load_n)
    slope = np.asarray(record.c_slope_rad)
    nominal, heavy, uphill = 0, 1, 2
    # c_load ≈ m g / 4 per foot: 13.10 kg → 32 N, +15 kg → 69 N.
    assert load[nominal] == pytest.approx(13.10 * 9.81 / 4, rel=0.1)
    assert load[heavy] == pytest.approx(28.10 * 9.81 / 4, rel=0.1)
    # Uphill along +x reads as nose-up, i.e. negative pitch, ≈ −6° = −0.105 rad.
    assert slope[uphill] < slope[nominal] - 0.07
    np.testing.assert_allclose(np.asarray(record.total_mass_kg)[[nominal, heavy]], [13.10, 28.10], atol=0.01)


def test_low_friction_floor_makes_the_feet_slip(short_sim):
    p = np.tile(param_space.midpoint(), (short_sim.batch_size, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * short_sim.batch_size)
    _, log = short_sim.rollout(short_sim.reset(p), p, gates, 1500)
    feet = np.asarray(log.foot_pos_m)[:, 500:]  # (B, T, 4, 3) after start-up
    force = np.asarray(log.foot_force_n)[:, 500:]
    speed = np.linalg.norm(np.diff(feet[..., :2], axis=1), axis=-1) / 1e-3  # horizontal foot speed
    loaded = force[:, 1:] > 20.0
    slip = np.array([speed[b][loaded[b]].mean() for b in range(short_sim.batch_size)])
    slippery, coarse = 3, 4
    assert slip[slippery] > 2.0 * slip[coarse]


def _reference_objective(record, target):
    """Eqs. (9)-(10) written out in NumPy from the record's raw per-step velocities and energy."""
    v = np.asarray(record.velocity_xy_mps, np.float64)
    reward = 1e-3 * np.minimum(np.exp(-((v[:, 0] - target) ** 2 + v[:, 1] ** 2) / 0.05), 0.85).sum()
    cot = float(record.energy_j) / (float(record.total_mass_kg) * 9.81 * max(float(record.distance_m), 0.05))
    return reward - 0.5 * cot


def test_objective_recomputed_for_a_new_target_from_a_stored_record(two_trials, tmp_path):
    _, record = two_trials
    one = jax.tree.map(lambda x: np.asarray(x)[0], record)
    np.savez(tmp_path / "record.npz", **one._asdict())
    loaded = protocol.TrialRecord(**dict(np.load(tmp_path / "record.npz")))
    for target in (0.3, 0.5, 0.8):
        assert float(objective.objective(loaded, target)) == pytest.approx(
            _reference_objective(one, target), rel=1e-4, abs=1e-4
        )
    assert float(objective.objective(loaded, 0.5)) == float(objective.objective(one, 0.5))


def test_degenerate_trials_get_a_finite_floor():
    steps = 100
    base = protocol.TrialRecord(
        velocity_xy_mps=np.tile([0.5, 0.0], (steps, 1)),
        energy_j=np.float32(2.0),
        distance_m=np.float32(0.05),
        total_mass_kg=np.float32(12.74),
        c_load_n=np.float32(31.0),
        c_slope_rad=np.float32(0.0),
        roll_mean_rad=np.float32(0),
        roll_std_rad=np.float32(0),
        pitch_std_rad=np.float32(0),
        saturation_fraction=np.float32(0),
        fell=np.float32(0),
        failed=np.float32(0),
        safety_margin=np.float32(1.0),
    )
    backwards = base._replace(velocity_xy_mps=np.tile([-0.5, 0.0], (steps, 1)), distance_m=np.float32(-0.05))
    nan = base._replace(energy_j=np.float32(np.nan))
    fell = base._replace(fell=np.float32(1.0))
    j_fwd, j_back, j_nan, j_fell = (float(objective.objective(r, 0.5)) for r in (base, backwards, nan, fell))
    assert j_back < j_fwd
    assert j_back >= objective.MIN_OBJECTIVE
    assert j_nan == j_fell == objective.MIN_OBJECTIVE


def test_bad_scenarios_are_rejected():
    with pytest.raises(ValueError, match=r"payload_kg = -1.0 \(instance 1\).*\[0, inf\)"):
        go1_model.make_scenarios(payload_kg=[0.0, -1.0])
    with pytest.raises(ValueError, match="friction = 0.0"):
        go1_model.make_scenarios(friction=0.0)
    with pytest.raises(ValueError, match="slope_deg = 45.0"):
        go1_model.make_scenarios(slope_deg=45.0)
    with pytest.raises(ValueError, match="slope_deg = nan"):
        go1_model.make_scenarios(slope_deg=np.nan)


def test_batch_sharded_over_two_cpu_devices_equals_one_device(two_trials):
    """The session batch sharded over two host devices (a subprocess: the device count is fixed at JAX start-up)
    gives the records of the one-device run to float rounding (XLA vectorizes 3 instances differently from 6)."""
    code = """
import json, jax, numpy as np
from cpgjax.go1 import model as go1_model
from cpgjax import mjx_go1
from cpgjax.trial import params, protocol
from tests.conftest import SCENARIOS, SHORT_TRIAL
sim = mjx_go1.MJXBackend(go1_model.make_scenarios(**SCENARIOS), trial_config=SHORT_TRIAL)
assert len(sim.mesh.devices.ravel()) == 2, sim.mesh
p = np.tile(params.midpoint(), (6, 1))
gates = protocol.batch_gates(["vmc_tegotae"] * 6)
state = sim.reset(p)
state, _ = sim.trial(state, p, gates)
state, record = sim.trial(state, p, gates)
assert len(state.data.qpos.sharding.device_set) == 2
print(json.dumps({k: np.asarray(v).tolist() for k, v in record._asdict().items()}))
"""
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="2")
    out = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        cwd=pathlib.Path(__file__).resolve().parents[1],
    )
    assert out.returncode == 0, out.stderr[-3000:]
    two = json.loads(out.stdout.strip().splitlines()[-1])
    _, one = two_trials
    np.testing.assert_array_equal(two["fell"], np.asarray(one.fell))
    # Rounding grows most on the slippery floor (μ 0.1), which slides: 0.29 % of its distance on a 2-vCPU AMD EPYC.
    # The batch's different scenarios walk distances at least 5 % apart, so 1 % still tells instances apart.
    np.testing.assert_allclose(two["distance_m"], np.asarray(one.distance_m), rtol=1e-2)
    np.testing.assert_allclose(two["energy_j"], np.asarray(one.energy_j), rtol=1e-2)
    np.testing.assert_allclose(two["c_load_n"], np.asarray(one.c_load_n), rtol=1e-3)
