"""cpgjax's Go1 model: loading, names resolved to indices, scenarios (friction, slope, payload, terrain) as
per-instance models, and the standing pose. Shared by every physics backend (MJX, C MuJoCo) so they simulate the
same robot.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import xml.etree.ElementTree as ElementTree
from importlib import resources
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax.go1 import constants, kinematics
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains

MODEL_FILE = "go1.xml"
JOINT_NAMES = tuple(f"{leg}_{part}_joint" for leg in constants.LEG_NAMES for part in constants.JOINT_PARTS)
FOOT_SENSOR_NAMES = tuple(f"{leg}_foot_force" for leg in constants.LEG_NAMES)
log = logging.getLogger(__name__)

MAX_ABS_SLOPE_DEG = 45.0
# docs/decisions.md §6: the payload is a rigid box of 0.3 x 0.2 x 0.1 m at the trunk's centre of mass.
PAYLOAD_BOX_M = (0.3, 0.2, 0.1)
# The payload carrier has no geom (the simulated model stays as is): videos and recordings draw that box at the
# carrier body's pose in this colour, where the payload is not zero.
PAYLOAD_RGBA = (0.9, 0.5, 0.1, 1.0)
# Standing pose: feet under the hips at the controller's nominal height h = 0.30 m (foot centre), x at the middle
# of the x-offset range; the foot sphere radius puts the trunk origin at 0.32 m.
STAND_FOOT_X_M = -0.035
STAND_FOOT_Z_M = -0.30
FOOT_RADIUS_M = 0.02
VISUAL_GROUP = 2  # the geom group of the geoms that are only seen (go1.xml's classes visual_*)
# The terrain model (:func:`load_terrain_model`): the contacts each foot sensor sums. A foot sphere (radius 0.02 m)
# on cells of terrain.CELL_M = 0.075 m overlaps at most 2 × 2 cells, 8 of the height field's triangular prisms, and
# MuJoCo makes at most one contact per prism (MJX at most 4 per pair).
FOOT_CONTACT_SLOTS = 8
# The terrain model's collision bits: the feet against the height field, the rest of the robot against a plane at
# the field's lowest level (a box against a height field costs 16x a plane in MJX: docs/physics.md, "Terrain").
_FEET_BIT, _BODY_BIT = 2, 1


def _model_xml() -> str:
    return resources.files("cpgjax.go1.assets").joinpath(MODEL_FILE).read_text()


def _with_terrain(xml: str) -> str:
    """go1.xml with the floor a height field (``terrain``, the geom keeping the name and index ``floor``): the feet
    collide with it, every other robot geom with the plane ``floor_below`` at the field's lowest level (on a static
    body after the robot, so that no body's or geom's index changes), and each foot sensor reports up to
    FOOT_CONTACT_SLOTS contacts, deepest first. The heights are the model's ``hfield_data`` (``terrain``)."""
    root = ElementTree.fromstring(xml)
    nrow = ncol = str(terrains.FIELD_VERTICES)
    ElementTree.SubElement(
        root.find("asset"),
        "hfield",
        name="terrain",
        nrow=nrow,
        ncol=ncol,
        size=" ".join(repr(v) for v in terrains.hfield_size()),
    )
    world = root.find("worldbody")
    floor = world.find("geom[@name='floor']")
    low_m = -terrains.MAX_AMPLITUDE_M / 2.0
    floor.attrib.update(type="hfield", hfield="terrain", pos=f"0 0 {low_m!r}", contype=str(_FEET_BIT))
    floor.attrib.pop("size")
    below = ElementTree.SubElement(world, "body", name="floor_below", pos=f"0 0 {low_m!r}")
    ElementTree.SubElement(
        below,
        "geom",
        name="floor_below",
        type="plane",
        size="0 0 0.05",
        contype=str(_BODY_BIT),
        conaffinity="0",
        priority=floor.get("priority"),
        friction=floor.get("friction"),
        group="3",
    )
    for geom in root.iter("geom"):
        if geom.get("name", "").endswith("_foot"):
            geom.set("conaffinity", str(_FEET_BIT))
    for sensor in root.find("sensor").iter("contact"):
        sensor.set("num", str(FOOT_CONTACT_SLOTS))
    return ElementTree.tostring(root, encoding="unicode")


