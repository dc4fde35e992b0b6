"""The filter's health: what state the estimate is in, rebuilt from evidence at every step.

:class:`HealthMonitor` keeps the evidence (when a UWB measurement was last accepted, the
recent innovations, IMU samples rejected, numerical faults, resets); :meth:`assess` turns
it into a :class:`Health` record, which the pose, the status and the terminal carry. The
record is never patched: each step builds a new one from the monitor and the covariance.

Phases (one at a time, in this order of precedence):

``waiting``     no estimate yet (collecting IMU samples and ranges to start)
``recovering``  re-initialised less than ``recover_hold_s`` ago and not yet free of faults,
                or waiting to restart after a reset
``coasting``    no accepted UWB measurement for ``coast_after_s``: IMU only, σ growing
``degraded``    running with a fault (below)
``aligning``    running, heading not yet observable
``tracking``    running, nothing wrong: the only phase in which :attr:`Health.healthy`

Faults: ``state_not_finite``, ``innovation_below_noise`` (``S < R``: ``P`` lost its
positive definiteness along a measurement), ``innovations_inconsistent`` (most of the last
``window_count`` UWB measurements, or the last four, fail the gate, or their NIS is far
above 1: no level holds then), ``imu_rejected`` (a sample was rejected within the last
second), ``imu_gap``,
``range_timeout`` (no accepted range for ``range_timeout_s``), ``position_uncertain``
(a protection level not known, or over its alert limit: the larger of the bank's solution
separation's, :mod:`uwbd.fusion.checks.separation`, and ``K σ + g b`` at
``integrity_risk``, σ the horizontal ellipse's major axis or σz, and ``g`` the ranges'
geometry's position error per metre of a bias ``range_bias_bound_m`` on every range
(:mod:`uwbd.fusion.checks.bias_gain`), horizontal or vertical; with
``height_needed`` off, the horizontal's alone), ``anchor_inconsistent`` (an anchor's
ranges disagree with the others' and it is not left out:
:mod:`uwbd.fusion.checks.anchor_consistency` or the separation; the status names it),
``mounting_inconsistent`` (with NHC on, the vehicle moves sideways in body axes: a
mounting turned about z, :mod:`uwbd.fusion.checks.mounting_yaw`; the status's
``mounting_finding`` says by how much), ``height_implausible`` (the estimate is at a height
the tag cannot be, :func:`height_bounds`: it is wrong, whatever its covariance claims, and
no level holds; the body's height, beyond the tag's bounds widened by the lever arm and
by ``K σz``).
Notes do not make the estimate unhealthy: ``anchor_excluded`` (an anchor found wrong is
left out; the rest agree), ``height_uncertain`` (with ``height_needed`` off, the vertical
level not known or over its limit), ``mirror_unresolved`` (coplanar anchors, side
not yet told by the data, the configured or default side in use; once the data have flipped
it, no vertical level holds until a hint says the side), ``mounting_suspect``
(at the start at rest gravity was over 30° from the body's up axis: a wrong
``imu.mounting``, or a vehicle on a slope; the status's ``mounting_finding`` says which way),
``range_model_held`` (a ``[range_model]`` is configured but not applied yet: it needs the
heading, which is not known yet), ``faults_clearing`` (the last fault ended less than
``clear_hold_s`` ago: still ``degraded``, so that the phase does not flicker).
"""

from __future__ import annotations

import collections
import math
from statistics import NormalDist

from uwbd.fusion.checks.separation import Separation
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.fusion.settings import HealthLimits
from uwbd.fusion.types import Health, Phase

NS = 1_000_000_000
FIX_HEIGHT_MARGIN_M = 3.0  # a height this far above every anchor, or below every anchor
# and below the floor by FLOOR_MARGIN_M (the navigation frame's z 0 taken as the floor), is
# not one the tag can be at
FLOOR_MARGIN_M = 0.5


