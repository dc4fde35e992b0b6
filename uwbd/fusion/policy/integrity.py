"""The bank's solution-separation test run as the filter goes (:mod:`..checks.separation`):
after an update, at most every ``EVERY_NS``, its protection levels and each anchor's test
statistic handed to the health monitor; and the exclusion.

**Exclusion.** An anchor whose separation is over its threshold in ``EXCLUDE_AFTER``
tests in a row is the likely fault: the main filter becomes that anchor's sub-filter (the
estimate that never took its ranges, :meth:`~uwbd.fusion.core.eskf.Eskf.adopt`) and the
anchor is left out (``Findings.separated``), as long as ``MIN_KEPT_ANCHORS`` others remain.
After ``HOLD_S`` (doubled at each exclusion of the same anchor) it is taken back on
trial: its sub-filter has not seen it since, so the bank tests it afresh, and a fault that
is still there is found and left out again. With too few anchors to leave one out, the
fault stays found: no protection level holds then, and the monitor says so, until
``ALARM_HOLD_S`` after the last test over its threshold (a fault a test or two misses
between its detections is still there).

**The lever arm.** The bank's lever member (``LEVER_MEMBER``) leaves no anchor out but
estimates the lever arm's error, which the main filter holds at zero (``imu.lever_arm_m``
taken as true, unless ``[fusion] lever_arm_sigma_m`` has it estimated). As the body turns,
a lever arm off moves that member away from the main filter: its separation over its
threshold, with the heading aligned (the member starts anew then: before, the unknown
heading looks like a lever arm off), the bank warm and no anchor found (the member takes
every anchor's ranges, and its states may take up part of an anchor's fault), is the fault
``lever_arm_inconsistent``, held ``LEVER_HOLD_S`` after its last detection; no level holds
meanwhile, and the status names ``imu.lever_arm_m`` with where the member puts the
antenna. It is not taken on (measured: a mounting turned about z also moves that member,
and a filter that then estimated the lever arm was healthy while 0.5 m off); nor is the
member's level part of the protection levels, which an unobserved lever arm would make
its prior's.

The bank starts anew with the main filter (a start, a restored covariance, a position
reset, an exclusion): its separations then say nothing yet, so for ``WARM_S`` after that
the levels over the anchors' faults are not known (the monitor says so: after a start, as
part of aligning; later, as ``position_uncertain``).
"""

from __future__ import annotations

import numpy as np

from uwbd.fusion.checks.separation import LEVER_MEMBER, Separation, SeparationTest
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.estimate import Estimate, Findings
from uwbd.fusion.policy.fusing import MIN_KEPT_ANCHORS
from uwbd.fusion.policy.installation import Installation
from uwbd.fusion.settings import HealthLimits

NS = 1_000_000_000
EVERY_NS = 50_000_000  # the test at most 20 times a second
WARM_S = 5.0  # after the bank starts anew, its separations are judged this much later
ALARM_HOLD_S = 5.0  # a fault found stands this long after its last test over the threshold
EXCLUDE_AFTER = 20  # tests in a row naming the same anchor (a second: not a burst of NLOS)
HOLD_S = 10.0  # an anchor left out is tried again after this (doubled each time, to MAX)
MAX_HOLD_S = 300.0
LEVER_HOLD_S = 30.0  # a lever arm found off stands this long after its last detection
NEVER_NS = 2**63 - 1


