"""The fusion core on short simulated runs, against the simulator's ground truth."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from scipy.stats import chi2
from truth import WIDE_LIMITS, position_errors

from drivers.frames import AnchorRange, ImuSample, UwbRanges
from uwbd.fusion.checks.gating import chi2_quantile
from uwbd.fusion.core import native
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE, TH_
from uwbd.fusion.core.lsq import coplanar, multilaterate
from uwbd.fusion.core.noise import ImuNoise
from uwbd.fusion.core.rotation import (
    Array,
    euler_from_quat,
    quat_from_euler,
    quat_mul,
    quat_to_matrix,
)
from uwbd.fusion.core.smoother import smooth
from uwbd.fusion.filter import Filter
from uwbd.fusion.settings import FilterConfig, Mode
from uwbd.fusion.types import Phase, Pose
from uwbd.tools.evaluate import (
    merge,
    run_filter,
    run_smoother,
    score,
    score_poses,
    truth_spikes,
)
from uwbd.tools.simulator import SimConfig, Simulation, simulate

SHORT = ((4.0, 0.0, 0.0, 0.0), (5.0, 1.5, 0.0, 0.0), (5.2, 1.5, 0.3, 0.0),
         (5.0, 1.2, 0.0, 0.2), (3.0, 0.0, 0.0, 0.0))


def short_sim(**kw: object) -> Simulation:
    return simulate(SimConfig(segments=SHORT, **kw))  # type: ignore[arg-type]


def config_for(sim: Simulation, **kw: object) -> FilterConfig:
    """Generic defaults, but for the simulator's white range noise (no multipath states) and
    with wide alert limits (truth.WIDE_LIMITS)."""
    kw.setdefault("multipath_states", False)
    kw.setdefault("health", WIDE_LIMITS)
    return FilterConfig(anchors_m=dict(enumerate(sim.config.anchors_m)),
                        mounting_rotation=sim.config.mounting,  # type: ignore[arg-type]
                        lever_arm_m=sim.config.lever_arm_m, **kw)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def sim() -> Simulation:
    return short_sim(seed=3)


# -- the algebra -----------------------------------------------------------------------
def random_eskf(seed: int) -> Eskf:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(N_CORE + 2, N_CORE + 2))
    P0 = A @ A.T / 10 + np.eye(N_CORE + 2) * 0.01
    return Eskf(rng.normal(size=3), rng.normal(size=3), quat_from_euler(0.1, -0.2, 1.0), P0,
                ImuNoise(), n_range_bias=2)


def test_joint_update_equals_sequential_scalar_updates() -> None:
    """With H at the prior and no re-linearisation, one joint update = sequential ones."""
    rng = np.random.default_rng(7)
    H, y, R = rng.normal(size=(5, N_CORE + 2)), rng.normal(size=5), rng.uniform(0.01, 0.1, 5)
    joint, seq = random_eskf(1), random_eskf(1)
    P0 = joint.P.copy()
    # the error state before injection, done by hand for the sequential version
    P, dx = P0.copy(), np.zeros(N_CORE + 2)
    for i in range(5):
        h = H[i]
        S = h @ P @ h + R[i]
        K = P @ h / S
        dx = dx + K * (y[i] - h @ dx)
        IKH = np.eye(len(dx)) - np.outer(K, h)
        P = IKH @ P @ IKH.T + R[i] * np.outer(K, K)
    dx_joint = joint.update(H, y, R)
    np.testing.assert_allclose(dx_joint, dx, atol=1e-12)
    _ = seq


def test_joseph_update_keeps_p_symmetric_positive_definite() -> None:
    ekf = random_eskf(2)
    rng = np.random.default_rng(3)
    for _ in range(200):
        H = rng.normal(size=(3, ekf.n))
        ekf.update(H, rng.normal(size=3), np.full(3, 1e-6))  # very precise: stresses P
        ekf.predict((0.1, 0.0, 9.8), (0.0, 0.0, 0.1), 0.005)
        ekf.propagate()
    assert np.allclose(ekf.P, ekf.P.T)
    assert np.linalg.eigvalsh(ekf.P).min() > 0


# -- the algebra -----------------------------------------------------------------------------
def test_joseph_form_is_right_for_a_de_weighted_non_optimal_gain() -> None:
    """A robust weight w uses the gain of R/w; the covariance must be that gain's under the
    nominal R: (I − KH) P (I − KH)ᵀ + K R Kᵀ, which (I − KH) P is not."""
    ekf = random_eskf(4)
    rng = np.random.default_rng(5)
    h, r, w = rng.normal(size=N_CORE + 2), 0.04, 0.3
    P = ekf.P.copy()
    K = P @ h / (h @ P @ h + r / w)
    IKH = np.eye(len(h)) - np.outer(K, h)
    expected = IKH @ P @ IKH.T + r * np.outer(K, K)
    ekf.sequential_update(h[None, :], np.array([0.0]), np.array([r]), lambda i, nu, s: w)
    # the reset after a zero correction leaves P alone
    np.testing.assert_allclose(ekf.P, expected, atol=1e-12)
    assert not np.allclose(ekf.P, IKH @ P, atol=1e-6)


def test_a_row_whose_variance_is_below_its_noise_is_skipped_not_fused() -> None:
    ekf = random_eskf(6)
    ekf.P[0, 0] = -1.0  # P no longer positive semi-definite along this row
    h = np.zeros(N_CORE + 2)
    h[0] = 1.0
    before = ekf.p.copy()
    rows = ekf.sequential_update(h[None, :], np.array([1.0]), np.array([0.01]),
                                 lambda i, nu, s: 1.0)
    assert rows[0].numerical and rows[0].weight == 0.0 and ekf.p == before


def test_gyro_noise_grows_the_attitude_covariance() -> None:
    """At rest with a certain start, one second adds σ_g² to each attitude variance."""
    noise = ImuNoise()
    ekf = Eskf((0, 0, 0), (0, 0, 0), (1.0, 0.0, 0.0, 0.0), np.eye(N_CORE) * 1e-12, noise)
    for _ in range(200):
        ekf.predict((0.0, 0.0, 9.80665), (0.0, 0.0, 0.0), 0.005)
    ekf.propagate()
    np.testing.assert_allclose(np.diag(ekf.P[TH_, TH_]), noise.gyro**2 * 1.0, rtol=0.01)


def test_strapdown_at_rest_stays_put() -> None:
    q = quat_from_euler(0.2, -0.1, 0.7)
    f_b = quat_to_matrix(q).T @ np.array([0, 0, 9.80665])
    ekf = Eskf((1, 2, 3), (0, 0, 0), q, np.eye(N_CORE) * 1e-4, ImuNoise())
    for _ in range(2000):  # 10 s at 200 Hz
        ekf.predict(f_b, (0.0, 0.0, 0.0), 0.005)
    np.testing.assert_allclose(ekf.p, (1, 2, 3), atol=1e-9)
    assert euler_from_quat(np.array(ekf.q)) == pytest.approx((0.2, -0.1, 0.7), abs=1e-12)


# -- least squares ---------------------------------------------------------------------
def test_least_squares_finds_the_tag_and_rejects_one_outlier() -> None:
    anchors = np.array(SimConfig().anchors_m)
    tag = np.array([3.0, -2.0, 1.0])
    d = np.linalg.norm(anchors - tag, axis=1)
    fix = multilaterate(anchors, d, core=native.core)
    assert fix is not None and np.allclose(fix.position_m, tag, atol=1e-3)
    d_bad = d.copy()
    d_bad[2] += 2.0  # one NLOS range
    fix = multilaterate(anchors, d_bad, sigma_m=0.05, core=native.core)
    assert fix is not None and not fix.used[2]
    assert np.allclose(fix.position_m, tag, atol=1e-3)


def test_coplanar_anchors_use_the_known_height() -> None:
    anchors = np.array([[0, 0, 2.0], [10, 0, 2.0], [10, 10, 2.0], [0, 10, 2.0]])
    assert coplanar(anchors)
    tag = np.array([4.0, 6.0, 0.5])
    fix = multilaterate(anchors, np.linalg.norm(anchors - tag, axis=1), fixed_z=0.5,
                        core=native.core)
    assert fix is not None and np.allclose(fix.position_m, tag, atol=1e-3)


# -- the filter against truth ----------------------------------------------------------
@pytest.mark.parametrize("mode", [Mode.TIGHT, Mode.LOOSE])
def test_filter_beats_least_squares_and_is_consistent(sim: Simulation, mode: Mode) -> None:
    poses, reports, flt = run_filter(config_for(sim, mode=mode), merge(sim.imu, sim.uwb))
    # scored after the heading alignment (about 2 s into the motion, which starts at 4 s)
    acc = score_poses(poses, sim.truth_t_ns, sim.truth_p_m, skip_s=9)
    anchors = np.array(sim.config.anchors_m)
    fixes = [(e.t_ns, multilaterate(anchors[[r.anchor_id for r in e.ranges]],
                                    np.array([r.range_m for r in e.ranges]), core=native.core))
             for e in sim.uwb]
    ls = score(np.array([t for t, f in fixes if f]), np.array([f.position_m for _, f in fixes
                                                              if f]),
               sim.truth_t_ns, sim.truth_p_m, skip_s=9)
    assert acc.rmse_xy_m < 0.8 * ls.rmse_xy_m
    if mode is Mode.TIGHT:  # loose trusts fixes whose errors are biased and correlated
        assert acc.rmse_xy_m < 0.07
        # never overconfident; right after the heading alignment it is on the cautious side
        # (full-length runs: NEES/3 0.88, benchmarks/bench_fusion.py)
        assert 0.1 < acc.nees_mean < 2.0
    assert flt.counters["initialisations"] == 1
    assert flt.counters["heading_alignments"] == 1
    assert flt.counters["started_rest"] == 1 and all(r.kind for r in reports)
    assert flt.health().phase is Phase.TRACKING and flt.health().healthy
    final = poses[-1]
    assert final.heading_observable
    yaw = euler_from_quat(np.array([final.orientation_xyzw[3], *final.orientation_xyzw[:3]]))[2]
    assert abs(math.remainder(yaw - sim.truth_yaw_rad[-1], math.tau)) < math.radians(3)


def test_heading_unknown_at_start_is_reported_then_found(sim: Simulation) -> None:
    poses, _, _ = run_filter(config_for(sim), merge(sim.imu, sim.uwb))
    assert not poses[0].heading_observable
    assert poses[0].health.phase in (Phase.ALIGNING, Phase.COASTING)
    assert "tracking" not in poses[0].status
    assert poses[-1].heading_observable and poses[-1].health.phase is Phase.TRACKING


@pytest.mark.parametrize("start_yaw_rad", [1.5, 2.8, -2.0])
def test_any_initial_heading_is_found(start_yaw_rad: float) -> None:
    """The filter's yaw guess at power-on is 0; the vehicle may face anywhere."""
    turned = short_sim(seed=5, start_yaw_rad=start_yaw_rad)
    poses, _, flt = run_filter(config_for(turned), merge(turned.imu, turned.uwb))
    assert flt.counters["heading_alignments"] == 1
    # no divergence (before the alignment existed: 0.5-1.9 m); some starts drive out of the
    # anchors' hull in this short run, so accuracy itself is left to the benchmark
    assert score_poses(poses, turned.truth_t_ns, turned.truth_p_m, skip_s=9).rmse_xy_m < 0.1
    final = poses[-1]
    yaw = euler_from_quat(np.array([final.orientation_xyzw[3], *final.orientation_xyzw[:3]]))[2]
    assert abs(math.remainder(yaw - turned.truth_yaw_rad[-1], math.tau)) < math.radians(5)
    assert final.heading_observable


