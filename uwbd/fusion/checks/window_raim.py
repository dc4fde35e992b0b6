"""Do the ranges agree with each other? A snapshot test over a window, in the spirit of GNSS
RAIM (docs/ekf.md §6), independent of what the filter has absorbed.

About ten times a second the latest range of each anchor (an epoch; or single ranges, five
times a second, each anchor's latest of the last two ``SINGLE_EVERY_NS``) makes a
*snapshot*: their innovations before the update ``y = z − h(x̂)`` and unit vectors anchor →
tag ``u`` are solved by weighted least squares
for one position offset, ``y ≈ uᵀ δp`` (weights ``1 / (σ_r² + σ_m²)``, each innovation
clipped at ``CLIP_SIGMAS`` σ: an NLOS range counts as a large one, not as a huge one).
What the offset cannot explain, the snapshot's SSE, does not depend on the filter's
state: a wrong installation that the state and the range-model states have absorbed
(their innovations grow small) still leaves it, where the geometry shows it at all.

Over ``window_s`` the snapshots' ``T = ΣSSE / Σ(n − 3)`` is tested against its
``1 − false_alarm`` quantile, successive snapshots taken as one in ``CORRELATED`` independent
(real range errors are correlated over about a second), and more than ``HIGH_SHARE`` of
its snapshots must each be over their own 90 % quantile. A failing window is the health
fault ``ranges_inconsistent``; its candidates are the anchors whose removal (Baarda's
leave-one-out, summed over the window) leaves a consistent rest, or all of them. ``T`` is
also the factor the covariance is inflated by for the protection levels; the snapshots'
mean ``δp`` (where the ranges alone put the tag, against the state) is added to them, and
so is their geometry's gain ``Σ_j |S_ij|`` (the most position error a bias of 1 m on every
range can make, ``S = (UᵀWU)⁻¹UᵀW``) times ``range_bias_bound_m``
(:mod:`uwbd.fusion.policy.health`). Which anchor to exclude is
:mod:`.anchor_consistency`'s call; this test only says the set disagrees.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array

Vec3 = tuple[float, float, float]

NS = 1_000_000_000
SNAPSHOT_EVERY_NS = 95_000_000  # epochs
# single ranges (100+ a second): a snapshot of each anchor's latest of the last two periods
SINGLE_EVERY_NS = 190_000_000
JUDGE_EVERY_NS = 500_000_000
CORRELATED = 3  # snapshots taken as one independent
MIN_ANCHORS = 5  # a snapshot needs two ranges more than the offset's three
MIN_SNAPSHOTS = 20  # an anchor is a candidate only with this many in the window
CLIP_SIGMAS = 4.0
# ... and the window fails only if more than this share of its snapshots are each over
# their own 90 % quantile: a fault of the installation is in every snapshot, a burst of
# NLOS (seconds) in a few, however large it makes the sum
HIGH_Z = 1.2816  # the standard normal's 90 % quantile
HIGH_SHARE = 0.5


@dataclass(frozen=True)
class RaimLimits:
    window_s: float = 8.0
    false_alarm: float = 1e-4  # of the window test, on a consistent window


class WindowRaim:
    """The window of snapshots and its test (see module doc)."""

    def __init__(self, limits: RaimLimits, core: Core) -> None:
        self.limits = limits
        self._core = core  # the snapshot's least squares: C, or the reference (None)
        self._latest: dict[int, tuple[int, float, float, float, float, float]] = {}  # t, y,
        # 1/var, u
        self._snapshot_ns = -(2**63)
        self._judged_ns = -(2**63)
        # per snapshot: its time, SSE, degrees of freedom, and each anchor's SSE reduction
        self._entries: collections.deque[
            tuple[int, float, int, bool, Vec3, Vec3, dict[int, float]]] = collections.deque()
        self._offset_sum: Vec3 = (0.0, 0.0, 0.0)
        self._gain_sum: Vec3 = (0.0, 0.0, 0.0)
        # the window's mean horizontal and vertical position error per metre of a bias on
        # every range (signs the worst): what the ranges' unmodelled biases can do
        self.bias_gain = (0.0, 0.0)
        self._sse = 0.0
        self._dof = 0
        self._high = 0  # snapshots over their own 90 % quantile
        self._reduction: dict[int, float] = {}
        self._count: collections.Counter[int] = collections.Counter()
        self._z = NormalDist().inv_cdf(1.0 - limits.false_alarm)
        self.inconsistent: tuple[int, ...] = ()  # the window fails: its candidates
        self.ratio = 1.0  # max(1, T): the covariance's inflation
        # the snapshots' mean δp: where the ranges alone put the tag, against the state
        self.offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

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

    def add(self, t_ns: int, ids: list[int], y: Array, u: Array, var_m2: Array) -> None:
        """Ranges before their update: anchors, innovations (m), unit vectors anchor → tag
        (rows of ``u``), the ranges' variances (m²)."""
        latest = self._latest
        # (in floats: numpy's calls cost more than the work on a few ranges)
        for anchor, yk, (ux, uy, uz), vk in zip(ids, y.tolist(), u.tolist(), var_m2.tolist(),
                                                 strict=True):
            if 0.0 < vk < math.inf and math.isfinite(yk + ux + uy + uz):
                clip = CLIP_SIGMAS * math.sqrt(vk)
                latest[anchor] = (t_ns, min(max(yk, -clip), clip), 1.0 / vk, ux, uy, uz)
        period = SINGLE_EVERY_NS if len(ids) < MIN_ANCHORS else SNAPSHOT_EVERY_NS
        if t_ns - self._snapshot_ns < period:
            return
        self._snapshot_ns = t_ns
        recent = t_ns - 2 * period
        self._snapshot(t_ns, [a for a, r in latest.items() if r[0] >= recent],
                       [r for r in latest.values() if r[0] >= recent])
        if t_ns - self._judged_ns >= JUDGE_EVERY_NS:
            self._judged_ns = t_ns
            self._forget_before(t_ns - int(self.limits.window_s * NS))
            self._judge()

    def clear(self) -> None:
        """A restart: the evidence was about the old estimate."""
        self._latest.clear()
        self._entries.clear()
        self._reduction.clear()
        self._count.clear()
        self._sse, self._dof, self._high = 0.0, 0, 0
        self._offset_sum = self._gain_sum = (0.0, 0.0, 0.0)
        self.inconsistent, self.ratio, self.offset_m = (), 1.0, (0.0, 0.0, 0.0)
        self.bias_gain = (0.0, 0.0)

    def _snapshot(self, t_ns: int, anchors: list[int],
                  rows: list[tuple[int, float, float, float, float, float]]) -> None:
        if len(rows) < MIN_ANCHORS:
            return
        core = self._core
        solved = (core.raim_snapshot(rows) if core is not None else solve_snapshot(rows))
        if solved is None:
            return
        dp, gain, sse, free, red = solved
        reduction = {a: x for a, x, f in zip(anchors, red, free, strict=True) if f > 1e-3}
        dof = len(rows) - 3
        high = sse / dof > ratio_quantile(HIGH_Z, dof)
        self._entries.append((t_ns, sse, dof, high, dp, gain, reduction))
        self._offset_sum = _plus(self._offset_sum, dp)
        self._gain_sum = _plus(self._gain_sum, gain)
        self._sse += sse
        self._dof += dof
        self._high += high
        for a, x in reduction.items():
            self._reduction[a] = self._reduction.get(a, 0.0) + x
            self._count[a] += 1

    def _forget_before(self, oldest_ns: int) -> None:
        entries, count, reduction = self._entries, self._count, self._reduction
        while entries and entries[0][0] < oldest_ns:
            _, sse, dof, high, dp, gain, per = entries.popleft()
            self._offset_sum = _plus(self._offset_sum, dp, -1.0)
            self._gain_sum = _plus(self._gain_sum, gain, -1.0)
            self._sse -= sse
            self._dof -= dof
            self._high -= high
            for a, red in per.items():
                count[a] -= 1
                if count[a] == 0:  # (and no rounding left behind)
                    del count[a], reduction[a]
                else:
                    reduction[a] -= red
        if not entries:
            self._sse, self._dof, self._high = 0.0, 0, 0
            self._offset_sum = self._gain_sum = (0.0, 0.0, 0.0)

    def _judge(self) -> None:
        dof = self._dof
        t = max(self._sse, 0.0) / dof if dof > 0 else 0.0
        self.ratio = max(1.0, t)
        n = len(self._entries)
        x, y, z = self._offset_sum
        self.offset_m = (x / n, y / n, z / n) if n else (0.0, 0.0, 0.0)
        gx, gy, gz = (c / n for c in self._gain_sum) if n else (0.0, 0.0, 0.0)
        self.bias_gain = (math.hypot(gx, gy), gz)
        if (dof <= 0 or t <= ratio_quantile(self._z, dof / CORRELATED)
                or self._high <= HIGH_SHARE * len(self._entries)):
            self.inconsistent = ()
            return
        passing = []
        for anchor, n in self._count.items():
            rest = dof - n
            if n >= MIN_SNAPSHOTS and rest > 0:
                t_rest = max(self._sse - self._reduction[anchor], 0.0) / rest
                if t_rest <= ratio_quantile(self._z, rest / CORRELATED):
                    passing.append(anchor)
        self.inconsistent = tuple(sorted(passing or self._count))


