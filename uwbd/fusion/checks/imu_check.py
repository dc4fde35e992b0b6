"""IMU integrity: which samples can be real, judged one at a time before fusion.

A sample is rejected, and counted by reason, when it

* holds a non-finite number (``imu_not_finite``);
* reads at or near the sensor's full scale on any axis (``imu_saturated``): a clipped
  reading says only that the true value was at least that large, and a shaken or
  glitching sensor pins there;
* jumps from the last accepted sample by more than a body can change between two samples
  (``imu_jump``): a corrupted word on the line. Only a short run of samples may be rejected
  for a jump; then the new level is taken as real (a collision is a real step).

The filter integrates over a rejected sample with the last accepted one, and
:attr:`ImuCheck.burst_s` tells how long the current run of rejected samples has lasted so
that the filter can widen its covariance for what it did not see, and treat its attitude
as lost after a long burst.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from uwbd.fusion.checks.intrinsics import BodyMaps
from uwbd.fusion.core.layout import IMU_LIMITS, IMU_MAPS
from uwbd.fusion.core.native import Core

# why a sample is rejected: the health's words, handed to the C front as they are
NOT_FINITE, SATURATED, JUMP = "imu_not_finite", "imu_saturated", "imu_jump"

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ImuLimits:
    """The sensor's full scale (per axis) and the largest credible sample-to-sample change.

    Defaults: the common ±16 g, ±2000 °/s ranges; a change of 8 g or 25 rad/s in one
    sample period is far beyond vibration or handling at the usual 100-1000 Hz."""

    acc_full_scale_mps2: float = 16 * 9.80665
    gyro_full_scale_rps: float = math.radians(2000.0)
    saturation_fraction: float = 0.98  # this close to full scale counts as clipped
    max_acc_jump_mps2: float = 8 * 9.80665
    max_gyro_jump_rps: float = 25.0
    max_jump_run: int = 3  # a jump rejects at most this many samples in a row


class ImuCheck:
    """Judges samples (sensor axes); keeps the last accepted one and the rejected run."""

    def __init__(self, limits: ImuLimits) -> None:
        self.limits = limits
        self.acc_clip = limits.saturation_fraction * limits.acc_full_scale_mps2
        self.gyro_clip = limits.saturation_fraction * limits.gyro_full_scale_rps
        self.last_good: tuple[Vec3, Vec3] | None = None
        self._jump_run = 0
        self._burst_start_ns: int | None = None
        self._last_ns: int | None = None

    def judge(self, t_ns: int, acc: Vec3, gyro: Vec3) -> str:
        """``""`` when the sample may be used, else the reason it may not."""
        reason = self._reason(acc, gyro)
        if reason:
            if self._burst_start_ns is None:
                self._burst_start_ns = self._last_ns if self._last_ns is not None else t_ns
        else:
            self.last_good = (acc, gyro)
            self._burst_start_ns = None
        self._last_ns = t_ns
        return reason

    def burst_s(self, t_ns: int) -> float:
        """How long samples have been rejected without a break (0 when the last was good)."""
        return 0.0 if self._burst_start_ns is None else (t_ns - self._burst_start_ns) / 1e9

    def _reason(self, acc: Vec3, gyro: Vec3) -> str:
        if not math.isfinite(acc[0] + acc[1] + acc[2] + gyro[0] + gyro[1] + gyro[2]):
            return NOT_FINITE  # NaN and inf propagate through the sum
        a, g = self.acc_clip, self.gyro_clip
        if (abs(acc[0]) >= a or abs(acc[1]) >= a or abs(acc[2]) >= a
                or abs(gyro[0]) >= g or abs(gyro[1]) >= g or abs(gyro[2]) >= g):
            return SATURATED
        last = self.last_good
        if last is not None and self._jump_run < self.limits.max_jump_run:
            (la, lg), lim = last, self.limits
            if (math.dist(acc, la) > lim.max_acc_jump_mps2
                    or math.dist(gyro, lg) > lim.max_gyro_jump_rps):
                self._jump_run += 1
                return JUMP
        self._jump_run = 0
        return ""


def new_imu_check(limits: ImuLimits, maps: BodyMaps, core: Core) -> Any:
    """An :class:`ImuCheck` (``core`` None), or on the C core its twin, the IMU front
    (``core/_imu.c``: the same screen with the same methods, which also maps a good sample
    with ``maps`` and integrates it in the same call, ``step``:
    :mod:`~uwbd.fusion.policy.propagation`)."""
    check = ImuCheck(limits)
    if core is None:
        return check
    screen = {"acc_clip": check.acc_clip, "gyro_clip": check.gyro_clip,
              "max_acc_jump": limits.max_acc_jump_mps2,
              "max_gyro_jump": limits.max_gyro_jump_rps, "max_jump_run": limits.max_jump_run}
    numbers = [float(x) for name in IMU_MAPS
               for x in np.ravel(getattr(maps, name))]  # (in layout.py's order, as the C reads)
    return core.ImuFront(tuple(screen[name] for name in IMU_LIMITS), numbers,
                         (NOT_FINITE, SATURATED, JUMP, ""))
