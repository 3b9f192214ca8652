"""The full-body recording (cpgjax/study/scene.py), read back from the .rrd: every body with its geoms, per-body
transforms that put the feet where the analytic leg kinematics does, the floor frame's tilt, the contact-force arrows
and the labels in the entity path."""

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from cpgjax.go1 import attitude, kinematics
from cpgjax.go1 import model as go1_model
from cpgjax.study import scene
from cpgjax.trial import protocol
from cpgjax.trial.condition import Condition

TICKS = 60


def _synthetic_log():
    """A rollout log whose legs swing and whose trunk moves and turns (no simulation needed)."""
    ids = go1_model.indices()
    t = np.arange(TICKS) * 1e-3
    qpos = np.tile(go1_model.standing_qpos(), (TICKS, 1))
    r = ids.root_qpos
    qpos[:, r] += 0.5 * t
    yaw = 0.3 + 2.0 * t
    qpos[:, r + 3 : r + 7] = np.stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)], axis=1)
    qpos[:, ids.joint_qpos] += 0.3 * np.sin(2 * np.pi * 5 * t)[:, None] * np.tile([0.3, 1.0, -0.8], 4)
    rng = np.random.default_rng(0)
    fields = dict(
        qpos=qpos,
        qvel=np.zeros((TICKS, 18)),
        torque_nm=np.zeros((TICKS, 12)),
        foot_force_n=rng.uniform(0, 60, (TICKS, 4)),
        foot_pos_m=rng.uniform(-1, 1, (TICKS, 4, 3)),
        amplitude=rng.uniform(0.8, 1.2, (TICKS, 4)),
        phase_rad=rng.uniform(0, 6, (TICKS, 4)),
        foot_target_m=np.zeros((TICKS, 4, 3)),
        rpy_rad=rng.uniform(-0.1, 0.1, (TICKS, 3)),
    )
    return protocol.StepLog(**fields)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    log = _synthetic_log()
    rollout = scene.Rollout(
        log=log,
        group="friction0.3",
        controller="vmc_tegotae",
        seed=1,
        condition=Condition(friction=0.3, slope_deg=7.5, payload_kg=2.0),
    )
    path = tmp_path_factory.mktemp("scene") / "one.rrd"
    rec = rr.RecordingStream("test_scene")
    rec.save(str(path))
    base = scene.log_rollout(rec, rollout)
    rec.flush()
    rec.disconnect()
    chunks = {}
    for chunk in RrdReader(path).stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return log, rollout, "/" + base, chunks


def _column(chunks, entity, name) -> list:
    """The rows of a component column of an entity (each row a list of instances), in logged order."""
    return [row for b in chunks[entity] if name in b.schema.names for row in b.column(name).to_pylist()]


def _first(rows) -> np.ndarray:
    """The first instance of each row, as floats."""
    return np.array([row[0] for row in rows], float)


def test_the_labels_are_in_the_entity_path(recorded):
    _, _, base, _ = recorded
    assert base == ("/rollout/best_friction0.3/vmc_tegotae/seed\\=1/friction\\=0.3\\,slope_deg\\=7.5\\,payload_kg\\=2")


def test_every_body_and_geom_is_recorded(recorded):
    _, _, base, chunks = recorded
    m = go1_model.load_visual_model()
    shapes = 0
    for body in ("trunk", *(f"{leg}_{part}" for leg in ("FR", "FL", "RR", "RL") for part in ("hip", "thigh", "calf"))):
        entity = f"{base}/world/robot/{body}"
        assert len(_column(chunks, entity, "Transform3D:translation")) == len(range(0, TICKS, scene.TICK_STRIDE))
        for kind, size in (
            ("boxes", "Boxes3D:half_sizes"),
            ("cylinders", "Cylinders3D:radii"),
            ("spheres", "Ellipsoids3D:half_sizes"),
        ):
            if f"{entity}/{kind}" in chunks:
                shapes += len(_column(chunks, f"{entity}/{kind}", size)[0])
    assert shapes == int(np.sum(m.geom_group == go1_model.VISUAL_GROUP)) == 29
    (half,) = _column(chunks, f"{base}/world/robot/FR_calf/spheres", "Ellipsoids3D:half_sizes")[0]
    np.testing.assert_allclose(np.array(half, float), [0.02] * 3, rtol=1e-6)


