"""The C core against its pure-Python reference (uwbd/fusion/eskf.py): each kernel on
random states, and whole filter runs (simulator presets, both real datasets) pose by pose."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.frames import ImuSample
from uwbd.config import parse
from uwbd.fusion import native
from uwbd.fusion.eskf import N_CORE, ImuNoise, Row
from uwbd.fusion.eskf import Eskf as _Eskf
from uwbd.fusion.filter import Filter
from uwbd.fusion.lsq import multilaterate
from uwbd.fusion.measurements import range_rows
from uwbd.fusion.outputs import MAX_OBSERVABLE_YAW_SIGMA
from uwbd.fusion.rest import ImuWindow, RestLimits
from uwbd.fusion.robust import AnchorStats, RobustPolicy, RowPolicy
from uwbd.fusion.settings import FilterConfig
from uwbd.fusion.types import FusionReport, Pose
from uwbd.tools.evaluate import merge, run_filter
from uwbd.tools.importer import INROL_LEVER_ARM_M, INROL_MOUNTING, load_iasl, load_inrol
from uwbd.tools.logtools import simulation_toml
from uwbd.tools.simulator import Z_DOWN, SimConfig, ceiling_room, handheld_async, simulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_core = pytest.mark.skipif(native.core is None, reason=f"C core: {native.implementation}")
POSITION_TOLERANCE_M = 1e-9


def twin(n_aux: int, seed: int) -> tuple[_Eskf, _Eskf]:
    """Two filters in the same random state, one on the C core, one on the reference."""
    rng = np.random.default_rng(seed)
    n = N_CORE + n_aux
    A = rng.normal(size=(n, n)) * 0.1
    P0 = A @ A.T + 0.01 * np.eye(n)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    args = (rng.normal(size=3) * 5, rng.normal(size=3), q, P0, ImuNoise(), n_aux,
            rng.normal(size=3) * 1e-3, rng.normal(size=3) * 0.05)
    tau = np.where(np.arange(n_aux) % 2 == 0, np.inf, 3.0) if n_aux else None
    sigma = np.full(n_aux, 0.1) if n_aux else None
    fast = _Eskf(*args, aux_tau_s=tau, aux_sigma=sigma)
    with native.pure_python():
        slow = _Eskf(*args, aux_tau_s=tau, aux_sigma=sigma)
    assert fast._core is not None and slow._core is None
    return fast, slow


def imu_stream(seed: int, count: int) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    rng = np.random.default_rng(seed)
    gravity = np.array([0.0, 0.0, 9.81])
    return [(tuple((rng.normal(size=3) + gravity).tolist()),
             tuple((rng.normal(size=3) * 0.5).tolist())) for _ in range(count)]


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8))
def test_propagation_symmetrised_in_c_is_numpys_to_the_bit(seed: int, n_aux: int) -> None:
    """propagate_core's own symmetrising gives the bits of numpy's ``0.5 * (P + P.T)``."""
    fast, _ = twin(n_aux, seed)
    for acc, gyro in imu_stream(seed, 20):
        fast.predict(acc, gyro, 0.005)
    assert native.core is not None
    args = (fast._Phi_epoch, fast.q, fast._sum_fn, fast._sum_w, fast._T, fast._q_rate)
    P_np, P_c = fast.P.copy(), fast.P.copy()
    native.core.propagate_core(P_np, args[0].copy(), *args[1:])
    native.core.propagate_core(P_c, args[0].copy(), *args[1:], True)
    assert np.array_equal(0.5 * (P_np + P_np.T), P_c)


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(2, 8), st.floats(0.001, 2.0), st.booleans(),
       st.booleans())
def test_the_gauss_markov_step_in_c_is_numpys_to_the_bit(seed: int, n_aux: int, T: float,
                                                       symmetrise: bool, keep: bool) -> None:
    """markov_step (in place, symmetrised if asked) gives the bits of the numpy steps; the
    epoch's decays move only where the transition is kept (for the smoother)."""
    fast, slow = twin(n_aux, seed)
    fast.keep_transition = slow.keep_transition = keep
    slow.P, slow.b_r = fast.P.copy(), np.random.default_rng(seed).normal(size=n_aux)
    fast.b_r = slow.b_r.copy()
    P_c, P_np = fast.P, slow.P
    assert fast._markov_step(P_c, T, symmetrise) is symmetrise
    assert slow._markov_step(P_np, T, symmetrise) is False
    if symmetrise:
        P_np = 0.5 * (P_np + P_np.T)
    assert np.array_equal(P_c, P_np) and np.array_equal(fast.b_r, slow.b_r)
    assert np.array_equal(fast._decay_epoch, slow._decay_epoch)
    assert keep or (fast._decay_epoch == 1.0).all()
    assert len(fast._markov_columns) == n_aux // 2  # (every other state: τ = 3 s)


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8))
def test_predict_and_propagate_match_the_reference(seed: int, n_aux: int) -> None:
    fast, slow = twin(n_aux, seed)
    for k, (acc, gyro) in enumerate(imu_stream(seed, 60)):
        for f in (fast, slow):
            f.predict(acc, gyro, 0.005)
            if k % 20 == 19:
                f.propagate()
        # the nominal state is the same to the bit: the same operations, no fused multiply-add
        assert (fast.p, fast.v, fast.q) == (slow.p, slow.v, slow.q)
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(fast.take_epoch()[0], slow.take_epoch()[0], rtol=1e-12,
                               atol=1e-15)


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
    np.testing.assert_allclose([r[:3] for r in rows_fast], [r[:3] for r in rows_slow],
                               rtol=1e-9, atol=1e-12)
    assert [c[0] for c in calls[0]] == [c[0] for c in calls[1]]
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.p + fast.v + fast.q, slow.p + slow.v + slow.q,
                               rtol=1e-9, atol=1e-12)


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
    policy = RowPolicy.of(kinds.encode(), 6.63, RobustPolicy(enabled=robust), fix_ok)
    twin_fast, _ = twin(n_aux, seed)  # the same rows, the policy called back from C
    called = twin_fast.sequential_update(H, y, R, policy.__call__, None)
    rows_fast = fast.sequential_update(H, y, R, _ReadNotCalled(*policy), None)
    assert [r.weight for r in rows_fast] == [r.weight for r in called]  # to the bit
    assert fast.p == twin_fast.p and fast.q == twin_fast.q
    rows_slow = slow.sequential_update(H, y, R, policy, None)
    np.testing.assert_allclose([r.weight for r in rows_fast], [r.weight for r in rows_slow],
                               rtol=1e-9)
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.p + fast.v + fast.q, slow.p + slow.v + slow.q,
                               rtol=1e-9, atol=1e-12)
    assert fast.b_r.tolist() == pytest.approx(slow.b_r.tolist(), rel=1e-9, abs=1e-12)


