"""Starting again: restarts, the attitude restarted in place, and what triggers them.

The steps :class:`~uwbd.fusion.filter.Filter` takes when the evidence says its estimate is
wrong or lost (docs/ekf.md §6): a start from UWB and fresh IMU samples (non-finite state,
a mirror flip, repeated divergence), the heading restarted in place after the IMU was
unusable (position, velocity, biases and tilt kept), levelling anew when gravity disagrees
at rest, a non-finite covariance restored, the covariance faded while the innovations are
inconsistent, and the position moved to a UWB fix that is consistent itself. Its own state
is the restart in progress; it acts on the :class:`~.estimate.Estimate` it is handed.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import P_, TH_, V_
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.estimate import Estimate, Findings, new_aligner
from uwbd.fusion.policy.fixes import RangeWindow, consistent
from uwbd.fusion.policy.health import height_bounds
from uwbd.fusion.policy.initialise import Start, start_state
from uwbd.fusion.policy.installation import Installation
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness
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
MAX_REST_TILT_DEG = 30.0  # gravity this far from body up at a start at rest: said


class Recovery:
    """The start and the restart steps (see module doc), and the restart in progress."""

    def __init__(self, cfg: FilterConfig, est: Estimate, installation: Installation,
                 findings: Findings, window: ImuWindow, ranges: RangeWindow,
                 stillness: UwbStillness, core: Core) -> None:
        self.cfg, self.est, self.installation, self.findings = cfg, est, installation, findings
        self._core = core  # the states it starts: on the C core, or the reference (None)
        self.window, self.ranges, self.stillness = window, ranges, stillness
        self.first_t_ns: int | None = None  # the first frame's time
        self.fixes: collections.deque[tuple[int, Array]] = collections.deque(maxlen=100)
        self.last_internal_error = ""
        self._started_ns: int | None = None  # a restart waits for fresh IMU data
        self._carry: Start | None = None  # what a restart keeps of the estimate before it
        self.last_good_P: Array | None = None  # the last finite covariance
        self._position_reset_ns = -(2**63)
        self._fade_ns: int | None = None
        self._tilt_bad_ns: int | None = None  # since when, at rest, gravity disagrees

    def _offset_sigma(self) -> float:
        """What a range's offset may be by the config, 1 σ: its anchor's and the tag's."""
        return math.hypot(self.cfg.range_bias_sigma_m, self.cfg.tag_delay_sigma_m)

    def try_start(self, t_ns: int, fix: LsqFix | None) -> None:
        cfg = self.cfg
        if fix is None or self.window.means() is None:
            return
        if self._started_ns is not None:  # a restart: fresh IMU data first
            if self.window.span_s() < 0.9 * cfg.static_window_s:
                return
            waited_long = True
        else:
            waited_long = (t_ns - (self.first_t_ns or t_ns)) / NS >= cfg.init_max_wait_s
        since = t_ns - cfg.init_static_s * NS
        recent = [(t, p) for t, p in self.fixes if t >= since]
        if self._started_ns is not None and not self._plausible_height(fix):
            # a restart waits for a fix that can be
            self.est.counters["fix_height_implausible"] += 1
            return
        rest = None
        if self._carry is None and self.window.static(cfg.init_static_s):
            rest = self.ranges.rest_fix(self.ranges.recent_epochs(since),
                                        self.installation.anchors, self._offset_sigma(),
                                        self._heights())
        start = start_state(cfg, self.window, fix, recent, list(self.fixes), waited_long,
                            self._carry, *self._state_sizes(),
                            rest_m=rest.fix.position_m if rest is not None else None,
                            rest_spread_m=rest.spread_m if rest is not None else 0.0,
                            bank=self.installation.bank,
                            bank_var=self.installation.bank_variances(), core=self._core)
        if start is None:
            return
        self._begin(start, t_ns)
        self.est.monitor.last_range_ns = t_ns  # the start is a UWB fix
        if rest is not None and rest.left_out is not None and start[1] == "rest":
            # the anchor test's finding from the start: its ranges are left out, and the
            # test, once the heading is known, confirms it or lets it go after its hold
            anchor, excess_m = rest.left_out
            self.findings.consistency.found(t_ns, anchor, excess_m, self._offset_sigma())
            self.est.counters["start_anchor_left_out"] += 1

    def internal_error(self, t_ns: int, err: Exception) -> None:
        """A numerical failure no check foresaw: counted, said, and the filter restarts
        rather than let the exception stop fusion."""
        self.est.counters["internal_errors"] += 1
        self.last_internal_error = f"{type(err).__name__}: {err}"
        self.restart(t_ns, "internal error")

    def restart(self, t_ns: int, reason: str, keep_biases: bool = True) -> None:
        """Drop the estimate and start again from UWB and fresh IMU samples, keeping only
        the biases (when they are finite and ``keep_biases``)."""
        ekf = self.est.ekf
        self._count_restart(reason)
        self._carry = None
        if keep_biases and ekf is not None and np.isfinite(
                np.concatenate([ekf.b_g, ekf.b_a, ekf.b_r])).all():
            self._carry = Start(None, None, np.array(ekf.b_g), np.array(ekf.b_a),
                                ekf.b_r.copy(), 0.0)
        self.est.ekf = None
        self.est.relevel = None
        self._started_ns = t_ns
        self.fixes.clear()  # from the old estimate's side of a mirror, perhaps
        self.findings.forget()  # its evidence was against the old estimate
        self.est.monitor.mounting_inconsistent = False
        self._forget_attitude(t_ns, reason)

    def lose_attitude(self, t_ns: int, reason: str) -> None:
        """The IMU was unusable too long for the attitude to be trusted: coast on the ranges
        (constant velocity, as through a gap) until fresh IMU samples span a window, then
        restart the heading there, keeping position, velocity, biases and the tilt from
        before (the EKF refines a changed tilt; re-levelling from gravity while moving puts
        the vehicle's acceleration into the tilt)."""
        self._count_restart(reason)
        self.est.relevel = "keep"
        self._forget_attitude(t_ns, reason)

    def relevel_when_ready(self, t_ns: int) -> None:
        ekf = self.est.ekf
        assert ekf is not None and self.est.t_ns is not None and self.est.relevel is not None
        if self.window.span_s() < 0.9 * self.cfg.static_window_s or (
                self.est.relevel == "level" and not self.window.static(self.cfg.static_window_s)):
            return  # levelling from gravity needs the vehicle at rest
        dt = (t_ns - self.est.t_ns) / NS
        if dt > 0:
            self.coast(dt)
        sig = float(np.sqrt(max(float(np.diag(ekf.P)[P_].max()), 0.0)))
        level = self.est.relevel == "level"
        carry = Start(np.array(ekf.p), np.array(ekf.v), np.array(ekf.b_g), np.array(ekf.b_a),
                      ekf.b_r.copy(), sig, None if level else np.array(ekf.q),
                      ekf.tilt_sigma_rad(), yaw_rad=ekf.yaw_rad())
        antenna = np.array(ekf.p) + ekf.R @ self.est.lever
        fix = LsqFix(antenna, np.diag(np.diag(ekf.P)[P_]), np.zeros(0), np.zeros(0, bool),
                     0.0, 0)
        start = start_state(self.cfg, self.window, fix, [], [], True, carry,
                            *self._state_sizes(), bank=self.installation.bank,
                            bank_var=self.installation.bank_variances(), core=self._core)
        if start is not None:
            self.est.relevel = None
            self.est.monitor.imu_gap = False
            self._begin(start, max(t_ns, self.est.t_ns))

    def _state_sizes(self) -> tuple[int, Array, int, int]:
        """``start_state``'s range-offset count, lever arm, multipath and lever-arm counts."""
        inst = self.installation
        return (len(inst.bias_index), self.est.lever, len(inst.mp_index),
                len(inst.lever_index))

    def _begin(self, start: tuple[Eskf, str], t_ns: int) -> None:
        ekf, how = start
        ekf.keep_transition = self.est.keep_transition  # Φ: only the smoother's
        self.est.ekf = ekf
        self.est.t_ns = t_ns
        # the health's, for the body (the antenna is within the lever arm of it): no level
        # beyond them
        low, high = self._heights()
        reach = float(np.linalg.norm(self.est.lever))
        self.est.monitor.heights_m = (low - reach, high + reach)
        self._carry = None
        self._started_ns = None
        self.last_good_P = None
        self.stillness.clear()
        self._position_reset_ns = -(2**63)
        self._tilt_bad_ns = None
        self.est.counters["initialisations"] += 1
        self.est.counters[f"started_{how}"] += 1
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
        self.est.monitor.mounting_suspect = tilt > MAX_REST_TILT_DEG
        if not self.est.monitor.mounting_suspect:
            self.findings.mounting_finding = ""
            return
        C_bs = np.array(self.cfg.mounting_rotation, dtype=float)  # sensor -> body
        sensor = C_bs.T @ acc  # the same force in the sensor's own axes
        k = int(np.argmax(np.abs(sensor)))
        up = f"{'+' if sensor[k] > 0 else '-'}{'xyz'[k]}"
        now = C_bs[:, k] * np.sign(sensor[k])
        j = int(np.argmax(np.abs(now)))
        self.findings.mounting_finding = (
            f"at rest the IMU reads gravity {tilt:.0f} deg from the body's up axis: the "
            f"vehicle stands that tilted, or imu.mounting is wrong: the sensor's {up} axis "
            f"points up, and imu.mounting turns it into the body's "
            f"{'+' if now[j] > 0 else '-'}{'xyz'[j]} (forward-left-up: up is +z)")

    def coast(self, dt: float) -> None:
        ekf = self.est.ekf
        assert ekf is not None
        ekf.coast(dt, COAST_ACCEL_SIGMA_MPS2, UNSEEN_RATE_SIGMA_RPS, UNSEEN_TILT_SIGMA_RPS)

    def _count_restart(self, reason: str) -> None:
        self.est.counters["restarts"] += 1
        self.est.counters[f"restart_{reason.replace(' ', '_')}"] += 1

    def _forget_attitude(self, t_ns: int, reason: str) -> None:
        self.window.clear()
        self.est.aligner = new_aligner(self.cfg)
        self.est.aligned = False
        # the phase centre waits for the heading again
        self.est.lever = self.installation.plain_lever
        self.est.monitor.reset(t_ns, reason, None)

    def restart_not_finite(self, t_ns: int) -> None:
        """A non-finite covariance with a finite state: ``P`` goes back to the last finite
        one, doubled in σ (the state itself was never touched by it: no row with a
        non-finite variance is fused). A non-finite state restarts, keeping finite biases."""
        ekf = self.est.ekf
        assert ekf is not None
        good = self.last_good_P
        if math.isfinite(sum(ekf.p) + sum(ekf.v) + sum(ekf.q)) and good is not None \
                and good.shape == ekf.P.shape:
            ekf.set_covariance(4.0 * good)
            self.est.counters["covariance_restored"] += 1
            self.est.monitor.reset(t_ns, "covariance not finite: the last finite one, widened",
                                   0.0)
        else:
            self.restart(t_ns, "state not finite")

    # -- when the evidence says the state is wrong ---------------------------------------
    def tilt_unchecked(self) -> None:
        """Not at rest at a tilt check: gravity's disagreement must start again."""
        self._tilt_bad_ns = None

    def check_tilt_against_gravity(self) -> None:
        """At rest the mean specific force is gravity's reaction: an attitude more than 10°
        from it for a second is wrong (the EKF can be confidently wrong about tilt after a
        fault); level it anew from the samples of the rest."""
        ekf, means = self.est.ekf, self.window.means(self.cfg.static_window_s)
        assert ekf is not None and self.est.t_ns is not None
        if means is None:
            return
        if ekf.tilt_from_gravity_rad(means[0]) <= MAX_TILT_ERROR_RAD:
            self._tilt_bad_ns = None
            return
        if self._tilt_bad_ns is None:
            self._tilt_bad_ns = self.est.t_ns
        elif self.est.t_ns - self._tilt_bad_ns >= NS:
            self._tilt_bad_ns = None
            self._count_restart("attitude against gravity")
            self.est.relevel = "level"
            self._forget_attitude(self.est.t_ns, "attitude against gravity")

    def fade(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array) -> None:
        """While the innovations are inconsistent, the state's covariance was too small for
        what happened: widen position and velocity e-fold per second (a fading memory) so
        that the gate opens again to ranges that are right, rather than reject them for good
        while the state drifts away."""
        last, self._fade_ns = self._fade_ns, t_ns
        ekf = self.est.ekf
        if ekf is None or last is None or not self.est.monitor.inconsistent:
            return
        # only towards ranges that agree with each other: NLOS on every anchor must not
        # widen the gate to itself
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, None, force=True, weigh=False)
        used = self.ranges.last_inputs
        if fix is None or not self._consistent(fix, *used):
            return
        rate = FADE_PER_S
        if len(used[1]) < 5:  # too few ranges to tell a common NLOS offset: fade slowly,
            if not self.est.monitor.diverged(t_ns):  # and only once it has lasted
                return
            rate = SLOW_FADE_PER_S
        dt_ns = min(max(t_ns - last, 0), MAX_FADE_STEP_NS)  # not a whole outage at once
        ekf.widen(slice(0, V_.stop), math.exp(0.5 * rate * dt_ns / NS))
        self.est.counters["covariance_faded"] += 1

    def check_divergence(self, t_ns: int, ids: list[int], anchors: Array,
                          ranges: Array) -> bool:
        """Restart or move the state when the evidence says it is wrong; True if it did."""
        ekf = self.est.ekf
        assert ekf is not None
        # (the ufunc itself: ndarray.sum's Python wrapper costs more than the sum)
        if not math.isfinite(float(np.add.reduce(ekf.P, axis=None)) + sum(ekf.p) + sum(ekf.v)
                             + sum(ekf.q)):
            self.restart_not_finite(t_ns)
            return True
        if not self.est.monitor.diverged(t_ns):
            return False
        # the ranges disagree with the state: believe them only if they agree with each other
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, None, force=True, weigh=False)
        if fix is None or not self._consistent(fix, *self.ranges.last_inputs):
            self.est.counters["divergence_without_consistent_fix"] += 1
            return False
        p_ant = np.array(ekf.p) + ekf.R @ self.est.lever
        jump = float(np.linalg.norm(fix.position_m - p_ant))
        spread = math.sqrt(max(float(np.trace(ekf.P[P_, P_]) + np.trace(fix.covariance)), 0.0))
        if jump <= 3.0 * spread:
            return False  # the fix agrees with the state after all: nothing to move
        if t_ns - self._position_reset_ns < REPEATED_RESET_NS:
            # moving the position did not make the ranges agree: the attitude, velocity or
            # biases are wrong too; start again from this consistent fix
            self.restart(t_ns, "diverged again after a position reset", keep_biases=False)
            return True
        self._position_reset_ns = t_ns
        self.est.counters["position_resets"] += 1
        ekf.move_to(np.array(ekf.p) + fix.position_m - p_ant, (0.0, 0.0, 0.0))
        self.inflate(velocity_mps=1.0, attitude_rad=0.0,
                      position_m=math.sqrt(max(np.trace(fix.covariance) / 3, 0.05**2)))
        self.est.monitor.reset(t_ns, "innovations inconsistent: position from a UWB fix", jump)
        return True

    def _consistent(self, fix: LsqFix, anchors: Array, ranges: Array) -> bool:
        cfg = self.cfg
        if not self._plausible_height(fix):
            self.est.counters["fix_height_implausible"] += 1
            return False
        return consistent(fix, anchors, ranges, cfg.range_sigma_m, cfg.tag_delay_sigma_m,
                          self.ranges.needed)

    def _heights(self) -> tuple[float, float]:
        """The heights the tag can be at, over the anchors known now (those the device
        reports among them)."""
        return height_bounds(self.cfg.height_range_m,
                             [a[2] for a in self.installation.anchors.values()])

    def _plausible_height(self, fix: LsqFix) -> bool:
        """A restart's or a reset's fix at a height the tag can be at."""
        low, high = self._heights()
        return low <= float(fix.position_m[2]) <= high

    def inflate(self, velocity_mps: float, attitude_rad: float, position_m: float = 0.0) -> None:
        ekf = self.est.ekf
        assert ekf is not None
        d = np.zeros(ekf.n)
        d[P_] = position_m**2
        d[V_] = velocity_mps**2
        d[TH_] = attitude_rad**2
        ekf.add_variances(d)
