"""Coarse heading alignment: the yaw error from velocity changes, INS against UWB.

A yaw error ψ turns every velocity change the INS integrates by ψ about the vertical. The
aligner keeps, at about 10 Hz, the UWB least-squares fixes and the INS's own cumulative
horizontal Δv (``Σ R f Δt``, untouched by measurements). Over windows of 1, 2 and 3 times
``window_s`` back, it compares the fixes' horizontal velocity change (line fits over one
second at both ends) with the INS's; once both exceed ``min_dv_mps``, the angle between them
is the yaw error, with σ = atan(σ_Δv / |Δv|) (σ_Δv: the fixes' line-fit error), at least
3°. A window whose σ is above 30° is not used: an EKF linearised about a heading that
uncertain turns falsely confident. (Adding what the INS's tilt and accelerometer-bias σ
from the covariance do to its Δv was tried: that σ is pessimistic enough that a drone or
a slow handheld run never aligned.)
"""

from __future__ import annotations

import collections
import math

import numpy as np

from uwbd.fusion.lsq import LsqFix
from uwbd.fusion.rotation import Array

SAMPLE_NS = 95_000_000  # fixes for the alignment: about 10 Hz
FIT_NS = 1_000_000_000  # each end's velocity: a line fit over one second of fixes
MIN_FIT_FIXES = 5
MIN_SIGMA_RAD = math.radians(3)
MAX_SIGMA_RAD = math.radians(30)  # a less certain heading waits for more motion


class HeadingAligner:
    def __init__(self, window_s: float, min_dv_mps: float, fix_sigma_m: float) -> None:
        self.window_ns = int(window_s * 1e9)
        self.min_dv_mps = min_dv_mps
        self._fix_sigma_m = fix_sigma_m
        self._fixes: collections.deque[tuple[int, Array]] = collections.deque()
        self._ins_dv: collections.deque[tuple[int, float, float]] = collections.deque()
        self._dv_xy = [0.0, 0.0]

    def add_ins_dv(self, dv_n: tuple[float, float, float]) -> None:
        """The INS's velocity change over the last propagation interval (navigation frame)."""
        self._dv_xy[0] += dv_n[0]
        self._dv_xy[1] += dv_n[1]

    def wants_fix(self, t_ns: int) -> bool:
        return not self._fixes or t_ns - self._fixes[-1][0] >= SAMPLE_NS

    def add_fix(self, t_ns: int, fix: LsqFix) -> tuple[float, float] | None:
        """Record a fix; returns (yaw error, its σ) once the heading can be told, else None."""
        self._fixes.append((t_ns, fix.position_m))
        self._fix_sigma_m = float(np.sqrt(max(np.trace(fix.covariance[:2, :2]) / 2, 1e-4)))
        self._ins_dv.append((t_ns, self._dv_xy[0], self._dv_xy[1]))
        horizon_ns = 3 * self.window_ns + 2 * FIT_NS
        for history in (self._ins_dv, self._fixes):
            while history and history[0][0] < t_ns - horizon_ns:
                history.popleft()
        return self._heading_error(t_ns)

    def _heading_error(self, t_ns: int) -> tuple[float, float] | None:
        end = [(t, p) for t, p in self._fixes if t >= t_ns - FIT_NS]
        if len(end) < MIN_FIT_FIXES:
            return None
        v1, t1 = velocity_fit(end)
        times = np.array([t for t, _, _ in self._ins_dv], dtype=float)
        cum = np.array([(x, y) for _, x, y in self._ins_dv])
        for k in (1, 2, 3):
            w_ns = k * self.window_ns
            if times[0] > t_ns - w_ns:
                return None  # not that much history yet
            start = [(t, p) for t, p in self._fixes if t_ns - w_ns <= t < t_ns - w_ns + FIT_NS]
            if len(start) < MIN_FIT_FIXES:
                continue
            v0, t0 = velocity_fit(start)
            dv_uwb = v1 - v0
            dv_ins = np.array([np.interp(t1, times, cum[:, i]) - np.interp(t0, times, cum[:, i])
                               for i in range(2)])
            size = min(float(np.linalg.norm(dv_uwb)), float(np.linalg.norm(dv_ins)))
            if size < self.min_dv_mps:
                continue
            dpsi = math.atan2(dv_ins[0] * dv_uwb[1] - dv_ins[1] * dv_uwb[0],
                              dv_ins[0] * dv_uwb[0] + dv_ins[1] * dv_uwb[1])
            # the angle error is the Δv error across the Δv over its length; that error is a
            # line-fit velocity's (one second of fixes with their own horizontal σ) at each end
            sigma_v = self._fix_sigma_m * math.sqrt(12 / len(end)) * math.sqrt(2)
            sigma = max(math.atan2(sigma_v, size), MIN_SIGMA_RAD)
            if sigma <= MAX_SIGMA_RAD:  # else the EKF, linearised about it, would go astray
                return dpsi, sigma
        return None


def velocity_fit(fixes: list[tuple[int, Array]]) -> tuple[Array, float]:
    """Horizontal velocity (m/s) of a straight-line fit through fixes, and its mid time (ns)."""
    t = np.array([t for t, _ in fixes], dtype=float)
    p = np.array([p[:2] for _, p in fixes])
    tm = float(t.mean())
    dt = (t - tm) / 1e9
    v = (dt @ (p - p.mean(axis=0))) / max(float(dt @ dt), 1e-9)
    return v, tm
