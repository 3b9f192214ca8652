"""The Go1's constants that several layers use, each defined once (sources in docs/go1-model.md).

Motor order everywhere is the SDK's: legs FR, FL, RR, RL, each hip (abduction), thigh, calf.
"""

from __future__ import annotations

import numpy as np

LEG_NAMES = ("FR", "FL", "RR", "RL")
JOINT_PARTS = ("hip", "thigh", "calf")
NUM_JOINTS = len(LEG_NAMES) * len(JOINT_PARTS)

# Motor torque limits (Unitree URDF effort limits; the MJCF's actuator ctrlrange), hip, thigh, calf × 4 legs.
TORQUE_LIMIT_NM = np.tile(np.array([23.7, 23.7, 35.55]), 4)
# Joint limits of the SDK's Safety (go1_const.h), hip, thigh, calf × 4 legs.
JOINT_LOWER_RAD = np.tile(np.array([-1.047, -0.663, -2.721]), 4)
JOINT_UPPER_RAD = np.tile(np.array([1.047, 2.966, -0.837]), 4)

GRAVITY_MPS2 = 9.81

# The deployment's tilt stop: IMU |roll| or |pitch| beyond this damps the motors (cpgjax.robot.safety), and a trial's
# safety margin reaches 0 there (cpgjax.trial.protocol.safety_margin).
TILT_STOP_RAD = 0.7

# The control tick: the paper's 1 kHz control loop, which the physics steps at too (docs/decisions.md §14). Every
# conversion between seconds and ticks goes through these.
CONTROL_HZ = 1000
TICK_S = 1 / CONTROL_HZ  # 0.001 s


def ticks(seconds: float) -> int:
    """The whole number of control ticks nearest ``seconds`` (``seconds · CONTROL_HZ``, rounded half to even)."""
    return int(round(seconds * CONTROL_HZ))


def seconds(num_ticks):
    """``num_ticks`` control ticks in seconds (``num_ticks / CONTROL_HZ``; an array gives an array)."""
    return num_ticks / CONTROL_HZ
