"""A moving tag's ranges: the batch adjustment of its path and the anchors together, and
the directions the ranges fix well enough to move (:mod:`uwbd.tools.survey`, "a moving tag's
ranges")."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from drivers.frames import UwbRanges
from uwbd.fusion.core import native
from uwbd.fusion.core.lsq import coplanar, multilaterate
from uwbd.fusion.core.rotation import Array
from uwbd.fusion.policy.mirror import MirrorSide
from uwbd.tools.survey.model import MAX_EVALUATIONS, MIN_EPOCH_RANGES, ROBUST_SCALE, TRUST, Settings


@dataclass
class TagData:
    """Tag ranges ready for the adjustment: range j measured ``range_m[j]`` to anchor
    ``anchor[j]`` (row index) from the tag at ``(1 - alpha) P[k0] + alpha P[k1]``."""

    knots: Array  # K x 3 initial tag positions
    times: Array  # K, s
    anchor: npt.NDArray[np.intp]
    k0: npt.NDArray[np.intp]
    k1: npt.NDArray[np.intp]
    alpha: Array
    range_m: Array


@dataclass
class Problem:
    ids: list[int]  # row i of the anchor arrays is anchor ids[i]
    start: Array  # N x 3 initial positions (also the held values)
    free: npt.NDArray[np.bool_]  # N x 3: which coordinates are estimated
    prior: Array  # N x 3 (nan: no prior)
    prior_sigma_m: float
    tag: TagData | None
    range_sigma_m: float
    pair_i: npt.NDArray[np.intp]
    pair_j: npt.NDArray[np.intp]
    pair_m: Array
    pair_sigma: Array
    offsets: bool
    offset_sigma_m: float

    def __post_init__(self) -> None:
        self.K = 0 if self.tag is None else len(self.tag.knots)
        self.N = len(self.ids)
        col = np.full((self.N, 3), -1, dtype=np.intp)
        col[self.free] = 3 * self.K + np.arange(int(self.free.sum()))
        self.anchor_col = col
        self.n_anchor = int(self.free.sum())
        self.offset_col = (3 * self.K + self.n_anchor + np.arange(self.N) if self.offsets
                           else np.zeros(0, dtype=np.intp))
        self.n = 3 * self.K + self.n_anchor + len(self.offset_col)
        self.prior_rows = np.flatnonzero((self.free & ~np.isnan(self.prior)).ravel())
        self._structure()

    def x0(self) -> Array:
        parts = [self.tag.knots.ravel() if self.tag is not None else np.zeros(0),
                 self.start[self.free], np.zeros(len(self.offset_col))]
        return np.concatenate(parts)

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        P = x[:3 * self.K].reshape(self.K, 3)
        A = self.start.copy()
        A[self.free] = x[3 * self.K:3 * self.K + self.n_anchor]
        b = x[self.offset_col] if self.offsets else np.zeros(self.N)
        return P, A, b

    def _structure(self) -> None:
        """Row and column of every Jacobian entry (fixed: only the values change)."""
        rows: list[npt.NDArray[np.intp]] = []
        cols: list[npt.NDArray[np.intp]] = []
        self.n_tag = 0 if self.tag is None else len(self.tag.range_m)
        r0 = 0
        if self.tag is not None:
            t = self.tag
            j = np.arange(self.n_tag)
            for k in (t.k0, t.k1):  # the two knots' x, y, z
                rows.append(np.repeat(j, 3))
                cols.append((3 * k[:, None] + np.arange(3)).ravel())
            ac = self.anchor_col[t.anchor]  # n_tag x 3
            self._tag_anchor_mask = (ac >= 0).ravel()
            rows.append(np.repeat(j, 3)[self._tag_anchor_mask])
            cols.append(ac.ravel()[self._tag_anchor_mask])
            if self.offsets:
                rows.append(j)
                cols.append(self.offset_col[t.anchor])
            r0 = self.n_tag
        self.n_pair = len(self.pair_m)
        if self.n_pair:
            j = r0 + np.arange(self.n_pair)
            self._pair_masks = []
            for idx in (self.pair_i, self.pair_j):
                ac = self.anchor_col[idx]
                mask = (ac >= 0).ravel()
                self._pair_masks.append(mask)
                rows.append(np.repeat(j, 3)[mask])
                cols.append(ac.ravel()[mask])
            r0 += self.n_pair
        self.n_prior = len(self.prior_rows)
        rows.append(r0 + np.arange(self.n_prior))
        cols.append(self.anchor_col.ravel()[self.prior_rows])
        r0 += self.n_prior
        if self.offsets:
            rows.append(r0 + np.arange(self.N))
            cols.append(self.offset_col)
            r0 += self.N
        self.m = r0
        self._rows = np.concatenate(rows)
        self._cols = np.concatenate(cols)

    def residuals(self, x: Array) -> Array:
        P, A, b = self.unpack(x)
        out: list[Array] = []
        if self.tag is not None:
            t = self.tag
            p = (1 - t.alpha)[:, None] * P[t.k0] + t.alpha[:, None] * P[t.k1]
            d = np.linalg.norm(p - A[t.anchor], axis=1)
            out.append((d + b[t.anchor] - t.range_m) / self.range_sigma_m)
        if self.n_pair:
            d = np.linalg.norm(A[self.pair_i] - A[self.pair_j], axis=1)
            out.append((d - self.pair_m) / self.pair_sigma)
        out.append((A.ravel()[self.prior_rows] - self.prior.ravel()[self.prior_rows])
                   / self.prior_sigma_m)
        if self.offsets:
            out.append(b / self.offset_sigma_m)
        return np.concatenate(out)

    def jacobian(self, x: Array) -> Any:
        P, A, _ = self.unpack(x)
        vals: list[Array] = []
        if self.tag is not None:
            t = self.tag
            p = (1 - t.alpha)[:, None] * P[t.k0] + t.alpha[:, None] * P[t.k1]
            diff = p - A[t.anchor]
            u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
            u /= self.range_sigma_m
            vals += [((1 - t.alpha)[:, None] * u).ravel(), (t.alpha[:, None] * u).ravel(),
                     (-u).ravel()[self._tag_anchor_mask]]
            if self.offsets:
                vals.append(np.full(self.n_tag, 1 / self.range_sigma_m))
        if self.n_pair:
            diff = A[self.pair_i] - A[self.pair_j]
            u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
            u /= self.pair_sigma[:, None]
            vals += [u.ravel()[self._pair_masks[0]], (-u).ravel()[self._pair_masks[1]]]
        vals.append(np.full(self.n_prior, 1 / self.prior_sigma_m))
        if self.offsets:
            vals.append(np.full(self.N, 1 / self.offset_sigma_m))
        return scipy.sparse.csr_matrix((np.concatenate(vals), (self._rows, self._cols)),
                                       shape=(self.m, self.n))


def _loss(n_tag: int) -> Any:
    """The robust loss for scipy (ρ, ρ', ρ'' of z = f²): ``arctan`` at ``ROBUST_SCALE`` on the
    first ``n_tag`` rows (the tag's ranges: NLOS), least squares on the rest (the pairs'
    medians, already robust; the priors)."""
    c2 = ROBUST_SCALE**2

    def loss(z: Array) -> Array:
        out = np.empty((3, len(z)))
        out[0], out[1], out[2] = z, 1.0, 0.0
        u = z[:n_tag] / c2
        out[0, :n_tag] = c2 * np.arctan(u)
        out[1, :n_tag] = 1 / (1 + u**2)
        out[2, :n_tag] = -2 * u / (c2 * (1 + u**2) ** 2)
        return out
    return loss


def solve(problem: Problem | Confined) -> tuple[Array, Any, int]:
    """The robust adjustment from the problem's start: the solution, the loss-weighted
    Jacobian there, the number of function evaluations."""
    result = scipy.optimize.least_squares(
        problem.residuals, problem.x0(), jac=problem.jacobian, method="trf",
        loss=_loss(problem.n_tag), x_scale="jac", tr_solver="lsmr", xtol=1e-10, ftol=1e-10,
        gtol=1e-10, max_nfev=MAX_EVALUATIONS)
    return np.asarray(result.x, dtype=float), result.jac, int(result.nfev)


def anchor_covariance(problem: Problem | Confined, jac: Any) -> Array:
    """The covariance (JᵀJ)⁻¹ of everything but the tag positions (anchor coordinates and
    offsets), those eliminated by the Schur complement; in units of the
    residuals' σ."""
    J = scipy.sparse.csc_matrix(jac)
    H = (J.T @ J).tocsc()
    nt = 3 * problem.K
    Haa = H[nt:, nt:].toarray()
    if nt:
        Htt = H[:nt, :nt].tocsc()
        Hta = H[:nt, nt:].toarray()
        # a tag position no range reaches (it cannot happen: each knot has 4 ranges) would
        # make Htt singular; a tiny ridge keeps the factorisation alive
        Htt = Htt + scipy.sparse.identity(nt, format="csc") * 1e-12
        lu = scipy.sparse.linalg.splu(Htt)
        Haa = Haa - Hta.T @ lu.solve(Hta)
    return np.asarray(np.linalg.pinv(Haa, hermitian=True), dtype=float)


def trusted_directions(problem: Problem) -> tuple[Array, Array]:
    """The directions of the free anchor coordinates that the ranges fix at least ``TRUST``
    times better (in σ) than the priors, and the rest: the eigenvectors of the ranges' own
    information about the anchors (the tag positions and offsets marginalised; the
    priors' information taken out), at the start (the configured layout). The adjustment
    moves the anchors in the first only: a direction the ranges hardly fix is where model
    errors (NLOS, the bias of a tag position estimated per epoch from few ranges) push the
    solution, far, and where that far-off solution then looks well fixed."""
    na = problem.n_anchor
    cov = anchor_covariance(problem, problem.jacobian(problem.x0()))
    info = np.linalg.pinv(cov[:na, :na], hermitian=True)
    prior = np.zeros(na)
    prior[problem.anchor_col.ravel()[problem.prior_rows] - 3 * problem.K] = \
        1 / problem.prior_sigma_m**2
    lam, V = np.linalg.eigh(0.5 * (info + info.T) - np.diag(prior))
    keep = lam * problem.prior_sigma_m**2 >= TRUST**2
    return V[:, keep], V[:, ~keep]


class Confined:
    """A problem whose free anchor coordinates move from ``origin`` along the columns of
    ``V`` only: x = T xr + shift."""

    def __init__(self, problem: Problem, V: Array, origin: Array) -> None:
        self.problem, self.V, self.origin = problem, V, origin
        self.K = problem.K
        self.n_tag = problem.n_tag
        nt, na, k = 3 * problem.K, problem.n_anchor, V.shape[1]
        rest = problem.n - nt - na
        self.n_anchor = k
        rows = [np.arange(nt), nt + np.repeat(np.arange(na), k), nt + na + np.arange(rest)]
        cols = [np.arange(nt), nt + np.tile(np.arange(k), na), nt + k + np.arange(rest)]
        vals = [np.ones(nt), V.ravel(), np.ones(rest)]
        self.T = scipy.sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(problem.n, nt + k + rest))
        self.shift = np.zeros(problem.n)
        self.shift[nt:nt + na] = origin

    def full(self, xr: Array) -> Array:
        return np.asarray(self.T @ xr + self.shift, dtype=float)

    def x0(self) -> Array:
        x = self.problem.x0()
        nt, na = 3 * self.K, self.problem.n_anchor
        return np.concatenate([x[:nt], self.V.T @ (x[nt:nt + na] - self.origin),
                               x[nt + na:]])

    def residuals(self, xr: Array) -> Array:
        return self.problem.residuals(self.full(xr))

    def jacobian(self, xr: Array) -> Any:
        return (self.problem.jacobian(self.full(xr)) @ self.T).tocsr()


