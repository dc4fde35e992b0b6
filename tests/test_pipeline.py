"""The pipeline's pose stream: the configured rate for every kind of tag."""

from __future__ import annotations

import numpy as np

from uwbd.config import apply_overrides, parse
from uwbd.service.pipeline import Pipeline, PoseList
from uwbd.tools.evaluate import merge
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import SimConfig, handheld_async, simulate


def poses_of(sim_cfg: SimConfig, rate_hz: float) -> tuple[list[int], list[int]]:
    sim = simulate(sim_cfg)
    config = parse(apply_overrides(simulation_toml(sim), [f"pipeline.pose_rate_hz={rate_hz}"]))
    sink = PoseList()
    pipeline = Pipeline(config, [sink])
    for frame in merge(sim.imu, sim.uwb):
        pipeline.on_frame(frame)
    pipeline.finish()
    return [p.t_ns for p in sink.poses], [m.t_ns for m in sim.uwb]


def test_single_ranges_update_at_once_but_poses_leave_at_the_configured_rate() -> None:
    """~170 single ranges a second, poses at 50 Hz: no pose per range, none closer than the
    period, and the filter tracks (the ranges were all fused)."""
    cfg = handheld_async(2)
    cfg = SimConfig(**{**cfg.__dict__, "segments": cfg.segments[:3]})
    times, ranges = poses_of(cfg, 50.0)
    gaps_s = np.diff(times) / 1e9
    duration_s = (times[-1] - times[0]) / 1e9
    assert len(ranges) > 3 * len(times)  # the ranges far outnumber the poses
    assert gaps_s.min() >= 0.02 - 1e-6 and len(times) >= 0.8 * 50 * duration_s


def test_an_epoch_of_several_ranges_brings_its_pose_out_at_once() -> None:
    """10 Hz epochs with a 2 Hz pose rate: a pose after every epoch all the same."""
    times, epochs = poses_of(SimConfig(seed=3, segments=((6.0, 0.0, 0.0, 0.0),)), 2.0)
    since_start = [t for t in epochs if t >= times[0]]  # (poses once the filter started)
    assert set(since_start) <= set(times) and len(times) < 1.5 * len(since_start)
