"""The contract of the C core with its pure-Python reference: :class:`CoreEskf` (the state
the C type ``_core.State`` owns) against :class:`Eskf` (uwbd/fusion/core/eskf.py, written as
docs/ekf.md reads) operation by operation on random states and inputs, the stateless
multilateration and rest moments, and whole filter runs (simulator presets, both real
datasets) pose by pose, within tolerances."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.frames import ImuSample
from uwbd.config import parse
from uwbd.fusion.checks.bias_gain import snapshot_gain
from uwbd.fusion.checks.imu_check import ImuCheck, ImuLimits, new_imu_check
from uwbd.fusion.checks.intrinsics import ImuIntrinsics, body_maps, to_body
from uwbd.fusion.core import lsq, native
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE, TH_, V_
from uwbd.fusion.core.lsq import multilaterate
from uwbd.fusion.core.noise import ImuNoise
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.core.state import CoreEskf, new_eskf
from uwbd.fusion.core.weights import Row, RowPolicy
from uwbd.fusion.filter import Filter
from uwbd.fusion.models.measurements import range_check, range_rows
from uwbd.fusion.policy.rest import ImuWindow
from uwbd.fusion.settings import Z_DOWN, FilterConfig, RestLimits, RobustPolicy
from uwbd.fusion.types import Pose
from uwbd.tools.evaluate import merge, run_filter, run_smoother
from uwbd.tools.importer import INROL_LEVER_ARM_M, INROL_MOUNTING, load_iasl, load_inrol
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.sim_presets import ceiling_room, handheld_async
from uwbd.tools.simulator import SimConfig, simulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_core = pytest.mark.skipif(native.core is None, reason=f"C core: {native.implementation}")
POSITION_TOLERANCE_M = 1e-9


def twin(n_aux: int, seed: int, broken: str | None = None, bank: tuple[int, ...] = ()
         ) -> tuple[CoreEskf, Eskf]:
    """Two filters in the same random state, one on the C core, one on the reference
    (``broken``: that part made not finite; ``bank``: their sub-filters' anchors)."""
    rng = np.random.default_rng(seed)
    n = N_CORE + n_aux
    A = rng.normal(size=(n, n)) * 0.1
    P0 = A @ A.T + 0.01 * np.eye(n)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    p = rng.normal(size=3) * 5
    if broken == "p":
        p[1] = math.inf
    elif broken == "P":
        P0[7, 7] = math.nan
    elif broken == "P_v":  # the velocity block: only the reference's product reads it
        P0[3, 4] = P0[4, 3] = math.inf
    args = (p, rng.normal(size=3), q, P0, ImuNoise(), n_aux)
    kwargs = dict(b_g=rng.normal(size=3) * 1e-3, b_a=rng.normal(size=3) * 0.05,
                  b_r=rng.normal(size=n_aux) * 0.1,
                  aux_tau_s=np.where(np.arange(n_aux) % 2 == 0, np.inf, 3.0),
                  aux_sigma=np.full(n_aux, 0.1), bank=bank,
                  # a member that leaves no anchor out has variances of its own (the lever's)
                  bank_var=np.array([[0.0] * n if a >= 0 else rng.uniform(0, 0.1, size=n)
                                     for a in bank]).reshape(len(bank), n))
    return (CoreEskf(*args, **kwargs, core=native.core),  # type: ignore[arg-type]
            Eskf(*args, **kwargs))  # type: ignore[arg-type]


def nominal(f: Eskf) -> Array:
    return np.concatenate([f.p, f.v, f.q, f.b_g, f.b_a, f.b_r])


def same_state(fast: Eskf, slow: Eskf, rtol: float = 1e-9, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(nominal(fast), nominal(slow), rtol=rtol, atol=atol)
    np.testing.assert_allclose(fast.P, slow.P, rtol=rtol, atol=atol)


def imu_stream(seed: int, count: int) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    rng = np.random.default_rng(seed)
    gravity = np.array([0.0, 0.0, 9.81])
    return [(tuple((rng.normal(size=3) + gravity).tolist()),
             tuple((rng.normal(size=3) * 0.5).tolist())) for _ in range(count)]


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8))
def test_predict_and_propagate_match_the_reference(seed: int, n_aux: int) -> None:
    """The INS step, the covariance over the interval with the Gauss–Markov decays, and
    the epoch's transition and Δv; the second epoch starts from identity again."""
    fast, slow = twin(n_aux, seed)
    for epoch in range(2):
        for k, (acc, gyro) in enumerate(imu_stream(seed + epoch, 60)):
            for f in (fast, slow):
                f.predict(acc, gyro, 0.005)
                if k % 20 == 19:
                    f.propagate()
            # the nominal state to the bit: the same operations, no fused multiply-add
            assert nominal(fast).tolist() == nominal(slow).tolist()
        assert fast.interval_s == slow.interval_s == 0.0
        np.testing.assert_allclose(fast.P, slow.P, rtol=1e-12, atol=1e-15)
        (Phi_fast, dv_fast), (Phi_slow, dv_slow) = fast.take_epoch(), slow.take_epoch()
        np.testing.assert_allclose(Phi_fast, Phi_slow, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(dv_fast, dv_slow, rtol=1e-12, atol=1e-15)


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 4), st.sampled_from(["none", "scale", "band"]))
def test_the_imu_front_step_is_judge_map_predict_propagate(seed: int, n_aux: int,
                                                          intrinsics: str) -> None:
    """ImuFront.step_many on the C State, a sample at a time: ImuCheck's verdict, to_body's
    maps (a mounting, scale and offsets, a gyro dead-band), Eskf.predict, and
    Eskf.propagate once the interval reaches 0.1 s; a rejected sample integrates nothing."""
    rng = np.random.default_rng(seed)
    C = tuple(tuple(r) for r in Z_DOWN)
    intr = {"none": ImuIntrinsics(),
            "scale": ImuIntrinsics(acc_scale=(1.01, 0.99, 1.02), acc_offset_mps2=(0.1, -0.2, 0.05),
                                   gyro_offset_rps=(0.01, 0.0, -0.02)),
            "band": ImuIntrinsics(gyro_offset_rps=(0.01, 0.0, -0.02),
                                  gyro_deadband_rps=0.3)}[intrinsics]
    def rotate(v: tuple[float, ...]) -> tuple[float, ...]:  # as ImuPropagation.to_body
        return tuple(r[0] * v[0] + r[1] * v[1] + r[2] * v[2] for r in C)

    acc_map, gyro_map = to_body(C, intr, rotate)
    front = new_imu_check(ImuLimits(), body_maps(C, intr), native.core)
    check = ImuCheck(ImuLimits())
    fast, slow = twin(n_aux, seed)
    stream = imu_stream(seed, 80)
    stream[30] = ((math.nan, 0.0, 9.8), stream[30][1])
    stream[50] = ((0.0, 0.0, 9.8 + 150.0), stream[50][1])
    for k, (acc, gyro) in enumerate(stream):
        t_ns = (k + 1) * 10_000_000
        dt_ns = int(rng.integers(4_000_000, 6_000_000))  # since the state's time
        rows, judged = front.step_many(fast.core_state, [(t_ns, acc, gyro)], t_ns - dt_ns,
                                       t_ns - dt_ns, 0.25, 0.1)
        reason = check.judge(t_ns, acc, gyro)
        if reason:
            assert judged == reason and rows == []
        else:
            body = (acc_map(acc), gyro_map(gyro))
            assert judged is None and rows == [(t_ns, *body[0], *body[1])]
            slow.predict(*body, dt_ns / 1e9)
            if slow.interval_s >= 0.1:
                slow.propagate()
        # the same sums in another order may round 1 ulp apart (seed 151: 1.7e-18 in a bias)
        np.testing.assert_allclose(nominal(fast), nominal(slow), rtol=1e-13, atol=1e-16)
        assert fast.interval_s == slow.interval_s
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-12, atol=1e-15)


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(2, 40), st.sampled_from(["none", "reject", "gap",
                                                                  "order"]))
