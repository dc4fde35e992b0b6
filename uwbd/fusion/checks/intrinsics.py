"""IMU intrinsics: what a six-position calibration (``uwbd calibrate-imu``) finds out about
the sensor, applied to every sample in its own axes before the mounting rotation.

Model, per sensor axis ``k`` (the sensor's gain and zero-g offset as datasheets state them)::

    a_meas[k] = acc_scale[k] · a_true[k] + acc_offset_mps2[k]  ->  a = (a_meas − offset) / scale
    ω = ω_meas − gyro_offset_rps, and |ω[k]| < gyro_deadband_rps -> 0 (off at 0)

:func:`to_body` folds the correction and the rotation sensor → body into one affine map per
sample (``M x − b``, the same 9 products as the rotation alone), and with every intrinsic at
its default it is the plain rotation, so a filter without a calibration computes exactly
what it did before. The raw readings are what the integrity check judges (full scale is the
sensor's, before any correction); the corrected ones are what the filter integrates.

The dead-band is what the thesis does to hold the heading still at rest. It is off by
default because it harms the EKF: a real turn slower than the band is lost altogether (the
heading error grows with it), and the residual gyro bias, which the EKF estimates as a state,
is removed while the sensor is still and present while it turns, so the bias the EKF sees is
not constant; ZUPT and the bias state already keep the heading still at rest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

Vec3 = tuple[float, float, float]
Rows3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
ONES = (1.0, 1.0, 1.0)
ZEROS = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ImuIntrinsics:
    """Per sensor axis: accelerometer gain and zero-g offset, gyro zero-rate offset, and a
    gyro dead-band (0: off)."""

    acc_scale: Vec3 = ONES
    acc_offset_mps2: Vec3 = ZEROS
    gyro_offset_rps: Vec3 = ZEROS
    gyro_deadband_rps: float = 0.0

    @property
    def is_identity(self) -> bool:
        """Every value at its default: the samples are used as they are."""
        return (self.acc_scale == ONES and self.acc_offset_mps2 == ZEROS
                and self.gyro_offset_rps == ZEROS and self.gyro_deadband_rps == 0.0)

    def correct_acc(self, a: Vec3) -> Vec3:
        """``(a_meas − offset) / scale`` in sensor axes."""
        (o0, o1, o2), (s0, s1, s2) = self.acc_offset_mps2, self.acc_scale
        return ((a[0] - o0) / s0, (a[1] - o1) / s1, (a[2] - o2) / s2)

    def correct_gyro(self, w: Vec3) -> Vec3:
        """``ω_meas − offset`` in sensor axes, each axis below the dead-band zeroed."""
        o, d = self.gyro_offset_rps, self.gyro_deadband_rps
        x, y, z = w[0] - o[0], w[1] - o[1], w[2] - o[2]
        if d > 0.0:
            x, y, z = (0.0 if abs(x) < d else x), (0.0 if abs(y) < d else y), \
                (0.0 if abs(z) < d else z)
        return (x, y, z)


def _affine(M: Rows3, b: Vec3) -> Callable[[Vec3], Vec3]:
    (m0, m1, m2), (m3, m4, m5), (m6, m7, m8) = M
    b0, b1, b2 = b

    def apply(v: Vec3) -> Vec3:
        x, y, z = v
        return (m0 * x + m1 * y + m2 * z - b0, m3 * x + m4 * y + m5 * z - b1,
                m6 * x + m7 * y + m8 * z - b2)
    return apply


class BodyMaps(NamedTuple):
    """The per-sample maps raw sensor axes → corrected body axes, as numbers: the
    accelerometer's ``acc_M a − acc_b``; the gyro's ``gyro_M ω − gyro_b``, or with a
    dead-band (``gyro_band > 0``) ``gyro_M band(ω − gyro_offset)``; :func:`to_body` makes
    the Python functions of that arithmetic."""

    acc_M: Rows3  # noqa: N815 - a matrix
    acc_b: Vec3
    gyro_M: Rows3  # noqa: N815 - a matrix
    gyro_b: Vec3
    gyro_offset: Vec3
    gyro_band: float


def body_maps(C_bs: Rows3, intrinsics: ImuIntrinsics) -> BodyMaps:
    """The maps for the mounting rotation ``C_bs`` and the calibration ``intrinsics``."""
    if intrinsics.is_identity:
        return BodyMaps(C_bs, ZEROS, C_bs, ZEROS, ZEROS, 0.0)
    s, o = intrinsics.acc_scale, intrinsics.acc_offset_mps2

    def scaled(row: Vec3) -> Vec3:  # C_bs diag(1/scale)
        return (row[0] / s[0], row[1] / s[1], row[2] / s[2])

    M = (scaled(C_bs[0]), scaled(C_bs[1]), scaled(C_bs[2]))  # M (a - o) = M a - M o
    if intrinsics.gyro_deadband_rps <= 0.0:
        return BodyMaps(M, _times(M, o), C_bs, _times(C_bs, intrinsics.gyro_offset_rps),
                        ZEROS, 0.0)
    return BodyMaps(M, _times(M, o), C_bs, ZEROS, intrinsics.gyro_offset_rps,
                    intrinsics.gyro_deadband_rps)


def to_body(C_bs: Rows3, intrinsics: ImuIntrinsics,
            rotate: Callable[[Vec3], Vec3]) -> tuple[Callable[[Vec3], Vec3],
                                                     Callable[[Vec3], Vec3]]:
    """The per-sample maps raw accelerometer and gyro readings (sensor axes) → corrected
    body axes. ``rotate`` is the plain ``C_bs v``: returned as both when every intrinsic is
    at its default (nothing else runs; the same numbers as ``M v − 0``)."""
    if intrinsics.is_identity:
        return rotate, rotate
    maps = body_maps(C_bs, intrinsics)
    acc = _affine(maps.acc_M, maps.acc_b)
    if maps.gyro_band <= 0.0:
        return acc, _affine(maps.gyro_M, maps.gyro_b)
    (m0, m1, m2), (m3, m4, m5), (m6, m7, m8) = maps.gyro_M
    o0, o1, o2 = maps.gyro_offset
    d = maps.gyro_band

    def gyro(w: Vec3) -> Vec3:  # the band is per sensor axis: before the rotation
        x, y, z = w[0] - o0, w[1] - o1, w[2] - o2
        if -d < x < d:
            x = 0.0
        if -d < y < d:
            y = 0.0
        if -d < z < d:
            z = 0.0
        return (m0 * x + m1 * y + m2 * z, m3 * x + m4 * y + m5 * z, m6 * x + m7 * y + m8 * z)
    return acc, gyro


def _times(M: Rows3, v: Vec3) -> Vec3:
    return (M[0][0] * v[0] + M[0][1] * v[1] + M[0][2] * v[2],
            M[1][0] * v[0] + M[1][1] * v[1] + M[1][2] * v[2],
            M[2][0] * v[0] + M[2][1] * v[1] + M[2][2] * v[2])
