"""A pose period's single ranges and the IMU samples among them, fused in one call of the
C core (decision (a) of the estimator's rebuild).

While tracking, :class:`~uwbd.fusion.filter.Filter` runs its policy with every epoch and,
for single ranges, once a pose period after them; the single ranges and the IMU samples
that come among them are queued here, in the order they came, and fused when the period
ends (or anything reads the state): ``State.fuse_period`` takes each item while it is the
common one (a sample the IMU front passes with no gap: the front's rule; a range not
earlier than the state, with a fresh IMU: :func:`.propagation.fresh_at`, judged here), and
returns each range's outcome; any other item goes through the policy's own step
(:meth:`ImuPropagation.step_one`, the filter's single-range step), which is also how the
pure-Python core takes every item: the reference the C core is held to
(tests/test_period.py). Its own state is the queue; the outcomes go to the parts they did
before (reports, counters, health evidence, anchor statistics).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from drivers.frames import ImuSample
from uwbd.fusion.checks.imu_check import ImuCheck
from uwbd.fusion.core.layout import N_CORE
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.state import CoreEskf
from uwbd.fusion.policy.estimate import Estimate, Findings
from uwbd.fusion.policy.fusing import MAX_RANGE_BIAS_SIGMA_M, MAX_SIGMA, EpochFusion
from uwbd.fusion.policy.installation import Installation
from uwbd.fusion.policy.propagation import (
    NUMERICAL_ERRORS,
    PROPAGATE_EVERY_S,
    ImuPropagation,
    fresh_at,
)
from uwbd.fusion.policy.recovery import Recovery
from uwbd.fusion.policy.rest import ImuWindow
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import FusionReport

# a message queued: t_ns, ids, anchors (k×3), ranges, their variance scales
Message = tuple[int, list[int], Array, Array, Array]
MIN_PROPAGATE_S = 0.02  # a range propagates the covariance at most this often
MAX_QUEUED = 512  # items: a caller that never asks for a pose still gets them fused
_SAMPLE, _RANGE = ord("i"), ord("r")


class PeriodQueue:
    """The period's items, and their fusion (see module doc)."""

    def __init__(self, cfg: FilterConfig, est: Estimate, findings: Findings,
                 installation: Installation, imu: ImuPropagation, window: ImuWindow,
                 fusion: EpochFusion, recovery: Recovery,
                 fuse_message: Callable[[Message], list[FusionReport]]) -> None:
        self.cfg, self.est, self.findings, self.installation = cfg, est, findings, installation
        self.imu, self.window, self.fusion, self.recovery = imu, window, fusion, recovery
        self._fuse_message = fuse_message  # the filter's step for one message
        # the C IMU front, where the core is C (None: every item takes the policy's step)
        self._front = None if isinstance(imu.check, ImuCheck) else imu.check
        self._items: list[ImuSample | Message] = []
        self._order = bytearray()
        self._samples: list[tuple[int, tuple[float, float, float], tuple[float, float, float]]] \
            = []
        self._ranges: list[tuple[int, int | None, list[float], float, float, tuple[int, ...]]] \
            = []
        self.period: list[Message] = []  # the period's ranges fused, for the checks
        self.reports: list[FusionReport] = []  # the fused items', until the filter hands them on
        self.core_ranges = 0  # ranges the core took (the others took the policy's step)

    def __bool__(self) -> bool:
        return bool(self._items)

    def add_samples(self, samples: Sequence[ImuSample]) -> bool:
        """A read's samples queued; False once the queue is full (fuse it)."""
        for s in samples:
            self._items.append(s)
            self._order.append(_SAMPLE)
            self._samples.append((s.t_ns, s.acc_mps2, s.gyro_rps))
        return len(self._items) < MAX_QUEUED

    def add_range(self, message: Message) -> bool:
        """A single range queued; False once the queue is full."""
        t_ns, ids, anchors, ranges, r_scale = message
        anchor = ids[0]
        self._items.append(message)
        self._order.append(_RANGE)
        self._ranges.append((t_ns, anchor, anchors[0].tolist(), float(ranges[0]),
                             self.cfg.range_sigma_m**2 * float(r_scale[0]),
                             self.installation.range_columns.get(anchor, ())))
        return len(self._items) < MAX_QUEUED

    def fuse(self) -> None:
        """Every queued item, in order: on the C core in one call while each is the common
        one, else through the policy's own step."""
        items, order, samples, ranges = self._items, bytes(self._order), self._samples, \
            self._ranges
        self._items, self._order, self._samples, self._ranges = [], bytearray(), [], []
        i = si = ri = 0
        while i < len(items):
            reason = None
            if self._front is not None and self._common_ready():
                try:
                    done, reason = self._fuse_core(order[i:], samples[si:], ranges[ri:],
                                                   items[i:])
                except NUMERICAL_ERRORS as err:  # (a restart: the rest as the policy's)
                    self.recovery.internal_error(_time_of(items[i]), err)
                    done = 0
                taken = order.count(_SAMPLE, i, i + done)
                i, si, ri = i + done, si + taken, ri + done - taken
                if i == len(items):
                    return
            item = items[i]
            try:
                if isinstance(item, ImuSample):
                    si += 1
                    if reason is not None:  # (the front judged it: rejected)
                        self.imu.step_one(item, reason)
                    else:
                        self.imu.predict_many((item,))
                else:
                    ri += 1
                    self.reports += self._fuse_message(item)
            except NUMERICAL_ERRORS as err:
                self.recovery.internal_error(_time_of(item), err)
            i += 1

    def _common_ready(self) -> bool:
        """The core can take the common items: a state on it, tracking, samples known."""
        ekf, imu = self.est.ekf, self.imu
        return isinstance(ekf, CoreEskf) and self.est.relevel is None \
            and self.est.aligned and imu.imu_t_ns is not None and imu.good_imu_ns is not None \
            and imu.last_imu is not None and self.est.t_ns is not None

    def _common_prefix(self, order: bytes, samples: list[Any], ranges: list[Any]) -> int:
        """How many items the core may take: up to the first range that is not the common
        one (earlier than the state: late; later, with the IMU not fresh: to coast through),
        the samples before it taken as common (the core stops at one that is not)."""
        state_ns, good_ns = self.est.t_ns, self.imu.good_imu_ns
        assert state_ns is not None and good_ns is not None
        max_gap_s = self.cfg.max_imu_gap_s
        si = ri = 0
        for k, kind in enumerate(order):
            if kind == _SAMPLE:
                t_ns = samples[si][0]
                si += 1
                if t_ns > state_ns:
                    state_ns = good_ns = t_ns
                continue
            t_ns = ranges[ri][0]
            ri += 1
            if t_ns < state_ns or (t_ns > state_ns and not fresh_at(t_ns, good_ns, max_gap_s)):
                return k
            state_ns = t_ns
        return len(order)

    def _fuse_core(self, order: bytes, samples: list[Any], ranges: list[Any],
                   items: list[ImuSample | Message]) -> tuple[int, str | None]:
        """The items on the C core while each is the common one: how many, and the IMU
        front's reason where it rejected the next."""
        est, imu = self.est, self.imu
        ekf = est.ekf
        assert isinstance(ekf, CoreEskf) and imu.last_imu is not None
        lever_index = self.installation.lever_index
        plain = self.installation.plain_lever
        assert imu.imu_t_ns is not None and est.t_ns is not None
        count = self._common_prefix(order, samples, ranges)
        if count == 0:
            return 0, None
        excluded = self.findings.excluded  # (as the period's policy left them: an anchor
        if excluded:  # left out keeps the state's step, without its row, id None)
            ranges = [(r[0], None, *r[2:]) if r[1] in excluded else r for r in ranges]
        done, reason, rows, outcomes, last_ns, state_ns, last, clamps, predicted = \
            ekf.fuse_period(self._front, order[:count], samples, ranges, plain.tolist(),
                            lever_index, self.fusion.range_policy(), MAX_SIGMA,
                            MAX_RANGE_BIAS_SIGMA_M, (imu.imu_t_ns, est.t_ns,
                                                     self.cfg.max_imu_gap_s, PROPAGATE_EVERY_S,
                                                     MIN_PROPAGATE_S),
                            (*imu.last_imu[0], *imu.last_imu[1]))
        if rows:
            self.window.add_rows(rows)
            imu.imu_t_ns, imu.good_imu_ns = last_ns, int(rows[-1][0])
            imu.last_imu = ((last[0], last[1], last[2]), (last[3], last[4], last[5]))
        est.t_ns = state_ns
        if predicted:
            est.monitor.imu_gap = False
        if outcomes:
            self.core_ranges += len(outcomes)
            imu.coasted = False
            if lever_index:  # the rows' lever: the given one + its error states'
                est.lever = plain + ekf.b_r[lever_index[0] - N_CORE:][:3]
        if clamps:
            est.counters["covariance_clamped"] += clamps
        k = 0
        for item in items[:done]:
            if isinstance(item, ImuSample):
                continue
            t_ns, ids, anchors, values, r_scale = item
            self.period.append(item)
            if ranges[k][1] is None:
                self.fusion.leave_out(t_ns, self.findings.excluded, ids, anchors, values,
                                      r_scale, self.reports)
            elif (outcome := outcomes[k]) is not None:
                self.reports += self.fusion.row_outcomes(t_ns, [("range", str(ids[0]))],
                                                         [outcome])
            k += 1
        return done, reason


def _time_of(item: ImuSample | Message) -> int:
    return item.t_ns if isinstance(item, ImuSample) else item[0]
