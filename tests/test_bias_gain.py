"""The ranges' geometry the protection levels' bias term takes (checks.bias_gain) and the
filter's own levels (policy.health): on synthetic snapshots, and in the filter on simulated
runs with the installation right and wrong."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from truth import position_errors

from uwbd.config import parse
from uwbd.fusion.checks.bias_gain import BiasGain, snapshot_gain
from uwbd.fusion.core import native
from uwbd.fusion.policy.health import HealthMonitor
from uwbd.fusion.settings import HealthLimits
from uwbd.fusion.types import Pose
from uwbd.tools.evaluate import merge, run_filter
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import SimConfig, simulate

NS = 1_000_000_000
EPOCH_NS = 1_700_000_000 * NS


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def test_the_window_s_gain_is_what_a_bias_on_every_range_does_to_a_fix() -> None:
    """Six anchors at 10 Hz: the window's gain is the mean over its snapshots of Σ_j |S_ij|
    (horizontal as the norm of x and y), the most a bias of 1 m on every range moves a
    least-squares fix; innovations play no part; a restart forgets."""
    rng = np.random.default_rng(4)
    window = BiasGain(native.core)
    ids = [0, 1, 2, 3, 4, 5]
    var = np.full(6, 0.1**2)
    u = _directions(rng, 6)
    for k in range(40):  # 4 s of the same geometry
        window.add(EPOCH_NS + k * NS // 10, ids, u, var)
    gain = snapshot_gain([(1.0 / 0.1**2, *map(float, uk)) for uk in u])
    assert gain is not None
    assert window.bias_gain == pytest.approx((math.hypot(gain[0], gain[1]), gain[2]))
    U = u * np.sqrt(1 / var)[:, None]  # and that is the fix's response to a common bias
    S = np.linalg.inv(U.T @ U) @ (u.T / var)
    np.testing.assert_allclose(gain, np.abs(S).sum(axis=1), rtol=1e-6)
    window.clear()
    assert window.bias_gain == (0.0, 0.0)


def test_single_ranges_make_snapshots_of_each_anchors_latest() -> None:
    """One range a message, 8 anchors in turn at 160 Hz: the window gathers each anchor's
    latest into snapshots, and its gain is the one of those 8 directions."""
    rng = np.random.default_rng(5)
    window = BiasGain(native.core)
    u = _directions(rng, 8)
    for k in range(160 * 4):
        a = k % 8
        window.add(EPOCH_NS + k * NS // 160, [a], u[a:a + 1], np.array([0.1**2]))
    gain = snapshot_gain([(1.0 / 0.1**2, *map(float, uk)) for uk in u])
    assert gain is not None
    assert window.bias_gain == pytest.approx((math.hypot(gain[0], gain[1]), gain[2]),
                                             rel=1e-6)


def _run(sim_cfg: SimConfig, move_anchor: tuple[float, float, float] | None
         ) -> tuple[list[Pose], np.ndarray]:
    """The seed layout's run with the datasheet config (anchor 3 moved in it), the poses
    after 8 s and their 3-D errors."""
    sim = simulate(sim_cfg)
    cfg = parse(simulation_toml(sim)).filter_config()
    if move_anchor is not None:
        anchors = dict(cfg.anchors_m)
        anchors[3] = tuple(a + d for a, d in zip(anchors[3], move_anchor, strict=True))  # type: ignore[assignment]
        cfg = dataclasses.replace(cfg, anchors_m=anchors)
    poses, _, _ = run_filter(cfg, merge(sim.imu, sim.uwb))  # (a pose after every message)
    poses = [p for p in poses if p.t_ns > sim.truth_t_ns[0] + 8 * NS]
    return poses, position_errors(poses, sim)


def test_protection_levels_bound_the_error_of_a_right_installation() -> None:
    """Every pose carries both levels (in its JSON too); they bound the true error on
    every pose of a fault-free run. (Over each anchor's fault, on this layout of six
    anchors and 0.1 m ranges, they are about 0.6 m and 1.4 m: measured.)"""
    poses, err = _run(SimConfig(seed=1), None)
    hpl = np.array([p.health.horizontal_protection_m for p in poses], dtype=float)
    vpl = np.array([p.health.vertical_protection_m for p in poses], dtype=float)
    assert np.isfinite(hpl).all() and np.isfinite(vpl).all()
    assert (np.hypot(err[:, 0], err[:, 1]) <= hpl).all()
    assert (np.abs(err[:, 2]) <= vpl).all()
    assert np.median(hpl) < 0.75 and np.median(vpl) < 1.6
    said = poses[-1].health.as_dict()
    assert said["horizontal_protection_m"] == pytest.approx(hpl[-1], abs=1e-4)
    assert said["vertical_protection_m"] == pytest.approx(vpl[-1], abs=1e-4)


def test_an_anchor_surveyed_off_is_left_out_and_no_pose_is_healthy_far_off() -> None:
    """Anchor 3 1 m off sideways in the config: it is left out (a note: the rest agree) on
    most poses, and no pose is healthy while more than 0.5 m off."""
    poses, err = _run(SimConfig(seed=1), (1.0, 0.0, 0.0))
    left_out = [p for p in poses if "anchor_excluded" in p.health.notes]
    assert len(left_out) > len(poses) // 2, (len(left_out), len(poses))
    off = np.linalg.norm(err, axis=1) > 0.5
    assert not any(p.health.healthy for p, o in zip(poses, off, strict=True) if o)


def test_the_filter_s_own_levels_are_its_sigma_and_the_bias_term() -> None:
    """K σ + g b: the Rayleigh and two-sided normal quantiles at the risk, and what a bias
    of the bound on every range makes of the ranges' geometry; over an alert limit:
    uncertain."""
    monitor = HealthMonitor(HealthLimits(integrity_risk=1e-3, horizontal_alert_limit_m=1.0,
                                         vertical_alert_limit_m=1.5))
    monitor.uwb_outcome(EPOCH_NS, True, 1.0)
    h = monitor.assess(EPOCH_NS, True, True, 0.2, True, 0.1, False, 0.1)
    assert h.horizontal_protection_m == pytest.approx(math.sqrt(-2 * math.log(1e-3)) * 0.1)
    assert h.vertical_protection_m == pytest.approx(3.2905 * 0.1, rel=1e-4)
    monitor.bias_gain = (1.0, 2.0)  # m per m of range bias, at the default 0.05 m bound
    h = monitor.assess(EPOCH_NS, True, True, 0.2, True, 0.1, False, 0.1)
    assert h.horizontal_protection_m == pytest.approx(3.7169 * 0.1 + 0.05, rel=1e-4)
    assert h.vertical_protection_m == pytest.approx(3.2905 * 0.1 + 0.1, rel=1e-4)
    assert "position_uncertain" not in h.faults
    monitor.bias_gain = (20.0, 2.0)
    assert "position_uncertain" in monitor.assess(EPOCH_NS, True, True, 0.2, True, 0.1,
                                                  False, 0.1).faults
