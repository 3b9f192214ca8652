"""Run the jitted CPG controller at 1 kHz on a Go1 (or the loopback simulated Go1), with safety.

Pieces, each usable alone:

* transports: :class:`UdpTransport` (cpgjax's own implementation of the SDK's low-level UDP protocol, used for the
  loopback simulated Go1 and usable on the robot) and :class:`SdkTransport` (the official ``unitree_legged_sdk``
  Python binding, optional extra ``go1``); both move :class:`~cpgjax.go1_protocol.RobotState` in and
  :class:`~cpgjax.go1_protocol.MotorCommand` out;
* :class:`FootForceCalibration`: raw foot-sensor counts → Newtons (decisions.md §3), stored as JSON;
* :class:`CompiledController`: ``cpg.controller_step`` compiled ahead of time for one flat float32 vector in and
  out (≈11 µs per call on this CPU), plus the robot-side trial signals (leg-odometry velocity, power, load);
* :func:`run_loop`: the 1 kHz loop — absolute deadlines with a short spin, overrun counting, frozen GC, real-time
  priority and CPU affinity when permitted — and its safety layer: soft start (hold the measured pose while the
  gains ramp, then move to the standing pose), clamps on torque, gains and joint positions checked *before*
  encoding, the SDK's power protection rule, tilt stop, stale-state watchdog, remote stop buttons, non-finite
  command guard, motor temperature limit, and a clean shutdown to damping on Ctrl-C. Every trip is logged with its
  reason and latches damping.

The robot's real address appears only as the default of :data:`GO1_ROBOT_IP`; tests and examples use 127.0.0.1.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import os
import signal
import socket
import time
from pathlib import Path
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from cpgjax import cpg, go1_model, kinematics
from cpgjax import go1_protocol as proto

log = logging.getLogger(__name__)

GO1_ROBOT_IP = "192.168.123.10"  # the SDK's low-level target (UDP_SERVER_IP_BASIC); used only with --robot go1
GO1_ROBOT_PORT = 8007  # UDP_SERVER_PORT
GO1_LOCAL_PORT = 8090  # local port of the SDK's C++ examples
# Joint limits used by the SDK's Safety (go1_const.h), motor order; hip, thigh, calf [rad].
JOINT_LOWER_RAD = np.tile(np.array([-1.047, -0.663, -2.721]), 4)
JOINT_UPPER_RAD = np.tile(np.array([1.047, 2.966, -0.837]), 4)
TORQUE_LIMIT_NM = np.asarray(cpg.TORQUE_LIMIT_NM, np.float64)

# Loop phases (logged per tick).
CONNECT, HOLD, RAMP, RUN, DAMP = range(5)
PHASE_NAMES = ("connect", "hold", "ramp", "run", "damp")


# ================================================================================================ calibration

class FootForceCalibration(NamedTuple):
    """N_i = (raw_i − offset_i) · scale_i: the Go1's foot sensor counts in Newtons (decisions.md §3)."""

    offset_counts: np.ndarray  # (4,) raw value with the foot in the air
    newton_per_count: np.ndarray  # (4,)

    def to_newtons(self, raw_counts: np.ndarray) -> np.ndarray:
        return (raw_counts - self.offset_counts) * self.newton_per_count

    def save(self, path) -> None:
        Path(path).write_text(json.dumps({"offset_counts": self.offset_counts.tolist(),
                                          "newton_per_count": self.newton_per_count.tolist()}, indent=1))

    @classmethod
    def load(cls, path) -> FootForceCalibration:
        d = json.loads(Path(path).read_text())
        return cls(np.asarray(d["offset_counts"], np.float64), np.asarray(d["newton_per_count"], np.float64))


def calibrate_foot_force(air_counts: np.ndarray, standing_counts: np.ndarray,
                         total_mass_kg: float) -> FootForceCalibration:
    """Calibration from raw samples: the offset is each foot's minimum in the air (swing phases or lifted robot,
    ``air_counts`` (K, 4)); one common scale makes the four feet carry the robot's weight while standing still
    (``standing_counts`` (M, 4)).

    Raises:
      ValueError: the standing signal is not above the offsets (no load seen).
    """
    offset = np.min(np.asarray(air_counts, np.float64), axis=0)
    loaded = np.sum(np.mean(np.asarray(standing_counts, np.float64), axis=0) - offset)
    if not loaded > 0:
        raise ValueError(f"standing foot counts are not above the in-air offsets {offset}; cannot calibrate")
    return FootForceCalibration(offset, np.full(4, total_mass_kg * go1_model.GRAVITY_MPS2 / loaded))


