"""Solution separation (docs/ekf.md §6): the main filter against the bank's sub-filters, each
of which has left one anchor's ranges out (Brenner 1996; the ARAIM algorithm description;
Joerger and Pervan's Kalman-filter integrity), in the position domain.

For sub-filter ``k`` (anchor ``k`` left out) the separation is its offset from the main
filter ``Δ_k = x_k − x_0`` (the bank keeps it: ``d_k``), with covariance ``P_k − P_0`` (the
main filter holds all the sub-filter's information and more). Under no fault, ``Δ_k`` is
zero-mean with that covariance; a fault on anchor ``k`` moves the main filter and not
sub-filter ``k``, so ``Δ_k`` shows it.

* **Detection**: ``|Δ_k|`` against its threshold ``T_k = (K_fa + √m b/σ_r) σ_Δk``
  (horizontal: the norm against the major axis of the horizontal ellipse of ``P_k − P_0``;
  vertical: z), ``K_fa`` at the false-alert probability shared over the ``m`` anchors, and
  the ranges' unmodelled bias ``b`` (each at most, in the ranges' σ ``σ_r``) moving the
  separation by at most ``√m b/σ_r σ_Δk`` without a fault (ARAIM's nominal bias). The
  ratio ``|Δ_k| / T_k`` is the test's statistic: over 1, anchor ``k`` is the likely fault.
* **Protection levels**: ``max(K_md σ_0, max_k (max(T_k, |Δ_k|) + K_md σ_k))`` with σ the
  main filter's and each sub-filter's own (major axis, or σz), ``K_md`` at the integrity
  risk shared over the fault-free and each single-anchor hypothesis (a separation over its
  threshold counts as itself: the main filter may then be that far from the fault-free
  sub-filter). Where the geometry without an anchor sees little, ``σ_k`` and ``T_k``
  grow, and so does the level.

The covariances' numbers come from the state (``separation_numbers``: the C core's, or
:func:`uwbd.fusion.core.bank.separation_numbers`); the thresholds and levels are made here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

from uwbd.fusion.core.bank import SeparationNumbers

MIN_SEPARATION_SIGMA_M = 1e-3  # σ of a separation is at least this (just after a new start)
# the bank's member that leaves no anchor out but estimates the lever arm, which the main
# filter holds known: its separation shows a lever arm off (no anchor id is negative)
LEVER_MEMBER = -2


@dataclass(frozen=True)
class Separation:
    """One test of the bank: the protection levels its hypotheses need (m), and each
    anchor's test statistic ``|Δ_k| / T_k`` (over 1: a detection)."""

    horizontal_m: float
    vertical_m: float
    ratios: dict[int, float]

    @property
    def suspect(self) -> int | None:
        """The anchor whose separation is over its threshold the most (None: none is). The
        lever member is not one: it takes each anchor's ranges, and its states may take up
        part of a faulty anchor's error."""
        anchors = [a for a in self.ratios if a != LEVER_MEMBER]
        if not anchors:
            return None
        anchor = max(anchors, key=self.ratios.__getitem__)
        return anchor if self.ratios[anchor] > 1.0 else None


class SeparationTest:
    """The multipliers for a bank of ``count`` sub-filters, made once; :meth:`test` per call."""

    def __init__(self, count: int, integrity_risk: float, false_alert: float,
                 bias_per_sigma: float = 0.0, lever: bool = False) -> None:
        """``count`` sub-filters, one of them the lever member if ``lever`` (tested, and not
        a hypothesis of the levels); ``bias_per_sigma``: each range's unmodelled bias bound
        over its noise's σ (the ranges' nominal bias, which moves a separation without a
        fault)."""
        share_fa = false_alert / max(count, 1)
        share_md = integrity_risk / (count + 1 - lever)
        # the horizontal: a norm against the major axis (Rayleigh, conservative); the
        # vertical: two-sided normal
        self.k_fa_h = math.sqrt(-2.0 * math.log(share_fa))
        self.k_fa_v = NormalDist().inv_cdf(1.0 - share_fa / 2.0)
        self.k_md_h = math.sqrt(-2.0 * math.log(share_md))
        self.k_md_v = NormalDist().inv_cdf(1.0 - share_md / 2.0)
        # a bias b on every range moves a separation by at most Σ|s_j| b ≤ √m ‖s‖ b, and
        # ‖s‖ σ_r is the separation's σ: √m (b / σ_r) σ_Δ more, on every threshold
        self.k_bias = math.sqrt(count) * bias_per_sigma

    def test(self, anchors: tuple[int, ...], numbers: SeparationNumbers) -> Separation:
        """The bank's numbers (:func:`~uwbd.fusion.core.bank.separation_numbers`: the main
        filter's and, in order, those of the sub-filter of each of ``anchors``)."""
        main_major, main_var_z, members = numbers
        k_h, k_v = self.k_fa_h + self.k_bias, self.k_fa_v + self.k_bias
        k_md_h, k_md_v = self.k_md_h, self.k_md_v
        level_h = level_v = 0.0
        ratios = {}
        for anchor, (sep_major, sep_var_z, own_major, own_var_z, d_h, d_v) in zip(
                anchors, members, strict=True):
            t_h = k_h * max(sep_major, MIN_SEPARATION_SIGMA_M)
            t_v = k_v * math.sqrt(max(sep_var_z, MIN_SEPARATION_SIGMA_M**2))
            ratios[anchor] = max(d_h / t_h, d_v / t_v)
            if anchor >= 0:  # the levels over the anchors' faults (the lever member detects;
                # an unobserved lever arm would make its level the prior's); a separation over
                # its threshold: that sub-filter may be the fault-free one, and the main
                # filter as far from the truth as it is from it and its own error
                level_h = max(level_h, max(t_h, d_h) + k_md_h * own_major)
                level_v = max(level_v, max(t_v, d_v) + k_md_v * math.sqrt(max(own_var_z, 0.0)))
        return Separation(max(k_md_h * main_major, level_h),
                          max(k_md_v * math.sqrt(max(main_var_z, 0.0)), level_v), ratios)