def layout_part(cov: Array, A: Array, free: npt.NDArray[np.bool_], vertical_only: bool
                 ) -> tuple[float, float]:
    """RMS 3-D 1-σ of the anchors relative to each other (the motions of the whole layout
    that the ranges cannot see projected out of the free coordinates' covariance) and of
    the rest (where the layout sits). In the config's frame those are the 6 rigid motions;
    in the user's (``vertical_only``: x, y and the heading held) the height and the tilts."""
    n = len(A)
    c = A.mean(axis=0)
    G = np.zeros((n, 3, 6))
    for k in range(3):
        G[:, k, k] = 1.0
    for k, axis in enumerate(np.eye(3)):
        G[:, :, 3 + k] = np.cross(axis, A - c)
    if vertical_only:  # a shift up and the two tilts, as they move the heights
        G = G[:, :, [2, 3, 4]]
        G[:, :2, :] = 0.0
    Gf = G.reshape(3 * n, -1)[free.ravel()]
    U, s, _ = np.linalg.svd(Gf, full_matrices=False)
    Q = U[:, s > 1e-9 * max(float(s.max()), 1e-300)] if s.size else U[:, :0]
    proj = np.eye(len(Gf)) - Q @ Q.T
    shape = proj @ cov @ proj
    total, inner = float(np.trace(cov)), float(np.trace(shape))
    return math.sqrt(max(inner, 0.0) / n), math.sqrt(max(total - inner, 0.0) / n)