# ================================================================================================ transports

class Transport(Protocol):
    """Moves one robot's low-level packets. ``receive`` never blocks."""

    power_tripped: bool  # the transport's own power protection (the SDK's Safety) has cut the motors

    def receive(self) -> proto.RobotState | None:
        """The newest valid state received since the last call, or None."""

    def send(self, cmd: proto.MotorCommand, state: proto.RobotState | None) -> None:
        """Send one command (already clamped and checked)."""

    def close(self) -> None: ...


def _check_port_free(port: int) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("", port))
        except OSError as e:
            raise OSError(f"local UDP port {port} is in use ({e}); the SDK would fail silently") from e


class UdpTransport:
    """The Go1 low-level protocol over a UDP socket connected to the robot (or the simulated Go1).

    Like the SDK, only datagrams from the robot's address count; unlike the SDK's ``Recv`` (which checks only the
    last datagram waiting), every waiting datagram is examined and the newest *valid* one is kept. Rejected
    datagrams are counted by reason in ``rejected``.
    """

    power_tripped = False

    def __init__(self, robot_address: tuple[str, int], local_port: int = 0):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        host = "127.0.0.1" if robot_address[0].startswith("127.") else ""
        self.sock.bind((host, local_port))
        self.sock.connect(robot_address)
        self.sock.setblocking(False)
        self.rejected = {"size": 0, "head": 0, "level": 0, "crc": 0}

    def receive(self) -> proto.RobotState | None:
        packets = []
        while True:
            try:
                packets.append(self.sock.recv(2048))
            except (BlockingIOError, ConnectionRefusedError):
                break
        newest = None
        for data in reversed(packets):
            error = proto.packet_error(data, proto.LOW_STATE_LENGTH)
            if error is not None:
                self.rejected[error.split(":")[0]] += 1
            elif newest is None:
                newest = data
        if newest is None:
            return None
        return proto.decode_low_state(newest)

    def send(self, cmd: proto.MotorCommand, state: proto.RobotState | None) -> None:
        try:
            self.sock.send(proto.encode_low_cmd(cmd))
        except ConnectionRefusedError:  # nobody listening yet (ICMP port unreachable); the watchdog handles it
            pass

    def close(self) -> None:
        self.sock.close()


class SdkTransport:
    """The robot through Unitree's ``unitree_legged_sdk`` 3.8 Python binding (``pip install --no-deps
    unitree-legged-sdk``; see docs/hardware.md). Non-blocking mode only (the binding holds the GIL).

    ``power_level`` (1…10) additionally runs the SDK's own ``Safety.PowerProtect`` on every command; its latched
    trip sets ``power_tripped`` (the SDK then sends the motors to mode 0).
    """

    power_tripped = False

    def __init__(self, robot_ip: str = GO1_ROBOT_IP, robot_port: int = GO1_ROBOT_PORT,
                 local_port: int = GO1_LOCAL_PORT, power_level: int | None = None):
        from unitree_legged_sdk import robot_interface as sdk  # optional extra "go1"

        _check_port_free(local_port)
        self._sdk = sdk
        self.udp = sdk.UDP(proto.LEVEL_LOW, local_port, robot_ip, robot_port)
        self.cmd = sdk.LowCmd()
        self.state = sdk.LowState()
        self.udp.InitCmdData(self.cmd)
        self._motors = self.cmd.motorCmd  # a cached list of references into the C++ struct (go1-sdk.md §1.7)
        self.safety = sdk.Safety(sdk.LeggedType.Go1) if power_level else None
        self.power_level = power_level

    def receive(self) -> proto.RobotState | None:
        if self.udp.Recv() != 0:
            return None
        self.udp.GetRecv(self.state)
        s, ms = self.state, self.state.motorState
        imu = s.imu
        return proto.RobotState(
            tick_ms=s.tick, quaternion_wxyz=np.array(imu.quaternion), gyro_rad_s=np.array(imu.gyroscope),
            accel_mps2=np.array(imu.accelerometer), rpy_rad=np.array(imu.rpy),
            motor_mode=np.array([ms[i].mode for i in range(12)], np.uint8),
            q_rad=np.array([ms[i].q for i in range(12)]), dq_rad_s=np.array([ms[i].dq for i in range(12)]),
            tau_est_nm=np.array([ms[i].tauEst for i in range(12)]),
            motor_temperature_c=np.array([ms[i].temperature for i in range(12)]),
            foot_force_raw=np.array(s.footForce), wireless_remote=bytes(s.wirelessRemote))

    def send(self, cmd: proto.MotorCommand, state: proto.RobotState | None) -> None:
        for i, m in enumerate(self._motors[:12]):
            m.mode, m.q, m.dq = int(cmd.mode[i]), float(cmd.q_rad[i]), float(cmd.dq_rad_s[i])
            m.tau, m.Kp, m.Kd = float(cmd.tau_nm[i]), float(cmd.kp_nm_rad[i]), float(cmd.kd_nm_s_rad[i])
        if self.safety is not None and self.safety.PowerProtect(self.cmd, self.state, self.power_level) < 0:
            self.power_tripped = True
        self.udp.SetSend(self.cmd)
        self.udp.Send()

    def close(self) -> None:
        del self.udp


