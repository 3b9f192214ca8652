"""The Go1 in a rerun recording, full body: each rollout's bodies with their visual geoms (logged once), a transform
per body every ``TICK_STRIDE`` ticks, the floor at the trial's slope, each foot's contact force as an arrow, and the
CPG's phase and amplitude per leg; the rollout's labels (group, controller, seed, condition) form its entity path.

Entities below ``rollout/best_<group>/<controller>/seed=<seed>/<condition>``:

* ``world`` — the floor frame (the simulation's; x uphill, docs/decisions.md §4), rotated so that the viewer's z is
  against gravity; below it ``floor`` (a grey slab whose top is the floor, tilted with the frame; on rough ground
  the height field's surface as a mesh, lighter where higher), ``robot/<body>``
  (per-body transforms; the body's geoms as boxes, cylinders and spheres below; ``robot/payload/boxes`` the
  payload's box, only where the rollout carries one) and ``contact_force/<leg>`` (arrows
  from each foot centre along the floor normal, ``FORCE_ARROW_M_PER_N`` long per newton).
* ``cpg/phase_rad/<leg>``, ``cpg/amplitude/<leg>``, ``foot_force_n/<leg>``, ``attitude_rad/<axis>`` — scalars every
  tick.

Timelines: ``step`` (the tick, 1 ms) and ``sim_time`` (the same as a duration, so the viewer plays in real time).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import mujoco
import numpy as np

from cpgjax.go1 import constants
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import terrain as terrains
from cpgjax.trial.condition import Condition

TICK_STRIDE = 10  # body transforms and arrows at 100 Hz (the scalars every tick)
FORCE_ARROW_M_PER_N = 0.004  # a foot carrying a quarter of the robot's weight (31 N): a 12 cm arrow
FLOOR_MARGIN_M = 0.6  # the floor slab spans the trunk's path and this much around it (its top at z = 0)
FLOOR_THICKNESS_M = 0.01


class Rollout(NamedTuple):
    """One rollout to record: its per-tick log (``protocol.StepLog`` of arrays (T, ...)) and its labels."""

    log: Any
    group: str
    controller: str
    seed: int
    condition: Condition


def entity_path(rollout: Rollout) -> str:
    import rerun as rr

    parts = (
        f"best_{rollout.group}",
        rollout.controller,
        f"seed={rollout.seed}",
        f"friction={rollout.condition.friction:g},slope_deg={rollout.condition.slope_deg:g},"
        f"payload_kg={rollout.condition.payload_kg:g}",
    )
    return "rollout/" + "/".join(rr.escape_entity_path_part(p) for p in parts)


def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    return np.asarray(wxyz)[..., [1, 2, 3, 0]]


def body_poses(qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (floor-frame) positions (T, nbody, 3) and quaternions (T, nbody, 4, wxyz) of every body of the visual
    model at each qpos row, by MuJoCo's forward kinematics."""
    m = go1_model.load_visual_model()
    d = mujoco.MjData(m)
    pos = np.empty((len(qpos), m.nbody, 3))
    quat = np.empty((len(qpos), m.nbody, 4))
    for k, row in enumerate(np.asarray(qpos, np.float64)):
        d.qpos[:] = row
        mujoco.mj_kinematics(m, d)
        pos[k], quat[k] = d.xpos, d.xquat
    return pos, quat


def _rgba(m, g) -> list[int]:
    return [int(round(255 * c)) for c in m.geom_rgba[g]]


