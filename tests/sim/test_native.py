"""The native (C MuJoCo) backend against the MJX backend, its failure handling, and backend selection.

MJX and C MuJoCo are independent implementations of the same physics (MJX in float32 JAX, C MuJoCo in float64, with
their own constraint solvers and collision code), so agreement is checked within tolerances stated per test; the
reasons are in docs/backends.md. The MJX side reuses the session simulator of ``conftest`` (compiled once).
"""

import argparse

import jax
import mujoco
import numpy as np
import pytest

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.sim import backends, native_physics
from cpgjax.sim import native as native_go1
from cpgjax.trial import objective, protocol
from cpgjax.trial import params as param_space
from tests import native_oracle
from tests.conftest import SHORT_TRIAL

NOMINAL, HEAVY, UPHILL, SLIPPERY, COARSE = 0, 1, 2, 3, 4
# Instances whose gait is well conditioned with the mid-box parameters (no slipping, no marginal balance): here the
# two engines stay together for whole trials. The heavy and slippery instances walk on the edge of falling, where
# tiny differences grow (chaotic contact sequences), so they are compared statistically only.
STEADY = [NOMINAL, UPHILL, COARSE, 5]


@pytest.fixture(scope="module")
def native_two_trials(native_sim, mid_params, vmc_tegotae_gates):
    state = native_sim.reset(mid_params)
    state, _ = native_sim.trial(state, mid_params, vmc_tegotae_gates)
    return native_sim.trial(state, mid_params, vmc_tegotae_gates)


def _figures(record) -> dict[str, np.ndarray]:
    return {
        "v_x": np.asarray(objective.mean_velocity(record))[..., 0],
        "cot": np.asarray(objective.cost_of_transport(record)),
        "c_load": np.asarray(record.c_load_n),
        "c_slope": np.asarray(record.c_slope_rad),
        "fell": np.asarray(record.fell),
        "margin": np.asarray(record.safety_margin),
    }


@pytest.mark.parametrize("stepping", [*native_physics.STEPPINGS, native_oracle.STEPPING])
def test_batched_steps_equal_a_persistent_mj_step_loop(stepping):
    """BatchPhysics (the FFI step or ``mujoco.batch`` in place) and the tests' reference (one ``mujoco.rollout`` call
    per step, ``tests.native_oracle``), warm start rebuilt from the states, against a plain ``mj_step`` loop on one
    persistent MjData, with the same PD torques: equal to float64 rounding (the loop warm-starts with MuJoCo's own
    acceleration, which differs in the last bits)."""
    scenario = go1_model.make_scenarios(friction=[0.6, 0.3], slope_deg=[0.0, 5.0], payload_kg=[0.0, 7.5])
    batch = native_oracle.batch_physics(scenario, stepping)
    assert batch.stepping == stepping
    ids = go1_model.indices()
    lay = batch.layout
    reference = [mujoco.MjData(batch.models[i]) for i in range(2)]
    for i, d in enumerate(reference):
        d.qpos[:] = go1_model.standing_qpos()
        mujoco.mj_forward(batch.models[i], d)
    q_stand = go1_model.standing_qpos()[ids.joint_qpos]
    for k in range(300):
        q, dq = batch.physics[:, lay.qpos][:, ids.joint_qpos], batch.physics[:, lay.qvel][:, ids.joint_dof]
        # float32, as the controller's torques (the ffi stepping takes float32)
        torque = (70.0 * (q_stand + 0.2 * np.sin(0.02 * k) - q) - 1.3 * dq).astype(np.float32)
        assert not batch.step(torque).any()
        for i, d in enumerate(reference):
            d.ctrl[ids.actuator] = torque[i]
            mujoco.mj_step(batch.models[i], d)
    for i, d in enumerate(reference):
        np.testing.assert_allclose(batch.physics[i, lay.qpos], d.qpos, atol=1e-9)
        np.testing.assert_allclose(batch.physics[i, lay.qvel], d.qvel, atol=1e-7)
        np.testing.assert_allclose(batch.warmstart[i], d.qacc_warmstart, atol=1e-4)
        np.testing.assert_allclose(batch.sensordata[i], d.sensordata, atol=1e-6)
    batch.close()


