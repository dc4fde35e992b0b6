"""UWB-only position: Gauss–Newton multilateration with covariance.

Residual ``r_i = |x − a_i| − d_i``, Jacobian rows ``u_iᵀ = (x − a_i)ᵀ/|x − a_i|``; each step
solves ``(JᵀJ) δ = −Jᵀ r``; the covariance of the fix is ``σ² (JᵀJ)⁻¹``.

* **2D / known height**: with ``fixed_z`` the height is held and only x, y are solved, for
  anchors that are (nearly) coplanar, where the vertical is poorly observed and mirrored.
* Gauss–Newton converges only linearly where the vertical is weakly observed (a tag between
  two anchor planes): the iteration stops at a 1 mm step, or keeps a fix still moving by
  < 1 cm after 20 steps. In the plane of most anchors it overshoots the height to and fro
  (the squares' curvature there is what Gauss–Newton leaves out): the step taken is halved
  while it raises the squares (``MAX_HALVINGS`` at most, after which it is taken as it
  is), which damps the swing. Both tests above judge the full step: a search cut short
  has not converged.
* **One outlier**: with at least one range more than the unknowns need, the range with the
  largest studentised residual is dropped when that residual exceeds ``outlier_sigma``,
  and the fix is solved again. 5 σ by default: NLOS excess is typically >= 0.5 m, while
  uncalibrated antenna delays bias good ranges by 0.1-0.25 m, which 3 σ (at σ = 0.1 m)
  would throw away, weakening the geometry (measured: worse on the real flight).

The iteration and the leverages run in the C core, the ``core`` each caller hands over (the
one chosen when its filter or tool was made, :mod:`.native`); the code here is the reference
it translates, which runs with ``core`` None.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbd.fusion.core.native import Core
from uwbd.fusion.core.rotation import Array

MAX_ITERATIONS = 20
CONVERGED_M = 1e-3  # a step this small ends the iteration: far below any range noise
ACCEPT_LAST_STEP_M = 1e-2  # after MAX_ITERATIONS, a fix still creeping this slowly is kept
MAX_HALVINGS = 10  # a step is cut to 1/1024 at most


@dataclass(frozen=True)
class LsqFix:
    """A multilateration solution. ``used`` marks the ranges kept; ``rms_m`` is the RMS of
    their residuals."""

    position_m: Array
    covariance: Array
    residuals_m: Array
    used: Array
    rms_m: float
    iterations: int


def coplanar(anchors_m: Array, tolerance_m: float = 0.3) -> bool:
    """Do the anchors lie (within ``tolerance_m``) on one plane?"""
    if len(anchors_m) < 4:
        return True
    centred = anchors_m - anchors_m.mean(axis=0)
    return bool(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(anchors_m))
                < tolerance_m)


def multilaterate(anchors_m: Array, ranges_m: Array, sigma_m: float = 0.1,
                  x0: Array | None = None, fixed_z: float | None = None,
                  outlier_sigma: float = 5.0, side: int = 1, *, core: Core) -> LsqFix | None:
    """Solve for the tag position; ``None`` when there are too few ranges or no convergence.
    ``side`` (+1 above, −1 below) is where to start when the anchors are coplanar and no
    ``x0`` is given (:mod:`uwbd.fusion.policy.mirror` decides it)."""
    dims = 2 if fixed_z is not None else 3
    used = np.ones(len(ranges_m), dtype=bool)
    fix = _solve(anchors_m, ranges_m, used, sigma_m, x0, fixed_z, side, core)
    if fix is None or used.sum() <= dims + 1:
        return fix
    # studentised residuals: r_i / (σ √(1 − h_ii)), h_ii the leverage of range i
    lev = _leverages(anchors_m[used], fix.position_m, dims, core)
    if lev is None:  # JᵀJ singular at the fix: no leverages, no outlier test
        return fix
    student = np.abs(fix.residuals_m[used]) / (sigma_m * np.sqrt(np.clip(1 - lev, 1e-6, None)))
    worst = int(np.argmax(student))
    if student[worst] <= outlier_sigma:
        return fix
    used[np.flatnonzero(used)[worst]] = False
    return _solve(anchors_m, ranges_m, used, sigma_m, fix.position_m, fixed_z, side,
                  core) or fix


def _leverages(anchors: Array, x: Array, dims: int, core: Core) -> Array | None:
    """``h_ii = J_i (JᵀJ)⁻¹ J_iᵀ`` of each range at ``x``; None where ``JᵀJ`` is singular."""
    if core is not None:
        lev = core.leverages(np.ascontiguousarray(anchors, dtype=float),
                             np.ascontiguousarray(x, dtype=float), dims)
        return None if lev is None else np.array(lev)
    diff = x - anchors
    J = (diff / np.linalg.norm(diff, axis=1, keepdims=True))[:, :dims]
    try:
        return np.einsum("ij,jk,ik->i", J, np.linalg.inv(J.T @ J), J)
    except np.linalg.LinAlgError:
        return None


def _initial_guess(anchors: Array, ranges: Array, fixed_z: float | None, side: int) -> Array:
    """Linear solution of the differenced range equations, else the anchors' centroid."""
    centroid = anchors.mean(axis=0)
    if fixed_z is None and len(anchors) >= 4 and not coplanar(anchors):
        A = 2 * (anchors[1:] - anchors[0])
        b = (ranges[0] ** 2 - ranges[1:] ** 2
             + np.sum(anchors[1:] ** 2, axis=1) - np.sum(anchors[0] ** 2))
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        return np.asarray(x, dtype=float)
    guess = centroid.copy()
    if fixed_z is not None:
        guess[2] = fixed_z
    else:
        guess[2] += 1.0 * side  # on the chosen side of a plane of anchors, not in it
    return guess


