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
* :mod:`.policy.alignment` and :mod:`.policy.heading` — the coarse heading from INS against
  UWB velocity changes, and the heading held until then;
* :mod:`.models.measurements` — the rows of each measurement model (range, fix, ZUPT, NHC, height);
* :mod:`.policy.robust` — de-weighting NLOS ranges, per-anchor statistics;
* :mod:`.policy.health` — the health record, and the evidence for restarts;
* :mod:`.policy.estimate` — the state the parts below share, declared once: the estimate and
  the installation checks' findings;
* :mod:`.policy.installation` — the anchors, the state's layout they give, each message's
  ranges resolved to anchor positions;
* :mod:`.policy.propagation` — each IMU sample judged, kept and integrated;
* :mod:`.policy.recovery` — the start, the restarts and what triggers them;
* :mod:`.policy.fusing` — one epoch's rows fused and each row's outcome;
* :mod:`.policy.constraints` — the ZUPT, NHC and height rows due, the tilt against gravity;
* :mod:`.policy.period` — a pose period's single ranges and IMU samples, queued and fused
  in one call of the core; the policy runs with every epoch and, for single ranges, once a
  pose period after them (:meth:`Filter._period_policy`: its decisions may land up to a
  period late);
* :mod:`.policy.integrity` — the bank's solution separation (:mod:`.checks.separation`):
  protection levels over each anchor's fault, and which anchor's separation is too large;
* :mod:`.policy.outputs` — the pose, the health record, the diagnostics;
* :mod:`.core.eskf` — the algebra (docs/ekf.md).

Each part is an object with its own state, handed the shared state it reads; the filter
holds them and runs them in sequence. The numbers are :class:`~uwbd.fusion.core.eskf.Eskf`'s
(on the C core, :class:`~uwbd.fusion.core.state.CoreEskf`); every decision is made here and
in the modules above.

Life cycle: **waiting** (collect IMU and fixes), start at rest or while moving, **aligning**
(heading held until the vehicle has moved enough), **tracking**. A rejected IMU burst or an
IMU gap widens the covariance for what was not seen; one longer than
``attitude_lost_after_s`` restarts the heading in place (position, velocity, biases and tilt
kept). A non-finite state restarts from UWB, keeping finite biases (a non-finite covariance
with a finite state only restores the last finite covariance). Innovations inconsistent for
a while move the position to a UWB fix, but only to one that is consistent itself (NLOS does
not pull the state away); diverging again within 10 s restarts from UWB, biases dropped. At
rest (IMU and UWB fixes both still), an attitude 10° against gravity for a second is
levelled anew. Without ranges the state coasts and its covariance grows.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.frames import AnchorRanges, ImuSample, UwbRanges
from uwbd.fusion.checks.bias_gain import BiasGain
from uwbd.fusion.checks.gating import GatingCounters, gate
from uwbd.fusion.core import native
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.rotation import Array, body_point
from uwbd.fusion.core.smoother import EpochRecord, Nominal
from uwbd.fusion.models.measurements import Rows
from uwbd.fusion.policy import outputs
from uwbd.fusion.policy.constraints import Constraints
from uwbd.fusion.policy.estimate import Estimate, Findings, new_aligner
from uwbd.fusion.policy.fixes import RangeWindow
from uwbd.fusion.policy.fusing import EpochFusion
from uwbd.fusion.policy.heading import hold_heading
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.policy.installation import Installation
from uwbd.fusion.policy.integrity import Integrity
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.fusion.policy.period import MIN_PROPAGATE_S, Message, PeriodQueue
from uwbd.fusion.policy.propagation import NUMERICAL_ERRORS, ImuPropagation
from uwbd.fusion.policy.recovery import Recovery
from uwbd.fusion.policy.rest import ImuWindow, UwbStillness
from uwbd.fusion.settings import FilterConfig, Mode
from uwbd.fusion.types import FusionReport, Health, Pose

Vec3 = tuple[float, float, float]
POLICY_EVERY_NS = 100_000_000  # with single ranges, at a slow pose rate: ten times a second
_NO_ANCHORS, _NONE = np.zeros((0, 3)), np.zeros(0)