def test_start_while_moving() -> None:
    moving = simulate(SimConfig(seed=4, segments=((3.0, 1.0, 0.1, 0.0), (12.0, 1.2, 0.0, 0.0))))
    poses, _, flt = run_filter(config_for(moving), merge(moving.imu, moving.uwb))
    assert flt.counters["started_moving"] == 1
    assert score_poses(poses, moving.truth_t_ns, moving.truth_p_m, skip_s=8).rmse_xy_m < 0.15


def test_gyro_bias_is_estimated_at_rest(sim: Simulation) -> None:
    _, _, flt = run_filter(config_for(sim), merge(sim.imu, sim.uwb))
    C = np.array(sim.config.mounting)
    assert flt.ekf is not None
    np.testing.assert_allclose(flt.ekf.b_g, C @ sim.gyro_bias_rps, atol=0.002)


# -- bad input -------------------------------------------------------------------------
def test_bad_input_is_counted_never_in_the_state(sim: Simulation) -> None:
    frames = list(merge(sim.imu, sim.uwb))
    bad: list[ImuSample | UwbRanges] = []
    for k, f in enumerate(frames):
        bad.append(f)
        if isinstance(f, ImuSample) and k % 97 == 0:
            bad.append(dataclasses.replace(f, acc_mps2=(math.nan, 0.0, 9.8)))
            bad.append(dataclasses.replace(f, t_ns=f.t_ns - 3_000_000))  # out of order
        if isinstance(f, UwbRanges) and k % 41 == 0:
            bad.append(dataclasses.replace(f, ranges=(
                AnchorRange(0, math.inf), AnchorRange(1, -3.0), AnchorRange(2, 1e7),
                AnchorRange(99, 5.0))))
    poses, _, flt = run_filter(config_for(sim), iter(bad))
    clean, _, _ = run_filter(config_for(sim), merge(sim.imu, sim.uwb))
    assert flt.counters["imu_not_finite"] > 0 and flt.counters["imu_out_of_order"] > 0
    rej = flt.gating.rejections
    assert rej["not_finite"] > 0 and rej["negative"] > 0 and rej["too_long"] > 0
    assert rej["unknown_anchor"] > 0
    assert all(map(math.isfinite, poses[-1].position_m))
    assert np.allclose(poses[-1].position_m, clean[-1].position_m, atol=0.05)


