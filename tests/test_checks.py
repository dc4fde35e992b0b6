"""What may enter the filter (uwbd/fusion/checks/): the IMU check on its own, in Python and
as the C IMU front (the same tests on both, and one against the other)."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uwbd.fusion.checks.imu_check import ImuCheck, ImuLimits, new_imu_check
from uwbd.fusion.checks.intrinsics import ImuIntrinsics, body_maps
from uwbd.fusion.core import native

STILL = ((0.0, 0.0, 9.8), (0.0, 0.0, 0.0))
NS = 1_000_000_000
IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _front(limits: ImuLimits) -> Any:
    front = new_imu_check(limits, body_maps(IDENTITY, ImuIntrinsics()), native.core)
    assert not isinstance(front, ImuCheck)
    return front


IMPLEMENTATIONS = [pytest.param(ImuCheck, id="python"),
                   pytest.param(_front, id="c", marks=pytest.mark.skipif(
                       native.core is None, reason="the C core is not built"))]


@pytest.mark.parametrize("make", IMPLEMENTATIONS)
def test_each_kind_of_impossible_sample_is_named(make: Callable[[ImuLimits], Any]) -> None:
    check = make(ImuLimits())
    assert check.judge(0, *STILL) == ""
    assert check.judge(5_000_000, (math.nan, 0.0, 9.8), (0.0, 0.0, 0.0)) == "imu_not_finite"
    assert check.judge(10_000_000, (0.0, 0.0, 9.8), (0.0, math.inf, 0.0)) == "imu_not_finite"
    full = ImuLimits().acc_full_scale_mps2
    assert check.judge(15_000_000, (0.0, -full, 9.8), (0.0, 0.0, 0.0)) == "imu_saturated"
    assert check.judge(20_000_000, (0.0, 0.0, 9.8), (0.0, 0.0, 34.8)) == "imu_saturated"
    assert check.judge(25_000_000, (0.0, 0.0, 9.8 + 100.0), (0.0, 0.0, 0.0)) == "imu_jump"
    assert check.last_good == STILL  # the rejected ones never replace it


@pytest.mark.parametrize("make", IMPLEMENTATIONS)
def test_a_jump_rejects_a_short_run_only_then_the_new_level_is_real(
        make: Callable[[ImuLimits], Any]) -> None:
    """A corrupted word is one sample; a collision is a real step: after max_jump_run
    rejected samples the new level is taken."""
    check = make(ImuLimits(max_jump_run=3))
    check.judge(0, *STILL)
    step = ((0.0, 0.0, 9.8 + 100.0), (0.0, 0.0, 0.0))
    reasons = [check.judge(k * 5_000_000, *step) for k in range(1, 6)]
    assert reasons == ["imu_jump"] * 3 + ["", ""]
    assert check.last_good == step


@pytest.mark.parametrize("make", IMPLEMENTATIONS)
def test_the_burst_lasts_from_the_last_good_sample_and_ends_with_a_good_one(
        make: Callable[[ImuLimits], Any]) -> None:
    check = make(ImuLimits())
    check.judge(1 * NS, *STILL)
    assert check.burst_s(1 * NS) == 0.0
    for k in range(1, 5):
        check.judge(NS + k * NS // 10, (math.nan, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert check.burst_s(NS + 4 * NS // 10) == 0.4  # since the good sample before it
    check.judge(NS + 5 * NS // 10, *STILL)
    assert check.burst_s(NS + 5 * NS // 10) == 0.0


SPECIAL = (math.nan, math.inf, -math.inf, 1e308, 156.9, -156.9, 34.2)


@pytest.mark.skipif(native.core is None, reason="the C core is not built")
@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 4), st.floats(0.0, 0.3))
def test_the_c_front_judges_as_the_python_check(seed: int, run: int, odd: float) -> None:
    """Any sequence (non-finite values, values that overflow a sum, clipped axes, jumps and
    runs of them, steps to a new level): the same reasons, bursts and last good sample."""
    rng = random.Random(seed)
    limits = ImuLimits(max_jump_run=run)
    python, c = ImuCheck(limits), _front(limits)
    t_ns, level = 0, 0.0
    for _ in range(80):
        t_ns += rng.randint(1, 50_000_000)
        if rng.random() < 0.1:
            level = rng.uniform(-100.0, 100.0)
        acc = [level + rng.gauss(0.0, 5.0) for _ in range(3)]
        gyro = [rng.gauss(0.0, 2.0) if rng.random() < 0.8 else rng.uniform(-33.0, 33.0)
                for _ in range(3)]
        if rng.random() < odd:
            (acc if rng.random() < 0.5 else gyro)[rng.randrange(3)] = rng.choice(SPECIAL)
        assert c.judge(t_ns, tuple(acc), tuple(gyro)) == python.judge(t_ns, tuple(acc),
                                                                      tuple(gyro))
        assert c.burst_s(t_ns + 1) == python.burst_s(t_ns + 1)
        assert c.last_good == python.last_good