# ================================================================================================ controller

OBS_SIZE = 35  # q 12 | dq 12 | quat 4 | gyro 3 | foot force 4
IN_SIZE = OBS_SIZE + 8 + 2 + 9  # obs | params 8 | gates 2 | CPG state (amplitude 4, phase 4, heading 1)
# Output layout (float32): torque | CPG state | rpy | stance | odometry velocity (v_x, v_y) | power ⟨|τ|, |q̇|⟩ [W] |
# mean foot force [N] | number of torques clipped to the motor limits.
OUT_TORQUE, OUT_STATE, OUT_RPY, OUT_STANCE = slice(0, 12), slice(12, 21), slice(21, 24), slice(24, 28)
OUT_VELOCITY, OUT_POWER, OUT_LOAD, OUT_SATURATED = slice(28, 30), 30, 31, 32
OUT_SIZE = 33


def leg_odometry_velocity(obs: cpg.Observation, stance: jax.Array) -> jax.Array:
    """Trunk velocity (v_x, v_y) [m/s] in the heading (yaw-only, gravity-aligned) frame from the stance legs'
    kinematics: v_body = −(J(q) q̇ + ω × p_foot), averaged over stance legs (zero when none is in stance)."""
    q = obs.joint_pos_rad.reshape(4, 3)
    dq = obs.joint_vel_rad_s.reshape(4, 3)
    jac = kinematics.legs_jacobian(q, kinematics.SIDE_SIGN)
    foot_rel = jnp.einsum("lij,lj->li", jac, dq)
    p_foot = kinematics.legs_fk(q, kinematics.SIDE_SIGN) + jnp.asarray(kinematics.HIP_POS_M, q.dtype)
    v_legs = -(foot_rel + jnp.cross(obs.gyro_rad_s, p_foot))
    v_body = jnp.sum(stance[:, None] * v_legs, axis=0) / jnp.maximum(jnp.sum(stance), 1.0)
    w, x, y, z = obs.imu_quat_wxyz
    rot = jnp.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    v_world = rot @ v_body
    yaw = cpg.quat_to_rpy(obs.imu_quat_wxyz)[2]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * v_world[0] + s * v_world[1], -s * v_world[0] + c * v_world[1]])


def unpack_observation(x: jax.Array) -> cpg.Observation:
    return cpg.Observation(x[0:12], x[12:24], x[24:28], x[28:31], x[31:35])


def flat_step(config: cpg.CPGConfig, x: jax.Array) -> jax.Array:
    """``cpg.controller_step`` on one flat input vector (IN_SIZE,) → one flat output vector (OUT_SIZE,)."""
    obs = unpack_observation(x)
    params = x[OBS_SIZE:OBS_SIZE + 8]
    gates = cpg.Gates(x[OBS_SIZE + 8], x[OBS_SIZE + 9])
    s = x[OBS_SIZE + 10:]
    state, torque, diag = cpg.controller_step(config, cpg.CPGState(s[0:4], s[4:8], s[8]), params, gates, obs)
    velocity = leg_odometry_velocity(obs, diag.stance)
    power = jnp.sum(jnp.abs(torque) * jnp.abs(obs.joint_vel_rad_s))
    return jnp.concatenate([torque, state.amplitude, state.phase_rad, state.heading_ref_rad[None], diag.rpy_rad,
                            diag.stance, velocity, power[None], jnp.mean(obs.foot_force_n)[None],
                            jnp.sum(diag.saturated)[None]])


