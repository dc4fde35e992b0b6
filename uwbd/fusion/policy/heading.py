"""The heading before it is known: held (an EKF linearised about a large yaw error turns
falsely confident within a second of motion) while :class:`~.alignment.HeadingAligner`
compares the INS's velocity changes with the UWB fixes'; once it tells the yaw error, the
EKF takes over with its σ."""

from __future__ import annotations

import math

import numpy as np

from uwbd.fusion.core.layout import BA_, BG_, TH_
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.policy.estimate import Estimate

HELD_YAW_SIGMA_RAD = 1e-3  # the heading's σ while it is held, before the coarse alignment


def hold_heading(est: Estimate, t_ns: int, dv: tuple[float, float, float],
                 fix: LsqFix | None) -> bool:
    """One message while the heading is held (``dv``: the INS's own velocity change since
    the last, ``fix``: the message's UWB fix, if any); True when it aligned the heading."""
    ekf = est.ekf
    assert ekf is not None
    est.aligner.add_ins_dv(dv)
    # the heading is unknown: the INS's horizontal Δv may point anywhere; for a heading
    # error uniform over ±180° the RMS error of a turned Δv is √2 |Δv|, so the fixes
    # must be free to say where it went
    extra = np.zeros(ekf.n)
    extra[3:5] = 2.0 * (dv[0] ** 2 + dv[1] ** 2)
    ekf.add_variances(extra)
    ekf.rotate_heading(0.0, HELD_YAW_SIGMA_RAD)
    if fix is None or not est.aligner.wants_fix(t_ns):
        return False
    # the INS's yaw, and what its horizontal accelerometer and gyro biases may still be
    w, x, y, z = ekf.q
    P = ekf.P
    result = est.aligner.add_fix(
        t_ns, fix, math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
        math.sqrt(max(P[BA_.start, BA_.start] + P[BA_.start + 1, BA_.start + 1], 0) / 2),
        math.sqrt(max(P[BG_.start, BG_.start] + P[BG_.start + 1, BG_.start + 1], 0) / 2),
        math.sqrt(max(P[TH_.start, TH_.start] + P[TH_.start + 1, TH_.start + 1], 0) / 2))
    if result is None:
        return False
    ekf.rotate_heading(*result)
    est.aligned = True
    est.counters["heading_alignments"] += 1
    return True
