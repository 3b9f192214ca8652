"""The deployment's safety layer, as pure functions: trip conditions on robot states (tilt, stop buttons, motor
temperature, the SDK's power-protection rule), the commands of each loop phase (torque, motor PD, damping), and the
guard that clamps and checks every command *before* it is encoded (the SDK silently wraps out-of-range torque and
gains, docs/go1-sdk.md §1.3).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cpgjax.go1 import attitude
from cpgjax.go1.constants import JOINT_LOWER_RAD, JOINT_UPPER_RAD, TILT_STOP_RAD, TORQUE_LIMIT_NM
from cpgjax.robot import wire


class SafetyConfig(NamedTuple):
    """Limits of the safety layer. Each trip latches damping and is logged with its reason."""

    max_tilt_rad: float = TILT_STOP_RAD  # |roll| or |pitch| (from the IMU quaternion) beyond this → damping
    watchdog_ticks: int = 5  # this many consecutive ticks without a new robot tick → damping
    stop_buttons: tuple[str, ...] = ("L2", "B")  # all pressed on the remote → damping (Unitree's damping combo)
    max_motor_temperature_c: int = 70
    # The SDK's PowerProtect rule (docs/go1-sdk.md §1.10): Σ|tauEst·dq| over the 12 legs motors above 100 W × level
    # counts up, below counts down; the trip fires at power_trip_count and latches.
    power_level: int = 9
    power_trip_count: int = 6
    kp_max_nm_rad: float = 100.0
    kd_max_nm_s_rad: float = 10.0


POWER_LEVELS = range(1, 11)  # the SDK's PowerProtect levels: a limit of 100 W per level
MAX_TILT_RAD = 1.2  # beyond ~70° the robot is on its side: a stop there protects nothing
MAX_MOTOR_TEMPERATURE_C = 90  # the motors' own protection is near 90 °C


def check_safety(safety: SafetyConfig) -> SafetyConfig:
    """``safety`` if every limit is in its allowed range; to call before anything is sent to a robot.

    Raises:
      ValueError: the message names the limit, its value and the allowed range.
    """

    def need(ok: bool, name: str, allowed: str) -> None:
        if not ok:
            raise ValueError(f"safety {name} = {getattr(safety, name)!r} is outside the allowed range {allowed}")

    def number(name: str) -> float:
        value = getattr(safety, name)
        return float(value) if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) else np.nan

    level = safety.power_level
    need(
        isinstance(level, (int, np.integer)) and not isinstance(level, bool) and level in POWER_LEVELS,
        "power_level",
        f"{POWER_LEVELS.start} … {POWER_LEVELS.stop - 1} (100 W each)",
    )
    need(0.0 < number("max_tilt_rad") <= MAX_TILT_RAD, "max_tilt_rad", f"(0, {MAX_TILT_RAD}] rad")
    need(
        isinstance(safety.watchdog_ticks, int) and 1 <= safety.watchdog_ticks <= 100, "watchdog_ticks", "1 … 100 ticks"
    )
    need(
        0 < number("max_motor_temperature_c") <= MAX_MOTOR_TEMPERATURE_C,
        "max_motor_temperature_c",
        f"(0, {MAX_MOTOR_TEMPERATURE_C}] °C",
    )
    need(isinstance(safety.power_trip_count, int) and safety.power_trip_count >= 1, "power_trip_count", "integers >= 1")
    need(0.0 <= number("kp_max_nm_rad") <= wire.KP_RANGE[1], "kp_max_nm_rad", f"[0, {wire.KP_RANGE[1]}] N·m/rad")
    need(0.0 <= number("kd_max_nm_s_rad") <= wire.KD_RANGE[1], "kd_max_nm_s_rad", f"[0, {wire.KD_RANGE[1]}] N·m·s/rad")
    unknown = [b for b in safety.stop_buttons if b not in wire.REMOTE_BUTTON_BITS]
    need(not unknown, "stop_buttons", f"names of {tuple(wire.REMOTE_BUTTON_BITS)}")
    return safety


def tilt_rad(quaternion_wxyz: np.ndarray) -> tuple[float, float]:
    """(roll, pitch) [rad] of a unit quaternion (``attitude.quat_to_rpy``)."""
    roll, pitch, _ = attitude.quat_to_rpy(tuple(float(v) for v in quaternion_wxyz))
    return roll, pitch


def state_trip_reason(state: wire.RobotState, safety: SafetyConfig, stop_mask: int) -> str | None:
    """The reason a fresh robot state must stop the robot (tilt, stop buttons, motor temperature), or None."""
    roll, pitch = tilt_rad(state.quaternion_wxyz)
    if not (abs(roll) <= safety.max_tilt_rad and abs(pitch) <= safety.max_tilt_rad):
        return f"tilt: roll {roll:+.3f} rad, pitch {pitch:+.3f} rad beyond ±{safety.max_tilt_rad} rad"
    if stop_mask and wire.remote_buttons(state.wireless_remote) & stop_mask == stop_mask:
        return f"remote stop buttons {'+'.join(safety.stop_buttons)} pressed"
    hottest = int(np.max(state.motor_temperature_c))
    if hottest >= safety.max_motor_temperature_c:
        motor = int(np.argmax(state.motor_temperature_c))
        return f"motor temperature: motor {motor} at {hottest} °C ≥ {safety.max_motor_temperature_c} °C"
    return None


# The trips a gait causes, by the start of their reasons (state_trip_reason, power_protect, and the SDK's own power
# protection in hardware_io): the robot tipped over or its motors drew too much power. An online optimization counts
# such a stop as an unsafe trial and may stand the robot up again (cpgjax.deployment.trials, docs/decisions.md §17).
# Every other trip (stop buttons, motor temperature, a stale or missing robot state, a non-finite command) ends the
# run: it is the operator's, the hardware's or the link's, not the gait's.
GAIT_TRIP_PREFIXES = ("tilt:", "power protection:", "the SDK's power protection")


def is_gait_trip(reason: str | None) -> bool:
    """Whether a trip ``reason`` is one a gait causes (:data:`GAIT_TRIP_PREFIXES`)."""
    return reason is not None and reason.startswith(GAIT_TRIP_PREFIXES)


def power_protect(counter: int, state: wire.RobotState, safety: SafetyConfig) -> tuple[int, str | None]:
    """One update of the SDK's power-protection counter; returns (counter, trip reason or None)."""
    power_w = float(np.sum(np.abs(state.tau_est_nm * state.dq_rad_s)))
    limit_w = 100.0 * min(max(safety.power_level, 1), 10)
    counter = counter + 1 if power_w > limit_w else max(counter - 1, 0)
    if counter >= safety.power_trip_count:
        return counter, (
            f"power protection: Σ|tauEst·dq| = {power_w:.0f} W > {limit_w:.0f} W (level {safety.power_level})"
        )
    return counter, None