def solve_snapshot(rows: list[tuple[int, float, float, float, float, float]]
                   ) -> tuple[Vec3, Vec3, float, list[float], list[float]] | None:
    """One snapshot's rows ``(t_ns, y, w, ux, uy, uz)`` solved by weighted least squares for
    one offset ``δp = S y``, ``S = (UᵀWU + εI)⁻¹UᵀW`` (ε 1e-9 of the trace): δp, the gain
    ``Σ_j |S_ij|``, the SSE ``Σ w r²``, each row's ``1 − leverage`` and the SSE's reduction
    without it, ``w r² / (1 − h)`` (Baarda's w-test squared); None when singular. The
    reference of the C core's ``raim_snapshot``."""
    table = np.array(rows)[:, 1:]
    y, w, U = table[:, 0], table[:, 1], table[:, 2:]
    N = U.T @ (U * w[:, None])
    try:
        Ni = np.linalg.inv(N + 1e-9 * np.trace(N) * np.eye(3))
    except np.linalg.LinAlgError:
        return None
    S = Ni @ (U.T * w)  # δp per metre of each range
    dp = S @ y
    r = y - U @ dp
    gain = np.abs(S).sum(axis=1)
    free = 1.0 - w * ((U @ Ni) * U).sum(axis=1)  # 1 − leverage
    red = w * r * r / np.maximum(free, 1e-3)
    px, py, pz = dp.tolist()
    gx, gy, gz = gain.tolist()
    return (px, py, pz), (gx, gy, gz), float(w @ (r * r)), free.tolist(), red.tolist()


def _plus(a: Vec3, b: Vec3, sign: float = 1.0) -> Vec3:
    return (a[0] + sign * b[0], a[1] + sign * b[1], a[2] + sign * b[2])


def ratio_quantile(z: float, dof: float) -> float:
    """The quantile of χ²(dof)/dof at the standard normal's ``z`` (Wilson–Hilferty: within
    1 % from dof 3)."""
    dof = max(dof, 1.0)
    a = 2.0 / (9.0 * dof)
    return (1.0 - a + z * math.sqrt(a)) ** 3