def test_the_imu_fronts_step_over_a_read_is_step_on_each_sample(seed: int, count: int,
                                                                 odd: str) -> None:
    """ImuFront.step_many over a read's samples: the same rows, screen and state, bit for
    bit, as over each sample alone, up to the first sample that is not the common one
    (rejected: judged, its reason said; a gap or out of order: not judged, no reason)."""
    rng = np.random.default_rng(seed)
    C = tuple(tuple(r) for r in Z_DOWN)
    maps = body_maps(C, ImuIntrinsics(gyro_offset_rps=(0.01, 0.0, -0.02)))
    fronts = (new_imu_check(ImuLimits(), maps, native.core),
              new_imu_check(ImuLimits(), maps, native.core))
    (fast, _), (slow, _) = twin(2, seed), twin(2, seed)
    stream = imu_stream(seed, count)
    times = [1_000_000_000 + 5_000_000 * (k + 1) for k in range(count)]
    at = int(rng.integers(1, count))
    if odd == "reject":
        stream[at] = ((math.nan, 0.0, 9.8), stream[at][1])
    elif odd == "gap":
        times[at:] = [t + 400_000_000 for t in times[at:]]
    elif odd == "order":
        times[at] = times[at - 1]
    samples = list(zip(times, *zip(*stream, strict=True), strict=True))
    rows, reason = fronts[0].step_many(fast.core_state, samples, 1_000_000_000,
                                       1_000_000_000, 0.25, 0.1)
    want, why, last = [], None, 1_000_000_000
    for t_ns, acc, gyro in samples:
        if t_ns <= last or (t_ns - last) / 1e9 > 0.25:
            break
        one, judged = fronts[1].step_many(slow.core_state, [(t_ns, acc, gyro)], last, last,
                                          0.25, 0.1)
        if not one:
            why = judged
            break
        want += one
        last = t_ns
    assert rows == want and reason == why
    assert (len(rows) == count) == (odd == "none")
    assert np.array_equal(nominal(fast), nominal(slow)) and np.array_equal(fast.P, slow.P)
    assert fronts[0].last_good == fronts[1].last_good


def test_a_filter_fed_whole_reads_gives_the_poses_of_one_sample_at_a_time() -> None:
    """Filter.predict_many (the pipeline's call per read) against predict per sample, with
    an IMU burst and a gap in the run: the same poses, bit for bit."""
    sim = simulate(SimConfig(seed=3, segments=((8.0, 0.0, 0.0, 0.0), (10.0, 0.6, 0.1, 0.0))))
    imu = list(sim.imu)
    for k in range(900, 905):  # bursts the screen rejects: not finite, and jumps
        imu[k] = dataclasses.replace(imu[k], acc_mps2=(math.nan, 0.0, 9.8))
    for k in range(1201, 1206):  # (the screen takes a jump as real after three)
        imu[k] = dataclasses.replace(imu[k], acc_mps2=(100.0, 0.0, 9.8))
    del imu[1500:1560]  # a 0.3 s gap
    cfg = parse(simulation_toml(sim)).filter_config()
    one, whole = Filter(cfg), Filter(cfg)
    poses = {}
    for flt, size in ((one, 1), (whole, 4)):
        out: list[Pose] = []
        read: list[ImuSample] = []  # up to `size` samples, none across a UWB epoch
        for f in merge(imu, sim.uwb):
            if isinstance(f, ImuSample):
                read.append(f)
                if len(read) == size:
                    flt.predict_many(read)
                    read = []
                continue
            if read:
                flt.predict_many(read)
                read = []
            flt.update(f)
            pose = flt.pose()
            if pose is not None:
                out.append(pose)
        poses[flt is one] = out
    assert len(poses[True]) > 50 and poses[True] == poses[False]
    assert whole.counters == one.counters


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.integers(1, 12),
       st.sampled_from([None, slice(6, 12), slice(6, 15)]))