def test_imu_gap_is_survived(sim: Simulation) -> None:
    gap = (sim.truth_t_ns[0] + 8 * 10**9, sim.truth_t_ns[0] + 10 * 10**9)
    imu = [s for s in sim.imu if not gap[0] <= s.t_ns < gap[1]]
    poses, _, flt = run_filter(config_for(sim), merge(imu, sim.uwb))
    assert flt.counters["imu_gaps"] == 1
    assert score_poses(poses, sim.truth_t_ns, sim.truth_p_m, skip_s=12).rmse_xy_m < 0.1


def _errors_xy(poses: list[Pose], sim: Simulation) -> tuple[Array, Array]:
    """Seconds into the run and the horizontal error of each pose."""
    t = np.array([p.t_ns for p in poses])
    err = np.linalg.norm(position_errors(poses, sim)[:, :2], axis=1)
    return (t - sim.truth_t_ns[0]) / 1e9, err


def test_persistent_nlos_does_not_pull_the_state_away(sim: Simulation) -> None:
    """Every range 3 m long for 3 s: rejected, the state coasts on the IMU (no jump to the
    NLOS-biased fix), the health says so, and the ranges are taken again afterwards."""
    t0 = sim.truth_t_ns[0]
    def shifted(e: UwbRanges) -> UwbRanges:
        if t0 + 9e9 <= e.t_ns < t0 + 12e9:
            return dataclasses.replace(e, ranges=tuple(
                dataclasses.replace(r, range_m=r.range_m + 3.0) for r in e.ranges))
        return e
    uwb = [shifted(e) for e in sim.uwb]
    poses, _, flt = run_filter(config_for(sim), merge(sim.imu, uwb))
    s, err = _errors_xy(poses, sim)
    # bounded during the fault, not only after: 3 s on the IMU alone (a jump to the biased
    # fix would be metres)
    assert err[(s >= 9) & (s < 16)].max() < 0.4
    assert err[s >= 16].max() < 0.15
    assert flt.counters["position_resets"] == 0 and flt.counters["restarts"] == 0
    late = [p.health for p, t in zip(poses, s, strict=True) if 10.5 <= t < 12]
    assert late and not any(h.healthy for h in late)
    assert {h.phase for h in late} <= {Phase.COASTING, Phase.DEGRADED}


