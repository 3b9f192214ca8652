"""The Go1's low-level UDP wire format (unitree_legged_sdk 3.8.x): LowCmd (614 B) and LowState (807 B).

Pure NumPy: each datagram is one record of a packed little-endian structured dtype whose field offsets are the
SDK's wire layout (docs/go1-sdk.md §1.3, verified against the SDK wheel), and the CRC is the SDK's word-wise CRC-32
(§1.4). Values are carried in SI units in :class:`MotorCommand` / :class:`RobotState`; the fixed-point encodings
(tau 1/256 N·m, Kp 1/32, Kd 1/16, tauEst /256) happen only here.

The SDK *silently wraps* out-of-range tau, Kp and Kd (200 N·m is sent as −56 N·m; Kp = −1 as ≈2047).
:func:`encode_low_cmd` therefore refuses any value the encoding cannot represent (and any non-finite value)
with :class:`ProtocolError`; callers clamp and check before encoding (``cpgjax.robot.safety.guard_command``).
"""

from __future__ import annotations

import zlib
from typing import NamedTuple

import numpy as np

LOW_CMD_LENGTH = 614  # bytes on the wire (the 734-byte C struct, compressed by the SDK)
LOW_STATE_LENGTH = 807  # bytes on the wire (the 937-byte C struct)
HEAD = (0xFE, 0xEF)
LEVEL_LOW = 0xFF  # levelFlag of low-level packets; 0xEE (high level) is rejected
NUM_MOTORS = 20  # motor slots in a packet; the legs use 0..11
NUM_LEG_MOTORS = 12

POS_STOP_F = 2.146e9  # q = PosStopF disables the motor's position term ("stop position control")
VEL_STOP_F = 16000.0  # dq = VelStopF disables the velocity term
MODE_SERVO = 0x0A
MODE_DAMPING = 0x00

# Representable ranges of the fixed-point fields (half-open: trunc(x · scale) must fit the integer type).
TAU_SCALE = 256.0  # int16 → [−128, 128) N·m
KP_SCALE = 32.0  # uint16 → [0, 2048) N·m/rad
KD_SCALE = 16.0  # uint16 → [0, 4096) N·m·s/rad
TAU_EST_SCALE = 256.0  # LowState tauEst, int16 / 256 → N·m
TAU_RANGE_NM = (-128.0, 128.0)
KP_RANGE = (0.0, 2048.0)
KD_RANGE = (0.0, 4096.0)

# wirelessRemote (40 B, joystick.h xRockerBtnDataStruct): btn u16 at byte 2, little-endian.
REMOTE_BUTTON_BITS = {
    "R1": 0x0001,
    "L1": 0x0002,
    "start": 0x0004,
    "select": 0x0008,
    "R2": 0x0010,
    "L2": 0x0020,
    "F1": 0x0040,
    "F2": 0x0080,
    "A": 0x0100,
    "B": 0x0200,
    "X": 0x0400,
    "Y": 0x0800,
    "up": 0x1000,
    "right": 0x2000,
    "down": 0x4000,
    "left": 0x8000,
}

_MOTOR_CMD_WIRE = np.dtype(
    [("mode", "u1"), ("q", "<f4"), ("dq", "<f4"), ("tau", "<i2"), ("kp", "<u2"), ("kd", "<u2"), ("reserve", "<u4", 3)]
)  # 27 B
_MOTOR_STATE_WIRE = np.dtype(
    [
        ("mode", "u1"),
        ("q", "<f4"),
        ("dq", "<f4"),
        ("ddq", "<i2"),
        ("tau_est", "<i2"),
        ("q_raw", "<f4"),
        ("dq_raw", "<f4"),
        ("ddq_raw", "<i2"),
        ("temperature", "i1"),
        ("reserve", "<u4", 2),
    ]
)  # 32 B
_IMU_WIRE = np.dtype(
    [
        ("quaternion", "<f4", 4),
        ("gyroscope", "<f4", 3),
        ("accelerometer", "<f4", 3),
        ("rpy", "<f4", 3),
        ("temperature", "i1"),
    ]
)  # 53 B
_BMS_STATE_WIRE = np.dtype(
    [
        ("version_h", "u1"),
        ("version_l", "u1"),
        ("bms_status", "u1"),
        ("soc", "u1"),
        ("current", "<i4"),
        ("cycle", "<u2"),
        ("bq_ntc", "i1", 2),
        ("mcu_ntc", "i1", 2),
        ("cell_vol", "u1", 10),
    ]
)  # 24 B; cell_vol × 32 → mV
_HEADER = [
    ("head", "u1", 2),
    ("level_flag", "u1"),
    ("frame_reserve", "u1"),
    ("sn", "<u4", 2),
    ("version", "<u4", 2),
    ("bandwidth", "<u2"),
]  # 22 B

