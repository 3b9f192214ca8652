"""The CPG controller against independent NumPy references of the paper's equations and against kinematic identities."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import cpg
from cpgjax.go1 import attitude, constants, kinematics, sensors
from cpgjax.trial import params as param_space
from tests import numpy_reference as ref

RNG = np.random.default_rng(0)


def random_params(n, rng=RNG):
    return param_space.from_unit(rng.uniform(size=(n, param_space.NUM_PARAMS)))


def observation(force_n=(0.0, 0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), q=None):
    q = np.tile([0.0, 0.85, -1.57], 4) if q is None else q
    return sensors.Observation(
        joint_pos_rad=jnp.asarray(q, jnp.float32),
        joint_vel_rad_s=jnp.zeros(12),
        imu_quat_wxyz=jnp.asarray(quat, jnp.float32),
        gyro_rad_s=jnp.zeros(3),
        foot_force_n=jnp.asarray(force_n, jnp.float32),
    )


@pytest.mark.parametrize("form", ["paper", "sqrt"])
def test_oscillator_derivatives_match_numpy(form):
    config = cpg.CPGConfig(amplitude_form=form)
    for p in random_params(20):
        r = RNG.uniform(0.1, 2.0, 4)
        theta = RNG.uniform(0, 2 * np.pi, 4)
        force = RNG.uniform(0, 80, 4)
        dr, dth = cpg.oscillator_derivatives(
            jnp.asarray(r), jnp.asarray(theta), jnp.asarray(p), jnp.asarray(force), 1.0, config
        )
        dr_ref, dth_ref = ref.hopf_derivatives(r, theta, p[4], p[2], p[3], p[7], force, squared_mu=form == "paper")
        np.testing.assert_allclose(dr, dr_ref, rtol=2e-5, atol=1e-3)
        np.testing.assert_allclose(dth, dth_ref, rtol=2e-5, atol=2e-4)


@jax.jit
def _run_steps(p, force, gate_tegotae):
    state = cpg.CPGState(
        jnp.full(4, 0.1), jnp.array([0.0, np.pi, np.pi, 0.0]), jnp.float32(0.0), jnp.float32(0.0), jnp.float32(0.0)
    )
    gates = cpg.Gates(vmc=jnp.float32(0.0), tegotae=gate_tegotae)
    obs = observation(force)

    def body(s, _):
        s, _, _ = cpg.controller_step(cpg.CPGConfig(), s, p, gates, obs)
        return s, s.phase_rad

    final, phases = jax.lax.scan(body, state, None, length=2000)
    return final, phases


def test_two_second_integration_matches_numpy():
    for p in random_params(3):
        force = RNG.uniform(0, 60, 4)
        final, _ = _run_steps(jnp.asarray(p, jnp.float32), jnp.asarray(force, jnp.float32), jnp.float32(1.0))
        r_ref, th_ref = ref.integrate([0.1] * 4, [0, np.pi, np.pi, 0], p, force, 2000)
        np.testing.assert_allclose(final.amplitude, r_ref, rtol=1e-4)
        wrapped = np.angle(np.exp(1j * (np.asarray(final.phase_rad) - th_ref)))
        np.testing.assert_allclose(wrapped, 0.0, atol=5e-3)


def _settle(p, config, steps=6000):
    state = cpg.CPGState(
        jnp.full(4, 0.1), jnp.array([0.3, 1.0, 2.5, 4.0]), jnp.float32(0.0), jnp.float32(0.0), jnp.float32(0.0)
    )  # far from trot
    gates = cpg.Gates(vmc=jnp.float32(0.0), tegotae=jnp.float32(0.0))

    def body(s, _):
        s = cpg.controller_step(config, s, p, gates, observation())[0]
        return s, s.phase_rad

    return jax.jit(lambda s: jax.lax.scan(body, s, None, length=steps))(state)


@pytest.mark.parametrize("form", ["paper", "sqrt"])
def test_limit_cycle_amplitude_and_trot_phase_lags(form):
    p = jnp.asarray(random_params(1)[0], jnp.float32)
    config = cpg.CPGConfig(amplitude_form=form)
    final, phases = _settle(p, config)
    mu = float(p[4])
    np.testing.assert_allclose(final.amplitude, mu if form == "paper" else np.sqrt(mu), rtol=1e-3)
    phases = np.asarray(phases)[-3000:]
    # Diagonal pairs (FR, RL) and (FL, RR) lock in phase: φ = 0.
    np.testing.assert_allclose(np.angle(np.exp(1j * (phases[:, 3] - phases[:, 0]))), 0.0, atol=1e-3)
    np.testing.assert_allclose(np.angle(np.exp(1j * (phases[:, 2] - phases[:, 1]))), 0.0, atol=1e-3)

    # With ω_swing ≠ ω_stance the instantaneous FR–FL difference wobbles, but FL runs FR's cycle half a period later
    # (φ = π): its lift-off (θ crossing 0) falls midway between two lift-offs of FR.
    def lift_offs(theta):
        return np.flatnonzero(np.diff(theta) < -np.pi)

    fr, fl = lift_offs(phases[:, 0]), lift_offs(phases[:, 1])
    period = np.diff(fr).mean()
    shift = np.array([(t - fr[fr < t].max()) / period for t in fl if (fr < t).any()])
    np.testing.assert_allclose(shift, 0.5, atol=0.01)


def test_equal_frequencies_lock_exactly_to_the_trot_matrix():
    p = jnp.asarray(random_params(1)[0], jnp.float32).at[2].set(12.0).at[3].set(12.0)  # ω_swing = ω_stance
    _, phases = _settle(p, cpg.CPGConfig())
    lag = np.angle(np.exp(1j * (np.asarray(phases[-1]) - float(phases[-1, 0]))))
    np.testing.assert_allclose(np.abs(lag), [0.0, np.pi, np.pi, 0.0], atol=1e-3)


def test_foot_targets_match_numpy():
    for p in random_params(10):
        r = RNG.uniform(0.5, 1.7, 4)
        theta = RNG.uniform(0, 2 * np.pi, 4)
        got = cpg.foot_targets(jnp.asarray(r), jnp.asarray(theta), jnp.asarray(p), cpg.CPGConfig())
        np.testing.assert_allclose(got, ref.foot_position(r, theta, p), atol=1e-6)


def test_ik_known_point():
    for side in (-1.0, 1.0):
        q = kinematics.leg_ik(jnp.array([-0.02, side * 0.08, -0.30]), side)
        np.testing.assert_allclose(q, [0.0, 0.854, -1.575], atol=1e-3)


def test_ik_fk_round_trip_over_workspace():
    for leg in range(4):
        side = float(kinematics.SIDE_SIGN[leg])
        q = np.stack([RNG.uniform(-0.6, 0.6, 500), RNG.uniform(-0.3, 2.0, 500), RNG.uniform(-2.7, -0.9, 500)], -1)
        feet = jax.vmap(kinematics.leg_fk, in_axes=(0, None))(jnp.asarray(q, jnp.float32), side)
        # Away from the abduction singularity (foot on the hip's x axis), where float32 IK loses precision.
        regular = np.asarray(feet[:, 1] ** 2 + feet[:, 2] ** 2 - kinematics.HIP_OFFSET_M**2) > 0.05**2
        q, feet = q[regular], feet[regular]
        q_back = jax.vmap(kinematics.leg_ik, in_axes=(0, None))(feet, side)
        np.testing.assert_allclose(q_back, q, atol=2e-3)
        feet_back = jax.vmap(kinematics.leg_fk, in_axes=(0, None))(q_back, side)
        np.testing.assert_allclose(feet_back, feet, atol=1e-5)


def test_jacobian_matches_finite_differences():
    jax_fk = jax.jit(kinematics.leg_fk)
    for _ in range(20):
        side = RNG.choice([-1.0, 1.0])
        q = np.array([RNG.uniform(-0.6, 0.6), RNG.uniform(-0.3, 2.0), RNG.uniform(-2.7, -0.9)])
        jac = np.asarray(kinematics.leg_jacobian(jnp.asarray(q), side))
        eps = 1e-3
        fd = np.stack(
            [
                (
                    np.asarray(jax_fk(jnp.asarray(q + eps * e), side), np.float64)
                    - np.asarray(jax_fk(jnp.asarray(q - eps * e), side), np.float64)
                )
                / (2 * eps)
                for e in np.eye(3)
            ],
            axis=1,
        )
        np.testing.assert_allclose(jac, fd, atol=2e-4)


def _one_step(gates, force, quat, p=None):
    p = jnp.asarray(param_space.midpoint() if p is None else p, jnp.float32)
    state = cpg.CPGState(
        jnp.full(4, 1.0), jnp.array([0.6, 3.9, 3.9, 0.6]), jnp.float32(0.0), jnp.float32(0.0), jnp.float32(0.0)
    )
    return cpg.controller_step(cpg.CPGConfig(), state, p, gates, observation(force, quat))


def _tilted_quat(roll, pitch, yaw=0.0):
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll / 2),
        np.sin(roll / 2),
        np.cos(pitch / 2),
        np.sin(pitch / 2),
        np.cos(yaw / 2),
        np.sin(yaw / 2),
    )
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def test_quaternion_to_rpy_convention():
    rpy = attitude.quat_to_rpy(jnp.asarray(_tilted_quat(0.1, 0.2, 0.3), jnp.float32))
    np.testing.assert_allclose(rpy, [0.1, 0.2, 0.3], atol=1e-6)
    # A rotation about +y tips the nose (body x axis) down: positive pitch is nose-down.
    nose = np.array([[np.cos(0.2), 0, np.sin(0.2)], [0, 1, 0], [-np.sin(0.2), 0, np.cos(0.2)]]) @ [1, 0, 0]
    assert nose[2] < 0


def test_open_loop_has_no_vmc_torque_and_no_force_term():
    quat = _tilted_quat(0.2, -0.15, 0.3)
    open_loop = cpg.controller_gates("open_loop")
    s0, tau0, d0 = _one_step(open_loop, np.zeros(4), quat)
    s1, tau1, _ = _one_step(open_loop, np.full(4, 60.0), quat)
    np.testing.assert_array_equal(d0.tau_vmc_nm, 0.0)
    np.testing.assert_array_equal(s0.phase_rad, s1.phase_rad)  # foot forces do not reach the phase
    np.testing.assert_array_equal(tau0, tau1)
    s2, _, _ = _one_step(cpg.controller_gates("tegotae"), np.full(4, 60.0), quat)
    assert np.abs(np.asarray(s2.phase_rad) - np.asarray(s0.phase_rad)).max() > 1e-3


def test_vmc_acts_on_stance_legs_only_and_corrects_attitude():
    quat = _tilted_quat(0.2, 0.15, 0.3)
    force = np.array([60.0, 0.0, 60.0, 60.0])  # FL in stance phase but unloaded (foot in the air): no VMC
    _, _, diag = _one_step(cpg.controller_gates("vmc"), force, quat)
    swing = np.asarray(diag.stance) == 0.0
    in_stance_phase = np.sin([0.6, 3.9, 3.9, 0.6]) <= 0
    np.testing.assert_array_equal(~swing, in_stance_phase & (force > 10.0))
    assert swing.any() and (~swing).any()
    tau = np.asarray(diag.tau_vmc_nm).reshape(4, 3)
    np.testing.assert_array_equal(tau[swing], 0.0)
    assert np.abs(tau[~swing]).max() > 1.0
    # Virtual work: the stance foot is pushed along F = [0, k_dir x_i e_ψ, k_r y_i sin φ − k_p x_i sin θ].
    q = np.tile([0.0, 0.85, -1.57], 4).reshape(4, 3)
    for leg in np.flatnonzero(~swing):
        jac = np.asarray(kinematics.leg_jacobian(jnp.asarray(q[leg]), kinematics.SIDE_SIGN[leg]))
        force = np.linalg.solve(jac.T, tau[leg])
        x_i, y_i = kinematics.FRONT_SIGN[leg], kinematics.SIDE_SIGN[leg]
        expected = [0.0, 300 * x_i * 0.3, 150 * y_i * np.sin(0.2) - 160 * x_i * np.sin(0.15)]
        np.testing.assert_allclose(force, expected, rtol=1e-3, atol=1e-3)


def test_torques_are_clipped_to_motor_limits():
    p = jnp.asarray(param_space.midpoint(), jnp.float32)
    obs = observation(q=np.tile([0.8, -0.5, -2.6], 4))  # far from the targets: PD asks for more than the motors have
    _, tau, diag = cpg.controller_step(cpg.CPGConfig(), cpg.init_state(obs), p, cpg.controller_gates("vmc"), obs)
    assert np.all(np.abs(np.asarray(tau)) <= constants.TORQUE_LIMIT_NM + 1e-6)
    assert np.asarray(diag.saturated).sum() > 0


def test_parameter_space_round_trip_and_validation():
    p = random_params(5)
    np.testing.assert_allclose(param_space.from_unit(param_space.to_unit(p)), p)
    param_space.validate(p)
    bad = p.copy()
    bad[3, 2] = 30.0
    with pytest.raises(ValueError, match=r"omega_swing_rad_s = 30.0 \(instance 3\).*\[16.0, 23.0\]"):
        param_space.validate(bad)
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="omega_swing_rad_s = nan"):
        param_space.validate(bad)
    with pytest.raises(ValueError, match="expected shape"):
        param_space.validate(np.zeros(7))
    with pytest.raises(ValueError, match="unknown controller"):
        cpg.controller_gates("pid")


def test_sigma_n_is_the_one_inactive_parameter_without_tegotae():
    """docs/decisions.md §13: without Tegotae σ_N is inactive, held at the box midpoint."""
    active = param_space.active_parameters([True, False])
    assert active.shape == (2, param_space.NUM_PARAMS) and active[0].all()
    assert [param_space.PARAM_NAMES[i] for i in np.flatnonzero(~active[1])] == ["sigma_n"]
    p = random_params(2)
    held = param_space.hold_inactive(p, active)
    np.testing.assert_array_equal(held[0], p[0])
    np.testing.assert_array_equal(held[1], np.where(active[1], p[1], param_space.midpoint()))
    assert held[1, param_space.SIGMA_N_INDEX] == param_space.midpoint()[param_space.SIGMA_N_INDEX]
