"""The baselines uwbd is measured against (uwbd.tools.baselines), on constructed IMU input
and on a short simulated run against the simulator's ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.frames import ImuSample
from uwbd.fusion.core.noise import GRAVITY_MPS2
from uwbd.fusion.core.rotation import Array, euler_from_quat, quat_from_euler, quat_to_matrix
from uwbd.fusion.settings import FilterConfig
from uwbd.tools.baselines import (
    ACCEL_MPS2,
    SWAPPED_GAINS,
    THESIS_GAINS,
    TURN_RATE_RPS,
    ComplementaryAttitude,
    Gains,
    Kf4,
    PureIns,
    StaticPoints,
    UwbLeastSquares,
)
from uwbd.tools.evaluate import merge, run_method, score
from uwbd.tools.simulator import SimConfig, Simulation, simulate

# 4 s still, a straight at 1.5 m/s, a left turn at 0.3 rad/s, a climb, 3 s still
SHORT = ((4.0, 0.0, 0.0, 0.0), (5.0, 1.5, 0.0, 0.0), (5.2, 1.5, 0.3, 0.0),
         (5.0, 1.2, 0.0, 0.2), (3.0, 0.0, 0.0, 0.0))
DT_NS = 5_000_000  # 200 Hz


@pytest.fixture(scope="module")
def sim() -> Simulation:
    return simulate(SimConfig(segments=SHORT, seed=3))


def config_for(sim: Simulation) -> FilterConfig:
    return FilterConfig(anchors_m=dict(enumerate(sim.config.anchors_m)),
                        mounting_rotation=sim.config.mounting,  # type: ignore[arg-type]
                        lever_arm_m=sim.config.lever_arm_m, multipath_states=False)


def feed(att: ComplementaryAttitude, k0: int, n: int, f_b: Array,
         w_b: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
    """``n`` samples of constant specific force and rate from sample ``k0``; the next k."""
    for k in range(k0, k0 + n):
        att.predict(ImuSample(k * DT_NS, tuple(f_b), w_b))  # type: ignore[arg-type]
    return k0 + n


def test_baselines_run_as_their_methods_should(sim: Simulation) -> None:
    cfg = config_for(sim)
    runs = {name: run_method(m, merge(sim.imu, sim.uwb)) for name, m in (
        ("ins", PureIns(cfg)), ("ls", UwbLeastSquares(cfg)), ("static", StaticPoints(cfg)),
        ("kf", Kf4(cfg)), ("kf swapped", Kf4(cfg, gains=SWAPPED_GAINS)))}
    acc = {name: score(t, p, sim.truth_t_ns, sim.truth_p_m, skip_s=6)
           for name, (t, p) in runs.items()}
    assert acc["ls"].rmse_xy_m < 0.25 and acc["static"].rmse_xy_m < 0.25
    assert acc["kf"].rmse_xy_m < 0.4 and acc["kf swapped"].rmse_xy_m < 0.4
    assert acc["ins"].rmse_xy_m > acc["ls"].rmse_xy_m  # an uncorrected INS drifts
    assert len(runs["ls"][0]) > 0.9 * len(sim.uwb)
    assert len(runs["static"][0]) == len(runs["ls"][0])  # a position for every fix
    for _, p in runs.values():
        assert np.all(np.isfinite(p))


def test_complementary_filter_levels_at_start_and_finds_roll_and_pitch_at_rest() -> None:
    q = quat_from_euler(0.1, -0.05, 0.0)
    f_b = quat_to_matrix(q).T @ np.array([0.0, 0.0, GRAVITY_MPS2])
    att = ComplementaryAttitude(np.eye(3))
    feed(att, 0, 1, f_b)
    assert euler_from_quat(att.q)[:2] == pytest.approx((0.1, -0.05), abs=1e-9)  # levelled
    att.q = np.array([1.0, 0.0, 0.0, 0.0])  # knocked off: the low gain (0.2) pulls it back
    feed(att, 1, 6000, f_b)
    assert att.kp == THESIS_GAINS.still
    assert euler_from_quat(att.q)[:2] == pytest.approx((0.1, -0.05), abs=1e-3)


@pytest.mark.parametrize("gains", [THESIS_GAINS, SWAPPED_GAINS])
def test_dual_gain_switches_on_turning_and_accelerating(gains: Gains) -> None:
    g = np.array([0.0, 0.0, GRAVITY_MPS2])
    att = ComplementaryAttitude(np.eye(3), gains=gains)
    k = feed(att, 0, 200, g)
    assert (att.turning, att.accelerating, att.kp) == (False, False, gains.still)
    # yawing (gravity stays put in body axes): slower than the threshold, then faster
    k = feed(att, k, 200, g, (0.0, 0.0, 0.5 * TURN_RATE_RPS))
    assert (att.turning, att.kp) == (False, gains.still)
    k = feed(att, k, 40, g, (0.0, 0.0, 2.0 * TURN_RATE_RPS))  # 0.2 s: 2 τ
    assert (att.turning, att.accelerating, att.kp) == (True, False, gains.moving)
    k = feed(att, k, 100, g)
    assert (att.turning, att.kp) == (False, gains.still)
    # vertical acceleration: |f| − g below the threshold, then above it
    k = feed(att, k, 200, g + np.array([0.0, 0.0, 0.5 * ACCEL_MPS2]))
    assert (att.accelerating, att.kp) == (False, gains.still)
    k = feed(att, k, 200, g + np.array([0.0, 0.0, 2.0 * ACCEL_MPS2]))
    assert (att.turning, att.accelerating, att.kp) == (False, True, gains.moving)
    feed(att, k, 200, g)
    assert (att.accelerating, att.kp) == (False, gains.still)
    assert att.moving_s == pytest.approx(0.2 + 1.0, abs=0.35)  # the turn, the acceleration


@pytest.mark.parametrize(("gains", "max_tilt_deg"), [(THESIS_GAINS, 5.0),
                                                     (SWAPPED_GAINS, 12.0)])
def test_attitude_error_on_a_simulated_run_is_bounded(sim: Simulation, gains: Gains,
                                                      max_tilt_deg: float) -> None:
    """The body stays level in the simulator. The thesis's gains tilt by the turns'
    centripetal acceleration (~2.6°); swapped, by the speed changes, which the |f| test does
    not see (the high still-gain follows a 2 m/s² deceleration to ~9°)."""
    kf = Kf4(config_for(sim), gains=gains)
    tilt, yaw = [], []
    for frame in merge(sim.imu, sim.uwb):
        if isinstance(frame, ImuSample):
            kf.predict(frame)
            k = (frame.t_ns - sim.imu[0].t_ns) // DT_NS
            up = quat_to_matrix(kf.attitude.q).T @ np.array([0.0, 0.0, 1.0])
            tilt.append(math.degrees(math.acos(min(1.0, float(up[2])))))
            yaw.append(math.degrees(math.remainder(
                euler_from_quat(kf.attitude.q)[2] - float(sim.truth_yaw_rad[k]), math.tau)))
        else:
            kf.update(frame)
    assert np.all(np.isfinite(tilt)) and np.all(np.isfinite(yaw))
    assert math.sqrt(np.mean(np.square(tilt))) < 3.0 and max(tilt) < max_tilt_deg
    assert max(np.abs(yaw)) < 1.0  # gyro bias from the still start: no drift to speak of
    assert kf.start_samples > 700  # the still start (4 s) averaged, not one sample
    assert 0 < kf.attitude.moving_s < 8.0  # the turn (5.2 s) and its blends


def test_static_points_hold_still_at_rest_and_follow_motion(sim: Simulation) -> None:
    sp = StaticPoints(config_for(sim))
    t0 = sim.truth_t_ns[0]
    rows = []
    for frame in merge(sim.imu, sim.uwb):
        if isinstance(frame, ImuSample):
            sp.predict(frame)
            continue
        sp.update(frame)
        p = sp.position()
        if p is not None and sp.fix is not None:
            rows.append(((frame.t_ns - t0) / 1e9, p, sp.fix.position_m, sp.at_rest))
    t = np.array([r[0] for r in rows])
    out, raw = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    rest = np.array([r[3] for r in rows])
    still = (t >= 2.0) & (t < 3.9)  # the still start, the mean under way
    assert rest[still].all()
    assert np.linalg.norm(out[still].std(axis=0)) < 0.3 * np.linalg.norm(raw[still].std(axis=0))
    # motion from 4 s: fix by fix again within 0.2 s, the straight at 1.5 m/s included
    moving = (t >= 4.2) & (t < 19.0)
    assert not rest[moving].any()
    np.testing.assert_array_equal(out[moving], raw[moving])
    truth = np.column_stack([np.interp(t[moving] * 1e9 + t0, sim.truth_t_ns, sim.truth_p_m[:, i])
                             for i in range(2)])
    assert math.sqrt(np.mean(np.sum((out[moving, :2] - truth) ** 2, axis=1))) < 0.25
    # the stop at the end: averaging again
    assert rest[t > 21.0].all() and sp.rest_fixes > 40