LOW_CMD_DTYPE = np.dtype(
    _HEADER
    + [
        ("motor", _MOTOR_CMD_WIRE, NUM_MOTORS),
        ("bms", "u1", 4),
        ("wireless_remote", "u1", 40),
        ("reserve", "<u4"),
        ("crc", "<u4"),
    ]
)
LOW_STATE_DTYPE = np.dtype(
    _HEADER
    + [
        ("imu", _IMU_WIRE),
        ("motor", _MOTOR_STATE_WIRE, NUM_MOTORS),
        ("bms", _BMS_STATE_WIRE),
        ("foot_force", "<i2", 4),
        ("foot_force_est", "<i2", 4),
        ("tick", "<u4"),
        ("wireless_remote", "u1", 40),
        ("reserve", "<u4"),
        ("crc", "<u4"),
    ]
)
assert LOW_CMD_DTYPE.itemsize == LOW_CMD_LENGTH and LOW_STATE_DTYPE.itemsize == LOW_STATE_LENGTH
assert LOW_CMD_DTYPE.fields["motor"][1] == 22 and LOW_CMD_DTYPE.fields["crc"][1] == 610
assert LOW_STATE_DTYPE.fields["motor"][1] == 75 and LOW_STATE_DTYPE.fields["foot_force"][1] == 739
assert LOW_STATE_DTYPE.fields["tick"][1] == 755 and LOW_STATE_DTYPE.fields["crc"][1] == 803


class ProtocolError(ValueError):
    """A datagram that is not a valid packet (size, head, level flag, CRC), or a command the wire cannot carry."""


class MotorCommand(NamedTuple):
    """One LowCmd in SI units, motor order FR, FL, RR, RL × (hip, thigh, calf); each field (12,) (slots 12..19 are
    sent as the SDK's InitCmdData leaves them: servo mode, PosStopF, VelStopF, zero gains).

    The motor applies τ = tau + kp (q − q_meas) + kd (dq − dq_meas) at ~10 kHz; q = POS_STOP_F disables the position
    term and dq = VEL_STOP_F the velocity term (docs/go1-sdk.md §1.8).
    """

    mode: np.ndarray  # uint8: MODE_SERVO or MODE_DAMPING
    q_rad: np.ndarray
    dq_rad_s: np.ndarray
    tau_nm: np.ndarray
    kp_nm_rad: np.ndarray
    kd_nm_s_rad: np.ndarray


class RobotState(NamedTuple):
    """One LowState in SI units (leg motors only), plus the raw sensor fields the robot reports without units."""

    tick_ms: int  # the robot's millisecond counter (u32)
    quaternion_wxyz: np.ndarray  # (4,)
    gyro_rad_s: np.ndarray  # (3,)
    accel_mps2: np.ndarray  # (3,)
    rpy_rad: np.ndarray  # (3,) as reported by the IMU
    motor_mode: np.ndarray  # (12,) uint8
    q_rad: np.ndarray  # (12,)
    dq_rad_s: np.ndarray  # (12,)
    tau_est_nm: np.ndarray  # (12,)
    motor_temperature_c: np.ndarray  # (12,) int
    foot_force_raw: np.ndarray  # (4,) int16 "foot airbag sensor" counts (convert with a calibration)
    wireless_remote: bytes  # 40 B


_BIT_REVERSED_BYTE = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def crc32_words(data: bytes) -> int:
    """The SDK's CRC over ``data`` (length a multiple of 4): MSB-first CRC-32, polynomial 0x04C11DB7, init
    0xFFFFFFFF, no reflection, no final XOR, fed little-endian uint32 words MSB first (docs/go1-sdk.md §1.4).

    Computed with zlib's (reflected) CRC-32: feeding each word MSB first equals feeding the word's 32 bits reversed
    LSB first, and a non-reflected CRC is the bit-reversal of the reflected CRC of the bit-reversed input
    (a few µs per packet, versus ≈85 µs for a table loop in Python).
    """
    swapped = np.frombuffer(data, "<u4").byteswap().tobytes()  # bytes of each word in MSB-first order
    reflected = zlib.crc32(swapped.translate(_BIT_REVERSED_BYTE)) ^ 0xFFFFFFFF
    return int(f"{reflected:032b}"[::-1], 2)


