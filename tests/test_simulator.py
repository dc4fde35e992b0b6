"""The simulator's schedules, faults and presets; the default run stays bit for bit."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import struct
from collections import Counter

import numpy as np
import pytest

from uwbd.config import parse
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.sim_presets import PRESETS, ceiling_room, handheld_async, seed_layout
from uwbd.tools.simulator import EPOCH_NS, SimConfig, Simulation, simulate

SHORT = ((3.0, 0.0, 0.0, 0.0), (5.0, 1.0, 0.2, 0.0), (2.0, 0.0, 0.0, 0.0))  # 10 s

# fingerprints of simulate(SimConfig()) and of a 100 Hz IMU run: the sha256 of both matched
# the simulator as it was before schedules, faults and presets were added (commit b1267ac)
# on an AVX-512 machine; numpy's SIMD sin/exp differ in the last bit between CPUs, so the
# figures below (taken on an AVX2 machine) are compared to 1e-9
DEFAULT_FINGERPRINT = [
    11721.0, 343425300000000.0, 228959967500000.03,
    82047.0, 176295.7205340762, 87850.79852798651,
    587.0, 17199100000000.0, 11475850000000.0,
    6918.0, 102301.16160823037, 51127.62053777175,
    11721.0, 343425300000000.0, 228959967500000.03,
    35163.0, 86339.45571503419, 59364.36893336137,
    35163.0, 1635.916688172034, -2137.401829375287,
    11721.0, 24307.140000003816, 17645.30112409879,
    3.0, 0.031702400412268676, 0.028718510939881557,
    3.0, -0.0003458710054929327, 0.00046880184164464636,
    6.0, -0.009000725453513232, -0.039258731250216554,
]
IMU_100HZ_SEED_1_FINGERPRINT = [
    5861.0, 171727300000000.0, 114494635000000.0,
    41027.0, 88402.75399691808, 44058.06031010371,
    587.0, 17199100000000.0, 11475850000000.0,
    6880.0, 101860.37085756654, 50893.70249498193,
    5861.0, 171727300000000.0, 114494635000000.0,
    17583.0, 43166.02275341398, 29679.802891064333,
    17583.0, 817.9583440879496, -1068.6121807982377,
    5861.0, 12154.74000000191, 8823.820611962876,
    3.0, 0.07488197058746658, 0.037062307396698316,
    3.0, 0.00024286603716384015, 0.004495262528502851,
    6.0, 0.0383401496881774, 0.030239485709163027,
]


def digest(sim: Simulation) -> str:
    h = hashlib.sha256()
    for f in sim.imu:
        h.update(struct.pack("<q7d", f.t_ns, *f.acc_mps2, *f.gyro_rps, f.temperature_c))
    for e in sim.uwb:
        h.update(struct.pack("<qq", e.t_ns, len(e.ranges)))
        for r in e.ranges:
            h.update(struct.pack("<qd", r.anchor_id, r.range_m))
    for a in (sim.truth_t_ns, sim.truth_p_m, sim.truth_v_mps, sim.truth_yaw_rad,
              sim.acc_bias_mps2, sim.gyro_bias_rps, sim.range_bias_m):
        h.update(np.ascontiguousarray(a, dtype="<f8" if a.dtype.kind == "f" else "<i8")
                 .tobytes())
    return h.hexdigest()


def fingerprint(sim: Simulation) -> list[float]:
    """Per quantity its count, sum and index-weighted sum: a change of the simulator moves
    them far more than the last bit a CPU's vector maths may."""
    quantities = [
        [float(f.t_ns - EPOCH_NS) for f in sim.imu],
        [v for f in sim.imu for v in (*f.acc_mps2, *f.gyro_rps, f.temperature_c)],
        [float(e.t_ns - EPOCH_NS) for e in sim.uwb],
        [v for e in sim.uwb for r in e.ranges for v in (r.anchor_id, r.range_m)],
        *(np.asarray(a, dtype=float).ravel() for a in (
            np.asarray(sim.truth_t_ns) - EPOCH_NS, sim.truth_p_m, sim.truth_v_mps,
            sim.truth_yaw_rad, sim.acc_bias_mps2, sim.gyro_bias_rps, sim.range_bias_m)),
    ]
    out = []
    for q in quantities:
        a = np.asarray(q, dtype=float)
        out += [float(len(a)), float(a.sum()), float(a @ np.linspace(0.0, 1.0, len(a)))]
    return out


