"""The pose a state gives: its covariance over position and attitude in
the navigation frame, and its numbers as the outputs hand them on (docs/ekf.md §1)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from uwbd.fusion.core.layout import P_, TH_
from uwbd.fusion.core.rotation import Array

# a pose's covariance (6×6 row-major over p and the nav-frame attitude), σ_xy, position,
# velocity, orientation (x, y, z, w)
PoseNumbers = tuple[tuple[float, ...], float, tuple[float, float, float],
                    tuple[float, float, float], tuple[float, float, float, float]]


def pose_numbers(p: Sequence[float] | Array, v: Sequence[float] | Array,
                 q: Sequence[float] | Array, R: Array, P: Array, aligned: bool
                 ) -> PoseNumbers | None:
    """The pose's covariance, horizontal σ, position, velocity and orientation (x, y, z,
    w); ``None`` when a number is not finite.

    The covariance is over position and the attitude error turned into the navigation
    frame, ``T P Tᵀ`` with ``T = [[I, 0, 0], [0, 0, R]]`` over (p, v, θ), made
    symmetric; while the heading is not ``aligned`` its σ is a placeholder, so yaw is
    given the variance π², uncorrelated: to a subscriber it is unknown."""
    T = np.zeros((6, TH_.stop))
    T[:3, P_] = np.eye(3)
    T[3:, TH_] = R
    M = T @ P[:TH_.stop, :TH_.stop] @ T.T
    cov = 0.5 * (M + M.T)
    if not aligned:
        cov[5, :] = 0.0
        cov[:, 5] = 0.0
        cov[5, 5] = math.pi**2
    w, x, y, z = q
    if not math.isfinite(sum(p) + sum(v) + w + x + y + z + float(cov.sum())):
        return None
    return (tuple(cov.ravel().tolist()), math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0)),
            (p[0], p[1], p[2]), (v[0], v[1], v[2]), (x, y, z, w))
