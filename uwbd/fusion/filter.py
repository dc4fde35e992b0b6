"""The fusion filter: frames in, poses and per-measurement reports out.

``Filter.predict(imu)``, ``Filter.update(uwb)``, ``Filter.pose()`` — deterministic (same
frames in, same poses out), no I/O; no exception leaves them (a numerical failure no check
foresaw is counted as ``internal_errors`` and restarts the filter). The top level below reads as
the sequence it runs; each step's policy has a module of its own:

* :mod:`.checks.anchor_consistency` — which anchor's ranges disagree with the others' (an
  anchor surveyed off, a biased one), named in the health and the status;
* :mod:`.checks.imu_check` — which IMU samples can be real (non-finite, clipped, impossible jumps),
  judged raw; then :mod:`.checks.intrinsics` corrects them (scale, offsets) on the way to body axes;
* :mod:`.policy.rest` — the recent IMU window and the rest test (start, ZUPT);
* :mod:`.policy.fixes` and :mod:`.policy.mirror` — UWB-only fixes from epochs or a window of single
  ranges, on the right side of a plane of anchors;
* :mod:`.policy.initialise` — the state at start (at rest, or while moving) and after a restart;
* :mod:`.policy.alignment` — the coarse heading from INS against UWB velocity changes;
* :mod:`.models.measurements` — the rows of each measurement model (range, fix, ZUPT, NHC, height);
* :mod:`.policy.robust` — de-weighting NLOS ranges, per-anchor statistics;
* :mod:`.policy.health` — the health record, and the evidence for restarts;
* :mod:`.policy.propagation` — each IMU sample judged, kept and integrated (a mixin of this class);
* :mod:`.policy.recovery` — the restarts themselves and what triggers them (a mixin of this class);
* :mod:`.policy.fusing` — one epoch's rows fused and each row's outcome (a mixin of this class);
* :mod:`.policy.outputs` — the pose, the health record, the diagnostics (a mixin of this class);
* :mod:`.core.eskf` — the algebra (docs/ekf.md).

The numbers (state, covariance, the algebra on them) are :class:`~uwbd.fusion.core.eskf.Eskf`'s,
on the C core where it is built (:class:`~uwbd.fusion.core.state.CoreEskf`); every decision is
made here and in the modules above.

Life cycle: **waiting** (collect IMU and fixes), start at rest or while moving, **aligning**
(heading held until the vehicle has moved enough), **tracking**. A rejected IMU burst or an
IMU gap widens the covariance for what was not seen; one longer than
``attitude_lost_after_s`` restarts the heading in place (position, velocity, biases and tilt
kept). A non-finite state restarts from UWB, keeping finite biases (a non-finite covariance
with a finite state only restores the last finite covariance). Innovations inconsistent for
a while move the position to a UWB fix, but only to one that is consistent itself (NLOS does
not pull the state away); diverging again within 10 s restarts from UWB, biases dropped. At
rest (IMU and UWB fixes both still), an attitude 10° against gravity for a second is
levelled anew.
Without ranges the state coasts and its covariance grows.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from drivers.frames import AnchorRanges, UwbRanges
from uwbd.fusion.checks.anchor_consistency import AnchorConsistency, ConsistencyLimits
from uwbd.fusion.checks.gating import GatingCounters, chi2_quantile, gate
from uwbd.fusion.checks.imu_check import ImuCheck, new_imu_check
from uwbd.fusion.checks.intrinsics import body_maps, to_body
from uwbd.fusion.checks.mounting_yaw import MountingYaw
from uwbd.fusion.checks.window_raim import RaimLimits, WindowRaim
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import BA_, BG_, N_CORE, TH_
from uwbd.fusion.core.lsq import LsqFix, coplanar
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.smoother import EpochRecord, Nominal
from uwbd.fusion.core.weights import RowPolicy
from uwbd.fusion.models.measurements import Rows, height_rows, nhc_rows, zupt_rows
from uwbd.fusion.policy.alignment import HeadingAligner
from uwbd.fusion.policy.fixes import RangeWindow
from uwbd.fusion.policy.fusing import EpochFusion
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.policy.initialise import Start
from uwbd.fusion.policy.mirror import WALL_NORMAL_Z, MirrorSide
from uwbd.fusion.policy.outputs import FilterOutputs
from uwbd.fusion.policy.propagation import NUMERICAL_ERRORS, ImuPropagation
from uwbd.fusion.policy.recovery import NS
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness
from uwbd.fusion.policy.robust import AnchorStats, quality_scale
from uwbd.fusion.settings import FilterConfig, Mode
from uwbd.fusion.types import FusionReport

Vec3 = tuple[float, float, float]
HELD_YAW_SIGMA_RAD = 1e-3  # the heading's σ while it is held, before the coarse alignment
MIN_PROPAGATE_S = 0.02  # and at most this often: P grows little in 20 ms
CONSTRAINT_EVERY_NS = 95_000_000  # ZUPT, NHC, known height: about 10 Hz
TILT_CHECK_EVERY_NS = NS // 2
MAX_ANCHOR_COORD_M = 1e4  # a device-reported anchor farther out than this is garbage


class Filter(ImuPropagation, EpochFusion, FilterOutputs):
    """Loosely or tightly coupled UWB/INS error-state EKF (see module doc)."""

    def __init__(self, config: FilterConfig, record: bool = False) -> None:
        """``record``: keep every epoch's prior and posterior for :mod:`.core.smoother` (offline;
        about 13 kB an epoch with 8 anchors)."""
        self.cfg = config
        self.records: list[EpochRecord] | None = [] if record else None
        C_bs = np.array(config.mounting_rotation, dtype=float)
        if not np.allclose(C_bs @ C_bs.T, np.eye(3), atol=1e-6) or np.linalg.det(C_bs) < 0:
            raise ValueError("mounting_rotation must be a proper rotation matrix")
        self._C = tuple(tuple(float(x) for x in row) for row in C_bs)
        (a, b, c), (d, e, f), (g, h, i) = self._C
        rows = ((a, b, c), (d, e, f), (g, h, i))
        # raw sensor axes -> corrected body axes, one affine map per sample (.intrinsics);
        # with the intrinsics at their defaults both are the plain rotation _to_body
        self._acc_to_body, self._gyro_to_body = to_body(rows, config.imu_intrinsics,
                                                        self._to_body)
        self.intrinsics_applied = not config.imu_intrinsics.is_identity
        # range rows' lever arm: the antenna's, or, with the range model applied, its phase
        # centre's (EpochFusion._apply_range_model)
        self._corrects = config.range_model.corrects_ranges
        self._plain_lever = np.array(config.lever_arm_m, dtype=float)
        self._model_lever = self._plain_lever + config.range_model.phase_centre_m()
        self.lever = self._plain_lever
        self._lever = tuple(float(c) for c in config.lever_arm_m)
        self.ekf: Eskf | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.gating = GatingCounters()
        self.anchor_stats: dict[int, AnchorStats] = {}
        self.monitor = HealthMonitor(config.health)
        self.monitor.range_model_held = config.range_model.enabled  # until the heading is known
        self.consistency = AnchorConsistency(ConsistencyLimits())
        self.raim = WindowRaim(RaimLimits())
        self.mounting_yaw = MountingYaw()
        self._excluded: set[int] = set()
        self.mounting_finding = ""
        self.imu_check = new_imu_check(config.imu_limits, body_maps(rows, config.imu_intrinsics))
        # on the C core, a good sample while tracking is judged, mapped and integrated in one
        # call (policy.propagation)
        self._front_steps = not isinstance(self.imu_check, ImuCheck)
        self.window = ImuWindow(max(config.static_window_s, config.init_static_s), config.rest,
                                config.gravity_mps2)
        # the anchors known: configured, and those the device reports (learnt before the
        # start, so that the mirror side and the range-model states cover them)
        self._anchors: dict[int, Vec3] = dict(config.anchors_m)
        # the configured anchors whose every coordinate is finite and in range (_resolve)
        self._configured = {a: pos for a, pos in config.anchors_m.items()
                            if all(abs(c) <= MAX_ANCHOR_COORD_M for c in pos)}
        # their positions and variance factors as arrays, by the epoch's anchor ids
        self._resolved: dict[tuple[int, ...], tuple[Array, Array]] = {}
        self.mirror = MirrorSide(np.zeros((0, 3)))
        self._fixed_z: float | None = None
        self.ranges = RangeWindow(config.range_window_s, config.fix_interval_s,
                                  config.range_sigma_m, self.mirror, None)
        self._bias_index: dict[int, int] = {}
        self._mp_index: dict[int, int] = {}
        self._range_columns: dict[int, tuple[int, ...]] = {}
        self._lever_index: tuple[int, ...] = ()  # (set by _layout)
        self._new_anchors = False
        self._layout()
        self.t_ns: int | None = None  # time of the nominal state
        self._imu_t_ns: int | None = None
        self._last_imu: tuple[Vec3, Vec3] | None = None  # body axes, the last one used
        self._fixes: collections.deque[tuple[int, Array]] = collections.deque(maxlen=100)
        self._first_t_ns: int | None = None
        self._start_started_ns: int | None = None  # a restart waits for fresh IMU data
        self._carry: Start | None = None  # what a restart keeps of the estimate before it
        self._last_good_P: Array | None = None
        self.last_internal_error = ""
        self._position_reset_ns = -(2**63)
        self._fade_ns: int | None = None
        self._at_rest = False  # ZUPT rows in this update
        self._constraints_ns = -(2**63)  # when ZUPT, NHC and height rows were last added
        self._good_imu_ns: int | None = None  # the last IMU sample that passed the checks
        self._relevel: str | None = None  # attitude restart pending: "keep" or "level" the tilt
        self._tilt_bad_ns: int | None = None  # since when, at rest, gravity disagrees
        self._tilt_check_ns = -(2**63)
        self.stillness = UwbStillness()
        self._coasted = False
        self._aligner = HeadingAligner(config.align_window_s, config.align_min_dv_mps,
                                       config.range_sigma_m)
        self._aligned = False
        self._policies: dict[tuple[str, bool], RowPolicy] = {}
        self._empty_rows: dict[int, Rows] = {}
        self._gate_1 = chi2_quantile(config.gate_probability, 1)
        self._gate_3 = chi2_quantile(config.gate_probability, 3)

    def _layout(self) -> None:
        """What follows from the anchors: the mirror side of a plane of them, the height
        held over coplanar ones, and one antenna-delay and one multipath state each."""
        cfg = self.cfg
        anchors = np.array(list(self._anchors.values()), dtype=float).reshape(-1, 3)
        old, self.mirror = self.mirror, MirrorSide(anchors, cfg.tag_side, cfg.height_range_m)
        if old.decided_by.startswith("ranges") and self.mirror.ambiguous:
            # what the ranges told about the side still holds with one anchor more
            self.mirror.sign, self.mirror.resolved = old.sign, old.resolved
            self.mirror.decided_by = old.decided_by
        # a known height replaces the vertical that a (horizontal) plane of anchors cannot
        # tell; over a wall the height is observed and the mirror is sideways
        horizontal = abs(float(self.mirror.normal[2])) >= WALL_NORMAL_Z
        self._fixed_z = (cfg.known_height_m
                         if len(anchors) and coplanar(anchors) and horizontal else None)
        self.ranges.side, self.ranges.fixed_z = self.mirror, self._fixed_z
        ids = sorted(self._anchors)
        tight = cfg.mode is Mode.TIGHT  # the offsets are unobservable from loose fixes
        self._bias_index = ({a: N_CORE + i for i, a in enumerate(ids)}
                            if cfg.range_bias_states and tight else {})
        first = N_CORE + len(self._bias_index)
        self._mp_index = ({a: first + i for i, a in enumerate(ids)}
                          if cfg.multipath_states and tight else {})
        # the lever arm's error, three constant states after those (off: none)
        last = first + len(self._mp_index)
        self._lever_index = (last, last + 1, last + 2) if cfg.lever_arm_sigma_m > 0 and tight \
            else ()
        # each anchor's range-model state columns, for its range rows
        self._range_columns = {a: tuple(c for index in (self._bias_index, self._mp_index)
                                        if (c := index.get(a)) is not None) for a in ids}

    # -- inputs ---------------------------------------------------------------------------

    def update(self, uwb: UwbRanges | AnchorRanges) -> list[FusionReport]:
        """Fuse one UWB message (an epoch, or a single range); one report per measurement.
        Anchor-to-anchor ranges (a survey's input, not the tag's) are passed over."""
        if not isinstance(uwb, UwbRanges):
            return []
        try:
            return self._update(uwb)
        except NUMERICAL_ERRORS as err:
            self._internal_error(uwb.t_ns, err)
            return []

    def _update(self, uwb: UwbRanges) -> list[FusionReport]:
        if self._first_t_ns is None:
            self._first_t_ns = uwb.t_ns
        result = gate(uwb, self.cfg.gating, self.gating)
        reports = [FusionReport(uwb.t_ns, "range", str(r.anchor_id), math.nan, math.nan,
                                math.nan, False, why.value) for r, why in result.rejected]
        if result.epoch is None:
            return reports
        ids, anchors, ranges, r_scale = self._resolve(result.epoch, reports)
        if len(ids) == 0:
            return reports
        self.ranges.add(uwb.t_ns, ids, anchors, ranges)
        fix = self._epoch_fix(uwb.t_ns, ids, anchors, ranges)
        return self._fuse_message(uwb.t_ns, ids, anchors, ranges, r_scale, fix, reports)

    def _epoch_fix(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array
                   ) -> LsqFix | None:
        """The message's UWB-only fix where one serves (to start, to align the heading, as
        loose mode's measurement), kept for the start; None where none does or can be made."""
        if self.ekf is not None and self.cfg.mode is not Mode.LOOSE and self._aligned:
            return None
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, self._antenna())
        if fix is not None:
            self._fixes.append((t_ns, fix.position_m))
        return fix

    def _fuse_message(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                      r_scale: Array, fix: LsqFix | None, reports: list[FusionReport]
                      ) -> list[FusionReport]:
        """The rest of :meth:`_update` once the message's ranges are kept and its fix is
        made."""
        if self.mirror.take_flip():
            self._restart(t_ns, "mirror side flipped by the ranges")
        self.monitor.mirror_unresolved = self.mirror.unresolved
        if self.ekf is None:
            if self._new_anchors:  # reported since the last start: laid out before the next
                self._new_anchors = False
                self._layout()
            self._try_start(t_ns, fix)
            return reports
        if self.t_ns is not None and t_ns < self.t_ns:
            self.counters["uwb_late"] += 1  # older than the state: the aligner's job
            return reports
        self._predict_to(t_ns)
        ekf = self.ekf
        if ekf.interval_s >= MIN_PROPAGATE_S or self.records is not None or not self._aligned:
            ekf.propagate()  # single ranges at 100+ Hz share one propagation per 20 ms
        Phi, dv = ekf.take_epoch(self.records is not None)
        # the smoother can step back from this epoch over a plain Kalman prediction only
        linked = self._aligned and not self._coasted
        self._coasted = False
        if not self._aligned:
            self._hold_heading(t_ns, dv, fix)
        self._track_fixes(t_ns, ids, anchors, ranges, fix)
        constraints: list[Rows] = []
        if t_ns - self._constraints_ns >= CONSTRAINT_EVERY_NS:
            # pseudo-measurements at a fixed rate: at 170 single ranges a second they would
            # otherwise weigh 17 times what they do with 10 Hz epochs
            self._constraints_ns = t_ns
            constraints = self._constraints()
        prior = self._snapshot() if self.records is not None else None
        ranges = self._apply_range_model(ids, anchors, ranges)
        if self._lever_index:  # the rows' lever: the given one (or phase centre) + its error
            base = self.lever if self.cfg.range_model.enabled else self._plain_lever
            self.lever = base + ekf.b_r[self._lever_index[0] - N_CORE:][:3]
        self._check_anchors(t_ns, ids, anchors, ranges, r_scale)
        ids, anchors, ranges, r_scale = self._exclude_findings(t_ns, ids, anchors, ranges,
                                                               r_scale, reports)
        reports += self._fuse_epoch(t_ns, ids, anchors, ranges, r_scale, fix, constraints)
        self._fade(t_ns, ids, anchors, ranges)
        if self._check_divergence(t_ns, ids, anchors, ranges):
            linked = False
        elif self.ekf is not None:
            self._last_good_P = self.ekf.P.copy()
        if prior is not None and self.records is not None and self.ekf is not None:
            assert Phi is not None
            self.records.append(EpochRecord(t_ns, *prior, *self._snapshot(),
                                            Phi if linked else None))
        return reports

    # -- internals ------------------------------------------------------------------------
    def _snapshot(self) -> tuple[Nominal, Array]:
        ekf = self.ekf
        assert ekf is not None
        return (Nominal(np.array(ekf.p), np.array(ekf.v), np.array(ekf.q), np.array(ekf.b_g),
                        np.array(ekf.b_a), ekf.b_r.copy()), ekf.P.copy())

    def _antenna(self) -> Array | None:
        """The antenna's position by the estimate (a start point for least squares)."""
        ekf = self.ekf
        if ekf is not None:  # p + R l, in floats (twice as fast as with R as an array)
            (px, py, pz), (w, x, y, z), (lx, ly, lz) = ekf.p, ekf.q, self._lever
            return np.array((
                px + ((1 - 2 * (y * y + z * z)) * lx + 2 * (x * y - w * z) * ly
                      + 2 * (x * z + w * y) * lz),
                py + (2 * (x * y + w * z) * lx + (1 - 2 * (x * x + z * z)) * ly
                      + 2 * (y * z - w * x) * lz),
                pz + (2 * (x * z - w * y) * lx + 2 * (y * z + w * x) * ly
                      + (1 - 2 * (x * x + y * y)) * lz)))
        return self._fixes[-1][1] if self._fixes else None

    def _resolve(self, epoch: UwbRanges, reports: list[FusionReport]
                 ) -> tuple[list[int], Array, Array, Array]:
        """Anchor positions for each range (configured first, else as the device sends),
        the ranges less the range model's attitude-free part, and the factor on each range's
        variance from the device's quality."""
        ids, anchors, ranges, scale = [], [], [], []
        configured = self._configured
        common = True  # every range to a configured anchor, with no quality
        for r in epoch.ranges:
            pos = configured.get(r.anchor_id)
            if pos is not None and r.quality is None:  # the common case: checked once
                ids.append(r.anchor_id)
                anchors.append(pos)
                ranges.append(r.range_m)
                scale.append(1.0)
                continue
            common = False
            pos = self.cfg.anchors_m.get(r.anchor_id, r.anchor_position_m)
            # every coordinate finite and in range (max() would let a NaN after the first by)
            if pos is None or not all(abs(c) <= MAX_ANCHOR_COORD_M for c in pos):
                why = "unknown_anchor" if pos is None else "anchor_position_invalid"
                self.gating.rejections[why] += 1
                reports.append(FusionReport(epoch.t_ns, "range", str(r.anchor_id), math.nan,
                                            math.nan, math.nan, False, why))
                continue
            if r.anchor_id not in self._anchors:  # reported by the device
                self._anchors[r.anchor_id] = pos
                if self.ekf is None:
                    self._layout()
                    self._fixes.clear()  # solved without this anchor's plane, perhaps
                    self.ranges.epochs.clear()
                else:  # the state's shape is fixed once started: at the next start
                    self._new_anchors = True
            ids.append(r.anchor_id)
            anchors.append(pos)
            ranges.append(r.range_m)
            scale.append(quality_scale(r.quality))
        if self._corrects:  # the anchors' calibrated delays, the distance term (range_model)
            ranges = self.cfg.range_model.corrected_m(ids, ranges)
        if common:  # the same anchors recur: their arrays made once (read only downstream)
            key = tuple(ids)
            arrays = self._resolved.get(key)
            if arrays is None:
                arrays = self._resolved[key] = (np.array(anchors, dtype=float).reshape(-1, 3),
                                                np.ones(len(ids)))
                for a in arrays:
                    a.flags.writeable = False
            return ids, arrays[0], np.array(ranges), arrays[1]
        return (ids, np.array(anchors, dtype=float).reshape(-1, 3), np.array(ranges),
                np.array(scale))

    def _hold_heading(self, t_ns: int, dv: Vec3, fix: LsqFix | None) -> None:
        """Until aligned the heading is held (an EKF linearised about a large yaw error
        turns falsely confident within a second of motion); then :class:`HeadingAligner`
        tells the yaw error and the EKF takes over with its σ."""
        ekf = self.ekf
        assert ekf is not None
        self._aligner.add_ins_dv(dv)
        # the heading is unknown: the INS's horizontal Δv may point anywhere; for a heading
        # error uniform over ±180° the RMS error of a turned Δv is √2 |Δv|, so the fixes
        # must be free to say where it went
        extra = np.zeros(ekf.n)
        extra[3:5] = 2.0 * (dv[0] ** 2 + dv[1] ** 2)
        ekf.add_variances(extra)
        ekf.rotate_heading(0.0, HELD_YAW_SIGMA_RAD)
        if fix is None or not self._aligner.wants_fix(t_ns):
            return
        # the INS's yaw, and what its horizontal accelerometer and gyro biases may still be
        w, x, y, z = ekf.q
        P = ekf.P
        result = self._aligner.add_fix(
            t_ns, fix, math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
            math.sqrt(max(P[BA_.start, BA_.start] + P[BA_.start + 1, BA_.start + 1], 0) / 2),
            math.sqrt(max(P[BG_.start, BG_.start] + P[BG_.start + 1, BG_.start + 1], 0) / 2),
            math.sqrt(max(P[TH_.start, TH_.start] + P[TH_.start + 1, TH_.start + 1], 0) / 2))
        if result is not None:
            ekf.rotate_heading(*result)
            self._aligned = True
            self.counters["heading_alignments"] += 1

    def _track_fixes(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                     fix: LsqFix | None) -> None:
        """UWB-only fixes for :class:`UwbStillness`, about 5 a second."""
        if self.stillness.wants_fix(t_ns):
            fix = fix or self.ranges.fix(t_ns, ids, anchors, ranges, self._antenna(),
                                         force=True, weigh=False)
            if fix is not None:
                self.stillness.add(t_ns, fix)
        self.stillness.forget_before(t_ns)

    def _constraints(self) -> list[Rows]:
        ekf = self.ekf
        assert ekf is not None
        cfg = self.cfg
        rows = []
        # constant velocity looks like rest to an IMU: require a slow estimate, and a state
        # that the ranges have not moved either (a ZUPT would otherwise pin v at 0 for good)
        slow = math.hypot(*ekf.v) < cfg.zupt_max_speed_mps and self.stillness.still()
        t_ns = self.t_ns or 0
        tilt_check_due = t_ns - self._tilt_check_ns >= TILT_CHECK_EVERY_NS
        still_imu = ((slow and cfg.zupt) or tilt_check_due) and self._imu_fresh() \
            and self.imu_check.burst_s(t_ns) == 0.0 and self.window.static(cfg.static_window_s)
        if tilt_check_due:
            self._tilt_check_ns = t_ns
            # the IMU still and the UWB fixes too, whatever the velocity estimate says (a
            # wrong tilt makes it wrong): the mean specific force is gravity's reaction
            if still_imu and self.stillness.still(allow_noise=True):
                self._check_tilt_against_gravity()
            else:
                self._tilt_bad_ns = None
        self._at_rest = bool(cfg.zupt and slow and still_imu and self._relevel is None)
        if self._at_rest:
            self.counters["zupt"] += 1
            rows.append(zupt_rows(ekf, cfg.zupt_sigma_mps))
        if cfg.nhc:
            rows.append(nhc_rows(ekf, cfg.nhc_sigma_mps))
            if self._aligned and not self._at_rest:  # the direction of travel in body axes
                vx, vy, _ = (ekf.R.T @ np.asarray(ekf.v)).tolist()
                self.mounting_yaw.add(vx, vy)
                self.monitor.mounting_inconsistent = self.mounting_yaw.error_deg is not None
        if cfg.known_height_m is not None:
            rows.append(height_rows(ekf, cfg.known_height_m, cfg.height_sigma_m))
        return rows