def _run_tampered(sim: Simulation, at_s: float, tamper: Callable[[Eskf], None]
                  ) -> tuple[list[Pose], Filter]:
    """The filter over ``sim``, its state tampered with once, before the first UWB update
    at or after ``at_s``; every pose must be finite."""
    flt = Filter(config_for(sim))
    poses: list[Pose] = []
    done = False
    for frame in merge(sim.imu, sim.uwb):
        if isinstance(frame, ImuSample):
            flt.predict(frame)
            continue
        if not done and frame.t_ns >= sim.truth_t_ns[0] + at_s * 1e9 and flt.ekf is not None:
            tamper(flt.ekf)
            done = True
        flt.update(frame)
        pose = flt.pose()
        if pose is not None:
            assert all(map(math.isfinite, pose.position_m + pose.velocity_mps + pose.covariance))
            poses.append(pose)
    return poses, flt


def test_a_wrong_state_is_moved_to_a_consistent_fix(sim: Simulation) -> None:
    """The state is knocked 4 m off and made overconfident (a divergence): the ranges are
    consistent with each other, so after a while the position is reset to their fix."""
    def knock(ekf: Eskf) -> None:  # through the state's own repairs: the C core's is read-only
        ekf.move_to(np.add(ekf.p, (4.0, 0.0, 0.0)), ekf.v)
        P = ekf.P.copy()
        P[:3, :3] *= 1e-4
        ekf.set_covariance(P)

    poses, flt = _run_tampered(sim, 10.0, knock)
    s, err = _errors_xy(poses, sim)
    assert flt.counters["position_resets"] >= 1
    assert flt.health().last_reset_jump_m is not None
    assert err[s >= 15].max() < 0.3
    off = [p.health for p, e in zip(poses, err, strict=True) if e > 1.0]
    assert off and not any(h.healthy for h in off)