@needs_core
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 8), st.floats(-3.2, 3.2))
def test_heading_turns_match_the_reference(seed: int, n_aux: int, dpsi: float) -> None:
    fast, slow = twin(n_aux, seed)
    for f in (fast, slow):
        f.rotate_heading(dpsi, 0.05)
    assert fast.q == slow.q
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-14)


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
    assert all(map(math.isfinite, fast.p + fast.v + fast.q))
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.p + fast.v + fast.q, slow.p + slow.v + slow.q,
                               rtol=1e-9, atol=1e-12)


@needs_core
def test_non_finite_ranges_give_no_fix_in_either() -> None:
    anchors = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 3], [5, 5, 4]])
    ranges = np.array([7.0, 7.0, 7.0, math.nan, 7.0])
    fast = multilaterate(anchors, ranges, 0.1)
    with native.pure_python():
        slow = multilaterate(anchors, ranges, 0.1)
    assert fast is None and slow is None


@needs_core
def test_an_error_in_decide_leaves_the_state_alone() -> None:
    fast, _ = twin(4, 7)
    P, p = fast.P.copy(), list(fast.p)

    def decide(i: int, nu: float, s: float) -> float:
        if i == 2:
            raise ValueError("boom")
        return 1.0

    with pytest.raises(ValueError, match="boom"):
        fast.sequential_update(np.eye(3, fast.n), np.ones(3), np.full(3, 0.01), decide)
    assert np.array_equal(fast.P, P) and fast.p == p


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
    fast = multilaterate(anchors, ranges, 0.1, **args)  # type: ignore[arg-type]
    with native.pure_python():
        slow = multilaterate(anchors, ranges, 0.1, **args)  # type: ignore[arg-type]
    assert (fast is None) == (slow is None)
    if fast is not None and slow is not None:
        assert fast.iterations == slow.iterations
        assert np.array_equal(fast.used, slow.used)
        np.testing.assert_allclose(fast.position_m, slow.position_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.covariance, slow.covariance, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(fast.residuals_m, slow.residuals_m, rtol=0, atol=1e-9)


@needs_core
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(1, 8), st.integers(0, 3), st.booleans(),
       st.sampled_from([None, slice(6, 12)]))