class Integrity:
    """The separation test and the exclusion over the filter's life (see module doc)."""

    def __init__(self, limits: HealthLimits, range_sigma_m: float, est: Estimate,
                 findings: Findings, installation: Installation) -> None:
        self.limits, self.est, self.findings = limits, est, findings
        self.installation = installation
        self._bias_per_sigma = limits.range_bias_bound_m / range_sigma_m
        self._tests: dict[tuple[int, bool], SeparationTest] = {}  # by size, lever member
        self._ekf: Eskf | None = None  # the state the bank below is of
        self._resets = 0
        self._since_ns = 0  # the bank started anew
        self._last_ns = -(2**63)
        self._run: tuple[int, int] = (-1, 0)  # the anchor named by the last tests, how often
        self._alarm_ns = -(2**63)  # the last test over its threshold
        self._strikes: dict[int, int] = {}  # how often each anchor was left out
        self._lever_from_ns = NEVER_NS  # the lever member is judged from then on
        self._lever_ns = -(2**63)  # its last test over the threshold

    def after_update(self, t_ns: int) -> None:
        """The test, when due, on the state's bank; the exclusion it calls for; the anchors
        left out whose time is up taken back; the lever member judged."""
        ekf, monitor = self.est.ekf, self.est.monitor
        separated = self.findings.separated
        for anchor, until_ns in list(separated.items()):
            if t_ns >= until_ns:
                del separated[anchor]
                if anchor not in self.findings.consistency.findings:  # (else still out)
                    self.findings.excluded.discard(anchor)
                self._said_excluded()
        if ekf is not None and ekf is not self._ekf:  # a new state: its lever member is
            self._lever_from_ns = NEVER_NS  # judged from its heading's alignment on
            self._lever_ns = -(2**63)
        if ekf is not None and (ekf is not self._ekf or ekf.bank_resets != self._resets):
            # (a new state: the start's warm-up, which the health counts as aligning)
            monitor.separation_starting = ekf is not self._ekf
            self._ekf, self._resets, self._since_ns = ekf, ekf.bank_resets, t_ns
            self._run, self._alarm_ns = (-1, 0), -(2**63)
        if ekf is None or not ekf.bank:
            monitor.separation = None
            monitor.separation_warm = monitor.separation_alarm = monitor.lever_alarm = False
            return
        if t_ns - self._last_ns < EVERY_NS:
            return
        self._last_ns = t_ns
        lever = LEVER_MEMBER in ekf.bank
        test = self._tests.get((len(ekf.bank), lever))
        if test is None:
            test = self._tests[len(ekf.bank), lever] = SeparationTest(
                len(ekf.bank), self.limits.integrity_risk, self.limits.false_alert_probability,
                self._bias_per_sigma, lever)
        sep = monitor.separation = test.test(ekf.bank, ekf.separation_numbers())
        monitor.separation_warm = warm = t_ns - self._since_ns >= WARM_S * NS
        suspect = sep.suspect if warm else None
        if suspect is not None:
            self._alarm_ns = t_ns
            member = ekf.bank.index(suspect)
            self.findings.suspect = (suspect, float(np.linalg.norm(ekf.bank_d[member, :3])))
        monitor.separation_alarm = warm and t_ns - self._alarm_ns < ALARM_HOLD_S * NS
        if not monitor.separation_alarm:  # (the finding lasts as long as its alarm)
            self.findings.suspect = None
        if lever:  # (while an anchor is found, the lever member may show its fault too)
            self._judge_lever(t_ns, ekf, sep, warm and not monitor.separation_alarm)
        if suspect is None:
            self._run = (-1, 0)
            return
        anchor, tests = self._run
        self._run = (suspect, tests + 1 if anchor == suspect else 1)
        if self._run[1] >= EXCLUDE_AFTER:
            self._exclude(t_ns, ekf, suspect)

    def _judge_lever(self, t_ns: int, ekf: Eskf, sep: Separation, judged: bool) -> None:
        """The lever member's separation, judged (``judged``: the bank warm and no anchor
        found within ``ALARM_HOLD_S``) once the heading is aligned and the member has had
        ``WARM_S`` since; a lever arm found off stands ``LEVER_HOLD_S`` after its last
        test over the threshold (it shows only while the body turns), whatever restarts
        the bank."""
        if judged and self.est.aligned and t_ns >= self._lever_from_ns \
                and sep.ratios[LEVER_MEMBER] > 1.0:
            self._lever_ns = t_ns
            self.findings.lever_arm_m = self._lever_of(ekf, ekf.bank.index(LEVER_MEMBER))
        alarm = self.est.monitor.lever_alarm = t_ns - self._lever_ns < LEVER_HOLD_S * NS
        if not alarm:
            self.findings.lever_arm_m = None

    def heading_aligned(self, ekf: Eskf) -> None:
        """The heading just aligned: the lever member starts anew (while the heading was
        held, the lever arm's states took up what the unknown heading did to the ranges,
        and a fault-free run looked like a lever arm 0.5 m off), judged ``WARM_S`` later."""
        if LEVER_MEMBER in ekf.bank:
            ekf.restart_member(ekf.bank.index(LEVER_MEMBER))
            self._lever_from_ns = (self.est.t_ns or 0) + int(WARM_S * NS)

    def _lever_of(self, ekf: Eskf, member: int) -> Array:
        """The lever arm (body, m) by the bank's ``member``."""
        columns = list(self.installation.lever_index)
        error = ekf.b_r[[c - N_CORE for c in columns]] + ekf.bank_d[member, columns]
        return np.asarray(self.installation.plain_lever + error, dtype=float)

    def _exclude(self, t_ns: int, ekf: Eskf, anchor: int) -> None:
        findings = self.findings
        left = set(ekf.bank) - {LEVER_MEMBER} - set(findings.separated) \
            - set(findings.consistency.findings)
        if len(left - {anchor}) < MIN_KEPT_ANCHORS:
            return  # too few to leave one out: found, not excluded
        ekf.adopt(ekf.bank.index(anchor))
        strikes = self._strikes[anchor] = self._strikes.get(anchor, 0) + 1
        hold_s = min(HOLD_S * 2 ** (strikes - 1), MAX_HOLD_S)
        findings.separated[anchor] = t_ns + int(hold_s * NS)
        findings.excluded.add(anchor)  # (its state's share is gone with the adoption)
        self._said_excluded()
        self.est.counters["anchors_excluded"] += 1
        self.est.counters["anchors_separated"] += 1
        findings.suspect = None  # (left out: anchors_excluded names it now)
        self.est.monitor.separation = None
        self.est.monitor.separation_warm = self.est.monitor.separation_alarm = False

    def _said_excluded(self) -> None:
        """The anchors left out, and whether the height went with them, to the health."""
        excluded = self.findings.excluded
        self.est.monitor.excluded = tuple(sorted(excluded))
        self.est.monitor.side_lost = self.installation.side_lost(excluded)