def test_trajectories_agree_with_mjx_over_a_short_horizon(short_sim, native_sim, mid_params, vmc_tegotae_gates):
    """Same scenario, parameters and initial state, 300 ticks (0.3 s) of closed-loop walking in both engines.

    Tolerance: 1 mm trunk position and 0.01 rad joint angles for the well-conditioned instances; the slipping and
    heavy instances within 2 mm / 0.03 rad over 0.2 s. Measured: ≤ 0.4 mm and ≤ 0.008 rad for the steady ones
    (most agree to float32 rounding; the uphill instance drifts the most).
    """
    steps = 300
    _, mjx_log = short_sim.rollout(short_sim.reset(mid_params), mid_params, vmc_tegotae_gates, steps)
    _, native_log = native_sim.rollout(native_sim.reset(mid_params), mid_params, vmc_tegotae_gates, steps)
    for field in protocol.StepLog._fields:
        assert np.shape(getattr(native_log, field)) == np.shape(getattr(mjx_log, field)), field
    ids = go1_model.indices()
    mq, nq = np.asarray(mjx_log.qpos), np.asarray(native_log.qpos)
    np.testing.assert_allclose(nq[STEADY, :, :3], mq[STEADY, :, :3], atol=1e-3)
    np.testing.assert_allclose(nq[STEADY][..., ids.joint_qpos], mq[STEADY][..., ids.joint_qpos], atol=1e-2)
    np.testing.assert_allclose(nq[:, :200, :3], mq[:, :200, :3], atol=2e-3)
    np.testing.assert_allclose(nq[:, :200][..., ids.joint_qpos], mq[:, :200][..., ids.joint_qpos], atol=3e-2)
    # Feet (kinematics of qpos here, geom_xpos in MJX): 5 mm, i.e. the 0.01 rad joint tolerance over a 0.43 m leg.
    np.testing.assert_allclose(
        np.asarray(native_log.foot_pos_m)[STEADY], np.asarray(mjx_log.foot_pos_m)[STEADY], atol=5e-3
    )
    phase_error = np.angle(np.exp(1j * (np.asarray(native_log.phase_rad) - np.asarray(mjx_log.phase_rad))))
    assert np.abs(phase_error[STEADY]).max() < 0.05


def test_trial_records_have_the_mjx_definitions(native_two_trials, two_trials):
    _, native = native_two_trials
    _, mjx = two_trials
    for a, b, name in zip(native, mjx, protocol.TrialRecord._fields, strict=True):
        assert np.shape(a) == np.shape(b) and np.asarray(a).dtype == np.asarray(b).dtype, name
    n, m = _figures(native), _figures(mjx)
    # Tolerance on the well-conditioned instances: 0.02 m/s, 5 % CoT, 2 % c_load, 0.01 rad c_slope.
    np.testing.assert_allclose(n["v_x"][STEADY], m["v_x"][STEADY], atol=0.02)
    np.testing.assert_allclose(n["cot"][STEADY], m["cot"][STEADY], rtol=0.05)
    np.testing.assert_allclose(n["c_load"][STEADY], m["c_load"][STEADY], rtol=0.02)
    np.testing.assert_allclose(n["c_slope"][STEADY], m["c_slope"][STEADY], atol=0.01)
    np.testing.assert_array_equal(n["fell"], m["fell"])
    # The worst moment of a trial, 0.03 of the margin: 5 mm of trunk height over the 0.18 m clearance, 0.02 rad.
    np.testing.assert_allclose(n["margin"][STEADY], m["margin"][STEADY], atol=0.03)


