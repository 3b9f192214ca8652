"""Physics profiles (cpgjax.go1.physics) against independent references: C MuJoCo's own contact forces and body
frames, the analytic DC-motor line, hand-written foot-sensor (the Gazebo plugin) and delay sequences, and the profiles'
sources."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from cpgjax import ablation, cpg, mjx_go1
from cpgjax.go1 import attitude, physics, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.optim import config as optimizer_config
from cpgjax.sim import native as native_go1
from cpgjax.sim import native_physics
from cpgjax.studies import transfer
from cpgjax.study import spec as study_spec
from cpgjax.trial import objective, optimizer_setting, params, protocol

IDS = go1_model.indices()


def _settled(profile: str):
    """C-MuJoCo model and data of the Go1 standing 0.5 s under joint PD (feet loaded unevenly: a real contact)."""
    m = go1_model.model_with_payload(0.0, profile).__copy__()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    d.qpos[IDS.root_qpos + 3 : IDS.root_qpos + 7] = [0.999, 0.02, 0.03, 0.0]  # a little roll and pitch
    target = d.qpos[IDS.joint_qpos].copy()
    for _ in range(500):
        d.ctrl[IDS.actuator] = 70.0 * (target - d.qpos[IDS.joint_qpos]) - 1.3 * d.qvel[IDS.joint_dof]
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    return m, d


@pytest.mark.parametrize("profile", ["paper", "soft"])
def test_calf_frame_force_is_the_contact_force_rotated_into_the_calf_body(profile):
    m, d = _settled(profile)
    reference = np.zeros(4)
    for leg in range(4):
        force_on_foot = np.zeros(3)
        for c in range(d.ncon):
            con = d.contact[c]
            if {con.geom1, con.geom2} != {IDS.foot_geom[leg], IDS.floor_geom}:
                continue
            wrench = np.zeros(6)
            mujoco.mj_contactForce(m, d, c, wrench)  # in the contact frame, exerted by geom1 on geom2
            world = con.frame.reshape(3, 3).T @ wrench[:3]
            force_on_foot += world if con.geom2 == IDS.foot_geom[leg] else -world
        calf_to_world = d.xmat[IDS.calf_body[leg]].reshape(3, 3)
        reference[leg] = (calf_to_world.T @ force_on_foot)[2]
    assert np.all(reference > 5.0)  # every foot loaded
    paper = physics.arrays(physics.get("paper"))
    signal = physics.foot_force_signal(
        paper, jnp.asarray(d.qpos), jnp.asarray(d.sensordata[IDS.foot_contact_data]), IDS.root_qpos, IDS.joint_qpos
    )
    np.testing.assert_allclose(np.asarray(signal), reference, rtol=1e-5, atol=1e-4)
    # The soft profile's signal is the contact normal force (the sensor's first component), as before profiles.
    soft = physics.arrays(physics.get("soft"))
    normal = physics.foot_force_signal(
        soft, jnp.asarray(d.qpos), jnp.asarray(d.sensordata[IDS.foot_contact_data]), IDS.root_qpos, IDS.joint_qpos
    )
    np.testing.assert_array_equal(np.asarray(normal), d.sensordata[IDS.foot_force_sensor].astype(np.float32))


def _sensor_sequence(profile_name: str, forces: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """The force the controller reads at each tick for per-tick forces (K, 4) and contact flags (K, 4)."""
    profile = physics.arrays(physics.get(profile_name))
    state = physics.init_state(jnp.zeros(4))
    seen = []
    for k in range(len(forces)):
        state, held = physics.foot_sensor_update(
            profile, state, jnp.asarray(forces[k], jnp.float32), jnp.asarray(contact[k])
        )
        state, _ = physics.actuate(profile, state, jnp.zeros(12), jnp.zeros(12))  # one tick passes
        seen.append(np.asarray(held))
    return np.array(seen)


def test_the_paper_signal_is_the_plugins_mean_over_in_contact_ticks_held_for_ten_ticks():
    # The unitree_ros foot contact plugin, written out by hand: at each 100 Hz update (ticks 0, 10, 20, ...) it
    # publishes the mean force of the contact entries since the last update (that tick included), 0 with none.
    rng = np.random.default_rng(3)
    forces = rng.uniform(0.0, 60.0, (45, 4))
    contact = rng.uniform(size=(45, 4)) < 0.6
    contact[11:21, 2] = False  # a foot in the air for a whole update period: reads 0
    forces[~contact] = 0.0
    expected = np.zeros((45, 4))
    for k in range(45):
        update = (k // 10) * 10
        window = range(max(update - 9, 0), update + 1)
        for leg in range(4):
            touching = [forces[t, leg] for t in window if contact[t, leg]]
            expected[k, leg] = np.mean(touching) if touching else 0.0
    seen = _sensor_sequence("paper", forces, contact)
    np.testing.assert_allclose(seen, expected, rtol=1e-6, atol=1e-5)
    assert np.all(seen[20:30, 2] == 0.0)


def test_sampling_profiles_read_the_update_ticks_force_as_before():
    # soft and go1 update every tick with the tick's own force, in contact or not (go1's noise reaches a foot in the
    # air); a 10-tick sampling profile without the mean holds the update tick's force.
    forces = np.arange(35.0)[:, None] * np.array([1.0, 2.0, 3.0, 4.0])
    contact = np.zeros((35, 4), bool)
    for name in ("soft", "go1"):
        np.testing.assert_array_equal(_sensor_sequence(name, forces, contact), forces.astype(np.float32))
    sampled = physics.get("paper")._replace(foot_force_contact_mean=False)
    physics.PROFILES["paper_sampled_test"] = sampled
    try:
        seen = _sensor_sequence("paper_sampled_test", forces, contact)
    finally:
        del physics.PROFILES["paper_sampled_test"]
    np.testing.assert_array_equal(seen, forces[(np.arange(35) // 10) * 10])


def test_a_paper_foot_touches_within_gazebos_contact_surface_layer():
    # unitree_gazebo earth.world: contact_surface_layer 0.001 m; the sampling profiles count penetration only.
    clearance = jnp.asarray([-1e-4, 5e-4, 9.9e-4, 1.5e-3])
    paper = physics.arrays(physics.get("paper"))
    np.testing.assert_array_equal(np.asarray(physics.touching(paper, clearance)), [True, True, True, False])
    soft = physics.arrays(physics.get("soft"))
    np.testing.assert_array_equal(np.asarray(physics.touching(soft, clearance)), [True, False, False, False])


def test_gazebo_friction_rule_caps_the_floor_at_the_feet_mu_under_paper_only():
    # gazebo-classic ODEPhysics: μ = min(μ_floor, μ_foot), with unitree_ros' feet at 0.6; MuJoCo's floor priority
    # elsewhere.
    scenario = go1_model.make_scenarios(friction=[0.3, 0.6, 0.9, 0.9, 0.9], physics=["paper"] * 3 + ["soft", "go1"])
    floor = [go1_model.scenario_model(scenario, i).geom_friction[IDS.floor_geom, 0] for i in range(5)]
    np.testing.assert_array_equal(floor, [0.3, 0.6, 0.6, 0.9, 0.9])
    batch = mjx_go1.make_batch_model(scenario)
    np.testing.assert_allclose(np.asarray(batch.model.geom_friction[:, IDS.floor_geom, 0]), floor, rtol=1e-6)


@pytest.mark.parametrize("speed_rad_s", [0.0, 5.0, 15.05, 29.0, 30.1, 45.0])
def test_the_torque_speed_envelope_is_the_dc_motor_line(speed_rad_s):
    profile = physics.arrays(physics.get("go1"))
    stall = np.tile([23.7, 23.7, 35.55], 4)
    no_load = np.tile([30.1, 30.1, 20.06], 4)
    state = physics.init_state(jnp.zeros(4))
    dq = np.full(12, speed_rad_s, np.float32)
    for _ in range(profile.latency_ticks + 1):  # let the full-torque command through the latency
        state, motoring = physics.actuate(profile, state, jnp.asarray(stall, jnp.float32), dq)
    line = stall * np.clip(1.0 - speed_rad_s / no_load, 0.0, 1.0)
    np.testing.assert_allclose(np.asarray(motoring), line, rtol=1e-6, atol=1e-5)
    state = physics.init_state(jnp.zeros(4))
    for _ in range(profile.latency_ticks + 1):
        state, braking = physics.actuate(profile, state, jnp.asarray(-stall, jnp.float32), dq)
    np.testing.assert_allclose(np.asarray(braking), -stall if speed_rad_s > 0 else -line, rtol=1e-6)


def test_gazebo_velocity_limit_cuts_torque_along_the_motion_only():
    profile = physics.arrays(physics.get("paper"))
    dq = np.tile([31.0, -31.0, 10.0], 4).astype(np.float32)  # hip over +30.1, thigh under −30.1, calf within 20.06
    command = np.tile([5.0, -5.0, 5.0], 4).astype(np.float32)
    _, applied = physics.actuate(profile, physics.init_state(jnp.zeros(4)), jnp.asarray(command), dq)
    np.testing.assert_array_equal(np.asarray(applied), np.tile([0.0, 0.0, 5.0], 4))
    _, braking = physics.actuate(profile, physics.init_state(jnp.zeros(4)), jnp.asarray(-command), dq)
    np.testing.assert_array_equal(np.asarray(braking), -command)


@pytest.mark.parametrize("latency", [0, 1, 2, 4])
def test_a_latency_of_k_ticks_shifts_the_applied_torques_by_k(latency):
    profile = physics.arrays(physics.get("soft"))._replace(latency_ticks=np.int32(latency))
    commands = np.random.default_rng(latency).uniform(-20.0, 20.0, (12, 12)).astype(np.float32)
    state, applied = physics.init_state(jnp.zeros(4)), []
    for command in commands:
        state, torque = physics.actuate(profile, state, jnp.asarray(command), jnp.zeros(12))
        applied.append(np.asarray(torque))
    expected = np.concatenate([np.zeros((latency, 12), np.float32), commands[: 12 - latency]])
    np.testing.assert_array_equal(np.array(applied), expected)


def test_go1_armature_is_the_rotor_inertia_times_the_gear_ratio_squared():
    rotor_kg_m2 = 0.000111842  # unitree_ros go1.urdf, the motor rotor's inertia about its axis
    ratios = np.tile([6.0, 6.0, 9.0], 4)  # mjlab's Go1: 6 hip and thigh, 1.5 × 6 knee
    m = go1_model.model_with_payload(0.0, "go1")
    np.testing.assert_allclose(m.dof_armature[IDS.joint_dof], rotor_kg_m2 * ratios**2, rtol=1e-12)
    assert np.all(go1_model.model_with_payload(0.0, "paper").dof_armature[IDS.joint_dof] == 0.0)


def test_profiles_set_the_sources_values():
    paper = go1_model.model_with_payload(0.0, "paper")
    np.testing.assert_array_equal(paper.dof_damping[IDS.joint_dof], 0.01)  # unitree_ros Gazebo joint damping
    np.testing.assert_array_equal(paper.dof_frictionloss[IDS.joint_dof], 0.2)  # unitree_ros Gazebo joint friction
    np.testing.assert_array_equal(paper.geom_solref[IDS.floor_geom], [2 * paper.opt.timestep, 1.0])
    # One solver for every profile: the fewest Newton iterations whose trials stay within the tolerance of a
    # converged solver under the stiff paper contact (studies/solver_fidelity.py, docs/physics.md).
    assert (paper.opt.iterations, paper.opt.ls_iterations) == (6, 10)
    soft = go1_model.model_with_payload(0.0, "soft")
    base = go1_model.load_model()
    for field in ("dof_armature", "dof_damping", "dof_frictionloss", "geom_solref", "geom_solimp"):
        np.testing.assert_array_equal(getattr(soft, field), getattr(base, field))  # soft = the MJCF as written


def test_unknown_profile_is_refused_with_the_allowed_names():
    with pytest.raises(
        ValueError,
        match=r"physics = 'gazebo' \(instance 1\).*allowed: \('soft', 'paper', 'go1', "
        r"'paper_5khz'\)",
    ):
        go1_model.make_scenarios(physics=["soft", "gazebo"])


def test_profiles_are_per_instance_and_switching_keeps_the_compiled_trial():
    config = protocol.TrialConfig(transition_steps=20, steady_steps=60)
    sim = native_go1.NativeBackend(go1_model.make_scenarios(physics=["soft", "paper", "go1"]), trial_config=config)
    armature = [mi.dof_armature[IDS.joint_dof[2]] for mi in sim.physics.models]
    assert armature == [0.01, 0.0, pytest.approx(0.000111842 * 81)]
    p = np.tile(params.midpoint(), (3, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * 3)
    _, first = sim.trial(sim.reset(p), p, gates)
    program = sim._program(native_go1.TRIAL_RECORDER, config)
    compiled = program.advance._cache_size()
    switched = sim.with_scenario(go1_model.make_scenarios(physics=["go1", "soft", "paper"]))
    _, second = switched.trial(switched.reset(p), p, gates)
    assert switched._program(native_go1.TRIAL_RECORDER, config) is program
    assert program.advance._cache_size() == compiled
    # Same three physics in another order: the same per-instance trials, moved with their instances.
    np.testing.assert_allclose(np.asarray(second.c_load_n), np.asarray(first.c_load_n)[[2, 0, 1]], rtol=1e-5)
    switched.physics.close()


def test_mjx_batches_profile_fields_per_instance():
    batch = mjx_go1.make_batch_model(go1_model.make_scenarios(physics=["soft", "paper", "go1"]))
    armature = np.asarray(batch.model.dof_armature)[:, IDS.joint_dof]
    np.testing.assert_allclose(armature[:, 2], [0.01, 0.0, 0.000111842 * 81], rtol=1e-6)
    assert batch.in_axes.dof_armature == 0 and batch.in_axes.geom_solref == 0 and batch.in_axes.dof_frictionloss == 0
    np.testing.assert_allclose(np.asarray(batch.model.geom_solref)[:, IDS.floor_geom, 0], [0.02, 0.002, 0.02])
    assert np.asarray(batch.profile.calf_frame).tolist() == [False, True, False]
    assert jax.tree.structure(batch.model) == jax.tree.structure(
        mjx_go1.make_batch_model(go1_model.make_scenarios(physics=["paper"] * 3)).model
    )


def test_context_ranges_follow_the_profile_and_clipping_is_reported():
    paper = study_spec.StudySpec("t", physics=("paper",)).optimizer_config()
    assert (paper.context_lower, paper.context_upper) == ((15.0, -0.4), (55.0, 0.1))  # docs/decisions.md §11
    assert study_spec.StudySpec("t", physics=("soft",)).optimizer_config().context_upper == (75.0, 0.1)  # widened
    with pytest.raises(study_spec.StudyError, match="normalize c_load over different ranges"):
        study_spec.validate(study_spec.StudySpec("t", physics=("soft", "paper")))
    clipped, messages = optimizer_config.clip_context(
        paper, np.array([[60.0, -0.1], [30.0, 0.2], [40.0, 0.0]]), objective.CONTEXT_NAMES, objective.CONTEXT_UNITS
    )
    np.testing.assert_array_equal(clipped, [[55.0, -0.1], [30.0, 0.1], [40.0, 0.0]])
    assert messages == [
        "instance 0: c_load = 60 N outside [15, 55], clipped for the GP",
        "instance 1: c_slope = 0.2 rad outside [-0.4, 0.1], clipped for the GP",
    ]


def test_domain_randomization_draws_each_trials_physics_and_the_engine_simulates_it():
    ranges = study_spec.Randomization(
        friction=(0.4, 1.0), payload_kg=(0.0, 5.0), mass_scale=(0.9, 1.1), latency_ticks=(0, 2), seed=3
    )
    draws = study_spec.randomized(ranges, 2, 50)
    assert np.all((draws["friction"] >= 0.4) & (draws["friction"] <= 1.0))
    assert set(np.unique(draws["latency_ticks"])) == {0, 1, 2}
    np.testing.assert_array_equal(study_spec.randomized(ranges, 3, 50)["mass_scale"][:2], draws["mass_scale"])
    spec = study_spec.StudySpec(
        "dr",
        num_trials=3,
        controllers=("open_loop",),
        randomize=ranges,
        trial=protocol.TrialConfig(transition_steps=20, steady_steps=60),
        optimizer=optimizer_setting.paper_config(capacity=3),
    )
    result = ablation.Engine(spec, backend="native").run()
    cond = result.conditions
    urdf_mass_kg = 13.10  # docs/go1-model.md: the model's total mass
    np.testing.assert_allclose(
        result.trials.total_mass_kg[:, 0], urdf_mass_kg * cond.mass_scale[0] + cond.payload_kg[0], atol=0.01
    )
    assert len(set(cond.friction[0].tolist())) == 3


def test_transfer_evaluates_every_run_in_every_environment():
    env = transfer.Environments("paper")
    assert env.names[:3] == ["soft", "paper", "go1"] and len(env.names) == 3 + transfer.EVALUATION_DRAWS
    j, v, cot, fell = transfer.evaluate(
        np.tile(params.midpoint(), (2, 1)),
        ["open_loop", "vmc_tegotae"],
        env,
        protocol.TrialConfig(transition_steps=20, steady_steps=100),
        "native",
        0.5,
    )
    assert j.shape == v.shape == cot.shape == fell.shape == (2, len(env.names))
    assert np.all(np.isfinite(j)) and np.all(j >= -1.0)


def test_mjx_profile_switch_keeps_the_compiled_trial(short_sim, mid_params, vmc_tegotae_gates):
    """``with_scenario`` to other physics profiles swaps model data and profile arrays, not the program: the paper
    profile's foot signal (the plugin's calf-frame mean) then reads otherwise than the soft contact normal, and its
    friction rule makes the μ 0.9 floor the μ 0.6 one."""
    state = short_sim.reset(mid_params)
    _, soft = short_sim.trial(state, mid_params, vmc_tegotae_gates)
    compiled = short_sim._trial._cache_size()
    scenario = short_sim.scenario
    switched = short_sim.with_scenario(
        go1_model.make_scenarios(
            scenario.friction, scenario.slope_deg, scenario.payload_kg, physics=["paper"] * short_sim.batch_size
        )
    )
    _, paper = switched.trial(switched.reset(mid_params), mid_params, vmc_tegotae_gates)
    assert switched._trial._cache_size() == compiled
    flat = (scenario.slope_deg == 0) & (scenario.payload_kg == 0) & (scenario.friction >= 0.6)
    paper_load, soft_load = np.asarray(paper.c_load_n)[flat], np.asarray(soft.c_load_n)[flat]
    assert np.all(np.abs(paper_load - soft_load) > 0.02 * soft_load)
    assert len(set(scenario.friction[flat].tolist())) > 1 and np.all(paper_load == paper_load[0])


def test_go1_sensor_noise_is_uniform_within_its_amplitudes_and_a_pure_function_of_seed_and_tick():
    """The go1 profile's readings differ from the noise-free observation (sensors.observe, the reference) by at most
    legged_gym's amplitudes, with zero mean; the paper profile reads exactly the truth; a seed and a tick fix the
    draw, another seed gives another; the motors and the trial's power see the true joint velocity."""
    m, d = _settled("go1")
    qpos, qvel, sens = (jnp.asarray(a, jnp.float32) for a in (d.qpos, d.qvel, d.sensordata))
    gravity = jnp.asarray(m.opt.gravity, jnp.float32)
    truth = sensors.observe(qpos, qvel, sens, gravity)

    def read(name, tick, seed=0):
        profile = physics.batch_arrays([name], noise_seed=[seed])
        profile = jax.tree.map(lambda x: x[0], profile)
        io = physics.init_state(jnp.zeros(4))._replace(tick=jnp.int32(tick))
        return sensors.measure(profile, io, qpos, qvel, sens, gravity)[1]

    draws = jax.vmap(lambda t: read("go1", t))(jnp.arange(2000))
    for field, amplitude in (("joint_pos_rad", 0.01), ("joint_vel_rad_s", 1.5), ("gyro_rad_s", 0.2)):
        error = np.asarray(getattr(draws, field)) - np.asarray(getattr(truth, field))
        assert np.all(np.abs(error) <= amplitude * (1 + 1e-4)), field
        assert np.abs(error).max() > 0.95 * amplitude, field  # the draws fill the range
        np.testing.assert_allclose(error.mean(), 0.0, atol=0.03 * amplitude)
        np.testing.assert_allclose(error.std(), amplitude / np.sqrt(3.0), rtol=0.05)  # uniform's std

    # Uncorrelated across readings, from tick to tick, and between seeds (|r| ≤ 0.1 over 2000 draws; 4.5 σ).
    def flat_draws(noise_seed):
        profile = jax.tree.map(lambda x: x[0], physics.batch_arrays(["go1"], noise_seed=noise_seed))
        return np.asarray(
            jax.vmap(lambda t: physics.NOISE_DRAWS.ravel(physics.noise_draws(profile, t)))(jnp.arange(2000))
        )

    u, other = flat_draws(None), flat_draws([1])
    r = np.corrcoef(np.concatenate([u, u[1:].tolist() + [u[0]], other], axis=1).T)
    n = physics.NUM_NOISY_READINGS
    assert np.abs(r - np.eye(3 * n)).max() < 0.1
    # The IMU turned about the trunk's x and y axes only, by at most 0.05 rad per axis.
    conjugate = jnp.array([1.0, -1.0, -1.0, -1.0]) * truth.imu_quat_wxyz
    turn = jax.vmap(lambda q: attitude.quat_mul(conjugate, q))(draws.imu_quat_wxyz)  # truth⁻¹ ⊗ reading
    turn = np.asarray(turn) * np.sign(np.asarray(turn)[:, :1])
    angle = 2 * np.arcsin(np.linalg.norm(turn[:, 1:], axis=1))
    assert np.all(angle <= 0.05 * np.sqrt(2) + 1e-4) and angle.max() > 0.03
    assert np.all(np.abs(turn[:, 3]) < 1e-3)
    force_error = np.asarray(draws.foot_force_n) - np.asarray(truth.foot_force_n)
    assert np.all(np.abs(force_error) <= 0.5 + 0.25 + 1e-3)  # ±1 count of noise, then counted in 0.5 N steps
    np.testing.assert_allclose(
        np.asarray(draws.foot_force_n) / 0.5, np.round(np.asarray(draws.foot_force_n) / 0.5), atol=1e-3
    )
    # Pure function of (seed, tick); another seed draws differently; the paper profile has no noise.
    a, b, c = read("go1", 7), read("go1", 7), read("go1", 7, seed=1)
    np.testing.assert_array_equal(np.asarray(a.joint_vel_rad_s), np.asarray(b.joint_vel_rad_s))
    assert not np.allclose(np.asarray(a.joint_vel_rad_s), np.asarray(c.joint_vel_rad_s))
    paper = read("paper", 7)
    np.testing.assert_array_equal(np.asarray(paper.joint_vel_rad_s), np.asarray(truth.joint_vel_rad_s))
    np.testing.assert_array_equal(np.asarray(paper.imu_quat_wxyz), np.asarray(truth.imu_quat_wxyz))
    # A noise scale on the paper profile gives it that multiple of the go1 amplitudes.
    scaled = physics.batch_arrays(["paper", "paper"], noise_scale=[2.0, -1.0])
    np.testing.assert_allclose(np.array(scaled.noise)[:, 0], 2 * np.array(physics.arrays(physics.get("go1")).noise))
    np.testing.assert_array_equal(np.array(scaled.noise)[:, 1], 0.0)
    # The motors see the true velocity: the control tick's torque equals actuate on qvel's joint velocities.
    profile = jax.tree.map(lambda x: x[0], physics.batch_arrays(["go1"]))
    io = physics.init_state(jnp.zeros(4))
    state, mid, gates = cpg.init_state(truth), jnp.asarray(params.midpoint()), cpg.Gates(1.0, 1.0)
    c = protocol.control(cpg.CPGConfig(), profile, io, state, mid, gates, qpos, qvel, sens, gravity)
    _, command, _ = cpg.controller_step(cpg.CPGConfig(), state, mid, gates, c.obs)
    _, expected = physics.actuate(profile, io, command, truth.joint_vel_rad_s)
    np.testing.assert_array_equal(np.asarray(c.torque_nm), np.asarray(expected))
    assert not np.allclose(np.asarray(c.obs.joint_vel_rad_s), np.asarray(truth.joint_vel_rad_s))


