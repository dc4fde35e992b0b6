"""Rauch–Tung–Striebel smoothing of a recorded filter run: the best trajectory from a log.

Offline only (``uwbd report``): each epoch's estimate is improved with the measurements that
came after it. The filter, built with ``record=True``, keeps per UWB epoch the nominal state
and covariance before and after the update and the transition ``Φ`` that led there from the
previous epoch (docs/ekf.md §7). The backward pass runs on the error state, relative to each
epoch's own nominal:

    C_k   = P_k⁺ Φ_{k+1}ᵀ (P_{k+1}⁻)⁻¹
    δ_k   = C_k (x^s_{k+1} ⊖ x⁻_{k+1})            x^s_k = x_k⁺ ⊕ δ_k
    P^s_k = P_k⁺ + C_k (P^s_{k+1} − P_{k+1}⁻) C_kᵀ

An epoch without a link to its predecessor (before the heading is aligned, after an IMU gap
or a re-initialisation) starts a new stretch: stretches are smoothed on their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uwbd.fusion.core.layout import BA_, BG_, N_CORE, P_, TH_, V_
from uwbd.fusion.core.rotation import Array, quat_from_rotvec, quat_mul


@dataclass(frozen=True)
class Nominal:
    """A copy of the nominal state: position, velocity, attitude (w, x, y, z), the biases."""

    p: Array
    v: Array
    q: Array
    b_g: Array
    b_a: Array
    b_r: Array

    def minus(self, other: Nominal) -> Array:
        """``self ⊖ other``: the error state that takes ``other`` to ``self``."""
        w, x, y, z = other.q
        dq = quat_mul(np.array([w, -x, -y, -z]), self.q)  # other⁻¹ ⊗ self
        return np.concatenate([self.p - other.p, self.v - other.v, _log(dq),
                               self.b_g - other.b_g, self.b_a - other.b_a, self.b_r - other.b_r])

    def plus(self, dx: Array) -> Nominal:
        """``self ⊕ δx`` (the filter's own injection)."""
        q = quat_mul(self.q, quat_from_rotvec(dx[TH_]))
        return Nominal(self.p + dx[P_], self.v + dx[V_], q / np.linalg.norm(q),
                       self.b_g + dx[BG_], self.b_a + dx[BA_], self.b_r + dx[N_CORE:])


@dataclass(frozen=True)
class EpochRecord:
    t_ns: int
    prior: Nominal
    P_prior: Array
    post: Nominal
    P_post: Array
    Phi: Array | None  # from the previous record to this one; None: a new stretch starts


def smooth(records: list[EpochRecord]) -> list[tuple[int, Nominal, Array]]:
    """Smoothed ``(t_ns, nominal, covariance)`` for every record, in order."""
    out: list[tuple[int, Nominal, Array]] = [(r.t_ns, r.post, r.P_post) for r in records]
    for k in range(len(records) - 2, -1, -1):
        nxt = records[k + 1]
        if nxt.Phi is None or nxt.P_prior.shape != records[k].P_post.shape:
            continue  # the last epoch of a stretch: its filtered estimate is already final
        cur = records[k]
        _, x_next, P_next = out[k + 1]
        # C = P_post Φᵀ P_prior⁻¹, on the states with a variance (one held known, at zero
        # variance, as the lever arm's error by default, is not smoothed)
        live = np.diag(nxt.P_prior) > 0.0
        C = np.zeros_like(cur.P_post)
        C[:, live] = np.linalg.solve(nxt.P_prior[np.ix_(live, live)],
                                     (nxt.Phi @ cur.P_post)[live]).T
        dx = C @ x_next.minus(nxt.prior)
        P = cur.P_post + C @ (P_next - nxt.P_prior) @ C.T
        out[k] = (cur.t_ns, cur.post.plus(dx), 0.5 * (P + P.T))
    return out


def _log(q: Array) -> Array:
    """``Log(q)``: the rotation vector of a unit quaternion (w, x, y, z)."""
    w, v = q[0], q[1:]
    if w < 0:
        w, v = -w, -v
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return 2.0 * v
    return 2.0 * math.atan2(s, w) * v / s