def height_bounds(height_range_m: tuple[float, float] | None,
                  anchor_heights: list[float]) -> tuple[float, float]:
    """The heights the tag can be at: ``height_range_m``; or else up to
    ``FIX_HEIGHT_MARGIN_M`` above the highest anchor, and down to that margin below the
    lowest anchor or ``FLOOR_MARGIN_M`` below the floor (z 0), whichever is lower. NLOS on
    every anchor at once leaves residuals as small as a true fix's at a place metres above
    or below any the tag can be, and a ground robot under anchors on a high ceiling is far
    below every anchor but not below the floor."""
    if height_range_m is not None:
        return height_range_m
    if not anchor_heights:
        return -math.inf, math.inf
    return (min(min(anchor_heights) - FIX_HEIGHT_MARGIN_M, -FLOOR_MARGIN_M),
            max(anchor_heights) + FIX_HEIGHT_MARGIN_M)


class HealthMonitor:
    """Evidence about the estimate, fed by the filter as it runs."""

    def __init__(self, limits: HealthLimits) -> None:
        self.limits = limits
        self.last_range_ns: int | None = None
        self._outcomes: collections.deque[tuple[bool, float]] = collections.deque()
        self._rejected = 0  # in the window
        self._nis_sum = 0.0
        self._rejected_run = 0
        self._inconsistent_since_ns: int | None = None
        self._imu_fault_ns: int | None = None
        self._numerical_ns: int | None = None
        self.imu_gap = False
        # ranges back after a timeout: the state coasted, and what its covariance claims is
        # untried until a window of innovations since then says it is consistent
        self._rejudging = False
        self.resets = 0
        self.last_reset: tuple[int, str, float | None] | None = None
        self.mirror_unresolved = False
        # the data flipped the side of a plane of anchors away from the default (a fault on
        # one anchor can, and then resolve it wrongly): the height is not known
        self.mirror_flipped = False
        self.anchor_suspects: tuple[int, ...] = ()  # checks.anchor_consistency's findings
        # checks.bias_gain's: the position error per metre of range bias (h, v)
        self.bias_gain = (0.0, 0.0)
        # the bank's solution separation (checks.separation, policy.integrity): its last
        # test, and whether the bank has run long enough since it started anew to judge by
        self.separation: Separation | None = None
        self.separation_warm = False
        self.excluded: tuple[int, ...] = ()  # the anchors left out of the updates (either test)
        self.side_lost = False  # and with them the side of the rest's plane: no height
        self.separation_starting = False  # its warm-up is the start's (not a restart's)
        self.separation_alarm = False  # an anchor's fault found, lately, and not left out
        self.lever_alarm = False  # the lever member found the lever arm off, lately
        risk = limits.integrity_risk
        self._k_horizontal = math.sqrt(-2.0 * math.log(risk))  # Rayleigh, on the major axis
        self._k_vertical = NormalDist().inv_cdf(1.0 - risk / 2.0)  # two-sided
        self.mounting_suspect = False  # gravity far from body up at the start at rest
        self.mounting_inconsistent = False  # the vehicle moves sideways in body axes (NHC)
        self.range_model_held = False  # a range model configured, not applied yet (no heading)
        # where the body can be: the tag's heights (height_bounds), wider by the lever arm
        self.heights_m = (-math.inf, math.inf)
        self._after_reset = False
        self._fault_ns: int | None = None  # the last assessment with a fault

    # -- evidence -------------------------------------------------------------------------
    def uwb_outcome(self, t_ns: int, accepted: bool, nis: float) -> None:
        """One UWB measurement (range or position axis) after the innovation test. The window
        is inconsistent when the last four all failed, or, full, when too many failed or
        their mean NIS is too large (in locals: this runs for every range)."""
        out, lim = self._outcomes, self.limits
        if accepted:
            last = self.last_range_ns
            if last is not None and t_ns - last > lim.range_timeout_s * NS:
                # the window judged the state before the coast: this one is judged afresh
                # (the first ranges after a long coast can pull it far, and leave it
                # overconfident)
                out.clear()
                self._rejected, self._nis_sum = 0, 0.0
                self._rejudging = True
            self.last_range_ns = t_ns
            self._rejected_run = 0
        else:
            self._rejected_run += 1
        nis = nis if nis < 25.0 else 25.0  # NaN and inf too
        out.append((accepted, nis))
        rejected, nis_sum = self._rejected + (not accepted), self._nis_sum + nis
        n, count = len(out), lim.window_count
        if n > count:
            old_accepted, old_nis = out.popleft()
            rejected -= not old_accepted
            nis_sum -= old_nis
            n -= 1
        self._rejected, self._nis_sum = rejected, nis_sum
        full = n >= count
        if self._rejudging and full:
            self._rejudging = False  # a full window since the ranges came back
        inconsistent = self._rejected_run >= 4 or (full and (
            rejected > lim.max_rejected_fraction * n or nis_sum / n > lim.max_mean_nis))
        if self._after_reset and full and not inconsistent:
            self._after_reset = False  # a full window since the reset, and it agrees
        if not inconsistent:
            self._inconsistent_since_ns = None
        elif self._inconsistent_since_ns is None:
            self._inconsistent_since_ns = t_ns

    def mirror_said(self, mirror: MirrorSide) -> None:
        """The side of a plane of anchors: unresolved (a note), or flipped by the data and
        in doubt (the note stays, and no vertical level holds)."""
        self.mirror_flipped = mirror.side_doubted
        self.mirror_unresolved = mirror.unresolved or mirror.side_doubted

    def imu_rejected(self, t_ns: int) -> None:
        self._imu_fault_ns = t_ns

    def numerical_fault(self, t_ns: int) -> None:
        self._numerical_ns = t_ns

    def reset(self, t_ns: int, reason: str, jump_m: float | None) -> None:
        """A re-initialisation: the evidence about the old estimate no longer applies."""
        self.resets += 1
        self.last_reset = (t_ns, reason, jump_m)
        self._outcomes.clear()
        self._rejected, self._nis_sum, self._rejected_run = 0, 0.0, 0
        self._inconsistent_since_ns = None
        self._rejudging = False
        self.anchor_suspects = ()
        # (the anchors left out, and the side lost with them, are the findings': kept)
        self.separation, self.separation_warm, self.separation_alarm = None, False, False
        self.lever_alarm = False
        self.separation_starting = False
        self._after_reset = True  # recovering until a window of innovations agrees

    # -- judgements -----------------------------------------------------------------------
    @property
    def inconsistent(self) -> bool:
        """The recent UWB innovations are inconsistent with the state's covariance."""
        return self._inconsistent_since_ns is not None

    def diverged(self, t_ns: int) -> bool:
        """Innovations inconsistent for ``diverged_after_s``: the state, not the ranges, is
        likely wrong (the caller checks that a consistent fix says so too)."""
        since = self._inconsistent_since_ns
        return since is not None and t_ns - since >= self.limits.diverged_after_s * NS

    def assess(self, t_ns: int, running: bool, heading_observable: bool,
               position_sigma_m: float | None, finite: bool,
               vertical_sigma_m: float | None = 0.0, imu_silent: bool = False,
               major_sigma_m: float | None = None, height_m: float = 0.0) -> Health:
        """``position_sigma_m``: √(σx² + σy²); ``vertical_sigma_m``: σz (``None``: not
        known, uncertain); ``major_sigma_m``: the horizontal error ellipse's major axis
        (``None``: ``position_sigma_m``, which bounds it); ``imu_silent``: no good IMU
        sample for longer than an IMU gap; ``height_m``: the estimate's height."""
        lim = self.limits
        since = None if self.last_range_ns is None else (t_ns - self.last_range_ns) / NS
        faults = []
        if not finite:
            faults.append("state_not_finite")
        if self._numerical_ns is not None and t_ns - self._numerical_ns < lim.imu_fault_hold_s * NS:
            faults.append("innovation_below_noise")
        if self._inconsistent_since_ns is not None:
            faults.append("innovations_inconsistent")
        if self._imu_fault_ns is not None and t_ns - self._imu_fault_ns < lim.imu_fault_hold_s * NS:
            faults.append("imu_rejected")
        if self.imu_gap or (running and imu_silent):
            faults.append("imu_gap")
        if running and since is not None and (since > lim.range_timeout_s or self._rejudging):
            faults.append("range_timeout")  # or just back, the state not yet judged again
        hpl = vpl = None
        h_ok = v_ok = starting = False
        if running:
            major = position_sigma_m if major_sigma_m is None else major_sigma_m
            gh, gv = self.bias_gain  # what the ranges' unmodelled biases can do
            b = lim.range_bias_bound_m
            hpl = None if major is None else self._k_horizontal * major + gh * b
            vpl = None if vertical_sigma_m is None else self._k_vertical * vertical_sigma_m + gv * b
            sep = self.separation
            warming = sep is not None and not self.separation_warm
            if (warming or self.separation_alarm or self.lever_alarm
                    or self._inconsistent_since_ns is not None):
                # the levels over the anchors' faults: not known yet, or an anchor's fault
                # found and not yet left out, or the lever arm's; or the innovations say the
                # covariance the levels come from is wrong (no level holds then; the phase
                # holds `degraded` a little longer, the levels return with consistency)
                hpl = vpl = None
            if sep is not None:  # and the levels over each anchor's fault
                hpl = None if hpl is None else max(hpl, sep.horizontal_m + gh * b)
                vpl = None if vpl is None else max(vpl, sep.vertical_m + gv * b)
            if self.side_lost or self.mirror_flipped:  # the tag may be the mirror image:
                # the height is not known
                vpl = None
            low, high = self.heights_m  # beyond its own σz too (NaN too): cannot be right
            slack = self._k_vertical * (vertical_sigma_m or 0.0)
            if not low - slack <= height_m <= high + slack:
                faults.append("height_implausible")
                hpl = vpl = None
            h_ok = hpl is not None and hpl <= lim.horizontal_alert_limit_m
            v_ok = vpl is not None and vpl <= lim.vertical_alert_limit_m
            starting = warming and self.separation_starting  # (aligning, below)
            if not starting and (not h_ok or (lim.height_needed and not v_ok)):
                faults.append("position_uncertain")
            # an anchor found wrong and not left out (too few others); one left out is a
            # note, the rest judged by the levels
            if set(self.anchor_suspects) - set(self.excluded) or self.separation_alarm:
                faults.append("anchor_inconsistent")
            if self.lever_alarm:
                faults.append("lever_arm_inconsistent")
            if self.mounting_inconsistent:
                faults.append("mounting_inconsistent")
        notes = (("anchor_excluded",) if self.excluded else ()) + (
            ("height_uncertain",) if running and not lim.height_needed and not v_ok else ()) + (
            ("mirror_unresolved",) if self.mirror_unresolved else ()) + (
            ("mounting_suspect",) if self.mounting_suspect else ()) + (
            ("range_model_held",) if self.range_model_held else ())
        if running and faults:
            self._fault_ns = t_ns if self._fault_ns is None else max(self._fault_ns, t_ns)
        clearing = (running and not faults and self._fault_ns is not None
                    and t_ns - self._fault_ns < lim.clear_hold_s * NS)
        if clearing:  # hysteresis: back to tracking only once no fault for clear_hold_s
            notes += ("faults_clearing",)
        reset_t, reason, jump = self.last_reset or (None, "", None)
        recent_reset = reset_t is not None and t_ns - reset_t < lim.recover_hold_s * NS
        if not running:
            phase = Phase.RECOVERING if self.resets else Phase.WAITING
        elif (recent_reset and faults) or self._after_reset:
            phase = Phase.RECOVERING
        elif since is None or since > lim.coast_after_s:
            phase = Phase.COASTING
        elif faults or clearing:
            phase = Phase.DEGRADED
        elif not heading_observable or starting:
            phase = Phase.ALIGNING
        else:
            phase = Phase.TRACKING
        return Health(phase, tuple(faults), notes, since, position_sigma_m, hpl, vpl,
                      self.resets, reset_t, reason, jump, h_ok, v_ok)
