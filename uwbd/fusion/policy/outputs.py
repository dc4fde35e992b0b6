"""What :class:`~uwbd.fusion.filter.Filter` says of itself (a mixin of it, as
:mod:`.propagation`, :mod:`.recovery` and :mod:`.fusing` are): the pose (its numbers are
the state's, :meth:`~uwbd.fusion.core.eskf.Eskf.pose_numbers`), the health record and the
status's diagnostics."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from uwbd.fusion.checks.anchor_consistency import AnchorConsistency
from uwbd.fusion.checks.mounting_yaw import MountingYaw
from uwbd.fusion.checks.window_raim import WindowRaim
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.fusion.policy.robust import AnchorStats
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import WAITING, Health, Pose

Vec3 = tuple[float, float, float]
NS = 1_000_000_000
MAX_OBSERVABLE_YAW_SIGMA = math.radians(10)  # the heading counts as known below this σ


class FilterOutputs:
    """The filter's outputs, and the state they read (set by the filter)."""

    ekf: Eskf | None
    t_ns: int | None
    _imu_t_ns: int | None
    _good_imu_ns: int | None
    cfg: FilterConfig
    monitor: HealthMonitor
    mirror: MirrorSide
    anchor_stats: dict[int, AnchorStats]
    consistency: AnchorConsistency
    raim: WindowRaim
    lever: Array
    _lever_index: tuple[int, ...]
    mounting_finding: str
    mounting_yaw: MountingYaw
    _aligned: bool
    _restart_not_finite: Callable[[int], None]  # the filter's (recovery)

    def health(self, now_ns: int | None = None) -> Health:
        """The health record, rebuilt from the evidence, at the state's time or at
        ``now_ns`` if later (the daemon's status on the wall clock: silent ports make the
        time since the last range and the last IMU sample grow, and the health says so)."""
        ekf = self.ekf
        t_ns = self.t_ns if self.t_ns is not None else self._imu_t_ns
        if t_ns is None:
            return WAITING
        if now_ns is not None and now_ns > t_ns:
            t_ns = now_ns
        good = self._good_imu_ns
        imu_silent = good is not None and t_ns - good > self.cfg.max_imu_gap_s * NS
        if ekf is None:
            return self.monitor.assess(t_ns, False, False, None, True)
        P = ekf.P
        sigma_xy = math.sqrt(max(P[0, 0] + P[1, 1], 0.0))
        sigma_z = math.sqrt(max(P[2, 2], 0.0))
        finite = math.isfinite(sigma_xy + sigma_z + sum(ekf.p) + sum(ekf.v) + sum(ekf.q))
        return self.monitor.assess(t_ns, True, self.heading_observable(), sigma_xy, finite,
                                   sigma_z, imu_silent, _major_sigma(P[0, 0], P[0, 1], P[1, 1]))

    @property
    def status(self) -> str:
        return self.health().summary()

    def heading_observable(self) -> bool:
        ekf = self.ekf
        return ekf is not None and heading_observable(self._aligned, ekf.yaw_sigma_rad() ** 2)

    def pose(self) -> Pose | None:
        """The pose now, or ``None`` before the start, while restarting, or when any of
        its numbers is not finite (which also restarts the filter)."""
        ekf = self.ekf
        t_ns = self.t_ns
        if ekf is None or t_ns is None:
            return None
        numbers = ekf.pose_numbers(self._aligned)
        if numbers is None:
            self._restart_not_finite(t_ns)
            return None
        covariance, sigma_xy, position, velocity, orientation = numbers
        observable = heading_observable(self._aligned, covariance[35])  # yaw's variance
        health = self.monitor.assess(t_ns, True, observable, sigma_xy, True,
                                     math.sqrt(max(covariance[14], 0.0)), False,  # σz²: [2, 2]
                                     _major_sigma(covariance[0], covariance[1], covariance[7]))
        return Pose(t_ns, position, velocity, orientation, covariance, health.summary(),
                    observable, health)

    def diagnostics(self, now_ns: int | None = None) -> dict[str, Any]:
        """For the status: the health record (at ``now_ns``, as :meth:`health`), the mirror
        side, per-anchor range statistics, findings and the snapshot test's suspects."""
        m = self.mirror
        mounting = self.mounting_finding or self.mounting_yaw.text()
        return {"health": self.health(now_ns).as_dict(),
                "mirror": {"ambiguous": m.ambiguous, "side": "above" if m.sign > 0 else "below",
                           "decided_by": m.decided_by, "resolved": m.resolved},
                "anchors": {str(a): s.as_dict() for a, s in sorted(self.anchor_stats.items())},
                "anchor_findings": [f.as_dict() for _, f in
                                    sorted(self.consistency.findings.items())],
                # the snapshot test fails: the anchors it suspects (checks.window_raim)
                "ranges_inconsistent": list(self.raim.inconsistent),
                # with [fusion] lever_arm_sigma_m: where the data put the antenna (body, m)
                **({"lever_arm_estimate_m": [round(float(c), 4) for c in self.lever]}
                   if self._lever_index and self.ekf is not None else {}),
                **({"mounting_finding": mounting} if mounting else {})}


def heading_observable(aligned: bool, yaw_variance: float) -> bool:
    """The rule: the heading counts as known once aligned and while its σ is under
    ``MAX_OBSERVABLE_YAW_SIGMA`` (the yaw's variance: the nav-z component of ``R δθ``)."""
    return aligned and math.sqrt(max(yaw_variance, 0.0)) < MAX_OBSERVABLE_YAW_SIGMA


def _major_sigma(xx: float, xy: float, yy: float) -> float:
    """σ along the major axis of the horizontal error ellipse (NaN stays NaN)."""
    half = (xx - yy) / 2
    return math.sqrt(max((xx + yy) / 2 + math.sqrt(half * half + xy * xy), 0.0))
