"""What :class:`~uwbd.fusion.filter.Filter` says of itself (a mixin of it, as
:mod:`.propagation`, :mod:`.recovery` and :mod:`.fusing` are): the pose, on the C core's
``pose_step`` or ``pose_numbers`` where it is built (``pose`` and ``_pose_numbers`` the
reference), the health record and
the status's diagnostics."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from uwbd.fusion import native
from uwbd.fusion.eskf import TH_, Eskf
from uwbd.fusion.health import NS, WAITING, Health, HealthMonitor, Phase
from uwbd.fusion.mirror import MirrorSide
from uwbd.fusion.robust import AnchorStats
from uwbd.fusion.rotation import Array
from uwbd.fusion.types import Pose

Vec3 = tuple[float, float, float]
MAX_OBSERVABLE_YAW_SIGMA = math.radians(10)  # the heading counts as known below this σ


class FilterOutputs:
    """The filter's outputs, and the state they read (set by the filter)."""

    ekf: Eskf | None
    t_ns: int | None
    _imu_t_ns: int | None
    monitor: HealthMonitor
    mirror: MirrorSide
    anchor_stats: dict[int, AnchorStats]
    _aligned: bool
    _pose_map: Array  # (p, v, θ) -> (p, R θ), its R rows filled per pose
    _restart_not_finite: Callable[[int], None]  # the filter's (recovery)
    pose_step: Any  # the C core's common pose (functools.partial), or None: the reference

    def _pose_parts(self) -> tuple[Any, ...]:
        """What the C core's common pose (``_core.pose_step``, ``_pose.c``) reads, in that
        file's order: the namespaces of this filter and its health monitor, the monitor's
        limits (the fault hold in ns), the types it makes, the two phases it gives and
        their summaries."""
        lim = self.monitor.limits
        numbers = (lim.imu_fault_hold_s * NS, lim.range_timeout_s, lim.max_sigma_m,
                   lim.coast_after_s, MAX_OBSERVABLE_YAW_SIGMA)
        return (vars(self), vars(self.monitor), tuple(map(float, numbers)), Pose, Health,
                Phase.TRACKING, Phase.ALIGNING, Phase.TRACKING.value, Phase.ALIGNING.value)

    def health(self) -> Health:
        """The health record, rebuilt from the evidence now."""
        ekf = self.ekf
        t_ns = self.t_ns if self.t_ns is not None else self._imu_t_ns
        if t_ns is None:
            return WAITING
        if ekf is None:
            return self.monitor.assess(t_ns, False, False, None, True)
        P = ekf.P
        sigma_xy = math.sqrt(max(P[0, 0] + P[1, 1], 0.0))
        finite = math.isfinite(sigma_xy + sum(ekf.p) + sum(ekf.v) + sum(ekf.q))
        return self.monitor.assess(t_ns, True, self.heading_observable(), sigma_xy, finite)

    @property
    def status(self) -> str:
        return self.health().summary()

    def heading_observable(self) -> bool:
        ekf = self.ekf
        return ekf is not None and self._aligned and ekf.yaw_sigma_rad() < MAX_OBSERVABLE_YAW_SIGMA

    def pose(self) -> Pose | None:
        """The pose now, or ``None`` before the start, while restarting, or when any of
        its numbers is not finite (which also restarts the filter)."""
        step = self.pose_step
        if step is not None:  # the common pose, whole, on the C core
            pose: Pose | None = step()
            if pose is not NotImplemented:
                return pose
        ekf = self.ekf
        t_ns = self.t_ns
        if ekf is None or t_ns is None:
            return None
        core = native.core
        if core is not None:  # the numbers in one call (_pose_numbers: the reference)
            ekf.P = np.ascontiguousarray(ekf.P)
            numbers = core.pose_numbers(ekf.P, ekf.q, ekf.p, ekf.v, self._aligned,
                                        MAX_OBSERVABLE_YAW_SIGMA)
        else:
            numbers = self._pose_numbers(ekf)
        if numbers is None:
            self._restart_not_finite(t_ns)
            return None
        covariance, sigma_xy, observable, position, velocity, orientation = numbers
        health = self.monitor.assess(t_ns, True, observable, sigma_xy, True)
        return Pose(t_ns, position, velocity, orientation, covariance, health.summary(),
                    observable, health)

    def _pose_numbers(self, ekf: Eskf) -> tuple[tuple[float, ...], float, bool, Vec3, Vec3,
                                                tuple[float, float, float, float]] | None:
        """The pose's covariance, horizontal σ, whether the heading is observable, position,
        velocity and orientation (x, y, z, w); ``None`` when a number is not finite.

        The covariance over position and the attitude error turned into the navigation
        frame is one product, ``T P Tᵀ`` with ``T = [[I, 0, 0], [0, 0, R]]`` over (p, v, θ)
        (measured: half the time of the same in plain floats)."""
        w, x, y, z = ekf.q
        T = self._pose_map
        T[3:, TH_] = ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
                      (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
                      (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))
        M = T @ ekf.P[:TH_.stop, :TH_.stop] @ T.T
        cov = tuple((0.5 * (M + M.T)).ravel().tolist())  # symmetric, as ROS expects
        if not self._aligned:  # held, its σ a placeholder: to a subscriber, yaw is unknown
            cov = _yaw_unknown(cov)
        p, v = ekf.p, ekf.v
        if not math.isfinite(sum(p) + sum(v) + w + x + y + z + sum(cov)):
            return None
        # the heading's σ is the nav-z attitude error's (yaw_sigma_rad)
        observable = self._aligned and math.sqrt(max(cov[35], 0.0)) < MAX_OBSERVABLE_YAW_SIGMA
        return (cov, math.sqrt(max(cov[0] + cov[7], 0.0)), observable, (p[0], p[1], p[2]),
                (v[0], v[1], v[2]), (x, y, z, w))

    def diagnostics(self) -> dict[str, Any]:
        """For the status: the health record, the mirror side, per-anchor range statistics."""
        m = self.mirror
        return {"health": self.health().as_dict(),
                "mirror": {"ambiguous": m.ambiguous, "side": "above" if m.sign > 0 else "below",
                           "decided_by": m.decided_by, "resolved": m.resolved},
                "anchors": {str(a): s.as_dict() for a, s in sorted(self.anchor_stats.items())}}


def _yaw_unknown(covariance: tuple[float, ...]) -> tuple[float, ...]:
    """The pose covariance (6×6 over position and nav-frame attitude, row-major) with the
    yaw's variance π² and no correlation: what a heading not yet aligned is worth."""
    cov = list(covariance)
    for i in range(6):
        cov[6 * i + 5] = cov[30 + i] = 0.0
    cov[35] = math.pi**2
    return tuple(cov)
