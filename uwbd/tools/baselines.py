"""The methods uwbd is measured against, kept as code paths (see docs/ekf.md for the main one).

* :class:`PureIns`: the filter's start-up, then the strapdown alone (no UWB after that).
* :class:`UwbLeastSquares`: one Gauss-Newton fix per epoch, or per 0.1 s of single ranges.
* :class:`StaticPoints`: the thesis's static-point filtering: those fixes, averaged while the
  vehicle is at rest (a running mean from the start of the rest), one by one otherwise.
* :class:`ComplementaryAttitude`: Mahony-style attitude from gyro, pulled towards the gravity
  direction of the accelerometer, whose signal first passes a 2nd-order Butterworth low-pass
  (fs 200 Hz, fc 2 Hz by default, designed by scipy), with the thesis's dual gain: one gain
  while turning or accelerating, another otherwise (:class:`Gains`).
* :class:`Kf4`: the thesis's loosely coupled filter: a 4-state ``[px py vx vy]`` Kalman
  filter (filterpy), driven by the horizontal acceleration that the complementary attitude
  puts into the navigation frame, corrected by UWB fixes (the static point while at rest)
  that pass the anchor-count check and lie within 1 m of the prediction.

Each has ``predict(imu)``, ``update(uwb)`` and ``position()`` like the main filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.signal import butter, sosfilt_zi

from drivers.frames import ImuSample, UwbRanges
from uwbd.fusion.core import native
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.noise import GRAVITY_MPS2
from uwbd.fusion.core.rotation import (
    Array,
    quat_from_euler,
    quat_from_rotvec,
    quat_mul,
    quat_to_matrix,
)
from uwbd.fusion.filter import Filter
from uwbd.fusion.policy.fixes import RangeWindow
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness
from uwbd.fusion.settings import FilterConfig

# -- motion state of the dual-gain attitude filter ------------------------------------------
# Turning: |ω − b|, the rate low-passed over MOTION_TAU_S, above TURN_RATE_RPS (11 °/s). That
# is well above what a still or steadily moving vehicle shows (gyro noise after the low-pass,
# ~0.001 rad/s here; the bias left after the rest average, < 0.01 rad/s; the sway of a hand
# or of a hovering drone, up to ~0.1 rad/s) and below deliberate turns (the simulator's
# 0.3 rad/s, a ground robot's 0.3–1 rad/s).
TURN_RATE_RPS = 0.2
MOTION_TAU_S = 0.1  # the rate's low-pass: vibration out, a turn's start kept (< 0.2 s late)
# Accelerating: | |f| − g_ref | above ACCEL_MPS2, f the Butterworth-low-passed specific force
# (vibration out) and g_ref its size at rest (the accelerometer's scale error in: i-ASL's UM7
# reads 10.36 m/s² at rest, 0.55 above g). 0.5 m/s² is above the accelerometer's noise after
# the low-pass (~0.01 m/s²) and its bias drift (~0.1 m/s²). The size of f moves with vertical
# acceleration one for one but with horizontal acceleration a_h only as a_h²/2g, so this test
# sees horizontal accelerations above √(2 g · 0.5) ≈ 3.1 m/s² only (turns it leaves to the
# gyro test; the simulator's ~2 m/s² starts and stops pass unseen); that is the thesis's
# test, kept as it is.
ACCEL_MPS2 = 0.5


@dataclass(frozen=True)
class Gains:
    """The gain ``k_p`` on the accelerometer's gravity correction, per motion state.

    Physically ``1/k_p`` is how long (s) the filter trusts its gyro integration before the
    accelerometer's "up" has pulled the tilt most of the way (the correction's time
    constant): a high gain follows the accelerometer within ~0.5 s (k_p 2), a low one averages
    it over ~5 s (k_p 0.2). While the vehicle accelerates (speeds up, brakes, or turns: the
    centripetal v·ω) the accelerometer measures that acceleration as well as gravity, its
    "up" tilted by about ``a_h / g`` (0.1 rad for 1 m/s²), so a high gain then pulls the
    attitude towards a wrong vertical; at rest or at steady speed in a straight line it
    measures gravity alone, and a high gain there only makes the tilt follow its noise more
    closely.

    * :data:`THESIS_GAINS` (k_p 2 while turning or accelerating, 0.2 otherwise) is the
      thesis as the issue words it: it leans on the accelerometer exactly while it is
      disturbed; a reason for it could be quick correction when the gyro's scale-factor and
      misalignment errors grow (during rotations).
    * :data:`SWAPPED_GAINS` (0.2 while turning or accelerating, 2 otherwise) is the usual
      adaptive-gain rule: ride the gyro through the disturbance, re-level quickly when the
      accelerometer measures gravity alone.
    * ``Gains(1.0, 1.0)``: one fixed gain (the baseline before the thesis's switching).
    """

    moving: float  # turning or accelerating
    still: float  # otherwise (at rest, or at steady speed in a straight line)


THESIS_GAINS = Gains(moving=2.0, still=0.2)
SWAPPED_GAINS = Gains(moving=0.2, still=2.0)


class PureIns:
    """Initialised like the main filter (at rest, from UWB), then inertial only."""

    def __init__(self, config: FilterConfig) -> None:
        self.filter = Filter(config)

    def predict(self, imu: ImuSample) -> None:
        self.filter.predict(imu)

    def update(self, uwb: UwbRanges) -> None:
        if self.filter.ekf is None:
            self.filter.update(uwb)

    def position(self) -> Array | None:
        return None if self.filter.ekf is None else np.array(self.filter.ekf.p)


class UwbLeastSquares:
    """Multilateration per epoch, or over a 0.1 s window of single ranges (one fix each
    0.1 s); anchors from the config, else as the device sends them. The raw ranges: a
    ``[range_model]`` is fitted as a whole, and its part that needs no attitude (the
    anchors' delays, the distance term) alone biases the height (inrol-env1: Z 0.158 →
    0.205 m), since the anchors' delays were fitted beside the tag's term."""

    def __init__(self, config: FilterConfig) -> None:
        self.anchors = dict(config.anchors_m)
        self.sigma_m = config.range_sigma_m
        known = np.array(list(self.anchors.values()), dtype=float).reshape(-1, 3)
        core = native.core  # the least squares' implementation, for this baseline
        self.window = RangeWindow(0.1, 0.1, self.sigma_m,
                                  MirrorSide(known, config.tag_side, config.height_range_m,
                                             core=core), None, core=core)
        self.fix: LsqFix | None = None  # the fix of the latest message, if it made one
        self._last: Array | None = None

    def predict(self, imu: ImuSample) -> None:
        """UWB only: the IMU is not used."""

    def update(self, uwb: UwbRanges) -> None:
        known = [(r.anchor_id, self.anchors.get(r.anchor_id, r.anchor_position_m), r.range_m)
                 for r in uwb.ranges if math.isfinite(r.range_m)]
        known = [(i, a, d) for i, a, d in known if a is not None]
        self.fix = None
        if not known:
            return
        ids = [i for i, _, _ in known]
        anchors = np.array([a for _, a, _ in known], dtype=float)
        ranges = np.array([d for _, _, d in known])
        self.window.add(uwb.t_ns, ids, anchors, ranges)
        self.fix = self.window.fix(uwb.t_ns, ids, anchors, ranges, self._last)
        if self.fix is not None:
            self._last = self.fix.position_m

    def position(self) -> Array | None:
        return None if self.fix is None else self.fix.position_m


class StaticPoints:
    """Static-point filtering of UWB fixes (the thesis): while the vehicle is at rest, the
    running mean of the least-squares fixes since the rest began; while it moves, each fix
    as it comes. At rest the fix noise (~0.1 m) then averages down and the position stands
    still; when motion starts the IMU sees it within a sample or two and fixes are used one
    by one again.

    Rest is the thesis's zero-velocity test, the main filter's (:class:`.rest.ImuWindow`):
    over the last ``static_window_s`` (0.5 s) the specific force steady and about ``g`` in
    size, the rate small and steady. An IMU cannot tell rest from a constant velocity, and a
    vehicle without vibration (the simulator's) looks at rest on every straight, so with
    ``uwb_check`` (the default) the fixes of the last second must not show motion either
    (:class:`.rest.UwbStillness`, as the main filter asks before a ZUPT).
    """

    def __init__(self, config: FilterConfig, uwb_check: bool = True) -> None:
        self.lsq = UwbLeastSquares(config)
        self.C_bs = np.array(config.mounting_rotation, dtype=float)
        self.span_s = config.static_window_s
        self.window = ImuWindow(config.static_window_s, config.rest, core=native.core)
        self.stillness = UwbStillness() if uwb_check else None
        self.point: Array | None = None  # the latest output: the mean at rest, else the fix
        self.at_rest = False
        self.n = 0  # fixes in the mean (0 while moving)
        self.rest_fixes = 0  # fixes that went into a mean, over the whole run
        self._sum = np.zeros(3)

    def predict(self, imu: ImuSample) -> None:
        self.window.add(imu.t_ns, tuple(self.C_bs @ np.asarray(imu.acc_mps2)),
                        tuple(self.C_bs @ np.asarray(imu.gyro_rps)))

    def update(self, uwb: UwbRanges) -> None:
        self.lsq.update(uwb)
        fix = self.lsq.fix
        if fix is None:
            return
        p = fix.position_m
        rest = self.window.static(self.span_s)
        if self.stillness is not None:  # every fix (the main filter takes ~5 a second)
            self.stillness.add(uwb.t_ns, fix)
            self.stillness.forget_before(uwb.t_ns)
            rest = rest and self.stillness.still(allow_noise=True)
        if not rest:
            self.at_rest, self.n, self._sum = False, 0, np.zeros(3)
            self.point = np.array(p)
            return
        # running mean since the rest began: x̄_n = Σ p_i / n
        self.at_rest = True
        self._sum = self._sum + p
        self.n += 1
        self.rest_fixes += 1
        self.point = self._sum / self.n

    @property
    def fix(self) -> LsqFix | None:
        """The least-squares fix of the latest message, if it made one."""
        return self.lsq.fix

    def position(self) -> Array | None:
        return None if self.lsq.fix is None else self.point


class ComplementaryAttitude:
    """Mahony complementary filter: ``q̇ = ½ q ⊗ (ω − b + k_p e)``, ``e = f̂_lp × ĝ_b``, with
    ``k_p`` switched by the motion state (:class:`Gains`, the motion tests at the module's
    top): ``gains.moving`` while turning or accelerating, ``gains.still`` otherwise.

    The attitude starts level with the first sample's specific force (roll and pitch from
    gravity, yaw 0: the thesis's static start), whose size is also ``g_ref_mps2`` until the
    user (:class:`Kf4`: the rest average) sets it."""

    def __init__(self, mounting: Array, fs_hz: float = 200.0, fc_hz: float = 2.0,
                 gains: Gains = THESIS_GAINS) -> None:
        self.C_bs = mounting
        self.sos = butter(2, fc_hz, btype="low", fs=fs_hz, output="sos")
        self._sections = self.sos.tolist()
        self._zi: list[list[list[float]]] | None = None  # per section, 2 states per axis
        self.gains = gains
        self.kp = gains.still  # the gain of the latest step
        self.turning = False
        self.accelerating = False
        self.moving_s = 0.0  # time spent turning or accelerating, and not
        self.still_s = 0.0
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.gyro_bias = np.zeros(3)
        self.g_ref_mps2: float | None = None
        self.t_ns: int | None = None
        self.acc_lp = np.zeros(3)
        self.rate_lp = np.zeros(3)  # ω − b, low-passed over MOTION_TAU_S

    def predict(self, imu: ImuSample) -> Array:
        """Update the attitude; returns the low-passed specific force (body)."""
        acc = self.C_bs @ np.asarray(imu.acc_mps2)
        gyro = self.C_bs @ np.asarray(imu.gyro_rps)
        if self._zi is None:  # the filter's steady state for this first sample
            self._zi = (sosfilt_zi(self.sos)[:, :, None] * acc[None, None, :]).tolist()
        self.acc_lp = np.array(_sosfilt_step(self._sections, self._zi, acc.tolist()))
        if self.t_ns is None:
            self.t_ns = imu.t_ns
            self._level(acc)
            return self.acc_lp
        dt = (imu.t_ns - self.t_ns) / 1e9
        self.t_ns = imu.t_ns
        if not 0 < dt < 0.5:
            return self.acc_lp
        w = gyro - self.gyro_bias
        self._judge_motion(w, dt)
        self.kp = self.gains.moving if self.turning or self.accelerating else self.gains.still
        g_body = quat_to_matrix(self.q).T @ np.array([0.0, 0.0, 1.0])  # "up" in body axes
        a = self.acc_lp / max(float(np.linalg.norm(self.acc_lp)), 1e-9)
        e = np.array([a[1] * g_body[2] - a[2] * g_body[1],  # a × g (np.cross costs 20×)
                      a[2] * g_body[0] - a[0] * g_body[2],
                      a[0] * g_body[1] - a[1] * g_body[0]])
        q = quat_mul(self.q, quat_from_rotvec((w + self.kp * e) * dt))
        self.q = q / np.linalg.norm(q)
        return self.acc_lp

    def _judge_motion(self, w: Array, dt: float) -> None:
        """Turning and accelerating, as the module constants define them."""
        alpha = 1.0 - math.exp(-dt / MOTION_TAU_S)
        self.rate_lp = self.rate_lp + alpha * (w - self.rate_lp)
        self.turning = float(np.linalg.norm(self.rate_lp)) > TURN_RATE_RPS
        g_ref = GRAVITY_MPS2 if self.g_ref_mps2 is None else self.g_ref_mps2
        self.accelerating = abs(float(np.linalg.norm(self.acc_lp)) - g_ref) > ACCEL_MPS2
        if self.turning or self.accelerating:
            self.moving_s += dt
        else:
            self.still_s += dt

    def _level(self, f_b: Array) -> None:
        """Roll and pitch from a specific force taken to be gravity alone (yaw 0):
        "up" in body axes is ``(−sin θ, sin φ cos θ, cos φ cos θ)``."""
        size = float(np.linalg.norm(f_b))
        if not math.isfinite(size) or size < 1e-6:
            return
        self.g_ref_mps2 = size
        roll = math.atan2(f_b[1], f_b[2])
        pitch = math.atan2(-f_b[0], math.hypot(f_b[1], f_b[2]))
        self.q = quat_from_euler(roll, pitch, 0.0)


def _sosfilt_step(sections: list[list[float]], zi: list[list[list[float]]],
                  x: list[float]) -> list[float]:
    """One sample through ``scipy.signal.sosfilt``'s cascade (transposed direct form II,
    its operations in its order, so the same numbers), ``zi`` updated in place: a sample
    at a time without a call into scipy per sample."""
    out = list(x)
    for (b0, b1, b2, _a0, a1, a2), (z0, z1) in zip(sections, zi, strict=True):
        for k, xk in enumerate(out):
            y = b0 * xk + z0[k]
            z0[k] = b1 * xk - a1 * y + z1[k]
            z1[k] = b2 * xk - a2 * y
            out[k] = y
    return out


class Kf4:
    """The thesis's 4-state KF (module doc). Static start: the gyro bias, and the size of
    gravity as the accelerometer measures it, are the means over the still start (every
    sample until the IMU's rest test first fails; the KF itself starts at the first fix). With
    ``static_points`` (the thesis) the fix it takes while at rest is the static point
    (:class:`StaticPoints`), with the single fix's covariance (the mean's errors are not
    independent from one update to the next: multipath and antenna delays are slow)."""

    def __init__(self, config: FilterConfig, gate_m: float = 1.0, min_anchors: int = 3,
                 accel_noise_mps2: float = 0.5, gains: Gains = THESIS_GAINS,
                 static_points: bool = True) -> None:
        self.fixes = StaticPoints(config) if static_points else UwbLeastSquares(config)
        self.attitude = ComplementaryAttitude(np.array(config.mounting_rotation, dtype=float),
                                              gains=gains)
        self.gate_m = gate_m
        self.min_anchors = min_anchors
        self.accel_noise = accel_noise_mps2
        self.kf: KalmanFilter | None = None
        self.rejected = 0
        self.span_s = config.static_window_s
        self.rest = ImuWindow(config.static_window_s, config.rest, core=native.core)
        self.start_samples = 0  # IMU samples averaged over the still start
        self._start_rest = True
        self._gyro_sum = np.zeros(3)
        self._acc_sum = 0.0

    def predict(self, imu: ImuSample) -> None:
        prev = self.attitude.t_ns
        f_b = self.attitude.predict(imu)
        self.fixes.predict(imu)
        if self._start_rest:
            self._still_start(imu)
        if self.kf is None or prev is None:
            return
        dt = (imu.t_ns - prev) / 1e9
        if not 0 < dt < 0.5:
            return
        a_n = quat_to_matrix(self.attitude.q) @ f_b - np.array([0.0, 0.0, GRAVITY_MPS2])
        kf = self.kf
        kf.F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
        kf.B = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        G = kf.B
        kf.Q = G @ G.T * self.accel_noise**2
        kf.predict(u=a_n[:2])

    def _still_start(self, imu: ImuSample) -> None:
        """Average gyro and |f| over the still start, which ends when a full rest window
        first says motion."""
        gyro = self.attitude.C_bs @ np.asarray(imu.gyro_rps)
        acc = self.attitude.C_bs @ np.asarray(imu.acc_mps2)
        self.rest.add(imu.t_ns, tuple(acc), tuple(gyro))
        if self.rest.span_s() >= 0.9 * self.span_s and not self.rest.static(self.span_s):
            self._start_rest = False
            return
        self.start_samples += 1
        self._gyro_sum = self._gyro_sum + gyro
        self._acc_sum += float(np.linalg.norm(acc))
        self.attitude.gyro_bias = self._gyro_sum / self.start_samples
        self.attitude.g_ref_mps2 = self._acc_sum / self.start_samples

    def update(self, uwb: UwbRanges) -> None:
        if sum(math.isfinite(r.range_m) for r in uwb.ranges) < self.min_anchors:
            return
        self.fixes.update(uwb)
        fix, point = self.fixes.fix, self.fixes.position()
        if fix is None or point is None:
            return
        z = point[:2]
        if self.kf is None:
            self.kf = KalmanFilter(dim_x=4, dim_z=2, dim_u=2)
            self.kf.x = np.array([z[0], z[1], 0.0, 0.0])
            self.kf.P = np.diag([0.1, 0.1, 0.5, 0.5])
            self.kf.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
            return
        if float(np.linalg.norm(z - self.kf.x[:2])) > self.gate_m:
            self.rejected += 1  # the thesis's consistency check: fixes > 1 m off are dropped
            return
        self.kf.update(z, R=fix.covariance[:2, :2] + np.eye(2) * 1e-4)

    def position(self) -> Array | None:
        point = self.fixes.position()
        if self.kf is None or point is None:
            return None
        return np.array([self.kf.x[0], self.kf.x[1], point[2]])


Baseline = PureIns | UwbLeastSquares | StaticPoints | Kf4


def comparison_methods(config: FilterConfig) -> dict[str, Baseline]:
    """The baselines every report and benchmark compares uwbd's filters against (names fit
    the report's 22-character column). "4-state KF (thesis)" has the thesis's gains as the
    issue gives them; "4-state KF, Kp swapped" the other way round (:class:`Gains`), kept
    beside it because it measured better (the simulator's runs, and tilt on the handheld
    run)."""
    return {"pure INS": PureIns(config), "uwb least squares": UwbLeastSquares(config),
            "uwb LSQ + static point": StaticPoints(config),
            "4-state KF (thesis)": Kf4(config),
            "4-state KF, Kp swapped": Kf4(config, gains=SWAPPED_GAINS)}
