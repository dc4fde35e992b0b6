"""Starting again: restarts, the attitude restarted in place, and what triggers them.

The steps :class:`~uwbd.fusion.filter.Filter` takes when the evidence says its estimate is
wrong or lost (docs/ekf.md §6): a start from UWB and fresh IMU samples (non-finite state,
a mirror flip, repeated divergence), the heading restarted in place after the IMU was
unusable (position, velocity, biases and tilt kept), levelling anew when gravity disagrees
at rest, a non-finite covariance restored, the covariance faded while the innovations are
inconsistent, and the position moved to a UWB fix that is consistent itself. A mixin of
the filter: these methods act on its state.
"""

from __future__ import annotations

import collections
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from uwbd.fusion.checks.anchor_consistency import AnchorConsistency
from uwbd.fusion.checks.mounting_yaw import MountingYaw
from uwbd.fusion.checks.window_raim import WindowRaim
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import P_, TH_, V_
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.alignment import HeadingAligner
from uwbd.fusion.policy.fixes import RangeWindow, consistent
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.policy.initialise import Start, start_state
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness

if TYPE_CHECKING:
    from uwbd.fusion.settings import FilterConfig

NS = 1_000_000_000
# what the IMU did not see (a gap, rejected samples): accelerations and turns of this σ per √s
COAST_ACCEL_SIGMA_MPS2 = 2.0
UNSEEN_RATE_SIGMA_RPS = 0.3
UNSEEN_TILT_SIGMA_RPS = 0.003  # roll and pitch: bounded by gravity, they wander far less
MAX_TILT_ERROR_RAD = math.radians(10)  # at rest, attitude against gravity
FADE_PER_S = 1.0  # variance growth rate while the innovations are inconsistent
SLOW_FADE_PER_S = 0.25
MAX_FADE_STEP_NS = NS // 5
REPEATED_RESET_NS = 10 * NS  # a second divergence this soon after a position reset restarts
FIX_HEIGHT_MARGIN_M = 3.0  # a reset's fix this far above or below every anchor is refused
MAX_REST_TILT_DEG = 30.0  # gravity this far from body up at a start at rest: said


