"""The IMU side of :class:`~uwbd.fusion.filter.Filter` (a mixin of it, as :mod:`.recovery` and
:mod:`.fusing` are): each sample judged, turned into body axes, kept in the rest window and
integrated (``predict``); the state brought to a measurement's time (``_predict_to``),
through IMU gaps by coasting."""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.frames import ImuSample
from uwbd.fusion.policy.recovery import COAST_ACCEL_SIGMA_MPS2, NS, UNSEEN_RATE_SIGMA_RPS, Recovery

Vec3 = tuple[float, float, float]
PROPAGATE_EVERY_S = 0.1  # the covariance follows the state at least this often (coasting)
NUMERICAL_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError)


class ImuPropagation(Recovery):
    """IMU samples in, the nominal state and its covariance propagated (see module doc)."""

    imu_check: Any  # an ImuCheck, or on the C core its twin the IMU front (with step)
    counters: collections.Counter[str]
    _C: tuple[tuple[float, ...], ...]
    _acc_to_body: Any
    _gyro_to_body: Any
    _imu_t_ns: int | None
    _good_imu_ns: int | None
    _last_imu: tuple[Vec3, Vec3] | None
    _coasted: bool
    _front_steps: bool

    def predict(self, imu: ImuSample) -> None:
        """Integrate one IMU sample (sensor axes); bad samples are counted, never used."""
        try:
            self._predict(imu)
        except NUMERICAL_ERRORS as err:
            self._internal_error(imu.t_ns, err)

    def _internal_error(self, t_ns: int, err: Exception) -> None:
        """A numerical failure no check foresaw: counted, said, and the filter restarts
        rather than let the exception stop fusion."""
        self.counters["internal_errors"] += 1
        self.last_internal_error = f"{type(err).__name__}: {err}"
        self._restart(t_ns, "internal error")

    def _predict(self, imu: ImuSample) -> None:
        t_ns = imu.t_ns
        prev = self._imu_t_ns
        if prev is not None and t_ns <= prev:  # judged no further: it changes nothing
            a, g = imu.acc_mps2, imu.gyro_rps
            finite = math.isfinite(a[0] + a[1] + a[2] + g[0] + g[1] + g[2])
            self.counters["imu_out_of_order" if finite else "imu_not_finite"] += 1
            return
        ekf = self.ekf
        if (self._front_steps and ekf is not None and ekf.core_state is not None
                and self._relevel is None and prev is not None and self.t_ns is not None
                and (t_ns - prev) / NS <= self.cfg.max_imu_gap_s and t_ns > self.t_ns):
            # the common sample (good, no gap, tracking): all of the steps below in one call
            # of the C IMU front, or only the judging when it is rejected
            judged = self.imu_check.step(ekf.core_state, t_ns, imu.acc_mps2, imu.gyro_rps,
                                         (t_ns - self.t_ns) / NS, PROPAGATE_EVERY_S)
            if judged.__class__ is tuple:
                self._imu_t_ns = self._good_imu_ns = self.t_ns = t_ns
                self.window.add(t_ns, *judged)
                self._last_imu = judged
                return
            reason = judged
        else:
            reason = self.imu_check.judge(t_ns, imu.acc_mps2, imu.gyro_rps)
        self._judged(imu, reason)

    def predict_many(self, samples: Sequence[ImuSample]) -> None:
        """A read's samples, in time order: what :meth:`predict` does to each, the common
        ones (good, no gap, tracking) stepped by the C IMU front in one call
        (``ImuFront.step_many``), the others one by one."""
        k, n = 0, len(samples)
        while k < n:
            ekf, prev, t_state = self.ekf, self._imu_t_ns, self.t_ns
            if not (self._front_steps and n - k > 1 and ekf is not None
                    and ekf.core_state is not None and self._relevel is None
                    and prev is not None and t_state is not None):
                self.predict(samples[k])
                k += 1
                continue
            rows, reason = self.imu_check.step_many(
                ekf.core_state, [(s.t_ns, s.acc_mps2, s.gyro_rps) for s in samples[k:]],
                prev, t_state, self.cfg.max_imu_gap_s, PROPAGATE_EVERY_S)
            if rows:
                last = rows[-1]
                self._imu_t_ns = self._good_imu_ns = self.t_ns = last[0]
                self.window.add_rows(rows)
                self._last_imu = (last[1:4], last[4:7])
                k += len(rows)
            if k == n:
                return
            if reason is None:  # not the common sample: the whole policy takes it
                self.predict(samples[k])
            else:  # judged and rejected: the policy takes it from there
                try:
                    self._judged(samples[k], reason)
                except NUMERICAL_ERRORS as err:
                    self._internal_error(samples[k].t_ns, err)
            k += 1

    def _judged(self, imu: ImuSample, reason: str) -> None:
        """A sample after the IMU check (``reason``: why it is rejected, or ""): counted,
        kept in the rest window, integrated (over a rejected one with the last good one),
        coasted over a gap."""
        t_ns, prev = imu.t_ns, self._imu_t_ns
        ekf = self.ekf
        if reason:
            self.counters[reason] += 1
            self.monitor.imu_rejected(t_ns)
        if self._first_t_ns is None:
            self._first_t_ns = t_ns
        self._imu_t_ns = t_ns
        gap_s = 0.0 if prev is None else (t_ns - prev) / NS  # since the last sample of any kind
        if not reason:  # judged raw (full scale is the sensor's), then corrected
            sample = (self._acc_to_body(imu.acc_mps2), self._gyro_to_body(imu.gyro_rps))
            self.window.add(t_ns, *sample)
            self._good_imu_ns = t_ns
        if ekf is None:
            if not reason:
                self._last_imu = sample
            return
        assert self.t_ns is not None
        cfg = self.cfg
        if self._relevel is not None:  # the attitude restarts once fresh samples span a window
            self._relevel_when_ready(t_ns)
            return
        dt = (t_ns - self.t_ns) / NS
        if reason:
            if self.imu_check.burst_s(t_ns) > cfg.attitude_lost_after_s or self._last_imu is None:
                # held that long, the last good sample says nothing: coast on the ranges
                self._lose_attitude(t_ns, "IMU samples rejected")
                return
            sample = self._last_imu  # integrate over the rejected one with the last good one
        elif gap_s > cfg.max_imu_gap_s:
            self.counters["imu_gaps"] += 1
            self._coasted = True
            if dt > 0:  # coasted by the ranges up to their last update; on to this sample
                self._coast(dt)
            self.t_ns = t_ns
            self._last_imu = sample
            if gap_s > cfg.attitude_lost_after_s:
                self._lose_attitude(t_ns, "IMU gap")
            else:
                self.monitor.imu_gap = False
            return
        if dt > 0:
            ekf.predict(sample[0], sample[1], dt)
            if reason:
                self._widen_for_unseen(dt)
            if ekf.interval_s >= PROPAGATE_EVERY_S:
                ekf.propagate()
        self.t_ns = t_ns
        self._last_imu = sample

    def _to_body(self, v: tuple[float, float, float]) -> Vec3:
        """``C_bs v`` in plain floats: this runs for every IMU sample."""
        (a, b, c), (d, e, f), (g, h, i) = self._C
        x, y, z = v
        return (a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z)

    def _imu_fresh(self, t_ns: int | None = None) -> bool:
        """The last IMU sample is at most ``max_imu_gap_s`` older than ``t_ns`` (the
        state's time by default)."""
        now = self.t_ns if t_ns is None else t_ns
        return self._relevel is None and self._good_imu_ns is not None and now is not None \
            and (now - self._good_imu_ns) / NS <= self.cfg.max_imu_gap_s

    def _predict_to(self, t_ns: int) -> None:
        """Bring the state to the measurement time: hold the last IMU sample while it is fresh
        (one IMU period at most, normally); in an IMU gap, coast at constant velocity with
        growing uncertainty, so the ranges keep the position while the IMU is away."""
        ekf = self.ekf
        assert ekf is not None and self.t_ns is not None
        dt = (t_ns - self.t_ns) / NS
        if dt <= 0:
            return
        if self._imu_fresh(t_ns) and self._last_imu is not None:
            ekf.predict(self._last_imu[0], self._last_imu[1], dt)
            self.monitor.imu_gap = False
        else:
            self._coasted = True
            self.monitor.imu_gap = True
            self._coast(dt)
        self.t_ns = t_ns

    def _widen_for_unseen(self, dt: float) -> None:
        """A rejected IMU sample hid ``dt`` of motion: widen velocity and attitude for it."""
        self._inflate(velocity_mps=COAST_ACCEL_SIGMA_MPS2 * math.sqrt(dt),
                      attitude_rad=UNSEEN_RATE_SIGMA_RPS * math.sqrt(dt))