def test_non_finite_state_restarts_and_no_pose_carries_it(sim: Simulation) -> None:
    def poison(ekf: Eskf) -> None:
        ekf.move_to(ekf.p, (ekf.v[0], math.inf, ekf.v[2]))

    poses, flt = _run_tampered(sim, 8.0, poison)
    assert flt.counters["restart_state_not_finite"] == 1
    s, err = _errors_xy(poses, sim)
    assert err[s >= 12].max() < 0.5 and poses[-1].health.resets == 1


def test_non_finite_covariance_is_recovered_once(sim: Simulation) -> None:
    """One NaN in P: caught at once, P restored from the last finite one (the state never
    saw the NaN), said in the health, and the filter goes on."""
    def poison(ekf: Eskf) -> None:
        P = ekf.P.copy()
        P[4, 4] = math.nan
        ekf.set_covariance(P)

    poses, flt = _run_tampered(sim, 8.0, poison)
    assert flt.counters["covariance_restored"] == 1 and flt.counters["restarts"] == 0
    s, err = _errors_xy(poses, sim)
    assert err[s >= 8].max() < 0.3
    assert poses[-1].health.resets == 1


def test_same_frames_same_poses_bit_for_bit(sim: Simulation) -> None:
    a, _, _ = run_filter(config_for(sim), merge(sim.imu, sim.uwb))
    b, _, _ = run_filter(config_for(sim), merge(sim.imu, sim.uwb))
    assert a == b


def test_truth_spikes_are_found() -> None:
    t = np.arange(10, dtype=np.int64) * 100_000_000
    p = np.column_stack([np.arange(10) * 0.05, np.zeros(10), np.zeros(10)])
    p[5, 2] = 2.0
    assert np.flatnonzero(truth_spikes(t, p)).tolist() == [5]


def test_filter_rejects_an_improper_mounting_rotation() -> None:
    with pytest.raises(ValueError, match="mounting_rotation"):
        Filter(FilterConfig(mounting_rotation=((1, 0, 0), (0, 1, 0), (0, 0, -1))))  # type: ignore[arg-type]


@pytest.mark.parametrize("p", [0.9, 0.99, 0.997, 0.9999])
@pytest.mark.parametrize("dof", [1, 3])
def test_chi2_gate_quantiles_match_scipy(p: float, dof: int) -> None:
    assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-12)


# -- the smoother -----------------------------------------------------------------------
def test_smoother_beats_the_filter_and_stays_consistent(sim: Simulation) -> None:
    cfg = config_for(sim)
    frames = list(merge(sim.imu, sim.uwb))
    poses, _, _ = run_filter(cfg, frames)
    filtered = score_poses(poses, sim.truth_t_ns, sim.truth_p_m, skip_s=8)
    t, p, cov = run_smoother(cfg, frames)
    smoothed = score(t, p, sim.truth_t_ns, sim.truth_p_m, cov, skip_s=8)
    assert smoothed.rmse_xy_m < 0.8 * filtered.rmse_xy_m
    assert smoothed.rmse_3d_m < filtered.rmse_3d_m
    assert 0.1 < smoothed.nees_mean < 3  # not overconfident (a short run: conservative)
    # the filter's epochs (but the one it started at), and never less certain than the filter
    assert list(t) == [q.t_ns for q in poses[1:]]
    sigma_f = np.array([np.trace(np.array(q.covariance).reshape(6, 6)[:3, :3])
                        for q in poses[1:]])
    assert np.all(np.trace(cov, axis1=1, axis2=2) <= sigma_f * (1 + 1e-9))