def test_a_tight_epoch_in_one_call_matches_rows_then_update(seed: int, k: int, extra: int,
                                                            robust: bool,
                                                            considered: slice | None) -> None:
    """fuse_ranges (range rows, extra rows, weights, injection, reset in C) against the
    reference: range_rows, the rows stacked, sequential_update in Python."""
    fast, slow = twin(2 * 8, seed)
    rng = np.random.default_rng(seed)
    for f in (fast, slow):
        f.b_r[:] = np.random.default_rng(seed + 3).normal(size=16) * 0.1
    ids = [int(a) for a in rng.choice(8, size=k, replace=False)]
    anchors = rng.uniform(-10, 10, size=(k, 3))
    ranges = np.linalg.norm(anchors - fast.p, axis=1) + rng.normal(size=k) * 0.3
    var = rng.uniform(0.001, 0.1, size=k)
    lever = rng.normal(size=3) * 0.2
    columns = {a: (N_CORE + a, N_CORE + 8 + a) for a in range(8)}
    H_extra = rng.normal(size=(extra, fast.n))
    y_extra, R_extra = rng.normal(size=extra) * 0.1, rng.uniform(0.001, 0.1, size=extra)
    kinds = b"r" * k + b"z" * extra
    policy = RowPolicy.of(kinds, 6.63, RobustPolicy(enabled=robust), True)
    rows_fast = fast.fuse_ranges(lever, anchors, ranges, var, tuple(columns[a] for a in ids),
                                 (H_extra, y_extra, R_extra), policy, considered)
    assert rows_fast is not None
    with native.pure_python():
        reference = range_rows(slow, lever, ids, anchors, ranges, var, columns)
    rows_slow = slow.sequential_update(np.vstack([reference.H, H_extra]),
                                       np.concatenate([reference.y, y_extra]),
                                       np.concatenate([reference.R, R_extra]), policy,
                                       considered)
    np.testing.assert_allclose([r[:3] for r in rows_fast], [r[:3] for r in rows_slow],
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.P, slow.P, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.p + fast.v + fast.q + fast.b_g + fast.b_a,
                               slow.p + slow.v + slow.q + slow.b_g + slow.b_a,
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fast.b_r, slow.b_r, rtol=1e-9, atol=1e-12)


@needs_core
def test_a_tight_epoch_with_an_antenna_on_an_anchor_is_left_to_the_reference() -> None:
    fast, _ = twin(0, 5)
    P, p = fast.P.copy(), list(fast.p)
    anchors = np.array([fast.p, [5.0, 0.0, 0.0]])  # the first anchor at the antenna
    rows = fast.fuse_ranges(np.zeros(3), anchors, np.array([0.0, 5.0]), np.full(2, 0.01),
                            ((), ()), (np.zeros((0, fast.n)), np.zeros(0), np.zeros(0)),
                            RowPolicy.of(b"rr", 6.63, RobustPolicy(), True), None)
    assert rows is None and np.array_equal(fast.P, P) and fast.p == p


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
    """Filter.pose's numbers in one call of the C core against ``_pose_numbers``: the
    covariance (yaw unknown while not aligned), σ_xy, the heading's observability, the
    state's numbers; None for both when one is not finite."""
    fast, _ = twin(n_aux, seed)
    if broken == "p":
        fast.p[1] = math.inf
    elif broken == "P":
        fast.P[7, 7] = math.nan
    elif broken == "P_v":  # the velocity block: only the reference's product reads it
        fast.P[3, 4] = fast.P[4, 3] = math.inf
    flt = Filter(FilterConfig(anchors_m={0: (0.0, 0.0, 0.0)}))
    flt.ekf, flt._aligned = fast, aligned
    assert native.core is not None
    numbers = native.core.pose_numbers(np.ascontiguousarray(fast.P), fast.q, fast.p, fast.v,
                                       aligned, MAX_OBSERVABLE_YAW_SIGMA)
    with np.errstate(invalid="ignore"):  # inf × 0 in the reference's product
        reference = flt._pose_numbers(fast)
    if broken is not None:
        assert numbers is None and reference is None
        return
    assert numbers is not None and reference is not None
    np.testing.assert_allclose(numbers[0], reference[0], rtol=1e-12, atol=1e-15)
    assert math.isclose(numbers[1], reference[1], rel_tol=1e-12)
    assert numbers[2] == reference[2] or abs(math.sqrt(reference[0][35])
                                             - MAX_OBSERVABLE_YAW_SIGMA) < 1e-12
    assert numbers[3:] == reference[3:]
    if not aligned:
        assert numbers[0][35] == math.pi**2 and numbers[0][5] == numbers[0][30] == 0.0


def _reference_outcomes(flt: Filter) -> None:
    """``flt`` reports its rows with the Python reference alone."""
    def outcomes(t_ns: int, keys: list[tuple[str, str]], rows: list[Row]
                 ) -> list[FusionReport]:
        reports = flt._row_outcomes(t_ns, keys, rows)
        flt._keep_covariance_sane()
        return reports
    flt._outcomes = outcomes  # type: ignore[assignment, method-assign]


