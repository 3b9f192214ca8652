"""The Go1's visual geoms: sized as the URDF's link geometry, placed at the links' frames, and invisible to the
physics (no contact, no mass): C MuJoCo steps bit for bit the same with them, and a study's trials.parquet is
byte-identical with and without them; both simulators run the model without them (go1_model.load_model)."""

import mujoco
import numpy as np
import pytest

from cpgjax import ablation, mjx_go1
from cpgjax.go1 import constants
from cpgjax.go1 import model as go1_model
from cpgjax.study import files as study_io
from cpgjax.study.spec import StudySpec
from cpgjax.trial import protocol
from tests.test_ablation import small_optimizer

# unitree_ros robots/go1_description/xacro/const.xacro (commit ca57a18): the "simplified collision value" link
# geometry, full lengths [m]; rotors: leg.xacro's cylinders (radius 0.035, length 0.02).
URDF_TRUNK_BOX_M = (0.3762, 0.0935, 0.114)
URDF_HIP_CYLINDER_M = (0.046, 0.04)  # radius, length (along y)
URDF_THIGH_BOX_M = (0.034, 0.0245, 0.213)  # x, y, z after leg.xacro's rpy (0, π/2, 0): the length along −z
URDF_CALF_BOX_M = (0.016, 0.016, 0.213)
URDF_ROTOR_CYLINDER_M = (0.035, 0.02)
URDF_FOOT_RADIUS_M = 0.02


def _geom(m, name):
    return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)


def _visual_geoms(m):
    return [g for g in range(m.ngeom) if m.geom_group[g] == go1_model.VISUAL_GROUP]


def test_visual_geoms_have_the_urdf_sizes():
    m = go1_model.load_visual_model()
    box, cyl, sphere = mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE
    expected = {"trunk_visual": (box, np.array(URDF_TRUNK_BOX_M) / 2)}
    for leg in constants.LEG_NAMES:
        expected[f"{leg}_hip_visual"] = (cyl, [URDF_HIP_CYLINDER_M[0], URDF_HIP_CYLINDER_M[1] / 2])
        expected[f"{leg}_thigh_visual"] = (box, np.array(URDF_THIGH_BOX_M) / 2)
        expected[f"{leg}_calf_visual"] = (box, np.array(URDF_CALF_BOX_M) / 2)
        expected[f"{leg}_foot_visual"] = (sphere, [URDF_FOOT_RADIUS_M])
        for rotor in ("hip_rotor", "thigh_rotor", "calf_rotor"):
            expected[f"{leg}_{rotor}_visual"] = (cyl, [URDF_ROTOR_CYLINDER_M[0], URDF_ROTOR_CYLINDER_M[1] / 2])
    assert sorted(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in _visual_geoms(m)) == sorted(expected)
    for name, (kind, size) in expected.items():
        g = _geom(m, name)
        assert m.geom_type[g] == kind, name
        np.testing.assert_allclose(m.geom_size[g, : len(size)], size, rtol=0, atol=1e-12, err_msg=name)