def test_sequential_update_matches_the_reference(seed: int, n_aux: int, m: int,
                                                 considered: slice | None) -> None:
    fast, slow = twin(n_aux, seed)
    rng = np.random.default_rng(seed + 1)
    H = rng.normal(size=(m, fast.n))
    y = rng.normal(size=m)
    R = rng.uniform(0.001, 0.1, size=m)
    R[rng.random(m) < 0.1] = -1.0  # a variance below zero: the row is numerical, skipped
    calls: list[list[tuple[int, float, float]]] = [[], []]

    def decider(log: list[tuple[int, float, float]]) -> Callable[[int, float, float], float]:
        def decide(i: int, nu: float, s: float) -> float:
            log.append((i, nu, s))
            return (0.0, 0.3, 1.0)[i % 3]  # rejected, de-weighted, fused
        return decide

    rows_fast = fast.sequential_update(H, y, R, decider(calls[0]), considered)
    rows_slow = slow.sequential_update(H, y, R, decider(calls[1]), considered)
    assert all(isinstance(r, Row) for r in rows_fast)
    assert [r.numerical for r in rows_fast] == [r.numerical for r in rows_slow]
    # (S after a dozen rows on a random P: a few 1e-9 of cancellation, summed in another order)
    np.testing.assert_allclose([r[:3] for r in rows_fast], [r[:3] for r in rows_slow],
                               rtol=1e-8, atol=1e-12)
    assert [c[0] for c in calls[0]] == [c[0] for c in calls[1]]
    same_state(fast, slow)
    fused = [r.weight > 0 and not r.numerical for r in rows_slow]
    if any(fused):
        np.testing.assert_allclose(fast.last_dx, slow.last_dx, rtol=1e-9, atol=1e-12)


class _ReadNotCalled(RowPolicy):
    """A policy the C core must read, never call back."""

    def __call__(self, i: int, nu: float, s: float) -> float:
        raise AssertionError("the C core called the policy back")


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.text("rpzn", min_size=1, max_size=10),
       st.booleans(), st.booleans(), st.floats(0.5, 20.0))
def test_the_row_policy_in_c_matches_its_reference(seed: int, n_aux: int, kinds: str,
                                                   robust: bool, fix_ok: bool,
                                                   scale: float) -> None:
    """Ranges gated and de-weighted, position axes by their fix, pseudo-measurements gated:
    the C core reads the policy tuple itself; called back on the same rows it gives the same
    weights to the bit, and the pure-Python update the same state (numpy's sums round
    differently in the last bits)."""
    fast, slow = twin(n_aux, seed)
    rng = np.random.default_rng(seed + 2)
    m = len(kinds)
    H = rng.normal(size=(m, fast.n))
    y = rng.normal(size=m) * scale  # from well inside the gate to far outside it
    R = rng.uniform(0.001, 0.1, size=m)
    policy = RobustPolicy(enabled=robust).rows(kinds.encode(), 6.63, fix_ok)
    twin_fast, _ = twin(n_aux, seed)  # the same rows, the policy called back from C
    called = twin_fast.sequential_update(H, y, R, policy.__call__, None)
    rows_fast = fast.sequential_update(H, y, R, _ReadNotCalled(*policy), None)
    assert [r.weight for r in rows_fast] == [r.weight for r in called]  # to the bit
    assert nominal(fast).tolist() == nominal(twin_fast).tolist()
    rows_slow = slow.sequential_update(H, y, R, policy, None)
    np.testing.assert_allclose([r.weight for r in rows_fast], [r.weight for r in rows_slow],
                               rtol=1e-9)
    same_state(fast, slow)


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.floats(-3.2, 3.2))
def test_heading_turns_match_the_reference(seed: int, n_aux: int, dpsi: float) -> None:
    fast, slow = twin(n_aux, seed)
    for f in (fast, slow):
        f.rotate_heading(dpsi, 0.05)
    same_state(fast, slow, atol=1e-14)
    assert fast.yaw_sigma_rad() == pytest.approx(0.05, rel=1e-9)


@needs_core
@pytest.mark.parametrize("considered", [slice(15, None), slice(-6, None), slice(6, 12)])
def test_odd_weights_and_considered_slices_match_the_reference(considered: slice) -> None:
    """A NaN weight is no fusion (in both), and any slice of states can be considered."""
    fast, slow = twin(6, 3)
    H = np.random.default_rng(3).normal(size=(4, fast.n))
    weights = iter([math.nan, 1.0, 0.5, math.nan] * 2)

    def decide(i: int, nu: float, s: float) -> float:
        return next(weights)

    for f in (fast, slow):
        f.sequential_update(H, np.ones(4), np.full(4, 0.01), decide, considered)
    assert np.isfinite(nominal(fast)).all()
    same_state(fast, slow)


@needs_core
def test_non_finite_ranges_give_no_fix_in_either() -> None:
    anchors = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 3], [5, 5, 4]])
    ranges = np.array([7.0, 7.0, 7.0, math.nan, 7.0])
    fast = multilaterate(anchors, ranges, 0.1, core=native.core)
    slow = multilaterate(anchors, ranges, 0.1, core=None)
    assert fast is None and slow is None


@needs_core
def test_an_error_in_decide_leaves_the_state_alone() -> None:
    fast, _ = twin(4, 7)
    P, x = fast.P.copy(), nominal(fast)

    def decide(i: int, nu: float, s: float) -> float:
        if i == 2:
            raise ValueError("boom")
        return 1.0

    with pytest.raises(ValueError, match="boom"):
        fast.sequential_update(np.eye(3, fast.n), np.ones(3), np.full(3, 0.01), decide)
    assert np.array_equal(fast.P, P) and np.array_equal(nominal(fast), x)