def model_xml_without_visual_geoms() -> str:
    """go1.xml with its visual geoms (classes ``visual_*``) removed: the physics alone."""
    root = ElementTree.fromstring(_model_xml())
    for parent in root.iter():
        for geom in [g for g in parent.findall("geom") if g.get("class", "").startswith("visual")]:
            parent.remove(geom)
    return ElementTree.tostring(root, encoding="unicode")


@functools.cache
def load_model() -> mujoco.MjModel:
    """The nominal Go1 MjModel that both simulators run (no payload, flat floor, friction 0.6): go1.xml without its
    visual geoms. Cached: copy before editing.

    The visual geoms are physically inert (no contact, no mass: C MuJoCo steps bit for bit the same with them,
    tests/go1/test_model_visual.py), but MJX compiles its kinematics over every geom, and with 29 more the compiled
    program rounds differently in float32 (a short study's figures differ by ~1e-7 relative, then the optimizer
    amplifies it). Leaving them out keeps every simulation independent of the model's looks."""
    return mujoco.MjModel.from_xml_string(model_xml_without_visual_geoms())


@functools.cache
def load_terrain_model() -> mujoco.MjModel:
    """:func:`load_model` with the floor a height field of flat heights (``_with_terrain``): the model of a batch
    with a terrain other than flat. Bodies, joints, geoms and actuators keep their indices; the foot sensors have
    FOOT_CONTACT_SLOTS slots each (:func:`foot_contact_slots`). Cached: copy before editing."""
    m = mujoco.MjModel.from_xml_string(_with_terrain(model_xml_without_visual_geoms()))
    m.hfield_data[:] = terrains.hfield_data(terrains.FLAT_GROUND)
    return m


@functools.cache
def _visual_terrain_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(_with_terrain(_model_xml()))


def visual_model(ground: terrains.Ground = terrains.FLAT_GROUND) -> mujoco.MjModel:
    """The model a video or a recording draws on ``ground``: :func:`load_visual_model` on flat ground (cached: copy
    before editing), else a fresh copy of it with the terrain model's height field carrying the ground's heights."""
    if ground.terrain == terrains.FLAT:
        return load_visual_model()
    m = _visual_terrain_model().__copy__()
    m.hfield_data[:] = terrains.hfield_data(ground)
    return m


@functools.cache
def load_visual_model() -> mujoco.MjModel:
    """go1.xml as written, visual geoms included (group ``VISUAL_GROUP``): the model that videos and recordings
    draw, with the same bodies, joints and qpos layout as :func:`load_model`. Cached: copy before editing."""
    return mujoco.MjModel.from_xml_string(_model_xml())


@dataclasses.dataclass(frozen=True)
class Go1Indices:
    """Model indices resolved by name (never hard-coded)."""

    trunk_body: int
    payload_body: int
    floor_geom: int
    root_qpos: int  # first of 7 free-joint qpos entries (position, quaternion wxyz)
    root_dof: int  # first of 6 free-joint dofs (linear velocity in world frame, angular velocity in trunk frame)
    joint_qpos: np.ndarray  # (12,) qpos address of each leg joint, motor order
    joint_dof: np.ndarray  # (12,) dof address of each leg joint
    actuator: np.ndarray  # (12,) actuator id driving each leg joint
    foot_force_sensor: np.ndarray  # (4,) sensordata address of each foot's contact force (normal component first)
    foot_contact_data: np.ndarray  # (4, 9) sensordata addresses of each foot's (force | normal | tangent) slots
    #                                (the flat model's; the terrain model's: foot_contact_slots)
    calf_body: np.ndarray  # (4,) calf bodies (the foot sphere's body)
    foot_geom: np.ndarray  # (4,) foot sphere geoms