def flat_initial_state(x_obs: jax.Array) -> jax.Array:
    """``cpg.init_state`` for the observation x_obs (OBS_SIZE,), as the flat CPG-state slice (9,)."""
    s = cpg.init_state(unpack_observation(x_obs))
    return jnp.concatenate([s.amplitude, s.phase_rad, s.heading_ref_rad[None]])


class CompiledController:
    """The controller step compiled ahead of time (``jit(...).lower(...).compile()``) and warmed up.

    ``step(x)`` takes the flat float32 input (IN_SIZE,) and returns the flat output (OUT_SIZE,) as NumPy;
    ``initial_state(x_obs)`` gives the CPG-state slice to start from.
    """

    def __init__(self, config: cpg.CPGConfig = cpg.CPGConfig(), warmup_calls: int = 200):
        # Run CPU computations on the calling thread: with asynchronous dispatch the loop thread (real-time
        # priority) waits for an XLA worker thread at normal priority, which a loaded machine delays by
        # milliseconds (p99 ≈ 1 ms vs ≈ 0.12 ms measured here). This is a process-wide JAX setting.
        jax.config.update("jax_cpu_enable_async_dispatch", False)
        self.config = config
        x = np.zeros(IN_SIZE, np.float32)
        x[24] = 1.0  # identity quaternion
        self._step = jax.jit(lambda v: flat_step(config, v)).lower(x).compile()
        self._init = jax.jit(flat_initial_state).lower(x[:OBS_SIZE]).compile()
        for _ in range(warmup_calls):
            self.step(x)
        self.initial_state(x[:OBS_SIZE])

    def step(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self._step(x))

    def initial_state(self, x_obs: np.ndarray) -> np.ndarray:
        return np.asarray(self._init(x_obs))


def pack_observation(state: proto.RobotState, calibration: FootForceCalibration, out: np.ndarray) -> None:
    """Write the controller's observation (SI units) from a LowState into out[:OBS_SIZE]."""
    out[0:12] = state.q_rad
    out[12:24] = state.dq_rad_s
    out[24:28] = state.quaternion_wxyz
    out[28:31] = state.gyro_rad_s
    out[31:35] = calibration.to_newtons(state.foot_force_raw)


# ================================================================================================ safety

class SafetyConfig(NamedTuple):
    """Limits of the safety layer. Each trip latches damping and is logged with its reason."""

    max_tilt_rad: float = 0.7  # |roll| or |pitch| (from the IMU quaternion) beyond this → damping
    watchdog_ticks: int = 5  # this many consecutive ticks without a new robot tick → damping
    stop_buttons: tuple[str, ...] = ("L2", "B")  # all pressed on the remote → damping (Unitree's damping combo)
    max_motor_temperature_c: int = 70
    # The SDK's PowerProtect rule (go1-sdk.md §1.10): Σ|tauEst·dq| over the 12 legs motors above 100 W × level
    # counts up, below counts down; the trip fires at power_trip_count and latches.
    power_level: int = 9
    power_trip_count: int = 6
    kp_max_nm_rad: float = 100.0
    kd_max_nm_s_rad: float = 10.0


def tilt_rad(quaternion_wxyz: np.ndarray) -> tuple[float, float]:
    """(roll, pitch) [rad] of a unit quaternion (same convention as ``cpg.quat_to_rpy``)."""
    w, x, y, z = (float(v) for v in quaternion_wxyz)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    return roll, pitch