def _log_geoms(rec, base: str, m: mujoco.MjModel, body: int) -> None:
    """The visual geoms of ``body`` in its frame, one entity per shape kind."""
    import rerun as rr

    geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == body and m.geom_group[g] == go1_model.VISUAL_GROUP]
    kinds = {
        int(mujoco.mjtGeom.mjGEOM_BOX): "boxes",
        int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinders",
        int(mujoco.mjtGeom.mjGEOM_SPHERE): "spheres",
    }
    for kind, name in kinds.items():
        these = [g for g in geoms if int(m.geom_type[g]) == kind]
        if not these:
            continue
        centers, quats = m.geom_pos[these], _xyzw(m.geom_quat[these])
        colors = [_rgba(m, g) for g in these]
        size = m.geom_size[these]
        if name == "boxes":
            shape = rr.Boxes3D(half_sizes=size, centers=centers, quaternions=quats, colors=colors, fill_mode="solid")
        elif name == "cylinders":  # MuJoCo's and rerun's cylinders both lie along their z
            shape = rr.Cylinders3D(
                radii=size[:, 0],
                lengths=2 * size[:, 1],
                centers=centers,
                quaternions=quats,
                colors=colors,
                fill_mode="solid",
            )
        else:
            shape = rr.Ellipsoids3D(
                half_sizes=np.repeat(size[:, :1], 3, axis=1), centers=centers, colors=colors, fill_mode="solid"
            )
        rr.log(f"{base}/{name}", shape, static=True, recording=rec)
    unknown = [g for g in geoms if int(m.geom_type[g]) not in kinds]
    if unknown:
        raise ValueError(
            f"visual geom {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, unknown[0])!r}: only boxes, "
            "cylinders and spheres are recorded"
        )


def payload_box():
    """The payload as drawn: a box of ``go1_model.PAYLOAD_BOX_M`` centred on the carrier body's frame (which has no
    geom), in ``go1_model.PAYLOAD_RGBA``."""
    import rerun as rr

    return rr.Boxes3D(
        half_sizes=[np.asarray(go1_model.PAYLOAD_BOX_M) / 2],
        colors=[[int(round(255 * c)) for c in go1_model.PAYLOAD_RGBA]],
        fill_mode="solid",
    )


def field_mesh(ground: terrains.Ground, low_m: np.ndarray, high_m: np.ndarray) -> dict[str, np.ndarray]:
    """The height field's surface over the floor-frame rectangle [low, high] (the cells that cover it) as a
    triangle mesh: ``vertex_positions`` (N, 3) [m] at the field's vertices and heights, ``triangle_indices`` (M, 3)
    split along each cell's diagonal from (c, r) to (c + 1, r + 1) as MuJoCo splits it."""
    heights = terrains.field_heights_m(ground)
    n = terrains.FIELD_VERTICES
    first = np.clip(np.floor((np.asarray(low_m) + terrains.FIELD_HALF_M) / terrains.CELL_M).astype(int), 0, n - 2)
    last = np.clip(np.ceil((np.asarray(high_m) + terrains.FIELD_HALF_M) / terrains.CELL_M).astype(int), 1, n - 1)
    cols, rows = np.arange(first[0], last[0] + 1), np.arange(first[1], last[1] + 1)
    c, r = np.meshgrid(cols, rows)  # (rows, cols)
    vertices = np.stack(
        [c * terrains.CELL_M - terrains.FIELD_HALF_M, r * terrains.CELL_M - terrains.FIELD_HALF_M, heights[r, c]],
        axis=-1,
    ).reshape(-1, 3)
    width = len(cols)
    at = (np.arange(len(rows) - 1)[:, None] * width + np.arange(width - 1)[None, :]).reshape(-1)  # cell (c, r)
    triangles = np.concatenate(
        [
            np.stack([at, at + 1, at + width + 1], -1),  # (0, 0), (1, 0), (1, 1)
            np.stack([at, at + width + 1, at + width], -1),
        ]
    )  # (0, 0), (1, 1), (0, 1)
    return {"vertex_positions": vertices, "triangle_indices": triangles}


