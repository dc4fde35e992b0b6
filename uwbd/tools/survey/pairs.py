"""Anchor-to-anchor ranges: each pair reduced to its median, and the layout placed from them
by classical multilateration (:mod:`uwbd.tools.survey`, "anchor-to-anchor ranges")."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from drivers.frames import AnchorRanges
from uwbd.fusion.core import native
from uwbd.fusion.core.lsq import multilaterate
from uwbd.fusion.core.rotation import Array
from uwbd.tools.survey.model import (
    MAD_TO_SIGMA,
    MEDIAN_EFFICIENCY,
    PAIR_SIGMA_FLOOR_M,
    PairRange,
    Settings,
    SurveyError,
    frame_of,
    side_of,
)


def reduce_pairs(reports: Sequence[AnchorRanges]) -> list[PairRange]:
    """Each pair's ranges (non-finite and non-positive ones dropped) as a :class:`PairRange`."""
    ranges: dict[tuple[int, int], list[float]] = {}
    for report in reports:
        for p in report.pairs:
            if math.isfinite(p.range_m) and p.range_m > 0 and p.anchor_a != p.anchor_b:
                key = (min(p.anchor_a, p.anchor_b), max(p.anchor_a, p.anchor_b))
                ranges.setdefault(key, []).append(p.range_m)
    out = []
    for (a, b), values in sorted(ranges.items()):
        r = np.array(values)
        med = float(np.median(r))
        spread = MAD_TO_SIGMA * float(np.median(np.abs(r - med)))
        outliers = int(np.sum(np.abs(r - med) > 5 * spread)) if spread > 0 else 0
        se = MEDIAN_EFFICIENCY * spread / math.sqrt(len(r))
        out.append(PairRange(a, b, len(r), med, max(se, PAIR_SIGMA_FLOOR_M), outliers))
    return out


def _horizontal(pairs: Sequence[PairRange], z: Mapping[int, float]
                ) -> tuple[dict[tuple[int, int], float], list[str]]:
    notes = []
    h: dict[tuple[int, int], float] = {}
    for p in pairs:
        dz = z[p.anchor_a] - z[p.anchor_b]
        if p.median_m < abs(dz):
            notes.append(f"anchors {p.anchor_a}-{p.anchor_b}: range {p.median_m:.3f} m is "
                         f"shorter than their height difference {abs(dz):.3f} m; taken as "
                         "straight above each other")
        h[(p.anchor_a, p.anchor_b)] = h[(p.anchor_b, p.anchor_a)] = math.sqrt(
            max(p.median_m**2 - dz**2, 0.0))
    return h, notes


def _place(ids: list[int], h: Mapping[tuple[int, int], float]) -> dict[int, Array]:
    """The anchors' horizontal positions from their horizontal distances alone (a frame of
    their own: the best-connected pair on the x axis, the next anchor on +y)."""
    degree = {a: sum((a, b) in h for b in ids) for a in ids}
    first = max(((a, b) for a in ids for b in ids if a < b and (a, b) in h),
                key=lambda ab: (sum((ab[0], c) in h and (ab[1], c) in h for c in ids),
                                degree[ab[0]] + degree[ab[1]], h[ab]))
    placed = {first[0]: np.zeros(2), first[1]: np.array([h[first], 0.0])}
    while True:
        candidates = [a for a in ids if a not in placed
                      and sum((a, b) in h for b in placed) >= 2]
        if not candidates:
            return placed
        a = max(candidates, key=lambda c: (sum((c, b) in h for b in placed), -c))
        near = sorted((b for b in placed if (a, b) in h),
                      key=lambda b: -h[(a, b)])
        # the two placed neighbours farthest apart give the best-conditioned intersection
        b, c = max(((b, c) for b in near for c in near if b < c),
                   key=lambda bc: float(np.linalg.norm(placed[bc[0]] - placed[bc[1]])))
        options = _circles(placed[b], h[(a, b)], placed[c], h[(a, c)])
        others = [n for n in near if n not in (b, c)]
        if others:  # a third neighbour tells the two intersections apart
            options.sort(key=lambda p: _misfit(p, placed, h, a, others))
        elif len(placed) > 2:  # two neighbours only: the side nearest the layout's middle
            middle = np.mean(list(placed.values()), axis=0)
            options.sort(key=lambda p: -float(np.linalg.norm(p - middle)))
        else:
            options.sort(key=lambda p: -p[1])  # the first anchor off the axis: +y
        guess = options[0]
        rows = near
        fix = multilaterate(np.array([[*placed[n], 0.0] for n in rows]),
                            np.array([h[(a, n)] for n in rows]), 0.01,
                            x0=np.array([*guess, 0.0]), fixed_z=0.0, outlier_sigma=1e9,
                            core=native.core)
        placed[a] = fix.position_m[:2] if fix is not None else guess


def _misfit(p: Array, placed: Mapping[int, Array], h: Mapping[tuple[int, int], float],
            a: int, others: Sequence[int]) -> float:
    return sum((float(np.linalg.norm(p - placed[n])) - h[(a, n)]) ** 2 for n in others)


def _circles(p: Array, r: float, q: Array, s: float) -> list[Array]:
    """Where circles (p, r) and (q, s) meet (touching, when noise keeps them apart)."""
    d = float(np.linalg.norm(q - p))
    if d < 1e-9:
        return [p + np.array([r, 0.0])]
    ex = (q - p) / d
    ey = np.array([-ex[1], ex[0]])
    x = (d * d + r * r - s * s) / (2 * d)
    y = math.sqrt(max(r * r - x * x, 0.0))
    return [p + x * ex + y * ey, p + x * ex - y * ey]


