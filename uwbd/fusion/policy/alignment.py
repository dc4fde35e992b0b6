"""Coarse heading alignment: the yaw error from velocity changes, INS against UWB.

A yaw error ψ turns every velocity change the INS integrates by ψ about the vertical. The
aligner keeps, at about 10 Hz, the UWB least-squares fixes, the INS's own cumulative
horizontal Δv (``Σ R f Δt``, untouched by measurements) and the INS's yaw. It fits the
fixes' velocities (line fits over consecutive seconds, back over 3 × ``window_s`` and one
second) as ``v = Rot(ψ) v_ins + v0 + c τ − J β − K γ``, with ``v0`` the INS's unknown
start velocity and three INS errors the held heading leaves uncorrected, each with the σ
the filter's covariance gives it as a prior:

* ``c``, a constant acceleration in the navigation frame: a tilt error (``g × δθ``). A
  start while moving levels the tilt on the vehicle's own acceleration (in a steady turn,
  the centripetal one), so ``c`` is as large as the accelerations that tell the heading:
  comparing raw Δv's, a run joined on a 4 m circle was turned 35-110° off with σ 7-16°;
* ``β``, the accelerometer bias, and ``γ``, ``g ×`` the horizontal gyro bias (it tilts
  the INS as it runs), both fixed to the body, so turned with it (``J = ∫ Rot(yaw) dt``,
  ``K = ∫ J dt``). In a steady turn a body-fixed error looks like a yaw error: the priors
  put that in σ.

ψ's σ is the fit's (the fixes' line-fit error), widened by its χ² when worse and by the
spread of the fits leaving out one second each (one span's velocity off, as along an NLOS
stretch, hides in χ²), at least 3°. The fit needs four seconds of fixes and the velocity
to have changed by ``min_dv_mps``. The EKF takes over with that σ: one of 10° or less at
once, one up to 30° only once it has settled (not 1.25× smaller than a second before: the
motion gives no more), above 30° never (an EKF linearised about a heading that uncertain
turns falsely confident; at 15-25° it already drifts while its σ shrinks).
"""

from __future__ import annotations

import bisect
import collections
import math
import statistics

import numpy as np

from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.noise import GRAVITY_MPS2
from uwbd.fusion.core.rotation import Array

SAMPLE_NS = 95_000_000  # fixes for the alignment: about 10 Hz
FIT_NS = 1_000_000_000  # each end's velocity: a line fit over one second of fixes
MIN_FIT_FIXES = 5
MIN_FITS = 4  # spans of fixes fitted: v0 and c take two, the rotation the rest
MIN_SIGMA_RAD = math.radians(3)
MAX_SIGMA_RAD = math.radians(30)  # a less certain heading waits for more motion
GOOD_SIGMA_RAD = math.radians(10)  # taken at once; up to MAX_SIGMA_RAD once σ has settled
SETTLE_RATIO = 1.25  # settled: σ a second ago at most this much larger


