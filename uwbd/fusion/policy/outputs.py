"""What :class:`~uwbd.fusion.filter.Filter` says of itself: the pose (its numbers are the
state's, :meth:`~uwbd.fusion.core.eskf.Eskf.pose_numbers`), the health record and the
status's diagnostics, each from the :class:`~.estimate.Estimate` and the findings it is
handed."""

from __future__ import annotations

import math
from typing import Any

from uwbd.fusion.core.pose import PoseNumbers
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.estimate import Estimate, Findings
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.fusion.types import WAITING, Health, Pose

NS = 1_000_000_000
MAX_OBSERVABLE_YAW_SIGMA = math.radians(10)  # the heading counts as known below this σ


def health_at(est: Estimate, t_ns: int | None, good_imu_ns: int | None,
              max_imu_gap_s: float) -> Health:
    """The health record, rebuilt from the evidence at ``t_ns`` (None: nothing seen yet);
    the IMU silent when its last good sample (``good_imu_ns``) is older than the gap."""
    if t_ns is None:
        return WAITING
    ekf = est.ekf
    imu_silent = good_imu_ns is not None and t_ns - good_imu_ns > max_imu_gap_s * NS
    if ekf is None:
        return est.monitor.assess(t_ns, False, False, None, True)
    P = ekf.P
    sigma_xy = math.sqrt(max(P[0, 0] + P[1, 1], 0.0))
    sigma_z = math.sqrt(max(P[2, 2], 0.0))
    finite = math.isfinite(sigma_xy + sigma_z + sum(ekf.p) + sum(ekf.v) + sum(ekf.q))
    observable = heading_observable(est.aligned, ekf.yaw_sigma_rad() ** 2)
    return est.monitor.assess(t_ns, True, observable, sigma_xy, finite, sigma_z, imu_silent,
                              _major_sigma(P[0, 0], P[0, 1], P[1, 1]), float(ekf.p[2]))


def pose_of(est: Estimate, t_ns: int, numbers: PoseNumbers) -> Pose:
    """The pose from the state's finite numbers (``Eskf.pose_numbers``) and its health."""
    covariance, sigma_xy, position, velocity, orientation = numbers
    observable = heading_observable(est.aligned, covariance[35])  # yaw's variance
    health = est.monitor.assess(t_ns, True, observable, sigma_xy, True,
                                math.sqrt(max(covariance[14], 0.0)), False,  # σz²: [2, 2]
                                _major_sigma(covariance[0], covariance[1], covariance[7]),
                                position[2])
    return Pose(t_ns, position, velocity, orientation, covariance, health.summary(),
                observable, health)


def diagnostics(health: Health, mirror: MirrorSide, findings: Findings,
                lever_estimate_m: Array | None) -> dict[str, Any]:
    """For the status: the health record, the mirror side, per-anchor range statistics,
    findings, the lever arm's estimate where it is one."""
    m = mirror
    mounting = findings.mounting_finding or findings.mounting_yaw.text()
    return {"health": health.as_dict(),
            "mirror": {"ambiguous": m.ambiguous, "side": "above" if m.sign > 0 else "below",
                       "decided_by": m.decided_by, "resolved": m.resolved},
            "anchors": {str(a): s.as_dict() for a, s in sorted(findings.anchor_stats.items())},
            "anchor_findings": [f.as_dict() for _, f in
                                sorted(findings.consistency.findings.items())],
            # the bank's separation left these out, and takes each back then (t_ns)
            "anchors_excluded": {str(a): until for a, until in sorted(findings.separated.items())},
            # with [fusion] lever_arm_sigma_m: where the data put the antenna (body, m)
            **({"lever_arm_estimate_m": [round(float(c), 4) for c in lever_estimate_m]}
               if lever_estimate_m is not None else {}),
            # the separation test names an anchor it has not left out (too few others)
            **({"anchor_suspected": {
                "anchor": findings.suspect[0],
                "separation_m": round(findings.suspect[1], 3),
                "finding": f"anchor {findings.suspect[0]}: the estimate without its ranges is "
                           f"{findings.suspect[1]:.2f} m from the one with them, beyond "
                           "chance: its surveyed position or its range offset is likely "
                           "wrong (check the survey, uwbd survey, and the anchor)"}}
               if findings.suspect is not None else {}),
            # the lever-arm test found imu.lever_arm_m off: where it puts the antenna
            **({"lever_arm_finding": {
                "key": "imu.lever_arm_m",
                "estimate_m": [round(float(c), 3) for c in findings.lever_arm_m],
                "finding": "the lever arm looks off: the data put the antenna at ({:+.2f}, "
                           "{:+.2f}, {:+.2f}) m (IMU -> antenna, body axes); check "
                           "imu.lever_arm_m".format(*findings.lever_arm_m)}}
               if findings.lever_arm_m is not None else {}),
            **({"mounting_finding": mounting} if mounting else {})}


def heading_observable(aligned: bool, yaw_variance: float) -> bool:
    """The rule: the heading counts as known once aligned and while its σ is under
    ``MAX_OBSERVABLE_YAW_SIGMA`` (the yaw's variance: the nav-z component of ``R δθ``)."""
    return aligned and math.sqrt(max(yaw_variance, 0.0)) < MAX_OBSERVABLE_YAW_SIGMA


def _major_sigma(xx: float, xy: float, yy: float) -> float:
    """σ along the major axis of the horizontal error ellipse (NaN stays NaN)."""
    half = (xx - yy) / 2
    return math.sqrt(max((xx + yy) / 2 + math.sqrt(half * half + xy * xy), 0.0))
