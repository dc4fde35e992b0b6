"""The methods uwbd is measured against, kept as code paths (see docs/ekf.md for the main one).

* :class:`PureIns`: the filter's start-up, then the strapdown alone (no UWB after that).
* :class:`UwbLeastSquares`: one Gauss-Newton fix per epoch, or per 0.1 s of single ranges.
* :class:`ComplementaryAttitude`: Mahony-style attitude from gyro, pulled towards the gravity
  direction of the accelerometer, whose signal first passes a 2nd-order Butterworth low-pass
  (fs 200 Hz, fc 2 Hz by default, designed by scipy).
* :class:`Kf4`: the thesis's loosely coupled filter: a 4-state ``[px py vx vy]`` Kalman
  filter (filterpy), driven by the horizontal acceleration that the complementary attitude
  puts into the navigation frame, corrected by UWB fixes that pass the anchor-count check
  and lie within 1 m of the prediction.

Each has ``predict(imu)``, ``update(uwb)`` and ``position()`` like the main filter.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.signal import butter, sosfilt, sosfilt_zi

from drivers.frames import ImuSample, UwbRanges
from uwbd.fusion.eskf import GRAVITY_MPS2
from uwbd.fusion.filter import Filter
from uwbd.fusion.fixes import RangeWindow
from uwbd.fusion.lsq import LsqFix
from uwbd.fusion.mirror import MirrorSide
from uwbd.fusion.rotation import Array, quat_from_rotvec, quat_mul, quat_to_matrix
from uwbd.fusion.settings import FilterConfig


class PureIns:
    """Initialised like the main filter (at rest, from UWB), then inertial only."""

    def __init__(self, config: FilterConfig) -> None:
        self.filter = Filter(config)

    def predict(self, imu: ImuSample) -> None:
        self.filter.predict(imu)

    def update(self, uwb: UwbRanges) -> None:
        if self.filter.ekf is None:
            self.filter.update(uwb)

    def position(self) -> Array | None:
        return None if self.filter.ekf is None else np.array(self.filter.ekf.p)


class UwbLeastSquares:
    """Multilateration per epoch, or over a 0.1 s window of single ranges (one fix each
    0.1 s); anchors from the config, else as the device sends them."""

    def __init__(self, config: FilterConfig) -> None:
        self.anchors = dict(config.anchors_m)
        self.sigma_m = config.range_sigma_m
        known = np.array(list(self.anchors.values()), dtype=float).reshape(-1, 3)
        self.window = RangeWindow(0.1, 0.1, self.sigma_m,
                                  MirrorSide(known, config.tag_side, config.height_range_m),
                                  None)
        self.fix: LsqFix | None = None  # the fix of the latest message, if it made one
        self._last: Array | None = None

    def predict(self, imu: ImuSample) -> None:
        """UWB only: the IMU is not used."""

    def update(self, uwb: UwbRanges) -> None:
        known = [(r.anchor_id, self.anchors.get(r.anchor_id, r.anchor_position_m), r.range_m)
                 for r in uwb.ranges if math.isfinite(r.range_m)]
        known = [(i, a, d) for i, a, d in known if a is not None]
        self.fix = None
        if not known:
            return
        ids = [i for i, _, _ in known]
        anchors = np.array([a for _, a, _ in known], dtype=float)
        ranges = np.array([d for _, _, d in known])
        self.window.add(uwb.t_ns, ids, anchors, ranges)
        self.fix = self.window.fix(uwb.t_ns, ids, anchors, ranges, self._last)
        if self.fix is not None:
            self._last = self.fix.position_m

    def position(self) -> Array | None:
        return None if self.fix is None else self.fix.position_m


class ComplementaryAttitude:
    """Mahony complementary filter: ``q̇ = ½ q ⊗ (ω − b + k_p e)``, ``e = ĝ_b × a_lp``."""

    def __init__(self, mounting: Array, fs_hz: float = 200.0, fc_hz: float = 2.0,
                 kp: float = 1.0) -> None:
        self.C_bs = mounting
        self.sos = butter(2, fc_hz, btype="low", fs=fs_hz, output="sos")
        self._zi: Array | None = None
        self.kp = kp
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.gyro_bias = np.zeros(3)
        self.t_ns: int | None = None
        self.acc_lp = np.zeros(3)

    def predict(self, imu: ImuSample) -> Array:
        """Update the attitude; returns the low-passed specific force (body)."""
        acc = self.C_bs @ np.asarray(imu.acc_mps2)
        gyro = self.C_bs @ np.asarray(imu.gyro_rps)
        if self._zi is None:
            self._zi = sosfilt_zi(self.sos)[:, :, None] * acc[None, None, :]
        out, self._zi = sosfilt(self.sos, acc[None, :], axis=0, zi=self._zi)
        self.acc_lp = out[0]
        if self.t_ns is None:
            self.t_ns = imu.t_ns
            return self.acc_lp
        dt = (imu.t_ns - self.t_ns) / 1e9
        self.t_ns = imu.t_ns
        if not 0 < dt < 0.5:
            return self.acc_lp
        g_body = quat_to_matrix(self.q).T @ np.array([0.0, 0.0, 1.0])  # "up" in body axes
        a = self.acc_lp / max(float(np.linalg.norm(self.acc_lp)), 1e-9)
        e = np.cross(a, g_body)
        q = quat_mul(self.q, quat_from_rotvec((gyro - self.gyro_bias + self.kp * e) * dt))
        self.q = q / np.linalg.norm(q)
        return self.acc_lp


class Kf4:
    """The thesis's 4-state KF (module doc). Static start: gyro bias averaged at rest."""

    def __init__(self, config: FilterConfig, gate_m: float = 1.0, min_anchors: int = 3,
                 accel_noise_mps2: float = 0.5) -> None:
        self.lsq = UwbLeastSquares(config)
        self.attitude = ComplementaryAttitude(np.array(config.mounting_rotation, dtype=float))
        self.gate_m = gate_m
        self.min_anchors = min_anchors
        self.accel_noise = accel_noise_mps2
        self.kf: KalmanFilter | None = None
        self.rejected = 0
        self._gyro_rest: list[Array] = []

    def predict(self, imu: ImuSample) -> None:
        prev = self.attitude.t_ns
        f_b = self.attitude.predict(imu)
        if self.kf is None:
            self._gyro_rest.append(self.attitude.C_bs @ np.asarray(imu.gyro_rps))
            self.attitude.gyro_bias = np.mean(self._gyro_rest[-400:], axis=0)
            return
        if prev is None:
            return
        dt = (imu.t_ns - prev) / 1e9
        if not 0 < dt < 0.5:
            return
        a_n = quat_to_matrix(self.attitude.q) @ f_b - np.array([0.0, 0.0, GRAVITY_MPS2])
        kf = self.kf
        kf.F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
        kf.B = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        G = kf.B
        kf.Q = G @ G.T * self.accel_noise**2
        kf.predict(u=a_n[:2])

    def update(self, uwb: UwbRanges) -> None:
        if sum(math.isfinite(r.range_m) for r in uwb.ranges) < self.min_anchors:
            return
        self.lsq.update(uwb)
        fix = self.lsq.fix
        if fix is None:
            return
        z = fix.position_m[:2]
        if self.kf is None:
            self.kf = KalmanFilter(dim_x=4, dim_z=2, dim_u=2)
            self.kf.x = np.array([z[0], z[1], 0.0, 0.0])
            self.kf.P = np.diag([0.1, 0.1, 0.5, 0.5])
            self.kf.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
            return
        if float(np.linalg.norm(z - self.kf.x[:2])) > self.gate_m:
            self.rejected += 1  # the thesis's consistency check: fixes > 1 m off are dropped
            return
        self.kf.update(z, R=fix.covariance[:2, :2] + np.eye(2) * 1e-4)

    def position(self) -> Array | None:
        fix = self.lsq.fix
        if self.kf is None or fix is None:
            return None
        return np.array([self.kf.x[0], self.kf.x[1], fix.position_m[2]])


def comparison_methods(config: FilterConfig) -> dict[str, PureIns | UwbLeastSquares | Kf4]:
    """The baselines every report and benchmark compares uwbd's filters against."""
    return {"pure INS": PureIns(config), "uwb least squares": UwbLeastSquares(config),
            "4-state KF (thesis)": Kf4(config)}
