"""UWB-only position fixes from whatever the tag sends: full epochs or single ranges.

A tag that reports all anchors at once (Nooploop, DWM1001) gives a fix per epoch. A tag
that ranges one anchor at a time (DW1000/DW3000 two-way ranging, round-robin) never does:
:class:`RangeWindow` keeps the latest range of each anchor for ``window_s`` and solves
them together. An epoch that alone holds enough anchors is solved alone (no older ranges
mixed in). Fixes serve to start the filter, to align the heading, to check a reset and,
in loose mode, as the measurements; they are made at most every ``min_interval_s`` from
a window (consecutive window fixes share most of their ranges).
"""

from __future__ import annotations

import math

import numpy as np

from uwbd.fusion.core.lsq import LsqFix, common_offset, multilaterate
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.mirror import MirrorSide

NS = 1_000_000_000


class RangeWindow:
    def __init__(self, window_s: float, min_interval_s: float, sigma_m: float,
                 side: MirrorSide, fixed_z: float | None) -> None:
        self.window_ns = int(window_s * NS)
        self.min_interval_ns = int(min_interval_s * NS)
        self.sigma_m = sigma_m
        self.side = side
        self.fixed_z = fixed_z
        self._latest: dict[int, tuple[int, list[float], float]] = {}
        self._last_fix_ns: int | None = None
        self.last_inputs: tuple[Array, Array] = (np.zeros((0, 3)), np.zeros(0))  # of the last fix

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
        anchors, it is not yet time for another window fix (unless ``force``), or the
        solution does not converge. ``weigh``: count the fix as evidence for the mirror side
        (once per message: checks that solve again say False)."""
        if len(ids) >= self.needed:
            self._last_fix_ns = t_ns
            return self._solve(anchors, ranges, x0, weigh)
        if not force and self._last_fix_ns is not None and \
                t_ns - self._last_fix_ns < self.min_interval_ns:
            return None
        oldest = t_ns - self.window_ns
        recent = [(pos, r) for t, pos, r in self._latest.values() if t >= oldest]
        if len(recent) < self.needed:
            return None
        self._last_fix_ns = t_ns
        return self._solve(np.array([p for p, _ in recent]), np.array([r for _, r in recent]),
                           x0, weigh)

    def _solve(self, anchors: Array, ranges: Array, x0: Array | None,
               weigh: bool) -> LsqFix | None:
        self.last_inputs = (anchors, ranges)
        if x0 is None and self.side.ambiguous and self.fixed_z is None:
            x0 = self.side.start_point()
        fix = multilaterate(anchors, ranges, self.sigma_m, x0, self.fixed_z,
                            side=self.side.sign)
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