def test_trial_figures_agree_statistically_over_random_parameters(short_sim, native_sim, vmc_tegotae_gates):
    """3 back-to-back trials × 6 scenarios with random parameters: 18 paired trials of 1.6 s.

    Most pairs agree tightly (|Δv_x| ≤ 0.02 m/s, CoT 5 %, c_load 2 %, c_slope 0.01 rad). Gaits on the edge of
    falling (here the heavy and the slippery scenario) follow different contact sequences in the two engines after a
    few hundred ms, so their figures differ trial by trial without a common sign. Tolerance: the fall outcome is the
    same in ≥ 2/3 of the pairs, ≥ 60 % of the pairs agree tightly, and over the pairs where neither robot fell the
    median differences are within the tight tolerances. Measured: 15/18 same outcome, 12/18 tight.
    """
    rng = np.random.default_rng(7)
    mjx_state = short_sim.reset(np.tile(param_space.midpoint(), (short_sim.batch_size, 1)))
    native_state = native_sim.reset(np.tile(param_space.midpoint(), (native_sim.batch_size, 1)))
    native, mjx = [], []
    for _ in range(3):
        unit = 0.25 + 0.5 * rng.random((short_sim.batch_size, param_space.NUM_PARAMS))  # inner half of the box
        params = param_space.from_unit(unit)
        mjx_state, mjx_record = short_sim.trial(mjx_state, params, vmc_tegotae_gates)
        native_state, native_record = native_sim.trial(native_state, params, vmc_tegotae_gates)
        mjx.append(_figures(mjx_record))
        native.append(_figures(native_record))
    n = {k: np.concatenate([f[k] for f in native]) for k in native[0]}
    m = {k: np.concatenate([f[k] for f in mjx]) for k in mjx[0]}
    differences = {
        "v_x": np.abs(n["v_x"] - m["v_x"]),
        "cot": np.abs(n["cot"] - m["cot"]) / np.maximum(m["cot"], 1e-3),
        "c_load": np.abs(n["c_load"] - m["c_load"]) / np.maximum(m["c_load"], 1.0),  # 0 N after a fall
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


def test_scenarios_have_their_physical_effect(native_two_trials):
    _, record = native_two_trials
    load, slope = np.asarray(record.c_load_n), np.asarray(record.c_slope_rad)
    assert load[NOMINAL] == pytest.approx(13.10 * 9.81 / 4, rel=0.1)
    assert load[HEAVY] == pytest.approx(28.10 * 9.81 / 4, rel=0.1)
    assert slope[UPHILL] < slope[NOMINAL] - 0.05  # nose-up on the 10° slope
    np.testing.assert_allclose(np.asarray(record.total_mass_kg)[[NOMINAL, HEAVY]], [13.10, 28.10], atol=0.01)
    v = np.asarray(objective.mean_velocity(record))
    assert 0.3 < v[NOMINAL, 0] < 0.8 and abs(v[NOMINAL, 1]) < 0.1


def test_backend_selection():
    assert jax.default_backend() == "cpu"  # the test suite runs on the CPU (Makefile: JAX_PLATFORMS=cpu)
    assert backends.default_backend() == "native"
    assert backends.resolve_backend("auto") == "native" and backends.resolve_backend("mjx") == "mjx"
    with pytest.raises(ValueError, match="unknown backend 'warp'"):
        backends.resolve_backend("warp")
    scenario = go1_model.make_scenarios(friction=[0.6, 0.9])
    sim = backends.make_backend(scenario, trial_config=SHORT_TRIAL)
    assert isinstance(sim, native_go1.NativeBackend) and sim.name == "native" and sim.batch_size == 2
    assert sim.trial_config == SHORT_TRIAL and sim.cpg_config == cpg.CPGConfig()
    parser = argparse.ArgumentParser()
    backends.add_backend_argument(parser)
    assert parser.parse_args([]).backend == "auto" and parser.parse_args(["--backend", "mjx"]).backend == "mjx"


def test_a_new_scenario_reuses_the_compiled_tick():
    config = protocol.TrialConfig(transition_steps=20, steady_steps=50)
    sim = native_go1.NativeBackend(go1_model.make_scenarios(friction=[0.6, 0.6]), trial_config=config)
    params = np.tile(param_space.midpoint(), (2, 1))
    gates = protocol.batch_gates(["open_loop", "vmc"])
    sim.trial(sim.reset(params), params, gates)
    heavier = sim.with_scenario(go1_model.make_scenarios(friction=[0.3, 0.9], payload_kg=[0.0, 15.0]))
    assert heavier._compiled is sim._compiled
    _, record = heavier.trial(heavier.reset(params), params, gates)
    np.testing.assert_allclose(np.asarray(record.total_mass_kg), [13.10, 28.10], atol=0.01)
    assert heavier.physics.models[0].geom_friction[go1_model.indices().floor_geom, 0] == 0.3
