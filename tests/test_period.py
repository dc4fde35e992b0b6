"""A pose period's single ranges and IMU samples fused in one call of the C core
(uwbd.fusion.policy.period): the same numbers as the policy's own step per item, its
reference, on runs where items leave the common path (IMU gaps, saturated and spiked
samples, an anchor away, an anchor surveyed off and left out, ranges that arrive late)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivers.frames import ImuSample
from uwbd.fusion.core import native
from uwbd.fusion.filter import Filter
from uwbd.fusion.settings import Z_DOWN, FilterConfig
from uwbd.tools.evaluate import merge, run_filter
from uwbd.tools.sim_presets import handheld_async
from uwbd.tools.simulator import simulate

POSE_PERIOD_NS = 20_000_000

pytestmark = pytest.mark.skipif(native.core is None, reason="the C core is not built")


def _run(cfg: FilterConfig, frames: list, per_item: bool) -> tuple[list, list, Filter]:
    """Poses at 50 Hz as the daemon makes them; ``per_item``: the queue's items each
    through the policy's step (the reference), never the core's fuse_period."""
    init = Filter.__init__

    def reference(self: Filter, *args: object, **kwargs: object) -> None:
        init(self, *args, **kwargs)  # type: ignore[arg-type]
        self.queue._front = None

    if per_item:
        Filter.__init__ = reference  # type: ignore[method-assign]
    try:
        poses, reports, flt = run_filter(cfg, frames, pose_period_ns=POSE_PERIOD_NS)
    finally:
        Filter.__init__ = init  # type: ignore[method-assign]
    return poses, reports, flt


@pytest.mark.parametrize("fault", ["imu", "anchor_off", "late"])
def test_the_core_fuses_a_period_as_the_policy_step_does(fault: str) -> None:
    sim_cfg = handheld_async(3)
    anchors = dict(enumerate(sim_cfg.anchors_m))
    if fault == "imu":
        sim_cfg = dataclasses.replace(
            sim_cfg, imu_gaps_s=((14.0, 0.7), (30.0, 1.0)), imu_saturations_s=((20.0, 0.05),),
            imu_spikes_s=(25.0, 25.5), anchor_outages_s=((2, 35.0, 5.0),))
    else:  # surveyed 1 m off: found and left out, its ranges the queue's without a row
        x, y, z = anchors[5]
        anchors[5] = (x + 1.0, y, z)
    sim = simulate(sim_cfg)
    cfg = FilterConfig(anchors_m=anchors, mounting_rotation=Z_DOWN,
                       lever_arm_m=sim_cfg.lever_arm_m)
    frames = list(merge(sim.imu, sim.uwb))
    if fault == "late":  # every 50th range arrives after the next three IMU samples
        for k in range(100, len(frames) - 4, 50):
            if not isinstance(frames[k], ImuSample):
                frames[k:k + 4] = [*frames[k + 1:k + 4], frames[k]]
    poses, reports, flt = _run(cfg, frames, per_item=False)
    ref_poses, ref_reports, ref = _run(cfg, frames, per_item=True)

    assert [p.t_ns for p in poses] == [p.t_ns for p in ref_poses]
    error = np.abs(np.array([p.position_m for p in poses])
                   - np.array([p.position_m for p in ref_poses])).max()
    assert error <= 1e-9
    assert [p.status for p in poses] == [p.status for p in ref_poses]
    assert flt.counters == ref.counters
    assert [(r.key, r.accepted, r.reason) for r in reports] == \
        [(r.key, r.accepted, r.reason) for r in ref_reports]
    # the core took the period's ranges but the policy's own message each period (about one
    # in three at 170 ranges a second), those before the heading is aligned and those that
    # left the common path
    ranges = flt.counters["range_accepted"] + flt.counters["range_rejected"]
    assert flt.queue.core_ranges > 0.35 * ranges
    assert ref.queue.core_ranges == 0
    if fault == "imu":
        assert flt.counters["imu_gaps"] >= 2 and flt.counters["imu_saturated"] > 0
    elif fault == "late":
        assert flt.counters["uwb_late"] > 10  # (each through the policy's step)
    else:
        assert flt.counters["range_excluded"] > 0


def test_the_policy_runs_once_a_pose_period_and_ten_times_a_second_at_least() -> None:
    """Single ranges at 170 a second: the policy runs once a pose period (20 ms: about 50
    times a second, not 170), and at a pose rate of 1 Hz still every 100 ms."""
    sim_cfg = handheld_async(3)
    sim = simulate(sim_cfg)
    frames = list(merge(sim.imu, sim.uwb))
    for period_ns, most_ns in ((POSE_PERIOD_NS, 20_000_000), (1_000_000_000, 100_000_000)):
        cfg = FilterConfig(anchors_m=dict(enumerate(sim_cfg.anchors_m)),
                           mounting_rotation=Z_DOWN, lever_arm_m=sim_cfg.lever_arm_m,
                           pose_period_ns=period_ns)
        runs: list[int] = []

        def watch(flt: Filter, runs: list[int] = runs) -> None:
            if flt.est.aligned and (not runs or flt._policy_ns != runs[-1]):
                runs.append(flt._policy_ns)

        run_filter(cfg, frames, pose_period_ns=POSE_PERIOD_NS, watch=watch)
        gaps = np.diff(runs[1:])  # (from the first run while tracking)
        assert len(gaps) > 100
        assert gaps.min() >= most_ns and np.median(gaps) < most_ns + 8_000_000
        assert np.percentile(gaps, 99) < most_ns + 20_000_000  # (a message's spacing late)
