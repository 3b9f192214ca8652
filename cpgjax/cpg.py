"""The CPG controller of the paper as one pure, jit-able 1 kHz step.

Oscillators (paper eqs. 1-3, Tegotae eq. 6), foot trajectories (eqs. 4-5), inverse kinematics and joint PD
(τ_ref, K_p = 70, K_d = 1.3), and Virtual Model Control (τ_vmc, docs/decisions.md §7): τ_cmd = τ_ref + τ_vmc, clipped
to the Go1 motor limits. The same ``controller_step`` runs in MJX, in C MuJoCo and on the robot.

Equation numbers follow the paper's displayed equations in order:
  (1) ṙ_i = α(μ² − r_i²) r_i                               amplitude
  (2) θ̇_i = ω_i + Σ_j r_j w_ij sin(θ_j − θ_i − φ_ij)        phase, open loop
  (3) ω_i = ω_swing if sin θ_i > 0 else ω_stance; Φ, the gait's phase lags φ_ij (:data:`GAITS`; the paper's: trot)
  (4) x_i,foot = x_i,offset − d_step r_i cos θ_i
  (5) z_i,foot = −h + g_c sin θ_i (swing) | −h + g_p sin θ_i (stance)
  (6) θ̇_i = (2) − σ_N N_i cos θ_i                          Tegotae force feedback

The four controllers of the paper's ablation differ only by data (``Gates``): one compiled batch can mix them.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax.go1 import attitude, constants, kinematics, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.trial.params import NUM_PARAMS

# The gaits' phase offsets [rad] of the legs FR, FL, RR, RL (cpgjax.go1.constants.LEG_NAMES), FR at 0: the coupling
# of the CPG-RL code of the same lab (Bellegarda & Ijspeert, "CPG-RL: Learning Central Pattern Generators for
# Quadruped Locomotion", RA-L 2022; docs/gaits.md), whose leg order is ours. The phase lag of eq. (3) is
# φ_ij = offset_j − offset_i, so that the coupled oscillators settle at θ_j − θ_i = φ_ij. A leg with a larger offset
# is ahead: it touches down (θ reaches π) earlier in the cycle. "walk" is the lateral-sequence walk (hind foot, then
# the fore foot of the same side: RL, FL, RR, FR); "walk_diagonal" is the code's own walk, the diagonal sequence
# (RR, FL, RL, FR), its offsets negated.
GAITS = {
    "trot": (0.0, np.pi, np.pi, 0.0),  # diagonal pairs FR+RL, FL+RR (the paper's)
    "pace": (0.0, np.pi, 0.0, np.pi),  # lateral pairs FR+RR, FL+RL
    "bound": (0.0, 0.0, np.pi, np.pi),  # front pair, then hind pair
    "walk": (0.0, np.pi, np.pi / 2, 3 * np.pi / 2),  # four beats, lateral sequence
    "walk_diagonal": (0.0, np.pi, 3 * np.pi / 2, np.pi / 2),  # four beats, diagonal sequence
    "pronk": (0.0, 0.0, 0.0, 0.0),  # all four together
}
DEFAULT_GAIT = "trot"


def gait_phase_lags(name: str) -> np.ndarray:
    """φ_ij (4, 4) [rad] of eq. (3) for the gait ``name`` of :data:`GAITS`: offset_j − offset_i.

    Args:
      name: a gait of :data:`GAITS`.

    Returns:
      (4, 4) float64 [rad], row i and column j holding φ_ij.

    Raises:
      ValueError: ``name`` is not in :data:`GAITS` (the message lists the allowed gaits).
    """
    if name not in GAITS:
        raise ValueError(f"unknown gait {name!r}; allowed: {', '.join(GAITS)}")
    offsets = np.asarray(GAITS[name], np.float64)
    return offsets[None, :] - offsets[:, None]


TROT_PHASE_LAG_RAD = gait_phase_lags("trot")

CONTROLLERS = ("open_loop", "vmc", "tegotae", "vmc_tegotae")
AMPLITUDE_FORMS = ("paper", "sqrt")  # CPGConfig.amplitude_form


class CPGConfig(NamedTuple):
    """Fixed control constants (paper appendix table "Control parameters"). Static: changing one recompiles."""

    alpha: float = 50.0  # amplitude convergence rate α
    coupling_weight: float = 1.0  # w_ij
    step_length_m: float = 0.05  # d_step
    body_height_m: float = 0.30  # h
    foot_y_m: float = 0.08  # lateral foot position in the leg frame (the hip offset l1)
    kp_nm_rad: float = 70.0  # joint PD K_p
    kd_nm_s_rad: float = 1.3  # joint PD K_d
    k_att_roll_n: float = 150.0  # VMC roll gain k_att,r
    k_att_pitch_n: float = 160.0  # VMC pitch gain k_att,p
    k_dir_n_rad: float = 300.0  # VMC heading gain k_dir
    # VMC acts on legs in stance: CPG stance phase (sin θ ≤ 0) *and* foot loaded beyond this normal force. A virtual
    # force on a foot in the air only swings the leg (docs/decisions.md, "§7 VMC (reconstruction)"). −inf: the
    # stance phase alone (docs/decisions.md §7's switch).
    vmc_contact_force_n: float = 10.0
    dt_s: float = constants.TICK_S  # control period (the 1 kHz tick)
    # docs/decisions.md §1 (switch): "paper" integrates α(μ² − r²)r (r → μ); "sqrt" integrates α(μ − r²)r (r → √μ),
    # the form of the lab's public code.
    amplitude_form: str = "paper"
    # The start from standing (docs/decisions.md §18); every default is the paper's start: r from 0.1 converging at
    # α, trot phases, the standing posture, VMC from the first tick.
    start_ramp_s: float = 0.0  # the amplitude target of eq. (1) rises linearly from 0 to μ over this long
    start_lean: bool = False  # stand leaning into the slope: feet at h·tan(pitch) in x
    start_lean_s: float = 0.0  # the lean is blended out of the foot targets over this long (0: the stance only)
    start_vmc_delay_s: float = 0.0  # VMC acts only this long after the start
    start_phase_rad: float = 0.0  # added to every oscillator's phase at the start


# Named start-ups (docs/decisions.md §18): the CPGConfig fields each sets. "paper" is the paper's start; "lean_ramp"
# stands leaning into the slope from the IMU's pitch and blends the lean out while the amplitude target ramps up
# over 3 s (the 1.5 s transition and the first half of the steady phase).
STARTUPS = {
    "paper": {},
    "lean_ramp": dict(start_ramp_s=3.0, start_lean=True, start_lean_s=3.0),
}
DEFAULT_STARTUP = "paper"


def with_startup(config: CPGConfig, name: str) -> CPGConfig:
    """``config`` with the start-up ``name`` of :data:`STARTUPS` (its other start fields at the paper's).

    Args:
      config: the controller constants; its fields not named ``start_*`` are kept.
      name: a start-up of :data:`STARTUPS`.

    Returns:
      A :class:`CPGConfig`: every ``start_*`` field at :class:`CPGConfig`'s default, then the ones ``name`` sets.

    Raises:
      ValueError: ``name`` is not in :data:`STARTUPS` (the message lists the allowed start-ups).
    """
    if name not in STARTUPS:
        raise ValueError(f"unknown start-up {name!r}; allowed: {', '.join(STARTUPS)}")
    paper = CPGConfig()
    return config._replace(
        **({f: getattr(paper, f) for f in CPGConfig._fields if f.startswith("start_")} | STARTUPS[name])
    )


class Gates(NamedTuple):
    """Per-instance controller variant as data: the modules (1.0 enables one, 0.0 disables it; shape () each) and
    the gait's phase lags φ_ij of eq. (3) (4, 4), so that one compiled batch mixes controllers and gaits."""

    vmc: jax.Array
    tegotae: jax.Array
    phase_lag_rad: jax.Array = TROT_PHASE_LAG_RAD


def controller_gates(name: str, gait: str = DEFAULT_GAIT) -> Gates:
    """Gates of one of CONTROLLERS ('open_loop', 'vmc', 'tegotae', 'vmc_tegotae') walking one of :data:`GAITS`.

    Args:
      name: a controller of :data:`CONTROLLERS`.
      gait: a gait of :data:`GAITS`.

    Returns:
      :class:`Gates` of NumPy float32: ``vmc`` and ``tegotae`` () each, 1.0 where ``name`` contains the module,
      ``phase_lag_rad`` (4, 4) [rad] from :func:`gait_phase_lags`.

    Raises:
      ValueError: ``name`` is not in :data:`CONTROLLERS`, or ``gait`` not in :data:`GAITS` (from
        :func:`gait_phase_lags`).
    """
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; allowed: {CONTROLLERS}")
    return Gates(
        vmc=np.float32("vmc" in name),
        tegotae=np.float32("tegotae" in name),
        phase_lag_rad=gait_phase_lags(gait).astype(np.float32),
    )


class CPGState(NamedTuple):
    """Controller state carried from tick to tick."""

    amplitude: jax.Array  # r_i, (4,)
    phase_rad: jax.Array  # θ_i in [0, 2π), (4,)
    heading_ref_rad: jax.Array  # ψ_des, heading at the start of the run, ()
    start_s: jax.Array  # time since the start, saturating at START_CLOCK_MAX_S, ()
    start_pitch_rad: jax.Array  # the IMU pitch at the start (the lean's), ()


START_CLOCK_MAX_S = 60.0
"""Where :attr:`CPGState.start_s` stops counting: every start-up phase is shorter (float32 keeps 1 ms steps there)."""


class Diagnostics(NamedTuple):
    """Per-tick internals, for logging, plots and tests."""

    foot_target_m: jax.Array  # (4, 3) leg-frame foot targets
    joint_target_rad: jax.Array  # (12,)
    tau_ref_nm: jax.Array  # (12,) joint PD torque
    tau_vmc_nm: jax.Array  # (12,) VMC torque (zero when the gate is off)
    stance: jax.Array  # (4,) 1.0 for legs in stance (sin θ ≤ 0 and foot loaded), where VMC acts
    rpy_rad: jax.Array  # (3,) roll, pitch (nose-down positive), yaw
    saturated: jax.Array  # (12,) 1.0 where the commanded torque was clipped to the motor limit


def oscillator_derivatives(
    amplitude,
    phase_rad,
    params,
    foot_force_n,
    tegotae_gate,
    config: CPGConfig,
    mu_scale=1.0,
    phase_lag_rad=TROT_PHASE_LAG_RAD,
):
    """(ṙ, θ̇) of the four coupled oscillators, eqs. (1)-(3) and the Tegotae term of eq. (6).

    Args:
      amplitude, phase_rad: r_i, θ_i, (4,) each.
      params: the 8 physical parameters (see ``cpgjax.trial.params``).
      foot_force_n: N_i, (4,).
      tegotae_gate: 1.0 adds −σ_N N_i cos θ_i (eq. 6), 0.0 gives the open-loop phase of eq. (2).
      mu_scale: the amplitude target is μ · mu_scale (the start's ramp, :func:`start_ramp`; 1 after it).
      config: the controller constants (α, w_ij, ``amplitude_form``).
      phase_lag_rad: φ_ij (4, 4), the gait (:func:`gait_phase_lags`).

    Returns:
      (ṙ_i (4,) [1/s], θ̇_i (4,) [rad/s]).
    """
    mu, sigma_n = params[4] * mu_scale, params[7]
    omega_swing, omega_stance = params[2], params[3]
    target = mu * mu if config.amplitude_form == "paper" else mu  # AMPLITUDE_FORMS
    d_amplitude = config.alpha * (target - amplitude * amplitude) * amplitude  # eq. (1)
    omega = jnp.where(jnp.sin(phase_rad) > 0.0, omega_swing, omega_stance)  # eq. (3)
    phase_diff = phase_rad[None, :] - phase_rad[:, None] - phase_lag_rad  # [i, j] = θ_j − θ_i − φ_ij
    coupling = jnp.sum(amplitude[None, :] * config.coupling_weight * jnp.sin(phase_diff), axis=1)  # eq. (2)
    feedback = -tegotae_gate * sigma_n * foot_force_n * jnp.cos(phase_rad)  # eq. (6)
    return d_amplitude, omega + coupling + feedback


def foot_targets(amplitude, phase_rad, params, config: CPGConfig, lean_x_m=0.0) -> jax.Array:
    """Leg-frame foot targets (4, 3) [m] from the oscillator states, eqs. (4)-(5); ``lean_x_m`` is added to every
    foot's x (the start's lean, :func:`lean_x_m`).

    Args:
      amplitude: r_i, (4,).
      phase_rad: θ_i, (4,) [rad].
      params: the 8 physical parameters (see ``cpgjax.trial.params``): g_c, g_p and the front and hind x offsets
        [m] are used.
      config: the controller constants (d_step, h, the lateral foot position).
      lean_x_m: shift of every foot's x [m], () (0: none).

    Returns:
      (4, 3) [m], one row (x, y, z) per leg in the leg frame, legs in the order of ``cpgjax.go1.constants.LEG_NAMES``.
    """
    g_c, g_p = params[0], params[1]
    x_offset = jnp.where(kinematics.FRONT_SIGN > 0, params[5], params[6]) + lean_x_m
    sin_phase = jnp.sin(phase_rad)
    x = x_offset - config.step_length_m * amplitude * jnp.cos(phase_rad)  # eq. (4)
    z = -config.body_height_m + jnp.where(sin_phase > 0.0, g_c, g_p) * sin_phase  # eq. (5)
    y = kinematics.SIDE_SIGN * config.foot_y_m
    return jnp.stack([x, jnp.broadcast_to(y, x.shape), z], axis=-1)


def vmc_torques(joint_pos_rad, rpy_rad, heading_ref_rad, stance, config: CPGConfig) -> jax.Array:
    """Attitude (roll, pitch) and direction (yaw) virtual-model torques (12,), docs/decisions.md §7.

    On stance legs, F_z,i = k_att,r y_i sin(roll) − k_att,p x_i sin(pitch) and F_y,i = k_dir x_i wrap(ψ − ψ_des),
    with x_i = ±1 front/hind and y_i = ±1 left/right; τ_vmc,i = J_iᵀ [0, F_y,i, F_z,i]. F is the force the leg
    applies to its foot (F_z > 0 lifts the foot), so a raised corner is lowered and a yaw error is turned back.

    Args:
      joint_pos_rad: measured joint angles (12,) [rad], leg by leg.
      rpy_rad: roll, pitch (nose-down positive), yaw (3,) [rad].
      heading_ref_rad: ψ_des, () [rad].
      stance: (4,), 1.0 for legs in stance, 0.0 for the others (no force).
      config: the controller constants (the gains k_att,r [N], k_att,p [N], k_dir [N/rad]).

    Returns:
      τ_vmc (12,) [N·m], leg by leg.
    """
    roll, pitch, yaw = rpy_rad[0], rpy_rad[1], rpy_rad[2]
    heading_error = jnp.arctan2(jnp.sin(yaw - heading_ref_rad), jnp.cos(yaw - heading_ref_rad))
    force_z = config.k_att_roll_n * kinematics.SIDE_SIGN * jnp.sin(
        roll
    ) - config.k_att_pitch_n * kinematics.FRONT_SIGN * jnp.sin(pitch)
    force_y = config.k_dir_n_rad * kinematics.FRONT_SIGN * heading_error
    force = stance[:, None] * jnp.stack([jnp.zeros(4), force_y, force_z], axis=-1)  # (4, 3)
    jac = kinematics.legs_jacobian(joint_pos_rad.reshape(4, 3), kinematics.SIDE_SIGN)  # (4, 3, 3)
    return jnp.einsum("lij,li->lj", jac, force).reshape(12)


def init_state(
    obs: sensors.Observation,
    config: CPGConfig = CPGConfig(),
    initial_amplitude: float = 0.1,
    phase_lag_rad=TROT_PHASE_LAG_RAD,
) -> CPGState:
    """Controller state at the start of a run: small amplitude, the gait's phases θ_j = φ_0j of ``phase_lag_rad``
    (+ ``config.start_phase_rad``), heading reference = heading now, the start's clock at 0 and the IMU pitch now
    (the lean's).

    Args:
      obs: the observation at the start (its IMU quaternion is read).
      config: the controller constants (``start_phase_rad``).
      initial_amplitude: r_i of every oscillator at the start.
      phase_lag_rad: φ_ij (4, 4) [rad], the gait (:func:`gait_phase_lags`).

    Returns:
      A float32 :class:`CPGState`.
    """
    phase = initial_phase_rad(config, phase_lag_rad)
    rpy = attitude.quat_to_rpy(obs.imu_quat_wxyz).astype(jnp.float32)
    return CPGState(
        amplitude=jnp.full((4,), initial_amplitude, jnp.float32),
        phase_rad=phase,
        heading_ref_rad=rpy[2],
        start_s=jnp.float32(0.0),
        start_pitch_rad=rpy[1],
    )


def initial_phase_rad(config: CPGConfig, phase_lag_rad) -> jax.Array:
    """The oscillators' phases (4,) at a start: the gait's φ_0j (``phase_lag_rad`` (4, 4)) + ``config.start_phase_rad``,
    in [0, 2π).

    Args:
      config: the controller constants (``start_phase_rad``).
      phase_lag_rad: φ_ij (4, 4) [rad], the gait (:func:`gait_phase_lags`).

    Returns:
      θ_j (4,) float32 [rad] in [0, 2π).
    """
    return jnp.mod(jnp.asarray(phase_lag_rad, jnp.float32)[0] + jnp.float32(config.start_phase_rad), 2.0 * jnp.pi)


def start_ramp(duration_s: float, start_s) -> jax.Array:
    """A start phase's progress in [0, 1] at ``start_s`` after the start: t / ``duration_s``, 1 if it lasts 0.

    Args:
      duration_s: the start phase's length [s] (static: a Python float); ≤ 0 for none.
      start_s: time since the start [s], any shape.

    Returns:
      min(1, ``start_s`` / ``duration_s``), the shape of ``start_s``; ones when ``duration_s`` ≤ 0.
    """
    if duration_s <= 0.0:
        return jnp.ones_like(start_s)
    return jnp.minimum(1.0, start_s / duration_s)


def lean_x_m(config: CPGConfig, pitch_rad) -> jax.Array:
    """The feet's x shift [m] that puts the centre of mass over the feet on a slope: h · tan(pitch) with the IMU
    pitch (nose-down positive; uphill: negative, the feet move back under the trunk). 0 unless ``start_lean``.

    Args:
      config: the controller constants (h, ``start_lean``).
      pitch_rad: the IMU pitch [rad], any shape.

    Returns:
      The x shift [m], the shape of ``pitch_rad``.
    """
    return config.body_height_m * jnp.tan(pitch_rad) * float(config.start_lean)


def standing_pose_rad(config: CPGConfig, imu_quat_wxyz: jax.Array) -> jax.Array:
    """The standing joint angles (12,) a start begins from: the standing pose, with the start's lean the feet shifted
    by :func:`lean_x_m` of the IMU's pitch (MJX's reset and the robot's soft start; the native backend's reset stands
    at the lean of its scenario's slope, the same pitch).

    Args:
      config: the controller constants (h, ``start_lean``).
      imu_quat_wxyz: the IMU's orientation (4,), (w, x, y, z).

    Returns:
      Joint angles (12,) [rad], leg by leg.
    """
    return go1_model.standing_legs_rad(lean_x_m(config, attitude.quat_to_rpy(imu_quat_wxyz)[1]))


def controller_step(
    config: CPGConfig, state: CPGState, params: jax.Array, gates: Gates, obs: sensors.Observation
) -> tuple[CPGState, jax.Array, Diagnostics]:
    """One 1 kHz control tick: (state, 8 parameters, observation) → (new state, 12 joint torques [N·m], diagnostics).

    The oscillators are advanced by one forward-Euler step of dt, then mapped to foot targets (eqs. 4-5), joint
    targets (inverse kinematics) and torques τ_cmd = clip(τ_ref + gate_vmc · τ_vmc) with
    τ_ref = K_p (q_des − q) − K_d q̇.

    Args:
      config: the controller constants (static).
      state: the controller state of the previous tick (:func:`init_state` at a start).
      params: the 8 physical parameters (8,) (see ``cpgjax.trial.params``).
      gates: the controller variant and gait (:class:`Gates`).
      obs: this tick's observation (joint angles [rad] and velocities [rad/s], IMU quaternion, foot forces [N]).

    Returns:
      (the next :class:`CPGState`, joint torques (12,) [N·m] clipped to the motor limits, :class:`Diagnostics`).

    Raises:
      ValueError: ``params``' last axis does not have ``NUM_PARAMS`` (8) entries.
    """
    if params.shape[-1] != NUM_PARAMS:
        raise ValueError(f"params must have {NUM_PARAMS} entries, got shape {params.shape}")
    start_s = jnp.minimum(state.start_s + config.dt_s, START_CLOCK_MAX_S)
    d_amp, d_phase = oscillator_derivatives(
        state.amplitude,
        state.phase_rad,
        params,
        obs.foot_force_n,
        gates.tegotae,
        config,
        mu_scale=start_ramp(config.start_ramp_s, start_s),
        phase_lag_rad=gates.phase_lag_rad,
    )
    amplitude = state.amplitude + config.dt_s * d_amp
    phase = jnp.mod(state.phase_rad + config.dt_s * d_phase, 2.0 * jnp.pi)

    lean_weight = 1.0 - start_ramp(config.start_lean_s, start_s)
    targets = foot_targets(amplitude, phase, params, config, lean_weight * lean_x_m(config, state.start_pitch_rad))
    q_des = kinematics.legs_ik(targets, kinematics.SIDE_SIGN).reshape(12)
    tau_ref = config.kp_nm_rad * (q_des - obs.joint_pos_rad) - config.kd_nm_s_rad * obs.joint_vel_rad_s

    rpy = attitude.quat_to_rpy(obs.imu_quat_wxyz)
    stance = ((jnp.sin(phase) <= 0.0) & (obs.foot_force_n > config.vmc_contact_force_n)).astype(tau_ref.dtype)
    vmc_on = gates.vmc * (start_s > config.start_vmc_delay_s)
    tau_vmc = vmc_on * vmc_torques(obs.joint_pos_rad, rpy, state.heading_ref_rad, stance, config)

    tau_cmd = tau_ref + tau_vmc
    limit = jnp.asarray(constants.TORQUE_LIMIT_NM, tau_cmd.dtype)
    torque = jnp.clip(tau_cmd, -limit, limit)
    diagnostics = Diagnostics(
        foot_target_m=targets,
        joint_target_rad=q_des,
        tau_ref_nm=tau_ref,
        tau_vmc_nm=tau_vmc,
        stance=stance,
        rpy_rad=rpy,
        saturated=(jnp.abs(tau_cmd) > limit).astype(tau_cmd.dtype),
    )
    return state._replace(amplitude=amplitude, phase_rad=phase, start_s=start_s), torque, diagnostics