def log_rollout(rec, rollout: Rollout) -> str:
    """Log one rollout (see the module's docstring) into the recording stream ``rec``; returns its entity path."""
    import rerun as rr

    log = rollout.log
    base = entity_path(rollout)
    m = go1_model.load_visual_model()
    qpos = np.asarray(log.qpos, np.float64)
    ticks = np.arange(qpos.shape[0])
    every = ticks[::TICK_STRIDE]

    def index(t):
        return [rr.TimeColumn("step", sequence=t), rr.TimeColumn("sim_time", duration=t * constants.TICK_S)]

    tilt = _xyzw(go1_model.slope_quaternion(rollout.condition.slope_deg))
    rr.log(f"{base}/world", rr.Transform3D(quaternion=tilt), static=True, recording=rec)
    trunk_xy = qpos[:, go1_model.indices().root_qpos : go1_model.indices().root_qpos + 2]
    low, high = trunk_xy.min(axis=0) - FLOOR_MARGIN_M, trunk_xy.max(axis=0) + FLOOR_MARGIN_M
    if rollout.condition.ground.terrain == terrains.FLAT:
        floor = rr.Boxes3D(
            mins=[[*low, -FLOOR_THICKNESS_M]],
            sizes=[[*(high - low), FLOOR_THICKNESS_M]],
            colors=[[190, 190, 185, 255]],
            fill_mode="solid",
        )
    else:
        mesh = field_mesh(rollout.condition.ground, low, high)
        shade = 150 + 80 * (mesh["vertex_positions"][:, 2] / terrains.MAX_AMPLITUDE_M + 0.5)  # lighter higher
        floor = rr.Mesh3D(**mesh, vertex_colors=np.stack([shade, shade, 0.97 * shade], -1).astype(np.uint8))
    rr.log(f"{base}/world/floor", floor, static=True, recording=rec)
    pos, quat = body_poses(qpos[every])
    payload_body = go1_model.indices().payload_body
    for body in range(1, m.nbody):
        path = f"{base}/world/robot/{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body)}"
        if body == payload_body:  # no geom: the payload's box, where there is a payload
            if rollout.condition.payload_kg <= 0.0:
                continue
            rr.log(f"{path}/boxes", payload_box(), static=True, recording=rec)
        else:
            _log_geoms(rec, path, m, body)
        rr.send_columns(
            path,
            indexes=index(every),
            columns=rr.Transform3D.columns(translation=pos[:, body], quaternion=_xyzw(quat[:, body])),
            recording=rec,
        )
    feet = np.asarray(log.foot_pos_m, np.float64)[every]  # (T', 4, 3) floor frame
    force = np.asarray(log.foot_force_n, np.float64)[every]  # (T', 4) normal force
    for k, leg in enumerate(constants.LEG_NAMES):
        vectors = np.zeros((len(every), 3))
        vectors[:, 2] = force[:, k] * FORCE_ARROW_M_PER_N
        rr.send_columns(
            f"{base}/world/contact_force/{leg}",
            indexes=index(every),
            columns=rr.Arrows3D.columns(origins=feet[:, k], vectors=vectors, colors=[[220, 60, 40, 255]] * len(every)),
            recording=rec,
        )
    for k, leg in enumerate(constants.LEG_NAMES):
        for key, values in (
            ("cpg/phase_rad", log.phase_rad),
            ("cpg/amplitude", log.amplitude),
            ("foot_force_n", log.foot_force_n),
        ):
            rr.send_columns(
                f"{base}/{key}/{leg}",
                indexes=index(ticks),
                columns=rr.Scalars.columns(scalars=np.asarray(values[:, k], np.float64)),
                recording=rec,
            )
    for k, axis in enumerate(("roll", "pitch", "yaw")):
        rr.send_columns(
            f"{base}/attitude_rad/{axis}",
            indexes=index(ticks),
            columns=rr.Scalars.columns(scalars=np.asarray(log.rpy_rad[:, k], np.float64)),
            recording=rec,
        )
    return base


def blueprint(bases: list[str]):
    """The viewer's layout: a tab per rollout (its 3D scene beside its CPG phases and foot forces), then a tab of the
    optimization's curves."""
    import rerun.blueprint as rrb

    tabs = [
        rrb.Horizontal(
            rrb.Spatial3DView(origin=f"{base}/world", name=base.split("/")[1]),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{base}/cpg/phase_rad", name="CPG phase [rad]"),
                rrb.TimeSeriesView(origin=f"{base}/foot_force_n", name="foot normal force [N]"),
            ),
            column_shares=[2, 1],
            name=base.split("/")[1],
        )
        for base in bases
    ]
    tabs.append(
        rrb.Grid(
            *(
                rrb.TimeSeriesView(origin=f"/optimization/{key}", name=key)
                for key in ("objective", "velocity_x_mps", "cost_of_transport", "c_load_n", "c_slope_rad", "beta")
            ),
            name="optimization",
        )
    )
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)