def test_visual_geoms_sit_at_the_link_frames():
    """Standing pose: each thigh box spans its thigh joint to its knee, each calf box its knee to its foot centre, the
    visual foot is the collision foot and the hip cylinder's axis is the thigh joint's (both along the body y)."""
    m = go1_model.load_visual_model()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    mujoco.mj_forward(m, d)
    for leg in constants.LEG_NAMES:
        thigh_joint = d.xanchor[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{leg}_thigh_joint")]
        knee = d.xanchor[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{leg}_calf_joint")]
        foot = d.geom_xpos[_geom(m, f"{leg}_foot")]
        np.testing.assert_allclose(d.geom_xpos[_geom(m, f"{leg}_thigh_visual")], (thigh_joint + knee) / 2, atol=1e-12)
        np.testing.assert_allclose(d.geom_xpos[_geom(m, f"{leg}_calf_visual")], (knee + foot) / 2, atol=1e-12)
        np.testing.assert_allclose(d.geom_xpos[_geom(m, f"{leg}_foot_visual")], foot, atol=1e-12)
        hip = _geom(m, f"{leg}_hip_visual")
        np.testing.assert_allclose(d.geom_xpos[hip], thigh_joint, atol=1e-12)
        axis = d.geom_xmat[hip].reshape(3, 3)[:, 2]  # a cylinder's axis is its z
        joint_axis = d.xaxis[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{leg}_thigh_joint")]
        assert abs(axis @ joint_axis) == pytest.approx(1.0, abs=1e-12)
        # the thigh box's length is along the segment joint → knee
        thigh = d.geom_xmat[_geom(m, f"{leg}_thigh_visual")].reshape(3, 3)[:, 2]
        segment = (knee - thigh_joint) / np.linalg.norm(knee - thigh_joint)
        assert abs(thigh @ segment) == pytest.approx(1.0, abs=1e-9)


def test_visual_geoms_neither_collide_nor_weigh():
    m, bare = go1_model.load_visual_model(), go1_model.load_model()
    assert m.ngeom - bare.ngeom == len(_visual_geoms(m)) == 1 + 4 * 7
    for g in _visual_geoms(m):
        assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0
    for field in (
        "body_mass",
        "body_inertia",
        "body_ipos",
        "body_iquat",
        "body_subtreemass",
        "dof_invweight0",
        "actuator_acc0",
    ):
        np.testing.assert_array_equal(getattr(m, field), getattr(bare, field), err_msg=field)
    # the same motion, bit for bit: 300 steps from the standing pose under a fixed torque that makes the legs move
    states = []
    for model in (m, bare):
        d = mujoco.MjData(model)
        d.qpos[:] = go1_model.standing_qpos(model)
        d.ctrl[:] = np.tile([2.0, -3.0, 5.0], 4)
        for _ in range(300):
            mujoco.mj_step(model, d)
        states.append((d.qpos.copy(), d.qvel.copy(), d.sensordata.copy(), d.ncon))
    for a, b in zip(*states, strict=True):
        np.testing.assert_array_equal(a, b)
    assert states[0][3] > 0  # the feet touch the floor


def _study_table(tmp_path, backend: str) -> bytes:
    spec = StudySpec(
        "visual_check",
        num_trials=3,
        controllers=("vmc_tegotae",),
        seeds=(0, 1),
        trial=protocol.TrialConfig(transition_steps=100, steady_steps=200),
        optimizer=small_optimizer(3),
    )
    result = ablation.Engine(spec, backend=backend).run(tmp_path)
    return study_io.write_trials(result, tmp_path / "trials.parquet").read_bytes()


def test_both_simulators_run_the_model_without_visual_geoms():
    physics_geoms = go1_model.load_model().ngeom
    assert not _visual_geoms(go1_model.load_model())
    scenario = go1_model.make_scenarios(friction=[0.6, 0.3], slope_deg=[0.0, 5.0], payload_kg=[0.0, 7.5])
    assert go1_model.scenario_model(scenario, 1).ngeom == physics_geoms  # the native backend's per-instance model
    assert mjx_go1.make_batch_model(scenario).model.ngeom == physics_geoms


@pytest.mark.slow
def test_study_trials_identical_with_visual_geoms(tmp_path, monkeypatch):
    """C MuJoCo (the native backend) running the model with its visual geoms gives the same study, byte for byte."""
    shipped = _study_table(tmp_path / "shipped", "native")
    for cached in (go1_model.indices, go1_model.model_with_payload):
        cached.cache_clear()
    monkeypatch.setattr(go1_model, "load_model", go1_model.load_visual_model)
    try:
        assert go1_model.model_with_payload(0.0).ngeom == go1_model.load_visual_model().ngeom  # it runs the looks
        with_looks = _study_table(tmp_path / "visual", "native")
    finally:
        for cached in (go1_model.indices, go1_model.model_with_payload):
            cached.cache_clear()
    assert len(shipped) > 1000 and shipped == with_looks
