"""UWB-only position fixes from whatever the tag sends: full epochs or single ranges.

A tag that reports all anchors at once (Nooploop, DWM1001) gives a fix per epoch. A tag
that ranges one anchor at a time (DW1000/DW3000 two-way ranging, round-robin) never does:
:class:`RangeWindow` keeps the latest range of each anchor for ``window_s`` and solves
them together. An epoch that alone holds enough anchors is solved alone (no older ranges
mixed in). Fixes serve to start the filter, to align the heading, to check a reset and,
in loose mode, as the measurements; they are made at most every ``min_interval_s`` from
a window (consecutive window fixes share most of their ranges).

A start at rest takes :meth:`RangeWindow.rest_fix`: each anchor's ranges of the rest's
epochs averaged, solved once, and tested against their noise (σ/√n each, plus the
offsets the config allows, ``fusion.range_bias_sigma_m`` and ``tag_delay_sigma_m``, which
no state has learnt yet) at a risk of 10⁻³. The test is only as sharp as the config's
claim: with the defaults (0.1 and 0.2 m, uncalibrated units) it sees little, with a
datasheet's or a calibration's few centimetres it sees an anchor surveyed off. One
epoch hides an anchor surveyed 1 m off sideways in the tag's height (its fix is 1-2 m
off with residuals of a few decimetres); a few seconds of them do not. When the set fails,
each anchor is left out in turn; one whose removal makes the rest pass and that disagrees
with the others' solution by more than that solution's own uncertainty allows (leaving out
the only anchor that sees the height lets the rest pass by losing the height, not by being
right) is a candidate, and exactly one candidate is left out of the start (fault
detection and exclusion, as in RAIM). With none (several anchors' offsets, which the
range-offset states then learn) or several (one anchor long, or another short, explain
the place alike) the plain solution stands, and the start is no surer than the distance
to the solutions it could not rule out (:class:`RestFix`); so too with four anchors, which
leave no range to spare for a test. Each set is solved from several starting points (a tag
near the plane of most anchors has a second minimum on its far side) and the best kept.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Mapping, Sequence
from statistics import NormalDist
from typing import NamedTuple

import numpy as np

from uwbd.fusion.core.lsq import LsqFix, common_offset, coplanar, multilaterate
from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.mirror import MirrorSide

NS = 1_000_000_000
REST_Z = NormalDist().inv_cdf(1.0 - 1e-3)  # the rest's test fails a right installation
# once in a thousand starts
REST_MIN_RANGES = 5  # an anchor's ranges the rest's average needs


class RestFix(NamedTuple):
    """A start at rest's position: the fix, the anchor left out of it with its mean range's
    excess over the fix's distance (None: none), and how far the solutions it could not rule
    out lie from it (without one anchor, where the set failed and no one anchor was named;
    with four anchors, any three's; else 0): the start's position is no surer than that."""

    fix: LsqFix
    left_out: tuple[int, float] | None
    spread_m: float = 0.0


class RangeWindow:
    def __init__(self, window_s: float, min_interval_s: float, sigma_m: float,
                 side: MirrorSide, fixed_z: float | None, *, core: Core) -> None:
        self.window_ns = int(window_s * NS)
        self._core = core  # the fixes' least squares: C, or the reference (None)
        self.min_interval_ns = int(min_interval_s * NS)
        self.sigma_m = sigma_m
        self.side = side
        self.fixed_z = fixed_z
        self._latest: dict[int, tuple[int, list[float], float]] = {}
        self._last_fix_ns: int | None = None
        self.last_inputs: tuple[Array, Array] = (np.zeros((0, 3)), np.zeros(0))  # of the last fix
        # the epochs solved alone (time, anchor ids, ranges), for a start at rest
        self.epochs: collections.deque[tuple[int, list[int], Array]] = \
            collections.deque(maxlen=100)

    @property
    def needed(self) -> int:
        """Anchors a fix takes: 3 with the height held, else 4."""
        return 3 if self.fixed_z is not None else 4

    def add(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array) -> None:
        # as lists (iterating the array makes a view of each row)
        for a, pos, r in zip(ids, anchors.tolist(), ranges.tolist(), strict=True):
            self._latest[a] = (t_ns, pos, r)

    def fix(self, t_ns: int, ids: list[int], anchors: Array, ranges: Array,
            x0: Array | None, force: bool = False, weigh: bool = True) -> LsqFix | None:
        """The fix at ``t_ns`` (after :meth:`add` of this message): from the message alone
        when it holds enough anchors, else from the window; ``None`` when there are too few
        anchors, it is not yet time for another window fix, or the solution does not
        converge. ``force``: a check's own fix, made at any time, which neither keeps the
        epoch nor delays the next fix (a check made every message would starve loose mode
        of its fixes). ``weigh``: count the fix as evidence for the mirror side (once per
        message: checks that solve again say False)."""
        if len(ids) >= self.needed:
            if not force:
                self._last_fix_ns = t_ns
                self.epochs.append((t_ns, ids, ranges))
            return self._solve(anchors, ranges, x0, weigh)
        if not force and self._last_fix_ns is not None and \
                t_ns - self._last_fix_ns < self.min_interval_ns:
            return None
        oldest = t_ns - self.window_ns
        recent = [(pos, r) for t, pos, r in self._latest.values() if t >= oldest]
        if len(recent) < self.needed:
            return None
        if not force:
            self._last_fix_ns = t_ns
        return self._solve(np.array([p for p, _ in recent]), np.array([r for _, r in recent]),
                           x0, weigh)

    def recent_epochs(self, since_ns: float) -> list[tuple[list[int], Array]]:
        """The epochs solved alone since ``since_ns``, as :meth:`rest_fix` takes them."""
        return [(ids, ranges) for t, ids, ranges in self.epochs if t >= since_ns]

    def rest_fix(self, epochs: list[tuple[list[int], Array]],
                 anchors_m: Mapping[int, Sequence[float]], offset_sigma_m: float,
                 heights_m: tuple[float, float] = (-math.inf, math.inf)) -> RestFix | None:
        """The rest's epochs (anchor ids, ranges) as one fix (:class:`RestFix`); None when
        too few anchors have enough ranges. ``offset_sigma_m``: what a range's offset may
        be, 1 σ (see the module doc); ``heights_m``: where the tag can be (a solution
        elsewhere is no hypothesis to start as unsure as)."""
        sums: dict[int, list[float]] = {}
        for ids, ranges in epochs:
            for a, r in zip(ids, ranges.tolist(), strict=True):
                if a in anchors_m:
                    sums.setdefault(a, []).append(r)
        ids = sorted(a for a, rs in sums.items() if len(rs) >= REST_MIN_RANGES)
        if len(ids) < self.needed:
            return None
        anchors = np.array([anchors_m[a] for a in ids], dtype=float)
        ranges = np.array([float(np.mean(sums[a])) for a in ids])
        sigma = np.sqrt(np.array([self.sigma_m**2 / len(sums[a]) for a in ids])
                        + offset_sigma_m**2)
        dims = 2 if self.fixed_z is not None else 3

        def solutions(keep: Array, near: Array | None = None,
                      both_sides: bool = False) -> list[tuple[float, LsqFix]]:
            """Each start's solution of the anchors ``keep``, with its squares (over σ²)."""
            out = []
            for x0 in self._rest_starts(anchors[keep], near, both_sides):
                fix = multilaterate(anchors[keep], ranges[keep], float(np.max(sigma)), x0,
                                    self.fixed_z, outlier_sigma=math.inf,
                                    side=self.side.sign, core=self._core)
                if fix is not None:
                    out.append((float(np.sum((fix.residuals_m / sigma[keep]) ** 2)), fix))
            return out

        def solved(keep: Array, near: Array | None = None) -> tuple[LsqFix, bool] | None:
            found = solutions(keep, near)
            if not found:
                return None
            sse, fix = min(found, key=lambda f: f[0])
            dof = int(keep.sum()) - dims
            return fix, dof <= 0 or sse <= dof * ratio_quantile(REST_Z, dof)

        every = np.ones(len(ids), dtype=bool)
        whole = solved(every)
        if whole is None:
            return None
        if len(ids) <= self.needed and not self.side.ambiguous:
            # no range to spare for naming one: any could be off (over anchors on one
            # plane, the mirror side holds the question of the height)
            here, (low, high) = whole[0].position_m, heights_m
            return RestFix(whole[0], None, max(
                (float(np.linalg.norm(fix.position_m - here)) for k in range(len(ids))
                 for _, fix in solutions(every & (np.arange(len(ids)) != k), here, True)
                 if low <= fix.position_m[2] <= high), default=0.0))
        if whole[1]:
            return RestFix(whole[0], None)
        candidates: list[tuple[float, int, LsqFix, float]] = []
        spread_m = 0.0
        for k in range(len(ids)):
            without = solved(every & (np.arange(len(ids)) != k), whole[0].position_m)
            if without is None or not without[1]:
                continue
            spread_m = max(spread_m, float(np.linalg.norm(without[0].position_m
                                                          - whole[0].position_m)))
            # the anchor against the others' solution and its uncertainty: an anchor whose
            # removal only takes away what the others' error needed to be seen (the height,
            # say) leaves a solution too loose to disagree with it
            fix = without[0]
            diff = fix.position_m - anchors[k]
            u = diff / np.linalg.norm(diff)
            excess = float(ranges[k] - np.linalg.norm(diff))
            w = abs(excess) / math.sqrt(sigma[k] ** 2 + float(u @ fix.covariance @ u))
            if w > REST_Z:
                candidates.append((w, ids[k], fix, excess))
        if len(candidates) != 1:  # none explains it, or more than one could: not told
            return RestFix(whole[0], None, spread_m)
        _, anchor, fix, excess = candidates[0]
        return RestFix(fix, (anchor, excess))

    def _rest_starts(self, anchors: Array, near: Array | None,
                     both_sides: bool = False) -> list[Array | None]:
        """Where the rest's least squares starts. Over anchors on one plane, the side's
        point (the whole installation's plane, or, for those heard, the linear guess on the
        side's side), unless ``both_sides`` asks for the tag and its mirror alike. Else the
        linear solution, and points under, among and over the anchors (above ``near``, a
        solution of all the ranges, else their centre): a tag near the plane of most
        anchors has a second minimum through that plane, which one range off can make the
        lower, and from far off the search for a height the ranges barely see does not
        converge: start from each, keep the best."""
        if self.fixed_z is not None:
            return [None]
        if self.side.ambiguous:
            return [self.side.start_point()]
        if coplanar(anchors) and not both_sides:
            return [None]
        x, y, z = (anchors.mean(axis=0) if near is None else near).tolist()
        low, high = float(anchors[:, 2].min()), float(anchors[:, 2].max())
        return [None, *(np.array([x, y, h]) for h in (low - 1.0, z, high + 1.0))]

    def _solve(self, anchors: Array, ranges: Array, x0: Array | None,
               weigh: bool) -> LsqFix | None:
        self.last_inputs = (anchors, ranges)
        if x0 is None and self.side.ambiguous and self.fixed_z is None:
            x0 = self.side.start_point()
        fix = multilaterate(anchors, ranges, self.sigma_m, x0, self.fixed_z,
                            side=self.side.sign, core=self._core)
        if fix is not None and weigh:
            self.side.weigh(anchors, ranges, fix, self.sigma_m, self.fixed_z)
        return fix


def consistent(fix: LsqFix, anchors: Array, ranges: Array, sigma_m: float,
               tag_delay_sigma_m: float, needed: int) -> bool:
    """A fix whose ranges agree with each other: all used, residual RMS within 2σ, at least
    ``needed`` anchors, and (with 5 ranges or more) no common offset beyond 3σ of the tag's
    delay — an NLOS detour on every anchor looks like one."""
    if not (fix.used.all() and fix.rms_m <= 2.0 * sigma_m and int(fix.used.sum()) >= needed):
        return False
    solved = common_offset(anchors, ranges, fix.position_m) if len(ranges) >= 5 else None
    return solved is None or abs(solved[0]) <= 3.0 * math.hypot(tag_delay_sigma_m, sigma_m)


def ratio_quantile(z: float, dof: float) -> float:
    """The quantile of χ²(dof)/dof at the standard normal's ``z`` (Wilson–Hilferty: within
    1 % from dof 3)."""
    dof = max(dof, 1.0)
    a = 2.0 / (9.0 * dof)
    return (1.0 - a + z * math.sqrt(a)) ** 3