def state_trip_reason(state: proto.RobotState, safety: SafetyConfig, stop_mask: int) -> str | None:
    """The reason a fresh robot state must stop the robot (tilt, stop buttons, motor temperature), or None."""
    roll, pitch = tilt_rad(state.quaternion_wxyz)
    if not (abs(roll) <= safety.max_tilt_rad and abs(pitch) <= safety.max_tilt_rad):
        return f"tilt: roll {roll:+.3f} rad, pitch {pitch:+.3f} rad beyond ±{safety.max_tilt_rad} rad"
    if stop_mask and proto.remote_buttons(state.wireless_remote) & stop_mask == stop_mask:
        return f"remote stop buttons {'+'.join(safety.stop_buttons)} pressed"
    hottest = int(np.max(state.motor_temperature_c))
    if hottest >= safety.max_motor_temperature_c:
        motor = int(np.argmax(state.motor_temperature_c))
        return f"motor temperature: motor {motor} at {hottest} °C ≥ {safety.max_motor_temperature_c} °C"
    return None


def power_protect(counter: int, state: proto.RobotState, safety: SafetyConfig) -> tuple[int, str | None]:
    """One update of the SDK's power-protection counter; returns (counter, trip reason or None)."""
    power_w = float(np.sum(np.abs(state.tau_est_nm * state.dq_rad_s)))
    limit_w = 100.0 * min(max(safety.power_level, 1), 10)
    counter = counter + 1 if power_w > limit_w else max(counter - 1, 0)
    if counter >= safety.power_trip_count:
        return counter, f"power protection: Σ|tauEst·dq| = {power_w:.0f} W > {limit_w:.0f} W (level {safety.power_level})"
    return counter, None


_SERVO = np.full(12, proto.MODE_SERVO, np.uint8)
_POS_STOP = np.full(12, proto.POS_STOP_F)
_VEL_STOP = np.full(12, proto.VEL_STOP_F)
_ZERO = np.zeros(12)
for _a in (_SERVO, _POS_STOP, _VEL_STOP, _ZERO):
    _a.flags.writeable = False  # shared by every command


def torque_command(torque_nm: np.ndarray) -> proto.MotorCommand:
    """Pure torque: both motor PD terms stopped (PosStopF, VelStopF, zero gains)."""
    return proto.MotorCommand(_SERVO, _POS_STOP, _VEL_STOP, torque_nm, _ZERO, _ZERO)


def pd_command(q_rad: np.ndarray, kp: float, kd: float) -> proto.MotorCommand:
    """Motor-side PD to joint positions (velocity target 0)."""
    return proto.MotorCommand(_SERVO, q_rad, _ZERO, _ZERO, np.full(12, kp), np.full(12, kd))


def damping_command(kd: float) -> proto.MotorCommand:
    """Damping: τ = −kd · dq on every motor (no stiffness, no torque)."""
    return proto.MotorCommand(_SERVO, _POS_STOP, _ZERO, _ZERO, _ZERO, np.full(12, kd))


def guard_command(cmd: proto.MotorCommand, safety: SafetyConfig) -> tuple[proto.MotorCommand, str | None]:
    """Check and clamp a command before it is encoded (the wire silently wraps out-of-range values).

    A non-finite tau, gain, velocity or (active) position target gives a trip reason. Otherwise torques are clamped
    to the motor limits, gains to [0, max], and position targets with Kp > 0 to the SDK's joint limits (a PosStopF
    target is kept: clamping it would switch the position term on).
    """
    position_active = cmd.kp_nm_rad > 0.0
    q_active = np.where(position_active, cmd.q_rad, 0.0)
    fields = (cmd.tau_nm, cmd.kp_nm_rad, cmd.kd_nm_s_rad, q_active, cmd.dq_rad_s)
    if not np.isfinite(np.concatenate(fields)).all():
        bad = [n for n, f in zip(("tau", "kp", "kd", "q", "dq"), fields) if not np.isfinite(f).all()]
        return cmd, f"non-finite command ({', '.join(bad)})"
    q = cmd.q_rad
    if position_active.any():
        q = np.where(position_active, np.minimum(np.maximum(q, JOINT_LOWER_RAD), JOINT_UPPER_RAD), q)
    return proto.MotorCommand(
        cmd.mode, q, cmd.dq_rad_s, np.minimum(np.maximum(cmd.tau_nm, -TORQUE_LIMIT_NM), TORQUE_LIMIT_NM),
        np.minimum(np.maximum(cmd.kp_nm_rad, 0.0), safety.kp_max_nm_rad),
        np.minimum(np.maximum(cmd.kd_nm_s_rad, 0.0), safety.kd_max_nm_s_rad)), None


# ================================================================================================ the loop