def test_smoother_does_not_reach_across_a_break(sim: Simulation) -> None:
    """Before the heading is aligned and at an IMU gap the state is changed outside the
    Kalman model: those epochs start a new stretch and keep their filtered estimate."""
    imu = [f for f in sim.imu if not 12e9 <= f.t_ns - sim.imu[0].t_ns < 13e9]
    flt = Filter(config_for(sim), record=True)
    for frame in merge(imu, sim.uwb):
        flt.predict(frame) if isinstance(frame, ImuSample) else flt.update(frame)
    assert flt.records is not None and flt.counters["imu_gaps"] == 1
    breaks = [k for k, r in enumerate(flt.records) if r.Phi is None]
    assert breaks[0] == 0 and len(breaks) > 1
    gap = [r.Phi is None for r in flt.records if 12e9 <= r.t_ns - sim.imu[0].t_ns < 13.5e9]
    assert any(gap)  # the gap's epochs are breaks
    smoothed = smooth(flt.records)
    changed = [not np.array_equal(x.p, r.post.p) for (_, x, _), r in zip(
        smoothed, flt.records, strict=True)]
    for k in range(len(flt.records) - 1):
        if flt.records[k + 1].Phi is None:  # no successor to learn from: filtered estimate
            assert not changed[k]
    assert sum(changed) > len(changed) / 2


def test_considered_states_are_not_corrected_and_keep_a_joseph_covariance() -> None:
    ekf = random_eskf(8)
    rng = np.random.default_rng(9)
    h, r = rng.normal(size=N_CORE + 2), 0.02
    P = ekf.P.copy()
    b_g = list(ekf.b_g)
    K = P @ h / (h @ P @ h + r)
    K[9:12] = 0.0  # the gyro biases, considered
    IKH = np.eye(len(h)) - np.outer(K, h)
    ekf.sequential_update(h[None, :], np.array([0.3]), np.array([r]), lambda i, nu, s: 1.0,
                          considered=slice(9, 12))
    assert ekf.b_g == b_g
    keep = np.r_[0:6, 9:N_CORE + 2]  # the attitude rows also take the reset after injection
    expected = IKH @ P @ IKH.T + r * np.outer(K, K)
    np.testing.assert_allclose(ekf.P[np.ix_(keep, keep)], expected[np.ix_(keep, keep)],
                               atol=1e-9)


def test_gauss_markov_states_decay_to_their_stationary_sigma() -> None:
    P0 = np.eye(N_CORE + 1) * 1e-6
    ekf = Eskf((0, 0, 0), (0, 0, 0), (1.0, 0.0, 0.0, 0.0), P0, ImuNoise(), n_range_bias=1,
               aux_tau_s=np.array([1.0]), aux_sigma=np.array([0.07]), b_r=(0.5,))
    for _ in range(50):  # 5 s in 0.1 s intervals
        for _ in range(20):
            ekf.predict((0.0, 0.0, 9.80665), (0.0, 0.0, 0.0), 0.005)
        ekf.propagate()
    assert abs(ekf.b_r[0]) < 0.5 * math.exp(-4.5)
    assert math.sqrt(ekf.P[N_CORE, N_CORE]) == pytest.approx(0.07, rel=0.01)


def test_a_tilt_against_gravity_at_rest_is_levelled_anew(sim: Simulation) -> None:
    """The attitude knocked 20° in roll and made confident, while at rest: gravity says
    otherwise, the tilt is levelled anew and the heading kept. (On the reference: no
    operation of the C core's state sets an attitude; the policy is the same Python.)"""
    def tilt(ekf: Eskf) -> None:
        ekf.q = quat_mul(np.array(ekf.q), quat_from_euler(math.radians(20), 0.0, 0.0)).tolist()
        ekf.P[TH_, TH_] *= 1e-4

    with native.pure_python():
        poses, flt = _run_tampered(sim, 2.0, tilt)
    assert flt.counters["restart_attitude_against_gravity"] == 1
    final = poses[-1]
    roll, pitch, _ = euler_from_quat(np.array([final.orientation_xyzw[3],
                                               *final.orientation_xyzw[:3]]))
    assert abs(roll) < math.radians(2) and abs(pitch) < math.radians(2)
    s, err = _errors_xy(poses, sim)
    assert err[s >= 12].max() < 0.2
