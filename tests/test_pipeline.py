"""The pipeline: its pose stream at the configured rate for every kind of tag, and the time
aligner that orders the sources' frames before the filter."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from truth import wide_limits_toml

from drivers.emulator import ENCODERS
from drivers.frames import ImuSample
from uwbd.config import apply_overrides, parse
from uwbd.fusion.types import Pose
from uwbd.logs.reading import read_log
from uwbd.service.aligner import Aligner
from uwbd.service.pipeline import Pipeline, PoseList
from uwbd.service.replay import replay
from uwbd.tools.evaluate import merge
from uwbd.tools.logtools import simulation_toml, write_simulation
from uwbd.tools.sim_presets import handheld_async
from uwbd.tools.simulator import SimConfig, simulate


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
    """~170 single ranges a second, poses at 50 Hz: no pose per range, 50 a second, and the
    filter tracks (the ranges were all fused)."""
    cfg = handheld_async(2)
    cfg = SimConfig(**{**cfg.__dict__, "segments": cfg.segments[:3]})
    times, ranges = poses_of(cfg, 50.0)
    gaps_s = np.diff(times) / 1e9
    duration_s = (times[-1] - times[0]) / 1e9
    assert len(ranges) > 3 * len(times)  # the ranges far outnumber the poses
    # on the 50 Hz grid (a pose may come a little early in its slot after a late one)
    assert gaps_s.min() >= 0.01 and 0.8 * 50 * duration_s <= len(times) <= 50 * duration_s + 2


def test_poses_leave_at_the_configured_rate_at_any_single_range_rate(tmp_path: Path) -> None:
    """#44: 180 single ranges a second (and 60, and 400) with a 100 Hz IMU, read as the ports
    send them (a log's reads, through the drivers): the poses leave at the configured 50 a
    second, not a period after each pose plus the wait for the next range (44 a second at
    180 before)."""
    base = handheld_async(3)
    for ranges_hz in (60.0, 180.0, 400.0):
        sim = simulate(SimConfig(**{**base.__dict__, "segments": base.segments[:3],
                                    "uwb_rate_hz": ranges_hz,
                                    "uwb_jitter_s": 0.2 / ranges_hz}))
        path = tmp_path / f"r{ranges_hz:.0f}.mcap"
        write_simulation(sim, path, "nlink")
        _, kept = replay(read_log(path), str(path))
        times = [p.t_ns for p in kept.poses]
        duration_s = (times[-1] - times[0]) / 1e9
        assert 0.98 * 50 * duration_s <= len(times) <= 50 * duration_s + 2, (ranges_hz,
                                                                               len(times))
        # and so in every second, on a grid of 20 ms slots (a pose late in its slot, the
        # next may come early in its own)
        per_s = np.bincount((np.array(times) - times[0]) // 10**9)[:-1]
        assert per_s.min() >= 48 and per_s.max() <= 51, (ranges_hz, per_s)
        assert min(np.diff(times)) > 0


def test_a_pose_due_within_a_read_leaves_after_the_reads_last_sample() -> None:
    """Reads of four IMU samples, poses at 50 Hz: each IMU pose is at a read's last sample
    (its newest state), never at one inside a read, where the pose fell due."""
    cfg = SimConfig(seed=5, segments=((6.0, 0.3, 0.0, 0.0),))
    poses, pipeline = poses_read_in(cfg, 4)
    sim = simulate(cfg)
    read_ends = {s.t_ns for k, s in enumerate(sim.imu) if k % 4 == 3}
    inside = {s.t_ns for s in sim.imu} - read_ends
    epochs = {m.t_ns for m in sim.uwb}
    times = [p.t_ns for p in poses]
    assert not [t for t in times if t in inside and t not in epochs]
    assert sum(t in read_ends for t in times) > 150  # most of 6 s of 50 Hz poses
    assert pipeline.poses == len(poses)


def test_an_epoch_of_several_ranges_brings_its_pose_out_at_once() -> None:
    """10 Hz epochs with a 2 Hz pose rate: a pose after every epoch all the same."""
    times, epochs = poses_of(SimConfig(seed=3, segments=((6.0, 0.0, 0.0, 0.0),)), 2.0)
    since_start = [t for t in epochs if t >= times[0]]  # (poses once the filter started)
    assert set(since_start) <= set(times) and len(times) < 1.5 * len(since_start)


def imu(t_ns: int) -> ImuSample:
    return ImuSample(t_ns=t_ns, acc_mps2=(0.0, 0.0, 9.8), gyro_rps=(0.0, 0.0, 0.0))


def test_the_aligner_releases_in_time_order_once_the_wait_has_passed() -> None:
    """Frames reaching it out of order are held until the latest arrival is ``wait_ns`` past
    them, then released oldest first; one older than a released frame is late: dropped and
    counted."""
    aligner = Aligner(wait_ns=10)
    out: list[int] = []
    for t in (100, 95, 103, 108, 111):
        out += [f.t_ns for f in aligner.push(imu(t))]
        assert out == sorted(out)
        assert all(t_out <= t - 10 for t_out in out)  # none before its wait is over
    assert out == [95, 100]
    assert aligner.push(imu(99)) == [] and aligner.late == 1  # older than 100, released
    assert [f.t_ns for f in aligner.flush()] == [103, 108, 111]
    assert aligner.stats() == {"late": 1, "overflow": 0, "pending": 0}


def test_the_aligner_without_a_wait_passes_frames_through_and_drops_the_late() -> None:
    aligner = Aligner()
    assert [f.t_ns for f in aligner.push(imu(5))] == [5]
    assert aligner.push(imu(4)) == [] and aligner.late == 1
    assert [f.t_ns for f in aligner.push(imu(5))] == [5]  # the same time is not late


def test_a_full_aligner_releases_early_and_counts_it() -> None:
    aligner = Aligner(wait_ns=1000, max_pending=2)
    released = [f.t_ns for t in (1, 2, 3, 4) for f in aligner.push(imu(t))]
    assert released == [1, 2] and aligner.overflow == 2


def test_the_status_on_the_wall_clock_notices_silent_ports() -> None:
    """Both sources stop (unplugged, stalled): the daemon's status ticks on the wall clock
    keep coming, and the health they carry counts the silence — coasting after a second,
    the IMU gap and the range timeout after five, never healthy — where it stayed at the
    last data's verdict, 'tracking', since_range_s frozen."""
    sim = simulate(SimConfig(segments=((4.0, 0.0, 0.0, 0.0), (5.0, 1.5, 0.0, 0.0),
                                       (5.2, 1.5, 0.3, 0.0), (5.0, 1.2, 0.0, 0.2)), seed=3))
    sink = PoseList()
    pipeline = Pipeline(parse(wide_limits_toml(simulation_toml(sim))), [sink])
    for frame in merge(sim.imu, sim.uwb):
        pipeline.on_frame(frame)
    last_ns = max(sim.imu[-1].t_ns, sim.uwb[-1].t_ns)
    assert pipeline.status(last_ns)["health"]["healthy"]
    for after_s, phase, faults in ((0.05, "tracking", set()), (2.0, "coasting", {"imu_gap"}),
                                   (6.0, "coasting", {"imu_gap", "range_timeout"})):
        health = pipeline.status(last_ns + int(after_s * 1e9))["health"]
        assert health["phase"] == phase and faults <= set(health["faults"]), health
        assert health["since_range_s"] >= after_s - 0.2
    assert pipeline.filter.pose() is not None  # the estimate itself is the data's, unchanged


def poses_read_in(sim_cfg: SimConfig, samples_a_read: int) -> tuple[list[Pose], Pipeline]:
    """The run's IMU as a WitMotion sends it (every packet type, ENCODERS["wit"]), read
    ``samples_a_read`` cycles at a time (a batched port: ports.SerialSource.batch_reads),
    each read stamped with its last sample's time; the ranges as frames."""
    sim = simulate(sim_cfg)
    sink = PoseList()
    pipeline = Pipeline(parse(simulation_toml(sim)), [sink])
    held: list[ImuSample] = []
    for frame in merge(sim.imu, sim.uwb):
        if not isinstance(frame, ImuSample):
            pipeline.on_frame(frame)
            continue
        held.append(frame)
        if len(held) == samples_a_read:
            pipeline.on_bytes("imu", frame.t_ns, b"".join(ENCODERS["wit"](s) for s in held))
            held = []
    pipeline.finish()
    return sink.poses, pipeline


def test_batched_reads_give_every_sample_its_own_time_from_the_second_read_on() -> None:
    """Four samples a read from the first read on: the period is learned from the second
    read (the time since the first's last sample over the four), every later sample is
    fused (none out of order) at its own time, and the poses are those of a sample a read
    (compared where both runs bring one out: after each UWB epoch)."""
    cfg = SimConfig(seed=4, segments=((10.0, 0.5, 0.0, 0.0),))
    batched, pipeline = poses_read_in(cfg, 4)
    single, reference = poses_read_in(cfg, 1)
    counters = pipeline.filter.counters
    assert counters["imu_out_of_order"] <= 3  # the first read's: no period to spread by yet
    assert reference.filter.counters["imu_out_of_order"] == 0
    assert pipeline.sample_times.period_ns["imu"] == reference.sample_times.period_ns["imu"]
    by_time = {p.t_ns: p.position_m for p in single}
    common = [p for p in batched if p.t_ns in by_time and p.t_ns > batched[0].t_ns + 3e9]
    assert len(common) >= 50
    worst_m = max(float(np.linalg.norm(np.subtract(p.position_m, by_time[p.t_ns])))
                  for p in common)
    assert worst_m < 0.01


class FrameTimes(PoseList):
    """A sink that keeps the IMU frames' times as the pipeline hands them on."""

    def __init__(self) -> None:
        super().__init__()
        self.imu_ns: list[int] = []

    def frame(self, frame: object) -> None:
        if isinstance(frame, ImuSample):
            self.imu_ns.append(frame.t_ns)


def test_every_imu_frame_gets_a_time_of_its_own_however_the_port_cuts_the_bytes() -> None:
    """A WitMotion stream cut into reads of 1 to 150 bytes (a backlog first, then a read
    per pose or less; some frames leave a read late, on the next cycle's wrap, stamped
    with an earlier read's time): every sample reaches the sinks and the filter, once,
    the finish's held cycle too, each later than the one before (none lost as out of
    order)."""
    rng = np.random.default_rng(7)
    sim = simulate(SimConfig(seed=2, segments=((3.0, 0.0, 0.0, 0.0),)))
    stream = b"".join(ENCODERS["wit"](s) for s in sim.imu)
    sink = FrameTimes()
    pipeline = Pipeline(parse(simulation_toml(sim)), [sink])
    at, t_ns = 0, sim.imu[0].t_ns
    while at < len(stream):
        size = 150 if at == 0 else int(rng.integers(1, 150))
        t_ns += size * 50_000  # ~200 kB/s: 22 bytes a sample at 200 Hz is 4.4 kB/s
        pipeline.on_bytes("imu", t_ns, stream[at:at + size])
        at += size
    pipeline.finish()
    times = sink.imu_ns
    assert len(times) == len(sim.imu)
    assert all(b > a for a, b in itertools.pairwise(times))
    assert pipeline.filter.counters["imu_out_of_order"] == 0