class ParamSchedule(Protocol):
    """Supplies the CPG parameters during the run phase and sees every controller output (robot time = ticks)."""

    finished: bool

    def params(self, run_tick: int) -> np.ndarray:
        """Parameters (8,) for this tick of the run phase."""

    def record(self, run_tick: int, out: np.ndarray) -> None:
        """The controller's flat output (OUT_SIZE,) of this tick."""


class FixedParams:
    """One parameter set for ``run_ticks`` ticks (None: until stopped)."""

    def __init__(self, params: np.ndarray, run_ticks: int | None = None):
        self._params = np.asarray(params, np.float32)
        self._run_ticks = run_ticks
        self.finished = False

    def params(self, run_tick: int) -> np.ndarray:
        return self._params

    def record(self, run_tick: int, out: np.ndarray) -> None:
        if self._run_ticks is not None and run_tick + 1 >= self._run_ticks:
            self.finished = True


class LoopConfig(NamedTuple):
    """Timing and soft start of the 1 kHz loop."""

    period_s: float = 0.001
    spin_s: float = 0.0002  # sleep until this long before the deadline, then spin
    connect_timeout_s: float = 2.0  # no robot state by then → give up
    hold_s: float = 0.5  # hold the measured pose while Kp ramps from hold_kp_fraction to stand_kp
    ramp_s: float = 1.0  # then move linearly to the standing pose
    stand_kp_nm_rad: float = 70.0
    stand_kd_nm_s_rad: float = 1.5
    hold_kp_fraction: float = 0.2
    damping_kd_nm_s_rad: float = 3.0
    end_damping_s: float = 1.0  # damping sent after a trip, Ctrl-C or the end of the run, before returning
    realtime_priority: int | None = 80  # SCHED_FIFO priority when permitted (None: leave the scheduler alone)
    cpu: int | None = None  # pin the loop thread to this CPU when permitted
    log_ticks: int = 120_000  # per-tick log ring buffer (the newest ticks are kept)


class TickLog(NamedTuple):
    """Per-tick records, chronological (the newest ``LoopConfig.log_ticks``)."""

    t_start_s: np.ndarray  # perf_counter at the start of the tick
    step_s: np.ndarray  # controller step latency (pack + compiled call + unpack)
    work_s: np.ndarray  # whole tick before waiting
    phase: np.ndarray  # CONNECT … DAMP
    fresh: np.ndarray  # a new robot state arrived this tick
    robot_tick_ms: np.ndarray
    obs: np.ndarray  # (n, OBS_SIZE) observation given to the controller (run phase)
    torque_nm: np.ndarray  # (n, 12) torque sent (run phase, after clamping)
    controller_torque_nm: np.ndarray  # (n, 12) torque returned by the controller (before clamping)

    @classmethod
    def allocate(cls, n: int) -> TickLog:
        return cls(np.zeros(n), np.zeros(n, np.float32), np.zeros(n, np.float32), np.full(n, -1, np.int8),
                   np.zeros(n, bool), np.zeros(n, np.uint32), np.zeros((n, OBS_SIZE), np.float32),
                   np.zeros((n, 12), np.float32), np.zeros((n, 12), np.float32))

    def chronological(self, ticks: int) -> TickLog:
        n = self.phase.shape[0]
        if ticks <= n:
            return TickLog(*(a[:ticks] for a in self))
        order = (np.arange(n) + ticks) % n
        return TickLog(*(a[order] for a in self))


class LoopResult(NamedTuple):
    trip: str | None  # the first safety trip, or None (clean end)
    events: list  # (tick, phase name, message)
    ticks: int
    overruns: int  # ticks whose work ended after the next deadline
    skipped_ticks: int  # deadlines dropped after an overrun longer than a period
    rejected_packets: dict
    realtime: str  # what scheduling the loop actually got
    log: TickLog

    def timing(self) -> dict:
        return timing_stats(self.log, self.overruns, self.ticks)


