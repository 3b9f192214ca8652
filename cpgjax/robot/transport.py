"""Transports of the Go1's low-level packets: :class:`UdpTransport` (cpgjax's own implementation of the SDK's
low-level UDP protocol, used for the loopback simulated Go1 and usable on the robot; :class:`LockstepTransport`
waits for a lockstep simulated Go1's answers) and :class:`SdkTransport` (the official ``unitree_legged_sdk`` Python
binding, optional extra ``go1``). Both move
:class:`~cpgjax.robot.wire.RobotState` in and :class:`~cpgjax.robot.wire.MotorCommand` out
(docs/go1-sdk.md §1.5–1.7).

The robot's real address appears only as the default of :data:`GO1_ROBOT_IP`; tests and examples use 127.0.0.1.
"""

from __future__ import annotations

import select
import socket
from typing import Protocol

import numpy as np

from cpgjax.robot import wire

GO1_ROBOT_IP = "192.168.123.10"  # the SDK's low-level target (UDP_SERVER_IP_BASIC); used only with --robot go1
GO1_ROBOT_PORT = 8007  # UDP_SERVER_PORT
GO1_LOCAL_PORT = 8090  # local port of the SDK's C++ examples


class Transport(Protocol):
    """Moves one robot's low-level packets. ``receive`` never blocks."""

    power_tripped: bool  # the transport's own power protection (the SDK's Safety) has cut the motors

    def receive(self) -> wire.RobotState | None:
        """The newest valid state received since the last call, or None."""

    def send(self, cmd: wire.MotorCommand, state: wire.RobotState | None) -> None:
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

    def receive(self) -> wire.RobotState | None:
        packets = []
        while True:
            try:
                packets.append(self.sock.recv(2048))
            except (BlockingIOError, ConnectionRefusedError):
                break
        newest = None
        for data in reversed(packets):  # newest first; each datagram's checks (CRC included) run once
            if newest is None:
                try:
                    newest = wire.decode_low_state(data)
                    continue
                except wire.ProtocolError as e:
                    error = str(e)
            else:
                error = wire.packet_error(data, wire.LOW_STATE_LENGTH)
            if error is not None:
                self.rejected[error.split(":")[0]] += 1
        return newest

    def send(self, cmd: wire.MotorCommand, state: wire.RobotState | None) -> None:
        try:
            self.sock.send(wire.encode_low_cmd(cmd))
        except ConnectionRefusedError:  # nobody listening yet (ICMP port unreachable); the watchdog handles it
            pass

    def close(self) -> None:
        self.sock.close()


class LockstepTransport(UdpTransport):
    """:class:`UdpTransport` for a simulated Go1 in lockstep pacing (one physics step per command): ``receive`` first
    waits, up to ``timeout_s``, for a datagram after each command, so the loop, its observations and the physics
    advance together however loaded the machine is. Not real time: never use it with a robot.

    Without the wait, a simulated Go1 starved of CPU answers late and in bursts, the loop runs on stale observations
    while the physics still steps once per command, and the walk can go unstable for reasons that are the machine's,
    not the loop's. Faults that withhold answers (drop, silence) cost one timeout per tick.
    """

    def __init__(self, robot_address: tuple[str, int], local_port: int = 0, timeout_s: float = 0.1):
        super().__init__(robot_address, local_port)
        self.timeout_s = timeout_s
        self._answer_due = False

    def receive(self) -> wire.RobotState | None:
        if self._answer_due:
            select.select([self.sock], [], [], self.timeout_s)
        return super().receive()

    def send(self, cmd: wire.MotorCommand, state: wire.RobotState | None) -> None:
        super().send(cmd, state)
        self._answer_due = True


class SdkTransport:
    """The robot through Unitree's ``unitree_legged_sdk`` 3.8 Python binding (``pip install --no-deps
    unitree-legged-sdk``; see docs/hardware.md). Non-blocking mode only (the binding holds the GIL).

    ``power_level`` (1…10) additionally runs the SDK's own ``Safety.PowerProtect`` on every command; its latched
    trip sets ``power_tripped`` (the SDK then sends the motors to mode 0).
    """

    power_tripped = False

    def __init__(
        self,
        robot_ip: str = GO1_ROBOT_IP,
        robot_port: int = GO1_ROBOT_PORT,
        local_port: int = GO1_LOCAL_PORT,
        power_level: int | None = None,
    ):
        from unitree_legged_sdk import robot_interface as sdk  # optional extra "go1"

        _check_port_free(local_port)
        self.udp = sdk.UDP(wire.LEVEL_LOW, local_port, robot_ip, robot_port)
        self.cmd = sdk.LowCmd()
        self.state = sdk.LowState()
        self.udp.InitCmdData(self.cmd)
        self._motors = self.cmd.motorCmd  # a cached list of references into the C++ struct (docs/go1-sdk.md §1.7)
        self.safety = sdk.Safety(sdk.LeggedType.Go1) if power_level else None
        self.power_level = power_level

    def receive(self) -> wire.RobotState | None:
        if self.udp.Recv() != 0:
            return None
        self.udp.GetRecv(self.state)
        s, ms = self.state, self.state.motorState
        imu = s.imu
        return wire.RobotState(
            tick_ms=s.tick,
            quaternion_wxyz=np.array(imu.quaternion),
            gyro_rad_s=np.array(imu.gyroscope),
            accel_mps2=np.array(imu.accelerometer),
            rpy_rad=np.array(imu.rpy),
            motor_mode=np.array([ms[i].mode for i in range(12)], np.uint8),
            q_rad=np.array([ms[i].q for i in range(12)]),
            dq_rad_s=np.array([ms[i].dq for i in range(12)]),
            tau_est_nm=np.array([ms[i].tauEst for i in range(12)]),
            motor_temperature_c=np.array([ms[i].temperature for i in range(12)]),
            foot_force_raw=np.array(s.footForce),
            wireless_remote=bytes(s.wirelessRemote),
        )

    def send(self, cmd: wire.MotorCommand, state: wire.RobotState | None) -> None:
        for i, m in enumerate(self._motors[:12]):
            m.mode, m.q, m.dq = int(cmd.mode[i]), float(cmd.q_rad[i]), float(cmd.dq_rad_s[i])
            m.tau, m.Kp, m.Kd = float(cmd.tau_nm[i]), float(cmd.kp_nm_rad[i]), float(cmd.kd_nm_s_rad[i])
        if self.safety is not None and self.safety.PowerProtect(self.cmd, self.state, self.power_level) < 0:
            self.power_tripped = True
        self.udp.SetSend(self.cmd)
        self.udp.Send()

    def close(self) -> None:
        del self.udp