@needs_core
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31), st.integers(3, 9), st.booleans(), st.booleans())
def test_multilateration_matches_the_reference(seed: int, k: int, height_held: bool,
                                              outlier: bool) -> None:
    rng = np.random.default_rng(seed)
    anchors = rng.uniform(-10, 10, size=(k, 3)) * (1.0, 1.0, 0.3)
    tag = rng.uniform(-5, 5, size=3)
    ranges = np.linalg.norm(anchors - tag, axis=1) + rng.normal(0, 0.05, size=k)
    if outlier:
        ranges[0] += 2.0  # NLOS: the outlier test drops it, given enough anchors
    args = dict(x0=None if seed % 2 else tag + 0.5, fixed_z=float(tag[2]) if height_held
                else None)
    fast = multilaterate(anchors, ranges, 0.1, **args,  # type: ignore[arg-type]
                         core=native.core)
    slow = multilaterate(anchors, ranges, 0.1, **args, core=None)  # type: ignore[arg-type]
    assert (fast is None) == (slow is None)
    if fast is not None and slow is not None:
        assert fast.iterations == slow.iterations
        assert np.array_equal(fast.used, slow.used)
        np.testing.assert_allclose(fast.position_m, slow.position_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.covariance, slow.covariance, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(fast.residuals_m, slow.residuals_m, rtol=0, atol=1e-9)


@needs_core
def test_a_tag_in_the_plane_of_most_anchors_gets_its_fix(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A ground robot's tag 0.4 m up among five anchors 0.4-1.2 m up and one at 3.4 m (a
    campaign room's ranges averaged at rest): the squares' curvature in height there is what
    Gauss–Newton leaves out, and its plain steps overshoot the height to and fro (no fix after
    20 steps). Halving a step that raises the squares damps the swing: a fix within 0.3 m
    of the tag, in C and the reference alike."""
    anchors = np.array([[25.175, 17.284, 1.159], [20.691, 20.545, 1.185], [0.1, 1.855, 0.863],
                        [19.517, 0.1, 0.364], [25.175, 4.466, 0.595], [4.790, 20.545, 3.391]])
    ranges = np.array([21.0891, 20.5779, 9.2391, 10.8180, 15.9665, 17.8661])
    fixes = [multilaterate(anchors, ranges, 0.05, x0=np.array([9.3, 3.7, z0]),
                           outlier_sigma=math.inf, core=core)
             for z0 in (-0.6, 0.7, 4.4) for core in (native.core, None)]
    assert all(f is not None and np.linalg.norm(f.position_m - (9.24, 3.39, 0.42)) < 0.3
               for f in fixes), fixes
    for fast, slow in zip(fixes[::2], fixes[1::2], strict=True):  # C, then the reference
        assert fast is not None and slow is not None and fast.iterations == slow.iterations
        np.testing.assert_allclose(fast.position_m, slow.position_m, rtol=0, atol=1e-9)
    monkeypatch.setattr(lsq, "MAX_HALVINGS", 0)
    assert multilaterate(anchors, ranges, 0.05, x0=np.array([9.3, 3.7, -0.6]),
                         outlier_sigma=math.inf, core=native.core) is None


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(1, 8), st.integers(0, 3), st.booleans(),
       st.sampled_from([None, slice(6, 12)]), st.booleans())
def test_a_tight_epoch_in_one_call_matches_rows_then_update(seed: int, k: int, extra: int,
                                                            robust: bool,
                                                            considered: slice | None,
                                                            lever_states: bool) -> None:
    """fuse_ranges (range rows, extra rows, weights, injection, reset in C) against the
    reference: range_rows, the rows stacked, sequential_update in Python; with the lever
    arm's error states too."""
    fast, slow = twin(2 * 8 + 3, seed)
    rng = np.random.default_rng(seed)
    ids = [int(a) for a in rng.choice(8, size=k, replace=False)]
    anchors = rng.uniform(-10, 10, size=(k, 3))
    ranges = np.linalg.norm(anchors - fast.p, axis=1) + rng.normal(size=k) * 0.3
    var = rng.uniform(0.001, 0.1, size=k)
    lever = rng.normal(size=3) * 0.2
    columns = {a: (N_CORE + a, N_CORE + 8 + a) for a in range(8)}
    lever_columns = tuple(range(N_CORE + 16, N_CORE + 19)) if lever_states else ()
    H_extra = rng.normal(size=(extra, fast.n))
    y_extra, R_extra = rng.normal(size=extra) * 0.1, rng.uniform(0.001, 0.1, size=extra)
    kinds = b"r" * k + b"z" * extra
    policy = RobustPolicy(enabled=robust).rows(kinds, 6.63, True)
    rows_fast = fast.fuse_ranges(lever, anchors, ranges, var, tuple(columns[a] for a in ids),
                                 lever_columns, (H_extra, y_extra, R_extra), policy,
                                 considered)
    assert rows_fast is not None and None not in rows_fast
    with native.pure_python():
        reference = range_rows(slow, lever, ids, anchors, ranges, var, columns, lever_columns)
    rows_slow = slow.sequential_update(np.vstack([reference.H, H_extra]),
                                       np.concatenate([reference.y, y_extra]),
                                       np.concatenate([reference.R, R_extra]), policy,
                                       considered)
    np.testing.assert_allclose([r[:3] for r in rows_fast if r is not None],
                               [r[:3] for r in rows_slow], rtol=1e-9, atol=1e-12)
    same_state(fast, slow)


@needs_core
@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31), st.booleans(), st.sampled_from([None, slice(6, 12)]))
def test_the_bank_advances_with_the_main_filter_in_c_as_in_the_reference(
        seed: int, robust: bool, considered: slice | None) -> None:
    """Each sub-filter's offset and covariance through every operation that moves P, C
    against the reference: propagation, a tight epoch (its anchor's rows left out, the main
    filter's weights), rows of no anchor, coasting, the repairs; and a turn of the heading
    turns the bank too, and a move starts it anew."""
    bank = (0, 2, 3, 5, 7, -2)
    fast, slow = twin(2 * 8, seed, bank=bank)
    rng = np.random.default_rng(seed)
    columns = {a: (N_CORE + a, N_CORE + 8 + a) for a in range(8)}

    def same_bank() -> None:
        same_state(fast, slow)
        assert fast.bank == slow.bank == bank
        np.testing.assert_allclose(fast.bank_d, slow.bank_d, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast.bank_P, slow.bank_P, rtol=1e-9, atol=1e-12)

    for _ in range(4):
        for f in (fast, slow):
            for _ in range(5):
                f.predict(np.array([0.1, -0.2, 9.8]), np.array([0.01, 0.02, -0.03]), 0.01)
            f.propagate()
        same_bank()
        k = int(rng.integers(3, 9))
        ids = [int(a) for a in rng.choice(8, size=k, replace=False)]
        anchors = rng.uniform(-10, 10, size=(k, 3))
        ranges = np.linalg.norm(anchors - fast.p, axis=1) + rng.normal(size=k) * 0.3
        var = rng.uniform(0.001, 0.1, size=k)
        H_extra = rng.normal(size=(2, fast.n))
        y_extra, R_extra = rng.normal(size=2) * 0.1, rng.uniform(0.001, 0.1, size=2)
        policy = RobustPolicy(enabled=robust).rows(b"r" * k + b"zz", 6.63, True)
        rows = fast.fuse_ranges(np.zeros(3), anchors, ranges, var,
                                tuple(columns[a] for a in ids), (), (H_extra, y_extra, R_extra),
                                policy, considered, ids)
        with native.pure_python():
            reference = range_rows(slow, np.zeros(3), ids, anchors, ranges, var, columns)
        slow.sequential_update(np.vstack([reference.H, H_extra]),
                               np.concatenate([reference.y, y_extra]),
                               np.concatenate([reference.R, R_extra]), policy, considered,
                               ids)
        same_bank()
        assert rows is not None
        if any(r is not None and r[2] > 0 and a in bank for a, r in zip(ids, rows, strict=False)):
            assert np.abs(fast.bank_d).max() > 0  # a sub-filter left a fused row out
        for f in (fast, slow):  # rows of no anchor (ZUPT, NHC): every sub-filter's
            f.sequential_update(np.eye(3, f.n, 3), np.full(3, 0.01), np.full(3, 1e-4),
                                RobustPolicy().rows(b"zzz", 6.63, True), None, None)
        same_bank()
        for f in (fast, slow):
            f.coast(0.05, 0.5, 0.01, 0.001)
            f.add_variances(np.full(f.n, 1e-4))
            f.widen(slice(3, 6), 1.5)
            f.clamp_covariance(np.full(N_CORE, 0.5), 0.3)
        same_bank()
    # the separation test's numbers, from the C state's memory as from the reference's
    (main_h, main_v, members), (ref_h, ref_v, ref_members) = \
        fast.separation_numbers(), slow.separation_numbers()
    assert len(members) == len(bank)
    np.testing.assert_allclose([main_h, main_v, *np.ravel(members)],
                               [ref_h, ref_v, *np.ravel(ref_members)], rtol=1e-9, atol=1e-12)
    for f in (fast, slow):
        f.rotate_heading(0.3, 0.1)
    same_bank()
    for f in (fast, slow):  # the lever member alone anew; the others keep what they know
        f.restart_member(len(bank) - 1)
        assert not f.bank_d[-1].any() and f.bank_d[:-1].any()
    same_bank()
    R = fast.R
    assert np.abs(fast.bank_d[:, TH_] @ R[2]).max() < 1e-12  # no heading offset left
    assert np.abs(fast.bank_d[:, :3]).max() > 0  # what they know of the position kept
    for f in (fast, slow):
        f.move_to(f.p, f.v)
        assert not np.abs(f.bank_d).any()
        np.testing.assert_array_equal(f.bank_P[:-1], np.repeat(f.P[None], len(bank) - 1, 0))
        np.testing.assert_array_equal(f.bank_P[-1] - f.P, np.diag(np.diag(f.bank_P[-1] - f.P)))
    np.testing.assert_allclose(fast.bank_P, slow.bank_P, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("core", [None, native.core], ids=["reference", "C"])
def test_a_sub_filter_is_the_filter_that_never_saw_its_anchor(core: object) -> None:
    """Linear rows on the position: sub-filter k's state (nominal + offset) and covariance
    are exactly those of a filter fed the same rows without anchor k's."""
    if core is None and native.core is None:
        pytest.skip("the reference alone: nothing to compare against")
    rng = np.random.default_rng(3)
    P0 = np.diag(np.full(N_CORE, 0.5))
    args = (rng.normal(size=3), np.zeros(3), (1.0, 0.0, 0.0, 0.0), P0, ImuNoise(), 0)
    main = new_eskf(core, *args, bank=(4, 6))  # type: ignore[arg-type]
    H = np.zeros((3, N_CORE))
    H[np.arange(3), [0, 1, 2]] = 1.0
    y, R = rng.normal(size=3), np.full(3, 0.04)
    main.sequential_update(H, y, R, lambda i, nu, s: 1.0, None, [4, 5, 6])
    for k, left_out in enumerate((4, 6)):
        keep = [i for i, a in enumerate((4, 5, 6)) if a != left_out]
        alone = new_eskf(core, *args)  # type: ignore[arg-type]
        alone.sequential_update(H[keep], y[keep], R[keep], lambda i, nu, s: 1.0, None)
        np.testing.assert_allclose(np.asarray(main.p) + main.bank_d[k, :3], alone.p,
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(main.bank_P[k], alone.P, rtol=0, atol=1e-12)


@pytest.mark.parametrize("core", [None, native.core], ids=["reference", "C"])
def test_a_sub_filter_with_variances_of_its_own_is_the_filter_that_estimates_them(
        core: object) -> None:
    """The lever member's arithmetic: a state the main filter holds known (variance 0) and
    a sub-filter that adds its own variance on it and leaves no anchor out. On linear
    rows that see that state, the sub-filter is exactly a filter started with that
    variance, the main filter's state is untouched by the rows' share on it, and a move
    starts the sub-filter anew with its variance again."""
    if core is None and native.core is None:
        pytest.skip("the reference alone: nothing to compare against")
    rng = np.random.default_rng(5)
    P0 = np.diag(np.concatenate([np.full(N_CORE, 0.5), [0.0]]))
    own = np.zeros((1, N_CORE + 1))
    own[0, N_CORE] = 0.09
    args = (rng.normal(size=3), np.zeros(3), (1.0, 0.0, 0.0, 0.0))
    main = new_eskf(core, *args, P0, ImuNoise(), 1, bank=(-2,),  # type: ignore[arg-type]
                    bank_var=own)
    H = np.zeros((4, N_CORE + 1))
    H[np.arange(4), [0, 1, 2, 0]] = 1.0
    H[3, N_CORE] = 1.0  # the last row sees the held state too
    y, R = rng.normal(size=4), np.full(4, 0.04)
    main.sequential_update(H, y, R, lambda i, nu, s: 1.0, None, [4, 5, 6, 7])
    assert main.b_r[0] == 0.0 and main.P[N_CORE, N_CORE] == 0.0
    alone = new_eskf(core, *args, P0 + np.diag(own[0]), ImuNoise(), 1)  # type: ignore[arg-type]
    alone.sequential_update(H, y, R, lambda i, nu, s: 1.0, None)
    np.testing.assert_allclose(np.asarray(main.p) + main.bank_d[0, :3], alone.p, rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(main.b_r + main.bank_d[0, N_CORE:], alone.b_r, rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(main.bank_P[0], alone.P, rtol=0, atol=1e-12)
    main.move_to(main.p, main.v)
    np.testing.assert_array_equal(main.bank_P[0], main.P + np.diag(own[0]))
    assert not main.bank_d.any()


@needs_core
def test_a_range_with_its_antenna_on_its_anchor_is_left_out_as_the_reference_drops_it(
        ) -> None:
    """No line to linearise: that range's row is None and the update is the other range's
    alone, as the reference's rows (which drop it) give."""
    fast, slow = twin(0, 5)
    anchors = np.array([fast.p, [5.0, 0.0, 0.0]])  # the first anchor at the antenna
    ranges, var = np.array([0.0, 5.0]), np.full(2, 0.01)
    rows = fast.fuse_ranges(np.zeros(3), anchors, ranges, var, ((), ()), (),
                            (np.zeros((0, fast.n)), np.zeros(0), np.zeros(0)),
                            RobustPolicy().rows(b"rr", 6.63, True), None)
    assert rows is not None and rows[0] is None and rows[1] is not None
    with native.pure_python():
        reference = range_rows(slow, np.zeros(3), [0, 1], anchors, ranges, var, {})
    assert reference.keys == [("range", "1")]
    (want,) = slow.sequential_update(reference.H, reference.y, reference.R,
                                     RobustPolicy().rows(b"r", 6.63, True), None)
    np.testing.assert_allclose(rows[1][:3], want[:3], rtol=1e-9, atol=1e-12)
    same_state(fast, slow)


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(1, 8), st.booleans())
def test_the_checks_innovations_and_single_fault_estimates_match_the_reference(
        seed: int, k: int, with_var: bool) -> None:
    """State.range_check (the anchor test's b̂ = (S⁻¹ν)_j/(S⁻¹)_jj and its weight, the
    snapshot's U and y, in one C call) against range_check's reference; nothing of the
    state changes."""
    fast, slow = twin(2 * 8, seed)
    rng = np.random.default_rng(seed)
    ids = [int(a) for a in rng.choice(8, size=k, replace=False)]
    anchors = rng.uniform(-10, 10, size=(k, 3))
    ranges = np.linalg.norm(anchors - fast.p, axis=1) + rng.normal(size=k) * 0.3
    var = rng.uniform(0.001, 0.1, size=k) if with_var else None
    lever = rng.normal(size=3) * 0.2
    columns = {a: (N_CORE + a, N_CORE + 8 + a) for a in range(8)}
    before = nominal(fast), fast.P.copy()
    got = range_check(fast, lever, ids, anchors, ranges, var, columns)
    want = range_check(slow, lever, ids, anchors, ranges, var, columns)
    assert got is not None and want is not None
    for a, b in zip(got, want, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    assert (got.b is not None) == with_var
    assert np.array_equal(nominal(fast), before[0]) and np.array_equal(fast.P, before[1])


@needs_core
def test_the_checks_leave_an_antenna_on_an_anchor_and_a_singular_s_alone() -> None:
    fast, slow = twin(0, 5)
    for f in (fast, slow):  # the first anchor at the antenna: no line to test
        assert range_check(f, np.zeros(3), [0, 1], np.array([f.p, [5.0, 0.0, 0.0]]),
                           np.array([0.0, 5.0]), np.full(2, 0.01), {}) is None
    anchors = np.array([[5.0, 0.0, 0.0], [5.0, 0.0, 0.0]])  # one line twice, no noise
    for f in (fast, slow):
        f.set_covariance(np.zeros((f.n, f.n)))
        checked = range_check(f, np.zeros(3), [0, 1], anchors + f.p, np.array([5.0, 5.0]),
                              np.zeros(2), {})
        assert checked is not None and checked.b is None and checked.d is None


@needs_core
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31), st.integers(5, 12), st.booleans())
def test_the_snapshot_gain_matches_the_reference(seed: int, k: int, flat: bool) -> None:
    """snapshot_gain (C) against bias_gain.snapshot_gain (five rows at least, as the window
    takes them); a snapshot whose rays all lie in one plane (``flat``) is nearly singular
    and still agrees."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(k, 3))
    if flat:
        u[:, 2] = 0.0
    u /= np.linalg.norm(u, axis=1)[:, None]
    rows = [(float(w), *map(float, uk)) for w, uk in
            zip(rng.uniform(10, 1000, size=k), u, strict=True)]
    got, want = native.core.snapshot_gain(rows), snapshot_gain(rows)  # type: ignore[union-attr]
    assert (got is None) == (want is None)
    if got is not None and want is not None:
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9)


def compare_runs(cfg: FilterConfig, frames: list[object]) -> list[Pose]:
    poses, _, _ = run_filter(cfg, frames)  # type: ignore[arg-type]
    with native.pure_python():
        reference, _, _ = run_filter(cfg, frames)  # type: ignore[arg-type]
    assert len(poses) == len(reference) > 0
    assert [q.t_ns for q in poses] == [q.t_ns for q in reference]
    a = np.array([q.position_m for q in poses])
    b = np.array([q.position_m for q in reference])
    worst = float(np.abs(a - b).max())
    assert worst <= POSITION_TOLERANCE_M, f"positions differ by up to {worst:.3g} m"
    assert [q.status for q in poses] == [q.status for q in reference]
    np.testing.assert_allclose([q.covariance for q in poses],
                               [q.covariance for q in reference], rtol=1e-6, atol=1e-12)
    return poses


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.booleans(),
       st.sampled_from([None, "p", "P", "P_v"]))
def test_the_pose_numbers_match_the_reference(seed: int, n_aux: int, aligned: bool,
                                              broken: str | None) -> None:
    """The pose's numbers: the covariance (yaw unknown while not aligned), σ_xy, the
    state's numbers; None for both when one is not finite. (Whether the heading is known
    is the policy's rule on them: outputs.heading_observable.)"""
    fast, slow = twin(n_aux, seed, broken)
    numbers = fast.pose_numbers(aligned)
    with np.errstate(invalid="ignore"):  # inf × 0 in the reference's product
        reference = slow.pose_numbers(aligned)
    if broken is not None:
        assert numbers is None and reference is None
        return
    assert numbers is not None and reference is not None
    np.testing.assert_allclose(numbers[0], reference[0], rtol=1e-12, atol=1e-15)
    assert math.isclose(numbers[1], reference[1], rel_tol=1e-12)
    np.testing.assert_allclose(np.concatenate(numbers[2:]), np.concatenate(reference[2:]),
                               rtol=0, atol=0)
    if not aligned:
        assert numbers[0][35] == math.pi**2 and numbers[0][5] == numbers[0][30] == 0.0


@needs_core
@pytest.mark.parametrize("preset", ["seed", "handheld", "ceiling"])
def test_filter_runs_match_the_reference(preset: str) -> None:
    sim_cfg = {"seed": SimConfig(seed=2, segments=((4.0, 0.0, 0.0, 0.0),
                                                   (16.0, 1.0, 0.3, 0.0))),
               "handheld": handheld_async(1), "ceiling": ceiling_room(1)}[preset]
    sim = simulate(sim_cfg)
    frames = list(merge(sim.imu, sim.uwb))
    if preset != "seed":
        frames = frames[: len(frames) // 3]  # the start and a first stretch of motion
    compare_runs(parse(simulation_toml(sim)).filter_config(), frames)


@needs_core
@pytest.mark.skipif(not DATA.is_dir(), reason="shared/data not beside the repository")
@pytest.mark.parametrize("name", ["iasl-s1", "inrol-env1"])
def test_real_runs_match_the_reference(name: str) -> None:
    load, mounting, lever, seconds = {
        "iasl-s1": (load_iasl, Z_DOWN, (0.0, 0.0, 0.0), 40.0),
        "inrol-env1": (load_inrol, INROL_MOUNTING, INROL_LEVER_ARM_M, 25.0)}[name]
    ds = load(DATA / name)
    frames = list(merge(ds.imu, ds.uwb))
    end_ns = frames[0].t_ns + int(seconds * 1e9)
    cfg = FilterConfig(anchors_m=ds.anchors_m, mounting_rotation=mounting, lever_arm_m=lever)
    poses = compare_runs(cfg, [f for f in frames if f.t_ns < end_ns])
    assert any(math.isfinite(q.position_m[0]) for q in poses)


def test_the_c_core_is_built() -> None:
    """The install builds the C core (gcc and the Python headers are all it needs); a
    missing one would otherwise only skip the comparisons above. To test a pure-Python
    install on purpose, set UWBD_PURE_PYTHON=1."""
    if os.environ.get(native.PURE_PYTHON_ENV, "") not in ("", "0"):
        pytest.skip("UWBD_PURE_PYTHON is set: the pure-Python install is under test")
    assert native.core is not None, (
        f"{native.implementation}: install gcc and the Python headers (python3-dev) and "
        "reinstall, or set UWBD_PURE_PYTHON=1 to test without the C core")


@needs_core
def test_the_environment_variable_forces_pure_python() -> None:
    code = "from uwbd.fusion.core import native; print(native.core is None, native.implementation)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, native.PURE_PYTHON_ENV: "1"}).stdout
    assert out.startswith("True pure Python (UWBD_PURE_PYTHON is set)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={k: v for k, v in os.environ.items()
                                          if k != native.PURE_PYTHON_ENV}).stdout
    assert out.startswith("False C core")


@needs_core
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 400), st.floats(0.01, 3.0))
def test_the_rest_tests_moments_match_numpys(seed: int, count: int, span_s: float) -> None:
    """The rest test on a window of rows: the C core's moments and numpy's, the same bits,
    so the same verdict; at rest and moving, jittered times, Unix-epoch ns."""
    rng = np.random.default_rng(seed)
    window = ImuWindow(4.0, RestLimits(), core=native.core)
    t = 1_700_000_000_000_000_000 + int(rng.integers(0, 10**12))
    still = rng.random() < 0.5
    level = rng.normal(0, 0.01 if still else 3.0, 6) + np.array([0, 0, 9.81, 0, 0, 0])
    for _ in range(count):
        t += int(rng.integers(4_000_000, 6_000_000))
        noise = rng.normal(0, 0.01 if still else 0.5, 6)
        window.add(t, tuple((level[:3] + noise[:3]).tolist()),  # type: ignore[arg-type]
                   tuple((level[3:] + noise[3:]).tolist()))  # type: ignore[arg-type]
    fast = native.core.window_moments(window.samples, span_s * 1e9)  # type: ignore[union-attr]
    a = np.array(window.samples).reshape(-1, 7)
    recent = a[int(np.searchsorted(a[:, 0], a[-1, 0] - span_s * 1e9)):, 1:] if count else a
    if len(recent) < 3:
        assert fast is None
    else:
        mean = recent.sum(axis=0) / len(recent)
        dev = recent - mean
        assert fast == (tuple(mean.tolist()),
                        tuple(np.sqrt((dev * dev).sum(axis=0) / len(recent)).tolist()))
    verdict = window.static(span_s)
    reference = ImuWindow(4.0, RestLimits(), core=None)
    for row in window.samples:
        reference.add(int(row[0]), row[1:4], row[4:7])  # type: ignore[arg-type]
    assert reference.static(span_s) == verdict


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.floats(0.001, 3.0))
def test_coasting_matches_the_reference(seed: int, n_aux: int, dt: float) -> None:
    fast, slow = twin(n_aux, seed)
    for f in (fast, slow):
        f.coast(dt, 2.0, 0.3, 0.003)
    same_state(fast, slow)
    (Phi_fast, _), (Phi_slow, _) = fast.take_epoch(), slow.take_epoch()
    np.testing.assert_allclose(Phi_fast, Phi_slow, rtol=1e-12)  # the decays' part


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.floats(0.01, 100.0),
       st.floats(0.5, 3.0))