class Recovery:
    """The restart steps of :class:`~uwbd.fusion.filter.Filter`, and the state they act on
    (set by the filter)."""

    cfg: FilterConfig
    ekf: Eskf | None
    t_ns: int | None
    lever: Array
    _plain_lever: Array
    counters: collections.Counter[str]
    monitor: HealthMonitor
    consistency: AnchorConsistency
    raim: WindowRaim
    mounting_yaw: MountingYaw
    window: ImuWindow
    ranges: RangeWindow
    _aligner: HeadingAligner
    _aligned: bool
    _bias_index: dict[int, int]
    _mp_index: dict[int, int]
    _lever_index: tuple[int, ...]
    _carry: Start | None
    _start_started_ns: int | None
    _first_t_ns: int | None
    _fixes: collections.deque[tuple[int, Array]]
    stillness: UwbStillness
    _anchors: dict[int, tuple[float, float, float]]
    _last_good_P: Array | None  # noqa: N815 - P as in docs/ekf.md
    _relevel: str | None
    _tilt_bad_ns: int | None
    _position_reset_ns: int
    _fade_ns: int | None
    records: list[Any] | None  # the smoother's epochs (Filter's ``record``)
    mounting_finding: str  # what the start at rest said of the mounting ("": nothing)
    _C: tuple[tuple[float, ...], ...]  # imu.mounting, sensor -> body
    def _offset_sigma(self) -> float:
        """What a range's offset may be by the config, 1 σ: its anchor's and the tag's."""
        return math.hypot(self.cfg.range_bias_sigma_m, self.cfg.tag_delay_sigma_m)

    def _try_start(self, t_ns: int, fix: LsqFix | None) -> None:
        cfg = self.cfg
        if fix is None or self.window.means() is None:
            return
        if self._start_started_ns is not None:  # a restart: fresh IMU data first
            if self.window.span_s() < 0.9 * cfg.static_window_s:
                return
            waited_long = True
        else:
            waited_long = (t_ns - (self._first_t_ns or t_ns)) / NS >= cfg.init_max_wait_s
        since = t_ns - cfg.init_static_s * NS
        recent = [(t, p) for t, p in self._fixes if t >= since]
        if self._start_started_ns is not None and not self._plausible_height(fix):
            self.counters["fix_height_implausible"] += 1  # a restart waits for a fix that can be
            return
        rest = None
        if self._carry is None and self.window.static(cfg.init_static_s):
            rest = self.ranges.rest_fix(self.ranges.recent_epochs(since), self._anchors,
                                        self._offset_sigma())
        start = start_state(cfg, self.window, fix, recent, list(self._fixes), waited_long,
                            self._carry, len(self._bias_index), self.lever, len(self._mp_index),
                            len(self._lever_index),
                            rest_m=rest[0].position_m if rest is not None else None)
        if start is None:
            return
        self._begin(start, t_ns)
        self.monitor.last_range_ns = t_ns  # the start is a UWB fix
        if rest is not None and rest[1] is not None and start[1] == "rest":
            # the anchor test's finding from the start: its ranges are left out, and the
            # test, once the heading is known, confirms it or lets it go after its hold
            anchor, excess_m = rest[1]
            self.consistency.found(t_ns, anchor, excess_m, self._offset_sigma())
            self.counters["start_anchor_left_out"] += 1

    def _restart(self, t_ns: int, reason: str, keep_biases: bool = True) -> None:
        """Drop the estimate and start again from UWB and fresh IMU samples, keeping only
        the biases (when they are finite and ``keep_biases``)."""
        ekf = self.ekf
        self._count_restart(reason)
        self._carry = None
        if keep_biases and ekf is not None and np.isfinite(
                np.concatenate([ekf.b_g, ekf.b_a, ekf.b_r])).all():
            self._carry = Start(None, None, np.array(ekf.b_g), np.array(ekf.b_a),
                                ekf.b_r.copy(), 0.0)
        self.ekf = None
        self._relevel = None
        self._start_started_ns = t_ns
        self._fixes.clear()  # from the old estimate's side of a mirror, perhaps
        self.consistency.clear()  # its evidence was against the old estimate
        self.raim.clear()
        self.mounting_yaw.clear()  # (the body velocity was the old heading's)
        self.monitor.mounting_inconsistent = False
        self._forget_attitude(t_ns, reason)

    def _lose_attitude(self, t_ns: int, reason: str) -> None:
        """The IMU was unusable too long for the attitude to be trusted: coast on the ranges
        (constant velocity, as through a gap) until fresh IMU samples span a window, then
        restart the heading there, keeping position, velocity, biases and the tilt from
        before (the EKF refines a changed tilt; re-levelling from gravity while moving puts
        the vehicle's acceleration into the tilt)."""
        self._count_restart(reason)
        self._relevel = "keep"
        self._forget_attitude(t_ns, reason)

    def _relevel_when_ready(self, t_ns: int) -> None:
        ekf = self.ekf
        assert ekf is not None and self.t_ns is not None and self._relevel is not None
        if self.window.span_s() < 0.9 * self.cfg.static_window_s or (
                self._relevel == "level" and not self.window.static(self.cfg.static_window_s)):
            return  # levelling from gravity needs the vehicle at rest
        dt = (t_ns - self.t_ns) / NS
        if dt > 0:
            self._coast(dt)
        sig = float(np.sqrt(max(float(np.diag(ekf.P)[P_].max()), 0.0)))
        level = self._relevel == "level"
        carry = Start(np.array(ekf.p), np.array(ekf.v), np.array(ekf.b_g), np.array(ekf.b_a),
                      ekf.b_r.copy(), sig, None if level else np.array(ekf.q),
                      ekf.tilt_sigma_rad(), yaw_rad=ekf.yaw_rad())
        antenna = np.array(ekf.p) + ekf.R @ self.lever
        fix = LsqFix(antenna, np.diag(np.diag(ekf.P)[P_]), np.zeros(0), np.zeros(0, bool),
                     0.0, 0)
        start = start_state(self.cfg, self.window, fix, [], [], True, carry,
                            len(self._bias_index), self.lever, len(self._mp_index),
                            len(self._lever_index))
        if start is not None:
            self._relevel = None
            self.monitor.imu_gap = False
            self._begin(start, max(t_ns, self.t_ns))

    def _begin(self, start: tuple[Eskf, str], t_ns: int) -> None:
        self.ekf, how = start
        self.ekf.keep_transition = self.records is not None  # Φ: only the smoother's
        self.t_ns = t_ns
        self._carry = None
        self._start_started_ns = None
        self._last_good_P = None
        self.stillness.clear()
        self._position_reset_ns = -(2**63)
        self._tilt_bad_ns = None
        self.counters["initialisations"] += 1
        self.counters[f"started_{how}"] += 1
        if how == "rest":
            self._judge_mounting()

    def _judge_mounting(self) -> None:
        """At a start at rest the IMU's mean specific force, in body axes (forward-left-up,
        through ``imu.mounting``), points along +z: gravity more than ``MAX_REST_TILT_DEG``
        from it is a vehicle standing that tilted, or, far more often, a mounting typed
        wrong (an upside-down sensor, a 90° turn). Said (a note, the status's
        ``mounting_finding``), not judged unhealthy: a ramp is not a fault."""
        means = self.window.means()
        if means is None:
            return
        acc = np.asarray(means[0], dtype=float)
        norm = float(np.linalg.norm(acc))
        tilt = math.degrees(math.acos(min(max(acc[2] / norm, -1.0), 1.0))) if norm > 0 else 0.0
        self.monitor.mounting_suspect = tilt > MAX_REST_TILT_DEG
        if not self.monitor.mounting_suspect:
            self.mounting_finding = ""
            return
        sensor = np.array(self._C).T @ acc  # the same force in the sensor's own axes
        k = int(np.argmax(np.abs(sensor)))
        up = f"{'+' if sensor[k] > 0 else '-'}{'xyz'[k]}"
        now = np.array(self._C)[:, k] * np.sign(sensor[k])
        j = int(np.argmax(np.abs(now)))
        self.mounting_finding = (
            f"at rest the IMU reads gravity {tilt:.0f} deg from the body's up axis: the "
            f"vehicle stands that tilted, or imu.mounting is wrong: the sensor's {up} axis "
            f"points up, and imu.mounting turns it into the body's "
            f"{'+' if now[j] > 0 else '-'}{'xyz'[j]} (forward-left-up: up is +z)")

    def _coast(self, dt: float) -> None:
        ekf = self.ekf
        assert ekf is not None
        ekf.coast(dt, COAST_ACCEL_SIGMA_MPS2, UNSEEN_RATE_SIGMA_RPS, UNSEEN_TILT_SIGMA_RPS)

    def _count_restart(self, reason: str) -> None:
        self.counters["restarts"] += 1
        self.counters[f"restart_{reason.replace(' ', '_')}"] += 1

    def _forget_attitude(self, t_ns: int, reason: str) -> None:
        self.window.clear()
        self._aligner = HeadingAligner(self.cfg.align_window_s, self.cfg.align_min_dv_mps,
                                       self.cfg.range_sigma_m)
        self._aligned = False
        self.lever = self._plain_lever  # the phase centre waits for the heading again
        self.monitor.reset(t_ns, reason, None)

    def _restart_not_finite(self, t_ns: int) -> None:
        """A non-finite covariance with a finite state: ``P`` goes back to the last finite
        one, doubled in σ (the state itself was never touched by it: no row with a
        non-finite variance is fused). A non-finite state restarts, keeping finite biases."""
        ekf = self.ekf
        assert ekf is not None
        good = self._last_good_P
        if math.isfinite(sum(ekf.p) + sum(ekf.v) + sum(ekf.q)) and good is not None \
                and good.shape == ekf.P.shape:
            ekf.set_covariance(4.0 * good)
            self.counters["covariance_restored"] += 1
            self.monitor.reset(t_ns, "covariance not finite: the last finite one, widened",
                               0.0)
        else:
            self._restart(t_ns, "state not finite")

    # -- when the evidence says the state is wrong ---------------------------------------
    def _check_tilt_against_gravity(self) -> None:
        """At rest the mean specific force is gravity's reaction: an attitude more than 10°
        from it for a second is wrong (the EKF can be confidently wrong about tilt after a
        fault); level it anew from the samples of the rest."""
        ekf, means = self.ekf, self.window.means(self.cfg.static_window_s)
        assert ekf is not None and self.t_ns is not None
        if means is None:
            return
        if ekf.tilt_from_gravity_rad(means[0]) <= MAX_TILT_ERROR_RAD:
            self._tilt_bad_ns = None
            return
        if self._tilt_bad_ns is None:
            self._tilt_bad_ns = self.t_ns
        elif self.t_ns - self._tilt_bad_ns >= NS:
            self._tilt_bad_ns = None
            self._count_restart("attitude against gravity")
            self._relevel = "level"
            self._forget_attitude(self.t_ns, "attitude against gravity")

    def _fade(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array) -> None:
        """While the innovations are inconsistent, the state's covariance was too small for
        what happened: widen position and velocity e-fold per second (a fading memory) so
        that the gate opens again to ranges that are right, rather than reject them for good
        while the state drifts away."""
        last, self._fade_ns = self._fade_ns, t_ns
        ekf = self.ekf
        if ekf is None or last is None or not self.monitor.inconsistent:
            return
        # only towards ranges that agree with each other: NLOS on every anchor must not
        # widen the gate to itself
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, None, force=True, weigh=False)
        used = self.ranges.last_inputs
        if fix is None or not self._consistent(fix, *used):
            return
        rate = FADE_PER_S
        if len(used[1]) < 5:  # too few ranges to tell a common NLOS offset: fade slowly,
            if not self.monitor.diverged(t_ns):  # and only once it has lasted
                return
            rate = SLOW_FADE_PER_S
        dt_ns = min(max(t_ns - last, 0), MAX_FADE_STEP_NS)  # not a whole outage at once
        ekf.widen(slice(0, V_.stop), math.exp(0.5 * rate * dt_ns / NS))
        self.counters["covariance_faded"] += 1

    def _check_divergence(self, t_ns: int, ids: list[int], anchors: Array,
                          ranges: Array) -> bool:
        """Restart or move the state when the evidence says it is wrong; True if it did."""
        ekf = self.ekf
        assert ekf is not None
        # (the ufunc itself: ndarray.sum's Python wrapper costs more than the sum)
        if not math.isfinite(float(np.add.reduce(ekf.P, axis=None)) + sum(ekf.p) + sum(ekf.v)
                             + sum(ekf.q)):
            self._restart_not_finite(t_ns)
            return True
        if not self.monitor.diverged(t_ns):
            return False
        # the ranges disagree with the state: believe them only if they agree with each other
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, None, force=True, weigh=False)
        if fix is None or not self._consistent(fix, *self.ranges.last_inputs):
            self.counters["divergence_without_consistent_fix"] += 1
            return False
        p_ant = np.array(ekf.p) + ekf.R @ self.lever
        jump = float(np.linalg.norm(fix.position_m - p_ant))
        spread = math.sqrt(max(float(np.trace(ekf.P[P_, P_]) + np.trace(fix.covariance)), 0.0))
        if jump <= 3.0 * spread:
            return False  # the fix agrees with the state after all: nothing to move
        if t_ns - self._position_reset_ns < REPEATED_RESET_NS:
            # moving the position did not make the ranges agree: the attitude, velocity or
            # biases are wrong too; start again from this consistent fix
            self._restart(t_ns, "diverged again after a position reset", keep_biases=False)
            return True
        self._position_reset_ns = t_ns
        self.counters["position_resets"] += 1
        ekf.move_to(np.array(ekf.p) + fix.position_m - p_ant, (0.0, 0.0, 0.0))
        self._inflate(velocity_mps=1.0, attitude_rad=0.0,
                      position_m=math.sqrt(max(np.trace(fix.covariance) / 3, 0.05**2)))
        self.monitor.reset(t_ns, "innovations inconsistent: position from a UWB fix", jump)
        return True

    def _consistent(self, fix: LsqFix, anchors: Array, ranges: Array) -> bool:
        cfg = self.cfg
        if not self._plausible_height(fix):
            self.counters["fix_height_implausible"] += 1
            return False
        return consistent(fix, anchors, ranges, cfg.range_sigma_m, cfg.tag_delay_sigma_m,
                          self.ranges.needed)

    def _plausible_height(self, fix: LsqFix) -> bool:
        """The fix's height within ``height_range_m``, or else within the anchors' heights
        widened by ``FIX_HEIGHT_MARGIN_M``: NLOS on every anchor at once leaves residuals
        as small as a true fix's, at a place metres above or below any the tag can be."""
        z = float(fix.position_m[2])
        if self.cfg.height_range_m is not None:
            low, high = self.cfg.height_range_m
            return low <= z <= high
        heights = [pos[2] for pos in self._anchors.values()]
        return not heights or (min(heights) - FIX_HEIGHT_MARGIN_M <= z
                               <= max(heights) + FIX_HEIGHT_MARGIN_M)

    def _inflate(self, velocity_mps: float, attitude_rad: float, position_m: float = 0.0) -> None:
        ekf = self.ekf
        assert ekf is not None
        d = np.zeros(ekf.n)
        d[P_] = position_m**2
        d[V_] = velocity_mps**2
        d[TH_] = attitude_rad**2
        ekf.add_variances(d)