def test_paper_5khz_is_paper_at_unitree_ros_physics_rate():
    """unitree_gazebo earth.world steps ODE every 0.2 ms (docs/physics.md): the profile is `paper` with five physics
    steps of 0.2 ms per 1 ms control tick, every other field the same; one batch steps at one rate, and MJX refuses
    it in one line."""
    fine, paper = physics.get("paper_5khz"), physics.get("paper")
    assert fine._replace(physics_substeps=1) == paper and fine.physics_substeps == 5
    assert go1_model.model_with_payload(0.0, "paper_5khz").opt.timestep == pytest.approx(0.0002)
    assert go1_model.model_with_payload(0.0, "paper").opt.timestep == pytest.approx(0.001)
    mixed = go1_model.make_scenarios(friction=[0.6, 0.6], physics=["paper", "paper_5khz"])
    with pytest.raises(
        ValueError,
        match=r"one batch steps its physics at one rate: profiles \['paper', "
        r"'paper_5khz'\] take \[1, 5\] physics steps per tick",
    ):
        native_physics.BatchPhysics(mixed)
    with pytest.raises(ValueError, match="'paper_5khz' steps its physics more than once per control tick"):
        mjx_go1.make_batch_model(go1_model.make_scenarios(friction=[0.6], physics="paper_5khz"))
    # The loopback Go1 steps five times per 1 ms tick too: its clock keeps the tick.
    from cpgjax.robot import sim_server

    go1 = sim_server.Go1Physics(physics="paper_5khz")
    start = go1.data.time
    for _ in range(10):
        go1.step(sim_server.COMMAND.zeros())
    assert go1.data.time - start == pytest.approx(0.010)