class HeadingAligner:
    def __init__(self, window_s: float, min_dv_mps: float, fix_sigma_m: float) -> None:
        self.window_ns = int(window_s * 1e9)
        self.min_dv_mps = min_dv_mps
        self._fix_sigma_m = fix_sigma_m
        self.max_fits = max(MIN_FITS, (3 * self.window_ns + FIT_NS) // FIT_NS)
        self._fixes: collections.deque[tuple[int, Array]] = collections.deque()
        # per fix: time, the INS's cumulative Δv (x, y), and J, K as (∫cos, ∫sin) pairs
        self._ins_dv: collections.deque[tuple[int, float, float, float, float, float, float]] \
            = collections.deque()
        self._dv_xy = [0.0, 0.0]
        self._last_yaw: tuple[int, float] | None = None
        self._jk = [0.0, 0.0, 0.0, 0.0]
        self._prior_sigma = (math.inf, 0.0, 0.0)  # g × tilt, accelerometer bias, g × gyro bias
        self._sigmas: collections.deque[tuple[int, float]] = collections.deque()  # (t, σ)

    def add_ins_dv(self, dv_n: tuple[float, float, float]) -> None:
        """The INS's velocity change over the last propagation interval (navigation frame)."""
        self._dv_xy[0] += dv_n[0]
        self._dv_xy[1] += dv_n[1]

    def wants_fix(self, t_ns: int) -> bool:
        return not self._fixes or t_ns - self._fixes[-1][0] >= SAMPLE_NS

    def add_fix(self, t_ns: int, fix: LsqFix, yaw_rad: float = 0.0,
                acc_bias_sigma_mps2: float = 0.0, gyro_bias_sigma_rps: float = 0.0,
                tilt_sigma_rad: float = math.inf) -> tuple[float, float] | None:
        """Record a fix with the INS's yaw and the σ of its horizontal accelerometer bias, gyro
        bias and tilt now; returns (yaw error, its σ) once the heading can be told, else None."""
        self._fixes.append((t_ns, fix.position_m))
        self._fix_sigma_m = float(np.sqrt(max(np.trace(fix.covariance[:2, :2]) / 2, 1e-4)))
        if self._last_yaw is not None:  # J and K by the trapezoid rule over the fix interval
            t0, yaw0 = self._last_yaw
            dt = (t_ns - t0) / 1e9
            mid = yaw0 + math.remainder(yaw_rad - yaw0, math.tau) / 2
            j = self._jk
            dj = (math.cos(mid) * dt, math.sin(mid) * dt)
            j[2] += (j[0] + dj[0] / 2) * dt
            j[3] += (j[1] + dj[1] / 2) * dt
            j[0] += dj[0]
            j[1] += dj[1]
        self._last_yaw = (t_ns, yaw_rad)
        self._prior_sigma = (GRAVITY_MPS2 * tilt_sigma_rad, acc_bias_sigma_mps2,
                             GRAVITY_MPS2 * gyro_bias_sigma_rps)
        ja, jb, ka, kb = self._jk
        self._ins_dv.append((t_ns, self._dv_xy[0], self._dv_xy[1], ja, jb, ka, kb))
        horizon_ns = 3 * self.window_ns + 2 * FIT_NS
        for history in (self._ins_dv, self._fixes):
            while history and history[0][0] < t_ns - horizon_ns:
                history.popleft()
        return self._heading_error(t_ns)

    def _heading_error(self, t_ns: int) -> tuple[float, float] | None:
        # the fixes' velocity over consecutive FIT_NS spans back from now, against the INS's
        # at each span's mid time (the fixes and the history are in time order: each span's
        # fixes are a slice, found by bisection)
        history = list(self._ins_dv)
        times = [float(h[0]) for h in history]
        fix_times = [t for t, _ in self._fixes]
        spans: list[tuple[int, int]] = []  # index ranges into the fixes, newest first
        end = t_ns
        while len(spans) < self.max_fits and end - FIT_NS >= times[0]:
            span = (bisect.bisect_right(fix_times, end - FIT_NS),
                    bisect.bisect_right(fix_times, end))
            end -= FIT_NS
            if span[1] - span[0] < MIN_FIT_FIXES:
                if not spans:
                    return None
                break  # a gap in the fixes: the history before it is not used
            spans.append(span)
        if len(spans) < MIN_FITS:
            return None
        v_uwb, tau = _span_velocities(fix_times, self._fixes, spans, t_ns)
        ins = [_interpolated(t_ns + t * 1e9, times, history) for t in tau]
        n_fit = [hi - lo for lo, hi in spans]
        moved = np.array(v_uwb) - v_uwb[0]
        if float(np.max(np.hypot(moved[:, 0], moved[:, 1]))) < self.min_dv_mps:
            return None  # the velocity has hardly changed: wait for more motion
        # whitened by the fixes' line-fit error; (v0, c, β, γ) are linear, each a 2-D
        # rotation-like pair of columns, so projecting them out commutes with turning every
        # point alike and the best ψ is the angle between what is left of both sides
        n = len(tau)
        sigma_v = self._fix_sigma_m * math.sqrt(12 / statistics.median(n_fit)) / (FIT_NS / 1e9)
        S = np.zeros((2 * n + 6, 2))  # Rot(ψ) v_ins = S (cos ψ, sin ψ)
        A = np.zeros((2 * n + 6, 8))
        y = np.zeros(2 * n + 6)
        for i, (t, v, (sx, sy, ja, jb, ka, kb)) in enumerate(zip(tau, v_uwb, ins, strict=True)):
            S[2 * i:2 * i + 2] = ((sx, -sy), (sy, sx))
            A[2 * i:2 * i + 2] = ((1, 0, t, 0, -ja, jb, -ka, kb), (0, 1, 0, t, -jb, -ja, -kb, -ka))
            y[2 * i:2 * i + 2] = v
        S[:2 * n] /= sigma_v
        A[:2 * n] /= sigma_v
        y[:2 * n] /= sigma_v
        for k, prior in enumerate(self._prior_sigma):  # c, β, γ ~ N(0, σ²): rows 0 = x / σ
            for axis in range(2):
                A[2 * n + 2 * k + axis, 2 + 2 * k + axis] = 1 / min(max(prior, 1e-9), 1e9)
        fit = _rotation_fit(S, A, y)
        if fit is None:
            return None
        dpsi, sigma, chi2 = fit
        dof = 2 * n + 6 - 9
        sigma *= math.sqrt(max(1.0, chi2 / dof))  # a fit worse than the fixes' noise: wider
        # one span's velocity off (an NLOS stretch moves the fixes smoothly) hides in χ²:
        # the spread of the fits without each span in turn (the jackknife) shows it
        turns = np.array([math.remainder(other - dpsi, math.tau) if math.isfinite(other)
                          else math.pi for other in _turns_leaving_out_each_span(S, A, y)])
        sigma = max(sigma, math.sqrt((n - 1) / n * float(np.sum((turns - turns.mean()) ** 2))))
        sigma = max(sigma, MIN_SIGMA_RAD)
        # the EKF takes over with σ (above 30° it would go astray, linearised about a heading
        # that uncertain, and above 10-15° it is already less robust): a σ still falling as
        # the motion goes on is waited for, one that has settled is taken
        recent = self._sigmas
        recent.append((t_ns, sigma))
        while recent[0][0] < t_ns - FIT_NS:
            recent.popleft()
        settled = t_ns - recent[0][0] >= FIT_NS - SAMPLE_NS and \
            recent[0][1] <= SETTLE_RATIO * sigma
        if sigma <= GOOD_SIGMA_RAD or (sigma <= MAX_SIGMA_RAD and settled):
            return dpsi, sigma
        return None


def _rotation_fit(S: Array, A: Array, y: Array) -> tuple[float, float, float] | None:
    """The turn ψ best fitting ``y = S (cos ψ, sin ψ) + A x`` (whitened, x free), its σ and
    the fit's χ²."""
    # what of S and y the columns of A cannot explain: projected out with A's QR (A has full
    # column rank, by the priors' rows)
    Q, _ = np.linalg.qr(A)
    both = np.column_stack((S, y))
    left = both - Q @ (Q.T @ both)
    ps, py = left[:, :2], left[:, 2]
    signal2 = float(np.sum(ps[:, 0] ** 2))  # both columns alike
    if not signal2 > 1e-12:
        return None
    dpsi = math.atan2(float(ps[:, 1] @ py), float(ps[:, 0] @ py))
    residual = py - ps @ np.array([math.cos(dpsi), math.sin(dpsi)])
    return dpsi, 1 / math.sqrt(signal2), float(residual @ residual)


def _span_velocities(fix_times: list[int], fixes: collections.deque[tuple[int, Array]],
                     spans: list[tuple[int, int]], t_ns: int) -> tuple[Array, list[float]]:
    """:func:`velocity_fit` over each span of fixes (adjacent index ranges, newest first),
    all at once from sums over the spans: each span's horizontal velocity, and its mid time
    in seconds from ``t_ns``."""
    first, last = spans[-1][0], spans[0][1]
    t = (np.array(fix_times[first:last], dtype=np.int64) - t_ns) / 1e9  # exact, then s
    p = np.array([fixes[k][1][:2] for k in range(first, last)])
    starts = np.array([lo for lo, _ in reversed(spans)]) - first
    n = np.array([hi - lo for lo, hi in reversed(spans)], dtype=float)
    sums = np.add.reduceat(np.column_stack((t, t * t, p, t[:, None] * p)), starts, axis=0)
    tm = sums[:, 0] / n
    var_t = np.maximum(sums[:, 1] - tm * sums[:, 0], 1e-9)  # Σ (t − t̄)²
    v = (sums[:, 4:6] - tm[:, None] * sums[:, 2:4]) / var_t[:, None]  # Σ (t − t̄)(p − p̄) / …
    return v[::-1], tm[::-1].tolist()


def _turns_leaving_out_each_span(S: Array, A: Array, y: Array) -> Array:
    """ψ of :func:`_rotation_fit` without each span's two rows in turn (NaN where nothing is
    left to fit): the fits stacked, one batched QR (measured: a tenth of the fits one by
    one; the same numbers to rounding)."""
    n = (len(y) - 6) // 2
    keep = np.array([np.r_[0:2 * i, 2 * i + 2:len(y)] for i in range(n)])
    Q, _ = np.linalg.qr(A[keep])
    both = np.concatenate((S[keep], y[keep][:, :, None]), axis=2)
    left = both - Q @ (Q.transpose(0, 2, 1) @ both)
    ps0, ps1, py = left[:, :, 0], left[:, :, 1], left[:, :, 2]
    turns = np.arctan2(np.einsum("ij,ij->i", ps1, py), np.einsum("ij,ij->i", ps0, py))
    turns[~(np.einsum("ij,ij->i", ps0, ps0) > 1e-12)] = math.nan
    return turns


def _interpolated(t: float, times: list[float],
                  history: list[tuple[int, float, float, float, float, float, float]]
                  ) -> tuple[float, ...]:
    """The history's six values at ``t``, linear between samples and held beyond the ends:
    ``np.interp`` per column, in the same arithmetic, with one search for all six."""
    j = bisect.bisect_right(times, t) - 1
    if j < 0:
        return history[0][1:]
    if j >= len(times) - 1:
        return history[-1][1:]
    t0 = times[j]
    if t == t0:
        return history[j][1:]
    a, b, span = history[j], history[j + 1], times[j + 1] - t0
    return tuple((b[i] - a[i]) / span * (t - t0) + a[i] for i in range(1, 7))


def velocity_fit(fixes: list[tuple[int, Array]]) -> tuple[Array, float]:
    """Horizontal velocity (m/s) of a straight-line fit through fixes, and its mid time (ns)."""
    t = np.array([t for t, _ in fixes], dtype=float)
    p = np.array([p[:2] for _, p in fixes])
    tm = float(t.mean())
    dt = (t - tm) / 1e9
    v = (dt @ (p - p.mean(axis=0))) / max(float(dt @ dt), 1e-9)
    return v, tm
