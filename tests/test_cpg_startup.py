"""The start from standing (docs/decisions.md §18): the ramp and the lean against NumPy transcriptions, the leaning
stance against C MuJoCo's centre of mass, both backends and the robot's soft start standing alike, and the
loopback Go1 starting on a slope."""

import json
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from cpgjax import cpg
from cpgjax import hardware_io as hio
from cpgjax.deployment import deploy
from cpgjax.go1 import kinematics
from cpgjax.go1 import model as go1_model
from cpgjax.robot import controller as compiled_controller
from cpgjax.robot import sim_server as sim
from cpgjax.robot import transport as go1_transport
from cpgjax.sim import native
from cpgjax.study import spec as study_spec
from cpgjax.trial import params as param_space
from tests import numpy_reference as ref
from tests.test_cpg import observation

LEAN_RAMP = cpg.with_startup(cpg.CPGConfig(), "lean_ramp")
DATA = pathlib.Path(__file__).parent / "data"


def _pitch_quat(pitch_rad: float) -> np.ndarray:
    """A rotation about +y by ``pitch_rad``: +x tips down, nose-down positive (the IMU's convention, §4)."""
    return np.array([np.cos(pitch_rad / 2), 0.0, np.sin(pitch_rad / 2), 0.0])


def test_the_paper_start_is_the_default_and_a_start_up_sets_only_start_fields():
    assert cpg.with_startup(cpg.CPGConfig(), "paper") == cpg.CPGConfig()
    assert cpg.with_startup(LEAN_RAMP, "paper") == cpg.CPGConfig()
    changed = [f for f in cpg.CPGConfig._fields if getattr(LEAN_RAMP, f) != getattr(cpg.CPGConfig(), f)]
    assert changed and all(f.startswith("start_") for f in changed)
    with pytest.raises(ValueError, match="unknown start-up 'lean'; allowed: paper, lean_ramp"):
        cpg.with_startup(cpg.CPGConfig(), "lean")


def test_the_ramp_and_the_lean_follow_a_numpy_transcription():
    """4 s of the controller, open loop, the IMU pitched 10° nose-up: r integrates eq. (1) with the target μ·p(t),
    p(t) = min(1, t / 3 s), and the foot x of eq. (4) carries (1 − p(t))·h·tan(pitch)."""
    p = param_space.midpoint()
    pitch = -np.radians(10.0)
    obs = observation(quat=_pitch_quat(pitch))
    state = cpg.init_state(obs, LEAN_RAMP)
    np.testing.assert_allclose(float(state.start_pitch_rad), pitch, atol=1e-6)

    def body(s, _):
        s, _, diag = cpg.controller_step(LEAN_RAMP, s, jnp.asarray(p, jnp.float32), cpg.Gates(0.0, 0.0), obs)
        return s, (s.amplitude, s.phase_rad, diag.foot_target_m)

    _, (amp, phase, target) = jax.jit(lambda s: jax.lax.scan(body, s, None, length=4000))(state)
    r, theta = np.full(4, 0.1), np.asarray(cpg.TROT_PHASE_LAG_RAD[0] % (2 * np.pi))
    for k in range(4000):
        progress = min(1.0, (k + 1) * 1e-3 / 3.0)
        dr, dth = ref.hopf_derivatives(r, theta, progress * p[4], p[2], p[3], p[7], np.zeros(4), tegotae=False)
        r, theta = r + 1e-3 * dr, np.mod(theta + 1e-3 * dth, 2 * np.pi)
        if k in (499, 1499, 2999, 3999):
            np.testing.assert_allclose(amp[k], r, rtol=2e-3, atol=2e-4)
            # float32 Euler against float64: the phases drift apart by a few mrad over 4 s
            np.testing.assert_allclose(np.angle(np.exp(1j * (np.asarray(phase[k]) - theta))), 0.0, atol=1e-2)
            want = ref.foot_position(np.asarray(amp[k]), np.asarray(phase[k]), p)  # eqs. (4)-(5) of the state
            want[:, 0] += (1.0 - progress) * 0.30 * np.tan(pitch)
            np.testing.assert_allclose(target[k], want, atol=2e-4)
    assert float(np.max(amp[2999])) > 0.99 * p[4] and float(np.max(amp[499])) < 0.25 * p[4]