def _solve(anchors_all: Array, ranges_all: Array, used: Array, sigma_m: float,
           x0: Array | None, fixed_z: float | None, side: int, core: Core) -> LsqFix | None:
    dims = 2 if fixed_z is not None else 3
    anchors, ranges = anchors_all[used], ranges_all[used]
    if len(ranges) < dims:
        return None
    x = np.array(x0 if x0 is not None else _initial_guess(anchors, ranges, fixed_z, side),
                 dtype=float)
    if fixed_z is not None:
        x[2] = fixed_z
    if core is not None:
        inverse = np.zeros((3, 3))
        iteration = core.gauss_newton(np.ascontiguousarray(anchors, dtype=float),
                                      np.ascontiguousarray(ranges, dtype=float), x,
                                      dims, MAX_ITERATIONS, MAX_HALVINGS, CONVERGED_M,
                                      ACCEPT_LAST_STEP_M, inverse)
        if iteration == 0:
            return None
        cov = sigma_m**2 * inverse
    else:
        solved = _iterate(anchors, ranges, x, dims)
        if solved is None:
            return None
        iteration, cov = solved
        cov *= sigma_m**2
    residuals = np.full(len(ranges_all), np.nan)
    residuals[used] = np.linalg.norm(x - anchors, axis=1) - ranges
    rms = float(np.sqrt(np.mean(residuals[used] ** 2)))
    return LsqFix(x, cov, residuals, used.copy(), rms, iteration)


def _iterate(anchors: Array, ranges: Array, x: Array, dims: int) -> tuple[int, Array] | None:
    """Gauss–Newton from ``x`` (in place): the iterations and ``(JᵀJ)⁻¹`` of the last step
    (top-left ``dims``), or ``None`` for no fix."""
    iteration = 0
    while True:
        iteration += 1
        diff = x - anchors
        dist = np.linalg.norm(diff, axis=1)
        if np.any(dist < 1e-6):
            return None
        r = dist - ranges
        J = (diff / dist[:, None])[:, :dims]
        JtJ = J.T @ J
        try:
            step = np.linalg.solve(JtJ, -J.T @ r)
        except np.linalg.LinAlgError:
            return None
        full = float(np.linalg.norm(step))  # judged whole: a search cut short has not converged
        before = _sum_squares(anchors, ranges, x)
        trial = x.copy()
        for halving in range(MAX_HALVINGS + 1):
            trial[:dims] = x[:dims] + step
            if halving == MAX_HALVINGS or not _sum_squares(anchors, ranges, trial) > before:
                break
            step = step * 0.5
        x[:dims] = trial[:dims]
        if full < CONVERGED_M:
            break
        if iteration == MAX_ITERATIONS:
            if not full <= ACCEPT_LAST_STEP_M:
                return None  # diverging, oscillating or NaN: no fix
            break
    inverse = np.zeros((3, 3))
    inverse[:dims, :dims] = np.linalg.inv(JtJ)
    return iteration, inverse


def _sum_squares(anchors: Array, ranges: Array, x: Array) -> float:
    return float(np.sum((np.linalg.norm(x - anchors, axis=1) - ranges) ** 2))


def common_offset(anchors_m: Array, ranges_m: Array, x0: Array) -> tuple[float, Array] | None:
    """The range offset common to all ranges, solved with the position (Gauss–Newton over
    ``x, y, z, b`` from ``x0``): the offset and the position. A fix that only fits with a
    large common offset is not a fix to trust (an NLOS detour on every anchor looks like
    one). ``None`` with fewer than 5 ranges or no convergence."""
    if len(ranges_m) < 5:
        return None
    x = np.append(np.array(x0, dtype=float), 0.0)
    for _ in range(MAX_ITERATIONS):
        diff = x[:3] - anchors_m
        dist = np.linalg.norm(diff, axis=1)
        if np.any(dist < 1e-6):
            return None
        J = np.column_stack([diff / dist[:, None], np.ones(len(dist))])
        try:
            step = np.linalg.solve(J.T @ J, -J.T @ (dist + x[3] - ranges_m))
        except np.linalg.LinAlgError:
            return None
        x += step
        if float(np.linalg.norm(step)) < CONVERGED_M:
            return float(x[3]), x[:3]
    return None
