"""Rotations. Quaternions are ``(w, x, y, z)`` numpy arrays, Hamilton product, and ``q``
rotates body vectors into the navigation frame: ``v_n = R(q) v_b`` (docs/ekf.md §1)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def skew(v: Array) -> Array:
    """``[v]×`` such that ``[v]× u = v × u``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def quat_mul(a: Array, b: Array) -> Array:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_from_rotvec(theta: Array) -> Array:
    """``Exp(θ)``: the rotation by ``|θ|`` about ``θ/|θ|``."""
    angle = math.sqrt(theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2)
    if angle < 1e-12:
        return np.array([1.0, 0.5 * theta[0], 0.5 * theta[1], 0.5 * theta[2]])
    s = math.sin(0.5 * angle) / angle
    return np.array([math.cos(0.5 * angle), s * theta[0], s * theta[1], s * theta[2]])


def quat_to_matrix(q: Array) -> Array:
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_from_matrix(r: Array) -> Array:
    """The unit quaternion (w >= 0) of a rotation matrix."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def quat_from_euler(roll: float, pitch: float, yaw: float) -> Array:
    """ZYX (yaw, then pitch, then roll) angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


def euler_from_quat(q: Array) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians, ZYX convention."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def turned(q: Sequence[float] | Array, tx: float, ty: float, tz: float) -> list[float]:
    """``q ⊗ Exp(θ)`` normalised, in plain floats (the per-IMU-sample attitude step)."""
    angle = math.sqrt(tx * tx + ty * ty + tz * tz)
    if angle < 1e-9:
        dw, s = 1.0, 0.5
    else:
        dw, s = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    dx, dy, dz = s * tx, s * ty, s * tz
    qw, qx, qy, qz = q
    nw = qw * dw - qx * dx - qy * dy - qz * dz
    nx = qw * dx + qx * dw + qy * dz - qz * dy
    ny = qw * dy - qx * dz + qy * dw + qz * dx
    nz = qw * dz + qx * dy - qy * dx + qz * dw
    norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    return [nw / norm, nx / norm, ny / norm, nz / norm]


def body_point(p: Sequence[float] | Array, q: Sequence[float] | Array,
               lever: Sequence[float]) -> tuple[float, float, float]:
    """``p + R(q) l``: a point fixed to the body (the antenna at lever arm ``l``) in the
    navigation frame, in floats (it runs for every UWB message)."""
    (px, py, pz), (w, x, y, z), (lx, ly, lz) = p, q, lever
    return (px + ((1 - 2 * (y * y + z * z)) * lx + 2 * (x * y - w * z) * ly
                  + 2 * (x * z + w * y) * lz),
            py + (2 * (x * y + w * z) * lx + (1 - 2 * (x * x + z * z)) * ly
                  + 2 * (y * z - w * x) * lz),
            pz + (2 * (x * z - w * y) * lx + 2 * (y * z + w * x) * ly
                  + (1 - 2 * (x * x + y * y)) * lz))
