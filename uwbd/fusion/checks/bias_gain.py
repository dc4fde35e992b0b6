"""What the ranges' unmodelled biases can do to the position, over a window of snapshots of
the geometry (docs/ekf.md §6), for the protection levels' bias term.

About ten times a second the latest range of each anchor (an epoch; or single ranges, five
times a second, each anchor's latest of the last two ``SINGLE_EVERY_NS``) makes a
*snapshot*: their unit vectors anchor → tag ``u`` and weights ``1 / (σ_r² + σ_m²)`` give the
least-squares gain ``S = (UᵀWU)⁻¹UᵀW``, and its ``Σ_j |S_ij|`` is the most position error a
bias of 1 m on every range can make, horizontal and vertical (signs the worst). The
window's mean is ``g`` in ``g b`` (``range_bias_bound_m``, :mod:`uwbd.fusion.policy.health`).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array

Vec3 = tuple[float, float, float]

NS = 1_000_000_000
SNAPSHOT_EVERY_NS = 95_000_000  # epochs
# single ranges (100+ a second): a snapshot of each anchor's latest of the last two periods
SINGLE_EVERY_NS = 190_000_000
JUDGE_EVERY_NS = 500_000_000
MIN_ANCHORS = 5  # a snapshot needs two ranges more than the offset's three
WINDOW_S = 8.0  # the gain is the mean over this many seconds of snapshots


class BiasGain:
    """The window of snapshots and its mean gain (see module doc)."""

    def __init__(self, core: Core, window_s: float = WINDOW_S) -> None:
        self.window_s = window_s
        self._core = core  # the snapshot's least squares: C, or the reference (None)
        self._latest: dict[int, tuple[int, float, float, float, float]] = {}  # t, 1/var, u
        self._snapshot_ns = -(2**63)
        self._judged_ns = -(2**63)
        self._entries: collections.deque[tuple[int, Vec3]] = collections.deque()  # t, gain
        self._gain_sum: Vec3 = (0.0, 0.0, 0.0)
        # the window's mean horizontal and vertical position error per metre of a bias on
        # every range (signs the worst): what the ranges' unmodelled biases can do
        self.bias_gain = (0.0, 0.0)

    def due(self, t_ns: int, ids: list[int]) -> bool:
        """Whether these ranges are wanted: a snapshot is due, or one of them is a single
        range whose anchor's latest is older than a snapshot's period (a snapshot gathers
        each anchor's latest)."""
        single = len(ids) < MIN_ANCHORS
        if t_ns - self._snapshot_ns >= (SINGLE_EVERY_NS if single else SNAPSHOT_EVERY_NS):
            return True
        latest = self._latest
        return single and any(
            a not in latest or t_ns - latest[a][0] >= SINGLE_EVERY_NS for a in ids)

    def add(self, t_ns: int, ids: list[int], u: Array, var_m2: Array) -> None:
        """Ranges' geometry: anchors, unit vectors anchor → tag (rows of ``u``), the ranges'
        variances (m²)."""
        latest = self._latest
        # (in floats: numpy's calls cost more than the work on a few ranges)
        for anchor, (ux, uy, uz), vk in zip(ids, u.tolist(), var_m2.tolist(), strict=True):
            if 0.0 < vk < math.inf and math.isfinite(ux + uy + uz):
                latest[anchor] = (t_ns, 1.0 / vk, ux, uy, uz)
        period = SINGLE_EVERY_NS if len(ids) < MIN_ANCHORS else SNAPSHOT_EVERY_NS
        if t_ns - self._snapshot_ns < period:
            return
        self._snapshot_ns = t_ns
        recent = t_ns - 2 * period
        self._snapshot(t_ns, [r[1:] for r in latest.values() if r[0] >= recent])
        if t_ns - self._judged_ns >= JUDGE_EVERY_NS:
            self._judged_ns = t_ns
            self._forget_before(t_ns - int(self.window_s * NS))
            n = len(self._entries)
            gx, gy, gz = (c / n for c in self._gain_sum) if n else (0.0, 0.0, 0.0)
            self.bias_gain = (math.hypot(gx, gy), gz)

    def clear(self) -> None:
        """A restart: the evidence was about the old estimate."""
        self._latest.clear()
        self._entries.clear()
        self._gain_sum = (0.0, 0.0, 0.0)
        self.bias_gain = (0.0, 0.0)

    def _snapshot(self, t_ns: int, rows: list[tuple[float, float, float, float]]) -> None:
        if len(rows) < MIN_ANCHORS:
            return
        core = self._core
        gain = core.snapshot_gain(rows) if core is not None else snapshot_gain(rows)
        if gain is None:
            return
        self._entries.append((t_ns, gain))
        self._gain_sum = _plus(self._gain_sum, gain)

    def _forget_before(self, oldest_ns: int) -> None:
        entries = self._entries
        while entries and entries[0][0] < oldest_ns:
            self._gain_sum = _plus(self._gain_sum, entries.popleft()[1], -1.0)
        if not entries:
            self._gain_sum = (0.0, 0.0, 0.0)


def snapshot_gain(rows: list[tuple[float, float, float, float]]) -> Vec3 | None:
    """One snapshot's rows ``(w, ux, uy, uz)``: the least-squares gain of one position
    offset, ``S = (UᵀWU + εI)⁻¹UᵀW`` (ε 1e-9 of the trace), as ``Σ_j |S_ij|`` per axis; None
    when singular. The reference of the C core's ``snapshot_gain``."""
    table = np.array(rows)
    w, U = table[:, 0], table[:, 1:]
    N = U.T @ (U * w[:, None])
    try:
        Ni = np.linalg.inv(N + 1e-9 * np.trace(N) * np.eye(3))
    except np.linalg.LinAlgError:
        return None
    gx, gy, gz = np.abs(Ni @ (U.T * w)).sum(axis=1).tolist()
    return gx, gy, gz


def _plus(a: Vec3, b: Vec3, sign: float = 1.0) -> Vec3:
    return (a[0] + sign * b[0], a[1] + sign * b[1], a[2] + sign * b[2])
