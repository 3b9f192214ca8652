"""A loopback simulated Go1: a separate process that speaks the robot's low-level UDP protocol on 127.0.0.1.

It receives LowCmd datagrams and answers LowState datagrams in the SDK's exact wire format
(``cpgjax.robot.wire``: 614/807 bytes, fixed-point fields, CRC), so the real ``unitree_legged_sdk`` and
``cpgjax.hardware_io`` both accept it. Each tick it applies the Go1 motor law to the latest command, steps C MuJoCo
with cpgjax's own Go1 model (1 ms), and reports the sensors with the same definitions as the simulator backends
(``cpgjax.go1.sensors.observe``), encoded in the robot's raw units. Foot forces are reported as raw int16 counts with a
per-foot offset and a scale (:data:`FOOT_FORCE_OFFSET_COUNTS`, :data:`FOOT_FORCE_N_PER_COUNT`) so that the deployment's
calibration path is exercised (docs/decisions.md §3).

Pacing: ``realtime`` steps at 1 kHz on absolute wall-clock deadlines once the first command has arrived (the
physics is frozen until then, like a robot waiting for low-level control), its clock's phase locked to the
commands' (:func:`phase_correction`), and streams one state per tick;
``lockstep`` steps once per received command and answers at once (deterministic tests on a loaded machine; drive it
with ``go1_transport.LockstepTransport``).

Fault injection for tests, resets and lifting the robot off the ground (foot-force calibration) go through a second
UDP socket (the control port, JSON requests), see :class:`SimGo1Client`. Run ``python -m cpgjax.robot.sim_server
--help``. Only 127.0.0.1 is ever bound.
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax.go1 import attitude, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1.constants import GRAVITY_MPS2, TICK_S, TORQUE_LIMIT_NM
from cpgjax.layout import FlatLayout
from cpgjax.robot import cpu_dispatch, memory_lock, wire

LOOPBACK = "127.0.0.1"
# The simulated foot sensor: raw = offset + N / scale (the real Go1's values are unknown and drift; the deployment
# calibrates them, docs/decisions.md §3).
FOOT_FORCE_OFFSET_COUNTS = np.array([14, -6, 22, 9])
FOOT_FORCE_N_PER_COUNT = 0.5
BRAKE_KD_NM_S_RAD = 20.0  # mode 0x00 (damping): Unitree's Gazebo motor model brakes with Kd = 20
MOTOR_TEMPERATURE_C = 38
FAULT_KINDS = (
    "drop",
    "late_ms",
    "corrupt_crc",
    "wrong_head",
    "freeze_tick",
    "silence",
    "push_roll_nm",
    "buttons",
    "power",
    "temperature_c",
    "nan_q",
)


def motor_torque(cmd: wire.MotorCommand, q_rad, dq_rad_s):
    """The Go1 motor law (docs/go1-sdk.md §1.8): in servo mode τ = tau + Kp (q* − q) + Kd (dq* − dq), with the position
    term off when q* = PosStopF and the velocity term off when dq* = VelStopF; in damping mode τ = −Kd_brake dq.
    Clipped to the motor limits (12,). JAX (it runs inside the simulated Go1's compiled motor step)."""
    kp = jnp.where(jnp.abs(cmd.q_rad - wire.POS_STOP_F) < 1e3, 0.0, cmd.kp_nm_rad)
    kd = jnp.where(jnp.abs(cmd.dq_rad_s - wire.VEL_STOP_F) < 1.0, 0.0, cmd.kd_nm_s_rad)
    q_err = jnp.where(kp > 0.0, cmd.q_rad - q_rad, 0.0)
    dq_err = jnp.where(kd > 0.0, cmd.dq_rad_s - dq_rad_s, 0.0)
    servo = cmd.tau_nm + kp * q_err + kd * dq_err
    tau = jnp.where(cmd.mode == wire.MODE_SERVO, servo, -BRAKE_KD_NM_S_RAD * dq_rad_s)
    return jnp.clip(tau, -TORQUE_LIMIT_NM, TORQUE_LIMIT_NM)


def _joints() -> np.ndarray:
    return np.zeros(12, np.float32)


class SensorReport(NamedTuple):
    """The LowState's sensor fields as the simulated Go1 reports them (:meth:`Go1Physics.sense`)."""

    quaternion_wxyz: np.ndarray  # (4,)
    gyro_rad_s: np.ndarray  # (3,)
    accel_mps2: np.ndarray  # (3,) the specific force of a robot at rest
    rpy_rad: np.ndarray  # (3,)
    q_rad: np.ndarray  # (12,)
    dq_rad_s: np.ndarray  # (12,)
    foot_force_raw: np.ndarray  # (4,) counts


class _DriveIn(NamedTuple):
    io: physics_profiles.ActuatorSensorState
    command: wire.MotorCommand
    q_rad: np.ndarray  # (12,) the joints' measured angles
    dq_rad_s: np.ndarray  # (12,)


class _DriveOut(NamedTuple):
    io: physics_profiles.ActuatorSensorState
    law_torque_nm: np.ndarray  # (12,) the motor law's torque
    applied_torque_nm: np.ndarray  # (12,) after the profile's motors


class _SenseIn(NamedTuple):
    io: physics_profiles.ActuatorSensorState
    qpos: np.ndarray
    qvel: np.ndarray
    sensordata: np.ndarray


class _SenseOut(NamedTuple):
    io: physics_profiles.ActuatorSensorState
    report: SensorReport


COMMAND = FlatLayout(wire.MotorCommand(*(_joints() for _ in wire.MotorCommand._fields)))
REPORT = FlatLayout(SensorReport(np.zeros(4), np.zeros(3), np.zeros(3), np.zeros(3), _joints(), _joints(), np.zeros(4)))


class _Layouts(NamedTuple):
    io: FlatLayout  # the profile's sensor and motor state
    drive_in: FlatLayout
    drive_out: FlatLayout
    reset_io: np.ndarray  # the flat state after a reset


@functools.cache
def _layouts() -> _Layouts:
    """The motor step's layouts, built at the first :class:`Go1Physics`: the example sensor and motor state is a JAX
    computation, and none may run at import (the process sets JAX's CPU dispatch and its CPUs first, ``main``)."""
    io = physics_profiles.init_state(np.zeros(4, np.float32))  # the sensor and motor state after a reset
    io_layout = FlatLayout(io)
    return _Layouts(
        io_layout,
        FlatLayout(_DriveIn(io, COMMAND.unravel(COMMAND.zeros()), _joints(), _joints())),
        FlatLayout(_DriveOut(io, _joints(), _joints())),
        np.asarray(io_layout.ravel(io, np.float32)),
    )


def command_vector(cmd: wire.MotorCommand) -> np.ndarray:
    """A motor command as the compiled motor step takes it: the :data:`COMMAND` layout, float32."""
    return COMMAND.ravel(cmd, np.float32)


class Go1Physics:
    """One C-MuJoCo Go1 (the scenario model of ``go1_model``), stepped 1 ms at a time with motor torques.

    The single place where the simulated Go1 touches the physics: ``step`` and ``sense`` are what a shared
    C-MuJoCo backend would replace.
    """

    def __init__(
        self,
        friction: float = 0.6,
        slope_deg: float = 0.0,
        payload_kg: float = 0.0,
        physics: str = physics_profiles.ROBOT_PROFILE,
        noise_seed: int = 0,
    ):
        scenario = go1_model.make_scenarios(friction, slope_deg, payload_kg, physics, noise_seed=noise_seed)
        self.model = go1_model.scenario_model(scenario, 0)
        self.data = mujoco.MjData(self.model)
        self._substeps = physics_profiles.get(physics).physics_substeps  # physics steps per 1 ms tick
        self.ids = go1_model.indices()
        self._standing = go1_model.standing_qpos(self.model)
        gravity = jax.numpy.asarray(self.model.opt.gravity, jax.numpy.float32)
        profile = physics_profiles.arrays(physics_profiles.get(physics))._replace(  # the sensors' noise stream
            noise_seed=np.uint32(scenario.noise_seed[0])
        )
        profile = jax.tree.map(jax.numpy.asarray, profile)
        # The simulators' sensor model and the profile's foot sensor and motors, compiled ahead of time on one flat
        # float32 vector in and out (a compiled call costs per argument), each laid out by name: one definition of
        # what the robot senses and how its motors respond.
        m = self.model
        lay = self._layouts = _layouts()
        io = lay.io.unravel(lay.reset_io)
        self._sense_layout = FlatLayout(_SenseIn(io, np.zeros(m.nq), np.zeros(m.nv), np.zeros(m.nsensordata)))
        self._sense_out = FlatLayout(_SenseOut(io, REPORT.unravel(REPORT.zeros())))

        def drive(x):  # _DriveIn → _DriveOut
            d = lay.drive_in.unravel(x)
            torque = motor_torque(d.command, d.q_rad, d.dq_rad_s)
            io, applied = physics_profiles.actuate(profile, d.io, torque, d.dq_rad_s)
            return lay.drive_out.ravel(_DriveOut(io, torque, applied))

        def sense(x):  # _SenseIn → _SenseOut
            s = self._sense_layout.unravel(x)
            io, obs = sensors.measure(profile, s.io, s.qpos, s.qvel, s.sensordata, gravity)
            return self._sense_out.ravel(_SenseOut(io, _report(obs)))

        compile_for = lambda f, n: jax.jit(f).lower(np.zeros(n, np.float32)).compile()  # noqa: E731
        self._drive = compile_for(drive, lay.drive_in.size)
        self._sense = compile_for(sense, self._sense_layout.size)
        self._drive_in = lay.drive_in.zeros()
        self._drive_views = lay.drive_in.unravel(self._drive_in)
        self._sense_in = self._sense_layout.zeros()
        self._sense_views = self._sense_layout.unravel(self._sense_in)
        self.reset()

    def reset(self) -> None:
        """Standing at the origin, at rest (on the ground)."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._standing
        mujoco.mj_forward(self.model, self.data)
        self.held_root_qpos = None
        self._io = self._layouts.reset_io.copy()

    def lift(self, height_m: float) -> None:
        """Hold the trunk ``height_m`` above its standing pose, like a robot hung from a crane for calibration: from
        the next step on its root is kept there at rest, and the legs move freely in the air."""
        root = self.ids.root_qpos
        self.held_root_qpos = self.data.qpos[root : root + 7].copy()
        self.held_root_qpos[2] += height_m

    def step(self, cmd: np.ndarray, push_roll_nm: float = 0.0) -> np.ndarray:
        """Apply a motor command (:func:`command_vector`) for one 1 ms tick [and an external roll torque on the
        trunk]: the motor law (:func:`motor_torque`), then the physics profile's motors (latency, torque-speed
        envelope, velocity limit), held over the profile's physics steps of the tick. Returns the motor law's torque
        (12,) [N·m]."""
        if self.held_root_qpos is not None:
            root, dof = self.ids.root_qpos, self.ids.root_dof
            self.data.qpos[root : root + 7] = self.held_root_qpos
            self.data.qvel[dof : dof + 6] = 0.0
        x, d, into, out_of = self._drive_in, self._drive_views, self._layouts.drive_in, self._layouts.drive_out
        x[into.slices.io] = self._io
        x[into.slices.command] = cmd
        d.q_rad[:] = self.data.qpos[self.ids.joint_qpos]
        d.dq_rad_s[:] = self.data.qvel[self.ids.joint_dof]
        out = np.asarray(self._drive(x))
        self._io = out[out_of.slices.io]
        self.data.ctrl[self.ids.actuator] = out[out_of.slices.applied_torque_nm]
        self.data.xfrc_applied[self.ids.trunk_body, 3:] = (push_roll_nm, 0.0, 0.0)
        mujoco.mj_step(self.model, self.data, nstep=self._substeps)
        return out[out_of.slices.law_torque_nm].astype(np.float64)

    def sense(self) -> np.ndarray:
        """What the robot's sensors report now (the profile's sensor model: noise, the foot sensor's counting): its
        LowState's sensor fields as one float64 vector laid out by :data:`REPORT`, for :func:`robot_state`."""
        x, s, layout = self._sense_in, self._sense_views, self._sense_out
        x[self._sense_layout.slices.io] = self._io
        s.qpos[:], s.qvel[:], s.sensordata[:] = self.data.qpos, self.data.qvel, self.data.sensordata
        out = np.asarray(self._sense(x))
        self._io = out[layout.slices.io]
        return out[layout.slices.report].astype(np.float64)

    def trunk_height_m(self) -> float:
        return float(self.data.qpos[self.ids.root_qpos + 2])