def _com_over_feet_m(m: mujoco.MjModel, qpos: np.ndarray) -> float:
    """The x distance [m] along the floor between the feet's centroid and the robot's centre of mass projected along
    gravity onto the floor (C MuJoCo's kinematics)."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    ids = go1_model.indices()
    com = d.subtree_com[ids.trunk_body]
    feet = d.geom_xpos[ids.foot_geom]
    floor_z = float(np.mean(feet[:, 2]))
    g = m.opt.gravity / np.linalg.norm(m.opt.gravity)
    at_floor = com + g * (com[2] - floor_z) / -g[2]
    return float(at_floor[0] - np.mean(feet[:, 0]))


def test_the_lean_stands_the_centre_of_mass_over_the_feet_as_on_level_ground():
    """Standing on level ground the centre of mass is ahead of the feet's centroid; on 10° and 12.5° uphill the
    paper's standing pose moves it back by about h·tan(slope) (5.3 and 6.7 cm), the lean's pose keeps it where it is
    on level ground, and the native backend's reset is that pose (the feet at h·tan(pitch) behind it)."""
    level = _com_over_feet_m(go1_model.load_model(), go1_model.standing_qpos())
    for slope_deg in (10.0, 12.5):
        scenario = go1_model.make_scenarios(slope_deg=[slope_deg])
        m = go1_model.scenario_model(scenario, 0)
        assert _com_over_feet_m(m, go1_model.standing_qpos(m)) - level < -0.04
        physics = native.NativeBackend(scenario, LEAN_RAMP).physics
        qpos = physics.standing_physics[0, physics.layout.qpos]
        assert abs(_com_over_feet_m(m, qpos) - level) < 0.002
        legs = qpos[go1_model.indices().joint_qpos].reshape(4, 3)
        feet = np.asarray(jax.vmap(kinematics.leg_fk)(jnp.asarray(legs, jnp.float32), kinematics.SIDE_SIGN))
        np.testing.assert_allclose(
            feet[:, 0], go1_model.STAND_FOOT_X_M + 0.30 * np.tan(-np.radians(slope_deg)), atol=1e-4
        )


def test_both_backends_and_the_robots_soft_start_stand_alike():
    from cpgjax import mjx_go1

    scenario = go1_model.make_scenarios(slope_deg=[12.5, 0.0])
    ids = go1_model.indices()
    physics = native.NativeBackend(scenario, LEAN_RAMP).physics
    native_q = physics.standing_physics[:, physics.layout.qpos][:, ids.joint_qpos]
    mjx_q = np.asarray(
        mjx_go1.MJXBackend(scenario, LEAN_RAMP).reset(np.tile(param_space.midpoint(), (2, 1))).data.qpos
    )[:, ids.joint_qpos]
    np.testing.assert_allclose(mjx_q, native_q, atol=2e-5)
    robot = np.stack([np.asarray(cpg.standing_pose_rad(LEAN_RAMP, _pitch_quat(-np.radians(s)))) for s in (12.5, 0.0)])
    np.testing.assert_allclose(robot, native_q, atol=2e-5)
    np.testing.assert_allclose(native_q[1], go1_model.standing_qpos()[ids.joint_qpos], atol=2e-6)  # level: no lean


def test_a_study_file_chooses_its_startup(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('name = "s"\ntrials = 4\nstartup = "lean_ramp"\n')
    spec = study_spec.read(path).spec
    assert spec.startup == "lean_ramp" and spec.cpg_config() == LEAN_RAMP
    assert study_spec.read(path, startup="paper").spec.startup is None  # the paper's: unset, as in older files
    path.write_text('name = "s"\ntrials = 4\nstartup = "lean"\n')
    with pytest.raises(study_spec.StudyError, match=r"startup: 'lean' is not allowed; allowed: paper, lean_ramp"):
        study_spec.read(path)
    with pytest.raises(study_spec.StudyError, match=r"unknown startup 'lean'; allowed: paper, lean_ramp"):
        study_spec.validate(study_spec.StudySpec("s", startup="lean"))  # the Python API, before any compute


def test_the_loopback_go1_starts_a_tuned_gait_on_10_degrees():
    """A gait tuned on 10° (tests/data/slope_10deg_gait.json: where it comes from) starts from standing on the
    loopback Go1's 10° slope with the lean_ramp start-up: the soft start stands at the leaning pose, no safety stop in
    6 s of walking, and the trunk climbs."""
    gait = json.loads((DATA / "slope_10deg_gait.json").read_text())
    params = np.array([gait["params"][name] for name in param_space.PARAM_NAMES])
    controller = compiled_controller.CompiledController(LEAN_RAMP)
    with sim.SimGo1Client(pacing="lockstep", slope_deg=10.0, physics=gait["physics"]) as robot:
        robot.reset()
        start_x = robot.stats()["trunk_xy_m"][0]
        transport = go1_transport.LockstepTransport(robot.address)
        try:
            result = hio.run_loop(
                transport,
                controller,
                hio.FixedParams(params, 6000),
                deploy.sim_calibration(),
                cpg.controller_gates(gait["controller"]),
            )
        finally:
            transport.close()
        climbed_m = robot.stats()["trunk_xy_m"][0] - start_x
    assert result.trip is None, result.events
    stood = result.log.command_q_rad[
        result.log.phase == hio.STAND if (result.log.phase == hio.STAND).any() else result.log.phase == hio.RAMP
    ][-1]
    legs = np.asarray(jax.vmap(kinematics.leg_fk)(jnp.asarray(stood.reshape(4, 3), jnp.float32), kinematics.SIDE_SIGN))
    assert np.all(legs[:, 0] < go1_model.STAND_FOOT_X_M - 0.04)  # leaning: the feet ≈ 5 cm further back
    assert climbed_m > 0.5, climbed_m