def test_the_covariance_repairs_match_the_reference(seed: int, n_aux: int, scale: float,
                                                    factor: float) -> None:
    """Clamping (with variances above their limits and one below zero), widening a slice,
    added variances, a restored covariance and a moved position, on both."""
    fast, slow = twin(n_aux, seed)
    rng = np.random.default_rng(seed)
    d = rng.uniform(0, scale, size=fast.n)
    d[0] = -2.0 * (fast.P[0, 0] + 1.0)  # a variance below zero
    for f in (fast, slow):
        f.add_variances(d)
    same_state(fast, slow)
    limit = np.full(N_CORE, 1.5)
    assert fast.clamp_covariance(limit, 1.0) == slow.clamp_covariance(limit, 1.0) is True
    same_state(fast, slow)
    assert np.diag(fast.P).max() <= 1.5**2 * (1 + 1e-12) and np.diag(fast.P).min() > 0
    assert fast.clamp_covariance(limit * 1e3, 1e3) is slow.clamp_covariance(limit * 1e3,
                                                                             1e3) is False
    for f in (fast, slow):
        f.widen(slice(0, V_.stop), factor)
        f.widen(TH_, 1.0 / factor)
    same_state(fast, slow)
    P = rng.normal(size=(fast.n, fast.n))
    for f in (fast, slow):
        f.set_covariance(P @ P.T)
        f.move_to((1.0, 2.0, 3.0), (0.0, -1.0, 0.5))
    same_state(fast, slow, rtol=0, atol=0)


