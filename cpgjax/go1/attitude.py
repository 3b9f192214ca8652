"""Quaternion and attitude maths, one definition for the simulator, the controller and the robot side.

Quaternions are (w, x, y, z), unit norm. Roll, pitch, yaw are ZYX Euler angles with pitch positive nose-down (ROS;
docs/decisions.md §4). Every function works on JAX arrays, traced or not (returning JAX: the jitted controller and
sensor model), and on NumPy arrays (returning NumPy: the loopback simulated Go1); :func:`quat_to_rpy` also takes a
tuple of Python floats (returning a tuple: the 1 kHz loop's tilt check, where NumPy's per-call overhead would cost
≈ 10 µs a tick against ≈ 2 µs).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

_SCALAR = SimpleNamespace(arctan2=math.atan2, arcsin=math.asin, clip=lambda v, lo, hi: max(lo, min(hi, v)), stack=tuple)


def _xp(*xs):
    """The namespace of the arguments' maths: ``jax.numpy`` if any is a JAX array or tracer, else NumPy for NumPy
    arrays, ``math`` for tuples of Python floats."""
    if any(isinstance(x, jax.Array) for x in xs):
        return jnp
    return _SCALAR if all(isinstance(x, tuple) for x in xs) else np


def quat_to_rpy(quat_wxyz):
    """Roll, pitch, yaw (3,) [rad] from a unit quaternion (4,)."""
    xp = _xp(quat_wxyz)
    w, x, y, z = quat_wxyz[0], quat_wxyz[1], quat_wxyz[2], quat_wxyz[3]
    roll = xp.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = xp.arcsin(xp.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = xp.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return xp.stack([roll, pitch, yaw])


def quat_mul(a, b):
    """The Hamilton product a ⊗ b of two quaternions (4,)."""
    xp = _xp(a, b)
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return xp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_rotate(quat_wxyz, v):
    """v (..., 3) rotated by the unit quaternion (4,): q v q*."""
    xp = _xp(quat_wxyz, v)
    w, u = quat_wxyz[0], quat_wxyz[1:]
    t = 2.0 * xp.cross(u, v)
    return v + w * t + xp.cross(u, t)


def quat_to_matrix(quat_wxyz):
    """The rotation matrix (3, 3) of a unit quaternion: body-frame vectors → world-frame vectors."""
    xp = _xp(quat_wxyz)
    w, x, y, z = quat_wxyz[0], quat_wxyz[1], quat_wxyz[2], quat_wxyz[3]
    return xp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def gravity_frame_quat(gravity):
    """Quaternion rotating floor-frame vectors into the gravity-aligned frame: the shortest arc taking −ĝ to +z (how
    an IMU on a slope reports its attitude, docs/decisions.md §4)."""
    xp = _xp(gravity)
    up = -gravity / xp.linalg.norm(gravity)
    q = xp.stack([1.0 + up[2], up[1], -up[0], xp.zeros_like(up[0])])  # (1 + u·z, u × z)
    return q / xp.linalg.norm(q)


def to_heading_frame(v_world, yaw_rad):
    """The x, y components of a world-frame vector (≥ 2,) in the heading (yaw-only) frame (2,)."""
    xp = _xp(v_world, yaw_rad)
    c, s = xp.cos(yaw_rad), xp.sin(yaw_rad)
    return xp.stack([c * v_world[0] + s * v_world[1], -s * v_world[0] + c * v_world[1]])
