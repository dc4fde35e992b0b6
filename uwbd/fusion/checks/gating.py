"""The UWB gating policy: which reported ranges may reach the filter.

One function, :func:`gate`, applied in one place (between driver and filter), so every
rejection is counted by reason and nothing downstream has to re-check NaN, sign or limits.
It judges what a range *is* (finite, positive, within limits, of acceptable device quality,
to a known anchor), never how it fits the state: that is the filter's innovation gate, whose
χ² thresholds :func:`chi2_quantile` gives.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass, field
from enum import Enum
from statistics import NormalDist
from typing import NamedTuple

from drivers.frames import AnchorRange, UwbRanges


class Rejection(str, Enum):
    """Why a range (or a whole epoch) was not let through."""

    NOT_FINITE = "not_finite"
    NEGATIVE = "negative"
    TOO_SHORT = "too_short"
    TOO_LONG = "too_long"
    LOW_QUALITY = "low_quality"
    UNKNOWN_ANCHOR = "unknown_anchor"
    DUPLICATE_ANCHOR = "duplicate_anchor"
    TOO_FEW_ANCHORS = "too_few_anchors"


@dataclass(frozen=True)
class GatingPolicy:
    """Limits on ranges. ``min_quality`` applies to devices that report a per-range quality
    (DWM1001 TLV, 0-100) and is ignored for ranges without one. ``known_anchors``, when set,
    rejects ranges to anchors the configuration has no position for. ``min_anchors`` is the
    epoch's anchor-count check after per-range rejections (3 for a 2D fix, 4 for 3D; a
    tightly coupled filter can use fewer)."""

    min_anchors: int = 3
    min_quality: float | None = None
    min_range_m: float = 0.0
    max_range_m: float = 100.0
    known_anchors: frozenset[int] | None = None

    def __post_init__(self) -> None:
        if self.min_anchors < 0:
            raise ValueError(f"min_anchors must be >= 0, got {self.min_anchors}")
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ValueError(
                f"need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")


@dataclass
class GatingCounters:
    """Running totals: epochs and ranges passed, and rejections by reason."""

    epochs_passed: int = 0
    ranges_passed: int = 0
    rejections: collections.Counter[str] = field(default_factory=collections.Counter)


class GateResult(NamedTuple):
    """The epoch with only the accepted ranges (``None`` if the epoch failed as a whole) and
    the rejected ranges with their reasons, for per-measurement reports. (A named tuple:
    every UWB message makes one.)"""

    epoch: UwbRanges | None
    rejected: tuple[tuple[AnchorRange, Rejection], ...]


def gate(epoch: UwbRanges, policy: GatingPolicy, counters: GatingCounters) -> GateResult:
    """Apply ``policy`` to one epoch, adding to ``counters``."""
    kept: list[AnchorRange] = []
    rejected: list[tuple[AnchorRange, Rejection]] = []
    seen: set[int] = set()
    for r in epoch.ranges:
        reason = _judge(r, policy, seen)
        seen.add(r.anchor_id)
        if reason is None:
            kept.append(r)
        else:
            rejected.append((r, reason))
            counters.rejections[reason.value] += 1
    if len(kept) < policy.min_anchors:
        counters.rejections[Rejection.TOO_FEW_ANCHORS.value] += 1
        return GateResult(None, tuple(rejected) if rejected else ())
    counters.epochs_passed += 1
    counters.ranges_passed += len(kept)
    if not rejected:
        return GateResult(epoch, ())
    return GateResult(dataclasses.replace(epoch, ranges=tuple(kept)), tuple(rejected))


def _judge(r: AnchorRange, policy: GatingPolicy, seen: set[int]) -> Rejection | None:
    d = r.range_m
    if not math.isfinite(d):
        return Rejection.NOT_FINITE
    if d < 0.0:
        return Rejection.NEGATIVE
    if d < policy.min_range_m:
        return Rejection.TOO_SHORT
    if d > policy.max_range_m:
        return Rejection.TOO_LONG
    if policy.min_quality is not None and r.quality is not None and not (
        r.quality >= policy.min_quality
    ):
        return Rejection.LOW_QUALITY
    if policy.known_anchors is not None and r.anchor_id not in policy.known_anchors:
        return Rejection.UNKNOWN_ANCHOR
    if r.anchor_id in seen:
        return Rejection.DUPLICATE_ANCHOR
    return None


def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of χ² with 1 or 3 degrees of freedom, exactly.

    Written out rather than taken from ``scipy.stats``, whose import alone costs the daemon
    ~70 MB of its memory budget: χ²₁ is the square of a standard normal, and the χ²₃ CDF
    ``erf(√(x/2)) − √(2x/π)·e^(−x/2)`` is inverted by bisection.
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability must be within (0, 1), got {p}")
    if dof == 1:
        return NormalDist().inv_cdf((1.0 + p) / 2.0) ** 2
    if dof != 3:
        raise ValueError(f"only 1 or 3 degrees of freedom, got {dof}")

    def cdf3(x: float) -> float:
        return math.erf(math.sqrt(x / 2)) - math.sqrt(2 * x / math.pi) * math.exp(-x / 2)

    lo, hi = 0.0, 1.0
    while cdf3(hi) < p:
        hi *= 2
    for _ in range(100):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf3(mid) < p else (lo, mid)
    return (lo + hi) / 2
