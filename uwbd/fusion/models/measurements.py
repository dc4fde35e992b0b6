"""Measurement rows: the linearised models of docs/ekf.md §4, one function per kind.

Each returns :class:`Rows` — ``H`` (m×n) at the current state, residuals ``y = z − h(x)``,
noise variances ``R``, and what each row is — for :meth:`Eskf.sequential_update`. When to
use which is the filter's policy, not theirs.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from uwbd.fusion.checks.anchor_consistency import single_fault_estimates
from uwbd.fusion.core.eskf import Eskf
from uwbd.fusion.core.layout import N_CORE, P_, RANGE_CHECK, TH_, V_
from uwbd.fusion.core.lsq import LsqFix
from uwbd.fusion.core.rotation import Array, skew


class Rows(NamedTuple):
    """Measurement rows of one update: ``H`` (m×n), residuals ``y``, noise variances ``R``,
    and what each row is (kind, key) for its report."""

    H: Array
    y: Array
    R: Array
    keys: list[tuple[str, str]]

    @staticmethod
    def empty(n: int) -> Rows:
        return Rows(np.zeros((0, n)), np.zeros(0), np.zeros(0), [])

    @staticmethod
    def stack(parts: list[Rows]) -> Rows:
        parts = [r for r in parts if r.keys]
        if len(parts) <= 1:
            return parts[0] if parts else Rows.empty(0)
        return Rows(np.vstack([r.H for r in parts]), np.concatenate([r.y for r in parts]),
                    np.concatenate([r.R for r in parts]), [k for r in parts for k in r.keys])


def range_rows(ekf: Eskf, lever_m: Array, ids: list[int], anchors: Array, ranges: Array,
               var: Array, columns: Mapping[int, tuple[int, ...]],
               lever_columns: tuple[int, ...] = ()) -> Rows:
    """One row per range: ``h = |p + R l − a| + Σ b`` over the range-model states whose
    columns ``columns`` gives the anchor (antenna delay, multipath; none if absent), and,
    with ``lever_columns`` (the lever arm's error states, ``l`` already holding them),
    ``H_δl = uᵀ R`` on those. The
    reference of the C core's tight epoch (:meth:`Eskf.fuse_ranges`): a range whose
    antenna is within 1 mm of its anchor is dropped here (the C core fuses a zero row)."""
    keys = range_keys(ids)
    U, y, keep = range_innovations(ekf, lever_m, ids, anchors, ranges, columns)
    if not keep.all():
        ids = [a for a, k in zip(ids, keep, strict=True) if k]
        keys = [k for k, kept in zip(keys, keep, strict=True) if kept]
        U, y, var = U[keep], y[keep], var[keep]
    H = np.zeros((len(ids), ekf.n))
    H[:, P_] = U
    H[:, TH_] = U @ (-ekf.R @ skew(lever_m))
    for i, anchor_id in enumerate(ids):
        for k in columns.get(anchor_id, ()):
            H[i, k] = 1.0
    if lever_columns:
        H[:, list(lever_columns)] = U @ ekf.R
    return Rows(H, y, var, keys)


def range_innovations(ekf: Eskf, lever_m: Array, ids: list[int], anchors: Array,
                      ranges: Array, columns: Mapping[int, tuple[int, ...]]
                      ) -> tuple[Array, Array, Array]:
    """What :func:`range_rows` predicts, without the rows: the unit vectors anchor →
    antenna, the innovations ``z − h``, and which ranges have a line to linearise (the
    antenna over 1 mm from its anchor)."""
    diff = np.array(ekf.p) + ekf.R @ lever_m - anchors
    dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    keep = dist >= 1e-3  # the antenna on an anchor: no line of sight to linearise
    U = diff / np.where(keep, dist, 1.0)[:, None]
    h = dist
    b_r = ekf.b_r
    for i, anchor_id in enumerate(ids):
        for k in columns.get(anchor_id, ()):
            h[i] += b_r[k - N_CORE]
    return U, ranges - h, keep


# layout.RANGE_CHECK's blocks (U, y, b, d) as per-range [start, end), as the C writes them
_CHECK_ENDS = tuple(itertools.accumulate(RANGE_CHECK.values()))
_CHECK_BLOCKS = tuple(zip((0, *_CHECK_ENDS[:-1]), _CHECK_ENDS, strict=True))
_CHECK_PER_RANGE = _CHECK_ENDS[-1]
assert tuple(RANGE_CHECK) == ("U", "y", "b", "d")


class RangeCheck(NamedTuple):
    """An epoch's ranges before their update, as the installation checks take them: unit
    vectors anchor → antenna (k×3), innovations (k), and, when asked, Baarda's single-fault
    estimate of each range and its weight (None when not asked or ``S`` is singular)."""

    U: Array
    y: Array
    b: Array | None
    d: Array | None


def range_check(ekf: Eskf, lever_m: Array, ids: list[int], anchors: Array, ranges: Array,
                var: Array | None, columns: Mapping[int, tuple[int, ...]]) -> RangeCheck | None:
    """:func:`range_innovations` and, with ``var``, the single-fault estimates from
    ``S = H P Hᵀ + diag(var)`` (:func:`~uwbd.fusion.checks.anchor_consistency.single_fault_
    estimates`); None when an antenna is within 1 mm of an anchor. On the C core, one call
    (``State.range_check``); this is its reference."""
    core: Any = ekf.core_state
    if core is not None:
        k = len(ids)
        out = np.empty(_CHECK_PER_RANGE * k)
        made = core.range_check(lever_m, anchors, ranges, var,
                                tuple([columns.get(a, ()) for a in ids]), out)
        if made is None:
            return None
        (u0, u1), (y0, y1), (b0, b1), (d0, d1) = (
            (k * start, k * end) for start, end in _CHECK_BLOCKS)
        U, y = out[u0:u1].reshape(k, 3), out[y0:y1]
        return RangeCheck(U, y, out[b0:b1], out[d0:d1]) if made else \
            RangeCheck(U, y, None, None)
    U, y, keep = range_innovations(ekf, lever_m, ids, anchors, ranges, columns)
    if not keep.all():
        return None
    if var is None:
        return RangeCheck(U, y, None, None)
    H = range_rows(ekf, lever_m, ids, anchors, ranges, var, columns).H
    estimates = single_fault_estimates(y, H @ ekf.P @ H.T + np.diag(var))
    return RangeCheck(U, y, *(estimates or (None, None)))


RANGE_KEYS: dict[int, tuple[str, str]] = {}  # anchor id -> its rows' (kind, key)


def range_keys(ids: list[int]) -> list[tuple[str, str]]:
    """What each range row is, ``("range", "<anchor id>")``: made once per anchor."""
    return [RANGE_KEYS.get(a) or _range_key(a) for a in ids]


def _range_key(anchor_id: int) -> tuple[str, str]:
    key = RANGE_KEYS[anchor_id] = ("range", str(anchor_id))
    return key


def position_rows(ekf: Eskf, lever_m: Array, fix: LsqFix, axes: int, sigma_m: float) -> Rows:
    """A least-squares fix of the antenna (loose mode), ``axes`` 3, or 2 with the height
    held; its own covariance (ranges of σ ``sigma_m``), at least 2 cm per axis, widened by
    the fix's own variance factor where its residuals say the ranges were worse than σ
    (a window's ranges of a moving tag are up to 0.2 s apart; multipath)."""
    R = ekf.R
    p_ant = np.array(ekf.p) + R @ lever_m
    H = np.zeros((axes, ekf.n))
    H[:, P_] = np.eye(3)[:axes]
    H[:, TH_] = (-R @ skew(lever_m))[:axes]
    used = int(fix.used.sum())
    factor = max(1.0, used * fix.rms_m**2 / ((used - axes) * sigma_m**2)) if used > axes \
        else 1.0
    var = np.maximum(factor * np.diag(fix.covariance)[:axes], 0.02**2)
    return Rows(H, fix.position_m[:axes] - p_ant[:axes], var,
                [("position", "xyz"[axis]) for axis in range(axes)])


def zupt_rows(ekf: Eskf, sigma_mps: float) -> Rows:
    """At rest: ``h = v``."""
    H = np.zeros((3, ekf.n))
    H[:, V_] = np.eye(3)
    return Rows(H, -np.array(ekf.v), np.full(3, sigma_mps**2),
                [("zupt", axis) for axis in "xyz"])


def nhc_rows(ekf: Eskf, sigma_mps: float) -> Rows:
    """A ground vehicle: no body lateral or vertical velocity, ``h = (v_b,y, v_b,z)``."""
    Rt = ekf.R.T
    v_b = Rt @ np.array(ekf.v)
    H = np.zeros((2, ekf.n))
    H[:, V_] = Rt[1:]
    H[:, TH_] = skew(v_b)[1:]
    return Rows(H, -v_b[1:], np.full(2, sigma_mps**2), [("nhc", "y"), ("nhc", "z")])


def height_rows(ekf: Eskf, height_m: float, sigma_m: float) -> Rows:
    """A known height: ``h = p_z``."""
    H = np.zeros((1, ekf.n))
    H[0, 2] = 1.0
    return Rows(H, np.array([height_m - ekf.p[2]]), np.array([sigma_m**2]), [("height", "z")])