@needs_core
def test_the_c_cores_state_is_read_only_and_seen_without_copies() -> None:
    """Python reads the C type's memory through numpy views (a predict shows at once) and
    can change it only through the operations."""
    fast, _ = twin(2, 11)
    p, P = fast.p, fast.P
    before = p.copy()
    fast.predict((0.0, 0.0, 9.81), (0.0, 0.0, 0.1), 0.01)
    assert fast.p is p and not np.array_equal(p, before)
    for view in (fast.p, fast.v, fast.q, fast.b_g, fast.b_a, fast.b_r, fast.P, fast.last_dx):
        assert not view.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        P[0, 0] = 1.0
    with pytest.raises(TypeError, match="inside its updates"):
        fast.inject(np.zeros(fast.n))


@needs_core
def test_a_state_of_the_wrong_shape_is_refused_with_what_is_wrong() -> None:
    noise = ImuNoise()
    with pytest.raises(ValueError, match="P0 must be 16x16"):
        CoreEskf((0, 0, 0), (0, 0, 0), (1, 0, 0, 0), np.eye(15), noise, 1, core=native.core)
    with pytest.raises(ValueError, match="b_r must hold 2 numbers"):
        CoreEskf((0, 0, 0), (0, 0, 0), (1, 0, 0, 0), np.eye(17), noise, 2, b_r=(0.0,),
                 core=native.core)
    assert native.core is not None
    with pytest.raises(ValueError, match="q: 4 numbers expected"):
        native.core.State((0, 0, 0), (0, 0, 0), (1, 0, 0), (0, 0, 0), (0, 0, 0), (),
                          np.eye(15), [0.0] * 15, (), (), 9.8, (), np.zeros(0))