def packet_crc(packet: bytes) -> int:
    """The CRC a packet must carry: over its first (len // 4 − 1) words (bytes [0, 608) of LowCmd, [0, 800) of
    LowState)."""
    return crc32_words(packet[: (len(packet) // 4 - 1) * 4])


def _finish(record: np.ndarray) -> bytes:
    record["crc"] = 0
    raw = record.tobytes()
    record["crc"] = packet_crc(raw)
    return record.tobytes()


def packet_error(data: bytes, length: int) -> str | None:
    """Why a datagram is not a valid packet of ``length`` bytes (size, head, level flag, CRC), or None."""
    if len(data) != length:
        return f"size: datagram of {len(data)} bytes, expected {length}"
    if data[0] != HEAD[0] or data[1] != HEAD[1]:
        return f"head: {bytes(data[:2]).hex()}, expected feef"
    if data[2] != LEVEL_LOW:
        return f"level: flag 0x{data[2]:02x}, expected 0x{LEVEL_LOW:02x}"
    stored, crc = int.from_bytes(data[-4:], "little"), packet_crc(data)
    if stored != crc:
        return f"crc: packet 0x{stored:08x}, computed 0x{crc:08x}"
    return None


def _parse(data: bytes, dtype: np.dtype) -> np.ndarray:
    error = packet_error(data, dtype.itemsize)
    if error is not None:
        raise ProtocolError(error)
    return np.frombuffer(data, dtype)[0]


_GAIN_FIELDS = ("tau_nm", "kp_nm_rad", "kd_nm_s_rad")
_FIXED_POINT_LOW = np.repeat([TAU_RANGE_NM[0], KP_RANGE[0], KD_RANGE[0]], NUM_LEG_MOTORS)
_FIXED_POINT_HIGH = np.repeat([TAU_RANGE_NM[1], KP_RANGE[1], KD_RANGE[1]], NUM_LEG_MOTORS)


def check_encodable(cmd: MotorCommand) -> None:
    """Raise ProtocolError if the command has a non-finite field or a tau/Kp/Kd the wire would wrap."""
    fixed = np.concatenate((cmd.tau_nm, cmd.kp_nm_rad, cmd.kd_nm_s_rad))
    if not ((_FIXED_POINT_LOW <= fixed) & (fixed < _FIXED_POINT_HIGH)).all():  # NaN fails both comparisons
        bad = _GAIN_FIELDS[int(np.argmin((_FIXED_POINT_LOW <= fixed) & (fixed < _FIXED_POINT_HIGH))) // NUM_LEG_MOTORS]
        i = _GAIN_FIELDS.index(bad)
        raise ProtocolError(
            f"{bad} = {getattr(cmd, bad)} is not encodable; allowed finite values in "
            f"[{_FIXED_POINT_LOW[i * NUM_LEG_MOTORS]}, {_FIXED_POINT_HIGH[i * NUM_LEG_MOTORS]})"
        )
    if not np.isfinite(np.concatenate((cmd.q_rad, cmd.dq_rad_s))).all():
        raise ProtocolError(f"q/dq not finite: {cmd.q_rad}, {cmd.dq_rad_s}")


def _low_cmd_template() -> bytes:
    # What the SDK's InitCmdData writes: head, level flag, and every motor slot in servo mode with the position and
    # velocity terms stopped and zero gains (so the unused slots 12..19 match the SDK byte for byte).
    record = np.zeros((), LOW_CMD_DTYPE)
    record["head"] = HEAD
    record["level_flag"] = LEVEL_LOW
    motors = record["motor"]
    motors["mode"] = MODE_SERVO
    motors["q"] = POS_STOP_F
    motors["dq"] = VEL_STOP_F
    record["motor"] = motors
    return record.tobytes()


_LOW_CMD_TEMPLATE = _low_cmd_template()
_MOTOR_CMD_START = LOW_CMD_DTYPE.fields["motor"][1]
_LEG_MOTORS_END = _MOTOR_CMD_START + NUM_LEG_MOTORS * _MOTOR_CMD_WIRE.itemsize
_WIRELESS_START = LOW_CMD_DTYPE.fields["wireless_remote"][1]
_CMD_CRC_START = LOW_CMD_DTYPE.fields["crc"][1]


def encode_low_cmd(cmd: MotorCommand, wireless_remote: bytes = bytes(40)) -> bytes:
    """The 614-byte LowCmd datagram for ``cmd`` (head FE EF, level 0xFF, CRC), truncating toward zero like the SDK.

    Raises:
      ProtocolError: a value the encoding cannot represent (see :func:`check_encodable`).
    """
    check_encodable(cmd)
    motors = np.zeros(NUM_LEG_MOTORS, _MOTOR_CMD_WIRE)
    motors["mode"] = cmd.mode
    motors["q"] = cmd.q_rad
    motors["dq"] = cmd.dq_rad_s
    motors["tau"] = np.trunc(cmd.tau_nm * TAU_SCALE)
    motors["kp"] = np.trunc(cmd.kp_nm_rad * KP_SCALE)
    motors["kd"] = np.trunc(cmd.kd_nm_s_rad * KD_SCALE)
    packet = bytearray(_LOW_CMD_TEMPLATE)
    packet[_MOTOR_CMD_START:_LEG_MOTORS_END] = motors.tobytes()
    packet[_WIRELESS_START : _WIRELESS_START + 40] = wireless_remote
    packet[_CMD_CRC_START:] = packet_crc(packet).to_bytes(4, "little")
    return bytes(packet)


def decode_low_cmd(data: bytes) -> MotorCommand:
    """The leg motors' command carried by a LowCmd datagram, in SI units (fixed-point fields decoded).

    Raises:
      ProtocolError: wrong size, head, level flag or CRC.
    """
    m = _parse(data, LOW_CMD_DTYPE)["motor"][:NUM_LEG_MOTORS]
    return MotorCommand(
        mode=m["mode"].copy(),
        q_rad=m["q"].astype(np.float64),
        dq_rad_s=m["dq"].astype(np.float64),
        tau_nm=m["tau"] / TAU_SCALE,
        kp_nm_rad=m["kp"] / KP_SCALE,
        kd_nm_s_rad=m["kd"] / KD_SCALE,
    )


def encode_low_state(state: RobotState, *, corrupt_crc: bool = False, head: tuple[int, int] = HEAD) -> bytes:
    """The 807-byte LowState datagram for ``state`` (tauEst as int16 of round(τ·256)). ``corrupt_crc`` and ``head``
    exist for fault injection by the simulated Go1."""
    record = np.zeros((), LOW_STATE_DTYPE)
    record["head"] = head
    record["level_flag"] = LEVEL_LOW
    imu = record["imu"]
    imu["quaternion"] = state.quaternion_wxyz
    imu["gyroscope"] = state.gyro_rad_s
    imu["accelerometer"] = state.accel_mps2
    imu["rpy"] = state.rpy_rad
    record["imu"] = imu
    motors = record["motor"][:NUM_LEG_MOTORS]
    motors["mode"] = state.motor_mode
    motors["q"] = motors["q_raw"] = state.q_rad
    motors["dq"] = motors["dq_raw"] = state.dq_rad_s
    motors["tau_est"] = np.clip(np.round(np.asarray(state.tau_est_nm) * TAU_EST_SCALE), -32768, 32767)
    motors["temperature"] = state.motor_temperature_c
    record["motor"][:NUM_LEG_MOTORS] = motors
    record["foot_force"] = state.foot_force_raw
    record["tick"] = state.tick_ms & 0xFFFFFFFF
    record["wireless_remote"] = np.frombuffer(state.wireless_remote, np.uint8)
    packet = _finish(record)
    if corrupt_crc:
        packet = packet[:-4] + bytes(b ^ 0xFF for b in packet[-4:])
    return packet


def decode_low_state(data: bytes) -> RobotState:
    """A LowState datagram in SI units (leg motors only).

    Raises:
      ProtocolError: wrong size, head, level flag or CRC.
    """
    r = _parse(data, LOW_STATE_DTYPE)
    m = r["motor"][:NUM_LEG_MOTORS]
    imu = r["imu"]
    return RobotState(
        tick_ms=int(r["tick"]),
        quaternion_wxyz=imu["quaternion"].astype(np.float64),
        gyro_rad_s=imu["gyroscope"].astype(np.float64),
        accel_mps2=imu["accelerometer"].astype(np.float64),
        rpy_rad=imu["rpy"].astype(np.float64),
        motor_mode=m["mode"].copy(),
        q_rad=m["q"].astype(np.float64),
        dq_rad_s=m["dq"].astype(np.float64),
        tau_est_nm=m["tau_est"] / TAU_EST_SCALE,
        motor_temperature_c=m["temperature"].astype(np.int64),
        foot_force_raw=r["foot_force"].astype(np.int64),
        wireless_remote=r["wireless_remote"].tobytes(),
    )


def remote_buttons(wireless_remote: bytes) -> int:
    """The 16 button bits of a wirelessRemote block (see REMOTE_BUTTON_BITS)."""
    return int.from_bytes(wireless_remote[2:4], "little")


def remote_with_buttons(*names: str) -> bytes:
    """A 40-byte wirelessRemote block with the named buttons pressed (sticks centred)."""
    bits = 0
    for name in names:
        bits |= REMOTE_BUTTON_BITS[name]
    return bytes(2) + bits.to_bytes(2, "little") + bytes(36)