def _report(obs: sensors.Observation) -> SensorReport:
    """The controller-facing sensors as the Go1 reports them (JAX, compiled into the sensor step): the IMU's
    quaternion, gyro, specific force of a robot at rest (R^T ẑ g: linear acceleration not modelled) and roll, pitch,
    yaw; the joints; the raw foot counts (offset + N / scale, rounded, int16 range)."""
    quat = obs.imu_quat_wxyz
    gravity_body = GRAVITY_MPS2 * attitude.quat_to_matrix(quat)[2]
    counts = FOOT_FORCE_OFFSET_COUNTS + jnp.round(obs.foot_force_n / FOOT_FORCE_N_PER_COUNT)
    return SensorReport(
        quat,
        obs.gyro_rad_s,
        gravity_body,
        attitude.quat_to_rpy(quat),
        obs.joint_pos_rad,
        obs.joint_vel_rad_s,
        jnp.clip(counts, -32768, 32767),
    )


def robot_state(
    sensed: np.ndarray, torque_nm: np.ndarray, tick_ms: int, *, buttons: tuple[str, ...] = ()
) -> wire.RobotState:
    """The LowState of the sensors' report (:meth:`Go1Physics.sense`, read by :data:`REPORT`'s field slices: views,
    cheaper per tick than building the pytree), tauEst = the applied torque."""
    at = REPORT.slices
    return wire.RobotState(
        tick_ms=tick_ms,
        quaternion_wxyz=sensed[at.quaternion_wxyz],
        gyro_rad_s=sensed[at.gyro_rad_s],
        accel_mps2=sensed[at.accel_mps2],
        rpy_rad=sensed[at.rpy_rad],
        motor_mode=_SERVO_MODES,
        q_rad=sensed[at.q_rad],
        dq_rad_s=sensed[at.dq_rad_s],
        tau_est_nm=torque_nm,
        motor_temperature_c=_TEMPERATURES_C,
        foot_force_raw=sensed[at.foot_force_raw].astype(np.int16),
        wireless_remote=wire.remote_with_buttons(*buttons),
    )