_SERVO = np.full(12, wire.MODE_SERVO, np.uint8)
_POS_STOP = np.full(12, wire.POS_STOP_F)
_VEL_STOP = np.full(12, wire.VEL_STOP_F)
_ZERO = np.zeros(12)
for _a in (_SERVO, _POS_STOP, _VEL_STOP, _ZERO):
    _a.flags.writeable = False  # shared by every command


def torque_command(torque_nm: np.ndarray) -> wire.MotorCommand:
    """Pure torque: both motor PD terms stopped (PosStopF, VelStopF, zero gains)."""
    return wire.MotorCommand(_SERVO, _POS_STOP, _VEL_STOP, torque_nm, _ZERO, _ZERO)


def pd_command(q_rad: np.ndarray, kp: float, kd: float) -> wire.MotorCommand:
    """Motor-side PD to joint positions (velocity target 0)."""
    return wire.MotorCommand(_SERVO, q_rad, _ZERO, _ZERO, np.full(12, kp), np.full(12, kd))


def damping_command(kd: float) -> wire.MotorCommand:
    """Damping: τ = −kd · dq on every motor (no stiffness, no torque)."""
    return wire.MotorCommand(_SERVO, _POS_STOP, _ZERO, _ZERO, _ZERO, np.full(12, kd))


def guard_command(cmd: wire.MotorCommand, safety: SafetyConfig) -> tuple[wire.MotorCommand, str | None]:
    """Check and clamp a command before it is encoded (the wire silently wraps out-of-range values).

    A non-finite tau, gain, velocity or (active) position target gives a trip reason. Otherwise torques are clamped
    to the motor limits, gains to [0, max], and position targets with Kp > 0 to the SDK's joint limits (a PosStopF
    target is kept: clamping it would switch the position term on).
    """
    position_active = cmd.kp_nm_rad > 0.0
    q_active = np.where(position_active, cmd.q_rad, 0.0)
    fields = (cmd.tau_nm, cmd.kp_nm_rad, cmd.kd_nm_s_rad, q_active, cmd.dq_rad_s)
    if not np.isfinite(np.concatenate(fields)).all():
        bad = [n for n, f in zip(("tau", "kp", "kd", "q", "dq"), fields, strict=True) if not np.isfinite(f).all()]
        return cmd, f"non-finite command ({', '.join(bad)})"
    q = cmd.q_rad
    if position_active.any():
        q = np.where(position_active, np.minimum(np.maximum(q, JOINT_LOWER_RAD), JOINT_UPPER_RAD), q)
    return wire.MotorCommand(
        cmd.mode,
        q,
        cmd.dq_rad_s,
        np.minimum(np.maximum(cmd.tau_nm, -TORQUE_LIMIT_NM), TORQUE_LIMIT_NM),
        np.minimum(np.maximum(cmd.kp_nm_rad, 0.0), safety.kp_max_nm_rad),
        np.minimum(np.maximum(cmd.kd_nm_s_rad, 0.0), safety.kd_max_nm_s_rad),
    ), None
