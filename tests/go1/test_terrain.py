"""Terrain as a scenario field (cpgjax/go1/terrain.py): validation, the height field against NumPy and against C
MuJoCo's own geometry, the summed foot sensor against C MuJoCo's contact forces and m·g, the fall judged against the
ground under the trunk, the periodic wrap, and the native and MJX backends on the same rough terrain."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from cpgjax import cli, mjx_go1
from cpgjax.go1 import constants, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains
from cpgjax.sim import native as native_go1
from cpgjax.sim import walk
from cpgjax.studies import video
from cpgjax.study import scene
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space
from cpgjax.trial.condition import Condition
from tests import test_outputs
from tests.conftest import SHORT_TRIAL

ROUGH = dict(terrain="rough", terrain_amplitude_m=0.04, terrain_seed=3)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (dict(terrain="hills"), r"scenario terrain = 'hills' \(instance 0\) is not a terrain; allowed: \('flat', "),
        (
            dict(terrain="rough", terrain_amplitude_m=0.07),
            r"scenario terrain_amplitude_m = 0.07 \(instance 0\) is outside the allowed range \[0, 0.06\]",
        ),
        (
            dict(terrain="rough", terrain_amplitude_m=[0.02, -0.01]),
            r"scenario terrain_amplitude_m = -0.01 \(instance 1\) is outside the allowed range",
        ),
        (dict(terrain_amplitude_m=0.02), r"terrain_amplitude_m = 0.02 \(instance 0\) on flat terrain: allowed 0"),
        (
            dict(terrain="rough", terrain_amplitude_m=0.02, terrain_seed=1.5),
            r"scenario terrain_seed = 1.5 \(instance 0\) is outside the allowed range an integer in \[0, 2\*\*32\)",
        ),
        (
            dict(terrain="blocks", terrain_amplitude_m=0.02, terrain_step_m=0.1),
            r"scenario terrain_step_m = 0.1 \(instance 0\) is outside the allowed range \[0.15, 4.0\] "
            r"\(the blocks' depth\)",
        ),
        (
            dict(terrain="rough", terrain_amplitude_m=0.02, terrain_step_m=0.3),
            r"scenario terrain_step_m = 0.3 \(instance 0\) on rough terrain: allowed 0",
        ),
    ],
)
def test_an_impossible_terrain_is_refused_in_one_line(fields, message):
    with pytest.raises(ValueError, match=message):
        go1_model.make_scenarios(**fields)


def test_the_highest_rough_ground_is_the_smallest_swing_clearance():
    """terrain.MAX_AMPLITUDE_M, a literal in the Go1's facts, is the g_c lower bound of the parameter box."""
    assert terrains.MAX_AMPLITUDE_M == param_space.PARAM_LOWER[param_space.PARAM_NAMES.index("ground_clearance_m")]


def test_the_default_is_flat_and_runs_the_plane_model():
    scenario = go1_model.make_scenarios(friction=[0.3, 0.6])
    assert list(scenario.terrain) == ["flat", "flat"] and not go1_model.has_terrain(scenario)
    m = go1_model.scenario_model(scenario, 0)
    assert m.nhfield == 0 and m.nsensordata == go1_model.load_model().nsensordata
    assert m.geom_type[go1_model.indices().floor_geom] == mujoco.mjtGeom.mjGEOM_PLANE
    assert go1_model.has_terrain(go1_model.make_scenarios(terrain=["flat", "rough"], terrain_amplitude_m=[0, 0.02]))