@functools.cache
def indices() -> Go1Indices:
    """Indices of the named bodies, joints, actuators and sensors (identical in every scenario variant)."""
    m = load_model()

    def obj_id(kind, name):
        i = mujoco.mj_name2id(m, kind, name)
        if i < 0:
            raise KeyError(f"the Go1 model has no {kind.name} named {name!r}")
        return i

    joints = [obj_id(mujoco.mjtObj.mjOBJ_JOINT, n) for n in JOINT_NAMES]
    actuator_of_joint = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)}
    root = obj_id(mujoco.mjtObj.mjOBJ_JOINT, "root")
    sensors = [obj_id(mujoco.mjtObj.mjOBJ_SENSOR, n) for n in FOOT_SENSOR_NAMES]
    return Go1Indices(
        trunk_body=obj_id(mujoco.mjtObj.mjOBJ_BODY, "trunk"),
        payload_body=obj_id(mujoco.mjtObj.mjOBJ_BODY, "payload"),
        floor_geom=obj_id(mujoco.mjtObj.mjOBJ_GEOM, "floor"),
        root_qpos=int(m.jnt_qposadr[root]),
        root_dof=int(m.jnt_dofadr[root]),
        joint_qpos=np.array([m.jnt_qposadr[j] for j in joints]),
        joint_dof=np.array([m.jnt_dofadr[j] for j in joints]),
        actuator=np.array([actuator_of_joint[j] for j in joints]),
        foot_force_sensor=np.array([m.sensor_adr[s] for s in sensors]),
        foot_contact_data=np.array([m.sensor_adr[s] + np.arange(9) for s in sensors]),
        calf_body=np.array([obj_id(mujoco.mjtObj.mjOBJ_BODY, f"{leg}_calf") for leg in constants.LEG_NAMES]),
        foot_geom=np.array([obj_id(mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_foot") for leg in constants.LEG_NAMES]),
    )


class Scenario(NamedTuple):
    """A batch of scenarios, one entry per instance, each an array of shape (batch,)."""

    friction: np.ndarray  # floor friction coefficient (the paper: 0.3 slippery, 0.6 normal, 0.9 coarse)
    # The feet's μ: the contact takes the smaller of floor's and feet's (Gazebo's rule, physics.contact_friction);
    # −1: the profile's own (paper: 0.6, the unitree_ros feet; soft, go1: none, the floor's μ holds).
    foot_friction: np.ndarray
    slope_deg: np.ndarray  # terrain slope, uphill along +x (gravity rotated about y, docs/decisions.md §4)
    payload_kg: np.ndarray  # mass added on the trunk (docs/decisions.md §6)
    physics: np.ndarray  # str, the physics profile (cpgjax.go1.physics.PROFILES, docs/decisions.md §15)
    mass_scale: np.ndarray  # every link's mass and inertia × this (domain randomization; 1: the URDF's)
    latency_ticks: np.ndarray  # int, actuation latency replacing the profile's (−1: the profile's own)
    noise_scale: np.ndarray  # sensor noise as a multiple of the robot's (go1 profile's); −1: the profile's own
    noise_seed: np.ndarray  # int, the instance's sensor-noise stream
    terrain: np.ndarray  # str, the ground (cpgjax.go1.terrain.TERRAINS; "flat": the plane)
    terrain_amplitude_m: np.ndarray  # rough: the heights' peak-to-peak range [m] (0 on flat)
    terrain_seed: np.ndarray  # int, the stream that draws the rough heights
    terrain_step_m: np.ndarray  # blocks: their depth [m] (0 on the other grounds)

    @property
    def batch_size(self) -> int:
        return int(self.friction.shape[0])


def make_scenarios(
    friction=0.6,
    slope_deg=0.0,
    payload_kg=0.0,
    physics=physics_profiles.DEFAULT_PROFILE,
    mass_scale=1.0,
    latency_ticks=-1,
    noise_scale=-1.0,
    noise_seed=0,
    terrain=terrains.FLAT,
    terrain_amplitude_m=0.0,
    terrain_seed=0,
    terrain_step_m=0.0,
    foot_friction=-1.0,
) -> Scenario:
    """Broadcast scalars or sequences to a batch of scenarios and validate them.

    A floor μ above the feet's, which the contact does not feel (:func:`friction_notes`), is logged as a warning
    naming the μ in effect, once per process for each profile and feet's μ.

    Raises:
      ValueError: a non-finite value, friction ≤ 0, a foot friction neither −1 nor > 0, |slope| ≥ 45°, a negative
        payload, an unknown physics profile, a mass scale outside [0.5, 1.5], a latency outside −1 …
        MAX_LATENCY_TICKS, a noise scale neither −1 nor in [0, 5], a noise seed that is not an integer in [0, 2³²), or
        a terrain, amplitude or terrain seed that ``terrain.check_terrain`` refuses; the message names the field, the
        value, the instance and the allowed range.
    """
    numbers = [np.atleast_1d(np.asarray(v, np.float64)) for v in (friction, foot_friction, slope_deg, payload_kg)]
    arrays = np.broadcast_arrays(
        *numbers,
        np.atleast_1d(np.asarray(physics, str)),
        np.atleast_1d(np.asarray(mass_scale, np.float64)),
        np.atleast_1d(np.asarray(latency_ticks, np.float64)),
        np.atleast_1d(np.asarray(noise_scale, np.float64)),
        np.atleast_1d(np.asarray(noise_seed, np.float64)),
        np.atleast_1d(np.asarray(terrain, str)),
        np.atleast_1d(np.asarray(terrain_amplitude_m, np.float64)),
        np.atleast_1d(np.asarray(terrain_seed, np.float64)),
        np.atleast_1d(np.asarray(terrain_step_m, np.float64)),
    )
    scenario = Scenario(*(np.array(a) for a in arrays))
    if scenario.friction.ndim != 1:
        raise ValueError(f"scenario fields must be scalars or 1-D sequences, got shape {scenario.friction.shape}")
    checks = (
        ("friction", scenario.friction, lambda v: v > 0.0, "(0, inf)"),
        ("foot_friction", scenario.foot_friction, lambda v: (v == -1.0) | (v > 0.0), "-1 (the profile's) or (0, inf)"),
        (
            "slope_deg",
            scenario.slope_deg,
            lambda v: np.abs(v) < MAX_ABS_SLOPE_DEG,
            f"(-{MAX_ABS_SLOPE_DEG}, {MAX_ABS_SLOPE_DEG})",
        ),
        ("payload_kg", scenario.payload_kg, lambda v: v >= 0.0, "[0, inf)"),
        ("mass_scale", scenario.mass_scale, lambda v: (v >= 0.5) & (v <= 1.5), "[0.5, 1.5]"),
        (
            "latency_ticks",
            scenario.latency_ticks,
            lambda v: (v == np.round(v)) & (v >= -1) & (v <= physics_profiles.MAX_LATENCY_TICKS),
            f"-1 (the profile's) or 0 … {physics_profiles.MAX_LATENCY_TICKS} ticks",
        ),
        (
            "noise_scale",
            scenario.noise_scale,
            lambda v: (v == -1.0) | ((v >= 0.0) & (v <= 5.0)),
            "-1 (the profile's) or [0, 5] × the go1 profile's",
        ),
        (
            "noise_seed",
            scenario.noise_seed,
            lambda v: (v == np.round(v)) & (v >= 0) & (v < 2.0**32),
            "an integer in [0, 2**32)",
        ),
    )
    for name, values, ok, allowed in checks:
        bad = ~np.isfinite(values) | ~ok(np.where(np.isfinite(values), values, 0.0))
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(
                f"scenario {name} = {float(values[i])!r} (instance {i}) is outside the allowed range {allowed}"
            )
    terrains.check_terrain(
        scenario.terrain, scenario.terrain_amplitude_m, scenario.terrain_seed, scenario.terrain_step_m
    )
    scenario = scenario._replace(
        latency_ticks=scenario.latency_ticks.astype(np.int64),
        noise_seed=scenario.noise_seed.astype(np.int64),
        terrain_seed=scenario.terrain_seed.astype(np.int64),
    )
    unknown = [i for i, name in enumerate(scenario.physics) if name not in physics_profiles.PROFILES]
    if unknown:
        i = unknown[0]
        raise ValueError(
            f"scenario physics = {str(scenario.physics[i])!r} (instance {i}) is not a profile; allowed: "
            f"{tuple(physics_profiles.PROFILES)}"
        )
    for key, line in friction_notes(scenario).items():
        _warn_once(key, line)
    return scenario


def effective_friction(scenario: Scenario) -> np.ndarray:
    """(batch,) the sliding μ each instance's feet feel on its floor (``physics.contact_friction``)."""
    return np.array(
        [
            physics_profiles.contact_friction(physics_profiles.get(str(name)), mu, foot)
            for name, mu, foot in zip(scenario.physics, scenario.friction, scenario.foot_friction, strict=True)
        ],
        np.float64,
    ).reshape(-1)


def friction_notes(scenario: Scenario) -> dict[tuple[str, float], str]:
    """(profile, feet's μ) → one line for each such pair of the batch whose floors include some above the feet's μ:
    the contact takes the smaller μ, so those floors walk as the feet's."""
    effective = effective_friction(scenario)
    capped: dict[tuple[str, float], list[float]] = {}
    for name, mu, foot, mu_in_effect in zip(
        scenario.physics, scenario.friction, scenario.foot_friction, effective, strict=True
    ):
        if mu > mu_in_effect:
            capped.setdefault((str(name), float(foot)), []).append(float(mu))
    notes = {}
    for (name, foot), floors in capped.items():
        feet = float(physics_profiles.feet_friction(physics_profiles.get(name), foot))
        whose = "the scenario's foot_friction" if foot >= 0.0 else f"the {name} profile's feet"
        asked = sorted(set(floors))
        shown = (
            ", ".join(f"{mu:g}" for mu in asked)
            if len(asked) <= 4
            else f"{len(asked)} values from {asked[0]:g} to {asked[-1]:g}"
        )
        notes[(name, feet)] = (
            f"friction above {feet:g} under physics {name} walks as {feet:g} (asked: {shown}): a contact takes the "
            f"smaller μ of floor and feet (Gazebo's rule), and the feet's is {feet:g} ({whose}); a foot friction at "
            "least the floor's (--foot-friction, scenario foot_friction) lets the floor's count"
        )
    return notes


_SAID: set[tuple[str, float]] = set()  # the (profile, feet's μ) pairs whose line this process has logged


def _warn_once(key: tuple[str, float], line: str) -> None:
    if key not in _SAID:
        _SAID.add(key)
        log.warning(line)


def gravity_vector(slope_deg) -> np.ndarray:
    """Gravity (..., 3) [m/s²] in the floor frame for a slope climbed along +x: g·(−sin s, 0, −cos s)."""
    s = np.deg2rad(np.asarray(slope_deg, np.float64))
    return constants.GRAVITY_MPS2 * np.stack([-np.sin(s), np.zeros_like(s), -np.cos(s)], axis=-1)


def slope_quaternion(slope_deg) -> np.ndarray:
    """(w, x, y, z) of the rotation from the floor frame to the frame whose z is against gravity: about y by −slope
    (the floor's x climbs at the slope angle; it turns :func:`gravity_vector` into (0, 0, −g))."""
    half = -np.deg2rad(float(slope_deg)) / 2.0
    return np.array([np.cos(half), 0.0, np.sin(half), 0.0])


def payload_inertia(payload_kg: float) -> np.ndarray:
    """Principal inertia (3,) [kg·m²] of the payload box (docs/decisions.md §6)."""
    a, b, c = PAYLOAD_BOX_M
    return payload_kg / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])


@functools.lru_cache(maxsize=512)
def model_with_payload(
    payload_kg: float, physics: str = physics_profiles.DEFAULT_PROFILE, mass_scale: float = 1.0, terrain: bool = False
) -> mujoco.MjModel:
    """A copy of the nominal model (the terrain model if ``terrain``) carrying ``payload_kg`` under the ``physics``
    profile's contact and joint fields, its links' masses and inertias × ``mass_scale``, with every derived quantity
    recomputed (``mj_setConst``: subtree masses, inverse weights, actuator_acc0, ...). Cached per (payload, profile,
    mass scale, terrain)."""
    m = (load_terrain_model() if terrain else load_model()).__copy__()
    ids = indices()
    profile = physics_profiles.get(physics)
    physics_profiles.apply_to_model(m, profile, ids.floor_geom, ids.joint_dof)
    m.opt.timestep /= profile.physics_substeps  # the control tick stays the file's 1 ms
    links = np.array([b for b in range(1, m.nbody) if b != ids.payload_body])
    m.body_mass[links] *= mass_scale
    m.body_inertia[links] *= mass_scale
    m.body_mass[ids.payload_body] = payload_kg
    m.body_inertia[ids.payload_body] = payload_inertia(payload_kg)
    mujoco.mj_setConst(m, mujoco.MjData(m))
    return m


def foot_contact_slots(nsensordata: int) -> np.ndarray:
    """The sensordata addresses of each foot's (force | normal | tangent) data in the model whose sensordata has
    ``nsensordata`` entries: (4, 9) in the flat model (one contact, ``Go1Indices.foot_contact_data``), (4,
    FOOT_CONTACT_SLOTS, 9) in the terrain model (the slots of a foot's contacts, empty ones zero)."""
    if nsensordata == load_model().nsensordata:
        return indices().foot_contact_data
    m = load_terrain_model()
    if nsensordata != m.nsensordata:
        raise ValueError(
            f"sensordata of {nsensordata} entries: the Go1 models have {load_model().nsensordata} (flat) "
            f"or {m.nsensordata} (terrain)"
        )
    sensors = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, n) for n in FOOT_SENSOR_NAMES]
    return np.array(
        [m.sensor_adr[s] + np.arange(FOOT_CONTACT_SLOTS * 9).reshape(FOOT_CONTACT_SLOTS, 9) for s in sensors]
    )