def usable(uwb: Sequence[UwbRanges], anchors: Mapping[int, int], max_range_m: float
            ) -> list[tuple[int, list[tuple[int, float]]]]:
    """Per message: time and the (anchor row, range) it holds that can be used (finite,
    positive, within ``max_range_m``, to a known anchor, one per anchor)."""
    out = []
    for msg in uwb:
        seen: set[int] = set()
        kept = []
        for r in msg.ranges:
            row = anchors.get(r.anchor_id)
            if (row is None or row in seen or not math.isfinite(r.range_m)
                    or not 0 < r.range_m <= max_range_m):
                continue
            seen.add(row)
            kept.append((row, r.range_m))
        if kept:
            out.append((msg.t_ns, kept))
    return out


def tag_data(messages: list[tuple[int, list[tuple[int, float]]]], A: Array,
              settings: Settings) -> TagData | None:
    """Tag positions to solve for, and each range's place between them; the positions
    start from multilateration against the starting anchors."""
    core = native.core  # the least squares' implementation, for this survey
    mirror = MirrorSide(A, settings.tag_side, settings.height_range_m, core=core)
    side = mirror.sign if mirror.ambiguous else 1
    flat = coplanar(A) if len(A) >= 4 else True
    sizes = [len(kept) for _, kept in messages]
    epochs = bool(sizes) and float(np.median(sizes)) >= 3
    groups: list[tuple[float, list[tuple[int, float, float]]]] = []  # (t, [(row, r, t)])
    if epochs:
        for t_ns, kept in messages:
            if len(kept) >= MIN_EPOCH_RANGES:
                groups.append((t_ns / 1e9, [(a, r, t_ns / 1e9) for a, r in kept]))
    else:
        t0 = messages[0][0] / 1e9 if messages else 0.0
        windows: dict[int, list[tuple[int, float, float]]] = {}
        for t_ns, kept in messages:
            t = t_ns / 1e9
            slot = int((t - t0) // settings.window_s)
            windows.setdefault(slot, []).extend((a, r, t) for a, r in kept)
        for slot, items in sorted(windows.items()):
            if len({a for a, _, _ in items}) >= MIN_EPOCH_RANGES:
                groups.append((t0 + (slot + 0.5) * settings.window_s, items))
    knots: list[Array] = []
    times: list[float] = []
    members: list[list[tuple[int, float, float]]] = []
    previous: Array | None = None
    for t, items in groups:
        rows = np.array([a for a, _, _ in items])
        ranges = np.array([r for _, r, _ in items])
        start = previous if previous is not None else (
            mirror.start_point() if mirror.ambiguous else None)
        fix = multilaterate(A[rows], ranges, settings.range_sigma_m, x0=start,
                            side=side, core=core)
        if fix is None or (not flat and fix.rms_m > 10 * settings.range_sigma_m):
            fix = multilaterate(A[rows], ranges, settings.range_sigma_m, side=side, core=core)
        if fix is None or not np.all(np.isfinite(fix.position_m)):
            continue
        if mirror.ambiguous and mirror.side_of(fix.position_m) * side < 0:
            fix = multilaterate(A[rows], ranges, settings.range_sigma_m,
                                x0=mirror.reflect(fix.position_m), side=side,
                                core=core) or fix
        previous = fix.position_m.copy()
        knots.append(fix.position_m.copy())
        times.append(t)
        members.append(items)
    if not knots:
        return None
    anchor: list[int] = []
    k0: list[int] = []
    k1: list[int] = []
    alpha: list[float] = []
    rng: list[float] = []
    T = np.array(times)
    for k, items in enumerate(members):
        for a, r, t in items:
            if epochs:
                lo, hi, w = k, k, 0.0
            else:  # between the knots around t, if they are neighbours in time
                lo = int(np.clip(np.searchsorted(T, t) - 1, 0, len(T) - 1))
                hi = min(lo + 1, len(T) - 1)
                gap = T[hi] - T[lo]
                if hi == lo or gap > 1.5 * settings.window_s or not T[lo] <= t <= T[hi]:
                    lo = hi = k
                    w = 0.0
                else:
                    w = (t - T[lo]) / gap
            anchor.append(a)
            k0.append(lo)
            k1.append(hi)
            alpha.append(w)
            rng.append(r)
    return TagData(np.array(knots), np.array(times), np.array(anchor, dtype=np.intp),
                    np.array(k0, dtype=np.intp), np.array(k1, dtype=np.intp),
                    np.array(alpha), np.array(rng))