def timing_stats(log: TickLog, overruns: int, ticks: int) -> dict:
    """Controller-step latency and loop-period statistics [µs] over the logged ticks after connection."""
    active = log.phase > CONNECT
    step_us = log.step_s[active & (log.phase == RUN)] * 1e6
    period_us = np.diff(log.t_start_s[active]) * 1e6
    pct = lambda a, q: float(np.percentile(a, q)) if a.size else float("nan")  # noqa: E731
    return {
        "ticks": int(ticks), "overruns": int(overruns), "overruns_per_10k_ticks": 1e4 * overruns / max(ticks, 1),
        "step_median_us": pct(step_us, 50), "step_p99_us": pct(step_us, 99),
        "step_max_us": float(step_us.max()) if step_us.size else float("nan"),
        "period_median_us": pct(period_us, 50), "period_p1_us": pct(period_us, 1),
        "period_p99_us": pct(period_us, 99), "period_max_us": float(period_us.max()) if period_us.size else float("nan"),
        "work_p99_us": pct(log.work_s[active] * 1e6, 99),
    }


def _enter_realtime(loop: LoopConfig):
    """Apply SCHED_FIFO and CPU affinity where permitted; return (description, restore function)."""
    notes, restores = [], []
    if loop.cpu is not None:
        try:
            old = os.sched_getaffinity(0)
            os.sched_setaffinity(0, {loop.cpu})
            restores.append(lambda: os.sched_setaffinity(0, old))
            notes.append(f"pinned to CPU {loop.cpu}")
        except (OSError, AttributeError) as e:
            notes.append(f"affinity not permitted ({e})")
    if loop.realtime_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(loop.realtime_priority))
            restores.append(lambda: os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0)))
            notes.append(f"SCHED_FIFO {loop.realtime_priority}")
        except (OSError, AttributeError) as e:
            notes.append(f"real-time priority not permitted ({e})")
    return ", ".join(notes) or "default scheduling", lambda: [r() for r in reversed(restores)]


