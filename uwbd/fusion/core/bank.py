"""The bank's reference arithmetic (docs/ekf.md §6): every sub-filter at once, as numpy
stacks ``P_k`` (K×n×n) and offsets ``d_k`` (K×n), for :class:`~.eskf.Eskf`, which the C
core's ``State`` is held to (tests/test_core.py); and the covariance clamp both the main
filter and each sub-filter take."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from uwbd.fusion.core.rotation import Array


def symmetric(P: Array) -> Array:
    """``(P + Pᵀ)/2`` of one covariance or of a stack of them."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def bank_variances(bank_var: Array | None, count: int, n: int) -> Array:
    """The variances each of ``count`` sub-filters adds at a start (``None``: none), checked
    to be ``count × n``."""
    if bank_var is None:
        return np.zeros((count, n))
    out = np.array(bank_var, dtype=float).reshape(-1)
    if out.size != count * n:
        raise ValueError(f"bank_var: {count * n} numbers expected, got {out.size}")
    return out.reshape(count, n)


def bank_started(P: Array, bank_var: Array) -> tuple[Array, Array]:
    """The bank started anew from the main filter's ``P``: offsets ``d_k = 0``, covariances
    ``P_k = P + diag(bank_var_k)``."""
    count, n = bank_var.shape
    Pk = np.repeat(P[None], count, axis=0)
    Pk[:, np.arange(n), np.arange(n)] += bank_var
    return np.zeros((count, n)), Pk


def bank_update(Pk: Array, d: Array, left_out: npt.NDArray[np.int64], H: Array, y: Array,
                R: Array, weights: Sequence[float], ids: Sequence[int] | None,
                considered: slice | None, dx: Array) -> None:
    """The main filter's update (rows, their weights, the correction ``δx`` it injected)
    on every sub-filter: :func:`bank_rows`, then ``d_k ← d_k − δx`` (the nominal state
    moved by ``δx``). ``ids``: the first rows' anchors (None: no row is an anchor's)."""
    if not len(left_out):
        return
    anchors = np.full(len(y), -1, dtype=np.int64)
    if ids is not None:
        anchors[:len(ids)] = ids
    bank_rows(Pk, d, left_out, H, y, R, weights, anchors, considered)
    d -= dx


def bank_rows(Pk: Array, d: Array, left_out: npt.NDArray[np.int64], H: Array, y: Array,
              R: Array, weights: Sequence[float], anchors: npt.NDArray[np.int64],
              considered: slice | None) -> None:
    """Rows fused on every sub-filter in place, each from its offset: row ``i`` (``H_i``,
    residual ``y_i`` at the nominal state, variance ``R_i``) with the main filter's weight
    ``weights[i]`` (0: not fused), left out of the sub-filter whose anchor (``left_out``)
    is the row's (``anchors[i]``; −1: none), and of one whose ``S`` is not finite or below
    ``R_i``; the gain and Joseph form of ``Eskf.sequential_update``."""
    for i, w in enumerate(weights):
        if not w > 0.0:
            continue
        h, r = H[i], float(R[i])
        U = Pk @ h  # (K, n)
        S = U @ h + r
        nu = y[i] - d @ h
        with np.errstate(invalid="ignore"):
            ok = (left_out != anchors[i]) & np.isfinite(S) & np.isfinite(nu) \
                & ~(r * (1 - 1e-9) > S)
        j = np.flatnonzero(ok)
        if not len(j):
            continue
        U, S, nu = U[j], S[j], nu[j]
        k = U / (S + r * (1.0 / w - 1.0))[:, None]
        if considered is not None:
            k[:, considered] = 0.0
        d[j] += k * nu[:, None]
        g = U - 0.5 * S[:, None] * k
        Pk[j] -= k[:, :, None] * g[:, None, :] + g[:, :, None] * k[:, None, :]


def clamped(P: Array, limit: Array) -> Array:
    """``P`` with every variance within ``limit`` and none negative (a row and its column
    scaled, which keeps it positive semi-definite); ``P`` itself when nothing was out."""
    d = np.diag(P)
    if not ((d > limit).any() or (d < 0).any()):
        return P
    scale = np.sqrt(np.minimum(1.0, limit / np.maximum(d, 1e-300)))
    P = P * scale[:, None] * scale[None, :]
    negative = np.diag(P) < 0
    if negative.any():
        P[np.diag_indices(len(P))] = np.where(negative, 1e-9, np.diag(P))
    return P


# the main filter's major-axis σ and vertical variance; per sub-filter k: those of P_k − P,
# those of P_k, and its offset's horizontal and vertical size
SeparationNumbers = tuple[float, float, list[tuple[float, float, float, float, float, float]]]


def separation_numbers(P: Array, bank_d: Array, bank_P: Array) -> SeparationNumbers:
    """The numbers the solution separation (:mod:`uwbd.fusion.checks.separation`) judges,
    in the position states: the main filter's σ along the major axis of its horizontal
    ellipse and its vertical variance; and for each sub-filter ``k`` the same two of
    ``P_k − P`` (the separation's covariance) and of ``P_k``, and ``|d_k|`` horizontally and
    vertically. The reference of the C core's ``State.separation_numbers``."""
    Pk = bank_P[:, :3, :3]
    D = Pk - P[:3, :3]
    rows = np.stack([major_sigma(D), D[:, 2, 2], major_sigma(Pk), Pk[:, 2, 2],
                     np.hypot(bank_d[:, 0], bank_d[:, 1]), np.abs(bank_d[:, 2])], axis=1)
    members = [(a, b, c, d, e, f) for a, b, c, d, e, f in rows.tolist()]
    return float(major_sigma(P[None, :3, :3])[0]), float(P[2, 2]), members


def major_sigma(C: Array) -> Array:
    """σ along the major axis of each horizontal ellipse of ``C`` (…×3×3), 0 where the
    numbers say less."""
    xx, xy, yy = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    half = (xx - yy) / 2
    result: Array = np.sqrt(np.maximum((xx + yy) / 2 + np.sqrt(half * half + xy * xy), 0.0))
    return result