def test_the_rough_heights_are_numpys_white_noise_periodic_with_a_flat_pad():
    period = terrains.period_heights_m(terrains.Ground("rough", 0.04, 3))
    u = np.random.default_rng(3).random((terrains.PERIOD_CELLS, terrains.PERIOD_CELLS))
    off_pad = period != 0.0
    np.testing.assert_array_equal(period[off_pad], 0.04 * (u[off_pad] - 0.5))
    assert period.min() >= -0.02 and period.max() <= 0.02 and np.ptp(period) > 0.039
    # The pad: every vertex within PAD_HALF_M of the origin is 0, and those are all the zeros.
    coord = np.arange(terrains.PERIOD_CELLS) * terrains.CELL_M
    near = np.minimum(coord, terrains.PERIOD_M - coord)
    pad = (near[:, None] <= terrains.PAD_HALF_M[1]) & (near[None, :] <= terrains.PAD_HALF_M[0])
    np.testing.assert_array_equal(~off_pad, pad)
    field = terrains.field_heights_m(terrains.Ground("rough", 0.04, 3))
    n = terrains.PERIOD_CELLS
    np.testing.assert_array_equal(field[:-n, :], field[n:, :])
    np.testing.assert_array_equal(field[:, :-n], field[:, n:])
    centre = terrains.FIELD_VERTICES // 2  # the vertex at the origin
    assert field[centre, centre] == 0.0 and field[centre, centre + 10] == period[0, 10]
    assert not np.array_equal(period, terrains.period_heights_m(terrains.Ground("rough", 0.04, 4)))


def test_the_blocks_are_numpys_heights_one_per_block_with_a_flat_pad():
    """Blocks of 0.3 m (4 cells): every vertex off the pad has its block's height, the blocks' heights being
    0.05 · (default_rng(5).random((32, 32)) − 0.5) in block order; the pad is flat; the field repeats by a period."""
    ground = terrains.Ground("blocks", 0.05, 5, 0.3)
    period = terrains.period_heights_m(ground)
    coord = np.arange(terrains.PERIOD_CELLS) * terrains.CELL_M
    block = (coord / 0.3 + 1e-9).astype(int)  # 9.6 m = 32 blocks of 0.3 m
    tops = 0.05 * (np.random.default_rng(5).random((32, 32)) - 0.5)
    near = np.minimum(coord, terrains.PERIOD_M - coord)
    pad = (near[:, None] <= terrains.PAD_HALF_M[1]) & (near[None, :] <= terrains.PAD_HALF_M[0])
    np.testing.assert_array_equal(period[~pad], tops[np.ix_(block, block)][~pad])
    assert np.all(period[pad] == 0.0)
    assert np.all(period[:4, 8:12] == period[0, 8])  # one block (x 0.6–0.9 m, y 0–0.3 m): a flat top
    field = terrains.field_heights_m(ground)
    n = terrains.PERIOD_CELLS
    np.testing.assert_array_equal(field[:-n, :], field[n:, :])


def test_a_slope_combines_with_rough_ground():
    """Rough ground on a 10° incline: the instance's model has the height field and the slope's gravity, and a short
    native trial of it walks (no failure)."""
    scenario = go1_model.make_scenarios(
        slope_deg=[10.0, 0.0], terrain="rough", terrain_amplitude_m=0.02, terrain_seed=3
    )
    m = go1_model.scenario_model(scenario, 0)
    assert m.nhfield == 1 and m.geom_type[go1_model.indices().floor_geom] == mujoco.mjtGeom.mjGEOM_HFIELD
    np.testing.assert_allclose(m.opt.gravity, go1_model.gravity_vector(10.0))
    sim = native_go1.NativeBackend(scenario, trial_config=SHORT_TRIAL)
    params = np.tile(param_space.midpoint(), (2, 1))
    _, record = sim.trial(sim.reset(params), params, protocol.batch_gates(["vmc_tegotae"] * 2))
    assert not np.asarray(record.failed).any()
    assert float(record.c_slope_rad[0]) < float(record.c_slope_rad[1]) - 0.05  # the incline is read (uphill: < 0)