def test_new_eskf_runs_the_core_it_is_handed_and_a_filter_chooses_once() -> None:
    args = ((0, 0, 0), (0, 0, 0), (1.0, 0.0, 0.0, 0.0), np.eye(N_CORE), ImuNoise())
    assert type(new_eskf(native.core, *args)) is (Eskf if native.core is None else CoreEskf)
    assert type(new_eskf(None, *args)) is Eskf
    with native.pure_python():
        chosen = Filter(FilterConfig())
    assert chosen.core is None  # made in the block: the reference, outside it too
    assert chosen.imu.check.__class__ is ImuCheck and chosen.window._core is None


@needs_core
def test_the_smoother_on_the_c_cores_records_matches_the_reference() -> None:
    """With ``record`` the epoch's Φ is kept (keep_transition) and the smoothed run is the
    reference's."""
    sim = simulate(SimConfig(seed=4, segments=((4.0, 0.0, 0.0, 0.0), (10.0, 1.0, 0.3, 0.0))))
    cfg = parse(simulation_toml(sim)).filter_config()
    frames = list(merge(sim.imu, sim.uwb))
    t_fast, p_fast, P_fast = run_smoother(cfg, frames)
    with native.pure_python():
        t_slow, p_slow, P_slow = run_smoother(cfg, frames)
    assert len(t_fast) > 100 and np.array_equal(t_fast, t_slow)
    np.testing.assert_allclose(p_fast, p_slow, rtol=0, atol=POSITION_TOLERANCE_M)
    np.testing.assert_allclose(P_fast, P_slow, rtol=1e-6, atol=1e-12)