def _fit_2d(src: Array, dst: Array, mirror: bool) -> tuple[Array, Array, float]:
    """The rotation (and mirror) plus translation best taking ``src`` onto ``dst`` (2-D,
    least squares): x' = R x + t; and its RMS misfit."""
    s = src * np.array([1.0, -1.0]) if mirror else src
    cs, cd = s.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((s - cs).T @ (dst - cd))
    R = (U @ Vt).T
    if np.linalg.det(R) < 0:
        Vt[-1] *= -1
        R = (U @ Vt).T
    if mirror:
        R = R @ np.diag([1.0, -1.0])
    t = cd - R @ cs
    misfit = float(np.sqrt(np.mean(np.sum((src @ R.T + t - dst) ** 2, axis=1))))
    return R, t, misfit


def reached_by(ids: list[int], pairs: Sequence[PairRange],
             messages: list[tuple[int, list[tuple[int, float]]]],
             rows_of: Mapping[int, int]) -> set[int]:
    out = {a for p in pairs for a in (p.anchor_a, p.anchor_b)}
    row_ids = {row: a for a, row in rows_of.items()}
    for _, kept in messages:
        out.update(row_ids[row] for row, _ in kept)
    return out & set(ids)


def pairs_start(ids: list[int], pairs: Sequence[PairRange], z: Mapping[int, float],
                 prior: Array, settings: Settings, notes: list[str]
                 ) -> tuple[Array, npt.NDArray[np.bool_]]:
    """Anchor-to-anchor ranges only: the anchors placed from their ranges alone, then put
    into the output frame (the user's, or the best fit to the configured positions). Heights
    are held (not free)."""
    h, said = _horizontal(pairs, z)
    notes += said
    placed = _place(ids, h)
    g = settings.gauge
    start = prior.copy()
    free = np.zeros((len(ids), 3), dtype=bool)
    names = sorted(placed)
    P = np.array([placed[a] for a in names])
    if g.user:
        assert g.origin is not None and g.x_axis is not None
        for a in (g.origin, g.x_axis):
            if a not in placed:
                raise SurveyError(f"anchor {a} cannot be placed from the anchor-to-anchor ranges "
                                  "(it needs ranges to 2 anchors placed before it)")
        o, x = placed[g.origin], placed[g.x_axis]
        R2, t2 = frame_of(np.array([*o, 0.0]), np.array([*x, 0.0]))
        Q = (np.column_stack([P, np.zeros(len(P))]) - t2) @ R2.T
        side_anchor = g.y_side
        if side_anchor is None:  # the side the config puts the off-axis anchors on
            sides = [(abs(float(prior[ids.index(a), 1])), a) for a in names
                     if a not in (g.origin, g.x_axis) and not math.isnan(prior[ids.index(a), 1])
                     and side_of(prior[ids.index(a)], prior[ids.index(g.x_axis)]) != 0]
            if not sides:
                raise SurveyError("which side of the x axis the anchors are on cannot be told: "
                                  "give --y-side ID (an anchor on the +y side)")
            side_anchor = max(sides)[1]
            want = side_of(prior[ids.index(side_anchor)], prior[ids.index(g.x_axis)])
        else:
            want = 1
            if side_anchor not in placed:
                raise SurveyError(f"--y-side {side_anchor}: that anchor cannot be placed from "
                                  "the anchor-to-anchor ranges")
        got = side_of(Q[names.index(side_anchor)], Q[names.index(g.x_axis)])
        if got == 0:
            raise SurveyError(f"anchor {side_anchor} lies on the x axis ({g.origin} -> "
                              f"{g.x_axis}): it cannot tell the sides apart; give another "
                              "--y-side")
        if got != want:
            Q[:, 1] *= -1
        for k, a in enumerate(names):
            start[ids.index(a), :2] = Q[k, :2]
    else:
        known = [a for a in names if not math.isnan(prior[ids.index(a), 0])]
        if len(known) < 3:
            raise SurveyError("the anchor-to-anchor ranges fix the layout but not where it is: "
                              "3 of its anchors need configured positions, or give --origin "
                              "and --x-axis")
        src = np.array([placed[a] for a in known])
        dst = np.array([prior[ids.index(a), :2] for a in known])
        fits = [_fit_2d(src, dst, m) for m in (False, True)]
        R2d, t2d, misfit = min(fits, key=lambda f: f[2])
        other = max(fits, key=lambda f: f[2])[2]
        if other < 1.5 * misfit or other - misfit < 0.05:
            raise SurveyError("the configured positions do not tell the layout from its mirror "
                              "image: give --origin, --x-axis and --y-side")
        for k, a in enumerate(names):
            start[ids.index(a), :2] = R2d @ P[k] + t2d
    for a in names:
        free[ids.index(a), :2] = True
    unplaced = [a for a in ids if a not in placed and a in {p.anchor_a for p in pairs}
                | {p.anchor_b for p in pairs}]
    if unplaced:
        notes.append("anchor(s) " + ", ".join(map(str, unplaced)) + " have ranges to one "
                     "anchor only: not placed")
    for a in unplaced:
        if math.isnan(prior[ids.index(a), 0]):
            raise SurveyError(f"anchor {a}: ranges to one other anchor only and no configured "
                              "position: it cannot be placed")
    return start, free