def test_the_ground_height_is_where_c_mujoco_finds_the_height_field():
    """terrain.ground_height_m against a vertical ray cast onto the model's hfield geom by C MuJoCo (mj_ray), at
    random points over the whole field, on both sides of the cells' diagonals."""
    scenario = go1_model.make_scenarios(**ROUGH)
    m = go1_model.scenario_model(scenario, 0)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    floor = go1_model.indices().floor_geom
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.99 * terrains.FIELD_HALF_M, 0.99 * terrains.FIELD_HALF_M, (200, 2))
    reference = []
    for x, y in points:
        geomid = np.zeros(1, np.int32)
        distance = mujoco.mj_ray(m, d, np.array([x, y, 1.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geomid)
        assert geomid[0] == floor
        reference.append(1.0 - distance)
    heights = jax.vmap(terrains.ground_height_m, in_axes=(None, 0, 0))(
        jnp.asarray(m.hfield_data, jnp.float32), points[:, 0], points[:, 1]
    )
    np.testing.assert_allclose(np.asarray(heights), reference, atol=2e-5)  # float32 of a 28.8 m grid
    assert np.ptp(reference) > 0.03


def test_the_field_repeats_by_a_period_so_the_wrap_keeps_the_ground():
    data = jnp.asarray(terrains.hfield_data(terrains.Ground("rough", 0.04, 3)), jnp.float32)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-4.8, 4.8, 100), rng.uniform(-4.8, 4.8, 100)
    here = jax.vmap(terrains.ground_height_m, in_axes=(None, 0, 0))(data, x, y)
    for dx, dy in ((terrains.PERIOD_M, 0.0), (-terrains.PERIOD_M, terrains.PERIOD_M)):
        there = jax.vmap(terrains.ground_height_m, in_axes=(None, 0, 0))(data, x + dx, y + dy)
        np.testing.assert_allclose(np.asarray(there), np.asarray(here), atol=2e-5)
    wrapped = terrains.wrap_xy_m(np.array([[5.0, -0.2], [-14.0, 9.7], [1.0, 2.0]]))
    np.testing.assert_allclose(wrapped, [[5.0 - 9.6, -0.2], [-14.0 + 9.6, 9.7 - 9.6], [1.0, 2.0]], atol=1e-12)


def _stand_on_rough_ground(m, x_m, steps=3000):
    """The Go1 held in its standing pose by joint PD (C MuJoCo) at (x, 0) on the rough field, let down from above
    the highest bump and settled for ``steps`` ms."""
    ids = go1_model.indices()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    d.qpos[ids.root_qpos] = x_m
    d.qpos[ids.root_qpos + 2] += terrains.MAX_AMPLITUDE_M / 2
    q_stand = d.qpos[ids.joint_qpos].copy()
    for _ in range(steps):
        d.ctrl[ids.actuator] = 60.0 * (q_stand - d.qpos[ids.joint_qpos]) - 2.0 * d.qvel[ids.joint_dof]
        mujoco.mj_step(m, d)
    return d


def _foot_contact_normals(m, d) -> np.ndarray:
    """Each foot's contacts' normal forces summed (4,) by C MuJoCo's mj_contactForce, and their count (4,)."""
    ids = go1_model.indices()
    total, count, force = np.zeros(4), np.zeros(4, int), np.zeros(6)
    for c in range(d.ncon):
        for leg, geom in enumerate(ids.foot_geom):
            if geom in d.contact[c].geom:
                mujoco.mj_contactForce(m, d, c, force)
                total[leg] += force[0]
                count[leg] += 1
    return total, count


def test_the_summed_foot_sensor_reads_every_contact_and_the_weight():
    """The Go1 standing still on rough ground, feet on several of the field's prisms: each foot's reading (the
    shared sensor model, ``sensors.observe``) is the sum of its contacts' normal forces by C MuJoCo's
    mj_contactForce, its deepest contact alone reads less, and the four feet's floor-frame forces carry m·g."""
    m = go1_model.scenario_model(go1_model.make_scenarios(**ROUGH), 0)
    d = _stand_on_rough_ground(m, x_m=1.0)
    assert np.abs(d.qvel).max() < 0.01  # nearly at rest (the soft contact creeps: 6 mm/s)
    reference, count = _foot_contact_normals(m, d)
    assert count.max() >= 2 and count.max() <= go1_model.FOOT_CONTACT_SLOTS
    obs = sensors.observe(d.qpos, d.qvel, d.sensordata, m.opt.gravity)
    np.testing.assert_allclose(np.asarray(obs.foot_force_n), reference, rtol=1e-6)
    deepest = d.sensordata[go1_model.foot_contact_slots(m.nsensordata)][:, 0, 0]
    assert np.all(deepest[count >= 2] < reference[count >= 2] - 0.5)
    world = physics_profiles.contact_force_world(d.sensordata[go1_model.foot_contact_slots(m.nsensordata)])
    weight_n = m.body_subtreemass[go1_model.indices().trunk_body] * constants.GRAVITY_MPS2
    assert float(np.sum(world[..., 2])) == pytest.approx(weight_n, rel=1e-3)


def test_mjx_sums_the_same_contacts_of_the_same_state():
    """MJX's summed reading of the state C MuJoCo settled into (one mjx.forward: its own collision and solver)
    against C MuJoCo's: MJX makes at most 4 contacts per foot–field pair, C one per prism, so the split differs and
    only the totals compare: each foot within 10 % + 1 N, the four feet's vertical forces m·g within 2 %."""
    m = go1_model.scenario_model(go1_model.make_scenarios(**ROUGH), 0)
    d = _stand_on_rough_ground(m, x_m=1.0)
    reference, _ = _foot_contact_normals(m, d)
    mx = mjx_go1.mjx.put_model(m)
    dx = jax.jit(mjx_go1.mjx.forward)(
        mx,
        mjx_go1.mjx.make_data(mx).replace(
            qpos=jnp.asarray(d.qpos, jnp.float32),
            qvel=jnp.asarray(d.qvel, jnp.float32),
            qacc_warmstart=jnp.asarray(d.qacc_warmstart, jnp.float32),
            ctrl=jnp.asarray(d.ctrl, jnp.float32),
        ),
    )
    obs = sensors.observe(dx.qpos, dx.qvel, dx.sensordata, mx.opt.gravity)
    np.testing.assert_allclose(np.asarray(obs.foot_force_n), reference, rtol=0.1, atol=1.0)
    world = physics_profiles.contact_force_world(np.asarray(dx.sensordata)[go1_model.foot_contact_slots(m.nsensordata)])
    weight_n = m.body_subtreemass[go1_model.indices().trunk_body] * constants.GRAVITY_MPS2
    assert float(np.sum(world[..., 2])) == pytest.approx(weight_n, rel=0.02)


def test_a_fall_is_judged_against_the_ground_under_the_trunk():
    config = protocol.TrialConfig()
    pre = protocol.PreStep(*(jnp.float32(0.0) for _ in protocol.PreStep._fields))
    qpos = jnp.asarray(go1_model.standing_qpos(), jnp.float32).at[go1_model.indices().root_qpos + 2].set(0.15)
    qvel, ok = jnp.zeros(18), jnp.bool_(False)
    assert float(protocol.tick_row(config, pre, qpos, qvel, ok).fell) == 0.0  # 0.15 m above the plane
    assert float(protocol.tick_row(config, pre, qpos, qvel, ok, jnp.float32(0.02)).fell) == 0.0
    assert float(protocol.tick_row(config, pre, qpos, qvel, ok, jnp.float32(0.04)).fell) == 1.0  # 0.11 m above


@pytest.fixture(scope="module")
def rough_pair():
    """Both backends on one batch: rough 4 cm (seed 3), rough 2 cm (seed 4), flat ground in the terrain model, and
    blocks of 0.3 m, 3 cm peak-to-peak (seed 5); under soft, as the flat comparison of the backends (its foot force
    the contact normal at 1 kHz, which carries m g / 4 standing)."""
    scenario = go1_model.make_scenarios(
        terrain=["rough", "rough", "flat", "blocks"],
        terrain_amplitude_m=[0.04, 0.02, 0.0, 0.03],
        terrain_seed=[3, 4, 0, 5],
        terrain_step_m=[0.0, 0.0, 0.0, 0.3],
        physics="soft",
    )
    return (
        native_go1.NativeBackend(scenario, trial_config=SHORT_TRIAL),
        mjx_go1.MJXBackend(scenario, trial_config=SHORT_TRIAL),
    )


def test_both_backends_walk_off_the_pad_onto_the_field(rough_pair):
    """300 ticks (0.3 s) of closed-loop walking from standing at x = 1 m, off the pad, feet on the field: in both
    engines every instance stays upright (trunk above 0.25 m, no fall) and its feet carry its weight on the field
    (the feet's mean summed normal force over the 0.3 s within 20 % of m·g / 4). The trajectories themselves are not
    compared tick by tick: on a height field each engine makes its own contact set (MJX at most 4 contacts per
    foot–field pair from its manifold, C MuJoCo one per prism it touches, each a soft constraint of its own), and
    the trunks part by millimetres within 0.3 s even on flat heights (measured: 1.9 mm on flat heights, 8.5 mm on
    4 cm, docs/backends.md); the trials are compared by their figures (the next test)."""
    params = np.tile(param_space.midpoint(), (4, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * 4)
    native, mjx = rough_pair
    r = go1_model.indices().root_qpos
    state = native.reset(params)
    state.physics[:, native.physics.layout.qpos.start + r] = 1.0
    _, native_log = native.rollout(state, params, gates, 300)
    state = mjx.reset(params)
    _, mjx_log = mjx.rollout(
        state._replace(data=state.data.replace(qpos=state.data.qpos.at[:, r].set(1.0))), params, gates, 300
    )
    for log in (native_log, mjx_log):
        assert np.all(np.asarray(log.qpos)[:, :, r + 2] > 0.25)
        load_n = np.asarray(log.foot_force_n).mean(axis=(1, 2))
        np.testing.assert_allclose(load_n, 13.10 * constants.GRAVITY_MPS2 / 4, rtol=0.2)


def test_native_and_mjx_trial_figures_agree_on_rough_terrain(rough_pair):
    """Two back-to-back short trials (1.6 s each; the robot leaves the pad after ~0.5 s; 8 pairs) with the mid-box
    parameters: 6 paired trials. On rough ground the two engines' contact sets differ (MJX makes at most 4 contacts
    per foot–field pair, C MuJoCo one per prism), so trajectories part after some hundred ms, as the flat
    comparison's gaits on the edge of falling do; the criterion is that comparison's statistical one
    (tests/sim/test_native.py::test_trial_figures_agree_statistically_over_random_parameters): the same fall
    outcome in ≥ 2/3 of the pairs, ≥ 60 % of the pairs within 0.02 m/s, 5 % CoT, 2 % c_load, 0.01 rad c_slope, and
    the medians over the walked pairs within those. The flat instance in the terrain model reads the plane's
    load."""
    params = np.tile(param_space.midpoint(), (4, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * 4)
    figures = []
    for sim in rough_pair:
        state = sim.reset(params)
        records = []
        for _ in range(2):
            state, record = sim.trial(state, params, gates)
            records.append(record)
        figures.append(
            {
                "v_x": np.concatenate([np.asarray(objective.mean_velocity(r))[:, 0] for r in records]),
                "cot": np.concatenate([np.asarray(objective.cost_of_transport(r)) for r in records]),
                "c_load": np.concatenate([np.asarray(r.c_load_n) for r in records]),
                "c_slope": np.concatenate([np.asarray(r.c_slope_rad) for r in records]),
                "fell": np.concatenate([np.asarray(r.fell) for r in records]),
            }
        )
    n, m = figures
    differences = {
        "v_x": np.abs(n["v_x"] - m["v_x"]),
        "cot": np.abs(n["cot"] - m["cot"]) / m["cot"],
        "c_load": np.abs(n["c_load"] - m["c_load"]) / m["c_load"],
        "c_slope": np.abs(n["c_slope"] - m["c_slope"]),
    }
    tight = {"v_x": 0.02, "cot": 0.05, "c_load": 0.02, "c_slope": 0.01}
    same_outcome = n["fell"] == m["fell"]
    agree = same_outcome & np.all([differences[k] <= tight[k] for k in tight], axis=0)
    assert same_outcome.mean() >= 2 / 3
    assert agree.mean() >= 0.6
    walked = (n["fell"] == 0) & (m["fell"] == 0)
    for key, tolerance in tight.items():
        assert np.median(differences[key][walked]) <= tolerance, key
    assert n["c_load"][2] == pytest.approx(13.10 * constants.GRAVITY_MPS2 / 4, rel=0.02)


def test_a_trial_that_ends_beyond_the_central_period_is_moved_back(rough_pair):
    """The end state of a trial started at x = 4.7 m (0.1 m inside the central period's edge, 4.8 m) is one period
    back in both backends: the robot walks 0.3–1 m in the 1.6 s trial, so it ends within 1 m past −4.8 m; no fall."""
    params = np.tile(param_space.midpoint(), (4, 1))
    gates = protocol.batch_gates(["vmc_tegotae"] * 4)
    r = go1_model.indices().root_qpos
    native, mjx = rough_pair
    state = native.reset(params)
    x_at = native.physics.layout.qpos.start + r
    state.physics[:, x_at] = 4.7
    state, record = native.trial(state, params, gates)
    x = state.physics[:, x_at]
    assert np.all((x > -4.8) & (x < -3.8)) and not np.asarray(record.fell).any()
    state = mjx.reset(params)
    state = state._replace(data=state.data.replace(qpos=state.data.qpos.at[:, r].set(4.7)))
    state, record = mjx.trial(state, params, gates)
    x = np.asarray(state.data.qpos[:, r])
    assert np.all((x > -4.8) & (x < -3.8)) and not np.asarray(record.fell).any()


def test_walk_takes_the_terrain_from_the_command_line(monkeypatch, capsys):
    walks = []

    def fake_walk(**kwargs):
        walks.append(kwargs)
        raise SystemExit(0)  # stop before the table: only what walk was asked for matters here

    monkeypatch.setattr(walk, "walk_trials", fake_walk)
    with pytest.raises(SystemExit):
        cli.main(["walk", "--terrain", "rough", "--terrain-amplitude", "0.04", "--terrain-seed", "3"])
    assert walks[-1]["ground"] == terrains.Ground("rough", 0.04, 3)
    with pytest.raises(SystemExit):
        cli.main(["walk"])
    assert walks[-1]["ground"] == terrains.Ground("flat", 0.0, 0)
    with pytest.raises(SystemExit):
        cli.main(["walk", "--terrain", "blocks", "--terrain-amplitude", "0.05", "--terrain-step", "0.3"])
    assert walks[-1]["ground"] == terrains.Ground("blocks", 0.05, 0, 0.3)
    assert cli.main(["walk", "--terrain", "blocks", "--terrain-amplitude", "0.05"]) == 2
    assert "--terrain blocks needs --terrain-step (the blocks' depth [m] in [0.15, 4])" in capsys.readouterr().err
    assert cli.main(["walk", "--terrain", "rough", "--terrain-amplitude", "0.05", "--terrain-step", "0.3"]) == 2
    assert "--terrain-step applies to --terrain blocks only" in capsys.readouterr().err
    assert cli.main(["walk", "--terrain-amplitude", "0.04"]) == 2
    assert "cpgjax walk: --terrain-amplitude applies to --terrain rough or blocks only" in capsys.readouterr().err
    assert cli.main(["walk", "--terrain", "rough"]) == 2
    assert "--terrain rough needs --terrain-amplitude (peak-to-peak [m] in (0, 0.06])" in capsys.readouterr().err
    for argv, message in (
        (["--terrain-amplitude", "0.07"], "0.07 is outside the allowed range (0, 0.06]"),
        (["--terrain", "hills"], "invalid choice: 'hills'"),
        (["--terrain-seed", "-1"], "-1 is outside the allowed range 0 … 4294967295"),
    ):
        with pytest.raises(SystemExit) as exit_:
            cli.main(["walk", *argv])
        assert exit_.value.code == 2 and message in capsys.readouterr().err
    assert len(walks) == 3  # nothing refused reached the walk


def test_walk_parquet_names_the_terrain():
    record = protocol.TrialRecord(*(np.zeros(()) for _ in protocol.TrialRecord._fields))
    trial = walk.WalkTrial(
        walk=0,
        trial=0,
        controller="vmc",
        physics="soft",
        condition=Condition(ground=terrains.Ground("rough", 0.04, 3)),
        friction_in_effect=0.6,
        params=param_space.midpoint(),
        record=record,
        objective=0.0,
        velocity_xy_mps=np.zeros(2),
        cot=0.0,
    )
    cols = walk.trial_columns([trial])
    assert (cols["terrain"][0], cols["terrain_amplitude_m"][0], cols["terrain_seed"][0]) == ("rough", 0.04, 3)
    assert not test_outputs.undocumented("walk.parquet", cols)


def test_a_video_draws_the_terrain(tmp_path):
    """The same standing robot off the pad, filmed on flat ground and twice on the same rough ground: the rough
    frames differ from the flat ones (the height field is drawn, shaded by its slopes: the ground's brightness
    varies more) and equal each other (the same seed, the same ground)."""
    stand = go1_model.standing_qpos(go1_model.load_visual_model())
    stand[go1_model.indices().root_qpos] = 1.5
    qpos = np.tile(stand, (40, 1))
    rough = terrains.Ground("rough", 0.04, 3)
    jobs = [
        video.Job(path=tmp_path / "flat.mp4", qpos=qpos),
        video.Job(path=tmp_path / "rough.mp4", qpos=qpos, condition=Condition(ground=rough)),
        video.Job(path=tmp_path / "again.mp4", qpos=qpos, condition=Condition(ground=rough)),
    ]
    try:
        flat, bumpy, again = (
            info["strip"][0].astype(float) for info in video.render_videos(jobs, width=320, height=240)
        )
    except video.RenderUnavailable as err:
        pytest.skip(f"no OpenGL backend: {err}")
    np.testing.assert_array_equal(bumpy, again)
    ground = slice(160, 240)  # the lower third of the picture: the ground in front of the camera
    assert np.abs(bumpy - flat)[ground].mean() > 5
    assert bumpy[ground].std() > flat[ground].std()


def test_a_recording_draws_the_field_under_the_path(tmp_path):
    """A rollout recorded on rough ground: its floor is a mesh whose vertices lie on the ground
    (``terrain.ground_height_m`` of the model's heights) and which covers the trunk's path with the slab's margin."""
    ids = go1_model.indices()
    ticks = 50
    qpos = np.tile(go1_model.standing_qpos(), (ticks, 1))
    qpos[:, ids.root_qpos] = np.linspace(1.0, 1.4, ticks)
    zeros = {name: np.zeros((ticks, 4)) for name in ("foot_force_n", "amplitude", "phase_rad")}
    log = protocol.StepLog(
        qpos=qpos,
        qvel=np.zeros((ticks, 18)),
        torque_nm=np.zeros((ticks, 12)),
        foot_pos_m=np.zeros((ticks, 4, 3)),
        foot_target_m=np.zeros((ticks, 4, 3)),
        rpy_rad=np.zeros((ticks, 3)),
        **zeros,
    )
    ground = terrains.Ground("rough", 0.04, 3)
    path = tmp_path / "rough.rrd"
    rec = rr.RecordingStream("test_terrain")
    rec.save(str(path))
    base = scene.log_rollout(
        rec, scene.Rollout(log=log, group="rough", controller="vmc", seed=0, condition=Condition(ground=ground))
    )
    rec.flush()
    rec.disconnect()
    vertices = [
        row
        for chunk in RrdReader(path).stream()
        if chunk.entity_path == f"/{base}/world/floor"
        for batch in [chunk.to_record_batch()]
        if "Mesh3D:vertex_positions" in batch.schema.names
        for row in batch.column("Mesh3D:vertex_positions").to_pylist()
    ]
    points = np.array(vertices[0], float)
    data = jnp.asarray(
        go1_model.scenario_model(go1_model.make_scenarios(**ground._asdict()), 0).hfield_data, jnp.float32
    )
    heights = jax.vmap(terrains.ground_height_m, in_axes=(None, 0, 0))(data, points[:, 0], points[:, 1])
    np.testing.assert_allclose(points[:, 2], np.asarray(heights), atol=2e-5)
    assert points[:, 0].min() <= 1.0 - scene.FLOOR_MARGIN_M and points[:, 0].max() >= 1.4 + scene.FLOOR_MARGIN_M
    assert points[:, 1].min() <= -scene.FLOOR_MARGIN_M and points[:, 1].max() >= scene.FLOOR_MARGIN_M
    assert np.ptp(points[:, 2]) > 0.03