def has_terrain(scenario: Scenario) -> bool:
    """Whether a batch runs the terrain model (:func:`load_terrain_model`): some instance is not on flat ground."""
    return bool(np.any(scenario.terrain != terrains.FLAT))


def check_same_model(scenario: Scenario, other: Scenario) -> None:
    """Raise ValueError in one line where two batches run different models (the plane and the terrain model: their
    states and compiled programs differ), so a backend cannot switch from one to the other."""
    if has_terrain(scenario) != has_terrain(other):
        raise ValueError(
            "a batch cannot switch between all-flat terrain and some rough terrain (the model and its "
            "states differ): start a backend for the new scenarios"
        )


def scenario_ground(scenario: Scenario, i: int) -> terrains.Ground:
    """Instance i's ground (its four terrain fields)."""
    return terrains.Ground(
        str(scenario.terrain[i]),
        float(scenario.terrain_amplitude_m[i]),
        int(scenario.terrain_seed[i]),
        float(scenario.terrain_step_m[i]),
    )


def scenario_model(scenario: Scenario, i: int) -> mujoco.MjModel:
    """The C-MuJoCo model of instance i: profile, payload, the μ in effect on the floor (:func:`effective_friction`)
    and gravity applied (a fresh copy)."""
    terrain = has_terrain(scenario)
    m = model_with_payload(
        float(scenario.payload_kg[i]), str(scenario.physics[i]), float(scenario.mass_scale[i]), terrain
    ).__copy__()
    m.geom_friction[indices().floor_geom, 0] = physics_profiles.contact_friction(
        physics_profiles.get(str(scenario.physics[i])), scenario.friction[i], scenario.foot_friction[i]
    )
    m.opt.gravity[:] = gravity_vector(scenario.slope_deg[i])
    if terrain:
        m.hfield_data[:] = terrains.hfield_data(scenario_ground(scenario, i))
    return m


