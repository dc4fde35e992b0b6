"""The gating policy: one function, rejections counted by reason."""

from __future__ import annotations

import math

import pytest

from drivers.frames import AnchorRange, UwbRanges
from uwbd.fusion.checks.gating import GatingCounters, GatingPolicy, Rejection, gate


def epoch(*ranges: AnchorRange) -> UwbRanges:
    return UwbRanges(5, ranges)


def test_each_bad_range_is_rejected_for_its_reason() -> None:
    policy = GatingPolicy(min_anchors=2, min_quality=50, min_range_m=0.1, max_range_m=60,
                          known_anchors=frozenset(range(10)))
    counters = GatingCounters()
    good = [AnchorRange(0, 3.0, 90.0), AnchorRange(1, 4.0)]  # no quality given: not judged
    bad = {
        Rejection.NOT_FINITE: AnchorRange(2, math.nan),
        Rejection.NEGATIVE: AnchorRange(3, -0.2),
        Rejection.TOO_SHORT: AnchorRange(4, 0.05),
        Rejection.TOO_LONG: AnchorRange(5, 1e6),
        Rejection.LOW_QUALITY: AnchorRange(6, 3.0, 10.0),
        Rejection.UNKNOWN_ANCHOR: AnchorRange(42, 3.0),
        Rejection.DUPLICATE_ANCHOR: AnchorRange(0, 3.1),
    }
    result = gate(epoch(*good, *bad.values()), policy, counters)
    assert result.epoch == epoch(*good)
    assert dict(result.rejected) == {r: why for why, r in bad.items()}
    assert counters.rejections == {why.value: 1 for why in bad}
    assert (counters.epochs_passed, counters.ranges_passed) == (1, 2)


def test_too_few_anchors_rejects_the_epoch() -> None:
    counters = GatingCounters()
    result = gate(epoch(AnchorRange(0, 3.0), AnchorRange(1, math.inf)), GatingPolicy(), counters)
    assert result.epoch is None
    assert counters.rejections == {"not_finite": 1, "too_few_anchors": 1}
    assert counters.epochs_passed == 0


def test_clean_epoch_passes_unchanged() -> None:
    e = epoch(*(AnchorRange(k, 2.0 + k) for k in range(4)))
    assert gate(e, GatingPolicy(), GatingCounters()).epoch is e


def test_policy_rejects_impossible_limits() -> None:
    with pytest.raises(ValueError, match="max_range_m"):
        GatingPolicy(min_range_m=5.0, max_range_m=1.0)