class Filter:
    """Loosely or tightly coupled UWB/INS error-state EKF (see module doc)."""

    def __init__(self, config: FilterConfig, record: bool = False) -> None:
        """``record``: keep every epoch's prior and posterior for :mod:`.core.smoother` (offline;
        about 13 kB an epoch with 8 anchors)."""
        self.cfg = config
        # the implementation of the numbers, chosen once: the C core, or the pure-Python
        # reference (UWBD_PURE_PYTHON=1); every part below is handed it
        core = self.core = native.core
        self.records: list[EpochRecord] | None = [] if record else None
        self.gating = GatingCounters()
        monitor = HealthMonitor(config.health)
        monitor.range_model_held = config.range_model.enabled  # until the heading is known
        self.ranges = RangeWindow(config.range_window_s, config.fix_interval_s,
                                  config.range_sigma_m, MirrorSide(np.zeros((0, 3)), core=core),
                                  None, core=core)
        self.installation = Installation(config, self.ranges, core)
        self.est = Estimate(monitor, new_aligner(config), self.installation.plain_lever,
                            record)
        self.findings = Findings(BiasGain(core))
        self.window = ImuWindow(max(config.static_window_s, config.init_static_s), config.rest,
                                config.gravity_mps2, core=core)
        self.stillness = UwbStillness()
        self.recovery = Recovery(config, self.est, self.installation, self.findings,
                                 self.window, self.ranges, self.stillness, core)
        self.imu = ImuPropagation(config, self.est, self.window, self.recovery, core)
        self.fusion = EpochFusion(config, self.est, self.installation, self.findings,
                                  self.imu.fresh)
        self.integrity = Integrity(config.health, config.range_sigma_m, self.est,
                                   self.findings, self.installation)
        self._lever = tuple(float(c) for c in config.lever_arm_m)
        self.constraints = Constraints(config, self.est, self.findings, self.window,
                                       self.stillness, self.imu, self.recovery, self.fusion)
        self._policy_ns = -(2**63)  # the policy's last run: once a pose period, and at
        self._policy_every_ns = min(config.pose_period_ns, POLICY_EVERY_NS)  # least this often
        # the period's single ranges and samples, fused at its end (or when read)
        self.queue = PeriodQueue(config, self.est, self.findings, self.installation, self.imu,
                                 self.window, self.fusion, self.recovery, self._fuse_single)
        # single ranges queue unless a range model corrects each at its state, or the
        # smoother records each update
        self._queues = not (config.range_model.enabled or config.range_model.anchor_degree
                            or record)

    # -- what the parts share, for the caller --------------------------------------------
    @property
    def ekf(self) -> Eskf | None:
        """The state's numbers (``None`` before the start and while restarting)."""
        self._fuse_queue()
        return self.est.ekf

    @property
    def t_ns(self) -> int | None:
        """The time of the nominal state."""
        self._fuse_queue()
        return self.est.t_ns

    @property
    def counters(self) -> collections.Counter[str]:
        """What happened, counted."""
        self._fuse_queue()
        return self.est.counters

    def flush(self) -> list[FusionReport]:
        """The period's queued ranges and samples fused now; the reports :meth:`update` has
        not handed on yet (the last of a run's)."""
        self._fuse_queue()
        reports, self.queue.reports = self.queue.reports, []
        return reports

    def _fuse_queue(self) -> None:
        """Anything that reads the state fuses the queued period first."""
        if self.queue:
            self.queue.fuse()

    # -- inputs ---------------------------------------------------------------------------
    def predict(self, imu: ImuSample) -> None:
        """Integrate one IMU sample (sensor axes); bad samples are counted, never used."""
        self.predict_many((imu,))

    def predict_many(self, samples: Sequence[ImuSample]) -> None:
        """A read's samples, in time order: what :meth:`predict` does to each (queued among
        a period's single ranges)."""
        if not self.queue:
            self.imu.predict_many(samples)
        elif not self.queue.add_samples(samples):
            self.queue.fuse()

    def update(self, uwb: UwbRanges | AnchorRanges) -> list[FusionReport]:
        """Fuse one UWB message (an epoch, or a single range: queued, fused at the period's
        end); a report per measurement fused since the last call (:meth:`flush`: the last).
        Anchor-to-anchor ranges (a survey's input, not the tag's) are passed over."""
        if not isinstance(uwb, UwbRanges):
            return []
        try:
            reports = self._update(uwb)
        except NUMERICAL_ERRORS as err:
            self.recovery.internal_error(uwb.t_ns, err)
            reports = []
        if self.queue.reports:  # (the period's queued ranges', fused since)
            reports, self.queue.reports = self.queue.reports + reports, []
        return reports

    # -- outputs --------------------------------------------------------------------------
    def health(self, now_ns: int | None = None) -> Health:
        """The health record, rebuilt from the evidence, at the state's time or at
        ``now_ns`` if later (the daemon's status on the wall clock: silent ports make the
        time since the last range and the last IMU sample grow, and the health says so)."""
        self._fuse_queue()
        t_ns = self.est.t_ns if self.est.t_ns is not None else self.imu.imu_t_ns
        if t_ns is not None and now_ns is not None and now_ns > t_ns:
            t_ns = now_ns
        return outputs.health_at(self.est, t_ns, self.imu.good_imu_ns, self.cfg.max_imu_gap_s)

    @property
    def status(self) -> str:
        return self.health().summary()

    def pose(self) -> Pose | None:
        """The pose now, or ``None`` before the start, while restarting, or when any of
        its numbers is not finite (which also restarts the filter)."""
        self._fuse_queue()
        ekf, t_ns = self.est.ekf, self.est.t_ns
        if ekf is None or t_ns is None:
            return None
        numbers = ekf.pose_numbers(self.est.aligned)
        if numbers is None:
            self.recovery.restart_not_finite(t_ns)
            return None
        return outputs.pose_of(self.est, t_ns, numbers)

    def diagnostics(self, now_ns: int | None = None) -> dict[str, Any]:
        """For the status: the health record (at ``now_ns``, as :meth:`health`), the mirror
        side, per-anchor range statistics and the findings."""
        lever = self.est.lever if self.installation.lever_estimated and self.est.ekf is not None \
            else None
        return outputs.diagnostics(self.health(now_ns), self.installation.mirror,
                                   self.findings, lever)

    # -- one UWB message ------------------------------------------------------------------
    def _update(self, uwb: UwbRanges) -> list[FusionReport]:
        if self.recovery.first_t_ns is None:
            self.recovery.first_t_ns = uwb.t_ns
        result = gate(uwb, self.cfg.gating, self.gating)
        reports = [FusionReport(uwb.t_ns, "range", str(r.anchor_id), math.nan, math.nan,
                                math.nan, False, why.value) for r, why in result.rejected]
        if result.epoch is None:
            return reports
        known = len(self.installation.anchors)
        ids, anchors, ranges, r_scale = self.installation.resolve(result.epoch, self.gating,
                                                                  reports)
        if len(self.installation.anchors) > known:  # the device reported a new anchor
            if self.est.ekf is None:
                self.installation.lay_out()
                self.recovery.fixes.clear()  # solved without this anchor's plane, perhaps
                self.ranges.epochs.clear()
            else:  # the state's shape is fixed once started: at the next start
                self.installation.new_anchors = True
        if len(ids) == 0:
            return reports
        self.ranges.add(uwb.t_ns, ids, anchors, ranges)
        message = (uwb.t_ns, ids, anchors, ranges, r_scale)
        if len(uwb.ranges) < 2 and self._tracking():  # a single range: its numbers now or
            if self._queues:  # at the period's end; the policy once a period, after them
                if not self.queue.add_range(message):
                    self.queue.fuse()
            else:
                reports += self._fuse_single(message)
            if uwb.t_ns - self._policy_ns >= self._policy_every_ns:
                self._fuse_queue()
                self._period_policy(message, reports)
            return reports
        self._fuse_queue()
        fix = self._epoch_fix(uwb.t_ns, ids, anchors, ranges)
        return self._decide(uwb.t_ns, ids, anchors, ranges, r_scale, fix, reports)

    def _epoch_fix(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array
                   ) -> LsqFix | None:
        """The message's UWB-only fix where one serves (to start, to align the heading, as
        loose mode's measurement), kept for the start; None where none does or can be made."""
        if self.est.ekf is not None and self.cfg.mode is not Mode.LOOSE and self.est.aligned:
            return None
        fix = self.ranges.fix(t_ns, ids, anchors, ranges, self._antenna())
        if fix is not None:
            self.recovery.fixes.append((t_ns, fix.position_m))
        return fix

    def _tracking(self) -> bool:
        """Tight, started, the heading aligned, not re-levelling: single ranges take the
        period's path (their numbers, then the policy once a period)."""
        return self.est.aligned and self.est.ekf is not None and self.est.relevel is None \
            and self.cfg.mode is Mode.TIGHT

    def _fuse_single(self, message: Message) -> list[FusionReport]:
        """A single range's numbers: the state brought to it, its row fused and reported
        (an anchor the policy left out: reported, its row left out); a range queued when
        the state has since stopped tracking takes the whole step (:meth:`_decide`)."""
        t_ns, ids, anchors, ranges, r_scale = message
        if not self._tracking():
            return self._decide(t_ns, ids, anchors, ranges, r_scale, None, [])
        reports: list[FusionReport] = []
        if self.est.t_ns is not None and t_ns < self.est.t_ns:
            self.est.counters["uwb_late"] += 1
            return reports
        self.imu.predict_to(t_ns)
        linked, Phi, _ = self._propagate()
        ranges = self._range_model(ids, anchors, ranges)
        self.queue.period.append((t_ns, ids, anchors, ranges, r_scale))
        excluded = self.findings.excluded  # (as the period's policy left them)
        if excluded and any(a in excluded for a in ids):
            ids, anchors, ranges, r_scale = self.fusion.leave_out(t_ns, excluded, ids, anchors,
                                                                  ranges, r_scale, reports)
        return self._fuse_numbers(t_ns, ids, anchors, ranges, r_scale, None, [], reports,
                                  linked, Phi)

    def _period_policy(self, message: Message, reports: list[FusionReport]) -> None:
        """The policy at the end of a period of single ranges (``message``: its last): the
        mirror side, the fixes for stillness, the constraints due, the installation checks
        on the period's ranges and the exclusions they call for, the separation test,
        fading and the divergence checks."""
        t_ns, ids, anchors, ranges, _ = message
        self._policy_ns = t_ns
        self._mirror_side(t_ns)
        if self.est.ekf is None or self.est.t_ns is None:
            return
        self._track_fixes(t_ns, ids, anchors, ranges, None)
        constraints = self.constraints.due(self.est.t_ns)
        period = self.queue.period
        for checked in period:  # the period's single ranges, in order
            self.fusion.check_anchors(*checked)
        self.fusion.decide_exclusions(sorted({a for m in period for a in m[1]}))
        period.clear()
        if constraints:
            linked, Phi, _ = self._propagate()
            self._fuse_numbers(self.est.t_ns, [], _NO_ANCHORS, _NONE, _NONE, None, constraints,
                               reports, linked, Phi)
        self._after_update(t_ns, ids, anchors, ranges)

    def _after_update(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array) -> bool:
        """The separation test, fading, the divergence checks: True if they moved the state."""
        self.integrity.after_update(t_ns)
        self.recovery.fade(t_ns, ids, anchors, ranges)
        if self.recovery.check_divergence(t_ns, ids, anchors, ranges):
            return True
        if self.est.ekf is not None:
            self.recovery.last_good_P = self.est.ekf.P.copy()
        return False

    def _mirror_side(self, t_ns: int) -> None:
        """The data flipped the side of a plane of anchors: a restart; the health told."""
        if self.installation.mirror.take_flip():
            self.recovery.restart(t_ns, "mirror side flipped by the ranges")
        self.est.monitor.mirror_said(self.installation.mirror)

    def _decide(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                r_scale: Array, fix: LsqFix | None, reports: list[FusionReport]
                ) -> list[FusionReport]:
        """A message with the policy: the start, the heading, the constraints due, the
        installation checks on the period's ranges, the exclusions, the integrity test, the
        fading and the divergence checks."""
        self._policy_ns = t_ns
        self._mirror_side(t_ns)
        if self.est.ekf is None:
            self.queue.period.clear()
            if self.installation.new_anchors:  # reported since the last start: laid out now
                self.installation.new_anchors = False
                self.installation.lay_out()
            self.recovery.try_start(t_ns, fix)
            self.integrity.after_update(t_ns)  # (a start: the bank's warm-up begins)
            return reports
        if self.est.t_ns is not None and t_ns < self.est.t_ns:
            self.est.counters["uwb_late"] += 1  # older than the state: the aligner's job
            return reports
        self.imu.predict_to(t_ns)
        linked, Phi, dv = self._propagate()
        if not self.est.aligned and hold_heading(self.est, t_ns, dv, fix):
            assert self.est.ekf is not None  # (the heading aligned: the bank's lever member
            self.integrity.heading_aligned(self.est.ekf)  # starts anew)
        self._track_fixes(t_ns, ids, anchors, ranges, fix)
        constraints = self.constraints.due(t_ns)
        ranges = self._range_model(ids, anchors, ranges)
        for message in self.queue.period:  # the period's single ranges, in order, then this
            self.fusion.check_anchors(*message)
        self.queue.period.clear()
        self.fusion.check_anchors(t_ns, ids, anchors, ranges, r_scale)
        ids, anchors, ranges, r_scale = self.fusion.exclude_findings(t_ns, ids, anchors,
                                                                     ranges, r_scale, reports)
        return self._fuse_numbers(t_ns, ids, anchors, ranges, r_scale, fix, constraints,
                                  reports, linked, Phi, decide=True)

    def _propagate(self) -> tuple[bool, Array | None, Vec3]:
        """The covariance to the message (single ranges at 100+ Hz share one propagation per
        20 ms); whether the smoother can step back over this epoch's prediction (a plain
        Kalman one: no gap coasted), and the epoch's Φ (kept when recording) and Δv."""
        ekf = self.est.ekf
        assert ekf is not None
        if ekf.interval_s >= MIN_PROPAGATE_S or self.records is not None or not self.est.aligned:
            ekf.propagate()
        Phi, dv = ekf.take_epoch(self.records is not None)
        linked = self.est.aligned and not self.imu.coasted
        self.imu.coasted = False
        return linked, Phi, dv

    def _range_model(self, ids: list[int], anchors: Array, ranges: Array) -> Array:
        """The ranges corrected by the range model; the rows' lever arm: the given one (or
        the phase centre) plus its error states' estimate."""
        ekf = self.est.ekf
        assert ekf is not None
        ranges = self.fusion.apply_range_model(
            ids, anchors, ranges, self._antenna() if self.cfg.range_model.anchor_degree else None)
        lever_index = self.installation.lever_index
        if lever_index:
            base = self.est.lever if self.cfg.range_model.enabled \
                else self.installation.plain_lever
            self.est.lever = base + ekf.b_r[lever_index[0] - N_CORE:][:3]
        return ranges

    def _fuse_numbers(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                      r_scale: Array, fix: LsqFix | None, constraints: list[Rows],
                      reports: list[FusionReport], linked: bool, Phi: Array | None,
                      decide: bool = False) -> list[FusionReport]:
        """The message's rows fused and reported (``decide``: :meth:`_after_update` too)."""
        prior = self._snapshot() if self.records is not None else None
        reports += self.fusion.fuse_epoch(t_ns, ids, anchors, ranges, r_scale, fix, constraints)
        if decide and self._after_update(t_ns, ids, anchors, ranges):
            linked = False
        if prior is not None and self.records is not None and self.est.ekf is not None:
            assert Phi is not None
            self.records.append(EpochRecord(t_ns, *prior, *self._snapshot(),
                                            Phi if linked else None))
        return reports

    def _snapshot(self) -> tuple[Nominal, Array]:
        ekf = self.est.ekf
        assert ekf is not None
        return (Nominal(np.array(ekf.p), np.array(ekf.v), np.array(ekf.q), np.array(ekf.b_g),
                        np.array(ekf.b_a), ekf.b_r.copy()), ekf.P.copy())

    def _antenna(self) -> Array | None:
        """The antenna's position by the estimate (a start point for least squares)."""
        ekf = self.est.ekf
        if ekf is not None:
            return np.array(body_point(ekf.p, ekf.q, self._lever))
        return self.recovery.fixes[-1][1] if self.recovery.fixes else None

    def _track_fixes(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
                     fix: LsqFix | None) -> None:
        """UWB-only fixes for :class:`UwbStillness`, about 5 a second."""
        if self.stillness.wants_fix(t_ns):
            fix = fix or self.ranges.fix(t_ns, ids, anchors, ranges, self._antenna(),
                                         force=True, weigh=False)
            if fix is not None:
                self.stillness.add(t_ns, fix)
        self.stillness.forget_before(t_ns)