def scenario_dependent_fields() -> tuple[str, ...]:
    """Names of the model's float arrays that a payload or a physics profile changes (found by comparing models, not
    from a hand-kept list)."""
    base = model_with_payload(0.0)
    others = [model_with_payload(15.0), model_with_payload(0.0, physics_profiles.DEFAULT_PROFILE, 1.1)] + [
        model_with_payload(0.0, name) for name in physics_profiles.PROFILES
    ]
    names = []
    for name in dir(base):
        a = getattr(base, name, None)
        if (
            isinstance(a, np.ndarray)
            and a.dtype.kind == "f"
            and any(not np.array_equal(a, getattr(other, name)) for other in others)
        ):
            names.append(name)
    return tuple(names)


# Leg-frame feet (4, 3) of the standing pose: STAND_FOOT_X_M in x, under the hips in y, STAND_FOOT_Z_M below them.
_STANDING_FEET_M = np.stack(
    [
        np.full(4, STAND_FOOT_X_M),
        np.asarray(kinematics.SIDE_SIGN) * kinematics.HIP_OFFSET_M,
        np.full(4, STAND_FOOT_Z_M),
    ],
    axis=-1,
)


def standing_legs_rad(foot_x_shift_m=0.0) -> jax.Array:
    """The 12 joint angles [rad] of the standing pose, the feet shifted by ``foot_x_shift_m`` in x (the start's lean,
    ``cpg.lean_x_m``). JAX (traceable)."""
    feet = jnp.asarray(_STANDING_FEET_M, jnp.float32).at[:, 0].add(foot_x_shift_m)
    return kinematics.legs_ik(feet, jnp.asarray(kinematics.SIDE_SIGN)).reshape(12)