@needs_core
@pytest.mark.parametrize("preset", ["handheld", "ceiling"])
def test_row_outcomes_in_c_match_the_reference(preset: str,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The rows' reports, counters, health evidence and anchor statistics of the C core
    are the reference's, to the bit, through rejected and down-weighted ranges (multipath)
    and a 6 s gap in the ranges (the window cleared and judged afresh)."""
    sim = simulate(handheld_async(3) if preset == "handheld" else ceiling_room(3))
    frames = list(merge(sim.imu, sim.uwb))
    gap_from = frames[0].t_ns + 20 * 10**9
    frames = [f for f in frames if isinstance(f, ImuSample)
              or not gap_from <= f.t_ns < gap_from + 6 * 10**9][: len(frames) // 2]
    cfg = parse(simulation_toml(sim)).filter_config()
    fast, slow = Filter(cfg), Filter(cfg)
    fast.epoch_step = slow.epoch_step = None  # (its outcomes are the C core's own)
    _reference_outcomes(slow)
    assert native.core is not None
    in_c = []
    core_outcomes = native.core.outcomes
    monkeypatch.setattr(native.core, "outcomes",
                        lambda *args: in_c.append(core_outcomes(*args)) or in_c[-1])
    reports: dict[int, list[FusionReport]] = {id(fast): [], id(slow): []}
    for flt in (fast, slow):
        for f in frames:
            if isinstance(f, ImuSample):
                flt.predict(f)
            else:
                reports[id(flt)] += flt.update(f)
    assert in_c and all(out is not NotImplemented for out in in_c)
    assert reports[id(fast)] == reports[id(slow)]
    assert fast.counters == slow.counters and fast.counters["range_rejected"] > 0
    assert fast.monitor.resets == slow.monitor.resets
    fm, sm = vars(fast.monitor), vars(slow.monitor)
    assert {k: list(v) if k == "_outcomes" else v for k, v in fm.items()} == \
        {k: list(v) if k == "_outcomes" else v for k, v in sm.items()}
    assert {a: vars(s) for a, s in fast.anchor_stats.items()} == \
        {a: vars(s) for a, s in slow.anchor_stats.items()}
    assert any(s.deweighted for s in fast.anchor_stats.values())


@needs_core
@pytest.mark.parametrize("case", ["unknown kind", "square overflows", "odd anchor stats",
                                  "no anchor stats", "window of no whole count"])
def test_row_outcomes_the_c_core_does_not_expect_are_left_to_the_reference(case: str) -> None:
    """Declined with nothing changed: a kind of row it does not name, an innovation whose
    square overflows (where Python raises), anchor statistics not of the shape it writes."""
    flt = Filter(FilterConfig(anchors_m={0: (0.0, 0.0, 0.0)}))
    rows = [Row(0.1, 1.0, 1.0, False), Row(0.1, 1.0, 1.0, False)]
    keys = [("range", "123456"), ("range", "7")]
    if case == "unknown kind":
        keys[1] = ("odd", "x")
    elif case == "square overflows":
        rows[1] = Row(1e200, 1.0, 0.0, False)
    elif case == "odd anchor stats":
        flt.anchor_stats[7] = AnchorStats(rejected=0.0)  # type: ignore[arg-type]
    elif case == "no anchor stats":
        flt.anchor_stats[7] = 42  # type: ignore[assignment]
    before = (dict(flt.counters), repr(vars(flt.monitor)), repr(flt.anchor_stats))
    assert native.core is not None
    parts = flt._outcome_parts()
    if case == "window of no whole count":
        parts = (*parts[:4], (5.0, 11.5, 0.5, 6.0), *parts[5:])
    for _ in range(3):
        assert native.core.outcomes(parts, 10**18, keys, rows) is NotImplemented
    assert (dict(flt.counters), repr(vars(flt.monitor)), repr(flt.anchor_stats)) == before
    if case == "square overflows":
        with pytest.raises(OverflowError):
            flt._row_outcomes(10**18, keys, rows)


@needs_core
def test_declined_row_outcomes_keep_no_memory() -> None:
    """Every object the checks made is let go when the call declines."""
    flt = Filter(FilterConfig(anchors_m={0: (0.0, 0.0, 0.0)}))
    keys = [("range", "123456")] * 3 + [("odd", "x")]
    rows = [Row(0.1, 1.0, 1.0, False)] * 4
    assert native.core is not None
    parts = flt._outcome_parts()
    tracemalloc.start()
    try:
        for _ in range(200):
            native.core.outcomes(parts, 10**18, keys, rows)
        first, _ = tracemalloc.get_traced_memory()
        for _ in range(2000):
            native.core.outcomes(parts, 10**18, keys, rows)
        second, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert second - first < 20_000  # a leak of 3 ints a call would be ~170 kB


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
    code = "from uwbd.fusion import native; print(native.core is None, native.implementation)"
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
    window = ImuWindow(4.0, RestLimits())
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
    with native.pure_python():
        assert ImuWindow._judge(window, span_s) == verdict
