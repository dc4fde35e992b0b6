"""The filter's faster forms against the plain ones they stand for: the heading aligner's
(every span's velocity fit at once, the interpolation of the INS history, the fits leaving
out each span — the jackknife — in one batched QR) and the UWB stillness test's velocity."""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uwbd.fusion.policy.alignment import (
    _interpolated,
    _rotation_fit,
    _span_velocities,
    _turns_leaving_out_each_span,
    velocity_fit,
)
from uwbd.fusion.policy.rest import _velocity_xy

T0_NS = 1_700_000_000 * 10**9


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31), st.integers(1, 8), st.integers(5, 12))
def test_every_spans_velocity_at_once_equals_one_fit_per_span(seed: int, spans: int,
                                                              per_span: int) -> None:
    rng = np.random.default_rng(seed)
    count = spans * per_span
    t = T0_NS + np.cumsum(rng.integers(60_000_000, 140_000_000, size=count))
    fixes = collections.deque((int(tk), rng.normal(size=3) * 5) for tk in t)
    bounds = [(k * per_span, (k + 1) * per_span) for k in reversed(range(spans))]
    now = int(t[-1]) + 5_000_000
    v, tau = _span_velocities([tk for tk, _ in fixes], fixes, bounds, now)
    for (lo, hi), v_k, tau_k in zip(bounds, v, tau, strict=True):
        # the fit on times from `now` (Unix-epoch ns as float64 are 256 ns apart: a fit on
        # them is off by ~1e-6 relative, which the sums, on times from `now`, are not)
        ref_v, ref_tm = velocity_fit([(tk - now, p) for tk, p in list(fixes)[lo:hi]])
        np.testing.assert_allclose(v_k, ref_v, rtol=1e-9, atol=1e-9)
        assert tau_k == pytest.approx(ref_tm / 1e9, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**31), st.floats(-0.5, 1.5))
def test_the_history_interpolates_as_numpy_does(seed: int, where: float) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    times = (T0_NS + np.cumsum(rng.integers(1, 10**8, size=n))).astype(float).tolist()
    history = [(int(tk), *rng.normal(size=6).tolist()) for tk in times]
    t = times[0] + where * (times[-1] - times[0]) if n > 1 else times[0] + where
    for at in (t, times[0], times[-1], times[n // 2]):
        expected = tuple(float(np.interp(at, times, [h[i] for h in history]))
                         for i in range(1, 7))
        assert _interpolated(at, times, history) == expected  # the same arithmetic: exact


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.integers(4, 12))
def test_the_jackknife_in_one_batch_equals_one_fit_per_span(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    rows = 2 * n + 6
    S, A, y = rng.normal(size=(rows, 2)), rng.normal(size=(rows, 8)), rng.normal(size=rows)
    turns = _turns_leaving_out_each_span(S, A, y)
    for i, turn in enumerate(turns):
        keep = [r for r in range(rows) if r not in (2 * i, 2 * i + 1)]
        ref = _rotation_fit(S[keep], A[keep], y[keep])
        if ref is None:
            assert math.isnan(turn)
        else:
            assert math.remainder(turn - ref[0], math.tau) == pytest.approx(0, abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31), st.integers(2, 12))
def test_the_stillness_velocity_equals_the_line_fit(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    t = T0_NS + np.cumsum(rng.integers(150_000_000, 250_000_000, size=n))
    fixes = collections.deque((int(tk), rng.normal(size=3)) for tk in t)
    reference, _ = velocity_fit([(tk - int(t[0]), p) for tk, p in fixes])
    np.testing.assert_allclose(_velocity_xy(fixes), reference, rtol=1e-9, atol=1e-12)