def assert_fingerprint(sim: Simulation, expected: list[float]) -> None:
    np.testing.assert_allclose(fingerprint(sim), expected, rtol=1e-9, atol=1e-9)


def seconds(t_ns: int) -> float:
    return (t_ns - EPOCH_NS) / 1e9


def short(**kw: object) -> Simulation:
    return simulate(SimConfig(segments=SHORT, **kw))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def base() -> Simulation:
    return short(seed=5)


@pytest.fixture(scope="module")
def handheld() -> Simulation:
    return simulate(handheld_async(0))


@pytest.fixture(scope="module")
def room() -> Simulation:
    return simulate(ceiling_room(0))


# -- the default run ----------------------------------------------------------------------
def test_default_run_is_unchanged_bit_for_bit() -> None:
    assert_fingerprint(simulate(SimConfig()), DEFAULT_FINGERPRINT)
    assert_fingerprint(simulate(SimConfig(seed=1, imu_rate_hz=100.0)),
                       IMU_100HZ_SEED_1_FINGERPRINT)
    assert digest(simulate(seed_layout(0))) == digest(simulate(SimConfig()))


def test_presets_are_deterministic_from_the_seed() -> None:
    for make in PRESETS.values():
        assert digest(simulate(make(3))) == digest(simulate(make(3)))
        assert digest(simulate(make(3))) != digest(simulate(make(4)))


# -- round-robin schedule -----------------------------------------------------------------
def test_round_robin_sends_one_range_a_message_at_distinct_times(handheld: Simulation) -> None:
    cfg = handheld.config
    n = len(cfg.anchors_m)
    assert all(len(m.ranges) == 1 for m in handheld.uwb)
    t = np.array([m.t_ns for m in handheld.uwb])
    assert np.all(np.diff(t) > 0)  # strictly increasing: no two messages share a time
    # anchors in turn: each range's anchor follows from its slot
    period_s = 1 / cfg.uwb_rate_hz
    slot = np.round((t - EPOCH_NS) / 1e9 / period_s - 0.5).astype(int)
    ids = np.array([m.ranges[0].anchor_id for m in handheld.uwb])
    assert np.array_equal(ids, slot % n)
    # jittered by up to uwb_jitter_s about the slot times, not pinned to them
    offset = (t - EPOCH_NS) / 1e9 - (slot + 0.5) * period_s
    assert np.abs(offset).max() <= cfg.uwb_jitter_s + 1e-9
    assert np.abs(offset).max() > 0.5 * cfg.uwb_jitter_s and np.std(offset) > 1e-4
    # each anchor at about rate / n (less the dropouts)
    duration_s = seconds(int(handheld.truth_t_ns[-1]))
    expected = cfg.uwb_rate_hz / n * duration_s * (1 - cfg.dropout_prob)
    counts = Counter(ids.tolist())
    assert sorted(counts) == list(range(n))
    assert all(abs(c - expected) < 0.05 * expected for c in counts.values())


