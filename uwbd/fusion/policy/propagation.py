"""The IMU side of :class:`~uwbd.fusion.filter.Filter`: each sample judged, turned into body
axes, kept in the rest window and integrated (``predict``); the state brought to a
measurement's time (``predict_to``), through IMU gaps by coasting. Its own state is the last
samples; it acts on the :class:`~.estimate.Estimate` it is handed, and a sample that calls
for a restart hands it to :class:`~.recovery.Recovery`."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from drivers.frames import ImuSample
from uwbd.fusion.checks.imu_check import ImuCheck, new_imu_check
from uwbd.fusion.checks.intrinsics import body_maps, to_body
from uwbd.fusion.core.native import Core
from uwbd.fusion.policy.estimate import Estimate
from uwbd.fusion.policy.recovery import (
    COAST_ACCEL_SIGMA_MPS2,
    NS,
    UNSEEN_RATE_SIGMA_RPS,
    Recovery,
)
from uwbd.fusion.policy.rest import ImuWindow
from uwbd.fusion.settings import FilterConfig

Vec3 = tuple[float, float, float]
PROPAGATE_EVERY_S = 0.1  # the covariance follows the state at least this often (coasting)
NUMERICAL_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError)


class ImuPropagation:
    """IMU samples in, the nominal state and its covariance propagated (see module doc)."""

    def __init__(self, cfg: FilterConfig, est: Estimate, window: ImuWindow,
                 recovery: Recovery, core: Core) -> None:
        self.cfg, self.est, self.window, self.recovery = cfg, est, window, recovery
        C_bs = np.array(cfg.mounting_rotation, dtype=float)
        if not np.allclose(C_bs @ C_bs.T, np.eye(3), atol=1e-6) or np.linalg.det(C_bs) < 0:
            raise ValueError("mounting_rotation must be a proper rotation matrix")
        self._C = tuple(tuple(float(x) for x in row) for row in C_bs)
        (a, b, c), (d, e, f), (g, h, i) = self._C
        rows = ((a, b, c), (d, e, f), (g, h, i))
        # raw sensor axes -> corrected body axes, one affine map per sample (.intrinsics);
        # with the intrinsics at their defaults both are the plain rotation to_body
        self.acc_to_body: Callable[[Vec3], Vec3]
        self.gyro_to_body: Callable[[Vec3], Vec3]
        self.acc_to_body, self.gyro_to_body = to_body(rows, cfg.imu_intrinsics, self.to_body)
        self.intrinsics_applied = not cfg.imu_intrinsics.is_identity
        self.check = new_imu_check(cfg.imu_limits, body_maps(rows, cfg.imu_intrinsics), core)
        # on the C core, a good sample while tracking is judged, mapped and integrated in one
        # call (ImuFront.step_many)
        self._front_steps = not isinstance(self.check, ImuCheck)
        self.imu_t_ns: int | None = None  # the last sample's, of any kind
        self.good_imu_ns: int | None = None  # the last sample that passed the checks
        self.last_imu: tuple[Vec3, Vec3] | None = None  # body axes, the last one used
        self.coasted = False  # through a gap since the last epoch

    def predict(self, imu: ImuSample) -> None:
        """Integrate one IMU sample (sensor axes); bad samples are counted, never used."""
        self.predict_many((imu,))

    def predict_many(self, samples: Sequence[ImuSample]) -> None:
        """A read's samples, in time order, each integrated or counted. While tracking, the
        C IMU front steps over the common ones (judged good, no gap, after the state) in one
        call (``ImuFront.step_many``: the rule is the front's); the policy takes each other
        sample, one at a time (:meth:`step_one`)."""
        k, n = 0, len(samples)
        while k < n:
            ekf, prev, t_state = self.est.ekf, self.imu_t_ns, self.est.t_ns
            if (self._front_steps and ekf is not None and ekf.core_state is not None
                    and self.est.relevel is None and prev is not None and t_state is not None):
                try:
                    rows, reason = self.check.step_many(
                        ekf.core_state, [(s.t_ns, s.acc_mps2, s.gyro_rps) for s in samples[k:]],
                        prev, t_state, self.cfg.max_imu_gap_s, PROPAGATE_EVERY_S)
                except NUMERICAL_ERRORS as err:  # (a time C cannot hold, say)
                    self.recovery.internal_error(samples[k].t_ns, err)
                    k += 1
                    continue
                if rows:
                    last = rows[-1]
                    self.imu_t_ns = self.good_imu_ns = self.est.t_ns = last[0]
                    self.window.add_rows(rows)
                    self.last_imu = (last[1:4], last[4:7])
                    k += len(rows)
                if k == n:
                    return
            else:
                reason = None
            self.step_one(samples[k], reason)  # judged and rejected, or not the common sample
            k += 1

    def step_one(self, imu: ImuSample, reason: str | None) -> None:
        """One sample the policy takes: ``reason``, why the front rejected it, or None where
        it is not the common one (then judged here)."""
        try:
            t_ns, prev = imu.t_ns, self.imu_t_ns
            if reason is None and prev is not None and t_ns <= prev:
                a, g = imu.acc_mps2, imu.gyro_rps  # judged no further: it changes nothing
                finite = math.isfinite(a[0] + a[1] + a[2] + g[0] + g[1] + g[2])
                self.est.counters["imu_out_of_order" if finite else "imu_not_finite"] += 1
                return
            if reason is None:
                reason = self.check.judge(t_ns, imu.acc_mps2, imu.gyro_rps)
            self._judged(imu, reason)
        except NUMERICAL_ERRORS as err:
            self.recovery.internal_error(imu.t_ns, err)

    def _judged(self, imu: ImuSample, reason: str) -> None:
        """A sample after the IMU check (``reason``: why it is rejected, or ""): counted,
        kept in the rest window, integrated (over a rejected one with the last good one),
        coasted over a gap."""
        t_ns, prev = imu.t_ns, self.imu_t_ns
        ekf = self.est.ekf
        if reason:
            self.est.counters[reason] += 1
            self.est.monitor.imu_rejected(t_ns)
        if self.recovery.first_t_ns is None:
            self.recovery.first_t_ns = t_ns
        self.imu_t_ns = t_ns
        gap_s = 0.0 if prev is None else (t_ns - prev) / NS  # since the last sample of any kind
        if not reason:  # judged raw (full scale is the sensor's), then corrected
            sample = (self.acc_to_body(imu.acc_mps2), self.gyro_to_body(imu.gyro_rps))
            self.window.add(t_ns, *sample)
            self.good_imu_ns = t_ns
        if ekf is None:
            if not reason:
                self.last_imu = sample
            return
        assert self.est.t_ns is not None
        cfg = self.cfg
        if self.est.relevel is not None:  # the attitude restarts once fresh samples span a window
            self.recovery.relevel_when_ready(t_ns)
            return
        dt = (t_ns - self.est.t_ns) / NS
        if reason:
            if self.check.burst_s(t_ns) > cfg.attitude_lost_after_s or self.last_imu is None:
                # held that long, the last good sample says nothing: coast on the ranges
                self.recovery.lose_attitude(t_ns, "IMU samples rejected")
                return
            sample = self.last_imu  # integrate over the rejected one with the last good one
        elif gap_s > cfg.max_imu_gap_s:
            self.est.counters["imu_gaps"] += 1
            self.coasted = True
            if dt > 0:  # coasted by the ranges up to their last update; on to this sample
                self.recovery.coast(dt)
            self.est.t_ns = t_ns
            self.last_imu = sample
            if gap_s > cfg.attitude_lost_after_s:
                self.recovery.lose_attitude(t_ns, "IMU gap")
            else:
                self.est.monitor.imu_gap = False
            return
        if dt > 0:
            ekf.predict(sample[0], sample[1], dt)
            if reason:
                self._widen_for_unseen(dt)
            if ekf.interval_s >= PROPAGATE_EVERY_S:
                ekf.propagate()
        self.est.t_ns = t_ns
        self.last_imu = sample

    def to_body(self, v: tuple[float, float, float]) -> Vec3:
        """``C_bs v`` in plain floats: this runs for every IMU sample."""
        (a, b, c), (d, e, f), (g, h, i) = self._C
        x, y, z = v
        return (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z)

    def fresh(self, t_ns: int | None = None) -> bool:
        """The last IMU sample is at most ``max_imu_gap_s`` older than ``t_ns`` (the
        state's time by default)."""
        now = self.est.t_ns if t_ns is None else t_ns
        return self.est.relevel is None and self.good_imu_ns is not None and now is not None \
            and fresh_at(now, self.good_imu_ns, self.cfg.max_imu_gap_s)

    def predict_to(self, t_ns: int) -> None:
        """Bring the state to the measurement time: hold the last IMU sample while it is fresh
        (one IMU period at most, normally); in an IMU gap, coast at constant velocity with
        growing uncertainty, so the ranges keep the position while the IMU is away."""
        ekf = self.est.ekf
        assert ekf is not None and self.est.t_ns is not None
        dt = (t_ns - self.est.t_ns) / NS
        if dt <= 0:
            return
        if self.fresh(t_ns) and self.last_imu is not None:
            ekf.predict(self.last_imu[0], self.last_imu[1], dt)
            self.est.monitor.imu_gap = False
        else:
            self.coasted = True
            self.est.monitor.imu_gap = True
            self.recovery.coast(dt)
        self.est.t_ns = t_ns

    def _widen_for_unseen(self, dt: float) -> None:
        """A rejected IMU sample hid ``dt`` of motion: widen velocity and attitude for it."""
        self.recovery.inflate(velocity_mps=COAST_ACCEL_SIGMA_MPS2 * math.sqrt(dt),
                      attitude_rad=UNSEEN_RATE_SIGMA_RPS * math.sqrt(dt))


def fresh_at(t_ns: int, good_ns: int, max_gap_s: float) -> bool:
    """The rule: a good IMU sample at ``good_ns`` is fresh at ``t_ns`` (at most an IMU gap
    before it); the state is then brought to ``t_ns`` with it, else it coasts."""
    return (t_ns - good_ns) / NS <= max_gap_s