_legs_ik = jax.jit(kinematics.legs_ik)


@functools.cache
def _standing_legs_rad(foot_x_shift_m: float = 0.0) -> np.ndarray:
    """:func:`standing_legs_rad` as a read-only NumPy constant, computed once per process and shift."""
    feet = _STANDING_FEET_M.copy()
    feet[:, 0] += foot_x_shift_m
    with jax.ensure_compile_time_eval():  # a constant, also when first called while tracing
        q_legs = _legs_ik(feet, np.asarray(kinematics.SIDE_SIGN))
    q_legs = np.asarray(q_legs, np.float64).reshape(12)
    q_legs.flags.writeable = False
    return q_legs


def standing_imu_pitch_rad(slope_deg) -> np.ndarray:
    """The IMU pitch [rad] of the trunk standing parallel to a floor of slope ``slope_deg`` (§4: the IMU reads
    against gravity, nose-down positive): −slope, nose up uphill."""
    return -np.radians(np.asarray(slope_deg, np.float64))


def standing_qpos(model: mujoco.MjModel | None = None, foot_x_shift_m: float = 0.0) -> np.ndarray:
    """qpos of the robot standing on the floor at the origin, heading +x, feet under the hips (shifted by
    ``foot_x_shift_m`` in x: the start's lean)."""
    m = load_model() if model is None else model
    ids = indices()
    qpos = np.array(m.qpos0, np.float64)
    qpos[ids.root_qpos : ids.root_qpos + 7] = [0.0, 0.0, -STAND_FOOT_Z_M + FOOT_RADIUS_M, 1.0, 0.0, 0.0, 0.0]
    qpos[ids.joint_qpos] = _standing_legs_rad(float(foot_x_shift_m))
    return qpos