def test_the_transforms_put_the_feet_where_the_leg_kinematics_does(recorded):
    """Foot centre = the calf's recorded transform applied to the foot sphere's centre, against the trunk pose from
    qpos and the analytic leg FK (go1.kinematics, docs/go1-model.md)."""
    log, _, base, chunks = recorded
    ids = go1_model.indices()
    ticks = np.arange(0, TICKS, scene.TICK_STRIDE)
    (center,) = _column(chunks, f"{base}/world/robot/FR_calf/spheres", "Ellipsoids3D:centers")[0]
    for k, leg in enumerate(("FR", "FL", "RR", "RL")):
        entity = f"{base}/world/robot/{leg}_calf"
        pos = _first(_column(chunks, entity, "Transform3D:translation"))
        quat = _first(_column(chunks, entity, "Transform3D:quaternion"))
        for row, tick in enumerate(ticks):
            q = log.qpos[tick]
            trunk_quat = q[ids.root_qpos + 3 : ids.root_qpos + 7]
            q_leg = q[ids.joint_qpos[3 * k : 3 * k + 3]]
            foot_trunk = kinematics.HIP_POS_M[k] + np.asarray(kinematics.leg_fk(q_leg, kinematics.SIDE_SIGN[k]))
            expected = q[ids.root_qpos : ids.root_qpos + 3] + attitude.quat_rotate(trunk_quat, foot_trunk)
            recorded_foot = pos[row] + attitude.quat_rotate(quat[row, [3, 0, 1, 2]], np.array(center, float))
            np.testing.assert_allclose(recorded_foot, expected, atol=2e-5)


def test_the_world_is_tilted_by_the_slope_and_the_arrows_are_the_forces(recorded):
    log, rollout, base, chunks = recorded
    (tilt,) = _first(_column(chunks, f"{base}/world", "Transform3D:quaternion"))
    down = attitude.quat_rotate(tilt[[3, 0, 1, 2]], go1_model.gravity_vector(rollout.condition.slope_deg))
    np.testing.assert_allclose(down / np.linalg.norm(down), [0, 0, -1], atol=1e-6)
    (center,) = _first(_column(chunks, f"{base}/world/floor", "Boxes3D:centers"))
    (half,) = _first(_column(chunks, f"{base}/world/floor", "Boxes3D:half_sizes"))
    assert center[2] + half[2] == pytest.approx(0.0, abs=1e-6)  # the floor's top is the floor frame's z = 0
    trunk = log.qpos[:, go1_model.indices().root_qpos : go1_model.indices().root_qpos + 2]
    assert np.all(np.abs(trunk - center[:2]) < half[:2])  # under the whole walk
    ticks = np.arange(0, TICKS, scene.TICK_STRIDE)
    for k, leg in enumerate(("FR", "FL", "RR", "RL")):
        entity = f"{base}/world/contact_force/{leg}"
        origins = _first(_column(chunks, entity, "Arrows3D:origins"))
        vectors = _first(_column(chunks, entity, "Arrows3D:vectors"))
        np.testing.assert_allclose(origins, log.foot_pos_m[ticks, k], atol=1e-6)
        np.testing.assert_allclose(vectors[:, 2], log.foot_force_n[ticks, k] * scene.FORCE_ARROW_M_PER_N, rtol=1e-6)
        assert np.all(vectors[:, :2] == 0)
    phase = _first(_column(chunks, f"{base}/cpg/phase_rad/FL", "Scalars:scalars"))
    np.testing.assert_allclose(phase, log.phase_rad[:, 1])


def test_the_payload_is_a_box_at_the_carrier_body_and_absent_without_one(recorded, tmp_path):
    """A rollout with a payload (the fixture's 2 kg): ``robot/payload/boxes`` is one box of the payload's size, and its
    transforms put the box's centre at the carrier body's place in the trunk (go1.xml's ``payload`` pos) at every
    recorded tick; the same rollout without a payload records no payload entity."""
    log, rollout, base, chunks = recorded
    (half,) = _column(chunks, f"{base}/world/robot/payload/boxes", "Boxes3D:half_sizes")[0]
    np.testing.assert_allclose(np.array(half, float), np.asarray(go1_model.PAYLOAD_BOX_M) / 2, rtol=1e-6)
    ids = go1_model.indices()
    carrier_m = go1_model.load_model().body_pos[ids.payload_body]
    np.testing.assert_allclose(carrier_m, [0.0223, 0.002, -0.0005])  # at the trunk's centre of mass
    pos = _first(_column(chunks, f"{base}/world/robot/payload", "Transform3D:translation"))
    quat = _first(_column(chunks, f"{base}/world/robot/payload", "Transform3D:quaternion"))
    for row, tick in enumerate(np.arange(0, TICKS, scene.TICK_STRIDE)):
        q = log.qpos[tick]
        trunk_quat = q[ids.root_qpos + 3 : ids.root_qpos + 7]
        np.testing.assert_allclose(
            pos[row], q[ids.root_qpos : ids.root_qpos + 3] + attitude.quat_rotate(trunk_quat, carrier_m), atol=1e-6
        )
        np.testing.assert_allclose(np.abs(quat[row, [3, 0, 1, 2]] @ trunk_quat), 1.0, atol=1e-6)  # the trunk's axes

    path = tmp_path / "unladen.rrd"
    rec = rr.RecordingStream("test_scene")
    rec.save(str(path))
    unladen = "/" + scene.log_rollout(rec, rollout._replace(condition=rollout.condition._replace(payload_kg=0.0)))
    rec.flush()
    rec.disconnect()
    entities = {chunk.entity_path for chunk in RrdReader(path).stream()}
    assert f"{unladen}/world/robot/trunk" in entities
    assert not [e for e in entities if "/robot/payload" in e]