def test_round_robin_ranges_are_the_true_distances_plus_errors() -> None:
    sim = short(uwb_schedule="round_robin", uwb_rate_hz=80.0, range_noise_m=0.0,
                nlos_rate_hz=0.0, seed=2)
    p = sim.truth_p_m
    anchors = np.array(sim.config.anchors_m)
    for m in sim.uwb[::25]:
        r = m.ranges[0]
        ts = seconds(m.t_ns)
        truth_t = (sim.truth_t_ns - EPOCH_NS) / 1e9
        pos = np.array([np.interp(ts, truth_t, p[:, k]) for k in range(3)])
        yaw = float(np.interp(ts, truth_t, sim.truth_yaw_rad))
        lever = np.array(sim.config.lever_arm_m)
        ant = pos + np.array([[math.cos(yaw), -math.sin(yaw), 0],
                              [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]) @ lever
        true = float(np.linalg.norm(anchors[r.anchor_id] - ant))
        assert r.range_m - sim.range_bias_m[r.anchor_id] == pytest.approx(true, abs=2e-3)


def test_nlos_is_more_frequent_on_the_low_anchors(handheld: Simulation) -> None:
    """Excess over the true range beyond 4 sigma of noise: NLOS."""
    sim = handheld
    anchors = np.array(sim.config.anchors_m)
    truth_t = sim.truth_t_ns
    nlos: Counter[str] = Counter()
    for m in sim.uwb:
        r = m.ranges[0]
        k = min(int(np.searchsorted(truth_t, m.t_ns)), len(truth_t) - 1)
        ant = sim.truth_p_m[k] + np.array([0.0, 0.0, sim.config.lever_arm_m[2]])
        excess = r.range_m - sim.range_bias_m[r.anchor_id] - np.linalg.norm(anchors[r.anchor_id]
                                                                            - ant)
        nlos["low" if anchors[r.anchor_id, 2] < 1 else "high"] += excess > 0.4
    assert nlos["low"] > 2 * nlos["high"]


def test_schedule_and_windows_are_checked() -> None:
    with pytest.raises(ValueError, match="uwb_schedule"):
        short(uwb_schedule="burst")
    with pytest.raises(ValueError, match="no anchor 9"):
        short(anchor_outages_s=((9, 1.0, 1.0),))
    with pytest.raises(ValueError, match="uwb_jitter_s"):
        short(uwb_schedule="round_robin", uwb_rate_hz=170.0, uwb_jitter_s=0.003)
    with pytest.raises(ValueError, match="anchor_nlos_rate_hz"):
        short(anchor_nlos_rate_hz=(0.1, 0.1))
    with pytest.raises(ValueError, match="imu_spikes_s"):
        short(imu_spikes_s=(11.0,))


# -- UWB faults -----------------------------------------------------------------------------
@pytest.mark.parametrize("schedule", ["epoch", "round_robin"])
def test_anchor_outage_silences_that_anchor_only(schedule: str) -> None:
    sim = short(uwb_schedule=schedule, uwb_rate_hz=60.0 if schedule == "round_robin" else 10.0,
                anchor_outages_s=((2, 3.0, 4.0),), seed=1)
    inside = [m for m in sim.uwb if 3.0 <= seconds(m.t_ns) < 7.0]
    outside = [m for m in sim.uwb if not 3.0 <= seconds(m.t_ns) < 7.0]
    assert inside and outside
    assert sum(r.anchor_id == 2 for m in inside for r in m.ranges) == 0
    assert {r.anchor_id for m in inside for r in m.ranges} == {0, 1, 3, 4, 5}
    assert sum(r.anchor_id == 2 for m in outside for r in m.ranges) > 10


@pytest.mark.parametrize("schedule", ["epoch", "round_robin"])
def test_uwb_outage_sends_no_message(schedule: str) -> None:
    windows = ((2.0, 1.5), (6.0, 0.5))
    sim = short(uwb_schedule=schedule, uwb_rate_hz=60.0 if schedule == "round_robin" else 10.0,
                uwb_outages_s=windows, seed=1)
    t = np.array([seconds(m.t_ns) for m in sim.uwb])
    for start, duration in windows:
        assert np.sum((t >= start) & (t < start + duration)) == 0
        assert np.sum((t >= start - 0.5) & (t < start)) > 0  # and messages either side
        assert np.sum((t >= start + duration) & (t < start + duration + 0.5)) > 0


def test_faults_change_nothing_outside_their_windows(base: Simulation) -> None:
    faulty = short(seed=5, uwb_outages_s=((2.0, 1.0),), anchor_outages_s=((0, 5.0, 2.0),),
                   imu_gaps_s=((4.0, 0.5),), imu_saturations_s=((6.0, 0.2),),
                   imu_spikes_s=(8.0,))
    ok = [m for m in base.uwb if not 2.0 <= seconds(m.t_ns) < 3.0]
    assert [m.t_ns for m in faulty.uwb] == [m.t_ns for m in ok]
    for a, b in zip(faulty.uwb, ok, strict=True):
        if not 5.0 <= seconds(a.t_ns) < 7.0:
            assert a == b
    touched = {f.t_ns for f in base.imu} - {f.t_ns for f in faulty.imu}
    assert all(4.0 <= seconds(t) < 4.5 for t in touched)
    clean = {f.t_ns: f for f in base.imu}
    changed = [f for f in faulty.imu if clean[f.t_ns] != f]
    assert all(6.0 <= seconds(f.t_ns) < 6.2 or seconds(f.t_ns) == 8.0 for f in changed)
    assert len(changed) == 0.2 * 200 + 1
    np.testing.assert_array_equal(faulty.truth_p_m, base.truth_p_m)


# -- IMU faults -----------------------------------------------------------------------------
def test_imu_gap_sends_no_sample_and_truth_goes_on(base: Simulation) -> None:
    sim = short(seed=5, imu_gaps_s=((2.0, 1.0), (7.3, 0.25)))
    t = np.array([seconds(f.t_ns) for f in sim.imu])
    assert np.sum((t >= 2.0) & (t < 3.0)) == 0 and np.sum((t >= 7.3) & (t < 7.55)) == 0
    assert len(sim.imu) == len(base.imu) - 200 - 50
    assert len(sim.truth_t_ns) == len(base.truth_t_ns)


def test_saturated_samples_read_full_scale_on_every_axis() -> None:
    cfg = SimConfig(segments=SHORT, seed=5, imu_saturations_s=((4.0, 0.5),))
    sim = simulate(cfg)
    inside = [f for f in sim.imu if 4.0 <= seconds(f.t_ns) < 4.5]
    assert len(inside) == 100
    assert cfg.acc_full_scale_mps2 == 16 * 9.80665
    assert cfg.gyro_full_scale_rps == math.radians(2000)
    for f in inside:
        assert f.acc_mps2 == (cfg.acc_full_scale_mps2,) * 3
        assert f.gyro_rps == (cfg.gyro_full_scale_rps,) * 3
    others = [f for f in sim.imu if not 4.0 <= seconds(f.t_ns) < 4.5]
    assert max(abs(a) for f in others for a in f.acc_mps2) < 0.2 * cfg.acc_full_scale_mps2


def test_each_spike_corrupts_exactly_one_sample(base: Simulation) -> None:
    cfg = SimConfig(segments=SHORT, seed=5, imu_spikes_s=(1.0012, 5.5, 9.0))
    sim = simulate(cfg)
    spiky = [f for f in sim.imu if f.acc_mps2[0] > 50 or f.gyro_rps[2] > 10]
    assert [seconds(f.t_ns) for f in spiky] == pytest.approx([1.0, 5.5, 9.0])
    clean = {f.t_ns: f for f in base.imu}
    for f in spiky:  # the spike on top of the clean reading, below full scale
        c = clean[f.t_ns]
        assert f.acc_mps2[0] - c.acc_mps2[0] == pytest.approx(cfg.imu_spike_acc_mps2[0])
        assert f.gyro_rps[2] - c.gyro_rps[2] == pytest.approx(cfg.imu_spike_gyro_rps[2])
        assert f.acc_mps2[1:] == c.acc_mps2[1:] and f.gyro_rps[:2] == c.gyro_rps[:2]
        assert abs(f.acc_mps2[0]) < 0.75 * cfg.acc_full_scale_mps2
        assert abs(f.gyro_rps[2]) < 0.75 * cfg.gyro_full_scale_rps
    # a spike in a gap lands on the nearest sample sent
    gapped = simulate(dataclasses.replace(cfg, imu_spikes_s=(5.5,), imu_gaps_s=((5.0, 0.52),)))
    spiky = [f for f in gapped.imu if f.acc_mps2[0] > 50]
    assert [seconds(f.t_ns) for f in spiky] == pytest.approx([5.52])


# -- presets --------------------------------------------------------------------------------
def inside_footprint(xy: np.ndarray, anchors: np.ndarray, margin_m: float) -> bool:
    """All points inside the anchors' convex hull (anchors in counter-clockwise order,
    as the presets list them), at least ``margin_m`` from its edges."""
    corners = anchors[:, :2]
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        edge = (b - a) / np.linalg.norm(b - a)
        dist = edge[0] * (xy[:, 1] - a[1]) - edge[1] * (xy[:, 0] - a[0])  # left of edge
        if dist.min() < margin_m:
            return False
    return True


def test_ceiling_room_stays_in_the_room(room: Simulation) -> None:
    cfg = room.config
    anchors = np.array(cfg.anchors_m)
    assert len(anchors) == 4 and np.all((anchors[:, 2] >= 2.3) & (anchors[:, 2] <= 2.6))
    assert len(set(anchors[:, 2])) > 1
    span = anchors.max(axis=0) - anchors.min(axis=0)
    assert 7 <= span[0] <= 8 and 5 <= span[1] <= 6
    assert cfg.start_m[2] == pytest.approx(0.45) and cfg.lever_arm_m == (0.0, 0.0, 0.27)
    z = room.truth_p_m[:, 2]
    assert z.min() >= 0.3 and z.max() <= 0.6 and z.max() - z.min() > 0.1  # it climbs
    assert inside_footprint(room.truth_p_m, anchors, margin_m=0.5)
    speed = np.linalg.norm(room.truth_v_mps[:, :2], axis=1)
    assert speed.max() <= 0.8 + 1e-9 and np.mean(speed < 1e-6) > 0.15  # slow, with stops
    assert 60 <= seconds(int(room.truth_t_ns[-1])) <= 90
    # the anchor outage in the middle, 20 s
    (i, start, duration), = cfg.anchor_outages_s
    assert duration == 20.0 and abs(start + duration / 2 - 38) < 5
    t = [seconds(m.t_ns) for m in room.uwb for r in m.ranges if r.anchor_id == i]
    assert not any(start <= x < start + duration for x in t)
    assert cfg.nlos_rate_hz > 0 and cfg.uwb_schedule == "epoch"


def test_handheld_async_layout_and_motion(handheld: Simulation) -> None:
    cfg = handheld.config
    anchors = np.array(cfg.anchors_m)
    assert len(anchors) == 8 and cfg.uwb_schedule == "round_robin"
    assert cfg.uwb_rate_hz == 170 and cfg.imu_rate_hz == 100 and cfg.range_noise_m == 0.1
    assert np.sum(np.abs(anchors[:, 2] - 0.3) < 0.05) == 4
    assert np.sum(np.abs(anchors[:, 2] - 2.3) < 0.05) == 4
    assert np.all(np.diff([f.t_ns for f in handheld.imu]) == 10_000_000)
    assert inside_footprint(handheld.truth_p_m, anchors[:4], margin_m=0.5)
    speed = np.linalg.norm(handheld.truth_v_mps[:, :2], axis=1)
    assert speed.max() <= 0.5 + 1e-9 and np.mean(speed < 1e-6) > 0.15
    assert np.abs(np.diff(handheld.truth_yaw_rad)).max() * cfg.imu_rate_hz <= 0.3 + 1e-6
    assert 50 <= seconds(int(handheld.truth_t_ns[-1])) <= 70


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_simulated_log_config_describes_each_preset(name: str) -> None:
    sim = simulate(PRESETS[name](0))
    cfg = sim.config
    config = parse(simulation_toml(sim))
    assert config.anchors_m == dict(enumerate(cfg.anchors_m))
    assert config.lever_arm_m == cfg.lever_arm_m
    assert config.imu_noise["acc_noise_mps2_rthz"] == pytest.approx(
        cfg.acc_noise_mps2 / math.sqrt(cfg.imu_rate_hz))
    assert config.imu_noise["gyro_noise_rps_rthz"] == pytest.approx(
        cfg.gyro_noise_rps / math.sqrt(cfg.imu_rate_hz))
    assert config.fusion["range_sigma_m"] == cfg.range_noise_m
