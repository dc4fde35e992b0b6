"""A simulated six-position IMU calibration capture (what ``uwbd calibrate-imu`` reads): the
simulator's IMU (:class:`~uwbd.tools.simulator.SimConfig`: rate, white noise, intrinsic
errors, full scale, seed) held still with each axis up and then down, turned by hand
between the holds."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.frames import ImuSample
from uwbd.fusion.core.rotation import Array, quat_from_matrix, quat_from_rotvec, quat_to_matrix
from uwbd.tools.simulator import EPOCH_NS, GRAVITY_MPS2, SimConfig

# each axis up, then down: every turn between them is a quarter turn
SIX_POSITIONS = ("+z", "+x", "+y", "-z", "-x", "-y")


@dataclass
class SixPositionCapture:
    """A simulated IMU calibration capture: the samples, each hold as (orientation, start s,
    end s) from the first sample (``"+x"``: x up), and the sensor's true errors."""

    imu: list[ImuSample]
    holds: list[tuple[str, float, float]]
    acc_scale: tuple[float, float, float]
    acc_offset_mps2: tuple[float, float, float]
    gyro_offset_rps: tuple[float, float, float]


def _held(orientation: str, yaw: float, tilt_rad: float, tilt_dir: float) -> Array:
    """Sensor -> ENU rotation with the named sensor axis up, turned by ``yaw`` about the
    vertical and tipped by ``tilt_rad`` about the horizontal direction ``tilt_dir``."""
    k, sign = "xyz".index(orientation[1]), 1.0 if orientation[0] == "+" else -1.0
    up = np.zeros(3)
    up[k] = sign  # the sensor axis that points up
    other = np.zeros(3)
    other[(k + 1) % 3] = 1.0
    R = np.array([other, np.cross(up, other), up])  # rows: sensor axes' images -> ENU x, y, z
    turn = quat_to_matrix(quat_from_rotvec(np.array([0.0, 0.0, yaw])))
    tip = quat_to_matrix(quat_from_rotvec(
        tilt_rad * np.array([math.cos(tilt_dir), math.sin(tilt_dir), 0.0])))
    held: Array = tip @ turn @ R
    return held


def six_position_capture(cfg: SimConfig | None = None, hold_s: float = 5.0,
                         turn_s: float = 2.0, tilt_deg: float = 2.0,
                         order: tuple[str, ...] = SIX_POSITIONS) -> SixPositionCapture:
    """The IMU of ``cfg`` (rate, white noise, intrinsic errors, full scale, seed) held still
    for ``hold_s`` in each orientation of ``order`` in turn, tipped off the axis by up to
    ``tilt_deg`` at random (a hand against a box), and turned by hand from one to the next
    over ``turn_s`` (the gyro sees the turn). The intrinsic offsets are the sensor's whole
    offset here: no random turn-on bias is drawn."""
    cfg = cfg or SimConfig()
    rng = np.random.default_rng(cfg.seed)
    g = np.array([0.0, 0.0, GRAVITY_MPS2])
    rate = cfg.imu_rate_hz
    held = [_held(o, rng.uniform(-math.pi, math.pi), math.radians(tilt_deg) * rng.random(),
                  rng.uniform(-math.pi, math.pi)) for o in order]
    f_s: list[Array] = []
    w_s: list[Array] = []
    holds: list[tuple[str, float, float]] = []
    n_hold, n_turn = round(hold_s * rate), round(turn_s * rate)
    for i, R in enumerate(held):
        t0 = len(f_s) / rate
        f_s += [R.T @ g] * n_hold
        w_s += [np.zeros(3)] * n_hold
        holds.append((order[i], t0, t0 + n_hold / rate))
        if i + 1 == len(held):
            break
        # R(t) = R Exp(s(t) φ), s a smoothstep 0 -> 1: the sensor turns at ṡ φ, about φ
        q_rel = quat_from_matrix(R.T @ held[i + 1])
        angle = 2.0 * math.atan2(float(np.linalg.norm(q_rel[1:])), float(q_rel[0]))
        norm = float(np.linalg.norm(q_rel[1:]))
        phi = q_rel[1:] / norm * angle if norm > 0 else np.zeros(3)
        for j in range(n_turn):
            u = (j + 0.5) / n_turn
            s, ds = 3 * u**2 - 2 * u**3, (6 * u - 6 * u**2) / turn_s
            Rt = R @ quat_to_matrix(quat_from_rotvec(s * phi))
            f_s.append(Rt.T @ g)
            w_s.append(ds * phi)
    f, w = np.array(f_s), np.array(w_s)
    acc = np.array(cfg.acc_scale) * f + np.array(cfg.acc_offset_mps2) \
        + rng.normal(0, cfg.acc_noise_mps2, f.shape)
    gyro = w + np.array(cfg.gyro_offset_rps) + rng.normal(0, cfg.gyro_noise_rps, w.shape)
    np.clip(acc, -cfg.acc_full_scale_mps2, cfg.acc_full_scale_mps2, out=acc)
    np.clip(gyro, -cfg.gyro_full_scale_rps, cfg.gyro_full_scale_rps, out=gyro)
    imu = [ImuSample(EPOCH_NS + round(k / rate * 1e9), (float(a[0]), float(a[1]), float(a[2])),
                     (float(b[0]), float(b[1]), float(b[2])), 25.0)
           for k, (a, b) in enumerate(zip(acc, gyro, strict=True))]
    return SixPositionCapture(imu, holds, cfg.acc_scale, cfg.acc_offset_mps2,
                              cfg.gyro_offset_rps)