class _StopRequest:
    """Ctrl-C (SIGINT) while the loop runs asks for a clean shutdown to damping instead of raising."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self) -> _StopRequest:
        try:
            self._old = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not the main thread: no handler, the caller stops the loop otherwise
            self._old = None
        return self

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _wait_until(deadline: float, spin_s: float) -> None:
    remaining = deadline - time.perf_counter()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while time.perf_counter() < deadline:
        pass


def run_loop(transport: Transport, controller: CompiledController, schedule: ParamSchedule,
             calibration: FootForceCalibration, gates: cpg.Gates, loop: LoopConfig = LoopConfig(),
             safety: SafetyConfig = SafetyConfig()) -> LoopResult:
    """Connect, soft-start, run the CPG at 1 kHz until ``schedule.finished``, Ctrl-C or a safety trip; then damp
    for ``loop.end_damping_s`` and return.

    Each tick: take the newest valid state (non-blocking) → watchdog and state checks → the phase's command (hold /
    ramp: motor PD; run: the compiled controller's torques; damp) → guard (finite, clamped) → power protection →
    send → wait for the next absolute deadline.
    """
    period = loop.period_s
    ids = go1_model.indices()
    stand_q = go1_model.standing_qpos()[ids.joint_qpos]
    stop_mask = sum(proto.REMOTE_BUTTON_BITS[b] for b in safety.stop_buttons)
    hold_ticks, ramp_ticks = max(1, round(loop.hold_s / period)), max(1, round(loop.ramp_s / period))
    end_ticks = max(1, round(loop.end_damping_s / period))
    damp = damping_command(loop.damping_kd_nm_s_rad)
    n_log = loop.log_ticks
    tick_log = TickLog.allocate(n_log)
    x = np.zeros(IN_SIZE, np.float32)
    x[OBS_SIZE + 8], x[OBS_SIZE + 9] = float(gates.vmc), float(gates.tegotae)

    events: list = []
    trip = None
    phase, phase_tick = CONNECT, 0
    last_state, last_robot_tick, stale = None, None, 0
    power_counter, hold_q, run_tick = 0, None, 0
    overruns = skipped = k = 0

    def enter(new_phase: int, message: str) -> None:
        nonlocal phase, phase_tick
        events.append((k, PHASE_NAMES[new_phase], message))
        log.info("tick %d: %s (%s)", k, PHASE_NAMES[new_phase], message)
        phase, phase_tick = new_phase, k

    realtime, restore = _enter_realtime(loop)
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        with _StopRequest() as stop:
            deadline = time.perf_counter()
            while True:
                t0 = time.perf_counter()
                state = transport.receive()
                fresh = state is not None and state.tick_ms != last_robot_tick
                if fresh:
                    last_state, last_robot_tick, stale = state, state.tick_ms, 0
                else:
                    stale += 1

                reason = None
                if phase == CONNECT:
                    if fresh:
                        hold_q = np.clip(state.q_rad, JOINT_LOWER_RAD, JOINT_UPPER_RAD)
                        enter(HOLD, "first robot state; holding the measured pose")
                    elif k * period > loop.connect_timeout_s:
                        reason = f"no robot state within {loop.connect_timeout_s} s"
                elif phase != DAMP:
                    if stale > safety.watchdog_ticks:
                        reason = f"stale state: no new robot tick for {stale} ticks"
                    elif fresh:
                        reason = state_trip_reason(state, safety, stop_mask)
                        if reason is None:
                            power_counter, reason = power_protect(power_counter, state, safety)
                    if reason is None and transport.power_tripped:
                        reason = "the SDK's power protection tripped"
                    if reason is None and stop.requested:
                        reason = "shutdown requested (Ctrl-C)"
                if reason is not None:
                    trip = trip or reason
                    enter(DAMP, reason)

                step_s = 0.0
                command_phase = phase  # the phase whose command this tick sends (logged)
                if phase == HOLD:
                    a = (k - phase_tick) / hold_ticks
                    cmd = pd_command(hold_q, loop.stand_kp_nm_rad * min(1.0, loop.hold_kp_fraction
                                                                         + (1 - loop.hold_kp_fraction) * a),
                                     loop.stand_kd_nm_s_rad)
                    if k - phase_tick + 1 >= hold_ticks:
                        enter(RAMP, "moving to the standing pose")
                elif phase == RAMP:
                    a = min(1.0, (k - phase_tick + 1) / ramp_ticks)
                    cmd = pd_command(hold_q + a * (stand_q - hold_q), loop.stand_kp_nm_rad, loop.stand_kd_nm_s_rad)
                    if a >= 1.0:
                        enter(RUN, "CPG running")
                elif phase == RUN:
                    ts = time.perf_counter()
                    pack_observation(last_state, calibration, x)
                    if run_tick == 0:  # start the CPG from the observation of its first tick (as the simulator)
                        x[OBS_SIZE + 10:] = controller.initial_state(x[:OBS_SIZE])
                    x[OBS_SIZE:OBS_SIZE + 8] = schedule.params(run_tick)
                    out = controller.step(x)
                    x[OBS_SIZE + 10:] = out[OUT_STATE]
                    step_s = time.perf_counter() - ts
                    schedule.record(run_tick, out)
                    cmd = torque_command(out[OUT_TORQUE].astype(np.float64))
                    i = k % n_log
                    tick_log.obs[i] = x[:OBS_SIZE]
                    tick_log.controller_torque_nm[i] = out[OUT_TORQUE]
                    run_tick += 1
                    if schedule.finished:
                        enter(DAMP, "run complete")
                elif phase == DAMP:
                    cmd = damp
                    if k - phase_tick >= end_ticks:
                        break
                else:
                    cmd = damp

                cmd, reason = guard_command(cmd, safety)
                if reason is not None:
                    trip = trip or reason
                    enter(DAMP, reason)
                    cmd = damp
                transport.send(cmd, last_state)

                i = k % n_log
                tick_log.t_start_s[i] = t0
                tick_log.step_s[i] = step_s
                tick_log.phase[i] = DAMP if reason is not None else command_phase
                tick_log.fresh[i] = fresh
                tick_log.robot_tick_ms[i] = last_robot_tick or 0
                tick_log.torque_nm[i] = cmd.tau_nm
                tick_log.work_s[i] = time.perf_counter() - t0
                k += 1

                deadline += period
                now = time.perf_counter()
                if now > deadline:
                    overruns += 1
                    if now > deadline + period:  # more than a period late: drop the missed deadlines
                        missed = int((now - deadline) / period)
                        skipped += missed
                        deadline += missed * period
                else:
                    _wait_until(deadline, loop.spin_s)
    finally:
        gc.enable()
        gc.unfreeze()
        restore()
    return LoopResult(trip=trip, events=events, ticks=k, overruns=overruns, skipped_ticks=skipped,
                      rejected_packets=dict(getattr(transport, "rejected", {})), realtime=realtime,
                      log=tick_log.chronological(k))
