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

The arithmetic runs on the bank's numbers as numpy arrays, once per call, for every
sub-filter at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from uwbd.fusion.core.rotation import Array

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

    def test(self, anchors: tuple[int, ...], P: Array, bank_d: Array, bank_P: Array
             ) -> Separation:
        """The main filter's covariance ``P``, the bank's offsets ``d_k`` and covariances
        ``P_k``, one per anchor in ``anchors``."""
        Pk = bank_P[:, :3, :3]
        D = Pk - P[:3, :3]
        sep_h = np.maximum(_major(D), MIN_SEPARATION_SIGMA_M)
        sep_v = np.sqrt(np.maximum(D[:, 2, 2], MIN_SEPARATION_SIGMA_M**2))
        t_h = (self.k_fa_h + self.k_bias) * sep_h
        t_v = (self.k_fa_v + self.k_bias) * sep_v
        own_h = self.k_md_h * _major(Pk)
        own_v = self.k_md_v * np.sqrt(np.maximum(Pk[:, 2, 2], 0.0))
        delta = bank_d[:, :3]
        d_h, d_v = np.hypot(delta[:, 0], delta[:, 1]), np.abs(delta[:, 2])
        ratio = np.maximum(d_h / t_h, d_v / t_v)
        main_h = self.k_md_h * float(_major(P[None, :3, :3])[0])
        main_v = self.k_md_v * math.sqrt(max(float(P[2, 2]), 0.0))
        # a separation over its threshold: that sub-filter may be the fault-free one, and
        # the main filter as far from the truth as it is from it and its own error
        # the levels over the anchors' faults (the lever member detects; an unobserved lever
        # arm would make its level the prior's)
        anchor = np.array(anchors) >= 0
        return Separation(
            max(main_h, float(np.max((np.maximum(t_h, d_h) + own_h)[anchor], initial=0.0))),
            max(main_v, float(np.max((np.maximum(t_v, d_v) + own_v)[anchor], initial=0.0))),
            dict(zip(anchors, ratio.tolist(), strict=True)))


def _major(C: Array) -> Array:
    """σ along the major axis of each horizontal ellipse of ``C`` (…×3×3), 0 where the
    numbers say less."""
    xx, xy, yy = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    half = (xx - yy) / 2
    return np.sqrt(np.maximum((xx + yy) / 2 + np.sqrt(half * half + xy * xy), 0.0))
