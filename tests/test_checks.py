"""What may enter the filter (uwbd/fusion/checks/): the IMU check on its own."""

from __future__ import annotations

import math

from uwbd.fusion.checks.imu_check import ImuCheck, ImuLimits

STILL = ((0.0, 0.0, 9.8), (0.0, 0.0, 0.0))
NS = 1_000_000_000


def test_each_kind_of_impossible_sample_is_named() -> None:
    check = ImuCheck(ImuLimits())
    assert check.judge(0, *STILL) == ""
    assert check.judge(5_000_000, (math.nan, 0.0, 9.8), (0.0, 0.0, 0.0)) == "imu_not_finite"
    assert check.judge(10_000_000, (0.0, 0.0, 9.8), (0.0, math.inf, 0.0)) == "imu_not_finite"
    full = ImuLimits().acc_full_scale_mps2
    assert check.judge(15_000_000, (0.0, -full, 9.8), (0.0, 0.0, 0.0)) == "imu_saturated"
    assert check.judge(20_000_000, (0.0, 0.0, 9.8), (0.0, 0.0, 34.8)) == "imu_saturated"
    assert check.judge(25_000_000, (0.0, 0.0, 9.8 + 100.0), (0.0, 0.0, 0.0)) == "imu_jump"
    assert check.last_good == STILL  # the rejected ones never replace it


def test_a_jump_rejects_a_short_run_only_then_the_new_level_is_real() -> None:
    """A corrupted word is one sample; a collision is a real step: after max_jump_run
    rejected samples the new level is taken."""
    check = ImuCheck(ImuLimits(max_jump_run=3))
    check.judge(0, *STILL)
    step = ((0.0, 0.0, 9.8 + 100.0), (0.0, 0.0, 0.0))
    reasons = [check.judge(k * 5_000_000, *step) for k in range(1, 6)]
    assert reasons == ["imu_jump"] * 3 + ["", ""]
    assert check.last_good == step


def test_the_burst_lasts_from_the_last_good_sample_and_ends_with_a_good_one() -> None:
    check = ImuCheck(ImuLimits())
    check.judge(1 * NS, *STILL)
    assert check.burst_s(1 * NS) == 0.0
    for k in range(1, 5):
        check.judge(NS + k * NS // 10, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert check.burst_s(NS + 4 * NS // 10) == 0.4  # since the good sample before it
    check.judge(NS + 5 * NS // 10, *STILL)
    assert check.burst_s(NS + 5 * NS // 10) == 0.0