_SERVO_MODES = np.full(12, wire.MODE_SERVO, np.uint8)
_TEMPERATURES_C = np.full(12, MOTOR_TEMPERATURE_C)


def apply_sensor_faults(state: wire.RobotState, faults: dict) -> wire.RobotState:
    """The state as reported under the active sensor faults (buttons, power, temperature, NaN joint angle)."""
    if "buttons" in faults:
        state = state._replace(wireless_remote=wire.remote_with_buttons(*faults["buttons"]))
    if "power" in faults:  # Σ|tauEst·dq| = 12 · 20 N·m · 5 rad/s = 1200 W
        state = state._replace(tau_est_nm=np.full(12, 20.0), dq_rad_s=np.full(12, 5.0))
    if "temperature_c" in faults:
        state = state._replace(motor_temperature_c=np.full(12, int(faults["temperature_c"])))
    if "nan_q" in faults:
        state = state._replace(q_rad=np.where(np.arange(12) == 0, np.nan, state.q_rad))
    return state


class TruthLog:
    """The simulated Go1's true trunk state after each physics step, by the tick its LowState reports (the robot's
    estimate has nothing to compare with on a real robot): appended each tick into preallocated chunks, written as
    ``sim_truth.parquet`` (:meth:`save`)."""

    CHUNK = 60_000  # one minute of ticks
    COLUMNS = ("tick_ms", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz", "vx_mps", "vy_mps", "vz_mps")

    def __init__(self):
        self._chunks = [np.empty((self.CHUNK, len(self.COLUMNS)))]
        self._n = 0

    def append(self, tick_ms: int, qpos: np.ndarray, qvel: np.ndarray, ids) -> None:
        if self._n == self.CHUNK:
            self._chunks.append(np.empty((self.CHUNK, len(self.COLUMNS))))
            self._n = 0
        row = self._chunks[-1][self._n]
        row[0] = tick_ms
        row[1:8] = qpos[ids.root_qpos : ids.root_qpos + 7]
        row[8:11] = qvel[ids.root_dof : ids.root_dof + 3]
        self._n += 1

    def rows(self) -> np.ndarray:
        return np.concatenate([*self._chunks[:-1], self._chunks[-1][: self._n]])

    def save(self, path: str) -> int:
        """Write every row to ``path`` (parquet; docs/outputs.md); returns the number of rows."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        rows = self.rows()
        columns = {name: rows[:, i] for i, name in enumerate(self.COLUMNS)}
        columns["tick_ms"] = rows[:, 0].astype(np.int64)
        pq.write_table(pa.table(columns), path)
        return len(rows)


def trial_truth(truth: dict[str, np.ndarray], robot_ticks: tuple[int, int] | None, dt_s: float = TICK_S) -> dict:
    """A trial's true figures from the simulated Go1's :class:`TruthLog` columns over the robot ticks [first, last]
    of its steady phase (None: not known, every figure null): the mean trunk velocity (v_x, v_y) in the heading
    (yaw-only) frame and the forward distance Σ v_x Δt, the definitions of the trial's own figures
    (``trial.protocol``, docs/decisions.md §9)."""
    m = (
        np.zeros(len(truth["tick_ms"]), bool)
        if robot_ticks is None
        else (truth["tick_ms"] >= robot_ticks[0]) & (truth["tick_ms"] <= robot_ticks[1])
    )
    if not m.any():
        return dict(true_velocity_x_mps=None, true_velocity_y_mps=None, true_distance_m=None)
    yaw = attitude.quat_to_rpy(np.stack([truth[k][m] for k in ("qw", "qx", "qy", "qz")]))[2]  # per tick
    v_x, v_y = attitude.to_heading_frame(np.stack([truth["vx_mps"][m], truth["vy_mps"][m]]), yaw)
    return dict(
        true_velocity_x_mps=float(v_x.mean()),
        true_velocity_y_mps=float(v_y.mean()),
        true_distance_m=float(v_x.sum() * dt_s),
    )


class SimGo1Server:
    """The simulated Go1's event loop (run it in its own process: ``python -m cpgjax.robot.sim_server``)."""

    def __init__(self, port: int = 0, control_port: int = 0, pacing: str = "realtime", **scenario):
        if pacing not in ("realtime", "lockstep"):
            raise ValueError(f"pacing must be 'realtime' or 'lockstep', got {pacing!r}")
        self.pacing = pacing
        self.physics = Go1Physics(**scenario)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, port))
        self.sock.setblocking(False)
        self.ctrl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ctrl.bind((LOOPBACK, control_port))
        self.ctrl.setblocking(False)
        self.faults: list[dict] = []  # {"kind", "value", "start", "stop"} in server ticks
        self._reset_counters()
        self.running = True

    def _reset_counters(self) -> None:
        self.tick = 0
        self.client = None
        self.command = None
        self.command_time_s = 0.0  # perf_counter when the newest command arrived
        self._pending: list = []  # datagrams received since the last tick: (bytes, address)
        self.torque = np.zeros(12)
        self.stats = {
            "commands": 0,
            "bad_packets": 0,
            "states_sent": 0,
            "max_abs_tau_cmd_nm": 0.0,
            "min_kp_cmd": float("inf"),
            "max_kp_cmd": 0.0,
            "max_kd_cmd": 0.0,
            "damping_commands": 0,
        }
        self._last_state = robot_state(self.physics.sense(), self.torque, self.tick)
        self.truth = TruthLog()

    @property
    def ports(self) -> tuple[int, int]:
        return self.sock.getsockname()[1], self.ctrl.getsockname()[1]

    def active_faults(self) -> dict:
        return {f["kind"]: f["value"] for f in self.faults if f["start"] <= self.tick < f["stop"]}

    # --------------------------------------------------------------------------------------------- control port

    def _handle_control(self) -> None:
        while True:
            try:
                data, addr = self.ctrl.recvfrom(65536)
            except BlockingIOError:
                return
            request = json.loads(data)
            op = request.get("op")
            reply = {"ok": True}
            if op == "reset":
                self.physics.reset()
                self._reset_counters()
                self.faults = []
            elif op == "upright":  # what an operator does after a safety stop; the clock and the logs run on
                self.physics.reset()
            elif op == "lift":
                self.physics.lift(float(request["height_m"]))
            elif op == "fault":
                kind = request["kind"]
                if kind not in FAULT_KINDS:
                    reply = {"ok": False, "error": f"unknown fault {kind!r}; allowed {FAULT_KINDS}"}
                else:
                    start = self.tick + int(request.get("after_ticks", 0))
                    self.faults.append(
                        {
                            "kind": kind,
                            "value": request.get("value", True),
                            "start": start,
                            "stop": start + int(request.get("ticks", 10**9)),
                        }
                    )
            elif op == "stats":
                reply.update(
                    self.stats,
                    tick=self.tick,
                    trunk_height_m=self.physics.trunk_height_m(),
                    trunk_xy_m=[float(v) for v in self.physics.data.qpos[:2]],
                )
            elif op == "truth":
                reply.update(rows=self.truth.save(request["path"]))
            elif op == "quit":
                self.running = False
            else:
                reply = {"ok": False, "error": f"unknown op {op!r}"}
            self.ctrl.sendto(json.dumps(reply).encode(), addr)

    # --------------------------------------------------------------------------------------------- robot port

    def _receive_commands(self) -> None:
        """Drain the robot socket into the pending datagrams (decoded at the next tick, :meth:`_take_commands`: a
        command's arrival costs the sender's CPU no more than a receive) and note when the newest arrived."""
        while True:
            try:
                self._pending.append(self.sock.recvfrom(2048))
            except BlockingIOError:
                return
            self.command_time_s = time.perf_counter()

    def _take_commands(self) -> int:
        """Decode the pending datagrams; keep the newest valid command. Returns the number of valid commands."""
        n = 0
        for data, addr in self._pending:
            try:
                cmd = wire.decode_low_cmd(data)
            except wire.ProtocolError:
                self.stats["bad_packets"] += 1
                continue
            self.command, self.client, n = command_vector(cmd), addr, n + 1
            s = self.stats
            s["commands"] += 1
            s["max_abs_tau_cmd_nm"] = max(s["max_abs_tau_cmd_nm"], float(np.max(np.abs(cmd.tau_nm))))
            s["min_kp_cmd"] = min(s["min_kp_cmd"], float(np.min(cmd.kp_nm_rad)))
            s["max_kp_cmd"] = max(s["max_kp_cmd"], float(np.max(cmd.kp_nm_rad)))
            s["max_kd_cmd"] = max(s["max_kd_cmd"], float(np.max(cmd.kd_nm_s_rad)))
            if np.all(cmd.kp_nm_rad == 0) and np.all(cmd.tau_nm == 0) and np.all(cmd.kd_nm_s_rad > 0):
                s["damping_commands"] += 1
        self._pending.clear()
        return n

    def _tick_once(self) -> None:
        """Motor law, one physics step, and (fault permitting) one LowState to the client."""
        faults = self.active_faults()
        if "freeze_tick" not in faults:
            self.torque = self.physics.step(self.command, float(faults.get("push_roll_nm", 0.0)))
            self.tick += 1
            self.truth.append(self.tick, self.physics.data.qpos, self.physics.data.qvel, self.physics.ids)
            self._last_state = robot_state(self.physics.sense(), self.torque, self.tick)
        else:
            self.tick += 1  # the server's clock runs on, the reported state (and its tick) does not
        if "silence" in faults or "drop" in faults or self.client is None:
            return
        if "late_ms" in faults:
            time.sleep(float(faults["late_ms"]) / 1000.0)
        state = apply_sensor_faults(self._last_state, faults)
        packet = wire.encode_low_state(
            state, corrupt_crc="corrupt_crc" in faults, head=(0x00, 0x00) if "wrong_head" in faults else wire.HEAD
        )
        self.sock.sendto(packet, self.client)
        self.stats["states_sent"] += 1

    def serve_forever(self) -> None:
        """Serve until a quit request. The garbage collector is off meanwhile (a collection of the objects that the
        imports and JAX leave behind took 1.1–1.8 ms, a stale-state trip on a loaded machine; a tick makes no
        reference cycles, so nothing accumulates)."""
        gc.collect()
        gc.freeze()
        gc.disable()
        next_deadline = None
        while self.running:
            timeout = None if next_deadline is None else max(0.0, next_deadline - time.perf_counter())
            readable, _, _ = select.select([self.sock, self.ctrl], [], [], timeout)
            if self.ctrl in readable:
                self._handle_control()
            if self.sock in readable:
                self._receive_commands()
            if self.pacing == "lockstep":  # one step per command, at once
                for _ in range(self._take_commands()):
                    self._tick_once()
                continue
            if self.command is None:  # frozen until the first valid command, which starts the clock
                self._take_commands()
                if self.command is None:
                    next_deadline = None
                    continue
            now = time.perf_counter()
            if next_deadline is None:
                next_deadline = now
            if now >= next_deadline:
                self._take_commands()
                self._tick_once()
                # Absolute deadlines, their phase locked to the commands'; after a stall the clock skips the missed
                # periods (no burst of catch-up steps).
                next_deadline += TICK_S + phase_correction(self.command_time_s, next_deadline + TICK_S)
                late_s = time.perf_counter() - next_deadline
                if late_s > 0.0:
                    next_deadline += (late_s // TICK_S + 1) * TICK_S
        self.sock.close()
        self.ctrl.close()


# The real-time clock's phase lock: each tick moves the next deadline a fraction of the way towards this long after
# the newest command's arrival (modulo the period), at most PHASE_STEP_MAX_S per tick. Locked, the simulated Go1
# ticks just after each command: sharing a CPU with the loop, its tick falls in the loop's idle time instead of
# preempting it, and the state reaches the loop before its next tick (as a robot whose boards are synchronised to
# the controller, like EtherCAT's distributed clocks). The rate stays 1 kHz: without commands the phase stays put.
PHASE_AFTER_COMMAND_S = 100e-6
PHASE_GAIN = 0.1
PHASE_STEP_MAX_S = 20e-6


def phase_correction(command_time_s: float, deadline_s: float) -> float:
    """The shift [s] of the deadline ``deadline_s`` towards the phase PHASE_AFTER_COMMAND_S after a command that
    arrived at ``command_time_s`` (same clock), bounded by PHASE_STEP_MAX_S."""
    error = (command_time_s + PHASE_AFTER_COMMAND_S - deadline_s + TICK_S / 2) % TICK_S - TICK_S / 2
    return min(max(PHASE_GAIN * error, -PHASE_STEP_MAX_S), PHASE_STEP_MAX_S)


class SimGo1Client:
    """Start the simulated Go1 in a child process and talk to its control port.

    >>> from cpgjax.robot import transport
    >>> with SimGo1Client(pacing="lockstep") as sim:
    ...     go1 = transport.LockstepTransport(sim.address)
    ...     sim.inject("corrupt_crc", ticks=5)
    """

    def __init__(
        self,
        pacing: str = "realtime",
        friction: float = 0.6,
        slope_deg: float = 0.0,
        payload_kg: float = 0.0,
        realtime_priority: int | None = None,
        cpus: set[int] | None = None,
        startup_timeout_s: float = 60.0,
        physics: str = physics_profiles.ROBOT_PROFILE,
        noise_seed: int = 0,
    ):
        physics_profiles.get(physics)  # an unknown name fails here, not in the child process
        cmd = [
            sys.executable,
            "-m",
            "cpgjax.robot.sim_server",
            "--pacing",
            pacing,
            "--friction",
            str(friction),
            "--slope-deg",
            str(slope_deg),
            "--payload-kg",
            str(payload_kg),
            "--physics",
            physics,
            "--noise-seed",
            str(noise_seed),
        ]
        if realtime_priority is not None:
            cmd += ["--realtime-priority", str(realtime_priority)]
        if cpus:
            cmd += ["--cpus", ",".join(str(c) for c in sorted(cpus))]
        env = dict(os.environ, JAX_PLATFORMS="cpu")
        self.process = subprocess.Popen(cmd, stdout=subprocess.PIPE, env=env, text=True)
        line, give_up = "", time.monotonic() + startup_timeout_s
        while not line.startswith("READY"):  # skip whatever the imports print
            ready, _, _ = select.select([self.process.stdout], [], [], max(0.0, give_up - time.monotonic()))
            line = self.process.stdout.readline() if ready else ""
            if not ready or (not line and self.process.poll() is not None):
                self.process.kill()
                raise RuntimeError("the simulated Go1 did not start")
        _, port, control_port = line.split()
        self.port, self.control_port = int(port), int(control_port)
        self._ctrl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._ctrl.settimeout(5.0)

    @property
    def address(self) -> tuple[str, int]:
        return LOOPBACK, self.port

    def request(self, op: str, **fields) -> dict:
        self._ctrl.sendto(json.dumps({"op": op, **fields}).encode(), (LOOPBACK, self.control_port))
        reply = json.loads(self._ctrl.recv(65536))
        if not reply.get("ok"):
            raise RuntimeError(f"simulated Go1 refused {op}: {reply.get('error')}")
        return reply

    def inject(self, kind: str, value=True, *, after_ticks: int = 0, ticks: int = 10**9) -> None:
        """Activate a fault (see FAULT_KINDS) for ``ticks`` server ticks, starting ``after_ticks`` from now."""
        self.request("fault", kind=kind, value=value, after_ticks=after_ticks, ticks=ticks)

    def reset(self) -> None:
        """Robot standing on the ground again, frozen until the next command; faults cleared; counters zeroed."""
        self.request("reset")

    def upright(self) -> None:
        """Put the robot back on its feet at the origin, at rest, as an operator does after a safety stop: unlike
        :meth:`reset`, the clock, the faults, the counters and the true-state log run on."""
        self.request("upright")

    def lift(self, height_m: float = 0.3) -> None:
        """Hang the robot ``height_m`` above where it stands (feet in the air) until the next reset."""
        self.request("lift", height_m=height_m)

    def stats(self) -> dict:
        return self.request("stats")

    def save_truth(self, path) -> int:
        """Write the true trunk state of every tick since the start (or the last reset) to ``path`` (parquet,
        :class:`TruthLog`); returns the number of ticks."""
        return int(self.request("truth", path=str(path))["rows"])

    def close(self) -> None:
        if self.process.poll() is None:
            try:
                self.request("quit")
                self.process.wait(timeout=5.0)
            except (OSError, RuntimeError, subprocess.TimeoutExpired, json.JSONDecodeError):
                self.process.kill()
                self.process.wait()
        self._ctrl.close()
        self.process.stdout.close()

    def __enter__(self) -> SimGo1Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, default=0, help="robot UDP port on 127.0.0.1 (0: ephemeral)")
    parser.add_argument("--control-port", type=int, default=0, help="control UDP port on 127.0.0.1 (0: ephemeral)")
    parser.add_argument("--pacing", choices=("realtime", "lockstep"), default="realtime")
    parser.add_argument("--friction", type=float, default=0.6)
    parser.add_argument("--slope-deg", type=float, default=0.0)
    parser.add_argument("--payload-kg", type=float, default=0.0)
    parser.add_argument(
        "--physics",
        choices=tuple(physics_profiles.PROFILES),
        default=physics_profiles.ROBOT_PROFILE,
        help="physics profile (docs/physics.md)",
    )
    parser.add_argument("--noise-seed", type=int, default=0, help="the sensors' noise stream")
    parser.add_argument(
        "--realtime-priority",
        type=int,
        help="SCHED_FIFO priority for the physics loop, when permitted (a robot is not starved "
        "by other processes; on a shared machine its simulation can be)",
    )
    parser.add_argument("--cpus", help="comma-separated CPUs to run on, when permitted (keep it off the loop's CPU)")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C meant for the loop: it stops, then closes this process
    if args.cpus:
        try:
            os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",")})  # before JAX starts its threads
        except OSError as e:
            print(f"CPU affinity not permitted ({e})", file=sys.stderr)
    if args.realtime_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime_priority))
        except OSError as e:
            print(f"real-time priority not permitted ({e})", file=sys.stderr)
    cpu_dispatch.request_inline()
    server = SimGo1Server(
        args.port,
        args.control_port,
        args.pacing,
        friction=args.friction,
        slope_deg=args.slope_deg,
        payload_kg=args.payload_kg,
        physics=args.physics,
        noise_seed=args.noise_seed,
    )
    note = memory_lock.lock()  # a robot's motor boards never wait on a disk; nor may their stand-in
    if note != memory_lock.LOCKED:
        print(note, file=sys.stderr)
    print("READY", *server.ports, flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
